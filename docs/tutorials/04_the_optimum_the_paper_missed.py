r"""
4. The optimum the paper missed
===============================

The hybrid minimum principle of tutorial 2 holds for one *sequence* of events. Choose the
wrong sequence and Newton's method will happily converge to an extremal of it, a
stationary point that is not the optimum. This tutorial shows that this is not an academic
worry: on the paper's second problem, ``multiple-collision``, the optimum has a different
sequence from the one the paper describes, and it is cheaper.

The task is that of tutorial 1 with a wall at :math:`y = 1`: push ``ball1`` so that
``ball2`` ends at the origin at :math:`T = 1`.
"""

# %%
# ``HYBRIDOC_TUTORIAL_QUICK=1`` (set by the test suite) runs a smaller version: shorter
# sequences searched, fewer starts in the reference's multi-start, fewer starts and
# iterations of gradient descent; the documentation runs the full version.
import os

from matplotlib.figure import Figure

import hybridoc
from hybridoc.plotting import plot_scene

QUICK = os.environ.get("HYBRIDOC_TUTORIAL_QUICK") == "1"
problem = "multiple-collision"

# %%
# Two extremals
# -------------
# The paper describes the optimum as one disc-disc collision followed by a wall bounce of
# ``ball2``. Give the reference that sequence and it solves the conditions of optimality
# for it:
two = hybridoc.solve(problem, "reference", sequence=["ball1|ball2", "ball2|wall"])
print(f"two events:   cost {two.cost:.12f}  {two.sequence}")

# %%
# Without a sequence, the reference collects candidates (the initial guess's events and
# variations of them, the transcription's, a batched multi-start) and keeps the cheapest
# extremal that the judge confirms by re-simulating its control:
# (``HYBRIDOC_TUTORIAL_QUICK=1``, set by the test suite, asks for the short search of the
# next section here instead, and reuses it there: one search instead of two.)
best = hybridoc.solve(
    problem, "reference", **({"search": 2, "multistart": 1} if QUICK else {})
)
print(f"the optimum:  cost {best.cost:.12f}  {best.sequence}  ({best.status})")
print(f"{(two.cost - best.cost) / two.cost:.1%} below the two-event extremal")
for e in best.events:
    print(f"  t = {e['time']:.6f}  {e['guard']}  ({e['kind']})")

fig = Figure(figsize=(11.0, 4.2), layout="constrained")
ax_best, ax_two = fig.subplots(1, 2)
plot_scene(
    problem,
    hybridoc.evaluate(problem, best),
    ax=ax_best,
    title=f"three events: cost {best.cost:.6f}",
)
plot_scene(
    problem,
    hybridoc.evaluate(problem, two),
    ax=ax_two,
    title=f"the paper's two events: cost {two.cost:.6f}",
)
ax_two.get_legend().remove()  # the same keys as on the left: more room for the drawing

# %%
# Left: ``ball1`` strikes ``ball2`` up towards the wall (1), ``ball2`` bounces back (2),
# and ``ball1``, still moving, meets it a second time (3) and deflects it onto the target.
# The second strike lets the first one be gentler. The paper's grid search only looked
# within the two-event family, where it found 0.3737; the exact extremal of that family is
# just below, and the three-event optimum is lower still.
#
# How to search for sequences
# ---------------------------
# ``search=K`` also solves every feasible sequence of up to :math:`K` events (pruned by the
# geometry: a disc at rest cannot move before it is struck, a disc coasting in a straight
# line cannot meet the same wall twice in a row) and reports the *landscape of
# extremals*: every sequence with its verified cost, or why no extremal of it exists.
# On the command line: ``hybridoc reference multiple-collision --search 5``.
depth = 2 if QUICK else 5
searched = best if QUICK else hybridoc.solve(problem, "reference", search=depth)
landscape = searched.info["landscape"]
verified = [row for row in landscape if row["cost"] is not None]
print(
    f"search up to {depth} events: {len(landscape)} sequences, {len(verified)} extremals"
)
for row in sorted(verified, key=lambda r: r["cost"]):
    print(f"  {row['cost']:.12f}  {', '.join(row['sequence']) or '(no event)'}")
failed = [row for row in landscape if row["cost"] is None]
print(f"  and {len(failed)} sequences without an extremal, e.g.")
for row in failed[:3]:
    print(f"    {', '.join(row['sequence'])}: {row['verdict'].split(';')[0]}")

# %%
# Nothing among the sequences searched beats the three-event optimum. Most sequences
# have no extremal at all: Newton finds no point that satisfies the conditions with those
# events, or the events it finds come in the wrong order.
#
# What gradient descent finds
# ---------------------------
# Gradient descent from the paper's initial guess follows the slope it is given; with
# exact gradients (tutorial 3) it still ends in the basin it starts in. A batched
# multi-start, many perturbed starts descending together, is what finds the better basin;
# it is what ``hybridoc crossval`` runs.
quick = {"iters": 50} if QUICK else {}  # the test suite: fewer iterations
single = hybridoc.solve(problem, "gd", **quick)
multi = hybridoc.solve(problem, "gd", starts=4 if QUICK else 32, **quick)
for label, sol in (
    ("one start", single),
    (f"{multi.settings.get('starts', '')} starts", multi),
):
    gap = (sol.cost - best.cost) / best.cost
    print(
        f"gd, {label:10s}: cost {sol.cost:.6f} ({gap:+.2%} from the optimum), "
        f"{len(sol.events)} events"
    )

fig_costs = Figure(figsize=(8.0, 3.4), layout="constrained")
ax = fig_costs.subplots()
labels = [", ".join(r["sequence"]) or "(no event)" for r in verified]
ax.barh(labels, [r["cost"] for r in verified], color="C0")
for label, sol, color in (
    ("gd, one start", single, "C1"),
    ("gd, multi-start", multi, "C2"),
):
    ax.axvline(sol.cost, color=color, ls="--", lw=1.2, label=f"{label}: {sol.cost:.4f}")
ax.set(
    xlabel="cost of the extremal", xlim=(0.3, max(r["cost"] for r in verified) * 1.05)
)
fig_costs.suptitle("multiple-collision: the extremals by event sequence")
ax.legend(fontsize=8, loc="lower right")
ax.grid(axis="x", alpha=0.3)

# %%
# The lesson: an extremal is a candidate, not an answer. The reference answers only after
# checking that no control it has met is cheaper, and ``hybridoc.solve(..., search=K)``
# widens the net. ``tests/test_reference.py`` checks the three-event cost against an
# independent closed form of that family (:doc:`/reference`).
#
# Next: tutorial 5 builds a scene of your own.
