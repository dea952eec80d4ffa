"""Reference datasets, read back and checked (:mod:`hybridoc.workflows.datasets`): the
:class:`Dataset`, :func:`load_dataset` and the checks of every load: the manifest's schema,
the columns' types and shapes, and the rows against the draws of the problem."""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.errors import HybridocError
from hybridoc.workflows.datasets.draws import BASELINE_STATUSES, STRINGS
from hybridoc.workflows.datasets.storage import COLUMNS, DATA_FILE, MANIFEST_FILE, parse_npz

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.problems import Scene

FORMAT = "hybridoc-dataset/1"


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


def initial_states_sha256(x0: np.ndarray) -> str:
    """The SHA-256 of ``(M, nx)`` initial states (little-endian float64, row-major): what a
    dataset of a problem with a Python distribution records of its draws."""
    return hashlib.sha256(np.ascontiguousarray(x0, dtype="<f8").tobytes()).hexdigest()


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
    _check_settings(manifest["settings"], where, bad)
    _check_nominal(manifest["nominal"], bad)
    if complete:
        _check_complete(manifest, bad)
    return manifest


def _check_settings(st: Any, where: str, bad: Callable[[str, str, Any], HybridocError]) -> None:
    """:func:`check_manifest` of ``settings``: one of its layouts, each field typed."""
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


def _check_nominal(nominal: Any, bad: Callable[[str, str, Any], HybridocError]) -> None:
    """:func:`check_manifest` of ``nominal``: null or the nominal solution's fields."""
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


def _check_complete(
    manifest: dict[str, Any], bad: Callable[[str, str, Any], HybridocError]
) -> None:
    """:func:`check_manifest` of a complete manifest's entries: hash, counts, columns,
    versions and the last run."""
    st = manifest["settings"]
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


def read_manifest(mpath: Path) -> dict[str, Any]:
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
    **{k: ("U", ("M",)) for k in STRINGS},
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
    manifest = read_manifest(mpath)
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
        columns = parse_npz(data)
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
