"""The simulator's discrete step as a CasADi function, for every contact model.

:func:`make_step` writes one step of :class:`hybridoc.solvers.simulator.Simulator` in CasADi
``SX`` symbols, with ``if_else`` for the contact branches, for any registered contact model
(:meth:`hybridoc.solvers.contacts.ContactModel.casadi_step`). The direct transcription and
the compiled rollout (:mod:`hybridoc.solvers.compiled`) are built from it, so they agree with
the torch simulator to rounding.

The impulse models (``direct``, ``lcp``, ``convex``) share :func:`step_parts`: the
symplectic-Euler (or exact-flow) prediction, contact detection and the time-of-impact
corrections, with the model's impulse solver in between (:class:`ImpulseInputs`). ``direct``
is the closed form per contact; ``lcp`` and ``convex`` solve a linear complementarity
problem with a positive definite matrix, whose solution is unique: :func:`enumerated_lcp`
writes it exactly as a choice among the solutions on every candidate active set, which
limits them to :data:`MAX_ENUMERATED_CONTACTS` potential contacts. :func:`step_parts` also
gives the contact tests, gaps and normal speeds, and with frozen contact branches the smooth
``direct`` step that :mod:`hybridoc.solvers.discrete_transcription` optimises over.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import casadi as ca
import numpy as np

from hybridoc.errors import SceneError
from hybridoc.problems import physics as ph
from hybridoc.solvers.contacts.base import INTEGRATORS, SIGN_TOLERANCE, TOI_MODES, ContactModel

__all__ = [
    "ImpulseInputs",
    "MAX_ENUMERATED_CONTACTS",
    "StepParts",
    "direct_impulses",
    "disc_kinematics",
    "enumerated_lcp",
    "enumeration_unsupported",
    "make_step",
    "step_expression",
    "step_parts",
]

NEWTON_ITERATIONS = 4  # as hybridoc.solvers.simulator.NEWTON_ITERATIONS

MAX_ENUMERATED_CONTACTS = 6
"""Most potential contacts (disc pairs plus disc-wall pairs) of a scene for which
:func:`enumerated_lcp` writes the coupled impulses. It enumerates all ``2**C`` candidate
active sets, so size and evaluation time double with every contact: at 6 contacts (three
discs and a wall) one step has about 5,000 ``SX`` nodes and a loss with gradient over 480
steps takes about 0.4 s in CasADi's virtual machine, at 9 about 70,000 nodes, 15 s to build
and 6 s per evaluation, slower than the torch simulator."""


class StepParts(NamedTuple):
    """The pieces of one impulse-model step (see :func:`step_parts`)."""

    s_next: Any
    """The state after the step."""
    applied: Any
    """Per contact, 1 where the true step applies an impulse, else 0."""
    gaps: Any
    """Per contact, the predicted gap ``d^`` after the smooth update."""
    speeds: Any
    """Per contact, the predicted normal speed ``w^`` after the smooth update."""


class ImpulseInputs(NamedTuple):
    """What an impulse model's CasADi solver sees of the ``C`` potential contacts of a step.

    Contacts are in the order of :func:`hybridoc.problems.physics.contacts`.
    """

    W: list[list[Any]]
    """The Delassus matrix ``J M^-1 J^T`` (``C x C`` nested lists) at the impulse normals."""
    w: list[Any]
    """Pre-impact normal speeds at the impulse state (negative approaching)."""
    active: list[Any]
    """Detected contacts: ``d^ < 0`` and ``w^ < 0`` at the predicted state."""
    hit: list[Any]
    """Detected and approaching at the impulse state (``w < 0``)."""
    inv_mass_sum: list[float]
    """``1/m_i + 1/m_j`` of a pair, ``1/m_i`` of a wall contact."""
    restitution: float
    """The coefficient of restitution."""


def disc_kinematics(scene: Any, s: Any, u: Any) -> tuple[list[Any], list[Any], list[Any]]:
    """Per-disc positions, velocities and accelerations ``u / m`` (2-vectors) of a state.

    Parameters
    ----------
    scene
        A :class:`~hybridoc.problems.Scene`.
    s, u
        State ``(4 n,)`` and control ``(nu,)`` symbols (``SX`` or ``MX``).

    Returns
    -------
    tuple of lists
        ``(p, v, a)``, one column 2-vector per disc; unactuated discs have ``a = 0``.
    """
    n = scene.n_discs
    p = [s[2 * i : 2 * i + 2] for i in range(n)]
    v = [s[2 * n + 2 * i : 2 * n + 2 * i + 2] for i in range(n)]
    a = []
    k = 0
    for d in scene.discs:
        if d.actuated:
            a.append(u[k : k + 2] / d.mass)
            k += 2
        else:
            a.append(ca.DM.zeros(2))
    return p, v, a


def direct_impulses(inputs: ImpulseInputs) -> list[Any]:
    """The ``direct`` impulses: ``-(1 + e) w / (1/m_i + 1/m_j)`` per approaching contact."""
    e = inputs.restitution
    return [
        ca.if_else(hit, ph.impulse(w, ims, e), 0.0)
        for hit, w, ims in zip(inputs.hit, inputs.w, inputs.inv_mass_sum, strict=True)
    ]


def enumeration_unsupported(label: str, scene: Any) -> str | None:
    """Why :func:`enumerated_lcp` cannot serve ``scene`` (too many contacts), or ``None``."""
    C = len(ph.contacts(scene.n_discs, len(scene.walls)))
    if C <= MAX_ENUMERATED_CONTACTS:
        return None
    return (
        f"contact model {label}: its CasADi step enumerates the active sets of at most "
        f"{MAX_ENUMERATED_CONTACTS} potential contacts and this scene has {C}; use the torch "
        "Simulator (path='torch')"
    )


def _solve_spd(A: list[list[Any]], b: list[Any]) -> list[Any]:
    """``A^-1 b`` by Gaussian elimination without pivoting (``A`` symmetric positive definite,
    so that every pivot is positive); entries are CasADi scalars or numbers."""
    k = len(b)
    A = [list(row) for row in A]
    b = list(b)
    for col in range(k):
        for r in range(col + 1, k):
            f = A[r][col] / A[col][col]
            for cc in range(col + 1, k):
                A[r][cc] = A[r][cc] - f * A[col][cc]
            b[r] = b[r] - f * b[col]
    x: list[Any] = [0.0] * k
    for r in reversed(range(k)):
        acc = b[r]
        for cc in range(r + 1, k):
            acc = acc - A[r][cc] * x[cc]
        x[r] = acc / A[r][r]
    return x


def enumerated_lcp(
    M: Sequence[Sequence[Any]],
    q: Sequence[Any],
    active: Sequence[Any],
    eligible: Sequence[bool] | None = None,
) -> list[Any]:
    """The solution of ``0 <= lambda _|_ M lambda + q >= 0`` on the active contacts, exactly.

    The CasADi form of :func:`hybridoc.solvers.impulses.solve_lcp` (``M = W``) and of
    :func:`hybridoc.solvers.impulses.solve_convex` (``M = H``, the regularised matrix): for a
    positive definite ``M`` the solution is unique, so it is the solution
    ``lambda_S = -M_SS^-1 q_S`` of the first candidate active set ``S`` (by size, then
    lexicographically) that is consistent: ``S`` within the active contacts,
    ``lambda_S >= -tol`` and ``(M lambda + q)_c >= -tol`` on the other active contacts, with
    the torch solvers' tolerance ``tol = SIGN_TOLERANCE * eps * max|q|``. Contacts that are not
    active get 0; without any active contact the empty set is consistent and every impulse is
    0, so that the step is the contact-free one, as the torch step's early return. The
    derivative is the active set's, as in torch.

    Parameters
    ----------
    M : sequence of sequences
        ``C x C`` symmetric positive definite matrix (CasADi scalars or numbers).
    q : sequence
        ``C`` CasADi scalars.
    active : sequence
        ``C`` CasADi conditions: the contacts that may take an impulse.
    eligible : sequence of bool, optional
        Contacts that can take an impulse at all (a static test, e.g. a positive diagonal of
        the Delassus matrix); default all.

    Returns
    -------
    list
        ``C`` CasADi scalars ``lambda_c >= 0``; NaN where no candidate set is consistent,
        which a positive definite ``M`` rules out up to rounding. A singular ``M``
        (redundant contacts, e.g. a disc squeezed between parallel walls), for which the
        torch solvers shift the diagonal and split the impulse arbitrarily, is not covered.

    Raises
    ------
    SceneError
        More than :data:`MAX_ENUMERATED_CONTACTS` eligible contacts.
    """
    C = len(q)
    idx = [c for c in range(C) if eligible is None or eligible[c]]
    if len(idx) > MAX_ENUMERATED_CONTACTS:
        raise SceneError(
            f"the CasADi LCP enumerates the active sets of at most {MAX_ENUMERATED_CONTACTS} "
            f"contacts, got {len(idx)}; use the torch Simulator (path='torch')"
        )
    scale: Any = float(np.finfo(float).tiny)
    for qc in q:
        scale = ca.fmax(scale, ca.fabs(qc))
    tol = SIGN_TOLERANCE * float(np.finfo(float).eps) * scale
    # the first consistent set wins: in a degenerate case (an impulse and its complementary
    # speed both zero) two sets are consistent, and a plain sum over sets would count it twice
    lam: list[Any] = [0.0] * C
    found: Any = ca.SX(0)
    for r in range(len(idx) + 1):
        for S in itertools.combinations(idx, r):
            lam_S = _solve_spd([[M[c][d] for d in S] for c in S], [-q[c] for c in S])
            valid: Any = ca.SX(1)
            for c in idx:
                if c in S:
                    ok = ca.logic_and(active[c], lam_S[S.index(c)] >= -tol)
                else:
                    mu = q[c]
                    for d, x in zip(S, lam_S, strict=True):
                        mu = mu + M[c][d] * x
                    ok = ca.logic_or(ca.logic_not(active[c]), mu >= -tol)
                valid = ca.logic_and(valid, ok)
            chosen = ca.logic_and(valid, ca.logic_not(found))
            found = ca.logic_or(found, valid)
            for c, x in zip(S, lam_S, strict=True):
                lam[c] = lam[c] + ca.if_else(chosen, x, 0.0)
    return [ca.if_else(found, x, np.nan) for x in lam]


def step_parts(
    scene: Any,
    s: Any,
    u: Any,
    toi: str = "both",
    integrator: str = "symplectic-euler",
    flags: Any = None,
    impulses: Callable[[ImpulseInputs], list[Any]] | None = None,
) -> StepParts:
    """One impulse-model step with its contact tests, optionally with frozen branches.

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
        (``if_else``). Otherwise one 0/1 per contact fixing the branches of the ``direct``
        impulses: the impulse is applied where the flag is 1, with the smooth, unclamped time
        of impact ``d^ / w^``; the step is then smooth in ``(s, u)``.
    impulses
        The impulse solver: ``None`` (default) or :func:`direct_impulses` for ``direct``,
        else an impulse model's :meth:`~hybridoc.solvers.contacts.ImpulseModel.casadi_impulses`.

    Returns
    -------
    StepParts
        The next state, the true branch tests (``direct``: detected and approaching; other
        solvers: a positive impulse), and the gaps ``d^`` and normal speeds ``w^``.
    """
    if toi not in TOI_MODES:
        raise SceneError(f"unknown toi setting {toi!r}; choose one of {', '.join(TOI_MODES)}")
    if integrator not in INTEGRATORS:
        raise SceneError(f"unknown integrator {integrator!r}; choose symplectic-euler or exact")
    exact = integrator == "exact"
    if exact and toi != "both":
        raise SceneError("integrator 'exact' needs toi='both'")
    if exact and flags is not None:
        raise SceneError("frozen contact flags need integrator 'symplectic-euler'")
    if flags is not None and impulses not in (None, direct_impulses):
        raise SceneError("frozen contact flags need the direct impulses")
    ops = ph.CASADI
    n = scene.n_discs
    dt = scene.dt
    e = scene.restitution
    m = [d.mass for d in scene.discs]
    p, v, a = disc_kinematics(scene, s, u)
    v_hat = [v[i] + a[i] * dt for i in range(n)]
    if exact:
        p_hat = [p[i] + (v[i] + 0.5 * a[i] * dt) * dt for i in range(n)]
    else:
        p_hat = [p[i] + v_hat[i] * dt for i in range(n)]
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

    cl = ph.contacts(n, len(scene.walls))
    actives, tests, gaps, speeds, nrms, ws, tois, ims_list, lams = (
        [],
        [],
        [],
        [],
        [],
        [],
        [],
        [],
        [],
    )
    for ci, c in enumerate(cl):
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
        inv_mass_sum = 1.0 / m[i] + (1.0 / m[j] if j is not None else 0.0)
        if flags is not None:
            # frozen: the time of impact of an applied contact is d^ / w^ (unclamped, smooth)
            w_frozen = ca.if_else(flags[ci] > 0.5, w_hat, -1.0)
            toi_c = flags[ci] * d_hat / w_frozen
            if use_bar:
                nrm, w = at_impact(toi_c, (rp, rv, ra, rv_hat), c)
            lams.append(flags[ci] * ph.impulse(w, inv_mass_sum, e))
        actives.append(active)
        tests.append(hit)
        gaps.append(d_hat)
        speeds.append(w_hat)
        nrms.append(nrm)
        ws.append(w)
        tois.append(toi_c)
        ims_list.append(inv_mass_sum)
    if flags is None:
        inputs = ImpulseInputs(_delassus(cl, nrms, m), ws, actives, tests, ims_list, e)
        lams = (impulses or direct_impulses)(inputs)
        if impulses not in (None, direct_impulses):
            tests = [lam > 0 for lam in lams]
    dv: list[Any] = [0] * n
    dp: list[Any] = [0] * n
    for c, lam, nrm, toi_c in zip(cl, lams, nrms, tois, strict=True):
        i, j = c.i, c.j
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


def _delassus(cl: list[ph.Contact], nrms: list[Any], m: list[float]) -> list[list[Any]]:
    """``W = J M^-1 J^T`` of the contacts with normals ``nrms``: ``W_cd = k_cd n_c . n_d``
    with ``k_cd`` the sum of ``s_ck s_dk / m_k`` over the discs ``k`` of both contacts
    (``s = +1`` on disc ``i``, ``-1`` on disc ``j``)."""

    def incidence(c: ph.Contact) -> dict[int, float]:
        return {c.i: 1.0} if c.j is None else {c.i: 1.0, c.j: -1.0}

    inc = [incidence(c) for c in cl]
    C = len(cl)
    W: list[list[Any]] = [[0.0] * C for _ in range(C)]
    for c in range(C):
        for d in range(c, C):
            k = sum(sc * inc[d][disc] / m[disc] for disc, sc in inc[c].items() if disc in inc[d])
            if k != 0.0:
                W[c][d] = W[d][c] = k * ca.dot(nrms[c], nrms[d])
    return W


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
    scene: Any,
    contact: str | ContactModel = "direct",
    toi: str = "both",
    integrator: str = "symplectic-euler",
) -> ca.Function:
    """The discrete step ``s_next = step(s, u)`` of a scene as a CasADi ``Function``.

    Parameters
    ----------
    scene
        A :class:`~hybridoc.problems.Scene`, a built-in name or a TOML path.
    contact
        Any registered contact model (:data:`hybridoc.solvers.contacts.CONTACT_MODELS`), by
        name (also as ``"lcp/both"``) or as an instance (then ``toi`` is the instance's).
    toi
        Time-of-impact correction of the impulse models: ``"none"``, ``"position"``,
        ``"velocity"`` or ``"both"``; ignored by the others.
    integrator
        ``"symplectic-euler"`` (default, the paper's) or ``"exact"`` (impulse models with
        ``toi="both"``).

    Returns
    -------
    casadi.Function
        ``Function('step', [s, u], [s_next])`` with ``SX`` inside, equal to one step of
        :class:`hybridoc.solvers.simulator.Simulator` with the same settings.

    Raises
    ------
    SceneError
        An unknown model or setting, or a combination without a CasADi form (one line that
        says why, from :meth:`~hybridoc.solvers.contacts.ContactModel.casadi_unsupported`).
    """
    from hybridoc.problem import disc_scene
    from hybridoc.solvers.contacts import contact_model

    scene = disc_scene(scene)
    model = contact if isinstance(contact, ContactModel) else contact_model(contact, toi=toi)
    s = ca.SX.sym("s", 4 * scene.n_discs)
    u = ca.SX.sym("u", scene.n_controls)
    s_next = model.casadi_step(scene, s, u, integrator)  # raises the model's reason, if any
    return ca.Function("step", [s, u], [s_next], ["s", "u"], ["s_next"])
