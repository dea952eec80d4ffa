"""The shooting core of one (structure, sequence): the unknowns ``z`` and their layout, the
residual assembled from phase maps (:class:`CoreBase`), and the generic problems' core whose
arcs are DOP853 maps of their laws (:class:`FlowCore`)."""

from __future__ import annotations

import itertools
import math
import weakref
from collections.abc import Sequence
from typing import Any

import casadi as ca
import numpy as np

from hybridoc.errors import SceneError
from hybridoc.ocp import HybridOCP
from hybridoc.reference.shooting.common import (
    LOCK,
    Arcs,
    checked_hamiltonian,
    fischer_burmeister,
    free_mode,
    global_law,
    has_closed_form_phases,
    reset_bounds,
    reset_controls,
    state_rows,
    switch_of,
    terminal_sizes,
)
from hybridoc.reference.shooting.flow import flow_of

EVENT_CONTROL_SAMPLES = 65
"""Samples per component (up to two components; 4096 points in all beyond) on which the
shooting's start looks for the minimum of ``lambda^T g`` over a reset's own control."""


class CoreBase:
    """The unknowns of one (structure, sequence) and their layout."""

    def __init__(
        self, ocp: HybridOCP, sequence: list[str], free: bool = False, arcs: Arcs | None = None
    ) -> None:
        names = [g.name for g in ocp.guards]
        unknown = [s for s in sequence if s not in names]
        if unknown:
            raise SceneError(f"unknown guard name(s) {unknown}; this problem has {names}")
        reason = checked_hamiltonian(ocp)
        if reason:
            raise SceneError(reason)
        self.sequence = list(sequence)
        self.guard_index = [names.index(s) for s in sequence]
        self.K = len(sequence)
        self.nx, self.nu = ocp.nx, ocp.nu
        self.disc = has_closed_form_phases(ocp)
        self.levels: tuple[int, ...] | None = None
        self.m_eq, self.m_in = terminal_sizes(ocp)
        self.free = bool(free)
        if arcs is None:
            arcs = (((free_mode(ocp.nu)),),) * (self.K + 1)
        self.arcs: Arcs = arcs
        # per phase, (arc, component, value) of each saturation switch, in time order
        self.switches: list[list[tuple[int, int, float]]] = [
            [switch_of(a, b, k, j) for j, (a, b) in enumerate(zip(p[:-1], p[1:], strict=True))]
            for k, p in enumerate(arcs)
        ]
        self.n_switch = sum(len(w) for w in self.switches)
        # resets that read the control: per event, the components of its own control v_k
        # (unknowns after the switches, before a free T; 0 where the reset reads none)
        comps = reset_controls(ocp)
        self.v_comps: list[tuple[int, ...]] = [comps[j] for j in self.guard_index]
        self.n_v = sum(len(c) for c in self.v_comps)
        self.v_bounds = reset_bounds(ocp)
        # per phase and switch, the pure state row whose boundary arc the switch enters
        # (-1 for any other switch): there c_r(s) = 0 and the costate jumps by
        # eta grad c_r, with eta an unknown of its own (after the switch times)
        pure = state_rows(ocp)
        self.jump_rows: list[list[int]] = [
            [
                i - self.nu
                if i >= self.nu and i - self.nu in pure and p[j + 1][i] == (0.0, 0.0)
                else -1
                for j, i, _ in w
            ]
            for p, w in zip(arcs, self.switches, strict=True)
        ]
        self.n_eta = sum(r >= 0 for w in self.jump_rows for r in w)
        self._residual_fns: tuple[Any, Any] | None = None
        self._ocp_ref = weakref.ref(ocp)

    @property
    def F(self) -> Any:
        """``(residual, Jacobian)`` of ``(z, x0, T)``; built on first use, since the
        search solves many sequences' NLPs whose Newton step never comes."""
        return self._residual()[0]

    @property
    def traj(self) -> Any:
        """Phase starts, states, costates, costs, ... of ``(z, x0, T)`` (see ``F``)."""
        return self._residual()[1]

    def _residual(self) -> tuple[Any, Any]:
        if self._residual_fns is None:
            ocp = self._ocp_ref()
            if ocp is None:
                raise RuntimeError("the problem of this shooting core no longer exists")
            with LOCK:
                if self._residual_fns is None:
                    self._residual_fns = self._build_residual(ocp)
        return self._residual_fns

    def _build_residual(self, ocp: HybridOCP) -> tuple[Any, Any]:
        raise NotImplementedError

    @property
    def nz(self) -> int:
        """Number of unknowns."""
        return (
            self.nx + self.K * (self.nx + 2) + self.m_eq + self.m_in + self.n_switch
            + self.n_eta + self.n_v + int(self.free)
        )  # fmt: skip

    def unpack_switches(self, z: Any) -> list[list[Any]]:
        """Per phase, its saturation switch times (absolute), in time order."""
        o = self.nx + self.K * (self.nx + 2) + self.m_eq + self.m_in
        out = []
        for w in self.switches:
            out.append([z[o + i] for i in range(len(w))])
            o += len(w)
        return out

    def unpack_etas(self, z: Any) -> list[list[Any]]:
        """Per phase and switch, the costate jump ``eta`` at the entry of a pure state
        row's boundary arc (0 at any other switch)."""
        o = self.nx + self.K * (self.nx + 2) + self.m_eq + self.m_in + self.n_switch
        out = []
        for w in self.jump_rows:
            row = []
            for r in w:
                if r >= 0:
                    row.append(z[o])
                    o += 1
                else:
                    row.append(0.0)
            out.append(row)
        return out

    def with_switches(
        self,
        z_base: np.ndarray,
        times: Sequence[Sequence[float]],
        etas: Sequence[Sequence[float]] | None = None,
    ) -> np.ndarray:
        """``z`` of this core from a point of the same sequence without saturation switches
        (``z_base``: multipliers, costates, terminal multipliers and a free ``T``), the
        switch times per phase and, per phase and switch, the costate jumps ``eta`` of the
        entries of pure state rows' boundary arcs (default 0; other switches' are
        ignored)."""
        z_base = np.asarray(z_base, dtype=float)
        o = self.nx + self.K * (self.nx + 2) + self.m_eq + self.m_in
        flat = [float(t) for w in times for t in w]
        if len(flat) != self.n_switch:
            raise ValueError(f"{self.n_switch} switch times expected, got {len(flat)}")
        jumps = [
            0.0 if etas is None else float(etas[k][j])
            for k, w in enumerate(self.jump_rows)
            for j, r in enumerate(w)
            if r >= 0
        ]
        return np.concatenate([z_base[:o], flat, jumps, z_base[o:]])

    def strip_switches(self, z: np.ndarray) -> np.ndarray:
        """The point without its switch times and entry jumps (:meth:`with_switches`'s
        ``z_base``)."""
        o = self.nx + self.K * (self.nx + 2) + self.m_eq + self.m_in
        return np.concatenate([z[:o], z[o + self.n_switch + self.n_eta :]])

    def entry_jump(self, k: int, i: int, s: Any, lam: Any, eta: Any) -> Any:
        """The costate after switch ``i`` of phase ``k``: ``lambda + eta grad c_r(s)`` at
        the entry of pure state row ``r``'s boundary arc (``lambda(t1-) = lambda(t1+) -
        eta grad c_r``, ``eta >= 0``: the measure ``-d nu`` of the direct adjoining's
        multiplier), ``lambda`` at any other switch."""
        r = self.jump_rows[k][i]
        if r < 0:
            return lam
        grad = self.fl.state_fn(s)[1]
        if isinstance(lam, np.ndarray):
            return lam + float(eta) * np.asarray(grad, dtype=float)[r]
        return lam + eta * grad[r, :].T

    def unpack_event_controls(self, z: Any) -> list[Any]:
        """Per event, the control its reset reads: ``v_k`` (``(nu,)``, its components from
        ``z``, 0 in those the reset does not read) for a reset that reads the control,
        ``None`` for any other."""
        o = self.nz - int(self.free) - self.n_v
        numeric = isinstance(z, np.ndarray)
        out: list[Any] = []
        for comps in self.v_comps:
            if not comps:
                out.append(None)
                continue
            parts: list[Any] = []
            for i in range(self.nu):
                if i in comps:
                    parts.append(z[o])
                    o += 1
                else:
                    parts.append(0.0)
            out.append(np.array(parts, dtype=float) if numeric else ca.vertcat(*parts))
        return out

    def with_event_controls(self, z: np.ndarray, controls: Sequence[Any]) -> np.ndarray:
        """``z`` with the reset controls ``controls`` (per event a ``(nu,)`` control or
        ``None``; only the components each reset reads are taken)."""
        z = np.array(z, dtype=float)
        o = self.nz - int(self.free) - self.n_v
        for comps, v in zip(self.v_comps, controls, strict=True):
            for i in comps:
                if v is not None:
                    z[o] = float(np.asarray(v, dtype=float).ravel()[i])
                o += 1
        return z

    def guard_at(self, k: int, s: Any, v: Any = None) -> Any:
        """``(psi, grad psi, g, Dg)`` of event ``k``'s guard at ``s``: a reset that reads the
        control at ``v`` (``Dg`` its Jacobian in ``s`` there)."""
        fn = self.guard_fns[k]
        return fn(s) if v is None else fn(s, v)

    def event_control_conditions(self, k: int, s: Any, v: Any, lam: Any) -> list[Any]:
        """The conditions of event ``k``'s reset control ``v`` at ``s(gamma-)`` and
        ``lambda(gamma+)``: per component ``i`` it reads, with ``d_i = d/dv_i lambda^T
        g(s, v)``, ``v_i - clip(v_i - d_i, lo_i, hi_i)``: zero exactly when ``d_i = 0``
        inside the bounds, ``d_i >= 0`` at the lower bound and ``d_i <= 0`` at the upper one
        (the first-order conditions of the box-constrained minimum; ``d_i`` alone without
        bounds). One system decides which bounds are active, as the Fischer-Burmeister
        terms do for terminal inequalities."""
        comps = self.v_comps[k]
        if not comps:
            return []
        d = self.reset_grads[k](s, v, lam)
        lo, hi = self.v_bounds
        out = []
        for i in comps:
            if lo[i] == -math.inf and hi[i] == math.inf:
                out.append(d[i])
                continue
            w = v[i] - d[i]
            if lo[i] > -math.inf:
                w = ca.fmax(w, float(lo[i]))
            if hi[i] < math.inf:
                w = ca.fmin(w, float(hi[i]))
            out.append(v[i] - w)
        return out

    def start_event_control(
        self, k: int, s: np.ndarray, lam: np.ndarray, hint: Any = None
    ) -> np.ndarray | None:
        """A start for event ``k``'s reset control at ``s(gamma-)`` and ``lambda(gamma+)``:
        the least ``lambda^T g(s, v)`` over samples of the bounds of the components the
        reset reads (:data:`EVENT_CONTROL_SAMPLES`; a side without a bound sampled up to
        100 from the other), the pointwise minimum the HMP asks of ``v``; ``hint`` (default
        0 clipped into the bounds) where no sample is lower. ``None`` for a reset that does
        not read the control."""
        comps = self.v_comps[k]
        if not comps:
            return None
        lo, hi = self.v_bounds
        base = np.zeros(self.nu) if hint is None else np.array(hint, dtype=float).ravel()
        base = np.clip(base, lo, hi)
        axes = []
        for i in comps:
            a, b = lo[i], hi[i]
            n = EVENT_CONTROL_SAMPLES
            far = np.concatenate([[0.0], np.logspace(-3, 2, n - 1)])
            if math.isfinite(a) and math.isfinite(b):
                axes.append(np.linspace(a, b, n))
            elif math.isfinite(a):
                axes.append(a + far)
            elif math.isfinite(b):
                axes.append(b - far)
            else:
                axes.append(np.concatenate([-far[:0:-1], far]))
        if len(axes) <= 2:
            grid = np.array(list(itertools.product(*axes)), dtype=float)
        else:
            rng = np.random.default_rng(0)
            grid = np.column_stack([rng.choice(ax, 4096) for ax in axes])
        V = np.repeat(base[None, :], grid.shape[0] + 1, axis=0)
        V[1:, list(comps)] = grid
        fn = self.reset_values[k]
        vals = np.asarray(
            fn.map(V.shape[0])(np.repeat(np.asarray(s, float).reshape(-1, 1), V.shape[0], 1),
                               V.T, np.repeat(np.asarray(lam, float).reshape(-1, 1),
                                              V.shape[0], 1)),
            dtype=float,
        ).ravel()  # fmt: skip
        vals = np.where(np.isfinite(vals), vals, np.inf)
        j = int(np.argmin(vals))
        if not vals[j] < vals[0] - 1e-12 * (1.0 + abs(vals[0])):
            return base
        return V[j]

    def horizon(self, z: Any, T: Any) -> Any:
        """The final time at ``z``: its last entry when free, else the parameter ``T``."""
        return z[self.nz - 1] if self.free else T

    def unpack_terminal(self, z: Any) -> tuple[Any, Any]:
        """The terminal multipliers ``nu`` (equalities) and ``mu`` (inequalities)."""
        o = self.nx + self.K * (self.nx + 2)
        return z[o : o + self.m_eq], z[o + self.m_eq : o + self.m_eq + self.m_in]

    def unpack(self, z: Any) -> tuple[Any, list[Any], list[Any], list[Any]]:
        """``lambda(0)``, event times, multipliers, post-event costates."""
        nx = self.nx
        lam0 = z[:nx]
        gam, pis, lps = [], [], []
        for k in range(self.K):
            o = nx + k * (nx + 2)
            gam.append(z[o])
            pis.append(z[o + 1])
            lps.append(z[o + 2 : o + 2 + nx])
        return lam0, gam, pis, lps

    def pack(
        self,
        lam0: np.ndarray,
        gam: Any,
        pis: Any,
        lps: Any,
        nu: Any = None,
        mu: Any = None,
        T: float | None = None,
        v: Sequence[Any] | None = None,
    ) -> np.ndarray:
        """Inverse of :meth:`unpack` (and :meth:`unpack_terminal`) for numbers: the terminal
        multipliers default to 0, a free final time to ``T`` (required then), the reset
        controls (per event ``(nu,)`` or ``None``, :meth:`unpack_event_controls`) to 0
        clipped into the bounds."""
        parts = [np.asarray(lam0, float).ravel()]
        for k in range(self.K):
            parts += [[float(gam[k]), float(pis[k])], np.asarray(lps[k], float).ravel()]
        parts.append(np.zeros(self.m_eq) if nu is None else np.asarray(nu, float).ravel())
        parts.append(np.zeros(self.m_in) if mu is None else np.asarray(mu, float).ravel())
        if self.n_switch:
            raise ValueError("a point with saturation switches is made by with_switches()")
        lo, hi = self.v_bounds
        for k, comps in enumerate(self.v_comps):
            given = None if v is None or v[k] is None else np.asarray(v[k], float).ravel()
            parts.append(np.array(
                [float(np.clip(0.0 if given is None else given[i], lo[i], hi[i])) for i in comps]
            ))  # fmt: skip
        if self.free:
            if T is None:
                raise ValueError("a free final time needs its value in pack(T=...)")
            parts.append(np.array([float(T)]))
        return np.concatenate(parts)

    def _assemble(
        self, ocp: HybridOCP, phase: Any, sym: Any, extra: Sequence[Any] = ()
    ) -> tuple[ca.Function, ca.Function]:
        """The residual (with its Jacobian) and the trajectory function, from ``phase(k, s,
        lambda, h) -> (s, lambda, running cost)`` and the symbol type ``sym``; ``extra``:
        symbols the pieces read besides ``(z, x0, T)``, inputs after them."""
        nx = self.nx
        z = sym.sym("z", self.nz)
        x0 = sym.sym("x0", nx)
        T_par = sym.sym("T")
        T = self.horizon(z, T_par)
        lam, gam, pis, lps = self.unpack(z)
        s: Any = x0
        t: Any = 0.0
        res = []
        starts, s_starts, l_starts, costs, s_minus, l_minus, rates = [], [], [], [], [], [], []
        sig = self.unpack_switches(z)
        etas = self.unpack_etas(z)
        switch_res: list[Any] = []
        vs = self.unpack_event_controls(z)
        v_res: list[Any] = []
        for k in range(self.K):
            starts.append(t)
            s_starts.append(s)
            l_starts.append(lam)
            sm, lm, J = self._phase_arcs(phase, k, s, lam, t, gam[k], sig, etas, switch_res)
            costs.append(J)
            # a reset that reads the control: s+ = g(s-, v_k), Dg its Jacobian at v_k
            psi, gpsi, sp, Dg = self.guard_at(k, sm, vs[k])
            lp = lps[k]
            v_res += self.event_control_conditions(k, sm, vs[k], lp)
            before, after = self.law_at(k, -1), self.law_at(k + 1, 0)
            res.append(psi)
            res.append(lm - ca.mtimes(Dg.T, lp) - pis[k] * gpsi)
            res.append(before.H_star(sm, lm) - after.H_star(sp, lp))
            s_minus.append(sm)
            l_minus.append(lm)
            rates.append(ca.dot(gpsi, ocp.f(sm, before.u_star(sm, lm))))
            s, lam, t = sp, lp, gam[k]
        starts.append(t)
        s_starts.append(s)
        l_starts.append(lam)
        sT, lT, J = self._phase_arcs(phase, self.K, s, lam, t, T, sig, etas, switch_res)
        costs.append(J)
        phiT, H_T = self._terminal_residual(z, sT, lT, res)
        res += switch_res
        res += v_res
        if self.free:
            res.append(H_T)
        R = ca.vertcat(*res)
        F = ca.Function("hmp_F", [z, x0, T_par, *extra], [R, ca.jacobian(R, z)])
        outputs = _traj_outputs(
            nx, starts, s_starts, l_starts, costs, phiT, s_minus, l_minus, rates, sT, lT, T, H_T
        )
        traj = ca.Function("hmp_traj", [z, x0, T_par, *extra], outputs)
        return F, traj

    def _phase_arcs(
        self,
        phase: Any,
        k: int,
        s: Any,
        lam: Any,
        t0: Any,
        t1: Any,
        sig: list[list[Any]],
        etas: list[list[Any]],
        switch_res: list[Any],
    ) -> tuple[Any, Any, Any]:
        """Phase ``k`` of :meth:`_assemble` from ``(s, lambda)`` at ``t0`` to ``t1``: its
        arcs, with the switching condition ``u_unc_i = value`` at each switch appended to
        ``switch_res``; the entry of a pure state row's boundary arc also needs ``c_r(s) =
        0``, and the costate jumps there."""
        ends = [t0, *sig[k], t1]
        J: Any = 0
        for j in range(len(self.arcs[k])):
            if j:
                switch_res.append(self.switch_condition(k, j, s, lam))
                r = self.jump_rows[k][j - 1]
                if r >= 0:
                    switch_res.append(self.fl.state_fn(s)[0][r])
                    lam = self.entry_jump(k, j - 1, s, lam, etas[k][j - 1])
            s, lam, Jj = phase(k, j, s, lam, ends[j + 1] - ends[j])
            J = Jj if j == 0 else J + Jj
        return s, lam, J

    def _terminal_residual(self, z: Any, sT: Any, lT: Any, res: list[Any]) -> tuple[Any, Any]:
        """Transversality first in ``res`` (with the terminal constraints' multipliers and,
        at its end, their conditions); returns ``phi(s(T))`` and ``H(T)``."""
        phiT, gphi = self.phi(sT)
        if self.terminal is None:
            res.insert(0, lT - gphi)
        else:
            # lambda(T) = grad phi - Dh_eq^T nu - Dh_in^T mu (module notes)
            nu, mu = self.unpack_terminal(z)
            h_eq, D_eq, h_in, D_in = self.terminal(sT)
            res.insert(0, lT - gphi + ca.mtimes(D_eq.T, nu) + ca.mtimes(D_in.T, mu))
            res.append(h_eq)
            res.append(fischer_burmeister(mu, h_in))
        return phiT, self.law_at(self.K, -1).H_star(sT, lT)

    def law_at(self, k: int, j: int) -> Any:
        """The law (``u_star``, ``H_star``) of arc ``j`` of phase ``k``."""
        return self  # disc scenes: one law

    def switch_condition(self, k: int, j: int, s: Any, lam: Any) -> Any:
        """The equation of the switch into arc ``j`` of phase ``k`` at ``(s, lambda)``:
        ``argmin H_i = bound`` for a saturation; on a problem with path constraints the
        free side's ``u*_i = bound``, or ``c_r(s, u*) = 0`` under the law without the row
        (``u`` is continuous at a junction: ``nu_r = 0`` there)."""
        _, i, value = self.switches[k][j - 1]
        fl = getattr(self, "fl", None)
        if fl is None or not fl.m_path:
            return self.u_unc(s, lam)[i] - value
        a = self.arcs[k][j - 1]
        free = self.law_at(k, j - 1) if a[i][0] != a[i][1] else self.law_at(k, j)
        u = free.u_star(s, lam)
        if i < self.nu:
            return u[i] - value
        return fl.c(s, u)[i - self.nu]


