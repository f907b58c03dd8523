"""The friction EKF of Yoon, Li, Ahn 2016 (Sec. 4, eq. 13-16): x = mu, f(mu) = mu, h(mu) = a_y of
eq. 13 with the slip angles of eq. 14 from the estimated beta and the brush tyre of eq. 15
(``common.tyres.brush_tyre``). The brush model's c_p l^2 comes from the axle cornering
stiffness of the vehicle profile (2 c_p l^2 = C_alpha per tyre, the slope of eq. 15 at
alpha = 0).

slipd (the paper notes the estimate is unreliable without excitation, Sec. 5.2): the update
runs only when |d a_y / d mu| >= ``min_sensitivity``; an innovation beyond the chi-square
``gate`` is down-weighted (Huber: bounded pull, no lock-out), since an a_y the model cannot
explain at any nearby mu is more likely a beta error or a longitudinal force (which eq. 13
leaves out) than mu.
"""

from __future__ import annotations

import math

from slipd.channels import Veh
from slipd.estimators.common.kalman import scalar_update
from slipd.estimators.common.tyres import brush_tyre, static_wheel_loads
from slipd.numba_cache import nb


@nb.njit(cache=True, _nrt=False)
def lateral_acceleration_model(mu, beta, yaw_rate, vx, steer, vehicle):
    """h(mu) of eq. 16: a_y = (2 f_yf cos(delta) + 2 f_yr) / m (eq. 13) and dh/dmu.

    Slip angles of eq. 14 (ISO 8855, the paper's): alpha_f = delta - (beta + a r / vx),
    alpha_r = -(beta - b r / vx). Static tyre loads Fz = m g b / (2 l) front, m g a / (2 l) rear;
    the brush model's stiffness is half the profile's axle cornering stiffness (per tyre).
    """
    mass = vehicle[Veh.MASS]
    lf = vehicle[Veh.LF]
    lr = vehicle[Veh.LR]
    stiffness_f = vehicle[Veh.CORNERING_STIFFNESS_F]
    stiffness_r = vehicle[Veh.CORNERING_STIFFNESS_R]
    fz_front, fz_rear = static_wheel_loads(vehicle)
    alpha_f = steer - (beta + lf * yaw_rate / vx)
    alpha_r = -(beta - lr * yaw_rate / vx)
    force_f, dforce_f = brush_tyre(alpha_f, mu, fz_front, 0.5 * stiffness_f)
    force_r, dforce_r = brush_tyre(alpha_r, mu, fz_rear, 0.5 * stiffness_r)
    cos_steer = math.cos(steer)
    ay = (2.0 * force_f * cos_steer + 2.0 * force_r) / mass
    day_dmu = (2.0 * dforce_f * cos_steer + 2.0 * dforce_r) / mass
    return ay, day_dmu


@nb.njit(cache=True, _nrt=False)
def friction_update(state, i_mu, i_p, i_updates, scratch, beta, yaw_rate, vx, steer, ay, ay_ok,
                    vehicle, q_mu, r_ay, min_speed, min_sensitivity, gate, mu_min,
                    mu_max):  # fmt: skip
    """One tick of the friction EKF on ``state[i_mu]`` (mu), ``state[i_p]`` (its variance) and
    ``state[i_updates]`` (excited updates so far): predict (f = mu, ``q_mu`` per step), then,
    with a valid ``ay`` (gravity-free, CoG) above ``min_speed`` and enough excitation, the
    scalar update by eq. 16 (``common.kalman.scalar_update``; one scratch slot), clamped to
    [mu_min, mu_max]."""
    mu = state[i_mu]
    state[i_p] += q_mu  # f(mu) = mu
    if not (ay_ok and vx > min_speed):
        return
    ay_model, h_mu = lateral_acceleration_model(mu, beta, yaw_rate, vx, steer, vehicle)
    if abs(h_mu) < min_sensitivity:
        return
    innovation = ay - ay_model
    d2 = innovation * innovation / (h_mu * state[i_p] * h_mu + r_ay)
    if d2 > gate:
        r_ay *= d2 / gate  # Huber: bounded pull, no lock-out
    scalar_update(state, i_mu, i_p, scratch, (h_mu,), innovation, r_ay)
    state[i_mu] = min(max(state[i_mu], mu_min), mu_max)
    state[i_updates] += 1.0
