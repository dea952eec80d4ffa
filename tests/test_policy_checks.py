"""Policies checked against their problem, and JSON from a user bounded (issue #32).

Accepted before with exit 0: an MLP policy for 4 states validated on an 8-state scene (the
network read the 8 states as two rows of 4 and used the first). A policy JSON nested
200 000 deep gave a RecursionError (an internal error). Now a policy's input and output
sizes are checked against the problem before any rollout, and every JSON hybridoc reads
from a user is bounded in size and nesting; each is one clear error (exit 2).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_here import run_here
from conftest import examples
from hypothesis import given, settings
from hypothesis import strategies as st
from small_scenes import strike_scene

from hybridoc.errors import HybridocError
from hybridoc.outputs import MAX_JSON_DEPTH, parse_json
from hybridoc.solution import Solution
from hybridoc.workflows.policy_format import (
    MLP,
    PolicyError,
    check_policy_sizes,
    load_mlp_policy,
    save_mlp_policy,
)

SCENE_TOML = strike_scene("sc-pol")


def _mlp(nx: int, nu: int, *, hidden: int = 3, timed: bool = True) -> MLP:
    rng = np.random.default_rng([nx, nu])
    n_in = nx + (1 if timed else 0)
    W0, W1 = rng.normal(size=(hidden, n_in)), rng.normal(size=(nu, hidden))
    return MLP((W0, W1), (np.zeros(hidden), np.zeros(nu)), input="t,state" if timed else "state")


@pytest.fixture
def scene(tmp_path: Path) -> Path:
    p = tmp_path / "scene.toml"
    p.write_text(SCENE_TOML)
    return p


@pytest.mark.parametrize("command", ["validate-policy", "evaluate"])
def test_an_mlp_for_4_states_is_refused_on_an_8_state_scene(
    tmp_path: Path, scene: Path, command: str
) -> None:
    path = save_mlp_policy(_mlp(4, 2), tmp_path / "p4.json")
    args = [command, str(scene), "--policy", str(path)]
    if command == "validate-policy":
        args += ["--samples", "1", "--workers", "1", "--no-progress"]
    done = run_here(*args)
    assert done.returncode == 2
    (line,) = done.stderr.strip().splitlines()
    assert "reads 4 states and returns 2 controls" in line and "8 states and 2" in line
    assert done.stdout == ""  # before any rollout or reference


@settings(max_examples=examples(12))
@given(nx=st.integers(1, 12), nu=st.integers(1, 4), timed=st.booleans())
def test_sizes_are_checked_against_the_problem(nx: int, nu: int, timed: bool) -> None:
    policy = _mlp(nx, nu, timed=timed)
    if (nx, nu) == (8, 2):
        check_policy_sizes(policy, 8, 2)
        assert policy(0.0, np.zeros(8)).shape == (2,)
        return
    with pytest.raises(PolicyError, match=f"reads {nx} states and returns {nu} controls"):
        check_policy_sizes(policy, 8, 2)
    if nx != 8:  # and the network itself never reads another number of state entries
        with pytest.raises(PolicyError, match=f"reads {nx} state entries"):
            policy(0.0, np.zeros(8))


def test_a_callable_without_sizes_is_left_to_the_rollout() -> None:
    check_policy_sizes(lambda t, s: np.zeros(2), 8, 2)  # nothing to compare before a call


# ---------------------------------------------------------------------------- JSON bounds


def _nested(depth: int, kind: str) -> bytes:
    if kind == "array":
        return b"[" * depth + b"]" * depth
    return b'{"a":' * depth + b"1" + b"}" * depth


@settings(max_examples=examples(8))
@given(
    depth=st.one_of(st.integers(MAX_JSON_DEPTH + 1, 2000), st.just(200_000)),
    kind=st.sampled_from(["array", "object"]),
)
def test_json_nested_too_deep_is_one_clear_error(depth: int, kind: str) -> None:
    with pytest.raises(HybridocError) as err:
        parse_json(_nested(depth, kind), "'x.json'")
    assert f"nests arrays and objects {depth} deep" in str(err.value)


@settings(max_examples=examples(6))
@given(depth=st.integers(1, MAX_JSON_DEPTH), kind=st.sampled_from(["array", "object"]))
def test_json_within_the_bound_parses(depth: int, kind: str) -> None:
    value = parse_json(_nested(depth, kind), "'x.json'")
    for _ in range(depth - 1):
        value = value[0] if kind == "array" else value["a"]
    assert value == ([] if kind == "array" else {"a": 1})


def test_brackets_inside_strings_do_not_count() -> None:
    deep_text = '"' + "[" * 10_000 + '\\"' + "{" * 10_000 + '"'
    assert parse_json(('{"a": [' + deep_text + "]}").encode(), "'x'") == {
        "a": ["[" * 10_000 + '"' + "{" * 10_000]
    }


def test_a_policy_json_nested_200000_deep(tmp_path: Path, scene: Path) -> None:
    p = tmp_path / "deep.json"
    p.write_bytes(_nested(200_000, "array"))
    with pytest.raises(PolicyError, match="200000 deep"):
        load_mlp_policy(p)
    done = run_here("evaluate", str(scene), "--policy", str(p))
    assert done.returncode == 2
    (line,) = done.stderr.strip().splitlines()
    assert "deep.json" in line and "200000 deep" in line


def test_a_solution_json_nested_200000_deep(tmp_path: Path) -> None:
    (tmp_path / "s.npz").write_bytes(b"")
    (tmp_path / "s.json").write_bytes(_nested(200_000, "object"))
    with pytest.raises(HybridocError, match="200000 deep"):
        Solution.load(tmp_path / "s.json")
    done = run_here("evaluate", "bouncing-ball", "--controls", str(tmp_path / "s.json"))
    assert done.returncode == 2
    assert "200000 deep" in done.stderr.strip().splitlines()[-1]
