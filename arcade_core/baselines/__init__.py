"""Baseline residual models and controllers the paper compares against (Appendix D, Sec. V).

- :mod:`~arcade_core.baselines.gp`: per-output ARD-RBF GPs on a FIFO buffer (GP-MPC);
- :mod:`~arcade_core.baselines.mlp`: MLP with online last-layer SGD and UT variance
  (MLP-MPC);
- :mod:`~arcade_core.baselines.sysid`: sparse polynomial/trigonometric regression (SysID);
- :mod:`~arcade_core.baselines.l1`: L1-adaptive thrust/rate augmentation (L1);
- :mod:`~arcade_core.baselines.proto`: encoder-prototype-decoder with attention over
  per-task prototypes (Proto-MPC, open loop).

All residual learners predict ``delta = x_{k+1} - f_nom(x_k, u_k)`` from ``(x, u)``.
"""

from arcade_core.baselines import gp, l1, mlp, proto, sysid

__all__ = ["gp", "l1", "mlp", "proto", "sysid"]
