"""The plant: CommonRoad's multi-body model (package ``vehiclemodels``) on a road with friction,
bank and grade, integrated over a whole manoeuvre with the driver in the loop.

The model is used as published (``vehicle_dynamics_mb``, Althoff & Wuersching, "CommonRoad:
Vehicle Models" 2020, section 6 and its Pacejka tyres); this module only adds what the package
leaves out, around its right-hand side:

- road friction: the Pacejka peak factors ``p_dy1``/``p_dx1`` are scaled by
  ``mu_road / p_dy1_nominal`` for the road segment under the car (the package notes say so);
- road bank and grade: their gravity components in the road plane act on every mass of the model
  (``g_x = -g sin(theta_road)`` on the longitudinal equation, ``g_y = -g sin(phi_road)`` on the
  lateral equations of the sprung and both unsprung masses). The ``cos`` reduction of the
  normal load (1 % at 8 deg) is neglected;
- two driver states appended to the 29 model states: the distance travelled ``s`` (road tables
  are indexed by it) and the integral of the speed error (the driver's PI speed control).

Sign conventions (measured, see tests/test_sim.py): the model's body frame is ISO 8855 for
``x[3]`` vx, ``x[10]`` vy, ``x[5]`` yaw rate and ``x[2]`` steer angle (left turn positive).
Its roll ``x[6]`` and pitch ``x[8]`` are converted by :data:`ROLL_SIGN` and :data:`PITCH_SIGN`.
"""

from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from slipd.errors import DependencyError, SlipdError

G = 9.81  # m/s^2, the value vehicle_dynamics_mb uses

class SimulationError(SlipdError):
    """The plant cannot continue (the scenario drove the car out of the model's domain)."""


#: scipy's odeint message of a successful call (full_output); anything else is LSODA giving up.
ODEINT_OK = "Integration successful."

#: Number of states of vehicle_dynamics_mb.
N_MB = 29
#: Index of the distance travelled and of the speed-error integral in the augmented state.
S_IDX = N_MB
IERR_IDX = N_MB + 1
N_AUG = N_MB + 2

# Indices into the model state (names from the header of vehicle_dynamics_mb.py).
POS_X, POS_Y, STEER, VX, YAW, YAW_RATE, ROLL, ROLL_RATE, PITCH, PITCH_RATE, VY = range(11)
Z_S, VZ_S = 11, 12
OMEGA_FL, OMEGA_FR, OMEGA_RL, OMEGA_RR = 23, 24, 25, 26

#: Plant wheel-speed states in ISO 8855 wheel order (FL, FR, RL, RR). The MB model's "left"
#: wheels sit at y = -T/2 of an ISO frame whose yaw rate is positive to the left: its own
#: kinematics give u_w_lf = vx + T_f/2 * r (vehicle_dynamics_mb.py), the speed of the right-hand
#: wheel; measured, in a left turn its "FL" wheel turns faster than "FR". The plant stays as
#: published (its forces are consistent with its geometry); only the labels are swapped.
ISO_WHEEL_STATES = (OMEGA_FR, OMEGA_FL, OMEGA_RR, OMEGA_RL)

#: Model roll (x[6]) -> ISO 8855 roll (positive right side down). Measured: in a left turn the
#: body leans to the right (outward) and x[6] comes out negative, so the sign flips.
ROLL_SIGN = -1.0
#: Model pitch (x[8]) -> ISO 8855 pitch (positive nose down). Measured: braking dives the nose
#: and x[8] comes out negative, so the sign flips.
PITCH_SIGN = -1.0


def _vehiclemodels():
    try:
        from vehiclemodels import parameters_vehicle1, parameters_vehicle2, parameters_vehicle3
        from vehiclemodels.init_mb import init_mb
        from vehiclemodels.utils.acceleration_constraints import acceleration_constraints
        from vehiclemodels.utils.steering_constraints import steering_constraints
        from vehiclemodels.vehicle_dynamics_mb import vehicle_dynamics_mb
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise DependencyError(
            "the simulator needs commonroad-vehicle-models and scipy: pip install slipd[sim]"
        ) from exc
    return {
        "params": {
            1: parameters_vehicle1.parameters_vehicle1,
            2: parameters_vehicle2.parameters_vehicle2,
            3: parameters_vehicle3.parameters_vehicle3,
        },
        "init_mb": init_mb,
        "dynamics": vehicle_dynamics_mb,
        "accel_limit": acceleration_constraints,
        "steer_limit": steering_constraints,
    }


