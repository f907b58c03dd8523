"""The drives slipd identify works on: logs read and latched through the codec like a replay,
then the SI signals each method needs, corrected with the calibration found so far.

A log is read with :func:`slipd.replay.readers.read_frames` (any format replay reads) and
latched with :func:`slipd.replay.engine.latch_log_or_recording` (the daemon's 100 Hz ticks, or
a flight recorder's own), with the profile's ``[calibration]`` left out: identification starts
from the raw sensors, so its results are absolute values, not corrections of corrections.
Segments never cross logs.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slipd.channels import N_IN, WHEEL_SPEEDS, G, In, Veh
from slipd.codec.calibration import calibrate_ticks, calibration_vector
from slipd.errors import ConfigError
from slipd.profile import Calibration, Profile, load_profile

DT = 0.01  # s, the tick interval of the latched drives


def raw_profile(profile: str | Path | Profile) -> Profile:
    """The profile without its ``[calibration]`` corrections (what the raw sensors are decoded
    with); the steer channel's divisor, which is not a correction, is kept."""
    if not isinstance(profile, Profile):
        profile = load_profile(profile)
    return dataclasses.replace(profile, calibration=Calibration(
        steer_divisor=profile.calibration.steer_divisor))


@dataclass
class Drive:
    """One log on the tick grid: tick times and the raw input vectors [n, U_LEN]."""

    name: str
    path: Path
    t: np.ndarray
    U: np.ndarray
    #: channels slipd import derived rather than read (channel name -> how; from the log's
    #: LOG.meta.json): they carry no sensor of their own to identify
    derived: dict[str, str] = field(default_factory=dict)

    @property
    def seconds(self) -> float:
        return float(len(self.t) * DT)


def read_drives(logs: list[Path], profile: Profile, progress: bool = True,
                bus_map: dict[str, str] | None = None) -> list[Drive]:
    """Every log read and latched through the codec with the raw profile (a progress bar over
    the logs on stderr)."""
    import sys

    from tqdm import tqdm

    from slipd.replay.engine import latch_log_or_recording
    from slipd.replay.readers import read_frames

    drives = []
    for path in tqdm(logs, desc="slipd identify: reading logs", unit="log", file=sys.stderr,
                     disable=not progress):
        path = Path(path)
        if not path.exists():
            raise ConfigError(f"{path}: no such log")
        frames = read_frames(path)
        inputs = latch_log_or_recording(frames, profile, bus_map)
        drives.append(Drive(path.name, path, inputs.t, inputs.U, derived_channels(path)))
    return drives


def derived_channels(log: Path) -> dict[str, str]:
    """The channels slipd import derived for ``log`` (its LOG.meta.json sidecar), or {}."""
    import json

    sidecar = log.with_name(log.name + ".meta.json")
    if not sidecar.is_file():
        return {}
    try:
        meta = json.loads(sidecar.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{sidecar}: not slipd import's JSON description of {log.name}: "
                          f"{exc}") from exc
    derived = meta.get("derived_on_request", {}) if isinstance(meta, dict) else {}
    return {str(k): str(v) for k, v in derived.items()} if isinstance(derived, dict) else {}


def _savgol_derivative(x: np.ndarray, window_s: float = 0.21) -> np.ndarray:
    from scipy.signal import savgol_filter

    n = int(round(window_s / DT)) | 1
    if len(x) <= n:
        return np.gradient(x, DT) if len(x) > 1 else np.zeros_like(x)
    return savgol_filter(x, n, 2, deriv=1, delta=DT)


def lowpass(x: np.ndarray, corner_hz: float) -> np.ndarray:
    """Zero-phase 2nd-order Butterworth low-pass (offline: no lag)."""
    from scipy.signal import butter, filtfilt

    if len(x) < 16:
        return x.copy()
    b, a = butter(2, corner_hz, fs=1.0 / DT)
    return filtfilt(b, a, x, padlen=min(len(x) - 1, 3 * max(len(a), len(b))))


@dataclass
class Signals:
    """A drive's SI signals (ISO 8855) after the calibration ``cal``; the IMU's values at the
    IMU (``ax_cog``/``ay_cog``: moved to the CoG in the plane, Rajamani eq. 2.5 style:
    a_cog = a_imu - r_dot k x rho + r^2 rho)."""

    drive: Drive
    ok: dict[In, np.ndarray]
    ax: np.ndarray
    ay: np.ndarray
    az: np.ndarray
    roll_rate: np.ndarray
    pitch_rate: np.ndarray
    yaw_rate: np.ndarray
    steer: np.ndarray  # rad, road-wheel angle as the profile divides it
    wheels: np.ndarray  # [n, 4] m/s
    vx: np.ndarray  # m/s, mean of the rear wheels (not steered)
    yaw_acc: np.ndarray  # rad/s^2, Savitzky-Golay derivative of the yaw rate
    ax_cog: np.ndarray
    ay_cog: np.ndarray
    dvx: np.ndarray  # m/s^2, derivative of vx
    gnss_speed: np.ndarray | None = None  # m/s, 3-D speed of a fix (NaN without)
    extra: dict = field(default_factory=dict)

    @property
    def t(self) -> np.ndarray:
        return self.drive.t

    def has(self, channel: In) -> bool:
        return bool(self.ok[channel].any())

    def all_ok(self, *channels: In) -> np.ndarray:
        mask = np.ones(len(self.t), dtype=bool)
        for channel in channels:
            mask &= self.ok[channel]
        return mask


