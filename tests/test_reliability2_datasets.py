"""Random perturbations of a valid dataset, each refused with one line (issue #32).

The issue's examples (initial states moved by 0.1 with the SHA-256 updated to match; a
dataset made with seed 7 whose manifest says seed 0; ``settings.samples = "five"``) are
single cases in ``test_dataset_checks.py`` and ``test_reliability2_examples.py``. Here they
are generated, on one genuine dataset made by :func:`make_dataset` once per module: a moved
initial state or target (any draw, any entry, any size of move), another seed, a manifest
field replaced by a value of another JSON type, a missing or an extra key at any level, a
column of another shape (rows added or dropped, an axis added, its entries' type changed),
each written as a determined editor would (the data file rehashed, the manifest's SHA-256
and column shapes updated to match). Each is refused by :func:`load_dataset` with one line
naming the dataset, and by ``validate-policy --dataset`` with exit 2, one line, before any
rollout (nothing on stdout).
"""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cli_here import run_here
from conftest import examples
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from small_scenes import strike_scene

from hybridoc.errors import HybridocError
from hybridoc.workflows import datasets as dsmod
from hybridoc.workflows.datasets import load_dataset, make_dataset

M = 3
SEED = 7
FAST = settings(
    max_examples=examples(25),
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)


@pytest.fixture(scope="module")
def genuine(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(the scene file, a genuine dataset of it: M draws, seed 7), made once."""
    d = tmp_path_factory.mktemp("genuine")
    scene = d / "scene.toml"
    scene.write_text(strike_scene("sc-perturb", steps=60))
    make_dataset(str(scene), M, d / "ds", seed=SEED, workers=1, progress=False)
    (d / "pol.py").write_text("import numpy as np\n\ndef p(t, s):\n    return np.zeros(2)\n")
    return scene, d / "ds"


def _read(ds: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    cols = dsmod._parse_npz((ds / dsmod.DATA_FILE).read_bytes())
    return cols, json.loads((ds / dsmod.MANIFEST_FILE).read_text())


def _write(
    out: Path, cols: dict[str, np.ndarray], manifest: dict[str, Any], rehash: bool = True
) -> Path:
    """The dataset as an editor who "updates the hash to match" would leave it."""
    out.mkdir(parents=True)
    body = dsmod._npz_bytes(cols)
    (out / dsmod.DATA_FILE).write_bytes(body)
    if rehash and isinstance(manifest, dict) and manifest.get("complete") is True:
        manifest = {
            **manifest,
            "sha256": hashlib.sha256(body).hexdigest(),
            "columns": {k: list(v.shape) for k, v in sorted(cols.items())},
        }
    (out / dsmod.MANIFEST_FILE).write_text(json.dumps(manifest))
    return out


def _refused(out: Path, scene: Path, *want: str) -> None:
    """Refused by load_dataset and by validate-policy --dataset, one line each."""
    with pytest.raises(HybridocError) as err:
        load_dataset(out)
    text = str(err.value)
    assert "\n" not in text and str(out) in text, text
    for w in want:
        assert w in text, (w, text)
    pol = f"{scene.parent / 'pol.py'}:p"
    done = run_here("validate-policy", str(scene), "--policy", pol, "--samples", str(M),
                    "--seed", str(SEED), "--dataset", str(out), "--workers", "1",
                    "--no-progress")  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert done.stdout == ""  # before any rollout
    (line,) = done.stderr.strip().splitlines()
    assert line == f"hybridoc: error: {text}"


def test_the_genuine_dataset_and_its_exact_copy_pass(
    genuine: tuple[Path, Path], tmp_path: Path
) -> None:
    scene, ds = genuine
    cols, manifest = _read(ds)
    copy_ = _write(tmp_path / "copy", cols, manifest)
    assert np.array_equal(load_dataset(copy_)["x0"], load_dataset(ds)["x0"])


@FAST
@given(
    column=st.sampled_from(["x0", "targets"]),
    data=st.data(),
    delta=st.one_of(st.floats(1e-300, 1e3), st.floats(-1e3, -1e-300), st.just(0.1)),
)
def test_a_moved_draw_is_refused_even_rehashed(
    tmp_path_factory: pytest.TempPathFactory,
    genuine: tuple[Path, Path],
    column: str,
    data: st.DataObject,
    delta: float,
) -> None:
    scene, ds = genuine
    cols, manifest = _read(ds)
    flat = cols[column].reshape(M, -1)
    row = data.draw(st.integers(0, M - 1), label="row")
    entry = data.draw(st.integers(0, flat.shape[1] - 1), label="entry")
    moved = flat[row, entry] + delta
    if np.isnan(moved):  # a disc without a target (NaN): given one
        moved = delta
    elif moved == flat[row, entry]:
        moved = np.nextafter(flat[row, entry], np.inf)  # a move below the last bit: one ulp
    flat[row, entry] = moved
    cols[column] = flat.reshape(cols[column].shape)
    out = _write(tmp_path_factory.mktemp("moved") / "ds", cols, manifest)
    name = "initial states" if column == "x0" else "targets"
    _refused(out, scene, f"the {name} of 1 draw(s)", f"draw {row} differs", f"seed {SEED}")


@FAST
@given(said=st.integers(0, 2**63 - 1).filter(lambda s: s != SEED))
def test_a_seed_that_is_not_the_datas_is_refused(
    tmp_path_factory: pytest.TempPathFactory, genuine: tuple[Path, Path], said: int
) -> None:
    scene, ds = genuine
    cols, manifest = _read(ds)
    manifest["settings"]["seed"] = said
    out = _write(tmp_path_factory.mktemp("seed") / "ds", cols, manifest)
    with pytest.raises(HybridocError, match=f"with seed {said} "):
        load_dataset(out)


def _paths(obj: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every key path of a manifest's objects (the column shapes' lists too)."""
    out = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.append((*prefix, k))
            out += _paths(v, (*prefix, k))
    return out


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats(allow_nan=False)
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner,
                                                                max_size=3),
    max_leaves=6,
)  # fmt: skip


