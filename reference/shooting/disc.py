"""The closed-form phases of a problem with a linear control flow ``f = (v, A u)``,
``L = eps |u|^2`` (:func:`~hybridoc.reference.shooting.has_closed_form_phases`; a compiled
disc scene offers it): polynomial phases, the residual shared by every sequence of one
length, and the NLP in event times and linear-in-time phase controls that starts Newton."""

from __future__ import annotations

import threading
import weakref
from typing import Any

import casadi as ca
import numpy as np

from hybridoc.ocp import HybridOCP, Structure
from hybridoc.reference.shooting.common import (
    LOCK,
    argmin_hamiltonian,
    built_once,
    has_closed_form_phases,
)
from hybridoc.reference.shooting.core import CoreBase


def prepare(ocp: HybridOCP, lengths: Any, max_iter: int = 100) -> None:
    """Disc scenes: build the NLPs of these numbers of events now, so that the worker
    processes a search forks share them instead of each compiling its own; nothing for
    other problems."""
    if has_closed_form_phases(ocp):
        for K in sorted(set(int(k) for k in lengths)):
            disc_nlp(ocp, K, max_iter)


class _DiscPieces:
    """Disc scenes: what every sequence of one structure shares (``u*``, ``H``, the guards,
    ``phi``, ``A`` and ``eps``), built once."""

    def __init__(self, ocp: HybridOCP) -> None:
        s, lam, u, H, _, u_star = argmin_hamiltonian(ocp)
        self.u_star = ca.Function("u_star", [s, lam], [u_star])
        self.H = ca.Function("H", [s, lam, u], [H])
        self.H_star = ca.Function("H_star", [s, lam], [ca.substitute(H, u, u_star)])
        self.guards = _disc_guard_fns(ocp, s)
        phi = ocp.phi(s)
        self.phi = ca.Function("phi", [s], [phi, ca.gradient(phi, s)])
        # f = (v, A u) with constant A; L = eps |u|^2: the problem's closed-form flow
        self.A, self.eps = _linear_flow(ocp)


_DISC_PIECES: weakref.WeakKeyDictionary[Structure, _DiscPieces] = weakref.WeakKeyDictionary()


def _disc_pieces(ocp: HybridOCP) -> _DiscPieces:
    return built_once(_DISC_PIECES, ocp.structure, lambda: _DiscPieces(ocp))


def _linear_flow(ocp: HybridOCP) -> tuple[np.ndarray, float]:
    """``(A, eps)`` of the problem's :class:`~hybridoc.capabilities.LinearControlFlow`
    (:func:`has_closed_form_phases`): for a compiled disc scene the same bits as the
    Jacobian ``df/du`` of its accelerations and its control weight."""
    flow = ocp.capabilities.flow
    if flow is None:
        raise ValueError("the closed-form phases need the problem's LinearControlFlow")
    return flow.A, flow.eps


class DiscCore(CoreBase):
    """Disc scenes: the exact polynomial phases of one sequence; its residual and trajectory
    are those of every sequence of its length (:class:`_DiscResidual`) with its guards."""

    def __init__(self, ocp: HybridOCP, sequence: list[str]) -> None:
        super().__init__(ocp, sequence)
        pieces = _disc_pieces(ocp)
        self.u_star, self.H, self.H_star, self.phi = (
            pieces.u_star, pieces.H, pieces.H_star, pieces.phi
        )  # fmt: skip
        self.f = ocp.f
        self.guard_fns = [pieces.guards[j] for j in self.guard_index]
        self.A, self.eps = pieces.A, pieces.eps
        self.terminal = None  # disc scenes have none (is_disc_scene)

    def phase_u(self, s0: Any, c0: Any, c1: Any, h: Any) -> tuple[Any, Any]:
        """State after ``h`` under ``u(tau) = c0 + c1 tau`` and its running cost."""
        return _phase_u(self.A, self.eps, s0, c0, c1, h)

    def control_coeffs(self, lam0: Any) -> tuple[Any, Any]:
        """``u(tau) = c0 + c1 tau`` from the costate at the phase start."""
        n2 = self.nx // 2
        lp, lv = lam0[:n2], lam0[n2:]
        c0 = -ca.mtimes(self.A.T, lv) / (2 * self.eps)
        c1 = ca.mtimes(self.A.T, lp) / (2 * self.eps)
        return c0, c1

    def phase(self, s0: Any, lam0: Any, h: Any) -> tuple[Any, Any, Any]:
        """``(s, lambda, running cost)`` after a phase of length ``h`` under ``u*``."""
        n2 = self.nx // 2
        c0, c1 = self.control_coeffs(lam0)
        s1, J = self.phase_u(s0, c0, c1, h)
        lam1 = ca.vertcat(lam0[:n2], lam0[n2:] - lam0[:n2] * h)
        return s1, lam1, J

    def _build_residual(self, ocp: HybridOCP) -> tuple[Any, Any]:
        shared = _disc_residual(ocp, self.K)
        idx = np.asarray(self.guard_index, dtype=float)
        return (
            _WithGuards(shared.F, shared.F_layout, idx),
            _WithGuards(shared.traj, shared.traj_layout, idx),
        )


