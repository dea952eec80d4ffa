r"""
10. Modes: a hopping robot
==========================

A hopping robot is in flight or in stance, and its dynamics are not the same in the two:
in flight only gravity acts, in stance a spring leg pushes it up and a motor in the leg can
add to it. Such a system has discrete **modes**, each with its own flow and running cost,
and transitions between them. In this tutorial we

1. write a one-legged hopper with two modes from CasADi expressions
   (:meth:`~hybridoc.ocp.HybridOCP.from_modes`),
2. solve it three ways: the HMP reference, direct transcription and gradient descent,
3. check the hybrid minimum principle on the optimum: the Hamiltonian of each mode is
   constant along it and equal across the switches, and the costate jumps along the guard,
4. list the hopper's mode sequences and the extremal of each.

A problem with modes is an ordinary :class:`~hybridoc.ocp.HybridOCP` whose last state
coordinate is the mode index (a float: 0, 1, ...): every method solves it unchanged.
What the model can and cannot express is in :doc:`/scenes` ("Modes").
"""

# %%
# The hopper
# ----------
# A mass :math:`m = 1` at height :math:`y` with velocity :math:`v`. In flight it falls,
# :math:`\dot v = -g`; the leg force :math:`u` is charged in the cost but acts on nothing.
# In stance the leg of rest length :math:`l_0` is a spring of stiffness :math:`k`, plus
# the motor: :math:`\dot v = -g + k (l_0 - y) + u`. Touchdown (flight to stance) when
# :math:`y - l_0` reaches zero from above, liftoff (stance to flight) when
# :math:`l_0 - y` does; the resets are the identity. It starts in flight at
# :math:`y = 1.3` at rest, and should be at :math:`y = 1.6` at :math:`T = 1.2`:
#
# .. math::
#
#    J = (y(T) - 1.6)^2 + 0.01 \int_0^T u^2\,dt .
#
# Each transition is a :class:`~hybridoc.guards.Guard` with a ``source`` and a ``target``
# mode, written in the state without the mode.
import os
import time

import casadi as ca
import numpy as np
from matplotlib.figure import Figure

import hybridoc
from hybridoc import Guard, HybridOCP
from hybridoc.reference.candidates import enumerate_sequences
from hybridoc.reference.result import reference_control

# ``HYBRIDOC_TUTORIAL_QUICK=1`` (the test suite) runs a smaller version of this page: the
# reference is given the optimal sequence, gradient descent is left out, and the
# sequences of the last section are solved without the reference's multi-start.
QUICK = os.environ.get("HYBRIDOC_TUTORIAL_QUICK") == "1"

g, k, l0 = 9.81, 400.0, 1.0
s = ca.SX.sym("s", 2)  # height, velocity (the mode is added)
u = ca.SX.sym("u")
y, v = s[0], s[1]
hopper = HybridOCP.from_modes(
    s,
    u,
    modes={
        "flight": (ca.vertcat(v, -g), 0.01 * u**2),
        "stance": (ca.vertcat(v, -g + k * (l0 - y) + u), 0.01 * u**2),
    },
    transitions=[
        Guard.from_expressions(
            "touchdown", s, y - l0, s, degree=2, source="flight", target="stance"
        ),
        Guard.from_expressions(
            "liftoff", s, l0 - y, s, source="stance", target="flight"
        ),
    ],
    initial_mode="flight",
    phi=(y - 1.6) ** 2,
    x0=[1.3, 0.0],
    horizon=1.2,
    steps=240,
    state_labels=["y", "v"],
    name="my-hopper",
)
print("modes:", hopper.modes, " state:", hopper.state_labels, " x0:", hopper.x0)

# %%
# The judge on the hopper without a push: it falls, bounces on its leg twice, and every
# event names its transition and the modes before and after.
free = hybridoc.evaluate(hopper)
for e in free.events:
    print(f"t = {e.time:.6f}  {e.name:9s}  {e.mode_before} -> {e.mode_after}")
print(f"cost {free.cost:.6f}: y(T) = {free.final_state[0]:.4f}, short of 1.6")

# %%
# Three ways to the optimum
# -------------------------
# The reference solves the hybrid minimum principle for the event sequences it finds;
# direct transcription collocates each phase (the stance's oscillation needs a finer mesh
# than the default to place the events to the judge's tolerance); gradient descent runs
# through the time-of-impact simulation. The hopper is the library's ``hopper`` too
# (:func:`~hybridoc.problems.library.hopper.hopper`, with exact flow maps of both modes).
HOP = ["touchdown", "liftoff", "touchdown", "liftoff"]
sols = {}
t0 = time.perf_counter()
if QUICK:  # the optimal sequence given: a second instead of ten
    sols["reference"] = hybridoc.solve(
        hopper, "reference", sequence=HOP, progress=False
    )
else:
    sols["reference"] = hybridoc.solve(hopper, "reference", progress=False)
sols["dt"] = hybridoc.solve(hopper, "dt", mesh=16)
if not QUICK:
    sols["gd"] = hybridoc.solve(hopper, "gd")
for name, sol in sols.items():
    print(f"{name:9s}  cost {sol.cost:.10f}  {sol.status.value:8s}  modes {sol.modes}")
print(f"({time.perf_counter() - t0:.0f} s)")

