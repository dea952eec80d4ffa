"""Figures: scenes with trajectories, controls and costates against time.

Every function returns a :class:`matplotlib.figure.Figure` built without pyplot, so nothing
is ever shown and no interactive backend is needed; :func:`save_figure` writes PNG through
matplotlib's Agg renderer.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, Patch, Polygon

from hybridoc.errors import SceneError

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.capabilities import Geometry

__all__ = [
    "mark_stages",
    "plot_controls",
    "plot_costates",
    "plot_landscape",
    "plot_scene",
    "plot_states",
    "plot_trajectories",
    "save_figure",
]

_POINTS_PER_INTERVAL = 10


def _colors(n: int) -> list[Any]:
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    return [cmap(k % 10) for k in range(n)]


def _positions(states: np.ndarray, geometry: Geometry) -> np.ndarray:
    """``(M, nx)`` states -> ``(M, n_bodies, 2)`` the bodies' positions."""
    states = np.asarray(states)
    return np.stack([geometry.position(states, i) for i in range(geometry.n_bodies)], axis=1)


def _path_states(evaluation: Any) -> np.ndarray:
    """States sampled densely along the trajectory (positions are continuous at jumps)."""
    if getattr(evaluation, "segments", None):
        ocp = evaluation.ocp
        t = np.linspace(0.0, ocp.horizon, _POINTS_PER_INTERVAL * ocp.steps + 1)
        return evaluation.sample(t)
    return np.asarray(evaluation.states)


def _wall_geometry(
    point: np.ndarray, normal: np.ndarray, box: tuple[float, float, float, float], depth: float
) -> tuple[np.ndarray, np.ndarray]:
    """End points of the wall across ``box`` and the hatched strip on its solid side."""
    x0, x1, y0, y1 = box
    along = np.array([-normal[1], normal[0]])
    corners = np.array([[x0, y0], [x0, y1], [x1, y0], [x1, y1]])
    proj = (corners - point) @ along
    lo, hi = proj.min() - 1.0, proj.max() + 1.0  # beyond the box; the axes clip
    a, b = point + lo * along, point + hi * along
    strip = np.array([a, b, b - depth * normal, a - depth * normal])
    return np.array([a, b]), strip


