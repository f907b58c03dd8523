"""The slip-based friction classifier of Carnier, Corno, Savaresi 2023 (Sec. 3, eq. 17-22,
Fig. 9-10): lambda-mu_x maps on Burckhardt curves per wheel (eq. 17-18, 20-21) and alpha-mu_y
maps on the observer's own tyre model per axle (eq. 9, 19, 20, 22); a detected change
re-initialises mu hat and the attraction value mu bar of eq. 14 (``classifier_update``).

Signs as in ``observer`` (ISO 8855, forces and slip angles positive to the left).
"""

from __future__ import annotations

import math

from slipd.channels import In, Veh
from slipd.estimators.carnier2023.observer import TYRE0, S, tyre_coefficients, tyre_force
from slipd.estimators.common.inputs import channel
from slipd.estimators.common.tyres import static_wheel_loads
from slipd.estimators.common.tyres import wheel_loads as rigid_wheel_loads
from slipd.numba_cache import nb

#: Burckhardt (1993) tyre-road characteristics, mu(lambda) = c1 (1 - exp(-c2 lambda)) - c3 lambda,
#: as tabulated e.g. by Kiencke & Nielsen, "Automotive Control Systems" (Table 7.1).
BURCKHARDT_DRY_ASPHALT = (1.2801, 23.99, 0.52)
BURCKHARDT_WET_ASPHALT = (0.857, 33.822, 0.347)
BURCKHARDT_SNOW = (0.1946, 94.129, 0.0646)
#: share of its static load a lifted wheel keeps in eq. 20 (a small, well-defined force)
MIN_LOAD_SHARE = 0.05


@nb.njit(cache=True, _nrt=False)
def burckhardt(slip, c1, c2, c3):
    """Burckhardt's mu(lambda) = c1 (1 - exp(-c2 lambda)) - c3 lambda for lambda >= 0."""
    return c1 * (1.0 - math.exp(-c2 * slip)) - c3 * slip


@nb.njit(cache=True, _nrt=False)
def map_region(slip, mu_measured, curve_high, curve_low, low_peak, slip_min, band, high_margin,
               min_gap):  # fmt: skip
    """Region of a (slip, mu) point on a classification map (Fig. 10): +1 high grip (red),
    -1 low grip (blue), 0 undefined (white).

    - high: |mu| >= low_peak + high_margin, whatever the slip - the tyre transmits more than
      the low surface can at any slip (its curve's peak ``low_peak``), which proves high grip
      even where the slip estimate is poor; or, above the slip limit, |mu| within
      ``band`` x gap of the high curve (gap = curve_high - curve_low);
    - low: above the slip limit, | |mu| - curve_low | <= band x gap - on the low curve, far
      below what high grip gives. A point well *below* the low curve fits neither surface (at
      that slip both would transmit more): it betrays a slip estimate that is too large, not
      low grip, and stays white;
    - white otherwise, and wherever |slip| < ``slip_min`` or gap < ``min_gap`` (the paper's
      green limits and white area: the curves merge at small slip, Fig. 19) or force and slip
      have opposite signs (a transient the steady maps do not describe).
    """
    if abs(mu_measured) >= low_peak + high_margin:
        return 1
    if abs(slip) < slip_min:
        return 0
    if mu_measured * slip <= 0.0:
        return 0
    gap = curve_high - curve_low
    if gap < min_gap:
        return 0
    excess = abs(mu_measured) - curve_low
    if excess >= (1.0 - band) * gap:
        return 1
    if abs(excess) <= band * gap:
        return -1
    return 0


@nb.njit(cache=True, _nrt=False)
def burckhardt_peak(c1, c2, c3):
    """Maximum of the Burckhardt curve: d mu / d lambda = c1 c2 exp(-c2 lambda) - c3 = 0."""
    if c3 <= 0.0:
        return c1
    slip = math.log(c1 * c2 / c3) / c2
    return burckhardt(max(slip, 0.0), c1, c2, c3)


