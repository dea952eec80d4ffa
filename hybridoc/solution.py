"""The :class:`Solution` type shared by every solver, and its bit-identical file format.

A solution *is* its control: :meth:`Solution.control` evaluates the control the method found
in full (piecewise constants for gd, the transcription's polynomial per element for dt, the
HMP control law ``u(t)`` of the reference), ``cost`` is the judge's cost of exactly that
control, and :func:`hybridoc.evaluate` judges it again bit for bit (also after
:meth:`Solution.save` and :meth:`Solution.load`). ``controls`` (alias ``x``) are its values on
the N-step grid: the control itself for gd, cell averages for dt and the reference, whose
own judged cost :meth:`Solution.to_grid` gives.

The Solution is data plus its file format, in the model layer (docs/architecture.rst), below
the problems, the judge and the reference. What needs them (its control as a function of
time, judging it, :meth:`Solution.to_grid`, :meth:`Solution.sample`) lives in the judge
layer as functions of a Solution, :mod:`hybridoc.judging`; the methods of the same names are
one-line delegations, which reach that module through the registry of
:mod:`hybridoc.providers` (filled by the package, above every layer), never by an upward
import or a ``"module:attribute"`` string. A Solution keeps the judge's evaluation its cost
came from (:attr:`Solution.evaluation`), so figures and reports need not judge it again.

A solution is saved as two files with the same stem: ``stem.npz`` holds every array
(``controls``, ``time_grid``, the optional trajectories and costates, and the method-specific
``arrays`` under the prefix ``arrays/``), ``stem.json`` holds everything else (method, scene,
cost parts, events, settings, timings, versions, info) and the list of arrays stored. Arrays
keep their dtype and bits; floats are written with Python's shortest round-tripping repr, so
:meth:`Solution.load` gives back exactly what :meth:`Solution.save` wrote.
"""

from __future__ import annotations

import json
import math
import platform
import struct
import sys
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from enum import StrEnum
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.errors import HybridocError
from hybridoc.providers import provider

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.evaluation import Evaluation
    from hybridoc.judging import ControlFunction, SolutionSample
    from hybridoc.ocp import HybridOCP

__all__ = ["Solution", "Status", "package_versions"]

_FORMAT = "hybridoc-solution"
_FORMAT_VERSION = 2
_READABLE_VERSIONS = (1, 2)


class Status(StrEnum):
    """What a solver's result is, judged by the event-exact evaluator.

    ``SUCCESS``
        The method met its own convergence test and the judge confirms what it modelled
        (its events, its cost).
    ``EXTREMAL``
        The verified extremal of an event sequence the user chose (the reference or dt with
        ``sequence=``): it satisfies the conditions of optimality for those events (the HMP,
        or the transcription's KKT conditions) and re-simulates to them, but it was not
        compared with other sequences, so it makes no claim to be the optimum. Not a
        finding (exit code 0); a cheaper known control makes it ``NOT_OPTIMAL``.
    ``NOT_OPTIMAL``
        A cheaper control is known (the initial guess, another method's solution): the
        result is not the optimum it would claim to be.
    ``EVENTS_DIFFER``
        Re-simulated by the judge, the control produces other events than the method
        modelled.
    ``INFEASIBLE``
        The control violates the problem's control bounds or path constraints.
    ``NOT_CONVERGED``
        The method stopped without meeting its convergence test (iteration limit, NaN).
    ``DISAGREE``
        Methods that should agree (a cross-validation) do not.
    ``BEST_FOUND``
        The best control a search for the global optimum found, without proof that it is
        the optimum: the coverage the search reached (``info["coverage"]``) does not exclude
        a cheaper control (a sequence of events within the claimed length not solved, an
        extremal found from a single start, the budget or the time limit stopped the
        search). It is a finding (exit code 1): nothing cheaper is known, but nothing
        rules it out either.
    """

    SUCCESS = "success"
    EXTREMAL = "extremal"
    NOT_OPTIMAL = "not-optimal"
    EVENTS_DIFFER = "events-differ"
    INFEASIBLE = "infeasible"
    NOT_CONVERGED = "not-converged"
    DISAGREE = "disagree"
    BEST_FOUND = "best-found"

    @property
    def code(self) -> int:
        """An integer like scipy's ``status``: 0 for success, then in the order above
        (``extremal`` 1, ``not-optimal`` 2, ``events-differ`` 3, ``infeasible`` 4,
        ``not-converged`` 5, ``disagree`` 6, ``best-found`` 7). ``int(status)`` gives it
        too; the files keep the string."""
        return _STATUS_CODES[self.value]

    def __int__(self) -> int:
        return self.code

    @property
    def exit_code(self) -> int:
        """The CLI's exit code: 0 success or extremal, 2 not converged, 1 any other finding."""
        if self in (Status.SUCCESS, Status.EXTREMAL):
            return 0
        return 2 if self is Status.NOT_CONVERGED else 1