class _DiscTemplate(DiscCore):
    """Disc scenes: the core of every sequence of ``K`` events, event ``k``'s guard chosen by
    the symbol ``idx[k]`` (as in :class:`_DiscNLP`)."""

    def __init__(self, ocp: HybridOCP, K: int) -> None:
        super().__init__(ocp, [g.name for g in ocp.guards][:1] * K)
        self.idx = ca.SX.sym("idx", K)
        self.all_guards = _disc_pieces(ocp).guards

    def guard_at(self, k: int, s: Any, v: Any = None) -> Any:
        if len(self.all_guards) == 1:  # nothing to choose (single-collision)
            return self.all_guards[0](s)
        return _selected_guard(self.all_guards, self.idx[k], s)


class _DiscResidual:
    """Disc scenes: the residual with its Jacobian, ``F(z, x0, T, idx)``, and the trajectory
    function, ``traj(z, x0, T, idx)``, of every sequence of ``K`` events of one structure,
    the guard of event ``k`` being number ``idx[k]``: built once per (structure, ``K``)
    instead of once per sequence (a search solves the Newton systems of dozens of sequences
    of each length; one build takes about as long as the Newton iterations of a screen)."""

    def __init__(self, ocp: HybridOCP, K: int) -> None:
        t = _DiscTemplate(ocp, K)
        self.F, self.traj = t._assemble(
            ocp, lambda k, j, s, lam, h: t.phase(s, lam, h), ca.SX, [t.idx]
        )
        self.F_layout, self.traj_layout = _dense_layout(self.F), _dense_layout(self.traj)


_DISC_RESIDUALS: weakref.WeakKeyDictionary[Structure, dict[int, _DiscResidual]] = (
    weakref.WeakKeyDictionary()
)


def _disc_residual(ocp: HybridOCP, K: int) -> _DiscResidual:
    with LOCK:
        shared = _DISC_RESIDUALS.setdefault(ocp.structure, {})
    return built_once(shared, K, lambda: _DiscResidual(ocp, K))


class _WithGuards:
    """A function of :class:`_DiscResidual` as ``fn(z, x0, T)`` of one sequence, its guard
    numbers bound, returning dense numpy arrays: evaluated through CasADi's buffer API
    (bound once per thread), the same virtual machine and the same bits as ``fn(z, x0, T,
    idx)`` without the ``DM`` conversions of that call, which cost more than the evaluation
    of a screen's residual (a structural zero reads 0.0, as in ``np.asarray`` of the ``DM``)."""

    def __init__(self, fn: ca.Function, layout: list[Any], idx: np.ndarray) -> None:
        self.fn, self.layout, self.idx = fn, layout, idx
        self._local = threading.local()

    def _buffers(self) -> tuple[Any, Any, list[np.ndarray], list[np.ndarray]]:
        bound = getattr(self._local, "bound", None)
        if bound is None:
            fn = self.fn
            buf, run = fn.buffer()
            args = [np.zeros(fn.nnz_in(i)) for i in range(fn.n_in())]
            outs = [np.zeros(fn.nnz_out(i)) for i in range(fn.n_out())]
            for i, a in enumerate(args):
                buf.set_arg(i, memoryview(a))
            for i, r in enumerate(outs):
                buf.set_res(i, memoryview(r))
            args[3][...] = self.idx
            bound = self._local.bound = (buf, run, args, outs)
        return bound

    def __call__(self, z: Any, x0: Any, T: Any) -> list[np.ndarray]:
        buf, run, args, outs = self._buffers()
        args[0][...] = np.asarray(z, dtype=float).ravel()
        args[1][...] = np.asarray(x0, dtype=float).ravel()
        args[2][...] = float(T)
        run()
        if buf.ret() != 0:
            raise RuntimeError(f"numerical evaluation of {self.fn.name()!r} failed")
        dense = []
        for r, (shape, where) in zip(outs, self.layout, strict=True):
            if where is None:
                dense.append(r.reshape(shape, order="F").copy())
            else:
                out = np.zeros(shape)
                out[where] = r
                dense.append(out)
        return dense

    def size1_out(self, i: int) -> int:
        return int(self.fn.size1_out(i))


