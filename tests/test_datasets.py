"""Initial-state distributions, reference datasets (resumable, pool = Dask = serial), policy
loading and validation over a distribution, and their bad inputs."""

from __future__ import annotations

import copy
import dataclasses
import json
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from small_scenes import strike_scene

import hybridoc
import hybridoc.workflows.datasets as dsmod
from hybridoc.cli import main
from hybridoc.errors import ControlsError, HybridocError, SceneError
from hybridoc.problems import load_scene
from hybridoc.problems.scene import DiscSpread, Distribution, Scene, Spread
from hybridoc.workflows.datasets import load_dataset, make_dataset
from hybridoc.workflows.policies import PolicyError, load_policy, validate_policy

M = 6  # draws of the shared dataset (each ~0.1 s warm)

SCENE_TOML = strike_scene("sc-dist")

POLICIES = """
import numpy as np

def good(t, s):
    return np.array([2.0 * (s[2] - s[0]) + 1.0, 2.0 * (s[3] - s[1]) + 2.0])

def miss(t, s):
    return np.array([-1.0, 0.0])

def wrong_shape(t, s):
    return np.zeros(3)

def nan(t, s):
    return np.array([np.nan, 0.0])

def raising(t, s):
    raise RuntimeError("boom")

not_callable = 3

class Klass:
    pass
"""


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("ds")
    (d / "scene.toml").write_text(SCENE_TOML)
    (d / "pol.py").write_text(POLICIES)
    return d


@pytest.fixture(scope="module")
def dataset(files: Path) -> Any:
    with pytest.MonkeyPatch.context() as mp:
        share_nominals(mp)  # its nominal, solved here, serves the tests of nominal_once
        return make_dataset(files / "scene.toml", M, files / "serial", workers=1, progress=False)


#: make_dataset's nominal references in this process: ``(scene as TOML, tol) -> nominal``
_NOMINALS: dict[tuple[str, float], Any] = {}


def share_nominals(mp: pytest.MonkeyPatch) -> None:
    """Patch make_dataset's nominal solve so that each scene's is solved once per process
    and each run gets its own copy (why: :func:`nominal_once`)."""
    solve = dsmod._nominal

    def once(source: Any, tol: float, progress: Any) -> Any:
        key = (source.to_toml(), float(tol))
        if key not in _NOMINALS:
            _NOMINALS[key] = solve(source, tol, progress)
        return copy.deepcopy(_NOMINALS[key])

    mp.setattr(dsmod, "_nominal", once)


@pytest.fixture
def nominal_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """The nominal reference of a scene solved once per process, for tests about what the
    runs do with it (chunks, resuming, engines, a Dask scheduler out of reach): each run
    into a new folder solved the same nominal again (1.5-5 s under load). That every run
    finds the same nominal, in another process too, is checked by test_dataset_faults.py
    (a subprocess's whole run against this process's, byte for byte)."""
    share_nominals(monkeypatch)


@pytest.fixture(scope="module")
def dask_client() -> Any:
    distributed = pytest.importorskip("distributed")
    cluster = distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    )
    client = distributed.Client(cluster)
    yield client
    client.close()
    cluster.close()


