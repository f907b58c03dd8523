"""Benchmarks: ``python -m benchmarks.NAME``. Kernels cache under the source key, as for the
slipd command (importing slipd sets nothing)."""

from slipd.numba_cache import use_keyed_cache

use_keyed_cache()
