"""Compiled closed-loop rollouts against the per-step judge, and the MLP policy format.

The compiled rollouts (hybridoc.workflows.rollouts) write the closed loop as one CasADi graph
and certify each rollout with the judge; here they are held to the per-step judge
(``hybridoc.evaluate(..., policy=...)``, a Python loop calling the policy at every grid
time) to 1e-9 on draws of single-collision and multiple-collision under random MLPs. The
policy format is held to the torch module it was exported from, and its loader to refusing
every malformed or hostile file without running anything. Code generation is off in the
tests (conftest): the compiled function runs in CasADi's virtual machine, the same graph.
"""

from __future__ import annotations

import hashlib
import io
import json
import pickle
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
import pytest
from small_scenes import strike_scene

import hybridoc
from hybridoc.problem import as_ocp
from hybridoc.workflows.policies import PolicyError, load_policy, validate_policy
from hybridoc.workflows.policy_format import (
    MLP,
    CasadiPolicy,
    load_mlp_policy,
    save_mlp_policy,
)
from hybridoc.workflows.rollouts import CompiledRollouts, closed_loop_evaluations

RTOL = 1e-9


def random_mlp(ocp: Any, seed: int, activation: str = "tanh", hidden: int = 12) -> MLP:
    """A random two-hidden-layer MLP around the problem's initial guess, strong enough to
    change the event sequences from draw to draw."""
    rng = np.random.default_rng(seed)
    sizes = [ocp.nx + 1, hidden, hidden, ocp.nu]
    Ws = tuple(
        rng.normal(size=(b, a)) / np.sqrt(a) for a, b in zip(sizes[:-1], sizes[1:], strict=True)
    )
    bs = tuple(0.1 * rng.normal(size=b) for b in sizes[1:])
    return MLP(
        Ws, bs, activation=activation, horizon=ocp.horizon, state_mean=ocp.x0,
        state_scale=np.ones(ocp.nx), output_offset=ocp.u_guess.mean(0),
        output_scale=np.full(ocp.nu, 1.5),
    )  # fmt: skip


def draws(ocp: Any, seed: int, n: int, width: float = 0.3) -> np.ndarray:
    """Initial states with the passive disc (ball2) moved within +-width."""
    rng = np.random.default_rng(seed)
    X = np.tile(ocp.x0, (n, 1))
    X[:, 2:4] += rng.uniform(-width, width, size=(n, 2))
    return X


def per_step(ocp: Any, x0: np.ndarray, policy: Any) -> Any:
    return hybridoc.evaluate(ocp.replace(x0=x0), policy=policy)


@pytest.mark.parametrize(
    ("problem", "seed", "activation"),
    [("single-collision", 0, "tanh"), ("single-collision", 1, "relu"),
     ("multiple-collision", 2, "tanh"), ("multiple-collision", 3, "sigmoid")],
)  # fmt: skip
def test_compiled_matches_per_step_judge(problem: str, seed: int, activation: str) -> None:
    ocp = as_ocp(problem)
    mlp = random_mlp(ocp, seed, activation)
    X0 = draws(ocp, seed, 3)
    runner = CompiledRollouts(ocp, mlp, batch=3, compile=False)
    evs, certs = closed_loop_evaluations(ocp, mlp, X0, compiled=runner)
    for x0, ev, cert in zip(X0, evs, certs, strict=True):
        ref = per_step(ocp, x0, mlp)
        assert cert.evaluation is not None, cert.reason  # certified, not a fallback
        assert abs(cert.compiled_cost - ref.cost) <= RTOL * abs(ref.cost)
        assert abs(ev.cost - ref.cost) <= RTOL * abs(ref.cost)
        assert ev.sequence == ref.sequence
        assert np.allclose(ev.controls, ref.controls, rtol=RTOL, atol=RTOL)
    # the draws collide (several times on multiple-collision)
    assert max(len(ev.sequence) for ev in evs) >= (2 if problem == "multiple-collision" else 1)


def test_casadi_policy_compiled_matches_per_step_judge() -> None:
    ocp = as_ocp("single-collision")
    t, s = ca.SX.sym("t"), ca.SX.sym("s", ocp.nx)
    # a feedback towards ball2 with a time-varying gain
    u = ca.vertcat(2.0 * (s[2] - s[0]) + 1.0, (2.0 + t) * (s[3] - s[1]) + 2.0)
    pol = load_policy(ca.Function("pd", [t, s], [u]))
    assert isinstance(pol, CasadiPolicy)
    X0 = draws(ocp, 5, 2)
    evs, certs = closed_loop_evaluations(
        ocp, pol, X0, compiled=CompiledRollouts(ocp, pol, batch=2, compile=False)
    )
    for x0, ev, cert in zip(X0, evs, certs, strict=True):
        ref = per_step(ocp, x0, pol)
        assert cert.evaluation is not None, cert.reason
        assert abs(ev.cost - ref.cost) <= RTOL * abs(ref.cost)
        assert abs(cert.compiled_cost - ref.cost) <= RTOL * abs(ref.cost)


