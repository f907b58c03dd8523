"""Tests of the Carnier, Corno, Savaresi 2023 hybrid observer: hybrid_friction (full, Fig. 1)
and hybrid_friction_nocls (the adaptive observer alone).

- the kernels agree with plain numpy/python re-implementations: V_x tilde (eq. 3-4, IQR),
  one observer step (eq. 2, 7-15) to 1e-12, the eq. 10 references, the classifier maps;
- the classifier's switching logic and re-initialisation (Sec. 3);
- robustness: invalid and non-finite inputs, non-finite state (RESET), start-up;
- zero allocations per step (numba NRT statistics in a subprocess);
- the paper's claims on the simulator's mu-jump scenario (Fig. 13/16, Table 2): the
  re-initialisation lowers the beta error after a jump, beta p99 <= 1.5 deg and below the
  observer without classifier, most jumps detected; no NaN over the suite (slow).
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import pytest
from nrt import allocations, sine_drive_inputs

from slipd.channels import (
    N_OUT,
    ST_INPUT_TIMEOUT,
    ST_NOT_CONVERGED,
    ST_RESET,
    U_LEN,
    U_TIME,
    VALID,
    WHEEL_SPEEDS,
    G,
    In,
    Out,
    Veh,
)
from slipd.estimators import registry
from slipd.estimators.carnier2023 import classifier, hybrid_friction, observer
from slipd.estimators.carnier2023.hybrid_friction import PARAMS
from slipd.estimators.carnier2023.observer import S, Tyre
from slipd.profile import load_profile

DT = 0.01
DEG = math.pi / 180.0
REPO = Path(__file__).resolve().parents[1]
#: Beta errors are scored where the true speed exceeds 20 km/h (the issue's evaluation rule).
MIN_EVAL_SPEED = 20.0 / 3.6


def load_vehicle() -> np.ndarray:
    from slipd.profile import load_profile

    return np.asarray(load_profile("default").vehicle, dtype=np.float64)


@pytest.fixture(scope="module")
def vehicle() -> np.ndarray:
    return load_vehicle()


@pytest.fixture(scope="module")
def params() -> np.ndarray:
    return registry.make_params(hybrid_friction)


def run(name: str, U: np.ndarray, vehicle: np.ndarray, overrides: dict | None = None):
    method = registry.load(name, overrides)
    state = method.init(vehicle)
    OUT = np.zeros((U.shape[0], N_OUT))
    method.run_ticks(state, U, method.params, vehicle, DT, OUT)
    return OUT, state


def cornering_ticks(n: int, speed: float = 15.0, ay: float = 3.0, seed: int = 0) -> np.ndarray:
    """Sensor inputs of a steady left turn at ``speed`` with noise (a plausible, not exact, car)."""
    rng = np.random.default_rng(seed)
    U = np.zeros((n, U_LEN))
    r = ay / speed
    U[:, In.AY] = ay + rng.normal(0.0, 0.05, n)
    U[:, In.AX] = rng.normal(0.0, 0.05, n)
    U[:, In.YAW_RATE] = r + rng.normal(0.0, 0.002, n)
    U[:, In.STEER] = 2.579 * r / speed + 0.01
    U[:, In.WHEEL_SPEED_FL] = speed - 0.69 * r
    U[:, In.WHEEL_SPEED_FR] = speed + 0.69 * r
    U[:, In.WHEEL_SPEED_RL] = speed - 0.68 * r
    U[:, In.WHEEL_SPEED_RR] = speed + 0.68 * r
    U[:, U_TIME] = np.arange(n) * DT
    for ch in (In.AX, In.AY, In.YAW_RATE, In.STEER, In.ROLL_RATE, In.PITCH_RATE, *WHEEL_SPEEDS):
        U[:, VALID + ch] = 1.0
    return U


# ---------------------------------------------------------------------------------------------
# the registry and the parameters
# ---------------------------------------------------------------------------------------------


def test_registry_loads_both_variants_on_one_kernel():
    full = registry.load("hybrid_friction")
    bare = registry.load("hybrid_friction_nocls")
    assert full.module is hybrid_friction and bare.module is hybrid_friction
    assert dict(bare.spec.overrides) == {"classifier_enabled": 0.0}
    assert full.params[PARAMS.CLASSIFIER_ENABLED] == 1.0
    assert bare.params[PARAMS.CLASSIFIER_ENABLED] == 0.0
    # Table 1
    assert full.params[PARAMS.KX_MIN] == 0.2 and full.params[PARAMS.KX_MAX] == 5.0
    assert full.params[PARAMS.KY_MIN] == 0.3 and full.params[PARAMS.KY_MAX] == 10.0
    assert full.params[PARAMS.K_MU] == 0.007 and full.params[PARAMS.K_MU_BAR] == 0.08
    assert full.params[PARAMS.GAMMA_MINUS] == pytest.approx(35.0 * DEG)


def test_reference_tyre_reproduces_both_reference_characteristics(vehicle, params):
    """eq. 8-10 with the derived coefficients: at mu_high the axle curve has the profile's
    cornering stiffness and peak MU_NOMINAL x Fz; at mu_low the same stiffness and mu_low x Fz."""
    state = hybrid_friction.init(params, vehicle)
    mu_high, mu_low = vehicle[Veh.MU_NOMINAL], params[PARAMS.MU_LOW]
    wheelbase = vehicle[Veh.LF] + vehicle[Veh.LR]
    fz_front = vehicle[Veh.MASS] * G * vehicle[Veh.LR] / wheelbase
    coef = state[S.TYRE : S.TYRE + 4]
    for mu in (mu_high, mu_low):
        c_r, k = observer.tyre_coefficients(mu, *coef, 1.0)
        assert observer.tyre_force(1e-5, c_r, k)[1] == pytest.approx(
            vehicle[Veh.CORNERING_STIFFNESS_F], rel=1e-6
        )
        assert observer.tyre_force(1.0, c_r, k)[0] == pytest.approx(mu * fz_front, rel=1e-6)
    # the saturation moves to smaller slip at low friction (Fig. 8)
    assert (
        observer.tyre_coefficients(mu_low, *coef, 1.0)[1]
        > 3 * observer.tyre_coefficients(mu_high, *coef, 1.0)[1]
    )


def test_explicit_tyre_coefficients_override_the_derived_ones(vehicle):
    params = registry.make_params(hybrid_friction, {"tyre_a_kf": -44.0, "tyre_b_kf": 57.0})
    state = hybrid_friction.init(params, vehicle)
    tyre = S.TYRE
    assert state[tyre + Tyre.A_KF] == -44.0 and state[tyre + Tyre.B_KF] == 57.0
    assert state[tyre + Tyre.B_CF] == pytest.approx(vehicle[Veh.CORNERING_STIFFNESS_F])


# ---------------------------------------------------------------------------------------------
# Sec. 2.1: V_x tilde (eq. 3-4) against a numpy reference
# ---------------------------------------------------------------------------------------------


def ref_vx_tilde(speeds, ok, ax, ay, vehicle, gamma=35.0 * DEG, min_accel=0.5):
    """eq. 3-4 and Fig. 6 with numpy: weights by the load-transfer cone, np.percentile for
    the quartiles, min (ax >= 0) or max (ax < 0) of the survivors."""
    lf, lr = vehicle[Veh.LF], vehicle[Veh.LR]
    pos = np.array([[lf, vehicle[Veh.TRACK_F] / 2], [lf, -vehicle[Veh.TRACK_F] / 2],
                    [-lr, vehicle[Veh.TRACK_R] / 2], [-lr, -vehicle[Veh.TRACK_R] / 2]])  # fmt: skip
    speeds, ok = np.asarray(speeds, float), np.asarray(ok, bool)
    k = np.ones(4)
    if math.hypot(ax, ay) >= min_accel:
        direction = math.atan2(-ay, -ax)
        off = np.angle(np.exp(1j * (np.arctan2(pos[:, 1], pos[:, 0]) - direction)))
        k = (np.abs(off) <= gamma).astype(float)
    k = np.where(ok, k, 0.0)
    if k.sum() == 0:
        k = ok.astype(float)
    v_wm = np.sum(k * speeds) / k.sum()
    values = np.append(speeds[ok], v_wm)
    q1, q3 = np.percentile(values, [25, 75])
    keep = values[(values >= q1 - 1.5 * (q3 - q1)) & (values <= q3 + 1.5 * (q3 - q1))]
    return keep.min() if ax >= 0 else keep.max()


VX_CASES = [
    # speeds, ok, ax, ay
    ((20.0, 20.1, 19.9, 20.05), (1, 1, 1, 1), 0.1, 0.0),  # cruising, all agree
    ((20.0, 20.1, 23.5, 23.9), (1, 1, 1, 1), 3.0, 0.0),  # rear wheels spinning (traction)
    ((15.0, 14.9, 16.2, 16.3), (1, 1, 1, 1), -6.0, 0.0),  # braking: front locking up
    ((20.0, 20.1, 26.0, 20.0), (1, 1, 1, 1), 0.4, 0.3),  # one wheel an outlier
    ((18.0, 18.3, 18.1, 18.2), (1, 1, 1, 1), -0.2, 6.0),  # cornering: no wheel in the cone
    ((18.0, 0.0, 18.1, 18.4), (1, 0, 1, 1), -1.5, 1.0),  # one wheel invalid
    ((12.0, 0.0, 0.0, 0.0), (1, 0, 0, 0), 1.0, 0.0),  # a single wheel
]


@pytest.mark.parametrize("case", VX_CASES)
def test_vx_tilde_matches_numpy_reference(case, vehicle):
    speeds, ok, ax, ay = case
    state = observer.new_state(1.0, True)
    vx, n_valid = observer.vx_from_wheels_lt(
        state, *speeds, *(bool(o) for o in ok), ax, ay, vehicle, 35.0 * DEG, 35.0 * DEG, 0.5, 1.5
    )
    assert n_valid == sum(ok)
    assert vx == pytest.approx(ref_vx_tilde(speeds, ok, ax, ay, vehicle), abs=1e-12)


def test_vx_tilde_discards_a_spinning_wheel_and_weights_the_loaded_axle(vehicle):
    state = observer.new_state(1.0, True)
    # braking (Fig. 5): the load moves to the front, only the front wheels have k_w = 1
    assert observer.load_transfer_weight(1.2, 0.7, math.atan2(0.0, 6.0), 35 * DEG, 35 * DEG) == 1.0
    assert observer.load_transfer_weight(-1.4, 0.7, math.atan2(0.0, 6.0), 35 * DEG, 35 * DEG) == 0.0
    # one rear wheel spinning 5 m/s fast while accelerating: eq. 4 takes the slowest survivor
    vx, _ = observer.vx_from_wheels_lt(state, 20.0, 20.02, 25.0, 20.01, True, True, True, True,
                                      2.0, 0.0, vehicle, 35 * DEG, 35 * DEG, 0.5, 1.5)  # fmt: skip
    assert vx == pytest.approx(20.0)
    assert observer.vx_from_wheels_lt(state, 0.0, 0.0, 0.0, 0.0, False, False, False, False,
                                     0.0, 0.0, vehicle, 0.6, 0.6, 0.5, 1.5)[1] == 0  # fmt: skip


def test_kx_is_scheduled_on_the_wheel_acceleration_mismatch():
    """eq. 5-6: wheels whose rates disagree with A_x (slip) switch K_x to K_x,min."""
    kx, delta = observer.kx_gain(1.0, 1.1, 0.9, 1.0, True, True, True, True, 1.0, 8.0, 0.2, 5.0)
    assert kx == 5.0 and delta == pytest.approx(0.2)
    kx, delta = observer.kx_gain(1.0, 1.0, 9.0, 8.0, True, True, True, True, 1.0, 8.0, 0.2, 5.0)
    assert kx == 0.2 and delta == pytest.approx(15.0)


# ---------------------------------------------------------------------------------------------
# Sec. 2.2-2.3: one observer step against a plain python reference (eq. 2, 7-15)
# ---------------------------------------------------------------------------------------------


def ref_lateral(vx, vy, r, steer, mu, coef, veh):
    """eq. 7-10 written out: slip angles (eq. 9, ISO), tanh axle forces, A_y hat."""
    lf, lr, m = veh[Veh.LF], veh[Veh.LR], veh[Veh.MASS]
    alpha = np.array([steer - math.atan((vy + lf * r) / vx), -math.atan((vy - lr * r) / vx)])
    c_r = np.array([coef[0] * mu + coef[1], coef[4] * mu + coef[5]])
    k = np.maximum(np.array([coef[2] * mu + coef[3], coef[6] * mu + coef[7]]), 1.0)
    force = c_r / k * np.tanh(k * alpha)
    return (force[0] * math.cos(steer) + force[1]) / m


def ref_observer_step(x, u, p, veh, coef, dt, noise=math.nan, straight_time=0.0):
    """eq. 2 by forward Euler with the gains of eq. 11-15 as documented in observer; ``noise``:
    the switches' noise state, (vx beta_dot)^2 averaged on straights (NaN: none yet), and
    ``straight_time`` the s of straight running before this tick."""
    vx, vy, mu, mu_bar, lowpass = x
    ax, ay, r, steer, vx_tilde, kx = u
    mu_nom = veh[Veh.MU_NOMINAL]
    ay_hat = ref_lateral(vx, vy, r, steer, mu, coef, veh)
    ay_star = ref_lateral(vx, vy, r, steer, mu_nom, coef, veh)
    vy_ref = veh[Veh.LR] * r
    xi = (ay_star - ref_lateral(vx, vy_ref, r, steer, mu_nom, coef, veh)) / (vy - vy_ref)
    xi_lin = -((coef[0] + coef[4]) * mu_nom + coef[1] + coef[5]) / (veh[Veh.MASS] * vx)
    xi = min(xi, p["xi_floor"] * xi_lin)  # both negative: |xi| >= xi_floor |xi_lin|
    beta_dot = (ay - r * vx) / vx
    lowpass += dt / p["beta_rate_highpass"] * (beta_dot - lowpass)
    beta_dot_hp = beta_dot - lowpass
    threshold, mu_threshold = p["beta_rate_threshold"], p["beta_rate_mu_threshold"]
    if p["switch_noise_sigmas"] > 0:  # thresholds above the noise measured on straights
        straight_time = straight_time + dt if abs(r) < p["yaw_rate_mu_threshold"] else 0.0
        if straight_time >= 2.0:
            sample = (beta_dot_hp * vx) ** 2
            noise = sample if math.isnan(noise) else (
                noise + dt / p["switch_noise_time_constant"] * (sample - noise))
        if not math.isnan(noise):
            floor = p["switch_noise_sigmas"] * math.sqrt(noise) / vx
            threshold, mu_threshold = max(threshold, floor), max(mu_threshold, floor)
    ky = p["ky_min"] if abs(beta_dot_hp) >= threshold else p["ky_max"]
    gain_y = xi / xi_lin**2 * ky
    excited = abs(beta_dot_hp) >= mu_threshold and abs(r) >= p["yaw_rate_mu_threshold"]
    mu_dot = p["k_mu"] * ay_star * (ay - ay_hat) if excited else p["k_mu_bar"] * (mu_bar - mu)
    return (
        vx + (ax + r * vy + kx * (vx_tilde - vx)) * dt,
        vy + (ay - r * vx + gain_y * (ay - ay_hat)) * dt,
        mu + mu_dot * dt,
    )


def test_lateral_model_matches_python_reference(vehicle, params):
    state = hybrid_friction.init(params, vehicle)
    coef = state[S.TYRE : S.TYRE + 8]
    for vx, vy, r, steer, mu in ((16.0, 0.1, 0.39, 0.064, 1.0), (9.0, -1.0, 0.5, 0.13, 0.4)):
        ay_hat, slope, _, _ = observer.lateral_model(vx, vy, r, steer, mu, state, vehicle, 1.0)
        assert ay_hat == pytest.approx(ref_lateral(vx, vy, r, steer, mu, coef, vehicle), rel=1e-12)
        eps = 1e-6
        numeric = (
            ref_lateral(vx, vy + eps, r, steer, mu, coef, vehicle)
            - ref_lateral(vx, vy - eps, r, steer, mu, coef, vehicle)
        ) / (2 * eps)
        assert slope == pytest.approx(numeric, rel=1e-5, abs=1e-6)


STEP_CASES = [
    # vx, vy, mu, ax, ay, r, steer, vx_tilde, beta_dot lowpass
    (16.0, 0.1, 1.0, 0.1, 6.2, 0.39, 0.064, 16.1, 0.0),  # dry corner, steady
    (16.0, -0.4, 0.3, -0.2, 2.6, 0.16, 0.085, 15.9, 0.0),  # low grip, front saturated
    (22.0, 0.3, 0.8, 0.0, -4.0, -0.35, -0.05, 22.0, -0.2),  # transient: k_y,min, mu adapts
    (9.7, -2.0, 0.6, 0.5, 4.9, 0.51, 0.133, 9.8, 0.0),  # large estimate error, saturated
]


#: the switches' noise state: none yet, and 0.3 m/s^2 (a raw IMU after the 5 Hz low-pass)
NOISE_STATES = [math.nan, 0.3**2]


@pytest.mark.parametrize("straight_time", [0.0, 5.0])
@pytest.mark.parametrize("noise", NOISE_STATES)
@pytest.mark.parametrize("sigmas", [0.0, 3.0])
@pytest.mark.parametrize("xi_floor", [0.0, 0.5])
@pytest.mark.parametrize("case", STEP_CASES + [(20.0, 0.1, 1.0, 0.0, 0.2, 0.01, 0.0, 20.0, 0.0)])
def test_observer_step_matches_python_reference(case, xi_floor, sigmas, noise, straight_time,
                                                vehicle, params):
    vx, vy, mu, ax, ay, r, steer, vx_tilde, lowpass = case
    p = {**hybrid_friction.DEFAULTS, "ky_min": 0.3, "ky_max": 10.0, "xi_floor": xi_floor,
         "switch_noise_sigmas": sigmas}
    state = hybrid_friction.init(params, vehicle)
    state[[S.VX, S.VY, S.MU, S.MU_DEFAULT, S.BETA_RATE_LOWPASS]] = vx, vy, mu, 1.0, lowpass
    state[S.AY_UTILISATION] = 0.0  # floor inactive for this comparison
    state[S.SWITCH_NOISE] = noise
    state[S.STRAIGHT_TIME] = straight_time
    coef = state[S.TYRE : S.TYRE + 8].copy()
    observer.observer_step(
        state, ax, ay, True, r, steer, vx_tilde, True, 5.0, vehicle, DT,
        p["ky_min"], p["ky_max"], p["beta_rate_threshold"], p["k_mu"], p["k_mu_bar"],
        p["beta_rate_mu_threshold"], p["yaw_rate_mu_threshold"], 0.0, 10.0, 1.0, 1.0,
        p["beta_rate_highpass"], 0.0, p["xi_floor"], p["switch_noise_sigmas"],
        p["switch_noise_time_constant"],
    )  # fmt: skip
    expected = ref_observer_step(
        (vx, vy, mu, 1.0, lowpass), (ax, ay, r, steer, vx_tilde, 5.0), p, vehicle, coef, DT,
        noise, straight_time,
    )
    np.testing.assert_allclose(state[[S.VX, S.VY, S.MU]], expected, rtol=1e-12, atol=1e-12)


def test_switches_do_not_trip_on_accelerometer_noise(vehicle, params):
    """A raw IMU's ay noise (0.3 m/s^2 after the vibration low-pass) makes eq. 13's beta_dot
    ~0.9 deg/s at 20 m/s, above Table 1's 0.3 deg/s: with the paper's threshold eq. 12 picks
    k_y,min on most ticks of a steady corner (the observer then integrates open loop: the
    endurance drive's -40 deg runaway). With the threshold at 3x the noise measured on the
    straight before, almost never; a real sideslip rate of a few deg/s still trips it."""

    def drive(sigmas):
        rng = np.random.default_rng(5)
        state = hybrid_friction.init(params, vehicle)
        state[[S.VX, S.VY, S.MU, S.MU_DEFAULT]] = 20.0, 0.0, vehicle[Veh.MU_NOMINAL], 1.0
        tripped = []
        for k in range(4000):  # 20 s straight, then 20 s of a steady corner (ay = r vx)
            r = 0.0 if k < 2000 else 0.1
            beta_dot = observer.observer_step(
                state, 0.0, r * 20.0 + rng.normal(0.0, 0.3), True, r, 0.0, 20.0, True, 5.0,
                vehicle, DT, 0.3, 10.0, 0.3 * DEG, 0.007, 0.08, 7 * DEG, 5 * DEG, 0.1, 1.3,
                1.0, 1.0, 0.3, 0.0, 0.5, sigmas, 10.0)[0]  # fmt: skip
            threshold = 0.3 * DEG
            if sigmas > 0:
                threshold = max(threshold, sigmas * math.sqrt(state[S.SWITCH_NOISE]) / 20.0)
            tripped.append(abs(beta_dot) >= threshold)
        return np.array(tripped[2500:]).mean(), threshold

    paper, _ = drive(0.0)
    aware, threshold = drive(3.0)
    assert paper > 0.5
    assert aware < 0.02
    assert math.radians(0.3) < threshold < math.radians(3.0)  # 3 x 0.3 / 20 rad/s = 2.6 deg/s


def test_vy_error_decays_at_k_y_in_the_linear_range(vehicle, params):
    """Delta = 1 / xi_lin^2 makes k_y the decay rate (1/s) of the vy error in the linear tyre
    range: a 0.05 m/s error on a straight shrinks by about k_y,max dt per tick."""
    state = hybrid_friction.init(params, vehicle)
    state[[S.VX, S.VY, S.MU, S.MU_DEFAULT]] = 20.0, 0.05, vehicle[Veh.MU_NOMINAL], 1.0
    state[S.BETA_RATE_LOWPASS] = 0.0
    ay_true = 0.0  # straight, vy = 0: the true lateral acceleration is 0
    observer.observer_step(state, 0.0, ay_true, True, 0.0, 0.0, 20.0, True, 5.0, vehicle, DT,
                          0.3, 10.0, 0.3 * DEG, 0.007, 0.08, 7 * DEG, 5 * DEG, 0.1, 1.3, 1.0,
                          1.0, 0.3, 0.0, 0.5, 0.0, 10.0)  # fmt: skip
    assert state[S.VY] == pytest.approx(0.05 * (1.0 - 10.0 * DT), rel=0.02)


# ---------------------------------------------------------------------------------------------
# Sec. 3: the classifier
# ---------------------------------------------------------------------------------------------


def test_burckhardt_dry_asphalt_peaks_near_1_17():
    slip = np.linspace(0.0, 1.0, 1001)
    mu = [classifier.burckhardt(s, *classifier.BURCKHARDT_DRY_ASPHALT) for s in slip]
    assert max(mu) == pytest.approx(1.17, abs=0.01)
    assert slip[int(np.argmax(mu))] == pytest.approx(0.17, abs=0.02)


@pytest.mark.parametrize(
    "slip, mu, expected",
    [
        (5 * DEG, 0.26, -1),  # on the low curve at large slip: low grip
        (5 * DEG, 0.65, 1),  # far above what the low surface can give: high grip
        (5 * DEG, 0.05, 0),  # far below the low curve: a bad slip estimate, white
        (5 * DEG, 0.42, 0),  # in between: white
        (1 * DEG, 0.26, 0),  # below the slip limit: white
        (1 * DEG, 0.5, 1),  # beyond the low surface's peak at any slip: high
        (-1 * DEG, 0.5, 1),  # even with the slip's sign wrong
        (5 * DEG, -0.26, 0),  # force against the slip: a transient, white
        (-5 * DEG, -0.65, 1),  # the map is symmetric
    ],
)
def test_map_regions(slip, mu, expected):
    high, low = 1.0, 0.3
    assert classifier.map_region(slip, mu, high, low, 0.3, 3 * DEG, 0.15, 0.15, 0.15) == expected


def test_map_is_white_where_the_curves_merge():
    assert classifier.map_region(0.2, 0.2, 0.25, 0.2, 0.3, 0.05, 0.15, 0.15, 0.15) == 0


def test_burckhardt_peak_is_the_curve_maximum():
    for c in (classifier.BURCKHARDT_DRY_ASPHALT, classifier.BURCKHARDT_SNOW):
        slip = np.linspace(0.0, 1.0, 100001)
        curve = c[0] * (1 - np.exp(-c[1] * slip)) - c[2] * slip
        assert classifier.burckhardt_peak(*c) == pytest.approx(curve.max(), rel=1e-8)


def test_classifier_switches_after_persistence_and_reinitialises_mu():
    state = observer.new_state(1.05, True)
    for _ in range(4):
        assert not classifier.classifier_update(state, False, True, 5.0, 1.05, 0.3)
    assert classifier.classifier_update(state, False, True, 5.0, 1.05, 0.3)
    assert state[S.CLASS_HIGH] == 0.0 and state[S.MU] == 0.3 and state[S.MU_DEFAULT] == 0.3
    # a high point interrupts a low streak; conflicting points count for neither
    assert not classifier.classifier_update(state, True, True, 1.0, 1.05, 0.3)
    assert classifier.classifier_update(state, True, False, 1.0, 1.05, 0.3)
    assert state[S.MU] == 1.05 and state[S.DETECTIONS] == 2.0


def test_wheel_loads_sum_to_the_weight_and_shift_with_acceleration(vehicle):
    loads = np.array(classifier.wheel_loads(0.0, 0.0, vehicle))
    assert loads.sum() == pytest.approx(vehicle[Veh.MASS] * G)
    braking = np.array(classifier.wheel_loads(-5.0, 0.0, vehicle))
    assert braking[:2].sum() > loads[:2].sum() and braking.sum() == pytest.approx(loads.sum())
    left_turn = np.array(classifier.wheel_loads(0.0, 5.0, vehicle))  # ISO: loads the right wheels
    assert left_turn[1] > left_turn[0] and left_turn[3] > left_turn[2]


# ---------------------------------------------------------------------------------------------
# robustness and the contract
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["hybrid_friction", "hybrid_friction_nocls"])
def test_outputs_complete_and_classes(name, vehicle):
    OUT, _ = run(name, cornering_ticks(500), vehicle)
    assert np.all(np.isfinite(OUT[:, [Out.BETA, Out.BETA_RATE, Out.VX, Out.VY, Out.MU,
                                      Out.SIGMA_BETA, Out.ROLL, Out.STATUS]]))  # fmt: skip
    assert np.all(OUT[:100, Out.STATUS].astype(int) & ST_NOT_CONVERGED)
    assert np.all(OUT[-100:, Out.STATUS] == 0.0)
    expected_class = 3.0 if name == "hybrid_friction" else 0.0  # dry start, no low evidence
    assert np.all(OUT[:, Out.FRICTION_CLASS] == expected_class)


def test_invalid_and_non_finite_inputs_never_give_nan(vehicle):
    n = 3000
    U = cornering_ticks(n)
    U[:, [In.DRIVE_TORQUE_RL, In.DRIVE_TORQUE_RR]] = 200.0
    U[:, VALID + In.DRIVE_TORQUE_RL : VALID + In.BRAKE_TORQUE_RR + 1] = 1.0
    rng = np.random.default_rng(3)
    dropped = rng.random((n, 8)) < 0.2
    for col, ch in enumerate((In.AX, In.AY, In.YAW_RATE, In.STEER, *WHEEL_SPEEDS)):
        U[dropped[:, col], VALID + ch] = 0.0
        U[dropped[:, col], ch] = np.nan  # an invalid channel may carry garbage
    U[1000:1100, VALID : VALID + 12] = 0.0  # a 1 s outage of everything
    U[1000:1100, :12] = np.inf
    U[::7, In.ROLL_RATE] = np.nan
    U[::11, In.DRIVE_TORQUE_RL] = np.nan
    OUT, state = run("hybrid_friction", U, vehicle)
    assert np.all(np.isfinite(OUT[:, [Out.BETA, Out.BETA_RATE, Out.VX, Out.VY, Out.MU,
                                      Out.SIGMA_BETA]]))  # fmt: skip
    assert np.all(np.isfinite(state[: S.DETECTIONS + 1]))
    status = OUT[:, Out.STATUS].astype(int)
    assert np.all(status[dropped.any(axis=1)] & ST_INPUT_TIMEOUT)
    assert np.all(status[1000:1100] & ST_INPUT_TIMEOUT)
    assert np.abs(OUT[:, Out.BETA]).max() < 0.2


def test_non_finite_state_resets_and_says_so(vehicle):
    U = cornering_ticks(600)
    params = registry.make_params(hybrid_friction)
    state = hybrid_friction.init(params, vehicle)
    OUT = np.zeros((600, N_OUT))
    hybrid_friction.run_ticks(state, U[:300], params, vehicle, DT, OUT[:300])
    state[S.VY] = np.nan
    hybrid_friction.run_ticks(state, U[300:], params, vehicle, DT, OUT[300:])
    status = OUT[:, Out.STATUS].astype(int)
    assert status[300] & ST_RESET and status[300] & ST_NOT_CONVERGED
    assert not np.any(status[301:] & ST_RESET)
    assert np.all(np.isfinite(OUT[300:, [Out.BETA, Out.VX, Out.VY, Out.MU]]))
    assert np.all(status[-50:] == 0)


def test_standstill_and_start_up(vehicle):
    U = np.zeros((600, U_LEN))
    for ch in (In.AX, In.AY, In.YAW_RATE, In.ROLL_RATE, In.PITCH_RATE, In.STEER, *WHEEL_SPEEDS):
        U[:, VALID + ch] = 1.0
    U[:50, VALID : VALID + 12] = 0.0  # nothing on the bus yet
    speed = np.clip((np.arange(600) - 200) * 0.05, 0.0, None)  # standing, then 5 m/s^2
    U[:, In.AX] = np.where(speed > 0, 5.0, 0.0)
    for ch in WHEEL_SPEEDS:
        U[:, ch] = speed
    OUT, _ = run("hybrid_friction", U, vehicle)
    status = OUT[:, Out.STATUS].astype(int)
    assert np.all(status[:250] & ST_NOT_CONVERGED)
    assert np.all(OUT[:250, Out.BETA] == 0.0)
    assert np.all(np.isfinite(OUT[:, [Out.BETA, Out.BETA_RATE, Out.VX, Out.VY, Out.MU]]))
    assert OUT[-1, Out.VX] == pytest.approx(speed[-1], abs=0.3)
    assert status[-1] == 0


def test_step_allocates_nothing():
    U = sine_drive_inputs(5000, 0.06, 0.3, 6.0)
    t = np.arange(len(U)) * 0.01
    U[:, In.DRIVE_TORQUE_RL] = U[:, In.DRIVE_TORQUE_RR] = 300.0
    U[:, In.WHEEL_SPEED_RL] += 2.0 * (np.sin(3 * t) > 0.9)  # slip: longitudinal map points
    U[:, VALID + In.DRIVE_TORQUE_FL : VALID + In.BRAKE_TORQUE_RR + 1] = 1.0
    counts = allocations(["hybrid_friction", "hybrid_friction_nocls"], U,
                         load_profile("default").vehicle)  # fmt: skip
    for name, (ticks_10, ticks_4980) in counts.items():
        assert ticks_4980 == ticks_10, name  # 4970 more ticks add nothing


# ---------------------------------------------------------------------------------------------
# the paper's claims on the simulator (CommonRoad multi-body plant)
# ---------------------------------------------------------------------------------------------


@functools.cache
def simulated(scenario: str, seed: int = 0) -> tuple[dict, np.ndarray]:
    from slipd.sim import simulate

    result = simulate(scenario, vehicle=2, seed=seed)
    return result.truth, result.ticks()


@functools.cache
def outputs(name: str, scenario: str, paper_switch: bool = False
            ) -> tuple[np.ndarray, dict, int]:
    """``paper_switch``: eq. 12-14's thresholds as Table 1 gives them (no noise floor)."""
    truth, U = simulated(scenario)
    method = registry.load(name, {"switch_noise_sigmas": 0.0} if paper_switch else None)
    vehicle = load_vehicle()
    state = method.init(vehicle)
    OUT = np.zeros((U.shape[0], N_OUT))
    method.run_ticks(state, U, method.params, vehicle, DT, OUT)
    return OUT, truth, min(U.shape[0], truth["t"].size)


def beta_errors_deg(name: str, scenario: str, window=None, paper_switch: bool = False
                    ) -> np.ndarray:
    """|beta error| (deg) where the true speed exceeds 20 km/h (and inside ``window``)."""
    OUT, truth, n = outputs(name, scenario, paper_switch)
    keep = np.hypot(truth["vx"][:n], truth["vy"][:n]) > MIN_EVAL_SPEED
    if window is not None:
        keep &= window[:n]
    return np.degrees(np.abs(OUT[:n, Out.BETA] - truth["beta"][:n]))[keep]


def friction_changes(truth: dict, n: int) -> list[tuple[int, int, bool]]:
    """(first tick, end tick, new side is high) of every crossing of mid-friction."""
    high = truth["mu"][:n] >= 0.6
    starts = list(np.flatnonzero(np.diff(high.astype(int)) != 0) + 1)
    ends = [*starts[1:], n]
    return [(s, e, bool(high[s])) for s, e in zip(starts, ends, strict=True)]


def test_mu_jump_beta_p99_meets_the_target_and_beats_the_bare_observer():
    """Fig. 16: the full observer's 99 % beta error is 1.5 deg, the pure adaptive observer's
    2.7 deg. Issue target: p99 <= 1.5 deg and below the observer without classifier, met with
    Table 1's switch thresholds. Measured (seed 0): full 0.77 deg (rms 0.35), without
    classifier 1.76 deg (rms 0.62). With the default noise floor on the switches
    (``observer._switch_noise``, which the real run and a vibrating IMU need) the classifier
    sees less slip in mu_jump's low-grip curves: full 2.72 deg, without 2.81 deg."""
    full = beta_errors_deg("hybrid_friction", "mu_jump", paper_switch=True)
    bare = beta_errors_deg("hybrid_friction_nocls", "mu_jump", paper_switch=True)
    p99_full, p99_bare = np.percentile(full, 99), np.percentile(bare, 99)
    assert p99_full <= 1.5, (p99_full, p99_bare)
    assert p99_full < p99_bare
    assert np.sqrt(np.mean(full**2)) < np.sqrt(np.mean(bare**2))
    default = beta_errors_deg("hybrid_friction", "mu_jump")
    default_bare = beta_errors_deg("hybrid_friction_nocls", "mu_jump")
    assert np.percentile(default, 99) <= 3.0
    assert np.percentile(default, 99) <= np.percentile(default_bare, 99)


def test_reinitialisation_lowers_the_beta_error_after_each_jump():
    """Fig. 13: after a change of friction the re-initialised mu hat is immediately close to
    the road's and the beta error in the adaptation phase drops. Scored over the 6 s after
    every jump (the scenario's jumps are 6.9 s apart). Measured (seed 0): mean |error| 0.27 deg
    with the classifier, 0.45 deg without."""
    _, truth, n = outputs("hybrid_friction", "mu_jump")
    window = np.zeros(n, dtype=bool)
    for start, _, _ in friction_changes(truth, n):
        window[start : start + 600] = True
    full = beta_errors_deg("hybrid_friction", "mu_jump", window)
    bare = beta_errors_deg("hybrid_friction_nocls", "mu_jump", window)
    assert np.mean(full) < 0.8 * np.mean(bare), (np.mean(full), np.mean(bare))


def test_classifier_detects_most_jumps_when_excited():
    """Table 2: 87 % of the changes detected, 2 % wrong, 11 % missed (no excitation); mean
    classification time 1.6-2.1 s. In the mu-jump scenario every change is followed by a
    curve within ~3 s. Measured (seed 0): 6 of 6 detected, 0 wrong switches; high -> low
    after 2.8 s (0.2-0.3 s after the car turns into the next curve), low -> high after 0.05 s
    (the car leaves the low patch at large slip: the force jumps past the low surface's peak);
    mean 1.4 s."""
    OUT, truth, n = outputs("hybrid_friction", "mu_jump")
    friction_class = OUT[:n, Out.FRICTION_CLASS]
    changes = friction_changes(truth, n)
    assert len(changes) == 6
    times, wrong = [], 0
    for start, end, high in changes:
        want = 3.0 if high else 1.0
        hits = np.flatnonzero(friction_class[start:end] == want)
        if hits.size:
            times.append(hits[0] * DT)
            wrong += int(np.any(friction_class[start + hits[0] : end] != want))
    assert len(times) >= 5  # "most": the paper's 87 % of 6 is 5.2
    assert wrong == 0
    assert np.mean(times) < 5.0, times
    # after a detection mu hat starts from the class's reference friction
    mu = OUT[:n, Out.MU]
    for start, end, high in changes:
        hits = np.flatnonzero(friction_class[start:end] == (3.0 if high else 1.0))
        if hits.size:
            assert abs(mu[start + hits[0]] - truth["mu"][start + hits[0]]) < 0.1


def test_without_classifier_mu_hat_stays_near_dry():
    """Fig. 15: the pure adaptive observer's mu is not responsive enough and almost keeps
    the dry value; it reports no friction class."""
    OUT, truth, n = outputs("hybrid_friction_nocls", "mu_jump")
    low = truth["mu"][:n] < 0.6
    assert np.mean(OUT[:n, Out.MU][low]) > 0.8
    assert np.all(OUT[:, Out.FRICTION_CLASS] == 0.0)


@pytest.mark.slow
def test_mu_jump_claims_hold_over_sensor_seeds():
    """Not an accident of one noise draw: over 6 sensor seeds (each its own offsets, drifts,
    misalignment) the classifier beats the bare observer on every seed. Measured 2026-12-05:
    full p99 2.72 / 0.74 / 0.89 / 1.29 / 2.77 / 2.88 deg, without classifier 2.81 / 2.88 /
    2.86 / 2.97 / 2.86 / 2.90 deg. With the paper's switch thresholds (switch_noise_sigmas =
    0) full 1.09 / 0.93 / 1.53 / 2.39 / 0.69 / 0.34: the switches above their noise (the
    method's docstring: real run 0.84 -> 0.59 deg, a raw IMU's endurance drive 5.94 -> 0.17)
    cost seeds 0, 4 and 5 here, where a steadier k_y follows the high-grip model into the low
    patches. The bound is the measured worst seed plus 10 %."""
    from slipd.sim import simulate

    vehicle = load_vehicle()
    p99 = {"hybrid_friction": [], "hybrid_friction_nocls": []}
    for seed in range(6):
        result = simulate("mu_jump", vehicle=2, seed=seed)
        U, truth = result.ticks(), result.truth
        n = min(U.shape[0], truth["t"].size)
        keep = np.hypot(truth["vx"][:n], truth["vy"][:n]) > MIN_EVAL_SPEED
        for name in p99:
            method = registry.load(name)
            state = method.init(vehicle)
            OUT = np.zeros((U.shape[0], N_OUT))
            method.run_ticks(state, U, method.params, vehicle, DT, OUT)
            err = np.degrees(np.abs(OUT[:n, Out.BETA] - truth["beta"][:n]))[keep]
            p99[name].append(np.percentile(err, 99))
    full, bare = np.array(p99["hybrid_friction"]), np.array(p99["hybrid_friction_nocls"])
    assert np.all(full <= 3.2), full
    assert np.all(full < bare), (full, bare)


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["handling_low_mu", "snow_drift", "j_turn", "banked_road"])
def test_no_nan_and_bounded_on_low_friction_and_banks(scenario):
    for name in ("hybrid_friction", "hybrid_friction_nocls"):
        OUT, truth, n = outputs(name, scenario)
        assert np.all(np.isfinite(OUT[:, [Out.BETA, Out.BETA_RATE, Out.VX, Out.VY, Out.MU,
                                          Out.SIGMA_BETA, Out.STATUS]]))  # fmt: skip
        assert np.all(np.abs(OUT[:, Out.BETA]) <= math.pi / 4)


def suite_scenarios() -> list[str]:
    from slipd.sim import SCENARIOS

    return [s for s in SCENARIOS if s != "endurance"]


@pytest.mark.slow
@pytest.mark.parametrize("scenario", suite_scenarios())
def test_no_nan_over_the_suite(scenario):
    from slipd.sim.plant import SimulationError

    try:
        simulated(scenario)
    except SimulationError as exc:
        pytest.skip(f"the simulator cannot run {scenario}: {exc}")
    for name in ("hybrid_friction", "hybrid_friction_nocls"):
        OUT, _, _ = outputs(name, scenario)
        values = OUT[:, [Out.BETA, Out.BETA_RATE, Out.VX, Out.VY, Out.MU, Out.SIGMA_BETA,
                         Out.ROLL, Out.FRICTION_CLASS, Out.STATUS]]  # fmt: skip
        assert np.all(np.isfinite(values)), name