def vehicle_parameters(vehicle: int = 2, extra_mass: float = 0.0, extra_mass_x: float = -0.6):
    """The package's parameter set ``vehicle`` (1 Ford Escort, 2 BMW 320i, 3 VW Vanagon), a copy.

    ``extra_mass`` kg of payload is added to the sprung mass ``extra_mass_x`` m ahead of its CoG
    (negative: behind, the rear seat and boot) at the sprung CoG height: the CoG moves
    (``a``, ``b`` change with the wheelbase kept), the yaw and pitch inertias gain the parallel
    axis terms of a 1 m long load. Roll inertia gains the load's own (0.3 m)^2 term.
    """
    vm = _vehiclemodels()
    if vehicle not in vm["params"]:
        from slipd.errors import ConfigError

        raise ConfigError(f"unknown vehicle parameter set {vehicle}; expected 1, 2 or 3")
    p = copy.deepcopy(vm["params"][vehicle]())
    if extra_mass > 0.0:
        m_old = p.m_s
        m_new = m_old + extra_mass
        shift = extra_mass * extra_mass_x / m_new  # CoG shift forward (+) of the sprung mass
        d_old = -shift  # old CoG relative to the new one
        d_load = extra_mass_x - shift
        load_len2 = 1.0 / 12.0  # (1 m)^2 / 12: a uniform 1 m long load
        p.I_z = p.I_z + m_old * d_old**2 + extra_mass * (d_load**2 + load_len2)
        p.I_y_s = p.I_y_s + m_old * d_old**2 + extra_mass * (d_load**2 + load_len2)
        p.I_Phi_s = p.I_Phi_s + extra_mass * 0.3**2
        p.a = p.a + shift
        p.b = p.b - shift
        p.m_s = m_new
        p.m = p.m + extra_mass
    return p


