"""``ensemble``: every seed method each tick, fused by N-method linear minimum variance.

Generalises the matrix-weighted linear minimum-variance fusion of Chen et al. 2018 (Sec. 3.2,
eq. 26-39; shared/papers/chen2018-pseudo-multisensor-fusion.md) from its three pseudo-sensors to
the N = 7 member methods below, for the scalar sideslip angle.

Members (``MEMBERS``): the registry's Specs with ``ensemble=True``, in registry order
(kinematic_heuristic, dk_ekf, d_ekf, k_kf, hybrid_friction, pseudo_fusion, gnss_magnetometer).
Not members: the floors ``zero`` and ``linear_kf`` and the variants (``*_nocls``,
``pseudo_fusion_kbe/dbe/wbe``), which rerun a member's kernels. numba cannot cache a kernel
that calls functions it is handed, so ``run_members`` calls each member's step by name: a new
member is a registry flag and one line there (an import-time check says so).

Fusion (one scalar per member, beta_i with error e_i = beta_i - beta)
    eq. 27  beta_0 = sum_i w_i beta_i with sum_i w_i = 1 (unbiasedness, eq. 26)
    eq. 30  J = w' P w -> min, P_ij = E[e_i e_j]
    eq. 38  w = P^-1 1 / (1' P^-1 1),  fused variance sigma_0^2 = 1 / (1' P^-1 1)

How P is obtained online, without ground truth (slipd's choice):

* pairwise difference moments, exponentially forgotten with time constant tau
  (``time_constant``, a = dt / tau), updated on every tick both members are usable:
      D_ij <- (1 - a) D_ij + a (beta_i - beta_j)^2,   M_ij <- (1 - a) M_ij + a
  and read bias-corrected, D_ij / M_ij (M_ij is the weight the started average has collected,
  so the first samples are not shrunk towards the zero start). D_ij is a raw second moment, not
  a variance: a persistent bias between two methods counts, as it does in the RMS.
  For any error statistics D_ij = P_ii + P_jj - 2 P_ij.
* N-cornered hat (Gray & Allan 1974; the least-squares form of the three-cornered hat that
  ``pseudo_fusion`` offers as its mode 1) with a family term: the N (N - 1) / 2 moments cannot
  identify the N (N + 1) / 2 elements of P, so P is given a structure with fewer unknowns. The
  errors of members that share kernels (``FAMILY``, the Specs' family: dk_ekf, d_ekf and k_kf
  are all built from the righetti_lenzo2025 dynamic EKF and kinematic KF) are modelled as a
  common part plus an own part, all other errors as independent:
      e_i = c_f(i) + u_i,  P_ii = C_f + U_i,  P_ij = C_f (same family f),  P_ij = 0 (otherwise)
      D_ij = U_i + U_j (same family),  D_ij = U_i + C_f(i) + U_j + C_f(j) (otherwise)
  (C of a family of one is part of its U.) The unknowns theta = [U_1..U_n, C_f..] are fitted to
  the moments of the n fused members by weighted least squares,
      min_theta sum_{i<j} c_ij (a_ij' theta - D_ij)^2,   c_ij = 1 / (D_ij + sigma_floor^2)^2,
  a_ij the 0/1 row of the model above, i.e. the normal equations (sum c_ij a_ij a_ij') theta =
  sum c_ij a_ij D_ij, solved by Gaussian elimination on the diagonally scaled SPD system.
  C_f is an unknown only when its family has >= 2 fused members and >= 2 fused members are
  outside it (otherwise it is not identifiable and taken as 0); the fit needs n >= 3.
  Negative U_i or C_f are set to 0. The weights c_ij make the fit one in relative errors: a
  sample second moment has a standard deviation proportional to its value (chi-square), so
  without them the degree-squared moments of a member that is far off dominate the fit and the
  small U_i of the good members come out as differences of large numbers (on the simulator:
  negative for one good member, which then took 90 % of the weight). Without
  families, equal c_ij and n = 3 this is T_1 = (D_12 + D_13 - D_23) / 2. Why the family term
  (measured on the simulator): dk_ekf and d_ekf differ by 0.3-0.8 deg where both are 1-4 deg
  off; treated as independent they look like the two best members and out-vote the others.
  With n = 2 the split is not observable and D_12 is shared in proportion to the members' own
  sigma_beta^2; with n = 1 the member is taken as it is.
* combination with the member's own sigma_beta (its filter covariance): a filter's covariance
  knows its noise model but not its model error, so it is a lower bound on the error variance:
      P_ii = max(U_i + C_f(i), sigma_i^2) + sigma_floor^2
  ``sigma_floor`` keeps P positive definite (a zero U_i, which the fit gives when errors are
  correlated beyond the model, cannot take all the weight) and bounds the weight ratio.
* eq. 38 with this P: x = P^-1 1 (Gaussian elimination, P is SPD), w = x / (1' x). Within a
  family a negative weight is the minimum-variance answer (the worse of two correlated members
  used to cancel the common error); it is clipped, w_i = max(x_i, 0) / sum_j max(x_j, 0), so all
  weights stay in [0, 1], and the fused variance is w' P w. A member whose differences to the
  others grow (it goes bad) loses its weight within about tau.

Limitation (what the differences cannot show): an error common to members of different
families (e.g. every method that assumes the nominal friction, on snow) does not appear in
their differences, so such a group still looks more precise than it is and an isolated member
that is right looks worse; only the common part of declared families is modelled. The full P
of Chen's eq. 30 is not identifiable from difference moments alone; the structure above is the
price of a truth-free P. Where several sensor errors act at once (benchmarks.accuracy's
``combined`` block: vibration, a misaligned IMU, a steering offset, tone-wheel speeds and skew
together) every member reads the same wrong inputs and their errors correlate at 0.5-0.9; the
fit then gives the smallest P_ii to whichever member carries the most of the common error
(pseudo_fusion 0.15 deg claimed against 0.41 true on vehicle 1's endurance drive, d_ekf 0.15
against 0.10), and the fusion is 0.28 deg there against d_ekf's 0.23. Median three-cornered
hats instead of the fit did not help (benchmarks/MEASUREMENTS.md).

Low-grip roads (``low_grip_members``, slipd): that limitation is the rule, not the exception,
where the road's grip is far below the profile's. In a drift on snow the members whose beta
rests on the profile's tyre friction (dk_ekf, pseudo_fusion's DBE) or on integrating the
accelerometer through the slide with dry-road corrections (kinematic_heuristic, k_kf, whose
vy leaks to 0) agree on one wrong drift and out-vote the one that reads the road: on seed 1's
snow drift pseudo_fusion was 8-15 deg off with a sigma of 1.0-1.2 deg, the fusion 5.5 deg RMS
against d_ekf's 2.0, whose own sigma there (4.7 deg median, its tyres saturated) is honest
and so weighs little. While the d_ekf member's friction class (hybrid_friction's slip-based
classifier, reported while settled, ``d_ekf``'s ``slip_friction``) is low grip, only
``LOW_GRIP_MEMBERS`` are usable: the two that estimate the road's friction and the one whose
beta needs no tyre model. On a dry road the classifier stays high (hybrid_friction's
docstring) and nothing changes. Measured (benchmarks.accuracy, beta RMS [deg] against
``low_grip_members`` = 0, the best member in brackets): s1 0.22 against 0.48 (d_ekf 0.22),
misalignment 0.24 / 0.53 (0.24), the other cars 0.16 / 0.29 and 0.22 / 0.51 (0.15, 0.22),
vibration 0.23 / 0.25 (0.21); but s0 0.21 / 0.19 and the level frame 0.25 / 0.19
(hybrid_friction 0.21): where the majority was right on seed 0's drift (1.17 deg) the fusion
now follows d_ekf (1.78); no other drive worse by more than 5 % (j_turn 1.13 -> 0.71, seed 0).
VALID share -0.2 point, VALID
ticks more than 2 deg off unchanged, none more than 5 deg off; within 10 % of its best member
on 11 of 12 blocks, against 7 before.
The road is taken as low-grip once the class has said so for ``low_grip_time`` (1 s, as long
as a member must be usable to enter the fusion) and as not low-grip again the same way: with
five sensor errors at once (vibration, a misaligned IMU, a steering offset, tone-wheel speeds,
skew) the classifier read low grip for 0.1-0.5 s at a time on a dry double lane change, and
decided per tick each flicker took four members out and kept them out for ``entry_time`` more,
leaving the three-member fusion to the two that were 3-4 deg off (0.78 deg against d_ekf's
0.13 on that drive; 0.38 now). Measured (benchmarks.accuracy, against the decision per tick):
snow_drift better on 28 of its 31 logs (s0 1.78 -> 1.70, the level frame 2.18 -> 2.11) and
worse on two of the ``combined`` block's (2.37 -> 2.82, 1.67 -> 1.76), j_turn VALID on 80 % of
its ticks instead of 68-69 % (the members no longer leave and re-enter as the class switches;
its RMS within 0.03), mu_jump up to 0.06 deg worse at a VALID share 3 points higher; every
block the same or better by 0.01 (level frame 0.24, mismatch 0.23), VALID > 2 deg unchanged.
Debounced here rather than in the classifier (whose own persistence is 5 ticks): d_ekf's
tyre model takes a flicker's friction for as long as it lasts, the fusion keeps a member out
for ``entry_time`` after it. Now within 10 % of its best member on every block but the level
frame (1.16 x, hybrid_friction) and the ``combined`` one (1.21 x, d_ekf; the limitation above).

Usable member (else weight 0 this tick, and its moments are not updated): status without
UNAVAILABLE, INPUT_TIMEOUT, NOT_CONVERGED or RESET; none of its own required channels (its
``REQUIRED``, default ``CORE_CHANNELS``) invalid in ``u``; finite beta with |beta| < 90 deg and
finite vx; one of ``LOW_GRIP_MEMBERS`` on a low-grip road; and usable for the last
``entry_time`` seconds without a break (its moments need that long to say anything). While
no member is fused (start-up: none has been usable for ``entry_time`` yet), the members usable
this tick, else all with finite outputs, are weighted by their own sigma_beta alone,
w_i ~ 1 / (sigma_i^2 + sigma_floor^2), with NOT_CONVERGED.

The spread floor (``spread_floor``, slipd): w'Pw is the variance of the P the difference
moments allow, remembered over tau; when members that agreed part ways within a tick (a
drift's onset on snow, where each lags the slip by its own amount) the moments still remember
the agreement. The fused variance is therefore at least the members' weighted spread about
the result, sum_i w_i (beta_i - beta_0)^2, and the fusion is NOT_CONVERGED while its sigma
exceeds ``converged_sigma_beta`` (1 deg, the Righetti-Lenzo filters' rule), so supervision
does not send it VALID. Measured on seed 1's snow drift with the friction-aware d_ekf as the
pipeline's dynamic witness (which agreed with a fusion 4-5 deg behind the drift's onset; the
witness keeps the paper's friction since, ``consistency.WITNESS``): VALID ticks more than 5
deg off 13.2 % -> 1.9 % of that drive's VALID ticks, 2-sigma coverage 0.64 -> 0.86. With the
paper's witness both are 0.00 % on every block of benchmarks.accuracy and the floor moves the
VALID share by at most 0.1 point: a bound for when the witnesses share the members' error.

Outputs: beta_0 and sigma_beta = sigma_0 as above; vx = sum w_i vx_i and vy = vx tan(beta_0) (so
that beta = atan2(vy, vx) holds for the fused values); beta rate and roll the same weighted mean
(over the members with a finite value, renormalised); mu the weighted mean over the members that
estimate it (NaN when none does); friction class that of the highest-weighted member reporting
one; DEGRADED when a used member says DEGRADED. Input supervision and VALID are added by
``slipd.estimators.supervision`` as for every method.

Members' consistency monitors (off by default: ``member_monitor``, ``monitor_sigma``; on with
``overrides``, e.g. ``slipd.estimate(log, estimator="ensemble", overrides={"member_monitor": 1,
"monitor_sigma": 1})``): each member's output runs through a consistency monitor of its own
(``slipd.estimators.consistency``, the pipeline's, with the d_ekf member's raw output as the
dynamic witness; the d_ekf member keeps the kinematic witness and its innovation test). With
``member_monitor`` a member its monitor fails is not usable while another usable member passes;
with ``monitor_sigma`` a member's own variance is its monitor's calibrated sigma^2 (its own
sigma with what the witnesses say of its error). Measured (benchmarks.accuracy, both on, beta
RMS [deg] against the fusion without them): the other cars 0.23 / 0.28 against 0.31 / 0.51
(vehicle 3's snow drift: the kinematic members agree on one wrong drift and fail their
monitors), level frame 0.43 against 0.51; but s0 0.32 against 0.23, the sensor variants 0.32-
0.59 against 0.22-0.55 (steering offset 0.39 against 0.23) and VALID > 5 deg up to 0.07 %
against 0.00 %. The dynamic witness is d_ekf, so failing a member for disagreeing with it pulls
the fusion to d_ekf, right where d_ekf is the best member and wrong where a sensor error
biases d_ekf (the steering offset). Monitor verdicts from the self-consistency checks alone
(kinematic witness, speed, innovation test) were worse everywhere but the other cars (s0 0.40).
Measured again once d_ekf took the road's friction from the wheels' slip (its
``slip_friction``): both on, s0 / s1 0.25 / 0.29 against 0.19 / 0.48, the other cars 0.18 /
0.24 against 0.30 / 0.51, misalignment 0.37 against 0.53, but VALID > 5 deg up to 0.06 %
against 0.00 %. Hence off: the truth-free fusion above decides unless a user wants the
members vouched for.

Params: the fusion's own (``FUSION_PARAMS``) first, the members' monitors' params under
``monitor__<field>`` (``consistency.DEFAULTS``), then every member's params vector under
``<member>__<field>`` names (``dk_ekf__q_vy_dyn``), defaults from each member's ``DEFAULTS``, so
``overrides`` can tune a member inside the ensemble. The fusion defaults are slipd's (no paper
gives them): tau = 2 s as ``pseudo_fusion``'s ``fusion_time_constant``, entry time 1 s,
sigma_floor 0.05 deg (ten steps of the output frame's beta, below every member's accuracy).

State layout (``LAYOUT``): the fusion block (``F``: member state and params bounds, usable
streaks, weights, variances P_ii, family terms C_f, moments, member outputs, scratch), then each
member's own state vector (its layout nested under the member's name, so that the daemon keeps
the members' learnt offsets and calibrations across restarts: ``PERSISTENT``). Member state
and params bounds are written by ``init`` into the state rather than frozen into the kernel as
constants, so that a member that grows a parameter cannot leave a cached kernel reading the
wrong slots. Each member's ``step`` is called on
slices of the ensemble's state and params (views, no allocation). The compiled members are
linked into this module's cached kernel; numba would not notice a change of a member module,
which is why slipd keys its whole numba cache to a hash of its sources (slipd/__init__.py).
"""

