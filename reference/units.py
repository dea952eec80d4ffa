"""The reference in the problem's own units: a disc scene is solved in its scaled units.

A disc scene states its units in :attr:`HybridOCP.scales <hybridoc.ocp.HybridOCP.scales>`
(:func:`hybridoc.scales.disc_scales`): a length, a time and a mass, each a power of two, and
an offset of the positions, a multiple of ``1024`` lengths. Every tolerance of the reference
(Newton's, the event-time and cost comparisons of the search, the costate guesses, the
candidate sources' own: the multi-start's random controls, the transcription's IPOPT) is
stated for numbers of order one. So :func:`~hybridoc.reference.solve_reference` solves the
*canonical* scene instead (:func:`canonical`): the same scene with the offset subtracted and
lengths, times and masses divided by their scales rounded to a power of :data:`BAND` (16).

Why powers of 16, not the scales themselves
    The canonical scenes of one physical scene in any units, or moved, then differ by factors
    of at most 4 in each unit (and an offset of at most ``512`` lengths), where the search
    finds the same optimum on the paper's scenes (tests/test_units_reference.py; measured
    before this module on single-collision and head-on with each factor 0.3 and 3: the same
    cost to 2e-15, the same events and status). A scene within a factor 4 of its own
    units (every scene of the paper, the library and the test suite) is solved exactly as
    before, bit for bit: dividing by the scales themselves changed the best-found answer
    of tests/scenes/channel.toml (length 2, seven events, found only by the multi-start,
    whose random controls have an absolute size) from 0.0689 to 0.0785.

Exact
    Dividing by powers of two is exact, and the offset is a multiple of a power of two near
    the positions, so the canonical scene holds the numbers of the scene without rounding
    (beyond what the scene's own positions far from the origin hold).

The answer in the problem's units
    :meth:`Units.to_problem`: controls times ``M L / T**2``, times times ``T``, states
    ``L s~ + offset`` (velocities ``L / T``), costates (``dJ/ds``) times ``L**2`` over the
    state's scale, costs times ``L**2``; then judged again on the problem itself. The
    messages and progress lines name costs in the problem's units (:func:`cost_shown`). The
    HMP residual (``info["residual"]``, ``arrays["residual_history"]``) stays the canonical
    scene's: a norm over unknowns of different units has no meaning in the problem's own.
    ``Solution.reference`` (the :class:`~hybridoc.reference.result.ReferenceResult`, whose
    shooting unknowns are the canonical scene's) is ``None``.
"""

from __future__ import annotations

import contextvars
import dataclasses
import math
import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridoc.ocp import HybridOCP
from hybridoc.problems import scene_of
from hybridoc.scales import pow2

__all__ = ["BAND", "Units", "canonical", "cost_shown", "in_problem_units"]

_COST_UNIT: contextvars.ContextVar[float] = contextvars.ContextVar("cost_unit", default=1.0)


def cost_shown(cost: float) -> float:
    """A cost of the problem being solved as the user's problem measures it: the messages
    and progress lines of a canonical solve (:func:`in_problem_units`) name costs in the
    units the user gave."""
    return float(cost) * _COST_UNIT.get()


@contextmanager
def in_problem_units(units: Units | None) -> Iterator[None]:
    """Within this block :func:`cost_shown` multiplies by ``units.cost`` (nothing when
    ``units`` is ``None``)."""
    token = _COST_UNIT.set(1.0 if units is None else units.cost)
    try:
        yield
    finally:
        _COST_UNIT.reset(token)


