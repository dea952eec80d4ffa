"""The HMP shooting system of one event sequence, compiled in CasADi.

For a fixed sequence of guards ``k_1, ..., k_K`` the hybrid minimum principle (DESIGN.md
section 2) is a square nonlinear system in::

    z = [lambda(0), (gamma_k, pi_k, lambda(gamma_k+)) for k = 1..K]

with residuals, in the same order::

    transversality      lambda(T) - grad phi(s(T))                       (nx)
    per event k:        psi_k(s(gamma_k-))                                (1)
                        lambda(gamma_k-) - Dg^T lambda(gamma_k+) - pi_k grad psi_k   (nx)
                        H(gamma_k-) - H(gamma_k+)                         (1)

where the phases between events carry ``(s, lambda)`` forward under ``u = argmin_u H``.
Taking ``lambda(gamma+)`` as an unknown (a light multiple shooting) avoids inverting the
reset Jacobian, which is singular for restitution 0.

Phase maps
    Disc scenes integrate exactly: ``lambda_p`` is constant, ``lambda_v`` linear, hence
    ``u = -A^T lambda_v / (2 eps)`` is linear in time (``A = M^-1 B``) and the positions are
    cubic. Any other :class:`~hybridoc.HybridOCP` whose Hamiltonian is quadratic in ``u``
    integrates the state-costate system with CVODES at tolerance 1e-13.

Globalisation (disc scenes)
    Because the optimal control is linear in time between events, the optimum also solves a
    small NLP in the event times and the two coefficients of ``u`` per phase. IPOPT solves
    it from a crude guess; its adjoint costates start Newton on the HMP system.
"""

from __future__ import annotations

import sys
import weakref
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from hybridoc.ocp import HybridOCP

# compiled systems per problem (they bake in x0 and T) and sequence
_SYSTEMS: weakref.WeakKeyDictionary[HybridOCP, dict[tuple[str, ...], Any]] = (
    weakref.WeakKeyDictionary()
)

__all__ = ["NewtonResult", "ShootingSystem", "is_disc_scene", "newton", "shooting_system"]


def is_disc_scene(ocp: HybridOCP) -> bool:
    """Whether ``ocp`` is a compiled disc scene: ``f = (v, A u)``, ``L = eps |u|^2``."""
    return "n_discs" in ocp.meta and "control_weight" in ocp.meta


