"""Shared test set-up: float64 for correctness tests and the persistent JAX cache."""

from arcade import jaxsetup

jaxsetup.configure(x64=True)
