"""The method contract (:mod:`hybridoc.methods`): every registered method, one test.

Each registered method runs through the same checks on a small problem, as
tests/test_contacts_compiled.py does for contact models: its ``run`` takes exactly its
options, its options are a frozen dataclass with help on every field, and ``hybridoc.solve``
returns a Solution whose cost is the judge's, whose status, success and message agree, and
whose summary lines print. Then a method defined here (``zero``, below) shows that adding a
solver is one definition and one registration line: ``hybridoc.solve`` and ``hybridoc solve``
offer it and its option at once.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest

import hybridoc
from hybridoc import cli
from hybridoc.errors import SceneError
from hybridoc.methods import (
    BUILTIN,
    METHODS,
    Method,
    get_method,
    option,
    register_method,
    unregister_method,
)
from hybridoc.solution import Solution, Status

PROBLEM = "head-on"
SMALL: dict[str, dict[str, object]] = {"gd": {"iters": 20}}
"""Options that keep a method quick on :data:`PROBLEM` (the others run with defaults)."""

CONTINUOUS = {"dt", "reference"}
"""Methods whose Solution carries a continuous control: its cost is the judge's cost of that
control, and the grid averages in ``controls``, judged piecewise constant, cost O(dt^2) more
(as tests/test_transcription.py and test_validation.py check)."""


# ------------------------------------------------------------------- the example method
@dataclass(frozen=True)
class ZeroOptions:
    """The options of the example method."""

    start: str = option(
        "guess", "the controls returned: the problem's guess or zeros", choices=("guess", "zero")
    )


def run_zero(ocp, *, initial=None, progress=None, start="guess"):
    """The guess or zero controls (or ``initial``), judged: the smallest possible method."""
    if initial is not None:
        u = np.asarray(getattr(initial, "controls", initial), dtype=float)
    elif start == "zero":
        u = np.zeros((ocp.steps, ocp.nu))
    else:
        u = ocp.u_guess
    ev = hybridoc.evaluate(ocp, u)
    return Solution.from_evaluation(ev, method="zero", scene=ocp.name, settings={"start": start})


ZERO = Method("zero", "the problem's guess or zero controls, judged", run_zero, ZeroOptions)


@pytest.fixture
def zero() -> Iterator[Method]:
    """The example method, registered for one test (one line) and removed after it."""
    register_method(ZERO)
    try:
        yield ZERO
    finally:
        unregister_method("zero")


# ------------------------------------------------------------------------- the contract
def _check_declaration(method: Method) -> None:
    method.check_signature()
    opts = method.options
    assert dataclasses.is_dataclass(opts) and opts.__dataclass_params__.frozen, method.name
    run_defaults = {
        p.name: p.default
        for p in inspect.signature(method.function()).parameters.values()
        if p.name in method.option_names()
    }
    for spec in method.specs():
        assert spec.help.strip(), f"{method.name}: option {spec.name} has no help"
        assert run_defaults[spec.name] == spec.default or (
            run_defaults[spec.name] is None and spec.default is None
        ), f"{method.name}: run's default of {spec.name} differs from its options'"
        if spec.choices is not None and spec.default is not None:
            assert spec.default in spec.choices, f"{method.name}: {spec.name}"
    assert method.tolerance > 0


def _check_solution(method: Method, sol: Solution, ocp: hybridoc.HybridOCP) -> None:
    assert isinstance(sol, Solution)
    assert sol.method == method.name and sol.scene == ocp.name
    assert isinstance(sol.status, Status)
    assert sol.success == (sol.status is Status.SUCCESS)
    assert isinstance(sol.message, str)
    assert sol.success or sol.message, f"{method.name}: status {sol.status} without a message"
    assert sol.timings["wall_time_s"] > 0
    assert sol.controls.shape == (ocp.steps, ocp.nu)
    judged = hybridoc.evaluate(ocp, sol.controls).cost
    if method.name in CONTINUOUS:
        assert 0.0 <= judged - sol.cost < 1e-3 * max(1.0, judged), method.name
    else:
        assert sol.cost == judged, method.name
    lines = method.summary_lines(sol)
    assert all(
        isinstance(pair, tuple) and len(pair) == 2 and all(isinstance(s, str) for s in pair)
        for pair in lines
    ), lines


def _check_contract(name: str, problem: str, options: dict[str, object]) -> Solution:
    method = METHODS[name]
    assert method.name == name and method.summary
    _check_declaration(method)
    ocp = hybridoc.as_ocp(problem)
    assert method.supports(ocp) is None
    sol = hybridoc.solve(ocp, name, **options)
    _check_solution(method, sol, ocp)
    with pytest.raises(SceneError, match=f"method '{name}' takes no option.s. no_such_option"):
        hybridoc.solve(ocp, name, no_such_option=1)
    return sol


@pytest.mark.parametrize("name", list(METHODS))
def test_every_method_keeps_the_contract(name: str) -> None:
    _check_contract(name, PROBLEM, SMALL.get(name, {}))


def test_the_builtin_methods_are_registered_lazily() -> None:
    assert set(BUILTIN) <= set(METHODS)
    for name, where in BUILTIN.items():
        module, _, attr = where.partition(":")
        assert METHODS[name] is getattr(__import__(module, fromlist=[attr]), attr)


def test_a_shared_option_means_the_same_for_every_method() -> None:
    """One flag serves every method with an option of that name: they must agree on it."""
    seen: dict[str, tuple[str, object, object]] = {}
    for name in METHODS:
        for spec in METHODS[name].specs():
            if not spec.cli:
                continue
            first = seen.setdefault(spec.name, (name, spec.choices, spec.parser))
            assert first[1:] == (spec.choices, spec.parser), (
                f"option {spec.name}: {first[0]} and {name} parse it differently"
            )


def test_unknown_method_is_one_line() -> None:
    with pytest.raises(SceneError, match="unknown method 'nosuch'; choose one of"):
        hybridoc.solve(PROBLEM, "nosuch")
    with pytest.raises(SceneError, match="unknown method"):
        get_method("nosuch")


# --------------------------------------------------------- adding a solver: one line
def test_a_new_method_keeps_the_contract(zero: Method) -> None:
    sol = _check_contract("zero", PROBLEM, {"start": "zero"})
    assert np.array_equal(sol.controls, np.zeros_like(sol.controls))
    assert sol.settings == {"start": "zero"}
    assert hybridoc.solve(PROBLEM, "zero").cost == hybridoc.evaluate(PROBLEM).cost


def test_a_new_method_is_gone_when_unregistered() -> None:
    register_method(ZERO)
    unregister_method("zero")
    assert "zero" not in METHODS and "zero" not in list(METHODS)
    with pytest.raises(KeyError):
        unregister_method("zero")


def test_a_new_method_and_its_option_are_on_the_command_line(
    zero: Method, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as info:
        cli.main(["solve", "--help"])
    assert info.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "zero options: --start {guess,zero} the controls returned" in text
    assert "zero: the problem's guess or zero controls, judged" in text

    assert cli.main(["solve", PROBLEM, "--method", "zero", "--start", "zero", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["method"] == "zero" and data["status"] == "success"
    assert data["settings"] == {"start": "zero"}
    assert data["cost"] == hybridoc.evaluate(PROBLEM, np.zeros((240, 2))).cost

    assert cli.main(["solve", PROBLEM, "--method", "zero"]) == 0
    out = capsys.readouterr().out
    assert "method    zero" in out and "settings  start guess" in out


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--method", "zero", "--start", "one"], "argument --start: invalid choice: 'one'"),
        (
            ["--method", "gd", "--start", "zero"],
            "--start applies to --method zero, not to --method gd",
        ),
    ],
)
def test_a_new_option_is_checked(
    zero: Method, capsys: pytest.CaptureFixture[str], args: list[str], fragment: str
) -> None:
    try:
        code = cli.main(["solve", PROBLEM, *args])
    except SystemExit as exc:
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("hybridoc: error: ") and fragment in err[0], err


def test_a_wrong_option_is_one_line(zero: Method) -> None:
    with pytest.raises(SceneError, match="takes no option.s. stat; it takes start"):
        hybridoc.solve(PROBLEM, "zero", stat="zero")


# ----------------------------------------------- what the workflows ask of a method (#30)
def test_the_builtin_records_say_what_they_represent() -> None:
    """The workflows ask the record, not the name: dt's control is continuous in time with
    its mesh as resolution, gd's is on the grid with its own early check; the registry
    keeps the modules' own records (the same objects)."""
    import hybridoc.reference.solve as reference
    import hybridoc.solvers.gd as gd
    import hybridoc.solvers.transcription as transcription
    from hybridoc.methods import METHODS, REPRESENTATIONS

    dt = METHODS["dt"]
    assert (dt.representation, dt.resolution_option) == ("continuous", "mesh")
    assert set(dt.projection_options) == {"mesh", "degree"}
    assert METHODS["gd"] is gd.METHOD and METHODS["gd"].representation == "grid"
    assert METHODS["gd"].check_options is gd.checked_options
    assert METHODS["dt"] is transcription.METHOD and METHODS["reference"] is reference.METHOD
    assert METHODS["reference"].representation == "continuous"
    assert all(m.representation in REPRESENTATIONS for m in METHODS.values())


