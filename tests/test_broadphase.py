"""The judge's broad phase (hybridoc.broadphase, issue #32): conservative boxes, sweep and
prune against all pairs, and the judge through it against the all-pairs judge.

The broad phase samples only the guards whose bodies' swept boxes come near each other, with
per-guard kernels whose values are those of the all-pairs kernels' rows bit for bit
(:func:`test_guard_kernels_are_the_rows_of_the_all_pairs_kernels`). The crossing search then
runs on fewer guards, and it halves a window for every guard whenever one guard needs it, so
a root can be polished from another bracket: an event time may differ in its last bit, and
later collisions amplify that as any perturbation (seen up to 5e-14 relative in the cost),
never the events themselves. The tests allow 1e-12.
"""

from __future__ import annotations

import functools
import math
import weakref
from typing import Any

import numpy as np
import pytest
from conftest import examples
from hypothesis import given, settings
from hypothesis import strategies as st
from scaling import transform

import hybridoc
from hybridoc import Disc, Scene, Wall, broadphase
from hybridoc import kernels as kmod
from hybridoc.capabilities import Capabilities
from hybridoc.errors import HybridocError

pytestmark = pytest.mark.usefixtures("virtual_machine")


# ------------------------------------------------------------------ boxes and pairs


def _brute(lo: np.ndarray, hi: np.ndarray) -> list[tuple[int, int]]:
    n = len(lo)
    return [
        (i, j)
        for i in range(n)
        for j in range(i + 1, n)
        if (lo[i] <= hi[j]).all() and (lo[j] <= hi[i]).all()
    ]


@settings(max_examples=examples(60), deadline=None)
@given(st.integers(0, 40), st.integers(0, 2**32 - 1), st.booleans())
def test_sweep_and_prune_finds_every_overlapping_pair(n: int, seed: int, ties: bool) -> None:
    rng = np.random.default_rng(seed)
    lo = rng.uniform(-3, 3, (n, 2))
    if ties:  # equal and touching coordinates: closed boxes overlap when they touch
        lo = np.round(lo)
    hi = lo + (np.round(rng.uniform(0, 2, (n, 2))) if ties else rng.uniform(0, 2, (n, 2)))
    pairs = broadphase.overlapping(lo, hi)
    assert [tuple(p) for p in pairs.tolist()] == _brute(lo, hi)


@settings(max_examples=examples(60), deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.0, 10.0))
def test_swept_boxes_hold_the_whole_motion(seed: int, h: float) -> None:
    rng = np.random.default_rng(seed)
    n = 8
    p, v, a = rng.normal(0, 5, (n, 2)), rng.normal(0, 5, (n, 2)), rng.normal(0, 5, (n, 2))
    a[rng.random((n, 2)) < 0.3] = 0.0  # some coordinates without acceleration
    r = rng.uniform(0.0, 1.0, n)
    lo, hi = broadphase.swept_boxes(p, v, a, h, r, 1.0)
    t = np.linspace(0.0, h, 2001)[:, None, None]
    x = p + v * t + 0.5 * a * t * t
    # every point of the motion, widened by the radius, lies inside (and strictly: margin)
    assert (x - r[:, None] > lo).all() and (x + r[:, None] < hi).all()


def _scene(n: int, seed: int, walls: int = 2, speed: float = 2.0, steps: int = 12) -> Scene:
    rng = np.random.default_rng(seed)
    discs: list[Disc] = []
    while len(discs) < n:
        r = float(rng.uniform(0.05, 0.25))
        p = rng.uniform(-1.2, 1.2, 2)
        if any(np.hypot(*(p - np.array(d.position))) < r + d.radius + 1e-3 for d in discs):
            continue
        k = len(discs)
        discs.append(
            Disc(
                name=f"d{k}",
                position=(float(p[0]), float(p[1])),
                radius=r,
                velocity=tuple(float(x) for x in speed * (rng.uniform(-1, 1, 2) - 0.5 * p)),
                mass=float(rng.uniform(0.2, 5.0)),
                actuated=k < 2,
                target=(0.0, 0.0) if k == 0 else None,
            )
        )
    ws = []
    for k in range(walls):
        ang = 2 * np.pi * k / max(walls, 1) + float(rng.uniform(0, 0.5))
        nrm = np.array([np.cos(ang), np.sin(ang)])
        ws.append(Wall(point=tuple(-1.8 * nrm), normal=tuple(nrm), name=f"w{k}"))
    return Scene(horizon=1.5, discs=tuple(discs), walls=tuple(ws), steps=steps,
                 restitution=float(rng.uniform(0.3, 1.0)), control_weight=0.01)  # fmt: skip


@functools.cache
def _compiled(n: int, seed: int) -> Any:
    return _scene(n, seed).to_ocp()


