"""Road courses as sequences of segments: curvature, speed, friction, bank and grade over the
distance travelled ``s``. The driver follows the curvature (CurvatureFollower) and the speed
profile; the plant reads friction, bank and grade from the :class:`~slipd.sim.plant.Road`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from slipd.sim.plant import Road


@dataclass(frozen=True)
class Segment:
    """``length`` m of road with constant curvature ``kappa`` (1/m, + left), a speed limit
    ``speed`` (m/s), friction ``mu``, bank (rad, ISO roll sign: + right edge lower) and grade
    (rad, + uphill)."""

    length: float
    kappa: float = 0.0
    speed: float = 20.0
    mu: float = 1.0489
    bank: float = 0.0
    grade: float = 0.0


@dataclass
class Course:
    """Tables over ``s`` built from segments: curvature, target speed and the road."""

    kappa_s: np.ndarray
    kappa: np.ndarray
    speed_s: np.ndarray
    speed: np.ndarray
    road: Road
    length: float
    _speed: object = field(default=None, repr=False)

    def speed_at(self, s: float) -> float:
        if self._speed is None:
            from slipd.sim.driver import LinearTable

            self._speed = LinearTable(self.speed_s, self.speed)
        return self._speed(s)


def build_course(
    segments: Sequence[Segment],
    transition: float = 15.0,
    accel: float = 1.5,
    decel: float = 2.5,
    step: float = 1.0,
    start_speed: float | None = None,
    end_speed: float | None = None,
) -> Course:
    """Curvature changes linearly over ``transition`` m (a clothoid) centred on each joint; the
    speed profile respects each segment's limit with ``accel``/``decel`` m/s^2 (forward and
    backward passes), so the driver brakes before a corner and not in it. ``start_speed``
    and ``end_speed`` pin the profile's ends."""
    edges = np.concatenate([[0.0], np.cumsum([seg.length for seg in segments])])
    length = float(edges[-1])
    s = np.arange(0.0, length + step, step)
    seg_idx = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, len(segments) - 1)
    kappa_raw = np.array([segments[i].kappa for i in seg_idx])
    # moving average over the transition length = linear curvature ramps at the joints
    width = max(1, int(round(transition / step)))
    kernel = np.ones(width) / width
    kappa = np.convolve(np.pad(kappa_raw, (width // 2, width - 1 - width // 2), mode="edge"),
                        kernel, mode="valid")
    limit = np.array([segments[i].speed for i in seg_idx], dtype=np.float64)
    # corners: never faster than the segment limit anywhere in the transition either
    padded = np.pad(limit, (width, width), mode="edge")
    limit = np.lib.stride_tricks.sliding_window_view(padded, 2 * width + 1).min(axis=1)
    v = limit.copy()
    if start_speed is not None:
        v[0] = start_speed
    if end_speed is not None:
        v[-1] = end_speed
    for i in range(1, len(s)):  # accelerate out of slow parts
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * accel * step))
    for i in range(len(s) - 2, -1, -1):  # brake into slow parts
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * decel * step))
    road = ramped_road(segments)
    return Course(kappa_s=s, kappa=kappa, speed_s=s, speed=v, road=road, length=length)


def _ramp_table(
    edges: np.ndarray, values: np.ndarray, ramp: float
) -> tuple[np.ndarray, np.ndarray]:
    """Knots of a piecewise-constant table with linear ramps of ``ramp`` m at the joints."""
    xs, ys = [edges[0]], [values[0]]
    for i in range(1, len(values)):
        xs += [edges[i] - ramp / 2, edges[i] + ramp / 2]
        ys += [values[i - 1], values[i]]
    xs.append(edges[-1])
    ys.append(values[-1])
    return np.array(xs), np.array(ys)


def ramped_road(segments: Sequence[Segment], ramp: float = 30.0) -> Road:
    """The road of ``segments`` with bank and grade ramped over ``ramp`` m at each joint (a road
    does not tilt in a step) and friction changing in steps (wet to dry, tarmac to ice)."""
    edges = np.concatenate([[0.0], np.cumsum([seg.length for seg in segments])])
    bank_s, bank = _ramp_table(edges, np.array([seg.bank for seg in segments]), ramp)
    grade_s, grade = _ramp_table(edges, np.array([seg.grade for seg in segments]), ramp)
    return Road(
        mu_s=edges[:-1], mu=np.array([seg.mu for seg in segments]),
        bank_s=bank_s, bank=bank, grade_s=grade_s, grade=grade,
    )
