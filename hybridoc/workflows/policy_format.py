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

from __future__ import annotations

import hashlib
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hybridoc.errors import HybridocError

__all__ = [
    "ACTIVATIONS",
    "FORMAT",
    "MAX_PARAMETERS",
    "INPUTS",
    "CasadiPolicy",
    "MLP",
    "PolicyError",
    "SATURATIONS",
    "check_policy_sizes",
    "load_mlp_policy",
    "saturation_bounds",
    "save_mlp_policy",
]

FORMAT = "hybridoc-mlp-policy"
"""The ``format`` entry of a policy JSON file."""
VERSION = 1
ACTIVATIONS = ("tanh", "relu", "sigmoid", "identity")
"""Activations of the hidden layers."""
INPUTS = ("t,state", "state")
"""What the network reads: the time and the state, or the state alone."""
_KEYS = {
    "format", "version", "weights", "sha256", "input", "horizon", "layers", "activation",
    "saturation",
}  # fmt: skip
SATURATIONS = ("clip",)
"""Kinds of output saturation of the format (module notes)."""
_NORMS = {"state_mean": "nx", "state_scale": "nx", "output_offset": "nu", "output_scale": "nu"}
_MAX_JSON_BYTES = 1 << 20
MAX_PARAMETERS = 10**8
"""The most weights and biases a policy file may describe (800 MB as float64): a larger
``layers`` entry is refused before its weights file is read."""
_NPZ_SLACK = 1 << 20  # bytes of zip and .npy headers allowed beyond a file's described data


class PolicyError(HybridocError, ValueError):
    """A policy spec that cannot be loaded (missing file, no such name, not callable, a
    policy file that does not describe a policy)."""


def _activation_np(name: str, x: np.ndarray) -> np.ndarray:
    if name == "tanh":
        return np.tanh(x)
    if name == "relu":
        return np.maximum(x, 0.0)
    if name == "sigmoid":
        return 1.0 / (1.0 + np.exp(-x))
    return x


def _activation_ca(name: str, x: Any) -> Any:
    import casadi as ca

    if name == "tanh":
        return ca.tanh(x)
    if name == "relu":
        return ca.fmax(x, 0.0)
    if name == "sigmoid":
        return 1.0 / (1.0 + ca.exp(-x))
    return x


def _vector(value: Any, n: int, what: str, default: float) -> np.ndarray:
    if value is None:
        return np.full(n, default)
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape != (n,):
        raise PolicyError(f"{what} must have {n} entries, got shape {np.shape(value)}")
    if not np.all(np.isfinite(arr)):
        raise PolicyError(f"{what} has non-finite entries")
    return arr


