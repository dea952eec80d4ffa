"""The generic hybrid optimal control problem.

A :class:`HybridOCP` is the one model that the reference, the solvers and the evaluator
consume::

    minimise   phi(s(T)) + integral_0^T L(s, u) dt
    subject to ds/dt = f(s, u)                  between events
               psi_k(s(gamma-)) = 0             guard k fires when psi_k crosses 0 from above
               s(gamma+) = g_k(s(gamma-))       reset of guard k

Everything symbolic is a CasADi :class:`casadi.Function`. Disc scenes compile to it
(:meth:`hybridoc.problems.Scene.to_ocp`); any other system is a few lines, e.g. a ball
bouncing under gravity::

    import casadi as ca
    from hybridoc import Guard, HybridOCP

    s, u = ca.SX.sym("s", 2), ca.SX.sym("u")          # height, velocity; thrust
    ocp = HybridOCP.from_expressions(
        s, u, f=ca.vertcat(s[1], u - 9.81), L=0.01 * u**2, phi=(s[0] - 1.0) ** 2,
        guards=[Guard.from_expressions("ground", s, s[0], ca.vertcat(s[0], -0.9 * s[1]),
                                       degree=2)],
        x0=[1.0, 0.0], horizon=2.0, steps=200)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from hybridoc.errors import ControlsError, SceneError

__all__ = ["Guard", "HybridOCP"]


@dataclass(frozen=True)
class Guard:
    """A named guard ``psi(s) = 0`` with its reset map ``s+ = g(s-)``.

    Parameters
    ----------
    name
        Unique name, e.g. ``"ball1|ball2"``.
    psi
        CasADi Function ``s -> scalar``; positive in free space.
    reset
        CasADi Function ``s -> s``.
    kind
        Free label reported with events, e.g. ``"disc-disc"``.
    bodies
        Names of the bodies involved, reported with events.
    detector
        Optional CasADi Function ``s -> scalar`` with the same sign and zero set as ``psi``
        that is polynomial along the flow (e.g. a squared distance). Used only to locate
        events; defaults to ``psi``.
    degree
        Degree in time of ``detector`` along the flow under a constant control, if it is a
        polynomial (then events are located exactly from ``degree + 1`` samples per grid
        interval); ``None`` for a general smooth guard.
    """

    name: str
    psi: ca.Function
    reset: ca.Function
    kind: str = "event"
    bodies: tuple[str, ...] = ()
    detector: ca.Function | None = None
    degree: int | None = None

    @classmethod
    def from_expressions(
        cls,
        name: str,
        s: ca.SX | ca.MX,
        psi: ca.SX | ca.MX,
        reset: ca.SX | ca.MX,
        *,
        kind: str = "event",
        bodies: Sequence[str] = (),
        detector: ca.SX | ca.MX | None = None,
        degree: int | None = None,
    ) -> Guard:
        """Build a guard from symbolic expressions in the state symbol ``s``."""
        tag = _casadi_name(name)
        det = None if detector is None else ca.Function(f"det_{tag}", [s], [detector])
        return cls(
            name=name,
            psi=ca.Function(f"psi_{tag}", [s], [psi]),
            reset=ca.Function(f"g_{tag}", [s], [reset]),
            kind=kind,
            bodies=tuple(bodies),
            detector=det,
            degree=degree,
        )


@dataclass
class HybridOCP:
    """A hybrid optimal control problem with autonomous state jumps.

    Parameters
    ----------
    f
        Flow, CasADi Function ``(s, u) -> ds/dt``.
    L
        Running cost, ``(s, u) -> scalar``.
    phi
        Terminal cost, ``s -> scalar``.
    guards
        The guards with their resets, in the order used to resolve simultaneous events.
    x0
        Initial state, shape ``(nx,)``.
    horizon
        Final time ``T``.
    steps
        ``N``, the grid for discrete solvers and piecewise-constant controls.
    u_guess
        Initial guess of the controls, ``(N, nu)``; default zeros.
    flow_map
        Optional CasADi Function ``(s, u, h) -> (s(h), integral_0^h L dt)`` for a constant
        control. Supply it when the flow has a closed form (disc scenes do); otherwise it is
        built from CasADi's CVODES integrator at tight tolerances.
    state_labels, control_labels
        Names of the components (plots, reports).
    name
        Problem name.
    meta
        Free-form extra information (disc scenes keep their layout here).
    """

    f: ca.Function
    L: ca.Function
    phi: ca.Function
    guards: list[Guard]
    x0: np.ndarray
    horizon: float
    steps: int
    u_guess: np.ndarray | None = None
    flow_map: ca.Function | None = None
    state_labels: list[str] | None = None
    control_labels: list[str] | None = None
    name: str = "ocp"
    meta: dict[str, Any] = field(default_factory=dict)
    _cache: dict[str, Any] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        self.x0 = np.asarray(self.x0, dtype=float).ravel()
        self.horizon = float(self.horizon)
        self.steps = int(self.steps)
        if self.horizon <= 0 or not np.isfinite(self.horizon):
            raise ValueError(f"horizon must be positive and finite, got {self.horizon}")
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        if self.f.n_in() != 2 or self.f.size1_in(0) != self.x0.size:
            raise ValueError("f must be a Function (s, u) -> ds/dt with s of the size of x0")
        if self.u_guess is None:
            self.u_guess = np.zeros((self.steps, self.nu))
        else:
            self.u_guess = self.check_controls(self.u_guess, what="u_guess")
        names = [g.name for g in self.guards]
        if len(set(names)) != len(names):
            raise ValueError(f"guard names must be unique: {names}")
        if self.state_labels is None:
            self.state_labels = [f"s{i}" for i in range(self.nx)]
        if self.control_labels is None:
            self.control_labels = [f"u{i}" for i in range(self.nu)]
        if self.flow_map is None:
            self.flow_map = _integrator_flow_map(self.f, self.L)
            # tells the evaluator it may sample the flow with one gridded integrator call
            self._cache["integrator_flow"] = True

    @classmethod
    def from_expressions(
        cls,
        s: ca.SX | ca.MX,
        u: ca.SX | ca.MX,
        *,
        f: ca.SX | ca.MX,
        L: ca.SX | ca.MX,
        phi: ca.SX | ca.MX,
        guards: Sequence[Guard],
        x0: Sequence[float] | np.ndarray,
        horizon: float,
        steps: int,
        **kwargs: Any,
    ) -> HybridOCP:
        """Build a problem from symbolic expressions in the state ``s`` and control ``u``."""
        return cls(
            f=ca.Function("f", [s, u], [f]),
            L=ca.Function("L", [s, u], [L]),
            phi=ca.Function("phi", [s], [phi]),
            guards=list(guards),
            x0=np.asarray(x0, dtype=float),
            horizon=horizon,
            steps=steps,
            **kwargs,
        )

    @property
    def nx(self) -> int:
        """State dimension."""
        return int(self.x0.size)

    @property
    def nu(self) -> int:
        """Control dimension."""
        return int(self.f.size1_in(1))

    @property
    def dt(self) -> float:
        """Grid step ``T / N``."""
        return self.horizon / self.steps

    def time_grid(self) -> np.ndarray:
        """The ``N + 1`` grid times."""
        return np.linspace(0.0, self.horizon, self.steps + 1)

    def check_controls(self, u: Any, *, what: str = "controls") -> np.ndarray:
        """Validate a piecewise-constant control array and return it as float64 ``(N, nu)``.

        A 1-D array is accepted when ``nu == 1``.
        """
        try:
            arr = np.array(u, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ControlsError(f"{what}: not a numeric array ({exc})") from None
        if arr.ndim == 1 and self.nu == 1:
            arr = arr[:, None]
        if arr.shape != (self.steps, self.nu):
            raise ControlsError(
                f"{what}: expected shape ({self.steps}, {self.nu}) (N rows, one column per "
                f"control component), got {arr.shape}"
            )
        if not np.all(np.isfinite(arr)):
            bad = np.argwhere(~np.isfinite(arr))[0]
            raise ControlsError(f"{what}: non-finite value at row {bad[0]}, column {bad[1]}")
        return arr

    def check_sequence(self, sequence: Any, *, what: str = "sequence") -> list[str]:
        """Validate an event sequence and return it as a list of guard names.

        ``sequence`` is a list of guard names in event order or one comma-separated string
        (``"ball1|ball2,ball2|wall"``); an empty list or a blank string means no event.

        Raises
        ------
        hybridoc.errors.SceneError
            For an empty name inside a non-empty sequence (``"a,,b"``), a name that is not a
            guard of this problem, or a value that is neither a string nor a list of strings.
        """
        if isinstance(sequence, str):
            items = [] if not sequence.strip() else [s.strip() for s in sequence.split(",")]
        elif isinstance(sequence, Sequence) and all(isinstance(s, str) for s in sequence):
            items = [s.strip() for s in sequence]
        else:
            raise SceneError(
                f"{what}: expected guard names (a list of strings or one comma-separated "
                f"string), got {sequence!r}"
            )
        names = [g.name for g in self.guards]
        if any(not s for s in items):
            raise SceneError(f"{what}: empty event name in {sequence!r}; the guards are {names}")
        bad = [s for s in items if s not in names]
        if bad:
            raise SceneError(f"{what}: unknown guard(s) {bad}; the guards are {names}")
        return items


def _casadi_name(name: str) -> str:
    """A valid CasADi function-name suffix derived from any guard name."""
    out = "".join(ch if ch.isalnum() else "_" for ch in name)
    while "__" in out:
        out = out.replace("__", "_")
    return out.strip("_") or "guard"


def _integrator_flow_map(f: ca.Function, L: ca.Function) -> ca.Function:
    """Flow map ``(s, u, h) -> (s(h), cost)`` from CVODES at tight tolerances."""
    return _integrator_flow_samples(f, L, [1.0], name="flow_map")


def _integrator_flow_samples(
    f: ca.Function, L: ca.Function, fractions: Sequence[float], *, name: str = "flow_samples"
) -> ca.Function:
    """``(s, u, h) -> (s(h * fractions), cost(h * fractions))`` by one CVODES call.

    ``fractions`` are increasing in (0, 1]; the outputs have one column per fraction.
    """
    nx, nu = f.size1_in(0), f.size1_in(1)
    s = ca.MX.sym("s", nx)
    u = ca.MX.sym("u", nu)
    h = ca.MX.sym("h")
    xs = ca.SX.sym("x", nx)
    ps = ca.SX.sym("p", nu + 1)
    us, hs = ps[:nu], ps[nu]
    # time scaled to [0, 1] so that h is a parameter (and h = 0 is allowed)
    dae = {"x": xs, "p": ps, "ode": hs * f(xs, us), "quad": hs * L(xs, us)}
    opts = {"abstol": 1e-13, "reltol": 1e-13, "max_num_steps": 100000}
    grid = [float(x) for x in fractions]
    integ = ca.integrator(f"{name}_int", "cvodes", dae, 0.0, grid, opts)
    res = integ(x0=s, p=ca.vertcat(u, h))
    return ca.Function(name, [s, u, h], [res["xf"], res["qf"]], ["s", "u", "h"], ["s_end", "cost"])
