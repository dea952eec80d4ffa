"""Tests of the non-impulse contact models (hybridoc.solvers.penalty)."""

from __future__ import annotations

import pytest
import torch

from hybridoc.errors import HybridocError
from hybridoc.solvers.contacts.compliant import compliant_step, damping_for_restitution
from hybridoc.solvers.contacts.pbd import pbd_step

F64 = torch.float64
DT = 1.0 / 480.0
NO_WALLS = (torch.zeros(0, 2, dtype=F64), torch.zeros(0, 2, dtype=F64))


def run(model, p, v, steps, radii, inv_mass, walls=NO_WALLS, acc=None, e=1.0, **kw):
    acc = torch.zeros_like(p) if acc is None else acc
    traj = [(p, v)]
    for _ in range(steps):
        if model == "compliant":
            p, v = compliant_step(p, v, acc, DT, radii, inv_mass, *walls, **kw)
        else:
            p, v = pbd_step(p, v, acc, DT, radii, inv_mass, *walls, e, **kw)
        traj.append((p, v))
    return traj


def two_discs(v1=2.0, offset=0.0, masses=(1.0, 1.0), angle_y=0.0):
    p = torch.tensor([[[-0.5 - offset * v1 * DT, 0.0], [0.5, angle_y]]], dtype=F64)
    v = torch.tensor([[[v1, 0.0], [0.0, 0.0]]], dtype=F64)
    radii = torch.tensor([0.2, 0.2], dtype=F64)
    inv_mass = 1.0 / torch.tensor(masses, dtype=F64)
    return p, v, radii, inv_mass


@pytest.mark.parametrize("model", ["compliant", "pbd"])
def test_momentum_conserved_in_disc_disc_contact(model):
    p, v, radii, inv_mass = two_discs(masses=(1.0, 3.0), angle_y=0.15)
    m = (1.0 / inv_mass)[None, :, None]
    traj = run(model, p, v, 300, radii, inv_mass)
    mom0 = (m * v).sum(1)
    touched = False
    for pk, vk in traj:
        assert torch.allclose((m * vk).sum(1), mom0, atol=1e-12)
        touched |= bool((pk[0, 0] - pk[0, 1]).norm() < 0.4 + 1e-9)
    assert touched
    # the collision happened and sent disc 2 off at an angle
    assert traj[-1][1][0, 1, 1] > 0.05


@pytest.mark.parametrize("offset", [0.0, 0.3, 0.7])
def test_compliant_head_on_roughly_exchanges_velocities(offset):
    p, v, radii, inv_mass = two_discs(offset=offset)
    pN, vN = run("compliant", p, v, 400, radii, inv_mass)[-1]
    # elastic, equal masses: exchange of velocities up to the step's switch-on error (~1%)
    assert abs(vN[0, 0, 0].item()) < 0.03 * 2.0
    assert vN[0, 1, 0].item() == pytest.approx(2.0, rel=0.03)
    assert torch.allclose(vN[..., 1], torch.zeros(1, 2, dtype=F64), atol=1e-14)


@pytest.mark.parametrize("masses", [(1.0, 1.0), (1.0, 3.0), (2.0, 0.5)])
@pytest.mark.parametrize("e", [1.0, 0.4])
def test_pbd_head_on_matches_impulse_closed_form(masses, e):
    p, v, radii, inv_mass = two_discs(offset=0.37, masses=masses)
    traj = run("pbd", p, v, 400, radii, inv_mass, e=e)
    vN = traj[-1][1][0, :, 0]
    m1, m2 = masses
    w = -2.0  # relative normal speed of disc 2 w.r.t. disc 1 along +x before contact
    J = -(1 + e) * w / (1 / m1 + 1 / m2)
    assert vN[0].item() == pytest.approx(2.0 - J / m1, abs=1e-10)
    assert vN[1].item() == pytest.approx(J / m2, abs=1e-10)
    # no penetration after any step
    for pk, _ in traj:
        assert (pk[0, 1] - pk[0, 0]).norm() >= 0.4 - 1e-12


def test_wall_bounce_restitution():
    wall = (torch.tensor([[0.0, 1.0]], dtype=F64), torch.tensor([[0.0, -1.0]], dtype=F64))
    p = torch.tensor([[[0.0, 0.5]]], dtype=F64)
    v = torch.tensor([[[0.3, 2.0]]], dtype=F64)
    radii, inv_mass = torch.tensor([0.2], dtype=F64), torch.tensor([1.0], dtype=F64)
    e = 0.5
    _, vN = run("pbd", p, v, 200, radii, inv_mass, walls=wall, e=e)[-1]
    assert torch.allclose(vN[0, 0], torch.tensor([0.3, -1.0], dtype=F64), atol=1e-12)
    c = damping_for_restitution(e, 2.0e4, 1.0)
    traj = run("compliant", p, v, 200, radii, inv_mass, walls=wall, damping=c)
    vN = traj[-1][1]
    assert vN[0, 0, 0].item() == pytest.approx(0.3, abs=1e-14)
    # exact for the continuous clamped spring-damper; the step adds O(sqrt(k/m) dt) = 0.3
    assert vN[0, 0, 1].item() == pytest.approx(-1.0, rel=0.1)
    deepest = max(pk[0, 0, 1].item() for pk, _ in traj)
    assert 0.8 < deepest < 0.82  # penetrates, but by less than 1/10 of the radius


