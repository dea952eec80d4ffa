"""Datasets checked against their problem (issue #32).

Accepted before with exit 0: a dataset whose initial states were moved by 0.1 with its
SHA-256 updated to match; a dataset made with seed 7 whose manifest says seed 0;
``settings.samples = "five"`` in a manifest. Now the initial states (and targets) are
recomputed from the manifest's scene and seed and compared bit for bit, and the manifest
is validated against its schema; each mismatch is one clear error (exit 2).

The datasets here are written directly (the rows a run writes, with the draws' initial
states and targets and placeholder results): the checks read the files, not the solves,
so no reference is solved.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cli_here import run_here
from conftest import examples
from hypothesis import given, settings
from hypothesis import strategies as st
from small_scenes import strike_scene

from hybridoc.errors import HybridocError
from hybridoc.problems.scene import Scene
from hybridoc.workflows import datasets as dsmod
from hybridoc.workflows.datasets import COLUMNS, FORMAT, check_manifest, load_dataset

SCENE_TOML = strike_scene("sc-check")

M = 4


def _columns(scene: Scene, samples: int, seed: int) -> dict[str, np.ndarray]:
    """The rows of a dataset of ``scene`` drawn with ``seed`` (placeholder results)."""
    draws = [scene.distribution.draw(scene, i, seed) for i in range(samples)]
    x0 = np.array([d.initial_state() for d in draws], dtype=float)
    return _rows(x0, np.array([d.targets() for d in draws], dtype=float), nu=2)


def _rows(x0: np.ndarray, targets: np.ndarray, nu: int) -> dict[str, np.ndarray]:
    """A dataset's columns for these initial states and targets (placeholder results)."""
    samples, nx = x0.shape
    n, k = 4, 1
    cols: dict[str, np.ndarray] = {
        "index": np.arange(samples),
        "x0": x0,
        "targets": targets,
        "status": np.array(["success"] * samples),
        "method": np.array(["warm"] * samples),
        "message": np.array([""] * samples),
        "sequence": np.array(["ball1|ball2"] * samples),
        "n_events": np.ones(samples, dtype=np.int64),
        "controls": np.zeros((samples, n, nu)),
        "control_coefficients": np.zeros((samples, k + 1, 2, nu)),
    }
    for name in ("cost", "terminal_cost", "running_cost", "residual"):
        cols[name] = np.zeros(samples)
    for name in ("event_times", "multipliers", "approach_speeds"):
        cols[name] = np.zeros((samples, k))
    cols["phase_starts"] = np.zeros((samples, k + 1))
    for name in ("phase_states", "phase_costates"):
        cols[name] = np.zeros((samples, k + 1, nx))
    for name in ("states_minus", "costates_minus"):
        cols[name] = np.zeros((samples, k, nx))
    for name in ("final_state", "final_costate", "lambda0"):
        cols[name] = np.zeros((samples, nx))
    assert set(cols) == COLUMNS
    return cols


def _write(out: Path, cols: dict[str, np.ndarray], manifest: dict[str, Any]) -> None:
    """Write ``dataset.npz`` and a manifest whose SHA-256 matches it (as an edit that
    "updates the hash to match" would)."""
    out.mkdir(parents=True, exist_ok=True)
    body = dsmod._npz_bytes(cols)
    (out / "dataset.npz").write_bytes(body)
    manifest = {
        **manifest,
        "sha256": hashlib.sha256(body).hexdigest(),
        "columns": {k: list(v.shape) for k, v in sorted(cols.items())},
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))


def _manifest(scene: Scene, samples: int, seed: int) -> dict[str, Any]:
    return _manifest_of(dsmod._settings(scene, samples, seed, 1e-10, False), samples)


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("scene") / "scene.toml"
    p.write_text(SCENE_TOML)
    return p


@pytest.fixture(scope="module")
def scene(scene_file: Path) -> Scene:
    return Scene.from_toml(scene_file)


def test_a_dataset_of_the_draws_loads(tmp_path: Path, scene: Scene) -> None:
    _write(tmp_path / "ds", _columns(scene, M, 7), _manifest(scene, M, 7))
    ds = load_dataset(tmp_path / "ds")
    assert len(ds) == M
    assert np.array_equal(ds["x0"], scene.sample_initial_states(M))  # the control case


