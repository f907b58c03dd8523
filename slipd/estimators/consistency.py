"""The consistency monitor: whether a method's estimate can be vouched for, and how far.

Input supervision (``supervision.supervise``) checks that the inputs are fresh, the method has
settled and the values fit the frame; it cannot see an estimate that has drifted. This monitor
compares every method, every tick, with two independent witnesses that fail in different
ways (DESIGN.md, "What VALID means"):

* the **kinematic witness**, x_K = [vx_K, vy_K]: the kinematic model (Selmanaj et al. 2017
  eq. 1, vx' = ax + r vy, vy' = ay - r vx, the IMU moved to the CoG in the plane) integrated
  from the method's own estimate and pulled back to it with the time constant T
  (``KIN_TIME_CONSTANT``), each channel with the method's other velocity in its cross term::

      vx_K' = ax + r vy - (vx_K - vx) / T,    vy_K' = ay - r vx - (vy_K - vy) / T

  In steady state vy_K - vy = T ((ay - r vx) - vy'): the method's lateral dynamics against
  the accelerometer's over the last ~T seconds. It parts from the method when the method's vy
  moves in a way the IMU does not show (a tyre model saturating in the wrong place, a reset,
  a jump) or when vx departs from the integral of ax (every wheel locked or spinning: the
  wheel-based speed is then wrong and so is beta). An ay bias b of the IMU (offset, road bank,
  the roll's g sin(phi) in a body-frame sensor) moves it by b T: the budget of that error,
  ``AY_BIAS`` + ``AY_BIAS_PER_AY`` |ay|, sets its scale. Blind to slow drift by construction.
* the **dynamic witness**: a dynamic single-track filter on the same inputs, ``d_ekf``
  (Righetti-Lenzo's D-EKF, nonlinear tanh tyre; for ``d_ekf`` itself the linear
  ``linear_kf``). Free of integration drift, it disagrees with a kinematic method that has
  integrated a bias for seconds. Its own error is the tyre data's: the rear slip angle that
  carries the measured ay, alpha_r (from the witness's tyre model inverted at the rear axle's
  force m a |ay| / l), times the relative uncertainty of the cornering stiffness
  (``C_REL_UNCERTAINTY``) and of the peak friction (``MU_REL_UNCERTAINTY``) through the slip
  angle's sensitivity to them at the utilisation x = |ay| / (mu g): for eq. 7's tanh tyre
  alpha = (mu Fz / C) atanh(x), d ln(alpha) / d ln(C) = -1 and d ln(alpha) / d ln(mu) =
  1 - x / ((1 - x^2) atanh(x)); the linear witness has no mu and underestimates alpha by
  atanh(x) / x - 1 there. So sigma_D = alpha_r (C_REL_UNCERTAINTY + the friction or the
  linear term) + ``WITNESS_FLOOR``. On a road well below the profile's friction the witness
  does not know it is wrong: a correct kinematic estimate then loses VALID (availability,
  never honesty, pays), and a dynamic method wrong with it is left to the kinematic witness.
  The witness keeps the paper's friction (``d_ekf:slip_friction=0``) although the default
  d_ekf reads it from the wheels' slip: measured with the friction-aware d_ekf as witness, it
  lagged seed 0's second snow-drift onset by 4-6 deg as pseudo_fusion did, agreed with it,
  and 20-30 % of pseudo_fusion's VALID ticks on that drive were more than 5 deg off under six
  of the mismatch cases (hybrid_friction_nocls up to 7.7 %, the ensemble 13 % on seed 1's);
  with the paper's witness, none. A witness is for failing estimates; one that is wrong
  differently from them fails more of them.
  A witness that has stopped explaining the measurements vouches for less: its own
  innovation test (below, on the witness's Out.NIS against the level it keeps on this car,
  kept on every tick the witness runs whatever the method does) gives the ratio r_W, and
  in the calibrated sigma its error scale is sigma_D sqrt(max(1, r_W)) (covariance matching:
  innovations r_W times their level, an error scale sqrt(r_W) times its own;
  ``WITNESS_INNOVATION_TEST``). The disagreement is still scored against sigma_D (which of the
  two is wrong is not known, so a failing witness may not fail a method less). Found on
  manoeuvres no block of benchmarks.accuracy had (a sine steer on mu 0.5 at 22 m/s, beta
  to -12 deg): every model-based method underestimated the slide by 7-12 deg together with
  the witness, agreed with it, and hybrid_friction, pseudo_fusion, kinematic_heuristic and
  the ensemble sent 20-43 % of their VALID ticks there more than 5 deg off; the witness's
  innovations were 30-90 x its level meanwhile. With the scaling: none on any drive of those
  manoeuvres on vehicles 1-3; on every block of benchmarks.accuracy VALID > 5 deg unchanged,
  VALID > 2 deg down (hybrid_friction 0.11 -> 0.00 % on seed 0, the ensemble 0.06 -> 0.00),
  2-sigma coverage 99.9-100 %, at 0.4-0.9 points of VALID share on the simulator and 2.5 on the
  real run (the methods but d_ekf), 7-20 on the regression test's short manoeuvres (10-19 s,
  the level learnt in their first seconds of straight driving). Not kept: clearing VALID
  outright above 10 x the level (the short manoeuvres lost 10-19 points), the root of the
  ratio over 10 (the slide stayed VALID 8-12 deg off), the scaled sigma_D also in the score
  (VALID > 5 deg 0.00 -> 0.03 % with vibration: a failing witness then failed less).
  Beyond ``NIS_RATIO_FAIL`` (where a filter's own VALID is cleared: plainly not tracking)
  the witness vouches for nothing, whatever |ay| (``Flag.WITNESS``), until it has been back
  within ``NIS_RATIO_WARN`` for ``RECOVERY_TIME``: on an icy sine steer (mu 0.35) the car kept
  sliding 6-7 deg after the wheel was straight, the witness's ratio fell to 15-20 with its
  beta at 0.9 deg, and its scale at the lower |ay| let hybrid_friction_nocls and
  pseudo_fusion's DBE and WBE through VALID 6 deg off (24-33 % of their VALID ticks on that
  drive); with the hold, none. It costs another ~2.5 points of VALID share on the regression
  test's short manoeuvres and 0.5 on the limits block.
  Not for the linear witness (d_ekf's, ``default_params``):
  a linear tyre's innovations grow with the utilisation on any road, a model error its sigma_D
  already carries (atanh(x) / x - 1); with it d_ekf was VALID on 80 % of the real run, not 97.

* the **innovation test** of a method with a Kalman filter (its ``Out.NIS``: the normalised
  innovation squared per measurement, averaged over ~1 s; Bar-Shalom et al. 2001 Sec. 5.4.2),
  against the level the filter keeps on this car: the geometric mean of NIS over the last
  ``NIS_LEVEL_TIME_CONSTANT`` seconds (an arithmetic mean of ln NIS until that much has been
  seen), each tick clipped so that the level rises at most ``NIS_LEVEL_CLIP_RATIO``-fold per
  time constant (a failure that lasts, 15 s of a drift on snow against a dry-road tyre, must
  not become the level: without the clip it did within seconds and 13.5 % of dk_ekf's VALID
  ticks there were > 5 deg off). The clip holds from the first tick: a drive that began with
  a few seconds of history (the simulator's 26 s snow drift, the daemon just started) clipped
  at the ratio itself raised the level a hundredfold in 8 s of drift, the test passed again and
  12.6 % of dk_ekf's VALID ticks on that drive with a steering offset were more than 5 deg off
  (2.1 % with vibration); with the rate bound, none. Its price is availability where the car's
  level really changes early in a drive (mu_jump, 48 s of friction steps dry <-> 0.3 every
  7 s: linear_kf VALID on 62-71 % of its ticks instead of 98 %, all within 2 deg; d_ekf on 76
  % instead of 92 %, its VALID ticks more than 2 deg off 6.0 % -> 2.1 %).
  A fresh state's level is not learnt from nothing: it starts at ``NIS_LEVEL_PRIOR``, a
  consistent filter's NIS per measurement (1), worth ``NIS_LEVEL_PRIOR_TIME`` seconds of
  history, and rises from there at the clipped rate (10-fold per time constant). Learnt from
  the first ticks instead (the test silent until 2 s had been seen), a drive that began in a
  manoeuvre taught the level the manoeuvre: on logs replayed from 2, 5 or 9 s into a drive
  (the suite's, the limits block's, a combined case's; a researcher's snippet, a daemon
  started mid-slide) the dynamic witness's innovations were 100-450 while its level on the
  car is ~2, its level became 130-260, and 0.04-0.74 % of every method's VALID ticks were
  more than 5 deg off (per snippet up to 100 %: linear_kf 349 of 349 on an icy sine steer,
  d_ekf 80 of 129 on a wet one); from the prior, 0.00 % for every method but d_ekf (0.01 %).
  The price is the time a car whose level is far above 1 takes to teach it: the real run's
  ~24 (an INS's noise, above) takes ~40 s, in which the witness vouches for less and d_ekf's
  own test says DEGRADED; its VALID share 2.7 points lower for the methods the dynamic
  witness judges, d_ekf's unchanged, and linear_kf's (its NIS there ~2700: a linear tyre on
  a race car) 12 points lower.
  Not against the chi-square bound itself: with the paper's measurement noise (R of
  Righetti-Lenzo eq. 28) the NIS of d_ekf sits at 2-4 per measurement on the simulator and at
  ~24 on the real run (an INS's noise and vibration, not a model failure: its beta error there
  is within 2 deg on 99 % of the VALID ticks), so an absolute bound would call every real car
  inconsistent. A model that stops explaining the measurements (tyres beyond the profile's
  friction, a spin, a j-turn's transient) lifts the NIS one to two orders of magnitude above
  the car's level for as long as it lasts. Measured (d_ekf on the short drives of both seeds,
  the mismatch cases and variants, NIS against each block's own level, offline): taking out
  the ticks above 10x its level leaves 0.01 % of the VALID ticks more than 2 deg off instead
  of 0.3-1.5 %, at 4-5 % of the VALID ticks; above 100x, 0.1-0.6 % at 1-2 %. On the real run
  the ratio stays below 3. Hence DEGRADED from ``NIS_RATIO_WARN`` (10x) and VALID cleared
  only from ``NIS_RATIO_FAIL`` (100x), where the filter is plainly not tracking: the suite's
  availability (VALID on >= 90 % of its ticks) does not allow the lower bound.

Decision (per tick, after supervision): a disagreement of more than ``N_SIGMA_FAIL`` of its
scale (either witness, or the speed beyond ``SPEED_TOLERANCE`` + ``SPEED_TOLERANCE_REL`` vx,
or the innovation test beyond ``NIS_RATIO_FAIL`` x its level) clears VALID and sets DEGRADED,
and keeps VALID off until the estimate has been consistent (below ``N_SIGMA_WARN`` and
``NIS_RATIO_WARN``) for ``RECOVERY_TIME``; one above ``N_SIGMA_WARN`` (or the innovation test
above ``NIS_RATIO_WARN``) sets DEGRADED only.
After a failure the kinematic witness stops following the method it failed (for at most
``FREE_RUN_TIME``, then it starts again from the method): a method whose wheel speeds all read
0 at speed (locked wheels) would otherwise pull the witness down to its own wrong speed within
T. The speed is checked even when the method says the car has stopped (below ``MIN_SPEED``),
the beta checks only above.

Calibrated sigma (the frame's SIGMA_BETA): the method's own sigma together with what the
witnesses say about its error, sigma^2 = sigma_m^2 + ``SIGMA_FLOOR``^2 + sigma_D^2 +
(d_D / 2)^2 + (d_K / 2)^2 (d_D, d_K the two disagreements in beta): a disagreement d means at
least one of the two is d off, so 2 sigma >= d keeps the method's error covered when the
witness is right, and the model-parameter term sigma_D covers the error both dynamic models
share. ``sigma2_coverage`` in eval measures whether it holds. VALID also needs this sigma
within ``VALID_MAX_SIGMA`` (2.5 deg: a VALID frame promises its error within 5 deg, which a
2-sigma bound above that cannot): where the witnesses cannot vouch closely (the dynamic
witness at a high utilisation with guessed tyre data, a large disagreement neither side of
which is known to be right) the frame is DEGRADED, not VALID. Measured before it was added:
pseudo_fusion_wbe on the real run (wheel speeds derived there from the INS speed, so its
beta has nothing to go on) was VALID on 17 % of the ticks and more than 5 deg off on 4.1 % of
those, all of them with a calibrated sigma above 2 deg; d_ekf loses 0.4-1 % of its VALID
ticks to the bound.

The monitor's state is its own float64 vector (``LAYOUT``); ``LAST_FLAGS`` holds the tick's
``Flag`` bits, which the daemon counts.
"""