from __future__ import annotations

import enum
import math

import numpy as np

from slipd.channels import (
    CORE_CHANNELS,
    N_IN,
    N_OUT,
    ST_DEGRADED,
    ST_INPUT_TIMEOUT,
    ST_NOT_CONVERGED,
    VALID,
    Out,
)
from slipd.estimators import consistency, registry
from slipd.estimators.carnier2023 import hybrid_friction
from slipd.estimators.chen2018 import pseudo_fusion
from slipd.estimators.common.outputs import write_outputs
from slipd.estimators.common.params import nested_fields
from slipd.estimators.ensemble.covariance import error_covariance, own_variance, update_moments
from slipd.estimators.ensemble.state import (
    _SPECS,
    EXCLUDING,
    FAMILY,
    FRICTION_MEMBER,
    FUSION_END,
    LAYOUT,
    LOW_GRIP_MASK,
    MEMBERS,
    N_MEMBERS,
    PERSISTENT,
    WITNESS_MEMBER,
    F,
    _member_monitor,
    _member_out,
    _member_params,
    _member_state,
    member_module,
)
from slipd.estimators.righetti_lenzo2025 import d_ekf, dk_ekf, k_kf
from slipd.estimators.selmanaj2017 import kinematic_heuristic
from slipd.estimators.yoon2016 import gnss_magnetometer
from slipd.numba_cache import nb