@settings(max_examples=examples(10))
@given(
    row=st.integers(0, M - 1),
    coord=st.integers(0, 7),
    delta=st.sampled_from([1e-12, -1e-9, 1e-6, 0.1, -0.1, 3.0]),
)
def test_moved_initial_states_are_refused_even_rehashed(
    tmp_path_factory: pytest.TempPathFactory, scene: Scene, row: int, coord: int, delta: float
) -> None:
    out = tmp_path_factory.mktemp("moved")
    cols = _columns(scene, M, 7)
    cols["x0"][row, coord] += delta
    _write(out, cols, _manifest(scene, M, 7))
    with pytest.raises(HybridocError) as err:
        load_dataset(out)
    text = str(err.value)
    assert f"draw {row} differs" in text and "seed 7" in text and "\n" not in text


@settings(max_examples=examples(6))
@given(said=st.integers(0, 10**6).filter(lambda s: s != 7))
def test_a_manifest_seed_that_is_not_the_datas_is_refused(
    tmp_path_factory: pytest.TempPathFactory, scene: Scene, said: int
) -> None:
    out = tmp_path_factory.mktemp("seed")
    _write(out, _columns(scene, M, 7), _manifest(scene, M, said))  # drawn with 7, says `said`
    with pytest.raises(HybridocError, match=f"with seed {said}"):
        load_dataset(out)


def test_moved_targets_are_refused(tmp_path: Path, scene: Scene) -> None:
    cols = _columns(scene, M, 7)
    cols["targets"][2, 1, 0] += 0.1
    _write(tmp_path / "ds", cols, _manifest(scene, M, 7))
    with pytest.raises(HybridocError, match="the targets of 1 draw"):
        load_dataset(tmp_path / "ds")


# one field at a time, each with values of another type or out of range
BAD_FIELDS: list[tuple[tuple[str, ...], list[Any]]] = [
    (("settings", "samples"), ["five", 0, -1, 2.5, True, None, [4], 10**12]),
    (("settings", "seed"), [-1, "0", 1.5, None, False, 2**64]),
    (("settings", "tol"), [0, -1e-10, "1e-10", None, True]),
    (("settings", "chunk"), [0, "25", 2.5]),
    (("settings", "full"), ["no", 0, None]),
    (("settings", "scene"), [3, None, ["x"]]),
    (("settings", "hybridoc"), [0.2, None]),
    (("complete",), ["true", 1, None]),
    (("counts",), [{"success": "4"}, {"success": M + 1}, [M], {"success": -1}]),
    (("methods",), [{"warm": 1.5}, None]),
    (("sha256",), ["abc", 5, None, "G" * 64]),
    (("last_run",), [{"engine": "serial"}, None, {"engine": 1, "workers": 1, "wall_time_s": 0}]),
    (("versions",), [[], {"numpy": 2}]),
    (("nominal",), [{"sequence": "x", "z": [], "cost": 1.0, "status": "success"}, 5]),
    (("settings", "surprise"), [1]),
    (("surprise",), [1]),
]
CASES = [(path, value) for path, values in BAD_FIELDS for value in values]


def _set(manifest: dict[str, Any], path: tuple[str, ...], value: Any) -> None:
    d = manifest
    for key in path[:-1]:
        d = d[key]
    d[path[-1]] = value


@settings(max_examples=examples(16))
@given(case=st.sampled_from(CASES))
def test_every_manifest_field_is_checked_against_its_schema(
    scene: Scene, case: tuple[tuple[str, ...], Any]
) -> None:
    path, value = case
    manifest = _manifest(scene, M, 7)
    manifest["sha256"] = "0" * 64
    manifest["columns"] = {k: list(v.shape) for k, v in _columns(scene, M, 7).items()}
    check_manifest(json.loads(json.dumps(manifest)), "m")  # the genuine one passes
    _set(manifest, path, value)
    with pytest.raises(HybridocError) as err:
        check_manifest(json.loads(json.dumps(manifest)), "m")
    text = str(err.value)
    assert "\n" not in text and (path[-1] in text or path[0] in text), text


def test_samples_five_is_refused_on_load(tmp_path: Path, scene: Scene) -> None:
    manifest = _manifest(scene, M, 7)
    manifest["settings"]["samples"] = "five"
    _write(tmp_path / "ds", _columns(scene, M, 7), manifest)
    with pytest.raises(HybridocError, match=r"'settings\.samples' must be an integer.*'five'"):
        load_dataset(tmp_path / "ds")


