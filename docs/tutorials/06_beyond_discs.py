r"""
6. Beyond discs
===============

Discs on a table are one kind of hybrid system. A ball bouncing on the floor, a paddle
juggling a ball, a pendulum striking a wall: anything that flows, then jumps when a guard
reaches zero, is a :class:`~hybridoc.ocp.HybridOCP`, and every method of hybridoc solves it
the same way. In this tutorial we

1. write a bouncing ball with a thrust from CasADi expressions, in a dozen lines,
2. check that it has the same optimum as the one in hybridoc's library of classic
   problems, and cross-validate the three methods on it,
3. solve the library's juggling paddle, a ball driven only through impacts, by all three
   methods and plot it.

The model is described in :doc:`/scenes` ("The model: HybridOCP").
"""

# %%
# A bouncing ball, written by hand
# --------------------------------
# A ball on a vertical line, at height :math:`h` with velocity :math:`v`, is pushed by a
# thrust :math:`u` (per unit mass) against gravity: :math:`\dot h = v`,
# :math:`\dot v = u - g`. It starts at rest at :math:`h = 1`. When the height reaches zero
# it bounces: the guard is :math:`\psi = h` and the reset :math:`(h, v) \mapsto (h, -e v)`
# with restitution :math:`e = 0.8`. We want it to be at height :math:`h^*` and at rest at
# :math:`t = T`, at a small cost of thrust:
#
# .. math::
#
#    J = (h(T) - h^*)^2 + v(T)^2 + 0.01 \int_0^T u^2\,dt .
#
# Dropped without thrust it bounces once at :math:`t_1 = \sqrt{2 h_0 / g}` and, after the
# bounce, climbs for :math:`e\,t_1` to the height :math:`e^2 h_0`. We take that apex as the
# horizon and ask for 0.3 higher: a task that needs a push, and that the library's
# :func:`~hybridoc.problems.library.bouncing_ball` poses with its defaults.
import math
import os
import time

import casadi as ca

import hybridoc
from hybridoc import Guard, HybridOCP
from hybridoc.problems.library import bouncing_ball, juggling_paddle
from hybridoc.workflows.validation import crossval_figures

# ``HYBRIDOC_TUTORIAL_QUICK=1`` (set by the test suite) runs a smaller version of this
# page: the reference searches without its multi-start, gradient descent runs from one
# start for at most 100 iterations, and the judge is timed over fewer repeats.
QUICK = os.environ.get("HYBRIDOC_TUTORIAL_QUICK") == "1"
options = (
    {"reference": {"multistart": 0}, "gd": {"starts": 1, "iters": 100}} if QUICK else {}
)
repeats = 3 if QUICK else 20

g, e, eps, h0 = 9.81, 0.8, 0.01, 1.0
t1 = math.sqrt(2 * h0 / g)  # the first bounce of the free drop
T = t1 * (1 + e)  # the apex after it
target = e**2 * h0 + 0.3

s = ca.SX.sym("s", 2)  # the state: height, velocity
u = ca.SX.sym("u")  # the control: thrust
h, v = s[0], s[1]
floor = Guard.from_expressions(
    "floor",
    s,
    h,
    ca.vertcat(h, -e * v),
    kind="bounce",
    bodies=("ball", "floor"),
    degree=2,
)
my_ball = HybridOCP.from_expressions(
    s,
    u,
    f=ca.vertcat(v, u - g),
    L=eps * u**2,
    phi=(h - target) ** 2 + v**2,
    guards=[floor],
    x0=[h0, 0.0],
    horizon=T,
    steps=200,
    state_labels=["h", "v"],
    control_labels=["u"],
    name="my bouncing ball",
)
print(f"T = {T:.6f}, target height {target:.2f}, N = {my_ball.steps}")