class FUSION_PARAMS(enum.IntEnum):
    TIME_CONSTANT = 0  # s, forgetting of the difference moments D_ij (slipd)
    ENTRY_TIME = 1  # s, a member is fused after this long usable without a break (slipd)
    SIGMA_FLOOR = 2  # rad, added in quadrature to every member's error sigma (slipd)
    MEMBER_MONITOR = 3  # 1: a member its consistency monitor fails is left out (slipd)
    MONITOR_SIGMA = 4  # 1: a member's own variance is its monitor's calibrated one (slipd)
    SPREAD_FLOOR = 5  # 1: the fused variance is at least the members' weighted spread (slipd)
    CONVERGED_SIGMA_BETA = 6  # rad, NOT_CONVERGED while the fused sigma exceeds it; 0 = none
    LOW_GRIP_MEMBERS = 7  # 1: on a low-grip road only LOW_GRIP_MEMBERS are fused (slipd)
    LOW_GRIP_TIME = 8  # s, the friction class must hold this long to change the road (slipd)


FUSION_DEFAULTS = {
    "time_constant": 2.0,
    "entry_time": 1.0,
    "sigma_floor": math.radians(0.05),
    "member_monitor": 0.0,
    "monitor_sigma": 0.0,
    "spread_floor": 1.0,
    # the Righetti-Lenzo filters' (d_ekf's): one sense of "settled"
    "converged_sigma_beta": d_ekf.DEFAULTS["converged_sigma_beta"],
    "low_grip_members": 1.0,
    # as long as a member must be usable to enter: a road is not judged on less evidence
    # than a member
    "low_grip_time": 1.0,
}