from __future__ import annotations

import enum
import math

import numpy as np

from slipd.channels import (
    ST_DEGRADED,
    ST_NOT_CONVERGED,
    ST_RESET,
    ST_UNAVAILABLE,
    ST_VALID,
    VALID,
    G,
    In,
    Out,
    Veh,
)
from slipd.estimators.common.filters import derivative_filter, lowpass
from slipd.estimators.common.kinematics import translate_to_cog_planar
from slipd.estimators.common.layout import build_layout
from slipd.estimators.common.params import build_params
from slipd.numba_cache import nb

PARAMS, DEFAULTS = build_params(
    "consistency",
    # the kinematic witness
    ("KIN_TIME_CONSTANT", 1.0),  # s, pull of the kinematic witness back to the method
    ("AY_BIAS", 0.3),  # m/s^2, 1-sigma of an unmodelled ay bias (offset after learning,
    #                    road bank up to ~2 deg)
    ("AY_BIAS_PER_AY", 0.03),  # -, and its share of |ay| (g sin(roll) of 1.5-3 deg/g, scale)
    ("AX_BIAS", 0.5),  # m/s^2, 1-sigma of an unmodelled ax bias (grade up to 5 %, pitch)
    ("SPEED_TOLERANCE", 1.0),  # m/s, |vx_K - vx| beyond it (and beyond the ax budget) fails
    ("SPEED_TOLERANCE_REL", 0.05),  # -, plus this share of vx (tyre slip of the wheels)
    # the dynamic witness (linear_kf)
    ("C_REL_UNCERTAINTY", 0.3),  # -, cornering stiffness known to 30 % (issue 15's mismatch)
    ("MU_REL_UNCERTAINTY", 0.2),  # -, peak friction of a dry road known to 20 %
    ("WITNESS_LINEAR", 0.0),  # 1: the witness is the linear model (no friction, no tanh)
    ("WITNESS_FLOOR", math.radians(0.2)),  # rad, the witness's error floor (sensor offsets)
    ("MAX_UTILISATION", 0.98),  # -, atanh(x)/x is taken at most here
    # decision
    ("N_SIGMA_FAIL", 3.0),  # disagreement / scale beyond which VALID is cleared
    ("N_SIGMA_WARN", 2.0),  # beyond which DEGRADED is set
    ("RECOVERY_TIME", 0.5),  # s below N_SIGMA_WARN before VALID may return
    ("FREE_RUN_TIME", 5.0),  # s the witness runs unanchored after a failure, at most
    ("SIGMA_FLOOR", math.radians(0.1)),  # rad, floor of the calibrated sigma
    ("VALID_MAX_SIGMA", math.radians(2.5)),  # rad, calibrated sigma beyond which VALID is
    #                    cleared: VALID promises |error| < 5 deg, i.e. 2 sigma within it
    ("AY_LOWPASS_TIME_CONSTANT", 0.08),  # s, |ay| of the budgets and the utilisation (2 Hz)
    ("MIN_SPEED", 3.0),  # m/s, below it beta is undefined: nothing is checked
    ("YAW_ACC_CUTOFF_HZ", 10.0),  # Hz, derivative filter of the CoG translation
    # the innovation test (methods with a Kalman filter: Out.NIS)
    ("NIS_LEVEL_TIME_CONSTANT", 30.0),  # s, memory of the filter's own NIS level on this car
    ("NIS_LEVEL_PRIOR", 1.0),  # the level a fresh state starts from: a consistent filter's
    #                            NIS per measurement (Bar-Shalom et al. 2001 Sec. 5.4.2)
    ("NIS_LEVEL_PRIOR_TIME", 2.0),  # s of history the prior is worth
    ("NIS_RATIO_WARN", 10.0),  # NIS / level beyond which DEGRADED is set
    ("NIS_RATIO_FAIL", 100.0),  # and beyond which VALID is cleared
    ("NIS_LEVEL_CLIP_RATIO", 10.0),  # the level rises at most this factor per time constant
    ("WITNESS_INNOVATION_TEST", 1.0),  # 1: the witness's own innovation test: sigma_D x sqrt(its
    #                    ratio) in the calibrated sigma, and nothing vouched for beyond
    #                    NIS_RATIO_FAIL until RECOVERY_TIME within NIS_RATIO_WARN (0 for the
    #                    linear witness: default_params)
)  # fmt: skip