# %%
# A :class:`~hybridoc.guards.Guard` is built from the state symbol, the expression of
# :math:`\psi` and the expression of the reset. Its ``degree`` says that :math:`\psi` is a
# polynomial of degree 2 in time while the thrust is constant, which lets the judge find
# every bounce exactly; leave it ``None`` for a guard that is not. ``kind`` and ``bodies``
# only label the events. Every other argument (the initial guess ``u_guess``, bounds
# ``u_min``/``u_max``, path constraints) keeps its default: here the guess is no thrust.
#
# The judge, on that guess, finds the bounce of the free drop, to the tolerance of the
# integrator that solves the flow (more on that below):
guess = hybridoc.evaluate(my_ball)
print(f"initial guess: cost {guess.cost:.6f}, events {guess.sequence}")
print(f"bounce at t = {guess.events[0].time:.12f}; sqrt(2 h0 / g) = {t1:.12f}")

# %%
# The same optimum as the library's
# ---------------------------------
# The library builds this problem with exactly these numbers. The reference solves both;
# the two optima must agree to the reference's accuracy:
library_ball = bouncing_ball()
print(
    library_ball.name,
    "| claimed optimal sequence:",
    library_ball.meta["claimed_sequence"],
)
mine = hybridoc.solve(my_ball, "reference", **options.get("reference", {}))
theirs = hybridoc.solve(library_ball, "reference", **options.get("reference", {}))
for label, sol in (("mine", mine), ("library", theirs)):
    print(
        f"{label:8s} {sol.status}  cost {sol.cost:.12f}  bounce at"
        f" {sol.events[0]['time']:.9f}  ({sol.timings['wall_time_s']:.1f} s)"
    )
print(f"relative difference {abs(mine.cost - theirs.cost) / theirs.cost:.1e}")

# %%
# One thing differs: the library's problem also carries a ``flow_map``, the closed-form
# solution of the flow under a constant thrust over a step :math:`\tau`,
# :math:`h + v\tau + (u - g)\tau^2/2`, :math:`v + (u - g)\tau`, and its cost
# :math:`\varepsilon u^2 \tau`. Without one, hybridoc integrates the flow with CVODES,
# accurate to its tight tolerances but slower. Ours is three lines (the flow map's inputs
# are the state, the control and the step), and
# :meth:`~hybridoc.ocp.HybridOCP.replace` adds it:
tau = ca.SX.sym("tau")
s_end = ca.vertcat(h + v * tau + (u - g) * tau**2 / 2, v + (u - g) * tau)
flow_map = ca.Function("flow_map", [s, u, tau], [s_end, eps * u**2 * tau])
integrated = my_ball
my_ball = my_ball.replace(flow_map=flow_map)
costs = {}
for label, problem in (("integrated", integrated), ("closed form", my_ball)):
    start = time.perf_counter()
    for _ in range(repeats):
        costs[label] = hybridoc.evaluate(problem, mine.controls).cost
    print(
        f"{label:11s} {(time.perf_counter() - start) / repeats * 1e3:5.1f} ms"
        " per judgement"
    )
print(f"the two costs differ by {abs(costs['integrated'] - costs['closed form']):.1e}")

# %%
# The judge prices the optimum's grid controls the same, to the integrator's tolerance,
# in a fraction of the time: give a flow map whenever the flow has a closed form.
#
# Three methods, cross-validated
# ------------------------------
# :func:`hybridoc.crossval` runs the reference, the direct transcription and gradient
# descent on our problem, exactly as on the paper's scenes in tutorial 1:
report, sols = hybridoc.crossval(my_ball, options=options)
print("agree:", report["agree"], report["reasons"])
for method in ("reference", "dt", "gd"):
    entry = report[method]
    print(
        f"{method:9s}  cost {entry['cost']:.9f}  gap {entry['cost_gap_relative']:.1e}"
        f" (tolerance {entry['tolerance']:.0e})  events {entry['sequence']}"
    )

# %%
# The states against time: the velocity jumps from :math:`v^-` to :math:`-e\,v^-` at
# the bounce. The ball ends almost at rest, some way below the target height: rising
# further would cost more thrust than it saves in the terminal cost.
ball_figures = crossval_figures(my_ball, sols)
fig_ball = ball_figures["trajectories"]
h_T, v_T = hybridoc.evaluate(my_ball, sols["reference"].controls).states[-1]
print(f"at T: height {h_T:.4f} (target {target:.2f}), velocity {v_T:+.4f}")