def _residual_and_jacobian(F: ca.Function, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Evaluate the shooting system; an integrator failure reads as a non-finite residual."""
    try:
        R, J = (np.asarray(x) for x in F(z))
    except RuntimeError:  # CVODES gives up on a wild trial point: let the line search back off
        n = int(F.size1_out(0))
        return np.full(n, np.nan), np.full((n, z.size), np.nan)
    return R.ravel(), J


@dataclass
class NewtonResult:
    """Outcome of :func:`newton`."""

    z: np.ndarray
    residual: float
    iterations: int
    converged: bool
    history: list[float] = field(default_factory=list)


class ShootingSystem:
    """Compiled HMP residual, trajectory and (disc scenes) globalising NLP for one sequence.

    Parameters
    ----------
    ocp
        The problem.
    sequence
        Guard names, in event order.
    """

    def __init__(self, ocp: HybridOCP, sequence: list[str]) -> None:
        names = [g.name for g in ocp.guards]
        unknown = [s for s in sequence if s not in names]
        if unknown:
            raise ValueError(f"unknown guard name(s) {unknown}; this problem has {names}")
        self.ocp = ocp
        self.sequence = list(sequence)
        self.guard_index = [names.index(s) for s in sequence]
        self.K = len(sequence)
        self.nx, self.nu = ocp.nx, ocp.nu
        self.disc = is_disc_scene(ocp)
        self.sym = ca.SX if self.disc else ca.MX
        self._build_pieces()
        self._build_residual()
        self._nlp: Any = None

    # ------------------------------------------------------------------ building blocks
    def _build_pieces(self) -> None:
        ocp, nx, nu = self.ocp, self.nx, self.nu
        s = ca.SX.sym("s", nx)
        lam = ca.SX.sym("lam", nx)
        u = ca.SX.sym("u", nu)
        H = ocp.L(s, u) + ca.dot(lam, ocp.f(s, u))
        Hu = ca.gradient(H, u)
        Huu = ca.hessian(H, u)[0]
        if ca.depends_on(Huu, u):
            raise ValueError(
                "the reference needs a Hamiltonian quadratic in u (L quadratic, f affine)"
            )
        u_star = -ca.solve(Huu, ca.substitute(Hu, u, ca.DM.zeros(nu)))
        H_star = ca.substitute(H, u, u_star)
        self.u_star = ca.Function("u_star", [s, lam], [u_star])
        self.H = ca.Function("H", [s, lam, u], [H])
        self.H_star = ca.Function("H_star", [s, lam], [H_star])
        # costate flow -dH/ds at the minimising u (envelope theorem: partial at fixed u)
        dlam = -ca.substitute(ca.gradient(H, s), u, u_star)
        self.guard_fns = []
        for j in self.guard_index:
            g = ocp.guards[j]
            psi = g.psi(s)
            gs = g.reset(s)
            self.guard_fns.append(
                ca.Function(f"ev{j}", [s], [psi, ca.gradient(psi, s), gs, ca.jacobian(gs, s)])
            )
        phi = ocp.phi(s)
        self.phi = ca.Function("phi", [s], [phi, ca.gradient(phi, s)])
        if self.disc:
            # f = (v, A u) with constant A; L = eps |u|^2
            A = np.asarray(ca.DM(ca.jacobian(ocp.f(s, u), u)))[nx // 2 :]
            self.A = A
            self.eps = float(ocp.meta["control_weight"])
        else:
            xs = ca.SX.sym("x", 2 * nx + 1)
            hs = ca.SX.sym("h")
            ss, ls = xs[:nx], xs[nx : 2 * nx]
            us = ca.substitute(u_star, ca.vertcat(s, lam), ca.vertcat(ss, ls))
            dl = ca.substitute(dlam, ca.vertcat(s, lam), ca.vertcat(ss, ls))
            ode = hs * ca.vertcat(ocp.f(ss, us), dl, ocp.L(ss, us))
            opts = {"abstol": 1e-13, "reltol": 1e-13, "max_num_steps": 200000}
            self._integ = ca.integrator(
                "hmp_phase", "cvodes", {"x": xs, "p": hs, "ode": ode}, 0.0, 1.0, opts
            )

    def phase_u(self, s0: Any, c0: Any, c1: Any, h: Any) -> tuple[Any, Any]:
        """Disc scenes: state after ``h`` under ``u(tau) = c0 + c1 tau`` and its running cost."""
        n2 = self.nx // 2
        A = self.A
        p0, v0 = s0[:n2], s0[n2:]
        a0 = ca.mtimes(A, c0)
        a1 = ca.mtimes(A, c1)
        p = p0 + v0 * h + a0 * h**2 / 2 + a1 * h**3 / 6
        v = v0 + a0 * h + a1 * h**2 / 2
        J = self.eps * (ca.sumsqr(c0) * h + ca.dot(c0, c1) * h**2 + ca.sumsqr(c1) * h**3 / 3)
        return ca.vertcat(p, v), J

    def control_coeffs(self, lam0: Any) -> tuple[Any, Any]:
        """Disc scenes: ``u(tau) = c0 + c1 tau`` from the costate at the phase start."""
        n2 = self.nx // 2
        lp, lv = lam0[:n2], lam0[n2:]
        c0 = -ca.mtimes(self.A.T, lv) / (2 * self.eps)
        c1 = ca.mtimes(self.A.T, lp) / (2 * self.eps)
        return c0, c1

    def phase(self, s0: Any, lam0: Any, h: Any) -> tuple[Any, Any, Any]:
        """``(s, lambda)`` after a phase of length ``h`` under the minimising control."""
        if self.disc:
            n2 = self.nx // 2
            c0, c1 = self.control_coeffs(lam0)
            s1, J = self.phase_u(s0, c0, c1, h)
            lam1 = ca.vertcat(lam0[:n2], lam0[n2:] - lam0[:n2] * h)
            return s1, lam1, J
        out = self._integ(x0=ca.vertcat(s0, lam0, 0), p=h)["xf"]
        nx = self.nx
        return out[:nx], out[nx : 2 * nx], out[2 * nx]

    def flow(self, s0: np.ndarray, lam0: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """Numeric ``(s, lambda)`` after time ``tau`` from the start of a phase."""
        s1, l1, _ = self.phase(ca.DM(s0), ca.DM(lam0), float(tau))
        return np.asarray(ca.evalf(s1)).ravel(), np.asarray(ca.evalf(l1)).ravel()

    # ------------------------------------------------------------------ HMP residual
    @property
    def nz(self) -> int:
        """Number of unknowns."""
        return self.nx + self.K * (self.nx + 2)

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

    def pack(self, lam0: np.ndarray, gam: Any, pis: Any, lps: Any) -> np.ndarray:
        """Inverse of :meth:`unpack` for numbers."""
        parts = [np.asarray(lam0, float).ravel()]
        for k in range(self.K):
            parts += [[float(gam[k]), float(pis[k])], np.asarray(lps[k], float).ravel()]
        return np.concatenate(parts) if parts else np.zeros(0)

    def _build_residual(self) -> None:
        ocp, nx = self.ocp, self.nx
        z = self.sym.sym("z", self.nz)
        lam, gam, pis, lps = self.unpack(z)
        s = ca.DM(ocp.x0)
        t: Any = 0.0
        res = []
        starts, s_starts, l_starts, costs, s_minus, l_minus, rates = [], [], [], [], [], [], []
        for k in range(self.K):
            starts.append(t)
            s_starts.append(s)
            l_starts.append(lam)
            sm, lm, J = self.phase(s, lam, gam[k] - t)
            costs.append(J)
            psi, gpsi, sp, Dg = self.guard_fns[k](sm)
            lp = lps[k]
            res.append(psi)
            res.append(lm - ca.mtimes(Dg.T, lp) - pis[k] * gpsi)
            res.append(self.H_star(sm, lm) - self.H_star(sp, lp))
            s_minus.append(sm)
            l_minus.append(lm)
            rates.append(ca.dot(gpsi, ocp.f(sm, self.u_star(sm, lm))))
            s, lam, t = sp, lp, gam[k]
        starts.append(t)
        s_starts.append(s)
        l_starts.append(lam)
        sT, lT, J = self.phase(s, lam, ocp.horizon - t)
        costs.append(J)
        phiT, gphi = self.phi(sT)
        res.insert(0, lT - gphi)
        R = ca.vertcat(*res)
        self.F = ca.Function("hmp_F", [z], [R, ca.jacobian(R, z)])
        running = sum(costs[1:], costs[0])
        hc = ca.horzcat
        self.traj = ca.Function(
            "hmp_traj",
            [z],
            [
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
            ],
        )

    # ------------------------------------------------------------------ globalising NLP
    def solve_nlp(self, gamma0: np.ndarray, coeffs0: np.ndarray) -> tuple[np.ndarray, bool]:
        """Disc scenes: IPOPT on event times and linear-in-time phase controls.

        Parameters
        ----------
        gamma0
            Guess of the event times, ``(K,)``.
        coeffs0
            Guess of ``[c0, c1]`` per phase, ``(K + 1, 2 nu)``.

        Returns
        -------
        z, success
            Starting point for Newton on the HMP system (costates of the NLP's control by
            the adjoint with the HMP jump relation) and IPOPT's success flag.
        """
        if self._nlp is None:
            self._build_nlp()
        solver, lbg, ubg, lbw, ubw, to_z = self._nlp
        w0 = np.concatenate([np.asarray(gamma0, float), np.asarray(coeffs0, float).ravel()])
        sol = solver(x0=w0, lbg=lbg, ubg=ubg, lbx=lbw, ubx=ubw)
        ok = bool(solver.stats()["success"])
        w = np.asarray(sol["x"]).ravel()
        return np.asarray(to_z(w)).ravel(), ok

    def z_from_controls(self, gamma: np.ndarray, coeffs: np.ndarray) -> np.ndarray:
        """Disc scenes: HMP unknowns from event times and linear phase controls.

        The costates are the adjoint of that control (with the HMP jump rule), so a
        near-optimal control gives a near-solution of the HMP system.
        """
        if self._nlp is None:
            self._build_nlp()
        w = np.concatenate([np.asarray(gamma, float), np.asarray(coeffs, float).ravel()])
        return np.asarray(self._nlp[-1](w)).ravel()

    def _build_nlp(self) -> None:
        ocp, nu, K, T = self.ocp, self.nu, self.K, self.ocp.horizon
        w = ca.SX.sym("w", K + (K + 1) * 2 * nu)
        gam = [w[k] for k in range(K)]
        C = [w[K + 2 * nu * k : K + 2 * nu * (k + 1)] for k in range(K + 1)]
        s = ca.DM(ocp.x0)
        t: Any = 0.0
        cost: Any = 0
        g, lbg, ubg = [], [], []
        ends = []  # (s-, s+, u-, u+, h) per event, for the adjoint
        hs = []
        for k in range(K + 1):
            h = (gam[k] if k < K else T) - t
            hs.append(h)
            c0, c1 = C[k][:nu], C[k][nu:]
            sm, J = self.phase_u(s, c0, c1, h)
            cost += J
            if k == K:
                s = sm
                break
            psi, gpsi, sp, Dg = self.guard_fns[k](sm)
            n2 = self.nx // 2
            g += [psi, ca.dot(gpsi[:n2], sm[n2:])]
            lbg += [0.0, -ca.inf]
            ubg += [0.0, 0.0]
            if k > 0:
                g.append(gam[k] - gam[k - 1])
                lbg.append(0.0)
                ubg.append(ca.inf)
            ends.append((sm, sp, c0 + c1 * h, C[k + 1][:nu], gpsi, Dg))
            s, t = sp, gam[k]
        phiT, gphi = self.phi(s)
        cost += phiT
        nlp = {"x": w, "f": cost, "g": ca.vertcat(*g) if g else ca.SX(0, 1)}
        opts = {
            "ipopt.print_level": 0,
            "ipopt.sb": "yes",
            "print_time": False,
            "ipopt.tol": 1e-12,
            "ipopt.acceptable_tol": 1e-9,
            "ipopt.max_iter": 100,
        }
        solver = ca.nlpsol("hmp_nlp", "ipopt", nlp, opts)
        lbw = [0.0] * K + [-ca.inf] * ((K + 1) * 2 * nu)
        ubw = [T] * K + [ca.inf] * ((K + 1) * 2 * nu)
        # adjoint of the NLP's control, backwards, with the evaluator's jump rule
        n2 = self.nx // 2
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
            Hp = self.H(sp, lam, up)
            pi = (Hp - ocp.L(sm, um) - ca.dot(lam, ca.mtimes(Dg, fm))) / ca.dot(gpsi, fm)
            pis[k - 1] = pi
            lam = ca.mtimes(Dg.T, lam) + pi * gpsi
        parts = [lam]
        for k in range(K):
            parts += [gam[k], pis[k], lps[k]]
        to_z = ca.Function("nlp_to_z", [w], [ca.vertcat(*parts)])
        self._nlp = (solver, lbg, ubg, lbw, ubw, to_z)

    # ------------------------------------------------------------------ feasibility fallback
    def solve_feasibility(self, z0: np.ndarray) -> tuple[np.ndarray, bool]:
        """IPOPT on ``min 0 s.t. R(z) = 0`` (generic problems' fallback)."""
        z = ca.MX.sym("z", self.nz)
        R = self.F(z)[0]
        solver = ca.nlpsol(
            "hmp_feas",
            "ipopt",
            {"x": z, "f": 0.5 * ca.sumsqr(R)},
            {
                "ipopt.print_level": 0,
                "ipopt.sb": "yes",
                "print_time": False,
                "ipopt.tol": 1e-14,
                # exact Hessians would need second-order CVODES sensitivities
                "ipopt.hessian_approximation": "limited-memory",
            },
        )
        sol = solver(x0=z0)
        return np.asarray(sol["x"]).ravel(), bool(solver.stats()["success"])


def shooting_system(ocp: HybridOCP, sequence: list[str]) -> ShootingSystem:
    """The compiled system for ``(ocp, sequence)``, cached on the problem."""
    cache = _SYSTEMS.setdefault(ocp, {})
    key = tuple(sequence)
    sys_ = cache.get(key)
    if sys_ is None:
        sys_ = ShootingSystem(ocp, list(sequence))
        cache[key] = sys_
    return sys_


def newton(
    system: ShootingSystem,
    z0: np.ndarray,
    *,
    tol: float = 1e-10,
    max_iter: int = 40,
    verbose: bool = False,
) -> NewtonResult:
    """Newton's method with exact Jacobian and a backtracking line search on ``|R|``.

    Iterates until the residual (max norm) stops improving below ``tol`` so the solution is
    polished to rounding; ``converged`` means ``residual <= tol`` with ordered event times
    inside ``(0, T)``.
    """
    F = system.F
    z = np.asarray(z0, dtype=float).copy()
    R, J = _residual_and_jacobian(F, z)  # non-finite: reported as not converged
    norm = float(np.max(np.abs(R))) if R.size else 0.0
    hist = [norm]
    if verbose:
        print(f"  newton {system.sequence}: it  0  |R|_inf = {norm:.3e}", file=sys.stderr)
    it = 0
    for it in range(1, max_iter + 1):
        if not np.isfinite(norm):
            break
        try:
            dz = -np.linalg.solve(J, R)
        except np.linalg.LinAlgError:
            dz = -np.linalg.lstsq(J, R, rcond=None)[0]
        alpha = 1.0
        n2 = float(R @ R)
        while True:
            zn = z + alpha * dz
            Rn, Jn = _residual_and_jacobian(F, zn)
            if np.all(np.isfinite(Rn)) and float(Rn @ Rn) <= (1 - 1e-4 * alpha) * n2:
                break
            alpha *= 0.5
            if alpha < 1e-6 or norm <= tol:  # at rounding level: no line search
                break
        new = float(np.max(np.abs(Rn))) if Rn.size else 0.0
        if verbose:
            print(
                f"  newton {system.sequence}: it {it:2d}  |R|_inf = {new:.3e}  step = "
                f"{alpha * np.linalg.norm(dz):.3e}  damping = {alpha:g}",
                file=sys.stderr,
            )
        if not np.isfinite(new) or (norm <= tol and new >= 0.5 * norm) or alpha < 1e-6:
            # no further progress: keep the best point
            if np.isfinite(new) and new < norm:
                z, R, J, norm = zn, Rn, Jn, new
                hist.append(norm)
            break
        z, R, J, norm = zn, Rn, Jn, new
        hist.append(norm)
        if norm == 0.0:
            break
        if len(hist) > 8 and norm > 0.5 * hist[-6] and norm > tol:
            break  # stagnating far from a root: not this sequence's basin
    _, gam, _, _ = system.unpack(z)
    T = system.ocp.horizon
    times = np.array([float(g) for g in gam])
    ordered = bool(np.all(np.diff(np.concatenate([[0.0], times, [T]])) > 0))
    return NewtonResult(z, norm, it, bool(norm <= tol and ordered), hist)
