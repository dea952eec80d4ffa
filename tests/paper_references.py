"""The default references of the paper's two scenes, solved once per test process.

test_reference and test_transcription both compare with ``solve_reference`` of the library's
``single-collision`` and ``multiple-collision`` scenes, sequence discovery included. As
module fixtures, every pytest-xdist worker that ran a test of either module solved them
again for each module (about 6 s and 20 s at load 8); here a worker solves each once.
Tests only read these solutions: nothing may change them.
"""

from __future__ import annotations

import functools

import hybridoc
from hybridoc.reference import solve_reference
from hybridoc.solution import Solution


@functools.cache
def paper_reference(name: str) -> Solution:
    """The default reference (discovery included) of the library scene ``name``, once."""
    return solve_reference(hybridoc.load_scene(name))
