r"""
2. The hybrid minimum principle, step by step
=============================================

Tutorial 1 called the reference the ground truth. Here we open it: we write down the
necessary conditions of optimality for the single-collision problem, check each of them
on the computed solution with a few lines of NumPy and CasADi, and finally reproduce the
optimal cost from a closed form that does not use hybridoc's solvers at all.

The conditions
--------------
With the Hamiltonian :math:`H(s, \lambda, u) = L(s, u) + \lambda^\top f(s, u)`, an optimal
control with one event at time :math:`\gamma` has a costate :math:`\lambda(t)` with

.. math::

   \dot\lambda &= -\partial H / \partial s
      &&\quad \text{between events (costate equation)}\\
   u &= \arg\min_u H
      &&\quad \text{(optimal control)}\\
   \lambda(T) &= \nabla\phi(s(T))
      &&\quad \text{(transversality)}\\
   \lambda(\gamma^-) &= Dg(s(\gamma^-))^\top \lambda(\gamma^+) + \pi\,\nabla\psi(s(\gamma^-))
      &&\quad \text{(costate jump, multiplier } \pi)\\
   H(\gamma^-) &= H(\gamma^+)
      &&\quad \text{(Hamiltonian continuity)}

and the guard condition :math:`\psi(s(\gamma^-)) = 0` that defines the event. The reference
solves these equations by Newton's method (shooting) for the unknowns
:math:`\lambda(0), \gamma, \pi, \lambda(\gamma^+)`.

For discs, :math:`s = (p, v)`, :math:`f = (v, M^{-1}Bu)` and :math:`L = \varepsilon|u|^2`.
So :math:`\dot\lambda_p = 0` and :math:`\dot\lambda_v = -\lambda_p`: the position costate
is constant and the velocity costate linear between events. Minimising
:math:`H = \varepsilon |u|^2 + \lambda_v^\top M^{-1} B u` gives
:math:`u = -B^\top M^{-\top} \lambda_v / (2\varepsilon)`, linear in time too.
"""

# %%
# The computed solution
# ---------------------
# The reference's :class:`~hybridoc.solution.Solution` keeps the extremal it solved for
# as ``sol.reference`` (a :class:`~hybridoc.reference.result.ReferenceResult`): event
# times, multipliers, the states and costates on both sides of each event, and the final
# state and costate.
import os

import casadi as ca
import numpy as np
from scipy.optimize import minimize

import hybridoc

# ``HYBRIDOC_TUTORIAL_QUICK=1`` (set by the test suite): the reference searches without
# its multi-start (the same extremal, sooner)
QUICK = os.environ.get("HYBRIDOC_TUTORIAL_QUICK") == "1"
np.set_printoptions(linewidth=88, suppress=True)
sol = hybridoc.solve(
    "single-collision", "reference", **({"multistart": 0} if QUICK else {})
)
ext = sol.reference
ocp = hybridoc.as_ocp("single-collision")
eps = 0.01  # the scene's control_weight
gamma = float(ext.event_times[0])
print(f"optimal cost {sol.cost:.12f}, one event {ext.sequence} at gamma = {gamma:.9f}")
print(f"jump multiplier pi = {ext.multipliers[0]:.9f}")
print(f"Newton's residual history: {[f'{r:.1e}' for r in ext.residual_history]}")

# %%
# The costate equation and the optimal control
# --------------------------------------------
# ``ext.dense(t)`` returns :math:`(s, \lambda, u)` at any times. Between events,
# :math:`\lambda_p` must stay constant, :math:`\lambda_v` must change at rate
# :math:`-\lambda_p`, and the control must be :math:`-\lambda_{v,1}/(2\varepsilon)` (unit
# mass, the force acts on ``ball1`` only: velocity components 4 and 5 of the state).
t = np.linspace(0.0, 1.0, 2001)
t = t[np.abs(t - gamma) > 1e-9]
s, lam, u = ext.dense(t)
h = 1e-6
_, lam_h, _ = ext.dense(t[:-1] + h)
phase = t[:-1] < gamma
same = (t[:-1] + h < gamma) == phase  # finite differences that do not cross the event
lam_dot = (lam_h - lam[:-1])[same] / h
print("max |d lambda_p/dt|            =", f"{np.abs(lam_dot[:, :4]).max():.1e}")
print(
    "max |d lambda_v/dt + lambda_p| =",
    f"{np.abs(lam_dot[:, 4:] + lam[:-1][same, :4]).max():.1e}",
)
print(
    "max |u + lambda_v1 / (2 eps)|  =",
    f"{np.abs(u + lam[:, 4:6] / (2 * eps)).max():.1e}",
)