def _traj_outputs(
    nx: int,
    starts: list[Any],
    s_starts: list[Any],
    l_starts: list[Any],
    costs: list[Any],
    phiT: Any,
    s_minus: list[Any],
    l_minus: list[Any],
    rates: list[Any],
    sT: Any,
    lT: Any,
    T: Any,
    H_T: Any,
) -> list[Any]:
    """The outputs of the trajectory function of :meth:`CoreBase._assemble`: phase starts,
    states, costates and costs, ``phi(s(T))``, the running cost, the states, costates and
    guard rates before each event, ``s(T)``, ``lambda(T)``, ``T`` and ``H(T)``."""
    running = sum(costs[1:], costs[0])
    hc = ca.horzcat
    return [
        hc(*starts),
        hc(*s_starts),
        hc(*l_starts),
        hc(*costs),
        phiT,
        running,
        hc(*s_minus) if s_minus else ca.DM(nx, 0),
        hc(*l_minus) if l_minus else ca.DM(nx, 0),
        hc(*rates) if rates else ca.DM(1, 0),
        sT,
        lT,
        T,
        H_T,
    ]


class FlowCore(CoreBase):
    """Other problems: one (structure, sequence, arcs, steps per arc); the arcs are the
    structure's DOP853 maps of their laws (:class:`Law`), composed in MX."""

    def __init__(
        self,
        ocp: HybridOCP,
        sequence: list[str],
        levels: tuple[int, ...],
        free: bool = False,
        arcs: Arcs | None = None,
    ) -> None:
        super().__init__(ocp, sequence, free, arcs)
        self.disc = False  # a disc scene with active bounds takes the generic flow
        fl = flow_of(ocp)
        self.fl = fl
        self.n_arcs = sum(len(p) for p in self.arcs)
        if len(levels) != self.n_arcs or any(int(n) < 1 for n in levels):
            raise ValueError(f"steps per arc: {self.n_arcs} positive integers, got {levels}")
        self.arc_levels = tuple(int(n) for n in levels)
        # per phase: the steps of its arcs together (the uniform grid of its dense output)
        self.levels = []
        self._arc_index: list[list[int]] = []
        i = 0
        for p in self.arcs:
            self._arc_index.append(list(range(i, i + len(p))))
            self.levels.append(sum(self.arc_levels[i : i + len(p)]))
            i += len(p)
        self.levels = tuple(self.levels)
        self.laws = [[fl.law(m) for m in p] for p in self.arcs]
        # the dense output's law: the problem's clip (the constrained minimum of H with
        # path constraints), right on every arc of a consistent extremal (the
        # unconstrained flow itself without constraints)
        self.flow: Any = fl.law(global_law(ocp)) if ocp.has_bounds or fl.m_path else fl
        self.u_star, self.H, self.H_star, self.f = fl.u_star, fl.H, fl.H_star, fl.f
        self.u_unc = fl.u_unc
        self.rhs, self.polynomial, self.phi = fl.rhs, fl.polynomial, fl.phi
        self.terminal = fl.terminal
        self.guard_fns = [fl.guards[j] for j in self.guard_index]
        self.reset_values = [fl.reset_values[j] for j in self.guard_index]
        self.reset_grads = [fl.reset_grads[j] for j in self.guard_index]

    def law_at(self, k: int, j: int) -> Any:
        return self.laws[k][j]

    def _build_residual(self, ocp: HybridOCP) -> tuple[Any, Any]:
        def phase(k: int, j: int, s: Any, lam: Any, h: Any) -> Any:
            return self.laws[k][j].phase(self.arc_levels[self._arc_index[k][j]])(s, lam, h)

        return self._assemble(ocp, phase, ca.MX)

    def arc_lengths(self, starts: np.ndarray, T: float, switches: Any) -> list[list[float]]:
        """Per phase, the lengths of its arcs."""
        ends = np.append(np.asarray(starts, dtype=float).ravel(), float(T))
        out = []
        for k in range(self.K + 1):
            cuts = [float(ends[k]), *[float(t) for t in switches[k]], float(ends[k + 1])]
            out.append(list(np.diff(cuts)))
        return out

    def switch_values(self, z: np.ndarray) -> list[list[float]]:
        """Per phase, the switch times of ``z`` as floats."""
        return [[float(t) for t in w] for w in self.unpack_switches(np.asarray(z, dtype=float))]

    def eta_values(self, z: np.ndarray) -> list[list[float]]:
        """Per phase and switch, the entry jumps ``eta`` of ``z`` as floats (0 where none)."""
        return [[float(e) for e in w] for w in self.unpack_etas(np.asarray(z, dtype=float))]

    def phase_errors(
        self, z: np.ndarray, x0: np.ndarray, T: float
    ) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
        """Per arc, the step-doubling estimate of the error it makes in the cost.

        Returns
        -------
        errors, cost, starts, states, costates
            ``|J_n - J_2n| + |lambda_end| . |s_n - s_2n|`` of each arc from its start (one
            arc per phase without saturation switches), the shooting cost, and the phase
            starts, states and costates.
        """
        out = [np.asarray(x) for x in self.traj(z, x0, T)]
        starts, s0, l0 = out[0].ravel(), out[1], out[2]
        cost = float(out[4].item()) + float(out[5].item())
        lengths = self.arc_lengths(starts, float(out[11].item()), self.switch_values(z))
        etas = self.eta_values(z)
        errors = np.zeros(self.n_arcs)
        for k in range(self.K + 1):
            s, lam = s0[:, k], l0[:, k]
            for j, law in enumerate(self.laws[k]):
                if j:
                    lam = self.entry_jump(k, j - 1, s, lam, etas[k][j - 1])
                i = self._arc_index[k][j]
                n, h = self.arc_levels[i], lengths[k][j]
                a = [np.asarray(v).ravel() for v in law.phase(n)(s, lam, h)]
                b = [np.asarray(v).ravel() for v in law.phase(2 * n)(s, lam, h)]
                errors[i] = abs(float(a[2][0] - b[2][0])) + float(
                    np.abs(b[1]) @ np.abs(a[0] - b[0])
                )
                s, lam = a[0], a[1]
        return errors, cost, starts, s0, l0

    def phase_nodes(
        self,
        states: np.ndarray,
        costates: np.ndarray,
        lengths: list[list[float]],
        counts: Sequence[int],
        etas: Sequence[Sequence[float]] | None = None,
    ) -> list[np.ndarray]:
        """Per phase, ``counts[k] + 1`` equally spaced nodes ``(s, lambda, running cost)``
        from its start state and costate through its arcs (``lengths``): the compiled map
        on a phase of one arc, else DOP853 steps that stop at each switch (where the
        costate jumps by ``etas[k][j]`` at the entry of a pure state row's boundary arc)."""
        out = []
        for k in range(self.K + 1):
            n = int(counts[k])
            laws = self.laws[k]
            if len(laws) == 1:
                out.append(
                    np.asarray(laws[0].nodes(n)(states[k], costates[k], lengths[k][0])).T.copy()
                )
                continue
            h = sum(lengths[k]) / n
            nx = self.nx
            cuts = np.cumsum(lengths[k])[:-1]
            x = np.concatenate([states[k], costates[k], [0.0]])
            rows = [x.copy()]
            t, j = 0.0, 0
            for i in range(1, n + 1):
                target = i * h
                while j < len(cuts) and cuts[j] < target:
                    x = np.asarray(laws[j].step(x, cuts[j] - t)).ravel()
                    if etas is not None:
                        x[nx : 2 * nx] = self.entry_jump(k, j, x[:nx], x[nx : 2 * nx], etas[k][j])
                    t, j = float(cuts[j]), j + 1
                x = np.asarray(laws[j].step(x, target - t)).ravel()
                t = target
                rows.append(x.copy())
            out.append(np.array(rows))
        return out