@nb.njit(cache=True, _nrt=False)
def wheel_loads(ax, ay, vehicle):
    """eq. 20: F_zi = k1 m g + k2 m A_x + k3 m A_y with the rigid-body coefficients
    k1 = static share (l_r / 2l front, l_f / 2l rear), k2 = -+ h / 2l (accelerating moves load
    to the rear), k3 = -+ h / track x the axle's static share (ISO: A_y > 0, a left turn, loads
    the right wheels; ``common.tyres.wheel_loads``). Returns (Fz_fl, Fz_fr, Fz_rl, Fz_rr) in N,
    each at least MIN_LOAD_SHARE of its static load."""
    static_f, static_r = static_wheel_loads(vehicle)
    return rigid_wheel_loads(ax, ay, vehicle, MIN_LOAD_SHARE * static_f,
                             MIN_LOAD_SHARE * static_r)  # fmt: skip


@nb.njit(cache=True, _nrt=False)
def longitudinal_point(wheel_speed, wheel_accel, drive, brake, vx_wheel, fz, vehicle):
    """(lambda, mu_x) of one wheel: eq. 17 lambda = (V_w - V_x) / max(V_w, V_x) with V_x the
    estimate referred to the wheel; eq. 21 F_x = (T_en - T_br - J omega_dot) / R with
    omega_dot = (dV_w / dt) / R; eq. 18 mu_x = F_x / F_z."""
    radius = vehicle[Veh.WHEEL_RADIUS]
    denominator = max(wheel_speed, vx_wheel)
    slip = (wheel_speed - vx_wheel) / denominator if denominator > 0.5 else 0.0
    force = (drive - brake - vehicle[Veh.WHEEL_INERTIA] * wheel_accel / radius) / radius
    return slip, force / fz


@nb.njit(cache=True, _nrt=False)
def _low_curve(alpha, fz_axle, mu_low, a_c, b_c, a_k, b_k, k_floor):
    """|mu_y| of the observer's own axle model (eq. 8, 10) at the low reference friction and
    the curve's peak C_r / k / Fz."""
    c_l, k_l = tyre_coefficients(mu_low, a_c, b_c, a_k, b_k, k_floor)
    return abs(tyre_force(alpha, c_l, k_l)[0]) / fz_axle, c_l / k_l / fz_axle


