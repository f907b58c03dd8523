"""Tests of the ``ensemble`` method (slipd.estimators.ensemble).

- the fusion on synthetic members with known independent errors: the weights converge to the
  inverse-variance weights of eq. 38 and the fused error to the minimum variance;
- a member that goes bad loses its weight; excluded statuses, invalid required inputs and
  non-finite outputs get zero weight; start-up falls back to the own sigmas;
- the registry entry, the params layout (members' defaults under prefixed names, overrides
  reach the member) and the state layout;
- the whole ensemble on the simulator: finite outputs, vy = vx tan(beta), weights sum to 1, it
  matches each member run alone, and zero allocations per step (numba NRT statistics).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from nrt import allocations, sine_drive_inputs

from slipd.channels import (
    N_OUT,
    ST_DEGRADED,
    ST_INPUT_TIMEOUT,
    ST_NOT_CONVERGED,
    ST_RESET,
    ST_UNAVAILABLE,
    U_LEN,
    VALID,
    In,
    Out,
)
from slipd.estimators import ensemble as ens
from slipd.estimators import registry
from slipd.estimators.ensemble import FUSION_PARAMS, MEMBERS, N_MEMBERS, F
from slipd.profile import load_profile

REPO = Path(__file__).resolve().parents[1]
DT = 0.01


@pytest.fixture(scope="module")
def vehicle() -> np.ndarray:
    from slipd.profile import load_profile

    return load_profile("default").vehicle


def all_valid_u() -> np.ndarray:
    u = np.zeros(U_LEN)
    u[VALID : VALID + len(In)] = 1.0
    return u


def weights(state: np.ndarray) -> np.ndarray:
    return state[F.WEIGHT : F.WEIGHT + N_MEMBERS].copy()


def set_member(state, m, beta, sigma=1e-5, status=0, vx=20.0, mu=math.nan, fclass=0.0):
    row = F.MEMBER_OUT + m * N_OUT
    state[row + Out.BETA] = beta
    state[row + Out.BETA_RATE] = 0.0
    state[row + Out.VX] = vx
    state[row + Out.VY] = vx * math.tan(beta)
    state[row + Out.MU] = mu
    state[row + Out.SIGMA_BETA] = sigma
    state[row + Out.ROLL] = 0.0
    state[row + Out.FRICTION_CLASS] = fclass
    state[row + Out.STATUS] = float(status)


def synthetic_run(sigmas_deg, n, params, vehicle, seed=0, bias_from=None, bias_deg=0.0):
    """Members beta_i = beta + e_i, e_i ~ N(0, sigma_i^2) independent; returns (W, fused error,
    member errors) over the ticks."""
    rng = np.random.default_rng(seed)
    state = ens.init(params, vehicle)
    u = all_valid_u()
    out = np.zeros(N_OUT)
    sig = np.radians(np.asarray(sigmas_deg))
    W = np.zeros((n, N_MEMBERS))
    fused_err = np.zeros(n)
    member_err = np.zeros((n, N_MEMBERS))
    for k in range(n):
        beta = 0.05 * math.sin(0.3 * k * DT)
        e = rng.normal(0.0, sig)
        if bias_from is not None and k >= bias_from:
            e[0] += math.radians(bias_deg)
        for m in range(N_MEMBERS):
            set_member(state, m, beta + e[m])
        ens.fuse_tick(state, u, params, DT, out)
        W[k] = weights(state)
        fused_err[k] = out[Out.BETA] - beta
        member_err[k] = e
    return W, fused_err, member_err, out


SIGMAS_DEG = [0.1, 0.2, 0.3, 0.5, 1.0, 2.0, 0.15]


def test_weights_converge_to_inverse_variance_weights(vehicle):
    # w'Pw alone: members with independent white errors spread about the result by about
    # their own sigma each tick, which the spread floor would report (it is meant for members
    # that part ways, test_members_parting_ways_widen_sigma_and_unsettle_the_fusion)
    params = registry.make_params(ens, {"time_constant": 30.0, "spread_floor": 0.0})
    n = 40000
    W, fused_err, member_err, out = synthetic_run(SIGMAS_DEG, n, params, vehicle)
    floor = params[FUSION_PARAMS.SIGMA_FLOOR] ** 2
    inverse = 1.0 / (np.radians(SIGMAS_DEG) ** 2 + floor)
    expected = inverse / inverse.sum()
    late = W[n // 2 :].mean(axis=0)
    np.testing.assert_allclose(late, expected, rtol=0.15, atol=0.005)
    assert np.allclose(W.sum(axis=1), 1.0)
    # the fused error reaches the minimum variance 1 / sum(1 / sigma_i^2) and beats every member
    rms = np.sqrt(np.mean(fused_err[n // 2 :] ** 2))
    optimum = math.sqrt(1.0 / np.sum(1.0 / np.radians(SIGMAS_DEG) ** 2))
    assert rms < 1.1 * optimum
    assert rms < 0.8 * np.sqrt(np.mean(member_err[n // 2 :] ** 2, axis=0)).min()
    # and the reported sigma_beta says so
    assert out[Out.SIGMA_BETA] == pytest.approx(math.sqrt(1.0 / inverse.sum()), rel=0.25)


def min_variance_weights(P: np.ndarray) -> np.ndarray:
    """Eq. 38 with negative weights clipped (as the kernel does), by numpy."""
    x = np.linalg.solve(P, np.ones(len(P)))
    x = np.clip(x, 0.0, None)
    return x / x.sum()


def test_family_common_error_is_identified_and_does_not_out_vote(vehicle):
    """dk_ekf, d_ekf, k_kf share a 1 deg error on top of small own errors: independent members
    would make them look best (their differences are small); the family term finds C_f."""
    params = registry.make_params(ens, {"time_constant": 30.0})
    floor = params[FUSION_PARAMS.SIGMA_FLOOR] ** 2
    own_deg = np.array([1.0, 0.05, 0.08, 0.1, 0.3, 0.5, 0.8])
    common_deg = 1.0
    family = np.array(ens.FAMILY) == ens.FAMILY[MEMBERS.index("dk_ekf")]
    rng = np.random.default_rng(5)
    state = ens.init(params, vehicle)
    u = all_valid_u()
    out = np.zeros(N_OUT)
    n = 40000
    W = np.zeros((n, N_MEMBERS))
    fused_err = np.zeros(n)
    for k in range(n):
        e = rng.normal(0.0, np.radians(own_deg))
        e[family] += rng.normal(0.0, math.radians(common_deg))
        for m in range(N_MEMBERS):
            set_member(state, m, 0.02 + e[m])
        ens.fuse_tick(state, u, params, DT, out)
        W[k] = weights(state)
        fused_err[k] = out[Out.BETA] - 0.02
    P = np.diag(np.radians(own_deg) ** 2) + floor * np.eye(N_MEMBERS)
    P[np.ix_(family, family)] += math.radians(common_deg) ** 2
    expected = min_variance_weights(P)
    np.testing.assert_allclose(W[n // 2 :].mean(axis=0), expected, atol=0.04)
    assert W[n // 2 :, family].sum(axis=1).mean() < 0.2
    common = state[F.COMMON + ens.FAMILY[MEMBERS.index("dk_ekf")]]
    assert common == pytest.approx(math.radians(common_deg) ** 2, rel=0.3)
    rms = np.sqrt(np.mean(fused_err[n // 2 :] ** 2))
    optimum = math.sqrt(expected @ P @ expected)
    assert rms < 1.15 * optimum
    assert np.degrees(rms) < 0.3  # independence would follow the family: about 1 deg


def test_equal_members_get_equal_weights(vehicle):
    params = registry.make_params(ens, {"time_constant": 30.0})
    W, *_ = synthetic_run([0.3] * N_MEMBERS, 20000, params, vehicle, seed=3)
    np.testing.assert_allclose(W[10000:].mean(axis=0), 1.0 / N_MEMBERS, rtol=0.1)


def test_a_member_that_goes_bad_loses_its_weight(vehicle):
    params = registry.make_params(ens)  # default forgetting (2 s)
    n, k_bad = 6000, 3000
    W, fused_err, *_ = synthetic_run(SIGMAS_DEG, n, params, vehicle, seed=1,
                                     bias_from=k_bad, bias_deg=3.0)  # fmt: skip
    assert W[k_bad - 500 : k_bad, 0].mean() > 0.3  # the best member leads before
    tau_ticks = int(params[FUSION_PARAMS.TIME_CONSTANT] / DT)
    assert W[k_bad + 3 * tau_ticks :, 0].max() < 0.01
    # a 3 deg bias of the once-best member ends up below 0.1 deg in the fused estimate
    assert np.degrees(np.abs(fused_err[k_bad + 3 * tau_ticks :]).mean()) < 0.1
    assert np.allclose(W.sum(axis=1), 1.0)


def test_members_parting_ways_widen_sigma_and_unsettle_the_fusion(vehicle):
    """A drift's onset: members that agreed for seconds part by degrees within a tick (each
    lags the slip by its own amount). The difference moments still remember the agreement, so
    w'Pw alone claims a small sigma; with ``spread_floor`` the fused sigma covers the members'
    weighted spread about the result and, above ``converged_sigma_beta``, the fusion says
    NOT_CONVERGED (so supervision does not send it VALID)."""
    u = all_valid_u()
    results = {}
    for name, overrides in (("default", {}),
                            ("w'Pw alone", {"spread_floor": 0.0, "converged_sigma_beta": 0.0})):
        params = registry.make_params(ens, overrides)
        state = ens.init(params, vehicle)
        out = np.zeros(N_OUT)
        rng = np.random.default_rng(4)
        for _ in range(300):  # 3 s of agreement within 0.05 deg
            for m in range(N_MEMBERS):
                set_member(state, m, math.radians(-2.0 + rng.normal(0.0, 0.05)))
            ens.fuse_tick(state, u, params, DT, out)
        assert not int(out[Out.STATUS]) & ST_NOT_CONVERGED
        parted = np.radians([-5.0, -9.0, -6.0, -12.0, -8.0, -4.0, -10.0])
        for m in range(N_MEMBERS):
            set_member(state, m, parted[m])
        ens.fuse_tick(state, u, params, DT, out)
        w = weights(state)
        spread = math.sqrt(float(np.sum(w * (parted - out[Out.BETA]) ** 2)))
        results[name] = (out[Out.SIGMA_BETA], spread, int(out[Out.STATUS]))
    sigma, spread, status = results["default"]
    assert spread > math.radians(1.0) and sigma >= spread * (1 - 1e-12)
    assert status & ST_NOT_CONVERGED
    sigma, spread, status = results["w'Pw alone"]
    assert sigma < 0.5 * spread and not status & ST_NOT_CONVERGED


def test_on_a_low_grip_road_only_the_members_that_read_the_road_are_fused(vehicle):
    """Four members agree on one drift (-12 deg), d_ekf and hybrid_friction, which estimate
    the road's friction, and gnss_magnetometer, which needs no tyres, on another (-4 deg).
    With d_ekf's friction class high the agreeing majority wins, as the difference moments
    say; once it reads low grip only LOW_GRIP_MEMBERS keep a weight and the fusion follows
    them; with ``low_grip_members`` 0 the majority wins on any road."""
    from slipd.estimators.ensemble.state import FRICTION_MEMBER, LOW_GRIP_MEMBERS, MEMBERS

    u = all_valid_u()
    keep = np.array([name in LOW_GRIP_MEMBERS for name in MEMBERS])
    fused = {}
    for case, fclass, overrides in (("high", 3.0, {}), ("low", 1.0, {}),
                                    ("low, off", 1.0, {"low_grip_members": 0.0})):
        params = registry.make_params(ens, overrides)
        state = ens.init(params, vehicle)
        out = np.zeros(N_OUT)
        rng = np.random.default_rng(5)
        for _ in range(400):
            for m in range(N_MEMBERS):
                beta = -4.0 if keep[m] else -12.0
                set_member(state, m, math.radians(beta + rng.normal(0.0, 0.3)),
                           sigma=math.radians(0.5 if keep[m] else 0.3),
                           fclass=fclass if m == FRICTION_MEMBER else 0.0)
            ens.fuse_tick(state, u, params, DT, out)
        fused[case] = (math.degrees(out[Out.BETA]), weights(state))
    for case in ("high", "low, off"):
        beta, w = fused[case]
        assert beta < -8.0 and w[~keep].sum() > 0.5, case
    beta, w = fused["low"]
    assert abs(beta + 4.0) < 0.5 and np.all(w[~keep] == 0.0)


def test_a_friction_class_that_flickers_does_not_take_members_out(vehicle):
    """A classifier fooled for a few ticks at a time (noisy wheel speeds on a dry road: 0.1-0.5
    s of low grip, seen with five sensor errors at once) must not take the members out each
    time, and each for ``entry_time`` more until it re-enters: the road is taken as low-grip
    only once the class has said so for ``low_grip_time``, and as dry again the same way.
    With ``low_grip_time`` 0 (the decision per tick) the flicker takes them out."""
    from slipd.estimators.ensemble.state import FRICTION_MEMBER, LOW_GRIP_MEMBERS, MEMBERS

    u = all_valid_u()
    keep = np.array([name in LOW_GRIP_MEMBERS for name in MEMBERS])

    def run(params, classes):
        """Every member on 0 deg; d_ekf's class per tick from ``classes``; the fewest members
        fused over the run and the weight the others had at its end."""
        state = ens.init(params, vehicle)
        out = np.zeros(N_OUT)
        fewest = N_MEMBERS
        for k, fclass in enumerate(classes):
            for m in range(N_MEMBERS):
                set_member(state, m, math.radians(0.3 * math.sin(0.1 * k + m)), sigma=1e-3,
                           fclass=fclass if m == FRICTION_MEMBER else 0.0)
            ens.fuse_tick(state, u, params, DT, out)
            if k > 200:
                fewest = min(fewest, int(state[F.FUSED : F.FUSED + N_MEMBERS].sum()))
        return fewest, weights(state)[~keep].sum()

    high, low = 3.0, 1.0
    period = [high] * 40 + [low] * 30  # 0.3 s of low grip every 0.7 s
    flicker = [high] * 300 + period * 10
    params = registry.make_params(ens)
    fewest, others = run(params, flicker)
    assert fewest == N_MEMBERS and others > 0.3
    fewest, _ = run(registry.make_params(ens, {"low_grip_time": 0.0}), flicker)
    assert fewest == int(keep.sum())
    # a class held for longer than low_grip_time is the road: the others leave after it ...
    hold = int(round(params[FUSION_PARAMS.LOW_GRIP_TIME] / DT))
    fewest, others = run(params, [high] * 300 + [low] * (hold + 10))
    assert fewest == int(keep.sum()) and others == 0.0
    # ... and not before
    fewest, _ = run(params, [high] * 300 + [low] * (hold - 2))
    assert fewest == N_MEMBERS


@pytest.mark.parametrize(
    "bad_status", [ST_UNAVAILABLE, ST_INPUT_TIMEOUT, ST_NOT_CONVERGED, ST_RESET]
)
def test_excluded_status_gets_zero_weight_that_tick(bad_status, vehicle):
    params = registry.make_params(ens)
    state = ens.init(params, vehicle)
    u = all_valid_u()
    out = np.zeros(N_OUT)
    rng = np.random.default_rng(2)
    for _ in range(300):
        for m in range(N_MEMBERS):
            set_member(state, m, 0.02 + rng.normal(0.0, 0.002))
        ens.fuse_tick(state, u, params, DT, out)
    assert np.all(weights(state) > 0.05)
    set_member(state, 2, 0.5, status=bad_status)  # a wild value that must not leak in
    ens.fuse_tick(state, u, params, DT, out)
    assert weights(state)[2] == 0.0
    assert abs(out[Out.BETA] - 0.02) < 0.005
    assert not int(out[Out.STATUS]) & ST_NOT_CONVERGED
    # back to normal: the member re-enters only after entry_time usable ticks
    entry = int(params[FUSION_PARAMS.ENTRY_TIME] / DT)
    for k in range(entry + 1):
        set_member(state, 2, 0.02)
        ens.fuse_tick(state, u, params, DT, out)
        if k < entry - 1:
            assert weights(state)[2] == 0.0
    assert weights(state)[2] > 0.0


def test_a_member_its_monitor_fails_is_left_out_while_another_is_vouched_for(vehicle):
    """member_monitor: a member whose consistency monitor failed it (CONSISTENT 0) gets no
    weight while a usable member passes; when every member fails, none is singled out."""
    params = registry.make_params(ens, {"member_monitor": 1.0})
    state = ens.init(params, vehicle)
    u = all_valid_u()
    out = np.zeros(N_OUT)
    rng = np.random.default_rng(3)

    def run(ticks, consistent):
        for _ in range(ticks):
            for m in range(N_MEMBERS):
                set_member(state, m, 0.02 + rng.normal(0.0, 0.002))
            state[F.CONSISTENT : F.CONSISTENT + N_MEMBERS] = consistent
            ens.fuse_tick(state, u, params, DT, out)

    run(300, 1.0)
    assert np.all(weights(state) > 0.05)
    failing = np.ones(N_MEMBERS)
    failing[4] = 0.0
    run(1, failing)
    assert weights(state)[4] == 0.0 and weights(state).sum() == pytest.approx(1.0)
    run(1, 0.0)  # nobody vouched for: the fusion of them all
    assert weights(state)[4] == 0.0  # (back after entry_time, as after any exclusion)
    run(int(params[FUSION_PARAMS.ENTRY_TIME] / DT) + 1, 0.0)
    assert np.all(weights(state) > 0.05)
    # off (the default): the verdicts change nothing
    off = registry.make_params(ens)
    assert off[FUSION_PARAMS.MEMBER_MONITOR] == 0.0 and off[FUSION_PARAMS.MONITOR_SIGMA] == 0.0
    state = ens.init(off, vehicle)
    for _ in range(300):
        for m in range(N_MEMBERS):
            set_member(state, m, 0.02 + rng.normal(0.0, 0.002))
        state[F.CONSISTENT : F.CONSISTENT + N_MEMBERS] = failing
        ens.fuse_tick(state, u, off, DT, out)
    assert weights(state)[4] > 0.05


def test_member_monitors_run_the_pipelines_monitor_on_each_member(simulated_drive, vehicle):
    """monitor_members: each member's verdict and calibrated sigma are what the pipeline's
    consistency monitor gives for that member's raw outputs with the d_ekf member as the
    dynamic witness (none for d_ekf itself)."""
    from slipd.estimators import consistency

    _, U = simulated_drive
    params = registry.make_params(ens, {"member_monitor": 1.0, "monitor_sigma": 1.0})
    method = registry.load("ensemble", {"member_monitor": 1.0, "monitor_sigma": 1.0})
    state = method.init(vehicle)
    out = np.zeros(N_OUT)
    outs = {name: np.zeros((len(U), N_OUT)) for name in MEMBERS}
    calibrated = np.zeros((len(U), N_MEMBERS))
    for k in range(len(U)):
        ens.step(state, U[k], params, vehicle, DT, out)
        for m, name in enumerate(MEMBERS):
            outs[name][k] = state[F.MEMBER_OUT + m * N_OUT : F.MEMBER_OUT + (m + 1) * N_OUT]
        calibrated[k] = state[F.CALIBRATED_SIGMA : F.CALIBRATED_SIGMA + N_MEMBERS]
    witness = outs["d_ekf"]
    for m, name in enumerate(MEMBERS):
        alone = outs[name].copy()
        mon = consistency.new_state()
        none = np.full_like(witness, np.nan)
        consistency.monitor_ticks(mon, U, alone, none if name == "d_ekf" else witness,
                                  consistency.default_params(), vehicle, np.full(len(U), DT))
        np.testing.assert_array_equal(calibrated[:, m], alone[:, Out.SIGMA_BETA], err_msg=name)


def test_non_finite_output_and_missing_required_input_get_zero_weight(vehicle):
    params = registry.make_params(ens)
    state = ens.init(params, vehicle)
    u = all_valid_u()
    out = np.zeros(N_OUT)
    for _ in range(300):
        for m in range(N_MEMBERS):
            set_member(state, m, 0.01 * (1 + m % 3))
        ens.fuse_tick(state, u, params, DT, out)
    gnss = MEMBERS.index("gnss_magnetometer")
    assert weights(state)[gnss] > 0.0
    set_member(state, 0, math.nan)
    set_member(state, 1, 0.02, vx=math.inf)
    u[VALID + In.GNSS_FIX] = 0.0  # gnss_magnetometer requires it; the core methods do not
    ens.fuse_tick(state, u, params, DT, out)
    w = weights(state)
    assert w[0] == 0.0 and w[1] == 0.0 and w[gnss] == 0.0
    assert w.sum() == pytest.approx(1.0)
    assert np.all(np.isfinite(out[[Out.BETA, Out.VX, Out.VY, Out.SIGMA_BETA]]))


def test_outputs_are_consistent_and_mu_comes_from_the_members_that_estimate_it(vehicle):
    params = registry.make_params(ens)
    state = ens.init(params, vehicle)
    u = all_valid_u()
    out = np.zeros(N_OUT)
    rng = np.random.default_rng(4)
    for _ in range(400):
        for m in range(N_MEMBERS):
            mu = 0.4 if m == 4 else (0.6 if m == 6 else math.nan)
            cls = 1.0 if m == 4 else 0.0
            set_member(state, m, 0.1 + rng.normal(0.0, 0.003), vx=15.0 + 0.1 * m,
                       mu=mu, fclass=cls, status=ST_DEGRADED if m == 5 else 0)  # fmt: skip
        ens.fuse_tick(state, u, params, DT, out)
    w = weights(state)
    assert out[Out.VY] == pytest.approx(out[Out.VX] * math.tan(out[Out.BETA]))
    assert out[Out.VX] == pytest.approx(np.sum(w * (15.0 + 0.1 * np.arange(N_MEMBERS))))
    expected_mu = (0.4 * w[4] + 0.6 * w[6]) / (w[4] + w[6])
    assert out[Out.MU] == pytest.approx(expected_mu)
    assert out[Out.FRICTION_CLASS] == 1.0
    assert int(out[Out.STATUS]) & ST_DEGRADED  # a fused member says degraded
    assert 0.0 < out[Out.SIGMA_BETA] < math.radians(0.5)


def test_start_up_uses_the_own_sigmas_and_says_not_converged(vehicle):
    params = registry.make_params(ens)
    state = ens.init(params, vehicle)
    u = all_valid_u()
    out = np.zeros(N_OUT)
    for m in range(N_MEMBERS):
        # a member at 0.3 rad claiming 1 rad of sigma against six at 0.01 rad claiming 0.001
        bad = m == N_MEMBERS - 1
        set_member(state, m, 0.3 if bad else 0.01, sigma=1.0 if bad else 1e-3)
    ens.fuse_tick(state, u, params, DT, out)
    assert int(out[Out.STATUS]) & ST_NOT_CONVERGED
    assert out[Out.BETA] == pytest.approx(0.01, abs=1e-5)
    # nothing finite at all: beta 0, flagged
    state = ens.init(params, vehicle)
    for m in range(N_MEMBERS):
        set_member(state, m, math.nan, status=ST_UNAVAILABLE)
    ens.fuse_tick(state, u, params, DT, out)
    assert out[Out.BETA] == 0.0
    assert int(out[Out.STATUS]) & ST_NOT_CONVERGED and int(out[Out.STATUS]) & ST_INPUT_TIMEOUT


def test_registry_and_params_layout(vehicle):
    assert registry.available()[-1] == "ensemble"  # append-only: the index is the bus estimator id
    method = registry.load("ensemble", {"dk_ekf__min_speed": 7.5, "time_constant": 3.0})
    assert method.params[FUSION_PARAMS.TIME_CONSTANT] == 3.0
    for name in MEMBERS:
        module = registry.load(name).module
        own = ens.member_params(method.params, name)
        expected = registry.make_params(module, {"min_speed": 7.5} if name == "dk_ekf" else None)
        np.testing.assert_array_equal(own, expected)
    state = method.init(vehicle)
    bounds = state[F.STATE_BOUNDS : F.STATE_BOUNDS + N_MEMBERS + 1].astype(int)
    assert bounds[0] == F[MEMBERS[0].upper()] and bounds[-1] == len(state) == ens.LAYOUT.size
    for m, name in enumerate(MEMBERS):
        mod = registry.load(name)
        np.testing.assert_array_equal(state[bounds[m] : bounds[m + 1]], mod.init(vehicle))
    for name in ("zero", "linear_kf", "pseudo_fusion_kbe", "hybrid_friction_nocls", "ensemble"):
        assert name not in MEMBERS


@pytest.fixture(scope="module")
def simulated_drive():
    from slipd.sim import simulate

    result = simulate("double_lane_change", vehicle=2, seed=0)
    return result.truth, np.ascontiguousarray(result.ticks())


def test_ensemble_on_the_simulator_runs_each_member_as_alone(simulated_drive, vehicle):
    truth, U = simulated_drive
    method = registry.load("ensemble")
    state = method.init(vehicle)
    OUT = np.zeros((U.shape[0], N_OUT))
    method.run_ticks(state, U, method.params, vehicle, DT, OUT)
    assert np.all(np.isfinite(OUT[:, [Out.BETA, Out.BETA_RATE, Out.VX, Out.VY, Out.ROLL]]))
    np.testing.assert_allclose(OUT[:, Out.VY], OUT[:, Out.VX] * np.tan(OUT[:, Out.BETA]))
    settled = (OUT[:, Out.STATUS].astype(int) & ST_NOT_CONVERGED) == 0
    assert settled[-100:].all()
    assert np.all(np.isfinite(OUT[settled, Out.SIGMA_BETA]))
    assert weights(state).sum() == pytest.approx(1.0)
    # each member inside the ensemble computes exactly what it computes alone
    bounds = state[F.STATE_BOUNDS : F.STATE_BOUNDS + N_MEMBERS + 1].astype(int)
    for m, name in enumerate(MEMBERS):
        alone = registry.load(name)
        own_state = alone.init(vehicle)
        own_out = np.zeros((U.shape[0], N_OUT))
        alone.run_ticks(own_state, U, alone.params, vehicle, DT, own_out)
        np.testing.assert_array_equal(state[bounds[m] : bounds[m + 1]], own_state, err_msg=name)
        row = F.MEMBER_OUT + m * N_OUT
        np.testing.assert_array_equal(state[row : row + N_OUT], own_out[-1], err_msg=name)
    # the fused beta is within the members' range and not worse than their median
    n = min(U.shape[0], truth["t"].size)
    fast = np.hypot(truth["vx"][:n], truth["vy"][:n]) > 20.0 / 3.6
    rms = float(np.sqrt(np.mean((OUT[:n, Out.BETA] - truth["beta"][:n])[fast] ** 2)))
    member_rms = []
    for name in MEMBERS:
        alone = registry.load(name)
        own_state = alone.init(vehicle)
        own_out = np.zeros((U.shape[0], N_OUT))
        alone.run_ticks(own_state, U, alone.params, vehicle, DT, own_out)
        error = (own_out[:n, Out.BETA] - truth["beta"][:n])[fast]
        member_rms.append(float(np.sqrt(np.mean(error**2))))
    assert rms <= np.median(member_rms)


def test_step_allocates_nothing():
    n = 3000
    t = np.arange(n) * 0.01
    U = sine_drive_inputs(n, 0.03, 0.2, 3.0)
    U[:, In.AZ] = 9.81
    U[:, In.MAG_X] = 20.0
    U[:, In.MAG_Z] = -40.0
    U[:, In.GNSS_VN] = 20.0
    U[:, In.GNSS_FIX] = 1.0
    U[:, VALID : VALID + len(In)] = 1.0
    U[1000:1100, VALID + In.AY] = 0.0  # the fallback paths too
    U[2000:2050, VALID : VALID + 12] = 0.0
    U[:, 2 * len(In)] = t
    ticks_10, ticks_many = allocations(["ensemble"], U, load_profile("default").vehicle)["ensemble"]
    # whatever the call itself costs (argument boxing), 2970 more ticks add nothing
    assert ticks_many == ticks_10


# ---------------------------------------------------------------------------------------------
# plain twin of error_covariance (the N-cornered hat with family terms, eq. 38)
# ---------------------------------------------------------------------------------------------


def plain_error_covariance(fused, moments, own, family, floor):
    """The module docstring's model in numpy: P of the fused members, the weights of eq. 38
    (negatives clipped) and w' P w. ``moments``: D_ij (N x N), ``own``: sigma_i^2."""
    idx = [i for i in range(N_MEMBERS) if fused[i]]
    n = len(idx)
    unknown = {}
    for f in sorted(set(family)):
        inside = sum(family[i] == f for i in idx)
        if inside >= 2 and n - inside >= 2:
            unknown[f] = n + len(unknown)
    common = dict.fromkeys(set(family), 0.0)
    solved = False
    theta = None
    if n >= 3:
        A = np.zeros((n + len(unknown), n + len(unknown)))
        b = np.zeros(n + len(unknown))
        for p in range(n):
            for q in range(p + 1, n):
                i, j = idx[p], idx[q]
                a = np.zeros(n + len(unknown))
                a[p] = a[q] = 1.0
                if family[i] != family[j]:
                    for f in (family[i], family[j]):
                        if f in unknown:
                            a[unknown[f]] += 1.0
                d = moments[i, j]
                weight = 1.0 / (d + floor) ** 2
                A += weight * np.outer(a, a)
                b += weight * a * d
        try:
            np.linalg.cholesky(A)
            theta = np.linalg.solve(A, b)
            solved = True
        except np.linalg.LinAlgError:
            solved = False
        if solved:
            for f, k in unknown.items():
                common[f] = max(theta[k], 0.0)
    variance = np.full(N_MEMBERS, np.nan)
    for p, i in enumerate(idx):
        if solved:
            hat = max(theta[p], 0.0) + common[family[i]]
        elif n == 2:
            other = idx[1 - p]
            total = own[i] + own[other]
            hat = (own[i] / total if total > 0 else 0.5) * moments[i, other]
        else:
            hat = own[i]
        variance[i] = max(hat, own[i]) + floor
    P = np.array([[variance[i] if i == j else (common[family[i]] if family[i] == family[j]
                   else 0.0) for j in idx] for i in idx])
    x = np.linalg.solve(P, np.ones(n))
    w_fused = np.where(x > 0, x, 0.0) / np.where(x > 0, x, 0.0).sum()
    w = np.zeros(N_MEMBERS)
    w[idx] = w_fused
    return w, variance, common, float(w_fused @ P @ w_fused)


