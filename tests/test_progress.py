"""The one progress protocol (hybridoc.progress): what a meter writes, on a fake clock."""

from __future__ import annotations

import io

import pytest

from hybridoc import progress as hp


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    now = [0.0]
    monkeypatch.setattr(hp.time, "perf_counter", lambda: now[0])
    monkeypatch.setattr(hp, "QUIET_S", 0.0)
    monkeypatch.setattr(hp, "REDRAW_S", 0.0)
    return now


def test_the_time_left_is_per_stage(clock: list[float]) -> None:
    out = io.StringIO()
    with hp.ProgressMeter("gd", stream=out, tty=True) as meter:
        meter.count(0, 100)
        clock[0] = 10.0
        meter.count(50, 100)  # 5 per second: 10 s left
        meter.stage("next")
        meter.count(0, 100)
        clock[0] = 11.0
        meter.count(10, 100)  # 10 per second in this stage: 9 s left, not 99
    text = out.getvalue()
    assert "50/100, 10 s left" in text
    assert "gd: next [##" in text and "10/100, 9 s left" in text
    assert text.endswith("\n")  # close ends the bar's line


def test_a_log_gets_plain_lines_at_its_pace(clock: list[float], monkeypatch) -> None:
    monkeypatch.setattr(hp, "QUIET_LOG_S", 5.0)
    monkeypatch.setattr(hp, "EVERY_LOG_S", 30.0)
    out = io.StringIO()
    with hp.ProgressMeter("dataset", stream=out, tty=False) as meter:
        for k in range(100):
            clock[0] = float(k)
            meter.count(k, 100, "0 failed")
        meter.count(100, 100, "0 failed")
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    # silent for 5 s, then one line per 30 s, and the last count
    assert [line.split("] ")[1].split("/")[0] for line in lines] == ["5", "35", "65", "95", "100"]


def test_as_progress_and_scope() -> None:
    assert isinstance(hp.as_progress(None, "x"), hp.NullProgress)
    assert isinstance(hp.as_progress(False, "x"), hp.NullProgress)
    meter = hp.as_progress(True, "x")
    assert isinstance(meter, hp.ProgressMeter)
    meter.close()

    class Recorder:
        def __init__(self) -> None:
            self.calls: list[tuple] = []

        def stage(self, text: str) -> None:
            self.calls.append(("stage", text))

        def detail(self, text: str) -> None:
            self.calls.append(("detail", text))

        def count(self, done: int, total: int, text: str = "") -> None:
            self.calls.append(("count", done, total))

        def close(self) -> None:
            self.calls.append(("close",))

    rec = Recorder()
    assert hp.as_progress(rec, "x") is rec
    with hp.progress_scope(rec, "x") as p:
        p.stage("a")
    assert rec.calls == [("stage", "a")]  # the caller's object is not closed for it
    with pytest.raises(TypeError, match="progress must be"):
        hp.as_progress("yes", "x")


def test_an_unknown_total_draws_no_bar_and_no_time_left(clock: list[float]) -> None:
    out = io.StringIO()
    with hp.ProgressMeter("gd", stream=out, tty=True) as meter:
        meter.stage("stage 1 of 2, smoothing")
        meter.count(0, None, "iterations")
        clock[0] = 2.0
        meter.count(300, None, "iterations, loss 0.5")  # 150 per second
    text = out.getvalue()
    assert "gd: stage 1 of 2, smoothing: 300 iterations, loss 0.5 (150/s) [2 s]" in text
    assert "[#" not in text and "/300" not in text and "left" not in text
    assert text.endswith("\n")  # no final count: close still ends the line


def test_gd_in_a_log_writes_plain_lines_with_its_stages(monkeypatch) -> None:
    # `hybridoc solve single-collision --method gd 2>log`: stderr is no terminal
    from hybridoc.solvers.gd import solve_gd

    monkeypatch.setattr(hp, "QUIET_LOG_S", 0.0)
    monkeypatch.setattr(hp, "EVERY_LOG_S", 0.0)
    err = io.StringIO()
    monkeypatch.setattr(hp.sys, "stderr", err)
    sol = solve_gd("single-collision", iters=5, progress=True)
    text = err.getvalue()
    assert text and "\r" not in text
    lines = text.splitlines()
    assert lines[0].startswith("gd: stage 1 of 4, smoothing mu 0.0001 [")
    assert "gd: stage 4 of 4, descent (lbfgs) after smoothing [" in text
    # one line per iteration at this pace, none with a total it does not have
    counted = [line for line in lines if " iterations, loss " in line]
    assert len(counted) == sol.info["iterations"] and not any("/5" in x for x in counted)


def test_learning_curve_marks_gd_stages() -> None:
    from matplotlib.figure import Figure

    from hybridoc.plotting import mark_stages
    from hybridoc.solvers.gd import solve_gd

    sol = solve_gd("single-collision", iters=5)
    hist = sol.arrays["loss_history"]
    marks = sol.info["history_stages"]
    assert [m[1] for m in marks] == ["mu 0.0001", "mu 1e-05", "mu 1e-06", "no smoothing"]
    starts = [m[0] for m in marks]
    assert starts[0] == 0 and starts == sorted(set(starts)) and starts[-1] < len(hist)
    # each stage starts from the last controls with a smaller smoothing penalty: the curve
    # steps down exactly at a mark
    for k in starts[1:]:
        assert hist[k] < hist[k - 1]
    fig = Figure()
    ax = fig.subplots()
    ax.plot(hist)
    mark_stages(ax, marks)
    assert [line.get_xdata()[0] for line in ax.lines[1:]] == starts[1:]  # no line at 0
    assert [t.get_text() for t in ax.texts] == [m[1] for m in marks]
    mark_stages(ax, None)
    assert len(ax.texts) == len(marks)


def test_a_shorter_redraw_covers_the_longer_one(clock: list[float]) -> None:
    out = io.StringIO()
    with hp.ProgressMeter("gd", stream=out, tty=True) as meter:
        meter.count(1, None, "iterations, loss 0.123456, and a long status")
        clock[0] = 1.0
        meter.count(2, None, "iterations, loss 0.5")
    draws = out.getvalue().rstrip("\n").split("\r")[1:]
    assert len(draws) == 2 and len(draws[1]) == len(draws[0])
    assert draws[1].rstrip().endswith("loss 0.5 (1/s) [1 s]")