def plot_scene(
    scene: Any,
    evaluation: Any = None,
    *,
    ax: Axes | None = None,
    title: str | None = None,
) -> Figure:
    """Draw a problem's bodies and walls to scale, optionally with the trajectory of an
    evaluation.

    What is drawn is the problem's geometry (:attr:`HybridOCP.capabilities.geometry
    <hybridoc.capabilities.Capabilities.geometry>`: a disc scene's discs and walls), the
    bodies at the positions of its initial state. Discs are drawn filled there and, with an
    evaluation, at ``t = T`` (dashed outline) and faintly where they take part in an event;
    paths of the disc centres, contact points of the events (crosses, numbered in time
    order), walls (thick line, hatched on the solid side) and targets (stars).

    Parameters
    ----------
    scene
        A problem with a geometry: a :class:`~hybridoc.problems.Scene`, a built-in name, a
        TOML path or a :class:`~hybridoc.HybridOCP` (anything
        :func:`~hybridoc.problem.as_ocp` takes).
    evaluation
        Optional :class:`~hybridoc.Evaluation` of this scene.
    ax
        Axes to draw into; default: a new figure.
    title
        Axes title; default: the scene name.

    Returns
    -------
    matplotlib.figure.Figure

    Raises
    ------
    hybridoc.errors.SceneError
        The problem has no geometry (plot its states with :func:`plot_trajectories`).
    """
    from hybridoc.problem import as_ocp

    ocp = as_ocp(scene)
    geo = ocp.capabilities.geometry
    if geo is None:
        raise SceneError(
            f"{ocp.name!r} has no geometry (bodies and walls) to draw: plot_trajectories "
            "draws its states against time"
        )
    n = geo.n_bodies
    radii = np.array([b.radius for b in geo.bodies])
    colors = _colors(n)
    p0 = _positions(np.asarray(ocp.x0, dtype=float)[None, :], geo)[0]

    path = None
    if evaluation is not None:
        path = _positions(_path_states(evaluation), geo)
        p_final = _positions(np.asarray(evaluation.final_state)[None, :], geo)[0]
    events = list(getattr(evaluation, "events", []) or [])

    box, span = _scene_box(geo, p0, radii, path)
    if ax is None:
        aspect = (box[3] - box[2]) / (box[1] - box[0])
        width = 7.5
        height = float(np.clip(5.2 * aspect, 3.5, 8.0)) + 0.6
        fig = Figure(figsize=(width, height), layout="constrained")
        ax = fig.add_subplot()
    else:
        fig = ax.figure  # type: ignore[assignment]
    handles: list[Any] = []

    _draw_walls(ax, geo, box, span, handles)
    _draw_discs(ax, geo, p0, colors, handles)
    if path is not None:
        for i in range(n):
            ax.plot(path[:, i, 0], path[:, i, 1], color=colors[i], lw=1.4)
            ax.add_patch(
                Circle(p_final[i], radii[i], fill=False, edgecolor=colors[i], lw=1.3, ls="--")
            )
        handles.append(Line2D([], [], color="0.3", lw=1.4, label="path of centre"))
        handles.append(Patch(facecolor="none", edgecolor="0.3", ls="--", label="position at t = T"))
    _draw_events(ax, geo, events, colors, handles)

    for i, d in enumerate(geo.bodies):
        if d.target is not None:
            ax.plot(*d.target, marker="*", ms=16, color=colors[i], mec="k", mew=0.8, zorder=6)
    if any(d.target is not None for d in geo.bodies):
        handles.append(
            Line2D([], [], color="0.5", marker="*", ls="none", ms=12, mec="k", label="target")
        )

    ax.set_xlim(box[0], box[1])
    ax.set_ylim(box[2], box[3])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.grid(True, lw=0.4, alpha=0.5)
    ax.set_title(title if title is not None else ocp.name)
    ax.legend(
        handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False
    )
    return fig


def _scene_box(
    geo: Geometry, p0: np.ndarray, radii: np.ndarray, path: np.ndarray | None
) -> tuple[tuple[float, float, float, float], float]:
    """The padded, square-ish view ``(x0, x1, y0, y1)`` of everything drawn, and its span."""
    # bounding box of everything drawn (discs with their radii, paths, targets)
    pts = [p0 - radii[:, None], p0 + radii[:, None]]
    if path is not None:
        flat = path.reshape(-1, 2)
        pts += [flat - radii.max(), flat + radii.max()]
    pts += [np.array([d.target]) for d in geo.bodies if d.target is not None]
    allp = np.vstack(pts)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    for w in geo.planes:  # keep the nearest point of each wall in view
        c = (lo + hi) / 2
        nrm = np.array(w.normal)
        q = c - ((c - np.array(w.point)) @ nrm) * nrm
        lo, hi = np.minimum(lo, q), np.maximum(hi, q)
    span = max(hi - lo)
    pad = 0.08 * span + 0.05
    lo, hi = lo - pad, hi + pad
    # a square-ish box avoids very thin figures
    size = hi - lo
    if size[0] < 0.5 * size[1]:
        extra = (0.5 * size[1] - size[0]) / 2
        lo[0], hi[0] = lo[0] - extra, hi[0] + extra
    elif size[1] < 0.5 * size[0]:
        extra = (0.5 * size[0] - size[1]) / 2
        lo[1], hi[1] = lo[1] - extra, hi[1] + extra
    return (lo[0], hi[0], lo[1], hi[1]), span


