"""Discrete filters on scalars with their memory in the caller's state vector.

Each filter keeps its memory at ``buf[i]`` of a caller-owned float64 buffer (a method's state),
so nothing is allocated per tick. NaN in the memory means "not started": the filter starts at
the first sample it sees (no start-up transient), so a method sets these slots to NaN at init
or reset.

From Selmanaj, Corno, Panzani, Savaresi (2017), "Vehicle sideslip estimation: a kinematic based
approach", section 2.1: continuous-time designs discretised by forward Euler.
"""

from __future__ import annotations

import math

from slipd.numba_cache import nb

#: Cut-off of the derivative filters (Selmanaj section 2.1: "derivative filters with a cutoff
#: frequency of 10 Hz", designed in continuous time and discretised by forward Euler).
DERIVATIVE_CUTOFF_HZ = 10.0


@nb.njit(cache=True, inline="always")
def lowpass(buf, i, signal, dt, time_constant):
    """First-order low-pass y' = (signal - y) / time_constant, forward Euler; returns y.

    ``buf[i]`` is y; NaN starts the filter at ``signal``. The Euler step is clipped at one
    time constant so a long tick gap cannot make the filter overshoot.
    """
    if not math.isfinite(buf[i]):
        buf[i] = signal
        return signal
    gain = dt / time_constant
    if gain > 1.0:
        gain = 1.0
    buf[i] += gain * (signal - buf[i])
    return buf[i]


@nb.njit(cache=True, inline="always")
def derivative_filter(buf, i, signal, dt, cutoff_hz):
    """Real derivative filter H(s) = s / (1 + s / wc), wc = 2 pi cutoff_hz, forward Euler.

    Selmanaj section 2.1: cut-off 10 Hz, continuous design discretised by forward Euler (at
    100 Hz wc*dt = 0.63 < 2, so the discrete filter is stable and close to the continuous one).
    Realised as wc * (signal - x) with the low-pass state x' = wc (signal - x) in ``buf[i]``.
    NaN in ``buf[i]`` starts the filter at ``signal`` (derivative 0, no start-up spike).
    """
    wc = 2.0 * math.pi * cutoff_hz
    if not math.isfinite(buf[i]):
        buf[i] = signal
        return 0.0
    derivative = wc * (signal - buf[i])
    step = wc * dt
    if step > 1.0:  # a long gap: land on the signal instead of overshooting it
        step = 1.0
    buf[i] += step * (signal - buf[i])
    return derivative


@nb.njit(cache=True, inline="always")
def leak(buf, i, dt, time_constant):
    """``buf[i]`` decays toward 0 with ``time_constant`` (x -= x dt / tau, the step clipped at
    one time constant); 0 means no leak. slipd's bound on an open kinematic integral of ay
    (k_kf's ``vy_leak_time_constant``, pseudo_fusion's ``kbe_vy_leak_time_constant``; k_kf's
    docstring gives the argument: an unmodelled lateral acceleration b settles the integral
    at b / r in a curve, the leak at b tau)."""
    if time_constant > 0.0:
        buf[i] *= 1.0 - min(dt / time_constant, 1.0)


#: s of straight running (|yaw rate| below a threshold) before a signal whose true value is
#: then ~0 is sampled as noise (``noise_power``): a slalom's yaw rate crosses zero where its
#: sideslip rate peaks.
STRAIGHT_SETTLE = 2.0


@nb.njit(cache=True, inline="always")
def straight_settled(buf, i, straight, dt):
    """Whether the car has gone ``straight`` for ``STRAIGHT_SETTLE`` s: ``buf[i]`` counts the
    seconds (0 at any tick that is not), the sampling condition of ``noise_power``."""
    buf[i] = buf[i] + dt if straight else 0.0
    return buf[i] >= STRAIGHT_SETTLE


@nb.njit(cache=True, inline="always")
def noise_power(buf, i, signal, sampling, dt, time_constant):
    """The mean square of ``signal`` averaged (``lowpass``, ``time_constant``) over the ticks
    where ``sampling`` says its true value is ~0 (going straight: what is left is the sensors'
    noise and the body's vibration); returns it from ``buf[i]``, NaN until first sampled.
    slipd's, for thresholds and bell widths set "above the noise" on sensors they were not
    tuned on (hybrid_friction's switches, kinematic_heuristic's bells)."""
    if sampling:
        lowpass(buf, i, signal * signal, dt, time_constant)
    return buf[i]


@nb.njit(cache=True, inline="always")
def gaussian_bell(a, sigma_a, b, sigma_b):
    """exp(-(a^2 / sigma_a^2 + b^2 / sigma_b^2) / 2): Selmanaj eq. 5-7's bivariate Gaussian, 1 at
    (0, 0), -> 0 when either argument grows (also Chen's straight-running weight)."""
    x = a / sigma_a
    y = b / sigma_b
    return math.exp(-0.5 * (x * x + y * y))


#: Memory of ``butterworth_lowpass``: its two direct-form II transposed states.
BUTTERWORTH_SLOTS = 2


@nb.njit(cache=True, inline="always")
def butterworth_lowpass(buf, i, signal, dt, cutoff_hz):
    """Second-order Butterworth low-pass (the bilinear transform with the cut-off prewarped,
    as scipy.signal.butter(2, cutoff_hz / (0.5 / dt)) designs it), direct form II transposed
    with its two states at ``buf[i]``, ``buf[i + 1]``; returns y. NaN in ``buf[i]`` starts the
    filter in its steady state at ``signal`` (no start-up transient). The coefficients follow
    ``dt``, so a catch-up step keeps the cut-off."""
    k = math.tan(math.pi * cutoff_hz * dt)
    norm = 1.0 / (1.0 + math.sqrt(2.0) * k + k * k)
    b0 = k * k * norm
    b1 = 2.0 * b0
    a1 = 2.0 * (k * k - 1.0) * norm
    a2 = (1.0 - math.sqrt(2.0) * k + k * k) * norm
    if not math.isfinite(buf[i]):
        buf[i] = (1.0 - b0) * signal
        buf[i + 1] = (b0 - a2) * signal
        return signal
    y = b0 * signal + buf[i]
    buf[i] = b1 * signal - a1 * y + buf[i + 1]
    buf[i + 1] = b0 * signal - a2 * y
    return y
