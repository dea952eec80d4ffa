"""An external gradient against the exact adjoint (hybridoc.workflows.gradcompare): the exact
gradient against itself, central finite differences of the judged cost, and perturbations of
known cosine and error, on a disc scene and on a problem that is not made of discs."""

from __future__ import annotations

import math

import numpy as np
import pytest

import hybridoc
from hybridoc.io import substep_problem
from hybridoc.problems.library.bouncing_ball import bouncing_ball
from hybridoc.workflows.gradcompare import (
    PHASES,
    GradientError,
    cell_phases,
    compare_gradient,
    gradient_figure,
)


@pytest.fixture(scope="module")
def single():
    # a coarse grid keeps the finite differences cheap; the event stays inside a cell
    return hybridoc.problem.as_ocp("single-collision").replace(steps=16)


@pytest.fixture(scope="module")
def ball():
    return bouncing_ball(bounces=2, steps=24)


def central_differences(ocp, u, h=1e-6):
    g = np.zeros_like(u)
    for idx in np.ndindex(*u.shape):
        up, um = u.copy(), u.copy()
        up[idx] += h
        um[idx] -= h
        g[idx] = (hybridoc.evaluate(ocp, up).cost - hybridoc.evaluate(ocp, um).cost) / (2 * h)
    return g


@pytest.mark.parametrize("name", ["single", "ball"])
def test_exact_against_itself(request, name):
    ocp = request.getfixturevalue(name)
    exact = hybridoc.gradient(ocp).d_controls
    for given in (exact, exact.ravel()):
        c = compare_gradient(ocp, given)
        assert c.cosine == pytest.approx(1.0, abs=1e-15)
        assert c.relative_error == 0.0 and c.overall.max_abs_error == 0.0
        assert all(p.error_norm == 0.0 and p.error_share == 0.0 for p in c.phases + c.components)
    assert sum(p.cells for p in c.phases) == ocp.steps
    assert [p.name for p in c.components] == list(ocp.control_labels)


@pytest.mark.parametrize("name", ["single", "ball"])
def test_central_differences_agree(request, name):
    ocp = request.getfixturevalue(name)
    u = ocp.u_guess
    assert hybridoc.evaluate(ocp, u).events  # the differences cross the event cells
    c = compare_gradient(ocp, central_differences(ocp, u), u)
    assert c.cosine > 1 - 1e-10
    assert c.relative_error < 1e-5
    assert len(c.events) >= 1


def test_perturbation_of_known_cosine(single):
    exact = hybridoc.gradient(single).d_controls
    te = hybridoc.evaluate(single).events[0].time
    t = single.time_grid()
    # w orthogonal to the exact gradient with |w| = |g*|, only in the cells after the event:
    # cosine 1/sqrt(2), relative error 1, all of the error there
    after = t[:-1] > te
    rng = np.random.default_rng(5)
    e_after = exact[after]
    w_after = rng.normal(size=e_after.shape)
    w_after -= np.sum(w_after * e_after) / np.sum(e_after * e_after) * e_after
    w = np.zeros_like(exact)
    w[after] = w_after * np.linalg.norm(exact) / np.linalg.norm(w_after)
    assert abs(np.sum(w * exact)) < 1e-14 * np.sum(exact * exact)
    c = compare_gradient(single, exact + w)
    assert c.cosine == pytest.approx(1 / math.sqrt(2), rel=1e-12)
    assert c.relative_error == pytest.approx(1.0, rel=1e-12)
    parts = {p.name: p for p in c.phases}
    # the cells: before the event those that end by it, one that holds it, the rest after
    n_before = int(np.sum(t[1:] <= te))
    assert parts["before the first event"].cells == n_before
    assert parts["cells with an event"].cells == 1
    assert parts["after the last event"].cells == single.steps - n_before - 1
    assert parts["before the first event"].error_norm == 0.0
    assert parts["after the last event"].error_share == pytest.approx(1.0, rel=1e-12)
    # scaling the exact gradient: cosine 1, relative error |a - 1|
    c = compare_gradient(single, 0.9 * exact)
    assert c.cosine == pytest.approx(1.0, abs=1e-14)
    assert c.relative_error == pytest.approx(0.1, rel=1e-12)


def test_cell_phases_between_events():
    t = np.linspace(0.0, 1.0, 11)
    ph = [PHASES[k] for k in cell_phases(t, [0.25, 0.5, 0.73])]
    assert ph[:2] == ["before the first event"] * 2
    assert ph[2] == "cells with an event"
    assert ph[3:5] == ["between events"] * 2  # 0.5 is a grid time: no cell holds it
    assert ph[5:7] == ["between events"] * 2
    assert ph[7] == "cells with an event"
    assert ph[8:] == ["after the last event"] * 2
    assert set(cell_phases(t, [])) == {PHASES.index("no events")}


def test_substeps_sum_to_the_coarse_gradient(single):
    # the coarse value acts on all K substeps: its derivative is the sum of theirs
    k = 5
    fine = substep_problem(single, k)
    u = np.repeat(single.u_guess, k, axis=0)
    g_fine = hybridoc.gradient(fine, u).d_controls
    c = compare_gradient(single, g_fine, u, substeps=k)
    assert c.relative_error < 1e-14 and c.substeps == k and c.exact.shape == (16 * k, 2)
    summed = g_fine.reshape(single.steps, k, 2).sum(axis=1)
    assert compare_gradient(single, summed).relative_error < 1e-12


def test_bad_gradients(single):
    exact = hybridoc.gradient(single).d_controls
    with pytest.raises(GradientError, match=r"expected \(16, 2\).*substeps=3"):
        compare_gradient(single, np.repeat(exact, 3, axis=0))
    with pytest.raises(GradientError, match=r"has shape \(2, 16\)"):
        compare_gradient(single, exact.T)
    bad = exact.copy()
    bad[3, 1] = np.nan
    with pytest.raises(GradientError, match="non-finite value nan at row 3, column 1"):
        compare_gradient(single, bad)
    with pytest.raises(GradientError, match="not a numeric array|numeric"):
        compare_gradient(single, [["a", "b"]] * 16)


def test_figure_and_report(single):
    # drawn to PNG by the command-line test; here the figure is built and read back
    exact = hybridoc.gradient(single).d_controls
    c = compare_gradient(single, exact * 1.1)
    fig = gradient_figure(c, label="scaled")
    assert len(fig.axes) == 3 and "cosine 1.0000" in fig.texts[0].get_text()
    d = c.to_dict()
    assert d["cosine"] == c.cosine and len(d["cell_error_norm"]) == 16
    assert d["cell_error_norm"] == pytest.approx(0.1 * np.linalg.norm(exact, axis=1), rel=1e-12)