@dataclass
class Road:
    """Road properties as functions of the distance travelled ``s`` (m).

    ``mu``: peak lateral friction coefficient per segment (step function: ``mu[i]`` applies from
    ``mu_s[i]`` on); ``bank``: rad, ISO 8855 roll sign of the road surface (positive: the right
    edge lower); ``grade``: rad, positive uphill. Bank and grade are linear between their knots
    and refer to the direction of travel (the car follows the road).
    """

    mu_s: np.ndarray = field(default_factory=lambda: np.array([0.0]))
    mu: np.ndarray = field(default_factory=lambda: np.array([1.0489]))
    bank_s: np.ndarray = field(default_factory=lambda: np.array([0.0]))
    bank: np.ndarray = field(default_factory=lambda: np.array([0.0]))
    grade_s: np.ndarray = field(default_factory=lambda: np.array([0.0]))
    grade: np.ndarray = field(default_factory=lambda: np.array([0.0]))

    def __post_init__(self) -> None:
        for name in ("mu_s", "mu", "bank_s", "bank", "grade_s", "grade"):
            setattr(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        self._mu_s = self.mu_s.tolist()
        self._mu = self.mu.tolist()
        self._flat = not (np.any(self.bank) or np.any(self.grade))
        from slipd.sim.driver import LinearTable

        self._bank_table = LinearTable(self.bank_s, self.bank)
        self._grade_table = LinearTable(self.grade_s, self.grade)

    def mu_at(self, s: float) -> float:
        """Friction of the segment under the car (scalar, used in the RHS)."""
        mu_s = self._mu_s
        i = len(mu_s) - 1
        while i > 0 and s < mu_s[i]:
            i -= 1
        return self._mu[i]

    def bank_grade_at(self, s: float) -> tuple[float, float]:
        if self._flat:
            return 0.0, 0.0
        return self._bank_table(s), self._grade_table(s)

    def mu_array(self, s: np.ndarray) -> np.ndarray:
        idx = np.searchsorted(self.mu_s, s, side="right") - 1
        return self.mu[np.clip(idx, 0, len(self.mu) - 1)]

    def bank_array(self, s: np.ndarray) -> np.ndarray:
        return np.interp(s, self.bank_s, self.bank)

    def grade_array(self, s: np.ndarray) -> np.ndarray:
        return np.interp(s, self.grade_s, self.grade)


#: Steering law: (t, model state as a list, s) -> road-wheel steer angle target, rad.
SteerLaw = Callable[[float, list, float], float]


@dataclass
class Driver:
    """What the driver does: a steering law, a speed target and optional acceleration demands.

    The steering actuator follows the target with a first-order lag ``steer_lag`` (a driver's
    arm or an EPS position loop, 0.05 s), so the model input ``u[0]`` is the steer *rate*
    ``(target - delta) / steer_lag``; the model clips it at its own limit (0.4 rad/s for set 2).
    Speed: PI control on ``speed_target(t, s)`` with ``speed_kp`` (1/s) and ``speed_ki`` (1/s^2);
    ``accel_override(t, x)`` (m/s^2, NaN = none) replaces the PI output (braking, throttle).
    """

    steer: SteerLaw
    speed_target: Callable[[float, float], float]
    accel_override: Callable[[float, list], float] | None = None
    steer_lag: float = 0.05
    speed_kp: float = 1.0
    speed_ki: float = 0.2
    steer_limit: float = 0.6
    #: The car's traction control (every car sold in the EU since 2014 has one): above
    #: ``tcs_slip`` of driven-wheel slip the engine torque is cut, ``tcs_gain`` m/s^2 per unit
    #: slip. Not applied to ``accel_override`` (a drift is driven with the system off).
    tcs_slip: float = 0.05
    tcs_gain: float = 40.0
    wheel_radius: float = 0.344

    def controls(self, t: float, x: list, s: float, ierr: float) -> tuple[float, float, float]:
        """(steer rate demand rad/s, acceleration demand m/s^2, speed error m/s)."""
        target = self.steer(t, x, s)
        if target > self.steer_limit:
            target = self.steer_limit
        elif target < -self.steer_limit:
            target = -self.steer_limit
        steer_rate = (target - x[STEER]) / self.steer_lag
        v_err = self.speed_target(t, s) - x[VX]
        accel = self.speed_kp * v_err + self.speed_ki * ierr
        if accel > 0.0 and x[VX] > 1.0:
            slip = 0.5 * (x[OMEGA_RL] + x[OMEGA_RR]) * self.wheel_radius / x[VX] - 1.0
            if slip > self.tcs_slip:
                accel = max(0.0, accel - self.tcs_gain * (slip - self.tcs_slip))
        if self.accel_override is not None:
            override = self.accel_override(t, x)
            if override == override:  # not NaN
                accel = override
                v_err = 0.0  # no integrator wind-up while overridden
        return steer_rate, accel, v_err


@dataclass
class PlantOutput:
    """Model states and their derivatives on the output grid (``t``, 100 Hz by default)."""

    t: np.ndarray  # s
    x: np.ndarray  # (n, 29) model states
    dx: np.ndarray  # (n, 29) their time derivatives (the model's right-hand side + gravity)
    s: np.ndarray  # m travelled
    accel_demand: np.ndarray  # m/s^2 after the model's acceleration constraints
    mu: np.ndarray  # road friction under the car
    bank: np.ndarray  # rad, ISO roll sign
    grade: np.ndarray  # rad, positive uphill


class Plant:
    """One car on one road with one driver; :meth:`run` integrates it."""

    def __init__(self, params, road: Road, driver: Driver, fast: bool = True) -> None:
        """``fast``: evaluate the model through slipd.sim.mb_fast (its numba transcription,
        equal to the package to rounding, ~30x faster) instead of the package's Python."""
        vm = _vehiclemodels()
        self.p = copy.deepcopy(params)  # the tyre's friction factors are rescaled in place
        self.road = road
        self.driver = driver
        driver.wheel_radius = params.R_w
        self.fast = fast
        self._dynamics = vm["dynamics"]
        self._accel_limit = vm["accel_limit"]
        self._init_mb = vm["init_mb"]
        self._p_dy1 = params.tire.p_dy1
        self._p_dx1 = params.tire.p_dx1
        self._mu_now = None
        if fast:
            from slipd.sim import mb_fast

            self._fast_rhs = mb_fast.vehicle_dynamics_mb
            self._packed = mb_fast.pack(self.p)
            self._tire_base = mb_fast.pack_tire(self.p.tire)
            self._tire_idx = (mb_fast.T_PDY1, mb_fast.T_PDX1)
            self._tires: dict[float, np.ndarray] = {}

    def _tire_for(self, mu: float) -> np.ndarray:
        """The packed tyre vector with the peak factors scaled for road friction ``mu``."""
        tire = self._tires.get(mu)
        if tire is None:
            tire = self._tire_base.copy()
            scale = mu / self._p_dy1
            tire[self._tire_idx[0]] *= scale
            tire[self._tire_idx[1]] *= scale
            self._tires[mu] = tire
        return tire

    def _set_mu(self, mu: float) -> None:
        if mu != self._mu_now:
            scale = mu / self._p_dy1
            self.p.tire.p_dy1 = self._p_dy1 * scale
            self.p.tire.p_dx1 = self._p_dx1 * scale
            self._mu_now = mu

    def rhs(self, t: float, y: np.ndarray) -> list:
        """Right-hand side of the augmented state [29 model states, s, speed-error integral]."""
        yl = y.tolist()
        x = yl[:N_MB]
        s = yl[S_IDX]
        steer_rate, accel, v_err = self.driver.controls(t, x, s, yl[IERR_IDX])
        mu = self.road.mu_at(s)
        if self.fast:
            f = self._fast_rhs(y[:N_MB], steer_rate, accel, self._packed,
                               self._tire_for(mu)).tolist()
        else:
            self._set_mu(mu)
            f = self._dynamics(x, [steer_rate, accel], self.p)
        bank, grade = self.road.bank_grade_at(s)
        if bank != 0.0 or grade != 0.0:
            f[VX] -= G * math.sin(grade)
            gy = -G * math.sin(bank)  # gravity pulls toward the lower edge
            f[VY] += gy
            f[15] += gy  # front unsprung lateral velocity
            f[20] += gy  # rear unsprung lateral velocity
        speed = math.hypot(x[VX], x[VY])
        f.append(speed)
        f.append(v_err)
        return f

    def initial_state(self, speed: float, yaw: float = 0.0, settle: float = 1.5) -> np.ndarray:
        """Straight driving at ``speed``: ``init_mb``'s state, then ``settle`` s of straight
        driving so the suspension sits at its loaded equilibrium (init_mb starts the sprung
        mass 2 cm off it, a heave transient an accelerometer would show)."""
        x0 = self._init_mb([0.0, 0.0, 0.0, speed, yaw, 0.0, 0.0], self.p)
        y0 = np.array([*x0, 0.0, 0.0], dtype=np.float64)
        if settle <= 0:
            return y0
        from scipy.integrate import odeint

        straight = Driver(steer=lambda t, x, s: 0.0, speed_target=lambda t, s: speed)
        saved, self.driver = self.driver, straight
        try:
            y = odeint(self.rhs, y0, [0.0, settle], tfirst=True, hmax=0.01, rtol=1e-4,
                       atol=1e-6, mxstep=20000)[-1]
        finally:
            self.driver = saved
        y[POS_X], y[POS_Y], y[YAW] = 0.0, 0.0, yaw
        y[S_IDX], y[IERR_IDX], y[VX] = 0.0, 0.0, speed
        y[OMEGA_FL : OMEGA_RR + 1] = speed / self.p.R_w
        return y

    def run(
        self,
        duration: float,
        speed: float,
        yaw: float = 0.0,
        dt: float = 0.01,
        segment: float = 20.0,
        progress: Callable[[float], None] | None = None,
        y0: np.ndarray | None = None,
    ) -> PlantOutput:
        """Integrate ``duration`` s from straight driving at ``speed`` m/s (or from ``y0``, an
        augmented state, e.g. the end of the previous leg).

        scipy's ``odeint`` (LSODA) with a 10 ms maximum step integrates each ``segment`` s in one
        call (restarting every tick is ~10x slower, ../shared/notes/simulation.md); the state is
        carried across segments so long drives need no more memory than their output.
        """
        try:
            from scipy.integrate import ODEintWarning, odeint
        except ImportError as exc:  # pragma: no cover
            raise DependencyError("the simulator needs scipy: pip install slipd[sim]") from exc
        n = int(round(duration / dt)) + 1
        t = np.arange(n) * dt
        y = np.empty((n, N_AUG))
        y[0] = self.initial_state(speed, yaw=yaw) if y0 is None else y0
        per_seg = max(1, int(round(segment / dt)))
        k = 0
        while k < n - 1:
            k_end = min(n - 1, k + per_seg)
            try:
                with warnings.catch_warnings():  # its failure is raised below, with the time
                    warnings.simplefilter("ignore", ODEintWarning)
                    sol, info = odeint(
                        self.rhs, y[k], t[k : k_end + 1], tfirst=True, hmax=dt,
                        rtol=1e-4, atol=1e-6, mxstep=5000, full_output=True,
                    )
            except ZeroDivisionError as exc:
                # the model divides by wheel-centre speeds: a car going backwards or spinning
                # has left the model's domain, the scenario must not ask for it
                raise SimulationError(
                    f"the car left the multi-body model's domain (spin or reversing) between "
                    f"t = {t[k]:.2f} and {t[k_end]:.2f} s"
                ) from exc
            if info["message"] != ODEINT_OK:
                # LSODA gave up (istate < 0) and fills the rest of the segment with zeros, a
                # standing car the model then divides by: report where, never return them
                # (the per-output arrays past the failure are uninitialised memory: an output
                # was reached where LSODA's time lies within one step after it)
                reached = info["tcur"] - t[k + 1 : k_end + 1]
                done = int(np.argmin((reached >= -1e-9) & (reached <= dt + 1e-9)))
                raise SimulationError(
                    f"the multi-body model could not be integrated past t = {t[k + done]:.2f} "
                    f"s (scipy odeint: {info['message'].strip()}); there vx = "
                    f"{sol[done][VX]:.1f} m/s, yaw rate {sol[done][YAW_RATE]:.2f} rad/s: the "
                    f"scenario drove the car out of the model's domain (e.g. a drift asked of a "
                    f"car whose driven axle cannot hold one)"
                )
            y[k + 1 : k_end + 1] = sol[1:]
            k = k_end
            if progress is not None:
                progress(t[k])
        return self._outputs(t, y)

    def _outputs(self, t: np.ndarray, y: np.ndarray) -> PlantOutput:
        n = len(t)
        dx = np.empty((n, N_MB))
        accel = np.empty(n)
        lim = self.p.longitudinal
        for k in range(n):
            f = self.rhs(t[k], y[k])
            dx[k] = f[:N_MB]
            yl = y[k].tolist()
            _, a_dem, _ = self.driver.controls(t[k], yl[:N_MB], yl[S_IDX], yl[IERR_IDX])
            accel[k] = self._accel_limit(yl[VX], a_dem, lim)
        # odeint integrates through the model's in-place clamp of negative wheel spin; the
        # clamped value is the physical one
        y[:, OMEGA_FL : OMEGA_RR + 1] = np.maximum(y[:, OMEGA_FL : OMEGA_RR + 1], 0.0)
        s = y[:, S_IDX].copy()
        return PlantOutput(
            t=t,
            x=y[:, :N_MB].copy(),
            dx=dx,
            s=s,
            accel_demand=accel,
            mu=self.road.mu_array(s),
            bank=self.road.bank_array(s),
            grade=self.road.grade_array(s),
        )
