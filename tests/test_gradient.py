"""The adjoint gradient against central finite differences, and the HMP jump conditions."""

from __future__ import annotations

import dataclasses
from functools import partial

import numpy as np
import pytest

import hybridoc
from hybridoc import Disc, HybridOCP, Scene, load_scene


def controls_for(scene: Scene, seed: int | None) -> np.ndarray:
    u = scene.initial_controls()
    if seed is None:
        return u
    rng = np.random.default_rng(seed)
    return u + 0.5 * rng.standard_normal(u.shape)


def event_signature(ev: hybridoc.Evaluation) -> list[tuple[tuple[str, ...], int]]:
    """The event sequence and the grid interval of each event.

    The cost is smooth only while both stay the same: when an event time crosses a grid
    time the control acting before the impact changes, and the cost has a kink in its second
    derivative there (C1, not C2), which spoils finite differences that straddle it.
    """
    intervals = [seg.interval for seg in ev.segments if seg.event is not None]
    return [(e.bodies, k) for e, k in zip(ev.events, intervals, strict=True)]


def richardson(cost_at, step: float) -> float:
    """Central difference with Richardson extrapolation (steps h and h/2, error O(h^4)).

    Larger steps than a plain central difference keep the rounding noise of the cost
    (about 1e-13 here: positions near 1 are advanced over hundreds of intervals) small.
    """

    def central(h: float) -> float:
        return (cost_at(h) - cost_at(-h)) / (2 * h)

    return (4 * central(step / 2) - central(step)) / 3


def fd_initial_state(ocp: HybridOCP, u: np.ndarray, step: float) -> np.ndarray:
    """Finite differences of the cost in each initial-state component."""
    probe = dataclasses.replace(ocp)  # a private copy whose x0 we may change
    base = event_signature(hybridoc.evaluate(ocp, u))

    def cost_at(k: int, d: float) -> float:
        probe.x0 = ocp.x0.copy()
        probe.x0[k] += d
        ev = hybridoc.evaluate(probe, u)
        assert event_signature(ev) == base, "the step crosses a change of the event sequence"
        return ev.cost

    return np.array([richardson(partial(cost_at, k), step) for k in range(ocp.nx)])


def fd_controls(ocp: HybridOCP, u: np.ndarray, entries: list[tuple[int, int]], step: float):
    base = event_signature(hybridoc.evaluate(ocp, u))

    def cost_at(n: int, j: int, d: float) -> float:
        up = u.copy()
        up[n, j] += d
        ev = hybridoc.evaluate(ocp, up)
        assert event_signature(ev) == base, "the step crosses a change of the event sequence"
        return ev.cost

    return np.array([richardson(partial(cost_at, n, j), step) for n, j in entries])


def assert_close(exact: np.ndarray, fd: np.ndarray, rel: float, step: float) -> None:
    """``|exact - fd| <= rel |exact| + noise``, noise = 1e-12 / step: what a cost rounding error
    of 1e-12 does to a difference quotient (tiny entries cannot be checked any closer)."""
    noise = 1e-12 / step
    err = np.abs(exact - fd) - rel * np.abs(exact)
    assert np.all(err <= noise), (
        f"max excess error {np.max(err):.2e} over the allowed noise {noise:.1e}\n{exact}\n{fd}"
    )


def sample_entries(ev: hybridoc.Evaluation, nu: int, seed: int) -> list[tuple[int, int]]:
    """Control entries: all components of the intervals with events, the first and the last
    interval, and a few random ones."""
    N = ev.controls.shape[0]
    rng = np.random.default_rng(seed)
    rows = {0, N - 1, *rng.choice(N, size=4, replace=False).tolist()}
    rows |= {seg.interval for seg in ev.segments if seg.event is not None}
    return [(n, j) for n in sorted(rows) for j in range(nu)]


CASES = [(name, seed) for name in hybridoc.builtin_names() for seed in (None, 1)]


@pytest.mark.parametrize(("name", "seed"), CASES)
def test_gradient_matches_finite_differences(name, seed):
    sc = load_scene(name)
    ocp = sc.to_ocp()
    u = controls_for(sc, seed)
    g = hybridoc.gradient(ocp, u)
    ev = g.evaluation
    assert ev.events, "the case must contain events"
    assert g.cost == ev.cost == hybridoc.evaluate(ocp, u).cost
    assert_close(g.d_initial_state, fd_initial_state(ocp, u, 1e-4), 1e-7, 1e-4)
    entries = sample_entries(ev, ocp.nu, seed=0 if seed is None else seed)
    exact = np.array([g.d_controls[n, j] for n, j in entries])
    assert_close(exact, fd_controls(ocp, u, entries, 1e-2), 1e-7, 1e-2)


def test_gradient_with_inelastic_oblique_impact_and_events_in_one_interval():
    sc = Scene(
        horizon=1.0,
        steps=4,
        restitution=0.5,
        discs=(
            Disc(
                "a",
                (0.0, 0.0),
                0.2,
                velocity=(1.0, 0.05),
                mass=1.5,
                actuated=True,
                initial_control=(0.3, 0.2),
            ),
            Disc("b", (0.5, 0.02), 0.2, mass=0.8),
            Disc("c", (1.0, -0.05), 0.2, target=(2.0, 0.5)),
        ),
    )
    ocp = sc.to_ocp()
    g = hybridoc.gradient(sc)
    ev = g.evaluation
    ev_intervals = [seg.interval for seg in ev.segments if seg.event is not None]
    assert len(ev_intervals) >= 2 and len(set(ev_intervals)) < len(ev_intervals)
    assert_close(g.d_initial_state, fd_initial_state(ocp, sc.initial_controls(), 1e-4), 1e-7, 1e-4)
    entries = [(n, j) for n in range(sc.steps) for j in range(2)]
    exact = np.array([g.d_controls[n, j] for n, j in entries])
    assert_close(exact, fd_controls(ocp, sc.initial_controls(), entries, 1e-2), 1e-7, 1e-2)