def _dense_layout(fn: ca.Function) -> list[Any]:
    """Per output of ``fn``: its shape and, when it is sparse, the rows and columns of its
    nonzeros in CasADi's order (``None`` when dense)."""
    out = []
    for i in range(fn.n_out()):
        sp = fn.sparsity_out(i)
        where = None
        if not sp.is_dense():
            rows, cols = sp.get_triplet()
            where = (np.asarray(rows, dtype=np.intp), np.asarray(cols, dtype=np.intp))
        out.append((sp.shape, where))
    return out


class _DiscNLP:
    """Disc scenes: the NLP in event times and linear-in-time phase controls for ``K``
    events, one compiled IPOPT instance per (structure, ``K``). Which guard each event is
    lies in the parameters (one index per event, the guards selected by
    ``if_else``, which also keeps an unselected guard's NaN out), so a search over
    many sequences of one length builds it once."""

    def __init__(self, ocp: HybridOCP, K: int, max_iter: int = 100) -> None:
        nx = ocp.nx
        n2 = nx // 2
        nu = ocp.nu
        s_sym = ca.SX.sym("s", nx)
        self.A, self.eps = _linear_flow(ocp)
        guard_fns = _disc_guard_fns(ocp, s_sym)
        phi_s = ocp.phi(s_sym)
        phi_fn = ca.Function("phi", [s_sym], [phi_s, ca.gradient(phi_s, s_sym)])

        w = ca.SX.sym("w", K + (K + 1) * 2 * nu)
        par = ca.SX.sym("p", nx + 1 + K)
        x0, T, idx = par[:nx], par[nx], par[nx + 1 :]
        # the transcription, in one block: phases, guards, approach and time order read
        # together as the NLP's constraints
        gam = [w[k] for k in range(K)]
        C = [w[K + 2 * nu * k : K + 2 * nu * (k + 1)] for k in range(K + 1)]
        s: Any = x0
        t: Any = 0.0
        cost: Any = 0
        g, lbg, ubg = [], [], []
        ends = []  # (s-, s+, u-, u+, grad psi, Dg) per event, for the adjoint
        hs = []
        for k in range(K + 1):
            h = (gam[k] if k < K else T) - t
            hs.append(h)
            c0, c1 = C[k][:nu], C[k][nu:]
            sm, J = _phase_u(self.A, self.eps, s, c0, c1, h)
            cost += J
            if k == K:
                s = sm
                break
            psi, gpsi, sp, Dg = _selected_guard(guard_fns, idx[k], sm)
            g += [psi, ca.dot(gpsi[:n2], sm[n2:])]
            lbg += [0.0, -ca.inf]
            ubg += [0.0, 0.0]
            g.append(gam[k] - (gam[k - 1] if k > 0 else 0.0))
            lbg.append(0.0)
            ubg.append(ca.inf)
            ends.append((sm, sp, c0 + c1 * h, C[k + 1][:nu], gpsi, Dg))
            s, t = sp, gam[k]
        if K:
            g.append(T - gam[K - 1])
            lbg.append(0.0)
            ubg.append(ca.inf)
        phiT, gphi = phi_fn(s)
        cost += phiT
        nlp = {"x": w, "p": par, "f": cost, "g": ca.vertcat(*g) if g else ca.SX(0, 1)}
        self.solver = _compile_disc_nlp(nlp, max_iter)
        self.lbg, self.ubg = lbg, ubg
        self.to_z = _disc_adjoint_fn(ocp, w, par, gphi, gam, hs, ends)


def _disc_guard_fns(ocp: HybridOCP, s_sym: Any) -> list[ca.Function]:
    """Disc scenes: per guard, ``s -> (psi, grad psi, g(s), Dg)``."""
    guard_fns = []
    for j, g in enumerate(ocp.guards):
        psi = g.psi(s_sym)
        gs = g.reset(s_sym)
        guard_fns.append(
            ca.Function(
                f"ev{j}", [s_sym], [psi, ca.gradient(psi, s_sym), gs, ca.jacobian(gs, s_sym)]
            )
        )
    return guard_fns