#: The dynamic witness: the method whose raw output the monitor checks every other method
#: against (slipd.pipeline runs it beside each method; inside the ensemble it is the d_ekf
#: member), and the witness of that method itself (of every method of its module). The paper's
#: D-EKF at the profile's friction, not the default d_ekf that reads the friction from wheel
#: slip: that one lags a snow drift's onset as the kinematic methods do, agreed with them, and
#: let pseudo_fusion's frames through 4-6 deg off (module docstring).
WITNESS = "d_ekf:slip_friction=0"
WITNESS_OF_WITNESS = "linear_kf"


@enum.unique
class Flag(enum.IntEnum):
    """Bits of LAST_FLAGS: what the monitor found this tick."""

    CHECKED = 1  # the monitor ran (method converged, moving)
    WARN = 2  # a disagreement beyond N_SIGMA_WARN: DEGRADED
    FAIL = 4  # beyond N_SIGMA_FAIL (or recovering from it): VALID cleared
    SPEED = 8  # vx departs from the integral of ax
    KINEMATIC = 16  # the kinematic witness disagrees
    DYNAMIC = 32  # the dynamic witness disagrees
    INNOVATION = 64  # the method's innovation test is beyond NIS_RATIO_WARN x its level
    IMPRECISE = 128  # the calibrated sigma is beyond VALID_MAX_SIGMA (FAIL set with it)
    WITNESS = 256  # the dynamic witness is not tracking (its own innovation test beyond
    #                NIS_RATIO_FAIL, or recovering from it): it vouches for nothing (FAIL set)