def test_a_manifest_nested_deep_is_one_clear_error(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    out.mkdir()
    (out / "manifest.json").write_text("[" * 200_000 + "]" * 200_000)
    (out / "dataset.npz").write_bytes(b"")
    with pytest.raises(HybridocError, match="200000 deep"):
        load_dataset(out)


# ---------------------------------------------------------------------------- commands


def test_validate_policy_refuses_a_moved_dataset(
    tmp_path: Path, scene: Scene, scene_file: Path
) -> None:
    cols = _columns(scene, M, 7)
    cols["x0"][1, 4] += 0.1
    _write(tmp_path / "ds", cols, _manifest(scene, M, 7))
    pol = tmp_path / "pol.py"
    pol.write_text("import numpy as np\ndef p(t, s):\n    return np.zeros(2)\n")
    done = run_here(
        "validate-policy", str(scene_file), "--policy", f"{pol}:p", "--samples", "2",
        "--dataset", str(tmp_path / "ds"), "--workers", "1", "--no-progress",
    )  # fmt: skip
    assert done.returncode == 2
    (line,) = done.stderr.strip().splitlines()
    assert "draw 1 differs by up to 0.1" in line


@pytest.mark.parametrize("edit", ["moved", "seed", "five"])
def test_dataset_rerun_refuses_an_edited_complete_dataset(
    tmp_path: Path, scene: Scene, scene_file: Path, edit: str
) -> None:
    cols, manifest = _columns(scene, M, 7), _manifest(scene, M, 7)
    if edit == "moved":
        cols["x0"][0, 5] -= 0.1
    elif edit == "seed":
        cols = _columns(scene, M, 0)  # made with seed 0, says 7 (the command's seed)
    else:
        manifest["settings"]["samples"] = "five"
    _write(tmp_path / "ds", cols, manifest)
    done = run_here(
        "dataset", str(scene_file), "--samples", str(M), "--workers", "1", "--no-progress",
        "--out", str(tmp_path / "ds"),
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    line = done.stderr.strip().splitlines()[-1]
    want = {
        "moved": "draw 0 differs by up to 0.1",
        "seed": "distribution with seed 7 (draw 0 differs",
        "five": "'settings.samples' must be an integer",
    }[edit]
    assert line.startswith("hybridoc: error:") and want in line, line


# ---------------------------------------------------------------------------- a Python distribution


def _spread(rng: np.random.Generator, m: int) -> np.ndarray:
    return np.array([1.0, 0.0]) + rng.uniform(-0.05, 0.05, (m, 2))


@pytest.fixture(scope="module")
def ball() -> Any:
    import hybridoc

    return hybridoc.as_ocp("bouncing-ball").replace(name="ball-dist", distribution=_spread)


def _problem_dataset(out: Path, ball: Any, x0: np.ndarray, recorded: np.ndarray) -> None:
    """A dataset of ``ball`` whose rows hold ``x0`` and whose settings record ``recorded``."""
    manifest = _manifest_of(dsmod._settings(ball, len(x0), 0, 1e-10, False, recorded), len(x0))
    _write(out, _rows(x0, np.zeros((len(x0), 0, 2)), nu=ball.nu), manifest)


def _manifest_of(settings_: dict[str, Any], samples: int) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "complete": True,
        "settings": settings_,
        "nominal": None,
        "versions": {"hybridoc": "test"},
        "counts": {"success": samples},
        "methods": {"warm": samples},
        "last_run": {"engine": "serial", "workers": 1, "wall_time_s": 0.5},
    }


def test_a_python_distributions_rows_must_hash_to_the_record(tmp_path: Path, ball: Any) -> None:
    x0 = dsmod.draw_initial_states(ball, M, 0)
    _problem_dataset(tmp_path / "good", ball, x0, x0)
    assert np.array_equal(load_dataset(tmp_path / "good")["x0"], x0)
    moved = x0.copy()
    moved[2, 0] += 0.1  # the data file rehashed, the settings' x0_sha256 left as it was
    _problem_dataset(tmp_path / "moved", ball, moved, x0)
    with pytest.raises(HybridocError, match="not the ones its manifest records"):
        load_dataset(tmp_path / "moved")


def test_validate_policy_checks_a_dataset_object_too(tmp_path: Path, scene: Scene) -> None:
    from hybridoc.workflows.datasets import Dataset
    from hybridoc.workflows.policies import validate_policy

    cols = _columns(scene, M, 7)
    _write(tmp_path / "ds", cols, _manifest(scene, M, 7))
    ds = load_dataset(tmp_path / "ds")
    ds.columns["x0"][3, 4] += 0.1  # edited in memory, after its load
    moved = Dataset(ds.path, ds.columns, ds.manifest)
    with pytest.raises(HybridocError, match="draw 3 differs by up to 0.1"):
        validate_policy(scene, lambda t, s: np.zeros(2), 2, dataset=moved, workers=1,
                        progress=False)  # fmt: skip