@settings(max_examples=examples(40), deadline=None)
@given(st.sampled_from([3, 8]), st.integers(0, 2**32 - 1), st.floats(0.0, 0.5))
def test_candidates_hold_every_guard_near_contact(n: int, seed: int, h: float) -> None:
    """Over ``[0, h]`` a guard that comes within 1e-6 of contact is a candidate."""
    ocp = _compiled(n, seed % 2)
    table = broadphase.contact_table(ocp)
    assert table is not None
    rng = np.random.default_rng(seed)
    s = ocp.x0 + np.r_[rng.normal(0, 0.2, 2 * n), rng.normal(0, 3, 2 * n)]
    u = rng.normal(0, 5, ocp.nu)
    cand = set(table.candidates(s, u, h).tolist())
    psi = kmod.kernels(ocp).numeric().psi
    a = (table.A @ u).reshape(n, 2)
    for t in np.linspace(0.0, h, 51):
        x = s.copy()
        x[: 2 * n] = s[: 2 * n] + s[2 * n :] * t + 0.5 * a.ravel() * t * t
        near = set(np.flatnonzero(psi(x)[0] <= 1e-6).tolist())
        assert near <= cand


# ------------------------------------------------------------------ the judge through it


def judge(scene: Scene, broad: bool, fn: Any) -> Any:
    """``fn(ocp)`` with the broad phase for every scene (or for none), on kernels built for
    that mode."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(broadphase, "THRESHOLD", 0 if broad else 10**9)
        mp.setattr(kmod, "_CACHE", weakref.WeakKeyDictionary())
        ocp = scene.to_ocp()
        assert (kmod.kernels(ocp).broad is not None) == broad
        return fn(ocp)


def _outcome(fn: Any, ocp: Any) -> Any:
    try:
        return fn(ocp)
    except HybridocError as exc:
        return type(exc)


def _same(a: Any, b: Any) -> None:
    if isinstance(a, type) or isinstance(b, type):
        assert a == b
        return
    assert [(e.guard, e.kind, e.bodies) for e in a.events] == [
        (e.guard, e.kind, e.bodies) for e in b.events
    ]
    T = a.ocp.horizon
    for ea, eb in zip(a.events, b.events, strict=True):
        assert abs(ea.time - eb.time) <= 1e-12 * T
        np.testing.assert_allclose(ea.state_after, eb.state_after, rtol=1e-12, atol=1e-12)
    assert math.isclose(a.cost, b.cost, rel_tol=1e-12, abs_tol=1e-300)
    np.testing.assert_allclose(a.final_state, b.final_state, rtol=1e-12, atol=1e-12)


def _evaluate(ocp: Any) -> Any:
    return _outcome(hybridoc.evaluate, ocp)


@settings(max_examples=examples(3), deadline=None)
@given(st.integers(2, 9), st.integers(0, 4), st.integers(0, 2**32 - 1), st.floats(0.5, 6.0))
def test_broad_phase_judges_as_all_pairs(n: int, walls: int, seed: int, speed: float) -> None:
    """Random crowded scenes with walls and fast discs: the same events and cost."""
    scene = _scene(n, seed, walls, speed)
    _same(judge(scene, True, _evaluate), judge(scene, False, _evaluate))


def test_broad_phase_graze_and_simultaneous_hits() -> None:
    """A disc grazing another (no jump), a disc in a right-angled corner (two walls at one
    instant, commuting) and a striker between two discs (not commuting: an error in both)."""
    graze = Scene(
        horizon=2.0,
        steps=8,
        discs=(
            Disc("a", (-1.0, 0.2), 0.1, velocity=(1.0, 0.0), actuated=True, target=(1.0, 0.2)),
            Disc("b", (0.0, 0.0), 0.1),
        ),
        control_weight=0.01,
    )
    corner = Scene(
        horizon=2.0,
        steps=8,
        discs=(Disc("a", (0.0, 0.0), 0.1, velocity=(1.0, 1.0), actuated=True, target=(0.0, 0.0)),)
        + tuple(Disc(f"p{i}", (-1.0 + 0.3 * i, -1.0), 0.1) for i in range(3)),
        walls=(Wall((1.0, 0.0), (-1.0, 0.0), "right"), Wall((0.0, 1.0), (0.0, -1.0), "top")),
        control_weight=0.01,
    )
    pinch = Scene(
        horizon=1.0,
        steps=4,
        discs=(
            Disc("s", (0.0, 0.0), 0.1, velocity=(1.0, 0.0), actuated=True, target=(0.0, 0.0)),
            Disc("b", (0.5, 0.15), 0.1),
            Disc("c", (0.5, -0.15), 0.1),
        ),
        control_weight=0.01,
    )
    results = {}
    for name, scene in (("graze", graze), ("corner", corner), ("pinch", pinch)):
        a, b = judge(scene, True, _evaluate), judge(scene, False, _evaluate)
        _same(a, b)
        results[name] = a
    assert results["graze"].events == []
    assert [e.name for e in results["corner"].events][:2] == ["a|right", "a|top"]
    assert results["corner"].events[0].time == results["corner"].events[1].time
    assert results["pinch"] is hybridoc.errors.SimultaneousEventError


def test_broad_phase_gradient_and_policy() -> None:
    """The adjoint and a zero-order-hold policy go through the broad phase alike."""
    scene = _scene(7, 3, walls=3, speed=3.0)

    def grad(ocp: Any) -> Any:
        return hybridoc.gradient(ocp)

    ga, gb = judge(scene, True, grad), judge(scene, False, grad)
    _same(ga.evaluation, gb.evaluation)
    assert ga.evaluation.events  # something to differentiate through
    np.testing.assert_allclose(ga.d_controls, gb.d_controls, rtol=1e-9, atol=1e-12)

    def policy(ocp: Any) -> Any:
        return hybridoc.evaluate(ocp, policy=lambda t, s: -0.5 * s[2 * 7 : 2 * 7 + 4])

    _same(judge(scene, True, policy), judge(scene, False, policy))


def test_guard_kernels_are_the_rows_of_the_all_pairs_kernels() -> None:
    scene = _scene(6, 11, walls=2)

    def check(ocp: Any) -> None:
        k = kmod.kernels(ocp)
        assert "interval_fn" not in k.__dict__  # the kernels over every guard: not yet
        num = k.numeric()
        full = [kmod.Num(f) for f in (k.interval_fn, k.window_fn, k.point_fn, k.contact_fn)]
        G, D = k.G, k.D
        rng = np.random.default_rng(0)
        for _ in range(5):
            s = ocp.x0 + rng.normal(0, 0.3, ocp.nx)
            u = rng.normal(0, 3, ocp.nu)
            _, _, S, Nz, pe = full[0](s, u, 0.1)
            W, WN = full[1](s, u, 0.02, 0.07)
            _, dv, dr, dn = full[2](s, u, 0.05)
            contact = full[3](s, u)
            for j in range(G):
                g = num.guard(j)
                iv = g.interval(s, u, 0.1)
                assert (iv[0] == S.reshape(D + 1, G)[:, j]).all()
                assert (iv[1] == Nz.reshape(D + 1, G)[:, j]).all() and iv[2][0] == pe[j]
                w = g.window(s, u, 0.02, 0.07)
                assert (w[0] == W.reshape(D + 1, G)[:, j]).all()
                assert (w[1] == WN.reshape(D + 1, G)[:, j]).all()
                assert [x[0] for x in g.point(s, u, 0.05)] == [dv[j], dr[j], dn[j]]
                assert [x[0] for x in g.contact(s, u)] == [c[j] for c in contact]

    judge(scene, True, check)


def test_problems_without_geometry_are_judged_all_pairs(monkeypatch: pytest.MonkeyPatch) -> None:
    """A problem that does not describe its guards as contacts (no geometry) has no table,
    and the judge samples all of its guards."""
    monkeypatch.setattr(broadphase, "THRESHOLD", 0)
    monkeypatch.setattr(kmod, "_CACHE", weakref.WeakKeyDictionary())
    ocp = _scene(3, 0, walls=1).to_ocp()
    assert broadphase.contact_table(ocp) is not None
    bare = ocp.replace(capabilities=Capabilities(flow=ocp.capabilities.flow))
    assert broadphase.contact_table(bare) is None
    assert kmod.kernels(bare).broad is None
    assert "interval_fn" in kmod.kernels(bare).__dict__


def test_broad_phase_far_from_the_origin_and_in_other_units() -> None:
    """The judge moves a far scene to its local frame (compiled again, with its own
    geometry): the broad phase there finds what all pairs find, and so in micrometres."""
    base = _scene(6, 5, walls=2, speed=3.0)
    for scene in (transform(base, shift=(1e6, -3e5)), transform(base, length=1e-6)):
        _same(judge(scene, True, _evaluate), judge(scene, False, _evaluate))


def test_the_callable_path_builds_the_kernels_over_every_guard_on_use() -> None:
    """evaluate_callable samples every guard (its own path): on a problem the broad phase
    judges, the kernels over every guard are built when it asks, with the same numbers."""
    scene = _scene(5, 2, walls=2, speed=2.0)

    def run(ocp: Any) -> Any:
        u = ocp.u_guess
        return hybridoc.evaluate_callable(
            ocp, lambda t: u[min(int(t / ocp.dt), ocp.steps - 1)], breakpoints=ocp.time_grid()
        )

    a, b = judge(scene, True, run), judge(scene, False, run)
    assert a.events and [e.guard for e in a.events] == [e.guard for e in b.events]
    assert a.cost == b.cost
