"""The judge's side of a :class:`~hybridoc.solution.Solution`: its control as a function of
time, its judged evaluation, its projection on an N-step grid and its samples.

A Solution is data plus its file format (the model layer, docs/architecture.rst); what needs
the judge, the problems or the reference lives here, in the judge layer, as functions of the
Solution: :func:`control_function`, :func:`control`, :func:`evaluate_solution`,
:func:`judge`, :func:`to_grid`, :func:`sample`. The Solution's methods of the same names are
one-line delegations to them.

How a model-layer method reaches a higher layer without importing it: through
:mod:`hybridoc.providers`, a registry in the model layer. ``hybridoc/__init__.py`` (the api
layer, above every other, imported before any of the package's modules) registers there the
loaders of this module (slot ``"judging"``) and of the reference's HMP control law of a
generic problem (slot ``"control-law:hmp"``, which :func:`control_function` asks for). The
model layer names neither, by import or by string; every dependency is an import that
``tests/test_architecture.py`` reads, and each goes downwards: api -> judging and
api -> reference (the loaders), judging -> judge, problems and model.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridoc import tolerances
from hybridoc.errors import HybridocError
from hybridoc.evaluation import Evaluation, checked_times
from hybridoc.evaluator import evaluate
from hybridoc.ocp import HybridOCP
from hybridoc.problem import as_ocp
from hybridoc.providers import provider
from hybridoc.solution import Solution

__all__ = [
    "COSTATE_RTOL",
    "ControlFunction",
    "SolutionSample",
    "control",
    "control_function",
    "evaluate_solution",
    "judge",
    "lagrange_pieces",
    "problem_of",
    "sample",
    "to_grid",
]


def _right_interpolation(times: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear interpolation of knots stored in time order (a jump: one time twice, before
    then after), right-continuous: at a repeated time the last value."""
    times = np.asarray(times, dtype=float)
    values = np.asarray(values, dtype=float)
    out = np.empty((t.size, values.shape[1]))
    for k, tk in enumerate(t):
        i = int(np.searchsorted(times, tk, side="right")) - 1
        if i < 0:
            out[k] = values[0]
        elif i >= times.size - 1 or times[i + 1] == times[i]:
            out[k] = values[i]
        else:
            w = (tk - times[i]) / (times[i + 1] - times[i])
            out[k] = (1.0 - w) * values[i] + w * values[i + 1]
    return out


_PHASES = frozenset({"phase_starts", "phase_states", "phase_costates"})
COSTATE_RTOL = tolerances.value("costate")
"""Relative tolerance of the costates that :func:`sample` rebuilds (the table's
``"costate"``, :mod:`hybridoc.tolerances`)."""

_ACTIVE_ROW = tolerances.value("active")
"""A path row whose value is within this of 0 under the reference's control is on an arc
where it is active (the reference holds such rows at 0 to its own tolerance)."""