# %%
# The thrust is linear in time between bounces and changes sign across the bounce:
# :math:`u = -\lambda_v / (2\varepsilon)`, and the hybrid minimum principle (tutorial 2)
# makes the costate jump so that :math:`u(\gamma^-) = -e\,u(\gamma^+)`. Gradient descent,
# which works on the grid, rounds the corner.
fig_ball_controls = ball_figures["controls"]

# %%
# The reference returns the costate after each jump; before the bounce
# :math:`\lambda_h` is constant and :math:`\dot\lambda_v = -\lambda_h`, so we can
# check the jump of the thrust from its numbers:
lam_0, lam_plus = sols["reference"].arrays["phase_costates"]
gamma = sols["reference"].arrays["event_times"][0]
u_minus = -(lam_0[1] - lam_0[0] * gamma) / (2 * eps)
u_plus = -lam_plus[1] / (2 * eps)
print(
    f"u(gamma-) = {u_minus:+.9f}, u(gamma+) = {u_plus:+.9f}, ratio {u_minus / u_plus:+.12f}"
)

# %%
# A juggling paddle
# -----------------
# :func:`~hybridoc.problems.library.juggling_paddle` is harder to steer: a paddle at
# :math:`y_p`, whose acceleration is the control, hits a passive ball at :math:`y_b` that
# only gravity moves. The guard :math:`\psi = y_b - y_p` moves with the paddle, and the
# impact sets the ball's velocity to :math:`v_p - e\,(v_b - v_p)`. The ball should reach
# the height 1.5 at rest at :math:`T = 1`, and the paddle return to rest at 0:
paddle = juggling_paddle()
print(paddle.name, "| horizon", paddle.horizon, "| N =", paddle.steps)
print("state:", paddle.state_labels, "| control:", paddle.control_labels)
print("guards:", [gd.name for gd in paddle.guards])
print("claimed optimal sequence:", paddle.meta["claimed_sequence"])

# %%
# The whole problem is written like ours (read ``problems/library/juggling_paddle.py``):
# four states, one guard, one reset. All three methods:
report, sols = hybridoc.crossval(paddle, options=options)
print("agree:", report["agree"], report["reasons"])
for method in ("reference", "dt", "gd"):
    sol = sols[method]
    times = ", ".join(f"{ev['time']:.6f}" for ev in sol.events)
    print(
        f"{method:9s}  {sol.status}  cost {sol.cost:.9f}  impact at {times}"
        f"  gap {report[method]['cost_gap_relative']:.1e}"
    )

# %%
# The paddle first draws back, then swings up and strikes the falling ball once, low; the
# ball's velocity jumps at the strike, the paddle's state is continuous (with the default
# mass ratio 0 the paddle is much heavier than the ball). The ball then rises to about
# 1.5, and the paddle slows down without returning to rest: its final state weighs only
# 0.1 in the cost.
paddle_figures = crossval_figures(paddle, sols)
fig_paddle = paddle_figures["trajectories"]
y_p, v_p, y_b, v_b = hybridoc.evaluate(paddle, sols["reference"].controls).states[-1]
print(
    f"at T: ball at {y_b:.4f} moving {v_b:+.4f}, paddle at {y_p:.4f} moving {v_p:+.4f}"
)
# sphinx_gallery_thumbnail_number = 5

# %%
# The paddle's acceleration is linear between events and jumps at the strike; the three
# methods lie on top of each other.
fig_paddle_controls = paddle_figures["controls"]

# %%
# The library holds two more problems, a ball on a slope and a pendulum striking a wall
# (:doc:`/scenes`), and every command takes any of them by name or a Python file's
# function: ``hybridoc crossval juggling-paddle`` prints the same as above, and
# ``hybridoc crossval my_ball.py:problem`` would solve ours.
