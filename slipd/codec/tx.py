"""Estimator outputs -> output-frame slots, the one mapping the daemon and replay share."""

from __future__ import annotations

import math

from slipd.channels import ST_VALID, Out
from slipd.codec.plan import Tx
from slipd.numba_cache import nb

_COPIED = int(Out.STATUS) + 1
_FINITE_SLOTS = (int(Tx.BETA), int(Tx.BETA_RATE), int(Tx.VX), int(Tx.VY), int(Tx.SIGMA_BETA),
                 int(Tx.ROLL), int(Tx.MU))
_MU, _MU_VALID, _ESTIMATOR_ID = int(Tx.MU), int(Tx.MU_VALID), int(Tx.ESTIMATOR_ID)
_SIGMA = int(Tx.SIGMA_BETA)
#: An unknown sigma_beta goes out as this (clamped by the encoder to the signal's maximum,
#: 20.475 deg): "do not rely on it", never 0.
UNKNOWN_SIGMA = 1.0e9


@nb.njit(cache=True, _nrt=False)
def fill_tx(out, estimator_id, tx):
    """Write SLIPD_STATE/AUX slots from ``out``. A non-finite value becomes 0 (its frame is
    then not VALID, see supervision.supervise; the bits must still be defined), except an
    unknown sigma_beta, which goes out at its maximum. MU_VALID: the method estimates mu and
    the frame is VALID (inputs fresh, method converged and consistent)."""
    mu_valid = 1.0 if (math.isfinite(out[Out.MU]) and (int(out[Out.STATUS]) & ST_VALID)) else 0.0
    for slot in range(_COPIED):
        tx[slot] = out[slot]
    if not math.isfinite(tx[_SIGMA]):
        tx[_SIGMA] = UNKNOWN_SIGMA
    for slot in _FINITE_SLOTS:
        if not math.isfinite(tx[slot]):
            tx[slot] = 0.0
    tx[_MU_VALID] = mu_valid
    tx[_ESTIMATOR_ID] = estimator_id


@nb.njit(cache=True, _nrt=False)
def fill_tx_rows(OUT, estimator_id, TX):
    for k in range(OUT.shape[0]):
        fill_tx(OUT[k], estimator_id, TX[k])