def _selected_guard(guard_fns: list[ca.Function], index: Any, sm: Any) -> tuple[Any, Any, Any, Any]:
    """Disc scenes: ``(psi, grad psi, g(s), Dg)`` at ``sm`` of guard ``index`` (``if_else``)."""
    parts = [fn(sm) for fn in guard_fns]
    pick = [index == j for j in range(len(guard_fns))]
    return tuple(
        sum(
            (ca.if_else(c, p[m], 0) for c, p in zip(pick, parts, strict=True)),
            ca.SX.zeros(parts[0][m].shape),
        )
        for m in range(4)
    )  # type: ignore[return-value]


def _compile_disc_nlp(nlp: dict[str, Any], max_iter: int) -> ca.Function:
    """Disc scenes: the quiet, tight IPOPT instance of the NLP."""
    opts = {
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",
        "print_time": False,
        "ipopt.tol": 1e-12,
        "ipopt.acceptable_tol": 1e-9,
        "ipopt.max_iter": max_iter,
    }
    return ca.nlpsol("hmp_nlp", "ipopt", nlp, opts)


def _disc_adjoint_fn(
    ocp: HybridOCP, w: Any, par: Any, gphi: Any, gam: list[Any], hs: list[Any], ends: list[Any]
) -> ca.Function:
    """Disc scenes: ``(w, p) -> z``, the NLP's adjoint costates with the evaluator's jump rule."""
    nx, K = ocp.nx, len(gam)
    n2 = nx // 2
    s_sym, u_sym, lam_sym = ca.SX.sym("s", nx), ca.SX.sym("u", ocp.nu), ca.SX.sym("lam", nx)
    H_fn = ca.Function(
        "H",
        [s_sym, lam_sym, u_sym],
        [ocp.L(s_sym, u_sym) + ca.dot(lam_sym, ocp.f(s_sym, u_sym))],
    )
    # the costate backwards through phases and jumps, in one block (the jump rule)
    lam = gphi
    lps: list[Any] = [None] * K
    pis: list[Any] = [None] * K
    for k in range(K, -1, -1):
        lam = ca.vertcat(lam[:n2], lam[n2:] + lam[:n2] * hs[k])
        if k == 0:
            break
        sm, sp, um, up, gpsi, Dg = ends[k - 1]
        lps[k - 1] = lam
        fm = ocp.f(sm, um)
        Hp = H_fn(sp, lam, up)
        pi = (Hp - ocp.L(sm, um) - ca.dot(lam, ca.mtimes(Dg, fm))) / ca.dot(gpsi, fm)
        pis[k - 1] = pi
        lam = ca.mtimes(Dg.T, lam) + pi * gpsi
    parts = [lam]
    for k in range(K):
        parts += [gam[k], pis[k], lps[k]]
    return ca.Function("nlp_to_z", [w, par], [ca.vertcat(*parts)])


_NLPS: weakref.WeakKeyDictionary[Structure, dict[tuple[int, int], _DiscNLP]] = (
    weakref.WeakKeyDictionary()
)


def disc_nlp(ocp: HybridOCP, K: int, max_iter: int = 100) -> _DiscNLP:
    nlps = _NLPS.setdefault(ocp.structure, {})
    return built_once(nlps, (K, max_iter), lambda: _DiscNLP(ocp, K, max_iter))


def _phase_u(A: np.ndarray, eps: float, s0: Any, c0: Any, c1: Any, h: Any) -> tuple[Any, Any]:
    """Disc scenes: state after ``h`` under ``u(tau) = c0 + c1 tau`` and its running cost."""
    n2 = s0.shape[0] // 2
    p0, v0 = s0[:n2], s0[n2:]
    a0 = ca.mtimes(A, c0)
    a1 = ca.mtimes(A, c1)
    p = p0 + v0 * h + a0 * h**2 / 2 + a1 * h**3 / 6
    v = v0 + a0 * h + a1 * h**2 / 2
    J = eps * (ca.sumsqr(c0) * h + ca.dot(c0, c1) * h**2 + ca.sumsqr(c1) * h**3 / 3)
    return ca.vertcat(p, v), J
