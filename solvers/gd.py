"""Optimal control by gradient descent through the differentiable simulator.

:func:`solve_gd` minimises the discrete objective of the paper's Eq. 8,
``phi(s_N) + sum_n eps |u_n|^2 dt`` over the ``N x nu`` piecewise-constant controls, with the
gradients of :class:`~hybridoc.solvers.simulator.Simulator` (or of its compiled twin
:class:`~hybridoc.solvers.compiled.CompiledLoss` for the default ``direct`` contact model), and
measures the result with the event-exact evaluator: the returned
:class:`~hybridoc.solution.Solution` carries the *true* continuous cost of the controls.
"""

from __future__ import annotations

import functools
import math
import numbers
import sys
import time
import tomllib
import warnings
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np
import torch

from hybridoc.errors import ControlsError, SceneError

__all__ = ["solve_gd", "PAPER_SETTINGS", "OPTIMIZERS", "DEFAULT_SMOOTHING", "default_settings"]

OPTIMIZERS = ("gd", "adam", "lbfgs")

PAPER_SETTINGS: dict[str, tuple[float, int]] = {
    "single-collision": (200.0, 500),
    "multiple-collision": (50.0, 1500),
}
"""The paper's plain gradient descent: ``scene name -> (learning rate, iterations)``."""

DEFAULT_SMOOTHING = (1e-4, 1e-5, 1e-6)
"""Default continuation weights of ``lbfgs`` (see ``smoothing`` in :func:`solve_gd`)."""


def _positive(x: Any) -> bool:
    """``x`` is a real number, finite and > 0 (not a string, not a bool)."""
    return isinstance(x, numbers.Real) and not isinstance(x, bool) and math.isfinite(x) and x > 0


class _NonFinite(Exception):
    """The loss or its gradient became NaN or infinite."""


def default_settings(scene: Any, optimizer: str) -> tuple[float, int]:
    """Default ``(learning rate, iterations)`` of an optimiser on a scene.

    Plain ``gd`` uses the paper's settings on the paper's problems and otherwise a learning
    rate of ``0.1 / dt`` (the gradient with respect to one control value scales with ``dt``)
    for 1000 iterations; ``adam`` uses 0.05 for 1000 iterations; ``lbfgs`` a step of 0.1 (the
    first trial step of its strong-Wolfe line search) for at most 300 iterations: with 1.0 it
    leaps from the multiple-collision guess to ``u = 0``, where nothing collides.
    """
    if optimizer == "gd":
        return PAPER_SETTINGS.get(scene.name, (0.1 / scene.dt, 1000))
    if optimizer == "adam":
        return 0.05, 1000
    if optimizer == "lbfgs":
        return 0.1, 300
    raise SceneError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")


class _Progress:
    """A one-line progress bar on stderr."""

    def __init__(self, total: int, label: str) -> None:
        self.total, self.label, self.last = total, label, 0.0

    def update(self, k: int, loss: float, force: bool = False) -> None:
        now = time.perf_counter()
        if not force and now - self.last < 0.1:
            return
        self.last = now
        width = 30
        filled = int(width * k / max(self.total, 1))
        bar = "#" * filled + "." * (width - filled)
        sys.stderr.write(f"\r{self.label} [{bar}] {k}/{self.total} loss {loss:.6g}")
        sys.stderr.flush()

    def close(self) -> None:
        sys.stderr.write("\n")
        sys.stderr.flush()


@functools.lru_cache(maxsize=2)
def _compiled_cached(scene_toml: str, toi: str, integrator: str) -> Any:
    from hybridoc.problems import Scene
    from hybridoc.solvers.compiled import CompiledLoss

    return CompiledLoss(Scene.from_dict(tomllib.loads(scene_toml)), toi=toi, integrator=integrator)


def _compiled_loss(scene: Any, toi: str, integrator: str) -> Any:
    # building the compiled graph takes about a second: reuse it across continuation stages
    # and repeated solves of the same scene
    return _compiled_cached(scene.to_toml(), toi, integrator)


