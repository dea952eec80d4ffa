"""The screens of an explicit search shared between worker processes and the parent.

``solve_reference(..., search=K)`` on a disc scene starts its screens in worker processes
before the guess's candidates and the sources, and the enumeration takes each screen's
outcome from whichever process ran it (``reference/solve.py``, ``_EarlyScreens``). A
screen's outcome is a function of the problem and the guess alone, so the landscape must
be the one of every screen run in order in one process, whoever ran which, also when a
worker raises or dies.
"""

from __future__ import annotations

import os

import pytest

import hybridoc
import hybridoc.reference.search.enumeration as rsolve
from hybridoc.reference import solve_reference

KWARGS = dict(search=2, multistart=0, transcription=False)


def _rows(sol):
    keys = ("sequence", "cost", "verdict", "origin")
    return [tuple(r[k] for k in keys) for r in sol.info["landscape"]]


@pytest.fixture(scope="module")
def scene():
    return hybridoc.load_scene("multiple-collision")


@pytest.fixture(scope="module")
def in_order(scene):
    """Every screen run in order in this process (no workers)."""
    mp = pytest.MonkeyPatch()
    mp.setattr(rsolve._EarlyScreens, "start", lambda *a, **k: None)
    try:
        return solve_reference(scene, **KWARGS)
    finally:
        mp.undo()


def _spy_start(monkeypatch, after_start=None):
    """Record the screens object ``start`` returns (and act on it, ``after_start``)."""
    started = []
    real = rsolve._EarlyScreens.start

    def spy(*args, **kwargs):
        early = real(*args, **kwargs)
        if early is not None and after_start is not None:
            after_start(early)
        started.append(early)
        return early

    monkeypatch.setattr(rsolve._EarlyScreens, "start", spy)
    return started


def _same(sol, in_order):
    assert _rows(sol) == _rows(in_order)
    assert sol.cost == in_order.cost
    assert sol.info["coverage"] == in_order.info["coverage"]


def test_outcomes_taken_from_the_workers_are_the_ones_run_here(scene, in_order, monkeypatch):
    # the parent waits for a worker's outcome before it claims any screen itself, so that
    # at least one outcome of the landscape comes from a worker process
    started = _spy_start(monkeypatch, after_start=lambda early: early._receive(60.0))
    sol = solve_reference(scene, **KWARGS)
    if started[0] is None:
        pytest.skip("no second usable core or no fork: the screens run in order anyway")
    assert started[0].by_worker >= 1
    _same(sol, in_order)
    assert not any(p.is_alive() for p in started[0].workers)  # ended with the search


def test_a_screen_that_raises_in_a_worker_is_run_again_here(scene, in_order, monkeypatch):
    # every screen raises in the workers (an unexpected error): the parent runs each of them
    # itself, where the error would surface; here it does not, so the landscape is the same
    parent = os.getpid()
    real = rsolve._search_one

    def flaky(seq):
        if os.getpid() != parent:
            raise RuntimeError("a worker's unexpected error")
        return real(seq)

    monkeypatch.setattr(rsolve, "_search_one", flaky)
    started = _spy_start(monkeypatch, after_start=lambda early: early._receive(60.0))
    sol = solve_reference(scene, **KWARGS)
    if started[0] is None:
        pytest.skip("no second usable core or no fork: the screens run in order anyway")
    assert started[0].by_worker == 0
    _same(sol, in_order)


def test_the_screens_of_a_worker_that_died_are_run_here(scene, in_order, monkeypatch):
    # a worker killed in its first screen (as by the OOM killer) leaves that screen claimed
    # and no outcome: the parent notices that it died and runs the screen itself
    import signal

    parent = os.getpid()
    real = rsolve._search_one

    def killed(seq):
        if os.getpid() != parent:
            os.kill(os.getpid(), signal.SIGKILL)
        return real(seq)

    monkeypatch.setattr(rsolve, "_search_one", killed)
    started = _spy_start(monkeypatch)
    sol = solve_reference(scene, **KWARGS)
    if started[0] is None:
        pytest.skip("no second usable core or no fork: the screens run in order anyway")
    assert all(p.exitcode == -signal.SIGKILL for p in started[0].workers)
    assert started[0].by_worker == 0
    _same(sol, in_order)


