"""``pseudo_fusion``: Chen et al. 2018 pseudo-multi-sensor information fusion (the paper's IFE).

The kinematics-based (``kbe``, eq. 2-3), dynamics-based (``dbe``: EKF on the 3-DOF model with
magic-formula tyres and load transfer, eq. 4-13) and wheel-speed-coupling (``wbe``: ridge RLS
with forgetting, eq. 14-25) estimators run side by side; their (yaw rate, sideslip) estimates
are pseudo-measurements fused by the matrix-weighted linear minimum-variance rule (``fusion``,
eq. 26-39). Each module's docstring gives its equations and slipd's additions.

``params[PART]`` selects the output: 0 the fused estimate, 1 KBE, 2 DBE, 3 WBE alone (the
registry's ``pseudo_fusion_kbe``, ``pseudo_fusion_dbe``, ``pseudo_fusion_wbe``); all four run
the same kernel, so the parts are exactly the ones inside the fusion, but for the KBE's leak
(``kbe_vy_leak_time_constant``, k_kf's bound), which only ``pseudo_fusion_kbe`` sets.

Sign convention. Chen's axes are x forward, y left (Fig. 1: "the right-to-left direction is
positive"), which is ISO 8855, and eq. 4 is ISO-consistent with wheel 1 front-left at y = +b_f.
Eq. 6, 7 and 14 print the opposite sign on the half-track terms (as if wheel 1 were on the
right, or the yaw rate positive clockwise): slipd uses the ISO 8855 form throughout, left
wheels at y = +b (slower and unloaded in a left turn): alpha_FL = d - atan((vy + l_f r) / (vx -
b_f r)), n_FL = (vx - r b_f) cos d + (vy + r l_f) sin d, F_zFL = ... - m ay h l_r / (2 b_f l).
No other conversion is needed (ay, r, beta all + to the left).

Pre-processing (``estimators.common``, as in the righetti_lenzo2025 family): IMU
accelerations moved to the CoG with the 3-D lever arm, gravity from body roll removed from ay
by the roll complementary filter. Not in the paper (its CarSim sensors sit at the CoG without
roll).

Robustness (not in the paper): invalid steer / ax / ay hold the last valid value and an invalid
yaw rate is replaced by the DBE's (the DBE also skips the ax / ay update); invalid wheels leave
their rows out of the WBE and the vx updates; without torque frames Fx = m ax / 4 (DEGRADED);
below ``min_speed`` everything is held at vy = 0. Each estimator restarts on its own when its
state is non-finite or leaves its model's domain (DBE |vy| >= vx, KBE |vy| >= 2 vx), the fusion
statistics when they are non-finite; RESET is raised when the output's source restarted (for
the fused output: any part). An output beyond +-45 deg is clamped and flagged NOT_CONVERGED.
"""

from __future__ import annotations

import enum
import math

import numpy as np

from slipd.channels import ST_DEGRADED, ST_INPUT_TIMEOUT, ST_NOT_CONVERGED, ST_RESET, VALID, In, Veh
from slipd.errors import ConfigError
from slipd.estimators.chen2018.dbe import dbe_predict, dbe_update, vertical_loads
from slipd.estimators.chen2018.fusion import fuse, own_covariances, update_difference_moments
from slipd.estimators.chen2018.kbe import kbe_predict, kbe_update
from slipd.estimators.chen2018.state import (
    D12,
    D13,
    D23,
    DBE_P,
    DBE_VX,
    FUSION_FIRST,
    FUSION_LAST,
    IMU,
    KBE_P,
    LAYOUT,
    ROLL,
    WBE_G,
    WBE_M,
    WBE_RES_VAR,
    WBE_VX,
    WHEEL_ACC,
    S,
)
from slipd.estimators.chen2018.wbe import wbe_shift, wbe_update
from slipd.estimators.common.filters import DERIVATIVE_CUTOFF_HZ, gaussian_bell, leak
from slipd.estimators.common.inputs import (
    corner_speed_mean,
    hold_last,
    read_inputs,
    reset_imu,
    wheel_accelerations,
    wheel_speeds,
)
from slipd.estimators.common.kinematics import kinematic_beta_rate
from slipd.estimators.common.outputs import held_sigma, write_held, write_outputs
from slipd.estimators.common.vehicle import require_vehicle
from slipd.numba_cache import nb


