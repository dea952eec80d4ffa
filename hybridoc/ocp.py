"""The generic hybrid optimal control problem.

A :class:`HybridOCP` is the one model that the reference, the solvers and the judge
consume::

    minimise   phi(s(T)) + integral_0^T L(s, u) dt
    subject to ds/dt = f(s, u)                  between events
               psi_k(s(gamma-)) = 0             guard k fires when psi_k crosses 0 from above
               s(gamma+) = g_k(s(gamma-))       reset of guard k (or g_k(s(gamma-), u))
               u_min <= u(t) <= u_max           optional control bounds
               c(s(t), u(t)) >= 0               optional path constraints

Modes
    A system with discrete modes (flight and stance, a valve open or shut), each with its
    own flow ``f_q`` and running cost ``L_q``, is the same model with one more state: the
    last coordinate is the mode index ``q`` (a float: 0, 1, ...), constant along every flow
    and set by the resets. :meth:`HybridOCP.from_modes` builds it from :class:`Mode` objects
    and guards with a ``source`` and ``target`` mode: ``f = f_q`` and ``L = L_q`` are selected
    by ``q``, and each guard fires only in its source mode. Every method (the judge, the
    reference, the transcription, gradient descent) then solves it unchanged, and the hybrid
    minimum principle comes out per mode: the Hamiltonian is ``L_q + lambda^T f_q`` on each
    side of a switch, and the costate of ``q`` decouples (``dH/dq = 0`` between switches).
    The state a user sees is ``(s, q)``, its last label ``"mode"``.

Resets that depend on the control
    A guard's reset may be ``s+ = g(s-, u)`` (:meth:`Guard.from_expressions` with ``u=``;
    :attr:`Guard.uses_control`): a restitution or an impulse the controller sets at the
    impact. On the N-grid (the judge of piecewise-constant controls, gradient descent) the
    reset reads the control of the grid cell in which the event happens, and the judge's
    adjoint adds ``lambda(gamma+)^T dg/du`` to that cell's gradient. In continuous time
    (the transcription, the reference) the reset's control at each event is a decision of
    its own, ``v_k`` in the control bounds: a single instant carries no running cost, so
    ``v_k`` minimises ``lambda(gamma+)^T g(s(gamma-), v)`` (a linear dependence needs bounds
    for a minimum to exist). Such a Solution stores the ``v_k``
    (``arrays["event_controls"]``) and the judge
    applies them at its events. The transcription and the HMP reference (where ``v_k`` are
    shooting unknowns with their own stationarity condition) solve these problems.

Terminal constraints and a free final time
    ``terminal_eq`` (``h(s(T)) = 0``) and ``terminal_ineq`` (``h(s(T)) >= 0``) are hard
    constraints; ``horizon_bounds = (T_min, T_max)`` frees the final time (``horizon`` is
    its guess). Issue #15 brings them to every method; a method that does not honour them
    yet says so instead of answering.

Time-dependent flows and costs
    ``f(t, s, u)`` and ``L(t, s, u)`` (and ``phi``, path and terminal constraints that read
    the time) are the same model with one more state: :meth:`HybridOCP.from_expressions`
    and :meth:`HybridOCP.from_modes` with ``t=t_sym`` add the time as a state coordinate
    placed after ``s`` (before the mode index, which stays last), with ``t' = 1``,
    ``t(0) = 0``, the label ``"t"``, and every reset keeping it. Every method then solves the
    problem unchanged, and the judge's gradient and the event rule come out exact (the
    costate of ``t`` carries ``dH/dt``: ``lambda_t + H`` is constant under a constant
    control). Guards stay functions of ``s`` (or of ``(s, t)`` where built
    on ``ca.vertcat(s, t)``). With a free final time the cost and constraints see the
    time ``t`` of the stretched grid, since the time coordinate integrates ``t' = 1``.

A required final mode
    ``final_mode`` (problems with modes) ties the terminal constraints to a mode: ``s(T)``
    must lie in that mode. The judge reports a control that ends in another mode as an
    infinite terminal violation (:attr:`HybridOCP.terminal_violation`), and the reference
    searches only mode sequences that end there (:meth:`HybridOCP.sequence_admissible`).

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
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import casadi as ca
import numpy as np

from hybridoc.capabilities import Capabilities
from hybridoc.errors import ControlsError, SceneError
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

MODE_LABEL = "mode"
"""The label of the mode index, the last state coordinate of a problem with modes."""

_SAME_DEPTH = 32
"""How deep :meth:`HybridOCP.from_modes` compares the modes' expressions for equality."""