def _make_loss(
    scene: Any, impulse: str, toi: str, contact: str | None, path: str, integrator: str
) -> Any:
    from hybridoc.solvers.simulator import IMPULSE_METHODS, Simulator

    if contact in IMPULSE_METHODS:
        impulse, contact = contact, None
    compilable = contact is None and impulse == "direct"
    if path not in ("auto", "compiled", "torch"):
        raise SceneError(f"unknown path {path!r}; choose auto, compiled or torch")
    if path == "compiled" and not compilable:
        raise SceneError("the compiled path exists only for the 'direct' impulse model")
    if path == "compiled" or (path == "auto" and compilable):
        return _compiled_loss(scene, toi, integrator), "compiled"
    sim = Simulator(scene, impulse=impulse, toi=toi, contact=contact, integrator=integrator)
    return sim, "torch"


def solve_gd(
    scene: Any,
    *,
    impulse: str = "direct",
    toi: str = "both",
    contact: str | None = None,
    optimizer: str = "lbfgs",
    iters: int | None = None,
    lr: float | None = None,
    callback: Callable[[int, float, np.ndarray], Any] | None = None,
    progress: bool = False,
    path: str = "auto",
    initial_controls: Any = None,
    integrator: str = "symplectic-euler",
    max_step: float | None = None,
    smoothing: Sequence[float] | None = None,
    _penalty: float = 0.0,
) -> Any:
    """Minimise the discrete objective by gradient descent through the simulator.

    Parameters
    ----------
    scene
        A :class:`~hybridoc.problems.Scene`, a built-in name or a TOML path.
    impulse, toi, contact
        The contact model, as in :class:`~hybridoc.solvers.simulator.Simulator`.
    optimizer
        ``"gd"`` (plain gradient descent, as in the paper), ``"adam"`` or ``"lbfgs"``
        (``torch.optim.LBFGS`` with a strong-Wolfe line search; default).
    iters, lr
        Iterations and learning rate; defaults from :func:`default_settings`.
    callback
        Called as ``callback(iteration, loss, controls)`` after every iteration; a true
        return value stops the optimisation.
    progress
        Show a progress bar on stderr (quiet by default).
    path
        ``"auto"`` (the compiled CasADi path where it exists, i.e. for ``direct`` impulses,
        else torch), ``"compiled"`` or ``"torch"``.
    initial_controls
        ``(N, nu)`` starting controls; default the scene's initial guess.
    integrator
        ``"symplectic-euler"`` (the paper's) or ``"exact"`` (exact flow and exact time of
        impact: the discrete loss equals the continuous cost; see
        :class:`~hybridoc.solvers.simulator.Simulator`).
    max_step
        ``lbfgs`` only: the largest change of any control value in one iteration (longer
        steps are shortened and the curvature history is reset); default: no limit.
    smoothing
        Continuation weights ``mu_1 > mu_2 > ...``: before the real problem, solve it with the
        penalty ``mu sum_n |u_{n+1} - u_n|^2 / dt`` (about ``mu int |du/dt|^2 dt``) added, for
        each ``mu`` in turn, each stage starting from the previous result (``iters`` iterations
        per stage). The loss of piecewise-constant controls has a kink wherever an event
        crosses a grid time at which the control jumps, and gradient methods stall there; the
        penalty weakens those kinks so that the events first move to the right times.
        Default: :data:`DEFAULT_SMOOTHING` for ``lbfgs``, none for ``gd`` and ``adam``.

    Returns
    -------
    hybridoc.solution.Solution
        Method ``"gd"``; the controls of the last iterate (of the best iterate if the loss
        became NaN or infinite, in which case a ``RuntimeWarning`` is issued and
        ``info["message"]`` says so). ``cost`` and its parts are the true continuous cost from
        :func:`hybridoc.evaluate`; ``info["loss"]`` is the discrete objective of the returned
        controls, ``info["iterations"]`` the iterations done; ``arrays["loss_history"]`` the
        discrete objective at the start of every iteration followed by the final one.

    Raises
    ------
    hybridoc.errors.SceneError
        An unknown scene, contact model, optimizer, integrator or path; ``iters`` not an
        integer >= 0; ``lr`` or ``max_step`` not a positive finite number; negative or
        non-finite smoothing weights.
    hybridoc.errors.ControlsError
        ``initial_controls`` of the wrong shape or not finite.
    """
    import hybridoc
    from hybridoc.problems import load_scene
    from hybridoc.solution import Solution

    scene = load_scene(scene)
    if optimizer not in OPTIMIZERS:
        raise SceneError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")
    lr0, it0 = default_settings(scene, optimizer)
    lr = lr0 if lr is None else lr
    iters = it0 if iters is None else iters
    # checked strictly: int(1.5) or float("1e-3") would hide a mistake in the caller
    if isinstance(iters, bool) or not isinstance(iters, numbers.Integral) or iters < 0:
        raise SceneError(f"iters must be an integer >= 0, got {iters!r}")
    if not _positive(lr):
        raise SceneError(f"lr must be a positive finite number, got {lr!r}")
    if max_step is not None and not _positive(max_step):
        raise SceneError(f"max_step must be a positive finite number or None, got {max_step!r}")
    iters, lr = int(iters), float(lr)
    t_start = time.perf_counter()
    loss_obj, used_path = _make_loss(scene, impulse, toi, contact, path, integrator)

    u0 = scene.initial_controls() if initial_controls is None else initial_controls
    try:
        u0 = np.array(u0, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ControlsError(f"initial controls: not a numeric array ({exc})") from None
    if u0.shape != (scene.steps, scene.n_controls) or not np.isfinite(u0).all():
        raise ControlsError(
            f"initial controls must be finite with shape ({scene.steps}, {scene.n_controls})"
        )
    if smoothing is None:
        smoothing = DEFAULT_SMOOTHING if optimizer == "lbfgs" and not _penalty else ()
    weights = tuple(smoothing) if isinstance(smoothing, Iterable | np.ndarray) else None
    if (
        isinstance(smoothing, str)
        or weights is None
        or not all(isinstance(m, numbers.Real) and math.isfinite(m) and m >= 0 for m in weights)
    ):
        raise SceneError(f"smoothing weights must be finite numbers >= 0, got {smoothing!r}")
    smoothing = tuple(float(m) for m in weights)
    if smoothing:
        kwargs = dict(
            impulse=impulse, toi=toi, contact=contact, optimizer=optimizer, iters=iters, lr=lr,
            callback=callback, progress=progress, path=path, integrator=integrator,
            max_step=max_step, smoothing=(),
        )  # fmt: skip
        histories, its, stages = [], 0, []
        for mu in smoothing:
            stage = solve_gd(scene, initial_controls=u0, _penalty=mu, **kwargs)
            u0 = stage.controls
            histories.append(stage.arrays["loss_history"])
            its += stage.info["iterations"]
            stages.append({"mu": mu, "loss": stage.info["loss"], "cost": stage.cost})
        sol = solve_gd(scene, initial_controls=u0, **kwargs)
        sol.settings["smoothing"] = list(smoothing)
        sol.info["iterations"] += its
        sol.info["stages"] = stages
        sol.arrays["loss_history"] = np.concatenate(histories + [sol.arrays["loss_history"]])
        sol.timings["solve_time_s"] = time.perf_counter() - t_start
        return sol
    u = torch.tensor(u0, dtype=torch.float64, requires_grad=True)
    best = {"loss": math.inf, "u": u0.copy()}
    n_evals = 0

    def evaluate_loss() -> torch.Tensor:
        nonlocal n_evals
        n_evals += 1
        if not torch.isfinite(u).all():
            raise _NonFinite("the controls became NaN or infinite")
        value = loss_obj.loss(u)
        if _penalty:
            value = value + _penalty * ((u[1:] - u[:-1]) ** 2).sum() / scene.dt
        val = float(value.detach())
        if not math.isfinite(val):
            raise _NonFinite(f"the loss became {val}")
        if val < best["loss"]:
            best["loss"], best["u"] = val, u.detach().numpy().copy()
        return value

    # L-BFGS has absolute thresholds (curvature pairs with y.s <= 1e-10 are dropped) while the
    # gradient with respect to one control value scales with dt: it sees the loss divided by dt.
    scale = 1.0 / scene.dt if optimizer == "lbfgs" else 1.0

    def closure() -> torch.Tensor:
        opt.zero_grad()
        value = evaluate_loss() * scale
        value.backward()
        if not torch.isfinite(u.grad).all():
            raise _NonFinite("the gradient became NaN or infinite")
        return value

    # A quasi-Newton step can leap into another contact sequence (on the multiple-collision
    # problem with lr = 1 straight to u = 0, where nothing collides and the terminal cost is
    # flat). Optionally, longer L-BFGS steps are cut back (inf-norm) and the history reset.
    if max_step is None:
        max_step = math.inf

    def make_optimizer() -> torch.optim.Optimizer:
        if optimizer == "gd":
            return torch.optim.SGD([u], lr=lr)
        if optimizer == "adam":
            return torch.optim.Adam([u], lr=lr)
        return torch.optim.LBFGS(
            [u],
            lr=lr,
            max_iter=1,
            history_size=50,
            line_search_fn="strong_wolfe",
            tolerance_grad=1e-12,
            tolerance_change=1e-15,
        )

    opt = make_optimizer()
    history: list[float] = []
    message = "finished the requested iterations"
    label = f"gd/{optimizer}" + (f" (smoothing stage, mu {_penalty:g})" if _penalty else "")
    bar = _Progress(iters, label) if progress else None
    k = 0
    fresh, restarts = True, 0
    t_loop = time.perf_counter()
    try:
        for k in range(iters):
            if optimizer == "lbfgs":
                if not history:
                    history.append(float(evaluate_loss().detach()))
                before = u.detach().clone()
                opt.step(closure)
                jump = float((u.detach() - before).abs().max())
                if jump > max_step:
                    with torch.no_grad():
                        u.copy_(before + (u - before) * (max_step / jump))
                    opt, fresh, restarts = make_optimizer(), True, restarts + 1
                    value = float(evaluate_loss().detach())
                    if value > history[-1]:
                        with torch.no_grad():
                            u.copy_(before)
                        value = history[-1]
                    history.append(value)
                elif torch.equal(before, u.detach()):
                    # Kinks of the loss (a contact moving to another step) can spoil the
                    # quasi-Newton model: restart from here with an empty history; stop when a
                    # fresh start makes no progress either.
                    history.append(history[-1])
                    if fresh:
                        message = "converged: L-BFGS made no further progress"
                        k += 1
                        break
                    opt, fresh, restarts = make_optimizer(), True, restarts + 1
                else:
                    history.append(float(evaluate_loss().detach()))
                    fresh = False
            else:
                history.append(float(closure().detach()))
                opt.step()
            if bar:
                bar.update(k + 1, history[-1])
            if callback is not None and callback(k + 1, history[-1], u.detach().numpy().copy()):
                message = "stopped by the callback"
                k += 1
                break
        else:
            k = iters
        if optimizer != "lbfgs" or not history:
            history.append(float(evaluate_loss().detach()))
        final_u = u.detach().numpy().copy()
        final_loss = history[-1]
        nan_stop = False
    except _NonFinite as exc:
        nan_stop = True
        final_u, final_loss = best["u"], best["loss"]
        message = (
            f"stopped early at iteration {k}: {exc}; returning the best iterate "
            f"(discrete loss {final_loss:.6g}); try a smaller learning rate"
        )
        warnings.warn(f"solve_gd: {message}", RuntimeWarning, stacklevel=2)
    finally:
        if bar:
            bar.update(k, history[-1] if history else math.nan, force=True)
            bar.close()
    t_opt = time.perf_counter() - t_loop
    ev = hybridoc.evaluate(scene, final_u)
    t_total = time.perf_counter() - t_start
    settings = {
        "impulse": impulse,
        "toi": toi,
        "contact": contact,
        "integrator": integrator,
        "optimizer": optimizer,
        "iters": iters,
        "lr": lr,
        "path": used_path,
    }
    info = {
        "loss": float(final_loss),
        "iterations": int(k),
        "loss_evaluations": int(n_evals),
        "nan_stop": nan_stop,
        "message": message,
        "ms_per_iteration": 1e3 * t_opt / max(k, 1),
        "restarts": restarts,
    }
    return Solution.from_evaluation(
        ev,
        method="gd",
        scene=scene,
        settings=settings,
        timings={"solve_time_s": t_total, "optimization_time_s": t_opt},
        info=info,
        arrays={"loss_history": np.array(history, dtype=float)},
    )