@enum.unique
class Part(enum.IntEnum):
    """Which estimate the method outputs (params[PART])."""

    FUSED = 0  # IFE of the paper: eq. 39
    KBE = 1
    DBE = 2
    WBE = 3


@enum.unique
class PARAMS(enum.IntEnum):
    PART = 0  # Part: 0 fused, 1 KBE, 2 DBE, 3 WBE
    # KBE (slipd's Kalman form of eq. 2)
    Q_VX_KBE = 1  # (m/s)^2 per s, process noise of the vx integral
    Q_VY_KBE = 2  # (m/s)^2 per s, process noise of the vy integral
    R_VX_KBE = 3  # (m/s)^2, wheel-based vx
    R_VY0_KBE = 4  # (m/s)^2, the vy = 0 pseudo-measurement (leak)
    SIGMA_YAW_RATE = 5  # rad/s, error of the measured yaw rate (gamma_1)
    # DBE (eq. 8-13)
    Q_VX_DBE = 6  # (m/s)^2 per s
    Q_VY_DBE = 7  # (m/s)^2 per s
    Q_R_DBE = 8  # (rad/s)^2 per s
    R_AX_DBE = 9  # (m/s^2)^2
    R_AY_DBE = 10  # (m/s^2)^2
    R_VX_DBE = 11  # (m/s)^2, wheel-based vx (slipd)
    # WBE (eq. 24-25)
    FORGETTING = 12  # rho of eq. 25, per tick
    RIDGE = 13  # k1 of eq. 24-25, eigenvalue increment, (m/s)^-2 units of H'H
    # fusion
    FUSION_TIME_CONSTANT = 14  # s, forgetting of the difference moments D_ij
    VARIANCE_FROM_DIFFERENCES = 15  # P_ii: 2 yaw-rate matching, 1 three-cornered hat, 0 C_i
    CROSS_COVARIANCE = 16  # 1: P_ij from the differences, 0: P_ij = 0
    FUSION_FLOOR = 17  # rad^2 added to both variances of every P_ii
    # common
    MIN_SPEED = 18  # m/s, below it the estimators are held at vy = 0
    P0_VX = 19  # (m/s)^2 initial variances
    P0_VY = 20
    P0_R = 21  # (rad/s)^2
    SETTLE_TICKS = 22  # ticks after (re)start before convergence may be claimed
    CONVERGED_SIGMA_BETA = 23  # rad
    ROLL_TIME_CONSTANT = 24  # s, roll complementary filter (0: no gravity compensation)
    STRAIGHT_SIGMA_YAW_RATE = 25  # rad/s, width of the KBE's straight-running Gaussian
    STRAIGHT_SIGMA_AY = 26  # m/s^2, width of the KBE's straight-running Gaussian
    ROLL_GAIN_LEARNING = 27  # 1 = the roll compensation's static gain learnt (slipd), 0 = profile
    ACCEL_LOWPASS_HZ = 28  # accelerometer vibration low-pass, Hz; 0 = none (the paper)
    WBE_SPEED_SHIFT = 29  # 1 = the WBE's rows follow the rear axle's speed (slipd), 0 = xi
    #                       constant over the forgetting memory (the paper)
    KBE_VY_LEAK_TIME_CONSTANT = 30  # s, the KBE's vy decays to 0 (slipd); 0 = none (the paper)