_MASKED = 1.0
"""The value of a guard outside its source mode: positive (free space, so it neither fires
nor counts as penetrated there) and constant along every flow of those modes (a polynomial
of degree 0, so the guard's declared ``degree`` still holds)."""


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
        CasADi Function ``s -> s``, or ``(s, u) -> s`` for a reset that depends on the
        control (:attr:`uses_control`; module notes, "Resets that depend on the control").
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
        interval); ``None`` for a general smooth guard. For a transition between modes: along
        the flow of its source mode.
    source, target
        For a transition of a problem with modes (:meth:`HybridOCP.from_modes`): the mode in
        which the guard can fire and the mode its reset enters; ``None`` for problems
        without modes.
    """

    name: str
    psi: ca.Function
    reset: ca.Function
    kind: str = "event"
    bodies: tuple[str, ...] = ()
    detector: ca.Function | None = None
    degree: int | None = None
    source: str | None = None
    target: str | None = None

    def __post_init__(self) -> None:
        r = self.reset
        if not isinstance(r, ca.Function) or r.n_in() not in (1, 2) or r.n_out() != 1:
            got = f"{r.n_in()} inputs" if isinstance(r, ca.Function) else type(r).__name__
            raise SceneError(
                f"guard {self.name!r}: the reset must be a casadi.Function s -> s or "
                f"(s, u) -> s, got {got}"
            )

    @property
    def uses_control(self) -> bool:
        """Whether the reset is a function of the state and the control, ``(s, u) -> s``."""
        return int(self.reset.n_in()) == 2

    def reset_at(self, s: Any, u: Any) -> Any:
        """The state after the jump, ``g(s)`` or ``g(s, u)``, for symbols or numbers
        (``u`` is read only by a reset that :attr:`uses_control`)."""
        return self.reset(s, u) if self.uses_control else self.reset(s)

    def check_reset(self, nx: int, nu: int, *, what: str | None = None) -> None:
        """Raise a :class:`~hybridoc.errors.SceneError` naming the expected signature unless
        the reset is ``s -> s`` or ``(s, u) -> s`` with ``s`` of size ``nx`` and ``u`` of
        size ``nu``."""
        r = self.reset
        sizes = tuple(r.size_in(i) for i in range(r.n_in()))
        want = ((nx, 1),) if r.n_in() == 1 else ((nx, 1), (nu, 1))
        if sizes != want or r.size_out(0) != (nx, 1):
            shown = ", ".join(f"{a}x{b}" for a, b in sizes)
            out = "x".join(map(str, r.size_out(0)))
            raise SceneError(
                f"{what or f'guard {self.name!r}'}: the reset must be a Function s -> s or "
                f"(s, u) -> s with s of size {nx} and u of size {nu} (a reset that depends on "
                f"the control takes the state first), got inputs ({shown}) -> {out}"
            )

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
        source: str | None = None,
        target: str | None = None,
        u: ca.SX | ca.MX | None = None,
    ) -> Guard:
        """Build a guard from symbolic expressions in the state symbol ``s``.

        ``reset`` may also use the control symbol ``u`` when it is given: the reset is then
        ``(s, u) -> s`` (module notes, "Resets that depend on the control"); a reset that
        does not use ``u`` stays ``s -> s``.
        """
        tag = _casadi_name(name)
        det = None if detector is None else ca.Function(f"det_{tag}", [s], [detector])
        with_u = u is not None and isinstance(reset, ca.SX | ca.MX) and ca.depends_on(reset, u)
        try:
            g = (
                ca.Function(f"g_{tag}", [s, u], [reset])
                if with_u
                else ca.Function(f"g_{tag}", [s], [reset])
            )
        except RuntimeError as exc:
            # CasADi's last line names the free symbols ("variables [u] are free")
            free = re.search(r"variables \[(.*?)\] are free", str(exc))
            which = f"it uses {free.group(1)}" if free else str(exc).splitlines()[-1]
            hint = "" if u is not None else " (pass u= for a reset that depends on the control)"
            raise SceneError(
                f"guard {name!r}: the reset must be an expression in s, or in s and u{hint}; "
                f"{which}"
            ) from None
        return cls(
            name=name,
            psi=ca.Function(f"psi_{tag}", [s], [psi]),
            reset=g,
            kind=kind,
            bodies=tuple(bodies),
            detector=det,
            degree=degree,
            source=source,
            target=target,
        )


@dataclass(frozen=True)
class Mode:
    """A discrete mode of a hybrid system: its flow and its running cost.

    Parameters
    ----------
    name
        Unique name, e.g. ``"stance"``.
    f
        CasADi Function ``(s, u) -> ds/dt`` (``s`` without the mode index).
    L
        Running cost, ``(s, u) -> scalar``; ``None`` for none.
    flow_map
        Optional exact flow map of this mode, ``(s, u, h) -> (s(h), integral_0^h L dt)`` for
        a constant control. When every mode has one, :meth:`HybridOCP.from_modes` assembles
        the problem's closed-form flow map from them (the judge then needs no integrator).
    """

    name: str
    f: ca.Function
    L: ca.Function | None = None
    flow_map: ca.Function | None = None

    @classmethod
    def from_expressions(
        cls,
        name: str,
        s: ca.SX | ca.MX,
        u: ca.SX | ca.MX,
        f: ca.SX | ca.MX,
        L: ca.SX | ca.MX | float | None = None,
    ) -> Mode:
        """Build a mode from expressions in the state symbol ``s`` and control ``u``."""
        tag = _casadi_name(name)
        return cls(
            name=name,
            f=ca.Function(f"f_{tag}", [s, u], [f]),
            L=None if L is None else ca.Function(f"L_{tag}", [s, u], [L]),
        )


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
        For a problem with modes: the mode ``s(T)`` must be in (module notes, "A required
        final mode"); ``None`` (default): any. Part of the structure.
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
        self._check_modes()
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
                self.flow_map = _integrator_flow_map(self.f, self.L)
            self.structure = Structure(integrator_flow=integrator)

    def _check_modes(self) -> None:
        """The mode names, the guards' source and target modes and the mode index of x0."""
        with_modes = [g.name for g in self.guards if g.source is not None or g.target is not None]
        if self.modes is None:
            if self.final_mode is not None:
                raise SceneError(
                    f"final_mode {self.final_mode!r} needs a problem with modes (build it with "
                    "HybridOCP.from_modes)"
                )
            if with_modes:
                raise SceneError(
                    f"guard(s) {with_modes} have a source or target mode but the problem has "
                    "no modes (build it with HybridOCP.from_modes)"
                )
            return
        if isinstance(self.modes, str) or not all(isinstance(m, str) and m for m in self.modes):
            raise SceneError(f"modes must be a sequence of non-empty names, got {self.modes!r}")
        self.modes = tuple(self.modes)
        if not self.modes:
            raise SceneError("modes must name at least one mode")
        if len(set(self.modes)) != len(self.modes):
            raise SceneError(f"mode names must be unique: {list(self.modes)}")
        for g in self.guards:
            for role, m in (("source", g.source), ("target", g.target)):
                if m is not None and m not in self.modes:
                    raise SceneError(
                        f"guard {g.name!r}: unknown {role} mode {m!r}; the modes are "
                        f"{list(self.modes)}"
                    )
        self.mode_index(self.x0, what="x0")
        if self.final_mode is not None and self.final_mode not in self.modes:
            raise SceneError(
                f"final_mode {self.final_mode!r} is not one of the modes {list(self.modes)}"
            )

    def mode_index(self, state: Any, *, what: str = "state") -> int:
        """The mode index of a state of a problem with modes (its last coordinate).

        Raises
        ------
        hybridoc.errors.SceneError
            For a problem without modes, or an index that is not an integer or out of range.
        """
        if self.modes is None:
            raise SceneError(f"{self.name}: the problem has no modes")
        arr = np.asarray(state, dtype=float).ravel()
        q = float(arr[-1]) if arr.size else math.nan
        if not (math.isfinite(q) and q == round(q) and 0 <= q < len(self.modes)):
            raise SceneError(
                f"{what}: the mode index (the last state coordinate) must be an integer from 0 "
                f"to {len(self.modes) - 1} (modes {list(self.modes)}), got {q!r}"
            )
        return int(q)

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
        ``s`` (module notes, "Time-dependent flows and costs"). ``x0`` and ``state_labels``
        then give ``s`` only; a guard may be a function of ``s`` or of ``(s, t)`` (built with
        ``ca.vertcat(s, t)`` as its state, its reset returning ``s`` alone).
        """
        if t is not None:
            if "flow_map" in kwargs:
                raise SceneError(
                    "from_expressions with t: a flow_map cannot be given (the time is added "
                    "to the state); leave it out and the flow is integrated"
                )
            lift = _TimeLift(s, t, u)
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
        """Build a problem with discrete modes (module notes, "Modes").

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
            :class:`Mode` objects, or a dict ``name -> (f, L)`` of expressions in ``s`` and
            ``u`` (``L`` may be ``None`` or ``0``), in index order.
        transitions
            :class:`Guard` objects with ``source`` and ``target`` mode names, ``psi`` and
            ``reset`` functions of ``s`` (:meth:`Guard.from_expressions` with ``s``). A
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
            ``(s, t, q)`` (module notes, "Time-dependent flows and costs"). :class:`Mode`
            objects and transitions stay functions of ``s``.
        **kwargs
            The other fields of :class:`HybridOCP` (``u_guess``, bounds, ``name``, ...);
            not ``flow_map`` (give each :class:`Mode` its ``flow_map`` instead).
        """
        if "flow_map" in kwargs:
            raise SceneError(
                "from_modes: give each Mode its flow_map (s, u, h) -> (s(h), cost) instead of "
                "one for the whole problem"
            )
        if t is not None:
            lift = _TimeLift(s, t, u)
            lifted = (
                [lift.mode(str(n), spec) for n, spec in modes.items()]
                if isinstance(modes, Mapping)
                else [lift.mode(m.name, m) for m in _as_modes(modes, s, u)]
            )
            return cls.from_modes(
                lift.x,
                u,
                modes=lifted,
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
        mode_list = _as_modes(modes, s, u)
        names = [m.name for m in mode_list]
        if len(set(names)) != len(names):
            raise SceneError(f"mode names must be unique: {names}")
        if initial_mode not in names:
            raise SceneError(f"initial_mode {initial_mode!r} is not one of the modes {names}")
        ns, nu = s.numel(), u.numel()
        x0_s = as_float_array(x0, "x0").ravel()
        if x0_s.size != ns:
            raise SceneError(
                f"x0 must give the {ns} components of s (the mode index is added from "
                f"initial_mode), got {x0_s.size}"
            )
        for m in mode_list:
            if m.f.n_in() != 2 or m.f.size1_in(0) != ns or m.f.size1_in(1) != nu:
                raise SceneError(f"mode {m.name!r}: f must be a Function (s, u) -> ds/dt")
            if m.f.size_out(0) != (ns, 1):
                raise SceneError(f"mode {m.name!r}: f must return {ns} derivatives")
        sym = ca.SX if isinstance(s, ca.SX) else ca.MX
        x, uu = sym.sym("x", ns + 1), sym.sym("u", nu)
        xs, q = x[:ns], x[ns]
        index = {name: float(k) for k, name in enumerate(names)}

        def select(values: list[Any]) -> Any:
            # component by component: one that is the same expression in every mode (y' = v
            # in flight and stance, a common running cost) stays free of the mode, so that
            # structural checks (a control weight independent of the state) still see it
            rows = []
            for i in range(values[0].numel()):
                col = [v[i] for v in values]
                if all(ca.is_equal(c, col[0], _SAME_DEPTH) for c in col[1:]):
                    rows.append(col[0])
                    continue
                # mode k where q < k + 1/2: robust to a q that an NLP moves by rounding
                out = col[-1]
                for k in range(len(col) - 2, -1, -1):
                    out = ca.if_else(q < k + 0.5, col[k], out)
                rows.append(out)
            return ca.vertcat(*rows)

        f_sel = select([m.f(xs, uu) for m in mode_list])
        L_sel = select([sym(0.0) if m.L is None else m.L(xs, uu) for m in mode_list])
        phi_fn = ca.Function("phi_s", [s], [phi])
        guards = [_transition(g, x, uu, ns, index, names) for g in transitions]
        fm = None
        if all(m.flow_map is not None for m in mode_list):
            h = sym.sym("h")
            ends = [m.flow_map(xs, uu, h) for m in mode_list]  # type: ignore[misc]
            fm = ca.Function(
                "flow_map",
                [x, uu, h],
                [ca.vertcat(select([e[0] for e in ends]), q), select([e[1] for e in ends])],
                ["s", "u", "h"],
                ["s_end", "cost"],
            )
        labels = None
        if state_labels is not None:
            labels = [*map(str, state_labels), MODE_LABEL]
            if len(labels) != ns + 1:
                raise SceneError(f"state_labels must name the {ns} components of s")
        else:
            labels = [f"s{i}" for i in range(ns)] + [MODE_LABEL]
        return cls(
            f=ca.Function("f", [x, uu], [ca.vertcat(f_sel, 0)]),
            L=ca.Function("L", [x, uu], [L_sel]),
            phi=ca.Function("phi", [x], [phi_fn(xs)]),
            guards=guards,
            x0=np.r_[x0_s, index[initial_mode]],
            horizon=horizon,
            steps=steps,
            flow_map=fm,
            path=None
            if path is None
            else ca.Function("path", [x, uu], [_in_state(path, s, u, xs, uu)]),
            state_labels=labels,
            modes=tuple(names),
            terminal_eq=None
            if terminal_eq is None
            else ca.Function("terminal_eq", [x], [_in_s(terminal_eq, s, xs)]),
            terminal_ineq=None
            if terminal_ineq is None
            else ca.Function("terminal_ineq", [x], [_in_s(terminal_ineq, s, xs)]),
            **kwargs,
        )

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


def as_float_array(value: Any, what: str, *, error: type[Exception] = SceneError) -> np.ndarray:
    """``value`` as a float64 array; only real numbers are accepted.

    Torch tensors (also ones that require grad) are detached and copied to the CPU. Complex,
    boolean, string and object data raise ``error`` with a message naming ``what``.
    """
    if hasattr(value, "detach") and hasattr(value, "cpu"):  # a torch tensor, without torch
        value = value.detach().cpu().numpy()
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise error(f"{what}: not a numeric array ({exc})") from None
    if raw.dtype.kind == "O":
        try:
            raw = np.array(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise error(f"{what}: not a numeric array ({exc})") from None
    if raw.dtype.kind == "b":
        raise error(f"{what}: expected real numbers, got a boolean array")
    if raw.dtype.kind == "c":
        raise error(f"{what}: expected real numbers, got complex values")
    if raw.dtype.kind in "USV":
        raise error(f"{what}: not a numeric array (got text)")
    if raw.dtype.kind not in "iuf":
        raise error(f"{what}: not a numeric array (data of type {raw.dtype})")
    return np.array(raw, dtype=np.float64)


def checked_steps(steps: Any) -> int:
    """``steps`` as an int in ``[1, MAX_STEPS]``, or a :class:`SceneError` (the one check of
    a grid size, for problems and scenes alike)."""
    if isinstance(steps, bool) or not isinstance(steps, int | np.integer) or steps < 1:
        raise SceneError(f"steps must be a positive integer, got {steps!r}")
    if steps > MAX_STEPS:
        raise SceneError(f"steps must be at most {MAX_STEPS} (hybridoc.ocp.MAX_STEPS), got {steps}")
    return int(steps)


def _as_modes(modes: Any, s: Any, u: Any) -> list[Mode]:
    """``from_modes``'s modes as :class:`Mode` objects."""
    if isinstance(modes, Mapping):
        out = []
        for name, spec in modes.items():
            if not isinstance(spec, tuple | list) or len(spec) != 2:
                raise SceneError(f"mode {name!r}: expected (f, L) expressions, got {spec!r}")
            f, L = spec
            out.append(Mode.from_expressions(str(name), s, u, f, None if L is None else L))
        modes = out
    modes = list(modes)
    if not modes:
        raise SceneError("from_modes needs at least one mode")
    for m in modes:
        if not isinstance(m, Mode):
            raise SceneError(f"modes must be Mode objects or a dict name -> (f, L), got {m!r}")
    return modes


