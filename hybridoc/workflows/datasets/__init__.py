"""Reference datasets: the exact optimal control of many initial states of one problem.

:func:`make_dataset` draws ``M`` initial states and solves each with the HMP reference;
:func:`load_dataset` reads the result back. The draws come from a disc scene's
``[distribution]`` table (:class:`~hybridoc.problems.distribution.Distribution`: concrete scenes,
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

import dataclasses
import hashlib
import json
import math
import multiprocessing as mp
import os
import sys
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc import children
from hybridoc.errors import HybridocError, SceneError
from hybridoc.progress import Progress, ProgressLike, progress_scope
from hybridoc.resources import check_samples_of
from hybridoc.solvers.threads import usable_cores
from hybridoc.workflows.datasets.draws import (
    BASELINE_STATUSES,
    DrawContext,
    check_count,
    distribution_problem,
    distribution_scene,
    draw_context,
    draw_initial_states,
    draw_ocp,
    draw_problem,
    problem_spec,
)
from hybridoc.workflows.datasets.draws import concat_columns as _concat
from hybridoc.workflows.datasets.draws import solve_chunk as _solve_chunk
from hybridoc.workflows.datasets.reading import (
    FORMAT,
    MAX_SAMPLES,
    Dataset,
    check_columns,
    check_draws,
    check_manifest,
    initial_states_sha256,
    load_dataset,
    settings_spec,
)
from hybridoc.workflows.datasets.reading import read_manifest as _read_manifest
from hybridoc.workflows.datasets.storage import CHUNK_NAME as _CHUNK_NAME
from hybridoc.workflows.datasets.storage import (
    COLUMNS,
    DATA_FILE,
    LOCK_FILE,
    MANIFEST_FILE,
    SHARD_DIR,
    SHARD_MARK,
)
from hybridoc.workflows.datasets.storage import SPEC_KEY as _SPEC_KEY
from hybridoc.workflows.datasets.storage import atomic_write as _atomic_write
from hybridoc.workflows.datasets.storage import is_ours as _is_ours
from hybridoc.workflows.datasets.storage import locked as _locked
from hybridoc.workflows.datasets.storage import npz_bytes as _npz_bytes
from hybridoc.workflows.datasets.storage import parse_npz as _parse_npz  # noqa: F401 (tests)
from hybridoc.workflows.datasets.storage import read_shard as _read_shard
from hybridoc.workflows.datasets.storage import remove_shards as _remove_shards
from hybridoc.workflows.datasets.storage import shard_dir as _shard_dir
from hybridoc.workflows.datasets.storage import sweep as _sweep
from hybridoc.workflows.datasets.storage import write_npz as _write_npz

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.ocp import HybridOCP
    from hybridoc.problems import Scene

__all__ = [
    "CHUNK",
    "COLUMNS",
    "DATA_FILE",
    "LOCK_FILE",
    "MANIFEST_FILE",
    "SHARD_DIR",
    "SHARD_MARK",
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
    "settings_spec",
    "source_draws",
    "source_seed",
    "usable_cores",
]

CHUNK = 25
"""Draws per chunk (one shard file, one task of the pool or of Dask)."""


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


def iter_chunks(n: int, size: int) -> Iterator[tuple[int, list[int]]]:
    """``(chunk id, indices)`` of ``range(n)`` in chunks of ``size``."""
    for k, a in enumerate(range(0, n, size)):
        yield k, list(range(a, min(a + size, n)))