def test_uncertified_rollouts_fall_back_to_the_judge(monkeypatch: pytest.MonkeyPatch) -> None:
    ocp = as_ocp("single-collision")
    mlp = random_mlp(ocp, 7)
    X0 = draws(ocp, 7, 3)
    runner = CompiledRollouts(ocp, mlp, batch=3, compile=False)
    run = runner.run

    def tampered(x0: Any) -> dict[str, np.ndarray]:
        out = run(x0)
        out["states"][0, 200:300] += 1e-6  # rollout 0: wrong states in cells 200 to 299
        out["untrusted"][1] = True  # rollout 1: a cell the step did not resolve
        out["running"][2] *= 1 + 1e-7  # rollout 2: a wrong cost
        return out

    monkeypatch.setattr(runner, "run", tampered)
    evs, certs = closed_loop_evaluations(ocp, mlp, X0, compiled=runner)
    assert [c.kind for c in certs] == ["grid states", "unresolved", "cost"]
    assert all(c.evaluation is None and c.reason for c in certs)
    for x0, ev in zip(X0, evs, strict=True):  # the per-step judge's numbers, bit for bit
        assert ev.cost == per_step(ocp, x0, mlp).cost


def test_unresolved_cells_are_flagged() -> None:
    ocp = as_ocp("multiple-collision")
    mlp = random_mlp(ocp, 2)
    X0 = draws(ocp, 2, 3)
    full = CompiledRollouts(ocp, mlp, batch=3, compile=False).run(X0)
    assert not full["untrusted"].any()
    # ball2 starting inside the wall: its guard is penetrated at the end of the first cell,
    # which the compiled step flags (the judge raises there: sustained contact)
    bad = X0.copy()
    bad[:, 3] = 0.95  # ball2's centre 0.05 below the wall y = 1, radius 0.2
    raw = CompiledRollouts(ocp, mlp, batch=3, compile=False).run(bad)
    assert raw["untrusted"].all()


def test_two_events_in_one_cell_sharing_a_disc() -> None:
    # three-disc-chain with the end disc 5e-5 from the middle one: the striker hits the
    # middle disc, which hits the end disc within the same cell. The compiled step resolves
    # both in order with max_events >= 2; with one event per cell it flags the cell, and the
    # per-step judge runs instead
    ocp = as_ocp("three-disc-chain")
    x0 = ocp.x0.copy()
    x0[4:6] = x0[2:4] + [0.40005, 0.01]  # end = middle + (sum of radii + 5e-5, 0.01)
    ocp = ocp.replace(x0=x0)
    t, s = ca.SX.sym("t"), ca.SX.sym("s", ocp.nx)
    pol = CasadiPolicy(ca.Function("push", [t, s], [ca.vertcat(3.0 - 0.5 * s[6], 0.0)]))
    ref = per_step(ocp, x0, pol)
    assert [e.name for e in ref.events[:2]] == ["striker|middle", "middle|end"]
    assert int(ref.events[0].time / ocp.dt) == int(ref.events[1].time / ocp.dt)
    evs, certs = closed_loop_evaluations(
        ocp, pol, x0[None], compiled=CompiledRollouts(ocp, pol, batch=1, compile=False)
    )
    assert certs[0].evaluation is not None, certs[0].reason
    assert abs(certs[0].compiled_cost - ref.cost) <= RTOL * ref.cost
    assert evs[0].sequence == ref.sequence
    one = CompiledRollouts(ocp, pol, max_events=1, batch=1, compile=False)
    evs, certs = closed_loop_evaluations(ocp, pol, x0[None], compiled=one)
    assert certs[0].evaluation is None and certs[0].kind == "unresolved"
    assert evs[0].cost == ref.cost


def test_unsupported_policies_and_problems() -> None:
    ocp = as_ocp("single-collision")
    with pytest.raises(PolicyError, match="only an MLP policy file"):
        CompiledRollouts(ocp, lambda t, s: np.zeros(2))
    small = MLP((np.zeros((2, 5)),), (np.zeros(2),))  # 4 states: not this problem's 8
    with pytest.raises(PolicyError, match="maps 4 states to 2 controls"):
        CompiledRollouts(ocp, small)