def _in_state(expr: Any, s: Any, u: Any, xs: Any, uu: Any) -> Any:
    """An expression in ``(s, u)`` rewritten in the augmented state's ``s`` part."""
    return ca.Function("tmp", [s, u], [expr])(xs, uu)


def _in_s(expr: Any, s: Any, xs: Any) -> Any:
    """An expression in ``s`` rewritten in the augmented state's ``s`` part."""
    return ca.Function("tmp", [s], [expr])(xs)


class _TimeLift:
    """The lowering of time dependence: expressions in ``(s, t, u)`` rewritten in the state
    ``x = (s, t)`` (module notes, "Time-dependent flows and costs")."""

    def __init__(self, s: Any, t: Any, u: Any) -> None:
        sym = ca.SX if isinstance(s, ca.SX) else ca.MX
        if not isinstance(t, ca.SX | ca.MX) or not t.is_symbolic() or t.numel() != 1:
            raise SceneError(f"t must be one scalar CasADi symbol (ca.SX.sym('t')), got {t!r}")
        self.s, self.t, self.u = s, t, u
        self.ns = int(s.numel())
        self.x = sym.sym("st", self.ns + 1)
        self.xs, self.xt = self.x[: self.ns], self.x[self.ns]

    def _call(self, args: list[Any], values: list[Any], expr: Any, what: str) -> Any:
        if not isinstance(expr, ca.SX | ca.MX):  # a number, e.g. L = 0
            expr = type(self.x)(as_float_array(expr, what))
        try:
            fn = ca.Function(f"lift_{_casadi_name(what)}", args, [expr])
        except RuntimeError as exc:
            names = ", ".join(a.name() if a.is_symbolic() else "?" for a in args)
            raise SceneError(
                f"{what} must be an expression in ({names}) only: {str(exc).splitlines()[0]}"
            ) from None
        return fn(*values)

    def of_stu(self, expr: Any, what: str) -> Any:
        """``expr(s, t, u)`` as an expression in ``(x, u)``."""
        return self._call([self.s, self.t, self.u], [self.xs, self.xt, self.u], expr, what)

    def of_st(self, expr: Any, what: str) -> Any:
        """``expr(s, t)`` as an expression in ``x``."""
        return self._call([self.s, self.t], [self.xs, self.xt], expr, what)

    def x0(self, x0: Any) -> np.ndarray:
        arr = as_float_array(x0, "x0").ravel()
        if arr.size != self.ns:
            raise SceneError(
                f"x0 must give the {self.ns} components of s (the time, 0 at the start, is "
                f"added), got {arr.size}"
            )
        return np.r_[arr, 0.0]

    def labels(self, kwargs: dict[str, Any]) -> dict[str, Any]:
        """``kwargs`` with ``"t"`` appended to the state labels."""
        out = dict(kwargs)
        given = out.get("state_labels")
        if given is None:
            given = [f"s{i}" for i in range(self.ns)]
        given = [*map(str, given)]
        if len(given) != self.ns:
            raise SceneError(f"state_labels must name the {self.ns} components of s")
        out["state_labels"] = [*given, "t"]
        return out

    def _of_state(self, fn: ca.Function | None, what: str) -> Any:
        """A function of ``s`` or of ``(s, t)`` at the symbolic ``x``."""
        if fn is None:
            return None
        n = fn.size1_in(0) if fn.n_in() == 1 else -1
        if n == self.ns:
            return fn(self.xs)
        if n == self.ns + 1:
            return fn(self.x)
        raise SceneError(f"{what} must be a Function of s ({self.ns}) or of (s, t) ({self.ns + 1})")

    def _of_state_u(self, fn: ca.Function, what: str) -> Any:
        """A reset ``(s, u)`` or ``((s, t), u)`` at the symbolic ``(x, u)``."""
        n, nu = fn.size1_in(0), int(self.u.numel())
        if fn.size1_in(1) != nu:
            raise SceneError(f"{what} must be a Function (s, u) -> s with u of size {nu}")
        if n == self.ns:
            return fn(self.xs, self.u)
        if n == self.ns + 1:
            return fn(self.x, self.u)
        raise SceneError(
            f"{what} must be a Function of (s, u) ({self.ns}) or of ((s, t), u) ({self.ns + 1})"
        )

    def guard(self, g: Guard) -> Guard:
        """A guard of ``s`` (or ``(s, t)``) as a guard of ``x``; its reset keeps the time."""
        if not isinstance(g, Guard):
            raise SceneError(f"guards must be Guard objects, got {g!r}")
        tag = _casadi_name(g.name)
        if g.uses_control:
            reset = self._of_state_u(g.reset, f"guard {g.name!r}: the reset")
        else:
            reset = self._of_state(g.reset, f"guard {g.name!r}: the reset")
        if reset.numel() == self.ns + 1:
            reset = reset[: self.ns]
        if reset.numel() != self.ns:
            raise SceneError(f"guard {g.name!r}: the reset must return the {self.ns} components")
        det = self._of_state(g.detector, f"guard {g.name!r}: the detector")
        lifted = ca.vertcat(reset, self.xt)
        return dataclasses.replace(
            g,
            psi=ca.Function(f"psi_{tag}", [self.x], [self._of_state(g.psi, f"guard {g.name!r}")]),
            reset=ca.Function(f"g_{tag}", [self.x, self.u], [lifted])
            if g.uses_control
            else ca.Function(f"g_{tag}", [self.x], [lifted]),
            detector=None if det is None else ca.Function(f"det_{tag}", [self.x], [det]),
        )

    def mode(self, name: str, spec: Any) -> Mode:
        """A mode of ``from_modes`` (``(f, L)`` expressions in ``(s, t, u)``, or a
        :class:`Mode` of ``s``) as a mode of ``x``; a Mode's flow map advances the time."""
        x, u = self.x, self.u
        if isinstance(spec, Mode):
            L = None if spec.L is None else ca.Function(f"L_{name}", [x, u], [spec.L(self.xs, u)])
            fm = None
            if spec.flow_map is not None:
                h = type(self.x).sym("h")
                end, cost = spec.flow_map(self.xs, u, h)
                fm = ca.Function(
                    f"fm_{_casadi_name(name)}", [x, u, h], [ca.vertcat(end, self.xt + h), cost]
                )
            return Mode(
                spec.name,
                f=ca.Function(
                    f"f_{_casadi_name(name)}", [x, u], [ca.vertcat(spec.f(self.xs, u), 1.0)]
                ),
                L=L,
                flow_map=fm,
            )
        if not isinstance(spec, tuple | list) or len(spec) != 2:
            raise SceneError(f"mode {name!r}: expected (f, L) expressions, got {spec!r}")
        f, L = spec
        return Mode.from_expressions(
            name,
            x,
            u,
            ca.vertcat(self.of_stu(f, f"mode {name!r}: f"), 1.0),
            None if L is None else self.of_stu(L, f"mode {name!r}: L"),
        )


