"""Test-session setup shared by every test module."""

from slipd.numba_cache import use_keyed_cache

# The kernels cache under a key of slipd's sources, as for the slipd command (importing slipd
# no longer sets it); child processes the tests start inherit the variable.
use_keyed_cache()
