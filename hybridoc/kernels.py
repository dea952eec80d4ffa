"""The CasADi functions the judge evaluates, compiled once per problem structure.

:func:`kernels` returns the :class:`Kernels` of a :class:`~hybridoc.HybridOCP`, built on first
use and kept (weakly) per :class:`~hybridoc.ocp.Structure`, so copies made by
:meth:`~hybridoc.HybridOCP.replace` share them. Numerical calls go through CasADi's buffer
API (:class:`Num`): calling a Function with numpy arrays converts every argument and result
to and from DM, which costs about a hundred times the arithmetic of a small disc-scene
function.
"""

from __future__ import annotations

import threading
import weakref
from functools import cached_property
from typing import Any

import casadi as ca
import numpy as np

from hybridoc.errors import EvaluationError
from hybridoc.ocp import HybridOCP, Structure, integrator_flow_samples
from hybridoc.rootfind import Chebyshev

__all__ = ["Kernels", "Num", "kernels", "UNKNOWN_DEGREE", "BATCH"]

UNKNOWN_DEGREE = 16
"""Interpolation degree for guards that are not polynomial along the flow."""
BATCH = 64
"""Grid intervals per batched call of SX kernels."""

_CACHE: weakref.WeakKeyDictionary[Structure, Kernels] = weakref.WeakKeyDictionary()
_LOCK = threading.Lock()


class Num:
    """Numerical evaluation of a CasADi Function through its buffer API.

    The inputs and outputs are numpy buffers bound once; a call copies the arguments in,
    evaluates, and returns flat copies of the (dense) outputs in CasADi's column-major order.
    """

    def __init__(self, fn: ca.Function) -> None:
        for i in range(fn.n_in()):
            if not fn.sparsity_in(i).is_dense():
                raise ValueError(f"{fn.name()}: input {i} is not dense")
        for i in range(fn.n_out()):
            if not fn.sparsity_out(i).is_dense():
                raise ValueError(f"{fn.name()}: output {i} is not dense")
        self.name = fn.name()
        self._args = [np.zeros(fn.nnz_in(i)) for i in range(fn.n_in())]
        self._res = [np.zeros(fn.nnz_out(i)) for i in range(fn.n_out())]
        self._buf, self._eval = fn.buffer()
        for i, a in enumerate(self._args):
            self._buf.set_arg(i, memoryview(a))
        for i, r in enumerate(self._res):
            self._buf.set_res(i, memoryview(r))

    def __call__(self, *args: Any) -> list[np.ndarray]:
        for a, x in zip(self._args, args, strict=True):
            a[...] = x
        self._eval()
        if self._buf.ret() != 0:
            raise EvaluationError(f"numerical evaluation of {self.name!r} failed")
        return [r.copy() for r in self._res]


def dense_fn(name: str, args: list[Any], outs: list[Any]) -> ca.Function:
    """A Function with dense outputs (the buffer API needs them)."""
    return ca.Function(name, args, [ca.densify(o) for o in outs])


def is_sx(ocp: HybridOCP) -> bool:
    """Whether every function of the problem is an SX function (cheap to evaluate)."""
    fns = [ocp.f, ocp.L, ocp.phi, ocp.flow_map, ocp.path]
    for g in ocp.guards:
        fns += [g.psi, g.reset, g.detector]
    return all(fn.is_a("SXFunction") for fn in fns if fn is not None)