def disc_flow(scene: Scene, s: np.ndarray, u: np.ndarray) -> np.ndarray:
    """f(s, u) = (v, B u / m) written out here, independently of the compiled model."""
    n = scene.n_discs
    acc = np.zeros((n, 2))
    for k, i in enumerate(scene.actuated_indices):
        acc[i] = u[2 * k : 2 * k + 2] / scene.discs[i].mass
    return np.concatenate([s[2 * n :], acc.ravel()])


def guard_gradient(scene: Scene, e: hybridoc.Event) -> np.ndarray:
    """grad psi at s(gamma-) for a disc-disc or disc-wall guard, by hand."""
    n = scene.n_discs
    names = [d.name for d in scene.discs]
    p = e.state_before[: 2 * n].reshape(n, 2)
    out = np.zeros(4 * n)
    i = names.index(e.bodies[0])
    if e.kind == "disc-disc":
        j = names.index(e.bodies[1])
        nrm = (p[i] - p[j]) / np.linalg.norm(p[i] - p[j])
        out[2 * i : 2 * i + 2] = nrm
        out[2 * j : 2 * j + 2] = -nrm
    else:
        out[2 * i : 2 * i + 2] = next(w.normal for w in scene.walls if w.name == e.bodies[1])
    return out


@pytest.mark.parametrize(
    ("name", "seed"), [("multiple-collision", None), ("three-disc-chain", 2), ("damped-walls", 1)]
)
def test_costate_jump_conditions(name, seed):
    sc = load_scene(name)
    u_all = controls_for(sc, seed)
    g = hybridoc.gradient(sc, u_all)
    ev = g.evaluation
    eps = sc.control_weight
    nx = 4 * sc.n_discs
    for e in ev.events:
        k = np.flatnonzero(g.costate_times == e.time)
        assert len(k) == 2, "lambda(gamma-) and lambda(gamma+) are both recorded"
        lam_minus, lam_plus = g.costates[k[0]], g.costates[k[1]]
        u = u_all[min(int(e.time / sc.dt), sc.steps - 1)]
        L = eps * u @ u
        H_minus = L + lam_minus @ disc_flow(sc, e.state_before, u)
        H_plus = L + lam_plus @ disc_flow(sc, e.state_after, u)
        assert H_minus == pytest.approx(H_plus, abs=1e-12 * (1 + abs(H_plus)))
        # lambda(gamma-) - Dg^T lambda(gamma+) is a multiple of grad psi; Dg by differences
        reset = sc.to_ocp().guards[e.guard].reset
        Dg = np.empty((nx, nx))
        for c in range(nx):
            d = np.zeros(nx)
            d[c] = 1e-6
            Dg[:, c] = (
                np.asarray(reset(e.state_before + d)).ravel()
                - np.asarray(reset(e.state_before - d)).ravel()
            ) / 2e-6
        r = lam_minus - Dg.T @ lam_plus
        n_hat = guard_gradient(sc, e)
        n_hat /= np.linalg.norm(n_hat)
        assert np.linalg.norm(r - (r @ n_hat) * n_hat) < 1e-7 * (1 + np.linalg.norm(lam_plus))


@pytest.mark.parametrize("name", hybridoc.builtin_names())
def test_costate_ends_and_free_flight(name):
    sc = load_scene(name)
    g = hybridoc.gradient(sc)
    n = sc.n_discs
    np.testing.assert_array_equal(g.d_initial_state, g.costates[0])
    assert g.costate_times[0] == 0.0 and g.costate_times[-1] == sc.horizon
    assert np.all(np.diff(g.costate_times) >= 0)
    # transversality: lambda(T) = grad phi = 2 (p_i(T) - target_i) for discs with a target
    grad_phi = np.zeros(4 * n)
    pT = g.evaluation.final_state[: 2 * n].reshape(n, 2)
    for i, d in enumerate(sc.discs):
        if d.target is not None:
            grad_phi[2 * i : 2 * i + 2] = 2 * (pT[i] - np.array(d.target))
    np.testing.assert_allclose(g.costates[-1], grad_phi, rtol=1e-15, atol=1e-15)
    # between events: lambda_p constant, lambda_v(t) = lambda_v(t') + lambda_p (t' - t)
    for a in range(len(g.costate_times) - 1):
        t0, t1 = g.costate_times[a], g.costate_times[a + 1]
        if t0 == t1:
            continue  # an event: a jump
        l0, l1 = g.costates[a], g.costates[a + 1]
        np.testing.assert_allclose(l0[: 2 * n], l1[: 2 * n], rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(
            l0[2 * n :], l1[2 * n :] + l1[: 2 * n] * (t1 - t0), rtol=1e-12, atol=1e-13
        )


def test_control_gradient_is_the_integral_of_dH_du():
    """Without events dJ/du_n = int_n (2 eps u + B^T lambda_v / m) dt, with lambda_v linear."""
    sc = load_scene("head-on")
    u = sc.initial_controls() * 0.1  # too weak to reach the target disc: no event
    g = hybridoc.gradient(sc, u)
    assert g.evaluation.events == []
    lam_v = g.costates[:, 4:6]  # striker's velocity costate at the grid points
    mid = 0.5 * (lam_v[:-1] + lam_v[1:])  # exact mean of a linear function
    expected = (2 * sc.control_weight * u + mid) * sc.dt
    np.testing.assert_allclose(g.d_controls, expected, rtol=1e-12, atol=1e-15)