#: Defaults. The paper publishes no filter tuning (only the vehicle of Table 1, which slipd takes
#: from the profile); every value below is slipd's, chosen from the sensor specifications of
#: the simulator (slipd.sim.sensors.SensorConfig) and the time scales named in the comments.
DEFAULTS = {
    "part": 0.0,
    "q_vx_kbe": 0.05,  # ~0.1 m/s^2 accelerometer offset over ~0.5 s correlation
    "q_vy_kbe": 0.005,  # chosen on the simulator suite from {0.02, 0.005}
    "r_vx_kbe": 0.04,
    "r_vy0_kbe": 0.25,  # with q_vy_kbe: leak time constant ~0.35 s on a straight
    "sigma_yaw_rate": math.radians(0.3),  # the gyro turn-on offset (sensors.py)
    "q_vx_dbe": 0.05,
    "q_vy_dbe": 0.01,
    "q_r_dbe": 0.01,
    "r_ax_dbe": 0.25,  # force observer errors: 5-8 % torque gain errors, rolling resistance
    "r_ay_dbe": 0.06,  # righetti_lenzo eq. 28's R_ay
    "r_vx_dbe": 0.04,
    "forgetting": 0.98,  # 0.5 s memory at 100 Hz
    "ridge": 0.5,  # vx shrinks by k1 (1 - rho) / 4 = 0.25 %, beta toward 0 at small steer
    "fusion_time_constant": 2.0,
    # yaw-rate matching (fusion's docstring; the three modes on the simulator suite:
    # benchmarks/MEASUREMENTS.md)
    "variance_from_differences": 2.0,
    "cross_covariance": 1.0,
    "fusion_floor": 1e-8,
    "min_speed": 3.0,
    "p0_vx": 1.0,
    "p0_vy": 1.0,
    "p0_r": 1e-2,
    "settle_ticks": 200.0,
    "converged_sigma_beta": 0.0175,
    "roll_time_constant": 1.0,
    "straight_sigma_yaw_rate": 0.05,  # Selmanaj 2017 Table 1 uses 0.18 on the yaw rate alone
    "straight_sigma_ay": 1.0,
    "roll_gain_learning": 1.0,
    "accel_lowpass_hz": 0.0,
    # the paper's constant xi lags a braking or accelerating car by a rho / (1 - rho) dt (wbe's
    # docstring) and the front rows turn that vx lag into vy: with the shift the WBE went from
    # 4.62 to 2.50 deg on the real run (race track, |ax| to 10 m/s^2; its wheel speeds there are
    # derived with beta = 0) and 0.78 -> 0.43 on the simulator's endurance drive, both seeds
    "wbe_speed_shift": 1.0,
    # 0 inside the fusion: its weights come from the KBE's covariance, which does not model a
    # leak; the registry's pseudo_fusion_kbe (the KBE alone, its output the open integral)
    # sets 2 s, k_kf's bound (common.filters.leak)
    "kbe_vy_leak_time_constant": 0.0,
}

#: |beta| beyond which the output is clamped and flagged (the 45 deg of the models' domain)
BETA_LIMIT = 0.25 * math.pi
#: (m/s)^2, the WBE's residual variance before any residual is seen: the wheel-speed noise
#: of the simulator's sensors at 20 m/s, (0.01 + 0.002 x 20)^2 (slipd.sim.sensors), so that the
#: WBE does not start with a zero covariance and take all the fusion weight.
WHEEL_SPEED_VARIANCE0 = 2.5e-3
#: Bits of ``reset_state``'s ``parts`` (and of ``insane_parts``).
RESET_KBE = 1
RESET_DBE = 2
RESET_WBE = 4
RESET_FUSION = 8
RESET_ALL = 15
#: The reset bit of each Part's own estimator (the fused output depends on all of them).
PART_RESET = (RESET_ALL, RESET_KBE, RESET_DBE, RESET_WBE)
#: floor of the speed in the held sigma_beta, m/s
HELD_SPEED_FLOOR = 0.1
_TORQUE_FIRST = int(In.DRIVE_TORQUE_FL)
_TORQUE_LAST = int(In.BRAKE_TORQUE_RR)


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """A fresh state vector (``state.LAYOUT``); the estimators start on the first speed sample."""
    require_vehicle("pseudo_fusion", vehicle, (
        Veh.MASS, Veh.YAW_INERTIA, Veh.LF, Veh.LR, Veh.TRACK_F, Veh.TRACK_R, Veh.WHEEL_RADIUS,
        Veh.MU_NOMINAL, Veh.TYRE_B, Veh.TYRE_C,
    ), finite=(Veh.TYRE_E,))  # fmt: skip
    if int(params[PARAMS.PART]) not in tuple(Part):
        raise ConfigError(f"pseudo_fusion: part must be one of 0..3, got {params[PARAMS.PART]}")
    # the kernels divide by these (numba raises on a division by zero): refuse them at load
    positive = (PARAMS.R_VX_KBE, PARAMS.R_VY0_KBE, PARAMS.R_AX_DBE, PARAMS.R_AY_DBE,
                PARAMS.R_VX_DBE, PARAMS.FORGETTING, PARAMS.FUSION_TIME_CONSTANT,
                PARAMS.STRAIGHT_SIGMA_YAW_RATE, PARAMS.STRAIGHT_SIGMA_AY, PARAMS.P0_VX,
                PARAMS.P0_VY, PARAMS.P0_R)  # fmt: skip
    for field in positive:
        if not params[field] > 0.0:
            raise ConfigError(f"pseudo_fusion: {field.name.lower()} must be > 0")
    if not (params[PARAMS.FORGETTING] <= 1.0 and params[PARAMS.RIDGE] > 0.0):
        raise ConfigError("pseudo_fusion: forgetting must be in (0, 1] and ridge > 0")
    if not params[PARAMS.KBE_VY_LEAK_TIME_CONSTANT] >= 0.0:
        raise ConfigError("pseudo_fusion: kbe_vy_leak_time_constant must be >= 0 (0: none)")
    return new_state()