class Kernels:
    """CasADi functions of one problem structure.

    ``interval(s, u, h) -> (s(h), cost, samples, noise, psi(s(h)))`` gives the detectors at
    the Chebyshev-Lobatto nodes of ``[0, h]`` with their rounding levels;
    ``window(s, u, a, b) -> (samples, noise)`` the same on a sub-interval ``[a, b]``;
    ``point(s, u, tau) -> (s(tau), det, d det / d tau)``; ``contact(s, u) -> (psi, dpsi/dt,
    d2psi/dt2, rounding level of psi)``; resets, their Jacobians and the adjoint pieces.
    """

    def __init__(self, ocp: HybridOCP) -> None:
        nx, nu, G = ocp.nx, ocp.nu, len(ocp.guards)
        self.sx = is_sx(ocp)
        sym = ca.SX if self.sx else ca.MX
        s, u, h = sym.sym("s", nx), sym.sym("u", nu), sym.sym("h")
        degrees = [g.degree for g in ocp.guards]
        exact = [d is not None and int(d) <= UNKNOWN_DEGREE for d in degrees]
        if G and all(exact):
            D = max(max(int(d) for d in degrees if d is not None), 1)
        else:
            D = UNKNOWN_DEGREE
        self.nx, self.nu, self.G, self.D = nx, nu, G, D
        self.exact = np.array(exact, dtype=bool)
        self.cheb = Chebyshev(D)
        self.names = [g.name for g in ocp.guards]
        fm = ocp.flow_map
        assert fm is not None
        dets = [g.detector if g.detector is not None else g.psi for g in ocp.guards]
        sp = sym.sym("sp", nx)
        det_expr = ca.vertcat(*[d(sp) for d in dets]) if G else sym(0, 1)
        det_grad = ca.jacobian(det_expr, sp) if G else sym(0, nx)
        # rounding level of each detector value: its own rounding plus the effect of a
        # perturbation eps max(1, |s|_inf) of every state component (the flow map's rounding)
        s_scale = ca.fmax(1.0, ca.mmax(ca.fabs(sp)))
        noise_expr = (
            8 * np.finfo(float).eps * (ca.fabs(det_expr) + ca.sum2(ca.fabs(det_grad)) * s_scale)
            if G
            else sym(0, 1)
        )
        det_fn = ca.Function("det", [sp], [det_expr, noise_expr])

        def det_cols(states: list[Any]) -> tuple[Any, Any]:
            if not G:
                return sym(0, len(states)), sym(0, len(states))
            outs = [det_fn(x) for x in states]
            return ca.horzcat(*[o[0] for o in outs]), ca.horzcat(*[o[1] for o in outs])

        x_nodes = self.cheb.x
        a_, b_ = sym.sym("a"), sym.sym("b")
        if ocp.structure.integrator_flow:
            # the built-in CVODES flow map: all nodes from one integration with a time grid
            fracs = (x_nodes[1:] + 1) / 2
            fracs[-1] = 1.0
            sampler = integrator_flow_samples(ocp.f, ocp.L, fracs)
            xs, qs = sampler(s, u, h)
            node_states = [s] + [xs[:, k] for k in range(D)]
            s_end, cost = xs[:, D - 1], qs[:, D - 1]
            # a sub-window [a, b]: flow to a, then sample
            s_a = sampler(s, u, a_)[0][:, D - 1]
            xw = sampler(s_a, u, b_ - a_)[0]
            win_states = [s_a] + [xw[:, k] for k in range(D)]
        else:
            s_end, cost = fm(s, u, h)
            # the end nodes are s itself and s_end: no extra flow evaluation (exact)
            node_states = [s]
            node_states += [fm(s, u, h * (xk + 1) / 2)[0] for xk in x_nodes[1:-1]]
            node_states.append(s_end)
            win_states = [fm(s, u, a_ + (b_ - a_) * (xk + 1) / 2)[0] for xk in x_nodes]
        samples, noise = det_cols(node_states)
        psi_end = ca.vertcat(*[g.psi(s_end) for g in ocp.guards]) if G else sym(0, 1)
        self.interval_fn = dense_fn("interval", [s, u, h], [s_end, cost, samples, noise, psi_end])
        w_samples, w_noise = det_cols(win_states)
        self.window_fn = dense_fn("window", [s, u, a_, b_], [w_samples, w_noise])
        # SX kernels are cheap: many grid intervals per call (what lies past an event is
        # computed again from the new state); an MX flow map (an integrator) is too costly to
        # evaluate past an event, so one interval per call
        self.chunk = BATCH if self.sx else 1
        self.batch_fn = (
            self.interval_fn.mapaccum("interval_acc", self.chunk)
            if self.chunk > 1
            else self.interval_fn
        )
        self.flow_fn = dense_fn("flow", [s, u, h], [s_end, cost])
        det_v, det_n = det_fn(s_end) if G else (sym(0, 1), sym(0, 1))
        det_r = ca.jacobian(det_v, h) if G else sym(0, 1)
        self.point_fn = dense_fn("point", [s, u, h], [s_end, det_v, det_r, det_n])
        self.det_fn = dense_fn("det_noise", [sp], list(det_fn(sp)))
        fs = ocp.f(sp, u)
        det_rate = ca.mtimes(det_grad, fs) if G else sym(0, 1)
        self.det_rate_fn = dense_fn("det_rate", [sp, u], [det_expr, det_rate, noise_expr])
        # the callable path samples detectors at the degree-16 nodes of each integrator step
        self.det_nodes_fn = self.det_fn.map(UNKNOWN_DEGREE + 1)
        psi = ca.vertcat(*[g.psi(sp) for g in ocp.guards]) if G else sym(0, 1)
        psi_grad = ca.jacobian(psi, sp) if G else sym(0, nx)
        rate = ca.mtimes(psi_grad, fs) if G else sym(0, 1)
        accel = ca.jtimes(rate, sp, fs) if G else sym(0, 1)
        psi_noise = (
            8 * np.finfo(float).eps * (ca.fabs(psi) + ca.sum2(ca.fabs(psi_grad)) * s_scale)
            if G
            else sym(0, 1)
        )
        self.contact_fn = dense_fn("contact", [sp, u], [psi, rate, accel, psi_noise])
        self.psi_fn = dense_fn("guards_psi", [sp], [psi])
        self.reset_fns = [
            dense_fn(f"reset{j}", [sp], [g.reset(sp)]) for j, g in enumerate(ocp.guards)
        ]
        # adjoint pieces: one Jacobian of (s_end, cost) w.r.t. (s, u) (for an integrator flow
        # map a single forward-sensitivity solve instead of four)
        jac = ca.jacobian(ca.vertcat(s_end, cost), ca.vertcat(s, u))
        seg_jac = dense_fn(
            "seg_jac", [s, u, h], [jac[:nx, :nx], jac[:nx, nx:], jac[nx, :nx].T, jac[nx, nx:].T]
        )
        self.seg_jac_fn = seg_jac.map(self.chunk) if self.chunk > 1 else seg_jac
        self.event_jac_fns = [
            dense_fn(
                f"event_jac{j}",
                [sp, u],
                [ca.gradient(g.psi(sp), sp), ca.jacobian(g.reset(sp), sp), g.reset(sp)],
            )
            for j, g in enumerate(ocp.guards)
        ]
        self.fL_fn = dense_fn("fL", [sp, u], [fs, ocp.L(sp, u)])
        sf = sym.sym("sf", nx)
        self.phi_fn = dense_fn("phi_grad", [sf], [ocp.phi(sf), ca.gradient(ocp.phi(sf), sf)])
        if ocp.path is not None:
            self.path_fn: ca.Function | None = dense_fn("path", [sp, u], [ocp.path(sp, u)])
        else:
            self.path_fn = None
        self._local = threading.local()

    def numeric(self) -> Numeric:
        """This thread's buffer-bound evaluators (buffers are not shared between threads)."""
        num = getattr(self._local, "num", None)
        if num is None:
            num = Numeric(self)
            self._local.num = num
        return num

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        del state["_local"]
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._local = threading.local()


