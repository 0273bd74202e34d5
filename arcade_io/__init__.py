"""The configuration and file layer: vehicle files, weight files, flight logs, run folders,
atomic and strict-JSON output, the JAX set-up, the option parsers the processes share, and
the discrepancy workflow run on a log and a vehicle or model file (`discrepancy.py`).

It imports only `arcade_core` (pure JAX, which knows nothing of files). The layers above it
use it: `arcade_control` (its nominal model is the default vehicle's), the simulator, the
services, deploy and the command line (design §2).
"""

__version__ = "0.1.0"
