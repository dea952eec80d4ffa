"""The reference's enumeration of event sequences (part of :mod:`hybridoc.reference.search`).

Every feasible sequence, length by length and by lower bound within a length
(:func:`run_enumeration`), each screened by Newton from the disc NLP or the warm starts
(``_search_one``) in worker processes where the platform can fork; the screens of an
explicit ``search`` start before the sources (:func:`start_screens`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from hybridoc.cores import usable_cores
from hybridoc.errors import ConvergenceError, EvaluationError
from hybridoc.evaluation import Evaluation
from hybridoc.ocp import HybridOCP
from hybridoc.reference.candidates import (
    default_depth,
    enumerate_sequences,
    guess_times,
    lower_bound,
)
from hybridoc.reference.result import make_result
from hybridoc.reference.search.book import (
    IMPOSSIBLE,
    MAX_PROOF_DEPTH,
    Book,
    Guess,
    Run,
    exhaustive_length,
    n_events,
    note_source,
    too_long,
)
from hybridoc.reference.sequence import SCREEN_NLP_ITER, solve_sequence
from hybridoc.reference.shooting import (
    has_closed_form_phases,
    newton,
    prepare,
    refine,
    shooting_system,
)
from hybridoc.reference.units import cost_shown as _J

MAX_WORKERS = 8
"""Worker processes of the search over sequences, at most (one per usable core)."""


_SEARCH_STATE: dict[str, Any] = {}

SCREEN_WAIT = 60.0
"""Seconds the search waits for a worker's screen with nothing else to do before it runs the
screen itself (a screen takes well under a second; a worker process forked from threads
could hang)."""
# a screen's claim (one signed byte per screen, shared with the worker processes): free,
# this process's, or the number of the worker that runs it (1, 2, ...)
_FREE, _PARENT = 0, -1


def _screen_worker(
    number: int, tasks: list[list[str]], claims: Any, lock: Any, results: Any
) -> None:
    """Worker ``number`` of :class:`_EarlyScreens`: the first screen nobody has claimed,
    until none is left; each outcome goes to ``results`` as ``(index, outcome)``, ``(index,
    None)`` where :func:`_search_one` raised (the parent runs it again and meets the error
    itself)."""
    from hybridoc.children import die_with_parent

    die_with_parent()  # a SIGKILLed search must not leave its screens running
    # the screening NLPs built here, while the parent solves the guess's candidates (it
    # builds those of the lengths it screens itself when it joins)
    prepare(_SEARCH_STATE["ocp"], {len(seq) for seq in tasks}, max_iter=SCREEN_NLP_ITER)
    first = 0  # claims only ever leave _FREE: the first free screen moves forward
    while True:
        with lock:
            while first < len(tasks) and claims[first] != _FREE:
                first += 1
            if first == len(tasks):
                break
            i = first
            claims[i] = number
        try:
            out: _Outcome | None = _search_one(tasks[i])
        except Exception:
            out = None
        results.put((i, out))


class _EarlyScreens:
    """The screens of an explicit ``search`` on a disc scene, started before the guess's
    candidates and the sources in worker processes (one per usable core but this one's, at
    most :data:`MAX_WORKERS` - 1), and shared with this process once the enumeration needs
    their outcomes: on two cores the worker screens while the sources run here, then both
    screen (multiple-collision, ``--search 5``: about 3 s of CPU here for the guess's
    candidates and the sources, 5.5 s of screens).

    A screen's outcome (:func:`_search_one`) depends on the problem, the guess, ``tol``,
    ``rtol`` and the warm-start sources alone, never on what the discovery has found or on
    the process that runs it, so :func:`run_enumeration` takes it as it is, in its own order and
    with its own pruning and skipping: the landscape is the one the screens run in order
    would give. Screened: every sequence of up to ``search`` events the enumeration lists
    whose lower bound is below the best cost known at the start (the bound it prunes with
    only falls), in the enumeration's order, the guess's candidates last (solved here
    first, they need no screen unless they fail). Each screen is claimed once, by a worker
    or by this process (:meth:`outcomes`); a screen the enumeration skips is wasted (on
    multiple-collision a few of 146: the sequences the sources solve first)."""

    def __init__(
        self,
        tasks: list[list[str]],
        claims: Any,
        lock: Any,
        results: Any,
        workers: list[Any],
    ) -> None:
        self.tasks = tasks
        self.index = {tuple(seq): i for i, seq in enumerate(tasks)}
        self.claims, self.lock, self.results, self.workers = claims, lock, results, workers
        self.done: dict[int, _Outcome] = {}
        self.by_worker = 0  # outcomes the workers gave

    @classmethod
    def start(
        cls,
        ocp: HybridOCP,
        run: Run,
        book: Book,
        guess: Guess,
        cands: Sequence[Sequence[tuple[str, float]]] = (),
    ) -> _EarlyScreens | None:
        """Start the workers (or ``None``: no explicit search, not a disc scene, one usable
        core, no ``fork``, or only a handful of sequences)."""
        import multiprocessing as mp

        workers = min(usable_cores(), MAX_WORKERS) - 1
        if (
            not run.search
            or not has_closed_form_phases(ocp)
            or workers < 1
            or "fork" not in mp.get_all_start_methods()
        ):
            return None
        best = book.best_bound()
        later = {tuple(n for n, _ in c) for c in cands}
        by_length: list[list[tuple[float, list[str]]]] = [[] for _ in range(run.search + 1)]
        for seq in enumerate_sequences(ocp, run.search):
            lb = lower_bound(ocp, seq)
            if lb < best:  # the enumeration prunes the others (an infinite bound too)
                by_length[len(seq)].append((lb, seq))
        # the enumeration's order: length by length, by lower bound within one
        order = [seq for rows in by_length for _, seq in sorted(rows, key=lambda r: r[0])]
        # the guess's candidates last (stable: the order kept otherwise)
        tasks = sorted(order, key=lambda q: tuple(q) in later)
        if len(tasks) <= 4:
            return None
        ctx = mp.get_context("fork")
        claims = ctx.RawArray("b", len(tasks))
        lock = ctx.Lock()
        results = ctx.Queue()
        _SEARCH_STATE.update(
            ocp=ocp, u0=guess.controls, ev=guess.evaluation, tol=book.tol, rtol=book.rtol,
            starters=book.starters,
        )  # fmt: skip
        procs = []
        try:
            for number in range(1, workers + 1):
                p = ctx.Process(
                    target=_screen_worker,
                    args=(number, tasks, claims, lock, results),
                    daemon=True,
                )
                p.start()  # forks with the state above
                procs.append(p)
        finally:
            _SEARCH_STATE.clear()
        book.say(f"enumeration: {len(tasks)} screens started before the sources")
        return cls(tasks, claims, lock, results, procs)

    def withdraw(self, keys: Any) -> None:
        """The screens of these sequences are not wanted (solved before the enumeration):
        no worker starts them."""
        with self.lock:
            for key in keys:
                i = self.index.get(tuple(key))
                if i is not None and self.claims[i] == _FREE:
                    self.claims[i] = _PARENT

    def _claim(self, i: int) -> bool:
        with self.lock:
            if self.claims[i] != _FREE:
                return False
            self.claims[i] = _PARENT
            return True

    def _receive(self, timeout: float | None) -> bool:
        """Take one outcome from the workers (waiting at most ``timeout`` seconds; ``None``:
        do not wait); ``False`` when none came."""
        import queue

        try:
            if timeout is None:
                i, out = self.results.get_nowait()
            else:
                i, out = self.results.get(timeout=timeout)
        except queue.Empty:
            return False
        if out is None:
            # _search_one raised in the worker: run here when wanted (_get), where the error
            # surfaces
            with self.lock:
                self.claims[i] = _PARENT
        else:
            self.by_worker += 1
            self.done[i] = out
        return True

    def _lost(self) -> None:
        """The screens of a worker that died without giving their outcomes: run here (one
        that ran out of screens has given all of its own and exited with code 0)."""
        dead = {n for n, p in enumerate(self.workers, 1) if p.exitcode not in (None, 0)}
        if not dead:
            return
        while self._receive(None):
            pass
        for i in range(len(self.tasks)):
            if self.claims[i] in dead and i not in self.done:
                self.claims[i] = _PARENT  # run here when wanted (_get)

    def _get(self, i: int, ahead: list[int]) -> _Outcome:
        """Screen ``i``'s outcome: a worker's, or run here when no worker has started it;
        while a worker runs it, this process runs the free screens of ``ahead`` (the
        enumeration's next ones), then of the others in order. A worker that gives no
        outcome for :data:`SCREEN_WAIT` seconds while nothing else is left to do here is
        taken for stuck: the screen is run here (the same outcome)."""
        waited = 0.0
        while i not in self.done:
            if waited >= SCREEN_WAIT:
                with self.lock:
                    self.claims[i] = _PARENT
            while self._receive(None):
                pass
            if i in self.done:
                break
            # claimed here and not done: withdrawn, or lost by a worker
            if self._claim(i) or self.claims[i] == _PARENT:
                self.done[i] = _search_one(self.tasks[i])
                break
            nxt = next((j for j in [*ahead, *range(len(self.tasks))] if self._claim(j)), None)
            if nxt is not None:
                self.done[nxt] = _search_one(self.tasks[nxt])
            elif not self._receive(1.0):
                waited += 1.0
                self._lost()
        return self.done.pop(i)

    def outcomes(
        self,
        ocp: HybridOCP,
        book: Book,
        guess: Guess,
        todo: list[list[str]],
        deadline: float | None = None,
    ) -> list[_Outcome]:
        """:func:`_search_one` of each sequence of ``todo``, in its order (:meth:`_get`);
        none after ``deadline`` (``time.perf_counter()``, the time limit): the outcomes
        then stop short of ``todo``."""
        _SEARCH_STATE.update(
            ocp=ocp, u0=guess.controls, ev=guess.evaluation, tol=book.tol, rtol=book.rtol,
            starters=book.starters,
        )  # fmt: skip
        idx = [self.index.get(tuple(seq)) for seq in todo]
        out: list[_Outcome] = []
        try:
            for pos, (seq, i) in enumerate(zip(todo, idx, strict=True)):
                if deadline is not None and time.perf_counter() >= deadline:
                    break
                if i is None:
                    out.append(_search_one(seq))
                else:
                    ahead = [j for j in idx[pos + 1 :] if j is not None]
                    out.append(self._get(i, ahead))
                book.progress.count(len(out), len(todo), "sequences")
        finally:
            _SEARCH_STATE.clear()
        return out

    def close(self) -> None:
        """Withdraw the screens nobody has claimed and end the workers (a screen one of them
        still runs is not wanted)."""
        with self.lock:
            for i in range(len(self.tasks)):
                if self.claims[i] == _FREE:
                    self.claims[i] = _PARENT
        for p in self.workers:
            if p.is_alive():
                p.terminate()
            p.join()
        self.results.close()
        self.results.cancel_join_thread()


def start_screens(
    ocp: HybridOCP,
    run: Run,
    book: Book,
    guess: Guess,
    cands: Sequence[Sequence[tuple[str, float]]] = (),
) -> _EarlyScreens | None:
    """The screens of an explicit ``search`` on a disc scene, started in worker processes
    before the guess's candidates and the sources (:meth:`_EarlyScreens.start`), or
    ``None``."""
    return _EarlyScreens.start(ocp, run, book, guess, cands)


# (sequence, point, (steps per arc, arcs) of its system, reason, seconds, final time)
_Outcome = tuple[list[str], np.ndarray | None, tuple[Any, Any] | None, str, float, float]


def _search_one(seq: list[str]) -> _Outcome:
    """A worker: Newton from the disc NLP (or the transcription) for one sequence."""
    ocp, u0, ev, tol, rtol, starters = (
        _SEARCH_STATE[k] for k in ("ocp", "u0", "ev", "tol", "rtol", "starters")
    )
    t0 = time.perf_counter()
    try:
        res, why = solve_sequence(
            ocp, seq, guess_times(ocp, seq, ev), u0, estimate=False,
            guess_ev=None if has_closed_form_phases(ocp) else ev, starters=starters, tol=tol,
            screen=True, rtol=rtol,
        )  # fmt: skip
    except (ConvergenceError, EvaluationError, np.linalg.LinAlgError) as exc:
        res, why = None, str(exc)
    if res is None:
        return seq, None, None, why, time.perf_counter() - t0, ocp.horizon
    # the steps per phase (and a free final time) travel with the point: a worker's cache is
    # not the parent's
    return seq, res.z, res.system.spec, why, time.perf_counter() - t0, res.horizon


def run_enumeration(
    ocp: HybridOCP, run: Run, book: Book, guess: Guess, early: _EarlyScreens | None = None
) -> None:
    """Every feasible sequence, length by length, up to the scene's depth
    (:func:`~hybridoc.reference.candidates.default_depth`) or ``search`` if longer: within
    one length in the order of the lower bound, each skipped where the bound is not below
    the cheapest verified extremal or known control, solved in worker processes (one per
    core, at most :data:`MAX_WORKERS`) where the platform can fork. Lengths beyond
    ``search`` stop when the budget is spent; ``book.exhaustive`` is the longest length
    completed.

    A ``success`` needs every sequence of up to one event more than the optimum's own
    covered (:func:`proof`): while the lengths so far are covered and the best verified
    extremal has ``depth`` events or more, the enumeration goes on to its length plus one
    (at most :data:`MAX_PROOF_DEPTH`; the budget stops these lengths too)."""
    t0 = time.perf_counter()
    if early is not None:
        early.withdraw(book.results)
    explicit = run.search or 0
    depth = max(explicit, default_depth(ocp))
    by_length = _by_length(ocp, book, depth)
    book.best_verified()  # the cheapest verified extremal so far bounds the enumeration
    solved = 0
    length = -1
    while True:
        length += 1
        if length > depth and depth < MAX_PROOF_DEPTH:
            # the proof needs one length beyond the optimum's: go on while it can succeed
            # (every length so far covered)
            best_res = book.best_verified()
            need = 0 if best_res is None else len(best_res.sequence) + 1
            if need > depth and exhaustive_length(book) == depth:
                depth = min(need, MAX_PROOF_DEPTH)
                book.say(f"enumeration: extended to {n_events(depth)} (the best has {need - 1})")
                by_length = _by_length(ocp, book, depth)
        if length > depth:
            break
        seqs = by_length[length]
        book.check_limit()
        bounded = length > explicit  # the budget may stop this length
        if bounded and book.left() <= 0:
            book.budget_stopped = True
            break
        todo = _to_solve(ocp, book, seqs, book.best_bound())
        if not todo:
            book.exhaustive = length  # every sequence of this length solved or pruned before
            continue
        book.progress.stage(f"enumeration of {n_events(length)}: {len(todo)} to solve")
        seqs_todo = [seq for _, seq in todo]
        hard = None if math.isinf(book.hard_deadline) else book.hard_deadline
        if early is not None and not bounded:
            outcomes = early.outcomes(ocp, book, guess, seqs_todo, deadline=hard)
        else:
            outcomes = _search_outcomes(
                ocp, book, seqs_todo, guess.controls, guess.evaluation,
                deadline=book.deadline if bounded else hard,
            )  # fmt: skip
        solved += len(outcomes)
        for seq, z, levels, why, took, horizon in outcomes:
            _record(ocp, book, seq, z, levels, why, took, horizon)
        if len(outcomes) == len(todo):
            _retry_failed(ocp, run, book, guess, [tuple(q) for q in seqs_todo], bounded)
        if len(outcomes) < len(todo):
            book.check_limit()
            book.budget_stopped = True
            book.say(
                f"enumeration: the budget of {run.budget:g} s is spent after {len(outcomes)} "
                f"of {len(todo)} sequences of {length} events"
            )
            break
        book.exhaustive = length
        if run.search is not None:
            for key in list(book.results):
                book.verify(key)  # the landscape's verdicts
        else:
            book.best_verified()
    note_source(book, "enumeration", "reference", solved, t0, depth=depth)


def _to_solve(
    ocp: HybridOCP, book: Book, seqs: list[list[str]], best: float
) -> list[tuple[float, list[str]]]:
    """The sequences of one length that the enumeration solves, ``(lower bound, sequence)``
    by lower bound: not those solved before, nor those whose bound is not below ``best``
    (the cheapest verified extremal or known control; pruned here), nor those that failed
    before and are pruned or too long."""
    todo: list[tuple[float, list[str]]] = []
    for seq in seqs:
        key = tuple(seq)
        book.proposed.add(key)
        if key in book.results:
            continue  # proposed and solved before
        lb = lower_bound(ocp, seq)
        if key in book.reasons:
            # failed before (a source's start): a valid bound still covers it; else the
            # enumeration's own start gets a try
            if lb >= best and book.reasons[key] != too_long(len(key)):
                book.pruned.add(key)
                book.reasons[key] = f"pruned: its cost is at least {lb:.6g} >= {best:.6g}"
                continue
            if key in book.pruned or book.reasons[key] == too_long(len(key)):
                continue
        if lb >= best:
            book.pruned.add(key)
            book.reasons[key] = (
                IMPOSSIBLE
                if math.isinf(lb)
                else f"pruned: its cost is at least {lb:.6g} >= {best:.6g}"
            )
            book.origins[key] = "enumeration"
            book.times[key] = 0.0
            continue
        todo.append((lb, seq))
    todo.sort(key=lambda item: item[0])
    return todo


def _retry_failed(
    ocp: HybridOCP,
    run: Run,
    book: Book,
    guess: Guess,
    keys: list[tuple[str, ...]],
    bounded: bool,
) -> None:
    """A second start for the enumerated sequences of a disc scene whose screen found no
    extremal, while the proof may still need them (no longer than the best verified
    extremal plus one): the full solve (:func:`~hybridoc.reference.sequence.solve_sequence` without
    ``screen``: the disc NLP to convergence, then the warm starts from the guess, such as
    the transcription with the sequence fixed). Multiple-collision's ``ball1|ball2`` has no
    screened extremal, and one from the full solve. Stops when the budget is spent (a
    length beyond ``search``) or at the time limit."""
    if not has_closed_form_phases(ocp):
        return  # a generic problem's screen already ran the warm starts from the guess
    best = book.best_verified()
    if best is None:
        return
    need = len(best.sequence) + 1
    ev = guess.evaluation
    for key in keys:
        if key in book.results or key in book.pruned or len(key) > need:
            continue
        if bounded and book.left() <= 0:
            book.budget_stopped = True
            return
        lb, bound = lower_bound(ocp, key), book.best_bound()
        if lb >= bound:  # excluded by what was found since its screen
            book.pruned.add(key)
            book.reasons[key] = f"pruned: its cost is at least {lb:.6g} >= {bound:.6g}"
            continue
        book.attempt(
            key, guess_times(ocp, key, ev), guess.controls, "enumeration (full solve)",
            estimate=False, guess_ev=ev, retry=True,
        )  # fmt: skip


def _by_length(ocp: HybridOCP, book: Book, depth: int) -> list[list[list[str]]]:
    """The feasible sequences of up to ``depth`` events, by length (kept in ``book``)."""
    book.depth = depth
    by_length: list[list[list[str]]] = [[] for _ in range(depth + 1)]
    for seq in enumerate_sequences(ocp, depth):
        by_length[len(seq)].append(seq)
    book.enumerated = [[tuple(q) for q in seqs] for seqs in by_length]
    return by_length


def _record(
    ocp: HybridOCP,
    book: Book,
    seq: list[str],
    z: np.ndarray | None,
    levels: tuple[Any, Any] | None,
    why: str,
    took: float,
    horizon: float,
) -> None:
    """One enumerated sequence's outcome: its extremal (Newton polishes the worker's point
    here, in one step, at the worker's steps per phase and final time) or the reason it has
    none."""
    key = tuple(seq)
    book.screened.add(key)
    book.origins.setdefault(key, "enumeration")
    book.times[key] = book.times.get(key, 0.0) + took
    if z is None:
        book.reasons[key] = why
        book.say(f"{seq} (enumeration): {why}")
        book.from_known(key)
        return
    # a free final time comes back fixed at the value found (result.make_result)
    at = ocp.replace(horizon=horizon) if ocp.free_horizon else ocp
    steps, arcs = levels if levels is not None else (None, None)
    S = shooting_system(at, seq, steps, free=False, arcs=arcs)
    nr = newton(S, z, tol=book.tol)
    if not nr.converged:
        book.reasons[key] = f"Newton from the enumeration's point: residual {nr.residual:.2e}"
        book.from_known(key)
        return
    ref = refine(S, nr, rtol=book.rtol, tol=book.tol, verbose=book.verbose)
    if not ref.ok:
        book.reasons[key] = ref.reason
        book.from_known(key)
        return
    res = make_result(ref.system, ref.newton, "search", ref.error)
    book.start_costs.setdefault(key, []).append(float(res.cost))
    old = book.results.get(key)
    if old is None or res.cost < old.cost - 1e-12 * abs(old.cost):
        book.results[key] = res
        book.verdicts.pop(key, None)
    book.say(f"{seq} (enumeration): cost {_J(res.cost):.12g}")


def _search_outcomes(
    ocp: HybridOCP,
    book: Book,
    todo: list[list[str]],
    u0: np.ndarray,
    ev: Evaluation,
    *,
    deadline: float | None = None,
) -> list[_Outcome]:
    """:func:`_search_one` on the sequences of ``todo`` in order, counted on
    ``book.progress``; with a ``deadline`` (``time.perf_counter()``), no sequence starts
    after it (the outcomes then stop short of ``todo``)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from hybridoc.children import die_with_parent

    def spent() -> bool:
        return deadline is not None and time.perf_counter() >= deadline

    _SEARCH_STATE.update(
        ocp=ocp, u0=u0, ev=ev, tol=book.tol, rtol=book.rtol, starters=book.starters
    )
    workers = min(usable_cores(), MAX_WORKERS)
    outcomes: list[_Outcome] = []
    # the screening NLP of each length once, before the workers fork (each would compile it)
    prepare(ocp, {len(seq) for seq in todo}, max_iter=SCREEN_NLP_ITER)
    try:
        if workers > 1 and len(todo) > 4 and "fork" in mp.get_all_start_methods():
            with ProcessPoolExecutor(
                workers, mp_context=mp.get_context("fork"), initializer=die_with_parent
            ) as pool:
                # a few sequences ahead of the workers, so that the deadline stops soon
                pending = [pool.submit(_search_one, seq) for seq in todo[: 2 * workers]]
                nxt = len(pending)
                while pending:
                    outcomes.append(pending.pop(0).result())
                    book.progress.count(len(outcomes), len(todo), "sequences")
                    if spent():
                        for f in pending:
                            f.cancel()
                        # what already ran still counts, in order
                        outcomes += [f.result() for f in pending if not f.cancelled()]
                        break
                    if nxt < len(todo):
                        pending.append(pool.submit(_search_one, todo[nxt]))
                        nxt += 1
        else:
            for seq in todo:
                if spent():
                    break
                outcomes.append(_search_one(seq))
                book.progress.count(len(outcomes), len(todo), "sequences")
    finally:
        _SEARCH_STATE.clear()
    return outcomes
