"""benchmarks/bench_all.py's one table (issue #18): target beside measured value, verdicts
from the numbers given, the load column, a failing section as a row (no timing here)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_all  # noqa: E402

OTHERS = [s for s in bench_all.SECTIONS if s != "tests"]


def _rows(out: str) -> list[list[str]]:
    lines = [ln for ln in out.splitlines() if ln.startswith("| ") and "---" not in ln]
    return [[c.strip() for c in ln.strip("|").split("|")] for ln in lines]


def test_given_test_times_are_judged_against_their_targets(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    skip = [a for s in OTHERS for a in ("--skip", s)]
    assert bench_all.main([*skip, "--make-test-s", "200", "--ci-run-s", "400"]) == 0
    rows = _rows(capsys.readouterr().out)
    assert rows[0] == ["what", "target", "measured", "result", "load"]
    make, ci = rows[1], rows[2]
    assert make[1] == "< 4 min" and make[2].startswith("200 s") and make[3] == "PASS"
    assert ci[1] == "< 6 min" and ci[2].startswith("400 s") and ci[3] == "MISS"
    # from a file, with its note; arguments win over it
    times = tmp_path / "t.json"
    times.write_text(json.dumps({"make_test_s": 250, "ci_run_s": 300, "note": "idle, abc"}))
    bench_all.main([*skip, "--times", str(times), "--ci-run-s", "999"])
    rows = _rows(capsys.readouterr().out)
    assert "250 s" in rows[1][2] and "idle, abc" in rows[1][2] and rows[1][3] == "MISS"
    assert rows[2][2].startswith("999 s")
    bench_all.main([*skip, "--times", str(tmp_path / "absent.json")])
    assert "not given" in _rows(capsys.readouterr().out)[1][2]


def test_a_failing_section_is_a_row(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(*_: object) -> list[bench_all.Row]:
        raise RuntimeError("no such thing")

    monkeypatch.setattr(bench_all, "search", broken)
    skip = [a for s in bench_all.SECTIONS if s != "search" for a in ("--skip", s)]
    assert bench_all.main(skip) == 0
    (header, row) = _rows(capsys.readouterr().out)
    assert row[0] == "search" and "FAILED: RuntimeError: no such thing" in row[2]
    assert row[3] == "MISS" and " / " in row[4]  # the load before / after
