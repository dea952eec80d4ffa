"""The README's headline numbers are what the code computes.

README.md states the exact optima of the paper's two problems once; the documentation
refers to them or computes them. These tests read the numbers from the README itself and
recompute them by the quickest route: the reference with the event sequence given.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import hybridoc

README = (Path(__file__).resolve().parents[1] / "README.md").read_text()


def _headline(pattern: str) -> float:
    match = re.search(pattern, README, flags=re.S)
    assert match, f"README no longer states {pattern!r}"
    return float(match.group(1))


@pytest.mark.parametrize(
    ("problem", "sequence", "pattern"),
    [
        ("single-collision", ["ball1|ball2"], r"`single-collision`: (0\.\d{9,})"),
        (
            "multiple-collision",
            ["ball1|ball2", "ball2|wall", "ball1|ball2"],
            r"`multiple-collision`: (0\.\d{9,}) with \*\*three\*\* events",
        ),
        (
            "multiple-collision",
            ["ball1|ball2", "ball2|wall"],
            r"one-collision-one-bounce\s+extremal (0\.\d{9,})",
        ),
    ],
    ids=["single-collision", "multiple-collision-three-events", "multiple-collision-two-events"],
)
def test_readme_optimum(problem: str, sequence: list[str], pattern: str) -> None:
    stated = _headline(pattern)
    sol = hybridoc.solve(problem, "reference", sequence=sequence)
    # the extremal of the given sequence; that it is the optimum is the discovery's claim
    # (tests/test_reference.py)
    assert sol.status is hybridoc.Status.EXTREMAL, sol.message
    assert sol.sequence == sequence
    assert sol.cost == pytest.approx(stated, rel=0, abs=1e-12)


def test_readme_gap_between_the_two_extremals() -> None:
    three = _headline(r"`multiple-collision`: (0\.\d{9,}) with")
    two = _headline(r"one-collision-one-bounce\s+extremal (0\.\d{9,})")
    stated = _headline(r"events \(ball 1 strikes.*?(\d+\.\d)% below")
    assert round(100 * (two - three) / two, 1) == stated


def test_readme_python_example_output() -> None:
    # the printed output of the README's first example
    ev = hybridoc.evaluate("single-collision")
    assert repr(ev.cost) in README
    assert str(ev.sequence) in README
