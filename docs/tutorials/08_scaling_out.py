r"""
8. Scaling out
==============

A feedback policy :math:`u = \pi(t, s)` is meant for many situations, not one. To trust
it we judge it on many initial states and compare each rollout with the exact optimum of
the same initial state. That takes many reference solves, and hybridoc spreads them over
a local process pool or a Dask cluster with identical results. In this tutorial we

1. give ``single-collision`` a distribution of initial states,
2. compute the exact optimum of every draw, once on a process pool and once on a Dask
   cluster, and check that the two files are the same byte for byte,
3. write a small feedback policy by hand and validate it against those optima.

The file formats and the command line are described in :doc:`/datasets`.
"""

# %%
# A distribution of initial states
# --------------------------------
# A :class:`~hybridoc.problems.distribution.Distribution` says what varies in a scene: here the
# start of ``ball2``, uniformly within :math:`\pm 0.2` of its nominal position in each
# coordinate. In a TOML scene it is the ``[distribution]`` table that
# ``toml_lines`` prints.
import dataclasses
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from distributed import Client, LocalCluster

import hybridoc
from hybridoc.problems import load_scene
from hybridoc.problems.distribution import DiscSpread, Distribution, Spread
from hybridoc.workflows.datasets import make_dataset
from hybridoc.workflows.policies import validate_policy
from hybridoc.workflows.policy_report import policy_figures

# the test suite runs a smaller version (``HYBRIDOC_TUTORIAL_QUICK=1``): a grid of 120
# steps instead of 480, 26 draws, still two chunks (of 25 and 1), and the nominal
# optimum of the policy below found without the reference's multi-start
QUICK = os.environ.get("HYBRIDOC_TUTORIAL_QUICK") == "1"
M = 26 if QUICK else 50  # draws

nominal = load_scene("single-collision")
if QUICK:
    nominal = nominal.with_steps(120)
spread = DiscSpread("ball2", position=Spread("uniform", (0.2, 0.2)))
scene = dataclasses.replace(nominal, distribution=Distribution(discs=(spread,), seed=0))
print("\n".join(scene.distribution.toml_lines()))

# %%
# Draw :math:`i` has its own random stream, seeded by ``(seed, i)``, so it is the same
# whatever the number of draws, their order or the machine that makes it:
x0 = scene.sample_initial_states(M)
print("initial states:", x0.shape)
print("state:", ", ".join(scene.to_ocp().state_labels))
print("ball2 starts in x", x0[:, 2].min().round(3), "to", x0[:, 2].max().round(3))
print("ball2 starts in y", x0[:, 3].min().round(3), "to", x0[:, 3].max().round(3))
print(
    "the first 5 draws, made alone, are the same:",
    (scene.sample_initial_states(5) == x0[:5]).all(),
)

# %%
# Exact optima on a process pool
# ------------------------------
# :func:`~hybridoc.workflows.datasets.make_dataset` solves the nominal scene once with the
# reference's full search, then every draw by Newton on the conditions of optimality,
# started from the nominal optimum, and accepts a draw only when the judge confirms it
# (:doc:`/datasets`). The draws go in chunks of 25, one task each, to a pool of worker
# processes; ``hybridoc dataset scene.toml --samples 50 --workers 2`` does the same on
# the command line. Everything is written into a temporary folder.
tmp = tempfile.TemporaryDirectory(prefix="hybridoc-tutorial-")
out = Path(tmp.name)
start = time.perf_counter()
pool_ds = make_dataset(scene, M, out / "pool", workers=2, progress=False)
print(f"{len(pool_ds)} draws in {time.perf_counter() - start:.1f} s on a pool of 2")
print(
    "status:", pool_ds.manifest["counts"], "| solved by:", pool_ds.manifest["methods"]
)
print("optimal event sequences:", sorted(set(pool_ds["sequence"].tolist())))
cost = pool_ds["cost"]
print(
    f"optimal cost from {cost.min():.4f} to {cost.max():.4f}, median {np.median(cost):.4f}"
)
print("files:", sorted(p.name for p in (out / "pool").iterdir()))

