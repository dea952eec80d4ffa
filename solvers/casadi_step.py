"""The simulator's discrete step as a CasADi function.

:func:`make_step` writes the same symplectic-Euler step with ``direct`` impulses and the
time-of-impact corrections as :class:`hybridoc.solvers.simulator.Simulator` (see that module
for the equations and for how several contacts in one step are handled) in CasADi ``SX``
symbols, with ``if_else`` for the contact branches. The direct transcription and the compiled
rollout (:mod:`hybridoc.solvers.compiled`) are built from it, so all three agree with the torch
simulator to rounding. :func:`step_parts` also gives the contact tests, gaps and normal
speeds, and with frozen contact branches the smooth step that
:mod:`hybridoc.solvers.discrete_transcription` optimises over.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import casadi as ca
import numpy as np

from hybridoc.errors import SceneError
from hybridoc.problems import physics as ph
from hybridoc.solvers.contacts.base import TOI_MODES

__all__ = ["StepParts", "make_step", "step_expression", "step_parts"]

NEWTON_ITERATIONS = 4  # as hybridoc.solvers.simulator.NEWTON_ITERATIONS


class StepParts(NamedTuple):
    """The pieces of one ``direct``-impulse step (see :func:`step_parts`)."""

    s_next: Any
    """The state after the step."""
    applied: Any
    """Per contact, 1 where the true step applies an impulse, else 0."""
    gaps: Any
    """Per contact, the predicted gap ``d^`` after the smooth update."""
    speeds: Any
    """Per contact, the predicted normal speed ``w^`` after the smooth update."""


def step_parts(
    scene: Any,
    s: Any,
    u: Any,
    toi: str = "both",
    integrator: str = "symplectic-euler",
    flags: Any = None,
) -> StepParts:
    """One ``direct``-impulse step with its contact tests, optionally with frozen branches.

    Contacts are in the simulator's order: disc pairs (``i < j``, scene order), then
    disc-wall (disc-major).

    Parameters
    ----------
    scene
        A :class:`~hybridoc.problems.Scene`.
    s, u
        State ``(nx,)`` and control ``(nu,)`` symbols (``SX`` or ``MX``).
    toi
        ``"none"``, ``"position"``, ``"velocity"`` or ``"both"``.
    integrator
        ``"symplectic-euler"`` or ``"exact"`` (needs ``toi="both"`` and no ``flags``), as in
        the simulator.
    flags
        ``None`` (default): the true step, each contact's impulse applied where its test holds
        (``if_else``). Otherwise one 0/1 per contact fixing the branches: the impulse is
        applied where the flag is 1, with the smooth, unclamped time of impact ``d^ / w^``;
        the step is then smooth in ``(s, u)``.

    Returns
    -------
    StepParts
        The next state, the true branch tests, and the gaps ``d^`` and normal speeds ``w^``.
    """
    if toi not in TOI_MODES:
        raise SceneError(f"unknown toi setting {toi!r}; choose one of {', '.join(TOI_MODES)}")
    if integrator not in ("symplectic-euler", "exact"):
        raise SceneError(f"unknown integrator {integrator!r}; choose symplectic-euler or exact")
    exact = integrator == "exact"
    if exact and toi != "both":
        raise SceneError("integrator 'exact' needs toi='both'")
    if exact and flags is not None:
        raise SceneError("frozen contact flags need integrator 'symplectic-euler'")
    ops = ph.CASADI
    n = scene.n_discs
    dt = scene.dt
    e = scene.restitution
    m = [d.mass for d in scene.discs]
    p = [s[2 * i : 2 * i + 2] for i in range(n)]
    v = [s[2 * n + 2 * i : 2 * n + 2 * i + 2] for i in range(n)]
    a = []
    k = 0
    for i, d in enumerate(scene.discs):
        if d.actuated:
            a.append(u[k : k + 2] / m[i])
            k += 2
        else:
            a.append(ca.DM.zeros(2))
    v_hat = [v[i] + a[i] * dt for i in range(n)]
    if exact:
        p_hat = [p[i] + (v[i] + 0.5 * a[i] * dt) * dt for i in range(n)]
    else:
        p_hat = [p[i] + v_hat[i] * dt for i in range(n)]
    dv: list[Any] = [0] * n
    dp: list[Any] = [0] * n
    use_bar = toi in ("velocity", "both")
    use_pos = toi in ("position", "both")

    def rel(x: list[Any], c: ph.Contact) -> Any:
        return x[c.i] - x[c.j] if c.j is not None else x[c.i]

    def gap_normal(r: Any, c: ph.Contact) -> tuple[Any, Any]:
        if c.j is not None:
            R = scene.discs[c.i].radius + scene.discs[c.j].radius
            return ph.pair_gap(r, R, ops)
        assert c.wall is not None
        wall = scene.walls[c.wall]
        nw = ca.DM(wall.normal)
        return ph.wall_gap(r, ca.DM(wall.point), nw, scene.discs[c.i].radius, ops), nw

    def at_impact(toi_c: Any, rels: tuple[Any, ...], c: ph.Contact) -> tuple[Any, Any]:
        # normal and normal speed at the time of impact (the velocity correction)
        rp, rv, ra, rv_hat = rels
        tau = dt - toi_c
        _, nrm = gap_normal(rp + tau * rv_hat, c)
        return nrm, ph.normal_speed(rv + tau * ra, nrm, ops)

    tests, gaps, speeds = [], [], []
    for ci, c in enumerate(ph.contacts(n, len(scene.walls))):
        i, j = c.i, c.j
        rp, rv, ra = rel(p, c), rel(v, c), rel(a, c)
        rp_hat, rv_hat = rel(p_hat, c), rel(v_hat, c)
        d_hat, n_hat = gap_normal(rp_hat, c)
        w_hat = ph.normal_speed(rv_hat, n_hat, ops)
        active = ca.logic_and(d_hat < 0, w_hat < 0)
        toi_c = ph.toi_linear(d_hat, w_hat, dt, active, ops)
        if exact:
            if c.is_pair:
                R = scene.discs[i].radius + scene.discs[c.j].radius  # type: ignore[index]
                tau = ph.refine_impact_time(
                    rp, rv, ra, dt - toi_c, active, dt, ops, R=R, iterations=NEWTON_ITERATIONS
                )
            else:
                assert c.wall is not None
                wall = scene.walls[c.wall]
                nw = ca.DM(wall.normal)
                off = float(np.dot(wall.point, wall.normal)) + scene.discs[i].radius
                tau = ph.refine_impact_time(
                    rp, rv, ra, dt - toi_c, active, dt, ops, normal=nw, offset=off,
                    iterations=NEWTON_ITERATIONS,
                )  # fmt: skip
            toi_c = ca.if_else(active, dt - tau, 0.0)
            _, nrm = gap_normal(rp + (rv + 0.5 * ra * tau) * tau, c)
            w = ph.normal_speed(rv + ra * tau, nrm, ops)
        elif use_bar:
            nrm, w = at_impact(toi_c, (rp, rv, ra, rv_hat), c)
        else:
            nrm, w = n_hat, w_hat
        hit = ca.logic_and(active, w < 0)
        tests.append(hit)
        gaps.append(d_hat)
        speeds.append(w_hat)
        inv_mass_sum = 1.0 / m[i] + (1.0 / m[j] if j is not None else 0.0)
        if flags is None:
            lam = ca.if_else(hit, ph.impulse(w, inv_mass_sum, e), 0.0)
        else:
            # frozen: the time of impact of an applied contact is d^ / w^ (unclamped, smooth)
            w_frozen = ca.if_else(flags[ci] > 0.5, w_hat, -1.0)
            toi_c = flags[ci] * d_hat / w_frozen
            if use_bar:
                nrm, w = at_impact(toi_c, (rp, rv, ra, rv_hat), c)
            lam = flags[ci] * ph.impulse(w, inv_mass_sum, e)
        dvi = lam / m[i] * nrm
        dv[i] = dv[i] + dvi
        if use_pos or exact:
            dp[i] = dp[i] + toi_c * dvi
        if j is not None:
            dvj = -lam / m[j] * nrm
            dv[j] = dv[j] + dvj
            if use_pos or exact:
                dp[j] = dp[j] + toi_c * dvj
    p_next = [p_hat[i] + dp[i] for i in range(n)]
    v_next = [v_hat[i] + dv[i] for i in range(n)]
    return StepParts(
        ca.vertcat(*p_next, *v_next), ca.vertcat(*tests), ca.vertcat(*gaps), ca.vertcat(*speeds)
    )


def step_expression(
    scene: Any, s: Any, u: Any, toi: str = "both", integrator: str = "symplectic-euler"
) -> Any:
    """The next state of one ``direct``-impulse step as a CasADi expression.

    The ``s_next`` of :func:`step_parts` with the same arguments (the true branches).

    Returns
    -------
    casadi.SX or casadi.MX
        The state after one step of length ``scene.dt``.
    """
    return step_parts(scene, s, u, toi, integrator).s_next


def make_step(
    scene: Any, contact: str = "direct", toi: str = "both", integrator: str = "symplectic-euler"
) -> ca.Function:
    """The discrete step ``s_next = step(s, u)`` of a scene as a CasADi ``Function``.

    Parameters
    ----------
    scene
        A :class:`~hybridoc.problems.Scene`, a built-in name or a TOML path.
    contact
        A contact model with a CasADi step (``compiled``); today ``"direct"``.
    toi
        Time-of-impact correction: ``"none"``, ``"position"``, ``"velocity"`` or ``"both"``.
    integrator
        ``"symplectic-euler"`` (default, the paper's) or ``"exact"``.

    Returns
    -------
    casadi.Function
        ``Function('step', [s, u], [s_next])`` with ``SX`` inside, equal to one step of
        :class:`hybridoc.solvers.simulator.Simulator` with the same settings.
    """
    from hybridoc.problems import disc_scene
    from hybridoc.solvers.contacts import CONTACT_MODELS, contact_model

    scene = disc_scene(scene)
    model = contact_model(contact, toi=toi)
    if not model.compiled:
        compiled = [name for name, cls in CONTACT_MODELS.items() if cls.compiled]
        raise SceneError(
            f"contact model {model.name!r} has no CasADi form; {', '.join(compiled)} do (use "
            "the torch Simulator for the others)"
        )
    s = ca.SX.sym("s", 4 * scene.n_discs)
    u = ca.SX.sym("u", scene.n_controls)
    return ca.Function(
        "step", [s, u], [step_expression(scene, s, u, toi, integrator)], ["s", "u"], ["s_next"]
    )
