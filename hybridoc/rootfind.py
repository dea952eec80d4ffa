"""Finding the first time a guard crosses zero on an interval, without ever skipping one.

The judge samples each guard's *detector* (a function with the guard's sign and zero set,
polynomial along the flow where possible) at the Chebyshev-Lobatto nodes of an interval and
works with its Chebyshev interpolant:

Proof of no crossing
    With coefficients ``c_k``, ``|T_k| <= 1`` gives ``p(t) >= c_0 - sum_k |c_k|`` on the
    interval. The detector is free of zeros when that bound, less the rounding level of the
    samples and, for a detector that is not polynomial, an estimate of the interpolation
    error from the last coefficients, stays positive. Each sample carries its own rounding
    level (:func:`hybridoc.kernels.rounding_level`): per guard, from the detector's gradient
    and curvature in the state components it depends on, times the rounding of those
    components (their magnitudes along the flow map, :func:`hybridoc.kernels.flow_scale_fn`).
    Every quantity below (the bound, the resolution test, "within rounding of zero") is
    taken per guard, so a guard between far or fast bodies never blurs another guard (one
    that needs halving has the others examined on the halves too: another path to the same
    roots, to rounding).

Subdivision
    Otherwise the interval is split in two unless it is *resolved*: the interpolant's error
    anywhere (the largest rounding level of the samples, the coefficients' own rounding and
    the interpolation error) is within a small factor of the smallest rounding level of the
    samples. On a long interval a small dip of the detector next to large values (discs that
    meet after a long flight) is lost in the rounding of the large values; halving the
    interval shrinks them until the dip is visible. Halves are examined in time order, so
    the first crossing found is the earliest.

Locating the crossing
    On a resolved interval the interpolant's real roots separate the interval into pieces
    of constant sign. The *true* detector is evaluated at one point inside each piece; a sign
    change from positive to negative brackets a crossing, which a safeguarded Newton iteration
    on the true detector (bisection whenever Newton leaves the bracket) locates to rounding.
    A dip of the interpolant that the true detector does not confirm, with the detector within
    its rounding level of zero, is a graze.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.polynomial import chebyshev as cheb

__all__ = ["Chebyshev", "CrossingSearch", "MAX_DEPTH"]

EPS = float(np.finfo(float).eps)
MAX_DEPTH = 64
"""Most halvings of one interval before the search gives up (an error, not a guess)."""
_LEBESGUE = 3.0  # rounding of the samples propagates to the interpolant by at most this
_RESOLVED = 64.0  # resolved: the interpolant's error within this factor of the finest noise


class Chebyshev:
    """Chebyshev-Lobatto nodes of degree ``D`` on ``[-1, 1]`` (ascending) and the map from
    values at the nodes to Chebyshev coefficients."""

    def __init__(self, D: int) -> None:
        self.D = int(D)
        self.x = -np.cos(np.pi * np.arange(self.D + 1) / self.D)
        self.interp = np.linalg.inv(cheb.chebvander(self.x, self.D))

    def coeffs(self, samples: np.ndarray) -> np.ndarray:
        """Coefficients ``(..., D + 1)`` from values ``(..., D + 1)`` at the nodes."""
        return samples @ self.interp.T

    def nodes(self, a: float, b: float) -> np.ndarray:
        """The nodes mapped to ``[a, b]``."""
        return a + (b - a) * (self.x + 1) / 2

    def free(self, samples: np.ndarray, noise: np.ndarray, exact: np.ndarray) -> np.ndarray:
        """Per guard, whether the interval is proven free of zeros (see the module notes)."""
        C = self.coeffs(samples)
        tail = np.where(exact, 0.0, 2.0 * (np.abs(C[..., -1]) + np.abs(C[..., -2])))
        sigma = _LEBESGUE * noise.max(axis=-1)
        lower = C[..., 0] - np.abs(C[..., 1:]).sum(axis=-1) - tail - sigma
        return lower > 0


@dataclass
class CrossingSearch:
    """The earliest downward crossing of any guard on ``[0, h]`` from one state.

    Parameters
    ----------
    cheb
        The node set.
    exact
        Per guard, whether its detector is a polynomial of degree ``<= D`` along the flow.
    window
        ``window(a, b) -> (samples, noise)``: detector values ``(G, D + 1)`` at the nodes of
        ``[a, b]`` and their rounding levels.
    value
        ``value(j, tau) -> (det, rate, noise)``: the true detector of guard ``j`` at ``tau``,
        its time derivative and its rounding level.
    approaching
        ``approaching(j, tau) -> bool``: whether guard ``j`` approaches fast enough at
        ``tau`` to jump (the grazing rule).
    penetrated
        ``penetrated(j, tau)``: called where guard ``j`` is found inside (below its rounding
        level) without an impact that put it there; it raises when that is beyond tolerance
        (sustained contact).
    time_scale
        The problem's unit of time (:attr:`Scales.time <hybridoc.scales.Scales.time>`): the
        floor of the rounding of a time near zero, so that the search halves and brackets
        alike in seconds or in microseconds.
    """

    cheb: Chebyshev
    exact: np.ndarray
    window: Callable[[float, float], tuple[np.ndarray, np.ndarray]]
    value: Callable[[int, float], tuple[float, float, float]]
    approaching: Callable[[int, float], bool]
    penetrated: Callable[[int, float], None] | None = None
    time_scale: float = 1.0

    def run(
        self, h: float, first: tuple[np.ndarray, np.ndarray] | None = None
    ) -> tuple[float, int] | None:
        """``(tau, guard)`` of the earliest crossing in ``[0, h]``, or ``None``.

        ``first``: the samples and noise on ``[0, h]`` when the caller has them already.
        """
        if h <= 0 or self.exact.size == 0:
            return None
        samples, noise = first if first is not None else self.window(0.0, h)
        # depth-first, left half first: the first crossing found is the earliest
        stack: list[tuple[float, float, np.ndarray, np.ndarray, int]] = [
            (0.0, h, samples, noise, 0)
        ]
        while stack:
            a, b, S, Nz, depth = stack.pop()
            free = self.cheb.free(S, Nz, self.exact)
            if free.all():
                continue
            C = self.cheb.coeffs(S)
            tail = np.where(self.exact, 0.0, 2.0 * (np.abs(C[:, -1]) + np.abs(C[:, -2])))
            # the interpolant's error everywhere against the accuracy needed where the
            # detector is smallest
            interp_noise = _LEBESGUE * Nz.max(axis=1) + 4 * EPS * np.abs(C).sum(axis=1) + tail
            unresolved = (~free) & (interp_noise > _RESOLVED * Nz.min(axis=1))
            tiny = (b - a) <= 64 * EPS * max(self.time_scale, abs(b))
            if unresolved.any() and not tiny:
                if depth >= MAX_DEPTH:
                    from hybridoc.errors import EvaluationError

                    j = int(np.flatnonzero(unresolved)[0])
                    raise EvaluationError(
                        f"cannot resolve guard {j} on a sub-interval of length {b - a:.3g}: its "
                        "detector is not resolved by 64 halvings (the flow may be too fast or "
                        "not smooth)"
                    )
                m = 0.5 * (a + b)
                Sl, Nl = self.window(a, m)
                Sr, Nr = self.window(m, b)
                stack.append((m, b, Sr, Nr, depth + 1))
                stack.append((a, m, Sl, Nl, depth + 1))
                continue
            hit = self._resolved(a, b, C, S, np.flatnonzero(~free))
            if hit is not None:
                return hit
        return None

    def _resolved(
        self, a: float, b: float, C: np.ndarray, S: np.ndarray, guards: np.ndarray
    ) -> tuple[float, int] | None:
        """Earliest confirmed crossing on a resolved interval among ``guards``."""
        found: list[tuple[float, int]] = []
        for j in guards:
            tau = self._guard(int(j), a, b, C[j], S[j])
            if tau is not None:
                found.append((tau, int(j)))
        if not found:
            return None
        return min(found)

    def _guard(self, j: int, a: float, b: float, c: np.ndarray, s: np.ndarray) -> float | None:
        half = 0.5 * (b - a)
        scale = np.abs(c).max()
        if scale == 0.0:
            return None
        cn = c / scale
        last = int(np.max(np.nonzero(np.abs(cn) > 1e-15)[0], initial=0))
        roots = cheb.chebroots(cn[: last + 1]) if last > 0 else np.zeros(0)
        # real roots, and the real parts of nearly real pairs (near-tangent dips)
        roots = roots[np.abs(roots.imag) <= 1e-6 + 1e-3 * np.abs(roots.real)].real
        roots = np.unique(np.clip(roots[(roots > -1 - 1e-9) & (roots < 1 + 1e-9)], -1.0, 1.0))
        ts = a + half * (roots + 1)
        # check points: the ends and one point inside every piece between consecutive roots
        cuts = np.unique(np.concatenate([[a], ts, [b]]))
        checks = [a]
        for lo, hi in zip(cuts[:-1], cuts[1:], strict=True):
            if hi > lo:
                checks.append(0.5 * (lo + hi))
        checks.append(b)
        prev_t, prev_d = None, None
        for t in checks:
            d, r, nz = self.value(j, t)
            if prev_t is None:
                if d <= nz:
                    # at contact already (e.g. just after a jump): a jump now if approaching
                    if self.approaching(j, t):
                        return t
                    prev_t, prev_d = t, None
                    continue
                prev_t, prev_d = t, d
                continue
            if prev_d is not None and prev_d > 0 and d < 0:
                tau = self._bracketed(j, prev_t, t)
                if self.approaching(j, tau):
                    return tau
                # a sign change at the rounding level without approach: a graze
            if d < -nz and self.penetrated is not None:
                # inside the guard without an impact (a resting contact pushed into, or a
                # graze that went on): the caller decides whether that is beyond tolerance
                self.penetrated(j, t)
            if d > 0 or abs(d) > nz:
                prev_t, prev_d = t, d
            elif prev_d is None or prev_d > 0:
                # within rounding of zero: a tangent touch; jumps only if approaching
                if self.approaching(j, t) and r < 0:
                    return t
                prev_t, prev_d = t, d
        return None

    def _bracketed(self, j: int, lo: float, hi: float) -> float:
        """Root of the true detector in ``[lo, hi]`` where it goes from > 0 to < 0:
        Newton's method, with bisection whenever a step leaves the bracket."""
        t = 0.5 * (lo + hi)
        for _ in range(200):
            d, r, _ = self.value(j, t)
            if d == 0.0:
                return t
            if d > 0:
                lo = t
            else:
                hi = t
            if hi - lo <= 4 * EPS * max(self.time_scale, abs(hi)):
                break
            newton = t - d / r if r != 0 else np.nan
            if lo < newton < hi:
                if abs(newton - t) <= 2 * EPS * max(self.time_scale, abs(t)):
                    return float(newton)
                t = float(newton)
            else:
                t = 0.5 * (lo + hi)
        d_lo = self.value(j, lo)[0]
        d_hi = self.value(j, hi)[0]
        return lo if abs(d_lo) <= abs(d_hi) else hi