@nb.njit(cache=True, _nrt=False)
def classify_tick(
    state, u, ax, ay, yaw_acc, steer, alpha_f, alpha_r, force_f_high, force_r_high, speeds,
    speeds_ok, wheel_acc, vx, vehicle, mu_low, k_floor, burckhardt_high, burckhardt_low,
    slip_min, alpha_min, band, high_margin, min_gap, yaw_moment_split,
):  # fmt: skip
    """Regions of every map point of one tick (Fig. 9): two axles on the alpha-mu_y map, four
    wheels on the lambda-mu_x map (only where the wheel's drive and brake torques are valid).

    ``force_*_high``: the axle forces of the observer's model at the high reference friction
    (MU_NOMINAL) at ``alpha_*``, from ``observer_step`` (the high curve of the lateral map, the
    same model (8) as the observer, Sec. 3). ``speeds``: the four wheel speeds referred to the
    CoG x axis (``compensate_wheel_speeds``), so lambda of eq. 17 compares them with vx hat
    directly; ``speeds_ok`` their validity; ``wheel_acc``: dV_w/dt of the raw speeds.
    Returns (any_high, any_low).

    Axle forces: eq. 22 is the steady-state split (yaw_acc = 0). With ``yaw_moment_split``
    (slipd, default on) the yaw balance I_z r' = l_f F_yF cos(delta) - l_r F_yR is kept too,
    F_yF cos(delta) = (l_r m A_y + I_z r') / l, F_yR = (l_f m A_y - I_z r') / l: in a steering
    transient the front force leads A_y, and the steady split would put a large front slip
    angle next to a small force, i.e. in the low-grip region, on a dry road.
    """
    fz_fl, fz_fr, fz_rl, fz_rr = wheel_loads(ax, ay, vehicle)
    any_high = False
    any_low = False
    # lateral map per axle, eq. 19 and 22 (with the yaw balance, see above)
    lf = vehicle[Veh.LF]
    lr = vehicle[Veh.LR]
    wheelbase = lf + lr
    m_ay = vehicle[Veh.MASS] * ay
    yaw_moment = vehicle[Veh.YAW_INERTIA] * yaw_acc if yaw_moment_split else 0.0
    t = TYRE0
    fz_front = fz_fl + fz_fr
    mu_y_front = (lr * m_ay + yaw_moment) / (wheelbase * math.cos(steer)) / fz_front
    low, low_peak = _low_curve(
        alpha_f, fz_front, mu_low, state[t], state[t + 1], state[t + 2], state[t + 3], k_floor
    )
    region = map_region(alpha_f, mu_y_front, abs(force_f_high) / fz_front, low, low_peak,
                        alpha_min, band, high_margin, min_gap)  # fmt: skip
    any_high |= region > 0
    any_low |= region < 0
    fz_rear = fz_rl + fz_rr
    mu_y_rear = (lf * m_ay - yaw_moment) / wheelbase / fz_rear
    low, low_peak = _low_curve(
        alpha_r,
        fz_rear,
        mu_low,
        state[t + 4],
        state[t + 5],
        state[t + 6],
        state[t + 7],
        k_floor,
    )
    region = map_region(alpha_r, mu_y_rear, abs(force_r_high) / fz_rear, low, low_peak,
                        alpha_min, band, high_margin, min_gap)  # fmt: skip
    any_high |= region > 0
    any_low |= region < 0
    # longitudinal map per wheel (eq. 17-18, 21)
    long_low_peak = burckhardt_peak(burckhardt_low[0], burckhardt_low[1], burckhardt_low[2])
    for i in range(4):
        if not speeds_ok[i]:
            continue
        drive, drive_ok = channel(u, In.DRIVE_TORQUE_FL + i)
        brake, brake_ok = channel(u, In.BRAKE_TORQUE_FL + i)
        if not (drive_ok and brake_ok):
            continue
        fz = fz_fl if i == 0 else fz_fr if i == 1 else fz_rl if i == 2 else fz_rr
        slip, mu_x = longitudinal_point(speeds[i], wheel_acc[i], drive, brake, vx, fz, vehicle)
        abs_slip = abs(slip)
        if abs_slip < slip_min and abs(mu_x) < long_low_peak + high_margin:
            continue  # white: skip the curves
        curve_high = burckhardt(abs_slip, burckhardt_high[0], burckhardt_high[1],
                                burckhardt_high[2])  # fmt: skip
        curve_low = burckhardt(abs_slip, burckhardt_low[0], burckhardt_low[1], burckhardt_low[2])
        region = map_region(slip, mu_x, curve_high, curve_low, long_low_peak, slip_min, band,
                            high_margin, min_gap)  # fmt: skip
        any_high |= region > 0
        any_low |= region < 0
    return any_high, any_low


@nb.njit(cache=True, _nrt=False)
def classifier_update(state, any_high, any_low, persistence_ticks, mu_high, mu_low):
    """The boolean mu bar of Sec. 3: a high-grip point while mu bar = 0 switches to high, a
    low-grip point while mu bar = 1 switches to low, anything else keeps it. A switch needs the
    points in the new region on ``persistence_ticks`` consecutive ticks (slipd: a one-sample
    noise spike must not re-initialise mu). On a switch mu hat and the attraction value mu bar
    of eq. 14 are re-initialised to the class's reference friction. Returns True on a switch.
    """
    state[S.HIGH_TICKS] = state[S.HIGH_TICKS] + 1.0 if any_high and not any_low else 0.0
    state[S.LOW_TICKS] = state[S.LOW_TICKS] + 1.0 if any_low and not any_high else 0.0
    is_high = state[S.CLASS_HIGH] > 0.5
    if not is_high and state[S.HIGH_TICKS] >= persistence_ticks:
        state[S.CLASS_HIGH] = 1.0
        state[S.MU] = mu_high
        state[S.MU_DEFAULT] = mu_high
        state[S.DETECTIONS] += 1.0
        return True
    if is_high and state[S.LOW_TICKS] >= persistence_ticks:
        state[S.CLASS_HIGH] = 0.0
        state[S.MU] = mu_low
        state[S.MU_DEFAULT] = mu_low
        state[S.DETECTIONS] += 1.0
        return True
    return False

