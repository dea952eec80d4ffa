"""Numpy optimisers of gradient descent (:mod:`hybridoc.solvers.gd`): no torch needed.

The compiled loss (:class:`~hybridoc.solvers.compiled.CompiledLoss`) hands out numpy values
and gradients, so the optimisers of :func:`~hybridoc.solvers.gd.solve_gd` run on numpy
buffers: importing torch (seconds) is left to the torch simulator, policies and training.

:class:`LBFGS`
    One L-BFGS iteration at a time: the two-loop recursion over at most ``history_size``
    curvature pairs (a pair with ``y.s <= 1e-10`` is dropped), the scaled identity
    ``y.s / y.y`` as the initial inverse Hessian, and the strong-Wolfe line search
    :func:`strong_wolfe` (bracketing, then zoom by safeguarded cubic interpolation). It is a
    port of ``torch.optim.LBFGS`` (itself after minFunc), so that gd's iterates are those of
    the torch optimiser it replaces, up to rounding. ``max_ls`` is the number of line-search
    evaluations after the first trial step: ``torch.optim.LBFGS(max_iter=1)``, as gd used
    it, allows ``max_eval - 1 = 0`` of them, which makes the line search one trial step of
    ``lr`` (``min(1, 1 / |g|_1) lr`` on a fresh start) taken when it lowers the loss;
    :data:`GD_LINE_SEARCH_EVALS` keeps that.
:func:`lbfgs_iterations`
    The L-BFGS loop of gd, as a generator of iterations: the max-step cut-back (a step that
    changes some coordinate by more than ``max_step`` is shortened to it, in the inf-norm,
    and the curvature history is reset; if the shortened step raises the loss, the iterate
    stays) and restarts at kinks (a step that does not move restarts from steepest descent
    with an empty history; a fresh start that does not move either has converged).
:func:`lbfgs_torch_step`
    What one call ``torch.optim.LBFGS.step(closure)`` does (up to ``max_iter`` iterations
    and ``max_eval`` evaluations, with its stopping tests), on :class:`LBFGS`: policy
    training (:func:`~hybridoc.workflows.training.train_policy`) runs it instead of the
    torch optimiser, whose first construction imports ``torch._dynamo`` (seconds).
:class:`SGD`, :class:`Adam`
    ``torch.optim.SGD`` and ``torch.optim.Adam`` (their defaults) on numpy arrays.
:func:`nonsmooth_bfgs`, :func:`min_norm_element`
    Full BFGS with a weak Wolfe line search, which keeps converging on a loss with kinks
    (Lewis and Overton, "Nonsmooth optimization via quasi-Newton methods", Math. Program.
    141, 2013) where L-BFGS with a strong Wolfe search stalls, and the certificate of its
    result: the smallest convex combination of the gradients at the last iterates near it
    (a Clarke-stationary point has one near zero; Burke, Lewis and Overton's gradient
    sampling test).

Every objective is a callable ``fun(x) -> (f, g)`` of a flat float array (``g`` a flat
array of the same size).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "GD_LINE_SEARCH_EVALS",
    "LBFGS",
    "SGD",
    "Adam",
    "Iteration",
    "lbfgs_iterations",
    "lbfgs_torch_step",
    "min_norm_element",
    "nonsmooth_bfgs",
    "strong_wolfe",
]

Objective = Callable[[np.ndarray], tuple[float, np.ndarray]]

GD_LINE_SEARCH_EVALS = 0
"""Line-search evaluations after the first trial step in gd's L-BFGS: none, as in
``torch.optim.LBFGS(max_iter=1)`` that gd used before (its ``max_eval`` of 1 left the
strong-Wolfe search no evaluation beyond the trial step)."""


def _cubic_interpolate(
    x1: float,
    f1: float,
    g1: float,
    x2: float,
    f2: float,
    g2: float,
    bounds: tuple[float, float] | None = None,
) -> float:
    """The minimiser of the cubic through ``(x1, f1, g1)`` and ``(x2, f2, g2)``, clipped to
    ``bounds`` (default: the interval between the points); its midpoint without a real
    minimiser."""
    if bounds is not None:
        lo, hi = bounds
    else:
        lo, hi = (x1, x2) if x1 <= x2 else (x2, x1)
    d1 = g1 + g2 - 3 * (f1 - f2) / (x1 - x2)
    d2_square = d1**2 - g1 * g2
    if d2_square >= 0:
        d2 = math.sqrt(d2_square)
        if x1 <= x2:
            pos = x2 - (x2 - x1) * ((g2 + d2 - d1) / (g2 - g1 + 2 * d2))
        else:
            pos = x1 - (x1 - x2) * ((g1 + d2 - d1) / (g1 - g2 + 2 * d2))
        return min(max(pos, lo), hi)
    return (lo + hi) / 2.0


# 84 code lines: a statement-for-statement port of torch.optim.lbfgs._strong_wolfe (bracket,
# then zoom), kept whole so that it reads line by line against the original
def strong_wolfe(
    fun: Objective,
    x: np.ndarray,
    t: float,
    d: np.ndarray,
    f: float,
    g: np.ndarray,
    gtd: float,
    *,
    c1: float = 1e-4,
    c2: float = 0.9,
    tolerance_change: float = 1e-9,
    max_ls: int = 25,
) -> tuple[float, np.ndarray, float, int]:
    """A step along ``d`` from ``x`` that meets the strong Wolfe conditions.

    ``f(x + t d) <= f + c1 t gtd`` (sufficient decrease) and ``|g(x + t d).d| <= c2 |gtd|``
    (curvature), found by bracketing from the trial step ``t`` (extrapolating by cubic
    interpolation, at most tenfold) and zooming into the bracket (safeguarded cubic
    interpolation), after minFunc and ``torch.optim.lbfgs._strong_wolfe``.

    Parameters
    ----------
    fun
        The objective, ``fun(x) -> (f, g)``.
    x, d
        The point and the descent direction.
    t
        The first trial step.
    f, g, gtd
        The value and gradient at ``x``, and the slope ``g.d < 0``.
    c1, c2
        The constants of the conditions.
    tolerance_change
        The zoom stops once the bracket is shorter than this (times ``max |d|``).
    max_ls
        Evaluations after the first trial step. With none, the search returns the trial
        step when its value is below ``f``, else 0.

    Returns
    -------
    f_new, g_new, t, evaluations
        The value and gradient at ``x + t d``, the step (0: no step lowered the loss) and
        the number of evaluations of ``fun``.
    """
    d_norm = float(np.abs(d).max())
    f_new, g_new = fun(x + t * d)
    evals = 1
    gtd_new = float(g_new @ d)
    t_prev, f_prev, g_prev, gtd_prev = 0.0, f, g, gtd
    done = False
    ls_iter = 0
    bracket: list[float] = []
    bracket_f: list[float] = []
    bracket_g: list[np.ndarray] = []
    bracket_gtd: list[float] = []
    while ls_iter < max_ls:
        if f_new > f + c1 * t * gtd or (ls_iter > 1 and f_new >= f_prev):
            bracket, bracket_f = [t_prev, t], [f_prev, f_new]
            bracket_g, bracket_gtd = [g_prev, g_new], [gtd_prev, gtd_new]
            break
        if abs(gtd_new) <= -c2 * gtd:
            bracket, bracket_f, bracket_g = [t], [f_new], [g_new]
            done = True
            break
        if gtd_new >= 0:
            bracket, bracket_f = [t_prev, t], [f_prev, f_new]
            bracket_g, bracket_gtd = [g_prev, g_new], [gtd_prev, gtd_new]
            break
        # extrapolate: a longer step, by cubic interpolation within [1.01 t, 10 t]
        lo, hi = t + 0.01 * (t - t_prev), t * 10
        t_next = _cubic_interpolate(t_prev, f_prev, gtd_prev, t, f_new, gtd_new, bounds=(lo, hi))
        t_prev, f_prev, g_prev, gtd_prev = t, f_new, g_new, gtd_new
        t = t_next
        f_new, g_new = fun(x + t * d)
        evals += 1
        gtd_new = float(g_new @ d)
        ls_iter += 1
    if ls_iter == max_ls:
        bracket, bracket_f, bracket_g = [0.0, t], [f, f_new], [g, g_new]
        bracket_gtd = [gtd, gtd_new]
    # zoom: shrink the bracket until a point meets the conditions
    insufficient = False
    low, high = (0, 1) if bracket_f[0] <= bracket_f[-1] else (1, 0)
    while not done and ls_iter < max_ls:
        if abs(bracket[1] - bracket[0]) * d_norm < tolerance_change:
            break
        t = _cubic_interpolate(
            bracket[0], bracket_f[0], bracket_gtd[0], bracket[1], bracket_f[1], bracket_gtd[1]
        )
        # too close to an end of the bracket (twice in a row, or at it): a tenth inside
        b_lo, b_hi = min(bracket), max(bracket)
        eps = 0.1 * (b_hi - b_lo)
        if min(b_hi - t, t - b_lo) < eps:
            if insufficient or t >= b_hi or t <= b_lo:
                t = b_hi - eps if abs(t - b_hi) < abs(t - b_lo) else b_lo + eps
                insufficient = False
            else:
                insufficient = True
        else:
            insufficient = False
        f_new, g_new = fun(x + t * d)
        evals += 1
        gtd_new = float(g_new @ d)
        ls_iter += 1
        if f_new > f + c1 * t * gtd or f_new >= bracket_f[low]:
            # no sufficient decrease, or not below the low end: the new high end
            bracket[high], bracket_f[high] = t, f_new
            bracket_g[high], bracket_gtd[high] = g_new, gtd_new
            low, high = (0, 1) if bracket_f[0] <= bracket_f[1] else (1, 0)
        else:
            if abs(gtd_new) <= -c2 * gtd:
                done = True
            elif gtd_new * (bracket[high] - bracket[low]) >= 0:
                # the old low end becomes the high end
                bracket[high], bracket_f[high] = bracket[low], bracket_f[low]
                bracket_g[high], bracket_gtd[high] = bracket_g[low], bracket_gtd[low]
            bracket[low], bracket_f[low] = t, f_new
            bracket_g[low], bracket_gtd[low] = g_new, gtd_new
    return bracket_f[low], bracket_g[low], bracket[low], evals


class LBFGS:
    """L-BFGS, one iteration per :meth:`step` (see the module notes).

    Parameters
    ----------
    lr
        The first trial step of the line search (``min(1, 1 / |g|_1) lr`` after a reset).
    history_size
        Curvature pairs kept.
    tolerance_grad
        No step once ``max |g| <= tolerance_grad``.
    tolerance_change
        No step once the slope ``g.d > -tolerance_change``; the line search's bracket
        tolerance.
    max_ls
        Line-search evaluations after the first trial step (:func:`strong_wolfe`).
    """

    def __init__(
        self,
        lr: float = 1.0,
        *,
        history_size: int = 50,
        tolerance_grad: float = 1e-12,
        tolerance_change: float = 1e-15,
        max_ls: int = 25,
    ) -> None:
        self.lr = lr
        self.history_size = history_size
        self.tolerance_grad = tolerance_grad
        self.tolerance_change = tolerance_change
        self.max_ls = max_ls
        self.evaluations = 0
        self.reset()

    def reset(self) -> None:
        """Forget the curvature history: the next step is along steepest descent."""
        self.n_iter = 0
        self.dirs: list[np.ndarray] = []  # the gradient changes y
        self.steps: list[np.ndarray] = []  # the steps s
        self.ro: list[float] = []
        self.h_diag = 1.0
        self.d: np.ndarray | None = None
        self.t = 0.0
        self.prev_g: np.ndarray | None = None

    def direction(self, g: np.ndarray) -> np.ndarray:
        """The search direction at gradient ``g`` (updating the curvature history with the
        last step): ``-H g`` by the two-loop recursion."""
        if self.n_iter == 1 or self.d is None or self.prev_g is None:
            self.dirs, self.steps, self.ro, self.h_diag = [], [], [], 1.0
            return -g
        y = g - self.prev_g
        s = self.d * self.t
        ys = float(y @ s)
        if ys > 1e-10:
            if len(self.dirs) == self.history_size:
                self.dirs.pop(0)
                self.steps.pop(0)
                self.ro.pop(0)
            self.dirs.append(y)
            self.steps.append(s)
            self.ro.append(1.0 / ys)
            self.h_diag = ys / float(y @ y)
        # the recursion's own arithmetic, in place through one scratch array: its numpy
        # calls, not its flops, are most of an iteration of gd (n of about 1000, 50 pairs)
        steps, dirs, ro = self.steps, self.dirs, self.ro
        n = len(dirs)
        al = [0.0] * n
        q = -g
        tmp = np.empty_like(q)
        mul, sub, add = np.multiply, np.subtract, np.add
        for i in range(n - 1, -1, -1):
            a = float(steps[i].dot(q)) * ro[i]
            al[i] = a
            sub(q, mul(dirs[i], a, out=tmp), out=q)
        r = mul(q, self.h_diag, out=q)
        for i in range(n):
            be = float(dirs[i].dot(r)) * ro[i]
            add(r, mul(steps[i], al[i] - be, out=tmp), out=r)
        return r

    def step(
        self,
        fun: Objective,
        x: np.ndarray,
        f: float,
        g: np.ndarray,
        *,
        max_ls: int | None = None,
    ) -> tuple[np.ndarray, float, np.ndarray]:
        """One iteration from ``x`` (value ``f``, gradient ``g``): the new point, its value
        and gradient (``x``, ``f``, ``g`` themselves when it does not move). ``max_ls``
        overrides ``self.max_ls`` for this iteration's line search."""
        if float(np.abs(g).max()) <= self.tolerance_grad:
            return x, f, g
        self.n_iter += 1
        d = self.direction(g)
        self.d, self.prev_g = d, g.copy()
        t = min(1.0, 1.0 / float(np.abs(g).sum())) * self.lr if self.n_iter == 1 else self.lr
        gtd = float(g @ d)
        if gtd > -self.tolerance_change:
            self.t = t
            return x, f, g
        max_ls = self.max_ls if max_ls is None else max_ls
        f_new, g_new, t, evals = strong_wolfe(fun, x, t, d, f, g, gtd, max_ls=max_ls)
        self.evaluations += evals
        self.t = t
        if t == 0:
            return x, f, g
        return x + t * d, f_new, g_new


