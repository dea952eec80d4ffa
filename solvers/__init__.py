"""Solvers: the differentiable simulator with gradient descent, and the direct transcription.

Modules (imported on demand, so that ``import hybridoc`` does not load torch):

- :mod:`hybridoc.solvers.simulator`: :class:`~hybridoc.solvers.simulator.Simulator`, the
  batched differentiable torch simulator with the paper's contact models.
- :mod:`hybridoc.solvers.casadi_step`: the same discrete step as a CasADi function.
- :mod:`hybridoc.solvers.compiled`: the compiled rollout, loss and gradient.
- :mod:`hybridoc.solvers.gd`: :func:`~hybridoc.solvers.gd.solve_gd`.
- :mod:`hybridoc.solvers.impulses`, :mod:`hybridoc.solvers.penalty`: contact models.
"""