def new_state() -> np.ndarray:
    """A state vector that starts on the first tick with a usable wheel speed."""
    state = np.zeros(LAYOUT.size, dtype=np.float64)
    reset_imu(state, IMU)
    state[WHEEL_ACC : WHEEL_ACC + 4] = np.nan  # the filters start on their first sample
    return state


@nb.njit(cache=True, _nrt=False)
def reset_state(state, vx, yaw_rate, params, parts):
    """(Re)start the estimators named by the bits ``parts`` at vy = 0 (straight-running
    assumption), vx and r as measured. Restarting the fusion restarts the tick counter."""
    vx = vx if math.isfinite(vx) else 0.0
    yaw_rate = yaw_rate if math.isfinite(yaw_rate) else 0.0
    p0_vx = params[PARAMS.P0_VX]
    p0_vy = params[PARAMS.P0_VY]
    if parts & RESET_KBE:
        state[S.KBE_VX] = vx
        state[S.KBE_VY] = 0.0
        state[KBE_P] = p0_vx
        state[KBE_P + 1] = 0.0
        state[KBE_P + 2] = p0_vy
    if parts & RESET_DBE:
        state[S.DBE_VX] = vx
        state[S.DBE_VY] = 0.0
        state[S.DBE_R] = yaw_rate
        state[DBE_P] = p0_vx
        state[DBE_P + 1] = 0.0
        state[DBE_P + 2] = 0.0
        state[DBE_P + 3] = p0_vy
        state[DBE_P + 4] = 0.0
        state[DBE_P + 5] = params[PARAMS.P0_R]
    if parts & RESET_WBE:
        # M_0 = k1 I, g_0 = 0 (eq. 24 without data: xi = 0); xi shows the start values until
        # the first wheel row arrives
        state[S.WBE_VX] = vx
        state[S.WBE_VY] = 0.0
        state[S.WBE_R] = yaw_rate
        for i in range(WBE_M, WBE_G + 2 + 1):
            state[i] = 0.0
        ridge = params[PARAMS.RIDGE]
        state[WBE_M] = ridge
        state[WBE_M + 3] = ridge
        state[WBE_M + 5] = ridge
        state[S.WBE_RES_VAR] = WHEEL_SPEED_VARIANCE0
        state[S.WBE_REAR_SPEED] = math.nan
    if parts & RESET_FUSION:
        for i in range(FUSION_FIRST, FUSION_LAST + 1):
            state[i] = 0.0
        state[S.TICKS] = 0.0


@nb.njit(cache=True, _nrt=False)
def _finite(state, first, last):
    for i in range(first, last + 1):
        if not math.isfinite(state[i]):
            return False
    return True