def _draw_walls(
    ax: Axes, geo: Geometry, box: tuple[float, float, float, float], span: float, handles: list[Any]
) -> None:
    """Each wall as a thick line across the view, hatched on its solid side."""
    for w in geo.planes:
        line, strip = _wall_geometry(
            np.array(w.point), np.array(w.normal), box, depth=0.04 * span + 0.03
        )
        ax.add_patch(
            Polygon(strip, closed=True, facecolor="0.85", edgecolor="0.35", hatch="///", lw=0)
        )
        ax.plot(line[:, 0], line[:, 1], color="0.15", lw=3, solid_capstyle="butt")
    if geo.planes:
        handles.append(Patch(facecolor="0.85", edgecolor="0.35", hatch="///", label="wall"))


def _draw_discs(
    ax: Axes, geo: Geometry, p0: np.ndarray, colors: list[Any], handles: list[Any]
) -> None:
    """The discs at their initial positions, filled and named."""
    for i, d in enumerate(geo.bodies):
        role = "actuated" if d.actuated else "passive"
        ax.add_patch(
            Circle(p0[i], d.radius, facecolor=colors[i], alpha=0.35, edgecolor=colors[i], lw=1.5)
        )
        ax.text(*p0[i], d.name, ha="center", va="center", fontsize=8)
        handles.append(
            Patch(facecolor=colors[i], alpha=0.5, edgecolor=colors[i], label=f"{d.name} ({role})")
        )


def _draw_events(
    ax: Axes, geo: Geometry, events: list[Any], colors: list[Any], handles: list[Any]
) -> None:
    """The discs faintly where they take part in an event and the numbered contact points."""
    names = [d.name for d in geo.bodies]
    radii = np.array([d.radius for d in geo.bodies])
    wall_by_name = {w.name: w for w in geo.planes}
    for k, ev in enumerate(events, start=1):
        s = np.asarray(ev.state_before)
        pos = _positions(s[None, :], geo)[0]
        involved = [names.index(b) for b in ev.bodies if b in names]
        for i in involved:
            ax.add_patch(
                Circle(
                    pos[i],
                    radii[i],
                    facecolor=colors[i],
                    alpha=0.12,
                    edgecolor=colors[i],
                    lw=0.8,
                    ls=":",
                )
            )
        contact = _contact_point(ev, pos, involved, radii, wall_by_name)
        if contact is not None:
            ax.plot(*contact, marker="x", color="k", ms=8, mew=2, zorder=5)
            ax.annotate(
                str(k),
                contact,
                xytext=(5, 4),
                textcoords="offset points",
                fontsize=9,
                fontweight="bold",
                bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.7},
                zorder=6,
            )
    if events:
        handles.append(
            Line2D([], [], color="k", marker="x", ls="none", ms=7, mew=2, label="contact point")
        )
        # the numbered events, listed in the legend so labels never collide in the plot
        for k, ev in enumerate(events, start=1):
            handles.append(
                Line2D(
                    [],
                    [],
                    color="k",
                    marker=f"${k}$",
                    ls="none",
                    ms=7,
                    label=f"t = {ev.time:.3f}: {' / '.join(ev.bodies)}",
                )
            )


def _contact_point(
    ev: Any, pos: np.ndarray, involved: list[int], radii: np.ndarray, wall_by_name: dict[str, Any]
) -> Any:
    """Where the bodies of an event touch, an ``(x, y)`` array (``None`` for other events)."""
    contact = None
    if ev.kind == "disc-disc" and len(involved) == 2:
        i, j = involved
        u = pos[j] - pos[i]
        contact = pos[i] + radii[i] * u / np.linalg.norm(u)
    elif ev.kind == "disc-wall" and involved:
        wall = next((wall_by_name[b] for b in ev.bodies if b in wall_by_name), None)
        if wall is not None:
            contact = pos[involved[0]] - radii[involved[0]] * np.array(wall.normal)
    return contact


def _event_lines(
    axes: Sequence[Axes], event_times: Any, colors: Mapping[str, Any] | None = None
) -> None:
    if event_times is None:
        return
    if isinstance(event_times, Mapping):
        groups = [(colors.get(k, "0.4") if colors else "0.4", v) for k, v in event_times.items()]
    else:
        groups = [("0.4", event_times)]
    for color, times in groups:
        for t in times:
            for a in axes:
                a.axvline(float(t), color=color, ls="--", lw=0.9, alpha=0.8)


