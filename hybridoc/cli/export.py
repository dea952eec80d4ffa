"""``hybridoc export``: a problem in other simulators' formats (issue #19; being built)."""

from __future__ import annotations

from typing import Any


def register(sub: Any) -> None:
    """Add ``export`` (no subcommand yet)."""
