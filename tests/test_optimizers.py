"""The numpy optimisers of gradient descent (hybridoc.solvers.optimizers): L-BFGS with the
strong-Wolfe line search, the max-step cut-back, the ports of torch's SGD, Adam and L-BFGS,
and a compiled-path solve that imports no torch."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from hybridoc.solvers.optimizers import (
    GD_LINE_SEARCH_EVALS,
    LBFGS,
    SGD,
    Adam,
    lbfgs_iterations,
    strong_wolfe,
)


def rosenbrock(x: np.ndarray) -> tuple[float, np.ndarray]:
    a, b = x[:-1], x[1:]
    f = float((100 * (b - a**2) ** 2 + (1 - a) ** 2).sum())
    g = np.zeros_like(x)
    g[:-1] += -400 * a * (b - a**2) - 2 * (1 - a)
    g[1:] += 200 * (b - a**2)
    return f, g


def quadratic(n: int = 20, cond: float = 100.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    A = Q @ np.diag(np.geomspace(1.0, cond, n)) @ Q.T
    b = rng.standard_normal(n)

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        return float(0.5 * x @ A @ x - b @ x), A @ x - b

    return fun, np.linalg.solve(A, b)


def _descend_checking_wolfe(fun, x0: np.ndarray, iters: int) -> tuple[np.ndarray, int]:
    """L-BFGS steps from ``x0`` until the gradient is below 1e-7 or it stops; asserts the
    strong Wolfe conditions (c1 = 1e-4, c2 = 0.9) at every accepted step."""
    opt = LBFGS(1.0, max_ls=25)
    x = np.array(x0, dtype=float)
    f, g = fun(x)
    for k in range(iters):
        if np.abs(g).max() < 1e-7:
            return x, k
        x_new, f_new, g_new = opt.step(fun, x, f, g)
        if x_new is x:  # no descent direction left (slope above -1e-15): converged
            return x, k
        d, t = opt.d, opt.t
        gtd = float(g @ d)
        assert gtd < 0 and t > 0
        assert f_new <= f + 1e-4 * t * gtd  # sufficient decrease
        assert abs(float(g_new @ d)) <= 0.9 * abs(gtd)  # strong curvature condition
        np.testing.assert_array_equal(x_new, x + t * d)
        x, f, g = x_new, f_new, g_new
    return x, iters


def test_lbfgs_rosenbrock_converges_with_strong_wolfe_steps() -> None:
    x, k = _descend_checking_wolfe(rosenbrock, np.array([-1.2, 1.0, -1.2, 1.0]), 200)
    np.testing.assert_allclose(x, 1.0, atol=1e-6)
    assert k < 200


def test_lbfgs_quadratic_converges_with_strong_wolfe_steps() -> None:
    fun, x_star = quadratic()
    x, k = _descend_checking_wolfe(fun, np.zeros(20), 100)
    np.testing.assert_allclose(x, x_star, atol=1e-8)
    assert k <= 60


def test_line_search_without_extra_evaluations_takes_the_trial_step_if_lower() -> None:
    fun, _ = quadratic(n=3)
    x = np.ones(3)
    f, g = fun(x)
    d = -g
    gtd = float(g @ d)
    f1, _, t1, n1 = strong_wolfe(fun, x, 1e-3, d, f, g, gtd, max_ls=0)
    assert (t1, n1) == (1e-3, 1) and f1 < f
    f2, g2, t2, n2 = strong_wolfe(fun, x, 1e6, d, f, g, gtd, max_ls=0)  # overshoots: no step
    assert (t2, n2) == (0.0, 1) and f2 == f and g2 is g


def test_lbfgs_iterations_honour_the_max_step_and_converge() -> None:
    fun, x_star = quadratic(n=10, cond=10.0)
    x0 = x_star + 3.0
    previous, events = x0, []
    for it in lbfgs_iterations(fun, x0, lr=1.0, max_step=0.05, max_ls=25):
        assert np.abs(it.x - previous).max() <= 0.05 * (1 + 1e-12)
        previous = it.x
        events.append(it.event)
        if len(events) > 2000:
            break
    assert events[-1] == "converged" and "cut" in events
    np.testing.assert_allclose(previous, x_star, atol=1e-6)


def test_lbfgs_iterations_restart_at_a_kink_then_converge() -> None:
    # |x| has a kink at 0: the trial step overshoots, a fresh start from there converges
    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        return float(np.abs(x).sum()), np.sign(x)

    events = [it.event for it in lbfgs_iterations(fun, np.array([0.3, -0.2]), lr=1.0, max_ls=0)]
    assert events[-1] == "converged"
    assert all(e in ("step", "restart", "converged") for e in events)


def _torch_lbfgs_iterates(x0: np.ndarray, iters: int, max_eval: int) -> list[np.ndarray]:
    torch = pytest.importorskip("torch")
    u = torch.tensor(x0, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS(
        [u], lr=0.1, max_iter=1, max_eval=max_eval, history_size=50,
        line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=1e-15,
    )  # fmt: skip

    def closure():
        opt.zero_grad()
        f, g = rosenbrock(u.detach().numpy())
        u.grad = torch.tensor(g, dtype=torch.float64)
        return torch.tensor(f, dtype=torch.float64)

    out = []
    for _ in range(iters):
        opt.step(closure)
        out.append(u.detach().numpy().copy())
    return out


@pytest.mark.parametrize("max_ls", [GD_LINE_SEARCH_EVALS, 25])
def test_lbfgs_is_torchs_lbfgs(max_ls: int) -> None:
    # gd's L-BFGS replaced torch.optim.LBFGS(max_iter=1, strong_wolfe), whose max_eval of 1
    # left no line-search evaluation beyond the trial step: the port follows its iterates
    # (to rounding, for 20 iterations: later, near the optimum, rounding may tip a decision)
    x0 = np.array([-1.2, 1.0, 0.5, -0.3])
    expected = _torch_lbfgs_iterates(x0, 20, max_eval=1 + max_ls)
    opt = LBFGS(0.1, max_ls=max_ls)
    x = x0.copy()
    f, g = rosenbrock(x)
    for want in expected:
        x, f, g = opt.step(rosenbrock, x, f, g)
        np.testing.assert_allclose(x, want, rtol=1e-12, atol=1e-12)


def test_sgd_and_adam_are_torchs() -> None:
    torch = pytest.importorskip("torch")
    fun, _ = quadratic(n=5)
    for make_np, make_torch in (
        (lambda: SGD(0.01), lambda p: torch.optim.SGD(p, lr=0.01)),
        (lambda: Adam(0.05), lambda p: torch.optim.Adam(p, lr=0.05)),
    ):
        x = np.ones(5)
        u = torch.tensor(x, requires_grad=True)
        opt_np, opt_t = make_np(), make_torch([u])
        for _ in range(20):
            x = opt_np.step(x, fun(x)[1])
            u.grad = torch.tensor(fun(u.detach().numpy())[1])
            opt_t.step()
        np.testing.assert_allclose(x, u.detach().numpy(), rtol=1e-12, atol=1e-14)


def test_a_compiled_path_solve_imports_no_torch() -> None:
    code = textwrap.dedent(
        """
        import sys
        from hybridoc.solvers.gd import solve_gd
        for problem, kw in [
            ("single-collision", {"iters": 20, "smoothing": (1e-4,)}),
            ("single-collision", {"optimizer": "adam", "iters": 5}),
            ("head-on", {"optimizer": "gd", "iters": 5, "integrator": "symplectic-euler"}),
            ("bouncing-ball-2", {"iters": 20}),
        ]:
            sol = solve_gd(problem, **kw)
            assert sol.settings["path"] == "compiled", problem
        assert "torch" not in sys.modules, "torch was imported"
        print("no torch")
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert "no torch" in out.stdout


