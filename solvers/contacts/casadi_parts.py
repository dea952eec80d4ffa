"""The CasADi pieces of the contact models' steps: the impulse models' shared step
(:func:`step_parts`), the exact LCP by enumeration of active sets (:func:`enumerated_lcp`)
and the per-disc kinematics of a state (:func:`disc_kinematics`).

The impulse models (``direct``, ``lcp``, ``convex``) share :func:`step_parts`: the
symplectic-Euler (or exact-flow) prediction, contact detection and the time-of-impact
corrections, with the model's impulse solver in between (:class:`ImpulseInputs`).
``lcp`` and ``convex`` solve a linear complementarity problem with a positive definite
matrix, whose solution is unique: :func:`enumerated_lcp` writes it exactly as a choice among
the solutions on every candidate active set, which limits them to
:data:`MAX_ENUMERATED_CONTACTS` potential contacts. :func:`step_parts` also gives the contact
tests, gaps and normal speeds, and with frozen contact branches the smooth ``direct`` step
that :mod:`hybridoc.solvers.discrete_transcription` optimises over.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import casadi as ca
import numpy as np

from hybridoc.errors import SceneError
from hybridoc.problems import physics as ph
from hybridoc.problems.compile import disc_accelerations
from hybridoc.solvers.contacts.base import INTEGRATORS, SIGN_TOLERANCE, TOI_MODES, contact_model

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.problems import Scene
    from hybridoc.solvers.contacts.impulse import ImpulseModel

__all__ = [
    "ImpulseInputs",
    "MAX_ENUMERATED_CONTACTS",
    "NEWTON_ITERATIONS",
    "StepParts",
    "disc_kinematics",
    "enumerated_lcp",
    "enumeration_unsupported",
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


def disc_kinematics(scene: Scene, s: Any, u: Any) -> tuple[list[Any], list[Any], list[Any]]:
    """Per-disc positions, velocities and accelerations ``u / m`` (2-vectors) of a state.

    Parameters
    ----------
    scene : Scene
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
    return p, v, disc_accelerations(scene, u)


def enumeration_unsupported(label: str, scene: Scene) -> str | None:
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

    The CasADi form of :func:`hybridoc.solvers.contacts.lcp.solve_lcp` (``M = W``) and of
    :func:`hybridoc.solvers.contacts.convex.solve_convex` (``M = H``, the regularised matrix): for a
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
    scene: Scene,
    s: Any,
    u: Any,
    model: ImpulseModel | str = "direct",
    integrator: str = "symplectic-euler",
    flags: Any = None,
) -> StepParts:
    """One impulse-model step with its contact tests, optionally with frozen branches.

    Contacts are in the simulator's order: disc pairs (``i < j``, scene order), then
    disc-wall (disc-major).

    Parameters
    ----------
    scene : Scene
        The disc scene.
    s, u
        State ``(nx,)`` and control ``(nu,)`` symbols (``SX`` or ``MX``).
    model : ImpulseModel or str
        The impulse model, with its time-of-impact setting (its ``toi``) and its impulse
        solver (its ``casadi_impulses``). A string is parsed by
        :func:`~hybridoc.solvers.contacts.base.contact_model`; a bare time-of-impact setting
        (``"both"``) means the ``direct`` model with it.
    integrator : str
        ``"symplectic-euler"`` or ``"exact"`` (needs ``toi="both"`` and no ``flags``), as in
        the simulator.
    flags
        ``None`` (default): the true step, each contact's impulse applied where its test holds
        (``if_else``). Otherwise one 0/1 per contact fixing the branches of the ``direct``
        impulses: the impulse is applied where the flag is 1, with the smooth, unclamped time
        of impact ``d^ / w^``; the step is then smooth in ``(s, u)``.

    Returns
    -------
    StepParts
        The next state, the true branch tests (``direct``: detected and approaching; other
        solvers: a positive impulse), and the gaps ``d^`` and normal speeds ``w^``.
    """
    if isinstance(model, str):
        model = contact_model("direct", toi=model) if model in TOI_MODES else contact_model(model)
    if not model.impulse_based:
        raise SceneError(f"step_parts needs an impulse model, not {model.label}")
    if integrator not in INTEGRATORS:
        raise SceneError(f"unknown integrator {integrator!r}; choose symplectic-euler or exact")
    exact = integrator == "exact"
    if exact and model.toi != "both":
        raise SceneError("integrator 'exact' needs toi='both'")
    if exact and flags is not None:
        raise SceneError("frozen contact flags need integrator 'symplectic-euler'")
    if flags is not None and not model.per_contact:
        raise SceneError("frozen contact flags need the direct impulses")
    n, m = scene.n_discs, [d.mass for d in scene.discs]
    p, v, a = disc_kinematics(scene, s, u)
    dt = scene.dt
    v_hat = [v[i] + a[i] * dt for i in range(n)]
    if exact:
        p_hat = [p[i] + (v[i] + 0.5 * a[i] * dt) * dt for i in range(n)]
    else:
        p_hat = [p[i] + v_hat[i] * dt for i in range(n)]
    cl = ph.contacts(n, len(scene.walls))
    kin = (p, v, a, p_hat, v_hat)
    cs = [
        _contact(scene, c, kin, model.toi, exact, None if flags is None else flags[k])
        for k, c in enumerate(cl)
    ]
    tests = [c.hit for c in cs]
    if flags is None:
        inputs = ImpulseInputs(
            _delassus(cl, [c.nrm for c in cs], m), [c.w for c in cs], [c.active for c in cs],
            tests, [c.inv_mass_sum for c in cs], scene.restitution,
        )  # fmt: skip
        lams = model.casadi_impulses(inputs)
        if not model.per_contact:
            tests = [lam > 0 for lam in lams]
    else:
        lams = [flags[k] * ph.impulse(c.w, c.inv_mass_sum, scene.restitution)
                for k, c in enumerate(cs)]  # fmt: skip
    use_pos = exact or model.toi in ("position", "both")
    dp, dv = _impulse_changes(cl, cs, lams, m, use_pos)
    p_next = [p_hat[i] + dp[i] for i in range(n)]
    v_next = [v_hat[i] + dv[i] for i in range(n)]
    return StepParts(
        ca.vertcat(*p_next, *v_next), ca.vertcat(*tests),
        ca.vertcat(*[c.gap for c in cs]), ca.vertcat(*[c.speed for c in cs]),
    )  # fmt: skip


