"""Policy files, the network (:mod:`hybridoc.workflows.policy_format`): :class:`MLP`, its
checks and saturation, and :class:`CasadiPolicy`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridoc.errors import HybridocError

__all__ = [
    "ACTIVATIONS",
    "MAX_PARAMETERS",
    "INPUTS",
    "CasadiPolicy",
    "MLP",
    "PolicyError",
    "SATURATIONS",
    "NORMS",
    "check_policy_sizes",
    "float_array",
    "saturation_bounds",
]

ACTIVATIONS = ("tanh", "relu", "sigmoid", "identity")
"""Activations of the hidden layers."""
INPUTS = ("t,state", "state")
"""What the network reads: the time and the state, or the state alone."""
SATURATIONS = ("clip",)
"""Kinds of output saturation of the format (module notes)."""
NORMS = {"state_mean": "nx", "state_scale": "nx", "output_offset": "nu", "output_scale": "nu"}
"""The optional normalisation arrays of a policy and the size each has."""
MAX_PARAMETERS = 10**8
"""The most weights and biases a policy file may describe (800 MB as float64): a larger
``layers`` entry is refused before its weights file is read."""


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
            W = float_array(W, f"layer {k} weight")
            b = float_array(b, f"layer {k} bias")
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
        for name, dim in NORMS.items():
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


def float_array(value: Any, what: str) -> np.ndarray:
    """``value`` as a float array of real numbers, else a :class:`PolicyError` naming
    ``what``."""
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
