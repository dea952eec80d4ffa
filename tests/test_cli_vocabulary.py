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
from hybridoc.cli.vocabulary import (
    SET_ALIASES,
    VOCABULARY,
    DeprecatedAlias,
    DeprecatedSetAlias,
)
from hybridoc.methods import METHODS

CONTROL_WORDS = ("control", "initial", "guess")
OUT_IS_A_FOLDER = {"dataset"}  # a resumable dataset folder (cmd_dataset's docstring says why)
OUT_IS_A_FILE = {"export"}  # one model file for another simulator, named by the user


def _alias(action: argparse.Action) -> bool:
    """A deprecated spelling: hidden from help, recording a note when used."""
    return isinstance(action, DeprecatedAlias | DeprecatedSetAlias)


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
        # a control file is --controls; another spelling only as a deprecated alias
        if any(w in f for f in flags for w in ("--initial", "--control")) and not _alias(action):
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


# ------------------------------------------------------------------ one word per concept
DEPRECATED = {flag for c in VOCABULARY.values() for flag in c.deprecated}
CANONICAL = {c.flag for c in VOCABULARY.values()}
#: the flags of the methods' options (hybridoc solve, hybridoc reference): their names
METHOD_FLAGS = {s.flag: s.name for m in METHODS.values() for s in m.specs() if s.cli}
#: what a flag looks like when it names a concept of the table: then it is the table's word
LOOKS_LIKE = {
    "iterations": (re.compile(r"iter|epoch"), {"--iters", "--terminal-iters"}),
    "contact model": (re.compile(r"model|contact"), {"--contact"}),
    "progress": (re.compile(r"^--no-"), {"--no-progress"}),
    "time of impact": (re.compile(r"toi"), {"--toi"}),
    "tolerance": (re.compile(r"tol"), {c.flag for c in VOCABULARY.values() if "tol" in c.flag}),
}


def test_the_table_is_consistent() -> None:
    """One spelling per concept, no old spelling that is another concept's word, and the
    Python keyword where the CLI word is not simply it (--controls/initial=, --no-progress/
    progress=False, --tolerance/tolerances=, --set)."""
    flags = [c.flag for c in VOCABULARY.values()]
    assert len(flags) == len(set(flags))
    assert not DEPRECATED & CANONICAL
    differ = {k for k, c in VOCABULARY.items()
              if c.python is not None and c.flag != "--" + c.python.replace("_", "-")}  # fmt: skip
    assert differ == {"controls", "progress", "agreement tolerance"}, differ
    for command, aliases in SET_ALIASES.items():
        for setting in aliases.values():
            method, option = setting.split(".")
            assert option in METHODS[method].option_names(), (command, setting)


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_flag_uses_the_vocabulary(name: str) -> None:
    """Old spellings only as hidden deprecated aliases; a flag that names a concept of the
    table is the table's word (or a method's option, whose flag is its Python name)."""
    for action in COMMANDS[name]._actions:
        flags = [s for s in action.option_strings if s.startswith("--")]
        if _alias(action):
            assert action.help == argparse.SUPPRESS, (name, flags)
            assert len(flags) == 1, (name, flags)
            if isinstance(action, DeprecatedSetAlias):
                assert SET_ALIASES[name][flags[0]] == action.setting, (name, flags)
            else:
                assert flags[0] in DEPRECATED, (name, flags)
            continue
        for flag in flags:
            generated = METHOD_FLAGS.get(flag) == action.dest  # a method's option
            assert flag not in DEPRECATED or generated, (name, flag)
            for concept, (pattern, allowed) in LOOKS_LIKE.items():
                if pattern.search(flag) and not generated:
                    assert flag in allowed, (name, flag, concept)


def test_every_word_is_used() -> None:
    used = {s for p in COMMANDS.values() for a in p._actions for s in a.option_strings}
    assert CANONICAL - used == set()


OLD_SPELLINGS = [
    (["gradcheck", "head-on", "--gd-iters", "5"], "gd_iters", "5", "--iters K,K"),
    (["compare-contacts", "head-on", "--models", "lcp"], "models", "lcp", "--contact M,M"),
    (["train-policy", "x.toml", "--samples", "2", "--out", "d", "--epochs", "7"], "iters",
     7, "--iters K"),
    (["train-policy", "x.toml", "--samples", "2", "--out", "d", "--no-toi"], "toi", "none",
     "--toi none"),
    (["convergence", "head-on", "--no-gd"], "no_gd", True, "--methods dt"),
    (["solve", "head-on", "--initial", "u.npy"], "initial", Path("u.npy"), "--controls"),
    (["crossval", "head-on", "--starts", "3", "--mesh", "8", "--gd-integrator",
      "symplectic-euler"], "set",
     ["gd.starts=3", "dt.mesh=8", "gd.integrator=symplectic-euler"], "--set gd.starts=3"),
]  # fmt: skip
"""Each old spelling once: the command line, the canonical ``dest`` and the value it gets
there, and what the (first) note says to use instead."""