# ---------------------------------------------------------------------------- the format


def test_round_trip_from_torch_mlp_policy(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    from hybridoc.workflows.training import mlp_policy

    module = mlp_policy("single-collision", hidden=16, layers=2, seed=3)
    with torch.no_grad():  # weights of order one, so that the comparison is not trivial
        for p in module.parameters():
            p.add_(0.3 * torch.randn(p.shape, dtype=torch.float64))
    path = save_mlp_policy(module, tmp_path / "pol")
    assert path == tmp_path / "pol.json" and (tmp_path / "pol.npz").is_file()
    spec = json.loads(path.read_text())
    assert spec["layers"] == [9, 16, 16, 2] and spec["activation"] == "tanh"
    pol = load_policy(str(path))
    assert isinstance(pol, MLP) and (pol.nx, pol.nu) == (8, 2)
    rng = np.random.default_rng(0)
    S = rng.normal(size=(20, 8))
    t = rng.uniform(0, 1, size=20)
    with torch.no_grad():
        want = module(torch.as_tensor(t), torch.as_tensor(S)).numpy()
    assert np.allclose(pol(t, S), want, rtol=1e-13, atol=1e-13)
    one = module(torch.tensor(t[0]), torch.as_tensor(S[0])).detach().numpy()
    assert np.allclose(pol(t[0], S[0]), one, rtol=1e-13, atol=1e-13)
    # the CasADi forms (weights constant, and weights an input) give the same numbers
    f, fp = pol.casadi(), pol.casadi(symbolic=True)
    for k in range(3):
        assert np.allclose(np.asarray(f(t[k], S[k])).ravel(), want[k], rtol=1e-13, atol=1e-13)
        got = np.asarray(fp(t[k], S[k], pol.parameters())).ravel()
        assert np.allclose(got, want[k], rtol=1e-13, atol=1e-13)
    # saving the loaded policy again writes the same arrays
    again = load_mlp_policy(save_mlp_policy(pol, tmp_path / "again.json"))
    assert np.array_equal(again.parameters(), pol.parameters())
    # and back to a trainable module with the same numbers
    back = pol.to_torch()
    with torch.no_grad():
        got = back(torch.as_tensor(t), torch.as_tensor(S)).numpy()
    assert np.array_equal(got, want)
    with pytest.raises(PolicyError, match="tanh hidden layers of one width"):
        MLP(pol.weights, pol.biases, activation="relu", horizon=1.0).to_torch()


def test_round_trip_from_sequential(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    net = torch.nn.Sequential(
        torch.nn.Linear(8, 6, dtype=torch.float64), torch.nn.ReLU(),
        torch.nn.Linear(6, 2, dtype=torch.float64),
    )  # fmt: skip
    mean = np.arange(8.0)
    path = save_mlp_policy(net, tmp_path / "seq.json", state_mean=mean, output_offset=[1.0, 2.0])
    pol = load_policy(path)
    S = np.random.default_rng(1).normal(size=(5, 8))
    with torch.no_grad():
        want = net(torch.as_tensor(S - mean)).numpy() + [1.0, 2.0]
    assert pol.input == "state" and pol.activation == "relu"
    assert np.allclose(pol(0.0, S), want, rtol=1e-13, atol=1e-13)
    with pytest.raises(PolicyError, match="layer Conv1d has no form"):
        save_mlp_policy(torch.nn.Sequential(torch.nn.Conv1d(1, 1, 1)), tmp_path / "x.json")
    mixed = torch.nn.Sequential(
        torch.nn.Linear(8, 4), torch.nn.Tanh(), torch.nn.Linear(4, 4), torch.nn.ReLU(),
        torch.nn.Linear(4, 2),
    )  # fmt: skip
    with pytest.raises(PolicyError, match="one activation for all layers"):
        save_mlp_policy(mixed, tmp_path / "x.json")


@pytest.fixture
def saved(tmp_path: Path) -> Path:
    mlp = random_mlp(as_ocp("single-collision"), 0)
    return save_mlp_policy(mlp, tmp_path / "pol.json")


def _rewrite(path: Path, **changes: Any) -> None:
    spec = json.loads(path.read_text())
    for k, v in changes.items():
        if v is None:
            spec.pop(k, None)
        else:
            spec[k] = v
    path.write_text(json.dumps(spec))


def _npz(path: Path, arrays: dict[str, Any], allow_pickle: bool = False) -> None:
    buf = io.BytesIO()
    np.savez(buf, **arrays, allow_pickle=allow_pickle) if allow_pickle else np.savez(buf, **arrays)
    path.write_bytes(buf.getvalue())


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"format": "something-else"}, "is not a policy file"),
        ({"version": 2}, "version 2 is not supported"),
        ({"layerz": [1]}, "unknown entries 'layerz'"),
        ({"layers": [9, 12, 12, 2, 2]}, "lacks layer3.weight or layer3.bias"),
        ({"layers": [9, 12, 12]}, "holds arrays 'layer2.bias', 'layer2.weight'"),
        ({"layers": [9, 12, 13, 2]}, "layer 1 has weight (12, 12)"),
        ({"layers": "9,12,12,2"}, "'layers' must list at least two positive integer"),
        ({"activation": "swish"}, "activation must be one of"),
        ({"input": "state"}, "state_mean must have 9 entries"),
        ({"horizon": -1.0}, "horizon must be a positive number"),
        ({"weights": "../pol.npz"}, "must be a file name in its folder"),
        ({"weights": "missing.npz"}, "which does not exist"),
        ({"sha256": "0" * 64}, "does not match the SHA-256"),
    ],
)
def test_bad_description_is_a_policy_error(saved: Path, change: dict, message: str) -> None:
    _rewrite(saved, **change)
    with pytest.raises(PolicyError, match=__import__("re").escape(message)):
        load_policy(str(saved))


