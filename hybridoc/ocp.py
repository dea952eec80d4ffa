"""The generic hybrid optimal control problem.

A :class:`HybridOCP` is the one model that the reference, the solvers and the judge
consume::

    minimise   phi(s(T)) + integral_0^T L(s, u) dt
    subject to ds/dt = f(s, u)                  between events
               psi_k(s(gamma-)) = 0             guard k fires when psi_k crosses 0 from above
               s(gamma+) = g_k(s(gamma-))       reset of guard k (or g_k(s(gamma-), u))
               u_min <= u(t) <= u_max           optional control bounds
               c(s(t), u(t)) >= 0               optional path constraints

Modes, time dependence and guards
    A system with discrete modes (:meth:`HybridOCP.from_modes`) and flows and costs that
    read the time (``t=`` in :meth:`HybridOCP.from_expressions` and
    :meth:`HybridOCP.from_modes`) are the same model with one more state coordinate each:
    :mod:`hybridoc.modes` explains both lowerings, and a required final mode. A guard and its
    reset, also one that depends on the control, is a :class:`~hybridoc.guards.Guard`
    (:mod:`hybridoc.guards`).

Terminal constraints and a free final time
    ``terminal_eq`` (``h(s(T)) = 0``) and ``terminal_ineq`` (``h(s(T)) >= 0``) are hard
    constraints; ``horizon_bounds = (T_min, T_max)`` frees the final time (``horizon`` is
    its guess). Issue #15 brings them to every method; a method that does not honour them
    yet says so instead of answering.

What the model cannot express yet
    Static parameters (decisions constant in time): fix such a parameter and solve for
    each value.

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

Data and structure
    The functions (``f``, ``L``, ``phi``, guards, flow map, constraints) are the problem's
    *structure*; ``x0``, ``horizon``, ``steps``, the initial guess, bounds, labels and name
    are *data*. Compiled artefacts (the evaluator's functions, shooting systems, NLPs) depend
    on the structure only: :meth:`HybridOCP.replace` returns a problem with other data that
    reuses them, which is what a sweep over initial states wants.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import casadi as ca
import numpy as np

from hybridoc.arrays import as_float_array
from hybridoc.capabilities import Capabilities
from hybridoc.errors import ControlsError, SceneError
from hybridoc.flowmaps import integrator_flow_map
from hybridoc.flowmaps import integrator_flow_samples as integrator_flow_samples
from hybridoc.guards import Guard
from hybridoc.modes import (
    MODE_LABEL,
    Mode,
    TimeLift,
    checked_modes,
    lifted_modes,
    mode_index_of,
    problem_fields,
)
from hybridoc.scales import Scales

__all__ = [
    "MAX_STEPS",
    "MODE_LABEL",
    "Guard",
    "HybridOCP",
    "Mode",
    "Structure",
    "as_float_array",
    "checked_steps",
]

MAX_STEPS = 10**6
"""The largest grid ``N`` a problem may have: a million cells (the controls alone are then
``16 nu`` MB, and every solver and the judge work cell by cell) is far beyond any grid the
methods need, and a typo such as ``steps = 1e20`` fails with one clear line instead of
exhausting memory."""


class Structure:
    """Identity of a problem's functions, shared by the copies :meth:`HybridOCP.replace`
    makes. Modules key their compiled artefacts on it (weakly)."""

    __slots__ = ("__weakref__", "integrator_flow")

    def __init__(self, integrator_flow: bool) -> None:
        self.integrator_flow = integrator_flow


# fields that do not change the structure (compiled functions stay valid)
_DATA_FIELDS = frozenset(
    {
        "x0",
        "horizon",
        "steps",
        "u_guess",
        "u_min",
        "u_max",
        "state_labels",
        "control_labels",
        "name",
        "meta",
        "horizon_bounds",
        "distribution",
    }
)


@dataclass(eq=False)
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
        The guards with their resets. Their order is the order in which events that happen
        at the same instant are reported.
    x0
        Initial state, shape ``(nx,)``.
    horizon
        Final time ``T``.
    steps
        ``N``, the grid for discrete solvers and piecewise-constant controls; at most
        :data:`MAX_STEPS`.
    u_guess
        Initial guess of the controls, ``(N, nu)``; default zeros (clipped to the bounds).
    flow_map
        Optional CasADi Function ``(s, u, h) -> (s(h), integral_0^h L dt)`` for a constant
        control. Supply it when the flow has a closed form (disc scenes do); otherwise it is
        built from CasADi's CVODES integrator at tight tolerances.
    u_min, u_max
        Optional control bounds, ``(nu,)`` each (``-inf`` / ``inf`` for none). Every method
        honours them or says that it cannot; the judge reports violations.
    path
        Optional path constraints, CasADi Function ``(s, u) -> (m,)``, required ``>= 0``
        along the trajectory.
    state_labels, control_labels
        Names of the components (plots, reports).
    name
        Problem name.
    meta
        Free-form extra information (disc scenes keep their layout here).
    modes
        The names of the discrete modes by index, for a problem with modes (built by
        :meth:`from_modes`): the last state coordinate is then the mode index. ``None``
        (default): no modes. Part of the structure, not data.
    terminal_eq
        Optional terminal equality constraints, CasADi Function ``s -> (m,)``, required
        ``= 0`` at ``s(T)`` (hard, unlike the penalty ``phi``). Part of the structure.
    terminal_ineq
        Optional terminal inequality constraints, ``s -> (m,)``, required ``>= 0`` at
        ``s(T)``. Part of the structure.
    horizon_bounds
        ``(T_min, T_max)`` for a free final time: ``T`` is then a decision variable in
        those bounds and ``horizon`` is its initial guess (and the ``T`` at which the judge
        evaluates given controls); the grid has ``N`` steps of ``T / N`` whatever ``T``.
        The cost depends on ``T`` through the running cost (``L = 1 + ...`` charges time).
        ``None`` (default): ``T = horizon`` is fixed. Data, not structure.
    distribution
        Optional distribution of initial states for the workflows over many draws
        (datasets, policy validation and training): a callable ``(rng, M) -> (M, nx)``
        array, ``rng`` a ``numpy.random.Generator``. The workflows call it with ``M = 1``
        and the generator ``default_rng([seed, i])`` for draw ``i``, so that a draw does
        not depend on how many are made. Data, not structure.
    final_mode
        For a problem with modes: the mode ``s(T)`` must be in (:mod:`hybridoc.modes`, "A
        required final mode"); ``None`` (default): any. Part of the structure.
    scales
        The units the problem is measured in (:class:`~hybridoc.scales.Scales`), which the
        methods use to work in numbers of order one. ``None`` (default):
        :meth:`Scales.identity <hybridoc.scales.Scales.identity>`. Disc scenes fill it from
        their lengths, horizon and masses. Part of the structure.
    capabilities
        What the problem offers beyond its functions (:class:`~hybridoc.capabilities.
        Capabilities`: a closed-form flow, a geometry, a serialisable spec, solver hints).
        ``None`` (default): nothing. The compilers fill it; methods and workflows ask for a
        capability instead of a type. Part of the structure: dropped by a :meth:`replace`
        that changes the functions.
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
    u_min: np.ndarray | None = None
    u_max: np.ndarray | None = None
    path: ca.Function | None = None
    state_labels: list[str] | None = None
    control_labels: list[str] | None = None
    name: str = "ocp"
    meta: dict[str, Any] = field(default_factory=dict)
    modes: tuple[str, ...] | None = None
    terminal_eq: ca.Function | None = None
    terminal_ineq: ca.Function | None = None
    horizon_bounds: tuple[float, float] | None = None
    distribution: Callable[[np.random.Generator, int], np.ndarray] | None = None
    final_mode: str | None = None
    scales: Scales | None = field(default=None, repr=False)
    capabilities: Capabilities | None = field(default=None, repr=False)
    structure: Structure = field(default=None, repr=False)  # type: ignore[assignment]

    DATA_FIELDS: ClassVar[frozenset[str]] = _DATA_FIELDS
    """The fields that :meth:`replace` may change without building a new structure."""

    def __post_init__(self) -> None:
        for attr in ("f", "L", "phi"):
            if not isinstance(getattr(self, attr), ca.Function):
                raise SceneError(f"{attr} must be a casadi.Function")
        self.x0 = as_float_array(self.x0, "x0").ravel()
        try:
            self.horizon = float(self.horizon)
        except (TypeError, ValueError):
            raise SceneError(f"horizon must be a number, got {self.horizon!r}") from None
        self.steps = checked_steps(self.steps)
        if self.horizon <= 0 or not np.isfinite(self.horizon):
            raise SceneError(f"horizon must be positive and finite, got {self.horizon}")
        if not np.all(np.isfinite(self.x0)):
            raise SceneError("x0 must be finite")
        if self.f.n_in() != 2:
            raise SceneError(f"f must be a Function (s, u) -> ds/dt, got {self.f.n_in()} inputs")
        if self.f.size1_in(0) != self.x0.size:
            raise SceneError(
                f"x0 has {self.x0.size} entries but f's state s has {self.f.size1_in(0)}: "
                "give x0 one value per state"
            )
        self.guards = list(self.guards)
        for g in self.guards:
            if not isinstance(g, Guard):
                raise SceneError(f"guards must be Guard objects, got {g!r}")
            g.check_reset(self.x0.size, self.nu)
        names = [g.name for g in self.guards]
        if len(set(names)) != len(names):
            raise SceneError(f"guard names must be unique: {names}")
        self.modes = checked_modes(self.modes, self.guards, self.final_mode, self.x0)
        self._check_terminal()
        self.u_min = self._bound(self.u_min, -np.inf, "u_min")
        self.u_max = self._bound(self.u_max, np.inf, "u_max")
        if np.any(self.u_min > self.u_max):
            raise SceneError("u_min must not exceed u_max")
        if self.scales is None:
            self.scales = Scales.identity(self.nx, self.nu)
        elif not isinstance(self.scales, Scales):
            raise SceneError(f"scales must be a hybridoc.scales.Scales, got {self.scales!r}")
        elif len(self.scales.state) != self.nx or len(self.scales.control) != self.nu:
            raise SceneError(
                f"scales has {len(self.scales.state)} state and {len(self.scales.control)} "
                f"control entries; the problem has {self.nx} and {self.nu}"
            )
        if self.capabilities is None:
            self.capabilities = Capabilities()
        elif not isinstance(self.capabilities, Capabilities):
            raise SceneError(
                "capabilities must be a hybridoc.capabilities.Capabilities, "
                f"got {self.capabilities!r}"
            )
        flow = self.capabilities.flow
        if flow is not None and (self.nx % 2 or flow.A.shape != (self.nx // 2, self.nu)):
            raise SceneError(
                f"capabilities.flow.A has shape {flow.A.shape}; a problem with {self.nx} states "
                f"and {self.nu} controls needs ({self.nx // 2}, {self.nu})"
            )
        if self.path is not None:
            p = self.path
            if not isinstance(p, ca.Function) or p.n_in() != 2 or p.n_out() != 1:
                raise SceneError("path must be a casadi.Function (s, u) -> (m,) constraints")
        if self.u_guess is None:
            self.u_guess = np.clip(np.zeros((self.steps, self.nu)), self.u_min, self.u_max)
        else:
            self.u_guess = self.check_controls(self.u_guess, what="u_guess", bounds=False)
        if self.state_labels is None:
            self.state_labels = [f"s{i}" for i in range(self.nx)]
        if self.control_labels is None:
            self.control_labels = [f"u{i}" for i in range(self.nu)]
        if self.structure is None:
            integrator = self.flow_map is None
            if integrator:
                self.flow_map = integrator_flow_map(self.f, self.L)
            self.structure = Structure(integrator_flow=integrator)

    def mode_index(self, state: Any, *, what: str = "state") -> int:
        """The mode index of a state of a problem with modes (its last coordinate).

        Raises
        ------
        hybridoc.errors.SceneError
            For a problem without modes, or an index that is not an integer or out of range.
        """
        return mode_index_of(self.modes, state, what=what, problem=self.name)

    def mode_of(self, state: Any) -> str:
        """The name of the mode of a state ``(s, q)`` (see :meth:`mode_index`)."""
        index = self.mode_index(state)
        assert self.modes is not None
        return self.modes[index]

    @property
    def initial_mode(self) -> str | None:
        """The mode of ``x0``; ``None`` without modes."""
        return None if self.modes is None else self.mode_of(self.x0)

    def modes_along(self, sequence: Any) -> list[str]:
        """The modes an event sequence visits from the initial mode, that one first.

        ``sequence`` is anything :meth:`check_sequence` takes. A guard without a target mode
        keeps the mode.

        Raises
        ------
        hybridoc.errors.SceneError
            For a problem without modes, an unknown guard, or a guard whose source is not
            the mode the sequence is in at that point.
        """
        if self.modes is None:
            raise SceneError(f"{self.name}: the problem has no modes")
        names = self.check_sequence(sequence)
        current = self.mode_of(self.x0)
        out = [current]
        for k, name in enumerate(names, start=1):
            g = self.guards[self.guard_index(name)]
            if g.source is not None and g.source != current:
                raise SceneError(
                    f"sequence {names}: event {k} ({name!r}) leaves mode {g.source!r}, but the "
                    f"system is in mode {current!r} there (modes so far: {' -> '.join(out)})"
                )
            if g.target is not None:
                current = g.target
            out.append(current)
        return out

    def sequence_feasible(self, sequence: Any) -> bool:
        """Whether an event sequence is possible mode by mode (each guard fires in its source
        mode); always ``True`` without modes. Unknown guard names raise
        :class:`~hybridoc.errors.SceneError`."""
        names = self.check_sequence(sequence)
        if self.modes is None:
            return True
        try:
            self.modes_along(names)
        except SceneError:
            return False
        return True

    def ends_in_final_mode(self, sequence: Any) -> bool:
        """Whether a mode-feasible event sequence leaves the system in :attr:`final_mode`
        (always ``True`` when there is none). A sequence that is not mode-feasible raises
        :class:`~hybridoc.errors.SceneError`."""
        if self.final_mode is None:
            return True
        return self.modes_along(sequence)[-1] == self.final_mode

    def sequence_admissible(self, sequence: Any) -> bool:
        """Whether a whole event sequence can be the answer: mode-feasible
        (:meth:`sequence_feasible`) and ending in :attr:`final_mode` when there is one. (A
        prefix being extended needs only :meth:`sequence_feasible`.)"""
        return self.sequence_feasible(sequence) and self.ends_in_final_mode(sequence)

    def admissible_sequence(self, sequence: Any, *, what: str = "sequence") -> list[str]:
        """A whole event sequence as a list of guard names (:meth:`check_sequence`), checked
        to be :meth:`sequence_admissible`.

        Raises
        ------
        hybridoc.errors.SceneError
            As :meth:`check_sequence`, and for a sequence that leaves a mode by another
            mode's transition or ends outside :attr:`final_mode`, naming the modes visited.
        """
        names = self.check_sequence(sequence, what=what)
        if self.modes is None:
            return names
        visited = self.modes_along(names)
        if self.final_mode is not None and visited[-1] != self.final_mode:
            raise SceneError(
                f"{what} {names} ends in mode {visited[-1]!r} ({' -> '.join(visited)}), but "
                f"the problem requires the final mode {self.final_mode!r}"
            )
        return names

    def _check_terminal(self) -> None:
        """Validate the terminal constraints and the final-time bounds."""
        for attr in ("terminal_eq", "terminal_ineq"):
            fn = getattr(self, attr)
            if fn is None:
                continue
            if (
                not isinstance(fn, ca.Function)
                or fn.n_in() != 1
                or fn.n_out() != 1
                or fn.size1_in(0) != self.nx
                or fn.size2_out(0) != 1
            ):
                raise SceneError(
                    f"{attr} must be a casadi.Function s -> (m,) constraints, with s of the "
                    f"size of x0 ({self.nx})"
                )
        if self.horizon_bounds is None:
            return
        try:
            lo, hi = (float(v) for v in self.horizon_bounds)
        except (TypeError, ValueError):
            raise SceneError(
                f"horizon_bounds must be two numbers (T_min, T_max), got {self.horizon_bounds!r}"
            ) from None
        if not (0 < lo <= hi < np.inf):
            raise SceneError(
                f"horizon_bounds must satisfy 0 < T_min <= T_max < inf, got ({lo}, {hi})"
            )
        if not lo <= self.horizon <= hi:
            raise SceneError(
                f"horizon {self.horizon} (the initial guess of the free final time) must lie "
                f"in horizon_bounds ({lo}, {hi})"
            )
        self.horizon_bounds = (lo, hi)

    @property
    def free_horizon(self) -> bool:
        """Whether the final time is free (:attr:`horizon_bounds` given)."""
        return self.horizon_bounds is not None

    @property
    def has_terminal_constraints(self) -> bool:
        """Whether the problem has terminal equality or inequality constraints (a
        required :attr:`final_mode` is apart: a constraint on the mode sequence)."""
        return self.terminal_eq is not None or self.terminal_ineq is not None

    def terminal_violation(self, s_end: Any) -> float:
        """Largest violation of the terminal constraints at the final state ``s_end``:
        ``max(|h_eq|, max(-h_ineq, 0))``, 0 when there are none; ``inf`` when ``s_end`` is
        not in the required :attr:`final_mode`."""
        s_end = np.asarray(s_end, dtype=float).ravel()
        if self.final_mode is not None and self.mode_of(s_end) != self.final_mode:
            return math.inf
        viol = 0.0
        if self.terminal_eq is not None:
            h = np.asarray(self.terminal_eq(s_end).full()).ravel()
            viol = max(viol, float(np.max(np.abs(h), initial=0.0)))
        if self.terminal_ineq is not None:
            h = np.asarray(self.terminal_ineq(s_end).full()).ravel()
            viol = max(viol, float(np.max(-h, initial=0.0)))
        return viol

    def _bound(self, value: Any, default: float, what: str) -> np.ndarray:
        if value is None:
            return np.full(self.nu, default)
        arr = as_float_array(value, what).ravel()
        if arr.size == 1:
            arr = np.full(self.nu, float(arr[0]))
        if arr.shape != (self.nu,) or np.any(np.isnan(arr)):
            raise SceneError(f"{what} must be {self.nu} numbers (inf for no bound), got {value!r}")
        return arr

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
        path: ca.SX | ca.MX | None = None,
        terminal_eq: ca.SX | ca.MX | None = None,
        terminal_ineq: ca.SX | ca.MX | None = None,
        t: ca.SX | ca.MX | None = None,
        **kwargs: Any,
    ) -> HybridOCP:
        """Build a problem from symbolic expressions in the state ``s`` and control ``u``.

        ``path``, if given, is an expression in ``s`` and ``u`` whose entries must stay
        ``>= 0``; ``terminal_eq`` and ``terminal_ineq`` are expressions in ``s`` (``= 0``
        and ``>= 0`` at ``s(T)``); the other keyword arguments are those of
        :class:`HybridOCP`.

        With ``t`` (a scalar symbol), ``f``, ``L``, ``phi``, ``path`` and the terminal
        constraints may depend on time: the problem is built with one more state coordinate,
        the time (``t' = 1``, ``t(0) = 0``, label ``"t"``, kept by every reset), placed after
        ``s`` (:mod:`hybridoc.modes`, "Time-dependent flows and costs"). ``x0`` and
        ``state_labels`` then give ``s`` only; a guard may be a function of ``s`` or of
        ``(s, t)`` (built with ``ca.vertcat(s, t)`` as its state, its reset returning ``s``
        alone).
        """
        if t is not None:
            if "flow_map" in kwargs:
                raise SceneError(
                    "from_expressions with t: a flow_map cannot be given (the time is added "
                    "to the state); leave it out and the flow is integrated"
                )
            lift = TimeLift(s, t, u)
            return cls.from_expressions(
                lift.x,
                u,
                f=ca.vertcat(lift.of_stu(f, "f"), 1.0),
                L=lift.of_stu(L, "L"),
                phi=lift.of_st(phi, "phi"),
                guards=[lift.guard(g) for g in guards],
                x0=lift.x0(x0),
                horizon=horizon,
                steps=steps,
                path=None if path is None else lift.of_stu(path, "path"),
                terminal_eq=None if terminal_eq is None else lift.of_st(terminal_eq, "terminal_eq"),
                terminal_ineq=None
                if terminal_ineq is None
                else lift.of_st(terminal_ineq, "terminal_ineq"),
                **lift.labels(kwargs),
            )
        return cls(
            f=ca.Function("f", [s, u], [f]),
            L=ca.Function("L", [s, u], [L]),
            phi=ca.Function("phi", [s], [phi]),
            guards=list(guards),
            x0=np.asarray(x0, dtype=float),
            horizon=horizon,
            steps=steps,
            path=None if path is None else ca.Function("path", [s, u], [path]),
            terminal_eq=None
            if terminal_eq is None
            else ca.Function("terminal_eq", [s], [terminal_eq]),
            terminal_ineq=None
            if terminal_ineq is None
            else ca.Function("terminal_ineq", [s], [terminal_ineq]),
            **kwargs,
        )

    @classmethod
    def from_modes(
        cls,
        s: ca.SX | ca.MX,
        u: ca.SX | ca.MX,
        *,
        modes: Sequence[Mode] | Mapping[str, tuple[Any, Any]],
        transitions: Sequence[Guard],
        initial_mode: str,
        phi: ca.SX | ca.MX,
        x0: Sequence[float] | np.ndarray,
        horizon: float,
        steps: int,
        path: ca.SX | ca.MX | None = None,
        state_labels: Sequence[str] | None = None,
        terminal_eq: ca.SX | ca.MX | None = None,
        terminal_ineq: ca.SX | ca.MX | None = None,
        t: ca.SX | ca.MX | None = None,
        **kwargs: Any,
    ) -> HybridOCP:
        """Build a problem with discrete modes (:mod:`hybridoc.modes`, "Modes").

        The problem's state is ``(s, q)``: ``s`` and the mode index ``q`` (a float: 0, 1,
        ... in the order of ``modes``), constant along every flow. Its flow and running cost
        are those of the current mode, ``f = (f_q(s, u), 0)`` and ``L = L_q(s, u)``; a
        transition's guard is ``psi(s)`` in its source mode and ``1`` (free space) in every
        other, and its reset is ``(g(s), index of the target)``.

        Parameters
        ----------
        s, u
            The state symbol (without the mode) and the control symbol.
        modes
            :class:`~hybridoc.modes.Mode` objects, or a dict ``name -> (f, L)`` of
            expressions in ``s`` and ``u`` (``L`` may be ``None`` or ``0``), in index order.
        transitions
            :class:`~hybridoc.guards.Guard` objects with ``source`` and ``target`` mode
            names, ``psi`` and ``reset`` functions of ``s`` (:meth:`Guard.from_expressions
            <hybridoc.guards.Guard.from_expressions>` with ``s``). A
            declared ``degree`` (along the source mode's flow) is kept: outside its source
            mode the guard is constant.
        initial_mode
            The mode at ``t = 0``.
        phi
            Terminal cost, an expression in ``s``.
        x0
            Initial ``s`` (without the mode index).
        horizon, steps
            ``T`` and ``N``.
        path
            Optional path constraints, an expression in ``s`` and ``u`` (``>= 0``).
        state_labels
            Labels of ``s``; ``"mode"`` is appended.
        terminal_eq, terminal_ineq
            Optional terminal constraints, expressions in ``s`` required ``= 0`` and
            ``>= 0`` at ``s(T)``.
        t
            Optional time symbol: the modes' expressions (the dict form), ``phi``, ``path``
            and the terminal constraints may then depend on time, and the state becomes
            ``(s, t, q)`` (:mod:`hybridoc.modes`, "Time-dependent flows and costs").
            :class:`~hybridoc.modes.Mode` objects and transitions stay functions of ``s``.
        **kwargs
            The other fields of :class:`HybridOCP` (``u_guess``, bounds, ``name``, ...);
            not ``flow_map`` (give each :class:`~hybridoc.modes.Mode` its ``flow_map``
            instead).
        """
        if "flow_map" in kwargs:
            raise SceneError(
                "from_modes: give each Mode its flow_map (s, u, h) -> (s(h), cost) instead of "
                "one for the whole problem"
            )
        if t is not None:
            lift = TimeLift(s, t, u)
            return cls.from_modes(
                lift.x,
                u,
                modes=lifted_modes(lift, modes, s, u),
                transitions=[lift.guard(g) for g in transitions],
                initial_mode=initial_mode,
                phi=lift.of_st(phi, "phi"),
                x0=lift.x0(x0),
                horizon=horizon,
                steps=steps,
                path=None if path is None else lift.of_stu(path, "path"),
                terminal_eq=None if terminal_eq is None else lift.of_st(terminal_eq, "terminal_eq"),
                terminal_ineq=None
                if terminal_ineq is None
                else lift.of_st(terminal_ineq, "terminal_ineq"),
                **lift.labels({**kwargs, "state_labels": state_labels}),
            )
        fields = problem_fields(
            s,
            u,
            modes=modes,
            transitions=transitions,
            initial_mode=initial_mode,
            phi=phi,
            x0=x0,
            path=path,
            state_labels=state_labels,
            terminal_eq=terminal_eq,
            terminal_ineq=terminal_ineq,
        )
        return cls(**fields, horizon=horizon, steps=steps, **kwargs)

    def replace(self, **changes: Any) -> HybridOCP:
        """A copy with some fields changed.

        Changing only data (``x0``, ``horizon``, ``steps``, ``u_guess``, bounds, labels,
        ``name``, ``meta``) keeps the structure, so compiled functions are reused. A new
        ``steps`` without a new ``u_guess`` resamples the guess at the new cell midpoints.
        """
        unknown = set(changes) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise TypeError(f"unknown HybridOCP field(s): {sorted(unknown)}")
        if "steps" in changes and "u_guess" not in changes:
            n_new = checked_steps(changes["steps"])  # before allocating the new guess
            mids = (np.arange(n_new) + 0.5) / n_new
            assert self.u_guess is not None
            changes["u_guess"] = self.u_guess[
                np.minimum((mids * self.steps).astype(int), -1 + self.steps)
            ]
        if set(changes) <= self.DATA_FIELDS:
            changes.setdefault("structure", self.structure)
        else:
            changes["structure"] = None
            if "flow_map" not in changes and self.structure.integrator_flow:
                changes["flow_map"] = None
            changes.setdefault("scales", None)  # other functions may mean other units
            changes.setdefault("capabilities", None)  # nor need they offer the same
        changes.setdefault("meta", dict(self.meta))
        return dataclasses.replace(self, **changes)

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

    @property
    def has_bounds(self) -> bool:
        """Whether some control bound is finite."""
        assert self.u_min is not None and self.u_max is not None
        return bool(np.any(np.isfinite(self.u_min)) or np.any(np.isfinite(self.u_max)))

    @property
    def has_closed_form_flow(self) -> bool:
        """Whether the flow map is exact (given) rather than CVODES's integration."""
        return not self.structure.integrator_flow

    def time_grid(self) -> np.ndarray:
        """The ``N + 1`` grid times."""
        return np.linspace(0.0, self.horizon, self.steps + 1)

    def check_controls(self, u: Any, *, what: str = "controls", bounds: bool = False) -> np.ndarray:
        """Validate a piecewise-constant control array and return it as float64 ``(N, nu)``.

        Accepts anything array-like of real numbers (a 1-D array when ``nu == 1``; torch
        tensors are detached). Complex, boolean, object or string arrays, wrong shapes and
        non-finite values raise :class:`~hybridoc.errors.ControlsError`; with ``bounds``, so
        do values outside ``[u_min, u_max]``.
        """
        arr = as_float_array(u, what, error=ControlsError)
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
        if bounds:
            viol = self.bound_violation(arr)
            if viol > 0:
                raise ControlsError(f"{what}: violates the control bounds by {viol:.3g}")
        return arr

    def bound_violation(self, u: np.ndarray) -> float:
        """Largest violation of the control bounds by ``(N, nu)`` controls (0 if none)."""
        assert self.u_min is not None and self.u_max is not None
        low = np.max(self.u_min - u, initial=0.0)
        high = np.max(u - self.u_max, initial=0.0)
        return float(max(low, high, 0.0))

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

    def guard_index(self, name: str) -> int:
        """Index of the guard called ``name``."""
        for k, g in enumerate(self.guards):
            if g.name == name:
                return k
        raise SceneError(f"unknown guard {name!r}; the guards are {[g.name for g in self.guards]}")


def checked_steps(steps: Any) -> int:
    """``steps`` as an int in ``[1, MAX_STEPS]``, or a :class:`SceneError` (the one check of
    a grid size, for problems and scenes alike)."""
    if isinstance(steps, bool) or not isinstance(steps, int | np.integer) or steps < 1:
        raise SceneError(f"steps must be a positive integer, got {steps!r}")
    if steps > MAX_STEPS:
        raise SceneError(f"steps must be at most {MAX_STEPS} (hybridoc.ocp.MAX_STEPS), got {steps}")
    return int(steps)