@nb.njit(cache=True, _nrt=False)
def insane_parts(state):
    """Bits of the estimators whose state must restart: non-finite, or outside their model's
    domain (DBE: |vy| < vx, beta within +-45 deg, the tyre model's; KBE: |vy| < 2 vx, the
    kinematics hold at any angle, this only catches a run-away integral)."""
    bad = 0
    vx = state[S.KBE_VX]
    if not (_finite(state, 0, 4) and vx > 0.0 and abs(state[S.KBE_VY]) < 2.0 * vx):
        bad |= RESET_KBE
    vx = state[S.DBE_VX]
    if not (_finite(state, DBE_VX, DBE_P + 5) and vx > 0.0 and abs(state[S.DBE_VY]) < vx):
        bad |= RESET_DBE
    if not _finite(state, WBE_VX, WBE_RES_VAR):
        bad |= RESET_WBE
    if not _finite(state, FUSION_FIRST, FUSION_LAST):
        bad |= RESET_FUSION
    return bad


@nb.njit(cache=True, inline="always")
def _inputs(state, u, vehicle, roll_time_constant, dt, learn_roll_gain, accel_lowpass_hz):
    """Pre-processed inputs of one tick with fallbacks (module docstring): ax, ay at the CoG
    (3-D lever arm), ay without the gravity component of the roll; an invalid yaw rate is the
    DBE's once it runs, an invalid ay the last valid one. Returns (ax, ay, yaw_rate, steer,
    ax_ok, ay_ok, status)."""
    yaw_fallback = state[S.DBE_R] if state[S.INITIALISED] > 0.5 else state[S.LAST_YAW_RATE]
    ax, ay, yaw_rate, _, steer, _, ax_ok, ay_ok, yaw_rate_ok, _, status = read_inputs(
        state, IMU, u, vehicle, yaw_fallback, DERIVATIVE_CUTOFF_HZ, roll_time_constant, True,
        dt, learn_roll_gain, accel_lowpass_hz,
    )  # fmt: skip
    if yaw_rate_ok:
        state[S.LAST_YAW_RATE] = yaw_rate
    ay = hold_last(state, S.LAST_AY, ay, ay_ok)
    return ax, ay, yaw_rate, steer, ax_ok, ay_ok, status


@nb.njit(cache=True, inline="always")
def longitudinal_forces(state, u, ax, vehicle, dt):
    """Fx per wheel (FL, FR, RL, RR) [N] and whether the torque frames were usable.

    Fx = (T_drive - T_brake - J_w dw/dt) / r_w with dw/dt = (dv/dt) / r_w from the derivative
    filter of the wheel speed (slipd's stand-in for the force observer of Chen's ref. [4]).
    Without valid torques the total m ax is shared equally.
    """
    rw = vehicle[Veh.WHEEL_RADIUS]
    inertia = vehicle[Veh.WHEEL_INERTIA] / (rw * rw)
    acc_fl, acc_fr, acc_rl, acc_rr, _, _, _, _ = wheel_accelerations(
        state, WHEEL_ACC, u, dt, DERIVATIVE_CUTOFF_HZ
    )
    torques_ok = True
    for ch in range(_TORQUE_FIRST, _TORQUE_LAST + 1):
        if not (u[VALID + ch] > 0.5 and math.isfinite(u[ch])):
            torques_ok = False
    if not torques_ok:
        share = 0.25 * vehicle[Veh.MASS] * ax
        return (share, share, share, share), False
    return (
        (u[In.DRIVE_TORQUE_FL] - u[In.BRAKE_TORQUE_FL]) / rw - inertia * acc_fl,
        (u[In.DRIVE_TORQUE_FR] - u[In.BRAKE_TORQUE_FR]) / rw - inertia * acc_fr,
        (u[In.DRIVE_TORQUE_RL] - u[In.BRAKE_TORQUE_RL]) / rw - inertia * acc_rl,
        (u[In.DRIVE_TORQUE_RR] - u[In.BRAKE_TORQUE_RR]) / rw - inertia * acc_rr,
    ), True


@nb.njit(cache=True, inline="always")
def _write(out, beta, vx, ax, ay, yaw_rate, sigma, roll, status):
    """vy = vx tan(beta), the kinematic beta rate; mu is the fixed MU_NOMINAL of the tyre
    model, not an estimate."""
    vy = vx * math.tan(beta)
    write_outputs(out, beta, kinematic_beta_rate(vx, vy, ax, ay, yaw_rate), vx, vy, math.nan,
                  sigma, roll, 0.0, status)  # fmt: skip


