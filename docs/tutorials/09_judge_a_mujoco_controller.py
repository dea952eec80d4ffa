r"""
9. Judge a MuJoCo controller
============================

Controllers are usually learned in a mainstream simulator, and the question that follows
is how far the controller, and the simulator's gradients, are from the truth. hybridoc
answers it for a MuJoCo user in four steps, on the paper's ``single-collision``:

1. export the scene to MuJoCo (:func:`~hybridoc.workflows.mujoco.scene_to_mjcf`, or
   ``hybridoc export mjcf``) and check that the exported contact keeps the scene's
   restitution;
2. optimise the control in MuJoCo the way users do: MuJoCo's per-step Jacobians
   (``mujoco.mjd_transitionFD``) chained backwards into a gradient, and L-BFGS from SciPy;
3. judge the result with :func:`hybridoc.evaluate`, against the exact optimum;
4. put MuJoCo's gradient beside the exact one (:func:`hybridoc.gradient`) and find why
   they differ.

Every number below is computed when this page is built. The settings are those of
:doc:`the MuJoCo page </mujoco>`: contact stiffness :math:`k = 10^6\,\mathrm{s^{-2}}` and
:math:`K = 10` MuJoCo steps per control interval.
"""

# %%
# The settings of this page
# -------------------------
# MuJoCo's gradient costs one ``mjd_transitionFD`` call per MuJoCo step (4800 of them
# here), so the optimisation gets a budget of cost-and-gradient evaluations rather than
# running to its end. ``HYBRIDOC_TUTORIAL_QUICK=1`` (set by the test suite) makes the
# budget and the cost scan below smaller.
import dataclasses
import os
import re
import tempfile
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from scipy.optimize import minimize

import hybridoc
from hybridoc.problems import load_scene
from hybridoc.workflows.mujoco import load_model, scene_to_mjcf

QUICK = os.environ.get("HYBRIDOC_TUTORIAL_QUICK") == "1"
STIFFNESS = 1e6  # k, 1/s^2: a contact lasts pi / sqrt(k) = 3.1 ms
SUBSTEPS = 10  # K: MuJoCo's step h = T / (N K) = 1/4800 s, 15 steps per contact
EVALUATIONS = 2 if QUICK else 80  # L-BFGS's budget of cost-and-gradient evaluations
SCAN = 9 if QUICK else 41  # constant controls in the cost scan

# %%
# Export the scene
# ----------------
# :func:`~hybridoc.workflows.mujoco.scene_to_mjcf` writes the MJCF text (the command line
# does the same: ``hybridoc export mjcf single-collision --out single-collision.xml``). Each
# disc is a sphere on two slide joints whose positions are world coordinates, the motors
# are named by the problem's control labels, and the contact is a spring-damper set by a
# negative ``solref``.
scene = load_scene("single-collision")
problem = scene.to_ocp()
xml = scene_to_mjcf(scene, substeps=SUBSTEPS, stiffness=STIFFNESS)
path = Path(tempfile.mkdtemp()) / "single-collision.xml"
path.write_text(xml)
print(
    "\n".join(line for line in xml.splitlines() if "solref" in line or "<motor" in line)
)

# %%
# :func:`~hybridoc.workflows.mujoco.load_model` compiles the file and knows the maps
# between MuJoCo's arrays and hybridoc's: a rollout of an ``(N, nu)`` control (each row
# held for :math:`K` steps), MuJoCo's cost with the problem's own running and terminal
# costs, and MuJoCo's gradient.
model = load_model(scene, xml=path)
print(
    f"MuJoCo step h = {model.timestep:.3g} s, {model.steps} steps over T = {scene.horizon}"
)

