"""Policies of the wrong size or too large, and JSON too deep or too big: refused before any
rollout, one line each (issue #32).

The issue's examples (an MLP policy for 4 states validated on an 8-state scene; a policy
JSON nested 200 000 deep) are single cases in ``test_policy_checks.py``. Here they are
generated: policies of any other input or output size through ``validate-policy`` and
``evaluate --policy``; JSON nested past :data:`~hybridoc.outputs.MAX_JSON_DEPTH` anywhere in
a policy, a solution or a manifest, of arrays and objects mixed; files past their size
bound; and policy files whose sizes are huge (a ``layers`` entry of 10**9 units, a weights
member whose header declares far more than its description, a weights file far larger than
its description), each refused before its weights or arrays are read.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest
from cli_here import run_here
from conftest import examples
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from small_scenes import strike_scene

from hybridoc.errors import HybridocError
from hybridoc.outputs import MAX_JSON_DEPTH, parse_json, read_json
from hybridoc.workflows.policy_format import (
    MAX_PARAMETERS,
    MLP,
    PolicyError,
    load_mlp_policy,
    save_mlp_policy,
)

SLUG = "sc-rel2-pol"
NX, NU = 8, 2  # the strike scene's states and controls
FAST = settings(
    max_examples=examples(12),
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("scene") / "scene.toml"
    p.write_text(strike_scene(SLUG, steps=60))
    return p


def _mlp(nx: int, nu: int, hidden: tuple[int, ...], timed: bool) -> MLP:
    rng = np.random.default_rng([nx, nu, *hidden])
    widths = [nx + (1 if timed else 0), *hidden, nu]
    Ws = tuple(rng.normal(size=(b, a)) for a, b in zip(widths, widths[1:], strict=False))
    bs = tuple(np.zeros(b) for b in widths[1:])
    return MLP(Ws, bs, input="t,state" if timed else "state")


def _refused_before_any_rollout(scene: Path, policy: Path, command: str, *want: str) -> str:
    args = [command, str(scene), "--policy", str(policy)]
    if command == "validate-policy":
        args += ["--samples", "1", "--workers", "1", "--no-progress"]
    done = run_here(*args)
    assert done.returncode == 2, done.stderr
    assert done.stdout == ""  # no rollout, no reference
    (line,) = done.stderr.strip().splitlines()
    assert line.startswith("hybridoc: error: ")
    for w in want:
        assert w in line, (w, line)
    return line


@FAST
@given(
    nx=st.integers(1, 16),
    nu=st.integers(1, 5),
    hidden=st.lists(st.integers(1, 6), min_size=0, max_size=2).map(tuple),
    timed=st.booleans(),
    command=st.sampled_from(["validate-policy", "evaluate"]),
)
def test_a_policy_of_another_size_is_refused_before_any_rollout(
    tmp_path_factory: pytest.TempPathFactory,
    scene: Path,
    nx: int,
    nu: int,
    hidden: tuple[int, ...],
    timed: bool,
    command: str,
) -> None:
    if (nx, nu) == (NX, NU):
        nu += 1  # the problem's own sizes: another output size instead
    path = save_mlp_policy(_mlp(nx, nu, hidden, timed), tmp_path_factory.mktemp("p") / "p.json")
    _refused_before_any_rollout(
        scene, path, command, f"reads {nx} states and returns {nu} controls",
        f"{NX} states and {NU} controls",
    )  # fmt: skip


# ---------------------------------------------------------------------------- huge sizes


def _policy_json(path: Path, layers: list[int], weights: str = "p.npz", **extra: object) -> Path:
    spec = {"format": "hybridoc-mlp-policy", "version": 1, "weights": weights,
            "input": "t,state", "horizon": 1.0, "layers": layers, "activation": "tanh",
            **extra}  # fmt: skip
    path.write_text(json.dumps(spec))
    return path


def _npy_header(shape: tuple[int, ...]) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": "<f8", "fortran_order": False, "shape": shape}
    )
    return buf.getvalue()


@FAST
@given(
    width=st.integers(MAX_PARAMETERS // 10 + 1, 10**12),
    depth=st.integers(1, 3),
    command=st.sampled_from(["validate-policy", "evaluate"]),
)
def test_layers_past_the_bound_are_refused_before_the_weights_are_read(
    tmp_path_factory: pytest.TempPathFactory, scene: Path, width: int, depth: int, command: str
) -> None:
    d = tmp_path_factory.mktemp("wide")
    # no weights file at all: the description alone is refused
    path = _policy_json(d / "p.json", [NX + 1, *[width] * depth, NU])
    with pytest.raises(PolicyError, match="parameters, more than the"):
        load_mlp_policy(path)
    _refused_before_any_rollout(scene, path, command, "refused before its weights are read")


@FAST
@given(
    member=st.sampled_from(
        ["layer0.weight", "layer0.bias", "layer1.weight", "state_mean", "output_scale", "surprise"]
    ),  # fmt: skip
    rows=st.integers(10**6, 10**12),
)
def test_a_weights_header_declaring_a_huge_array_is_refused_before_it_is_read(
    tmp_path_factory: pytest.TempPathFactory, scene: Path, member: str, rows: int
) -> None:
    # every member as described, but one whose header declares `rows` rows with only a few
    # bytes behind it: numpy would allocate the declared array before reading
    d = tmp_path_factory.mktemp("header")
    good = save_mlp_policy(_mlp(NX, NU, (3,), True), d / "p.json")
    arrays = dict(np.load(d / "p.npz"))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, a in arrays.items():
            if name != member:
                zf.writestr(f"{name}.npy", _npy_bytes(a))
        zf.writestr(f"{member}.npy", _npy_header((rows, 9)) + b"\0" * 64)
    (d / "p.npz").write_bytes(buf.getvalue())
    spec = json.loads(good.read_text())
    spec.pop("sha256")  # a hand-written file: no hash to catch it
    good.write_text(json.dumps(spec))
    with pytest.raises(PolicyError) as err:
        load_mlp_policy(good)
    text = str(err.value)
    assert "\n" not in text and (member in text or f"({rows}, 9)" in text), text
    assert _refused_before_any_rollout(scene, good, "evaluate").endswith(text)


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def test_a_weights_file_far_larger_than_its_description_is_not_read(
    tmp_path: Path, scene: Path
) -> None:
    path = save_mlp_policy(_mlp(NX, NU, (3,), True), tmp_path / "p.json")
    with open(tmp_path / "p.npz", "r+b") as fh:  # a sparse file: 64 GiB, nothing on disk
        fh.truncate(64 << 30)
    with pytest.raises(PolicyError, match="refused before it is read"):
        load_mlp_policy(path)
    _refused_before_any_rollout(scene, path, "validate-policy", "refused before it is read")


def test_a_policy_within_its_bounds_still_loads(tmp_path: Path) -> None:
    mlp = _mlp(NX, NU, (4, 4), True)
    loaded = load_mlp_policy(save_mlp_policy(mlp, tmp_path / "p.json"))
    s = np.linspace(-1, 1, NX)
    assert np.array_equal(loaded(0.3, s), mlp(0.3, s))


# ---------------------------------------------------------------------------- JSON bounds


def _deep(depth: int, seed: int) -> str:
    """JSON nested ``depth`` deep, arrays and objects mixed at random (``seed``)."""
    kinds = np.random.default_rng(seed).random(depth) < 0.5
    opens = "".join("[" if k else '{"k":' for k in kinds)
    closes = "".join("]" if k else "}" for k in reversed(kinds))
    return opens + "1" + closes


@st.composite
def deep_documents(draw: st.DrawFn) -> tuple[str, int]:
    """A JSON object whose entry (of a key a real file has, or another) nests past the
    bound; the total depth counts the object itself."""
    depth = draw(st.one_of(st.integers(MAX_JSON_DEPTH, MAX_JSON_DEPTH + 200),
                           st.integers(1000, 5000), st.just(200_000)))  # fmt: skip
    key = draw(st.sampled_from(["layers", "saturation", "settings", "controls", "x"]))
    seed = draw(st.integers(0, 2**32 - 1))
    return '{"format": "x", "' + key + '": ' + _deep(depth, seed) + "}", depth + 1


@FAST
@given(doc=deep_documents(), reader=st.sampled_from(["policy", "solution", "manifest"]))
def test_json_nested_past_the_bound_is_one_line_from_every_reader(
    tmp_path_factory: pytest.TempPathFactory, scene: Path, doc: tuple[str, int], reader: str
) -> None:
    text, depth = doc
    d = tmp_path_factory.mktemp("deep")
    with pytest.raises(HybridocError) as err:
        parse_json(text.encode(), "'x'")
    assert f"{depth} deep" in str(err.value)
    if reader == "policy":
        (d / "p.json").write_text(text)
        args = ["evaluate", str(scene), "--policy", str(d / "p.json")]
    elif reader == "solution":
        (d / "s.json").write_text(text)
        (d / "s.npz").write_bytes(b"")
        args = ["evaluate", "bouncing-ball", "--controls", str(d / "s.json")]
    else:
        (d / "ds").mkdir()
        (d / "ds" / "manifest.json").write_text(text)
        (d / "ds" / "dataset.npz").write_bytes(b"")
        (d / "pol.py").write_text("import numpy as np\ndef p(t, s):\n    return np.zeros(2)\n")
        args = ["validate-policy", str(scene), "--policy", f"{d / 'pol.py'}:p", "--samples",
                "1", "--dataset", str(d / "ds"), "--workers", "1", "--no-progress"]  # fmt: skip
    done = run_here(*args)
    assert done.returncode == 2 and done.stdout == ""
    (line,) = done.stderr.strip().splitlines()
    assert f"{depth} deep" in line, line


@FAST
@given(depth=st.integers(1, MAX_JSON_DEPTH), seed=st.integers(0, 2**32 - 1))
def test_json_within_the_bound_parses_as_json_does(depth: int, seed: int) -> None:
    text = _deep(depth, seed)
    assert parse_json(text.encode(), "'x'") == json.loads(text)


@FAST
@given(
    extra=st.integers(1, 4096),
    shape=st.sampled_from(["string", "list", "spaces"]),
)
def test_json_past_its_size_bound_is_refused_before_it_is_parsed(
    tmp_path_factory: pytest.TempPathFactory, extra: int, shape: str
) -> None:
    bound = 1 << 16
    filler = {"string": '"' + "a" * (bound + extra) + '"',
              "list": "[" + ",".join(["1"] * ((bound + extra) // 2 + 1)) + "]",
              "spaces": "1" + " " * (bound + extra)}[shape]  # fmt: skip
    p = tmp_path_factory.mktemp("big") / "b.json"
    p.write_text(filler)
    with pytest.raises(HybridocError, match=f"larger than {bound} bytes"):
        read_json(p, max_bytes=bound)
    assert read_json(p, max_bytes=len(filler)) is not None  # the bound, not the content


@pytest.mark.skipif(os.name != "posix", reason="FIFOs")
@pytest.mark.parametrize("reader", ["policy", "solution"])
def test_a_fifo_where_a_json_file_goes_never_blocks(
    tmp_path: Path, scene: Path, reader: str
) -> None:
    fifo = tmp_path / "f.json"
    os.mkfifo(fifo)
    if reader == "policy":
        done = run_here("evaluate", str(scene), "--policy", str(fifo))
    else:
        (tmp_path / "f.npz").write_bytes(b"")
        done = run_here("evaluate", "bouncing-ball", "--controls", str(fifo))
    assert done.returncode == 2 and done.stdout == ""
    (line,) = done.stderr.strip().splitlines()
    assert str(fifo) in line, line