#: fused-member masks beside the random ones: one member, two (the split by own variance),
#: a family and one other (C_f not identifiable), everything
MASKS = ((0, 0, 0, 0, 0, 1, 0), (1, 0, 0, 0, 1, 0, 0), (0, 1, 1, 0, 0, 0, 1), (1,) * N_MEMBERS)


@pytest.mark.parametrize("seed", range(12 + len(MASKS)))
def test_error_covariance_agrees_with_its_plain_twin(seed, vehicle):
    rng = np.random.default_rng(seed)
    params = registry.make_params(ens)
    state = ens.init(params, vehicle)
    fused = rng.random(N_MEMBERS) < 0.85
    if seed >= 12:
        fused = np.array(MASKS[seed - 12], dtype=bool)
    sigma = np.radians(rng.uniform(0.05, 2.0, N_MEMBERS))
    moments = np.zeros((N_MEMBERS, N_MEMBERS))
    for i in range(N_MEMBERS):
        for j in range(i + 1, N_MEMBERS):
            moments[i, j] = moments[j, i] = sigma[i] ** 2 + sigma[j] ** 2 * rng.uniform(0.5, 2)
    own = np.radians(rng.uniform(0.01, 0.5, N_MEMBERS)) ** 2
    for m in range(N_MEMBERS):
        state[F.FUSED + m] = float(fused[m])
        set_member(state, m, 0.0, sigma=math.sqrt(own[m]))
        for j in range(N_MEMBERS):
            state[F.MOMENT + m * N_MEMBERS + j] = moments[m, j]
            state[F.MASS + m * N_MEMBERS + j] = 1.0
    floor = params[FUSION_PARAMS.SIGMA_FLOOR] ** 2
    n, variance = ens.error_covariance(state, floor, False)
    w, var_ii, common, fused_variance = plain_error_covariance(fused, moments, own, ens.FAMILY,
                                                               floor)
    assert n == fused.sum()
    np.testing.assert_allclose(weights(state), w, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(state[F.VARIANCE : F.VARIANCE + N_MEMBERS], var_ii, rtol=1e-8)
    for f, value in common.items():
        assert state[F.COMMON + f] == pytest.approx(value, rel=1e-8, abs=1e-18)
    assert variance == pytest.approx(fused_variance, rel=1e-8)