# %%
# Every Solution gives the modes its optimum visits (:attr:`~hybridoc.Solution.modes`,
# from its events' ``mode_before`` and ``mode_after``). The optimum hops twice, as the
# free hopper does, but times its hops: the first stance pushes, then pulls (a lower,
# quicker hop), the second pulls, then pushes hard, and at ``T`` the hopper is at 1.29,
# still rising. The push is zero in flight, where it would act on nothing.
ref = sols["reference"]
times, states, lam = ref.costate_times, ref.states, ref.costates
u_of, _ = reference_control(ref)
# u is right-continuous: on the row before a jump (the event's time recorded twice) take
# its limit from the left
left = np.r_[times[1:] == times[:-1], False]
U = np.array(
    [
        u_of(np.nextafter(t, -np.inf) if lt else t)
        for t, lt in zip(times, left, strict=True)
    ]
)
fig = Figure(figsize=(8.0, 4.2), layout="constrained")
ax_y, ax_u = fig.subplots(2, 1, sharex=True)
ax_y.plot(times, states[:, 0], label="reference")
ax_y.plot(free.times, free.states[:, 0], "--", color="grey", label="no push")
ax_y.axhline(l0, color="k", lw=0.6)
ax_y.set_ylabel("y")
ax_y.legend(loc="upper left")
for name, sol in sols.items():
    ax_u.step(sol.time_grid[:-1], sol.controls[:, 0], where="post", label=name)
ax_u.set_ylabel("u")
ax_u.set_xlabel("t")
ax_u.legend(loc="lower left")
for ax in (ax_y, ax_u):
    for e in ref.events:
        ax.axvline(e["time"], color="k", lw=0.4, ls=":")
fig_hop = fig

# %%
# The hybrid minimum principle, mode by mode
# ------------------------------------------
# With :math:`f = f_q` and :math:`L = L_q` selected by the mode, the Hamiltonian is
# :math:`H_q = L_q + \lambda^\top f_q` in mode :math:`q`. Along an optimum of an autonomous
# problem it is constant, and at each switch it is continuous: the same constant in every
# mode. The reference's Solution carries the costate (both sides of every event), so we
# can check it. The costate of the mode index is zero throughout: nothing depends on it
# but the choice of flow, which is constant between switches.
H = np.array(
    [
        float(hopper.L(ca.DM(x), ca.DM(uu)))
        + lm @ np.array(hopper.f(ca.DM(x), ca.DM(uu))).ravel()
        for x, uu, lm in zip(states, U, lam, strict=True)
    ]
)
modes_at = [hopper.mode_of(x) for x in states]
for q in hopper.modes:
    sel = np.array([m == q for m in modes_at])
    print(f"H in {q:6s}: {H[sel].mean():+.10f}, spread {np.ptp(H[sel]):.1e}")
print(f"largest |dlambda_mode|: {np.abs(lam[:, 2]).max():.1e}")

# %%
# At an event the costate jumps by :math:`\lambda(\gamma^-) = Dg^\top\lambda(\gamma^+)
# + \pi \nabla\psi`. The resets are the identity and both guards have the gradient
# :math:`\pm(1, 0)` in :math:`(y, v)`, so only :math:`\lambda_y` jumps, by the multiplier
# :math:`\pi`; :math:`\lambda_v`, and with it the stance's optimal push
# :math:`u = -\lambda_v / 0.02`, is continuous.
for e in ref.events:
    at = np.flatnonzero(times == e["time"])
    before, after = lam[at[0]], lam[at[-1]]
    print(
        f"{e['guard']:9s} t = {e['time']:.6f}: jump of lambda_y {after[0] - before[0]:+.6f},"
        f" of lambda_v {after[1] - before[1]:+.1e}"
    )
fig = Figure(figsize=(8.0, 4.2), layout="constrained")
ax_h, ax_l = fig.subplots(2, 1, sharex=True)
for q, color in zip(hopper.modes, ("tab:blue", "tab:orange"), strict=True):
    sel = np.array([m == q for m in modes_at])
    ax_h.plot(times[sel], H[sel], ".", ms=3, color=color, label=f"H in {q}")
ax_h.set_ylim(H.mean() - 1e-3, H.mean() + 1e-3)
ax_h.set_ylabel("Hamiltonian")
ax_h.legend(loc="upper right")
ax_l.plot(times, lam[:, 0], label=r"$\lambda_y$")
ax_l.plot(times, lam[:, 1], label=r"$\lambda_v$")
ax_l.set_ylabel("costate")
ax_l.set_xlabel("t")
ax_l.legend(loc="lower left")
for ax in (ax_h, ax_l):
    for e in ref.events:
        ax.axvline(e["time"], color="k", lw=0.4, ls=":")
fig_hmp = fig

# %%
# The mode sequences
# ------------------
# Only sequences in which each transition leaves the mode the hopper is in can happen:
# :meth:`~hybridoc.ocp.HybridOCP.sequence_feasible` says which, and
# :meth:`~hybridoc.ocp.HybridOCP.modes_along` which modes they visit. The reference's
# search tries only those. Shooting on each of them: the hopper must touch down (it falls
# whatever the leg does), the one-hop sequence has a costlier extremal, and the
# three-event one (ending in stance) has none that re-simulates to its own events.
sequences = list(enumerate_sequences(hopper, 4))
for seq in sequences:
    line = " -> ".join(hopper.modes_along(seq))
    if QUICK and len(seq) < 2:
        print(f"{len(seq)} events: {line}")
        continue
    try:
        sol = hybridoc.solve(
            hopper,
            "reference",
            sequence=seq,
            progress=False,
            **({"multistart": 0} if QUICK else {}),
        )
        found = f"extremal cost {sol.cost:.6f} ({sol.status.value})"
    except hybridoc.HybridocError as exc:
        found = f"no extremal ({type(exc).__name__})"
    print(f"{len(seq)} events: {line}: {found}")
print("feasible?", ["liftoff"], hopper.sequence_feasible(["liftoff"]))
