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
from typing import Any

import numpy as np

from hybridoc.errors import SceneError
from hybridoc.solvers.contacts import CONTACT_MODELS, ContactModel, contact_model

__all__ = [
    "PAPER_OPTIMUM",
    "compare_contacts",
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


#: Paper learning rates of plain gradient descent (section 5), 50 elsewhere.
_PAPER_LR = {"single-collision": 200.0, "multiple-collision": 50.0}
_PAPER_ITERS = {"single-collision": 500, "multiple-collision": 1500}
#: The optimal losses the paper reports from its grid search (Table 1), drawn in the
#: learning-curve figure. The exact optima are 0.311416870358 and 0.356279430543.
PAPER_OPTIMUM = {"single-collision": 0.3115, "multiple-collision": 0.3737}


def paper_gd_settings(scene: Any) -> tuple[float, int]:
    """``(learning rate, iterations)`` of the paper's plain gradient descent on ``scene``.

    200 and 500 on single-collision, 50 and 1500 on multiple-collision; 50 and 500 elsewhere.
    """
    return _PAPER_LR.get(scene.name, 50.0), _PAPER_ITERS.get(scene.name, 500)


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    nb = float(np.linalg.norm(b))
    diff = float(np.linalg.norm(np.asarray(a) - np.asarray(b)))
    return diff / nb if nb > 0 else (0.0 if diff == 0 else math.inf)


def gradient_errors(
    scene: Any, controls: np.ndarray, model: ContactModel, exact: Any = None
) -> dict[str, Any]:
    """Relative errors of one contact model's gradient against the exact gradient.

    Parameters
    ----------
    scene
        A :class:`~hybridoc.problems.Scene`.
    controls
        ``(N, nu)`` piecewise-constant controls at which both gradients are taken.
    model
        The contact model.
    exact
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


def gradcheck_points(scene: Any, gd_iters: list[int]) -> list[tuple[str, np.ndarray]]:
    """The controls at which ``gradcheck`` compares gradients.

    The initial guess and the iterates ``gd_iters`` of the paper's plain gradient descent with
    the default contact model (``direct``, TOI ``both``), so that the points follow the path an
    optimiser takes towards the optimum.
    """
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
    scene: Any,
    *,
    models: list[ContactModel] | None = None,
    iters: int | None = None,
    lr: float | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Plain gradient descent (the paper's settings, symplectic Euler) with every model.

    Every model runs on the compiled CasADi path where it has one for ``scene``
    (:func:`hybridoc.solvers.gd.make_loss`), else on the torch simulator.

    Parameters
    ----------
    scene
        A :class:`~hybridoc.problems.Scene`.
    models
        The contact models (default :func:`compared_models`).
    iters, lr
        Iterations and learning rate (default :func:`paper_gd_settings`).
    progress
        Show on stderr a progress line per model, named after the model.

    Returns
    -------
    dict
        ``{model label: hybridoc.solution.Solution}`` in the order of ``models``; each
        Solution carries the discrete loss (``info["loss"]``), the true continuous cost
        (``cost``), the events of its controls (``events``, see :func:`contact_note`) and the
        learning curve (``arrays["loss_history"]``).
    """
    from hybridoc.solvers.gd import _Progress, solve_gd

    lr0, it0 = paper_gd_settings(scene)
    iters = it0 if iters is None else iters
    models = list(models or compared_models())
    out = {}
    for k, model in enumerate(models, 1):
        toi = getattr(model, "toi", "both")
        bar = _Progress(iters, f"{model.label} ({k}/{len(models)})") if progress else None

        def show(it: int, loss: float, _u: Any, bar: Any = bar) -> bool:
            bar.update(it, loss)
            return False

        try:
            sol = solve_gd(
                scene,
                contact=model.name,
                toi=toi,
                integrator="symplectic-euler",
                optimizer="gd",
                lr=lr0 if lr is None else lr,
                iters=iters,
                callback=show if bar is not None else None,
            )
            if bar is not None:
                bar.update(sol.info["iterations"], sol.info["loss"], force=True)
        finally:
            if bar is not None:
                bar.close()
        out[model.label] = sol
    return out


def contact_note(label: str, sol: Any) -> str | None:
    """``"<label>: no contact in the final trajectory"`` when the event-exact evaluation of a
    solution's controls has no contact event (the models were not compared on a collision),
    else ``None``."""
    if sol.events:
        return None
    return f"{label}: no contact in the final trajectory"