def _kind(v: Any) -> str:
    """A JSON value's type, as the schema tells them apart."""
    if isinstance(v, bool) or v is None:
        return repr(v) if v is None else "bool"
    if isinstance(v, int | float):
        return "number"
    return type(v).__name__


def _get(d: Any, path: tuple[Any, ...]) -> Any:
    for k in path:
        d = d[k]
    return d


@FAST
@given(data=st.data())
def test_a_field_of_another_type_is_refused(
    tmp_path_factory: pytest.TempPathFactory, genuine: tuple[Path, Path], data: st.DataObject
) -> None:
    scene, ds = genuine
    cols, manifest = _read(ds)
    # every field but the ones the writer fills in (hash, shapes) and free text (scene,
    # version strings, status names), whose type alone is checked
    paths = [p for p in _paths(manifest) if p[0] not in ("sha256", "columns")]
    path = data.draw(st.sampled_from(paths), label="field")
    old = _get(manifest, path)
    value = data.draw(JSON_VALUES.filter(lambda v: _kind(v) != _kind(old)), label="value")
    if value is None and (path == ("nominal",) or (path[0] == "versions" and len(path) == 2)):
        return  # null by design: no nominal (a Python distribution), a package not installed
    bad = copy.deepcopy(manifest)
    _get(bad, path[:-1])[path[-1]] = value
    out = _write(tmp_path_factory.mktemp("type") / "ds", cols, bad)
    with pytest.raises(HybridocError) as err:
        load_dataset(out)
    assert "\n" not in str(err.value)