# %%
# Every row holds the optimum of one draw: its cost, events, event times, the optimal
# control on the grid (``controls``, shape ``(M, N, nu)``) and in exact form, and the
# states and costates at the events: the supervision a learned policy needs (tutorial 7).
print({k: pool_ds[k].shape for k in ("controls", "event_times", "phase_states")})

# %%
# The same on a Dask cluster
# --------------------------
# ``dask=`` sends the chunks to a ``dask.distributed`` cluster instead: an address such as
# ``"tcp://10.0.0.5:8786"``, ``"local"``, or a :class:`distributed.Client` we opened
# ourselves. Here a :class:`distributed.LocalCluster` of two workers stands in for a real
# cluster. Its workers are threads of this process (``processes=False``): worker
# *processes* would be started afresh and re-import the script that started them, which
# for this page is the documentation build. A script of your own can use processes, and
# ``hybridoc dataset ... --dask local`` does.
cluster = LocalCluster(
    n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
)
client = Client(cluster)
print("workers:", len(client.scheduler_info()["workers"]))
start = time.perf_counter()
dask_ds = make_dataset(scene, M, out / "dask", dask=client, progress=False)
print(f"{len(dask_ds)} draws in {time.perf_counter() - start:.1f} s on Dask")

pool_bytes = (out / "pool" / "dataset.npz").read_bytes()
dask_bytes = (out / "dask" / "dataset.npz").read_bytes()
print("identical files:", pool_bytes == dask_bytes, f"({len(pool_bytes)} bytes)")
print("sha256 pool:", pool_ds.manifest["sha256"])
print("sha256 dask:", dask_ds.manifest["sha256"])
print("engines:", [ds.manifest["last_run"]["engine"] for ds in (pool_ds, dask_ds)])

# %%
# The engines differ and the data do not: every draw has its own random stream and every
# Newton solve starts from the same nominal point, so a draw's answer does not depend on
# which worker solved it or when.
#
# A feedback policy
# -----------------
# A policy is any callable ``u = policy(t, state)``; the judge samples it at the grid
# times and holds its value over each step, as a digital controller does. Ours is written
# by hand from the nominal optimum :math:`u^\circ(t)`, :math:`s^\circ(t)`:
#
# ``open_loop``
#    plays :math:`u^\circ(t)` and ignores the state: the baseline;
# ``follow``
#    while ``ball2`` is still at rest, steers ``ball1`` (proportional-derivative) along
#    the nominal path shifted by ``ball2``'s offset :math:`d` from its nominal start, so
#    that the strike is the nominal strike moved by :math:`d`; after the strike it plays
#    :math:`u^\circ(t)` (which is zero there).
#
# Dask workers load a policy from its file, so we write it into a file
# (``path/to/policy.py:name`` is also what ``hybridoc validate-policy`` takes) with the
# nominal trajectory next to it:
reference = hybridoc.solve(nominal, "reference", **({"multistart": 0} if QUICK else {}))
path = hybridoc.evaluate(nominal, reference.controls)
np.savez(
    out / "nominal.npz",
    u=reference.controls,
    s=path.sample(nominal.time_grid()[:-1]),
    dt=nominal.dt,
)
POLICY = """
from pathlib import Path

import numpy as np

NOMINAL = np.load(Path(__file__).with_name("nominal.npz"))
U, S, DT = NOMINAL["u"], NOMINAL["s"], float(NOMINAL["dt"])
KP, KD = 60.0, 12.0  # gains of the tracking


def open_loop(t, s):
    return U[min(int(t / DT + 1e-9), len(U) - 1)]


def follow(t, s):
    k = min(int(t / DT + 1e-9), len(U) - 1)
    if s[6] != 0 or s[7] != 0:  # ball2 moves: after the strike
        return U[k]
    d = s[2:4] - S[0, 2:4]  # ball2's offset from its nominal start
    return U[k] + KP * (S[k, 0:2] + d - s[0:2]) + KD * (S[k, 4:6] - s[4:6])
"""
(out / "policy.py").write_text(POLICY)

