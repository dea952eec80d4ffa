"""The exact N-step problem that gradient descent minimises, solved by IPOPT.

Gradient descent (:mod:`hybridoc.solvers.gd`) minimises the discrete loss::

    phi(s_N) + sum_n eps |u_n|^2 dt,    s_{n+1} = step(s_n, u_n)

of the simulator's step (symplectic Euler, an impulse model and the time-of-impact
corrections). Here the same step, in CasADi (:func:`hybridoc.solvers.casadi_step.make_step`),
is transcribed by multiple shooting (states and controls at every step, the step as an
equality constraint) and solved by IPOPT with exact second derivatives from a warm start.

The step is only piecewise smooth (a contact impulse is applied or not), and IPOPT's
infeasible iterates would leave the contact branches freely (e.g. drop the collision). So
each round freezes the branches at those of a rollout of the current controls, keeps every
contact in its region by bounds on the predicted gap and normal speed, solves that smooth
NLP, and re-reads the branches from a rollout of the result; rounds repeat until the
branches no longer change (a local optimum of the piecewise-smooth loss, possibly on a
branch boundary). From a warm start near the optimum (the direct transcription's control,
the default, or gradient descent's result) this gives the floor that gradient descent can
reach at this N. The reported ``discrete_loss`` is that of a fresh rollout of
the returned controls through the step, not the NLP's value.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np

from hybridoc.errors import ConvergenceError, HybridocError
from hybridoc.evaluator import evaluate
from hybridoc.ocp import HybridOCP
from hybridoc.problem import ProblemLike, disc_scene
from hybridoc.solution import Solution

if TYPE_CHECKING:
    from hybridoc.problems.scene import Scene

__all__ = ["discrete_gap", "discrete_loss", "solve_discrete"]

_ACCEPTED = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


def _scene(scene: ProblemLike) -> Scene:
    return disc_scene(scene)


def _local(scene: Scene) -> Scene:
    """``scene`` moved by minus its scales' offset (a multiple of 1024 lengths near its
    centroid): the same problem with every position, target and wall point near the origin,
    each subtraction exact (the two numbers are within a factor two). Its steps round at the
    scene's own lengths, not at ``eps`` times its distance from the origin (rollouts of a
    scene at ``1e6`` lost ``2e-9`` of the loss); the controls are the same. ``scene`` itself
    where the offset is zero."""
    from hybridoc.problems.disc_ocp import translated

    off = np.asarray(scene.to_ocp().scales.state_offset[:2], dtype=float)
    if not off.any():
        return scene
    return translated(scene, -off)  # p + (-off) is p - off exactly


def _terminal(scene: Scene, s: Any) -> Any:
    out = 0
    for i, d in enumerate(scene.discs):
        if d.target is not None:
            out = out + ca.sumsqr(s[2 * i : 2 * i + 2] - ca.DM(d.target))
    return out


def _frozen_step(scene: Scene, toi: str) -> tuple[ca.Function, ca.Function]:
    """The ``direct`` step with its contact branches fixed by flags, and the branch tests.

    Both come from :func:`hybridoc.solvers.casadi_step.step_parts` (with the flags of the
    true branches the frozen step reproduces ``make_step`` to rounding; checked in the tests).
    Returns ``step(s, u, flags) -> (s_next, d^, w^)`` with ``flags`` one 0/1 per contact
    (impulse applied or not) and the predicted gaps and normal speeds ``d^``, ``w^``, and
    ``tests(s, u) -> (flags, d^, w^)`` of the true step.
    """
    from hybridoc.solvers.casadi_step import step_parts

    s = ca.SX.sym("s", 4 * scene.n_discs)
    u = ca.SX.sym("u", scene.n_controls)
    true = step_parts(scene, s, u, toi)
    flags = ca.SX.sym("flags", true.applied.size1())
    frozen = step_parts(scene, s, u, toi, flags=flags)
    step = ca.Function("frozen_step", [s, u, flags], [frozen.s_next, frozen.gaps, frozen.speeds])
    test = ca.Function("contact_flags", [s, u], [true.applied, true.gaps, true.speeds])
    return step, test


def discrete_loss(
    scene: ProblemLike, controls: Any, *, contact: str = "direct", toi: str = "both"
) -> float:
    """The discrete loss of ``(N, nu)`` controls under the CasADi step (float64).

    Parameters
    ----------
    scene
        A Scene, a built-in name, a TOML path or a :class:`~hybridoc.problems.DiscOCP`.
    controls
        ``(N, nu)`` controls.
    contact, toi
        Simulator settings, as in :func:`hybridoc.solvers.casadi_step.make_step`.

    Returns
    -------
    float
        ``phi(s_N) + sum_n eps |u_n|^2 dt``.
    """
    from hybridoc.solvers.casadi_step import make_step

    scene = _scene(scene)
    ocp = scene.to_ocp()
    u = ocp.check_controls(controls)
    scene = _local(scene)  # the same loss, rounded at the scene's own lengths
    ocp = scene.to_ocp()
    step = make_step(scene, contact=contact, toi=toi)
    roll = step.mapaccum("roll", scene.steps)
    states = np.asarray(roll(scene.initial_state(), u.T))
    s_N = states[:, -1]
    term = float(ocp.phi(s_N))
    return term + scene.control_weight * scene.dt * float(np.sum(u**2))


class _DiscreteNLP:
    """The N steps by multiple shooting with the contact branches frozen by parameters (a
    smooth NLP, solved with exact second derivatives), and rollouts of the true step that
    read the branches.

    The branch region is kept by bounds on the predicted gaps and normal speeds
    ``(d^, w^)``: an applied contact needs ``d^ <= 0`` and ``w^ <= 0``; a skipped one keeps
    ``d^ >= 0`` or ``w^ >= 0`` (whichever holds at the start); and an applied contact keeps
    its time of impact within the step: ``d^ - dt w^ >= 0``.
    """

    def __init__(
        self, scene: Scene, ocp: HybridOCP, contact: str, toi: str, tol: float, max_iter: int
    ) -> None:
        from hybridoc.solvers.casadi_step import make_step

        self.scene, self.ocp = scene, ocp
        N, nu = scene.steps, ocp.nu
        self.N, self.nu = N, nu
        if contact != "direct":
            make_step(scene, contact=contact, toi=toi)  # raises the clear error
        true_step = make_step(scene, contact=contact, toi=toi)
        self.roll = true_step.mapaccum("roll", N)
        fstep, ftest = _frozen_step(scene, toi)
        self.nc = nc = ftest.size1_out(0)
        self.x0 = x0 = scene.initial_state()
        self.nx = nx = x0.size
        # the NLP in the problem's own units (issue #32): variables (s - s0) / sigma_s and
        # u / sigma_u, the steps' rows divided by the state scales, gaps by the length,
        # normal speeds by length / time, the objective by the cost scale; nothing is
        # scaled where the scales are the identity (the NLP of before)
        sc = ocp.scales
        self.scaled = not sc.is_identity
        self.sx, self.off, self.su = sc.state_array, sc.offset_array, sc.control_array
        self.cs = float(sc.cost)
        S = ca.SX.sym("S", nx, N + 1)
        U = ca.SX.sym("U", nu, N)
        F = ca.SX.sym("F", nc, N)
        if self.scaled:
            Sp = S * ca.repmat(ca.DM(self.sx), 1, N + 1) + ca.repmat(ca.DM(self.off), 1, N + 1)
            Up = U * ca.repmat(ca.DM(self.su), 1, N)
        else:
            Sp, Up = S, U
        nxt, gaps, speeds = fstep.map(N)(Sp[:, :-1], Up, F)
        if self.scaled:
            gl, vl = float(sc.length), float(sc.length / sc.time)
            g = ca.vertcat(
                ca.vec(S[:, 0] - ca.DM(sc.to_scaled_state(x0))),
                # the step as an increment: no rounding of s0 + sigma_s S - s0
                ca.vec(S[:, 1:] - S[:, :-1] - (nxt - Sp[:, :-1]) / ca.repmat(ca.DM(self.sx), 1, N)),
                ca.vec(gaps / gl),
                ca.vec(speeds / vl),
                ca.vec((gaps - scene.dt * speeds) / gl),
            )
        else:
            g = ca.vertcat(
                ca.vec(S[:, 0] - ca.DM(x0)),
                ca.vec(S[:, 1:] - nxt),
                ca.vec(gaps),
                ca.vec(speeds),
                ca.vec(gaps - scene.dt * speeds),
            )
        self.n_eq = nx * (N + 1)
        J = _terminal(scene, Sp[:, -1]) + scene.control_weight * scene.dt * ca.sumsqr(Up)
        if self.scaled:
            J = J / self.cs
        opts = {
            "ipopt.tol": tol,
            "ipopt.max_iter": max_iter,
            "ipopt.print_level": 0,
            "ipopt.sb": "yes",
            # no bound relaxation: a contact held at its branch boundary must not cross it
            "ipopt.bound_relax_factor": 0.0,
            "print_time": False,
        }
        nlp = {"x": ca.vertcat(ca.vec(S), ca.vec(U)), "f": J, "g": g, "p": ca.vec(F)}
        self.solver = ca.nlpsol("discrete", "ipopt", nlp, opts)
        self.flags_of = ftest.map(N)
        self.last: Any = None  # (flags, gaps) of the latest rollout

    def pack(self, states: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The NLP's (scaled) variables of physical states ``(nx, N + 1)`` and ``(N, nu)``
        controls."""
        if self.scaled:
            states = (states - self.off[:, None]) / self.sx[:, None]
            u = u / self.su[None, :]
        return np.concatenate([states.ravel(order="F"), u.T.ravel(order="F")])

    def controls(self, w: np.ndarray) -> np.ndarray:
        """The physical ``(N, nu)`` controls of the NLP's variables ``w``."""
        u = w[self.nx * (self.N + 1) :].reshape((self.nu, self.N), order="F").T.copy()
        return u * self.su[None, :] if self.scaled else u

    def rollout(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """States ``(nx, N + 1)``, contact flags ``(nc, N)`` and the loss of ``u``'s rollout
        (its flags and gaps are kept as :attr:`last`)."""
        x0, scene = self.x0, self.scene
        states = np.hstack([x0[:, None], np.asarray(self.roll(x0, u.T))])
        fl, gp, sp = (np.asarray(x) for x in self.flags_of(states[:, :-1], u.T))
        self.last = (fl.ravel(order="F"), gp.ravel(order="F"))
        loss = float(self.ocp.phi(states[:, -1])) + scene.control_weight * scene.dt * float(
            np.sum(u**2)
        )
        return states, fl, loss

    def region(self, f: np.ndarray, gp: np.ndarray, off_gap: np.ndarray) -> tuple[Any, Any]:
        """``lbg``, ``ubg`` that keep every contact in the branch of its flag."""
        m = f.size
        lo = np.full(3 * m, -np.inf)
        hi = np.full(3 * m, np.inf)
        on = f > 0.5
        hi[:m][on] = 0.0
        hi[m : 2 * m][on] = 0.0
        lo[2 * m :][on] = 0.0
        by_gap = ~on & ((gp >= 0) | off_gap)
        lo[:m][by_gap] = 0.0
        lo[m : 2 * m][~on & ~by_gap] = 0.0
        zeros = np.zeros(self.n_eq)
        return np.concatenate([zeros, lo]), np.concatenate([zeros, hi])

    def flipped(self, f: np.ndarray, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Flags on the other side of the active gap bounds (collision one step later or
        earlier), or None when no gap bound is active."""
        nc, N = self.nc, self.N
        lam_gap = np.abs(lam[: f.size]).reshape((nc, N), order="F")
        F2 = f.reshape((nc, N), order="F").copy()
        off = np.zeros_like(F2, dtype=bool)
        act = np.argwhere(lam_gap > 1e-9)
        if act.size == 0:
            return None
        for c, n in act:
            if F2[c, n] > 0.5:  # held at d^ = 0 from inside: let it hit one step later
                F2[c, n] = 0.0
                off[c, n] = True
                if n + 1 < N:
                    F2[c, n + 1] = 1.0
            else:  # held at d^ = 0 from outside: let it hit here, not at its later step
                later = np.flatnonzero(F2[c, n + 1 :] > 0.5)
                F2[c, n] = 1.0
                if later.size:
                    F2[c, n + 1 + later[0]] = 0.0
        return F2.ravel(order="F"), off.ravel(order="F")


@dataclass
class _Rounds:
    """The outcome of :func:`_refreeze`."""

    u: np.ndarray  # the best controls
    flags: np.ndarray  # their rollout's contact flags
    loss: float
    loss0: float  # the warm start's
    status: str  # IPOPT's, of the last round
    iterations: int
    rounds: int
    converged: bool


def _refreeze(nlp: _DiscreteNLP, u0: np.ndarray, max_rounds: int, verbose: bool) -> _Rounds:
    """Solve the frozen NLP, re-read the branches from a rollout of its controls, and repeat
    until they no longer change; at a boundary (an active gap bound) the branches on its other
    side are tried too. Stops at the first round that does not lower the loss."""
    best_u = u0
    states, fl, best_loss = nlp.rollout(u0)
    loss0 = best_loss
    status, iters, rounds, converged = "", 0, 0, False
    try_flags, try_off = fl.ravel(order="F"), np.zeros(fl.size, dtype=bool)
    flipping = False
    for rounds in range(1, max_rounds + 1):
        w0 = nlp.pack(states, best_u)
        lbg, ubg = nlp.region(try_flags, nlp.last[1], try_off)
        res = nlp.solver(x0=w0, lbg=lbg, ubg=ubg, p=try_flags)
        stats = nlp.solver.stats()
        status = str(stats.get("return_status", ""))
        iters += int(stats.get("iter_count", 0))
        ok = bool(stats.get("success", False)) or status == "Solved_To_Acceptable_Level"
        if not ok:
            converged = flipping  # the flipped branch is infeasible: the boundary is optimal
            break
        w = np.asarray(res["x"]).ravel()
        u_new = nlp.controls(w)
        saved = nlp.last
        states_new, fl_new, loss_new = nlp.rollout(u_new)
        consistent_round = np.array_equal(fl_new.ravel(order="F"), try_flags)
        if verbose:
            print(
                f"round {rounds}: {status}, {stats.get('iter_count')} it, loss {loss_new:.12g}, "
                f"NLP {float(res['f']) * (nlp.cs if nlp.scaled else 1.0):.12g}, branches "
                f"kept: {consistent_round}",
                file=sys.stderr,
            )
        if loss_new >= best_loss - 1e-13 * abs(best_loss):
            # no progress on the neighbouring branches: a local optimum on the boundary
            # between branches (a contact exactly at a step end), or the end of progress
            nlp.last = saved if not flipping else nlp.last
            converged = flipping or consistent_round
            break
        best_u, states, fl, best_loss = u_new, states_new, fl_new, loss_new
        nxt = nlp.flipped(fl.ravel(order="F"), np.asarray(res["lam_g"]).ravel()[nlp.n_eq :])
        if nxt is not None and consistent_round:
            try_flags, try_off = nxt
            flipping = True
        elif consistent_round:
            converged = True
            break
        else:
            try_flags, try_off = fl.ravel(order="F"), np.zeros(fl.size, dtype=bool)
            flipping = False
    return _Rounds(best_u, fl, best_loss, loss0, status, iters, rounds, converged)


def _warm_start(scene: Scene, ocp: HybridOCP, warm_start: Any) -> np.ndarray:
    """The ``(N, nu)`` controls of :func:`solve_discrete`'s ``warm_start``."""
    if warm_start is None:
        from hybridoc.solvers.transcription import solve_dt

        return solve_dt(scene).controls
    if isinstance(warm_start, str) and warm_start == "initial":
        return np.asarray(ocp.u_guess, dtype=float)
    return ocp.check_controls(getattr(warm_start, "controls", warm_start), what="warm start")


def solve_discrete(
    scene: ProblemLike,
    *,
    contact: str = "direct",
    toi: str = "both",
    warm_start: Any = None,
    tol: float = 1e-12,
    max_iter: int = 1000,
    max_rounds: int = 10,
    verbose: bool = False,
) -> Solution:
    """Minimise the simulator's discrete N-step loss exactly with IPOPT.

    Parameters
    ----------
    scene
        A Scene, a built-in name, a TOML path or a :class:`~hybridoc.problems.DiscOCP` (its
        ``steps`` is the N).
    contact, toi
        Simulator settings (default: ``direct`` impulses with both TOI corrections).
    warm_start
        ``None`` (the direct transcription's control, cell-averaged on the grid: usually in
        the optimum's branch pattern), ``"initial"`` (the scene's initial guess), an
        ``(N, nu)`` array or a :class:`~hybridoc.solution.Solution` (its controls), e.g.
        gradient descent's result.
    tol, max_iter
        IPOPT's settings (per round).
    max_rounds
        Most re-freezings of the contact branches.
    verbose
        Print IPOPT's log.

    Returns
    -------
    Solution
        Method ``"discrete"``: ``cost`` and its parts from the event-exact evaluator (the
        true continuous cost of the piecewise-constant controls), ``info["discrete_loss"]``
        the discrete loss of a rollout of the controls (the floor for gradient descent at this
        N), ``info["warm_start_loss"]`` that of the warm start, ``info["converged"]`` whether
        the last round ended in IPOPT's optimum with the contact branches unchanged (a local
        optimum of the piecewise-smooth loss); otherwise the best consistent rollout found.

    Raises
    ------
    ConvergenceError
        IPOPT failed.
    """
    scene = _scene(scene)
    ocp = scene.to_ocp()
    u0 = _warm_start(scene, ocp, warm_start)
    t0 = time.perf_counter()
    local = _local(scene)  # the same problem near the origin: the same controls
    nlp = _DiscreteNLP(local, local.to_ocp(), contact, toi, tol, max_iter)
    r = _refreeze(nlp, u0, max_rounds, verbose)
    if r.loss >= r.loss0 and r.rounds == 1 and r.status not in _ACCEPTED:
        raise ConvergenceError(
            f"discrete transcription did not converge (IPOPT: {r.status}); try a warm start "
            "closer to the optimum (e.g. the direct transcription's or gradient descent's "
            "controls)"
        )
    u = r.u
    consistent = bool(np.array_equal(nlp.rollout(u)[1], r.flags))
    solve_time = time.perf_counter() - t0
    loss = discrete_loss(scene, u, contact=contact, toi=toi)
    loss0 = discrete_loss(scene, u0, contact=contact, toi=toi)
    if loss > loss0 + 1e-12 * max(ocp.scales.cost, abs(loss0)):  # max(1, |J|) in its units
        # the branch pattern changed along the way and IPOPT ended above its start
        raise ConvergenceError(
            f"discrete transcription ended above its warm start ({loss:.10g} > {loss0:.10g}); "
            "try a warm start closer to the optimum"
        )
    ev = evaluate(ocp, u)
    return Solution.from_evaluation(
        ev,
        method="discrete",
        scene=scene.name,
        settings={"contact": contact, "toi": toi, "tol": tol, "steps": scene.steps},
        timings={"solve_time_s": solve_time},
        info={
            "discrete_loss": loss,
            "warm_start_loss": loss0,
            "iterations": r.iterations,
            "rounds": r.rounds,
            "branches_consistent": consistent,
            "converged": r.converged,
            "ipopt_status": r.status,
        },
    )


def discrete_gap(ocp: ProblemLike, sol: Solution) -> dict[str, Any]:
    """Gradient descent on the paper's discrete objective against that objective's optimum.

    The symplectic Euler loss that gd minimises is not the continuous cost; its own optimum
    comes from :func:`solve_discrete`, the same N steps transcribed and solved by IPOPT with
    the contact branches frozen, warm-started from gd's control (from the transcription's
    control instead it can stop in a higher local optimum of this piecewise-smooth loss:
    +1.3e-5 on multiple-collision).

    Parameters
    ----------
    ocp
        The disc problem: a name, a Scene or a :class:`~hybridoc.problems.DiscOCP`.
    sol
        Gradient descent's solution (its ``info["loss"]`` and controls).

    Returns
    -------
    dict
        ``discrete_loss`` (gd's), ``discrete_optimum`` and ``discrete_gap_relative``; or
        ``discrete_error`` when the transcription of the discrete problem failed.
    """
    loss = float(sol.info.get("loss", float("nan")))
    try:
        d = solve_discrete(disc_scene(ocp), warm_start=sol)
    except HybridocError as exc:
        return {"discrete_loss": loss, "discrete_error": str(exc)}
    best = float(d.info["discrete_loss"])
    return {
        "discrete_loss": loss,
        "discrete_optimum": best,
        "discrete_gap_relative": (loss - best) / abs(best),
    }