@dataclass
class Iteration:
    """One iteration of :func:`lbfgs_iterations`: the iterate, its value and gradient, and
    what happened: ``"step"``, ``"cut"`` (a step shortened to ``max_step``), ``"cut-rejected"``
    (the shortened step raised the loss: the iterate stayed), ``"restart"`` (no step: the
    history is reset) or ``"converged"`` (no step from a fresh start; the last iteration)."""

    x: np.ndarray
    f: float
    g: np.ndarray
    event: str


def lbfgs_iterations(
    fun: Objective,
    x0: np.ndarray,
    *,
    lr: float = 1.0,
    max_step: float = math.inf,
    history_size: int = 50,
    max_ls: int = 25,
    tolerance_grad: float = 1e-12,
    tolerance_change: float = 1e-15,
    start: tuple[float, np.ndarray] | None = None,
) -> Iterator[Iteration]:
    """L-BFGS with the max-step cut-back and restarts at kinks (module notes), one
    :class:`Iteration` per iteration, endless until it converges; ``start`` is ``(f, g)`` at
    ``x0`` when known. ``fun`` may raise to stop it."""
    opt = LBFGS(
        lr, history_size=history_size, tolerance_grad=tolerance_grad,
        tolerance_change=tolerance_change, max_ls=max_ls,
    )  # fmt: skip
    x = np.array(x0, dtype=float)
    f, g = fun(x) if start is None else start
    fresh = True
    while True:
        x_new, f_new, g_new = opt.step(fun, x, f, g)
        jump = float(np.abs(x_new - x).max()) if x_new is not x else 0.0
        if jump > max_step:
            # a quasi-Newton step can leap into another event sequence: cut it back and
            # forget the curvature history
            x_cut = x + (x_new - x) * (max_step / jump)
            opt.reset()
            fresh = True
            f_cut, g_cut = fun(x_cut)
            if f_cut > f:
                yield Iteration(x, f, g, "cut-rejected")
                continue
            x, f, g = x_cut, f_cut, g_cut
            yield Iteration(x, f, g, "cut")
        elif jump == 0.0:
            # kinks of the loss can spoil the quasi-Newton model: restart from here with an
            # empty history; a fresh start that makes no progress either has converged
            if fresh:
                yield Iteration(x, f, g, "converged")
                return
            opt.reset()
            fresh = True
            yield Iteration(x, f, g, "restart")
        else:
            x, f, g, fresh = x_new, f_new, g_new, False
            yield Iteration(x, f, g, "step")


