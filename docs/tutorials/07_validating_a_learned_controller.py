r"""
7. Validating a learned controller
==================================

The tutorials so far solved one initial state at a time. A feedback policy
:math:`u = \pi(t, s)` is trained once and then used from many initial states, so it has to be
judged on many: for each one we can compute the exact optimum :math:`J^*` and ask how far
the policy's true closed-loop cost :math:`J_\pi` is above it. In this tutorial we

1. give ``single-collision`` a distribution of initial states and write a small neural
   network policy,
2. train it through the differentiable simulator twice, with and without the
   time-of-impact corrections of tutorial 3,
3. look at the simulator's gradients next to the exact closed-loop gradient, to see why
   one of the two trainings fails,
4. validate both policies against the exact optima of fresh draws.
"""

# %%
# The settings of this page
# -------------------------
# Training runs hundreds of closed-loop simulations, so this page runs a small version of
# the experiment: a coarser grid than the paper's, few training draws and a few hundred
# iterations. ``HYBRIDOC_TUTORIAL_QUICK=1`` (set by the test suite) makes it smaller still.
# The full experiment, on the paper's grid with more draws and iterations, is
# ``benchmarks/policy_gap.py`` in the repository; it takes minutes rather than seconds.
import copy
import dataclasses
import os
import tempfile
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure

import hybridoc
from hybridoc.problems import load_scene
from hybridoc.problems.distribution import DiscSpread, Distribution, Spread
from hybridoc.solvers.simulator import Simulator
from hybridoc.workflows.datasets import make_dataset
from hybridoc.workflows.policies import validate_policy
from hybridoc.workflows.policy_report import policy_figures
from hybridoc.workflows.training import mlp_policy, train_policy

QUICK = os.environ.get("HYBRIDOC_TUTORIAL_QUICK") == "1"
STEPS = 60  # control intervals, fewer than the paper's
N_TRAIN = 8 if QUICK else 16  # training draws
N_VAL = 4 if QUICK else 25  # validation draws
ITERS = 20 if QUICK else 200  # Adam iterations
# iterations at which we look at the gradients
SNAPSHOTS = (0, 12) if QUICK else (0, 3, 6, 12)

# %%
# A distribution and a policy
# ---------------------------
# As in tutorial 8, a :class:`~hybridoc.problems.distribution.Distribution` moves the start of
# ``ball2``, here uniformly by up to :math:`\pm 0.3` in each coordinate.
# :meth:`~hybridoc.problems.scene.Scene.with_steps` puts the scene on the coarser grid.
# Training and validation use different draws: the training states come from seed 1, the
# validation below uses the distribution's own seed 0.
nominal = load_scene("single-collision")
spread = DiscSpread("ball2", position=Spread("uniform", (0.3, 0.3)))
scene = dataclasses.replace(
    nominal.with_steps(STEPS), distribution=Distribution(discs=(spread,), seed=0)
)
print("\n".join(scene.distribution.toml_lines()))
x_train = scene.sample_initial_states(N_TRAIN, seed=1)
print(f"grid of {scene.steps} steps (the paper's: {nominal.steps}); dt {scene.dt:.4f}")
print(f"{N_TRAIN} training states")

# %%
# :func:`~hybridoc.workflows.training.policy.mlp_policy` builds a small ``tanh`` network
# :math:`(t, s) \mapsto u` with its inputs scaled to the scene. Its output is the scene's
# initial control plus the network, whose last layer starts small, so the untrained policy
# acts almost like the initial guess. It is a float64 ``torch.nn.Module`` that takes one
# state or a batch.
untrained = mlp_policy(scene, hidden=32, layers=2, seed=0)
n_params = sum(p.numel() for p in untrained.parameters())
x0 = torch.as_tensor(scene.initial_state())
with torch.no_grad():
    u_start = untrained(torch.tensor(0.0), x0).numpy()
print(f"2 hidden layers of 32, {n_params} parameters")
print("untrained pi(0, s0):", u_start.round(4))
print("initial guess u(0): ", scene.initial_controls()[0])

