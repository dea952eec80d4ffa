"""dt's options are declared once (issue #30): :class:`DTOptions` holds the defaults and the
checks, :func:`solve_dt` is a thin wrapper of :func:`run_dt` whose signature is generated
from the dataclass."""

from __future__ import annotations

import dataclasses
import inspect

import numpy as np
import pytest

import hybridoc
from hybridoc.errors import OptionError, SceneError
from hybridoc.solvers.transcription import METHOD, DTOptions, run_dt, solve_dt


def test_the_signature_is_the_dataclass() -> None:
    params = inspect.signature(solve_dt).parameters
    assert list(params)[:3] == ["problem", "initial", "progress"]
    fields = dataclasses.fields(DTOptions)
    assert list(params)[3:] == [f.name for f in fields]
    for f in fields:
        p = params[f.name]
        assert p.kind is p.KEYWORD_ONLY and p.default == f.default, f.name
    METHOD.check_signature()


@pytest.mark.parametrize(
    "options, match",
    [
        ({"degree": 0}, "degree must be an integer from 1 to 9"),
        ({"degree": 2.0}, "degree must be an integer"),
        ({"degree": True}, "degree must be an integer"),
        ({"mesh": 0}, "mesh must be elements per phase"),
        ({"mesh": "4"}, "mesh must be an integer or a list"),
        ({"mesh": []}, "mesh must be elements per phase"),
        ({"time_limit": -1.0}, "time_limit must be a positive number"),
        ({"time_limit": float("inf")}, "time_limit must be a positive number"),
        ({"terminal_tol": 0.0}, "terminal_tol must be a positive number"),
        ({"terminal_tol": "1e-8"}, "terminal_tol must be a positive number"),
    ],
)
def test_bad_options_are_one_option_error_where_they_are_made(options, match) -> None:
    with pytest.raises(OptionError, match=match) as info:
        DTOptions(**options)
    assert isinstance(info.value, SceneError) and isinstance(info.value, ValueError)
    # the same check, the same error, through every entry point (before any work)
    with pytest.raises(OptionError, match=match):
        solve_dt("single-collision", **options)
    with pytest.raises(OptionError, match=match):
        hybridoc.solve("single-collision", "dt", **options)


def test_values_are_normalised_and_a_mesh_per_phase_is_checked_against_the_sequence() -> None:
    opts = DTOptions(degree=np.int64(4), mesh=(2, 3))
    assert type(opts.degree) is int and opts.degree == 4
    with pytest.raises(OptionError, match=r"mesh must be one integer or 1 \(one per phase\)"):
        solve_dt("single-collision", sequence=[], mesh=[4, 4])


def test_an_unknown_keyword_is_a_type_error_naming_it() -> None:
    with pytest.raises(
        TypeError, match=r"^solve_dt\(\) got an unexpected keyword argument 'mseh'$"
    ):
        solve_dt("single-collision", mseh=4)


def test_run_dt_takes_the_options_object() -> None:
    ocp = hybridoc.as_ocp("single-collision")
    a = solve_dt(ocp, mesh=4, progress=False)
    b = run_dt(ocp, DTOptions(mesh=4), progress=False)
    assert a.cost == b.cost and np.array_equal(a.controls, b.controls)
    assert a.status is b.status and a.settings == b.settings
    c = run_dt(ocp)  # None: the defaults
    d = solve_dt(ocp)
    assert c.cost == d.cost and np.array_equal(c.controls, d.controls)
