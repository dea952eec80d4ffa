"""The public shooting system of one event sequence (:class:`ShootingSystem`,
:func:`shooting_system`) and the cache of compiled cores behind it."""

from __future__ import annotations

import weakref
from collections.abc import Sequence
from typing import Any

import casadi as ca
import numpy as np

from hybridoc.ocp import HybridOCP, Structure
from hybridoc.reference.shooting.common import (
    LEVELS,
    Arcs,
    built_once,
    full_law,
    global_law,
    has_closed_form_phases,
    path_rows,
    reset_bounds,
    reset_controls,
    residual_and_jacobian,
)
from hybridoc.reference.shooting.core import FlowCore
from hybridoc.reference.shooting.disc import DiscCore, disc_nlp
from hybridoc.reference.shooting.flow import flow_of

_CORES: weakref.WeakKeyDictionary[Structure, dict[Any, Any]] = weakref.WeakKeyDictionary()


class ShootingSystem:
    """The HMP system of one event sequence for one problem (its ``x0`` and ``T``).

    Parameters
    ----------
    ocp
        The problem.
    sequence
        Guard names, in event order.
    """

    def __init__(self, ocp: HybridOCP, sequence: list[str], core: Any = None) -> None:
        self.ocp = ocp
        self.core = core if core is not None else _core(ocp, list(sequence), None)
        self.x0 = np.asarray(ocp.x0, dtype=float)
        self.T = float(ocp.horizon)
        """The final time (a free final time's initial guess)."""

    def horizon_of(self, z: np.ndarray) -> float:
        """The final time at ``z`` (its last entry when free, else :attr:`T`)."""
        return float(z[-1]) if self.core.free else self.T

    def fixed_at(self, z: np.ndarray) -> tuple[ShootingSystem, np.ndarray]:
        """A free final time's system and point as the fixed-time system of the problem at
        the final time of ``z`` (``problem.replace(horizon=T)``) and its point: the same
        equations less ``H(T) = 0``. A fixed-time system returns itself."""
        if not self.core.free:
            return self, z
        ocp = self.ocp.replace(horizon=self.horizon_of(z))
        levels, arcs = self._spec()
        core = _core(ocp, self.sequence, levels, False, arcs)
        return ShootingSystem(ocp, self.sequence, core), z[:-1]

    def with_free(self, T: float | None = None) -> ShootingSystem:
        """The free-final-time system of the same sequence and steps (problem at ``T``)."""
        ocp = self.ocp if T is None else self.ocp.replace(horizon=float(T))
        levels, arcs = self._spec()
        return ShootingSystem(ocp, self.sequence, _core(ocp, self.sequence, levels, True, arcs))

    def _spec(self) -> tuple[tuple[int, ...] | None, Arcs | None]:
        """``(steps per arc, arcs)`` that rebuild this system's core (``None`` for disc)."""
        if self.disc:
            return None, None
        return self.core.arc_levels, self.core.arcs

    @property
    def spec(self) -> tuple[tuple[int, ...] | None, Arcs | None]:
        """What :func:`shooting_system` needs besides the problem and the sequence to
        rebuild this system: ``(levels, arcs)`` (``(None, None)`` for a disc scene)."""
        return self._spec()

    def switch_times(self, z: np.ndarray) -> list[list[float]]:
        """Per phase, the saturation switch times of ``z`` (empty lists without them)."""
        return [[float(t) for t in w] for w in self.core.unpack_switches(np.asarray(z, float))]

    def __getattr__(self, name: str) -> Any:
        # the core's compiled pieces (sequence, K, nx, nu, disc, levels, A, eps, guard_fns,
        # u_star, ...)
        if name == "core":
            raise AttributeError(name)
        return getattr(self.core, name)

    def F(self, z: np.ndarray) -> tuple[Any, Any]:
        """Residual and its Jacobian at ``z``."""
        return self.core.F(z, self.x0, self.T)

    def residual(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual and Jacobian as numpy arrays (non-finite on an evaluation failure)."""
        return residual_and_jacobian(_Bound(self), z)

    def traj(self, z: np.ndarray) -> list[np.ndarray]:
        """Phase starts, states, costates, costs and the end state of a point ``z``
        (:meth:`nodes` then follows its saturation switches)."""
        out = [np.asarray(x) for x in self.core.traj(z, self.x0, self.T)]
        self._switches = self.switch_times(z)
        self._etas = None if self.disc else self.core.eta_values(z)
        return out

    def phase_errors(self, z: np.ndarray) -> tuple[np.ndarray, float]:
        """Per phase, the estimated error the integration makes in the cost (step doubling,
        module notes), and the shooting cost; zeros for disc scenes (exact phases)."""
        if self.disc:
            out = self.traj(z)
            return np.zeros(self.K + 1), float(out[4].item()) + float(out[5].item())
        errors, cost, *_ = self.core.phase_errors(z, self.x0, self.T)
        return errors, cost

    def nodes(
        self,
        starts: np.ndarray,
        states: np.ndarray,
        costates: np.ndarray,
        T: float | None = None,
    ) -> list[np.ndarray]:
        """Generic problems: the nodes ``(n_k + 1, 2 nx + 1)`` of each phase's steps, from the
        phase starts, states and costates (``(K + 1,)``, ``(K + 1, nx)`` twice), up to the
        final time ``T`` (default :attr:`T`)."""
        return self.sample(starts, states, costates, self.core.levels, T)

    def sample(
        self,
        starts: np.ndarray,
        states: np.ndarray,
        costates: np.ndarray,
        counts: Sequence[int],
        T: float | None = None,
        switches: Sequence[Sequence[float]] | None = None,
        etas: Sequence[Sequence[float]] | None = None,
    ) -> list[np.ndarray]:
        """Generic problems: ``counts[k] + 1`` equally spaced nodes of each phase (as
        :meth:`nodes`), through the saturation switches ``switches`` and with the entry
        jumps ``etas`` of pure state rows (default: those of the last :meth:`traj`)."""
        end = self.T if T is None else float(T)
        if switches is None:
            switches = getattr(self, "_switches", None)
            if switches is None or len(switches) != self.K + 1:
                switches = [[]] * (self.K + 1)
        if etas is None and self.core.n_eta:
            etas = getattr(self, "_etas", None)
        lengths = self.core.arc_lengths(starts, end, switches)
        return self.core.phase_nodes(states, costates, lengths, counts, etas)

    @property
    def arc_levels(self) -> tuple[int, ...]:
        """Generic problems: the DOP853 steps of each arc (phase-major)."""
        return self.core.arc_levels

    def with_levels(self, levels: tuple[int, ...]) -> ShootingSystem:
        """The same system with other numbers of steps per arc (generic problems; one arc
        per phase without saturation switches)."""
        core = _core(self.ocp, self.sequence, levels, self.core.free, self.core.arcs)
        return ShootingSystem(self.ocp, self.sequence, core)

    def with_arcs(self, arcs: Arcs, levels: tuple[int, ...] | None = None) -> ShootingSystem:
        """The same sequence and final-time mode with other arcs (generic flow)."""
        core = _core(self.ocp, self.sequence, levels, self.core.free, arcs)
        return ShootingSystem(self.ocp, self.sequence, core)

    def solve_nlp(
        self, gamma0: np.ndarray, coeffs0: np.ndarray, max_iter: int = 100
    ) -> tuple[np.ndarray, bool, float]:
        """Disc scenes: IPOPT on event times and linear-in-time phase controls.

        Returns
        -------
        z, success, infeasibility
            Starting point for Newton on the HMP system (costates of the NLP's control by
            the adjoint with the HMP jump relation), IPOPT's success flag and the largest
            violation of the NLP's constraints (guards, approach, time order) at its point.
        """
        nlp = disc_nlp(self.ocp, self.K, max_iter)
        solver, lbg, ubg, to_z = nlp.solver, nlp.lbg, nlp.ubg, nlp.to_z
        K, nu = self.K, self.nu
        lbw = [0.0] * K + [-ca.inf] * ((K + 1) * 2 * nu)
        ubw = [self.T] * K + [ca.inf] * ((K + 1) * 2 * nu)
        par = np.concatenate([self.x0, [self.T], self.guard_index])
        w0 = np.concatenate([np.asarray(gamma0, float), np.asarray(coeffs0, float).ravel()])
        sol = solver(x0=w0, p=par, lbg=lbg, ubg=ubg, lbx=lbw, ubx=ubw)
        ok = bool(solver.stats()["success"])
        w = np.asarray(sol["x"]).ravel()
        g = np.asarray(sol["g"], dtype=float).ravel()
        viol = np.maximum(np.asarray(lbg, float) - g, g - np.asarray(ubg, float))
        infeasibility = float(np.max(viol, initial=0.0)) if np.all(np.isfinite(g)) else np.inf
        return np.asarray(to_z(w, par)).ravel(), ok, infeasibility

    def z_from_controls(self, gamma: np.ndarray, coeffs: np.ndarray) -> np.ndarray:
        """Disc scenes: HMP unknowns from event times and linear phase controls (their
        adjoint costates, with the HMP jump rule)."""
        to_z = disc_nlp(self.ocp, self.K).to_z
        par = np.concatenate([self.x0, [self.T], self.guard_index])
        w = np.concatenate([np.asarray(gamma, float), np.asarray(coeffs, float).ravel()])
        return np.asarray(to_z(w, par)).ravel()


class _Bound:
    """``F(z)`` with the system's data bound (for :func:`residual_and_jacobian`)."""

    def __init__(self, system: ShootingSystem) -> None:
        self.system = system

    def __call__(self, z: np.ndarray) -> tuple[Any, Any]:
        return self.system.F(z)

    def size1_out(self, i: int) -> int:
        return int(self.system.core.F.size1_out(i))


def _core(
    ocp: HybridOCP,
    sequence: list[str],
    levels: Any,
    free: bool | None = None,
    arcs: Arcs | None = None,
) -> Any:
    """The compiled core of ``(structure, sequence)`` (and steps per arc, whether the final
    time is an unknown: default, whether the problem's is free, and the arcs: default one
    per phase under the problem's bounds), shared."""
    # levels name a generic flow: a disc scene's extremal with active bounds (the
    # closed-form phases have no saturation)
    disc = has_closed_form_phases(ocp) and arcs is None and (levels is None or not ocp.has_bounds)
    free = ocp.free_horizon if free is None else bool(free)
    if not disc:
        if arcs is None:
            arcs = ((global_law(ocp),),) * (len(sequence) + 1)
        width = ocp.nu + path_rows(ocp)
        arcs = tuple(tuple(full_law(m, width) for m in p) for p in arcs)
        if len(arcs) != len(sequence) + 1:
            raise ValueError(f"arcs: one tuple per phase ({len(sequence) + 1}), got {len(arcs)}")
        if levels is None:
            levels = LEVELS.get(ocp.structure, {}).get((tuple(sequence), arcs))
        if levels is None:
            fl = flow_of(ocp)
            levels = tuple(fl.law(m).start_steps for p in arcs for m in p)
    # the bounds of the resets' own controls enter the compiled conditions (data, not
    # structure: part of the key)
    comps = dict(zip([g.name for g in ocp.guards], reset_controls(ocp), strict=True))
    vkey = None
    if any(comps.get(n) for n in sequence):
        vkey = tuple(tuple(map(float, b)) for b in reset_bounds(ocp))
    key = (tuple(sequence), None if disc else tuple(int(n) for n in levels), free, arcs, vkey)
    cores = _CORES.setdefault(ocp.structure, {})
    return built_once(
        cores,
        key,
        lambda: (
            DiscCore(ocp, list(sequence))
            if disc
            else FlowCore(ocp, list(sequence), key[1], free, arcs)
        ),
    )


def shooting_system(
    ocp: HybridOCP,
    sequence: list[str],
    levels: tuple[int, ...] | None = None,
    *,
    free: bool | None = None,
    arcs: Arcs | None = None,
) -> ShootingSystem:
    """The system for ``(ocp, sequence)``; the compiled core is shared by every problem with
    the same structure.

    Parameters
    ----------
    ocp, sequence
        The problem and the guard names in event order.
    levels
        Generic problems: DOP853 steps on each of the ``K + 1`` phases; default: those the
        sequence was last accepted at by :func:`refine` (for this structure), else
        :data:`SUBSTEPS_POLYNOMIAL` or :data:`SUBSTEPS` each. Ignored for disc scenes.
    free
        Whether the final time is an unknown (its guess ``ocp.horizon``); default: whether
        ``ocp`` has a free final time. ``False`` on such a problem solves it at
        ``ocp.horizon`` (a final time at its bound, or an extremal already found).
    arcs
        The control law of each arc of each phase (saturation switches
        between arcs as unknowns); ``levels`` then counts steps per arc. Default: one arc
        per phase, ``u* = clip(argmin H, u_min, u_max)`` (``argmin H`` without bounds), and
        a disc scene's closed-form phases.
    """
    core = _core(ocp, list(sequence), levels, free, arcs)
    return ShootingSystem(ocp, list(sequence), core)
