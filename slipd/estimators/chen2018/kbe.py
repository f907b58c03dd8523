"""KBE, the kinematics-based estimator of Chen et al. 2018 (Sec. 2.1), state [vx, vy].

eq. 1-2  vx' = ax + vy r,  vy' = ay - vx r (integrated, forward Euler), eq. 3 beta = vy / vx
         (slipd writes atan2(vy, vx), equal to first order). gamma_1 is the measured yaw rate
         (the paper: "in x_1, the estimation of yaw rate is the real yaw rate").

slipd additions (the open integral of eq. 2 drifts without bound: gyro and accelerometer
offsets of production sensors integrate to metres per second within a minute): the integral
is run as a Kalman filter whose vx is corrected by the wheel-based speed (R ``r_vx_kbe``) and
whose vy is pulled to 0 by a pseudo-measurement only while the car runs straight:
R = ``r_vy0_kbe`` / F with F = exp(-(r^2 / s_r^2 + ay^2 / s_ay^2) / 2) the Gaussian
straight-running heuristic of Selmanaj et al. 2017 (eq. 5-6). In a corner F ~ 0 and the
integral runs open, as in the paper (where the KBE alone is the output, ``pseudo_fusion_kbe``,
vy also leaks to 0 with k_kf's 2 s: pseudo_fusion's ``kbe_vy_leak_time_constant``). Its
covariance (random-walk process noise ``q_vx_kbe``, ``q_vy_kbe``, per second) is the KBE's own
error covariance for the fusion.
"""

from __future__ import annotations

from slipd.estimators.chen2018.state import KBE_P, SCRATCH_P, S
from slipd.estimators.common.kalman import per_step, predict_covariance, scalar_update
from slipd.numba_cache import nb

#: F below which the straight-running pseudo-measurement is skipped (its R would be ~inf)
MIN_STRAIGHT_WEIGHT = 1e-6
_KBE_VX = int(S.KBE_VX)


@nb.njit(cache=True, _nrt=False)
def kbe_predict(state, ax, ay, yaw_rate, q_vx, q_vy, dt):
    """Eq. 2, forward Euler: vx += (ax + vy r) dt, vy += (ay - vx r) dt; P = F P F' + Q dt."""
    vx = state[S.KBE_VX]
    vy = state[S.KBE_VY]
    state[S.KBE_VX] = vx + (ax + vy * yaw_rate) * dt
    state[S.KBE_VY] = vy + (ay - vx * yaw_rate) * dt
    predict_covariance(state, KBE_P, SCRATCH_P, (1.0, yaw_rate * dt, -yaw_rate * dt, 1.0),
                       (per_step(q_vx, dt, 1.0), per_step(q_vy, dt, 1.0)))  # fmt: skip


@nb.njit(cache=True, _nrt=False)
def kbe_update(state, vx_meas, vx_ok, r_vx, r_vy0, straight):
    """vx from the wheels (if any) and the vy = 0 pseudo-measurement (slipd's bound on the
    integral of eq. 2) with variance r_vy0 / ``straight``: full strength on a straight, none
    in a corner, where the integral runs open as in the paper."""
    if vx_ok:
        scalar_update(state, _KBE_VX, KBE_P, SCRATCH_P, (1.0, 0.0), vx_meas - state[S.KBE_VX],
                      r_vx)  # fmt: skip
    if straight > MIN_STRAIGHT_WEIGHT:
        scalar_update(state, _KBE_VX, KBE_P, SCRATCH_P, (0.0, 1.0), -state[S.KBE_VY],
                      r_vy0 / straight)  # fmt: skip
