"""One CLI vocabulary across every command: one flag for a control input (--controls FILE,
old spellings only as deprecated aliases), --policy for a policy, --out DIR with the naming
rule <problem-slug>_<command>.{json,npz,png}, and help texts in plain text."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import pytest

from hybridoc.cli import build_parser, main
from hybridoc.cli._util import output_stem, problem_slug

CONTROL_WORDS = ("control", "initial", "guess")
OUT_IS_A_FOLDER = {"dataset"}  # a resumable dataset folder (cmd_dataset's docstring says why)
OUT_IS_A_FILE = {"export"}  # one model file for another simulator, named by the user


def _commands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    (sub,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    out = {}
    for name, p in sub.choices.items():
        p.complete()  # the deferred arguments too
        out[name] = p
    return out


COMMANDS = _commands()


def test_every_command_is_checked() -> None:
    assert {"crossval", "dataset", "validate-policy", "train-policy", "solve", "evaluate",
            "validate", "reference"} <= set(COMMANDS)  # fmt: skip


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_flag_names(name: str) -> None:
    p = COMMANDS[name]
    for action in p._actions:
        flags = [s for s in action.option_strings if s.startswith("--")]
        help_text = action.help or ""
        # a control file is --controls; another spelling only beside it, as a deprecated alias
        if any(w in f for f in flags for w in ("--initial", "--control")):
            assert "--controls" in flags or flags == ["--control-weight"], (name, flags)
            if len(flags) > 1:
                assert "deprecated" in help_text, (name, flags)
        # a positional that takes a control file or a policy is deprecated beside its flag
        if not action.option_strings and action.metavar in ("CONTROLS", "POLICY"):
            assert help_text.startswith("deprecated"), (name, action.metavar)
        if "--policy" in flags:
            assert action.metavar == "SPEC", name
        if "--out" in flags and name not in OUT_IS_A_FILE:
            assert action.metavar == "DIR", name
            if name not in OUT_IS_A_FOLDER:
                assert f"<problem>_{name}" in " ".join(help_text.split()), (name, help_text)
    # no other flag names a policy
    for action in p._actions:
        assert not any("polic" in s and s != "--policy" for s in action.option_strings), name


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_help_is_plain_text(name: str) -> None:
    text = COMMANDS[name].format_help()
    assert "``" not in text, name
    assert not re.search(r":(func|mod|class|meth|attr|data):`", text), name


def test_output_names_follow_one_rule(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A library problem's slug is its registry name, a file's is the problem's name."""
    assert problem_slug("bouncing-ball-2", object()) == "bouncing-ball-2"
    assert problem_slug("single-collision", object()) == "single-collision"

    class Named:
        name = "my problem (v2)"

    assert problem_slug("x.py:f", Named()) == "my-problem-v2"
    assert output_stem(tmp_path, "bouncing-ball", "solve", "gd").name == "bouncing-ball_solve_gd"
    # a real run: evaluate's files
    code = main(["evaluate", "bouncing-ball-2", "--json", "--out", str(tmp_path)])
    assert code in (0, 1)
    json.loads(capsys.readouterr().out)
    # hidden files are hybridoc's record of what it wrote (hybridoc.outputs)
    names = sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith("."))
    assert names and all(n.startswith("bouncing-ball-2_evaluate") for n in names), names
    assert {Path(n).suffix for n in names} <= {".json", ".npz", ".png"}


def test_deprecated_aliases_still_work(tmp_path: Path) -> None:
    args = build_parser().parse_args(["solve", "bouncing-ball", "--initial", "u.npy"])
    assert args.initial == Path("u.npy")
    args = build_parser().parse_args(["solve", "bouncing-ball", "--controls", "u.npy"])
    assert args.initial == Path("u.npy")
    args = build_parser().parse_args(["validate-policy", "x.toml", "p.json", "--samples", "1"])
    assert args.policy_positional == "p.json" and args.policy is None
