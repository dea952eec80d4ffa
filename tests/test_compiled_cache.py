"""The core layer's code cache (:mod:`hybridoc.compiled`) and the judge's compiled kernels.

The judge's SX kernels go to generated C once they are hot (issue #18): the numbers must be
the virtual machine's bit for bit, and nothing changes where compiling is off, impossible
(an integrator's flow) or not yet done.
"""

from __future__ import annotations

import pickle
import time

import casadi as ca
import numpy as np
import pytest

from hybridoc import compiled, evaluate, gradient
from hybridoc.kernels import Num, kernels
from hybridoc.problems import load_problem
from hybridoc.solvers import codegen


def test_the_solvers_codegen_is_the_core_cache() -> None:
    # one cache and one compilation queue for the judge and the solvers
    for name in codegen.__all__:
        assert getattr(codegen, name) is getattr(compiled, name)


def _probe() -> ca.Function:
    x, y = ca.SX.sym("x", 3), ca.SX.sym("y", 2, 2)
    out = ca.vertcat(ca.sin(x) * ca.sum1(x), ca.sum1(ca.vec(y)) / 3.0)
    return ca.Function("bind_probe", [x, y], [out, ca.densify(ca.mtimes(y, y))])


def test_bound_buffers_equal_the_call_and_the_virtual_machine(compiling: None) -> None:
    fn = _probe()
    acc = compiled.Accelerated(fn, wait=True)
    assert acc.native is not None, acc.error
    x, y = np.array([0.3, -1.7, 2.9]), np.array([[1.5, -0.25], [0.125, 3.0]])
    ins = [x.copy(), y.reshape(-1, order="F").copy()]
    outs = [np.zeros(4), np.zeros(4)]
    call = acc.native.bind(ins, outs)
    assert call() == 0
    vm = [np.asarray(o).reshape(-1, order="F") for o in fn(x, y)]
    native = [o.reshape(-1, order="F") for o in acc.native(x, y.reshape(-1, order="F"))]
    for got, a, b in zip(outs, vm, native, strict=True):
        np.testing.assert_array_equal(got, a)
        np.testing.assert_array_equal(got, b)
    ins[0][:] = [1.0, 2.0, 3.0]  # the buffers are read at each call
    assert call() == 0
    np.testing.assert_array_equal(outs[0], np.asarray(fn([1.0, 2.0, 3.0], y)[0]).ravel())


def test_bind_refuses_wrong_buffers(compiling: None) -> None:
    acc = compiled.Accelerated(_probe(), wait=True)
    assert acc.native is not None, acc.error
    good_in, good_out = [np.zeros(3), np.zeros(4)], [np.zeros(4), np.zeros(4)]
    with pytest.raises(ValueError, match="where 3 float64"):
        acc.native.bind([np.zeros(2), np.zeros(4)], good_out)
    with pytest.raises(ValueError, match="float64"):
        acc.native.bind([np.zeros(3, dtype=np.float32), np.zeros(4)], good_out)
    with pytest.raises(ValueError, match="expected 2 inputs"):
        acc.native.bind(good_in[:1], good_out)
    x = ca.SX.sym("x", 2)
    sparse = ca.Function("sparse_probe", [x], [ca.diag(x)])
    acc = compiled.Accelerated(sparse, wait=True)
    assert acc.native is not None, acc.error
    with pytest.raises(ValueError, match="sparse output"):
        acc.native.bind([np.zeros(2)], [np.zeros(4)])


def _judge(problem, u):  # noqa: ANN001, ANN202
    ev = evaluate(problem, u)
    g = gradient(problem, u)
    return ev, g


def test_the_judge_compiled_is_the_judge_bit_for_bit(compiling: None) -> None:
    problem = load_problem("bouncing-ball-2")  # a fresh structure: its own kernels
    u = problem.u_guess * 1.1
    k = kernels(problem)
    before_ev, before_g = _judge(problem, u)
    deadline = time.time() + 120
    while True:  # hot kernels start compiling in the background
        accs = [k.accelerated(fn) for fn in (k.batch_fn, k.seg_jac_fn, k.point_fn)]
        if all(a is not None and (a.compiled or a.error) for a in accs):
            break
        assert time.time() < deadline, "the judge's kernels were not compiled"
        _judge(problem, u)
    assert all(a is not None and a.native is not None for a in accs), [a.error for a in accs]
    after_ev, after_g = _judge(problem, u)
    assert after_ev.cost == before_ev.cost
    np.testing.assert_array_equal(after_ev.times, before_ev.times)
    np.testing.assert_array_equal(after_ev.states, before_ev.states)
    assert [e.time for e in after_ev.events] == [e.time for e in before_ev.events]
    np.testing.assert_array_equal(after_g.d_controls, before_g.d_controls)
    np.testing.assert_array_equal(after_g.d_initial_state, before_g.d_initial_state)
    # the kernels still travel to worker processes (their libraries stay here)
    again = pickle.loads(pickle.dumps(k))
    assert again.accelerated(again.batch_fn) is not None


