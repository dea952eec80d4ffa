"""Reference datasets: the exact optimal control of many initial states of one problem.

:func:`make_dataset` draws ``M`` initial states and solves each with the HMP reference;
:func:`load_dataset` reads the result back. The draws come from a disc scene's
``[distribution]`` table (:class:`~hybridoc.problems.scene.Distribution`: concrete scenes,
targets included), or, for any :class:`~hybridoc.HybridOCP`, from a distribution declared
in Python: :attr:`HybridOCP.distribution <hybridoc.HybridOCP>` or ``make_dataset``'s
``distribution`` argument, a callable ``(rng, M) -> (M, nx)`` initial states, called for
draw ``i`` with ``M = 1`` and its own generator ``default_rng([seed, i])``
(:func:`draw_initial_states`). The draws of such a problem are made in the calling process;
pool workers get the problem by ``fork`` (or, with Dask or without ``fork``, load it again
from its name: a problem given as a name or ``file.py:function``).

How each draw is solved
    The nominal scene is solved once with the reference's full discovery
    (:func:`~hybridoc.reference.solve_reference`). Each draw is then solved by Newton on the
    HMP system of the nominal's event sequence, started from the nominal's solution
    (``method = "warm"``), and accepted only when

    1. Newton converges (HMP residual below ``tol``, event times in order);
    2. the judge re-simulates the extremal's ``u(t)`` to exactly its events and its cost
       (:func:`~hybridoc.reference.verify_reference`);
    3. no sequence of at most one event can beat it (the reference's lower bound), and the
       scene's initial guess, judged, is not cheaper.

    Every other draw is solved with the full discovery (``method = "full"``); with
    ``full=True`` every draw is. Draws that fail are kept with status ``failed`` and the
    reason in ``message``; nothing is dropped.

    A draw's status is the reference's (issue #29): ``success`` only where its optimum is
    proven, ``best-found`` for a verified extremal (HMP satisfied, re-simulated to its own
    events) that is the best found but not proven optimal. A nominal that is only
    ``best-found`` still gives the warm start, and its warm draws are ``best-found`` too:
    a warm draw is never more proven than the nominal it starts from.

Files (in the output directory)
    ``dataset.npz``
        One row per draw (columns below), written deterministically (fixed zip
        timestamps), so equal data give byte-identical files.
    ``manifest.json``
        Versions, settings (the scene as TOML, samples, seed, chunk size, tol), the nominal
        solution, counts per status, the data file's SHA-256, timings.
    ``shards/``
        Finished chunks while a run is in progress. The folder is made by the run with a
        marker file (``.hybridoc-shards``) in it; a ``shards/`` without that marker is
        someone else's and an error, never touched. Once ``dataset.npz`` is written, the
        run removes the chunk files and the marker, then the folder if nothing else is
        left in it.
    ``.hybridoc-dataset.lock``
        Held (``flock``) by the run that writes in the directory, removed when it ends: a
        second run into the same directory fails at once.

Writes, resume and checks
    Every file is written under a unique temporary name in its directory and renamed over
    the target, so a run killed at any point leaves either the old file or the new one;
    the temporaries of a killed run (``.NAME.PID.XXXXXXXX.tmp``) are removed by the next.
    A run started again with the same settings checks every shard (a readable zip with
    the expected columns, rows and indices, computed with the same settings and nominal
    solution), keeps the good ones, says which are bad and computes those again, and
    writes the same bytes as an uninterrupted run. The data file's SHA-256 is checked on
    every load (:func:`load_dataset`, and a rerun that finds the dataset complete): a
    mismatch is an error naming the file and both hashes; the file is left as it is.
    Every load also checks the manifest against its schema (:func:`check_manifest`: the
    type and range of every field) and the rows against the problem (:func:`check_draws`:
    the initial states and targets recomputed from the manifest's scene and seed and
    compared bit for bit), so that a file edited and rehashed, or a manifest whose seed
    is not the data's, is an error too. A ``dataset.npz`` that no manifest of ours
    records (the user's own), or a link at either file's name, is never overwritten: the
    run refuses at once, before any solve.
    Pool workers end when the process that started them dies.

Columns
    ``index``, ``x0`` ``(M, nx)``, ``targets`` ``(M, n_discs, 2)`` (NaN: no target),
    ``status`` (``success``, ``best-found``, ``not-optimal``, ``infeasible``, ``failed``;
    :data:`BASELINE_STATUSES` are the verified ones), ``method``
    (``warm``, ``full``, ``""`` for a failure), ``message``, ``cost``, ``terminal_cost``,
    ``running_cost``, ``residual``, ``sequence`` (guard names joined by ``,``),
    ``n_events``, ``event_times`` ``(M, K)``, ``multipliers`` ``(M, K)``,
    ``approach_speeds`` ``(M, K)``, ``controls`` ``(M, N, nu)`` (cell averages of the
    optimal ``u(t)``), ``control_coefficients`` ``(M, K + 1, 2, nu)`` (``u = c0 + c1 (t -
    t_k)`` on phase ``k``), ``phase_starts`` ``(M, K + 1)``, ``phase_states`` and
    ``phase_costates`` ``(M, K + 1, nx)`` (after each jump), ``states_minus`` and
    ``costates_minus`` ``(M, K, nx)`` (before each jump), ``final_state``,
    ``final_costate`` and ``lambda0`` ``(M, nx)``. ``K`` is the largest number of events
    of any draw; shorter rows are padded with NaN.

Scale-out
    Chunks of draws run in a local process pool over the usable cores (default), in the
    calling process (``workers=1``), or on a ``dask.distributed`` cluster (``dask=``
    an address, ``"local"`` or a ``Client``). Draw ``i`` has its own random stream and
    every draw starts from the same nominal point, so the data do not depend on the engine,
    the number of workers or the order in which chunks finish.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import hashlib
import io
import json
import math
import multiprocessing as mp
import os
import re
import secrets
import sys
import time
import warnings
import zipfile
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc import children
from hybridoc.errors import HybridocError, SceneError
from hybridoc.progress import Progress, ProgressLike, progress_scope
from hybridoc.resources import check_samples_of
from hybridoc.solvers.threads import usable_cores

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.ocp import HybridOCP
    from hybridoc.problems import Scene
    from hybridoc.reference import ReferenceResult

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: runs are not locked
    fcntl = None  # type: ignore[assignment]

__all__ = [
    "CHUNK",
    "COLUMNS",
    "DATA_FILE",
    "MANIFEST_FILE",
    "Dataset",
    "DrawContext",
    "MAX_SAMPLES",
    "check_count",
    "check_dask",
    "check_columns",
    "check_draws",
    "check_manifest",
    "distribution_problem",
    "distribution_scene",
    "draw_context",
    "draw_initial_states",
    "draw_ocp",
    "draw_problem",
    "initial_states_sha256",
    "iter_chunks",
    "load_dataset",
    "make_dataset",
    "problem_spec",
    "run_chunks",
    "source_draws",
    "source_seed",
    "usable_cores",
]

DATA_FILE = "dataset.npz"
MANIFEST_FILE = "manifest.json"
SHARD_DIR = "shards"
SHARD_MARK = ".hybridoc-shards"
_MARK_TEXT = (
    "hybridoc-dataset-shards/1\n"
    "Unfinished chunks of 'hybridoc dataset'; it removes them when the dataset is written.\n"
)
LOCK_FILE = ".hybridoc-dataset.lock"
_SPEC_KEY = "_spec"
"""A shard's extra column: the SHA-256 of the settings and nominal solution it was
computed with."""
_CHUNK_NAME = re.compile(r"chunk-\d{6}\.npz")
_TMP_NAME = re.compile(r"\.(?P<name>.+)\.\d+\.[0-9a-f]{8}\.tmp")
"""Names of :func:`_atomic_write`'s temporaries (and of a shard folder being made)."""
COLUMNS = frozenset(
    "index x0 targets status method message cost terminal_cost running_cost residual "
    "sequence n_events event_times multipliers approach_speeds controls "
    "control_coefficients phase_starts phase_states phase_costates states_minus "
    "costates_minus final_state final_costate lambda0".split()
)
"""The columns of a dataset (module notes)."""
FORMAT = "hybridoc-dataset/1"
CHUNK = 25
"""Draws per chunk (one shard file, one task of the pool or of Dask)."""

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
_STRINGS = ("status", "method", "message", "sequence")


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