def test_a_method_record_is_checked() -> None:
    from hybridoc.methods import Method, NoOptions

    def run(ocp, *, initial=None, progress=None):  # noqa: ANN001, ANN202
        return None

    with pytest.raises(TypeError, match="representation"):
        Method("x", "x", run, representation="exact")
    with pytest.raises(TypeError, match="'mesh' is not one of its options"):
        Method("x", "x", run, options=NoOptions, resolution_option="mesh")


def test_loss_history_default_reads_the_array() -> None:
    import numpy as np

    from hybridoc.methods import loss_history

    class Sol:
        arrays: dict = {}

    sol = Sol()
    assert loss_history(sol) is None
    sol.arrays = {"loss_history": np.array([])}
    assert loss_history(sol) is None
    sol.arrays = {"loss_history": np.array([3.0, 2.0])}
    assert list(loss_history(sol)) == [3.0, 2.0]


def test_a_continuous_method_is_projected_by_its_record(registered: object) -> None:
    """crossval's yardstick for a method continuous in time: the method re-solved from the
    reference on its own resolution, refined by doubling that option; nothing names it."""
    import dataclasses as dc

    from hybridoc.methods import Method, option
    from hybridoc.workflows.validation import refined_projection, representable

    @dc.dataclass(frozen=True)
    class CellOptions:
        cells: int = option(4, "pieces of the control")

    seen: list[int] = []

    def run(ocp, *, initial=None, progress=None, cells=4):  # noqa: ANN001, ANN202
        seen.append(cells)
        sol = hybridoc.Solution.from_evaluation(
            hybridoc.evaluate(ocp, initial.controls), method="pieces", scene=ocp
        )
        sol.info["cells"] = [cells]
        return sol

    registered(
        Method("pieces", "the reference's controls", run, options=CellOptions,
               representation="continuous", resolution_option="cells",
               projection_options=("cells",))
    )  # fmt: skip
    ocp = hybridoc.as_ocp("bouncing-ball")
    ref = hybridoc.solve(ocp, "reference")
    got = representable(ocp, "pieces", ref)
    assert got["representable"] == "pieces re-solved from the reference on its own cells"
    assert got["representable_cells"] == [4] and got["representable_sequence_matches"]
    fine = refined_projection(ocp, "pieces", ref)
    assert fine["refined"] == "pieces re-solved from the reference on cells 8"
    assert seen == [4, 4, 8]
