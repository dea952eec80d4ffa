"""Policies on problems with control bounds: the MLP's output clipped to them (the policy
format's ``saturation``), and ``validate-policy``/``train-policy`` flagging any policy whose
closed loop breaks the bounds, path or terminal constraints (exit code 1), never reporting
its cost gap as a result.

The bounded shuttle (``|u| <= 1.2``, a bounce off a wall, terminal x(T) = 0, v(T) = -1.5)
on a coarse grid carries the clip's checks: a policy strong enough to push past the bound
is clipped to it exactly, compiled and per-step judge agree to 1e-9, and the clipped
policy's exact closed-loop gradient matches central differences. A bouncing ball with
``|u| <= 3`` and no terminal constraint shows validate-policy's verdicts against real
references: the clipped policy is compared (exit 0), the same weights unclipped are
infeasible (exit 1, the bounds named with the judge's largest violation).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import hybridoc
from hybridoc.cli import main
from hybridoc.workflows.datasets import draw_initial_states, load_dataset, make_dataset
from hybridoc.workflows.policies import PolicyError
from hybridoc.workflows.policy_format import MLP, load_mlp_policy, save_mlp_policy
from hybridoc.workflows.rollouts import CompiledRollouts, closed_loop_evaluations
from hybridoc.workflows.training import judged_loss, mlp_policy

A = 1.2  # the shuttle's force limit
STEPS = 40
PROBLEMS = """
import numpy as np
import hybridoc

def shuttle():
    p = hybridoc.as_ocp("bounded-shuttle")
    spread = lambda rng, M: p.x0 + rng.uniform(-0.02, 0.02, (M, p.nx))
    return p.replace(name="shuttle", steps=40, u_guess=np.full((40, 1), 0.6),
                     distribution=spread)

def ball():
    p = hybridoc.as_ocp("bouncing-ball")
    spread = lambda rng, M: p.x0 + rng.uniform(-0.05, 0.05, (M, p.nx))
    return p.replace(name="ball3", steps=30, u_min=np.array([-3.0]), u_max=np.array([3.0]),
                     distribution=spread)