@FAST
@given(data=st.data(), add=st.booleans())
def test_a_missing_or_an_extra_key_is_refused(
    tmp_path_factory: pytest.TempPathFactory,
    genuine: tuple[Path, Path],
    data: st.DataObject,
    add: bool,
) -> None:
    scene, ds = genuine
    cols, manifest = _read(ds)
    # the objects whose keys are fixed: the manifest, its settings, nominal, last_run
    fixed = [(), ("settings",), ("last_run",)] + ([("nominal",)] if manifest["nominal"] else [])
    where = data.draw(st.sampled_from(fixed), label="object")
    obj = _get(manifest, where)
    if add:
        key = data.draw(st.text(min_size=1, max_size=10).filter(lambda k: k not in obj))
        obj[key] = data.draw(JSON_VALUES, label="value")
    else:
        key = data.draw(st.sampled_from(sorted(obj)), label="key")
        if where == () and key in ("sha256", "columns"):
            return  # rehashing fills them in again: dropped from the written file below
        del obj[key]
    out = _write(tmp_path_factory.mktemp("keys") / "ds", cols, manifest)
    _refused(out, scene)


@pytest.mark.parametrize("where", ["settings", "columns"])
def test_a_name_with_line_breaks_is_named_on_one_line(
    genuine: tuple[Path, Path], tmp_path: Path, where: str
) -> None:
    # found by the fuzzing of the test above: an extra settings key "\r" was printed raw
    scene, ds = genuine
    cols, manifest = _read(ds)
    if where == "settings":
        manifest["settings"]["\r\nsurprise"] = 1
    else:
        cols["\nsurprise"] = np.zeros(M)
    out = _write(tmp_path / "ds", cols, manifest)
    _refused(out, scene, "surprise")


@FAST
@given(data=st.data())
def test_a_column_of_another_shape_or_type_is_refused(
    tmp_path_factory: pytest.TempPathFactory, genuine: tuple[Path, Path], data: st.DataObject
) -> None:
    scene, ds = genuine
    cols, manifest = _read(ds)
    name = data.draw(st.sampled_from(sorted(cols)), label="column")
    a = cols[name]
    how = data.draw(st.sampled_from(["drop a row", "add a row", "add an axis", "text",
                                     "all rows"]), label="how")  # fmt: skip
    if how == "drop a row":
        a = a[:-1]
    elif how == "add a row":
        a = np.concatenate([a, a[-1:]])
    elif how == "add an axis":
        a = a[..., None]
    elif how == "text":
        a = a.astype(str)
    else:  # every column one row short, and the manifest's samples with them
        cols = {k: v[:-1] for k, v in cols.items()}
        a = cols[name]
    if how == "text" and a.dtype.kind == "U" and cols[name].dtype.kind == "U":
        return  # a text column as text: not a change
    cols[name] = a
    out = _write(tmp_path_factory.mktemp("shape") / "ds", cols, manifest)
    _refused(out, scene)


def test_a_data_file_edited_without_its_hash_is_refused(
    genuine: tuple[Path, Path], tmp_path: Path
) -> None:
    scene, ds = genuine
    cols, manifest = _read(ds)
    cols["cost"] = cols["cost"] * 0.5  # a "better" reference, the hash left as it was
    out = _write(tmp_path / "ds", cols, manifest, rehash=False)
    _refused(out, scene, "SHA-256 expected")


def test_a_dataset_of_another_scene_is_refused(genuine: tuple[Path, Path], tmp_path: Path) -> None:
    # the genuine dataset of this scene, checked against another scene's problem
    scene, ds = genuine
    other = tmp_path / "other.toml"
    other.write_text(strike_scene("sc-perturb", steps=60).replace("radius = 0.2", "radius = 0.25"))
    shutil.copy(scene.parent / "pol.py", tmp_path / "pol.py")
    done = run_here("validate-policy", str(other), "--policy", f"{tmp_path / 'pol.py'}:p",
                    "--samples", str(M), "--seed", str(SEED), "--dataset", str(ds),
                    "--workers", "1", "--no-progress")  # fmt: skip
    assert done.returncode == 2 and done.stdout == ""
    (line,) = done.stderr.strip().splitlines()
    assert str(ds) in line, line
