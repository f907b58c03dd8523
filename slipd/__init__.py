"""slipd: real-time vehicle sideslip estimation, CAN in, sideslip frames out.

The Python API (README "Python API"; details in :mod:`slipd.api`):

* :func:`decode` a log to SI input channels per 10 ms tick (a pandas DataFrame);
* :func:`estimate` sideslip with one or more methods from a log, python-can Messages, a
  simulation or a DataFrame of channels;
* :func:`evaluate` estimates against ground truth (accuracy and the VALID-honesty figures);
* :func:`simulate` a drive on the independent plant; :func:`read_truth` a truth CSV;
* :func:`plot` estimates against truth; :class:`Estimator` for one tick at a time in a loop.

Importing slipd compiles nothing, imports neither numba nor pandas and changes no environment
variable.
"""

from slipd.api import (
    Estimator,
    Output,
    Simulation,
    decode,
    estimate,
    evaluate,
    plot,
    read_truth,
    simulate,
)

__all__ = ["decode", "estimate", "evaluate", "simulate", "read_truth", "plot", "Estimator",
           "Output", "Simulation"]