def test_bad_files_are_policy_errors(saved: Path, tmp_path: Path) -> None:
    npz = saved.with_suffix(".npz")
    saved_text = saved.read_text()
    cases: list[tuple[str, str]] = []
    (tmp_path / "junk.json").write_text("{not json")
    cases.append((str(tmp_path / "junk.json"), "is not valid JSON"))
    cases.append((str(tmp_path / "none.json"), "does not exist"))
    # weights that are not an .npz, with no recorded hash
    _rewrite(saved, sha256=None)
    npz.write_bytes(b"print('hello')\n")
    cases.append((str(saved), "cannot read"))
    for spec, message in cases:
        with pytest.raises(PolicyError, match=message):
            load_policy(spec)
    # an extra array, a non-finite weight, a text array
    saved.write_text(saved_text)
    good = dict(np.load(io.BytesIO(_saved_bytes(tmp_path)), allow_pickle=False))
    for arrays, message in [
        ({**good, "extra": np.zeros(3)}, "holds arrays 'extra'"),
        ({**good, "layer0.weight": np.full((12, 9), np.nan)}, "non-finite"),
        ({**good, "layer0.bias": np.array(["a"] * 12)}, "must hold real numbers"),
    ]:
        _npz(npz, arrays)
        _rewrite(saved, sha256=None)
        with pytest.raises(PolicyError, match=message):
            load_policy(str(saved))


def _saved_bytes(tmp_path: Path) -> bytes:
    path = save_mlp_policy(random_mlp(as_ocp("single-collision"), 0), tmp_path / "fresh.json")
    return path.with_suffix(".npz").read_bytes()


