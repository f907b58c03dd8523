"""The parameters an engineer would measure on the simulated car, derived from the plant's data.

These describe the car in slipd's vocabulary (``slipd.channels.Veh``) for the vehicle profile
and for the driver model's feed-forward. They are computed, never copied by hand, so the profile
and the plant cannot drift apart unnoticed (tests/test_sim.py checks them against steady-state
simulations).
"""

from __future__ import annotations

import math

from slipd.sim.plant import G, vehicle_parameters

#: Where the IMU sits relative to the CoG when the profile does not say (ISO 8855 body axes, m):
#: an ESC unit on the tunnel under the front seats, ahead of and below the CoG.
DEFAULT_IMU_POSITION = (0.25, 0.0, -0.25)

#: Steering-wheel to road-wheel ratio of the simulated car when the profile does not say (the
#: shipped default profile's value; a BMW 3-series has 15-16:1).
DEFAULT_STEER_RATIO = 16.0


def static_axle_loads(p) -> tuple[float, float]:
    """Static front and rear axle loads (N), as ``init_mb`` computes them (sprung mass split by
    its CoG position plus the unsprung masses)."""
    wheelbase = p.a + p.b
    front = p.m_s * G * p.b / wheelbase + p.m_uf * G
    rear = p.m_s * G * p.a / wheelbase + p.m_ur * G
    return front, rear


def derived(vehicle: int = 2, extra_mass: float = 0.0) -> dict[str, float]:
    """Measured-style parameters of parameter set ``vehicle`` keyed by ``Veh`` member name.

    - LF/LR from the static axle loads (a scale under each axle), not the sprung-mass CoG;
    - cornering stiffness per axle: the Pacejka slope at zero slip K_y = |p_ky1| F_z (the
      package's simplified K_y0, tire_model.formula_lateral) summed over the axle's two tyres
      at the static load;
    - Pacejka B/C/E of one tyre at the average static load: C = p_cy1, E = p_ey1,
      B = K_y / (C D) with D = p_dy1 F_z (so D/F_z = MU_NOMINAL);
    - roll stiffness from the suspension data: spring pairs (K T^2 / 2 per axle) plus the
      model's auxiliary torsion terms K_ts, in series with the tyres' vertical stiffness
      (K_zt T^2 / 2); damping: the dampers' K_sd T^2 / 2. (The multi-body model rolls more than
      these springs alone say: :func:`steady_state_test` measures the effective value);
    - longitudinal stiffness: p_kx1 F_z of one tyre at the average static load.
    """
    p = vehicle_parameters(vehicle, extra_mass=extra_mass)
    front, rear = static_axle_loads(p)
    wheelbase = p.a + p.b
    weight = front + rear
    mass = weight / G
    t = p.tire
    fz_mean = weight / 4.0
    c_y = t.p_cy1
    d_y = t.p_dy1 * fz_mean
    k_y = abs(t.p_ky1) * fz_mean
    springs = 0.5 * (p.K_sf * p.T_f**2 + p.K_sr * p.T_r**2) + p.K_tsf + p.K_tsr
    tyres = 0.5 * p.K_zt * (p.T_f**2 + p.T_r**2)
    roll_stiffness = springs * tyres / (springs + tyres)
    return {
        "MASS": mass,
        "YAW_INERTIA": p.I_z,
        "ROLL_INERTIA": p.I_Phi_s,
        "LF": wheelbase * rear / weight,
        "LR": wheelbase * front / weight,
        "TRACK_F": p.T_f,
        "TRACK_R": p.T_r,
        "H_COG": p.h_cg,
        # the profile's roll_axis_height: distance from the roll axis (h_raf, h_rar above
        # ground; 0 for set 2: the compliant joints sit at ground level) up to the CoG
        "H_ROLL_AXIS": p.h_cg - 0.5 * (p.h_raf + p.h_rar),
        "WHEEL_RADIUS": p.R_w,
        "STEER_RATIO": DEFAULT_STEER_RATIO,
        "IMU_X": DEFAULT_IMU_POSITION[0],
        "IMU_Y": DEFAULT_IMU_POSITION[1],
        "IMU_Z": DEFAULT_IMU_POSITION[2],
        "ROLL_STIFFNESS": roll_stiffness,
        "ROLL_DAMPING": 0.5 * (p.K_sdf * p.T_f**2 + p.K_sdr * p.T_r**2),
        "CORNERING_STIFFNESS_F": abs(t.p_ky1) * front,
        "CORNERING_STIFFNESS_R": abs(t.p_ky1) * rear,
        "LONGITUDINAL_STIFFNESS": t.p_kx1 * fz_mean,
        "MU_NOMINAL": t.p_dy1,
        "WHEEL_INERTIA": p.I_y_w,
        "TYRE_B": k_y / (c_y * d_y),
        "TYRE_C": c_y,
        "TYRE_E": t.p_ey1,
    }