# plain ints for the kernels (numba cannot convert an IntEnum member)
_CHECKED, _WARN, _FAIL = int(Flag.CHECKED), int(Flag.WARN), int(Flag.FAIL)
_SPEED, _KINEMATIC, _DYNAMIC = int(Flag.SPEED), int(Flag.KINEMATIC), int(Flag.DYNAMIC)
_INNOVATION, _IMPRECISE, _WITNESS = int(Flag.INNOVATION), int(Flag.IMPRECISE), int(Flag.WITNESS)

LAYOUT = build_layout(
    "consistency",
    "KIN_VX",  # m/s, kinematic witness
    "KIN_VY",  # m/s
    "ANCHORED",  # 1 once the witness follows the method (0: re-anchor at the next check)
    "AY_LP",  # m/s^2, low-passed CoG ay
    "D_YAW_RATE",  # derivative filter memory (CoG translation)
    "RECOVERY",  # s the estimate still has to stay consistent before VALID may return
    "FREE_RUN",  # s left of running the kinematic witness unanchored (after a failure)
    "LAST_FLAGS",  # Flag bits of the last tick
    "KIN_SCORE",  # the last disagreements, in units of their scale (diagnostics)
    "DYN_SCORE",
    "SPEED_ERROR",  # m/s, vx_K - vx
    "LOG_NIS_SUM",  # the innovation test's level: forgotten sum of ln NIS ...
    "LOG_NIS_WEIGHT",  # ... and of the weights (level = exp(sum / weight))
    "NIS_RATIO",  # the last NIS / level (diagnostics)
    "WITNESS_LOG_NIS_SUM",  # the same level of the dynamic witness's own NIS ...
    "WITNESS_LOG_NIS_WEIGHT",
    "WITNESS_NIS_RATIO",  # ... and its last ratio (diagnostics)
    "WITNESS_RECOVERY",  # s the witness still has to stay within NIS_RATIO_WARN to vouch again
)
S = LAYOUT.S
#: what the daemon keeps across restarts (slipd.pipeline's persistent_slots): the innovation
#: levels on this car, which a fresh state learns from the prior at most tenfold per time
#: constant (the real run's ~24: ~40 s)
PERSISTENT = ("LOG_NIS_SUM", "LOG_NIS_WEIGHT", "WITNESS_LOG_NIS_SUM", "WITNESS_LOG_NIS_WEIGHT")
# the innovation test's level: two consecutive slots (sum, weight) per filter it watches
_METHOD_NIS_LEVEL = int(S.LOG_NIS_SUM)
_WITNESS_NIS_LEVEL = int(S.WITNESS_LOG_NIS_SUM)
for _level in (_METHOD_NIS_LEVEL, _WITNESS_NIS_LEVEL):
    assert LAYOUT.element_names[_level + 1].endswith("LOG_NIS_WEIGHT")