def signals(drive: Drive, profile: Profile, calibration: Calibration,
            steer_scale: float = 1.0) -> Signals:
    """The drive's signals with ``calibration`` applied by the codec's own correction (the
    plain twin of the sampling kernel, slipd.codec.calibration.calibrate_ticks).
    ``steer_scale``: the old over the new steering ratio (the drive was latched with the
    profile's ratio; a new one rescales the steer channel as the codec would)."""
    cal = calibration_vector(calibration)
    U = drive.U
    if steer_scale != 1.0:
        U = U.copy()
        U[:, In.STEER] *= steer_scale
        U[:, In.STEER_RATE] *= steer_scale
    U = calibrate_ticks(cal, U)
    ok = {c: U[:, N_IN + c] > 0.5 for c in In}
    col = {c: U[:, c] for c in In}
    wheels = np.column_stack([col[c] for c in WHEEL_SPEEDS])
    vx = 0.5 * (wheels[:, 2] + wheels[:, 3])
    veh = profile.vehicle
    yaw_rate = col[In.YAW_RATE]
    yaw_acc = _savgol_derivative(yaw_rate)
    rho_x, rho_y = float(veh[Veh.IMU_X]), float(veh[Veh.IMU_Y])
    ax_cog = col[In.AX] + yaw_acc * rho_y + yaw_rate**2 * rho_x
    ay_cog = col[In.AY] - yaw_acc * rho_x + yaw_rate**2 * rho_y
    gnss = None
    if ok[In.GNSS_VN].any() and ok[In.GNSS_VE].any():
        fix = ok[In.GNSS_VN] & ok[In.GNSS_VE] & (col[In.GNSS_FIX] > 0.5)
        vu = np.where(ok[In.GNSS_VU], col[In.GNSS_VU], 0.0)
        speed = np.sqrt(col[In.GNSS_VN] ** 2 + col[In.GNSS_VE] ** 2 + vu**2)
        gnss = np.where(fix, speed, np.nan)
    return Signals(drive, ok, col[In.AX], col[In.AY], col[In.AZ], col[In.ROLL_RATE],
                   col[In.PITCH_RATE], yaw_rate, col[In.STEER], wheels, vx, yaw_acc, ax_cog,
                   ay_cog, _savgol_derivative(vx), gnss)


def runs(mask: np.ndarray, min_seconds: float, trim_seconds: float = 0.0
         ) -> list[tuple[int, int]]:
    """Contiguous stretches [start, stop) of ``mask`` at least ``min_seconds`` long after
    ``trim_seconds`` is cut from each end."""
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        return []
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    trim = int(round(trim_seconds / DT))
    need = int(math.ceil(min_seconds / DT))
    result = []
    for a, b in zip(starts, stops, strict=True):
        a, b = a + trim, b - trim
        if b - a >= max(need, 1):
            result.append((int(a), int(b)))
    return result


def split(segments: list[tuple], max_seconds: float) -> list[tuple]:
    """Segments ``(..., start, stop)`` cut into pieces of about ``max_seconds`` (the
    bootstrap's resampling units); what precedes start and stop (a drive index) is kept."""
    size = int(round(max_seconds / DT))
    out = []
    for segment in segments:
        *head, a, b = segment
        pieces = max(1, int(round((b - a) / size)))
        bounds = np.linspace(a, b, pieces + 1).round().astype(int)
        out.extend((*head, int(lo), int(hi))
                   for lo, hi in zip(bounds[:-1], bounds[1:], strict=True) if hi > lo)
    return out


def moving_std(x: np.ndarray, seconds: float) -> np.ndarray:
    """Centred moving standard deviation over ``seconds``."""
    n = max(1, int(round(seconds / DT)))
    kernel = np.ones(n) / n
    mean = np.convolve(x, kernel, mode="same")
    mean_sq = np.convolve(x * x, kernel, mode="same")
    return np.sqrt(np.maximum(mean_sq - mean * mean, 0.0))


__all__ = ["DT", "G", "Drive", "Signals", "derived_channels", "lowpass", "moving_std",
           "raw_profile", "read_drives", "runs", "signals", "split"]
