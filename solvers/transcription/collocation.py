"""Radau collocation tables and the piecewise control polynomials of a transcription: its
``u(t)``, also rebuilt from a saved Solution (:func:`control_function`,
:func:`resample_controls`).
"""

from __future__ import annotations

import bisect
from collections.abc import Callable
from dataclasses import dataclass
from math import comb
from typing import Any

import casadi as ca
import numpy as np

from hybridoc.errors import HybridocError
from hybridoc.judging import lagrange_pieces

__all__ = [
    "Radau",
    "average_on_cells",
    "control_function",
    "lagrange_basis",
    "pieces_at_one_time",
    "resample_controls",
]


@dataclass(frozen=True)
class Radau:
    """Radau IIA tables on ``[0, 1]`` for degree ``d``."""

    tau: np.ndarray  # (d + 1,): 0 and the d Radau points (the last is 1)
    D: np.ndarray  # (d + 1, d): D[r, j] = dP_r/dtau at Radau point j
    w: np.ndarray  # (d,): Radau quadrature weights
    bernstein: np.ndarray  # (d, d): Bernstein coefficients of the control polynomial

    @classmethod
    def make(cls, d: int) -> Radau:
        pts = np.array(ca.collocation_points(d, "radau"), dtype=float)
        tau = np.concatenate([[0.0], pts])
        D = np.zeros((d + 1, d))
        for r in range(d + 1):
            others = np.delete(tau, r)
            poly = np.poly1d(others, r=True) / np.prod(tau[r] - others)
            D[r] = np.polyder(poly)(pts)
        w = np.zeros(d)
        for j in range(d):
            others = np.delete(pts, j)
            poly = np.poly1d(others, r=True) / np.prod(pts[j] - others)
            w[j] = np.polyint(poly)(1.0)
        # the control polynomial of degree n = d - 1 through the Radau points: monomial
        # coefficients a = V^-1 u, Bernstein coefficients b_i = sum_k<=i C(i,k)/C(n,k) a_k
        n = d - 1
        to_bern = np.array(
            [[comb(i, k) / comb(n, k) if k <= i else 0.0 for k in range(d)] for i in range(d)]
        )
        bernstein = to_bern @ np.linalg.inv(np.vander(pts, d, increasing=True))
        return cls(tau=tau, D=D, w=w, bernstein=bernstein)

    def control_basis(self, s: np.ndarray) -> np.ndarray:
        """Lagrange basis through the Radau points evaluated at ``s``: shape (len(s), d)."""
        return lagrange_basis(self.tau[1:], s)