_NOT_RUNNING = ST_NOT_CONVERGED | ST_RESET | ST_UNAVAILABLE


def new_state() -> np.ndarray:
    state = np.zeros(LAYOUT.size, dtype=np.float64)
    state[S.AY_LP] = np.nan
    state[S.D_YAW_RATE] = np.nan
    return state


@nb.njit(cache=True, inline="always")
def _usable(u, ch):
    return u[VALID + ch] > 0.5 and math.isfinite(u[ch])


@nb.njit(cache=True, inline="always")
def witness_sigma(ay_abs, params, vehicle):
    """sigma_D of the dynamic witness at |ay| (module docstring), rad."""
    lf = vehicle[Veh.LF]
    wheelbase = lf + vehicle[Veh.LR]
    mu_fz_rear = vehicle[Veh.MU_NOMINAL] * vehicle[Veh.MASS] * G * lf / wheelbase
    stiffness = vehicle[Veh.CORNERING_STIFFNESS_R]
    x = ay_abs / (vehicle[Veh.MU_NOMINAL] * G)  # utilisation of either axle (static loads)
    x_max = params[PARAMS.MAX_UTILISATION]
    if x > x_max:
        x = x_max
    alpha_linear = x * mu_fz_rear / stiffness  # the rear force m a |ay| / l over C_r
    if x < 1e-6:
        return params[PARAMS.WITNESS_FLOOR]
    ratio = math.atanh(x) / x  # the tanh tyre's slip angle over the linear one's
    if params[PARAMS.WITNESS_LINEAR] > 0.5:
        alpha, model = alpha_linear, ratio - 1.0
    else:
        alpha = alpha_linear * ratio
        model = params[PARAMS.MU_REL_UNCERTAINTY] * abs(
            1.0 - x / ((1.0 - x * x) * math.atanh(x)))
    return alpha * (params[PARAMS.C_REL_UNCERTAINTY] + model) + params[PARAMS.WITNESS_FLOOR]