class Numeric:
    """Lazily bound :class:`Num` evaluators of one :class:`Kernels` (one thread)."""

    def __init__(self, k: Kernels) -> None:
        self.k = k
        self._resets: dict[int, Num] = {}
        self._event_jac: dict[int, Num] = {}

    @cached_property
    def interval(self) -> Num:
        return Num(self.k.interval_fn)

    @cached_property
    def window(self) -> Num:
        return Num(self.k.window_fn)

    @cached_property
    def batch(self) -> Num:
        return Num(self.k.batch_fn)

    @cached_property
    def flow(self) -> Num:
        return Num(self.k.flow_fn)

    @cached_property
    def point(self) -> Num:
        return Num(self.k.point_fn)

    @cached_property
    def det(self) -> Num:
        return Num(self.k.det_fn)

    @cached_property
    def det_rate(self) -> Num:
        return Num(self.k.det_rate_fn)

    @cached_property
    def det_nodes(self) -> Num:
        return Num(self.k.det_nodes_fn)

    @cached_property
    def contact(self) -> Num:
        return Num(self.k.contact_fn)

    @cached_property
    def psi(self) -> Num:
        return Num(self.k.psi_fn)

    @cached_property
    def seg_jac(self) -> Num:
        return Num(self.k.seg_jac_fn)

    @cached_property
    def fL(self) -> Num:
        return Num(self.k.fL_fn)

    @cached_property
    def phi_grad(self) -> Num:
        return Num(self.k.phi_fn)

    @cached_property
    def path(self) -> Num | None:
        return None if self.k.path_fn is None else Num(self.k.path_fn)

    def reset(self, j: int) -> Num:
        if j not in self._resets:
            self._resets[j] = Num(self.k.reset_fns[j])
        return self._resets[j]

    def event_jac(self, j: int) -> Num:
        if j not in self._event_jac:
            self._event_jac[j] = Num(self.k.event_jac_fns[j])
        return self._event_jac[j]


def kernels(ocp: HybridOCP) -> Kernels:
    """The compiled kernels of ``ocp``'s structure (built once, shared by its copies)."""
    k = _CACHE.get(ocp.structure)
    if k is None:
        with _LOCK:
            k = _CACHE.get(ocp.structure)
            if k is None:
                k = Kernels(ocp)
                _CACHE[ocp.structure] = k
    return k