_STATUS_CODES = {
    "success": 0,
    "extremal": 1,
    "not-optimal": 2,
    "events-differ": 3,
    "infeasible": 4,
    "not-converged": 5,
    "disagree": 6,
    "best-found": 7,
}

_ARRAY_PREFIX = "arrays/"
# Array fields that are stored in the .npz (required ones first).
_REQUIRED_ARRAYS = ("controls", "time_grid")
_OPTIONAL_ARRAYS = ("state_times", "states", "costate_times", "costates")
_DICT_FIELDS = ("settings", "timings", "versions", "info")


@lru_cache(maxsize=1)
def _versions_cached() -> tuple[tuple[str, str | None], ...]:
    out: list[tuple[str, str | None]] = [("python", platform.python_version())]
    for dist in ("hybridoc", "numpy", "scipy", "casadi", "torch"):
        mod = sys.modules.get(dist)
        version = getattr(mod, "__version__", None) if mod is not None else None
        if version is None:
            # read the installed metadata instead of importing (torch takes seconds to import)
            try:
                version = metadata.version(dist)
            except metadata.PackageNotFoundError:
                version = None
        out.append((dist, None if version is None else str(version)))
    return tuple(out)


def package_versions() -> dict[str, str | None]:
    """Versions of Python and of hybridoc's dependencies (``None`` where not installed)."""
    return dict(_versions_cached())


def _jsonable(value: Any, where: str) -> Any:
    """Convert to JSON-native types (dict/list/str/int/float/bool/None), or raise."""
    if value is None or isinstance(value, bool | str):
        return value
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        return float(value)
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "biuf":
            raise TypeError(f"{where}: arrays of dtype {value.dtype} are not JSON-able")
        return _jsonable(value.tolist(), where)
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise TypeError(f"{where}: keys must be strings, got {k!r}")
            out[k] = _jsonable(v, f"{where}[{k!r}]")
        return out
    if isinstance(value, list | tuple):
        return [_jsonable(v, f"{where}[{i}]") for i, v in enumerate(value)]
    raise TypeError(f"{where}: {type(value).__name__} is not JSON-able")


