"""What slipd identify prints and puts in ``--report DIR``: the summary table, the handling
diagram, the single-track fit's residuals over time and the sensor offsets over the drive
(and the roll gradient where it was found)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from slipd.errors import DependencyError
from slipd.eval.plots import save
from slipd.identify import QUANTITIES, Identification
from slipd.identify.data import DT
from slipd.identify.profile_text import UNITS, interval_text, rounded


def _old_value(result: Identification, key: str):
    from slipd.channels import Veh
    from slipd.profile import TYRE_KEYS, VEHICLE_KEYS

    table, _, name = key.rpartition(".")
    if table == "calibration":
        return getattr(result.profile.calibration, name)
    index = TYRE_KEYS.get(name) if table == "vehicle.tyre" else VEHICLE_KEYS.get(name)
    return float(result.profile.vehicle[Veh(index)]) if index is not None else None


def _fmt(key: str, value) -> str:
    if isinstance(value, tuple | list):
        return "[" + ", ".join(f"{rounded(key, float(v)):g}" for v in value) + "]"
    return f"{rounded(key, float(value)):g}" if value is not None else "-"


def summary_lines(result: Identification) -> list[str]:
    """The table of identified values and the list of what was left alone."""
    lines = []
    findings = result.outcome.findings
    written = result.written()
    keys = [k for name in QUANTITIES for k in QUANTITIES[name]]
    rows = [("quantity", "was", "identified", "95 % CI", "data", "method")]
    for key in keys:
        if key not in findings:
            continue
        f = findings[key]
        mark = "" if key in written else " (not written: --only)"
        unit = UNITS.get(key, "")
        rows.append((f"{key}{' [' + unit + ']' if unit else ''}", _fmt(key, _old_value(result,
                                                                                         key)),
                     _fmt(key, f.value) + mark, interval_text(key, f), f.data_text(), f.method))
    widths = [max(len(r[i]) for r in rows) for i in range(5)]
    for row in rows:
        lines.append("  ".join(c.ljust(w) for c, w in zip(row[:5], widths, strict=True))
                     + "  " + row[5])
    left = result.left()
    if left:
        lines.append("")
        lines.append("left as they were:")
        for key, missing in left.items():
            lines.append(f"  {key}: {getattr(missing, 'reason', missing)}")
    k_us = result.outcome.diagnostics.get("understeer_gradient")
    if k_us is not None:
        value, (lo, hi) = k_us
        lines.append("")
        lines.append(f"understeer gradient (handling diagram): {math.degrees(value) * 9.81:.3f} "
                     f"deg/g, 95 % CI [{math.degrees(lo) * 9.81:.3f}, "
                     f"{math.degrees(hi) * 9.81:.3f}]")
        fit = result.outcome.diagnostics.get("single_track")
        if fit is not None:
            cf, cr, _iz, m, lf, lr = fit["params"]
            implied = m / (lf + lr) * (lr / cf - lf / cr)
            lines.append(f"understeer gradient of the fitted stiffnesses: "
                         f"{math.degrees(implied) * 9.81:.3f} deg/g")
    for message in result.outcome.messages:
        lines.append(message)
    return lines


def _figure(**kwargs):
    """A pyplot-free figure (headless, as slipd.eval.plots draws)."""
    try:
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise DependencyError("--report needs matplotlib: pip install 'slipd[plot]'") from exc
    return Figure(layout="constrained", **kwargs)


def _drive_offsets(result: Identification) -> list[float]:
    """Start of each drive on one time axis (the drives one after another), s."""
    offsets, total = [], 0.0
    for d in result.drives:
        offsets.append(total)
        total += d.seconds
    return offsets


def plot_handling(result: Identification, path: Path) -> bool:
    diag = result.outcome.diagnostics.get("handling")
    if diag is None:
        return False
    gain, gradient_gain, intercept = diag["fit"]
    kin = np.concatenate([p[3] for p in diag["pieces"]])
    cen = np.concatenate([p[4] for p in diag["pieces"]])
    delta = np.concatenate([p[5] for p in diag["pieces"]])
    speed = cen / np.where(np.abs(kin) > 1e-9, kin, np.nan) * diag["wheelbase"]
    speed = np.sqrt(np.abs(speed))
    step = max(1, len(kin) // 6000)
    road = (delta - intercept) / gain  # the road-wheel angle with the identified ratio, offset
    fig = _figure(figsize=(12, 5))
    left, right = fig.subplots(1, 2)
    sc = left.scatter(np.degrees(kin[::step]), np.degrees(road[::step]), s=2, c=speed[::step],
                      cmap="viridis")
    lim = np.nanpercentile(np.abs(np.degrees(kin)), 99.5)
    left.plot([-lim, lim], [-lim, lim], "k-", lw=1, label="delta = L / R")
    left.set_xlabel("L r / v_x  [deg]  (kinematic steer of the profile's wheelbase)")
    left.set_ylabel("road-wheel angle, identified ratio and offset  [deg]")
    left.set_title("steering ratio and offset")
    left.legend(loc="upper left")
    fig.colorbar(sc, ax=left, label="speed [m/s]")
    excess = road - kin
    right.scatter(cen[::step], np.degrees(excess[::step]), s=2, c=speed[::step], cmap="viridis")
    k_us = gradient_gain / gain
    xs = np.linspace(np.nanmin(cen), np.nanmax(cen), 10)
    right.plot(xs, np.degrees(k_us * xs), "r-", lw=2,
               label=f"K_us = {math.degrees(k_us) * 9.81:.2f} deg/g")
    right.axhline(0.0, color="k", lw=0.5)
    right.set_xlabel("lateral acceleration r v_x  [m/s^2]")
    right.set_ylabel("delta - L / R  [deg]")
    right.set_title("handling diagram (Gillespie 1992, ch. 6)")
    right.legend(loc="upper left")
    right.set_ylim(np.nanpercentile(np.degrees(excess), [0.5, 99.5]) * 1.5)
    fig.suptitle("quasi-steady ticks in the linear range")
    save(fig, path)
    return True


def plot_residuals(result: Identification, path: Path) -> bool:
    diag = result.outcome.diagnostics.get("single_track")
    if diag is None:
        return False
    data = diag["data"]
    r_model, ay_model = diag["r_model"], diag["ay_model"]
    offsets = _drive_offsets(result)
    fig = _figure(figsize=(12, 9))
    axes = fig.subplots(3, 1)
    rms = []
    for j, piece in enumerate(data.pieces):
        a, b = data.starts[j], data.stops[j]
        ticks = data.scored[j]
        t = offsets[piece["drive"]] + (ticks - a) * DT + piece["start"] * DT
        res_r = np.degrees(r_model[ticks] - data.r[ticks])
        res_ay = ay_model[ticks] - data.ay[ticks]
        axes[0].plot(t, res_r, ".", ms=1, color="C0")
        axes[1].plot(t, res_ay, ".", ms=1, color="C1")
        rms.append((float(np.sqrt(np.mean((data.r[a:b] - data.r[a:b].mean()) ** 2))), j))
    axes[0].set_ylabel("yaw rate: model - measured [deg/s]")
    axes[1].set_ylabel("a_y: model - measured [m/s^2]")
    axes[1].set_xlabel("drive time [s] (logs one after another)")
    axes[0].set_title("single-track fit residuals over time (scored ticks of each segment)")
    best = max(rms)[1]
    a, b = data.starts[best], data.stops[best]
    t = np.arange(b - a) * DT
    axes[2].plot(t, np.degrees(data.r[a:b]), "k-", lw=1, label="yaw rate measured [deg/s]")
    axes[2].plot(t, np.degrees(r_model[a:b]), "C0--", lw=1.5, label="model")
    axes[2].plot(t, data.ay[a:b], "C7-", lw=1, label="a_y measured (tyres) [m/s^2]")
    axes[2].plot(t, ay_model[a:b], "C1--", lw=1.5, label="model")
    axes[2].set_xlabel("time in the segment [s]")
    axes[2].set_title("the most excited segment")
    axes[2].legend(loc="upper right", fontsize=8, ncol=2)
    save(fig, path)
    return True


def plot_offsets(result: Identification, path: Path) -> bool:
    from slipd.channels import In
    from slipd.identify.imu import ACCEL, GYRO, _channel

    stops = result.outcome.diagnostics.get("standstills") or []
    raw = result.outcome.diagnostics.get("raw_signals")
    units = result.outcome.diagnostics.get("wheel_units")
    if not stops and units is None:
        return False
    offsets = _drive_offsets(result)
    fig = _figure(figsize=(12, 9))
    axes = fig.subplots(3, 1, sharex=True)
    findings = result.outcome.findings
    for ax, channels, key, scale, unit in (
            (axes[0], GYRO, "calibration.gyro_offset", 180.0 / math.pi, "deg/s"),
            (axes[1], ACCEL, "calibration.accel_offset", 1.0, "m/s^2")):
        if not stops or raw is None:
            ax.text(0.5, 0.5, "no standstill", ha="center", transform=ax.transAxes)
            continue
        finding = findings.get(key)
        for i, channel in enumerate(channels):
            t = [offsets[k] + 0.5 * (a + b) * DT for k, a, b in stops]
            values = [scale * float(np.mean(_channel(raw[k], channel)[a:b])) for k, a, b in
                      stops]
            if channel == In.AZ:
                values = [v - 9.81 for v in values]
            ax.plot(t, values, "o", color=f"C{i}", label=f"{channel.name.lower()} at each stop"
                    + (" - g" if channel == In.AZ else ""))
            if finding is not None and key == "calibration.gyro_offset":
                ax.axhline(finding.values()[i], color=f"C{i}", lw=1)
        ax.set_ylabel(f"[{unit}]")
        ax.legend(loc="upper right", fontsize=8, ncol=3)
    axes[0].set_title("gyro means at each standstill (lines: identified offsets)")
    axes[1].set_title("accelerometer means at each standstill (gravity through the mounting "
                      "and the offsets: slipd.identify.imu)")
    if units is not None:
        wheel_units, _ = units
        for i, name in enumerate(("fl", "fr", "rl", "rr")):
            t = [offsets[k] + 0.5 * (a + b) * DT for k, a, b in wheel_units]
            values = [float(np.mean(result.corrected[k].wheels[a:b, i] /
                                    result.corrected[k].wheels[a:b].mean(axis=1)))
                      for k, a, b in wheel_units]
            axes[2].plot(t, values, ".", color=f"C{i}", label=f"{name} / mean (corrected)")
        axes[2].axhline(1.0, color="k", lw=0.5)
        axes[2].set_ylabel("wheel speed / mean")
        axes[2].set_title("each wheel against the mean on steady straights, after the "
                          "identified rolling radii")
        axes[2].legend(loc="upper right", fontsize=8, ncol=4)
    axes[2].set_xlabel("drive time [s] (logs one after another)")
    save(fig, path)
    return True


def plot_roll(result: Identification, path: Path) -> bool:
    diag = result.outcome.diagnostics.get("roll")
    if diag is None:
        return False
    from slipd.channels import G

    phi = np.concatenate([p[3] for p in diag["pieces"]])
    force = np.concatenate([p[4] for p in diag["pieces"]]) - G * phi
    step = max(1, len(phi) // 8000)
    fig = _figure(figsize=(7, 5))
    ax = fig.subplots()
    ax.plot(force[::step], np.degrees(phi[::step]), ".", ms=1, alpha=0.5)
    xs = np.linspace(force.min(), force.max(), 10)
    ax.plot(xs, np.degrees(diag["c"] * xs), "r-",
            label=f"fit; roll gradient {np.degrees(diag['gradient']) * G:.2f} deg/g of a_y,meas")
    ax.set_xlabel("tyres' lateral force / m = a_y,meas - g phi, band-passed [m/s^2]")
    ax.set_ylabel("roll (roll rate integrated), band-passed [deg]")
    ax.set_title("roll gradient")
    ax.legend()
    save(fig, path)
    return True


def write_report(result: Identification, folder: Path, extra_lines: list[str] = ()) -> list[Path]:
    """summary.txt and the figures into ``folder``; returns the files written."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, plot in (("handling_diagram.png", plot_handling),
                       ("fit_residuals.png", plot_residuals),
                       ("offsets.png", plot_offsets), ("roll_gradient.png", plot_roll)):
        if plot(result, folder / name):
            written.append(folder / name)
    summary = folder / "summary.txt"
    summary.write_text("\n".join([*summary_lines(result), *extra_lines,
                                  "", "figures: " + ", ".join(p.name for p in written)]) + "\n")
    return [summary, *written]