def _member_fields() -> list[tuple[str, float]]:
    """(PARAMS name, default) of every member param, prefixed with the member's name."""
    fields = []
    for spec in _SPECS:
        module = member_module(spec.name)
        values = registry.make_params(module, spec.overrides)
        fields += nested_fields(spec.name, module.PARAMS,
                                {field.name.lower(): values[int(field)] for field in module.PARAMS})
    return fields


_FIELDS = _member_fields()
_N_FUSION = len(FUSION_PARAMS)
#: the members' consistency monitors' params (slipd.estimators.consistency), after the fusion's
_MONITOR_FIELDS = nested_fields("monitor", consistency.PARAMS, consistency.DEFAULTS)
_MONITOR0 = _N_FUSION
_N_MONITOR = len(_MONITOR_FIELDS)
_N_HEAD = _N_FUSION + _N_MONITOR  # the first member's params start here
PARAMS = enum.IntEnum(
    "PARAMS",
    [(f.name, int(f)) for f in FUSION_PARAMS]
    + [(name, _MONITOR0 + k) for k, (name, _) in enumerate(_MONITOR_FIELDS)]
    + [(name, _N_HEAD + k) for k, (name, _) in enumerate(_FIELDS)],
)
PARAMS.__doc__ = ("Fusion params, the members' monitors' as MONITOR__<FIELD>, then each member's "
                  "params as <MEMBER>__<FIELD>.")