def _impulse_changes(
    cl: list[ph.Contact], cs: list[_Contact], lams: list[Any], m: list[float], use_pos: bool
) -> tuple[list[Any], list[Any]]:
    """Per disc, the position correction ``sum_c toi_c dv_c`` (with ``use_pos``) and the
    velocity change ``sum_c dv_c`` of the impulses ``lams``."""
    dv: list[Any] = [0] * len(m)
    dp: list[Any] = [0] * len(m)
    for c, lam, cc in zip(cl, lams, cs, strict=True):
        for disc, sign in ((c.i, 1.0), (c.j, -1.0)):
            if disc is None:
                continue
            dvi = sign * lam / m[disc] * cc.nrm
            dv[disc] = dv[disc] + dvi
            if use_pos:
                dp[disc] = dp[disc] + cc.toi * dvi
    return dp, dv


class _Contact(NamedTuple):
    """One contact of a step: its tests, its impulse state and its time of impact."""

    active: Any
    hit: Any
    gap: Any
    speed: Any
    nrm: Any
    w: Any
    toi: Any
    inv_mass_sum: float


def _gap_normal(scene: Scene, r: Any, c: ph.Contact) -> tuple[Any, Any]:
    """Gap and unit normal of contact ``c`` at relative position ``r``."""
    if c.j is not None:
        R = scene.discs[c.i].radius + scene.discs[c.j].radius
        return ph.pair_gap(r, R, ph.CASADI)
    assert c.wall is not None
    wall = scene.walls[c.wall]
    nw = ca.DM(wall.normal)
    return ph.wall_gap(r, ca.DM(wall.point), nw, scene.discs[c.i].radius, ph.CASADI), nw


def _refined_tau(scene: Scene, c: ph.Contact, rels: tuple[Any, ...], tau0: Any, active: Any) -> Any:
    """The exact integrator's contact time: Newton on the gap along the exact flow."""
    rp, rv, ra = rels
    dt = scene.dt
    if c.is_pair:
        R = scene.discs[c.i].radius + scene.discs[c.j].radius  # type: ignore[index]
        return ph.refine_impact_time(
            rp, rv, ra, tau0, active, dt, ph.CASADI, R=R, iterations=NEWTON_ITERATIONS
        )
    assert c.wall is not None
    wall = scene.walls[c.wall]
    off = float(np.dot(wall.point, wall.normal)) + scene.discs[c.i].radius
    return ph.refine_impact_time(
        rp, rv, ra, tau0, active, dt, ph.CASADI, normal=ca.DM(wall.normal), offset=off,
        iterations=NEWTON_ITERATIONS,
    )  # fmt: skip


def _contact(
    scene: Scene, c: ph.Contact, kin: tuple[list[Any], ...], toi: str, exact: bool, flag: Any
) -> _Contact:
    """Detection, time of impact and impulse state of contact ``c`` (``flag``: frozen)."""
    ops, dt = ph.CASADI, scene.dt

    def rel(x: list[Any]) -> Any:
        return x[c.i] - x[c.j] if c.j is not None else x[c.i]

    rp, rv, ra, rp_hat, rv_hat = (rel(x) for x in kin)
    use_bar = toi in ("velocity", "both")

    def at_impact(toi_c: Any) -> tuple[Any, Any]:
        # normal and normal speed at the time of impact (the velocity correction)
        tau = dt - toi_c
        _, nrm = _gap_normal(scene, rp + tau * rv_hat, c)
        return nrm, ph.normal_speed(rv + tau * ra, nrm, ops)

    d_hat, n_hat = _gap_normal(scene, rp_hat, c)
    w_hat = ph.normal_speed(rv_hat, n_hat, ops)
    active = ca.logic_and(d_hat < 0, w_hat < 0)
    toi_c = ph.toi_linear(d_hat, w_hat, dt, active, ops)
    if exact:
        tau = _refined_tau(scene, c, (rp, rv, ra), dt - toi_c, active)
        toi_c = ca.if_else(active, dt - tau, 0.0)
        _, nrm = _gap_normal(scene, rp + (rv + 0.5 * ra * tau) * tau, c)
        w = ph.normal_speed(rv + ra * tau, nrm, ops)
    elif use_bar:
        nrm, w = at_impact(toi_c)
    else:
        nrm, w = n_hat, w_hat
    hit = ca.logic_and(active, w < 0)
    m = scene.discs
    inv_mass_sum = 1.0 / m[c.i].mass + (1.0 / m[c.j].mass if c.j is not None else 0.0)
    if flag is not None:
        # frozen: the time of impact of an applied contact is d^ / w^ (unclamped, smooth)
        w_frozen = ca.if_else(flag > 0.5, w_hat, -1.0)
        toi_c = flag * d_hat / w_frozen
        if use_bar:
            nrm, w = at_impact(toi_c)
    return _Contact(active, hit, d_hat, w_hat, nrm, w, toi_c, inv_mass_sum)


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