# %%
# Training through the simulator
# ------------------------------
# :func:`~hybridoc.workflows.training.train_policy` rolls the policy out in closed
# loop in the differentiable simulator from all training states at once
# (:meth:`~hybridoc.solvers.simulator.Simulator.rollout_policy`: symplectic Euler,
# impulses, the control held over each step) and minimises the mean cost
# (:meth:`~hybridoc.solvers.simulator.Simulator.policy_loss`) with Adam, keeping the best
# iterate. We train two copies of the same untrained network: one in the simulator with
# both time-of-impact corrections (``toi="both"``), one without (``toi="none"``). The
# callback keeps a copy of the weights at a few early iterations for the next section.
policies = {"untrained": untrained}
histories, snapshots = {}, {}
print(f"{'policy':9s} {'first loss':>10s} {'best loss':>10s} {'at iter.':>8s} time")
for toi in ("both", "none"):
    policy = copy.deepcopy(untrained)
    kept = {0: copy.deepcopy(policy.state_dict())}

    def keep(it: int, loss: float, policy=policy, kept=kept) -> None:
        """After iteration ``it``: keep the weights of the next one."""
        if it + 1 in SNAPSHOTS:
            kept[it + 1] = copy.deepcopy(policy.state_dict())

    result = train_policy(
        scene, policy, x_train, toi=toi, iters=ITERS, lr=1e-2, seed=0, callback=keep
    )
    name = f"toi={toi}"
    policies[name], histories[name], snapshots[name] = policy, result.losses, kept
    print(
        f"{name:9s} {result.losses[0]:10.4f} {result.final_loss:10.4f}"
        f" {int(np.argmin(result.losses)):8d} {result.seconds:6.1f}s"
    )

# sphinx_gallery_thumbnail_number = 1
fig_training = Figure(figsize=(6.4, 3.6), layout="constrained")
ax = fig_training.subplots()
for name, losses in histories.items():
    ax.plot(losses, lw=1.3, label=name)
ax.set(xlabel="Adam iteration", ylabel="simulator loss (mean over the draws)")
ax.set_title(f"training on {N_TRAIN} draws, grid of {STEPS} steps")
ax.grid(alpha=0.3)
ax.legend()

# %%
# With the corrections the loss falls steadily. Without them it rises within a few
# iterations and then stays on a plateau, and keeping the best iterate hands back weights
# from the first few iterations.
#
# What the gradients said
# -----------------------
# :func:`hybridoc.closed_loop_cost` is the judge's event-exact closed-loop cost of a policy
# (zero-order hold, the mean over initial states) as a torch scalar. Its ``backward`` is the
# exact gradient with respect to the policy's weights, by the adjoint of the hybrid system
# with its jump (tutorial 2) and the policy's reaction to the state at every grid time. At
# the weights kept above we compare it with the gradient of each simulator's loss: the
# cosine of the angle between them (1: the same direction). We also count the training
# draws in which ``ball1`` still strikes ``ball2``.


def value_and_grad(policy: torch.nn.Module, loss_fn) -> tuple[float, torch.Tensor]:
    """``loss_fn()`` and its gradient with respect to the weights, as one vector."""
    policy.zero_grad()
    loss = loss_fn()
    loss.backward()
    grad = torch.cat([p.grad.reshape(-1) for p in policy.parameters()])
    return float(loss.detach()), grad