class _Marker:
    """Unpickling this object would create a file: it must never happen."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, ...]:
        return (Path.touch, (Path(self.path),))


def test_a_policy_file_never_runs_code(saved: Path, tmp_path: Path) -> None:
    marker = tmp_path / "ran"
    npz = saved.with_suffix(".npz")
    good = dict(np.load(npz, allow_pickle=False))
    evil = np.empty(1, dtype=object)
    evil[0] = _Marker(str(marker))
    _npz(npz, {**good, "layer0.bias": evil}, allow_pickle=True)
    with pytest.raises(PolicyError):  # the hash recorded at saving no longer matches
        load_policy(str(saved))
    _rewrite(saved, sha256=hashlib.sha256(npz.read_bytes()).hexdigest())
    with pytest.raises(PolicyError, match="cannot read"):  # object arrays are refused
        load_policy(str(saved))
    # a bare pickle named as the weights
    raw = tmp_path / "raw.npz"
    raw.write_bytes(pickle.dumps(_Marker(str(marker))))
    _rewrite(saved, weights="raw.npz", sha256=None)
    with pytest.raises(PolicyError, match="cannot read"):
        load_policy(str(saved))
    assert not marker.exists()


# ---------------------------------------------------------------------------- validate_policy

SCENE = strike_scene("sc-dist")  # test_datasets' scene


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Any]:
    """A scene with a distribution, an MLP policy file, and a dataset without references
    (its rows say so): the rollouts do not depend on them, and solving them would take
    seconds."""
    from hybridoc.problems import load_scene
    from hybridoc.workflows.datasets import Dataset

    d = tmp_path_factory.mktemp("roll")
    (d / "scene.toml").write_text(SCENE)
    scene = load_scene(d / "scene.toml")
    ocp = scene.to_ocp()
    mlp = random_mlp(ocp, 11)
    save_mlp_policy(mlp, d / "pol.json")
    n = 3
    draws = [scene.distribution.draw(scene, i, 7) for i in range(n)]
    x0 = np.array([s.initial_state() for s in draws])
    targets = np.array([s.targets() for s in draws], dtype=float)
    cols = {
        "index": np.arange(n), "x0": x0, "targets": targets,
        "status": np.array(["failed"] * n), "cost": np.full(n, np.nan),
        "message": np.array(["not solved in this test"] * n), "sequence": np.array([""] * n),
    }  # fmt: skip
    # a manifest as make_dataset writes it before any draw is solved (validate_policy checks
    # an in-memory dataset as it checks a file: issue #32)
    from hybridoc.workflows.datasets import FORMAT, _settings

    settings = _settings(scene, n, 7, 1e-10, False)
    manifest = {"format": FORMAT, "complete": False, "settings": settings, "nominal": None}
    return d, Dataset(d, cols, manifest)


def test_validate_policy_compiled_equals_judge(small: tuple[Path, Any]) -> None:
    d, refs = small
    kw: dict[str, Any] = {"dataset": refs, "workers": 1, "progress": False}
    pol = str(d / "pol.json")
    comp = validate_policy(d / "scene.toml", pol, 3, rollouts="compiled", **kw)
    judge = validate_policy(d / "scene.toml", pol, 3, rollouts="judge", **kw)
    auto = validate_policy(d / "scene.toml", pol, 3, **kw)
    assert comp.summary["rollouts"]["compiled"] == 3 and comp.summary["rollouts"]["fallback"] == 0
    assert list(comp.columns["rollout_path"]) == ["compiled"] * 3
    assert judge.summary["rollouts"]["judge"] == 3
    assert auto.summary["rollouts"]["mode"] == "compiled"
    a, b = comp.columns["policy_cost"], judge.columns["policy_cost"]
    assert np.all(np.isfinite(b)) and np.all(np.abs(a - b) <= RTOL * np.abs(b))
    assert list(comp.columns["policy_sequence"]) == list(judge.columns["policy_sequence"])
    with pytest.raises(PolicyError, match="hold the control over each grid interval"):
        validate_policy(d / "scene.toml", pol, 1, rollouts="compiled", hold="continuous", **kw)
    python = validate_policy(d / "scene.toml", lambda t, s: mlp_of(d)(t, s), 1, **kw)
    assert python.summary["rollouts"] == {
        "mode": "judge", "compiled": 0, "fallback": 0, "judge": 1, "fallback_kinds": {},
        "compiled_max_rel_diff": None,
    }  # fmt: skip
    with pytest.raises(PolicyError, match="only an MLP policy file"):
        validate_policy(d / "scene.toml", lambda t, s: mlp_of(d)(t, s), 1, rollouts="compiled",
                        **kw)  # fmt: skip


def mlp_of(d: Path) -> MLP:
    return load_mlp_policy(d / "pol.json")


def test_cli_validate_policy_rollouts(
    small: tuple[Path, Any], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from hybridoc.cli import main
    from hybridoc.workflows import policies

    d, refs = small
    real = policies.validate_policy
    # the in-memory dataset of the fixture in place of references the command would solve
    monkeypatch.setattr(
        policies, "validate_policy", lambda *a, **k: real(*a, **{**k, "dataset": refs})
    )
    args = ["validate-policy", str(d / "scene.toml"), str(d / "pol.json"), "--samples", "2",
            "--workers", "1", "--no-progress", "--rollouts", "compiled"]  # fmt: skip
    assert main([*args, "--json"]) == 1  # 1: no draw has a reference to compare with
    out = json.loads(capsys.readouterr().out)
    assert out["summary"]["rollouts"]["compiled"] == 2
    assert out["settings"]["rollouts"] == "compiled"
    main(args)
    assert "rollouts" in (text := capsys.readouterr().out) and "compiled 2" in text
    assert main([*args, "--hold", "continuous"]) == 2
    assert "no compiled rollout" in capsys.readouterr().err
