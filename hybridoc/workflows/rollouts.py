"""Closed-loop rollouts with the policy compiled into the step, certified by the judge.

The judge's closed loop (:func:`hybridoc.evaluate` with ``policy=``, zero-order hold) is a
Python loop over the grid: the policy is called at each grid time on the exact state, and
each interval is searched for events on its own (37 ms per single-collision rollout).
:class:`CompiledRollouts` writes the same closed loop as one CasADi graph,

.. math::

    s_{k+1} = F(s_k, \\pi(t_k, s_k)),

with ``F`` the time-of-impact step of :func:`hybridoc.solvers.toi_sim.toi_step` (the exact
flow map of the problem, every guard's crossing located by Newton's method on its detector,
the problem's own resets, up to ``max_events`` events per cell, one after the other), iterated
by ``mapaccum`` over the ``N`` cells and ``map``-ped over a batch of initial states, and
compiled to C (:class:`hybridoc.solvers.codegen.Accelerated`). The policy is an :class:`MLP`
(its weights an input of the graph, so compiled code serves every policy of the same
architecture) or a :class:`CasadiPolicy`. An MLP's output saturation (the clip to the
control bounds of its file's ``saturation`` entry) is part of the graph, as ``fmax`` and
``fmin`` of its finite bounds, the same exact operations as the file's numpy policy
(a control at a bound is the bound in both), and its bounds are part of the architecture
(:func:`fingerprint`).

The compiled step is not the judge
    It looks for a crossing only where a guard ends a cell (or what remains of it after an
    event) penetrated and approaching; the judge proves every interval free of crossings
    (:mod:`hybridoc.rootfind`), so it also finds a contact that dips in and out within a
    cell. It resolves at most ``max_events`` events per cell and applies simultaneous
    events in guard order; the judge resolves any number, checks that simultaneous jumps
    commute and applies its grazing rule and its sustained-contact and Zeno checks
    (:mod:`hybridoc.events`).

So every rollout is certified by the judge
    :meth:`CompiledRollouts.certify` evaluates the rollout's controls ``u_k`` in the judge
    (open loop, its batched path: about 5 ms on single-collision), and accepts the rollout
    only when (1) the judge's states at the grid times match the compiled ones, (2) the
    policy, called as the judge calls it, returns ``u_k`` again at the judge's states, and
    (3) the compiled cost matches the judge's, each to ``rtol`` (1e-9) relative. Then the
    controls are those of the judge's closed loop up to ``rtol``, and the cost reported is
    the judge's, with its bound, path and terminal violations (the certificate's
    evaluation: :func:`~hybridoc.workflows.policies.validate_policy` flags a rollout that
    is not feasible). A rollout whose compiled step flagged a cell it cannot resolve (a guard
    still penetrated at the end of a cell: more events than ``max_events``, or a crossing
    missed), or that fails a check, is not certified: its caller runs the per-step judge
    (:func:`closed_loop_evaluations` does), and counts it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridoc import tolerances
from hybridoc.errors import ControlsError, EvaluationError
from hybridoc.evaluation import Evaluation
from hybridoc.evaluator import evaluate
from hybridoc.ocp import HybridOCP
from hybridoc.problem import ProblemLike, as_ocp
from hybridoc.workflows.policy_format import MLP, CasadiPolicy, PolicyError

__all__ = [
    "BATCH",
    "MAX_EVENTS",
    "RTOL",
    "Certified",
    "CompiledRollouts",
    "compilable",
    "closed_loop_evaluations",
    "fingerprint",
    "unsupported",
]

BATCH = 25
"""Initial states per call of the compiled function (padded): the chunk of
:func:`hybridoc.workflows.policies.validate_policy`."""
MAX_EVENTS = 3
"""Events per cell that the compiled step resolves."""
RTOL = tolerances.value("rollout")
"""Relative agreement with the judge that certifies a compiled rollout."""
_PENETRATION = tolerances.value(
    "penetration"
)  # a guard below -this at a cell's end: the cell was not resolved


def compilable(policy: Any) -> bool:
    """Whether a loaded policy can be compiled into the closed-loop step (an :class:`MLP` or
    a :class:`CasadiPolicy`)."""
    return isinstance(policy, MLP | CasadiPolicy)


def fingerprint(policy: MLP | CasadiPolicy) -> str:
    """A digest of everything a compiled policy is made of (architecture, normalisations,
    weights; a CasADi policy's serialisation): equal digests, the same compiled rollout."""
    import hashlib

    h = hashlib.sha256()
    if isinstance(policy, MLP):
        h.update(repr(policy.description()).encode())
        for a in (policy.parameters(), policy.state_mean, policy.state_scale,
                  policy.output_offset, policy.output_scale):  # fmt: skip
            h.update(np.ascontiguousarray(a, dtype=float).tobytes())
    else:
        h.update(policy.function.serialize().encode())
    return h.hexdigest()


def unsupported(ocp: HybridOCP, policy: Any) -> str | None:
    """Why ``policy`` on ``ocp`` has no compiled rollout, or ``None``."""
    if not compilable(policy):
        return (
            f"the policy is a {type(policy).__name__}: only an MLP policy file (policy.json) or "
            "a casadi.Function is compiled"
        )
    if (policy.nx, policy.nu) != (ocp.nx, ocp.nu):
        return (
            f"the policy maps {policy.nx} states to {policy.nu} controls; {ocp.name!r} has "
            f"{ocp.nx} states and {ocp.nu} controls"
        )
    if not ocp.has_closed_form_flow or ocp.flow_map is None or not ocp.flow_map.is_a("SXFunction"):
        return f"{ocp.name!r} has no closed-form flow map: its compiled step would not be exact"
    if not all(g.psi.is_a("SXFunction") and g.reset.is_a("SXFunction") for g in ocp.guards):
        return f"{ocp.name!r} has guards that are not SX functions"
    if isinstance(policy, CasadiPolicy) and not policy.function.is_a("SXFunction"):
        try:
            policy.function.expand()
        except RuntimeError:
            return "the CasADi policy cannot be expanded to SX (it calls an external function)"
    return None


@dataclass
class Certified:
    """One compiled rollout and the judge's verdict on it.

    Attributes
    ----------
    evaluation
        The judge's :class:`~hybridoc.evaluation.Evaluation` of the rollout's controls when
        certified, else ``None`` (run the per-step judge).
    reason
        Why it is not certified (``""`` when it is).
    kind
        The reason in a word, for counting: ``"unresolved"`` (a cell the compiled step
        flagged), ``"judge-error"`` (the judge raised on the rollout's controls), ``"cost"``,
        ``"grid states"`` or ``"controls"`` (a check failed); ``""`` when certified.
    compiled_cost
        The compiled rollout's cost (NaN when it did not finish).
    cost_rel_diff, state_rel_diff, control_rel_diff
        The largest relative differences between compiled and judge: cost, grid states,
        and controls against the policy at the judge's states (NaN where not computed).
    """

    evaluation: Evaluation | None
    reason: str
    compiled_cost: float
    kind: str = ""
    cost_rel_diff: float = float("nan")
    state_rel_diff: float = float("nan")
    control_rel_diff: float = float("nan")


class CompiledRollouts:
    """The closed loop of ``policy`` on a problem's structure as one compiled function.

    Parameters
    ----------
    problem
        The problem; draws that change only ``x0`` (and, for disc scenes, the targets,
        which enter the terminal cost only) share its compiled function.
    policy
        An :class:`MLP` or a :class:`CasadiPolicy` (:func:`load_policy
        <hybridoc.workflows.policies.load_policy>` gives them).
    max_events
        Events per cell that the compiled step resolves.
    batch
        Initial states per call (a batch is padded to a multiple of it).
    compile
        ``True``: build the C code now, in the foreground (or load it from the cache) when
        code generation is on (:mod:`hybridoc.solvers.codegen`); ``False``: CasADi's virtual
        machine until the background compilation is ready.

    Raises
    ------
    PolicyError
        A policy or problem without a compiled form (:func:`unsupported` says why).
    """

    def __init__(
        self,
        problem: ProblemLike,
        policy: MLP | CasadiPolicy,
        *,
        max_events: int = MAX_EVENTS,
        batch: int = BATCH,
        compile: bool = True,
    ) -> None:
        import casadi as ca

        from hybridoc.solvers.codegen import Accelerated
        from hybridoc.solvers.toi_sim import toi_step

        ocp = as_ocp(problem)
        why = unsupported(ocp, policy)
        if why is not None:
            raise PolicyError(f"no compiled rollout: {why}")
        self.ocp, self.policy = ocp, policy
        self.nx, self.nu, self.steps = ocp.nx, ocp.nu, ocp.steps
        self.batch = int(batch)
        self.max_events = int(max_events)
        pol = policy.casadi(symbolic=True)
        if not pol.is_a("SXFunction"):
            pol = pol.expand()
        self.params = policy.parameters()
        step = toi_step(ocp, ocp.dt, max_events=self.max_events)
        s, t = ca.SX.sym("s", ocp.nx), ca.SX.sym("t")
        p = ca.SX.sym("p", self.params.size)
        u = pol(t, s, p) if pol.n_in() == 3 else pol(t, s)
        s_next, c = step(s, u)
        if ocp.guards:
            psi = ca.vertcat(*[g.psi(s_next) for g in ocp.guards])
            flag = ca.mmin(psi) < -_PENETRATION
        else:
            flag = ca.SX(0)
        cell = ca.Function("closed_loop_cell", [s, t, p], [s_next, c, u, flag])
        x0, T, P = ca.MX.sym("x0", ocp.nx), ca.MX.sym("T", 1, ocp.steps), ca.MX.sym("p", p.numel())
        X, C, U, F = cell.mapaccum("closed_loop", ocp.steps)(x0, T, P)
        roll = ca.Function("closed_loop_rollout", [x0, T, P], [X, C, U, F])
        self.function = Accelerated(roll.map(self.batch), wait=compile)
        self._grid = ocp.time_grid()

    @property
    def compiled(self) -> bool:
        """Whether the C code is in use (else CasADi's virtual machine)."""
        return bool(self.function.compiled)

    def run(self, x0: Any) -> dict[str, np.ndarray]:
        """The compiled closed loop from each row of ``x0`` ``(B, nx)``.

        Returns
        -------
        dict
            ``states`` ``(B, N + 1, nx)`` at the grid times, ``controls`` ``(B, N, nu)``,
            ``running`` ``(B,)`` (the running costs), ``untrusted`` ``(B,)`` (a cell that the
            step did not resolve, or a non-finite number).
        """
        X0 = np.asarray(x0, dtype=float).reshape(-1, self.nx)
        B, N, L = X0.shape[0], self.steps, self.batch
        nb = -(-B // L) if B else 0
        pad = np.concatenate([X0, np.repeat(X0[-1:], nb * L - B, axis=0)]) if B else X0
        T = self._grid[None, :-1]
        out: dict[str, list[np.ndarray]] = {"X": [], "C": [], "U": [], "F": []}
        for b in range(nb):
            res = self.function(pad[b * L : (b + 1) * L].T, T, self.params)
            for key, r in zip("XCUF", res, strict=True):
                out[key].append(np.asarray(r))
        if not B:
            z = np.zeros((0,))
            return {
                "states": np.zeros((0, N + 1, self.nx)), "controls": np.zeros((0, N, self.nu)),
                "running": z, "untrusted": z.astype(bool),
            }  # fmt: skip
        # map concatenates horizontally: each output is (rows, N * L) per call
        X = np.concatenate(out["X"], axis=1).reshape(self.nx, nb * L, N).transpose(1, 2, 0)
        C = np.concatenate(out["C"], axis=1).reshape(nb * L, N)
        U = np.concatenate(out["U"], axis=1).reshape(self.nu, nb * L, N).transpose(1, 2, 0)
        F = np.concatenate(out["F"], axis=1).reshape(nb * L, N)
        states = np.concatenate([pad[:, None, :], X], axis=1)[:B]
        running = np.array([float(np.cumsum(np.r_[0.0, c])[-1]) for c in C[:B]])
        bad = (F[:B] > 0.5).any(axis=1)
        bad |= ~np.isfinite(states).all(axis=(1, 2)) | ~np.isfinite(U[:B]).all(axis=(1, 2))
        return {"states": states, "controls": U[:B].copy(), "running": running, "untrusted": bad}

    def certify(
        self, problems: list[HybridOCP], *, rtol: float = RTOL, **judge: Any
    ) -> list[Certified]:
        """Compiled rollouts of each problem (its ``x0``), each certified by the judge.

        Parameters
        ----------
        problems
            Problems of this structure (draws of a distribution).
        rtol
            Relative agreement required of the cost, the grid states and the controls.
        **judge
            Passed to :func:`hybridoc.evaluate` (``graze_tol``, ``penetration_tol``, ...).

        Returns
        -------
        list of Certified
            One per problem, in order.
        """
        raw = self.run(np.array([ocp.x0 for ocp in problems]))
        return [
            self._certify_one(
                ocp,
                raw["states"][i],
                raw["controls"][i],
                raw["running"][i],
                bool(raw["untrusted"][i]),
                rtol,
                judge,
            )  # fmt: skip
            for i, ocp in enumerate(problems)
        ]

    def _certify_one(
        self,
        ocp: HybridOCP,
        S: np.ndarray,
        U: np.ndarray,
        running: float,
        untrusted: bool,
        rtol: float,
        judge: dict[str, Any],
    ) -> Certified:
        if untrusted:
            return Certified(
                None,
                "a cell the compiled step does not resolve (a guard penetrated at its end: "
                f"more than {self.max_events} events, or a missed crossing)",
                float("nan"),
                "unresolved",
            )
        J_c = running + float(ocp.phi(S[-1]))
        try:
            ev = evaluate(ocp, U, **judge)
        except (EvaluationError, ControlsError) as exc:
            return Certified(None, f"the judge: {' '.join(str(exc).split())}", J_c, "judge-error")
        idx = np.array([seg.interval for seg in ev.segments], dtype=int)
        first = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
        S_j = np.vstack([[ev.segments[i].s0 for i in first], ev.final_state])
        ds = float(np.max(np.abs(S_j - S) / np.maximum(1.0, np.abs(S_j))))
        u_j = np.asarray(self.policy(self._grid[:-1], S_j[:-1]), dtype=float).reshape(U.shape)
        du = float(np.max(np.abs(u_j - U) / np.maximum(1.0, np.abs(u_j))))
        dJ = abs(J_c - ev.cost) / max(abs(ev.cost), np.finfo(float).tiny)
        cert = Certified(ev, "", J_c, "", dJ, ds, du)
        for what, d in (("cost", dJ), ("grid states", ds), ("controls", du)):
            if not d <= rtol:  # NaN fails too
                cert.evaluation = None
                cert.reason = f"the {what} differ from the judge's by {d:.3g} (relative)"
                cert.kind = what
                break
        return cert


def closed_loop_evaluations(
    problem: ProblemLike,
    policy: Any,
    x0: Any,
    *,
    compiled: CompiledRollouts | None = None,
    rtol: float = RTOL,
    **judge: Any,
) -> tuple[list[Evaluation], list[Certified]]:
    """The judge's zero-order-hold closed-loop evaluations from many initial states, compiled.

    Parameters
    ----------
    problem
        The problem; each row of ``x0`` replaces its initial state.
    policy
        An :class:`MLP` or a :class:`CasadiPolicy`.
    x0
        ``(B, nx)`` initial states.
    compiled
        A :class:`CompiledRollouts` of this problem and policy to reuse.
    rtol
        See :meth:`CompiledRollouts.certify`.
    **judge
        Passed to :func:`hybridoc.evaluate`.

    Returns
    -------
    evaluations
        The judge's evaluations: certified compiled rollouts, and for the others the
        per-step judge's ``evaluate(problem, policy=policy)``.
    certified
        The certificates (``evaluation is None``: that rollout went through the per-step
        judge; ``reason`` says why).

    Raises
    ------
    PolicyError
        A policy or problem without a compiled form.
    EvaluationError, ControlsError
        What the per-step judge raises on a rollout that was not certified.
    """
    ocp = as_ocp(problem)
    X0 = np.asarray(x0, dtype=float).reshape(-1, ocp.nx)
    runner = compiled if compiled is not None else CompiledRollouts(ocp, policy)
    problems = [ocp.replace(x0=row.copy()) for row in X0]
    certs = runner.certify(problems, rtol=rtol, **judge)
    evs = [
        c.evaluation if c.evaluation is not None else evaluate(p, policy=policy, **judge)
        for p, c in zip(problems, certs, strict=True)
    ]
    return evs, certs
