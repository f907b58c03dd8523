"""``pseudo_fusion``: Chen et al. 2018 pseudo-multi-sensor information fusion (the paper's IFE).

The kinematics-based (KBE, eq. 2-3), dynamics-based (DBE, EKF on the 3-DOF model with
magic-formula tyres and load transfer, eq. 4-13) and wheel-speed-coupling (WBE, ridge RLS with
forgetting, eq. 14-25) estimators run side by side; their (yaw rate, sideslip) estimates are
pseudo-measurements fused by the matrix-weighted linear minimum-variance rule (eq. 26-39).
The kernels, the state layout (``S``, including the fusion weights W1..W3 at ``S.W1_GG`` ..
``S.W3_BB``), the ISO 8855 conversion of the paper's signs and the online estimate of the
error covariances P_ij are documented in ``slipd.estimators.chen``.

``params[PART]`` selects the output: 0 the fused estimate (this module), 1 KBE, 2 DBE, 3 WBE
alone (also registered as ``pseudo_fusion_kbe``, ``pseudo_fusion_dbe``, ``pseudo_fusion_wbe``);
all four run the same kernel, so the parts are exactly the ones inside the fusion.
"""

from __future__ import annotations

from slipd.estimators.chen import DEFAULTS as _CHEN_DEFAULTS
from slipd.estimators.chen import PARAMS, Part, S, init, run_ticks, step

__all__ = ["DEFAULTS", "PARAMS", "S", "Part", "init", "run_ticks", "step"]

DEFAULTS = {**_CHEN_DEFAULTS, "part": float(Part.FUSED)}
