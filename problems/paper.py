"""The numbers of the paper hybridoc starts from (``../shared/seed/``), each stated once.

Everything that compares with the paper (``hybridoc ablation``, ``compare-contacts``,
``gradcheck``, the benchmarks, the docs) reads them from here.
"""

from __future__ import annotations

__all__ = [
    "EXACT_OPTIMUM",
    "PAPER_OPTIMUM",
    "PAPER_SETTINGS",
    "PAPER_TABLE1",
    "TOI_LABELS",
]

PAPER_SETTINGS: dict[str, tuple[float, int]] = {
    "single-collision": (200.0, 500),
    "multiple-collision": (50.0, 1500),
}
"""The paper's plain gradient descent (section 5): ``problem -> (learning rate, iterations)``."""

PAPER_TABLE1: dict[str, dict[str, float]] = {
    "none": {"single-collision": 0.3616, "multiple-collision": 0.5261},
    "position": {"single-collision": 0.3949, "multiple-collision": 0.5841},
    "velocity": {"single-collision": 0.4797, "multiple-collision": 0.6142},
    "both": {"single-collision": 0.3151, "multiple-collision": 0.3785},
}
"""The paper's Table 1: the final loss of its plain gradient descent, by time-of-impact
setting and problem."""

PAPER_OPTIMUM: dict[str, float] = {"single-collision": 0.3115, "multiple-collision": 0.3737}
"""The optimal losses the paper reports from its grid search (Table 1)."""

EXACT_OPTIMUM: dict[str, float] = {
    "single-collision": 0.311416870358,
    "multiple-collision": 0.356279430543,
}
"""The exact optima (``hybridoc reference``, to the digits printed); the tests check that
the reference reproduces them."""

TOI_LABELS: dict[str, str] = {
    "none": "no TOI",
    "position": "TOI-Position",
    "velocity": "TOI-Velocity",
    "both": "TOI-Position + TOI-Velocity",
}
"""The paper's names of the time-of-impact settings."""
