"""``hybridoc compare-trajectory``: another simulator's trajectory against the judge's
(issue #19; being built)."""

from __future__ import annotations

from typing import Any


def register(sub: Any) -> None:
    """Add ``compare-trajectory`` (not yet)."""