DEFAULTS = {**FUSION_DEFAULTS, **{name.lower(): value for name, value in _MONITOR_FIELDS},
            **{name.lower(): value for name, value in _FIELDS}}


def member_params(params: np.ndarray, name: str) -> np.ndarray:
    """The slice of the ensemble's params vector that is member ``name``'s params vector."""
    start = _N_HEAD
    for member in MEMBERS:
        length = len(member_module(member).PARAMS)
        if member == name:
            return params[start : start + length]
        start += length
    raise KeyError(name)


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """The fusion block (bounds, empty moments) followed by each member's ``init`` state."""
    member_states = []
    params_bounds = [_N_HEAD]
    for name in MEMBERS:
        module = member_module(name)
        own = member_params(params, name)
        member_states.append(np.asarray(module.init(own.copy(), vehicle), dtype=np.float64))
        params_bounds.append(params_bounds[-1] + len(own))
    if params_bounds[-1] != len(params):
        raise ValueError(f"ensemble: params vector has {len(params)} elements, "
                         f"the members need {params_bounds[-1]}")
    state_bounds = [FUSION_END]
    for member_state in member_states:
        state_bounds.append(state_bounds[-1] + len(member_state))
    if state_bounds[-1] != LAYOUT.size:
        raise ValueError(f"ensemble: the members' states add up to {state_bounds[-1]} slots, "
                         f"the layout has {LAYOUT.size}")
    state = np.zeros(LAYOUT.size, dtype=np.float64)
    state[F.STATE_BOUNDS : F.STATE_BOUNDS + N_MEMBERS + 1] = state_bounds
    state[F.PARAMS_BOUNDS : F.PARAMS_BOUNDS + N_MEMBERS + 1] = params_bounds
    state[F.VARIANCE : F.VARIANCE + N_MEMBERS] = np.nan
    for m in range(N_MEMBERS):
        _member_monitor(state, m)[:] = consistency.new_state()
    state[F.CONSISTENT : F.CONSISTENT + N_MEMBERS] = 1.0
    state[F.CALIBRATED_SIGMA : F.CALIBRATED_SIGMA + N_MEMBERS] = np.nan
    for m, name in enumerate(MEMBERS):
        for channel in getattr(member_module(name), "REQUIRED", CORE_CHANNELS):
            state[F.REQUIRED + m * N_IN + int(channel)] = 1.0
        state[state_bounds[m] : state_bounds[m + 1]] = member_states[m]
    return state



