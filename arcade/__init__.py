"""Host-side glue for ARCADE: the `arcade` command line, file formats and run folders.

The algorithms live in `arcade_core` (pure JAX); processes in `services`; the MuJoCo
vehicle in `simulator`; launch and configuration in `deploy`.
"""

__version__ = "0.1.0"
