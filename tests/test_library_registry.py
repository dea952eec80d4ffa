"""Adding a library problem is one file: a function with the :func:`library_problem`
decorator (docs/architecture.rst, "Add a problem")."""

from __future__ import annotations

import casadi as ca
import pytest

import hybridoc
from hybridoc.problems import library_names, load_problem
from hybridoc.problems.library import LIBRARY, describe, library_problem
from hybridoc.problems.library.registry import NOTES


@pytest.fixture
def restore_library():
    saved, notes = dict(LIBRARY), dict(NOTES)
    yield
    LIBRARY.clear()
    LIBRARY.update(saved)
    NOTES.clear()
    NOTES.update(notes)


def test_a_new_problem_is_one_decorated_function(restore_library):
    # what the new file problems/library/drifting_cart.py would hold
    @library_problem("drifting-cart-3", note="three seconds", horizon=3.0)
    @library_problem("drifting-cart")
    def drifting_cart(horizon: float = 1.0) -> hybridoc.HybridOCP:
        """A cart pushed to the origin, no events."""
        s, u = ca.SX.sym("s", 2), ca.SX.sym("u", 1)
        return hybridoc.HybridOCP.from_expressions(
            s, u, f=ca.vertcat(s[1], u), L=u**2, phi=100 * ca.sumsqr(s), guards=[],
            x0=[1.0, 0.0], horizon=horizon, steps=20, name="drifting-cart",
        )  # fmt: skip

    assert {"drifting-cart", "drifting-cart-3"} <= set(library_names())
    assert load_problem("drifting-cart-3").horizon == 3.0
    assert describe("drifting-cart-3") == "A cart pushed to the origin, no events. (three seconds)"
    # every method and the judge take it by name
    sol = hybridoc.solve("drifting-cart", "dt")
    assert sol.success and sol.cost < hybridoc.evaluate("drifting-cart").cost
    with pytest.raises(ValueError, match="registered twice"):
        library_problem("drifting-cart")(drifting_cart)


def test_the_built_ins_are_registered_by_their_modules():
    assert set(LIBRARY) >= {"bouncing-ball", "bouncing-ball-2", "ball-on-slope",
                            "juggling-paddle", "pendulum-wall"}  # fmt: skip
    assert LIBRARY["bouncing-ball-2"]().meta["params"]["bounces"] == 2