def _same(a: Any, b: Any) -> bool:
    """Bit-level equality of JSON-like values and arrays (NaN equals NaN, 0.0 != -0.0)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
            return False
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    if isinstance(a, float) or isinstance(b, float):
        if not (isinstance(a, float) and isinstance(b, float)):
            return False
        return struct.pack("<d", a) == struct.pack("<d", b) or (math.isnan(a) and math.isnan(b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return type(a) is type(b) and a == b


def _stem(path: str | Path) -> Path:
    """``x``, ``x.npz`` and ``x.json`` all name the pair ``x.npz`` + ``x.json``."""
    p = Path(path)
    if p.suffix in (".npz", ".json"):
        return p.with_suffix("")
    return p


def _with(stem: Path, suffix: str) -> Path:
    return stem.with_name(stem.name + suffix)


def _judging() -> Any:
    """:mod:`hybridoc.judging`, the judge layer's functions of a Solution, through the
    registry the package fills (:mod:`hybridoc.providers`: no upward import)."""
    return provider("judging")


def __getattr__(name: str) -> Any:
    # names that moved to hybridoc.judging (#30), still importable from here
    if name in _MOVED:
        return getattr(_judging(), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


_MOVED = frozenset({"COSTATE_RTOL", "ControlFunction", "SolutionSample", "lagrange_pieces"})


@dataclass(eq=False, repr=False)
class Solution:
    """A control with its cost, trajectory and provenance: what every solver returns.

    A Solution is its control: :meth:`control` evaluates ``u(t)`` as the method found it
    (:attr:`control_kind`), and ``cost`` is the judge's cost of exactly that control, which
    ``hybridoc.evaluate(problem, sol)`` reproduces bit for bit, also after
    :meth:`save` and :meth:`load`. :meth:`to_grid` projects it onto an N-step grid (with its
    own judged cost); :meth:`sample` gives states, controls, costates and modes at any times
    (the judge layer's functions of :mod:`hybridoc.judging`). :attr:`evaluation` is the
    judge's evaluation the cost came from, kept in memory (not in the files).

    Names as in :class:`scipy.optimize.OptimizeResult` where they fit: :attr:`x` (the
    control on the grid), :attr:`fun` (the cost), :attr:`success`, :attr:`status` (``int``
    gives scipy's integer), :attr:`message`, :attr:`nit`, :attr:`nfev`.

    ``==`` compares field by field, arrays bit for bit (see :meth:`equals`).

    Parameters
    ----------
    method
        Producer, e.g. ``"reference"``, ``"dt"``, ``"gd"``, ``"initial-guess"``, ``"user"``.
    scene
        Scene name.
    controls
        ``(N, nu)`` values on ``time_grid``: the control itself for a piecewise-constant
        method (gd), the cell averages of the continuous control for dt and the reference
        (see :attr:`control_kind`).
    time_grid
        ``(N + 1,)`` grid times.
    cost, terminal_cost, running_cost
        The cost ``J`` and its two parts: the judge's, of the control :meth:`control`.
    events
        ``[{"time", "kind", "bodies", "guard"}, ...]`` in time order; for a problem with
        modes also ``"mode_before"`` and ``"mode_after"`` (see :attr:`modes`).
    state_times, states
        Optional trajectory: ``(M,)`` times and ``(M, nx)`` states (an event may appear
        twice, before and after the jump).
    costate_times, costates
        Optional costate ``lambda(t)``, same layout.
    settings
        Solver settings (JSON-able).
    timings
        Seconds, e.g. ``{"solve_time_s": 0.05}``.
    versions
        Package versions; filled automatically.
    info
        Method-specific JSON-able scalars and lists (residual, iterations, ...).
    arrays
        Method-specific arrays (loss history, ...).
    status
        A :class:`Status` (or its string value): what the result is, judged by the
        evaluator. :attr:`success` is ``status == "success"``.
    message
        One line saying why the status is what it is (empty for a plain success).
    """

    method: str
    scene: str
    controls: np.ndarray
    time_grid: np.ndarray
    cost: float
    terminal_cost: float
    running_cost: float
    events: list[dict[str, Any]] = field(default_factory=list)
    state_times: np.ndarray | None = None
    states: np.ndarray | None = None
    costate_times: np.ndarray | None = None
    costates: np.ndarray | None = None
    settings: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, Any] = field(default_factory=dict)
    versions: dict[str, Any] = field(default_factory=package_versions)
    info: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    status: Status | str = Status.SUCCESS
    message: str = ""

    __hash__ = None  # type: ignore[assignment]  # mutable

    def __post_init__(self) -> None:
        if not isinstance(self.method, str) or not isinstance(self.scene, str):
            raise TypeError("method and scene must be strings")
        try:
            self.status = Status(self.status)
        except ValueError:
            raise ValueError(
                f"status must be one of {[s.value for s in Status]}, got {self.status!r}"
            ) from None
        if not isinstance(self.message, str):
            raise TypeError("message must be a string")
        self.controls = np.asarray(self.controls)
        self.time_grid = np.asarray(self.time_grid)
        if self.controls.ndim != 2:
            raise ValueError(f"controls must be (N, nu), got shape {self.controls.shape}")
        if self.time_grid.shape != (self.controls.shape[0] + 1,):
            raise ValueError(
                f"time_grid must have N + 1 = {self.controls.shape[0] + 1} entries, "
                f"got shape {self.time_grid.shape}"
            )
        for name in ("cost", "terminal_cost", "running_cost"):
            setattr(self, name, float(getattr(self, name)))
        for t_name, x_name in (("state_times", "states"), ("costate_times", "costates")):
            t, x = getattr(self, t_name), getattr(self, x_name)
            if (t is None) != (x is None):
                raise ValueError(f"{t_name} and {x_name} must be given together")
            if t is not None:
                t, x = np.asarray(t), np.asarray(x)
                if t.ndim != 1 or x.ndim != 2 or x.shape[0] != t.shape[0]:
                    raise ValueError(
                        f"{t_name} must be (M,) and {x_name} (M, nx), got {t.shape} and {x.shape}"
                    )
                setattr(self, t_name, t)
                setattr(self, x_name, x)
        self.events = _jsonable(list(self.events), "events")
        for name in _DICT_FIELDS:
            setattr(self, name, _jsonable(dict(getattr(self, name)), name))
        arrays = {}
        for k, v in dict(self.arrays).items():
            if not isinstance(k, str) or not k:
                raise TypeError(f"arrays: names must be non-empty strings, got {k!r}")
            arr = np.asarray(v)
            if arr.dtype.kind not in "biufc":
                raise TypeError(f"arrays[{k!r}]: dtype {arr.dtype} cannot be saved")
            arrays[k] = arr
        self.arrays = arrays

    @property
    def success(self) -> bool:
        """Whether :attr:`status` is :attr:`Status.SUCCESS`."""
        return self.status is Status.SUCCESS

    @property
    def sequence(self) -> list[str]:
        """The guard names of :attr:`events` (``"a|b"`` for events stored without a name)."""
        return [str(e.get("guard") or "|".join(e.get("bodies", []))) for e in self.events]

    @property
    def modes(self) -> list[str] | None:
        """The modes the solution visits, in order, from its events' ``mode_before`` and
        ``mode_after`` (a problem with modes, :meth:`hybridoc.HybridOCP.from_modes`);
        ``None`` when the events carry no modes (a problem without modes, or no event: then
        the mode is the initial one throughout)."""
        if not self.events or any("mode_before" not in e for e in self.events):
            return None
        return [str(self.events[0]["mode_before"])] + [str(e["mode_after"]) for e in self.events]

    def set_status(self, status: Status | str, message: str = "") -> Solution:
        """Set :attr:`status` and :attr:`message`; returns ``self``."""
        self.status = Status(status)
        self.message = str(message)
        return self

    # ------------------------------------------------------------------ scipy's names
    @property
    def x(self) -> np.ndarray:
        """The control on the grid, ``(N, nu)`` (:attr:`controls`), as scipy's solution
        vector ``x``; :meth:`control` is the control itself."""
        return self.controls

    @property
    def fun(self) -> float:
        """The cost (:attr:`cost`), as scipy's ``fun``."""
        return self.cost

    @property
    def nit(self) -> int | None:
        """The method's iterations (gd: descent steps, dt: IPOPT's, the reference: Newton's
        of the returned extremal); ``None`` where the method does not count them."""
        for key in ("iterations", "newton_iterations"):
            value = self.info.get(key)
            if isinstance(value, int) and not isinstance(value, bool) and value >= 0:
                return value
        return None

    @property
    def nfev(self) -> int | None:
        """Evaluations of the method's objective (gd: loss evaluations); ``None`` where the
        method does not count them."""
        value = self.info.get("loss_evaluations")
        return value if isinstance(value, int) and not isinstance(value, bool) else None

    # ------------------------------------------------------------------ the control
    @property
    def horizon(self) -> float:
        """The final time ``T``: ``info["horizon"]`` (a free final time as found), else the
        last grid time."""
        value = self.info.get("horizon")
        return float(self.time_grid[-1]) if value is None else float(value)

    @property
    def control_kind(self) -> str:
        """What :meth:`control` is, read from the arrays the method stored.

        ``"piecewise-constant"``
            :attr:`controls` on :attr:`time_grid` (gd, a user's controls).
        ``"piecewise-polynomial"``
            dt: per collocation element the polynomial through the controls at the Radau
            points (arrays ``element_bounds``, ``radau_controls``, ``control_nodes``).
        ``"phase-linear"``
            The reference on a disc scene: ``u = c0 + c1 (t - t_k)`` on each phase
            (arrays ``phase_starts``, ``control_coefficients``).
        ``"hmp"``
            The reference on a generic problem: the HMP control law ``u = argmin H`` along
            the state and costate rebuilt from each phase's start (arrays ``phase_starts``,
            ``phase_states``, ``phase_costates``, ``substeps``); needs the problem.
        """
        a = self.arrays
        if "element_bounds" in a and "radau_controls" in a:
            return "piecewise-polynomial"
        if "phase_starts" in a and "control_coefficients" in a:
            return "phase-linear"
        if {"phase_starts", "phase_states", "phase_costates"} <= a.keys():
            return "hmp"
        return "piecewise-constant"

    @property
    def event_controls(self) -> np.ndarray | None:
        """``(K, nu)``: the control each reset reads, event by event, for a continuous-time
        control on a problem whose resets depend on the control (``arrays["event_controls"]``,
        stored by dt: its ``v_k``); ``None`` otherwise. The judge of :meth:`control` applies
        row ``k`` at the ``k``-th event (a piecewise-constant control's resets read their
        cell's control)."""
        value = self.arrays.get("event_controls")
        return None if value is None else np.asarray(value, dtype=float)

    @property
    def problem(self) -> HybridOCP | None:
        """The problem this Solution is bound to (:meth:`bind`; a method binds the problem
        it solved); ``None`` for a Solution loaded from a file until it is bound."""
        return self.__dict__.get("_bound_problem")

    def bind(self, problem: Any) -> Solution:
        """Bind the problem (anything :func:`hybridoc.problem.as_ocp` takes) that the
        methods below use when they are given none; returns ``self``."""
        self.__dict__["_bound_problem"] = _judging().as_ocp(problem)
        return self

    def control_function(self, problem: Any = None) -> ControlFunction:
        """The control ``u(t)`` for one time at a time, with its breakpoints: what
        :func:`hybridoc.evaluate` judges (:func:`hybridoc.judging.control_function`)."""
        return _judging().control_function(self, problem)

    def control(self, t: float | Sequence[float] | np.ndarray, problem: Any = None) -> np.ndarray:
        """The control at ``t``: ``(nu,)`` for one time, ``(M, nu)`` for ``M`` times
        (:func:`hybridoc.judging.control`)."""
        return _judging().control(self, t, problem)

    @property
    def evaluation(self) -> Evaluation | None:
        """The judge's :class:`~hybridoc.Evaluation` this Solution's cost came from: kept by
        :meth:`from_evaluation`, :meth:`judge`, :meth:`with_evaluation` and :meth:`to_grid`,
        so that figures and reports use it without judging again. ``None`` where there is
        none: a Solution loaded from a file or unpickled (the file format does not store it),
        or one whose ``cost``, ``terminal_cost`` or ``running_cost`` was changed since (it
        would not be where they came from). To judge a Solution anew (another problem, a
        loaded file): ``hybridoc.evaluate(problem, sol)``."""
        ev = self.__dict__.get("_evaluation")
        if ev is None:
            return None
        parts = (self.cost, self.terminal_cost, self.running_cost)
        judged = (float(ev.cost), float(ev.terminal_cost), float(ev.running_cost))
        return ev if all(_same(a, b) for a, b in zip(parts, judged, strict=True)) else None

    def with_evaluation(self, ev: Evaluation) -> Solution:
        """Take ``cost``, ``terminal_cost`` and ``running_cost`` from the judge's evaluation
        ``ev`` of this Solution's control and keep ``ev`` as :attr:`evaluation`; returns
        ``self``. A method that judged its control itself (the same evaluation as
        ``hybridoc.evaluate(problem, sol)``, bit for bit) calls it instead of setting the
        cost parts one by one."""
        self.cost = float(ev.cost)
        self.terminal_cost = float(ev.terminal_cost)
        self.running_cost = float(ev.running_cost)
        self.__dict__["_evaluation"] = ev
        return self

    def judge(self, problem: Any = None) -> Evaluation:
        """Set the cost parts to the judge's, of :meth:`control`, keep that evaluation
        (:attr:`evaluation`) and return it (:func:`hybridoc.judging.judge`)."""
        return _judging().judge(self, problem)

    def to_grid(self, N: int | None = None, problem: Any = None) -> Solution:
        """The control projected onto the N-step grid: cell averages, held constant, with
        their own judged cost (:func:`hybridoc.judging.to_grid`)."""
        return _judging().to_grid(self, N, problem)

    def sample(
        self, t: float | Sequence[float] | np.ndarray, problem: Any = None
    ) -> SolutionSample:
        """States, controls, costates and modes at any times in ``[0, T]``
        (:func:`hybridoc.judging.sample`)."""
        return _judging().sample(self, t, problem)

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state.pop("_bound_problem", None)  # compiled functions: bind again after unpickling
        state.pop("_evaluation", None)  # holds the problem too: judge again if needed
        return state

    def __repr__(self) -> str:
        n, nu = self.controls.shape
        return (
            f"Solution(method={self.method!r}, scene={self.scene!r}, "
            f"status={Status(self.status).value!r}, cost={self.cost!r}, "
            f"control={self.control_kind!r}, N={n}, nu={nu}, events={len(self.events)})"
        )

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_evaluation(
        cls,
        ev: Any,
        *,
        method: str,
        scene: Any,
        settings: Mapping[str, Any] | None = None,
        timings: Mapping[str, Any] | None = None,
        info: Mapping[str, Any] | None = None,
        arrays: Mapping[str, np.ndarray] | None = None,
        gradient: Any = None,
    ) -> Solution:
        """Build a solution from an :class:`~hybridoc.Evaluation`.

        Parameters
        ----------
        ev
            The evaluation: controls, cost parts, events and trajectory are taken from it.
        method
            Producer name.
        scene
            Scene name (or an object with a ``name``, e.g. a Scene, whose name is used).
        settings, timings, info, arrays
            As in :class:`Solution`.
        gradient
            Optional :class:`~hybridoc.Gradient` of the same controls; its costates are kept.

        The Solution keeps ``ev`` as :attr:`evaluation` and is bound to ``ev.ocp``.
        """
        scene_name = scene if isinstance(scene, str) else str(getattr(scene, "name", scene))
        costate_times = costates = None
        if gradient is not None:
            costate_times = np.array(gradient.costate_times)
            costates = np.array(gradient.costates)
        sol = cls(
            method=method,
            scene=scene_name,
            controls=np.array(ev.controls),
            time_grid=ev.ocp.time_grid(),
            cost=ev.cost,
            terminal_cost=ev.terminal_cost,
            running_cost=ev.running_cost,
            events=ev.event_dicts(),
            state_times=np.array(ev.times),
            states=np.array(ev.states),
            costate_times=costate_times,
            costates=costates,
            settings=dict(settings or {}),
            timings=dict(timings or {}),
            info=dict(info or {}),
            arrays=dict(arrays or {}),
        )
        sol.__dict__["_bound_problem"] = ev.ocp
        sol.__dict__["_evaluation"] = ev
        return sol

    # ------------------------------------------------------------------ comparison
    def equals(self, other: object) -> bool:
        """Field-by-field equality; arrays must match in dtype, shape and bits."""
        if not isinstance(other, Solution):
            return False
        for f in fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if f.name == "arrays":
                if a.keys() != b.keys() or not all(_same(a[k], b[k]) for k in a):
                    return False
            elif (a is None) != (b is None) or (a is not None and not _same(a, b)):
                return False
        return True

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Solution):
            return NotImplemented
        return self.equals(other)

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> tuple[Path, Path]:
        """Write ``stem.npz`` and ``stem.json``; ``path`` may be ``stem``, ``stem.npz`` or
        ``stem.json``. Parent directories are created.

        Each file is written by the rules of :mod:`hybridoc.outputs`: through a temporary
        file renamed over its name, never through a symbolic link, and never over a file
        that hybridoc did not write (both names are checked before either is written).

        Returns
        -------
        tuple of Path
            The two files written.

        Raises
        ------
        hybridoc.errors.HybridocError
            A name refused (a link, or a file hybridoc did not write), or a file that
            cannot be written.
        """
        from hybridoc.outputs import check_targets, write_text, write_with

        self.__post_init__()  # re-validate fields changed since construction
        stem = _stem(path)
        npz_path, json_path = _with(stem, ".npz"), _with(stem, ".json")
        stored: dict[str, np.ndarray] = {
            "controls": self.controls,
            "time_grid": self.time_grid,
        }
        for name in _OPTIONAL_ARRAYS:
            value = getattr(self, name)
            if value is not None:
                stored[name] = value
        for k, v in self.arrays.items():
            stored[_ARRAY_PREFIX + k] = v
        meta = {
            "format": _FORMAT,
            "format_version": _FORMAT_VERSION,
            "method": self.method,
            "scene": self.scene,
            "cost": self.cost,
            "terminal_cost": self.terminal_cost,
            "running_cost": self.running_cost,
            "events": self.events,
            "settings": self.settings,
            "timings": self.timings,
            "versions": self.versions,
            "info": self.info,
            "stored_arrays": list(stored),
            "status": Status(self.status).value,
            "message": self.message,
        }
        text = json.dumps(meta, indent=2)
        check_targets(npz_path, json_path)  # neither file is written if either is refused
        # a file object: numpy must not append ".npz"
        write_with(npz_path, lambda fh: np.savez(fh, **stored))
        write_text(json_path, text + "\n")
        return npz_path, json_path

    @classmethod
    def load(cls, path: str | Path) -> Solution:
        """Read a solution written by :meth:`save`.

        Raises
        ------
        hybridoc.errors.HybridocError
            If a file is missing, unreadable or inconsistent.
        """
        given = Path(path)
        stem = _stem(path)
        npz_path, json_path = _with(stem, ".npz"), _with(stem, ".json")
        # the file the user named first, then its partner
        order = (npz_path, json_path) if given.suffix != ".json" else (json_path, npz_path)
        for p in order:
            if not p.is_file():
                if p != order[0]:
                    raise HybridocError(
                        f"solution file {str(p)!r} does not exist (a Solution is the pair "
                        f"{npz_path.name} + {json_path.name})"
                    )
                raise HybridocError(f"solution file {str(p)!r} does not exist")
        from hybridoc.outputs import read_json

        # bounded in size and nesting: a file nested 200 000 deep is one clear error
        meta = read_json(json_path, f"solution file {str(json_path)!r}")
        if not isinstance(meta, dict) or meta.get("format") != _FORMAT:
            raise HybridocError(f"{str(json_path)!r} is not a hybridoc solution file")
        if meta.get("format_version") not in _READABLE_VERSIONS:
            raise HybridocError(
                f"{str(json_path)!r}: unsupported solution format version "
                f"{meta.get('format_version')!r} (this hybridoc reads {_FORMAT_VERSION})"
            )
        try:
            with np.load(npz_path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise HybridocError(f"solution file {str(npz_path)!r} is unreadable: {exc}") from None
        expected = meta.get("stored_arrays")
        if not isinstance(expected, list) or sorted(expected) != sorted(arrays):
            raise HybridocError(
                f"{str(npz_path)!r} does not match {str(json_path)!r}: arrays "
                f"{sorted(arrays)} stored, {expected} expected"
            )
        kwargs: dict[str, Any] = {}
        for key in ("method", "scene", "cost", "terminal_cost", "running_cost", "events"):
            if key not in meta:
                raise HybridocError(f"{str(json_path)!r}: missing key {key!r}")
            kwargs[key] = meta[key]
        for key in _DICT_FIELDS:
            kwargs[key] = meta.get(key, {})
        kwargs["status"] = meta.get("status", "success")
        kwargs["message"] = meta.get("message", "")
        for name in _REQUIRED_ARRAYS + _OPTIONAL_ARRAYS:
            kwargs[name] = arrays.get(name)
        kwargs["arrays"] = {
            k[len(_ARRAY_PREFIX) :]: v for k, v in arrays.items() if k.startswith(_ARRAY_PREFIX)
        }
        if kwargs["controls"] is None or kwargs["time_grid"] is None:
            raise HybridocError(f"{str(npz_path)!r}: controls or time_grid missing")
        try:
            return cls(**kwargs)
        except (TypeError, ValueError) as exc:
            raise HybridocError(f"solution {str(stem)!r} is inconsistent: {exc}") from None

    # ------------------------------------------------------------------ display
    def summary(self) -> str:
        """A few human-readable lines: method, scene, cost parts, events."""
        n, nu = self.controls.shape
        lines = [
            f"{self.method} solution of {self.scene!r}: N = {n}, {nu} control components",
            f"  status {Status(self.status).value}" + (f": {self.message}" if self.message else ""),
            f"  cost {self.cost:.12g} (terminal {self.terminal_cost:.12g}, "
            f"running {self.running_cost:.12g})",
            f"  events: {len(self.events)}",
        ]
        for e in self.events:
            bodies = ", ".join(str(b) for b in e.get("bodies", []))
            modes = f"  {e['mode_before']} -> {e['mode_after']}" if "mode_before" in e else ""
            lines.append(f"    t = {float(e['time']):.9f}  {e.get('kind', '?')}  {bodies}{modes}")
        return "\n".join(lines)