@nb.njit(cache=True, inline="always")
def _member(state, u, params, vehicle, dt, m):
    """The arguments of member m's ``step``: views of its state, params and outputs."""
    return (_member_state(state, m), u, _member_params(state, params, m), vehicle, dt,
            _member_out(state, m))


@nb.njit(cache=True, _nrt=False)
def run_members(state, u, params, vehicle, dt):
    """Each member's ``step`` on its slices (static calls, in MEMBERS order: numba caches no
    kernel that calls a function it is handed)."""
    kinematic_heuristic.step(*_member(state, u, params, vehicle, dt, 0))
    dk_ekf.step(*_member(state, u, params, vehicle, dt, 1))
    d_ekf.step(*_member(state, u, params, vehicle, dt, 2))
    k_kf.step(*_member(state, u, params, vehicle, dt, 3))
    hybrid_friction.step(*_member(state, u, params, vehicle, dt, 4))
    pseudo_fusion.step(*_member(state, u, params, vehicle, dt, 5))
    gnss_magnetometer.step(*_member(state, u, params, vehicle, dt, 6))


@nb.njit(cache=True, _nrt=False)
def member_usable(state, u, m):
    """True when member m's output of this tick may enter the fusion (see module docstring)."""
    row = F.MEMBER_OUT + m * N_OUT
    status = int(state[row + Out.STATUS])
    if status & EXCLUDING:
        return False
    beta = state[row + Out.BETA]
    if not (math.isfinite(beta) and abs(beta) < 0.5 * math.pi):
        return False
    if not math.isfinite(state[row + Out.VX]):
        return False
    required = F.REQUIRED + m * N_IN
    for ch in range(N_IN):
        if state[required + ch] > 0.5 and u[VALID + ch] < 0.5:
            return False
    return True


#: the monitor's FAIL bit (consistency.Flag.FAIL)
_MONITOR_FAIL = int(consistency.Flag.FAIL)
#: the witness member's monitor has no dynamic witness (NaN outputs: not running)
_NO_WITNESS = np.full(N_OUT, np.nan)


@nb.njit(cache=True, _nrt=False)
def monitor_members(state, u, params, vehicle, dt):
    """Each member's output of this tick through a consistency monitor of its own (the
    pipeline's, ``slipd.estimators.consistency``, with the d_ekf member's raw output as the
    dynamic witness; the d_ekf member has only the kinematic witness and its innovation test):
    CONSISTENT = 0 when the monitor fails it, CALIBRATED_SIGMA its calibrated sigma. The
    member's own outputs stay as they are (the monitor works on a copy)."""
    monitor_params = params[_MONITOR0 : _MONITOR0 + _N_MONITOR]
    scratch = state[F.MONITOR_OUT : F.MONITOR_OUT + N_OUT]
    for m in range(N_MEMBERS):
        row = _member_out(state, m)
        for c in range(N_OUT):
            scratch[c] = row[c]
        if m == WITNESS_MEMBER:
            witness = _NO_WITNESS
        else:
            witness = _member_out(state, WITNESS_MEMBER)
        monitor_state = _member_monitor(state, m)
        consistency.monitor(monitor_state, u, scratch, witness, monitor_params, vehicle, dt)
        failed = int(monitor_state[consistency.S.LAST_FLAGS]) & _MONITOR_FAIL
        state[F.CONSISTENT + m] = 0.0 if failed else 1.0
        state[F.CALIBRATED_SIGMA + m] = scratch[Out.SIGMA_BETA]