# %%
# Validating it
# -------------
# :func:`~hybridoc.workflows.policies.validate_policy` rolls the policy out in closed loop on the
# first :math:`M` draws (on the same engines) and compares each rollout's true cost
# :math:`J_\pi` with the optimum :math:`J^*` of the same draw from our dataset:
reports = {}
for name in ("open_loop", "follow"):
    spec = f"{out / 'policy.py'}:{name}"
    reports[name] = validate_policy(
        scene, spec, M, dataset=pool_ds, workers=2, progress=False
    )
for name, rep in reports.items():
    sm = rep.summary
    print(
        f"{name:9s}  relative gap (J - J*)/J*: mean {sm['rel_gap_mean']:7.2%}"
        f"  median {sm['rel_gap_median']:7.2%}  p95 {sm['rel_gap_p95']:7.2%}"
        f"  max {sm['rel_gap_max']:7.2%}"
    )
    print(
        f"{'':9s}  absolute gap: mean {sm['gap_mean']:.4f}, max {sm['gap_max']:.4f};"
        f" events differ in {sm['sequence_mismatch_rate']:.0%}"
        f" of {sm['compared']} draws"
    )

# %%
# Played open loop, the nominal push strikes a displaced ``ball2`` at the wrong angle, or
# misses it: the rollouts whose events differ from the optimum's are those without a
# collision.
open_seq = reports["open_loop"].columns["policy_sequence"]
print("open-loop rollouts without a collision:", int(np.sum(open_seq == "")), "of", M)

# %%
# Following ``ball2`` keeps every strike. What remains is the aim: the strike moved by
# :math:`d` sends ``ball2`` along the nominal path moved by :math:`d`, so it ends about
# :math:`d` off, where the optimum re-aims. The worst draws of ``follow`` start far from
# the nominal (the largest possible :math:`|d|` is :math:`0.2\sqrt 2`):
for w in reports["follow"].worst[:3]:
    d = np.array(w["x0"][2:4]) - nominal.initial_state()[2:4]
    print(
        f"draw {w['index']:2d}: d = ({d[0]:+.3f}, {d[1]:+.3f}), |d| = {np.hypot(*d):.3f};"
        f"  J = {w['policy_cost']:.4f}, J* = {w['reference_cost']:.4f}"
    )
print(f"largest possible |d| = {0.2 * np.sqrt(2):.3f}")

# %%
# The same validation on the Dask cluster gives the same numbers:
on_dask = validate_policy(
    scene,
    f"{out / 'policy.py'}:follow",
    M,
    dataset=dask_ds,
    dask=client,
    progress=False,
)
same = all(
    np.array_equal(on_dask.columns[k], reports["follow"].columns[k])
    for k in ("policy_cost", "gap", "policy_sequence", "mismatch")
)
print("same rollouts on Dask and on the pool:", same)

# %%
# The figures
# -----------
# :func:`~hybridoc.workflows.policy_report.policy_figures` draws what
# ``hybridoc validate-policy --out`` saves (through
# :func:`~hybridoc.workflows.policy_report.report_figures`): the histogram of the relative
# gap and the gap over the two initial-state coordinates that vary (red crosses: a rollout
# whose events differ from the optimum's).
labels = list(scene.to_ocp().state_labels)
figures = {
    name: policy_figures(rep, labels, f"single-collision, {name}")
    for name, rep in reports.items()
}
fig_open_scatter = figures["open_loop"]["gap_scatter"]
# sphinx_gallery_thumbnail_number = 3

# %%
# Open loop, the gap grows quickly as ``ball2`` moves to the right of its nominal start,
# and the crosses (every one a rollout without a collision) lie there. Following
# ``ball2``, the histogram of the gap:
fig_follow_hist = figures["follow"]["gap_hist"]

# %%
# and its map: small near the nominal start, largest where ``ball2`` starts to the right.
fig_follow_scatter = figures["follow"]["gap_scatter"]

# %%
# Closing
# -------
# A cluster holds threads (or processes) until it is closed:
client.close()
cluster.close()
tmp.cleanup()

# %%
# Next steps: :doc:`/datasets` lists every column of a dataset and every option of
# ``hybridoc dataset`` and ``hybridoc validate-policy``; on a real cluster, start a
# scheduler and workers (``dask scheduler``, ``dask worker ADDRESS``) on machines that
# have hybridoc installed and pass ``--dask ADDRESS``.