class _PhaseCostates:
    """The costate of a reference Solution at any times: state and costate integrated from
    the start of each time's phase under the Solution's control (:func:`sample`)."""

    def __init__(
        self,
        ocp: HybridOCP,
        u: Callable[[float], np.ndarray],
        starts: np.ndarray,
        states: Any,
        costates: Any,
    ) -> None:
        import casadi as ca

        self.u = u
        self.starts = starts
        self.states = np.asarray(states, dtype=float).reshape(starts.size, -1)
        self.costates = np.asarray(costates, dtype=float).reshape(starts.size, -1)
        self.nx = self.states.shape[1]
        s, lam, uu = ca.MX.sym("s", ocp.nx), ca.MX.sym("lam", ocp.nx), ca.MX.sym("u", ocp.nu)
        H = ocp.L(s, uu) + ca.dot(lam, ocp.f(s, uu))
        # partial derivative at fixed u: u(t) is given, not the minimiser of this H
        self.rhs = ca.Function("state_costate", [s, lam, uu], [ocp.f(s, uu), -ca.gradient(H, s)])
        self.path = None
        if ocp.path is not None:
            # on an arc where path rows are active the costate also carries c_s^T nu, with
            # nu from the stationarity H_u = c_u^T nu of the active rows; a pure state row
            # (c independent of u) is held on its boundary arc by its derivative
            # c1 = c_s f (indirect adjoining), whose multiplier enters the same way
            c = ocp.path(s, uu)
            held = ca.vertcat(
                *[
                    c[r] if ca.depends_on(c[r], uu) else ca.jtimes(c[r], s, ocp.f(s, uu))
                    for r in range(c.numel())
                ]
            )
            self.path = ca.Function(
                "path_parts",
                [s, lam, uu],
                [c, ca.jacobian(held, uu), ca.jacobian(held, s), ca.gradient(H, uu)],
            )

    def _path_term(self, s: np.ndarray, lam: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``c_s^T nu`` over the path rows active at ``(s, u)`` (zero where none is)."""
        assert self.path is not None
        c, cu, cs, hu = (np.asarray(v, dtype=float) for v in self.path(s, lam, u))
        active = np.flatnonzero(np.abs(c.ravel()) <= _ACTIVE_ROW)
        if active.size == 0:
            return np.zeros(self.nx)
        nu = np.linalg.lstsq(cu[active].T, hu.ravel(), rcond=None)[0]
        return cs[active].T @ nu

    def __call__(self, times: np.ndarray) -> np.ndarray:
        from scipy.integrate import solve_ivp

        nx = self.nx
        out = np.empty((times.size, nx))
        phase = np.clip(np.searchsorted(self.starts, times, side="right") - 1, 0, None)

        def rhs(t: float, z: np.ndarray) -> np.ndarray:
            u = self.u(t)
            ds, dl = self.rhs(z[:nx], z[nx:], u)
            dl = np.asarray(dl).ravel()
            if self.path is not None:
                dl = dl + self._path_term(z[:nx], z[nx:], u)
            return np.concatenate([np.asarray(ds).ravel(), dl])

        for k in np.unique(phase):
            rows = np.flatnonzero(phase == k)
            t0 = float(self.starts[k])
            z0 = np.concatenate([self.states[k], self.costates[k]])
            at = times[rows]
            ahead = at > t0
            out[rows[~ahead]] = self.costates[k]
            if not ahead.any():
                continue
            order = np.argsort(at[ahead], kind="stable")
            t_eval = at[ahead][order]
            scale = np.maximum(np.abs(z0), 1.0)
            sol = solve_ivp(
                rhs, (t0, float(t_eval[-1])), z0, method="DOP853", t_eval=t_eval,
                rtol=COSTATE_RTOL, atol=COSTATE_RTOL * scale,
            )  # fmt: skip
            if not sol.success:
                raise HybridocError(
                    f"the costate from the phase starting at t = {t0:.6g} could not be "
                    f"integrated: {sol.message}"
                )
            out[rows[ahead][order]] = sol.y[nx:].T
        return out


def _lagrange_basis(nodes: np.ndarray, s: np.ndarray) -> np.ndarray:
    out = np.ones((s.size, nodes.size))
    for j in range(nodes.size):
        for m in range(nodes.size):
            if m != j:
                out[:, j] *= (s - nodes[m]) / (nodes[j] - nodes[m])
    return out


def lagrange_pieces(
    t: Sequence[float] | np.ndarray,
    bounds: np.ndarray,
    nodes: np.ndarray,
    values: np.ndarray,
    lo: np.ndarray | float = -np.inf,
    hi: np.ndarray | float = np.inf,
) -> np.ndarray:
    """A piecewise polynomial control at the times ``t``, shape ``(len(t), nu)``.

    On element ``e``, ``[bounds[e], bounds[e + 1]]``, the control is the Lagrange polynomial
    through ``values[:, e, j]`` at the relative positions ``nodes[j]`` in ``[0, 1]``, clipped
    into ``[lo, hi]``; each element holds its right end (``t`` at a bound takes the element
    that starts there). The transcription evaluates its control with this very function, so
    a saved dt Solution's ``u(t)`` is the one it judged, bit for bit.

    Parameters
    ----------
    t
        Times.
    bounds
        ``(E + 1,)`` increasing element bounds.
    nodes
        ``(d,)`` interpolation positions in ``[0, 1]`` (dt: the Radau points).
    values
        ``(nu, E, d)`` control values at the nodes.
    lo, hi
        Control bounds.
    """
    t = np.atleast_1d(np.asarray(t, dtype=float))
    idx = np.clip(np.searchsorted(bounds, t, side="right") - 1, 0, bounds.size - 2)
    s = (t - bounds[idx]) / (bounds[idx + 1] - bounds[idx])
    u = np.einsum("nj,unj->nu", _lagrange_basis(nodes, s), values[:, idx, :])
    return np.clip(u, lo, hi)


class ControlFunction:
    """A Solution's control ``u(t)`` as the judge calls it: one time in, ``(nu,)`` out.

    Attributes
    ----------
    kind
        :attr:`~hybridoc.solution.Solution.control_kind`.
    breakpoints
        Times inside ``(0, T)`` where ``u`` may jump or kink (grid times, element bounds,
        events): the judge restarts its integration there.
    horizon
        ``T``.
    event_controls
        ``(K, nu)``: the control each reset reads, event by event
        (:attr:`~hybridoc.solution.Solution.event_controls`), which the judge of a
        continuous control applies at its events; ``None``: none.
    """

    def __init__(
        self,
        kind: str,
        fn: Callable[[float], Any],
        breakpoints: Any,
        horizon: float,
        event_controls: np.ndarray | None = None,
    ) -> None:
        self.kind = kind
        self.fn = fn
        self.breakpoints = np.asarray(breakpoints, dtype=float).ravel()
        self.horizon = float(horizon)
        self.event_controls = event_controls

    def __call__(self, t: float) -> np.ndarray:
        return np.asarray(self.fn(t), dtype=float).ravel()

    def __repr__(self) -> str:
        return (
            f"ControlFunction(kind={self.kind!r}, horizon={self.horizon!r}, "
            f"breakpoints={self.breakpoints.size})"
        )


@dataclass(repr=False)
class SolutionSample:
    """What :func:`sample` returns, one row per time.

    Attributes
    ----------
    t
        ``(M,)`` the times asked for.
    states
        ``(M, nx)`` the judge's state, after any jump at exactly that time.
    controls
        ``(M, nu)`` the Solution's control (right-continuous at its breakpoints).
    costates
        ``(M, nx)`` the costate after any jump at exactly that time: the reference's
        rebuilt exactly, other methods' interpolated linearly between the times they stored
        them (:func:`sample` says what it is per control kind); ``None`` when the
        method stores none.
    modes
        The mode of each state (problems with modes); ``None`` otherwise.
    """

    t: np.ndarray
    states: np.ndarray
    controls: np.ndarray
    costates: np.ndarray | None
    modes: list[str] | None

    def __repr__(self) -> str:
        nx = self.states.shape[1] if self.states.ndim == 2 else 0
        return (
            f"SolutionSample({self.t.size} times, nx={nx}, nu={self.controls.shape[-1]}, "
            f"costates={'yes' if self.costates is not None else 'no'}, "
            f"modes={'yes' if self.modes is not None else 'no'})"
        )


def _cell_averages(
    u: Callable[[float], np.ndarray], cuts: np.ndarray, grid: np.ndarray, n_gauss: int = 6
) -> np.ndarray:
    """Cell averages on ``grid`` of ``u``, smooth between ``cuts`` (Gauss-Legendre on each
    piece: exact for polynomials up to degree 11)."""
    xg, wg = np.polynomial.legendre.leggauss(n_gauss)
    pts = np.union1d(grid, cuts)
    pts = pts[(pts >= grid[0]) & (pts <= grid[-1])]
    a, b = pts[:-1], pts[1:]
    keep = b > a
    a, b = a[keep], b[keep]
    mid, half = 0.5 * (a + b), 0.5 * (b - a)
    tq = (mid[:, None] + half[:, None] * xg[None, :]).ravel()
    uq = np.array([u(float(tk)) for tk in tq]).reshape(a.size, n_gauss, -1)
    integ = np.einsum("q,pqu->pu", wg, uq) * half[:, None]
    cell = np.clip(np.searchsorted(grid, mid, side="right") - 1, 0, grid.size - 2)
    out = np.zeros((grid.size - 1, uq.shape[-1]))
    np.add.at(out, cell, integ)
    return out / np.diff(grid)[:, None]


def _checked_times(times: Any, horizon: float, name: str = "times") -> np.ndarray:
    return checked_times(times, horizon, name)


def problem_of(sol: Solution, problem: Any = None) -> HybridOCP:
    """The problem ``problem`` names (anything :func:`~hybridoc.problem.as_ocp` takes), or
    the one ``sol`` is bound to when it is ``None``.

    Raises
    ------
    hybridoc.errors.HybridocError
        No problem given and none bound.
    """
    if problem is not None:
        return as_ocp(problem)
    bound = sol.problem
    if bound is None:
        raise HybridocError(
            f"this {sol.method} Solution of {sol.scene!r} is bound to no problem: pass "
            "problem= or call sol.bind(problem) (a loaded Solution knows only the name)"
        )
    return bound


def control_function(sol: Solution, problem: Any = None) -> ControlFunction:
    """The control ``u(t)`` for one time at a time, with its breakpoints: what
    :func:`hybridoc.evaluate` judges.

    Parameters
    ----------
    sol
        The Solution.
    problem
        Needed only by the reference's control law on a generic problem
        (:attr:`~hybridoc.solution.Solution.control_kind` ``"hmp"``, provided by the slot
        ``"control-law:hmp"`` of :mod:`hybridoc.providers`); default: the bound problem.
    """
    kind, a, T = sol.control_kind, sol.arrays, sol.horizon
    if kind == "piecewise-constant":
        grid = [float(g) for g in sol.time_grid]
        values, last = sol.controls, sol.controls.shape[0] - 1

        def u_grid(t: float) -> np.ndarray:
            return values[min(max(bisect.bisect_right(grid, t) - 1, 0), last)]

        return ControlFunction(kind, u_grid, sol.time_grid[1:-1], T)
    if kind == "piecewise-polynomial":
        bounds = np.asarray(a["element_bounds"], dtype=float)
        nodes = _control_nodes(sol)
        flat = np.asarray(a["radau_controls"], dtype=float)
        vals = flat.reshape(flat.shape[0], -1, nodes.size)
        nu = vals.shape[0]
        lo = np.asarray(a.get("u_min", np.full(nu, -np.inf)), dtype=float)
        hi = np.asarray(a.get("u_max", np.full(nu, np.inf)), dtype=float)

        def u_poly(t: float) -> np.ndarray:
            return lagrange_pieces(np.array([t]), bounds, nodes, vals, lo, hi)[0]

        return ControlFunction(kind, u_poly, bounds[1:-1], T, sol.event_controls)
    if kind == "phase-linear":
        C = np.asarray(a["control_coefficients"], dtype=float)
        starts = np.asarray(a["phase_starts"], dtype=float)

        def u_lin(t: float) -> np.ndarray:
            k = max(int(np.searchsorted(starts, t, side="right")) - 1, 0)
            return C[k, 0] + C[k, 1] * (t - starts[k])

        return ControlFunction(kind, u_lin, starts[1:], T, sol.event_controls)
    u, breakpoints = provider(f"control-law:{kind}")(sol, problem_of(sol, problem))
    return ControlFunction(kind, u, breakpoints, T, sol.event_controls)


def _control_nodes(sol: Solution) -> np.ndarray:
    nodes = sol.arrays.get("control_nodes")
    if nodes is not None:
        return np.asarray(nodes, dtype=float)
    # a dt file from before the nodes were stored: the Radau points of its degree
    import casadi as ca

    try:
        degree = int(sol.settings["degree"])
    except (KeyError, TypeError, ValueError):
        raise HybridocError(
            "this dt Solution stores neither control_nodes nor its collocation degree"
        ) from None
    return np.array(ca.collocation_points(degree, "radau"), dtype=float)


def control(
    sol: Solution, t: float | Sequence[float] | np.ndarray, problem: Any = None
) -> np.ndarray:
    """The control of ``sol`` at ``t``: ``(nu,)`` for one time, ``(M, nu)`` for ``M`` times.

    Right-continuous at its breakpoints (grid times, element bounds, events); ``problem``
    as in :func:`control_function`.

    Raises
    ------
    hybridoc.errors.HybridocError
        For a time outside ``[0, T]`` (named ``t``).
    """
    times = _checked_times(t, sol.horizon, "t")
    fn = control_function(sol, problem)
    out = np.array([fn(float(tk)) for tk in times]).reshape(times.size, -1)
    return out[0] if np.ndim(t) == 0 else out


def evaluate_solution(sol: Solution, problem: Any = None) -> Evaluation:
    """The judge's evaluation of ``sol``'s :func:`control`:
    ``hybridoc.evaluate(problem, sol)`` (default: the bound problem). It judges anew; the
    evaluation the Solution's cost came from is :attr:`~hybridoc.solution.Solution.evaluation`.
    """
    return evaluate(problem_of(sol, problem), sol)


def judge(sol: Solution, problem: Any = None) -> Evaluation:
    """Set ``sol``'s ``cost``, ``terminal_cost`` and ``running_cost`` to the judge's, of
    :func:`control`, keep that evaluation (:attr:`~hybridoc.solution.Solution.evaluation`)
    and return it (methods call it on what they return)."""
    ev = evaluate_solution(sol, problem)
    sol.with_evaluation(ev)
    return ev


def to_grid(sol: Solution, N: int | None = None, problem: Any = None) -> Solution:
    """The control projected onto the N-step grid: cell averages, held constant.

    On the Solution's own grid these are :attr:`~hybridoc.solution.Solution.x` (what every
    method stores); on another grid they are computed by Gauss-Legendre quadrature (6
    points) on each piece between the grid times and the control's breakpoints (exact for
    the polynomial controls of gd, dt and the reference on disc scenes).

    Parameters
    ----------
    sol
        The Solution.
    N
        Grid intervals on ``[0, T]``; default: the problem's.
    problem
        Default: the bound problem.

    Returns
    -------
    Solution
        Piecewise constant (:attr:`~hybridoc.solution.Solution.control_kind`
        ``"piecewise-constant"``) with its own judged cost, events and trajectory, bound to
        ``problem.replace(steps=N)`` (which ``hybridoc.evaluate`` needs when ``N`` is not
        the problem's); ``info``
        ``"projected_from"`` names the control kind and ``"projected_cost"`` the cost of
        the control projected, and on a problem with terminal constraints or a final
        mode ``"terminal_violation"`` the judged violation of the averages (they do not
        keep the constraints). The best a piecewise-constant method can reach on that
        grid is at most this cost.
    """
    ocp = problem_of(sol, problem)
    n = ocp.steps if N is None else N
    grid_ocp = ocp.replace(steps=n)
    if ocp.free_horizon:
        grid_ocp = grid_ocp.replace(horizon=sol.horizon)
    grid = grid_ocp.time_grid()
    if np.array_equal(grid, sol.time_grid):
        # every method stores its control's cell averages on its own grid: x itself
        averages = np.array(sol.controls, dtype=float)
    else:
        fn = control_function(sol, ocp)
        averages = _cell_averages(fn, fn.breakpoints, grid)
    info: dict[str, Any] = {
        "projected_from": sol.control_kind,
        "projected_cost": sol.cost,
        "steps": int(n),
    }
    if ocp.free_horizon:
        info["horizon"] = sol.horizon
    ev = evaluate(grid_ocp, averages)
    if ocp.has_terminal_constraints or ocp.final_mode is not None:
        # the averages do not keep the constraints: say by how much they miss them
        info["terminal_violation"] = float(ev.terminal_violation)
    out = Solution.from_evaluation(ev, method=sol.method, scene=sol.scene, info=info)
    out.time_grid = np.array(grid)
    out.settings = dict(sol.settings)
    out.set_status(
        sol.status,
        f"the {sol.control_kind} control of {sol.method} averaged on N = {n} cells",
    )
    out.bind(grid_ocp)
    return out


def sample(
    sol: Solution, t: float | Sequence[float] | np.ndarray, problem: Any = None
) -> SolutionSample:
    """States, controls, costates and modes at any times in ``[0, T]``.

    The states are the judge's event-exact simulation of :func:`control`
    (:meth:`Evaluation.sample <hybridoc.Evaluation.sample>`), after any jump at exactly
    that time. What the costates are depends on
    :attr:`~hybridoc.solution.Solution.control_kind`:

    ``"hmp"``, ``"phase-linear"`` (the reference)
        The costate of the extremal, rebuilt exactly: state and costate integrated
        together, ``s' = f(s, u(t))``, ``lambda' = -dH/ds(s, lambda, u(t))`` with
        ``H = L + lambda^T f`` and ``u(t)`` the Solution's control, from the start of the
        phase that holds ``t`` (``phase_starts``, ``phase_states``, ``phase_costates``:
        after the jump at an event time) by an adaptive DOP853 at a relative tolerance
        of ``1e-13``.
    ``"piecewise-polynomial"`` (dt)
        The transcription's multipliers, interpolated linearly between the times it
        stored them: an approximation of the costate of its discrete problem.
    ``"piecewise-constant"``
        The costates a method stored, interpolated linearly; gd and a user's controls
        store none (``None``). The exact costate of a piecewise-constant control is the
        judge's discrete adjoint, :func:`hybridoc.gradient`'s ``costate_times`` and
        ``costates``.

    Parameters
    ----------
    sol
        The Solution.
    t
        One time or an array of times in ``[0, T]``.
    problem
        Default: the bound problem.

    Raises
    ------
    hybridoc.errors.HybridocError
        For a time outside ``[0, T]`` (named ``t``), or no problem to simulate.
    """
    times = _checked_times(t, sol.horizon, "t")
    ev = evaluate_solution(sol, problem)
    states = ev.sample(times)
    fn = control_function(sol, ev.ocp)
    controls = np.array([fn(float(tk)) for tk in times]).reshape(times.size, -1)
    costates = None
    a = sol.arrays
    if sol.control_kind in ("hmp", "phase-linear") and _PHASES <= a.keys():
        # from the start of each arc where the reference stored them (junctions of path
        # constraints: after the costate jump at a pure state constraint's entry)
        part = "arc" if {"arc_starts", "arc_states", "arc_costates"} <= a.keys() else "phase"
        starts = np.asarray(a[f"{part}_starts"], dtype=float)
        rebuilt = _PhaseCostates(ev.ocp, fn, starts, a[f"{part}_states"], a[f"{part}_costates"])
        costates = rebuilt(times)
    elif sol.costates is not None and sol.costate_times is not None:
        costates = _right_interpolation(sol.costate_times, sol.costates, times)
    modes = None
    if ev.ocp.modes is not None:
        modes = [ev.ocp.mode_of(s) for s in states]
    return SolutionSample(times, states, controls, costates, modes)