@nb.njit(cache=True, inline="always")
def _log_nis_level(state, level):
    """ln of the level kept from slot ``level`` on (LOG_NIS_SUM, LOG_NIS_WEIGHT):
    the forgotten sum bias-corrected by its weight (a mean of what was seen so far while less
    than a time constant has been)."""
    return state[level] / state[level + 1]


@nb.njit(cache=True, inline="always")
def innovation_ratio(state, nis, params, dt, level=_METHOD_NIS_LEVEL):
    """The innovation test: ``nis`` (a filter's Out.NIS) over the level this filter keeps on
    this car (module docstring), after taking it into the level kept from slot ``level`` on
    (the method's: LOG_NIS_SUM; the dynamic witness's: WITNESS_LOG_NIS_SUM); 0 without a
    finite, positive NIS. The level starts at the consistent filter's NIS_LEVEL_PRIOR, worth
    NIS_LEVEL_PRIOR_TIME seconds of history."""
    if not (math.isfinite(nis) and nis > 0.0):
        return 0.0
    log_sum, weight = level, level + 1
    gain = min(1.0, dt / params[PARAMS.NIS_LEVEL_TIME_CONSTANT])
    if state[weight] <= 0.0:
        # a fresh level (a new state, a reset): the prior, weighted as the history it stands
        # for (the weight that many seconds of ticks would have)
        prior_weight = 1.0 - (1.0 - gain) ** (params[PARAMS.NIS_LEVEL_PRIOR_TIME] / dt)
        state[weight] = prior_weight
        state[log_sum] = prior_weight * math.log(params[PARAMS.NIS_LEVEL_PRIOR])
    # a tick far above the level is the anomaly the test is for, not the car's level: it
    # raises the level by at most what a tick at the clip ratio raises a level of a whole time
    # constant's memory (a factor CLIP_RATIO per time constant, from the first tick on), so
    # that neither a long inconsistency (a 15 s drift on snow) nor a drive that begins in one
    # (a log cut mid-manoeuvre, a daemon started in a slide) becomes the level before the test
    # has seen it. The clip is scaled by the weight because the bias-corrected mean of a short
    # memory moves by 1 / weight more per tick: unscaled, 4 s of history let a drift raise the
    # level 100-fold in 8 s (module docstring)
    log_nis = min(math.log(nis), _log_nis_level(state, level) + state[weight]
                  * math.log(params[PARAMS.NIS_LEVEL_CLIP_RATIO]))
    state[log_sum] += gain * (log_nis - state[log_sum])
    state[weight] += gain * (1.0 - state[weight])
    return nis / math.exp(_log_nis_level(state, level))