@nb.njit(cache=True, _nrt=False)
def mark_usable(state, u, entry_ticks, member_monitor, low_grip):
    """Per member: USABLE = usable this tick (1/0), USABLE_TICKS its streak, FUSED = usable for
    at least ``entry_ticks`` ticks (the member enters the fusion). With ``member_monitor``, a
    member its consistency monitor fails (CONSISTENT 0) is not usable while another usable one
    passes (when every one fails, none is vouched for and all stay). With ``low_grip`` (the
    road is low-grip, ``fuse_tick``) only the LOW_GRIP_MEMBERS are usable."""
    vouched = False
    for m in range(N_MEMBERS):
        usable = member_usable(state, u, m) and not (low_grip and LOW_GRIP_MASK[m] < 0.5)
        state[F.USABLE + m] = 1.0 if usable else 0.0
        vouched = vouched or (member_monitor and usable and state[F.CONSISTENT + m] > 0.5)
    for m in range(N_MEMBERS):
        if state[F.USABLE + m] > 0.5 and not (vouched and state[F.CONSISTENT + m] < 0.5):
            state[F.USABLE_TICKS + m] += 1.0
        else:
            state[F.USABLE + m] = 0.0
            state[F.USABLE_TICKS + m] = 0.0
        fused = state[F.USABLE + m] > 0.5 and state[F.USABLE_TICKS + m] >= entry_ticks
        state[F.FUSED + m] = 1.0 if fused else 0.0


@nb.njit(cache=True, _nrt=False)
def road_is_low_grip(state, change_ticks):
    """True while the road is taken as low-grip: the friction member's settled classifier has
    said low grip (anything else: not low) for ``change_ticks`` consecutive ticks since the
    road was last taken as not low-grip, and the reverse. A classifier that flickers for less
    (noisy wheel speeds on a dry road) would otherwise take members out for a few ticks each
    time, and each of them out for ``entry_time`` more until it re-enters."""
    said_low = _member_out(state, FRICTION_MEMBER)[Out.FRICTION_CLASS] == hybrid_friction.CLASS_LOW
    taken_low = state[F.LOW_GRIP] > 0.5
    if said_low == taken_low:
        state[F.LOW_GRIP_CHANGE_TICKS] = 0.0
    else:
        state[F.LOW_GRIP_CHANGE_TICKS] += 1.0
        if state[F.LOW_GRIP_CHANGE_TICKS] >= change_ticks:
            taken_low = said_low
            state[F.LOW_GRIP] = 1.0 if said_low else 0.0
            state[F.LOW_GRIP_CHANGE_TICKS] = 0.0
    return taken_low


@nb.njit(cache=True, _nrt=False)
def _weighted_mean(state, channel):
    """sum w_i y_i / sum w_i over the members with w_i > 0 and a finite y_i (NaN if none)."""
    num = 0.0
    den = 0.0
    for m in range(N_MEMBERS):
        w = state[F.WEIGHT + m]
        value = state[F.MEMBER_OUT + m * N_OUT + channel]
        if w > 0.0 and math.isfinite(value):
            num += w * value
            den += w
    return num / den if den > 0.0 else math.nan