@nb.njit(cache=True, inline="always")
def _update_and_fuse(state, params, vehicle, u, steer, fx, fz, ax, ax_ok, ay, ay_ok, yaw_rate,
                     vx_meas, vx_ok, dt):  # fmt: skip
    """The a posteriori step at tick k of the three estimators and their fusion (eq. 38-39).
    Returns (beta, vx, var) of each of Part's outputs, in Part order."""
    first_tick = state[S.TICKS] < 0.5
    straight = gaussian_bell(  # how sure the car runs straight
        yaw_rate, params[PARAMS.STRAIGHT_SIGMA_YAW_RATE], ay, params[PARAMS.STRAIGHT_SIGMA_AY]
    )
    kbe_update(state, vx_meas, vx_ok, params[PARAMS.R_VX_KBE], params[PARAMS.R_VY0_KBE], straight)
    leak(state, S.KBE_VY, dt, params[PARAMS.KBE_VY_LEAK_TIME_CONSTANT])  # slipd: DEFAULTS
    dbe_update(
        state, steer, fx, fz, vehicle, ax, ax_ok, params[PARAMS.R_AX_DBE], ay, ay_ok,
        params[PARAMS.R_AY_DBE], vx_meas, vx_ok, params[PARAMS.R_VX_DBE],
    )  # fmt: skip
    v_fl, v_fr, v_rl, v_rr, ok_fl, ok_fr, ok_rl, ok_rr = wheel_speeds(u)
    # slipd: the rows seen so far follow the rear axle's speed (module docstring of wbe); NaN
    # minus anything is NaN, so a tick without both rear wheels, or after one, shifts nothing
    rear_speed = 0.5 * (v_rl + v_rr) if ok_rl and ok_rr else math.nan
    speed_change = rear_speed - state[S.WBE_REAR_SPEED]
    if params[PARAMS.WBE_SPEED_SHIFT] > 0.5 and math.isfinite(speed_change):
        wbe_shift(state, speed_change, params[PARAMS.RIDGE])
    state[S.WBE_REAR_SPEED] = rear_speed
    wbe_update(
        state, (v_fl, v_fr, v_rl, v_rr), (ok_fl, ok_fr, ok_rl, ok_rr), steer, vehicle,
        params[PARAMS.FORGETTING], params[PARAMS.RIDGE],
    )  # fmt: skip
    own1, own2, own3, beta1, beta2, beta3 = own_covariances(
        state, params[PARAMS.SIGMA_YAW_RATE], params[PARAMS.FORGETTING]
    )
    x1 = (yaw_rate, beta1)
    x2 = (state[S.DBE_R], beta2)
    x3 = (state[S.WBE_R], beta3)
    if first_tick:
        # no history yet: the moments the own covariances imply for independent errors
        for k in range(3):
            state[D12 + k] = own1[k] + own2[k]
            state[D13 + k] = own1[k] + own3[k]
            state[D23 + k] = own2[k] + own3[k]
    gain = dt / params[PARAMS.FUSION_TIME_CONSTANT]
    if gain > 1.0:
        gain = 1.0
    update_difference_moments(state, D12, x1[0] - x2[0], x1[1] - x2[1], gain)
    update_difference_moments(state, D13, x1[0] - x3[0], x1[1] - x3[1], gain)
    update_difference_moments(state, D23, x2[0] - x3[0], x2[1] - x3[1], gain)
    _, beta0, var0 = fuse(
        state, own1, own2, own3, x1, x2, x3,
        int(params[PARAMS.VARIANCE_FROM_DIFFERENCES]), params[PARAMS.CROSS_COVARIANCE] > 0.5,
        params[PARAMS.FUSION_FLOOR],
    )  # fmt: skip
    return ((beta0, state[S.DBE_VX], var0), (beta1, state[S.KBE_VX], own1[2]),
            (beta2, state[S.DBE_VX], own2[2]), (beta3, state[S.WBE_VX], own3[2]))


