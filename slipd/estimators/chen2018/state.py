"""The state vector of ``pseudo_fusion``: the three estimators, the fusion's statistics and
weights, the held inputs and the working memory (``common.layout``)."""

from __future__ import annotations

from slipd.estimators.common.inputs import ImuMemory
from slipd.estimators.common.layout import build_layout

LAYOUT = build_layout(
    "chen2018",
    # KBE: [vx, vy] m/s, P packed (xx, xy, yy)
    "KBE_VX", "KBE_VY", ("KBE_P", 3),
    # DBE: [vx, vy, r], P packed (00 01 02 11 12 22)
    "DBE_VX", "DBE_VY", "DBE_R", ("DBE_P", 6),
    # WBE: xi = [vx, vy, r], information matrix M (packed), g = sum rho^j H'Y, and the
    # (m/s)^2 weighted mean squared wheel-speed residual
    "WBE_VX", "WBE_VY", "WBE_R", ("WBE_M", 6), ("WBE_G", 3), "WBE_RES_VAR",
    "WBE_REAR_SPEED",  # m/s, the rear wheels' mean speed of the last tick (NaN: unknown)
    # difference moments D_ij (gg, gb, bb) of x_i - x_j
    ("D12", 3), ("D13", 3), ("D23", 3),
    # fusion weights W_i (2x2 row-major: gg, gb, bg, bb); rows/cols: 0 yaw rate, 1 beta
    ("W1", 4), ("W2", 4), ("W3", 4),
    "FUSED_R",  # rad/s
    "FUSED_BETA",  # rad
    "FUSED_VAR_BB",  # rad^2, (L' P^-1 L)^-1 [b, b]
    "CROSS_SCALE",  # 1: the fusion used the cross blocks, 0: P was not PD with them
    # held inputs and pre-processing memory
    "LAST_AY", "LAST_YAW_RATE", ("IMU", ImuMemory),
    ("WHEEL_ACC", 4),  # derivative filters of the wheel speeds (J_w dw/dt of the DBE)
    "INITIALISED", "TICKS",
    # scratch: the fusion solve's P (6x6 row-major) and Z = P^-1 L (6x2 row-major); the
    # Kalman kernels' working memory uses SCRATCH_P too (never at the same time)
    ("SCRATCH_P", 36), ("SCRATCH_Z", 12),
)  # fmt: skip
S = LAYOUT.S
KBE_P = int(S.KBE_P)
DBE_VX = int(S.DBE_VX)
DBE_P = int(S.DBE_P)
WBE_VX = int(S.WBE_VX)
WBE_M = int(S.WBE_M)
WBE_G = int(S.WBE_G)
WBE_RES_VAR = int(S.WBE_RES_VAR)
D12 = int(S.D12)
D13 = int(S.D13)
D23 = int(S.D23)
#: Index of W_i[row, col] in the state: W_INDEX[i - 1] + 2 * row + col.
W_INDEX = (int(S.W1), int(S.W2), int(S.W3))
FUSION_FIRST = D12  # the fusion statistics, D12 .. CROSS_SCALE
FUSION_LAST = int(S.CROSS_SCALE)
IMU = int(S.IMU)
ROLL = IMU + int(ImuMemory.ROLL)
WHEEL_ACC = int(S.WHEEL_ACC)
SCRATCH_P = int(S.SCRATCH_P)
SCRATCH_Z = int(S.SCRATCH_Z)
