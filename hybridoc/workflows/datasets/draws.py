"""Reference datasets, the draws (:mod:`hybridoc.workflows.datasets`): what a dataset is
drawn from (a scene's ``[distribution]`` table or a Python distribution), one draw solved by
the reference, and its row of columns."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.errors import HybridocError, SceneError

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.ocp import HybridOCP
    from hybridoc.problems import Scene
    from hybridoc.reference import ReferenceResult

_VARIABLE_K = {  # column -> number of extra rows beyond K (K events, K + 1 phases)
    "event_times": 0,
    "multipliers": 0,
    "approach_speeds": 0,
    "states_minus": 0,
    "costates_minus": 0,
    "phase_starts": 1,
    "phase_states": 1,
    "phase_costates": 1,
    "control_coefficients": 1,
}
STRINGS = ("status", "method", "message", "sequence")


# ---------------------------------------------------------------------------- the scene


def distribution_scene(problem: Any) -> Scene:
    """The disc scene with a ``[distribution]`` table that ``problem`` names.

    Parameters
    ----------
    problem
        A built-in name, a ``.toml`` path, ``file.py:function`` or a
        :class:`~hybridoc.problems.Scene`.

    Returns
    -------
    Scene

    Raises
    ------
    HybridocError
        ``problem`` is a generic :class:`~hybridoc.HybridOCP`, not a disc scene.
    SceneError
        The scene has no ``[distribution]`` table (or cannot be loaded).
    """
    from hybridoc.problems import load_problem, scene_of

    obj = load_problem(problem)
    if scene_of(obj, compiled=False) is None:
        raise HybridocError(
            f"datasets need a disc scene with a [distribution] table; {obj.name!r} is a "
            "generic HybridOCP"
        )
    if obj.distribution is None:
        raise SceneError(
            f"scene {obj.name!r} has no [distribution] table: add one to draw initial states "
            "(see docs: datasets)"
        )
    return obj


def distribution_problem(problem: Any, distribution: Any = None) -> Scene | HybridOCP:
    """What a dataset of ``problem`` is drawn from: a disc scene with a ``[distribution]``
    table, or a :class:`~hybridoc.HybridOCP` with a Python distribution.

    Parameters
    ----------
    problem
        A built-in name, a ``.toml`` path, ``file.py:function``, a
        :class:`~hybridoc.problems.Scene` or a :class:`~hybridoc.HybridOCP`.
    distribution
        A callable ``(rng, M) -> (M, nx)`` (:attr:`HybridOCP.distribution
        <hybridoc.HybridOCP>`) overriding the problem's own; default: the problem's
        (its ``distribution`` field, or its scene's ``[distribution]`` table).

    Returns
    -------
    Scene or HybridOCP
        The scene (with its distribution) when the draws come from a ``[distribution]``
        table, otherwise the problem with ``distribution`` set.

    Raises
    ------
    SceneError
        No distribution anywhere, or one that is not callable.
    """
    from hybridoc.ocp import HybridOCP
    from hybridoc.problem import as_ocp
    from hybridoc.problems import load_problem, scene_of

    obj = load_problem(problem) if isinstance(problem, str | Path) else problem
    if distribution is None:
        # a scene's [distribution] table: the scene's own, or a compiled scene's without a
        # Python distribution
        table = scene_of(obj, compiled=False)
        if table is None and isinstance(obj, HybridOCP) and obj.distribution is None:
            table = scene_of(obj)
        if table is not None and table.distribution is not None:
            return table
    ocp = as_ocp(obj)
    dist = distribution if distribution is not None else ocp.distribution
    if dist is None:
        python = (
            "a distribution in Python (HybridOCP(distribution=...) or "
            "problem.replace(distribution=...): a callable (rng, M) -> (M, nx) initial states; "
            "see docs: datasets)"
        )
        if scene_of(ocp) is not None:
            raise SceneError(
                f"scene {ocp.name!r} has no [distribution] table: add one to draw initial "
                f"states, or give the problem {python}"
            )
        raise SceneError(f"{ocp.name!r} has no distribution of initial states: give it {python}")
    if not callable(dist):
        raise SceneError(
            f"the distribution of {ocp.name!r} must be a callable (rng, M) -> (M, nx), "
            f"got {type(dist).__name__}"
        )
    return ocp if dist is ocp.distribution else ocp.replace(distribution=dist)


def draw_initial_states(ocp: HybridOCP, samples: int, seed: int) -> np.ndarray:
    """The ``(samples, nx)`` initial states of the first ``samples`` draws of a problem's
    Python distribution: draw ``i`` is ``distribution(default_rng([seed, i]), 1)[0]``.

    Raises
    ------
    SceneError
        A distribution that raises, or returns another shape than ``(1, nx)`` (or
        ``(nx,)``), or non-finite values; the message names the draw.
    """
    dist = ocp.distribution
    if dist is None:
        raise SceneError(f"{ocp.name!r} has no distribution of initial states")
    out = np.empty((samples, ocp.nx))
    for i in range(samples):
        try:
            x = np.asarray(dist(np.random.default_rng([seed, i]), 1), dtype=float)
        except SceneError:
            raise
        except Exception as exc:  # the user's callable: any error is theirs, said as one line
            raise SceneError(
                f"the distribution of {ocp.name!r} failed on draw {i}: {type(exc).__name__}: {exc}"
            ) from None
        if x.shape not in ((1, ocp.nx), (ocp.nx,)):
            raise SceneError(
                f"the distribution of {ocp.name!r} returned shape {x.shape} for M = 1; "
                f"expected (1, {ocp.nx}) (M initial states of nx = {ocp.nx})"
            )
        if not np.all(np.isfinite(x)):
            raise SceneError(f"the distribution of {ocp.name!r} returned a non-finite state "
                             f"on draw {i}: {x.ravel().tolist()}")  # fmt: skip
        out[i] = x.ravel()
    return out


def check_count(value: Any, what: str, low: int) -> int:
    """``value`` as an ``int`` when it is an integer (not a bool) of at least ``low``.

    Raises
    ------
    HybridocError
        Otherwise: ``"<what> must be an integer >= <low>, got <value>"``.
    """
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
        raise HybridocError(f"{what} must be an integer >= {low}, got {value!r}")
    return int(value)


# ---------------------------------------------------------------------------- one draw


@dataclass
class DrawContext:
    """What a worker needs for every draw of one dataset (built once per process,
    :func:`draw_context`).

    Attributes
    ----------
    scene
        The scene with its distribution; ``None`` for a problem with a Python distribution.
    ocp
        The nominal problem (draws that change only the initial state reuse its compiled
        structure, :func:`draw_ocp`).
    seed
        The seed of the draws.
    sequence, z
        The nominal reference's event sequence and shooting unknowns (the warm start), or
        ``None``.
    tol
        HMP residual required of every extremal.
    full
        Every draw with the full discovery (no warm start).
    warm_status
        The status of a warm-started draw: the nominal's, ``success`` only when the
        nominal's optimum is proven, else ``best-found``.
    x0
        The ``(M, nx)`` initial states of a problem with a Python distribution (drawn by the
        calling process, :func:`draw_initial_states`); ``None`` for a scene.
    """

    scene: Scene | None
    ocp: HybridOCP
    seed: int
    sequence: list[str] | None
    z: np.ndarray | None
    tol: float
    full: bool
    x0: np.ndarray | None = None
    warm_status: str = "success"


BASELINE_STATUSES: frozenset[str] = frozenset({"success", "best-found"})
"""Reference statuses of a verified extremal that serves as a draw's baseline: ``success``
(its optimum proven) and ``best-found`` (the best found, not proven optimal; issue #29).
Every other status (``not-optimal``, ``infeasible``, ``failed``, ...) is a failed draw."""


_CONTEXTS: dict[str, DrawContext] = {}
_PROBLEMS: dict[str, HybridOCP] = {}
"""Problems with a Python distribution, by the key in their draws' specification: set by
the calling process before its pool forks, so that workers inherit them."""


def problem_spec(ocp: HybridOCP, text: str | None, x0: np.ndarray) -> dict[str, Any]:
    """The part of a task specification that names a problem with a Python distribution:
    ``{"problem": key, "load": text or None, "x0": draws}`` (the problem registered in this
    process under ``key`` for forked workers; ``text`` loads it elsewhere)."""
    key = f"{ocp.name}@{id(ocp):x}"
    _PROBLEMS.clear()  # one dataset at a time per process
    _PROBLEMS[key] = ocp
    return {"problem": key, "load": text, "x0": np.asarray(x0, dtype=float).tolist()}


def _problem_of(spec: dict[str, Any]) -> HybridOCP:
    ocp = _PROBLEMS.get(spec["problem"])
    if ocp is not None:
        return ocp
    if spec.get("load") is None:
        raise HybridocError(
            f"problem {spec['problem'].rpartition('@')[0]!r} is a Python object that this "
            "worker cannot load: run with workers=1 or a fork-based pool, or give the problem "
            "by name (path/to/file.py:function) for Dask"
        )
    from hybridoc.problem import as_ocp

    return as_ocp(spec["load"])


def draw_context(spec: dict[str, Any]) -> DrawContext:
    """The :class:`DrawContext` of a worker's task specification, built once per process.

    Parameters
    ----------
    spec
        ``{"spec": the scene's spec, "seed", "tol", "full", "nominal": None or {"sequence",
        "z"}}`` (:func:`~hybridoc.problems.load_spec`: ``{"kind": "scene", "toml": TOML
        text}``); for a problem with a Python distribution ``"problem"``, ``"load"`` and
        ``"x0"`` (:func:`problem_spec`) instead of ``"spec"``.
    """
    key = hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()
    ctx = _CONTEXTS.get(key)
    if ctx is None:
        nominal = spec.get("nominal")
        common = {
            "seed": int(spec["seed"]),
            "sequence": None if nominal is None else list(nominal["sequence"]),
            "z": None if nominal is None else np.array(nominal["z"], dtype=float),
            "tol": float(spec["tol"]),
            "full": bool(spec["full"]),
            # a warm draw is no more proven than its nominal (a manifest of before issue
            # #29 has only success nominals)
            "warm_status": "success"
            if nominal is None or nominal.get("status", "success") == "success"
            else "best-found",
        }
        if "spec" in spec:
            from hybridoc.problems import load_spec

            scene = load_spec(spec["spec"])
            ctx = DrawContext(scene=scene, ocp=scene.to_ocp(), **common)
        else:
            x0 = np.array(spec["x0"], dtype=float)
            ctx = DrawContext(scene=None, ocp=_problem_of(spec), x0=x0, **common)
        _CONTEXTS.clear()  # one dataset at a time per process
        _CONTEXTS[key] = ctx
    return ctx


def draw_ocp(ctx_scene: Scene, ocp: HybridOCP, scene_i: Scene) -> HybridOCP:
    """The problem of one draw: the nominal's compiled structure with another ``x0`` when
    only positions and velocities changed, a fresh compile when a target did."""
    same = all(a.target == b.target for a, b in zip(ctx_scene.discs, scene_i.discs, strict=True))
    if same:
        return ocp.replace(x0=scene_i.initial_state(), name=scene_i.name, source_scene=scene_i)
    return scene_i.to_ocp()


def draw_problem(ctx: DrawContext, index: int) -> tuple[Scene | None, HybridOCP]:
    """Draw ``index`` of the context's distribution: its scene (named ``<scene>#<index>``;
    ``None`` for a problem with a Python distribution) and its problem (:func:`draw_ocp`;
    the nominal problem with the draw's ``x0``, named ``<problem>#<index>``)."""
    if ctx.scene is None:
        assert ctx.x0 is not None
        return None, ctx.ocp.replace(x0=ctx.x0[index], name=f"{ctx.ocp.name}#{index}")
    scene_i = ctx.scene.distribution.draw(ctx.scene, index, ctx.seed)
    scene_i = dataclasses.replace(scene_i, name=f"{ctx.scene.name}#{index}")
    return scene_i, draw_ocp(ctx.scene, ctx.ocp, scene_i)


def _record_of(res: ReferenceResult, status: str, method: str, message: str) -> dict[str, Any]:
    C = res.control_coefficients()
    nu = res.system.nu
    return {
        "status": status,
        "method": method,
        "message": message,
        "cost": float(res.cost),
        "terminal_cost": float(res.terminal_cost),
        "running_cost": float(res.running_cost),
        "residual": float(res.residual),
        "sequence": ",".join(res.sequence),
        "n_events": len(res.sequence),
        "event_times": np.asarray(res.event_times, dtype=float),
        "multipliers": np.asarray(res.multipliers, dtype=float),
        "approach_speeds": np.asarray(res.approach_speeds, dtype=float),
        "controls": res.cell_averages(),
        "control_coefficients": (
            np.full((len(res.sequence) + 1, 2, nu), np.nan) if C is None else C
        ),
        "phase_starts": np.asarray(res.phase_starts, dtype=float),
        "phase_states": np.asarray(res.phase_states, dtype=float),
        "phase_costates": np.asarray(res.phase_costates, dtype=float),
        "states_minus": np.asarray(res.states_minus, dtype=float).reshape(-1, res.system.nx),
        "costates_minus": np.asarray(res.costates_minus, dtype=float).reshape(-1, res.system.nx),
        "final_state": np.asarray(res.final_state, dtype=float),
        "final_costate": np.asarray(res.final_costate, dtype=float),
        "lambda0": np.asarray(res.phase_costates[0], dtype=float),
    }


def _failed_record(ocp: HybridOCP, message: str) -> dict[str, Any]:
    nx, nu, N = ocp.nx, ocp.nu, ocp.steps
    nan = float("nan")
    return {
        "status": "failed",
        "method": "",
        "message": " ".join(message.split()),
        "cost": nan,
        "terminal_cost": nan,
        "running_cost": nan,
        "residual": nan,
        "sequence": "",
        "n_events": -1,
        "event_times": np.zeros(0),
        "multipliers": np.zeros(0),
        "approach_speeds": np.zeros(0),
        "controls": np.full((N, nu), nan),
        "control_coefficients": np.full((1, 2, nu), nan),
        "phase_starts": np.full(1, nan),
        "phase_states": np.full((1, nx), nan),
        "phase_costates": np.full((1, nx), nan),
        "states_minus": np.zeros((0, nx)),
        "costates_minus": np.zeros((0, nx)),
        "final_state": np.full(nx, nan),
        "final_costate": np.full(nx, nan),
        "lambda0": np.full(nx, nan),
    }


def _warm(ctx: DrawContext, ocp: HybridOCP) -> tuple[ReferenceResult | None, str]:
    """The nominal sequence's extremal from the nominal point, verified; or why not."""
    from hybridoc.reference import warm_extremal

    assert ctx.sequence is not None and ctx.z is not None
    return warm_extremal(ocp, ctx.sequence, ctx.z, tol=ctx.tol, start_x0=ctx.ocp.x0)


def _solve_draw(ctx: DrawContext, index: int) -> dict[str, Any]:
    """The record of draw ``index``: warm start, then the full discovery."""
    from hybridoc.reference import solve_reference

    scene_i, ocp = draw_problem(ctx, index)
    head = {
        "index": index,
        "x0": np.array(ocp.x0, dtype=float) if scene_i is None else scene_i.initial_state(),
        "targets": np.zeros((0, 2)) if scene_i is None else scene_i.targets(),
    }
    why = "full discovery requested"
    if not ctx.full and ctx.sequence is not None:
        try:
            res, why = _warm(ctx, ocp)
        except Exception as exc:  # whatever went wrong, the full discovery decides
            res, why = None, f"{type(exc).__name__}: {exc}"
        if res is not None:
            return {**head, **_record_of(res, ctx.warm_status, "warm", "")}
    try:
        sol = solve_reference(ocp)
    except Exception as exc:  # kept as a failed row, never lost (e.g. a worker that may
        # not fork the reference's own pool on a remote Dask cluster)
        return {**head, **_failed_record(ocp, f"{type(exc).__name__}: {exc}")}
    rec = _record_of(sol.reference, sol.status.value, "full", sol.message)
    return {**head, **rec, "message": sol.message or f"warm start not accepted: {why}"}


def solve_chunk(spec: dict[str, Any], indices: list[int]) -> dict[str, np.ndarray]:
    """A worker's task: the stacked records of ``indices``."""
    ctx = draw_context(spec)
    return _stack([_solve_draw(ctx, i) for i in indices])


# ---------------------------------------------------------------------------- columns


def _pad_rows(arrays: list[np.ndarray], rows: int) -> np.ndarray:
    out = []
    for a in arrays:
        a = np.asarray(a, dtype=float)
        if a.shape[0] < rows:
            pad = np.full((rows - a.shape[0], *a.shape[1:]), np.nan)
            a = np.concatenate([a, pad])
        out.append(a)
    return np.stack(out)


def _stack(records: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """Records -> columns (variable-length ones padded with NaN)."""
    K = max((len(r["event_times"]) for r in records), default=0)
    out: dict[str, np.ndarray] = {}
    for key in records[0]:
        vals = [r[key] for r in records]
        if key in _VARIABLE_K:
            out[key] = _pad_rows(vals, K + _VARIABLE_K[key])
        elif key in STRINGS:
            out[key] = np.array(vals, dtype=str)
        elif key in ("index", "n_events"):
            out[key] = np.array(vals, dtype=np.int64)
        else:
            out[key] = np.array(vals, dtype=float)
    return out


def concat_columns(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Columns of several chunks, in order, re-padded to the largest ``K``."""
    K = max(p["event_times"].shape[1] for p in parts)
    out = {}
    for key in parts[0]:
        if key in _VARIABLE_K:
            rows = K + _VARIABLE_K[key]
            arrs = []
            for p in parts:
                a = p[key]
                if a.shape[1] < rows:
                    pad = np.full((a.shape[0], rows - a.shape[1], *a.shape[2:]), np.nan)
                    a = np.concatenate([a, pad], axis=1)
                arrs.append(a)
            out[key] = np.concatenate(arrs)
        elif key in STRINGS:
            out[key] = np.concatenate([p[key].astype(object) for p in parts]).astype(str)
        else:
            out[key] = np.concatenate([p[key] for p in parts])
    return out