"""


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("policy-bounds")
    (d / "problems.py").write_text(PROBLEMS)
    return d


@pytest.fixture(scope="module")
def shuttle(files: Path) -> hybridoc.HybridOCP:
    return hybridoc.as_ocp(f"{files / 'problems.py'}:shuttle")


def strong(
    problem: hybridoc.HybridOCP, saturate: bool, seed: int = 1, gain: float = 30.0
) -> torch.nn.Module:
    """mlp_policy with a last layer ``gain`` times larger: the raw output swings past the
    bounds over part of the horizon and stays inside them elsewhere (the shuttle's from 0.15
    to 2.1 by default, the ball's from -0.2 to 5 with seed 2, gain 40)."""
    pol = mlp_policy(problem, hidden=6, layers=1, seed=seed, saturate=saturate)
    with torch.no_grad():
        pol.net[-1].weight.mul_(gain)
    return pol


def test_the_clip_keeps_the_controls_in_bounds_and_compiled_matches_the_judge(
    shuttle: hybridoc.HybridOCP, tmp_path: Path
) -> None:
    sat, raw = strong(shuttle, True), strong(shuttle, False)
    assert raw.u_min is None and sat.u_min.tolist() == [-A] and sat.u_max.tolist() == [A]
    path = save_mlp_policy(sat, tmp_path / "sat.json")
    mlp = load_mlp_policy(path)
    assert mlp.saturated and json.loads(path.read_text())["saturation"] == {
        "kind": "clip", "lower": [-A], "upper": [A],
    }  # fmt: skip
    unclipped = load_mlp_policy(save_mlp_policy(raw, tmp_path / "raw.json"))
    assert not unclipped.saturated and "saturation" not in json.loads(
        (tmp_path / "raw.json").read_text()
    )
    X0 = draw_initial_states(shuttle, 3, 0)
    evs, certs = closed_loop_evaluations(
        shuttle, mlp, X0, compiled=CompiledRollouts(shuttle, mlp, batch=3, compile=False)
    )
    for x0, ev, cert in zip(X0, evs, certs, strict=True):
        assert cert.evaluation is not None, cert.reason  # certified: no fallback
        p = shuttle.replace(x0=x0)
        step = hybridoc.evaluate(p, policy=mlp)  # the per-step judge, the file's policy
        module = hybridoc.evaluate(p, policy=sat)  # ... and the torch module
        assert abs(ev.cost - step.cost) <= 1e-9 * abs(step.cost)
        np.testing.assert_allclose(ev.controls, step.controls, rtol=1e-9, atol=1e-12)
        assert module.cost == pytest.approx(step.cost, rel=1e-12)
        assert ev.bound_violation == 0.0 and step.bound_violation == 0.0
        u = step.controls[:, 0]
        assert np.max(np.abs(u)) == A  # the clip is active: it lands on the bound exactly
        assert np.sum(np.abs(u) < A) >= 5  # ... and not everywhere
        # the clip by hand: the unclipped network at the states the clipped loop visits
        idx = np.array([seg.interval for seg in step.segments])
        first = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
        S = np.array([step.segments[i].s0 for i in first])
        u_raw = unclipped(shuttle.time_grid()[:-1], S)[:, 0]
        assert np.max(np.abs(u_raw)) > A + 0.3
        out = np.abs(u_raw) >= A
        assert np.array_equal(u[out], A * np.sign(u_raw[out]))
        np.testing.assert_allclose(u[~out], u_raw[~out], rtol=1e-14)  # batched vs one by one
        # the same weights unclipped break the bound in their own closed loop
        assert hybridoc.evaluate(p, policy=unclipped).bound_violation > 0.3


def test_the_clipped_policys_gradient_against_central_differences(
    shuttle: hybridoc.HybridOCP,
) -> None:
    """train_policy's exact adjoint through the clip (zero where a control is clipped)
    against central differences of the judge's cost, with a bounce in the loop."""
    pol = strong(shuttle, True)
    x0 = draw_initial_states(shuttle, 2, 5)
    loss = judged_loss(shuttle, pol, x0)
    loss.backward()
    evs = [hybridoc.evaluate(shuttle.replace(x0=x), policy=pol) for x in x0]
    assert all(ev.sequence == ["wall"] for ev in evs)
    clipped = np.concatenate([np.abs(ev.controls[:, 0]) == A for ev in evs])
    assert 0 < clipped.sum() < clipped.size  # some clipped, some not
    params = list(pol.parameters())
    rng = np.random.default_rng(2)
    d = [torch.as_tensor(rng.standard_normal(p.shape)) for p in params]
    exact = sum(float((p.grad * di).sum()) for p, di in zip(params, d, strict=True))

    def judge(eps: float) -> float:
        with torch.no_grad():
            for p, di in zip(params, d, strict=True):
                p.add_(eps * di)
        cost = np.mean([hybridoc.evaluate(shuttle.replace(x0=x), policy=pol).cost for x in x0])
        with torch.no_grad():
            for p, di in zip(params, d, strict=True):
                p.sub_(eps * di)
        return float(cost)

    eps = 1e-6
    fd = (judge(eps) - judge(-eps)) / (2 * eps)
    print(f"directional derivative: adjoint {exact:.12g}, central differences {fd:.12g}")
    assert abs(exact) > 1e-2
    assert fd == pytest.approx(exact, rel=1e-6)


@pytest.fixture(scope="module")
def ball_refs(files: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[str, Path]:
    """The exact references of the first draw of the bounded ball (seed 0)."""
    spec = f"{files / 'problems.py'}:ball"
    out = tmp_path_factory.mktemp("ball-refs") / "refs"
    make_dataset(spec, 1, out, workers=1, progress=False)
    return spec, out


def _validate(
    spec: str, policy: Path, refs: Path, capsys: pytest.CaptureFixture[str]
) -> tuple[int, dict[str, Any], str]:
    code = main(["validate-policy", spec, "--policy", str(policy), "--samples", "1",
                 "--dataset", str(refs), "--workers", "1", "--no-progress", "--json"])  # fmt: skip
    cap = capsys.readouterr()
    return code, json.loads(cap.out), cap.err


def test_validate_policy_flags_an_unclipped_policy_that_leaves_the_bounds(
    ball_refs: tuple[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec, refs = ball_refs
    problem = hybridoc.as_ocp(spec)
    x0 = draw_initial_states(problem, 1, 0)[0]
    sat, raw = strong(problem, True, 2, 40.0), strong(problem, False, 2, 40.0)
    sat_path = save_mlp_policy(sat, tmp_path / "sat.json")
    raw_path = save_mlp_policy(raw, tmp_path / "raw.json")
    # the judge's own verdicts, independent of validate-policy
    ev_sat = hybridoc.evaluate(problem.replace(x0=x0), policy=load_mlp_policy(sat_path))
    ev_raw = hybridoc.evaluate(problem.replace(x0=x0), policy=load_mlp_policy(raw_path))
    assert ev_sat.feasible and ev_raw.bound_violation > 1.0

    code, report, err = _validate(spec, sat_path, refs, capsys)
    s = report["summary"]
    assert code == 0, err
    # issue #29: the draw's reference may be best-found (verified, not proven optimal); it is
    # a baseline all the same, and the summary says which kind it is
    ref_status = str(load_dataset(refs).columns["status"][0])
    assert ref_status in ("success", "best-found")
    assert s["reference_best_found"] == int(ref_status == "best-found")
    assert s["reference_proven"] == int(ref_status == "success")
    assert report["worst"][0]["reference_status"] == ref_status
    assert s["infeasible"] == 0 and s["compared"] == 1
    assert s["violations"]["bound"] == {"draws": 0, "max": 0.0}
    assert s["gap_mean"] == pytest.approx(ev_sat.cost - report["worst"][0]["reference_cost"])
    assert s["gap_mean"] > 0

    code, report, err = _validate(spec, raw_path, refs, capsys)
    s = report["summary"]
    assert code == 1
    assert s["infeasible"] == 1 and s["compared"] == 0 and s["gap_mean"] is None
    assert report["worst"] == []  # no gap listed as a result
    assert s["violations"]["bound"]["draws"] == 1
    assert s["violations"]["bound"]["max"] == pytest.approx(ev_raw.bound_violation, rel=1e-9)
    assert s["violations"]["path"]["draws"] == s["violations"]["terminal"]["draws"] == 0
    line = f"control bounds on 1 draw(s) (by up to {ev_raw.bound_violation:.3g})"
    assert "INFEASIBLE on 1 of 1 judged draw(s)" in err and line in err, err
    # the text report says so before its gap table
    main(["validate-policy", spec, "--policy", str(raw_path), "--samples", "1",
          "--dataset", str(refs), "--workers", "1", "--no-progress"])  # fmt: skip
    out = capsys.readouterr().out
    assert f"INFEASIBLE on 1 draw(s): {line}" in out
    assert "NOT the policy's gap" in out


def test_policy_report_columns_name_the_violations(
    ball_refs: tuple[str, Path], tmp_path: Path
) -> None:
    from hybridoc.workflows.policies import validate_policy

    spec, refs = ball_refs
    problem = hybridoc.as_ocp(spec)
    raw = load_mlp_policy(save_mlp_policy(strong(problem, False, 2, 40.0), tmp_path / "r.json"))
    for rollouts in ("compiled", "judge"):
        rep = validate_policy(spec, raw, 1, dataset=refs, workers=1, progress=False,
                              rollouts=rollouts)  # fmt: skip
        c = rep.columns
        assert not rep.feasible and c["status"].tolist() == ["infeasible"]
        assert np.isnan(c["gap"][0]) and np.isfinite(c["policy_cost"][0])
        assert c["bound_violation"][0] > 1.0 and not c["feasible"][0]
        assert c["message"][0].startswith("the policy's controls violate the control bounds by")


def test_old_policy_files_load_unchanged_and_saturation_is_checked(tmp_path: Path) -> None:
    """A version-1 file written before the saturation entry existed loads as before (no
    clip); a one-sided bound round-trips with null for the open side; malformed entries
    are PolicyErrors naming the entry."""
    rng = np.random.default_rng(0)
    W0, b0, W1, b1 = rng.normal(size=(4, 3)), rng.normal(size=4), rng.normal(size=(1, 4)), [0.5]
    arrays = {"layer0.weight": W0, "layer0.bias": b0, "layer1.weight": W1, "layer1.bias": b1}
    np.savez(tmp_path / "old.npz", **arrays)
    old = {
        "format": "hybridoc-mlp-policy", "version": 1, "weights": "old.npz",
        "input": "t,state", "horizon": 2.0, "layers": [3, 4, 1], "activation": "tanh",
    }  # fmt: skip
    (tmp_path / "old.json").write_text(json.dumps(old))
    mlp = load_mlp_policy(tmp_path / "old.json")
    assert not mlp.saturated and mlp.output_min is None
    t, s = 0.5, np.array([3.0, -2.0])
    z = np.r_[2 * t / 2.0 - 1, s]
    np.testing.assert_allclose(mlp(t, s), W1 @ np.tanh(W0 @ z + b0) + b1, rtol=1e-14)
    assert "saturation" not in mlp.description()

    one_sided = MLP(mlp.weights, mlp.biases, horizon=2.0, output_max=[0.25])
    path = save_mlp_policy(one_sided, tmp_path / "one.json")
    entry = json.loads(path.read_text())["saturation"]
    assert entry == {"kind": "clip", "lower": [None], "upper": [0.25]}
    back = load_mlp_policy(path)
    assert back.output_min.tolist() == [-np.inf] and back.output_max.tolist() == [0.25]
    S = rng.normal(scale=3.0, size=(50, 2))
    np.testing.assert_array_equal(back(t, S), np.minimum(mlp(t, S), 0.25))
    assert back.to_torch().u_max.tolist() == [0.25]  # and back into a trainable module

    for bad, message in [
        ({"kind": "tanh", "lower": [0.0], "upper": [1.0]}, "kind 'tanh' is not one of clip"),
        ({"kind": "clip", "lower": [0.0, 1.0], "upper": [1.0]}, "must list 1 bounds"),
        ({"kind": "clip", "lower": ["0"], "upper": [1.0]}, "holds '0', not a number"),
        ({"kind": "clip", "lower": [2.0], "upper": [1.0]}, "exceeds output_max"),
        ({"lower": [0.0], "upper": [1.0]}, "'saturation' must be"),
    ]:
        (tmp_path / "bad.json").write_text(json.dumps({**old, "saturation": bad}))
        with pytest.raises(PolicyError, match=message):
            load_mlp_policy(tmp_path / "bad.json")


def test_train_policy_clips_and_reports_a_terminal_violation(
    files: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The shuttle's terminal constraint is not in the training loss: the trained policy
    stays in the bounds (its file clips) but misses x(T) = 0, v(T) = -1.5, which the
    command reports, with exit code 1."""
    spec = f"{files / 'problems.py'}:shuttle"
    code = main(["train-policy", spec, "--samples", "2", "--iters", "2", "--hidden", "4",
                 "--layers", "1", "--out", str(tmp_path), "--json", "--no-progress"])  # fmt: skip
    cap = capsys.readouterr()
    payload = json.loads(cap.out)
    assert code == 1
    assert payload["saturated"] and payload["infeasible"] == 2
    assert payload["violations"]["bound"] == {"draws": 0, "max": 0.0}
    assert payload["violations"]["terminal"]["draws"] == 2
    policy = load_mlp_policy(payload["policy"])
    assert policy.saturated and policy.output_max.tolist() == [A]
    problem = hybridoc.as_ocp(spec)
    x0 = draw_initial_states(problem, 2, payload["seed"])
    worst = max(hybridoc.evaluate(problem.replace(x0=x), policy=policy).terminal_violation
                for x in x0)  # fmt: skip
    assert payload["violations"]["terminal"]["max"] == pytest.approx(worst, rel=1e-9)
    assert "INFEASIBLE on 2 of 2 training draw(s)" in cap.err
    assert "terminal constraints on 2 draw(s)" in cap.err


def test_cli_validate_flags_controls_out_of_bounds(
    shuttle: hybridoc.HybridOCP, files: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``hybridoc validate`` of a control file that pushes past the force limit: the judge's
    violation in the report, an INFEASIBLE line, exit code 1 (not a cost gap as a result)."""
    u = np.full((STEPS, 1), 0.6)
    u[5:9] = 1.5  # 0.3 past the bound
    np.save(tmp_path / "u.npy", u)
    ev = hybridoc.evaluate(shuttle, u)
    code = main(["validate", f"{files / 'problems.py'}:shuttle", "--controls",
                 str(tmp_path / "u.npy"), "--json"])  # fmt: skip
    cap = capsys.readouterr()
    report = json.loads(cap.out)
    assert code == 1
    assert not report["feasible"]
    assert report["bound_violation"] == pytest.approx(0.3, rel=1e-12)
    assert report["terminal_violation"] == pytest.approx(ev.terminal_violation, rel=1e-12)
    assert "INFEASIBLE" in cap.err and "control bounds by 0.3" in cap.err


def test_a_best_found_reference_is_a_baseline_and_the_report_says_it_is_not_proven() -> None:
    """Issue #29: a draw whose reference is best-found (a verified extremal, not proven
    optimal) is compared with the policy; not-optimal and failed references are not. The
    columns and the summary say which references are proven, and a policy that beats a
    best-found reference is counted apart from one that beats a proven optimum."""
    from hybridoc.workflows.policies import _report

    statuses = ["success", "best-found", "best-found", "not-optimal", "failed"]
    M = len(statuses)
    ref = {
        "index": np.arange(M), "x0": np.zeros((M, 2)), "targets": np.zeros((M, 0, 2)),
        "status": np.array(statuses), "cost": np.array([1.0, 2.0, 3.0, 4.0, np.nan]),
        "sequence": np.array(["g"] * M), "message": np.array(["", "", "", "cheaper", "x"]),
    }  # fmt: skip
    zero = np.zeros(M)
    roll = {
        "rollout_status": np.array(["ok"] * M), "feasible": np.ones(M, bool),
        "policy_cost": np.array([1.5, 2.5, 2.7, 5.0, 6.0]), "policy_sequence": ref["sequence"],
        "bound_violation": zero, "path_violation": zero, "terminal_violation": zero,
        "rollout_message": np.array([""] * M), "rollout_path": np.array(["judge"] * M),
        "fallback_reason": np.array([""] * M),
    }  # fmt: skip
    rep = _report(ref, roll, 0.0)
    c, s = rep.columns, rep.summary
    assert c["status"].tolist() == ["ok", "ok", "ok", "reference-failed", "reference-failed"]
    assert c["reference_status"].tolist() == statuses
    assert c["reference_proven"].tolist() == [True, False, False, False, False]
    np.testing.assert_allclose(c["gap"][:3], [0.5, 0.5, -0.3], rtol=1e-12)
    assert np.isnan(c["gap"][3:]).all()
    assert (s["compared"], s["reference_proven"], s["reference_best_found"]) == (3, 1, 2)
    assert s["reference_failed"] == 2
    assert (s["negative_gaps"], s["negative_gaps_proven"]) == (1, 0)


def test_a_best_found_nominal_warm_starts_and_its_warm_draws_are_not_proven(
    ball_refs: tuple[str, Path],
) -> None:
    """Issue #29: the bounded ball's nominal reference is best-found (no sequence length
    covered). It is a verified extremal, so the dataset keeps it as the draws' warm start
    (before, only a success nominal was kept and every draw got the full discovery), and a
    warm draw is no more proven than its nominal."""
    from hybridoc.workflows.datasets import draw_context, problem_spec

    spec, refs = ball_refs
    ds = load_dataset(refs)
    nominal = ds.manifest["nominal"]
    assert nominal is not None and nominal["status"] in ("success", "best-found")
    assert set(ds.columns["status"].tolist()) <= {"success", "best-found"}
    warm = ds.columns["method"] == "warm"
    assert set(ds.columns["status"][warm].tolist()) <= {nominal["status"]}
    ocp = hybridoc.as_ocp(spec)
    task = {**problem_spec(ocp, spec, ds.columns["x0"]), "seed": 0, "tol": 1e-10,
            "full": False, "nominal": nominal}  # fmt: skip
    ctx = draw_context(task)
    assert ctx.sequence == nominal["sequence"] and ctx.warm_status == nominal["status"]
    for status, warm_status in (("success", "success"), ("best-found", "best-found")):
        other = draw_context({**task, "nominal": {**nominal, "status": status}})
        assert other.warm_status == warm_status
