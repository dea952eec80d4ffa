"""The contact models side by side: gradient checks and the paper's comparison.

:func:`gradient_errors` measures how right a contact model's gradient is: the gradient of the
discrete loss (torch autograd through :class:`~hybridoc.solvers.simulator.Simulator`) against
the exact gradient of the continuous cost (:func:`hybridoc.gradient`, the HMP adjoint), with
respect to the initial positions, the initial velocities and the controls.
:func:`gradcheck_points` gives the points (the initial guess and iterates of plain gradient
descent). :func:`compare_contacts` runs the paper's plain gradient descent with every contact
model and reports the discrete loss and the true continuous cost (the paper's Figures 5/6 and
10/11). The models compared are read from the registry (:func:`compared_models`). The
``hybridoc gradcheck`` and ``hybridoc compare-contacts`` commands print these.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.errors import SceneError
from hybridoc.problem import ProblemLike, as_ocp, disc_scene
from hybridoc.progress import ProgressLike, progress_scope
from hybridoc.solvers.contacts import CONTACT_MODELS, ContactModel, contact_model

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.solution import Solution

__all__ = [
    "compare_contacts",
    "DEFAULT_GD_SETTINGS",
    "compared_models",
    "contact_note",
    "gradcheck_points",
    "gradient_errors",
    "paper_gd_settings",
    "parse_models",
]


def compared_models() -> list[ContactModel]:
    """The models compared by default, read from the registry: the paper's baseline
    ``direct/none``, every impulse model with both TOI corrections, every other model."""
    out = [contact_model("direct", toi="none")]
    for cls in CONTACT_MODELS.values():
        out.append(cls(toi="both") if cls.impulse_based else cls())
    return out


def parse_models(names: str | None) -> list[ContactModel]:
    """Models from a comma-separated list such as ``"direct/none,lcp/both,pbd"``."""
    if not names:
        return compared_models()
    out = []
    for name in names.split(","):
        name = name.strip()
        if not name:
            continue
        try:
            out.append(contact_model(name))
        except SceneError as exc:
            raise SceneError(f"{exc} (give a comma-separated list, e.g. direct/none,pbd)") from None
    return out


DEFAULT_GD_SETTINGS: tuple[float, int] = (50.0, 500)
"""``(learning rate, iterations)`` of plain gradient descent on a scene whose author gave
no gd hints."""


def paper_gd_settings(scene: ProblemLike) -> tuple[float, int]:
    """``(learning rate, iterations)`` of the paper's plain gradient descent on ``scene``.

    The problem's own gd hints ``lr`` and ``iters``
    (:meth:`~hybridoc.capabilities.Capabilities.hints_for`; a scene file's ``[hints.gd]``:
    the paper's scenes carry the paper's settings, 200 and 500 on single-collision, 50 and
    1500 on multiple-collision, :data:`hybridoc.problems.paper.PAPER_SETTINGS`), each
    defaulting to :data:`DEFAULT_GD_SETTINGS` (50 and 500).

    Parameters
    ----------
    scene : ProblemLike
        The disc scene (any problem, :func:`hybridoc.problem.as_ocp`).

    Returns
    -------
    tuple of (float, int)
    """
    hints = as_ocp(scene).capabilities.hints_for("gd")
    lr, iters = DEFAULT_GD_SETTINGS
    return hints.get("lr", lr), hints.get("iters", iters)


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    nb = float(np.linalg.norm(b))
    diff = float(np.linalg.norm(np.asarray(a) - np.asarray(b)))
    return diff / nb if nb > 0 else (0.0 if diff == 0 else math.inf)


def gradient_errors(
    scene: ProblemLike, controls: np.ndarray, model: ContactModel, exact: Any = None
) -> dict[str, Any]:
    """Relative errors of one contact model's gradient against the exact gradient.

    Parameters
    ----------
    scene : ProblemLike
        The disc scene (:func:`hybridoc.problem.disc_scene`).
    controls : numpy.ndarray
        ``(N, nu)`` piecewise-constant controls at which both gradients are taken.
    model : ContactModel
        The contact model.
    exact : hybridoc.Gradient, optional
        The :class:`hybridoc.Gradient` at ``controls`` if already computed.

    Returns
    -------
    dict
        ``loss`` (discrete objective), ``cost`` (continuous cost), and the relative errors
        ``||g_sim - g_exact|| / ||g_exact||`` for the initial positions (``err_position``),
        initial velocities (``err_velocity``) and controls (``err_controls``); ``cosine`` is
        the cosine between the two control gradients.
    """
    import torch

    import hybridoc

    scene = disc_scene(scene)
    if exact is None:
        exact = hybridoc.gradient(scene, controls)
    from hybridoc.solvers.simulator import Simulator

    sim = Simulator(scene, contact=model)
    u = torch.tensor(np.asarray(controls, dtype=float), dtype=torch.float64, requires_grad=True)
    x0 = sim.x0.detach().clone().requires_grad_(True)
    loss = sim.loss(u, x0)
    loss.backward()
    gx = x0.grad.detach().cpu().numpy()
    gu = u.grad.detach().cpu().numpy()
    ex = np.asarray(exact.d_initial_state, dtype=float)
    eu = np.asarray(exact.d_controls, dtype=float)
    n2 = 2 * scene.n_discs
    nu_norm = float(np.linalg.norm(gu) * np.linalg.norm(eu))
    return {
        "loss": float(loss.detach()),
        "cost": float(exact.cost),
        "err_position": _rel(gx[:n2], ex[:n2]),
        "err_velocity": _rel(gx[n2:], ex[n2:]),
        "err_controls": _rel(gu, eu),
        "cosine": float(np.sum(gu * eu) / nu_norm) if nu_norm > 0 else math.nan,
    }


def gradcheck_points(scene: ProblemLike, gd_iters: list[int]) -> list[tuple[str, np.ndarray]]:
    """The controls at which ``gradcheck`` compares gradients on a disc scene
    (:func:`hybridoc.problem.disc_scene`).

    The initial guess and the iterates ``gd_iters`` of the paper's plain gradient descent with
    the default contact model (``direct``, TOI ``both``), so that the points follow the path an
    optimiser takes towards the optimum.
    """
    scene = disc_scene(scene)
    points = [("initial", scene.initial_controls())]
    wanted = sorted({int(k) for k in gd_iters if int(k) > 0})
    if not wanted:
        return points
    from hybridoc.solvers.gd import solve_gd

    lr, _ = paper_gd_settings(scene)
    saved: dict[int, np.ndarray] = {}

    def keep(k: int, loss: float, u: np.ndarray) -> bool:
        if k in wanted:
            saved[k] = u
        return k >= wanted[-1]

    solve_gd(
        scene, optimizer="gd", lr=lr, iters=wanted[-1], callback=keep,
        integrator="symplectic-euler",
    )  # fmt: skip
    points += [(f"gd-{k}", saved[k]) for k in wanted if k in saved]
    return points


def compare_contacts(
    scene: ProblemLike,
    *,
    models: list[ContactModel] | None = None,
    iters: int | None = None,
    lr: float | None = None,
    progress: ProgressLike = None,
) -> dict[str, Solution]:
    """Plain gradient descent (the paper's settings, symplectic Euler) with every model.

    Every model runs on the compiled CasADi path where it has one for ``scene``
    (:func:`hybridoc.solvers.gd.make_loss`), else on the torch simulator.

    Parameters
    ----------
    scene : ProblemLike
        The disc scene (any problem that names one).
    models : list of ContactModel, optional
        The contact models (default :func:`compared_models`).
    iters, lr : int and float, optional
        Iterations and learning rate (default :func:`paper_gd_settings`).
    progress : bool or Progress, optional
        ``True`` for a progress meter on stderr, or a :class:`~hybridoc.progress.Progress`:
        a stage per model, named after it, and a count of its iterations.

    Returns
    -------
    dict
        ``{model label: hybridoc.solution.Solution}`` in the order of ``models``; each
        Solution carries the discrete loss (``info["loss"]``), the true continuous cost
        (``cost``), the events of its controls (``events``, see :func:`contact_note`) and the
        learning curve (``arrays["loss_history"]``).
    """
    from hybridoc.solvers.gd import solve_gd

    lr0, it0 = paper_gd_settings(scene)
    iters = it0 if iters is None else iters
    models = list(models or compared_models())
    out = {}
    with progress_scope(progress, "compare-contacts") as meter:
        for k, model in enumerate(models, 1):
            meter.stage(f"{model.label} ({k}/{len(models)})")

            def show(it: int, loss: float, _u: Any) -> bool:
                meter.count(it, iters, f"loss {loss:.6g}")
                return False

            sol = solve_gd(
                scene,
                contact=model,
                integrator="symplectic-euler",
                optimizer="gd",
                lr=lr0 if lr is None else lr,
                iters=iters,
                callback=show,
            )
            meter.count(sol.info["iterations"], iters, f"loss {sol.info['loss']:.6g}")
            out[model.label] = sol
    return out


def contact_note(label: str, sol: Solution) -> str | None:
    """``"<label>: no contact in the final trajectory"`` when the event-exact evaluation of a
    solution's controls has no contact event (the models were not compared on a collision),
    else ``None``."""
    if sol.events:
        return None
    return f"{label}: no contact in the final trajectory"