# %%
# Transversality
# --------------
# The terminal cost is :math:`\phi = |p_2(T)|^2`, so :math:`\lambda(T)` must be
# :math:`2 p_2(T)` in the position components of ``ball2`` and zero elsewhere.
sT, lamT = ext.final_state, ext.final_costate
grad_phi = np.asarray(
    ca.Function("gphi", [x := ca.SX.sym("x", 8)], [ca.gradient(ocp.phi(x), x)])(sT)
).ravel()
print("lambda(T)      =", np.round(lamT, 6) + 0.0)  # + 0.0: no negative zeros
print("grad phi(s(T)) =", np.round(grad_phi, 6) + 0.0)

# %%
# The costate jump and its multiplier
# -----------------------------------
# At the event the state jumps by the reset map :math:`g` (an elastic impact) and the
# costate by the transpose of its Jacobian, plus the multiplier :math:`\pi` times the
# guard's gradient. Both :math:`g` and :math:`\psi` are CasADi functions of the problem,
# so their derivatives are one call away.
guard = ocp.guards[ocp.guard_index(ext.sequence[0])]
x = ca.SX.sym("x", ocp.nx)
Dg = ca.Function("Dg", [x], [ca.jacobian(guard.reset(x), x)])
grad_psi = ca.Function("grad_psi", [x], [ca.gradient(guard.psi(x), x)])

s_minus, lam_minus = ext.states_minus[0], ext.costates_minus[0]
s_plus, lam_plus = ext.phase_states[1], ext.phase_costates[1]
pi = ext.multipliers[0]
jump = np.asarray(Dg(s_minus)).T @ lam_plus + pi * np.asarray(grad_psi(s_minus)).ravel()
print(f"guard at the event  psi(s(gamma-)) = {float(guard.psi(s_minus)):.1e}")
reset_error = np.abs(np.asarray(guard.reset(s_minus)).ravel() - s_plus).max()
print(f"reset               |g(s-) - s+|   = {reset_error:.1e}")
print(f"costate jump        max residual   = {np.abs(lam_minus - jump).max():.1e}")
print("lambda(gamma-) =", np.round(lam_minus, 4) + 0.0)
print("lambda(gamma+) =", np.round(lam_plus, 4) + 0.0)


# %%
# After the impact ``ball1`` no longer matters, so its costate, and with it its force, is
# zero; before the impact its costate carries the target error back through the coming
# collision. The multiplier :math:`\pi` is the price of the event time: the term
# :math:`\pi\nabla\psi` is what makes the two sides consistent.
#
# Hamiltonian continuity
# ----------------------
# :math:`H` is constant along each phase of an autonomous problem, and it must not jump
# at the event: the event time is optimal.
def hamiltonian(s, lam):
    """H(s, lambda, u*) with the optimal control u* = -lambda_v1 / (2 eps).

    Parameters
    ----------
    s, lam : numpy.ndarray
        State and costate, shape ``(8,)``.

    Returns
    -------
    float
        The Hamiltonian.
    """
    u = -lam[4:6] / (2 * eps)
    return float(ocp.L(s, u)) + float(lam @ np.asarray(ocp.f(s, u)).ravel())


H_minus, H_plus = hamiltonian(s_minus, lam_minus), hamiltonian(s_plus, lam_plus)
H_start = hamiltonian(ext.phase_states[0], ext.phase_costates[0])
H_end = hamiltonian(sT, lamT)
print(f"H(0) = {H_start:.12f}   H(gamma-) = {H_minus:.12f}")
print(f"H(T) = {H_end:.12f}   H(gamma+) = {H_plus:.12f}")
print(f"jump of H at the event: {H_plus - H_minus:.1e}")