# %%
# Does the exported contact bounce?
# ---------------------------------
# A head-on bounce: ``ball1`` starts at 2 m/s towards ``ball2``, which sits 1 m above it,
# and no force acts. The scene's restitution is 1, so the kinetic energy after the bounce
# should equal the energy before. We compare the exported contact with MuJoCo's default one
# (``solref = "0.02 1"``, ``solimp = "0.9 0.95 0.001"``), which a hand translation gets.
bounce = dataclasses.replace(
    scene,
    discs=(dataclasses.replace(scene.discs[0], velocity=(0.0, 2.0)), scene.discs[1]),
)
exported = scene_to_mjcf(bounce, substeps=SUBSTEPS, stiffness=STIFFNESS)
default = re.sub(r'\s+sol(ref|imp)="[^"]*"', "", exported)  # MuJoCo's defaults
zero = np.zeros((scene.steps, scene.n_controls))
energy = {}
for label, text in [("exported", exported), ("default", default)]:
    file = Path(tempfile.mkdtemp()) / f"{label}.xml"
    file.write_text(text)
    roll = load_model(bounce, xml=file).rollout(zero)
    energy[label] = np.sum(roll.states[-1, 4:] ** 2) / 2.0**2
    print(
        f"{label:>8} contact: energy after / before {energy[label]:.4f}, "
        f"deepest penetration {1e3 * roll.max_penetration:.2f} mm"
    )

# %%
# The exported contact keeps the energy to about a tenth of a percent; MuJoCo's default
# contact is a damped spring that loses about half of it. The small gain of the exported
# one comes from the contact starting on a MuJoCo step rather than at the instant of touch;
# it shrinks with more substeps (the MuJoCo page has the numbers).
#
# The exact optimum, run in MuJoCo
# --------------------------------
# The reference gives the exact optimum :math:`J^*` (tutorial 1 shows that its search finds
# this one-event sequence; naming the sequence here saves the search). Its control is a
# function of time; ``optimum.controls`` are its values on the grid, which cost a little
# more when held over each interval. Run in the exported model, those values cost a little
# more again: MuJoCo's Euler step ends positions :math:`O(h)` away from the exact flow, and
# its contact is slightly compliant. With MuJoCo's default contact the bounce is too weak
# and the cost is far off.
optimum = hybridoc.solve(problem, "reference", sequence=["ball1|ball2"])
sampled = hybridoc.evaluate(problem, optimum.controls)
in_mujoco = model.rollout(optimum.controls)
file = Path(tempfile.mkdtemp()) / "default.xml"
file.write_text(re.sub(r'\s+sol(ref|imp)="[^"]*"', "", xml))
default_cost = load_model(scene, xml=file).cost(optimum.controls)
for label, cost in [
    ("the exact optimum J*", optimum.cost),
    ("its grid values, judged", sampled.cost),
    ("its grid values in MuJoCo", in_mujoco.cost),
    ("the same with MuJoCo's default contact", default_cost),
]:
    print(f"{label:>38}  {cost:.6f}  ({100 * (cost / optimum.cost - 1):+.2f}% vs J*)")
print(
    f"ball2 at T: MuJoCo {in_mujoco.states[-1, 2:4]}, judge {sampled.final_state[2:4]}"
)

# %%
# Optimise in MuJoCo
# ------------------
# :meth:`~hybridoc.workflows.mujoco.MujocoModel.cost_and_gradient` is what a MuJoCo user
# writes: at every step ``mjd_transitionFD`` gives the Jacobians
# :math:`A_i = \partial s_{i+1}/\partial s_i` and :math:`B_i = \partial s_{i+1}/\partial u_i`
# by finite differences of one step, and the costate runs backwards,
# :math:`\lambda_i = A_i^\top \lambda_{i+1}` (plus the running cost's derivatives), with
# :math:`\partial J/\partial u_i = B_i^\top \lambda_{i+1} + h\,\partial L/\partial u`.
# L-BFGS starts from the scene's initial guess. We judge every control it evaluates.
u_start = scene.initial_controls()
history: list[tuple[float, float]] = []


