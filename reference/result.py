"""The reference's result type: one HMP extremal, its dense evaluation and its Solution."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hybridoc.ocp import HybridOCP
from hybridoc.reference._nodes import control_from_nodes, dense_from_nodes, same_arrays
from hybridoc.reference.shooting import NewtonResult, ShootingSystem, state_rows
from hybridoc.reference.sources import PhaseCostates

__all__ = ["GRAZE_FLAG", "ReferenceResult", "hmp_control", "make_result", "reference_control"]

#: approach speeds ``|d psi/dt|`` below this flag the event as grazing
GRAZE_FLAG = 1e-6
#: steps per phase that rebuild ``u(t)`` of a saved generic solution without ``substeps``
LEGACY_SUBSTEPS = 64


@dataclass
class ReferenceResult:
    """The HMP solution for one event sequence.

    Attributes
    ----------
    ocp
        The problem.
    sequence
        Guard names in event order.
    event_times
        ``gamma_k``, shape ``(K,)``.
    multipliers
        Jump multipliers ``pi_k``.
    phase_starts, phase_states, phase_costates
        Start time, ``s`` and ``lambda`` (after the jump) of each of the ``K + 1`` phases.
    states_minus, costates_minus
        ``s(gamma_k-)`` and ``lambda(gamma_k-)``, shape ``(K, nx)``.
    approach_speeds
        ``d psi_k / dt`` just before each event (negative for a real impact).
    final_state, final_costate
        ``s(T)``, ``lambda(T)``.
    cost, terminal_cost, running_cost
        Shooting cost and its parts.
    residual
        Max-norm of the HMP residual at the solution.
    newton_iterations, residual_history
        Newton's iteration count and residual per iteration (quadratic convergence).
    grazing
        True if some event has approach speed below ``GRAZE_FLAG`` in magnitude.
    path
        How Newton was started: ``"costate-estimate"``, ``"nlp"`` or ``"feasibility"``.
    levels
        Generic problems: the DOP853 steps of each phase (``None`` for disc scenes, whose
        phases are exact).
    integration_error
        The estimated relative error of ``cost`` from the integration (step doubling; 0 for
        disc scenes).
    nodes
        Generic problems: per phase, the ``(n_k + 1, 2 nx + 1)`` nodes of its steps
        (``s``, ``lambda``, running cost), from which ``u(t)`` is rebuilt between them.
    terminal_eq_multipliers, terminal_ineq_multipliers
        ``nu`` and ``mu`` of the terminal constraints (empty without them), with
        ``lambda(T) = grad phi - Dh_eq^T nu - Dh_in^T mu`` and ``mu >= 0``.
    final_hamiltonian
        ``H(T)`` under ``u*``: the derivative of the optimal cost with respect to the final
        time; 0 (to the tolerance) at a free final time strictly inside its bounds.
    judged_terminal_violation
        The terminal constraints' violation at the judge's re-simulated final state, set by
        :func:`~hybridoc.reference.sequence.judged_reference` (``None`` before).
    event_controls
        ``(K, nu)``: the control each event's reset reads, on a sequence with a reset that
        depends on the control: its own control ``v_k`` there (a shooting unknown), elsewhere
        ``u(gamma_k-)`` (which that reset does not read); ``None`` on any other sequence.
        The judge applies them at its events (``arrays["event_controls"]``).
    arc_starts, arc_states, arc_costates, arc_levels, arc_nodes
        A generic problem with path constraints whose phases have junctions: every arc's
        start time (phase starts and junctions, in time order), ``s`` and ``lambda`` there,
        its DOP853 steps and its nodes under the constrained minimum of ``H``; ``u(t)`` is
        rebuilt per arc, so that no step of the dense output crosses a kink of ``u``
        (``None`` otherwise: per phase). ``arc_costates`` are after the costate jump at the
        entry of a pure state constraint's boundary arc.
    arc_laws
        With pure state constraints (whose boundary arcs the pointwise minimum of ``H``
        cannot tell): each arc's own law (:data:`~hybridoc.reference.shooting.ArcLaw`), by
        which its nodes and ``u(t)`` are rebuilt; ``None`` otherwise.
    coverage
        What the search that chose this extremal covered (the sources, the sequences
        proposed, solved and pruned, the exhaustive length, whether the budget stopped it,
        the best cost of each number of events), set by
        :func:`~hybridoc.reference.solve.solve_reference` on the extremal it returns and
        copied to ``info["coverage"]``; ``None`` for an extremal solved on its own.
    start_costs
        The costs of the extremals that every converged start reached in the solve of the
        sequence that found this one (:func:`~hybridoc.reference.sequence.solve_sequence`;
        the cheapest is this one): the search's test that the sequence's extremal was found
        from several starts.
    judged
        The judge's re-simulation of :meth:`control_function` that verified this extremal
        (:func:`~hybridoc.reference.sequence.judged_reference`; ``None`` before, or where it
        did not verify). :meth:`to_solution` takes the judge's cost from it when the
        Solution's ``u(t)``, rebuilt from its arrays, is provably the same function.
    """

    ocp: HybridOCP
    sequence: list[str]
    event_times: np.ndarray
    multipliers: np.ndarray
    phase_starts: np.ndarray
    phase_states: np.ndarray
    phase_costates: np.ndarray
    states_minus: np.ndarray
    costates_minus: np.ndarray
    approach_speeds: np.ndarray
    final_state: np.ndarray
    final_costate: np.ndarray
    cost: float
    terminal_cost: float
    running_cost: float
    residual: float
    newton_iterations: int
    residual_history: list[float]
    grazing: bool
    path: str
    system: ShootingSystem = field(repr=False)
    z: np.ndarray = field(repr=False)
    levels: tuple[int, ...] | None = None
    integration_error: float = 0.0
    nodes: list[np.ndarray] | None = field(default=None, repr=False)
    terminal_eq_multipliers: np.ndarray = field(default_factory=lambda: np.zeros(0))
    terminal_ineq_multipliers: np.ndarray = field(default_factory=lambda: np.zeros(0))
    final_hamiltonian: float = 0.0
    judged_terminal_violation: float | None = None
    event_controls: np.ndarray | None = None
    coverage: dict[str, Any] | None = field(default=None, repr=False)
    judged: Any = field(default=None, repr=False, compare=False)
    arc_starts: np.ndarray | None = None
    arc_states: np.ndarray | None = None
    arc_costates: np.ndarray | None = None
    arc_levels: tuple[int, ...] | None = None
    arc_nodes: list[np.ndarray] | None = field(default=None, repr=False)
    start_costs: tuple[float, ...] = field(default=(), repr=False, compare=False)
    arc_laws: list[tuple[tuple[float, float], ...]] | None = None

    def _piece_laws(self, attr: str) -> Any:
        """``attr`` (``"dense"``, ``"dense_u"``) of the dense output's law: one per arc with
        pure state constraints, else the constrained minimum of ``H``."""
        core = self.system.core
        if self.arc_laws is not None and self.arc_nodes is not None:
            return [getattr(core.fl.law(m), attr) for m in self.arc_laws]
        return getattr(core.flow, attr)

    @property
    def horizon(self) -> float:
        """The final time (a free one as found)."""
        return float(self.ocp.horizon)

    @property
    def horizon_at_bound(self) -> str | None:
        """``"min"`` or ``"max"`` when a free final time lies at that bound, else ``None``."""
        bounds = self.ocp.horizon_bounds
        if bounds is None:
            return None
        if self.horizon <= bounds[0]:
            return "min"
        if self.horizon >= bounds[1]:
            return "max"
        return None

    def terminal_multipliers(self) -> dict[str, Any]:
        """``info["terminal_multipliers"]``: ``eq`` (``nu``), ``ineq`` (``mu``) and the
        sign convention."""
        return {
            "eq": [float(v) for v in self.terminal_eq_multipliers],
            "ineq": [float(v) for v in self.terminal_ineq_multipliers],
            "convention": "lambda(T) = grad phi - Dh_eq^T eq - Dh_ineq^T ineq, ineq >= 0",
        }

    # ------------------------------------------------------------------ dense evaluation
    def _phase_of(self, t: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.phase_starts, t, side="right") - 1, 0, None)

    def control_coefficients(self) -> np.ndarray | None:
        """Disc scenes: ``(K + 1, 2, nu)`` with ``u = c0 + c1 (t - t_k)`` on phase ``k``."""
        S = self.system
        if not S.disc:
            return None
        out = np.empty((self.phase_starts.size, 2, S.nu))
        for k, lam in enumerate(self.phase_costates):
            c0, c1 = S.core.control_coeffs(lam)
            out[k, 0] = np.asarray(c0).ravel()
            out[k, 1] = np.asarray(c1).ravel()
        return out

    def dense(
        self, times: Sequence[float] | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(s, lambda, u)`` at ``times`` (after any jump at exactly that time)."""
        t = np.atleast_1d(np.asarray(times, dtype=float))
        S = self.system
        k = self._phase_of(t)
        tau = t - self.phase_starts[k]
        nx, n2 = S.nx, S.nx // 2
        if S.disc:
            C = self.control_coefficients()
            assert C is not None
            c0, c1 = C[k, 0], C[k, 1]
            u = c0 + c1 * tau[:, None]
            a0, a1 = c0 @ S.A.T, c1 @ S.A.T
            s0, l0 = self.phase_states[k], self.phase_costates[k]
            tt = tau[:, None]
            p = s0[:, :n2] + s0[:, n2:] * tt + a0 * tt**2 / 2 + a1 * tt**3 / 6
            v = s0[:, n2:] + a0 * tt + a1 * tt**2 / 2
            lam = np.hstack([l0[:, :n2], l0[:, n2:] - l0[:, :n2] * tt])
            return np.hstack([p, v]), lam, u
        if t.size == 0:
            return np.zeros((0, nx)), np.zeros((0, nx)), np.zeros((0, S.nu))
        nodes, levels, starts = self._pieces()
        s_out, l_out, u_out = dense_from_nodes(
            self._piece_laws("dense"), nodes, levels, starts, self.ocp.horizon, t
        )
        return s_out, l_out, u_out

    def _pieces(self) -> tuple[list[np.ndarray], Sequence[int], np.ndarray]:
        """The dense output's nodes, steps and start times: per arc where they are kept,
        else per phase."""
        if self.arc_nodes is not None:
            assert self.arc_levels is not None and self.arc_starts is not None
            return self.arc_nodes, self.arc_levels, self.arc_starts
        assert self.nodes is not None and self.levels is not None
        return self.nodes, self.levels, self.phase_starts

    def control(self, t: float) -> np.ndarray:
        """The optimal control ``u(t)`` (right-continuous at events)."""
        return self.dense([t])[2][0]

    def control_function(self) -> Callable[[float], np.ndarray]:
        """A fast scalar callable ``u(t)`` for :func:`hybridoc.evaluate_callable`."""
        C = self.control_coefficients()
        starts = self.phase_starts
        if C is None:
            nodes, levels, piece_starts = self._pieces()
            return control_from_nodes(
                self._piece_laws("dense_u"), nodes, levels, piece_starts, self.ocp.horizon
            )

        def u(t: float) -> np.ndarray:
            k = max(int(np.searchsorted(starts, t, side="right")) - 1, 0)
            return C[k, 0] + C[k, 1] * (t - starts[k])

        return u

    def cell_averages(self) -> np.ndarray:
        """``(N, nu)``: the mean of ``u(t)`` over each grid interval.

        Gauss-Legendre (6 points) on each piece between grid points and events: exact for
        the linear controls of disc scenes.
        """
        grid = self.ocp.time_grid()
        x, w = np.polynomial.legendre.leggauss(6)
        cuts = np.union1d(grid, self.event_times)
        a, b = cuts[:-1], cuts[1:]
        mid = 0.5 * (a + b)
        # evaluate each piece strictly inside so the phase is unambiguous
        tq = (mid[:, None] + 0.5 * (b - a)[:, None] * x[None, :]).ravel()
        u = self.dense(tq)[2].reshape(a.size, x.size, -1)
        integ = 0.5 * (b - a)[:, None] * np.einsum("q,pqn->pn", w, u)
        cell = np.clip(np.searchsorted(grid, mid, side="right") - 1, 0, grid.size - 2)
        out = np.zeros((grid.size - 1, u.shape[2]))
        np.add.at(out, cell, integ)
        return out / np.diff(grid)[:, None]

    def trajectory(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Times (grid and events, events twice: before and after), states, costates."""
        grid = self.ocp.time_grid()
        t = np.union1d(grid, self.event_times)
        s, lam, _ = self.dense(t)
        times, S, L = list(t), list(s), list(lam)
        for k in range(len(self.sequence) - 1, -1, -1):
            i = int(np.searchsorted(t, self.event_times[k]))
            times.insert(i, float(self.event_times[k]))
            S.insert(i, self.states_minus[k])
            L.insert(i, self.costates_minus[k])
        # at T: the end of the last phase
        S[-1], L[-1] = self.final_state, self.final_costate
        return np.array(times), np.array(S), np.array(L)

    def event_dicts(self) -> list[dict[str, Any]]:
        """``[{"time", "kind", "bodies", "guard"}]`` as the judge writes them (with
        ``"mode_before"`` and ``"mode_after"`` on a problem with modes)."""
        out = []
        modes = None if self.ocp.modes is None else self.ocp.modes_along(self.sequence)
        for k, (name, t) in enumerate(zip(self.sequence, self.event_times, strict=True)):
            g = self.ocp.guards[self.ocp.guard_index(name)]
            out.append({"time": float(t), "kind": g.kind, "bodies": list(g.bodies), "guard": name})
            if modes is not None:
                out[-1].update(mode_before=modes[k], mode_after=modes[k + 1])
        return out

    def phase_costates_at(self, times: Sequence[float] | np.ndarray) -> PhaseCostates:
        """This extremal's states and costates cut at other event times: a warm start of the
        shooting of a neighbouring sequence (the events the judge's re-simulation of this
        control has). A time within ``1e-7 T`` of one of this extremal's own events takes
        the values on either side of its jump; elsewhere the costate is continuous, so the
        new event's multiplier starts at 0."""
        t = np.asarray(times, dtype=float).ravel()
        T = self.horizon
        s_in, l_in, _ = self.dense(np.clip(t, 0.0, T)) if t.size else (None, None, None)
        starts, ends, states = [self.phase_costates[0]], [], []
        for k, tk in enumerate(t):
            assert s_in is not None and l_in is not None
            near = np.abs(self.event_times - tk) <= 1e-7 * T
            if near.any():
                j = int(np.argmax(near))
                states.append(self.states_minus[j])
                ends.append(self.costates_minus[j])
                starts.append(self.phase_costates[j + 1])
            else:
                states.append(s_in[k])
                ends.append(l_in[k])
                starts.append(l_in[k])
        states.append(self.final_state)
        ends.append(self.final_costate)
        return PhaseCostates(t, starts, ends, states, horizon=T)

    def hmp_residuals(self) -> dict[str, float]:
        """Max-norm of each group of HMP conditions, recomputed from the stored numbers."""
        R = np.asarray(self.system.F(self.z)[0]).ravel()
        nx = self.system.nx
        out = {"transversality": float(np.max(np.abs(R[:nx])))}
        K = len(self.sequence)
        end = nx + K * (nx + 2)
        blk = R[nx:end].reshape(K, nx + 2) if K else np.zeros((0, nx + 2))
        out["guard"] = float(np.max(np.abs(blk[:, 0]), initial=0.0))
        out["costate_jump"] = float(np.max(np.abs(blk[:, 1:-1]), initial=0.0))
        out["hamiltonian"] = float(np.max(np.abs(blk[:, -1]), initial=0.0))
        m_eq, m_in = self.system.core.m_eq, self.system.core.m_in
        if m_eq:
            out["terminal_eq"] = float(np.max(np.abs(R[end : end + m_eq])))
        if m_in:
            out["terminal_ineq"] = float(np.max(np.abs(R[end + m_eq : end + m_eq + m_in])))
        n_v = int(getattr(self.system.core, "n_v", 0))
        if n_v:
            # the reset controls' conditions close the residual (before a free T's H(T))
            stop = R.size - int(self.system.core.free)
            out["event_control"] = float(np.max(np.abs(R[stop - n_v : stop])))
        if self.ocp.free_horizon and self.horizon_at_bound is None:
            out["free_time"] = abs(float(self.final_hamiltonian))
        return out

    def to_solution(
        self, *, timings: dict[str, Any] | None = None, info: dict[str, Any] | None = None
    ) -> Any:
        """The :class:`~hybridoc.solution.Solution` (method ``"reference"``).

        Its status is ``extremal``: one extremal knows nothing of other event sequences;
        :func:`~hybridoc.reference.solve.solve_reference` sets ``success`` when its
        discovery has compared it with everything else it met.
        """
        from hybridoc.solution import Solution, Status

        times, states, costates = self.trajectory()
        arrays = self._solution_arrays()
        base_info = self._solution_info(info)
        sol = Solution(
            method="reference",
            scene=self.ocp.name,
            controls=self.cell_averages(),
            time_grid=self.ocp.time_grid(),
            cost=self.cost,
            terminal_cost=self.terminal_cost,
            running_cost=self.running_cost,
            events=self.event_dicts(),
            state_times=times,
            states=states,
            costate_times=times,
            costates=costates,
            settings={},
            timings=dict(timings or {}),
            info=base_info,
            arrays=arrays,
            status=Status.EXTREMAL,
        )
        sol.reference = self  # type: ignore[attr-defined]  # u(t) for generic problems
        # the cost is the judge's, of the control the Solution carries (rebuilt from its
        # arrays, as after a save and a load): the shooting's own stays in info
        sol.info["shooting_cost"] = float(self.cost)
        sol.bind(self.ocp)
        ev = self._judged_as_saved(sol)
        if ev is None:
            sol.judge()
        else:
            sol.with_evaluation(ev)
        return sol

    def _solution_arrays(self) -> dict[str, np.ndarray]:
        """The Solution's ``arrays``: what rebuilds ``u(t)`` and the costates after a load
        (event times, phase and arc nodes, control coefficients, substeps, event controls)."""
        arrays = {
            "event_times": np.asarray(self.event_times, dtype=float),
            "multipliers": np.asarray(self.multipliers, dtype=float),
            "phase_starts": self.phase_starts,
            "phase_states": self.phase_states,
            "phase_costates": self.phase_costates,
            "residual_history": np.asarray(self.residual_history),
        }
        C = self.control_coefficients()
        if C is not None:
            arrays["control_coefficients"] = C
        if self.levels is not None:
            arrays["substeps"] = np.asarray(self.levels, dtype=np.int64)
        if self.arc_nodes is not None:
            assert self.arc_levels is not None
            arrays["arc_starts"] = np.asarray(self.arc_starts, dtype=float)
            arrays["arc_states"] = np.asarray(self.arc_states, dtype=float)
            arrays["arc_costates"] = np.asarray(self.arc_costates, dtype=float)
            arrays["arc_substeps"] = np.asarray(self.arc_levels, dtype=np.int64)
            if self.arc_laws is not None:
                arrays["arc_laws"] = np.asarray(self.arc_laws, dtype=float)
        if self.event_controls is not None:
            # the resets' own controls, which the judge applies at its events
            arrays["event_controls"] = np.asarray(self.event_controls, dtype=float)
        return arrays

    def _solution_info(self, info: dict[str, Any] | None) -> dict[str, Any]:
        """The Solution's ``info``: the extremal's residual, sequence and event times, its
        integration, terminal multipliers and final time where it has them, the coverage,
        and ``info`` on top."""
        base_info = {
            "residual": float(self.residual),
            "sequence": list(self.sequence),
            "newton_iterations": int(self.newton_iterations),
            "grazing": bool(self.grazing),
            "event_times": [float(t) for t in self.event_times],
            "approach_speeds": [float(a) for a in self.approach_speeds],
            "start": self.path,
        }
        if self.levels is not None:
            base_info["substeps"] = [int(n) for n in self.levels]
            base_info["integration_error"] = float(self.integration_error)
        if self.ocp.has_terminal_constraints:
            base_info["terminal_multipliers"] = self.terminal_multipliers()
            if self.judged_terminal_violation is not None:
                base_info["terminal_violation"] = float(self.judged_terminal_violation)
        if self.ocp.free_horizon:
            base_info["horizon"] = self.horizon
            base_info["horizon_at_bound"] = self.horizon_at_bound
            base_info["final_hamiltonian"] = float(self.final_hamiltonian)
        if self.coverage is not None:
            base_info["coverage"] = self.coverage
        base_info.update(info or {})
        return base_info

    def _judged_as_saved(self, sol: Any) -> Any:
        """The verification's evaluation (:attr:`judged`) where it is, bit for bit, what the
        judge gives for the Solution ``sol`` (``hybridoc.evaluate(problem, sol)``), else
        ``None``: the Solution's ``u(t)``, rebuilt from its arrays, evaluates the same law
        (the same CasADi functions) from the same nodes, steps and start times (generic
        problems), or the same phase-linear coefficients (disc scenes), with the same
        breakpoints and event controls, on the problem at the same final time. Judging it
        again (an integration of the whole horizon, 0.1 to 0.2 s on pendulum-wall and the
        hopper) would repeat the verification's integration step for step."""
        ev = self.judged
        if ev is None:
            return None
        try:
            cf = sol.control_function(self.ocp)
        except (ValueError, KeyError, AttributeError):
            return None
        mine, bps = reference_control(self)
        if (
            float(cf.horizon) != float(self.ocp.horizon)
            or not same_arrays([cf.breakpoints], [np.asarray(bps, dtype=float)])
            or (cf.event_controls is None) != (self.event_controls is None)
            or (
                self.event_controls is not None
                and not same_arrays([cf.event_controls], [self.event_controls])
            )
        ):
            return None
        C = self.control_coefficients()
        if C is not None:
            # disc scenes: the Solution's phase-linear law of its stored coefficients
            # (Solution.control_function) is this result's u(t) formula
            a = sol.arrays
            same = cf.kind == "phase-linear" and same_arrays(
                [a["control_coefficients"], a["phase_starts"]], [C, self.phase_starts]
            )
            return ev if same else None
        theirs = getattr(cf.fn, "pieces", None)
        ours = getattr(mine, "pieces", None)
        if cf.kind != "hmp" or theirs is None or ours is None:
            return None
        (f1, n1, l1, s1, h1), (f2, n2, l2, s2, h2) = theirs, ours
        same = (
            len(f1) == len(f2)
            and all(a is b for a, b in zip(f1, f2, strict=True))
            and tuple(l1) == tuple(l2)
            and h1 == h2
            and same_arrays([*n1, s1], [*n2, s2])
        )
        return ev if same else None


def reference_control(
    obj: Any, problem: Any = None
) -> tuple[Callable[[float], np.ndarray], list[float]]:
    """The continuous optimal control of a reference solution and its breakpoints.

    Parameters
    ----------
    obj
        A :class:`ReferenceResult`, or a :class:`~hybridoc.solution.Solution` of method
        ``"reference"`` (also one loaded from disk: disc scenes store the linear control
        coefficients of every phase; other problems their phase states and costates, from
        which ``u(t)`` is rebuilt with ``problem``).
    problem
        The problem of a Solution loaded from disk that is not a disc scene.

    Returns
    -------
    u, breakpoints
        ``u(t) -> (nu,)`` and the event times, ready for
        ``hybridoc.evaluate_callable(ocp, u, breakpoints=breakpoints)``.
    """
    if isinstance(obj, ReferenceResult):
        cuts = obj.event_times if obj.arc_starts is None else obj.arc_starts[1:]
        return obj.control_function(), [float(t) for t in cuts]
    ref = getattr(obj, "reference", None)
    if isinstance(ref, ReferenceResult):
        return reference_control(ref)
    arrays = getattr(obj, "arrays", {})
    if "phase_starts" not in arrays:
        raise ValueError("this solution carries no reference control (no arrays 'phase_starts')")
    if "control_coefficients" not in arrays:
        if problem is None or "phase_states" not in arrays:
            raise ValueError(
                "rebuilding this reference's u(t) needs its problem: reference_control(sol, ocp)"
            )
        return hmp_control(obj, problem)
    C = np.asarray(arrays["control_coefficients"], dtype=float)
    starts = np.asarray(arrays["phase_starts"], dtype=float)

    def u(t: float) -> np.ndarray:
        k = max(int(np.searchsorted(starts, t, side="right")) - 1, 0)
        return C[k, 0] + C[k, 1] * (t - starts[k])

    return u, [float(t) for t in starts[1:]]


def hmp_control(solution: Any, problem: Any) -> tuple[Callable[[float], np.ndarray], list[float]]:
    """The HMP control law of a reference Solution on a generic problem, from its arrays.

    ``u(t) = argmin_u H(s, lambda, u)`` along the state and costate integrated from each
    phase's start (``phase_starts``, ``phase_states``, ``phase_costates``) with the phase's
    DOP853 steps (``substeps``): the same nodes whether the Solution was just solved or
    loaded from a file, so the judge's cost of it is the same bit for bit
    (:meth:`~hybridoc.solution.Solution.control_function` calls this, ``CONTROL_LAWS``).

    Parameters
    ----------
    solution
        A Solution of method ``"reference"`` on a problem that is not a disc scene.
    problem
        Its problem (anything :func:`~hybridoc.problem.as_ocp` takes).

    Returns
    -------
    u, breakpoints
        ``u(t) -> (nu,)`` and the phase starts after the first (the event times).
    """
    from hybridoc.problem import as_ocp
    from hybridoc.reference.shooting import shooting_system

    arrays, info = solution.arrays, solution.info
    ocp = as_ocp(problem)
    if info.get("horizon") is not None and float(info["horizon"]) != ocp.horizon:
        ocp = ocp.replace(horizon=float(info["horizon"]))
    seq = list(info["sequence"])
    starts_g = np.asarray(arrays["phase_starts"], dtype=float)
    P, L0 = np.asarray(arrays["phase_states"]), np.asarray(arrays["phase_costates"])
    # a file from before the steps were stored: a fine fixed number (u(t) is then
    # accurate, though not bit for bit the saved solve's)
    levels = tuple(int(n) for n in arrays.get("substeps", [LEGACY_SUBSTEPS] * starts_g.size))
    S = shooting_system(ocp, seq, levels, free=False)
    if "arc_starts" in arrays:
        # path constraints with junctions: per arc, under the constrained minimum of H
        # (the nodes the solve's own u(t) has)
        starts_a = np.asarray(arrays["arc_starts"], dtype=float)
        steps = tuple(int(n) for n in arrays["arc_substeps"])
        # pure state constraints: each arc's own law (arc_laws), else the constrained
        # minimum of H
        laws: Any = S.core.flow
        if "arc_laws" in arrays:
            laws = [
                S.core.fl.law(tuple((float(a), float(b)) for a, b in m))
                for m in np.asarray(arrays["arc_laws"], dtype=float)
            ]
        nodes = _arc_nodes(
            laws, starts_a, np.asarray(arrays["arc_states"]),
            np.asarray(arrays["arc_costates"]), steps, ocp.horizon,
        )  # fmt: skip
        dense_u = [law.dense_u for law in laws] if isinstance(laws, list) else laws.dense_u
        u = control_from_nodes(dense_u, nodes, steps, starts_a, ocp.horizon)
        return u, [float(t) for t in starts_a[1:]]
    nodes = S.nodes(starts_g, P, L0)
    u = control_from_nodes(S.core.flow.dense_u, nodes, levels, starts_g, ocp.horizon)
    return u, [float(t) for t in starts_g[1:]]


def _arc_nodes(
    flow: Any,
    starts: np.ndarray,
    states: np.ndarray,
    costates: np.ndarray,
    levels: Sequence[int],
    horizon: float,
) -> list[np.ndarray]:
    """Per arc, the ``(n + 1, 2 nx + 1)`` nodes of its ``n`` DOP853 steps under ``flow``
    (the constrained minimum of ``H``, which is each arc's own law on a consistent
    extremal; with pure state constraints a list: each arc's own law) from the arc's
    start."""
    ends = np.append(starts[1:], horizon)
    laws = list(flow) if isinstance(flow, list) else [flow] * len(starts)
    return [
        np.asarray(law.nodes(int(n))(s, lam, float(b - a))).T.copy()
        for a, b, s, lam, n, law in zip(starts, ends, states, costates, levels, laws, strict=True)
    ]


# ---------------------------------------------------------------------- one sequence
def make_result(
    S: ShootingSystem, nr: NewtonResult, path: str, error: float = 0.0
) -> ReferenceResult:
    """The :class:`ReferenceResult` of a converged Newton point (``error``: the integration's
    estimated relative cost error, :func:`~hybridoc.reference.shooting.refine`). A free
    final time's point becomes the fixed-time extremal of the problem at that time
    (:meth:`~hybridoc.reference.shooting.ShootingSystem.fixed_at`)."""
    S, z = S.fixed_at(nr.z)
    nr = NewtonResult(z, nr.residual, nr.iterations, nr.converged, list(nr.history))
    out = S.traj(nr.z)
    starts, s0, l0, _, phiT, run, sm, lm, rates, sT, lT, _, H_T = out
    _, gam, pis, _ = S.unpack(nr.z)
    nu, mu = S.core.unpack_terminal(nr.z)
    rates = rates.ravel()
    levels = None if S.disc else tuple(S.levels)
    nodes = None if S.disc else S.nodes(starts.ravel(), s0.T, l0.T)
    arcs = _arc_pieces(S, nr.z, float(out[11].item())) if _has_junctions(S) else None
    return ReferenceResult(
        event_controls=_event_controls(S, nr.z, sm, lm),
        ocp=S.ocp,
        sequence=list(S.sequence),
        event_times=np.array([float(g) for g in gam]),
        multipliers=np.array([float(p) for p in pis]),
        phase_starts=starts.ravel(),
        phase_states=s0.T.copy(),
        phase_costates=l0.T.copy(),
        states_minus=sm.T.copy(),
        costates_minus=lm.T.copy(),
        approach_speeds=rates,
        final_state=sT.ravel(),
        final_costate=lT.ravel(),
        cost=float(phiT.item()) + float(run.item()),
        terminal_cost=float(phiT.item()),
        running_cost=float(run.item()),
        residual=nr.residual,
        newton_iterations=nr.iterations,
        residual_history=list(nr.history),
        grazing=bool(np.any(np.abs(rates) < GRAZE_FLAG)),
        path=path,
        system=S,
        z=nr.z,
        levels=levels,
        integration_error=float(error),
        nodes=nodes,
        terminal_eq_multipliers=np.asarray(nu, dtype=float).ravel().copy(),
        # a Fischer-Burmeister root has mu >= 0 up to rounding: the sign shown is the one
        # the conditions require
        terminal_ineq_multipliers=np.maximum(np.asarray(mu, dtype=float).ravel(), 0.0),
        final_hamiltonian=float(H_T.item()),
        **(arcs or {}),
    )


def _event_controls(
    S: ShootingSystem, z: np.ndarray, s_minus: np.ndarray, l_minus: np.ndarray
) -> np.ndarray | None:
    """``(K, nu)``: per event the control its reset reads (:attr:`ReferenceResult.
    event_controls`), ``None`` when no reset of the sequence reads the control."""
    core = S.core
    if not getattr(core, "n_v", 0):
        return None
    vs = core.unpack_event_controls(np.asarray(z, dtype=float))
    rows = []
    for k, v in enumerate(vs):
        u = np.asarray(core.law_at(k, -1).u_star(s_minus[:, k], l_minus[:, k]), float).ravel()
        if v is not None:
            u[list(core.v_comps[k])] = v[list(core.v_comps[k])]
        rows.append(u)
    return np.array(rows, dtype=float)


def _has_junctions(S: ShootingSystem) -> bool:
    """Whether ``S`` is a generic problem's system with path constraints and some phase of
    more than one arc (its ``u(t)`` is then rebuilt per arc)."""
    return not S.disc and S.ocp.path is not None and any(len(p) > 1 for p in S.core.arcs)


def _arc_pieces(S: ShootingSystem, z: np.ndarray, horizon: float) -> dict[str, Any]:
    """The arcs of ``S`` at ``z`` as :class:`ReferenceResult`'s ``arc_*`` fields: each arc's
    start, ``s`` and ``lambda`` there (the shooting's own phase maps carry them across the
    junctions), its steps and its nodes."""
    out = S.traj(z)
    starts, s0, l0 = out[0].ravel(), out[1].T, out[2].T
    core = S.core
    switches = S.switch_times(z)
    etas = core.eta_values(z)
    lengths = core.arc_lengths(starts, horizon, switches)
    times, states, costates = [], [], []
    i = 0
    for k in range(S.K + 1):
        s, lam = s0[k], l0[k]
        cuts = [float(starts[k]), *switches[k]]
        for j, (t, law) in enumerate(zip(cuts, core.laws[k], strict=True)):
            if j:
                lam = core.entry_jump(k, j - 1, s, lam, etas[k][j - 1])
            times.append(t)
            states.append(np.asarray(s, dtype=float).ravel())
            costates.append(np.asarray(lam, dtype=float).ravel())
            h = lengths[k][j]
            s, lam, _ = (np.asarray(v).ravel() for v in law.phase(core.arc_levels[i])(s, lam, h))
            i += 1
    arc_starts = np.array(times)
    P, L = np.array(states), np.array(costates)
    levels = tuple(int(n) for n in core.arc_levels)
    # pure state constraints: each arc's own law (the pointwise minimum of H does not know
    # where a boundary arc is)
    laws = [m for p in core.arcs for m in p] if state_rows(S.ocp) else None
    flow = core.flow if laws is None else [core.fl.law(m) for m in laws]
    return {
        "arc_starts": arc_starts,
        "arc_states": P,
        "arc_costates": L,
        "arc_levels": levels,
        "arc_nodes": _arc_nodes(flow, arc_starts, P, L, levels, horizon),
        "arc_laws": laws,
    }
