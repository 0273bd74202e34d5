"""The `arcade` command line and the offline jobs it runs (training, demos, reports).

The algorithms live in `arcade_core` (pure JAX) and `arcade_control` (the closed-loop
control library); files and configuration in `arcade_io`; processes in `services`; the
MuJoCo vehicle in `simulator`; launch in `deploy`.
"""

from arcade_io import __version__

__all__ = ["__version__"]
