r"""
5. Your own scene
=================

Time to leave the paper's problems. In this tutorial we write a disc scene of our own in
TOML, check it, solve it, read its events, and meet the errors hybridoc raises when a scene
or a control is wrong. The scene format is described in full in :doc:`/scenes`.
"""

# %%
# Writing the scene
# -----------------
# A bank shot: a cue disc (actuated: a force acts on it) must send a lighter puck to a
# target, and there is a cushion (a wall) at :math:`y = 0.8`, its normal pointing into
# free space. The puck bounces with restitution 0.9. Everything not given takes its
# default (``control_weight`` 0.01, masses 1, discs at rest).
import os
import tempfile
from pathlib import Path
from textwrap import fill

import numpy as np

import hybridoc
from hybridoc.plotting import plot_scene

SCENE = """
name = "bank-shot"
horizon = 1.5
steps = 300
restitution = 0.9

[[discs]]
name = "cue"
position = [0.0, -1.0]
radius = 0.15
actuated = true
initial_control = [0.0, 2.0]

[[discs]]
name = "puck"
position = [0.0, 0.0]
radius = 0.1
mass = 0.5
target = [0.6, 0.3]

[[walls]]
name = "cushion"
point = [0.0, 0.8]
normal = [0.0, -1.0]
"""
# ``HYBRIDOC_TUTORIAL_QUICK=1`` (set by the test suite) runs a smaller version: a coarser
# grid, and fewer starts in the reference's multi-start
QUICK = os.environ.get("HYBRIDOC_TUTORIAL_QUICK") == "1"
if QUICK:
    SCENE = SCENE.replace("steps = 300", "steps = 100")
folder = Path(tempfile.mkdtemp())
path = folder / "bank-shot.toml"
path.write_text(SCENE)

# %%
# Checking it
# -----------
# Loading validates the scene (types, names, overlaps, ...; below). The compiled problem
# has one guard per pair of bodies that can touch, named after them:
scene = hybridoc.load_scene(path)
ocp = scene.to_ocp()
print(
    f"{scene.name}: {scene.n_discs} discs, {len(scene.walls)} wall, T = {scene.horizon}"
)
print("guards:", [g.name for g in ocp.guards])
print("controls:", ocp.control_labels)

# %%
# The judge shows what the initial guess does. Every event has a time, a kind, the bodies
# involved and the guard's name, the name to use in event sequences:
guess = hybridoc.evaluate(scene)
print(f"initial guess: cost {guess.cost:.6f}")
for e in guess.event_dicts():
    print(f"  t = {e['time']:.6f}  {e['kind']:9s}  {' and '.join(e['bodies'])}")
fig_guess = plot_scene(scene, guess, title="bank-shot: the initial guess")
fig_guess.set_size_inches(7.0, 5.0)

# %%
# A straight push: the puck rattles between the cue and the cushion and ends far from the
# target. On the command line, ``hybridoc show bank-shot.toml`` and ``hybridoc evaluate
# bank-shot.toml`` print the same.
#
# Solving it
# ----------
# The reference and the transcription, as in tutorial 1:
ref = hybridoc.solve(path, "reference", **({"multistart": 1} if QUICK else {}))
dt = hybridoc.solve(path, "dt")
for sol in (ref, dt):
    print(f"{sol.method:9s} {sol.status}  cost {sol.cost:.6f}  events {sol.sequence}")
fig_ref = plot_scene(
    scene, hybridoc.evaluate(scene, ref), title=f"the optimum: {ref.cost:.4f}"
)
fig_ref.set_size_inches(7.0, 5.0)

# %%
# The optimum is a clean bank shot: one strike, one bounce off the cushion. The
# transcription, started from the rattling guess, stays in the basin of the guess's
# events and returns a local optimum with more events and a higher cost: it is a local
# method. The reference looks at other sequences (the guess's with an event dropped, every
# single event, the transcription's, a multi-start) and keeps the cheapest verified one;
# :func:`hybridoc.crossval` would flag the disagreement. Started from the reference's
# control, the transcription agrees:
dt_again = hybridoc.solve(path, "dt", initial=ref)
print(
    f"dt from the reference: cost {dt_again.cost:.9f} vs {ref.cost:.9f}, {dt_again.sequence}"
)

# %%
# The errors you will meet
# ------------------------
# Every mistake in a scene is a :class:`~hybridoc.errors.SceneError` whose one-line
# message names the file, the body and the key. A typo:
bad = folder / "bad.toml"
bad.write_text(SCENE.replace("mass = 0.5", "mas = 0.5"))
try:
    hybridoc.load_scene(bad)
except hybridoc.SceneError as exc:
    print(fill(str(exc), 88))  # wrapped to fit the page

# %%
# Discs that overlap at :math:`t = 0` (touching is allowed):
bad.write_text(SCENE.replace("position = [0.0, 0.0]", "position = [0.0, -0.9]"))
try:
    hybridoc.load_scene(bad)
except hybridoc.SceneError as exc:
    print(fill(str(exc), 88))  # wrapped to fit the page

# %%
# A value out of range:
bad.write_text(SCENE.replace("restitution = 0.9", "restitution = 1.5"))
try:
    hybridoc.load_scene(bad)
except hybridoc.SceneError as exc:
    print(fill(str(exc), 88))  # wrapped to fit the page

# %%
# Controls are checked as well: a :class:`~hybridoc.errors.ControlsError` for a NaN
# (a diverged optimiser, typically) or a wrong shape. Both errors derive from
# :class:`~hybridoc.errors.HybridocError`, so one ``except`` catches every error hybridoc
# raises on purpose.
controls = scene.initial_controls()
controls[10, 0] = np.nan
for attempt in (controls, controls[:10]):
    try:
        hybridoc.evaluate(scene, attempt)
    except hybridoc.HybridocError as exc:
        print(fill(f"{type(exc).__name__}: {exc}", 88))

# %%
# From here, :doc:`/scenes` describes every key and the built-in scenes, and
# ``path/to/file.py:function`` makes any :class:`~hybridoc.ocp.HybridOCP` written in
# Python a problem for every command.