@pytest.mark.parametrize(("argv", "dest", "value", "note"), OLD_SPELLINGS)
def test_old_spellings_map_onto_the_new_ones_with_a_note(
    argv: list[str], dest: str, value: object, note: str
) -> None:
    args = build_parser().parse_args(argv)
    assert getattr(args, dest) == value
    notes = args._deprecated
    assert notes and "deprecated" in notes[0] and note in notes[0], notes
    # one note per old spelling given, naming it
    old = [a for a in argv if a in DEPRECATED or a in SET_ALIASES.get(argv[0], {})]
    assert [n.split()[0] for n in notes] == old, notes


def test_every_old_spelling_is_tested() -> None:
    """Each deprecated alias of the table (and each old flag of --set) is in
    :data:`OLD_SPELLINGS`, so that it is known to still work while it is kept."""
    given = {a for argv, *_ in OLD_SPELLINGS for a in argv}
    set_flags = {flag for flags in SET_ALIASES.values() for flag in flags}
    assert (DEPRECATED | set_flags) - given == set()


def test_an_error_names_the_old_spelling_as_typed(capsys: pytest.CaptureFixture[str]) -> None:
    """A user error about a flag given by its old spelling names the flag as it was typed,
    and the error stays the one line (no deprecation note after it)."""
    for flag, new in (("--models", "--contact"), ("--gd-iters", "--iters")):
        argv = ["gradcheck", "head-on", "--against", "g.npy", flag, "5"]
        assert main(argv) == 2
        (line,) = capsys.readouterr().err.splitlines()
        assert f"{flag} compare contact models: not with --against" in line, line
        argv[4] = new
        assert main(argv) == 2
        (line,) = capsys.readouterr().err.splitlines()
        assert f"{new} compare contact models: not with --against" in line, line


def test_the_new_spellings_parse_without_a_note() -> None:
    p = build_parser()
    args = p.parse_args(["train-policy", "x.toml", "--samples", "2", "--out", "d", "--iters",
                         "7", "--toi", "velocity"])  # fmt: skip
    assert (args.iters, args.toi) == (7, "velocity")
    assert not getattr(args, "_deprecated", None)
    args = p.parse_args(["train-policy", "x.toml", "--samples", "2", "--out", "d", "--toi"])
    assert args.toi == "both"
    args = p.parse_args(["crossval", "head-on", "--set", "gd.starts=3", "--set", "dt.mesh=8"])
    assert args.set == ["gd.starts=3", "dt.mesh=8"]
    assert p.parse_args(["solve", "head-on", "--no-progress"]).no_progress is True


def test_set_is_checked_against_the_registry(capsys: pytest.CaptureFixture[str]) -> None:
    """--set METHOD.OPTION=VALUE: an unknown method or option, or a bad value, is one error
    line naming the valid choices (exit 2), before any solve."""
    from hybridoc.errors import OptionError
    from hybridoc.methods import parse_settings

    assert parse_settings(["gd.starts=3", "dt.mesh=8", "gd.time-limit=2", "gd.starts=4"]) == {
        "gd": {"starts": 4, "time_limit": 2.0},
        "dt": {"mesh": 8},
    }
    for bad, words in [
        ("nope.starts=1", ("unknown method 'nope'", "reference, dt, gd")),
        ("gd.nope=1", ("gd has no option 'nope'", "starts")),
        ("gd.starts=0", ("integer >= 1",)),
        ("gd.integrator=euler", ("exact, symplectic-euler",)),
        ("gd.callback=x", ("no option 'callback'",)),  # the Python API's only
        ("gd.starts", ("METHOD.OPTION=VALUE",)),
    ]:
        with pytest.raises(OptionError) as info:
            parse_settings([bad])
        assert all(w in str(info.value) for w in words), (bad, str(info.value))
        assert main(["crossval", "bouncing-ball", "--set", bad, "--no-progress"]) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith("hybridoc: error: --set"), err


def test_a_deprecated_flag_notes_once_the_command_ran(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The note comes after the answer; after a user error the error stays the one line."""
    import hybridoc.workflows.validation as val

    def fake(ocp: object, **kwargs: object) -> object:
        return {"problem": "x", "agree": True, "reasons": [], "options": kwargs["options"]}, {}

    monkeypatch.setattr(val, "crossval", fake)
    assert main(["crossval", "bouncing-ball", "--starts", "2", "--no-progress", "--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["options"] == {"gd": {"starts": 2}}
    assert err.splitlines()[-1] == (
        "hybridoc: warning: --starts is deprecated and will be removed; use --set gd.starts=2"
    )
    assert main(["crossval", "bouncing-ball", "--starts", "0", "--no-progress"]) == 2
    assert len(capsys.readouterr().err.splitlines()) == 1
