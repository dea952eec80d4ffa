"""The issue's examples of data loss, untrusted datasets and policies, crashes and hangs,
each reproduced exactly (issue #32), where no other test does.

Where each example of the issue is tested (the 202-disc judge and the ``--samples``,
``--starts`` and huge-header memory cases are ``test_resources.py``'s):

Data loss
    - ``evaluate``, ``solve --method dt``, ``train-policy``, ``export`` through a planted
      link: ``test_outputs_safe.py`` (``test_evaluate_never_writes_through_a_link``,
      ``test_solve_dt_...``, ``test_train_policy_...``, ``test_export_...``); every
      command and name: ``test_reliability2_outputs.py``.
    - a user's ``dataset.npz`` overwritten by ``dataset`` and ``validate-policy``:
      ``test_outputs_safe.py`` (``test_dataset_never_overwrites_a_users_dataset_npz``,
      ``test_validate_policy_never_overwrites_a_users_dataset_npz``).
    - ``HYBRIDOC_CACHE`` at a 1777 folder re-permissioned to 0700:
      ``test_cache_shared.py`` (the cache itself) and here (a command).
Datasets and policies trusted
    - x0 moved by 0.1 with its SHA-256 updated: ``test_dataset_checks.py``
      (``test_validate_policy_refuses_a_moved_dataset``); generated:
      ``test_reliability2_datasets.py``.
    - made with seed 7, manifest says seed 0: here, exactly (``test_dataset_checks.py``
      draws other seeds).
    - ``settings.samples = "five"``: ``test_dataset_checks.py``
      (``test_samples_five_is_refused_on_load``, and through ``dataset``).
    - an MLP for 4 states on an 8-state scene: ``test_policy_checks.py``
      (``test_an_mlp_for_4_states_is_refused_on_an_8_state_scene``).
Crashes and hangs
    - an unwritable output folder: internal error after the whole solve: here, with
      ``solve`` (``test_outputs_safe.py`` has ``evaluate``; every command:
      ``test_reliability2_outputs.py``).
    - a policy JSON nested 200 000 deep: ``test_policy_checks.py``
      (``test_a_policy_json_nested_200000_deep``).
    - FIFOs at the cache's record names, ``solve`` hangs: here, through ``solve`` itself
      (``test_cache_shared.py`` has the cache's own calls).
    - a child process that outlived its parent: ``test_reliability2_children.py``.
"""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest
from cli_here import run_here
from small_scenes import strike_scene
from test_outputs_safe import _unwritable

import hybridoc
from hybridoc.errors import HybridocError
from hybridoc.workflows import datasets as dsmod
from hybridoc.workflows.datasets import load_dataset, make_dataset

posix = pytest.mark.skipif(os.name != "posix", reason="POSIX folders and FIFOs")


def test_a_dataset_made_with_seed_7_whose_manifest_says_seed_0(tmp_path: Path) -> None:
    scene = tmp_path / "scene.toml"
    scene.write_text(strike_scene("sc-seed", steps=60))
    make_dataset(str(scene), 2, tmp_path / "ds", seed=7, workers=1, progress=False)
    manifest_path = tmp_path / "ds" / dsmod.MANIFEST_FILE
    manifest = json.loads(manifest_path.read_text())
    assert manifest["settings"]["seed"] == 7
    manifest["settings"]["seed"] = 0  # the data file, and so its SHA-256, unchanged
    manifest_path.write_text(json.dumps(manifest))
    with pytest.raises(HybridocError, match="distribution with seed 0"):
        load_dataset(tmp_path / "ds")
    pol = tmp_path / "pol.py"
    pol.write_text("import numpy as np\ndef p(t, s):\n    return np.zeros(2)\n")
    done = run_here("validate-policy", str(scene), "--policy", f"{pol}:p", "--samples", "2",
                    "--seed", "0", "--dataset", str(tmp_path / "ds"), "--workers", "1",
                    "--no-progress")  # fmt: skip
    assert done.returncode == 2 and done.stdout == ""
    (line,) = done.stderr.strip().splitlines()
    assert "with seed 0 (draw 0 differs" in line, line


@posix
def test_solve_into_an_unwritable_folder_is_refused_before_the_solve(tmp_path: Path) -> None:
    d = _unwritable(tmp_path)
    done = run_here("solve", "single-collision", "--method", "dt", "--out", str(d))
    assert done.returncode == 2  # was 3 (PermissionError), after the whole solve
    assert done.stdout == ""  # refused first: no solve for nothing
    (line,) = done.stderr.strip().splitlines()
    assert line.startswith("hybridoc: error: cannot write in output directory") and str(d) in line


# `hybridoc ARGS` with a FIFO at the record name (and an unrecorded file at the library's
# name) of every compiled function the run looks up in its cache, planted just before the
# lookup; no compilation is started (only the lookups are the issue's)
FIFO_RUNNER = """
import hashlib, os, sys
from pathlib import Path
from hybridoc import compiled

cache = Path(os.environ["HYBRIDOC_CACHE"])
lookup = compiled.Accelerated.__init__
planted = []

def plant(self, fn, **kw):
    key = hashlib.sha256(fn.serialize().encode()).hexdigest()[:24]
    lib = cache / f"{fn.name()}_{key}.so"
    record = cache / f"{lib.name}.sha256"
    if not os.path.lexists(record):
        lib.write_bytes(b"\\x7fELF not a library")
        os.mkfifo(record)
        planted.append(record)
    lookup(self, fn, **kw)

compiled.Accelerated.__init__ = plant
compiled.Accelerated._start = lambda self: None
from hybridoc.cli import main

code = main(sys.argv[1:])
print("planted", len(planted), file=sys.stderr)
sys.exit(code)
"""


@posix
def test_fifos_at_the_caches_record_names_never_make_solve_wait(tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    cache.mkdir(mode=0o700)
    root = str(Path(hybridoc.__file__).resolve().parents[1])
    path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)
    env = {**os.environ, "HYBRIDOC_CACHE": str(cache), "HYBRIDOC_CODEGEN": "1", "PYTHONPATH": path}
    cmd = [sys.executable, "-c", FIFO_RUNNER, "solve", "single-collision", "--method", "dt",
           "--json"]  # fmt: skip
    try:
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        pytest.fail("solve waited on a FIFO in the code cache")
    assert done.returncode in (0, 1), done.stderr  # an answer (best-found: 1)
    assert json.loads(done.stdout)["cost"] > 0
    planted = int(done.stderr.strip().splitlines()[-1].split()[-1])
    assert planted >= 1  # the run did look its functions up
    fifos = [p for p in cache.iterdir() if stat.S_ISFIFO(p.lstat().st_mode)]
    assert len(fifos) <= planted  # nothing new; a FIFO hybridoc did not record may go


@posix
def test_a_command_never_re_permissions_a_shared_cache_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from hybridoc import compiled

    if compiled.compiler() is None:
        pytest.skip("no C compiler: compiled code, and its cache, are off")
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o1777)
    monkeypatch.setenv("HYBRIDOC_CACHE", str(shared))
    monkeypatch.setenv("HYBRIDOC_CODEGEN", "1")
    monkeypatch.setattr(compiled, "_WARNED", set())
    done = run_here("evaluate", "single-collision", "--json")
    assert done.returncode == 0, done.stderr
    assert stat.S_IMODE(shared.stat().st_mode) == 0o1777  # was 0o700: others locked out
    assert list(shared.iterdir()) == []  # nothing written into the shared folder
