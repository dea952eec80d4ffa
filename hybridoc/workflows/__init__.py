"""Applications built on the core: what hybridoc does with its solvers, not how they solve.

The core (the problem model, the judge, the solvers and the reference) knows nothing of
this package; these modules import the core and the CLI imports them.

- :mod:`hybridoc.workflows.datasets`: reference datasets, the exact optima of many draws of
  a scene's ``[distribution]`` (``hybridoc dataset``).
- :mod:`hybridoc.workflows.policies`: feedback policies from files, and their validation
  against a dataset (``hybridoc validate-policy``).
- :mod:`hybridoc.workflows.policy_format`: MLP policy files that run no code
  (``policy.json`` and its weights), and CasADi policies.
- :mod:`hybridoc.workflows.rollouts`: closed-loop rollouts with the policy compiled into the
  step, each certified by the judge.
- :mod:`hybridoc.workflows.validation`: methods measured against the reference
  (``hybridoc crossval``, ``validate`` and ``convergence``).
- :mod:`hybridoc.workflows.training`: feedback policies trained through the differentiable
  simulator, and the judge's exact closed-loop gradient.
- :mod:`hybridoc.workflows.ablation`: the paper's Table 1 (``hybridoc ablation``).
- :mod:`hybridoc.workflows.gradcompare`: any simulator's gradient against the exact adjoint
  (``hybridoc gradcheck --against``).
- :mod:`hybridoc.workflows.trajectories`: any simulator's trajectory and events against the
  judge's (``hybridoc compare-trajectory``).
- :mod:`hybridoc.workflows.mujoco`: disc scenes exported to MuJoCo (``hybridoc export
  mjcf``), with rollouts, MuJoCo's costs and MuJoCo's gradients to judge (needs the
  ``mujoco`` extra).

Each long run takes one ``progress`` argument (:mod:`hybridoc.progress`). Importing this
package imports none of its modules.
"""