@nb.njit(cache=True, _nrt=False)
def monitor(state, u, out, witness, params, vehicle, dt):
    """Check ``out`` (the supervised outputs of one tick) against the witnesses; clear VALID
    and set DEGRADED as the module docstring says, write the calibrated SIGMA_BETA. ``witness``
    is the dynamic witness's output of the same tick (NaN: none). Allocates nothing."""
    status = int(out[Out.STATUS])
    vx = out[Out.VX]
    vy = out[Out.VY]
    beta = out[Out.BETA]
    sigma_m = out[Out.SIGMA_BETA]
    yaw_rate, yaw_ok = u[In.YAW_RATE], _usable(u, In.YAW_RATE)
    ax_imu, ax_ok = u[In.AX], _usable(u, In.AX)
    ay_imu, ay_ok = u[In.AY], _usable(u, In.AY)
    imu_ok = yaw_ok and ax_ok and ay_ok
    yaw_acc = derivative_filter(state, S.D_YAW_RATE, yaw_rate if yaw_ok else 0.0, dt,
                                params[PARAMS.YAW_ACC_CUTOFF_HZ])  # fmt: skip
    ax, ay = translate_to_cog_planar(ax_imu, ay_imu, yaw_rate, yaw_acc, vehicle[Veh.IMU_X],
                                     vehicle[Veh.IMU_Y])  # fmt: skip
    ay_lp = lowpass(state, S.AY_LP, ay if ay_ok else 0.0, dt,
                    params[PARAMS.AY_LOWPASS_TIME_CONSTANT])  # fmt: skip
    ay_abs = abs(ay_lp)
    # the dynamic witness, when it runs; its innovation level is kept on every tick it runs
    # and moves, whatever the method does (a method that settles late must not learn a level
    # from the manoeuvre it is then asked to pass)
    w_status = witness[Out.STATUS]
    witness_running = math.isfinite(w_status) and (int(w_status) & _NOT_RUNNING) == 0 and (
        math.isfinite(witness[Out.BETA]))
    witness_ratio = 0.0
    if witness_running and witness[Out.VX] >= params[PARAMS.MIN_SPEED]:
        witness_ratio = innovation_ratio(state, witness[Out.NIS], params, dt,
                                         _WITNESS_NIS_LEVEL)
    state[S.WITNESS_NIS_RATIO] = witness_ratio
    # a witness plainly not tracking (beyond NIS_RATIO_FAIL, where a filter's own VALID is
    # cleared) vouches for nothing until it has been within NIS_RATIO_WARN for RECOVERY_TIME
    if params[PARAMS.WITNESS_INNOVATION_TEST] > 0.5:
        if witness_ratio > params[PARAMS.NIS_RATIO_FAIL]:
            state[S.WITNESS_RECOVERY] = params[PARAMS.RECOVERY_TIME]
        elif witness_ratio <= params[PARAMS.NIS_RATIO_WARN] and state[S.WITNESS_RECOVERY] > 0.0:
            state[S.WITNESS_RECOVERY] = max(0.0, state[S.WITNESS_RECOVERY] - dt)
    running = (status & _NOT_RUNNING) == 0 and math.isfinite(vx) and math.isfinite(vy) and (
        math.isfinite(beta))
    if not (running and imu_ok):
        # nothing to check: the method is not estimating (supervision says so) or the IMU is
        # missing (INPUT_TIMEOUT); the witness re-anchors at the next check
        state[S.ANCHORED] = 0.0
        state[S.FREE_RUN] = 0.0
        state[S.LAST_FLAGS] = 0.0
        if math.isfinite(sigma_m):
            out[Out.SIGMA_BETA] = math.sqrt(sigma_m * sigma_m
                                            + params[PARAMS.SIGMA_FLOOR] ** 2)
        return
    if state[S.ANCHORED] < 0.5:
        state[S.KIN_VX] = vx
        state[S.KIN_VY] = vy
        state[S.ANCHORED] = 1.0
    # the kinematic witness, one forward-Euler step pulled towards the method (not while it
    # runs free after a failure); each channel's cross term takes the method's other velocity,
    # so that vx_K checks vx against ax and vy_K checks vy against ay. With the witness's own
    # (vx' = ax + r vy_K, vy' = ay - r vx_K) an error of one channel rotated into the other at
    # the yaw rate while it ran free: a lateral failure grew into a speed error of several m/s
    # within seconds, a speed failure the method did not have
    t_kin = params[PARAMS.KIN_TIME_CONSTANT]
    pull = 0.0 if state[S.FREE_RUN] > 0.0 else 1.0 / t_kin
    kvx = state[S.KIN_VX]
    kvy = state[S.KIN_VY]
    state[S.KIN_VX] = kvx + (ax + yaw_rate * vy - (kvx - vx) * pull) * dt
    state[S.KIN_VY] = kvy + (ay - yaw_rate * vx - (kvy - vy) * pull) * dt
    flags = _CHECKED
    # speed: beyond the wheel-slip tolerance and what the ax budget integrates in T
    speed_error = state[S.KIN_VX] - vx
    speed_scale = (params[PARAMS.SPEED_TOLERANCE] + params[PARAMS.SPEED_TOLERANCE_REL] * vx
                   + params[PARAMS.AX_BIAS] * t_kin)
    speed_score = abs(speed_error) / speed_scale
    moving = vx >= params[PARAMS.MIN_SPEED]
    # lateral: the witness's vy against the method's, in beta, over its bias budget
    kin_beta_error = 0.0
    kin_score = 0.0
    if moving:
        kin_beta_error = (state[S.KIN_VY] - vy) / vx
        kin_scale = (params[PARAMS.AY_BIAS] + params[PARAMS.AY_BIAS_PER_AY] * ay_abs) * (
            t_kin / vx)
        kin_score = abs(kin_beta_error) / kin_scale
    # the dynamic witness's disagreement
    sigma_d = witness_sigma(ay_abs, params, vehicle)
    dyn_error = 0.0
    dyn_score = 0.0
    vouch_d = sigma_d  # the witness's error scale where it vouches (the calibrated sigma)
    if moving and witness_running:
        # a witness whose own model has stopped explaining the measurements (its innovations
        # far above the level it keeps on this car: tyres beyond the friction it assumes, a
        # spin) vouches for less: its error scale grows as the root of its innovation ratio.
        # A disagreement with it still counts at its scale at the level: which of the two is
        # wrong is not known, so it may not fail a method less than before
        if params[PARAMS.WITNESS_INNOVATION_TEST] > 0.5 and witness_ratio > 1.0:
            vouch_d = sigma_d * math.sqrt(witness_ratio)
        dyn_error = beta - witness[Out.BETA]
        dyn_score = abs(dyn_error) / sigma_d
    n_fail = params[PARAMS.N_SIGMA_FAIL]
    n_warn = params[PARAMS.N_SIGMA_WARN]
    worst = max(kin_score, dyn_score)
    nis_ratio = innovation_ratio(state, out[Out.NIS], params, dt) if moving else 0.0
    if nis_ratio > params[PARAMS.NIS_RATIO_WARN]:
        flags |= _INNOVATION
        flags |= _FAIL if nis_ratio > params[PARAMS.NIS_RATIO_FAIL] else _WARN
    if speed_score > 1.0:
        flags |= _SPEED | _FAIL
    if kin_score > n_warn:
        flags |= _KINEMATIC
    if dyn_score > n_warn:
        flags |= _DYNAMIC
    if worst > n_fail:
        flags |= _FAIL
    elif worst > n_warn:
        flags |= _WARN
    # a failure holds until the estimate has been consistent for RECOVERY_TIME; the witness
    # runs free from the first failure until the method agrees with it again
    consistent = worst <= n_warn and speed_score <= 0.5 and not flags & _INNOVATION
    if flags & _FAIL:
        state[S.RECOVERY] = params[PARAMS.RECOVERY_TIME]
        if state[S.FREE_RUN] <= 0.0:
            state[S.FREE_RUN] = params[PARAMS.FREE_RUN_TIME]
    elif consistent and state[S.RECOVERY] > 0.0:
        state[S.RECOVERY] = max(0.0, state[S.RECOVERY] - dt)
    if consistent:
        state[S.FREE_RUN] = 0.0
    elif state[S.FREE_RUN] > 0.0:
        state[S.FREE_RUN] = max(0.0, state[S.FREE_RUN] - dt)
        if state[S.FREE_RUN] <= 0.0:
            # the free run is over (FREE_RUN_TIME at most): the witness starts again from the
            # method. Pulled back from where it ran to instead, it never caught up with a
            # method whose failure had passed, which then stayed failed for the rest of the
            # drive (the failure re-armed the free run every FREE_RUN_TIME)
            state[S.ANCHORED] = 0.0
    if state[S.RECOVERY] > 0.0:
        flags |= _FAIL
    # after the method's own recovery and free run: the witness's failure is not the method's
    if moving and state[S.WITNESS_RECOVERY] > 0.0:
        flags |= _WITNESS | _FAIL
    # calibrated sigma (an unknown one, zero's, stays unknown); VALID only while it is
    # within what VALID promises (no hold: it is a bound, not a verdict on the method)
    if math.isfinite(sigma_m):
        sigma2 = params[PARAMS.SIGMA_FLOOR] ** 2 + vouch_d * vouch_d + sigma_m * sigma_m
        sigma2 += 0.25 * (dyn_error * dyn_error + kin_beta_error * kin_beta_error)
        out[Out.SIGMA_BETA] = math.sqrt(sigma2)
        if sigma2 > params[PARAMS.VALID_MAX_SIGMA] ** 2:
            flags |= _IMPRECISE | _FAIL
    if flags & _FAIL:
        status = (status & ~ST_VALID) | ST_DEGRADED
    elif flags & _WARN:
        status |= ST_DEGRADED
    out[Out.STATUS] = float(status)
    state[S.LAST_FLAGS] = float(flags)
    state[S.KIN_SCORE] = kin_score
    state[S.DYN_SCORE] = dyn_score
    state[S.SPEED_ERROR] = speed_error
    state[S.NIS_RATIO] = nis_ratio