def cosine(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(a @ b / (a.norm() * b.norm()))


sims = {toi: Simulator(scene, toi=toi) for toi in ("both", "none")}
probe = copy.deepcopy(untrained)
print(f"{'trained':9s} {'iter.':>5s} {'exact J':>8s}   cos(exact, simulator)  strikes")
print(f"{'':9s} {'':5s} {'':8s}   {'toi=both':>10s} {'toi=none':>10s}")
for name, kept in snapshots.items():
    for it, state in kept.items():
        probe.load_state_dict(state)
        j_exact, exact = value_and_grad(
            probe, lambda: hybridoc.closed_loop_cost(scene, probe, x_train)
        )
        cos = {}
        for toi, sim in sims.items():
            _, grad = value_and_grad(probe, lambda s=sim: s.policy_loss(probe, x_train))
            cos[toi] = cosine(grad, exact)
        strikes = sum(
            bool(hybridoc.evaluate(scene.with_initial_state(x), policy=probe).events)
            for x in x_train
        )
        print(
            f"{name:9s} {it:5d} {j_exact:8.4f}  "
            f" {cos['both']:10.4f} {cos['none']:10.4f}  {strikes:3d}/{N_TRAIN}"
        )

# %%
# At the untrained weights both simulators' gradients point roughly where the exact one
# points. Along the uncorrected training the uncorrected gradient soon points elsewhere,
# even uphill (a negative cosine): that simulator applies the impulse at the end of the step
# in which the discs overlap, so its slope is that of one tooth of the staircase of
# tutorial 3, and on a coarse grid the teeth are wide. Its steps raise the true cost and
# steer ``ball1`` towards missing ``ball2``; once no draw has a strike left the simulators
# agree again, but a policy that never strikes has nothing left to learn. The corrected
# gradient follows the exact one much more closely. It is not exact either: on this coarse
# grid the simulated path is not the judge's, and where a draw comes close to a grazing
# contact the two gradients can differ; the mean over the draws, whose terms partly cancel,
# shows it. On the paper's finer grid the teeth are narrower and the uncorrected training
# does learn, only less well (``benchmarks/policy_gap.py``).
#
# Validation against the exact optima
# -----------------------------------
# Now the other draws. :func:`~hybridoc.workflows.datasets.make_dataset` computes the exact
# optimum of each of the first draws of the distribution (tutorial 8 and :doc:`/datasets`
# explain how). :func:`~hybridoc.workflows.policies.validate_policy` rolls a policy out in
# the judge on the same draws, with the control held over each step as in training, and
# compares each rollout's cost :math:`J_\pi` with the optimum :math:`J^*` of the same draw.
# The optimum is an open-loop control that knows the draw in advance: a gap of zero is the
# best possible.
tmp = tempfile.TemporaryDirectory(prefix="hybridoc-tutorial-")
out = Path(tmp.name)
references = make_dataset(scene, N_VAL, out / "references", workers=1, progress=False)
print(f"{len(references)} exact optima:", references.manifest["counts"])
optima = references["cost"]
print(f"optimal cost from {optima.min():.4f} to {optima.max():.4f}")
reports = {
    name: validate_policy(
        scene, policy, N_VAL, dataset=references, workers=1, progress=False
    )
    for name, policy in policies.items()
}
print("relative gap (J_pi - J*)/J* over the validation draws")
print(f"{'policy':9s} {'median':>7s} {'mean':>7s} {'max':>7s}")
for name, rep in reports.items():
    sm = rep.summary
    print(
        f"{name:9s} {sm['rel_gap_median']:7.1%} {sm['rel_gap_mean']:7.1%}"
        f" {sm['rel_gap_max']:7.1%}"
        f"  (events differ from J*'s in {sm['sequence_mismatch_rate']:.0%})"
    )

# %%
# The untrained policy plays roughly the initial guess and is far above the optimum
# everywhere. The policy trained with the corrections closes most of that gap on draws it
# never saw. The one trained without them hardly differs from the untrained one: training
# handed back the weights of its first few iterations.
#
# The figures
# -----------
# :func:`~hybridoc.workflows.policy_report.policy_figures` draws what
# ``hybridoc validate-policy --out`` saves (through
# :func:`~hybridoc.workflows.policy_report.report_figures`): the histogram of the relative
# gap and the gap over the initial-state coordinates that vary.
labels = list(scene.to_ocp().state_labels)
figures = {
    name: policy_figures(reports[name], labels, f"single-collision, {name}")
    for name in ("toi=both", "toi=none")
}
fig_hist = figures["toi=both"]["gap_hist"]

# %%
# Over the initial states, the gap of the policy trained with the corrections:
fig_map = figures["toi=both"]["gap_scatter"]

# %%
# and of the one trained without them (mind the colour scale):
fig_map_none = figures["toi=none"]["gap_scatter"]
tmp.cleanup()

# %%
# The draws with the largest absolute gaps :math:`J_\pi - J^*` of the corrected policy, with
# ``ball2``'s offset from its nominal start:
for w in reports["toi=both"].worst[:3]:
    d = np.array(w["x0"][2:4]) - nominal.initial_state()[2:4]
    print(
        f"draw {w['index']:2d}: offset ({d[0]:+.3f}, {d[1]:+.3f});"
        f"  J_pi = {w['policy_cost']:.4f}, J* = {w['reference_cost']:.4f}"
        f"  ({w['rel_gap']:.0%} above)"
    )

# %%
# A small network trained for seconds is still some way from the optimum, and the
# validation says where: the map shows which starts of ``ball2`` it handles worst. More
# draws, iterations and the paper's grid shrink the gap (``benchmarks/policy_gap.py``).
# :func:`hybridoc.closed_loop_cost` can also train a policy directly on the judge's exact
# cost, as any torch loss (``loss.backward()``, then an optimiser step); it is slower per
# step than the simulator, since the judge rolls out one initial state at a time.
#
# Next: tutorial 8 computes the exact optima of many more draws on a process pool and on a
# Dask cluster, and validates a hand-written policy against them.
