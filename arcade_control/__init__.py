"""The closed-loop control library: what the processes and the evaluations share.

- ``nominal``: the control period ``CONTROL_DT`` and the nominal model ``f_nom`` over it;
- ``scenario``: the flight plan (take-off, hover, ramped figure-eight, release) and its flat
  reference;
- ``methods``, ``learners``, ``guard``, ``knobs``: the control methods (nominal, L1, GP,
  MLP, ours and its variants), their adaptive state at take-off, the learned residual's
  trust region, and the knobs they fly with;
- ``step``: the jitted per-step controller update (learn, plan, correct);
- ``stack``: what the adapter and controller services compute per message; ``hover``:
  the fallback laws;
- ``expert``, ``cartpole``: the expert pilot of the quadrotor's training flights and the
  cartpole's offline data.

Pure JAX and NumPy on top of :mod:`arcade_core`; the default vehicle's parameters and
weight files are read through :mod:`arcade_io`. Layers above it (simulator, services,
deploy, command line, benchmarks) compose these; it imports none of them.
"""