def same(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal arrays, NaN equal to NaN where the dtype has NaN."""
    return bool(np.array_equal(a, b, equal_nan=np.asarray(a).dtype.kind in "fc"))


# ---------------------------------------------------------------------------- distributions


def scene_dict() -> dict[str, Any]:
    return tomllib.loads(SCENE_TOML)


def test_distribution_round_trip_and_draws() -> None:
    scene = Scene.from_dict(scene_dict())
    assert scene.distribution is not None
    assert scene.distribution.seed == 7
    again = Scene.from_dict(tomllib.loads(scene.to_toml()))
    assert again == scene
    assert again.with_steps(10).distribution == scene.distribution
    xs = scene.sample_initial_states(20)
    assert xs.shape == (20, 8)
    # only ball2's position varies, within +-0.3 of the nominal
    assert np.all(xs[:, [0, 1, 4, 5, 6, 7]] == scene.initial_state()[[0, 1, 4, 5, 6, 7]])
    assert np.all(np.abs(xs[:, 2:4] - np.array([-1.0, -1.0])) <= 0.3)
    # draw i does not depend on how many are drawn; another seed gives other draws
    assert np.array_equal(scene.sample_initial_states(5), xs[:5])
    assert np.array_equal(scene.draw_scenes(3, start=4)[0].initial_state(), xs[4])
    assert not np.array_equal(scene.sample_initial_states(5, seed=8), xs[:5])
    drawn = scene.draw_scenes(2)
    assert drawn[1].name == "sc-dist#1" and drawn[1].distribution is None


def test_distribution_python_object_normal_and_target_range() -> None:
    base = load_scene("single-collision")
    dist = Distribution(
        discs=(
            DiscSpread("ball1", velocity=Spread("normal", (0.1, 0.1))),
            DiscSpread("ball2", target={"range": [[-0.1, 0.1], [0.0, 0.2]]}),
        ),
        seed=1,
    )
    scene = dataclasses.replace(base, distribution=dist)
    drawn = scene.draw_scenes(10)
    targets = np.array([s.discs[1].target for s in drawn])
    assert np.all((targets[:, 0] >= -0.1) & (targets[:, 0] <= 0.1))
    assert np.all((targets[:, 1] >= 0.0) & (targets[:, 1] <= 0.2))
    assert len({s.discs[0].velocity for s in drawn}) == 10
    assert Scene.from_dict(tomllib.loads(scene.to_toml())) == scene


def test_overlapping_draws_are_redrawn_then_capped() -> None:
    data = scene_dict()
    # about half of these draws put ball2 onto ball1: they are redrawn
    data["distribution"]["discs"]["ball2"] = {"position": {"range": [[-1.0, -1.0], [-2.2, -1.4]]}}
    scene = Scene.from_dict(data)
    for s in scene.draw_scenes(10):
        assert math_dist(s.discs[0].position, s.discs[1].position) >= 0.4 - 1e-12
    data["distribution"]["discs"]["ball2"] = {"position": {"range": [[-1.0, -1.0], [-2.1, -1.9]]}}
    data["distribution"]["max_tries"] = 5
    scene = Scene.from_dict(data)
    with pytest.raises(SceneError, match=r"sample 0 .*no draw without overlaps in 5 tries"):
        scene.draw_scenes(1)


def math_dist(a: Any, b: Any) -> float:
    return float(np.hypot(a[0] - b[0], a[1] - b[1]))


BAD_DISTRIBUTIONS = [
    ("not a table", 3, ["'distribution' must be a table"]),
    ("unknown key", {"sed": 1, "discs": {"ball2": {"position": {"uniform": [1, 1]}}}}, ["sed"]),
    ("seed negative", {"seed": -1, "discs": {"ball2": {"position": {"uniform": [1, 1]}}}},
     ["seed", "integer >= 0"]),
    ("max_tries zero", {"max_tries": 0, "discs": {"ball2": {"position": {"uniform": [1, 1]}}}},
     ["max_tries", ">= 1"]),
    ("nothing varies", {"seed": 1}, ["nothing varies"]),
    ("unknown disc", {"discs": {"ball9": {"position": {"uniform": [1, 1]}}}},
     ["distribution.discs.ball9", "no disc of that name"]),
    ("unknown field", {"discs": {"ball2": {"mass": {"uniform": [1, 1]}}}}, ["mass", "allowed"]),
    ("unknown kind", {"discs": {"ball2": {"position": {"gauss": [1, 1]}}}},
     ["ball2.position", "unknown spread 'gauss'"]),
    ("two kinds", {"discs": {"ball2": {"position": {"uniform": [1, 1], "normal": [1, 1]}}}},
     ["ball2.position", "one of the keys"]),
    ("negative width", {"discs": {"ball2": {"position": {"uniform": [-0.1, 1]}}}},
     ["ball2.position", ">= 0"]),
    ("nan width", {"discs": {"ball2": {"velocity": {"normal": [float("nan"), 1]}}}},
     ["ball2.velocity", "finite"]),
    ("range reversed", {"discs": {"ball2": {"position": {"range": [[1, 0], [0, 1]]}}}},
     ["range", "low 1.0 > high 0.0"]),
    ("range flat", {"discs": {"ball2": {"position": {"range": [0, 1]}}}}, ["range"]),
    ("target on a disc without one", {"discs": {"ball1": {"target": {"uniform": [1, 1]}}}},
     ["ball1.target", "no target"]),
]  # fmt: skip


@pytest.mark.parametrize(("dist", "words"), [c[1:] for c in BAD_DISTRIBUTIONS],
                         ids=[c[0] for c in BAD_DISTRIBUTIONS])  # fmt: skip
def test_bad_distribution_tables(dist: Any, words: list[str]) -> None:
    data = scene_dict()
    data["distribution"] = copy.deepcopy(dist)
    with pytest.raises(SceneError) as exc:
        Scene.from_dict(data)
    for w in words:
        assert w in str(exc.value), str(exc.value)


def test_bad_draw_arguments() -> None:
    scene = Scene.from_dict(scene_dict())
    for bad in (0, -1, 2.5, True):
        with pytest.raises(SceneError, match="samples"):
            scene.draw_scenes(bad)
    with pytest.raises(SceneError, match="seed"):
        scene.draw_scenes(1, seed=-3)
    with pytest.raises(SceneError, match="no \\[distribution\\]"):
        load_scene("single-collision").draw_scenes(1)


# ---------------------------------------------------------------------------- datasets


def test_dataset_columns_and_manifest(dataset: Any) -> None:
    c = dataset.columns
    assert len(dataset) == M
    assert list(c["index"]) == list(range(M))
    assert set(c) == dsmod.COLUMNS
    assert set(c["status"]) == {"success"}, c["message"]
    assert set(c["sequence"]) == {"ball1|ball2"}
    assert c["controls"].shape == (M, 480, 2)
    assert c["event_times"].shape == (M, 1) and c["phase_costates"].shape == (M, 2, 8)
    assert c["control_coefficients"].shape == (M, 2, 2, 2)
    assert np.all(c["residual"] <= 1e-10)
    scene = dataset.scene
    assert np.array_equal(c["x0"], scene.sample_initial_states(M))
    # every cost is the judge's cost of the optimal u(t) of that draw
    from hybridoc.reference import reference_control
    from hybridoc.reference.result import make_result
    from hybridoc.reference.shooting import newton, shooting_system

    i = 2
    ocp = scene.draw_scenes(1, start=i)[0].to_ocp()
    S = shooting_system(ocp, ["ball1|ball2"])
    z0 = S.pack(c["lambda0"][i], c["event_times"][i], c["multipliers"][i],
                c["phase_costates"][i, 1:])  # fmt: skip
    res = make_result(S, newton(S, z0), "check")
    u, bps = reference_control(res)
    assert hybridoc.evaluate_callable(ocp, u, breakpoints=bps).cost == pytest.approx(
        c["cost"][i], rel=1e-9
    )
    m = dataset.manifest
    assert m["complete"] and m["counts"] == {"success": M}
    assert m["nominal"]["sequence"] == ["ball1|ball2"]
    assert m["versions"]["numpy"] == np.__version__
    assert m["settings"]["samples"] == M and m["settings"]["seed"] == 7
    assert sorted(p.name for p in dataset.path.iterdir()) == ["dataset.npz", "manifest.json"]
    assert load_dataset(dataset.path / "dataset.npz").manifest["sha256"] == m["sha256"]


def test_dataset_resumes_to_the_same_file(
    files: Path, dataset: Any, monkeypatch: pytest.MonkeyPatch, nominal_once: None
) -> None:
    monkeypatch.setattr(dsmod, "CHUNK", 2)
    ref = make_dataset(files / "scene.toml", M, files / "chunk2", workers=1, progress=False)
    # the chunk size is part of the settings, not of the data
    for k, v in dataset.columns.items():
        assert same(v, ref.columns[k]), k
    calls = {"n": 0}
    solve = dsmod._solve_chunk

    def flaky(spec: Any, idx: list[int]) -> Any:
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return solve(spec, idx)

    out = files / "interrupted"
    monkeypatch.setattr(dsmod, "_solve_chunk", flaky)
    with pytest.raises(KeyboardInterrupt):
        make_dataset(files / "scene.toml", M, out, workers=1, progress=False)
    assert sorted(p.name for p in (out / "shards").iterdir()) == [
        ".hybridoc-shards",  # the marker of a folder that hybridoc made
        "chunk-000000.npz",
    ]
    with pytest.raises(HybridocError, match="incomplete"):
        load_dataset(out)
    seen: list[list[int]] = []

    def counting(spec: Any, idx: list[int]) -> Any:
        seen.append(idx)
        return solve(spec, idx)

    monkeypatch.setattr(dsmod, "_solve_chunk", counting)
    done = make_dataset(files / "scene.toml", M, out, workers=1, progress=False)
    assert seen == [[2, 3], [4, 5]]  # nothing computed twice
    assert (out / "dataset.npz").read_bytes() == (files / "chunk2" / "dataset.npz").read_bytes()
    assert done.manifest["sha256"] == ref.manifest["sha256"]
    # a complete dataset is not computed again
    seen.clear()
    make_dataset(files / "scene.toml", M, out, workers=1, progress=False)
    assert seen == []
    with pytest.raises(HybridocError, match="other settings"):
        make_dataset(files / "scene.toml", M + 1, out, workers=1, progress=False)


def test_dataset_identical_under_pool_and_dask(
    files: Path, dataset: Any, dask_client: Any, nominal_once: None
) -> None:
    pool = make_dataset(files / "scene.toml", M, files / "pool", workers=2, progress=False)
    dsk = make_dataset(
        files / "scene.toml", M, files / "dask", workers=1, dask=dask_client, progress=False
    )
    data = (files / "serial" / "dataset.npz").read_bytes()
    assert (files / "pool" / "dataset.npz").read_bytes() == data
    assert (files / "dask" / "dataset.npz").read_bytes() == data
    assert pool.manifest["last_run"]["engine"] == "process-pool"
    assert dsk.manifest["last_run"]["engine"] == "dask"


def test_failed_draws_are_kept_and_marked(
    files: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import hybridoc.reference

    def broken(*args: Any, **kwargs: Any) -> Any:
        raise hybridoc.ConvergenceError("no extremal (test)")

    monkeypatch.setattr(hybridoc.reference, "solve_reference", broken)
    code = main(["dataset", str(files / "scene.toml"), "--samples", "3", "--out",
                 str(tmp_path), "--workers", "1", "--no-progress"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 1 and "3 of 3 draws have no verified optimum" in err
    ds = load_dataset(tmp_path)
    assert list(ds["status"]) == ["failed"] * 3
    assert all("no extremal (test)" in m for m in ds["message"])
    assert np.array_equal(ds["x0"], Scene.from_toml(files / "scene.toml").sample_initial_states(3))
    assert np.all(np.isnan(ds["cost"])) and ds.manifest["counts"] == {"failed": 3}


def test_dataset_bad_inputs(files: Path, tmp_path: Path, nominal_once: None) -> None:
    for bad in (0, -5):
        with pytest.raises(HybridocError, match="samples must be an integer >= 1"):
            make_dataset(files / "scene.toml", bad, tmp_path / "x")
    with pytest.raises(SceneError, match="no \\[distribution\\] table"):
        make_dataset("single-collision", 2, tmp_path / "x")
    # a generic HybridOCP needs a distribution in Python (tests/test_workflows_any_problem.py)
    with pytest.raises(SceneError, match="has no distribution of initial states"):
        make_dataset("bouncing-ball", 2, tmp_path / "x")
    with pytest.raises(HybridocError, match="workers"):
        make_dataset(files / "scene.toml", 2, tmp_path / "x", workers=0)
    with pytest.raises(HybridocError, match="bad Dask scheduler address"):
        make_dataset(files / "scene.toml", 2, tmp_path / "y", dask="nonsense", progress=False)
    with pytest.raises(HybridocError, match="cannot connect to the Dask scheduler"):
        make_dataset(files / "scene.toml", 2, tmp_path / "z", dask="tcp://127.0.0.1:9",
                     progress=False)  # fmt: skip
    with pytest.raises(HybridocError, match="not a dataset directory"):
        load_dataset(tmp_path)


# ---------------------------------------------------------------------------- policies


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit.script in torch >= 2.9
def test_load_policy_specs_and_errors(files: Path, tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")

    class Lin(torch.nn.Module):
        def forward(self, t: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
            return torch.stack([s[2] - s[0], s[3] - s[1] + 2.0])

    pt = tmp_path / "lin.pt"
    torch.jit.script(Lin()).save(str(pt))
    pi = load_policy(str(pt))
    ev = hybridoc.evaluate(files / "scene.toml", policy=pi)
    assert np.isfinite(ev.cost)
    assert load_policy(f"{files / 'pol.py'}:good")(0.0, np.zeros(8)).shape == (2,)
    f = lambda t, s: np.zeros(2)  # noqa: E731
    assert load_policy(f) is f
    (tmp_path / "junk.pt").write_bytes(b"not a model")
    (tmp_path / "bad.py").write_text("raise ValueError('oops')\n")
    cases = [
        (str(tmp_path / "missing.pt"), "does not exist"),
        (str(tmp_path / "junk.pt"), "cannot load"),
        (f"{tmp_path / 'missing.py'}:good", "does not exist"),
        (f"{files / 'pol.py'}:nope", "has no 'nope'"),
        (f"{files / 'pol.py'}:not_callable", "not a callable"),
        (f"{files / 'pol.py'}:Klass", "a class"),
        (f"{tmp_path / 'bad.py'}:x", "raised ValueError"),
        (str(files / "pol.py"), "name the callable"),
        ("policy.onnx", "expected a TorchScript file"),
        (3, "a policy is"),
    ]
    for spec, words in cases:
        with pytest.raises(PolicyError, match=words):
            load_policy(spec)


@pytest.mark.parametrize(
    ("name", "words"),
    [
        ("wrong_shape", "returned 3 value"),
        ("nan", "non-finite"),
        ("raising", "raised RuntimeError"),
    ],
)
def test_bad_policies_are_one_clear_error(
    files: Path, dataset: Any, name: str, words: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(ControlsError, match=f"sample 0: .*{words}"):
        validate_policy(files / "scene.toml", f"{files / 'pol.py'}:{name}", 2,
                        dataset=dataset, workers=1, progress=False)  # fmt: skip
    code = main(["evaluate", str(files / "scene.toml"), "--policy", f"{files / 'pol.py'}:{name}"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and words in err, err


def test_dataset_and_rollouts_report_through_one_progress(files: Path, dataset: Any,
                                                          tmp_path: Path) -> None:  # fmt: skip
    stages: list[str] = []
    counts: list[tuple[int, int, str]] = []

    class Recorder:
        def stage(self, text: str) -> None:
            stages.append(text)

        def detail(self, text: str) -> None:
            pass

        def count(self, done: int, total: int, text: str = "") -> None:
            counts.append((done, total, text))

        def close(self) -> None:
            raise AssertionError("a caller's Progress is not closed by the run")

    rec = Recorder()
    ds = make_dataset(files / "scene.toml", 2, tmp_path / "two", workers=1, progress=rec)
    assert "nominal scene" in stages and stages[-1] == "draws"
    assert counts[-1] == (2, 2, f"{int(np.sum(ds['status'] != 'success'))} failed")
    stages.clear()
    counts.clear()
    validate_policy(files / "scene.toml", f"{files / 'pol.py'}:good", 2, dataset=dataset,
                    workers=1, progress=rec)  # fmt: skip
    assert stages == ["references", "rollouts"] and counts[-1] == (2, 2, "0 failed")


def test_validate_policy_report(files: Path, dataset: Any, dask_client: Any) -> None:
    rep = validate_policy(files / "scene.toml", f"{files / 'pol.py'}:good", M,
                          dataset=dataset.path, workers=1, progress=False)  # fmt: skip
    s = rep.summary
    assert s["compared"] == M and s["sequence_mismatch_rate"] == 0.0
    gap = rep.columns["policy_cost"] - dataset["cost"]
    assert s["gap_max"] == pytest.approx(gap.max()) and s["gap_median"] == np.median(gap)
    assert s["gap_mean"] > 0 and s["negative_gaps"] == 0
    assert rep.worst[0]["gap"] == s["gap_max"] and len(rep.worst[0]["x0"]) == 8
    # never reaching ball2: every sequence differs from the optimum
    miss = validate_policy(files / "scene.toml", f"{files / 'pol.py'}:miss", 4,
                           dataset=dataset, workers=2, progress=False)  # fmt: skip
    assert miss.summary["sequence_mismatch_rate"] == 1.0
    assert set(miss.columns["policy_sequence"]) == {""}
    again = validate_policy(files / "scene.toml", f"{files / 'pol.py'}:miss", 4,
                            dataset=dataset, dask=dask_client, progress=False)  # fmt: skip
    for k, v in miss.columns.items():
        assert same(v, again.columns[k]), k
    with pytest.raises(HybridocError, match="has 6 samples; 7 requested"):
        validate_policy(files / "scene.toml", f"{files / 'pol.py'}:good", M + 1, dataset=dataset)
    with pytest.raises(HybridocError, match="another scene or seed"):
        validate_policy(files / "scene.toml", f"{files / 'pol.py'}:good", 2, seed=1,
                        dataset=dataset)  # fmt: skip
    with pytest.raises(HybridocError, match="hold"):
        validate_policy(files / "scene.toml", f"{files / 'pol.py'}:good", 2, hold="foh")
    cont = validate_policy(files / "scene.toml", f"{files / 'pol.py'}:good", 1, hold="continuous",
                           dataset=dataset, workers=1, progress=False)  # fmt: skip
    assert cont.summary["compared"] == 1 and cont.summary["gap_max"] > 0


# ---------------------------------------------------------------------------- command line


def test_cli_validate_policy_json_and_figures(
    files: Path, dataset: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main([
        "validate-policy", str(files / "scene.toml"), f"{files / 'pol.py'}:miss", "--samples",
        "4", "--dataset", str(dataset.path), "--workers", "1", "--json", "--out", str(tmp_path),
        "--no-progress",
    ])  # fmt: skip
    out = capsys.readouterr().out
    payload = json.loads(out)
    assert code == 0
    assert payload["summary"]["sequence_mismatch_rate"] == 1.0
    for suffix in (".json", ".npz", "_gap_hist.png", "_gap_scatter.png"):
        assert (tmp_path / f"sc-dist_validate-policy{suffix}").stat().st_size > 0


def test_cli_dataset_and_bad_inputs(
    files: Path, dataset: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # an existing complete dataset of the same settings: answered without solving
    code = main(["dataset", str(files / "scene.toml"), "--samples", str(M), "--out",
                 str(dataset.path), "--json"])  # fmt: skip
    payload = json.loads(capsys.readouterr().out)
    assert code == 0 and payload["counts"] == {"success": M}
    assert payload["sha256"] == dataset.manifest["sha256"]
    bad = [
        (["dataset", str(files / "scene.toml"), "--samples", "0", "--out", str(tmp_path)],
         "integer >= 1"),
        (["dataset", "single-collision", "--samples", "2", "--out", str(tmp_path)],
         "no [distribution] table"),
        (["dataset", str(files / "scene.toml"), "--samples", "2", "--out", str(tmp_path),
          "--dask", "nonsense"], "bad Dask scheduler address"),
        (["validate-policy", str(files / "scene.toml"), "nope.pt", "--samples", "2"],
         "does not exist"),
        (["validate-policy", str(files / "scene.toml"), f"{files / 'pol.py'}:good",
          "--samples", "-1"], "integer >= 1"),
        (["evaluate", "single-collision", "--policy", "x.py"], "name the callable"),
        (["evaluate", "single-collision", "--hold", "continuous"], "--hold applies"),
    ]  # fmt: skip
    for argv, words in bad:
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse's usage errors
            code = exc.code
        err = capsys.readouterr().err
        assert code == 2, (argv, err)
        assert words in err and err.count("\n") == 1, (argv, err)