# %%
# The reference recomputes every group of conditions from its stored numbers, too:
for group, value in ext.hmp_residuals().items():
    print(f"{group:15s} {value:.1e}")

# %%
# The closed form
# ---------------
# For this problem the conditions can be solved almost by hand. Fix the impact time
# :math:`\gamma` and the contact normal :math:`n = (\cos\theta, \sin\theta)` pointing from
# ``ball1`` to ``ball2``. Then ``ball1`` must travel from :math:`p_0` at rest to the contact
# position :math:`q_0 - 2rn` and arrive with some velocity :math:`V`; the least effort for
# a double integrator to do that in time :math:`\gamma` is
#
# .. math::
#
#    \int_0^\gamma |u|^2\,dt = \frac{4|V|^2}{\gamma} - \frac{12\, d\cdot V}{\gamma^2}
#       + \frac{12|d|^2}{\gamma^3}, \qquad d = q_0 - 2rn - p_0 .
#
# An elastic impact of equal masses hands over the normal velocity: ``ball2`` leaves
# with :math:`(V\cdot n)\,n` and coasts for :math:`\tau = T - \gamma`; ``ball1`` no longer
# matters, so its force is zero. Writing :math:`V = a n + b t` with :math:`t \perp n`, the
# cost is a quadratic in :math:`(a, b)`, minimised exactly, which leaves a minimisation
# over :math:`(\gamma, \theta)` alone:
p0, q0, target, r, T = (
    np.array([-1.0, -2.0]),
    np.array([-1.0, -1.0]),
    np.zeros(2),
    0.2,
    1.0,
)


def one_collision_cost(x):
    """Cost of striking the resting ``ball2`` at time ``x[0]`` along angle ``x[1]``.

    Parameters
    ----------
    x : sequence of float
        ``(gamma, theta)``: impact time and direction of the contact normal.

    Returns
    -------
    float
        The least cost over the striker's arrival velocity (``inf`` if it cannot strike).
    """
    g, th = x
    if not 0 < g < T:
        return np.inf
    n, tang = np.array([np.cos(th), np.sin(th)]), np.array([-np.sin(th), np.cos(th)])
    d = q0 - 2 * r * n - p0
    tau, c = T - g, q0 - target
    a = (12 * eps * (d @ n) / g**2 - 2 * tau * (c @ n)) / (8 * eps / g + 2 * tau**2)
    if a <= 0:  # the striker must approach
        return np.inf
    b = 3 * (d @ tang) / (2 * g)
    effort = (
        4 * (a * a + b * b) / g
        - 12 * (d @ n * a + d @ tang * b) / g**2
        + 12 * d @ d / g**3
    )
    return eps * effort + np.sum((c + tau * a * n) ** 2)


grid = [
    (one_collision_cost((g, th)), g, th)
    for g in np.linspace(0.05, 0.95, 19)
    for th in np.linspace(-np.pi, np.pi, 72, endpoint=False)
]
start = min(grid)[1:]
res = minimize(
    one_collision_cost,
    start,
    method="Nelder-Mead",
    options={"xatol": 1e-12, "fatol": 1e-16, "maxiter": 5000},
)
print(f"closed form:  cost {res.fun:.12f} at gamma = {res.x[0]:.9f}")
print(f"reference:    cost {sol.cost:.12f} at gamma = {gamma:.9f}")
print(f"relative difference {abs(res.fun - sol.cost) / sol.cost:.1e}")

# %%
# Two independent routes, the shooting on the hybrid minimum principle and a
# two-parameter minimisation of a closed form, give the same optimum, which lies below the
# paper's grid-search value 0.3115. ``tests/test_reference.py`` makes the same check for
# this problem and for closed forms of the others (:doc:`/reference`).
#
# Next: tutorial 3 asks what the gradient of a *simulator* has to do with all this.
