"""A dataset serialises its scene one way, by the problem's spec (issue #30): the manifest's
``settings.spec`` is ``{"kind": "scene", "toml": ...}``, read back with
``hybridoc.problems.load_spec``; a manifest of before (``settings.scene``, the TOML text
alone) still loads, and a policy validates against either."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from small_scenes import strike_scene

from hybridoc.errors import HybridocError
from hybridoc.problems import Scene, from_spec, load_spec, spec_of
from hybridoc.workflows.datasets import check_manifest, load_dataset, make_dataset
from hybridoc.workflows.policies import _check_references


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Scene]:
    d = tmp_path_factory.mktemp("spec")
    (d / "scene.toml").write_text(strike_scene("sc-spec"))
    ds = make_dataset(d / "scene.toml", 2, d / "new", workers=1, progress=False)
    return ds.path, Scene.from_toml(d / "scene.toml")


def test_the_manifest_holds_the_scene_spec(made: tuple[Path, Scene]) -> None:
    path, scene = made
    manifest = json.loads((path / "manifest.json").read_text())
    st = manifest["settings"]
    assert "scene" not in st and st["spec"] == spec_of(scene)
    ds = load_dataset(path)
    assert ds.spec == spec_of(scene) and ds.scene == scene
    assert isinstance(load_spec(ds.spec), Scene)
    assert from_spec(ds.spec).name == scene.name
    _check_references(ds, scene, ds.manifest["settings"]["seed"], 2)


def test_a_manifest_of_before_still_loads(made: tuple[Path, Scene], tmp_path: Path) -> None:
    path, scene = made
    old = tmp_path / "old"
    shutil.copytree(path, old)
    manifest = json.loads((old / "manifest.json").read_text())
    st = manifest["settings"]
    st["scene"] = st.pop("spec")["toml"]  # the layout of before: the TOML text alone
    (old / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    ds = load_dataset(old)  # the schema, the SHA-256 and the redrawn rows all pass
    assert ds.spec == spec_of(scene) and ds.scene == scene
    assert np.array_equal(ds["x0"], load_dataset(path)["x0"])
    _check_references(ds, scene, st["seed"], 2)


@pytest.mark.parametrize(
    "spec",
    [
        {"kind": "library", "toml": "x"},
        {"kind": "scene"},
        {"kind": "scene", "toml": 3},
        {"kind": "scene", "toml": "", "extra": 1},
        "horizon = 1.0",
    ],
)
def test_a_bad_settings_spec_is_one_line(made: tuple[Path, Scene], spec: object) -> None:
    path, _ = made
    manifest = json.loads((path / "manifest.json").read_text())
    manifest["settings"]["spec"] = spec
    with pytest.raises(HybridocError, match="'settings.spec' must be a scene's spec") as info:
        check_manifest(manifest, "m")
    assert "\n" not in str(info.value)


def test_spec_and_scene_together_are_refused(made: tuple[Path, Scene]) -> None:
    path, scene = made
    manifest = json.loads((path / "manifest.json").read_text())
    manifest["settings"]["scene"] = scene.to_toml()
    with pytest.raises(HybridocError, match="unknown: 'scene'"):
        check_manifest(manifest, "m")