def cost_and_gradient(x: np.ndarray) -> tuple[float, np.ndarray]:
    u = x.reshape(u_start.shape)
    cost, grad = model.cost_and_gradient(u)
    history.append((cost, hybridoc.evaluate(problem, u).cost))
    return cost, grad.ravel()


result = minimize(
    cost_and_gradient,
    u_start.ravel(),
    jac=True,
    method="L-BFGS-B",
    # at most 10 evaluations per line search (SciPy's default 20): the same end, sooner
    options={"maxfun": EVALUATIONS, "maxiter": EVALUATIONS, "maxls": 10},
)
u_mujoco = result.x.reshape(u_start.shape)
judged = hybridoc.evaluate(problem, u_mujoco)
mujoco_cost = model.cost(u_mujoco)
gap = judged.cost / optimum.cost - 1
print(f"L-BFGS: {result.nfev} evaluations, {result.nit} iterations; {result.message}")
under = 1 - mujoco_cost / judged.cost
print(f"MuJoCo's cost of its control  {mujoco_cost:.6f}")
print(
    f"the judge's cost of it        {judged.cost:.6f} ({100 * gap:+.2f}% vs the optimum)"
)
print(f"MuJoCo under-reports it by    {100 * under:.2f}%")
print("its events:", [(e.name, round(e.time, 4)) for e in judged.events])
print("the optimum's:", [(e["guard"], round(e["time"], 4)) for e in optimum.events])

# %%
# The optimisation makes fast progress and then stops a few percent above the optimum: its
# last line search found no descent (SciPy's message ``ABNORMAL``). The judge's cost of
# each evaluated control follows MuJoCo's, slightly above it: MuJoCo's cost flatters its own
# controls.
evals = np.arange(1, len(history) + 1)
fig_history = Figure(figsize=(6.4, 3.4), layout="constrained")
ax = fig_history.subplots()
for k, (label, style) in enumerate(
    [("MuJoCo's cost", "o-"), ("the judge's cost", "s--")]
):
    above = 100 * (np.array([h[k] for h in history]) / optimum.cost - 1)
    ax.plot(evals, above, style, ms=3, label=label)
ax.set_yscale("symlog", linthresh=1.0)  # MuJoCo's cost may fall below the optimum
ax.axhline(0.0, color="k", lw=0.8)
ax.set_xlabel("cost-and-gradient evaluation of L-BFGS")
ax.set_ylabel("% above the exact optimum")
ax.set_title("single-collision optimised in MuJoCo, judged by hybridoc")
ax.legend()

# %%
# MuJoCo's gradient against the exact one
# ---------------------------------------
# At the initial guess, :func:`hybridoc.gradient` gives the exact gradient of the
# continuous cost (the adjoint with the jump relation at the collision). MuJoCo's gradient
# agrees in ``ux`` and after the collision (grey line), and is several times too large in
# ``uy`` before it: the push that decides when the collision happens.
cost_mj, grad_mj = model.cost_and_gradient(u_start)
exact = hybridoc.gradient(problem, u_start)
g_ex = exact.d_controls
cosine = float(
    np.sum(grad_mj * g_ex) / (np.linalg.norm(grad_mj) * np.linalg.norm(g_ex))
)
rel_err = float(np.linalg.norm(grad_mj - g_ex) / np.linalg.norm(g_ex))
print(f"cosine {cosine:.3f}, relative error {rel_err:.2f}")

t_mid = scene.time_grid()[:-1] + scene.dt / 2
t_event = exact.evaluation.events[0].time
fig_gradient = Figure(figsize=(7.2, 3.4), layout="constrained")
axes = fig_gradient.subplots(1, 2, sharex=True)
for k, ax in enumerate(axes):
    ax.plot(t_mid, g_ex[:, k] / scene.dt, lw=2, label="exact (hybridoc.gradient)")
    ax.plot(
        t_mid, grad_mj[:, k] / scene.dt, "--", lw=1.5, label="MuJoCo (mjd_transitionFD)"
    )
    ax.axvline(t_event, color="0.6", lw=0.8)
    ax.set_xlabel("t")
    ax.set_title(f"dJ/d{scene.control_labels()[k]} per unit time")