def _solve_chunk(spec: dict[str, Any], indices: list[int]) -> dict[str, np.ndarray]:
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
        elif key in _STRINGS:
            out[key] = np.array(vals, dtype=str)
        elif key in ("index", "n_events"):
            out[key] = np.array(vals, dtype=np.int64)
        else:
            out[key] = np.array(vals, dtype=float)
    return out


def _concat(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
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
        elif key in _STRINGS:
            out[key] = np.concatenate([p[key].astype(object) for p in parts]).astype(str)
        else:
            out[key] = np.concatenate([p[key] for p in parts])
    return out


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """``arrays`` as ``.npz`` bytes, byte for byte reproducibly (fixed zip timestamps,
    sorted names)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for name in sorted(arrays):
            arr = np.ascontiguousarray(arrays[name])
            body = io.BytesIO()
            np.lib.format.write_array(body, arr, allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            zf.writestr(info, body.getvalue())
    return buf.getvalue()


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> str:
    """Write ``arrays`` as ``.npz`` (:func:`_npz_bytes`) atomically; returns the SHA-256 of
    the file."""
    data = _npz_bytes(arrays)
    _atomic_write(path, data)
    return hashlib.sha256(data).hexdigest()


def _parse_npz(data: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _tmp_name(path: Path) -> Path:
    """A temporary name next to ``path`` that no other process or call uses."""
    return path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):  # not every file system syncs a directory
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file of a unique name in the same
    directory, synced and renamed over it: readers and concurrent writers see the old file
    or the new one, never a part; a crash leaves at most a temporary (:func:`_sweep`)."""
    tmp = _tmp_name(path)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise HybridocError(f"cannot write {str(path)!r}: {exc.strerror or exc}") from None
    _fsync_dir(path.parent)


def _sweep(folder: Path, files: Callable[[str], bool], dirs: Callable[[str], bool]) -> None:
    """Remove the temporaries a killed run left in ``folder``: files ``.NAME.PID.HEX.tmp``
    with ``files(NAME)`` true and, with ``dirs(NAME)`` true, shard folders that were being
    made (only our marker inside). Called with the lock held, so no run is writing them."""
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return
    for e in entries:
        m = _TMP_NAME.fullmatch(e.name)
        if m is None:
            continue
        with contextlib.suppress(OSError):
            if e.is_dir(follow_symlinks=False) and dirs(m["name"]):
                _sweep(Path(e.path), lambda n: n == SHARD_MARK, lambda n: False)
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(os.path.join(e.path, SHARD_MARK))
                os.rmdir(e.path)  # fails, and keeps it, if anything else is inside
            elif e.is_file(follow_symlinks=False) and files(m["name"]):
                os.unlink(e.path)


# ---------------------------------------------------------------------------- files we own

_HELD_LOCKS: set[int] = set()


def _drop_inherited_locks() -> None:
    # a forked child (pool worker, the reference's search pool) shares the lock's open file
    # description; closing its copy keeps a child that outlives the run from holding the lock
    for fd in _HELD_LOCKS:
        with contextlib.suppress(OSError):
            os.close(fd)
    _HELD_LOCKS.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_drop_inherited_locks)


_NO_LOCKS = {errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOLCK}
"""``flock`` errors of a file system without locks (not of a lock held by another run)."""


