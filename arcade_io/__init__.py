"""The configuration and file layer: vehicle files, weight files, flight logs, run folders,
atomic and strict-JSON output, the JAX set-up, and the option parsers the processes share.

Below it only `arcade_control` reads the default vehicle through it and `arcade_core` (pure
JAX) knows nothing of files; above it the simulator, the services, deploy and the command
line (design §2).
"""

__version__ = "0.1.0"