@dataclass(frozen=True, eq=False)
class MLP:
    """A multilayer perceptron feedback policy ``u = pi(t, s)`` in numpy (module notes).

    Parameters
    ----------
    weights
        ``(out, in)`` matrices of the affine layers, first to last.
    biases
        ``(out,)`` vectors of the same layers.
    activation
        One of :data:`ACTIVATIONS`, after every layer but the last.
    input
        ``"t,state"`` (the first input is the time) or ``"state"``.
    horizon
        ``T`` of the time input ``2 t / T - 1``; ``None``: the raw time.
    state_mean, state_scale
        ``(nx,)`` input normalisation ``(s - mean) / scale``; default 0 and 1.
    output_offset, output_scale
        ``(nu,)`` output ``offset + scale * net``; default 0 and 1.
    output_min, output_max
        ``(nu,)`` bounds the output is clipped to (``-inf``/``inf`` or ``None``: a side
        without a bound); both ``None`` (the default), or no finite entry: no saturation.

    Raises
    ------
    PolicyError
        Shapes that do not chain, a non-finite value, an unknown activation or input,
        bounds that are NaN, on the wrong side (a lower bound of ``inf``) or crossed.
    """

    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]
    activation: str = "tanh"
    input: str = "t,state"
    horizon: float | None = None
    state_mean: np.ndarray | None = None
    state_scale: np.ndarray | None = None
    output_offset: np.ndarray | None = None
    output_scale: np.ndarray | None = None
    output_min: np.ndarray | None = None
    output_max: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.activation not in ACTIVATIONS:
            raise PolicyError(
                f"activation must be one of {', '.join(ACTIVATIONS)}, got {self.activation!r}"
            )
        if self.input not in INPUTS:
            raise PolicyError(f"input must be one of {', '.join(INPUTS)}, got {self.input!r}")
        if len(self.weights) != len(self.biases) or not self.weights:
            raise PolicyError(
                f"an MLP needs one bias per weight matrix and at least one layer, got "
                f"{len(self.weights)} weight matrices and {len(self.biases)} biases"
            )
        Ws, bs = [], []
        for k, (W, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            W = _float_array(W, f"layer {k} weight")
            b = _float_array(b, f"layer {k} bias")
            if W.ndim != 2 or b.shape != (W.shape[0],):
                raise PolicyError(
                    f"layer {k}: weight must be (out, in) and bias (out,), got {W.shape} and "
                    f"{b.shape}"
                )
            if Ws and W.shape[1] != Ws[-1].shape[0]:
                raise PolicyError(
                    f"layer {k} takes {W.shape[1]} inputs but layer {k - 1} gives {Ws[-1].shape[0]}"
                )
            Ws.append(W)
            bs.append(b)
        object.__setattr__(self, "weights", tuple(Ws))
        object.__setattr__(self, "biases", tuple(bs))
        n_t = 1 if self.input == "t,state" else 0
        nx = Ws[0].shape[1] - n_t
        if nx < 1:
            raise PolicyError(f"the first layer takes {Ws[0].shape[1]} inputs: no state entry")
        if self.horizon is not None:
            h = float(self.horizon)
            if not (math.isfinite(h) and h > 0):
                raise PolicyError(f"horizon must be a positive number, got {self.horizon!r}")
            object.__setattr__(self, "horizon", h)
        nu = Ws[-1].shape[0]
        for name, dim in _NORMS.items():
            n = nx if dim == "nx" else nu
            default = 0.0 if name in ("state_mean", "output_offset") else 1.0
            object.__setattr__(self, name, _vector(getattr(self, name), n, name, default))
        if np.any(self.state_scale == 0):
            raise PolicyError("state_scale has zero entries (it divides the state)")
        lo, hi = saturation_bounds(self.output_min, self.output_max, nu)
        object.__setattr__(self, "output_min", lo)
        object.__setattr__(self, "output_max", hi)

    @property
    def saturated(self) -> bool:
        """Whether the output is clipped to bounds (``output_min``/``output_max`` set)."""
        return self.output_min is not None

    @property
    def nx(self) -> int:
        """State dimension the policy reads."""
        return int(self.weights[0].shape[1] - (1 if self.input == "t,state" else 0))

    @property
    def nu(self) -> int:
        """Control dimension it returns."""
        return int(self.weights[-1].shape[0])

    @property
    def layers(self) -> list[int]:
        """Widths: the network's input, every hidden layer, the output."""
        return [int(self.weights[0].shape[1])] + [int(W.shape[0]) for W in self.weights]

    def __call__(self, t: Any, state: Any) -> np.ndarray:
        """The controls ``(nu,)`` for one state ``(nx,)``, or ``(B, nu)`` for ``(B, nx)``
        (``t`` a number or ``(B,)``)."""
        s = np.asarray(state, dtype=float)
        if s.ndim not in (1, 2) or s.shape[-1] != self.nx:
            # never reshape another size into this one (8 states read as 2 rows of 4)
            raise PolicyError(
                f"this policy reads {self.nx} state entries, got a state of shape {s.shape}"
            )
        single = s.ndim == 1
        S = s.reshape(-1, self.nx)
        z = (S - self.state_mean) / self.state_scale
        if self.input == "t,state":
            tt = np.broadcast_to(np.asarray(t, dtype=float).reshape(-1), (S.shape[0],))
            if self.horizon is not None:
                tt = 2.0 * tt / self.horizon - 1.0
            z = np.concatenate([tt[:, None], z], axis=1)
        last = len(self.weights) - 1
        for k, (W, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            z = z @ W.T + b
            if k < last:
                z = _activation_np(self.activation, z)
        u = self.output_offset + self.output_scale * z
        if self.output_min is not None:
            u = np.minimum(np.maximum(u, self.output_min), self.output_max)
        return u[0] if single else u

    def parameters(self) -> np.ndarray:
        """Every weight and bias in one vector, layer by layer (each weight column-major, as
        CasADi reshapes): the ``p`` of :meth:`casadi` with ``symbolic=True``."""
        parts = []
        for W, b in zip(self.weights, self.biases, strict=True):
            parts += [W.ravel(order="F"), b]
        return np.concatenate(parts)

    def casadi(self, symbolic: bool = False) -> Any:
        """The policy as a CasADi SX Function.

        Parameters
        ----------
        symbolic
            ``False``: ``policy(t, s) -> u`` with the weights as constants. ``True``:
            ``policy(t, s, p) -> u`` with the weights an input (:meth:`parameters`), so that
            compiled code depends on the architecture only, not on the weights.

        Returns
        -------
        casadi.Function
        """
        import casadi as ca

        t, s = ca.SX.sym("t"), ca.SX.sym("s", self.nx)
        p = ca.SX.sym("p", self.parameters().size) if symbolic else None
        z = (s - ca.DM(self.state_mean)) / ca.DM(self.state_scale)
        if self.input == "t,state":
            tin = 2.0 * t / self.horizon - 1.0 if self.horizon is not None else t
            z = ca.vertcat(tin, z)
        off = 0
        last = len(self.weights) - 1
        for k, (W, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            if p is None:
                Wk, bk = ca.DM(W), ca.DM(b)
            else:
                n_out, n_in = W.shape
                Wk = ca.reshape(p[off : off + n_out * n_in], n_out, n_in)
                off += n_out * n_in
                bk = p[off : off + n_out]
                off += n_out
            z = ca.mtimes(Wk, z) + bk
            if k < last:
                z = _activation_ca(self.activation, z)
        u = ca.DM(self.output_offset) + ca.DM(self.output_scale) * z
        if self.output_min is not None:
            u = _clip_ca(u, self.output_min, self.output_max)
        args = [t, s] if p is None else [t, s, p]
        names = ["t", "s"] if p is None else ["t", "s", "p"]
        return ca.Function("policy", args, [u], names, ["u"])

    def to_torch(self) -> Any:
        """The same policy as a trainable :class:`hybridoc.workflows.training.MLPPolicy`
        (float64), to train further from a saved file.

        Raises
        ------
        PolicyError
            A policy that :class:`~hybridoc.workflows.training.MLPPolicy` cannot represent:
            it reads ``(t, state)`` with a ``horizon``, has ``tanh`` hidden layers of one
            width.
        """
        hidden = {int(W.shape[0]) for W in self.weights[:-1]}
        if (
            self.input != "t,state"
            or self.horizon is None
            or len(hidden) > 1
            or (hidden and self.activation != "tanh")
        ):
            raise PolicyError(
                "training.MLPPolicy reads (t, state) with a horizon and has tanh hidden layers "
                f"of one width; this policy is {self!r} with horizon {self.horizon}"
            )
        import torch

        from hybridoc.workflows.training import MLPPolicy

        module = MLPPolicy(
            self.nx, self.nu, hidden=hidden.pop() if hidden else 1,
            layers=len(self.weights) - 1, horizon=self.horizon, s_mean=self.state_mean,
            s_scale=self.state_scale, u_offset=self.output_offset, u_scale=self.output_scale,
            u_min=self.output_min, u_max=self.output_max,
            generator=torch.Generator(),  # its random start is overwritten: leave torch's own
        )  # fmt: skip
        linears = [m for m in module.net if isinstance(m, torch.nn.Linear)]
        with torch.no_grad():
            for lin, W, b in zip(linears, self.weights, self.biases, strict=True):
                lin.weight.copy_(torch.as_tensor(W))
                lin.bias.copy_(torch.as_tensor(b))
        return module

    def description(self) -> dict[str, Any]:
        """The JSON entries of the format that describe the architecture (``saturation``
        only when the output is clipped, so that an unsaturated policy is described as
        before)."""
        spec: dict[str, Any] = {
            "input": self.input,
            "horizon": self.horizon,
            "layers": self.layers,
            "activation": self.activation,
        }
        if self.output_min is not None and self.output_max is not None:
            # null for a side without a bound: JSON has no infinity
            spec["saturation"] = {
                "kind": "clip",
                "lower": [float(x) if np.isfinite(x) else None for x in self.output_min],
                "upper": [float(x) if np.isfinite(x) else None for x in self.output_max],
            }
        return spec

    def __repr__(self) -> str:
        sat = ", saturation='clip'" if self.saturated else ""
        return (
            f"MLP(layers={self.layers}, activation={self.activation!r}, input={self.input!r}{sat})"
        )


def saturation_bounds(
    lower: Any, upper: Any, nu: int
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The output bounds of a policy with ``nu`` controls, checked.

    Parameters
    ----------
    lower, upper
        ``(nu,)`` bounds (``-inf``/``inf``: a side without one), or ``None`` for none.

    Returns
    -------
    lower, upper
        ``(nu,)`` float arrays, or ``(None, None)`` when no entry is finite (no saturation).

    Raises
    ------
    PolicyError
        A wrong shape, NaN, a lower bound of ``inf`` or an upper one of ``-inf``, crossed
        bounds.
    """
    if lower is None and upper is None:
        return None, None
    out = []
    for value, name, side in ((lower, "output_min", -np.inf), (upper, "output_max", np.inf)):
        if value is None:
            out.append(np.full(nu, side))
            continue
        arr = _float_array_inf(value, name).reshape(-1)
        if arr.shape != (nu,):
            raise PolicyError(f"{name} must have {nu} entries, got shape {np.shape(value)}")
        if np.any(arr == -side):
            raise PolicyError(f"{name} has an entry {-side}: no control could meet it")
        out.append(arr)
    lo, hi = out
    if np.any(lo > hi):
        j = int(np.flatnonzero(lo > hi)[0])
        raise PolicyError(f"output_min[{j}] = {lo[j]!r} exceeds output_max[{j}] = {hi[j]!r}")
    if not (np.isfinite(lo).any() or np.isfinite(hi).any()):
        return None, None
    return lo, hi


def _float_array_inf(value: Any, what: str) -> np.ndarray:
    """Real numbers, infinities allowed (a side without a bound), NaN not."""
    arr = np.asarray(value)
    if arr.dtype.kind not in "fiu" or arr.dtype == np.bool_:
        raise PolicyError(f"{what} must hold real numbers, got dtype {arr.dtype}")
    arr = arr.astype(float)
    if np.isnan(arr).any():
        raise PolicyError(f"{what} has NaN entries")
    return arr


def _clip_ca(u: Any, lower: np.ndarray, upper: np.ndarray) -> Any:
    """``min(max(u, lower), upper)`` per entry as CasADi SX, only on the finite sides (the
    same numbers as :meth:`MLP.__call__`'s numpy clip: max and min are exact)."""
    import casadi as ca

    rows = []
    for j in range(u.numel()):
        r = u[j]
        if np.isfinite(lower[j]):
            r = ca.fmax(r, float(lower[j]))
        if np.isfinite(upper[j]):
            r = ca.fmin(r, float(upper[j]))
        rows.append(r)
    return ca.vertcat(*rows)


def _float_array(value: Any, what: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in "fiu" or arr.dtype == np.bool_:
        raise PolicyError(f"{what} must hold real numbers, got dtype {arr.dtype}")
    arr = arr.astype(float)
    if not np.all(np.isfinite(arr)):
        raise PolicyError(f"{what} has non-finite entries")
    return arr


def check_policy_sizes(policy: Any, nx: int, nu: int, where: str = "the policy") -> None:
    """Check a policy's input and output sizes against a problem's ``nx`` states and ``nu``
    controls, before any rollout: for a policy that states them (``nx`` and ``nu``
    integers: an :class:`MLP`, a :class:`CasadiPolicy`, a trained MLP policy). A callable
    that does not state them is checked by the rollout, at its first call.

    Raises
    ------
    PolicyError
        Either size differs: one line with both.
    """
    sizes = [getattr(policy, k, None) for k in ("nx", "nu")]
    if not all(isinstance(v, int | np.integer) and not isinstance(v, bool) for v in sizes):
        return
    pnx, pnu = (int(v) for v in sizes)
    if (pnx, pnu) != (int(nx), int(nu)):
        raise PolicyError(
            f"{where} reads {pnx} states and returns {pnu} controls, but the problem has "
            f"{nx} states and {nu} controls: it was made for another problem"
        )


# ---------------------------------------------------------------------------- files


def _json_path(path: str | Path) -> Path:
    p = Path(path)
    return p if p.suffix.lower() == ".json" else p.with_suffix(".json")


def load_mlp_policy(path: str | Path) -> MLP:
    """Read a policy JSON file and its weights; nothing in them is executed.

    Parameters
    ----------
    path
        ``policy.json`` (module notes).

    Returns
    -------
    MLP

    Raises
    ------
    PolicyError
        A missing or unreadable file, JSON that is not the format, weights that do not
        match the description or the recorded SHA-256, non-finite numbers.
    """
    path = Path(path)
    where = repr(str(path))
    if not path.is_file():
        raise PolicyError(f"policy file {where} does not exist")
    from hybridoc.outputs import read_json

    # bounded in size and nesting (a file nested 200 000 deep is one clear error)
    spec = read_json(path, where, max_bytes=_MAX_JSON_BYTES, error=PolicyError)
    if not isinstance(spec, dict) or spec.get("format") != FORMAT:
        raise PolicyError(f"{where} is not a policy file: its 'format' must be {FORMAT!r}")
    if spec.get("version") != VERSION:
        raise PolicyError(
            f"{where}: version {spec.get('version')!r} is not supported (this hybridoc reads "
            f"version {VERSION})"
        )
    unknown = sorted(set(spec) - _KEYS)
    if unknown:
        raise PolicyError(f"{where}: unknown entries {', '.join(map(repr, unknown))}")
    layers = spec.get("layers")
    if (
        not isinstance(layers, list)
        or len(layers) < 2
        or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 1 for n in layers)
    ):
        raise PolicyError(
            f"{where}: 'layers' must list at least two positive integer widths (input, ..., "
            f"output), got {layers!r}"
        )
    parameters = sum((layers[k] + 1) * layers[k + 1] for k in range(len(layers) - 1))
    if parameters > MAX_PARAMETERS:
        raise PolicyError(
            f"{where}: 'layers' {_shown(layers)} describes {parameters} parameters, more than "
            f"the {MAX_PARAMETERS} a policy file may hold: refused before its weights are read"
        )
    weights = _weights_file(path, spec, where)
    # what the file may hold: the layers, the normalisations, at most 16 bytes a number
    shapes = {f"layer{k}.{part}": shape for k in range(len(layers) - 1)
              for part, shape in (("weight", (layers[k + 1], layers[k])),
                                  ("bias", (layers[k + 1],)))}  # fmt: skip
    for name, side in _NORMS.items():
        shapes[name] = (layers[-1],) if side == "nu" else None  # nx: checked by the MLP
    _check_weights_size(weights, parameters + 4 * max(layers), where)
    arrays = _read_npz(weights, spec.get("sha256"), where, shapes)
    Ws, bs = [], []
    for k in range(len(layers) - 1):
        W, b = arrays.pop(f"layer{k}.weight", None), arrays.pop(f"layer{k}.bias", None)
        if W is None or b is None:
            raise PolicyError(f"{weights.name!r} lacks layer{k}.weight or layer{k}.bias")
        if W.shape != (layers[k + 1], layers[k]) or b.shape != (layers[k + 1],):
            raise PolicyError(
                f"{weights.name!r}: layer {k} has weight {W.shape} and bias {b.shape}; "
                f"{where} describes ({layers[k + 1]}, {layers[k]}) and ({layers[k + 1]},)"
            )
        Ws.append(W)
        bs.append(b)
    norms = {k: arrays.pop(k) for k in list(arrays) if k in _NORMS}
    if arrays:
        raise PolicyError(
            f"{weights.name!r} holds arrays {', '.join(map(repr, sorted(arrays)))} that "
            f"{where} does not describe"
        )
    horizon = spec.get("horizon")
    if horizon is not None and (isinstance(horizon, bool) or not isinstance(horizon, int | float)):
        raise PolicyError(f"{where}: 'horizon' must be a number or null, got {horizon!r}")
    lower, upper = _saturation(spec.get("saturation"), layers[-1], where)
    try:
        return MLP(
            tuple(Ws), tuple(bs),
            activation=spec.get("activation", "tanh"), input=spec.get("input", "t,state"),
            horizon=horizon, output_min=lower, output_max=upper, **norms,
        )  # fmt: skip
    except PolicyError as exc:
        raise PolicyError(f"{where}: {exc}") from None


def _saturation(entry: Any, nu: int, where: str) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The bounds of a ``saturation`` entry (module notes); absent or ``null``: none."""
    if entry is None:
        return None, None
    form = "{'kind': 'clip', 'lower': [...], 'upper': [...]}"
    if not isinstance(entry, dict) or set(entry) != {"kind", "lower", "upper"}:
        raise PolicyError(f"{where}: 'saturation' must be {form} or null, got {entry!r}")
    if entry["kind"] not in SATURATIONS:
        raise PolicyError(
            f"{where}: saturation kind {entry['kind']!r} is not one of {', '.join(SATURATIONS)}"
        )
    sides = []
    for name, missing in (("lower", -np.inf), ("upper", np.inf)):
        values = entry[name]
        if not isinstance(values, list) or len(values) != nu:
            raise PolicyError(
                f"{where}: saturation {name!r} must list {nu} bounds (one per control, null "
                f"for none), got {values!r}"
            )
        for v in values:
            if v is not None and (isinstance(v, bool) or not isinstance(v, int | float)):
                raise PolicyError(f"{where}: saturation {name!r} holds {v!r}, not a number")
        sides.append(np.array([missing if v is None else float(v) for v in values]))
    return sides[0], sides[1]


def _weights_file(path: Path, spec: dict[str, Any], where: str) -> Path:
    name = spec.get("weights")
    if not isinstance(name, str) or not name:
        raise PolicyError(f"{where}: 'weights' must name the .npz file beside it")
    # a bare name in the same folder: a description cannot point at other files
    if Path(name).name != name or name in (".", ".."):
        raise PolicyError(f"{where}: 'weights' must be a file name in its folder, got {name!r}")
    weights = path.parent / name
    if not weights.is_file():
        raise PolicyError(f"{where} names the weights file {name!r}, which does not exist")
    return weights


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _check_weights_size(weights: Path, numbers: int, where: str) -> None:
    """Refuse a weights file larger than the numbers its description holds can take (16
    bytes each, plus headers) before reading it."""
    try:
        size = weights.stat().st_size
    except OSError as exc:
        raise PolicyError(f"cannot read {str(weights)!r}: {exc.strerror or exc}") from None
    if size > 16 * numbers + _NPZ_SLACK:
        raise PolicyError(
            f"{str(weights)!r} holds {size} bytes, more than the {numbers} numbers that "
            f"{where} describes can take: refused before it is read"
        )


def _declared_shapes(data: bytes, weights: Path) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """The shapes and types the members of an ``.npz`` file declare in their headers (read
    without the arrays: a header may declare far more than the file holds)."""
    import zipfile

    from numpy.lib import format as npformat

    out: dict[str, tuple[tuple[int, ...], np.dtype]] = {}
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        for info in zf.infolist():
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            with zf.open(info) as fh:
                head = io.BytesIO(fh.read(65536 + 16))
            version = npformat.read_magic(head)
            read = (
                npformat.read_array_header_1_0
                if version == (1, 0)
                else npformat.read_array_header_2_0
            )
            shape, _, dtype = read(head)
            out[name] = (tuple(int(n) for n in shape), np.dtype(dtype))
    return out


def _check_declared(
    data: bytes, weights: Path, where: str, shapes: dict[str, tuple[int, ...] | None]
) -> None:
    """The members of a weights file, by the shapes their headers declare, against its
    description (``shapes``: name -> shape, ``None`` for a state-sized vector), with the
    messages of the checks after the load; nothing is allocated for a member."""
    try:
        members = _declared_shapes(data, weights)
    except Exception as exc:  # zipfile and numpy's header parser raise many kinds
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise PolicyError(f"cannot read {str(weights)!r} as .npz weights: {first}") from None
    for name, (_, dtype) in members.items():
        if dtype.hasobject:  # a pickle: never read
            raise PolicyError(
                f"cannot read {str(weights)!r} as .npz weights: {name} is an object array"
            )
        if dtype.kind not in "fiu":
            raise PolicyError(f"{weights.name!r}: {name} must hold real numbers, got dtype {dtype}")
    declared = {name: shape for name, (shape, _) in members.items()}
    unknown = sorted(set(declared) - set(shapes))
    if unknown:
        raise PolicyError(
            f"{weights.name!r} holds arrays {', '.join(map(repr, unknown))} that {where} does "
            "not describe"
        )
    k = 0
    while f"layer{k}.weight" in shapes:
        W, b = (declared.get(f"layer{k}.{part}") for part in ("weight", "bias"))
        want_W, want_b = shapes[f"layer{k}.weight"], shapes[f"layer{k}.bias"]
        if W is not None and b is not None and (W != want_W or b != want_b):
            raise PolicyError(
                f"{weights.name!r}: layer {k} has weight {W} and bias {b}; {where} describes "
                f"{want_W} and {want_b}"
            )
        k += 1
    for name in _NORMS:
        shape = declared.get(name)
        if shape is None:
            continue
        want = shapes[name]
        if (want is None and (len(shape) != 1 or shape[0] > _NPZ_SLACK)) or (
            want is not None and shape != want
        ):
            n = "the state's" if want is None else str(want[0])
            raise PolicyError(f"{weights.name!r}: {name} must have {n} entries, got shape {shape}")


def _read_npz(
    weights: Path,
    sha: Any,
    where: str,
    shapes: dict[str, tuple[int, ...] | None] | None = None,
) -> dict[str, np.ndarray]:
    """The arrays of a weights file; with ``shapes`` (name -> the shape its description
    gives, ``None``: any vector), each member's declared shape is checked against it before
    any array is read, so that a header declaring a huge array allocates nothing."""
    try:
        data = weights.read_bytes()
    except OSError as exc:
        raise PolicyError(f"cannot read {str(weights)!r}: {exc.strerror or exc}") from None
    if sha is not None:
        if not isinstance(sha, str) or hashlib.sha256(data).hexdigest() != sha.lower():
            raise PolicyError(
                f"{str(weights)!r} does not match the SHA-256 recorded in {where}: the weights "
                "were changed or belong to another policy"
            )
    if shapes is not None:
        _check_declared(data, weights, where, shapes)
    try:
        # allow_pickle=False: an object array in the file is refused, never unpickled
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            return {k: _float_array(npz[k], f"{weights.name!r}: {k}") for k in npz.files}
    except PolicyError:
        raise
    except Exception as exc:  # numpy raises ValueError, OSError, zipfile errors, ...
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise PolicyError(f"cannot read {str(weights)!r} as .npz weights: {first}") from None


def save_mlp_policy(
    policy: Any,
    path: str | Path,
    *,
    input: str | None = None,
    horizon: float | None = None,
    state_mean: Any = None,
    state_scale: Any = None,
    output_offset: Any = None,
    output_scale: Any = None,
    output_min: Any = None,
    output_max: Any = None,
) -> Path:
    """Write a policy as ``<stem>.json`` and ``<stem>.npz`` (module notes).

    Parameters
    ----------
    policy
        An :class:`MLP`; a :class:`hybridoc.workflows.training.MLPPolicy` (its
        normalisations and horizon come with it); or a ``torch.nn.Sequential`` of
        ``Linear`` layers with one kind of activation (``Tanh``, ``ReLU``, ``Sigmoid``)
        between them, described by the keywords.
    path
        ``<stem>.json`` (or a stem): the JSON file; the weights go beside it.
    input, horizon, state_mean, state_scale, output_offset, output_scale, output_min, output_max
        For a ``Sequential`` only: what it reads (``"t,state"`` or ``"state"``, default
        ``"state"``), the normalisations of :class:`MLP` and the bounds its output is
        clipped to (the JSON's ``saturation``).

    Returns
    -------
    Path
        The JSON file.

    Raises
    ------
    PolicyError
        A module that is not such an MLP (another layer kind, mixed activations).
    hybridoc.errors.HybridocError
        A link, or a file hybridoc did not write, at either name (:mod:`hybridoc.outputs`);
        a file that cannot be written.
    """
    extra = {
        "input": input, "horizon": horizon, "state_mean": state_mean,
        "state_scale": state_scale, "output_offset": output_offset,
        "output_scale": output_scale, "output_min": output_min, "output_max": output_max,
    }  # fmt: skip
    mlp = _as_mlp(policy, extra)
    json_path = _json_path(path)
    npz_path = json_path.with_suffix(".npz")
    arrays: dict[str, np.ndarray] = {}
    for k, (W, b) in enumerate(zip(mlp.weights, mlp.biases, strict=True)):
        arrays[f"layer{k}.weight"] = W
        arrays[f"layer{k}.bias"] = b
    for name in _NORMS:
        arrays[name] = getattr(mlp, name)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    data = buf.getvalue()
    spec = {
        "format": FORMAT,
        "version": VERSION,
        "weights": npz_path.name,
        "sha256": hashlib.sha256(data).hexdigest(),
        **mlp.description(),
    }
    from hybridoc.outputs import check_targets, write_bytes, write_text

    # by the rules of hybridoc.outputs (atomically, never through a link or over a user's
    # file), both names checked before either is written
    check_targets(npz_path, json_path)
    write_bytes(npz_path, data)
    write_text(json_path, json.dumps(spec, indent=2) + "\n")
    return json_path


def _as_mlp(policy: Any, extra: dict[str, Any]) -> MLP:
    """An :class:`MLP` from what :func:`save_mlp_policy` accepts."""
    given = {k: v for k, v in extra.items() if v is not None}
    if isinstance(policy, MLP):
        if given:
            raise PolicyError(f"an MLP carries its own settings; got {', '.join(given)}")
        return policy
    net = getattr(policy, "net", None)
    if net is not None and hasattr(policy, "s_mean") and hasattr(policy, "u_offset"):
        # training.MLPPolicy: the form this format was made for
        if given:
            raise PolicyError(f"an MLPPolicy carries its own settings; got {', '.join(given)}")
        Ws, bs, act = _sequential_layers(net)

        def arr(x: Any) -> np.ndarray:
            return x.detach().cpu().numpy().astype(float)

        u_min, u_max = getattr(policy, "u_min", None), getattr(policy, "u_max", None)
        return MLP(
            Ws, bs, activation=act, input="t,state", horizon=float(policy.horizon),
            state_mean=arr(policy.s_mean), state_scale=arr(policy.s_scale),
            output_offset=arr(policy.u_offset), output_scale=arr(policy.u_scale),
            output_min=None if u_min is None else arr(u_min),
            output_max=None if u_max is None else arr(u_max),
        )  # fmt: skip
    if type(policy).__name__ == "Sequential":
        Ws, bs, act = _sequential_layers(policy)
        return MLP(Ws, bs, activation=act, **{"input": "state", **given})
    raise PolicyError(
        "save_mlp_policy takes an MLP, a training.MLPPolicy or a torch.nn.Sequential of Linear "
        f"layers and activations, got {type(policy).__name__}"
    )


_TORCH_ACTIVATIONS = {"Tanh": "tanh", "ReLU": "relu", "Sigmoid": "sigmoid"}


def _sequential_layers(net: Any) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...], str]:
    """Weights, biases and the activation of a ``Sequential`` of ``Linear`` and activations."""
    Ws: list[np.ndarray] = []
    bs: list[np.ndarray] = []
    acts: list[str] = []
    expect_linear = True
    for m in net:
        kind = type(m).__name__
        if kind == "Identity" or kind == "Dropout":
            continue  # no-ops in evaluation
        if kind == "Linear":
            if not expect_linear:
                raise PolicyError("two Linear layers in a row without an activation between them")
            Ws.append(m.weight.detach().cpu().numpy().astype(float))
            b = m.bias
            bs.append(
                np.zeros(m.out_features) if b is None else b.detach().cpu().numpy().astype(float)
            )
            expect_linear = False
        elif kind in _TORCH_ACTIVATIONS:
            if expect_linear:
                raise PolicyError(f"{kind} must follow a Linear layer")
            acts.append(_TORCH_ACTIVATIONS[kind])
            expect_linear = True
        else:
            raise PolicyError(
                f"layer {kind} has no form in the policy format (Linear, "
                f"{', '.join(_TORCH_ACTIVATIONS)})"
            )
    if not Ws:
        raise PolicyError("the network has no Linear layer")
    if expect_linear:
        raise PolicyError("the network ends with an activation; the format's last layer is Linear")
    if len(set(acts)) > 1:
        raise PolicyError(f"the format has one activation for all layers, got {sorted(set(acts))}")
    return tuple(Ws), tuple(bs), acts[0] if acts else "identity"


# ---------------------------------------------------------------------------- CasADi policies


class CasadiPolicy:
    """A feedback policy given as a ``casadi.Function`` ``(t, s) -> u``.

    Called as any policy (numpy in, numpy out), and compiled into the judge's closed-loop
    rollouts as an expression (:mod:`hybridoc.workflows.rollouts`).

    Parameters
    ----------
    fn
        Two inputs, ``t`` (scalar) and ``s`` (a column), and one output ``u`` (a column);
        without free variables.

    Raises
    ------
    PolicyError
        Another signature, or free variables.
    """

    def __init__(self, fn: Any) -> None:
        import casadi as ca

        if not isinstance(fn, ca.Function):
            raise PolicyError(f"a CasADi policy is a casadi.Function, got {type(fn).__name__}")
        if fn.n_in() != 2 or fn.n_out() != 1:
            raise PolicyError(
                f"a CasADi policy maps (t, s) to u: two inputs and one output, got "
                f"{fn.n_in()} inputs and {fn.n_out()} outputs"
            )
        if fn.size_in(0) != (1, 1) or fn.size_in(1)[1] != 1 or fn.size_out(0)[1] != 1:
            raise PolicyError(
                f"a CasADi policy takes t (1x1) and s (nx x 1) and returns u (nu x 1), got "
                f"{fn.size_in(0)}, {fn.size_in(1)} -> {fn.size_out(0)}"
            )
        if fn.has_free():
            raise PolicyError(f"CasADi policy {fn.name()!r} has free variables")
        self.function = fn
        self.nx = int(fn.size_in(1)[0])
        self.nu = int(fn.size_out(0)[0])

    def __call__(self, t: Any, state: Any) -> np.ndarray:
        """The controls ``(nu,)`` for one state ``(nx,)``, or ``(B, nu)`` for ``(B, nx)``."""
        s = np.asarray(state, dtype=float)
        if s.ndim not in (1, 2) or s.shape[-1] != self.nx:
            # never reshape another size into this one (8 states read as 2 rows of 4)
            raise PolicyError(
                f"this policy reads {self.nx} state entries, got a state of shape {s.shape}"
            )
        single = s.ndim == 1
        S = s.reshape(-1, self.nx)
        tt = np.broadcast_to(np.asarray(t, dtype=float).reshape(-1), (S.shape[0],))
        if single:
            return np.asarray(self.function(float(tt[0]), S[0])).reshape(-1)
        out = self.function.map(S.shape[0])(tt[None, :], S.T)
        return np.asarray(out).T.copy()

    def casadi(self, symbolic: bool = False) -> Any:
        """The Function itself (``symbolic`` is accepted for the interface of
        :meth:`MLP.casadi`; a CasADi policy has no separate weights)."""
        return self.function

    def parameters(self) -> np.ndarray:
        """No separate weights: an empty vector."""
        return np.zeros(0)

    def __repr__(self) -> str:
        return f"CasadiPolicy({self.function.name()!r}, nx={self.nx}, nu={self.nu})"
