"""Every tutorial of the gallery (docs/tutorials/NN_*.py) runs as a test.

The documentation build executes the same scripts (sphinx-gallery), so a tutorial that
breaks fails ``make test`` before it fails ``make docs``. The tests set
``HYBRIDOC_TUTORIAL_QUICK=1``: tutorials that search or iterate a lot run a smaller version
of themselves; the documentation runs the full one.
"""

from __future__ import annotations

import os
import runpy
from pathlib import Path

import pytest

# No background C compilation: a quick tutorial is over before most of its compilations
# pay. Side by side, sequential, fresh code cache: the module took 83.3 s of CPU with them
# (30 compilations, 37 s of the compiler) against 54.7 s without, the same 54 s wall.
pytestmark = pytest.mark.usefixtures("virtual_machine")

TUTORIALS = sorted(
    (Path(__file__).resolve().parents[1] / "docs" / "tutorials").glob("[0-9][0-9]_*.py")
)


def test_tutorials_found():
    assert len(TUTORIALS) >= 5, TUTORIALS


@pytest.mark.parametrize("path", TUTORIALS, ids=lambda p: p.stem)
def test_tutorial_runs(path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import matplotlib

    matplotlib.use("Agg")
    monkeypatch.setenv("HYBRIDOC_TUTORIAL_QUICK", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.chdir(tmp_path)  # anything a tutorial writes stays out of the tree
    runpy.run_path(str(path), run_name="__main__")
    import matplotlib.pyplot as plt

    plt.close("all")
    assert os.environ["HYBRIDOC_TUTORIAL_QUICK"] == "1"
