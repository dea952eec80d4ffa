"""Solvers: the direct transcription, gradient descent through differentiable simulation,
and what they give the reference.

Modules (imported on demand, so that ``import hybridoc`` does not load torch; the method
registry is :mod:`hybridoc.methods`):

- :mod:`hybridoc.solvers.transcription`, :mod:`hybridoc.solvers.discrete_transcription`:
  direct transcription of the continuous problem and of the simulator's discrete one.
- :mod:`hybridoc.solvers.gd`, :mod:`hybridoc.solvers.multistart`,
  :mod:`hybridoc.solvers.starting`: :func:`~hybridoc.solvers.gd.solve_gd`, its batched
  multi-start and the multi-start's starting controls; ``gd`` is a package
  split by concern (options, loss, descent, kinks, hops, multi-start, terminal constraints,
  the entry points and the Method), whose ``__init__`` re-exports its public names.
- :mod:`hybridoc.solvers.simulator`: :class:`~hybridoc.solvers.simulator.Simulator`, the
  batched differentiable torch disc simulator.
- :mod:`hybridoc.solvers.contacts`: the contact models, one module each, and their registry.
- :mod:`hybridoc.solvers.casadi_step`, :mod:`hybridoc.solvers.toi_sim`: the disc step and
  the generic time-of-impact step as CasADi functions.
- :mod:`hybridoc.solvers.compiled`, :mod:`hybridoc.solvers.codegen`: the compiled rollout,
  loss and gradient, and its C code generation.
- :mod:`hybridoc.solvers.gradcheck`: gradient checks and the contact model comparison.
- :mod:`hybridoc.solvers.candidates`: the candidate sources the reference takes sequences
  from (the transcription, the multi-start), registered through
  :data:`hybridoc.methods.BUILTIN_SOURCES`.
"""