def lagrange_basis(pts: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Lagrange basis through ``pts`` evaluated at ``s``: shape ``(len(s), len(pts))``."""
    out = np.ones((s.size, pts.size))
    for j in range(pts.size):
        for m in range(pts.size):
            if m != j:
                out[:, j] *= (s - pts[m]) / (pts[j] - pts[m])
    return out


class _PiecewisePolynomial:
    """``u(t)`` of a transcription Solution, rebuilt from its arrays."""

    def __init__(self, solution: Any) -> None:
        try:
            self.eb = np.asarray(solution.arrays["element_bounds"], dtype=float)
            vals = np.asarray(solution.arrays["radau_controls"], dtype=float)
            self.d = int(solution.settings["degree"])
        except (KeyError, AttributeError, TypeError):
            raise HybridocError(
                "not a direct-transcription Solution (no collocation data)"
            ) from None
        self.rad = Radau.make(self.d)
        self.vals = vals.reshape(vals.shape[0], -1, self.d)  # (nu, elements, d)
        nu = self.vals.shape[0]
        self.lo = np.asarray(solution.arrays.get("u_min", np.full(nu, -np.inf)), dtype=float)
        self.hi = np.asarray(solution.arrays.get("u_max", np.full(nu, np.inf)), dtype=float)

    def at(self, t: np.ndarray) -> np.ndarray:
        return lagrange_pieces(t, self.eb, self.rad.tau[1:], self.vals, self.lo, self.hi)


def average_on_cells(
    u_at: Callable[[np.ndarray], np.ndarray], bounds: np.ndarray, grid: np.ndarray, n_gauss: int = 6
) -> np.ndarray:
    """Cell averages on ``grid`` of a function smooth between ``bounds`` (Gauss-Legendre)."""
    xg, wg = np.polynomial.legendre.leggauss(n_gauss)
    cuts = np.union1d(grid, bounds)
    cuts = cuts[(cuts >= grid[0]) & (cuts <= grid[-1])]
    a, b = cuts[:-1], cuts[1:]
    keep = b - a > 0
    a, b = a[keep], b[keep]
    mid, half = 0.5 * (a + b), 0.5 * (b - a)
    tq = (mid[:, None] + half[:, None] * xg[None, :]).ravel()
    uq = u_at(tq).reshape(a.size, n_gauss, -1)
    integ = np.einsum("q,pqu->pu", wg, uq) * half[:, None]
    cell = np.clip(np.searchsorted(grid, mid, side="right") - 1, 0, grid.size - 2)
    out = np.zeros((grid.size - 1, uq.shape[-1]))
    np.add.at(out, cell, integ)
    return out / np.diff(grid)[:, None]


def pieces_at_one_time(
    bounds: np.ndarray,
    nodes: np.ndarray,
    values: np.ndarray,
    lo: np.ndarray | float,
    hi: np.ndarray | float,
) -> Callable[[float], np.ndarray]:
    """``t -> lagrange_pieces([t], bounds, nodes, values, lo, hi)[0]``, bit for bit.

    The judge calls a continuous control at every stage of its integrator, one time at a
    time (6000 to 10000 calls per transcription on the hopper), where
    :func:`~hybridoc.judging.lagrange_pieces`'s dozen array operations on one-element
    arrays cost about 40 us a call idle. Here the element and the Lagrange basis are plain
    floats, computed by the same operations in the same order (so the same roundings), and
    the weighted sum and the clip are the very ``einsum`` and ``clip`` of
    ``lagrange_pieces`` on arrays of the same shapes and layouts: the einsum's summation
    order depends on its SIMD kernel (two lanes here, not left to right), which only the
    same call reproduces on every machine.
    """
    b = np.asarray(bounds, dtype=float).tolist()
    last = len(b) - 2
    nd = np.asarray(nodes, dtype=float).tolist()
    d = len(nd)
    den = [[nd[j] - nd[m] for m in range(d)] for j in range(d)]
    V = np.asarray(values, dtype=float)
    # each element's values as lagrange_pieces indexes them (values[:, idx, :], idx an array)
    per = [V[:, np.array([e]), :] for e in range(V.shape[1])]
    others = [[m for m in range(d) if m != j] for j in range(d)]

    def u(t: float) -> np.ndarray:
        t = float(t)
        e = min(max(bisect.bisect_right(b, t) - 1, 0), last)
        a = b[e]
        s = (t - a) / (b[e + 1] - a)
        basis = []
        for j in range(d):
            w = 1.0
            dj = den[j]
            for m in others[j]:
                w *= (s - nd[m]) / dj[m]
            basis.append(w)
        # ndarray.clip: what np.clip calls, without its 3 us of dispatch
        return np.einsum("nj,unj->nu", np.array([basis]), per[e]).clip(lo, hi)[0]

    return u


def control_function(solution: Any) -> Callable[[float], np.ndarray]:
    """The continuous-time control ``u(t)`` of a Solution returned by :func:`solve_dt`.

    Rebuilt from ``solution.arrays`` (``element_bounds``, ``radau_controls``) and the
    collocation degree, so it also works for a saved and reloaded solution.
    """
    pp = _PiecewisePolynomial(solution)
    return pieces_at_one_time(pp.eb, pp.rad.tau[1:], pp.vals, pp.lo, pp.hi)


def resample_controls(solution: Any, grid: np.ndarray) -> np.ndarray:
    """Cell averages of a transcription Solution's ``u(t)`` on any time grid.

    Parameters
    ----------
    solution
        A Solution from :func:`solve_dt`.
    grid
        Increasing times from 0 to T (e.g. ``ocp.replace(steps=N).time_grid()``).

    Returns
    -------
    numpy.ndarray
        ``(len(grid) - 1, nu)`` averages (exact up to rounding: Gauss-Legendre on each
        polynomial piece).
    """
    pp = _PiecewisePolynomial(solution)
    return average_on_cells(pp.at, pp.eb, np.asarray(grid, dtype=float))