def mark_stages(ax: Axes, stages: Sequence[Sequence[Any]] | None) -> None:
    """Mark the stages of a learning curve: a vertical line where each stage starts and
    its name.

    Parameters
    ----------
    ax
        The axes of a loss against the iteration index.
    stages
        ``[start, name]`` pairs, ``start`` the index in the loss history where the stage
        begins (gd's ``sol.info["history_stages"]``); ``None`` or empty: nothing is drawn.
        The first stage gets its name and no line (the curve starts there).
    """
    for start, name in stages or ():
        x = float(start)
        if x > 0:
            ax.axvline(x, color="0.35", ls=":", lw=1.0)
        # at the top of the axes whatever the y scale: the curve spans decades
        ax.annotate(
            str(name), xy=(x, 1.0), xycoords=ax.get_xaxis_transform(), xytext=(2, -3),
            textcoords="offset points", rotation=90, ha="left", va="top", fontsize=7,
            color="0.25", bbox={"fc": "white", "ec": "none", "alpha": 0.7, "pad": 0.5},
        )  # fmt: skip


def plot_controls(
    time_grid: np.ndarray,
    controls: Mapping[str, np.ndarray],
    labels: Sequence[str],
    *,
    title: str | None = None,
    event_times: Sequence[float] | Mapping[str, Sequence[float]] | None = None,
) -> Figure:
    """Piecewise-constant controls against time, one panel per control component.

    Parameters
    ----------
    time_grid
        The ``N + 1`` grid times.
    controls
        ``{method name: (N, nu) array}``; several methods are overlaid.
    labels
        The ``nu`` component names (y-axis labels).
    title
        Figure title.
    event_times
        Times drawn as vertical dashed lines; a mapping ``{method name: times}`` draws each
        method's events in its colour.

    Returns
    -------
    matplotlib.figure.Figure
    """
    edges = np.asarray(time_grid, dtype=float)
    nu = len(labels)
    fig = Figure(figsize=(8.0, 1.0 + 1.9 * nu), layout="constrained")
    axes = fig.subplots(nu, 1, sharex=True, squeeze=False)[:, 0]
    colors = dict(zip(controls, _colors(len(controls)), strict=True))
    for name, values in controls.items():
        u = np.asarray(values, dtype=float)
        if u.ndim == 1:
            u = u[:, None]
        if u.shape != (edges.size - 1, nu):
            raise ValueError(
                f"controls[{name!r}] has shape {u.shape}, expected ({edges.size - 1}, {nu})"
            )
        for k, a in enumerate(axes):
            a.stairs(u[:, k], edges, color=colors[name], lw=1.5, label=name, baseline=None)
    for k, a in enumerate(axes):
        a.set_ylabel(labels[k])
        a.grid(True, lw=0.4, alpha=0.5)
        a.ticklabel_format(axis="y", useOffset=False)
    _event_lines(axes, event_times, colors)
    axes[-1].set_xlabel("t")
    axes[-1].set_xlim(edges[0], edges[-1])
    handles, names = axes[0].get_legend_handles_labels()
    if event_times is not None and len(event_times):
        handles.append(Line2D([], [], color="0.4", ls="--", lw=0.9))
        names.append("event")
    axes[0].legend(handles, names, fontsize=8, loc="best")
    if title:
        fig.suptitle(title)
    return fig