def test_the_judge_compiles_nothing_without_codegen_or_for_an_integrator(
    monkeypatch: pytest.MonkeyPatch, compiling: None
) -> None:
    pendulum = kernels(load_problem("pendulum-wall"))
    assert not pendulum.sx and pendulum.accelerated(pendulum.interval_fn) is None
    monkeypatch.setenv("HYBRIDOC_CODEGEN", "0")
    ball = kernels(load_problem("bouncing-ball"))
    assert ball.accelerated(ball.batch_fn) is None
    num = Num(ball.batch_fn, None)  # the virtual machine, as before
    assert len(num(np.zeros(ball.nx), np.zeros(ball.nu * ball.chunk), np.zeros(ball.chunk)))


# ------------------------------------------------- an integrator's flow: DOP853 twins of CVODES


def _cvodes_only(name: str):  # noqa: ANN202
    """A fresh problem whose judge keeps CVODES (its kernels without DOP853 twins)."""
    problem = load_problem(name)
    kernels(problem).rk_fns = {}
    return problem


def test_the_dop853_flow_is_more_accurate_than_cvodes() -> None:
    from scipy.integrate import solve_ivp

    from hybridoc import kernels as kmod
    from hybridoc.ocp import integrator_flow_samples

    problem = load_problem("pendulum-wall")
    fracs = kmod._node_fractions(kernels(problem).cheb.x)  # noqa: SLF001
    rk = kmod._dop853_sampler(problem.f, problem.L, fracs)  # noqa: SLF001
    cv = integrator_flow_samples(problem.f, problem.L, fracs)
    f, L = problem.f, problem.L
    rng = np.random.default_rng(3)
    for _ in range(5):
        s0, u0 = problem.x0 + rng.normal(0, 1, problem.nx), rng.normal(0, 3, problem.nu)
        h = problem.dt * rng.uniform(0.3, 1.0)

        def rhs(t, z, u0=u0):  # noqa: ANN001, ANN202, ARG001
            x = z[: problem.nx]
            return np.concatenate([np.asarray(f(x, u0)).ravel(), np.asarray(L(x, u0)).ravel()])

        ref = solve_ivp(rhs, (0, h), np.append(s0, 0.0), method="DOP853", rtol=3e-14,
                        atol=1e-16, t_eval=h * fracs, max_step=h / 64)  # fmt: skip
        xs, qs, err = (np.asarray(v) for v in rk(s0, u0, h))
        assert err.item() <= 1.0
        rk_gap = np.max(np.abs(xs - ref.y[: problem.nx]))
        cv_gap = np.max(np.abs(np.asarray(cv(s0, u0, h)[0]) - ref.y[: problem.nx]))
        assert rk_gap < 1e-13
        assert rk_gap < cv_gap
        np.testing.assert_allclose(qs.ravel(), ref.y[problem.nx], rtol=1e-12, atol=1e-15)


def test_the_judge_of_an_integrator_flow_agrees_with_cvodes() -> None:
    twin, cvodes = load_problem("pendulum-wall"), _cvodes_only("pendulum-wall")
    assert kernels(twin).rk_fns and not kernels(cvodes).rk_fns
    rng = np.random.default_rng(1)
    for u in (twin.u_guess, twin.u_guess + rng.normal(0, 2, twin.u_guess.shape)):
        a, b = _judge(twin, u), _judge(cvodes, u)
        assert abs(a[0].cost - b[0].cost) <= 1e-10 * abs(b[0].cost)
        assert [e.guard for e in a[0].events] == [e.guard for e in b[0].events]
        np.testing.assert_allclose(
            [e.time for e in a[0].events], [e.time for e in b[0].events], atol=1e-10
        )
        scale = np.max(np.abs(b[1].d_controls))
        np.testing.assert_allclose(a[1].d_controls, b[1].d_controls, atol=1e-7 * scale)
    num = kernels(twin).numeric()
    assert num.interval.fallbacks == 0 and num.point.fallbacks == 0


def test_a_coarse_dop853_step_falls_back_to_cvodes() -> None:
    twin, cvodes = load_problem("pendulum-wall"), _cvodes_only("pendulum-wall")
    checked, plain = kernels(twin).numeric().flow, kernels(cvodes).numeric().flow
    s0, u0 = twin.x0, np.array([0.5])
    fine = checked(s0, u0, twin.dt)
    assert checked.fallbacks == 0
    np.testing.assert_allclose(fine[0], plain(s0, u0, twin.dt)[0], atol=1e-11)
    coarse = checked(s0, u0, 40 * twin.horizon)  # 16 steps of seconds: far off the tolerance
    assert checked.fallbacks == 1
    for x, y in zip(coarse, plain(s0, u0, 40 * twin.horizon), strict=True):
        np.testing.assert_array_equal(x, y)


def test_native_calls_return_their_own_arrays(compiling: None) -> None:
    # the lock holder's calls go through buffers bound once: what they return is a copy
    fn = _probe()
    acc = compiled.Accelerated(fn, wait=True)
    assert acc.native is not None, acc.error
    y = np.array([[1.5, -0.25], [0.125, 3.0]])
    first = acc.native(np.array([0.3, -1.7, 2.9]), y)
    kept = [o.copy() for o in first]
    second = acc.native(np.array([1.0, 2.0, 3.0]), 2.0 * y.T.T)  # a transposed view reads as y
    for a, b in zip(first, kept, strict=True):
        np.testing.assert_array_equal(a, b)
    for got, want in zip(second, fn([1.0, 2.0, 3.0], 2.0 * y), strict=True):
        assert got.shape == np.asarray(want).shape and got.flags.f_contiguous
        np.testing.assert_array_equal(got, np.asarray(want))