@contextlib.contextmanager
def _locked(out: Path) -> Iterator[None]:
    """Hold the lock of the output directory ``out`` (``flock`` on :data:`LOCK_FILE`,
    without waiting) for the block, and remove the lock file at its end.

    Raises
    ------
    HybridocError
        Another run holds it, or it cannot be taken.
    """
    path = out / LOCK_FILE
    if fcntl is None:  # pragma: no cover
        yield
        return
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise HybridocError(f"cannot create {str(path)!r}: {exc.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if isinstance(exc, BlockingIOError):
                raise HybridocError(
                    f"another hybridoc dataset run holds the lock on {str(out)!r} "
                    f"({LOCK_FILE}); wait for it to end or choose another --out"
                ) from None
            if exc.errno in _NO_LOCKS:
                # some network file systems (Lustre without -o flock, some NFS/SMB mounts)
                # have no locks at all: run, but say what is not protected
                warnings.warn(
                    f"the file system of {str(out)!r} does not support locks "
                    f"({exc.strerror}): running without the lock on the folder; do not "
                    "start a second run into it until this one ends",
                    UserWarning,
                    stacklevel=3,
                )
                with contextlib.suppress(OSError):
                    path.unlink()
                yield
                return
            raise HybridocError(f"cannot lock {str(path)!r}: {exc.strerror}") from None
        # the run before may have removed the file as it ended, after we opened it: the
        # lock counts only on the file that is at the path now
        try:
            if os.path.samestat(os.fstat(fd), os.stat(path)):
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    _HELD_LOCKS.add(fd)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            path.unlink()  # still holding it, so no other run has it
        _HELD_LOCKS.discard(fd)
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def _is_ours(folder: Path) -> bool:
    """Whether ``folder`` is a shard folder made by :func:`_shard_dir` (its marker)."""
    try:
        with open(folder / SHARD_MARK, encoding="utf-8") as f:
            return f.readline() == _MARK_TEXT.splitlines(keepends=True)[0]
    except (OSError, UnicodeDecodeError):
        return False


def _shard_dir(out: Path, resuming: bool = False) -> Path:
    """The shard folder of ``out``: made with its marker in one rename (a kill leaves no
    unmarked folder of ours), or ours already.

    ``resuming``: ``out`` holds our manifest of an unfinished run with the same settings.
    A run of an older hybridoc (no marker) left a ``shards/`` there holding nothing but
    chunk files; it is adopted (marked), and its chunks are checked like any other.

    Raises
    ------
    HybridocError
        ``out/shards`` exists and is not ours: nothing in it is touched.
    """
    d = out / SHARD_DIR
    if resuming and d.is_dir() and not d.is_symlink() and not _is_ours(d):
        names = os.listdir(d)
        if all(_CHUNK_NAME.fullmatch(n) or _TMP_NAME.fullmatch(n) for n in names):
            (d / SHARD_MARK).write_text(_MARK_TEXT, encoding="utf-8")
    if not d.exists() and not d.is_symlink():
        tmp = _tmp_name(d)
        try:
            tmp.mkdir()
            fd = os.open(tmp / SHARD_MARK, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(_MARK_TEXT)
            os.rename(tmp, d)
        except OSError as exc:
            _sweep(out, lambda n: False, lambda n: n == SHARD_DIR)
            raise HybridocError(f"cannot create {str(d)!r}: {exc.strerror or exc}") from None
    elif not (d.is_dir() and not d.is_symlink() and _is_ours(d)):
        raise HybridocError(
            f"{str(d)!r} exists and was not made by 'hybridoc dataset' (it has no "
            f"{SHARD_MARK} marker); hybridoc never deletes files it did not write: move it "
            "away or choose another --out"
        )
    return d


def _remove_shards(d: Path, say: Callable[[str], None]) -> None:
    """Remove what the runs wrote in the shard folder ``d`` (chunks, temporaries, the marker
    last) and then the folder if nothing else is left in it. The dataset is complete by
    then: a failure is said, not raised."""
    try:
        for e in list(os.scandir(d)):
            m = _TMP_NAME.fullmatch(e.name)
            if e.is_file(follow_symlinks=False) and (
                _CHUNK_NAME.fullmatch(e.name) or (m and _CHUNK_NAME.fullmatch(m["name"]))
            ):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(e.path)
        others = sorted(n for n in os.listdir(d) if n != SHARD_MARK)
        if others:
            say(f"kept {d}: it holds files that hybridoc did not write ({', '.join(others[:3])})")
            return
        os.unlink(d / SHARD_MARK)
        os.rmdir(d)
    except OSError as exc:
        say(f"cannot remove {d}: {exc.strerror or exc}")


def _read_shard(
    path: Path, indices: list[int], spec_hash: str
) -> tuple[dict[str, np.ndarray] | None, str]:
    """The columns of the finished chunk ``path`` of ``indices``, or ``None`` and why it
    cannot be used ("" when it does not exist)."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None, ""
    except OSError as exc:
        return None, f"cannot be read ({exc.strerror})"
    try:
        cols = _parse_npz(data)
    except Exception as exc:  # truncated or damaged: whatever numpy or zipfile raise
        return None, f"is damaged ({type(exc).__name__}: {exc})"
    if set(cols) != COLUMNS | {_SPEC_KEY}:
        return None, "has other columns"
    if cols.pop(_SPEC_KEY).tolist() != [spec_hash]:
        return None, "was computed with other settings"
    n = len(indices)
    if cols["index"].dtype.kind != "i" or not np.array_equal(cols["index"], indices):
        return None, f"holds other draws than {indices[0]} to {indices[-1]}"
    if any(a.ndim == 0 or a.shape[0] != n for a in cols.values()):
        return None, f"does not have {n} rows in every column"
    return cols, ""


# ---------------------------------------------------------------------------- engines


def _dask_client(dask: Any, workers: int) -> tuple[Any, Callable[[], None]]:
    """A ``distributed.Client`` for ``dask`` and a function that closes what was opened."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:  # pragma: no cover
        raise HybridocError(
            "--dask needs dask.distributed: pip install 'dask[distributed]'"
        ) from None
    if isinstance(dask, Client):
        return dask, lambda: None
    check_dask(dask)
    if dask == "local":
        import dask as dask_module

        # non-daemonic workers, so that the reference's full search may run its own pool
        with dask_module.config.set({"distributed.worker.daemon": False}):
            cluster = LocalCluster(
                n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None
            )
        client = Client(cluster)

        def close() -> None:
            client.close()
            cluster.close()

        return client, close
    try:
        client = Client(dask, timeout="5s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise HybridocError(f"cannot connect to the Dask scheduler at {dask!r}: {exc}") from None
    return client, client.close


def check_dask(dask: Any) -> None:
    """Raise :class:`~hybridoc.errors.HybridocError` for a ``dask`` argument that is neither
    ``None``, ``"local"``, an address ``[scheme://]host:port`` nor a ``Client``."""
    if dask is None or dask == "local" or type(dask).__name__ == "Client":
        return
    if not isinstance(dask, str) or not dask.strip():
        raise HybridocError(f"dask must be 'local', a scheduler address or a Client, got {dask!r}")
    rest = dask.split("://", 1)[-1]
    host, _, port = rest.rpartition(":")
    if not host or not port.isdigit():
        raise HybridocError(
            f"bad Dask scheduler address {dask!r}: expected 'local' or [tcp://]host:port "
            "(e.g. tcp://10.0.0.5:8786)"
        )


# the rules of hybridoc.children; kept as this module's names (tests replace
# _die_with_parent to exercise the fallback thread)
_die_with_parent = children.pdeathsig
_watch_parent = children.watch_parent


def _worker_start(parent: int, initializer: Callable[[], None] | None) -> None:
    """Pool initializer: end this worker with its parent, then run ``initializer``.

    Without it a worker outlives a parent killed with SIGKILL: it waits on the pool's pipe,
    whose other ends its sibling workers hold open. The processes a worker forks (the
    reference's own pools) die with it in turn.
    """
    if not _die_with_parent():
        _watch_parent(parent)
    if os.getppid() != parent:  # it died before the signal was asked for
        os._exit(1)
    children.forks_die_with_this_process()
    if initializer is not None:
        initializer()


def run_chunks(
    fn: Callable[..., Any],
    common: Any,
    chunks: list[tuple[int, list[int]]],
    *,
    workers: int,
    dask: Any = None,
    on_result: Callable[[int, Any], None],
    initializer: Callable[[], None] | None = None,
) -> None:
    """Run ``fn(common, indices)`` for each ``(chunk id, indices)`` and hand each result to
    ``on_result(chunk id, result)`` in the calling process, as chunks finish.

    ``workers == 1`` and no ``dask``: in this process. Otherwise a process pool of
    ``workers`` (fork where available; they end when this process dies) or the Dask cluster
    ``dask``.
    """
    if not chunks:
        return
    if dask is not None:
        client, close = _dask_client(dask, workers)
        try:
            from distributed import as_completed as dask_completed

            futs = {client.submit(fn, common, idx, pure=False): cid for cid, idx in chunks}
            for fut in dask_completed(futs):
                on_result(futs[fut], fut.result())
        finally:
            close()
        return
    if workers <= 1 or len(chunks) == 1:
        for cid, idx in chunks:
            on_result(cid, fn(common, idx))
        return
    method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
    with ProcessPoolExecutor(
        min(workers, len(chunks)),
        mp_context=mp.get_context(method),
        initializer=_worker_start,
        initargs=(os.getpid(), initializer),
    ) as pool:
        futs = {pool.submit(fn, common, idx): cid for cid, idx in chunks}
        try:
            for fut in as_completed(futs):
                on_result(futs[fut], fut.result())
        except BaseException:
            # stopped early (an error, Ctrl-C): the running chunks' results would be
            # dropped, so their workers are killed rather than waited for
            children.kill_pool(pool)
            raise


# ---------------------------------------------------------------------------- datasets


@dataclass
class Dataset:
    """A reference dataset read by :func:`load_dataset`.

    Attributes
    ----------
    path
        Its directory.
    columns
        Column name -> array, one row per draw (module notes).
    manifest
        The JSON manifest.
    """

    path: Path
    columns: dict[str, np.ndarray]
    manifest: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.columns["index"].shape[0])

    def __getitem__(self, key: str) -> np.ndarray:
        return self.columns[key]

    @property
    def scene(self) -> Scene:
        """The scene (with its distribution) the dataset was drawn from.

        Raises
        ------
        HybridocError
            A dataset of a problem with a Python distribution (its settings name the
            problem and the SHA-256 of its initial states instead).
        """
        from hybridoc.problems import load_spec

        spec = self.spec
        if spec is None:
            settings = self.manifest["settings"]
            raise HybridocError(
                f"the dataset in {str(self.path)!r} was drawn from a problem with a Python "
                f"distribution ({settings.get('problem')!r}), not from a scene"
            )
        return load_spec(spec)

    @property
    def spec(self) -> dict[str, Any] | None:
        """The spec (:func:`hybridoc.problems.load_spec`) of the scene whose
        ``[distribution]`` table the draws come from, ``{"kind": "scene", "toml": ...}``;
        ``None`` for a problem with a Python distribution. A manifest of before issue #30
        holds the TOML text alone (``settings.scene``): read as its spec."""
        return settings_spec(self.manifest["settings"])

    @property
    def ok(self) -> np.ndarray:
        """Rows whose status is ``success``: the reference proves their optimum."""
        return self.columns["status"] == "success"

    @property
    def verified(self) -> np.ndarray:
        """Rows with a verified reference, proven (``success``) or not (``best-found``): a
        baseline for a policy's cost (:data:`BASELINE_STATUSES`)."""
        return np.isin(self.columns["status"], list(BASELINE_STATUSES))


def _settings(
    source: Scene | HybridOCP, samples: int, seed: int, tol: float, full: bool,
    x0: np.ndarray | None = None,
) -> dict[str, Any]:  # fmt: skip
    """The settings a dataset is made with (a resumed run must have the same): the scene's
    spec (:func:`~hybridoc.problems.spec_of`, its TOML), or a problem's name with the
    SHA-256 of its drawn initial states."""
    from hybridoc import __version__
    from hybridoc.problems import spec_of

    if x0 is None:
        what: dict[str, Any] = {"spec": spec_of(source)}
    else:
        what = {
            "problem": source.name,
            "nominal_x0": [float(v) for v in source.x0],
            "x0_sha256": initial_states_sha256(x0),
        }
    return {
        "format": FORMAT,
        "hybridoc": __version__,
        **what,
        "samples": samples,
        "seed": seed,
        "chunk": CHUNK,
        "tol": tol,
        "full": full,
    }


def _notice(text: str) -> None:
    """A line on stderr about the nominal solve or what the run found in its folder (shards
    computed again, files kept): said whatever the progress display, as a log line."""
    print(f"dataset: {text}", file=sys.stderr, flush=True)


def _nominal(source: Scene | HybridOCP, tol: float, progress: Progress) -> dict[str, Any] | None:
    from hybridoc.problems import scene_of
    from hybridoc.reference import solve_reference

    table = scene_of(source, compiled=False)
    label = "nominal scene" if table is not None else "nominal problem"
    progress.stage(label)
    t0 = time.perf_counter()
    nominal = (
        dataclasses.replace(table, distribution=None)
        if table is not None
        else source.replace(distribution=None)
    )
    try:
        sol = solve_reference(nominal, tol=tol, progress=progress)
    except HybridocError as exc:
        _notice(f"{label}: no reference ({exc}); every draw gets the full discovery")
        return None
    res = sol.reference
    _notice(
        f"{label}: {sol.status.value}, cost {sol.cost:.12g}, events {sol.sequence} "
        f"({time.perf_counter() - t0:.2f} s)"
    )
    # a best-found nominal is a verified extremal too: it warm-starts the draws, which are
    # then best-found as well (DrawContext.warm_status)
    if sol.status.value not in BASELINE_STATUSES:
        return None
    return {
        "sequence": list(res.sequence),
        "z": [float(x) for x in res.z],
        "cost": float(sol.cost),
        "status": sol.status.value,
    }


def _check_own_units(source: Scene | HybridOCP) -> None:
    """Refuse a disc scene the reference solves in other units (far from its own units or
    from the origin: :func:`hybridoc.reference.units.canonical`): a dataset's rows hold the
    reference's shooting unknowns, which are then the canonical scene's."""
    from hybridoc.problem import as_ocp
    from hybridoc.reference.units import canonical

    ocp = as_ocp(source)
    units = canonical(ocp)
    if units is not None:
        sc = ocp.scales
        raise SceneError(
            f"dataset: the scene is far from its own units (length scale {sc.length:g}, time "
            f"scale {sc.time:g}, offset {sc.state_offset[:2]}); datasets are built for scenes "
            "within a factor 4 of their units and near the origin (docs: trust, units and "
            "place): state the scene in units of its own size"
        )


def make_dataset(
    problem: Any,
    samples: int,
    out: str | Path,
    *,
    seed: int | None = None,
    workers: int | None = None,
    dask: Any = None,
    tol: float = 1e-10,
    full: bool = False,
    progress: ProgressLike = True,
    distribution: Any = None,
) -> Dataset:
    """Solve the reference for ``samples`` draws of a problem's distribution; write and
    return the dataset (module notes).

    Parameters
    ----------
    problem
        A disc scene with a ``[distribution]`` table, or any problem with a Python
        distribution (:attr:`HybridOCP.distribution <hybridoc.HybridOCP>`, or
        ``distribution``): a name, a ``.toml`` path, ``file.py:function``, a
        :class:`~hybridoc.problems.scene.Scene` or a :class:`~hybridoc.HybridOCP`.
    samples
        ``M`` >= 1.
    out
        Output directory (created). A run interrupted there resumes when started again
        with the same settings; other settings there are an error. One run at a time
        writes there (a lock); files hybridoc did not write are never removed.
    seed
        Overrides the distribution's seed.
    workers
        Processes of the local pool (default: the usable cores; 1: this process), or Dask
        workers of ``dask="local"``.
    dask
        ``None`` (local pool), ``"local"`` (a ``LocalCluster``), a scheduler address or a
        ``distributed.Client``.
    tol
        HMP residual required of every extremal.
    full
        Solve every draw with the full discovery (no warm start).
    progress
        ``True`` (a progress bar on stderr, the default), ``False``/``None`` or a
        :class:`~hybridoc.progress.Progress` (:func:`hybridoc.progress.as_progress`): the
        stages and the draws done, with the failures. The nominal solve's line and what the
        run finds in ``out`` (a resumed run, shards computed again, files kept) are said on
        stderr in any case.
    distribution
        A callable ``(rng, M) -> (M, nx)`` initial states overriding the problem's own
        (:func:`distribution_problem`); its seed is ``seed`` (default 0).

    Returns
    -------
    Dataset

    Raises
    ------
    HybridocError
        Bad arguments, a scene without a distribution, an output directory holding another
        dataset, or locked by another run, or holding a ``shards/`` that hybridoc did not
        make; a complete dataset there whose data file fails its SHA-256 (left as it is);
        an unreachable Dask scheduler.
    """
    samples = check_count(samples, "samples", 1)
    source = distribution_problem(problem, distribution)
    check_samples_of(source, samples)  # before the nominal solve and any allocation
    _check_own_units(source)
    seed = source_seed(source, seed)
    workers = usable_cores() if workers is None else check_count(workers, "workers", 1)
    check_dask(dask)
    if not (isinstance(tol, int | float) and math.isfinite(tol) and tol > 0):
        raise HybridocError(f"tol must be a positive number, got {tol!r}")
    draws = source_draws(source, problem, samples, seed)
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise HybridocError(
            f"cannot create output directory {str(out)!r}: {exc.strerror}"
        ) from None
    settings = _settings(source, samples, seed, float(tol), bool(full), draws.get("x0"))
    with _locked(out), progress_scope(progress, "dataset") as p:
        return _make(out, source, settings, draws, workers, dask, p)


def initial_states_sha256(x0: np.ndarray) -> str:
    """The SHA-256 of ``(M, nx)`` initial states (little-endian float64, row-major): what a
    dataset of a problem with a Python distribution records of its draws."""
    return hashlib.sha256(np.ascontiguousarray(x0, dtype="<f8").tobytes()).hexdigest()


def source_seed(source: Scene | HybridOCP, seed: int | None) -> int:
    """The seed of the draws: ``seed``, else a scene distribution's own, else 0."""
    if seed is not None:
        return check_count(seed, "seed", 0)
    dist = getattr(source, "distribution", None)
    return int(getattr(dist, "seed", 0))


def source_draws(
    source: Scene | HybridOCP, problem: Any, samples: int, seed: int
) -> dict[str, Any]:
    """The draws' part of a task specification (:func:`draw_context`): a scene's spec, or
    a problem's initial states drawn here (:func:`problem_spec`). Draw 0 of a scene is made
    here too, so that a distribution that cannot be drawn fails in this process."""
    from hybridoc.problems import scene_of, spec_of

    table = scene_of(source, compiled=False)
    if table is not None:
        table.distribution.draw(table, 0, seed)
        return {"spec": spec_of(table)}
    text = str(problem) if isinstance(problem, str | Path) else None
    return problem_spec(source, text, draw_initial_states(source, samples, seed))


def _existing(out: Path, settings: dict[str, Any]) -> dict[str, Any] | Dataset | None:
    """What ``out`` holds of a run with ``settings``: ``None`` (nothing), the manifest of an
    unfinished run, or the complete :class:`Dataset` (its SHA-256 checked).

    Raises
    ------
    HybridocError
        A manifest that cannot be read or has other settings; a data file that fails its
        SHA-256.
    """
    mpath = out / MANIFEST_FILE
    if not mpath.exists() and not mpath.is_symlink():
        if (out / DATA_FILE).exists() or (out / DATA_FILE).is_symlink():
            # no manifest records it: the user's own file, never overwritten
            raise HybridocError(
                f"{str(out / DATA_FILE)!r} exists and was not written by 'hybridoc dataset' "
                f"(no {MANIFEST_FILE} records it): hybridoc never overwrites a file it did not "
                "write; move it away or choose another --out"
            )
        return None
    manifest = _read_manifest(mpath)
    if manifest.get("settings") != settings:
        raise HybridocError(
            f"{str(out)!r} holds a dataset with other settings (scene, samples, seed, tol "
            "or version); choose another --out or remove it"
        )
    if manifest.get("complete"):
        if (out / DATA_FILE).exists():
            # its SHA-256 is checked: a damaged or edited file is an error, kept as it is
            ds = load_dataset(out)
            if (out / SHARD_DIR).is_dir() and _is_ours(out / SHARD_DIR):
                _remove_shards(out / SHARD_DIR, _notice)  # a run killed as it cleaned up
            _notice(f"{out / DATA_FILE} is complete already")
            return ds
        _notice(f"{out / DATA_FILE} is missing: computing it again")
        manifest["complete"] = False
        _write_json(mpath, manifest)
    return manifest


def _good_shards(
    chunks: list[tuple[int, list[int]]], shard: dict[int, Path], spec_hash: str
) -> tuple[dict[int, dict[str, np.ndarray]], list[tuple[int, list[int]]]]:
    """The columns of the usable finished chunks, and the chunks still to compute (each bad
    shard said)."""
    parts: dict[int, dict[str, np.ndarray]] = {}
    todo = []
    for cid, idx in chunks:
        cols, why = _read_shard(shard[cid], idx, spec_hash)
        if cols is None:
            if why:
                _notice(f"shard {shard[cid].name} {why}: computing it again")
            todo.append((cid, idx))
        else:
            parts[cid] = cols
    return parts, todo


def _make(
    out: Path,
    source: Scene | HybridOCP,
    settings: dict[str, Any],
    draws: dict[str, Any],
    workers: int,
    dask: Any,
    progress: Progress,
) -> Dataset:
    """:func:`make_dataset` in ``out``, with its lock held."""
    _sweep(out, lambda n: n in (DATA_FILE, MANIFEST_FILE), lambda n: n == SHARD_DIR)
    manifest = _existing(out, settings)
    if isinstance(manifest, Dataset):
        return manifest
    # before the nominal solve, so that a folder that is not ours fails at once
    _check_data_file(out)
    sdir = _shard_dir(out, resuming=manifest is not None)
    _sweep(sdir, lambda n: bool(_CHUNK_NAME.fullmatch(n)), lambda n: False)
    t0 = time.perf_counter()
    samples, seed, tol, full = (settings[k] for k in ("samples", "seed", "tol", "full"))
    if manifest is None:
        nominal = None if full else _nominal(source, tol, progress)
        manifest = {
            "format": FORMAT,
            "complete": False,
            "settings": settings,
            "nominal": nominal,
        }
        _write_json(out / MANIFEST_FILE, manifest)
    nominal = manifest.get("nominal")
    spec = {**draws, "seed": seed, "tol": tol, "full": full, "nominal": nominal}
    spec_hash = hashlib.sha256(
        json.dumps({"settings": settings, "nominal": nominal}, sort_keys=True).encode()
    ).hexdigest()
    chunks = list(iter_chunks(samples, CHUNK))
    shard = {cid: sdir / f"chunk-{cid:06d}.npz" for cid, _ in chunks}
    parts, todo = _good_shards(chunks, shard, spec_hash)
    done = samples - sum(len(idx) for _, idx in todo)
    if done:
        _notice(f"resuming: {done} of {samples} samples already done")
    progress.stage("draws")
    tally = {"done": done, "failed": 0}

    def on_result(cid: int, cols: dict[str, np.ndarray]) -> None:
        _write_npz(shard[cid], {**cols, _SPEC_KEY: np.array([spec_hash])})
        parts[cid] = cols
        tally["done"] += len(cols["index"])
        tally["failed"] += int(np.sum(~np.isin(cols["status"], list(BASELINE_STATUSES))))
        progress.count(tally["done"], samples, f"{tally['failed']} failed")

    engine = "dask" if dask is not None else ("serial" if workers == 1 else "process-pool")
    run_chunks(_solve_chunk, spec, todo, workers=workers, dask=dask, on_result=on_result)
    run = {"engine": engine, "workers": workers, "t0": t0}
    return _finish(out, manifest, [parts[cid] for cid, _ in chunks], sdir, run)


def _finish(
    out: Path,
    manifest: dict[str, Any],
    parts: list[dict[str, np.ndarray]],
    sdir: Path,
    run: dict[str, Any],
) -> Dataset:
    """Write the data file and the complete manifest, and remove the shards."""
    data = _concat(parts)
    body = _npz_bytes(data)
    _check_data_file(out, body)  # the shards stay: a run after the file is moved finishes
    _atomic_write(out / DATA_FILE, body)
    digest = hashlib.sha256(body).hexdigest()
    status, counts = data["status"], {}
    for s in sorted(set(status.tolist())):
        counts[s] = int(np.sum(status == s))
    methods = {
        m or "none": int(np.sum(data["method"] == m)) for m in sorted(set(data["method"].tolist()))
    }
    from hybridoc.solution import package_versions

    manifest.update(
        complete=True,
        versions=package_versions(),
        counts=counts,
        methods=methods,
        sha256=digest,
        columns={k: list(v.shape) for k, v in sorted(data.items())},
        last_run={
            "engine": run["engine"],
            "workers": run["workers"],
            "wall_time_s": time.perf_counter() - run["t0"],
        },
    )
    _write_json(out / MANIFEST_FILE, manifest)
    _remove_shards(sdir, _notice)
    return Dataset(out, data, manifest)


def _check_data_file(out: Path, body: bytes | None = None) -> None:
    """Refuse to write ``out/dataset.npz`` over anything but a file of this run: a link, or
    something that is not a regular file, always; with ``body``, a file whose bytes differ
    (the file a run killed after writing it left has the very same bytes, since the data
    are written deterministically; any other is the user's).

    Raises
    ------
    HybridocError
        One line naming the file.
    """
    dpath = out / DATA_FILE
    if dpath.is_symlink() or (dpath.exists() and not dpath.is_file()):
        raise HybridocError(
            f"{str(dpath)!r} is a symbolic link or not a regular file: hybridoc never writes "
            "through a link; remove it or choose another --out"
        )
    if body is not None and dpath.exists():
        try:
            same = dpath.stat().st_size == len(body) and dpath.read_bytes() == body
        except OSError:
            same = False
        if not same:
            raise HybridocError(
                f"{str(dpath)!r} exists and was not written by this dataset run: hybridoc "
                "never overwrites a file it did not write; move it away and run the same "
                "command again (the finished shards are kept)"
            )


def _write_json(path: Path, obj: Any) -> None:
    _atomic_write(path, (json.dumps(obj, indent=1) + "\n").encode())


_SHA256 = re.compile(r"[0-9a-f]{64}")
_SETTINGS_COMMON = {"format", "hybridoc", "samples", "seed", "chunk", "tol", "full"}
_SETTINGS_SPEC = _SETTINGS_COMMON | {"spec"}
_SETTINGS_SCENE = _SETTINGS_COMMON | {"scene"}  # before issue #30: the TOML text alone
_SETTINGS_PROBLEM = _SETTINGS_COMMON | {"problem", "nominal_x0", "x0_sha256"}
_MANIFEST_KEYS = {"format", "complete", "settings", "nominal"}
_COMPLETE_KEYS = {"versions", "counts", "methods", "sha256", "columns", "last_run"}
#: the most draws a dataset may record (its columns hold the optimal controls of each)
MAX_SAMPLES = 10**9


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _counts(v: Any) -> bool:
    return isinstance(v, dict) and all(
        isinstance(k, str) and _is_int(n) and n >= 0 for k, n in v.items()
    )


def settings_spec(settings: dict[str, Any]) -> dict[str, Any] | None:
    """The spec of the scene whose ``[distribution]`` table a dataset's draws come from,
    from its manifest's settings (checked by :func:`check_manifest`): ``settings.spec``, or
    the TOML text of a manifest of before issue #30 (``settings.scene``) as a spec; ``None``
    for a problem with a Python distribution."""
    if "spec" in settings:
        return dict(settings["spec"])
    if "scene" in settings:
        return {"kind": "scene", "toml": settings["scene"]}
    return None


def check_manifest(manifest: Any, where: str) -> dict[str, Any]:
    """Validate a dataset manifest against its schema: the type and range of every field,
    written as code (module notes, ``manifest.json``).

    Returns
    -------
    dict
        ``manifest``.

    Raises
    ------
    HybridocError
        The first field that is missing, unknown, of another type or out of range: one
        line naming it and what it holds.
    """

    def bad(field: str, want: str, got: Any) -> HybridocError:
        shown = repr(got)
        shown = shown if len(shown) <= 60 else shown[:57] + "..."
        return HybridocError(f"{where}: {field!r} must be {want}, got {shown}")

    if not isinstance(manifest, dict):
        raise bad("manifest", "a JSON object", manifest)
    if manifest.get("format") != FORMAT:
        raise bad("format", repr(FORMAT), manifest.get("format"))
    complete = manifest.get("complete")
    if not isinstance(complete, bool):
        raise bad("complete", "true or false", complete)
    allowed = _MANIFEST_KEYS | (_COMPLETE_KEYS if complete else set())
    unknown = sorted(set(manifest) - allowed)
    if unknown:
        raise HybridocError(f"{where}: unknown entries {', '.join(map(repr, unknown))}")
    missing = sorted(allowed - set(manifest))
    if missing:
        raise HybridocError(f"{where}: missing entries {', '.join(map(repr, missing))}")
    st = manifest["settings"]
    if not isinstance(st, dict):
        raise bad("settings", "a JSON object", st)
    keys = (
        _SETTINGS_SPEC if "spec" in st else _SETTINGS_SCENE if "scene" in st else _SETTINGS_PROBLEM
    )
    if set(st) != keys:
        extra, lack = sorted(set(st) - keys), sorted(keys - set(st))
        raise HybridocError(
            f"{where}: 'settings' must hold exactly {', '.join(sorted(keys))} (unknown: "
            f"{', '.join(map(repr, extra)) or 'none'}; missing: {', '.join(lack) or 'none'})"
        )
    checks: list[tuple[str, str, Callable[[Any], bool]]] = [
        ("format", repr(FORMAT), lambda v: v == FORMAT),
        ("hybridoc", "a version string", lambda v: isinstance(v, str)),
        ("samples", f"an integer in [1, {MAX_SAMPLES}]",
         lambda v: _is_int(v) and 1 <= v <= MAX_SAMPLES),
        ("seed", "an integer in [0, 2**63)", lambda v: _is_int(v) and 0 <= v < 2**63),
        ("chunk", "a positive integer", lambda v: _is_int(v) and v >= 1),
        ("tol", "a positive finite number", lambda v: _is_number(v) and v > 0),
        ("full", "true or false", lambda v: isinstance(v, bool)),
        ("spec", 'a scene\'s spec {"kind": "scene", "toml": TOML text}',
         lambda v: isinstance(v, dict) and set(v) == {"kind", "toml"}
         and v["kind"] == "scene" and isinstance(v["toml"], str)),
        ("scene", "the scene as TOML text", lambda v: isinstance(v, str)),
        ("problem", "the problem's name", lambda v: isinstance(v, str)),
        ("nominal_x0", "a list of finite numbers",
         lambda v: isinstance(v, list) and len(v) >= 1 and all(map(_is_number, v))),
        ("x0_sha256", "a SHA-256 in hex",
         lambda v: isinstance(v, str) and _SHA256.fullmatch(v) is not None),
    ]  # fmt: skip
    for key, want, ok in checks:
        if key in st and not ok(st[key]):
            raise bad(f"settings.{key}", want, st[key])
    nominal = manifest["nominal"]
    if nominal is not None:
        if not isinstance(nominal, dict) or set(nominal) != {"sequence", "z", "cost", "status"}:
            raise bad("nominal", "null or {sequence, z, cost, status}", nominal)
        if not isinstance(nominal["sequence"], list) or not all(
            isinstance(g, str) for g in nominal["sequence"]
        ):
            raise bad("nominal.sequence", "a list of guard names", nominal["sequence"])
        if not isinstance(nominal["z"], list) or not all(map(_is_number, nominal["z"])):
            raise bad("nominal.z", "a list of finite numbers", nominal["z"])
        if not _is_number(nominal["cost"]):
            raise bad("nominal.cost", "a finite number", nominal["cost"])
        if not isinstance(nominal["status"], str):
            raise bad("nominal.status", "a status", nominal["status"])
    if not complete:
        return manifest
    samples = st["samples"]
    if not isinstance(manifest["sha256"], str) or not _SHA256.fullmatch(manifest["sha256"]):
        raise bad("sha256", "a SHA-256 in hex", manifest["sha256"])
    for key in ("counts", "methods"):
        v = manifest[key]
        if not _counts(v) or sum(v.values()) != samples:
            raise bad(key, f"counts of the {samples} draws by name", v)
    cols = manifest["columns"]
    if (
        not isinstance(cols, dict)
        or set(cols) != COLUMNS
        or not all(
            isinstance(v, list) and v and v[0] == samples and all(_is_int(n) and n >= 0 for n in v)
            for v in cols.values()
        )
    ):
        raise bad("columns", f"the shapes of the columns ({samples} rows each)", cols)
    if not isinstance(manifest["versions"], dict) or not all(
        isinstance(k, str) and (v is None or isinstance(v, str))
        for k, v in manifest["versions"].items()
    ):
        raise bad("versions", "package names and versions", manifest["versions"])
    run = manifest["last_run"]
    if (
        not isinstance(run, dict)
        or set(run) != {"engine", "workers", "wall_time_s"}
        or not isinstance(run["engine"], str)
        or not (_is_int(run["workers"]) and run["workers"] >= 1)
        or not (_is_number(run["wall_time_s"]) and run["wall_time_s"] >= 0)
    ):
        raise bad("last_run", "{engine, workers, wall_time_s}", run)
    return manifest


def _read_manifest(mpath: Path) -> dict[str, Any]:
    """The manifest at ``mpath``: a regular file (not a link), bounded JSON, schema-checked."""
    from hybridoc.outputs import read_json

    if mpath.is_symlink():
        raise HybridocError(
            f"{str(mpath)!r} is a symbolic link: a dataset's manifest is a file 'hybridoc "
            "dataset' wrote; remove it or choose another --out"
        )
    manifest = read_json(mpath, f"dataset manifest {str(mpath)!r}", max_bytes=16 << 20)
    return check_manifest(manifest, f"dataset manifest {str(mpath)!r}")


# each column's type ("f" float, "i" integer, "U" text) and shape, in the sizes of the module
# notes: M draws, nx states, D discs, K events (K + 1 phases), N steps, nu controls
_COLUMN_SCHEMA: dict[str, tuple[str, tuple[Any, ...]]] = {
    "index": ("i", ("M",)),
    "x0": ("f", ("M", "nx")),
    "targets": ("f", ("M", "D", 2)),
    **{k: ("U", ("M",)) for k in _STRINGS},
    **{k: ("f", ("M",)) for k in ("cost", "terminal_cost", "running_cost", "residual")},
    "n_events": ("i", ("M",)),
    **{k: ("f", ("M", "K")) for k in ("event_times", "multipliers", "approach_speeds")},
    "controls": ("f", ("M", "N", "nu")),
    "control_coefficients": ("f", ("M", ("K", 1), 2, "nu")),
    "phase_starts": ("f", ("M", ("K", 1))),
    **{k: ("f", ("M", ("K", 1), "nx")) for k in ("phase_states", "phase_costates")},
    **{k: ("f", ("M", "K", "nx")) for k in ("states_minus", "costates_minus")},
    **{k: ("f", ("M", "nx")) for k in ("final_state", "final_costate", "lambda0")},
}
_KINDS = {"f": ("f", "a float"), "i": ("iu", "an integer"), "U": ("U", "a text")}


def check_columns(
    columns: dict[str, np.ndarray], where: str, *, complete: bool = True
) -> dict[str, int]:
    """Check a dataset's columns against their schema: the names, each column's type and
    number of axes, and sizes that agree across columns (the same ``nx``, ``K``, ``nu``
    everywhere; ``K + 1`` phases; ``n_events`` within ``[0, K]``). With ``complete=False``
    (a :class:`Dataset` made in memory) only the columns it has are checked, and ``index``
    and ``x0``, which every check of the rows needs.

    Returns
    -------
    dict
        The sizes: ``M``, ``nx``, ``D``, ``K``, ``N``, ``nu``.

    Raises
    ------
    HybridocError
        The first column that breaks it: one line naming the dataset and the column.
    """
    needed = COLUMNS if complete else {"index", "x0"}
    if not needed <= set(columns) <= COLUMNS:
        extra, lack = sorted(set(columns) - COLUMNS), sorted(needed - set(columns))
        raise HybridocError(
            f"{where}: its columns are not a dataset's (unknown: "
            f"{', '.join(map(repr, extra)) or 'none'}; "
            f"missing: {', '.join(lack) or 'none'})"
        )
    sizes: dict[str, int] = {}
    for name, (kind, dims) in _COLUMN_SCHEMA.items():
        if name not in columns:
            continue
        a = columns[name]
        kinds, said = _KINDS[kind]
        if not isinstance(a, np.ndarray) or a.dtype.kind not in kinds:
            got = getattr(getattr(a, "dtype", None), "str", type(a).__name__)
            raise HybridocError(f"{where}: its column {name!r} must be {said} array, got {got}")
        if a.ndim != len(dims):
            raise HybridocError(
                f"{where}: its column {name!r} must have {len(dims)} axes, got shape {a.shape}"
            )
        for axis, (dim, n) in enumerate(zip(dims, a.shape, strict=True)):
            sym, extra = (dim, 0) if not isinstance(dim, tuple) else dim
            want = sym if isinstance(sym, int) else sizes.setdefault(sym, n - extra)
            if n - extra != want or n - extra < 0:
                raise HybridocError(
                    f"{where}: its column {name!r} has shape {a.shape}, whose axis {axis} does "
                    "not agree with the other columns"
                )
    events = columns.get("n_events")
    if events is not None and "K" in sizes and events.size:
        # a failed draw's row says -1 (_failed_record): no events, and not a count
        status = columns.get("status")
        failed = (
            np.asarray(status) == "failed"
            if status is not None and np.shape(status) == np.shape(events)
            else np.zeros(np.shape(events), dtype=bool)
        )
        low = np.where(failed, -1, 0)
        if np.any(events < low) or np.any(events > sizes["K"]):
            raise HybridocError(
                f"{where}: its column 'n_events' is not within [0, {sizes['K']}] "
                "(-1 for a failed draw)"
            )
    return sizes


def check_draws(ds: Dataset) -> None:
    """Check a dataset's rows against its problem: the ``index`` column is ``0..M-1``, and
    the initial states (and targets) are the draws of the distribution with the recorded
    seed, recomputed here from the scene in the manifest and compared exactly (bit for
    bit: the same code draws them). For a problem with a Python distribution, the initial
    states hash to the recorded ``x0_sha256`` (redrawn and compared by
    :func:`hybridoc.workflows.policies.validate_policy`, which has the problem).

    Raises
    ------
    HybridocError
        A row that is not its draw: one line naming the dataset, the first such draw and
        by how much it differs.
    """
    st, cols = ds.manifest["settings"], ds.columns
    where = f"the dataset in {str(ds.path)!r}"
    sizes = check_columns(cols, where, complete=False)  # load_dataset: all of them
    M, seed = st["samples"], st["seed"]
    if sizes["M"] != M:
        raise HybridocError(f"{where}: it has {sizes['M']} rows; its manifest says {M}")
    x0 = np.asarray(cols["x0"])
    if cols["index"].shape != (M,) or not np.array_equal(cols["index"], np.arange(M)):
        raise HybridocError(f"{where}: its index column is not 0..{M - 1}")
    spec = settings_spec(st)
    if spec is None:
        if x0.shape != (M, len(st["nominal_x0"])):
            raise HybridocError(f"{where}: its initial states have shape {x0.shape}")
        if initial_states_sha256(x0) != st["x0_sha256"]:
            raise HybridocError(
                f"{where}: its initial states are not the ones its manifest records "
                "(x0_sha256): they were changed after it was written"
            )
        return
    from hybridoc.problems import load_spec

    try:
        scene = load_spec(spec)
        if scene.distribution is None:
            raise HybridocError("it has no [distribution]")
        draws = [scene.distribution.draw(scene, i, seed) for i in range(M)]
    except HybridocError as exc:
        raise HybridocError(f"{where}: the scene in its manifest cannot be drawn: {exc}") from None
    want_x0 = np.array([d.initial_state() for d in draws], dtype=float).reshape(M, -1)
    want_targets = np.array([d.targets() for d in draws], dtype=float)
    for name, got, want in (("initial states", x0, want_x0),
                            ("targets", np.asarray(cols["targets"]), want_targets)):  # fmt: skip
        if got.shape != want.shape:
            raise HybridocError(
                f"{where}: its {name} have shape {got.shape}; the scene's draws {want.shape}"
            )
        same = (got == want) | (np.isnan(got) & np.isnan(want))
        if not same.all():
            rows = np.flatnonzero(~same.reshape(M, -1).all(axis=1))
            diff = np.nanmax(np.abs(got[rows[0]] - want[rows[0]]))
            raise HybridocError(
                f"{where}: the {name} of {rows.size} draw(s) are not the draws of its scene's "
                f"distribution with seed {seed} (draw {int(rows[0])} differs by up to "
                f"{diff:.3g}): the data or the manifest were changed after it was written"
            )
    nu = len(scene.control_labels())
    if sizes.get("nu", nu) != nu:
        raise HybridocError(
            f"{where}: its controls have {sizes['nu']} entries per step; its scene has {nu}"
        )


def load_dataset(path: str | Path) -> Dataset:
    """Read a dataset written by :func:`make_dataset` (a directory or its ``dataset.npz``),
    checking the data file against the SHA-256 in its manifest.

    Raises
    ------
    HybridocError
        Not a dataset, an incomplete one (run ``hybridoc dataset`` again to finish it), a
        manifest that fails its schema (:func:`check_manifest`), a data file that is not
        the one the manifest records (changed or damaged since it was written: the message
        names it and both hashes), or rows that are not the draws of the problem the
        manifest records (:func:`check_draws`: the initial states recomputed from the
        seed and the distribution).
    """
    p = Path(path)
    if p.is_file():
        p = p.parent
    mpath, dpath = p / MANIFEST_FILE, p / DATA_FILE
    if not mpath.exists() and not mpath.is_symlink():
        raise HybridocError(f"{str(p)!r} is not a dataset directory (no {MANIFEST_FILE})")
    manifest = _read_manifest(mpath)
    if not manifest.get("complete") or not dpath.exists():
        raise HybridocError(
            f"the dataset in {str(p)!r} is incomplete: run the same 'hybridoc dataset' command "
            "again to resume it"
        )
    try:
        data = dpath.read_bytes()
    except OSError as exc:
        raise HybridocError(f"cannot read {str(dpath)!r}: {exc.strerror}") from None
    expected, actual = manifest.get("sha256"), hashlib.sha256(data).hexdigest()
    if actual != expected:
        raise HybridocError(
            f"{str(dpath)!r} is not the file its manifest records (SHA-256 expected "
            f"{expected}, actual {actual}): it was changed or damaged after it was written; "
            "to compute it again, remove it and run the same 'hybridoc dataset' command"
        )
    try:
        columns = _parse_npz(data)
    except Exception as exc:  # the recorded hash of an unreadable file: whatever numpy raises
        raise HybridocError(f"cannot read {str(dpath)!r}: {type(exc).__name__}: {exc}") from None
    shapes = {k: list(v.shape) for k, v in sorted(columns.items())}
    if shapes != manifest["columns"]:
        raise HybridocError(
            f"{str(dpath)!r} does not hold the columns its manifest records (names or shapes)"
        )
    check_columns(columns, f"the dataset in {str(p)!r}")  # every column, typed and shaped
    ds = Dataset(p, columns, manifest)
    check_draws(ds)  # the rows against the problem: a file rehashed after an edit fails here
    return ds


def iter_chunks(n: int, size: int) -> Iterator[tuple[int, list[int]]]:
    """``(chunk id, indices)`` of ``range(n)`` in chunks of ``size``."""
    for k, a in enumerate(range(0, n, size)):
        yield k, list(range(a, min(a + size, n)))