@nb.njit(cache=True, nogil=True, _nrt=False)
def monitor_ticks(state, U, OUT, WITNESS, params, vehicle, tick_dt):
    """``monitor`` over a recording: ``tick_dt[k]`` is the time of tick k's steps (dt times
    its catch-up steps)."""
    for k in range(U.shape[0]):
        monitor(state, U[k], OUT[k], WITNESS[k], params, vehicle, tick_dt[k])


def default_params(witness_linear: bool = False) -> np.ndarray:
    """The params vector; ``witness_linear``: the witness is ``linear_kf`` (for d_ekf)."""
    params = np.empty(len(PARAMS), dtype=np.float64)
    for field in PARAMS:
        params[field] = DEFAULTS[field.name.lower()]
    params[PARAMS.WITNESS_LINEAR] = 1.0 if witness_linear else 0.0
    if witness_linear:
        # a linear tyre's innovations grow with the utilisation on any road: that model error
        # is already in its sigma_D (atanh(x) / x - 1), not news of a model that stopped
        # explaining the measurements (measured: d_ekf VALID on 80 % of the real run with it)
        params[PARAMS.WITNESS_INNOVATION_TEST] = 0.0
    return params


__all__ = ["DEFAULTS", "Flag", "LAYOUT", "PARAMS", "default_params", "monitor",
           "innovation_ratio", "monitor_ticks", "new_state", "witness_sigma", "WITNESS",
           "WITNESS_OF_WITNESS"]