def _transition(
    g: Guard, x: Any, u: Any, ns: int, index: dict[str, float], names: list[str]
) -> Guard:
    """A transition of ``from_modes`` as a guard of the augmented state ``x = (s, q)``."""
    if not isinstance(g, Guard):
        raise SceneError(f"transitions must be Guard objects, got {g!r}")
    for role, m in (("source", g.source), ("target", g.target)):
        if m is None:
            raise SceneError(f"transition {g.name!r} needs a {role} mode (one of {names})")
        if m not in index:
            raise SceneError(f"transition {g.name!r}: unknown {role} mode {m!r}; modes {names}")
    for what, fn in (("psi", g.psi), ("detector", g.detector)):
        if fn is not None and (fn.n_in() != 1 or fn.size1_in(0) != ns):
            raise SceneError(f"transition {g.name!r}: {what} must be a Function of s ({ns})")
    g.check_reset(ns, int(u.numel()), what=f"transition {g.name!r}")
    xs, q = x[:ns], x[ns]
    here = ca.fabs(q - index[g.source]) < 0.5  # type: ignore[index]
    tag = _casadi_name(g.name)

    def masked(fn: ca.Function, prefix: str) -> ca.Function:
        return ca.Function(f"{prefix}_{tag}", [x], [ca.if_else(here, fn(xs), _MASKED)])

    after = ca.vertcat(g.reset_at(xs, u), index[g.target])  # type: ignore[index]
    return dataclasses.replace(
        g,
        psi=masked(g.psi, "psi"),
        reset=ca.Function(f"g_{tag}", [x, u] if g.uses_control else [x], [after]),
        detector=None if g.detector is None else masked(g.detector, "det"),
    )