def lbfgs_torch_step(
    opt: LBFGS,
    fun: Objective,
    x: np.ndarray,
    f: float,
    g: np.ndarray,
    *,
    max_iter: int = 20,
    max_eval: int | None = None,
) -> tuple[np.ndarray, float, np.ndarray]:
    """One call of ``torch.optim.LBFGS.step(closure)`` with ``line_search_fn="strong_wolfe"``.

    Up to ``max_iter`` iterations of ``opt`` from ``x``, as torch's optimiser makes them in
    one call, its curvature history kept in ``opt`` from call to call. The iterations stop
    after ``max_eval`` evaluations (the one at ``x`` included: each line search gets what is
    left), once ``max |g| <= opt.tolerance_grad``, once the slope ``g.d`` is above
    ``-opt.tolerance_change``, or when the last step moved no coordinate or changed the loss
    by no more than ``opt.tolerance_change``. ``opt`` should be built with torch's defaults
    (``history_size=100, tolerance_grad=1e-7, tolerance_change=1e-9``) for torch's
    iterates, which it reproduces up to rounding (torch's fused multiply-adds and dot
    products round differently).

    Parameters
    ----------
    opt
        The optimiser and its state (``opt.max_ls`` is not used: the evaluations left are).
    fun
        The objective, ``fun(x) -> (f, g)``; an exception it raises propagates.
    x, f, g
        The start and its value and gradient (torch's call evaluates them first; here the
        caller passes them, e.g. the last call's result, which is the same point).
    max_iter
        Iterations at most (torch's ``max_iter``).
    max_eval
        Evaluations at most, the one at ``x`` included; default ``max_iter * 5 // 4``.

    Returns
    -------
    x, f, g
        The new point, its value and gradient (``x``, ``f``, ``g`` when it does not move).
    """
    max_eval = max_iter * 5 // 4 if max_eval is None else max_eval
    evals = 1
    for n in range(1, max_iter + 1):
        f_prev, before = f, opt.evaluations
        # each line search gets the evaluations left (torch's max_eval)
        x, f, g = opt.step(fun, x, f, g, max_ls=max_eval - evals)
        used = opt.evaluations - before
        if used == 0:  # converged gradient, or no descent direction: no search was made
            break
        evals += used
        if (
            n == max_iter
            or evals >= max_eval
            or float(np.abs(g).max()) <= opt.tolerance_grad
            or float(np.abs(opt.d * opt.t).max()) <= opt.tolerance_change
            or abs(f - f_prev) < opt.tolerance_change
        ):
            break
    return x, f, g


