"""Solvers: the registry, gradient descent through differentiable simulation, and the
direct transcription.

Modules (imported on demand, so that ``import hybridoc`` does not load torch):

- :mod:`hybridoc.solvers.registry`: :func:`~hybridoc.solvers.registry.solve` and the
  method registry :data:`~hybridoc.solvers.registry.METHODS`.
- :mod:`hybridoc.solvers.simulator`: :class:`~hybridoc.solvers.simulator.Simulator`, the
  batched differentiable torch disc simulator.
- :mod:`hybridoc.solvers.contacts`: the contact models, one module each, and their registry;
  :mod:`hybridoc.solvers.impulses`: the impulse solvers they use.
- :mod:`hybridoc.solvers.casadi_step`, :mod:`hybridoc.solvers.toi_sim`: the disc step and
  the generic time-of-impact step as CasADi functions.
- :mod:`hybridoc.solvers.compiled`, :mod:`hybridoc.solvers.codegen`: the compiled rollout,
  loss and gradient, and its C code generation.
- :mod:`hybridoc.solvers.gd`, :mod:`hybridoc.solvers.multistart`:
  :func:`~hybridoc.solvers.gd.solve_gd` and its batched multi-start.
- :mod:`hybridoc.solvers.transcription`, :mod:`hybridoc.solvers.discrete_transcription`:
  direct transcription of the continuous problem and of the simulator's discrete one.
- :mod:`hybridoc.solvers.validation`, :mod:`hybridoc.solvers.gradcheck`: cross-validation and
  gradient checks.
- :mod:`hybridoc.solvers.candidates`: the candidate sources the reference takes sequences
  from (the transcription, the multi-start); importing this package registers them.
"""

from hybridoc.solvers.candidates import register_builtin_sources

register_builtin_sources()