@pytest.mark.parametrize("model", ["compliant", "pbd"])
def test_no_contact_is_plain_symplectic_euler(model):
    g = torch.Generator().manual_seed(0)
    p = torch.tensor([[[-1.0, 0.0], [1.0, 0.0]], [[0.0, -1.0], [0.0, 1.0]]], dtype=F64)
    v = 0.1 * torch.randn(2, 2, 2, generator=g, dtype=F64)
    acc = torch.randn(2, 2, 2, generator=g, dtype=F64)
    radii, inv_mass = torch.tensor([0.2, 0.3], dtype=F64), torch.tensor([1.0, 0.5], dtype=F64)
    walls = (torch.tensor([[0.0, 3.0]], dtype=F64), torch.tensor([[0.0, -1.0]], dtype=F64))
    if model == "compliant":
        p1, v1 = compliant_step(p, v, acc, DT, radii, inv_mass, *walls)
    else:
        p1, v1 = pbd_step(p, v, acc, DT, radii, inv_mass, *walls, 1.0)
    v_ref = v + acc * DT
    p_ref = p + v_ref * DT
    assert torch.allclose(v1, v_ref, rtol=0, atol=1e-15)
    assert torch.allclose(p1, p_ref, rtol=0, atol=1e-15)


@pytest.mark.parametrize("model", ["compliant", "pbd"])
def test_gradcheck_small_case(model):
    # two discs overlapping each other and one disc overlapping the wall: every branch active
    p = torch.tensor([[[0.0, 0.0], [0.35, 0.1]], [[0.0, 0.79], [1.0, 0.0]]], dtype=F64)
    v = torch.tensor([[[1.0, 0.2], [-0.5, 0.0]], [[0.1, 1.5], [0.0, 0.0]]], dtype=F64)
    acc = torch.tensor([[[0.3, -0.2], [0.0, 0.1]], [[0.0, 2.0], [0.5, 0.0]]], dtype=F64)
    radii = torch.tensor([0.2, 0.21], dtype=F64)
    inv_mass = torch.tensor([1.0, 0.6], dtype=F64)
    wp = torch.tensor([[0.0, 1.0]], dtype=F64)
    wn = torch.tensor([[0.0, -1.0]], dtype=F64)
    inputs = [x.clone().requires_grad_(True) for x in (p, v, acc, radii, inv_mass)]
    if model == "compliant":

        def f(p, v, acc, radii, inv_mass):
            return compliant_step(p, v, acc, DT, radii, inv_mass, wp, wn, damping=3.0)

    else:

        def f(p, v, acc, radii, inv_mass):
            return pbd_step(p, v, acc, DT, radii, inv_mass, wp, wn, 0.8, iterations=3)

    assert torch.autograd.gradcheck(f, inputs, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("model", ["compliant", "pbd"])
def test_float32_and_batch(model):
    p, v, radii, inv_mass = two_discs(offset=0.2)
    p = p.expand(3, -1, -1).clone()
    v = v.expand(3, -1, -1) * torch.tensor([1.0, 1.5, 0.5], dtype=F64)[:, None, None]
    p64, v64 = run(model, p, v, 300, radii, inv_mass)[-1]
    p32, v32 = run(model, p.float(), v.float(), 300, radii.float(), inv_mass.float())[-1]
    assert p32.dtype == torch.float32 and p32.shape == (3, 2, 2)
    assert torch.allclose(v32.double(), v64, atol=2e-3)
    # each batch element on its own gives the same answer
    _, v1 = run(model, p[1:2], v[1:2], 300, radii, inv_mass)[-1]
    assert torch.allclose(v1[0], v64[1], atol=1e-13)


def test_input_errors():
    p, v, radii, inv_mass = two_discs()
    with pytest.raises(HybridocError, match="shape"):
        compliant_step(p[0], v[0], v[0], DT, radii, inv_mass, *NO_WALLS)
    with pytest.raises(HybridocError, match="radii"):
        pbd_step(p, v, torch.zeros_like(p), DT, radii[:1], inv_mass, *NO_WALLS, 1.0)
    with pytest.raises(HybridocError, match="iteration"):
        pbd_step(p, v, torch.zeros_like(p), DT, radii, inv_mass, *NO_WALLS, 1.0, iterations=0)
    with pytest.raises(HybridocError, match="restitution"):
        damping_for_restitution(0.0, 1e4, 1.0)


@pytest.mark.parametrize("e", [0.15, 0.4, 0.9])
def test_damping_for_restitution_against_ode(e):
    from scipy.integrate import solve_ivp

    k, m = 3.0e4, 0.7
    c = damping_for_restitution(e, k, m)

    def force(t, y):  # x = penetration depth, contact ends when k x + c x' = 0
        return y[0] * k + c * y[1]

    force.terminal, force.direction = True, -1
    sol = solve_ivp(
        lambda t, y: [y[1], -(k * y[0] + c * y[1]) / m],
        [0.0, 1.0],
        [0.0, 1.0],
        events=force,
        rtol=1e-11,
        atol=1e-13,
    )
    assert -sol.y_events[0][0][1] == pytest.approx(e, rel=1e-7)