def _two_loop(steps, dirs, ro, h_diag, g):
    """The two-loop recursion as torch.optim.LBFGS writes it, out of place."""
    al = [0.0] * len(dirs)
    q = -g
    for i in range(len(dirs) - 1, -1, -1):
        al[i] = float(steps[i] @ q) * ro[i]
        q = q - al[i] * dirs[i]
    r = q * h_diag
    for i in range(len(dirs)):
        be = float(dirs[i] @ r) * ro[i]
        r = r + (al[i] - be) * steps[i]
    return r


def test_lbfgs_direction_is_the_two_loop_recursion_and_the_bfgs_inverse() -> None:
    # direction() computes the recursion in place: the same arithmetic, so the same bits as
    # torch's out-of-place form, and -H g for the BFGS inverse Hessian H built from the
    # same pairs (dense, independently)
    rng = np.random.default_rng(3)
    n, m = 40, 7
    opt = LBFGS(1.0, history_size=m)
    A = rng.standard_normal((n, n))
    A = A @ A.T + n * np.eye(n)
    x, g = rng.standard_normal(n), None
    for _ in range(m + 3):  # more pairs than the history holds: the oldest are dropped
        g = A @ x
        opt.n_iter += 1
        d = opt.direction(g)
        opt.d, opt.prev_g, opt.t = d, g.copy(), 0.5
        x = x + 0.5 * d
    g = A @ x
    opt.n_iter += 1
    d = opt.direction(g)
    # the pairs direction() recursed over, the last step's appended
    steps, dirs, ro, h = opt.steps, opt.dirs, opt.ro, opt.h_diag
    assert len(steps) == m
    np.testing.assert_array_equal(d, _two_loop(steps, dirs, ro, h, g))
    H = h * np.eye(n)
    for s, y in zip(steps, dirs, strict=True):
        rho = 1.0 / float(y @ s)
        V = np.eye(n) - rho * np.outer(y, s)
        H = V.T @ H @ V + rho * np.outer(s, s)
    np.testing.assert_allclose(d, -H @ g, rtol=1e-9, atol=1e-12 * np.abs(H @ g).max())
