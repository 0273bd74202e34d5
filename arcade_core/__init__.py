"""ARCADE core: pure JAX algorithms (no I/O, no clocks, no globals).

Everything here is a function of arrays and small immutable state (NamedTuples or
equinox modules), jit- and vmap-friendly.
"""