@dataclass(frozen=True)
class Units:
    """The canonical problem of a disc scene and how to state its answers in the scene's
    units (:func:`canonical`).

    Attributes
    ----------
    ocp
        The canonical problem (lengths, times and masses in units of the scene's scales,
        positions less the offset).
    length, time, mass
        The scene's length, time and mass scales (powers of two).
    offset
        The offset of the positions, ``(2,)`` (a multiple of ``1024 * length`` each).
    """

    ocp: HybridOCP
    length: float
    time: float
    mass: float
    offset: np.ndarray

    @property
    def cost(self) -> float:
        """The cost scale, ``length**2``."""
        return self.length**2

    @property
    def force(self) -> float:
        """The control (force) scale, ``mass * length / time**2``."""
        return self.mass * self.length / self.time**2

    @property
    def speed(self) -> float:
        """The velocity scale, ``length / time``."""
        return self.length / self.time

    def _state_scale(self, nx: int) -> tuple[np.ndarray, np.ndarray]:
        n = nx // 4
        scale = np.r_[np.full(2 * n, self.length), np.full(2 * n, self.speed)]
        offset = np.r_[np.tile(self.offset, n), np.zeros(2 * n)]
        return scale, offset

    def states(self, s: Any) -> np.ndarray:
        """Canonical states (last axis ``nx``) in the scene's units."""
        s = np.asarray(s, dtype=float)
        scale, offset = self._state_scale(s.shape[-1])
        return s * scale + offset

    def costates(self, lam: Any) -> np.ndarray:
        """Canonical costates (``dJ/ds``, last axis ``nx``) in the scene's units."""
        lam = np.asarray(lam, dtype=float)
        scale, _ = self._state_scale(lam.shape[-1])
        return lam * (self.cost / scale)

    def controls_in(self, u: Any) -> np.ndarray:
        """Controls of the scene in canonical units."""
        return np.asarray(u, dtype=float) / self.force

    def initial_in(self, initial: Any) -> Any:
        """:func:`~hybridoc.reference.solve_reference`'s ``initial`` (``None``, controls or
        a Solution) for the canonical problem: its controls."""
        if initial is None:
            return None
        controls = getattr(initial, "controls", initial)
        try:
            u = np.asarray(controls, dtype=float)
        except (TypeError, ValueError):
            return controls  # the canonical problem's check names what is wrong
        return self.controls_in(u)

    def to_problem(self, sol: Any, problem: HybridOCP, rtol: float) -> Any:
        """The canonical Solution ``sol`` stated in the units of ``problem`` and judged on
        it (returns ``sol``, changed).

        The judge of ``problem`` gives the cost; where it disagrees with the canonical cost
        (times ``length**2``) by more than ``rtol``, or finds other events, the status says
        so (``disagree`` or ``events-differ``).
        """
        from hybridoc.solution import Status

        T, J = self.time, self.cost
        sol.controls = np.asarray(sol.controls, dtype=float) * self.force
        sol.time_grid = problem.time_grid()
        for name in ("state_times", "costate_times"):
            if getattr(sol, name) is not None:
                setattr(sol, name, np.asarray(getattr(sol, name), dtype=float) * T)
        if sol.states is not None:
            sol.states = self.states(sol.states)
        if sol.costates is not None:
            sol.costates = self.costates(sol.costates)
        sol.events = [dict(e, time=float(e["time"]) * T) for e in sol.events]
        sol.arrays = self._arrays(dict(sol.arrays))
        sol.info = self._info(sol.info)
        sol.reference = None  # the canonical ReferenceResult: see the module notes
        canonical_cost = float(sol.cost) * J
        sol.bind(problem)
        ev = sol.judge()
        sol.info["units"] = {
            "length": self.length,
            "time": self.time,
            "mass": self.mass,
            "offset": [float(v) for v in self.offset],
            "canonical_cost": canonical_cost,
        }
        judged = list(ev.sequence)
        mine = [e["guard"] for e in sol.events]
        if judged != mine:
            sol.set_status(
                Status.EVENTS_DIFFER,
                f"the judge in the problem's own units finds the events {judged}; the "
                f"reference, solved in its scaled units, has {mine}",
            )
        elif abs(sol.cost - canonical_cost) > self.agreement(rtol) * abs(canonical_cost):
            sol.set_status(
                Status.DISAGREE,
                f"the judge in the problem's own units gives the cost {sol.cost:.12g}; the "
                f"reference, solved in its scaled units, {canonical_cost:.12g}",
            )
        return sol

    def agreement(self, rtol: float) -> float:
        """How closely the judge in the problem's own units must agree with the canonical
        cost: ``rtol`` plus what the problem's own numbers resolve, ``16 eps`` times the
        distance of the offset in lengths (positions far from the origin in small units
        hold fewer digits of the scene: ``|offset| / length = 1e6`` leaves ``3.6e-9``)."""
        reach = float(np.max(np.abs(self.offset), initial=0.0)) / self.length
        return rtol + 16 * np.finfo(float).eps * reach

    def _arrays(self, a: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        T, J = self.time, self.cost
        out = dict(a)
        for name in ("event_times", "phase_starts", "arc_starts"):
            if name in a:
                out[name] = np.asarray(a[name], dtype=float) * T
        for name in ("phase_states", "arc_states"):
            if name in a:
                out[name] = self.states(a[name])
        for name in ("phase_costates", "arc_costates"):
            if name in a:
                out[name] = self.costates(a[name])
        if "multipliers" in a:  # of the gradients of gaps, which are lengths
            out["multipliers"] = np.asarray(a["multipliers"], dtype=float) * (J / self.length)
        if "control_coefficients" in a:  # u = c0 + c1 (t - t_k)
            C = np.array(a["control_coefficients"], dtype=float)
            C[:, 0] *= self.force
            C[:, 1] *= self.force / T
            out["control_coefficients"] = C
        if "event_controls" in a:
            out["event_controls"] = np.asarray(a["event_controls"], dtype=float) * self.force
        return out

    def _info(self, info: dict[str, Any]) -> dict[str, Any]:
        out = _costs_scaled(info, self.cost)
        for name in ("event_times",):
            if name in out:
                out[name] = [float(t) * self.time for t in out[name]]
        if "approach_speeds" in out:
            out["approach_speeds"] = [float(v) * self.speed for v in out["approach_speeds"]]
        return out


BAND = 16.0
"""The canonical scene's units are the scene's own scales rounded to a power of ``BAND``:
its lengths, times and masses stay within a factor 4 of their own scales (module notes)."""


def _band(scale: float) -> float:
    """``scale`` (a power of two) rounded to the nearest power of :data:`BAND`."""
    e = round(math.log2(pow2(scale)))
    b = round(math.log2(BAND))
    return math.ldexp(1.0, b * round(e / b))


_COST_KEYS = frozenset({"cost", "best_cost", "shooting_cost"})
_RESULT = re.compile(r"^cost (\S+) \((.*)\)$", re.DOTALL)


def _costs_scaled(value: Any, factor: float) -> Any:
    """``value`` (the info of a Solution) with every cost times ``factor``: the entries
    named in ``_COST_KEYS`` and the candidates' ``"result"`` lines (``"cost X (verdict)"``)."""
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            if k in _COST_KEYS and isinstance(v, float | int) and not isinstance(v, bool):
                out[k] = float(v) * factor
            elif k == "result" and isinstance(v, str) and (m := _RESULT.match(v)):
                out[k] = f"cost {float(m.group(1)) * factor:.12g} ({m.group(2)})"
            else:
                out[k] = _costs_scaled(v, factor)
        return out
    if isinstance(value, list):
        return [_costs_scaled(v, factor) for v in value]
    return value


def canonical(ocp: HybridOCP) -> Units | None:
    """The canonical problem of a disc scene whose scales are not the identity (module
    notes); ``None`` for any other problem (solved as it is)."""
    sc = ocp.scales
    if sc is None or sc.is_identity:
        return None
    scene = scene_of(ocp)  # the disc scene of the problem's data, or None
    if scene is None:
        return None
    n = scene.n_discs
    mass = sc.control[0] * sc.time**2 / sc.length if sc.control else 1.0
    # only whole bands of BAND (module notes): the scenes within a factor 4 of their own
    # units are solved as they are
    L, T, M = (_band(v) for v in (sc.length, sc.time, mass))
    off = np.asarray(sc.state_offset[:2], dtype=float)
    if L == T == M == 1.0 and not off.any():
        return None
    shift = -off / L
    force = M * L / T**2
    discs = []
    for d in scene.discs:
        kw: dict[str, Any] = dict(
            position=tuple(np.asarray(d.position, dtype=float) / L + shift),
            radius=d.radius / L,
            velocity=tuple(np.asarray(d.velocity, dtype=float) / (L / T)),
            mass=d.mass / M,
        )
        if d.initial_control is not None:
            kw["initial_control"] = np.asarray(d.initial_control, dtype=float) / force
        if d.target is not None:
            kw["target"] = tuple(np.asarray(d.target, dtype=float) / L + shift)
        discs.append(dataclasses.replace(d, **kw))
    walls = [
        dataclasses.replace(w, point=tuple(np.asarray(w.point, dtype=float) / L + shift))
        for w in scene.walls
    ]
    canon = dataclasses.replace(
        scene,
        discs=tuple(discs),
        walls=tuple(walls),
        horizon=scene.horizon / T,
        control_weight=scene.control_weight * M**2 / T**3,
        distribution=None,
    )
    c_ocp = canon.to_ocp()
    assert c_ocp.capabilities.geometry is not None and c_ocp.nx == 4 * n
    # the problem's own grid guess, in canonical units (a scene's initial_control may
    # have been replaced by HybridOCP.replace)
    c_ocp = c_ocp.replace(u_guess=np.asarray(ocp.u_guess, dtype=float) / force)
    return Units(ocp=c_ocp, length=L, time=T, mass=M, offset=off)