def understeer_gradient(vehicle: int = 2, extra_mass: float = 0.0) -> float:
    """K_us (rad per m/s^2) of the linear single-track model: m/L (l_r/C_f - l_f/C_r)."""
    d = derived(vehicle, extra_mass)
    wheelbase = d["LF"] + d["LR"]
    return d["MASS"] / wheelbase * (
        d["LR"] / d["CORNERING_STIFFNESS_F"] - d["LF"] / d["CORNERING_STIFFNESS_R"]
    )


def single_track_steady_state(
    vehicle: int, speed: float, steer: float, extra_mass: float = 0.0
) -> tuple[float, float]:
    """Yaw rate (rad/s) and sideslip (rad) of the linear single-track model in steady state.

    r = v delta / (L + K_us v^2);  beta = (l_r - l_f m v^2 / (C_r L)) r / v
    (Mitschke & Wallentowitz, Dynamik der Kraftfahrzeuge, ch. 26; ISO 8855 signs).
    """
    d = derived(vehicle, extra_mass)
    wheelbase = d["LF"] + d["LR"]
    k_us = understeer_gradient(vehicle, extra_mass)
    r = speed * steer / (wheelbase + k_us * speed**2)
    beta = (d["LR"] - d["LF"] * d["MASS"] * speed**2 / (d["CORNERING_STIFFNESS_R"] * wheelbase)) * (
        r / speed
    )
    return r, beta


def _circle(vehicle: int, speed: float, steer: float, duration: float) -> dict[str, float]:
    """Settled means of a constant-steer run (the last second)."""
    from slipd.sim.driver import steer_step
    from slipd.sim.plant import ROLL, ROLL_SIGN, STEER, VX, VY, YAW_RATE, Driver, Plant, Road

    driver = Driver(steer=steer_step(0.5, steer, 0.3), speed_target=lambda t, s: speed)
    out = Plant(vehicle_parameters(vehicle), Road(), driver).run(duration, speed)
    last = slice(-100, None)
    return {
        "vx": float(out.x[last, VX].mean()),
        "vy": float(out.x[last, VY].mean()),
        "r": float(out.x[last, YAW_RATE].mean()),
        "delta": float(out.x[last, STEER].mean()),
        "ay": float((out.dx[last, VY] + out.x[last, YAW_RATE] * out.x[last, VX]).mean()),
        "roll": float(ROLL_SIGN * out.x[last, ROLL].mean()),
    }


def steady_state_test(vehicle: int = 2, speed: float = 20.0, steer: float = 0.01,
                      duration: float = 6.0) -> dict[str, float]:
    """Drive constant-steer circles at +steer and -steer and measure what a test engineer would.

    Half the difference of the two runs removes the tyres' straight-running offsets (ply steer
    and conicity terms p_hy1, p_vy1 of the Pacejka data give beta ~ 0.06 deg when driving
    straight). Returns the measured yaw rate, sideslip, lateral acceleration and roll, the linear
    single-track predictions, the effective axle cornering stiffnesses C_f = F_yf / alpha_f,
    C_r = F_yr / alpha_r (F_yf = m a_y l_r / L, F_yr = m a_y l_f / L,
    alpha_f = delta - (v_y + l_f r) / v_x, alpha_r = -(v_y - l_r r) / v_x) and the roll stiffness
    of the static roll model phi = m h a_y / (K - m g h) (h = H_ROLL_AXIS).
    """
    d = derived(vehicle)
    left = _circle(vehicle, speed, steer, duration)
    right = _circle(vehicle, speed, -steer, duration)
    half = {k: 0.5 * (left[k] - right[k]) for k in ("vy", "r", "delta", "ay", "roll")}
    vx = 0.5 * (left["vx"] + right["vx"])
    wheelbase = d["LF"] + d["LR"]
    m = d["MASS"]
    alpha_f = half["delta"] - (half["vy"] + d["LF"] * half["r"]) / vx
    alpha_r = -(half["vy"] - d["LR"] * half["r"]) / vx
    h = d["H_ROLL_AXIS"]
    r_lin, beta_lin = single_track_steady_state(vehicle, vx, half["delta"])
    return {
        "speed": vx, "steer": half["delta"], "yaw_rate": half["r"],
        "beta": math.atan2(half["vy"], vx), "ay": half["ay"], "roll": half["roll"],
        "yaw_rate_linear": r_lin, "beta_linear": beta_lin,
        "cornering_stiffness_f": m * half["ay"] * d["LR"] / wheelbase / alpha_f,
        "cornering_stiffness_r": m * half["ay"] * d["LF"] / wheelbase / alpha_r,
        "roll_stiffness": m * h * half["ay"] / half["roll"] + m * G * h,
    }


def describe(vehicle: int = 2) -> str:
    """A human-readable table of :func:`derived` (for the profile and the report)."""
    lines = [f"# vehicle parameter set {vehicle} as measured (SI)"]
    for key, value in derived(vehicle).items():
        lines.append(f"{key.lower()} = {value:.6g}")
    lines.append(f"# understeer gradient K_us = {understeer_gradient(vehicle):.5f} rad/(m/s^2)")
    lines.append(f"# = {math.degrees(understeer_gradient(vehicle)) * G:.3f} deg/g")
    return "\n".join(lines)
