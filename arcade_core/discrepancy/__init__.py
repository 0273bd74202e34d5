"""Model discrepancy: the effect library, models with effects, identification (design §6).

- :mod:`~arcade_core.discrepancy.catalog`: canonical effects (names, units, ranges; plain
  data, shared with the simulator); :mod:`~arcade_core.discrepancy.tables`: effect tables
  checked against it;
- :mod:`~arcade_core.discrepancy.quadrotor`, :mod:`~arcade_core.discrepancy.cartpole`:
  the nominal models (Appendix D) with the effect terms, parameter vectors ``theta``;
- :mod:`~arcade_core.discrepancy.identify`: sparse selection over effects with block
  bootstrap confidence and nonlinear parameter fit (its parts:
  :mod:`~arcade_core.discrepancy.linearise`, :mod:`~arcade_core.discrepancy.subsets`);
- :mod:`~arcade_core.discrepancy.localize`: where the gap is (regimes, changepoint
  segments via Algorithm 1);
- :mod:`~arcade_core.discrepancy.workflow`: the workflow on one log (align, localise,
  name, add, show), with its settings and the split of the log in
  :mod:`~arcade_core.discrepancy.settings` and the model's predictions in
  :mod:`~arcade_core.discrepancy.prediction`.

Submodules are imported explicitly (the library is imported by the simulator, which should
not pay for JAX).
"""