axes[0].legend(fontsize=8)

# %%
# Why: a sawtooth in MuJoCo's cost
# --------------------------------
# Along constant controls :math:`u = (0, c)` near the initial guess's :math:`c = 3`, the
# judge's cost is smooth, while MuJoCo's has a tooth each time the collision moves by one
# MuJoCo step: the contact can only begin on a step. The average slope is right; the
# local slope, which is what finite-difference Jacobians see, is not. MuJoCo's gradient
# along this line is the slope of the tooth.
half = 0.005 if QUICK else 0.01
cs = np.linspace(3.0 - half, 3.0 + half, SCAN)
constant = [np.tile([0.0, c], (scene.steps, 1)) for c in cs]
scan_mj = np.array([model.cost(u) for u in constant])
scan_ex = np.array([hybridoc.evaluate(problem, u).cost for u in constant])
local = np.diff(scan_mj) / np.diff(cs)
mean_mj = (scan_mj[-1] - scan_mj[0]) / (cs[-1] - cs[0])
mean_ex = (scan_ex[-1] - scan_ex[0]) / (cs[-1] - cs[0])
slope_mj, slope_ex = grad_mj[:, 1].sum(), g_ex[:, 1].sum()
print(f"MuJoCo's slope between neighbours: {local.min():.2f} to {local.max():.2f}")
print(f"average slope: MuJoCo {mean_mj:.3f}, exact {mean_ex:.3f}")
print(f"gradient along the line at c = 3: MuJoCo {slope_mj:.3f}, exact {slope_ex:.3f}")

fig_scan = Figure(figsize=(6.4, 3.4), layout="constrained")
ax = fig_scan.subplots()
ax.plot(cs, scan_mj, ".-", label="MuJoCo's cost")
ax.plot(cs, scan_ex, "-", label="the judge's cost")
tangent = cost_mj + slope_mj * (cs - 3.0)
ax.plot(cs, tangent, ":", color="C0", label="MuJoCo's gradient at c = 3")
ax.set_xlabel("c in the constant control u = (0, c)")
ax.set_ylabel("cost")
ax.legend()

# %%
# The mismatch, in numbers
# ------------------------
summary = [
    ("energy ratio of a head-on bounce, MuJoCo's default contact", energy["default"]),
    ("energy ratio of a head-on bounce, exported contact", energy["exported"]),
    ("MuJoCo's cost of the optimum's grid values / J*", in_mujoco.cost / optimum.cost),
    ("the same with MuJoCo's default contact", default_cost / optimum.cost),
    (
        "judged cost of MuJoCo's L-BFGS control / J*",
        judged.cost / optimum.cost,
    ),
    ("MuJoCo's cost of that control / its judged cost", mujoco_cost / judged.cost),
    ("cosine of MuJoCo's and the exact gradient at the guess", cosine),
    ("relative error of MuJoCo's gradient at the guess", rel_err),
]
width = max(len(k) for k, _ in summary)
print("\n".join(f"{k.ljust(width)}  {v:.4f}" for k, v in summary))

# %%
# The command line does the same with files. ``hybridoc evaluate single-collision
# --controls ctrl.npy --substeps 10`` judges a control logged from MuJoCo at its own steps
# (``N K`` rows, one per ``d.ctrl``) exactly on the finer grid, and ``hybridoc gradcheck
# single-collision --against grad.npy`` reports the cosine and the errors of any
# simulator's gradient against the exact one, before and after each event. Whatever
# simulator produced a control, the judge says what it is worth; here it says that
# MuJoCo's optimiser stopped a few percent above the optimum, that MuJoCo's own cost hides
# part of that gap, and that the reason is in MuJoCo's gradient, not in the optimiser.