def test_the_screen_of_a_stuck_worker_is_run_here(scene, in_order, monkeypatch):
    # a worker that hangs in its first screen (as a process forked from threads might) gives
    # no outcome: after SCREEN_WAIT seconds with nothing else to do the parent runs it
    import time

    parent = os.getpid()
    real = rsolve._search_one

    def stuck(seq):
        if os.getpid() != parent:
            time.sleep(3600)
        return real(seq)

    monkeypatch.setattr(rsolve, "_search_one", stuck)
    monkeypatch.setattr(rsolve, "SCREEN_WAIT", 1.0)
    started = _spy_start(monkeypatch)
    sol = solve_reference(scene, **KWARGS)
    if started[0] is None:
        pytest.skip("no second usable core or no fork: the screens run in order anyway")
    assert started[0].by_worker == 0
    assert not any(p.is_alive() for p in started[0].workers)  # ended with the search
    _same(sol, in_order)


def test_the_screened_sequences_are_the_enumeration_s_in_its_order(scene, monkeypatch):
    # screened: every sequence of up to K events whose lower bound is below the best cost
    # known at the start, in the enumeration's order (length, then bound), the guess's
    # candidates last; none the enumeration prunes anyway
    from hybridoc.problem import as_ocp
    from hybridoc.reference.candidates import enumerate_sequences, lower_bound

    ocp = as_ocp(scene)
    started = _spy_start(monkeypatch)
    sol = solve_reference(scene, search=3, multistart=0, transcription=False)
    early = started[0]
    if early is None:
        pytest.skip("no second usable core or no fork: the screens run in order anyway")
    tasks = [tuple(q) for q in early.tasks]
    assert len(tasks) == len(set(tasks))
    guess = {tuple(c["sequence"]) for c in sol.info["candidates"] if c["origin"] == "initial guess"}
    lead = [q for q in tasks if q not in guess]
    assert tasks[: len(lead)] == lead  # the guess's candidates last
    keys = [(len(q), lower_bound(ocp, q)) for q in lead]
    assert keys == sorted(keys)
    every = {tuple(q) for q in enumerate_sequences(ocp, 3)}
    initial = sol.info["known_controls"][0]["cost"]
    want = {q for q in every if lower_bound(ocp, q) < initial}
    assert set(tasks) == want
    # the enumeration's own pruning and skipping are as without the workers: each
    # enumerated sequence has a row
    rows = {tuple(r["sequence"]) for r in sol.info["landscape"]}
    assert want <= rows


def test_guessed_event_times_read_psi_once_per_trajectory_and_guard():
    # guess_times evaluates each guard's psi along the guess's trajectory once (issue #18:
    # the search guesses the times of ~150 sequences from one trajectory); the times are
    # those of psi mapped over the states after the previous event, bit for bit
    import numpy as np

    from hybridoc.reference import candidates as rc
    from hybridoc.reference.candidates import enumerate_sequences, guess_times

    ocp = hybridoc.load_scene("multiple-collision").to_ocp()
    ev = hybridoc.evaluate(ocp, ocp.u_guess)  # the guess a search starts from
    rc._PSI.pop(id(ev), None)

    def direct(seq):
        out, prev, T = [], 0.0, ocp.horizon
        obs = rc._event_list(ev)
        for name in seq:
            match = [tt for n, tt in obs if n == name and tt > prev]
            m = (ev.times > prev) & (ev.times < T)
            if match:
                tt = match[0]
            elif m.any():
                psi_fn = ocp.guards[ocp.guard_index(name)].psi
                psi = np.asarray(psi_fn.map(int(m.sum()))(ev.states[m].T)).ravel()
                tt = float(ev.times[m][int(np.argmin(psi))])
            else:
                tt = 0.5 * (prev + T)
            tt = min(max(tt, prev + 1e-3 * T), T * (1 - 1e-3))
            out.append(tt)
            prev = tt
        return np.array(out)

    seqs = list(enumerate_sequences(ocp, 4))
    assert len(seqs) > 20
    for seq in seqs:
        assert np.array_equal(guess_times(ocp, seq, ev), direct(seq)), seq
    assert len(rc._PSI[id(ev)][1]) == len(ocp.guards)  # one psi per guard, not per call
