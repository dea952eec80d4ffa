"""Shared test settings: the hypothesis profiles of the property tests.

``ci`` (the default): a fixed seed (derandomized) and a bounded number of examples, so that
``make test`` stays within its time budget and is reproducible. ``fuzz``: a hundred times
more examples with random seeds (``make fuzz`` sets ``HYBRIDOC_FUZZ=1``).
"""

from __future__ import annotations

import os
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

# One BLAS thread per test worker (set before numpy is imported): pytest-xdist runs a
# worker per core, and OpenBLAS's own threads (numpy's, scipy's and CasADi's IPOPT/MUMPS) then
# contend with the other worker and spin; side by side on 2 busy cores, 50 solves of a
# 300 x 300 system took 17 s with OpenBLAS's default of two threads against 0.6 s with one.
for _blas in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_blas, "1")
# tests import helper modules (the oracle, the library's independent optima) by name
sys.path.insert(0, str(Path(__file__).resolve().parent))
# The hot CasADi functions (the multi-start's batched loss, the judge's kernels) compiled to
# C in the background, as for a user: their virtual machine made the default references of
# the disc scenes the suite's largest cost. One cache for the session's workers (and later
# runs), kept out of the user's own. From a cold cache, side by side: test_trust_regressions
# and test_global_reference 144 s of CPU against 186 s on the virtual machine (compilation
# included). HYBRIDOC_CODEGEN=0 turns it off.
os.environ.setdefault("HYBRIDOC_CODEGEN", "1")
os.environ.setdefault(
    "HYBRIDOC_CACHE", str(Path(tempfile.gettempdir()) / f"hybridoc-tests-{os.getuid()}")
)

FUZZ = os.environ.get("HYBRIDOC_FUZZ", "") not in ("", "0")
#: examples per property test at CI size; ``make fuzz`` runs FUZZ_FACTOR times more
FUZZ_FACTOR = 100

settings.register_profile(
    "ci",
    derandomize=True,
    deadline=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
settings.register_profile(
    "fuzz",
    derandomize=False,
    deadline=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
settings.load_profile("fuzz" if FUZZ else "ci")


def examples(n: int) -> int:
    """The number of examples of a property test: ``n`` at CI size, 100 ``n`` when fuzzing."""
    return n * FUZZ_FACTOR if FUZZ else n


@pytest.fixture(scope="module")
def virtual_machine() -> Iterator[None]:
    """No background C compilation for a module (``pytestmark =
    pytest.mark.usefixtures("virtual_machine")``): where nearly every call is a new
    structure (random examples), each would be compiled once for nothing."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HYBRIDOC_CODEGEN", "0")
        yield


@pytest.fixture
def compiling(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Background C compilation on, into a cache of the test's own (skipped without cc)."""
    from hybridoc.solvers import codegen

    if codegen.compiler() is None:
        pytest.skip("no C compiler on this machine")
    monkeypatch.setenv("HYBRIDOC_CODEGEN", "1")
    monkeypatch.setenv("HYBRIDOC_CACHE", str(tmp_path / "cache"))


#: test modules with the longest tests (tutorials, cross-validations, regression scenes):
#: started first, so that pytest-xdist's workers do not wait on one of them at the end
LONG_FIRST = ("test_tutorials.py", "test_validation.py", "test_trust_regressions.py")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Run the modules of :data:`LONG_FIRST` first (a stable sort: order within is kept)."""
    items.sort(key=lambda item: item.path.name not in LONG_FIRST)


@pytest.fixture
def registered() -> Iterator[object]:
    """Register test methods for one test (removed after it): ``registered(method)``."""
    from hybridoc.methods import register_method, unregister_method

    names: list[str] = []

    def add(method: object) -> None:
        register_method(method)
        names.append(method.name)

    yield add
    for name in names:
        unregister_method(name)