@nb.njit(cache=True, _nrt=False)
def fuse(state, floor, calibrated, spread_floor, converged_sigma, out):
    """Eq. 38-39 with the P of ``error_covariance``; writes the weights and ``out``. With
    ``spread_floor`` the fused variance is at least the weighted spread of the fused members
    about the result, sum w_i (beta_i - beta_0)^2; NOT_CONVERGED while the fused sigma exceeds
    ``converged_sigma`` (> 0)."""
    n, variance = error_covariance(state, floor, calibrated)
    status = 0
    information = 0.0
    if n > 0:
        information = 1.0 / variance
        for m in range(N_MEMBERS):
            if state[F.WEIGHT + m] > 0.0:
                status |= int(state[F.MEMBER_OUT + m * N_OUT + Out.STATUS]) & ST_DEGRADED
    else:
        # nobody fused yet (start-up, after a loss): the members usable this tick, else those
        # with finite outputs, weighted by their own sigma_beta alone; flagged not converged
        any_usable = False
        for m in range(N_MEMBERS):
            any_usable = any_usable or state[F.USABLE + m] > 0.5
        total = 0.0
        for m in range(N_MEMBERS):
            row = F.MEMBER_OUT + m * N_OUT
            ok = math.isfinite(state[row + Out.BETA]) and math.isfinite(state[row + Out.VX])
            if any_usable:
                ok = state[F.USABLE + m] > 0.5
            w = 1.0 / (own_variance(state, m, calibrated) + floor) if ok else 0.0
            state[F.WEIGHT + m] = w
            total += w
        for m in range(N_MEMBERS):
            state[F.WEIGHT + m] = state[F.WEIGHT + m] / total if total > 0.0 else 0.0
        status = ST_NOT_CONVERGED | (0 if total > 0.0 else ST_INPUT_TIMEOUT)
    beta = _weighted_mean(state, Out.BETA)
    vx = _weighted_mean(state, Out.VX)
    if not (math.isfinite(beta) and math.isfinite(vx)):
        beta = 0.0
        vx = 0.0 if not math.isfinite(vx) else vx
        status |= ST_NOT_CONVERGED
    if n > 0 and spread_floor:
        # w'Pw holds for the P the difference moments allow, which cannot show an error the
        # members share (module docstring); members that part ways this tick (a drift's onset,
        # each lagging by its own amount) are direct evidence of an error at least that large
        spread = 0.0
        for m in range(N_MEMBERS):
            w = state[F.WEIGHT + m]
            value = state[F.MEMBER_OUT + m * N_OUT + Out.BETA]
            if w > 0.0 and math.isfinite(value):
                spread += w * (value - beta) ** 2
        if spread > 1.0 / information:
            information = 1.0 / spread
    if converged_sigma > 0.0 and information > 0.0 and 1.0 / information > converged_sigma ** 2:
        status |= ST_NOT_CONVERGED
    beta_rate = _weighted_mean(state, Out.BETA_RATE)
    roll = _weighted_mean(state, Out.ROLL)
    friction_class = 0.0
    best = 0.0
    for m in range(N_MEMBERS):
        value = state[F.MEMBER_OUT + m * N_OUT + Out.FRICTION_CLASS]
        if state[F.WEIGHT + m] > best and math.isfinite(value) and value > 0.0:
            best = state[F.WEIGHT + m]
            friction_class = value
    write_outputs(out, beta, beta_rate if math.isfinite(beta_rate) else 0.0, vx,
                  vx * math.tan(beta), _weighted_mean(state, Out.MU),
                  math.sqrt(1.0 / information) if information > 0.0 else math.nan, roll,
                  friction_class, status)  # fmt: skip


@nb.njit(cache=True, _nrt=False)
def step(state, u, params, vehicle, dt, out):
    """One tick: every member's step and consistency monitor, then the N-member
    minimum-variance fusion of beta."""
    run_members(state, u, params, vehicle, dt)
    if params[FUSION_PARAMS.MEMBER_MONITOR] > 0.5 or params[FUSION_PARAMS.MONITOR_SIGMA] > 0.5:
        monitor_members(state, u, params, vehicle, dt)
    fuse_tick(state, u, params, dt, out)


@nb.njit(cache=True, _nrt=False)
def fuse_tick(state, u, params, dt, out):
    """The fusion part of ``step`` on the member outputs already in ``state[F.MEMBER_OUT:]``."""
    decay = dt / params[FUSION_PARAMS.TIME_CONSTANT]
    decay = decay if decay < 1.0 else 1.0
    low_grip = params[FUSION_PARAMS.LOW_GRIP_MEMBERS] > 0.5 and road_is_low_grip(
        state, params[FUSION_PARAMS.LOW_GRIP_TIME] / dt)
    mark_usable(state, u, params[FUSION_PARAMS.ENTRY_TIME] / dt,
                params[FUSION_PARAMS.MEMBER_MONITOR] > 0.5, low_grip)
    update_moments(state, decay)
    fuse(state, params[FUSION_PARAMS.SIGMA_FLOOR] ** 2, params[FUSION_PARAMS.MONITOR_SIGMA] > 0.5,
         params[FUSION_PARAMS.SPREAD_FLOOR] > 0.5, params[FUSION_PARAMS.CONVERGED_SIGMA_BETA], out)


@nb.njit(cache=True, nogil=True, _nrt=False)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])



__all__ = ["DEFAULTS", "FAMILY", "FUSION_PARAMS", "LAYOUT", "MEMBERS", "N_MEMBERS", "PARAMS",
           "PERSISTENT", "F", "error_covariance", "fuse", "fuse_tick", "init", "member_params",
           "run_ticks", "step"]