def _casadi_name(name: str) -> str:
    """A valid CasADi function-name suffix derived from any guard name."""
    # ASCII only: str.isalnum accepts letters such as "\u00e9", which CasADi rejects
    out = "".join(ch if ch.isascii() and ch.isalnum() else "_" for ch in name)
    while "__" in out:
        out = out.replace("__", "_")
    return out.strip("_") or "guard"


def _integrator_flow_map(f: ca.Function, L: ca.Function) -> ca.Function:
    """Flow map ``(s, u, h) -> (s(h), cost)`` from CVODES at tight tolerances."""
    return integrator_flow_samples(f, L, [1.0], name="flow_map")


def integrator_flow_samples(
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
    # quad_err_con: without it CVODES steps by the state alone, and a state that is easy to
    # integrate (a polynomial) gives long steps and a running cost off by 1e-4 relative
    opts = {
        "abstol": 1e-13,
        "reltol": 1e-13,
        "max_num_steps": 100000,
        "show_eval_warnings": False,
        "quad_err_con": True,
    }
    grid = [float(x) for x in fractions]
    integ = ca.integrator(f"{name}_int", "cvodes", dae, 0.0, grid, opts)
    res = integ(x0=s, p=ca.vertcat(u, h))
    return ca.Function(name, [s, u, h], [res["xf"], res["qf"]], ["s", "u", "h"], ["s_end", "cost"])
