"""Policy files that run no code: a multilayer perceptron as weights plus a JSON description.

A policy from a stranger must not run code when it is loaded. TorchScript and
``file.py:name`` policies do (:func:`hybridoc.workflows.policies.load_policy` documents
them); this format does not: ``policy.json`` is read with :mod:`json` and the weights file
beside it with :func:`numpy.load` without pickles, and what comes out is a plain
:class:`MLP` whose evaluation is a few numpy products. The same object gives its CasADi
expression (:meth:`MLP.casadi`), so the judge's closed-loop rollouts can be compiled
(:mod:`hybridoc.workflows.rollouts`).

The format (version 1)
    ``policy.json``::

        {"format": "hybridoc-mlp-policy", "version": 1,
         "weights": "policy.npz", "sha256": "<hex digest of policy.npz>",
         "input": "t,state", "horizon": 1.0,
         "layers": [9, 32, 32, 2], "activation": "tanh",
         "saturation": {"kind": "clip", "lower": [-1.0, null], "upper": [1.0, 2.5]}}

    and ``policy.npz`` with the arrays ``layer<k>.weight`` (``(out, in)``, as
    ``torch.nn.Linear``) and ``layer<k>.bias`` for each of the ``len(layers) - 1`` affine
    layers, and optionally ``state_mean``, ``state_scale`` (``(nx,)``), ``output_offset``
    and ``output_scale`` (``(nu,)``). The policy is

    .. math::

        u = o + \\sigma_o \\odot A_K(\\ldots a(A_1 z)),\\quad
        z = [\\,2 t / T - 1,\\ (s - \\mu) / \\sigma_s\\,]

    with ``A_k x = W_k x + b_k``, the activation ``a`` (``tanh``, ``relu``, ``sigmoid`` or
    ``identity``) after every layer but the last, ``T`` the ``horizon`` (``null``: the raw
    time ``t`` enters), and without the time entry when ``input`` is ``"state"``. Absent
    normalisation arrays mean the identity. It is the form of
    :class:`hybridoc.workflows.training.MLPPolicy`, which :func:`save_mlp_policy` writes as
    it is. ``weights`` names a file in the folder of the JSON file; ``sha256`` (written by
    :func:`save_mlp_policy`, optional for hand-written files) must then match it.

    ``saturation`` (optional; absent or ``null``: none) bounds the output,

    .. math::

        u_j \\leftarrow \\min(\\max(u_j, l_j), h_j),

    with ``lower`` ``l`` and ``upper`` ``h`` one entry per control each, ``null`` for a side
    without a bound. :func:`~hybridoc.workflows.training.mlp_policy` puts the problem's
    control bounds there, so that the policy's controls never leave them (the judge's
    :attr:`Evaluation.bound_violation <hybridoc.Evaluation>` is 0). A clip, not a smooth
    squashing such as ``mid + half * tanh(raw / half)``: under box bounds the minimum
    principle's control is the unconstrained minimiser clipped to the box (a bang arc at
    the bound, as the bounded shuttle's force), which a clipped network represents with
    finite weights and a squashed one only in the limit of infinite ones; the clip also
    lands exactly on the bound (``mid + half`` can round past ``h``). Its gradient is zero
    where a control is clipped, which is the exact gradient of the clipped policy's cost.

A CasADi policy
    :class:`CasadiPolicy` wraps a ``casadi.Function`` ``(t, s) -> u`` given in Python (it is
    code the user runs, so it is not a file format).
"""

from hybridoc.workflows.policy_format.files import FORMAT, VERSION, load_mlp_policy, save_mlp_policy
from hybridoc.workflows.policy_format.network import (
    ACTIVATIONS,
    INPUTS,
    MAX_PARAMETERS,
    MLP,
    SATURATIONS,
    CasadiPolicy,
    PolicyError,
    check_policy_sizes,
    saturation_bounds,
)

__all__ = [
    "ACTIVATIONS",
    "FORMAT",
    "MAX_PARAMETERS",
    "INPUTS",
    "CasadiPolicy",
    "MLP",
    "PolicyError",
    "SATURATIONS",
    "VERSION",
    "check_policy_sizes",
    "load_mlp_policy",
    "saturation_bounds",
    "save_mlp_policy",
]