@nb.njit(cache=True, _nrt=False)
def step(state, u, params, vehicle, dt, out):
    """One tick: update the three estimators with tick k's measurements, fuse (eq. 38-39),
    write ``out`` (the part selected by params[PART]) and predict to tick k + 1 with tick k's
    inputs (eq. 2, eq. 9-10). Allocates nothing."""
    min_speed = params[PARAMS.MIN_SPEED]
    ax, ay, yaw_rate, steer, ax_ok, ay_ok, status = _inputs(
        state, u, vehicle, params[PARAMS.ROLL_TIME_CONSTANT], dt,
        params[PARAMS.ROLL_GAIN_LEARNING] > 0.5, params[PARAMS.ACCEL_LOWPASS_HZ],
    )
    vx_meas, n_wheels = corner_speed_mean(u, steer, yaw_rate, vehicle)
    vx_ok = n_wheels > 0
    if n_wheels < 4:
        status |= ST_INPUT_TIMEOUT
    fx, torques_ok = longitudinal_forces(state, u, ax, vehicle, dt)
    if not torques_ok:
        status |= ST_DEGRADED
    fz = vertical_loads(ax, ay, vehicle)
    roll = state[ROLL]
    speed_now = vx_meas if vx_ok else state[S.DBE_VX]
    speed_floor = max(min_speed, HELD_SPEED_FLOOR)
    if state[S.INITIALISED] < 0.5 or speed_now < min_speed:
        # start-up / standstill: hold at vy = 0 on the wheel speed
        if vx_ok:
            reset_state(state, vx_meas, yaw_rate, params, RESET_ALL)
            state[S.INITIALISED] = 1.0
        write_held(out, max(speed_now, 0.0),
                   held_sigma(params[PARAMS.P0_VY], speed_now, speed_floor), roll, status)
        return
    parts = _update_and_fuse(state, params, vehicle, u, steer, fx, fz, ax, ax_ok, ay, ay_ok,
                             yaw_rate, vx_meas, vx_ok, dt)  # fmt: skip
    part = int(params[PARAMS.PART])
    beta, vx, var = parts[part]
    # --- a priori for tick k + 1 with tick k's inputs ------------------------------------------
    kbe_predict(state, ax, ay, yaw_rate, params[PARAMS.Q_VX_KBE], params[PARAMS.Q_VY_KBE], dt)
    dbe_predict(
        state, steer, fx, fz, vehicle,
        params[PARAMS.Q_VX_DBE], params[PARAMS.Q_VY_DBE], params[PARAMS.Q_R_DBE], dt,
    )  # fmt: skip
    state[S.TICKS] += 1.0
    bad = insane_parts(state)
    if not (math.isfinite(beta) and math.isfinite(vx) and vx > 0.0 and math.isfinite(var)):
        bad = RESET_ALL
    if bad:
        reset_state(state, speed_now, yaw_rate, params, bad)
        own = PART_RESET[part]
        # RESET when the output's own source restarted (the fused output: any part)
        if bad & own or bad & RESET_FUSION:
            status |= ST_RESET | ST_NOT_CONVERGED
        if bad == RESET_ALL or (part > 0 and bad & own):
            _write(out, 0.0, speed_now, ax, ay, yaw_rate,
                   held_sigma(params[PARAMS.P0_VY], speed_now, speed_floor), roll, status)
            return
    if abs(beta) > BETA_LIMIT:
        # beyond a single-track model's domain (the fused output can be, by extrapolating
        # weights): clamp and say so
        beta = BETA_LIMIT if beta > 0.0 else -BETA_LIMIT
        status |= ST_NOT_CONVERGED
    sigma = math.sqrt(var) if var > 0.0 else 0.0
    if state[S.TICKS] < params[PARAMS.SETTLE_TICKS] or not (
        sigma <= params[PARAMS.CONVERGED_SIGMA_BETA]
    ):
        status |= ST_NOT_CONVERGED
    _write(out, beta, vx, ax, ay, yaw_rate, sigma, roll, status)


@nb.njit(cache=True, nogil=True, _nrt=False)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])


__all__ = ["DEFAULTS", "LAYOUT", "PARAMS", "Part", "init", "run_ticks", "step"]
