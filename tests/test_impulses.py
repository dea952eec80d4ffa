"""Tests of the impulse models' torch impulse solves (``ImpulseModel.impulses`` of ``direct``,
``lcp`` and ``convex``, each in its own module of hybridoc.solvers.contacts)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from hybridoc.errors import EvaluationError, HybridocError
from hybridoc.solvers.contacts import CONTACT_MODELS, contact_model
from hybridoc.solvers.contacts.convex import solve_convex
from hybridoc.solvers.contacts.lcp_solver import prepare_impulses

F64 = torch.float64

IMPULSE_METHODS = ("direct", "lcp", "convex")
"""The built-in impulse models."""


def solve_impulses(method, W, w, active, restitution):
    """The impulses of the model called ``method`` (its ``impulses`` method)."""
    return contact_model(method).impulses(W, w, active, restitution)


def test_the_impulse_models_are_registered():
    assert all(CONTACT_MODELS[name].impulse_based for name in IMPULSE_METHODS)


def contact_system(positions, velocities, masses, pairs):
    """Delassus matrix, pre-impact normal velocities and Jacobian of disc-disc contacts.

    Row ``c`` of ``J`` for pair (i, j) with ``n = (p_i - p_j) / |p_i - p_j|`` is ``+n`` on disc i
    and ``-n`` on disc j, so that ``J v`` is the separating speed.
    """
    p = torch.as_tensor(positions, dtype=F64)
    v = torch.as_tensor(velocities, dtype=F64).reshape(-1)
    m = torch.as_tensor(masses, dtype=F64)
    n_discs = p.shape[0]
    J = torch.zeros(len(pairs), 2 * n_discs, dtype=F64)
    for c, (i, j) in enumerate(pairs):
        n = (p[i] - p[j]) / (p[i] - p[j]).norm()
        J[c, 2 * i : 2 * i + 2] = n
        J[c, 2 * j : 2 * j + 2] = -n
    minv = torch.repeat_interleave(1.0 / m, 2)
    W = (J * minv) @ J.T
    return W[None], (J @ v)[None], J, minv, v


def apply(J, minv, v, lam):
    return v + minv * (J.T @ lam[0])


def brute_force_lcp(W, q, active):
    """All solutions of LCP(W, q) on the active contacts, by enumeration of the active sets."""
    C = len(q)
    idx = np.flatnonzero(active)
    sols = []
    for r in range(len(idx) + 1):
        for S in itertools.combinations(idx, r):
            lam = np.zeros(C)
            S = list(S)
            if S:
                lam[S] = np.linalg.solve(W[np.ix_(S, S)], -q[S])
            mu = q + W @ lam
            if (lam >= -1e-12).all() and (mu[active] >= -1e-12).all():
                sols.append(lam)
    return sols


@pytest.mark.parametrize("method", IMPULSE_METHODS)
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_single_contact_closed_form(method, e):
    m1, m2 = 1.3, 0.7
    W, w, J, minv, v = contact_system(
        [[0.0, 0.0], [0.3, 0.4]], [[1.0, 2.0], [-0.5, 0.1]], [m1, m2], [(1, 0)]
    )
    active = torch.ones(1, 1, dtype=torch.bool)
    lam = solve_impulses(method, W, w, active, e)
    # closed form of DESIGN.md section 1
    expected = -(1 + e) * w[0, 0] / (1 / m1 + 1 / m2)
    assert w[0, 0] < 0
    tol = 1e-8 if method == "convex" else 1e-13
    assert lam[0, 0].item() == pytest.approx(expected.item(), rel=tol)
    w_plus = J @ apply(J, minv, v, lam)
    assert w_plus[0].item() == pytest.approx(-e * w[0, 0].item(), abs=1e-8 * abs(w[0, 0].item()))


def v_configuration():
    """Disc 0 falls onto discs 1 and 2, which touch each other and disc 0 (60 degree V)."""
    r = 0.2
    positions = [[0.0, 2 * r * math.sqrt(3.0) / 2], [-r, 0.0], [r, 0.0]]
    velocities = [[0.0, -1.0], [0.0, 0.0], [0.0, 0.0]]
    return contact_system(positions, velocities, [1.0, 1.0, 1.0], [(0, 1), (0, 2), (1, 2)])


def newton_cradle():
    """Three touching discs in a row; the first moves into the other two at unit speed."""
    return contact_system(
        [[0.0, 0.0], [0.4, 0.0], [0.8, 0.0]],
        [[1.0, 0.0], [0.0, 0.0], [0.0, 0.0]],
        [1.0, 1.0, 1.0],
        [(1, 0), (2, 1)],
    )


@pytest.mark.parametrize("method", ["lcp", "convex"])
@pytest.mark.parametrize("case", [v_configuration, newton_cradle])
@pytest.mark.parametrize("e", [0.0, 0.6, 1.0])
def test_simultaneous_contacts_physics(method, case, e):
    W, w, J, minv, v = case()
    active = torch.ones_like(w, dtype=torch.bool)
    lam = solve_impulses(method, W, w, active, e)
    v_plus = apply(J, minv, v, lam)
    w_plus = J @ v_plus
    tol = 1e-7 if method == "convex" else 1e-12
    # complementarity with Newton's restitution law
    slack = w_plus + e * w[0]
    assert (lam >= 0).all()
    assert (slack >= -tol).all()
    assert (lam[0] * slack).abs().max() < tol
    # momentum (unit masses): sum of velocities unchanged
    assert torch.allclose(v_plus.reshape(-1, 2).sum(0), v.reshape(-1, 2).sum(0), atol=1e-12)
    # energy: dKE = lambda^T (w- + w+) / 2 = (1 - e) lambda^T w- / 2 on the active contacts
    ke = lambda vel: 0.5 * (vel**2 / minv).sum()  # noqa: E731
    if e == 1.0:
        assert ke(v_plus).item() == pytest.approx(ke(v).item(), rel=tol)
    else:
        assert ke(v_plus) < ke(v)


def test_newton_cradle_simultaneous_solution():
    # Simultaneous Newton restitution (e = 1) on the cradle: w+ = [1, 0] = J v+ and momentum give
    # v+ = [-1/3, 2/3, 2/3] (not the sequential-collision answer [0, 0, 1]).
    W, w, J, minv, v = newton_cradle()
    active = torch.ones(1, 2, dtype=torch.bool)
    lam = solve_impulses("lcp", W, w, active, 1.0)
    assert torch.allclose(lam, torch.tensor([[4 / 3, 2 / 3]], dtype=F64), atol=1e-14)
    v_plus = apply(J, minv, v, lam).reshape(3, 2)[:, 0]
    assert torch.allclose(v_plus, torch.tensor([-1 / 3, 2 / 3, 2 / 3], dtype=F64), atol=1e-14)
    # direct: only the approaching contact takes an impulse, the plain two-disc exchange
    lam_d = solve_impulses("direct", W, w, active, 1.0)
    assert torch.allclose(lam_d, torch.tensor([[1.0, 0.0]], dtype=F64), atol=1e-14)


def test_direct_is_independent_per_contact_in_v():
    W, w, J, minv, v = v_configuration()
    active = torch.ones(1, 3, dtype=torch.bool)
    lam = solve_impulses("direct", W, w, active, 1.0)
    expected = -2.0 * w[0] / torch.diagonal(W[0])
    expected[2] = 0.0  # discs 1 and 2 are at rest relative to each other
    assert torch.allclose(lam[0], expected, atol=1e-14)
    v_plus = apply(J, minv, v, lam)
    assert torch.allclose(v_plus.reshape(-1, 2).sum(0), v.reshape(-1, 2).sum(0), atol=1e-14)


def random_problems(B, C, seed, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    J = torch.randn(B, C, C + 2, generator=g, dtype=dtype)
    W = J @ J.transpose(1, 2)
    w = torch.randn(B, C, generator=g, dtype=dtype)
    active = torch.rand(B, C, generator=g) < 0.8
    return W, w, active


def test_lcp_matches_enumeration_and_convex():
    W, w, active = random_problems(60, 4, seed=3)
    e = 0.5
    lam = solve_impulses("lcp", W, w, active, e)
    lam_c = solve_convex(W, w, active, prepare_impulses(W, w, active, e), regularization=1e-12)
    for b in range(W.shape[0]):
        sols = brute_force_lcp(W[b].numpy(), (1 + e) * w[b].numpy(), active[b].numpy())
        assert len(sols) == 1  # P-matrix: unique solution
        np.testing.assert_allclose(lam[b].numpy(), sols[0], atol=1e-10)
    assert torch.allclose(lam, lam_c, atol=1e-6 * lam.abs().max())


@pytest.mark.parametrize("method", IMPULSE_METHODS)
def test_gradcheck(method):
    W, w, active = random_problems(4, 4, seed=11)
    W = W.clone().requires_grad_(True)
    w = w.clone().requires_grad_(True)
    e = torch.tensor([0.3, 0.7, 1.0, 0.5], dtype=F64, requires_grad=True)
    lam = solve_impulses(method, W, w, active, e)
    # the sample is away from degenerate points: every active contact is strictly in or out
    assert (lam > 0).any() and ((lam == 0) & active).any()
    assert torch.autograd.gradcheck(
        lambda W, w, e: solve_impulses(method, W, w, active, e), (W, w, e), atol=1e-7, rtol=1e-6
    )


def test_convex_gradient_close_to_lcp_gradient():
    W, w, active = random_problems(5, 3, seed=5)
    grads = []
    for method in ("lcp", "convex"):
        Wr = W.clone().requires_grad_(True)
        wr = w.clone().requires_grad_(True)
        (solve_impulses(method, Wr, wr, active, 0.8) ** 2).sum().backward()
        grads.append((Wr.grad, wr.grad))
    # convex sees only the symmetric part of W: compare along symmetric perturbations
    sym = lambda G: 0.5 * (G + G.transpose(1, 2))  # noqa: E731
    assert torch.allclose(sym(grads[0][0]), sym(grads[1][0]), rtol=1e-5, atol=1e-6)
    assert torch.allclose(grads[0][1], grads[1][1], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("method", IMPULSE_METHODS)
def test_float32_and_batch_shapes(method):
    W, w, active = random_problems(7, 3, seed=2)
    lam64 = solve_impulses(method, W, w, active, 0.9)
    lam32 = solve_impulses(method, W.float(), w.float(), active, 0.9)
    assert lam32.dtype == torch.float32 and lam32.shape == (7, 3)
    assert torch.allclose(lam32.double(), lam64, rtol=1e-3, atol=1e-4 * lam64.abs().max())
    # each batch element solved on its own gives the same answer
    for b in range(7):
        one = solve_impulses(method, W[b : b + 1], w[b : b + 1], active[b : b + 1], 0.9)
        assert torch.allclose(one[0], lam64[b], atol=1e-12)


@pytest.mark.parametrize("method", IMPULSE_METHODS)
def test_inactive_and_separating_contacts_get_zero(method):
    W, w, active = random_problems(6, 4, seed=8)
    w = -w.abs()  # all approaching
    active[:, 1] = False
    lam = solve_impulses(method, W, w, active, 1.0)
    assert (lam[:, 1] == 0).all()
    assert (lam[~active] == 0).all()
    none = solve_impulses(method, W, w, torch.zeros_like(active), 1.0)
    assert (none == 0).all()
    sep = solve_impulses(method, W, w.abs(), torch.ones_like(active), 1.0)
    assert (sep == 0).all()


def test_redundant_contacts_stay_finite():
    # a disc squeezed between two parallel walls: W = [[1, -1], [-1, 1]] is singular
    W = torch.tensor([[[1.0, -1.0], [-1.0, 1.0]]], dtype=F64)
    w = torch.tensor([[-1.0, 1.0]], dtype=F64)
    active = torch.ones(1, 2, dtype=torch.bool)
    for method in IMPULSE_METHODS:
        lam = solve_impulses(method, W, w, active, 1.0)
        assert torch.isfinite(lam).all()
        w_plus = w + (W @ lam[..., None])[..., 0]
        assert torch.allclose(w_plus, torch.tensor([[1.0, -1.0]], dtype=F64), atol=1e-6)


def test_errors():
    W, w, active = random_problems(2, 2, seed=1)
    with pytest.raises(HybridocError, match="unknown contact model"):
        solve_impulses("magic", W, w, active, 1.0)
    bad = w.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(EvaluationError, match="non-finite"):
        solve_impulses("lcp", W, bad, active, 1.0)
    with pytest.raises(EvaluationError, match="shape"):
        solve_impulses("direct", W, w[:, :1], active, 1.0)