class SGD:
    """Plain gradient descent, ``x - lr g`` (``torch.optim.SGD`` without momentum)."""

    def __init__(self, lr: float) -> None:
        self.lr = lr

    def step(self, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        return x - self.lr * g


class Adam:
    """Adam with bias correction (``torch.optim.Adam``'s defaults: betas 0.9 and 0.999,
    eps 1e-8, no weight decay)."""

    def __init__(
        self, lr: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8
    ) -> None:
        self.lr = lr
        self.b1, self.b2 = betas
        self.eps = eps
        self.k = 0
        self.m: Any = 0.0
        self.v: Any = 0.0

    def step(self, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        self.k += 1
        self.m = self.m + (1 - self.b1) * (g - self.m)
        self.v = self.v * self.b2 + (1 - self.b2) * g * g
        step_size = self.lr / (1 - self.b1**self.k)
        denom = np.sqrt(self.v) / math.sqrt(1 - self.b2**self.k) + self.eps
        return x - step_size * (self.m / denom)


# ---------------------------------------------------------------------- losses with kinks
def min_norm_element(G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The point of smallest norm in the convex hull of the rows of ``G`` ``(m, n)``, and
    its weights: ``min |lambda G|`` over ``lambda >= 0``, ``sum lambda = 1``.

    Solved as a non-negative least-squares problem with the sum as one heavily weighted
    row (an exact method, finite, for the few gradients of a bundle)."""
    from scipy.optimize import nnls

    G = np.asarray(G, dtype=float)
    m = G.shape[0]
    if m == 1:
        return G[0].copy(), np.ones(1)
    scale = max(float(np.abs(G).max()), 1e-300)
    weight = 1e3
    A = np.vstack([G.T / scale, weight * np.ones((1, m))])
    b = np.concatenate([np.zeros(G.shape[1]), [weight]])
    lam, _ = nnls(A, b, maxiter=50 * m)
    lam = lam / max(float(lam.sum()), 1e-300)
    return lam @ G, lam


@dataclass
class NonsmoothResult:
    """What :func:`nonsmooth_bfgs` returns."""

    x: np.ndarray
    """The best iterate."""
    f: float
    """Its value."""
    g: np.ndarray
    """Its gradient."""
    iterations: int
    evaluations: int
    message: str
    """Why it stopped."""
    stationarity: float
    """The certificate: the norm of the smallest convex combination of the gradients
    sampled around ``x`` (:func:`min_norm_element`), relative (``|d| (1 + |x|_inf) /
    (1 + |f|)``); small at a Clarke-stationary point."""
    bundle: int
    """How many gradients went into it."""


def _weak_wolfe(
    fun: Objective,
    x: np.ndarray,
    f: float,
    g: np.ndarray,
    d: np.ndarray,
    *,
    c1: float = 1e-4,
    c2: float = 0.9,
    max_evals: int = 30,
) -> tuple[float, np.ndarray, float, np.ndarray]:
    """Lewis and Overton's weak Wolfe search by bisection and doubling: a step with
    sufficient decrease and ``g(x + t d).d >= c2 g.d``; else the last step with sufficient
    decrease, else ``t = 0``. Returns ``(t, x + t d, f, g)`` there."""
    gd0 = float(g @ d)
    lo, hi, t = 0.0, math.inf, 1.0
    best: tuple[float, np.ndarray, float, np.ndarray] = (0.0, x, f, g)
    for _ in range(max_evals):
        xt = x + t * d
        ft, gt = fun(xt)
        if not ft <= f + c1 * t * gd0:  # also NaN
            hi = t
        else:
            best = (t, xt, ft, gt)
            if float(gt @ d) >= c2 * gd0:
                return best
            lo = t
        t = 2.0 * lo if math.isinf(hi) else 0.5 * (lo + hi)
    return best


def _relative(norm: float, x: np.ndarray, f: float) -> float:
    """A gradient's norm as a relative rate: ``|g| (1 + |x|_inf) / (1 + |f|)``, about the
    relative change of ``f`` per relative change of ``x``."""
    return norm * (1.0 + float(np.abs(x).max())) / (1.0 + abs(f))


class _Counted:
    """The objective of :func:`nonsmooth_bfgs` on flat arrays, counting its calls."""

    def __init__(self, fun: Objective) -> None:
        self.fun = fun
        self.count = 0

    def __call__(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        self.count += 1
        value, grad = self.fun(z)
        return float(value), np.asarray(grad, dtype=float).ravel()


def _sampled_bundle(
    counted: _Counted,
    x: np.ndarray,
    trail: list[tuple[np.ndarray, np.ndarray]],
    eps: float,
    pairs: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, int]:
    """Gradient sampling of :func:`nonsmooth_bfgs` at ``x``: the smallest convex combination
    of the gradients at the iterates within ``eps`` (relative) and at ``pairs`` random pairs
    ``x +- r``, and the size of that bundle."""
    n = x.size
    reach = eps * (1.0 + float(np.abs(x).max()))
    G = [gi for xi, gi in trail if float(np.abs(xi - x).max()) <= reach]
    for _ in range(pairs):
        r = reach * rng.uniform(-1.0, 1.0, n)
        G += [counted(x + r)[1], counted(x - r)[1]]
    d, _ = min_norm_element(np.array(G))
    return d, len(G)


def _bfgs_update(H: np.ndarray | None, s: np.ndarray, y: np.ndarray, sy: float) -> np.ndarray:
    """The inverse Hessian of :func:`nonsmooth_bfgs` after the pair ``s``, ``y`` with
    ``sy = s.y > 0`` (scaled at the first pair; ``H`` is updated in place)."""
    if H is None:
        H = np.eye(s.size) * (sy / float(y @ y))
    # the rank-two BFGS update of the inverse, O(n^2)
    Hy = H @ y
    rho = 1.0 / sy
    H += (rho * rho * float(y @ Hy) + rho) * np.outer(s, s) - rho * (
        np.outer(Hy, s) + np.outer(s, Hy)
    )
    return H


def nonsmooth_bfgs(
    fun: Objective,
    x0: np.ndarray,
    *,
    max_iter: int = 1000,
    gtol: float = 1e-6,
    ftol: float = 1e-15,
    patience: int = 10,
    radii: tuple[float, float] = (1e-4, 1e-7),
    pairs: int = 8,
    seed: int = 0,
    start: tuple[float, np.ndarray] | None = None,
    stop: Callable[[], bool] | None = None,
) -> NonsmoothResult:
    """Minimise a loss with kinks: full BFGS with a weak Wolfe line search, and gradient
    sampling where it stalls (module notes).

    BFGS runs until its line search finds no decrease or ``patience`` iterations in a row
    lower ``f`` by less than ``ftol |f|``. Then gradient sampling: the gradients at ``x``,
    at ``pairs`` pairs ``x +- eps r`` (``r`` random in the unit box, ``eps`` relative to
    ``1 + |x|_inf``) and at the iterates within ``eps`` make a bundle; the smallest convex
    combination ``d`` of it (:func:`min_norm_element`) is the certificate. Small enough
    (``|d| (1 + |x|_inf) <= gtol (1 + |f|)``): stationary, stop. Else an Armijo step along
    ``-d``; where it lowers ``f``, BFGS starts again from there; where it does not, ``eps``
    shrinks tenfold, from ``radii[0]`` down to ``radii[1]``.

    Parameters
    ----------
    fun
        The objective, ``x -> (f, g)`` on flat arrays.
    x0
        The start.
    max_iter
        The most iterations (BFGS and sampling steps together).
    gtol, ftol, patience, radii, pairs, seed
        See above; ``seed`` seeds the sampling.
    start
        ``(f, g)`` at ``x0`` when known.
    stop
        Called before each iteration; a true return value stops it (``message``
        ``"stopped"``).

    Returns
    -------
    NonsmoothResult
        The last (and best: every step lowers ``f``) iterate; ``stationarity`` the relative
        norm of the last certificate (of the gradient at ``x`` alone when no sampling ran).
    """
    rng = np.random.default_rng(seed)
    x = np.array(x0, dtype=float).ravel()
    n = x.size
    counted = _Counted(fun)
    if start is None:
        f, g = counted(x)
    else:
        f, g = float(start[0]), np.asarray(start[1], dtype=float).ravel()
    H: np.ndarray | None = None  # the inverse Hessian, scaled at the first pair
    trail: list[tuple[np.ndarray, np.ndarray]] = [(x.copy(), g.copy())]
    stale, k, bundle = 0, 0, 1
    stationarity = _relative(float(np.linalg.norm(g)), x, f)
    eps = radii[0]
    message = f"the iteration limit ({max_iter})"
    sampling = False
    while k < max_iter:
        if stop is not None and stop():
            message = "stopped"
            break
        k += 1
        if sampling:
            d, bundle = _sampled_bundle(counted, x, trail, eps, pairs, rng)
            stationarity = _relative(float(np.linalg.norm(d)), x, f)
            if stationarity <= gtol:
                message = f"stationary: gradients within {eps:.0e} cancel"
                break
            t, dd = 1.0, float(d @ d)
            for _ in range(40):  # Armijo backtracking along -d
                ft, gt = counted(x - t * d)
                if ft < f - 1e-4 * t * dd:
                    break
                t *= 0.5
            else:
                eps *= 0.1
                if eps < radii[1] * (1 - 1e-9):
                    message = f"no decrease along the sampled gradients down to {radii[1]:.0e}"
                    break
                continue
            x, f, g = x - t * d, ft, gt
            trail.append((x.copy(), g.copy()))
            sampling, stale = False, 0
            continue
        d = -g if H is None else -(H @ g)
        if not float(g @ d) < 0.0:  # not a descent direction: forget the curvature
            H, d = None, -g
        t, xn, fn, gn = _weak_wolfe(counted, x, f, g, d)
        if t == 0.0:
            sampling = True
            continue
        s, y = xn - x, gn - g
        sy = float(s @ y)
        if sy > 0.0:
            H = _bfgs_update(H, s, y, sy)
        stale = 0 if fn < f - ftol * abs(f) else stale + 1
        x, f, g = xn, fn, gn
        trail.append((x.copy(), g.copy()))
        del trail[: max(0, len(trail) - (n + 1))]
        stationarity = _relative(float(np.linalg.norm(g)), x, f)
        if stale >= patience:
            sampling = True
    return NonsmoothResult(
        x=x, f=f, g=g, iterations=k, evaluations=counted.count, message=message,
        stationarity=stationarity, bundle=bundle,
    )  # fmt: skip