def plot_costates(
    times: np.ndarray | Mapping[str, np.ndarray],
    costates: np.ndarray | Mapping[str, np.ndarray],
    labels: Sequence[str],
    event_times: Sequence[float] | None = None,
    *,
    title: str | None = None,
) -> Figure:
    """Costate components against time, with the jumps at events left open.

    Parameters
    ----------
    times
        ``(M,)`` times; an event time appears twice (both sides of the jump). A mapping
        ``{name: times}`` together with a mapping ``costates`` overlays several costates.
    costates
        ``(M, nx)`` values, or ``{name: (M, nx)}``.
    labels
        The ``nx`` state-component names.
    event_times
        Times drawn as vertical dashed lines.
    title
        Figure title.

    Returns
    -------
    matplotlib.figure.Figure
    """
    if isinstance(costates, Mapping):
        if not isinstance(times, Mapping) or times.keys() != costates.keys():
            raise ValueError("with a mapping of costates, times must map the same names")
        series = {
            k: (np.asarray(times[k], float), np.asarray(costates[k], float)) for k in costates
        }
    else:
        series = {"costate": (np.asarray(times, float), np.asarray(costates, float))}
    nx = len(labels)
    ncols = 2 if nx > 1 else 1
    nrows = (nx + ncols - 1) // ncols
    fig = Figure(figsize=(9.0, 0.8 + 1.7 * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, sharex=True, squeeze=False)
    flat = axes.ravel()
    colors = dict(zip(series, _colors(len(series)), strict=True))
    for name, (t, lam) in series.items():
        if lam.shape != (t.size, nx):
            raise ValueError(f"costates {name!r}: shape {lam.shape}, expected ({t.size}, {nx})")
        # split at repeated times so a jump is a gap, not a vertical line
        cuts = np.flatnonzero(np.diff(t) == 0) + 1
        pieces = np.split(np.arange(t.size), cuts)
        for k in range(nx):
            for m, idx in enumerate(pieces):
                flat[k].plot(
                    t[idx], lam[idx, k], color=colors[name], lw=1.4, label=name if m == 0 else None
                )
    for k in range(nx):
        flat[k].set_ylabel(f"λ[{labels[k]}]")
        flat[k].grid(True, lw=0.4, alpha=0.5)
        flat[k].ticklabel_format(axis="y", useOffset=False)
    for a in flat[nx:]:
        a.set_visible(False)
    _event_lines(flat[:nx], event_times)
    for a in axes[-1]:
        a.set_xlabel("t")
    if len(series) > 1:
        flat[0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    return fig


def _scene_overlay(ocp: Any, evals: Mapping[str, Any], *, title: str) -> Figure:
    """The problem's geometry drawn with the first evaluation, the others' paths overlaid."""
    names = list(evals)
    fig = plot_scene(ocp, evals[names[0]], title=title)
    ax = fig.axes[0]
    styles = ["--", ":", "-."]
    geo = ocp.capabilities.geometry
    for k, name in enumerate(names[1:]):
        path = _positions(_path_states(evals[name]), geo)
        for i in range(geo.n_bodies):
            ax.plot(
                path[:, i, 0],
                path[:, i, 1],
                ls=styles[k % len(styles)],
                color="k",
                lw=1.1,
                alpha=0.8,
                label=f"{name} paths" if i == 0 else None,
            )
    # one legend: plot_scene's entries, then the overlay's. A second legend added with
    # add_artist is invisible to the constrained layout and gets clipped at the right edge.
    handles: list[Any] = []
    labels: list[str] = []
    old = ax.get_legend()
    if old is not None:
        handles += list(old.legend_handles)
        labels += [t.get_text() for t in old.get_texts()]
        old.remove()
    handles.append(Line2D([], [], color="0.3", lw=1.5))
    labels.append(f"{names[0]} paths (solid)")
    h2, l2 = ax.get_legend_handles_labels()
    keep = [(h, lab) for h, lab in zip(h2, l2, strict=True) if lab.endswith(" paths")]
    handles += [h for h, _ in keep]
    labels += [lab for _, lab in keep]
    ax.legend(
        handles, labels, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False
    )
    return fig


# ---------------------------------------------------------------------------- crossval


def plot_states(
    evaluations: Mapping[str, Any],
    labels: Sequence[str],
    *,
    title: str | None = None,
) -> Figure:
    """State components against time for one or more evaluations, jumps left open.

    Parameters
    ----------
    evaluations
        ``{name: Evaluation}``; trajectories are sampled densely on piecewise-constant
        evaluations.
    labels
        The ``nx`` state-component names.
    title
        Figure title.
    """
    nx = len(labels)
    ncols = 2 if nx > 1 else 1
    nrows = (nx + ncols - 1) // ncols
    fig = Figure(figsize=(9.0, 0.8 + 1.7 * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, sharex=True, squeeze=False)
    flat = axes.ravel()
    colors = dict(zip(evaluations, _colors(len(evaluations)), strict=True))
    styles = ["-", "--", ":", "-."]
    for m, (name, ev) in enumerate(evaluations.items()):
        t, X = _dense_path(ev)
        cuts = np.flatnonzero(np.diff(t) == 0) + 1
        for k in range(nx):
            for q, idx in enumerate(np.split(np.arange(t.size), cuts)):
                flat[k].plot(
                    t[idx], X[idx, k], color=colors[name], ls=styles[m % len(styles)], lw=1.4,
                    label=name if q == 0 else None,
                )  # fmt: skip
    all_events = sorted({e.time for ev in evaluations.values() for e in ev.events})
    for k in range(nx):
        flat[k].set_ylabel(labels[k])
        flat[k].grid(True, lw=0.4, alpha=0.5)
        flat[k].ticklabel_format(axis="y", useOffset=False)
        for te in all_events:
            flat[k].axvline(te, color="0.5", ls=":", lw=0.8)
    for a in flat[nx:]:
        a.set_visible(False)
    for a in axes[-1]:
        a.set_xlabel("t")
    flat[0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    return fig


def _dense_path(ev: Any) -> tuple[np.ndarray, np.ndarray]:
    """Times and states along an evaluation: dense samples plus both sides of every jump."""
    t = np.asarray(ev.times, dtype=float)
    X = np.asarray(ev.states, dtype=float)
    if getattr(ev, "segments", None):
        ocp = ev.ocp
        ts = np.linspace(0.0, ocp.horizon, _POINTS_PER_INTERVAL * ocp.steps + 1)
        ts = np.setdiff1d(ts, t)
        Xs = ev.sample(ts)
        t_all = np.concatenate([t, ts])
        X_all = np.concatenate([X, Xs])
        order = np.argsort(t_all, kind="stable")
        return t_all[order], X_all[order]
    return t, X


def plot_trajectories(
    ocp: Any, evaluations: Mapping[str, Any], *, title: str | None = None
) -> Figure:
    """The trajectories of one or more evaluations: a problem with a geometry (a disc scene)
    drawn to scale with the paths overlaid, any other problem as states against time."""
    if ocp.capabilities.geometry is not None:
        return _scene_overlay(ocp, evaluations, title=title or ocp.name)
    return plot_states(evaluations, list(ocp.state_labels), title=title)


def plot_landscape(
    landscape: Sequence[Mapping[str, Any]],
    chosen: Sequence[str] | None = None,
    *,
    title: str = "",
    label_limit: int = 12,
) -> Figure:
    """The extremal landscape of a reference search: the cost of every extremal found, one
    per event sequence, sorted, with the chosen optimum marked.

    Parameters
    ----------
    landscape
        Rows with ``"sequence"`` (guard names) and ``"cost"`` (``None`` where no extremal
        was found: left out), e.g. ``info["landscape"]`` of ``solve_reference(..., search=K)``;
        rows with a ``"verdict"`` that starts ``"not verified:"`` (an extremal whose
        re-simulation has other events) are drawn hollow.
    chosen
        The sequence of the reference's answer, marked in red.
    label_limit
        Label each point with its sequence when there are at most this many; otherwise
        only the chosen one is named.
    """
    rows = [r for r in landscape if r.get("cost") is not None]
    rows.sort(key=lambda r: float(r["cost"]))
    fig = Figure(figsize=(7.0, 4.2), layout="constrained")
    ax = fig.add_subplot()
    costs = np.array([float(r["cost"]) for r in rows])
    ranks = np.arange(1, len(rows) + 1)
    names = [", ".join(r["sequence"]) or "(no event)" for r in rows]
    bad = np.array([str(r.get("verdict", "")).startswith("not verified:") for r in rows], bool)
    hit = np.array([list(r["sequence"]) == list(chosen or ()) for r in rows], bool)
    if chosen is None:
        hit[:] = False
    ok = ~bad & ~hit
    ax.plot(ranks, costs, color="0.7", lw=0.8, zorder=1)
    ax.scatter(ranks[ok], costs[ok], s=30, color="C0", zorder=2, label="extremal")
    if bad.any():
        other = bad & ~hit
        ax.scatter(ranks[other], costs[other], s=30, facecolors="none", edgecolors="C0",
                   zorder=2, label="extremal (other events re-simulated)")  # fmt: skip
    if hit.any():
        ax.scatter(ranks[hit], costs[hit], s=90, marker="*", color="C3", zorder=3,
                   label="the reference's optimum")  # fmt: skip
    for i, name in enumerate(names):
        if len(rows) <= label_limit or hit[i]:
            ax.annotate(name, (ranks[i], costs[i]), textcoords="offset points", xytext=(6, -3),
                        fontsize=7, rotation=20, color="C3" if hit[i] else "0.25")  # fmt: skip
    if len(costs) and costs.min() > 0 and costs.max() / costs.min() > 30:
        ax.set_yscale("log")
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.margins(y=0.12)
    ax.set_xlabel("extremals, cheapest first (one per event sequence)")
    ax.set_ylabel("cost J")
    ax.set_xlim(0.5, max(len(rows), 1) + 0.5 + 0.25 * max(len(rows), 1))
    ax.grid(alpha=0.3)
    if len(rows):
        ax.legend(fontsize=8, loc="upper left")
    else:
        ax.text(0.5, 0.5, "no extremal found", ha="center", va="center",
                transform=ax.transAxes)  # fmt: skip
    ax.set_title(title or f"extremal landscape ({len(rows)} sequences)", fontsize=10)
    return fig


def figure_path(path: str | Path) -> Path:
    """The file :func:`save_figure` writes for ``path``: ``.png`` appended when there is no
    suffix (as matplotlib does).

    Raises
    ------
    hybridoc.errors.HybridocError
        A suffix that is no figure format matplotlib writes.
    """
    from matplotlib.backend_bases import FigureCanvasBase

    from hybridoc.errors import HybridocError

    p = Path(path)
    if not p.suffix:
        p = p.with_name(p.name + ".png")
    supported = FigureCanvasBase.get_supported_filetypes()
    if p.suffix[1:].lower() not in supported:
        raise HybridocError(
            f"cannot write {str(p)!r}: {p.suffix!r} is not a figure format "
            f"(use one of {', '.join('.' + k for k in sorted(supported))})"
        )
    return p


def save_figure(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` (dpi 120), creating parent directories, and close it.

    The format follows the suffix (``.png``, ``.pdf``, ``.svg``, ...); a path without one
    gets ``.png`` appended (:func:`figure_path`), and the path returned says so.

    Returns
    -------
    pathlib.Path
        The file written.

    Raises
    ------
    hybridoc.errors.HybridocError
        A suffix that is no figure format matplotlib writes; a link, or a file hybridoc did
        not write, at the path (:mod:`hybridoc.outputs`); a file that cannot be written.
    """
    from hybridoc.outputs import write_with

    p = figure_path(path)
    kind = p.suffix[1:].lower()
    # by the rules of hybridoc.outputs: atomically, never through a link or over a user's file
    write_with(p, lambda fh: fig.savefig(fh, dpi=120, format=kind))
    if getattr(fig.canvas, "manager", None) is not None:  # a pyplot figure: release it
        import matplotlib.pyplot as plt

        plt.close(fig)
    return p
