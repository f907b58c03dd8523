"""Plots of an evaluation, drawn to be read in print and by colour-blind readers.

:func:`plot_evaluation` draws one log: the beta estimates against the truth over time (Righetti
& Lenzo 2025, Figs. 8-9, draw the same), when each method was VALID, the beta error over time
on the VALID ticks, the CDF of |beta error| over the scored ticks and, optionally, the inputs
(ay, yaw rate, steer, speed). A method's estimate is drawn only where its frames said VALID
(dropped elsewhere) so the figure shows what a controller would have trusted; its VALID
spans are a strip of its own. Up to ``OVERLAY_MAX`` methods share the panels; more become
small multiples (one error panel per method on a common scale), since 13 lines on one axis
cannot be told apart.

:func:`plot_summary` draws a suite or the mismatch cases as two heatmaps (groups x methods):
beta RMS over the scored ticks and the share of VALID ticks more than 5 deg off, each cell
annotated; :func:`plot_summary_cdf` the pooled |beta error| distribution of each method from
the accumulators' histograms (no per-tick arrays).

Colours: the Okabe-Ito colour-blind-safe palette (Okabe & Ito 2008, "Color Universal Design")
without its black (the truth is black), with a line style per cycle of it; a method keeps its
colour and style in every figure (by its place in the registry). Figures are
``matplotlib.figure.Figure`` objects, not pyplot state, so they draw headless and display in
notebooks; the file type follows the suffix (PNG, PDF, SVG).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from slipd.channels import Out, Status
from slipd.errors import ConfigError, DependencyError
from slipd.eval.metrics import Accumulator, Errors, Scores, wrap_angle

#: Okabe-Ito without black, the hardest-to-see yellow last.
OKABE_ITO = ("#E69F00", "#56B4E9", "#009E73", "#0072B2", "#D55E00", "#CC79A7", "#F0E442")
LINE_STYLES = ("-", "--", "-.", ":")
HATCHES = {"-": None, "--": "//", "-.": "..", ":": "xx"}
SUFFIXES = (".png", ".pdf", ".svg")
#: Methods drawn on shared panels; more become small multiples.
OVERLAY_MAX = 4
TRUTH_COLOUR = "black"
INVALID_SHADE = "0.88"
#: The CDFs start here: errors below 0.01 deg are drawn at it (a perfect estimate).
CDF_FLOOR_DEG = 0.01
#: Input panels: name -> (label, SI -> display factor).
INPUT_PANELS = {
    "ay": ("ay [m/s$^2$]", 1.0),
    "yaw_rate": ("yaw rate [deg/s]", 180.0 / math.pi),
    "steer": ("steer [deg]", 180.0 / math.pi),
    "speed": ("speed [km/h]", 3.6),
}


def style(name_or_index: str | int) -> dict:
    """Colour and line style of a method: by its place in the registry (the same in every
    figure), or by position for a name slipd does not know. Distinct for 28 methods."""
    i = name_or_index
    if isinstance(name_or_index, str):
        from slipd.estimators.registry import available

        names = available()
        i = names.index(name_or_index) if name_or_index in names else len(names)
    return {"color": OKABE_ITO[i % len(OKABE_ITO)],
            "linestyle": LINE_STYLES[(i // len(OKABE_ITO)) % len(LINE_STYLES)]}


def _figure(**kwargs):
    try:
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise DependencyError("plots need matplotlib: pip install 'slipd[plot]'") from exc
    return Figure(layout="constrained", **kwargs)


def check_suffix(path: str | Path) -> None:
    if Path(path).suffix.lower() not in SUFFIXES:
        raise ConfigError(f"--plot {path}: expected a file ending in {', '.join(SUFFIXES)}")


def save(fig, path: str | Path | None) -> None:
    """Write ``fig`` to ``path`` (PNG at 150 dpi; PDF and SVG as vectors)."""
    if path is None:
        return
    check_suffix(path)
    try:
        fig.savefig(path, dpi=150)
    except OSError as exc:
        raise ConfigError(f"--plot {path}: cannot write: {exc.strerror or exc}") from exc


def _valid(out: np.ndarray) -> np.ndarray:
    return (np.nan_to_num(out[:, Out.STATUS]).astype(np.int64) & int(Status.VALID)) != 0


def _spans(t: np.ndarray, mask: np.ndarray, dt: float = 0.01) -> list[tuple[float, float]]:
    """(start, width) of each run of True in ``mask`` over ticks ``t``."""
    if not mask.any():
        return []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    starts, stops = edges[::2], edges[1::2] - 1
    return [(float(t[a]), float(t[b] - t[a] + dt)) for a, b in zip(starts, stops, strict=True)]


def _error_deg(t, out, truth_t, truth_beta) -> np.ndarray:
    beta_true = np.arctan2(np.interp(t, truth_t, np.sin(truth_beta)),
                           np.interp(t, truth_t, np.cos(truth_beta)))
    err = np.degrees(wrap_angle(out[:, Out.BETA] - beta_true))
    inside = (t >= truth_t[0]) & (t <= truth_t[-1])
    return np.where(inside, err, np.nan)


def _cdf(ax, errors: Errors | None, **st) -> None:
    if errors is None or not errors.beta_err.size:
        return
    e = np.sort(np.degrees(np.abs(errors.beta_err)))
    ax.plot(np.maximum(e, CDF_FLOOR_DEG), np.arange(1, e.size + 1) / e.size, lw=1.4, **st)


def _format_cdf(ax, lines: bool) -> None:
    ax.set_xscale("log")
    ax.set_xlim(left=CDF_FLOOR_DEG)
    ax.set_xlabel("|beta error| [deg], all scored ticks")
    ax.set_ylabel("cumulative fraction")
    ax.set_ylim(0.0, 1.0)
    for level in (2, 5):
        ax.axvline(level, color="0.5", lw=0.6, ls="--")
    ax.grid(True, which="both", alpha=0.3)
    if not lines:
        ax.text(0.5, 0.5, "no scored ticks", ha="center", va="center", transform=ax.transAxes)


def input_series(t: np.ndarray, channel) -> dict[str, tuple]:
    """The input panels' series: ``channel(name)`` -> (SI values, valid or None) or None for
    a channel the run lacks; speed is the mean of the four wheel speeds."""
    series = {}
    for name in ("ay", "yaw_rate", "steer"):
        got = channel(name)
        if got is not None:
            series[name] = (t, *got)
    wheels = [channel(f"wheel_speed_{w}") for w in ("fl", "fr", "rl", "rr")]
    if all(w is not None for w in wheels):
        values = np.mean([w[0] for w in wheels], axis=0)
        flags = [w[1] for w in wheels if w[1] is not None]
        series["speed"] = (t, values, np.logical_and.reduce(flags) if flags else None)
    return series


def _input_panels(axes, inputs: Mapping[str, tuple], t0: float) -> None:
    for ax, (name, (t, values, valid)) in zip(axes, inputs.items(), strict=True):
        label, factor = INPUT_PANELS.get(name, (name, 1.0))
        shown = np.where(valid, np.asarray(values) * factor, np.nan) if valid is not None \
            else np.asarray(values) * factor
        ax.plot(np.asarray(t) - t0, shown, color="0.25", lw=0.8)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(True, alpha=0.3)


def plot_evaluation(
    path: str | Path | None,
    truth_t: np.ndarray,
    truth_beta: np.ndarray,
    estimates: Mapping[str, tuple[np.ndarray, np.ndarray]],
    errors: Mapping[str, Errors],
    title: str = "",
    inputs: Mapping[str, tuple] | None = None,
    overlay_max: int = OVERLAY_MAX,
    t0: float | None = None,
):
    """One log's figure; returns the Figure (written to ``path`` when given).

    ``estimates``: name -> (tick times, outputs [n, N_OUT]) on the truth's time axis;
    ``errors``: name -> the scored errors (slipd.eval.metrics.errors) for the CDF;
    ``inputs``: optional name -> (t, SI values, valid or None) for the input panels (keys of
    INPUT_PANELS draw with their units); ``t0``: time shown as 0 (default: the truth's start).
    """
    if path is not None:
        check_suffix(path)
    truth_t = np.asarray(truth_t, dtype=np.float64)
    truth_beta = np.asarray(truth_beta, dtype=np.float64)
    t0 = float(truth_t[0]) if t0 is None else t0
    inputs = dict(inputs or {})
    if len(estimates) > overlay_max:
        fig = _small_multiples(truth_t, truth_beta, estimates, errors, inputs, t0)
    else:
        fig = _overlay(truth_t, truth_beta, estimates, errors, inputs, t0)
    if title:
        fig.suptitle(title, fontsize=11)
    save(fig, path)
    return fig


def _overlay(truth_t, truth_beta, estimates, errors, inputs, t0):
    n = len(estimates)
    heights = [1.0] * len(inputs) + [3.0, 0.35 + 0.22 * n, 2.0, 2.2]
    fig = _figure(figsize=(10, 1.5 + 0.85 * sum(heights)))
    axes = fig.subplots(len(heights), 1, gridspec_kw={"height_ratios": heights})
    time_axes = list(axes[:-1])
    for ax in time_axes[1:]:
        ax.sharex(time_axes[0])
    _input_panels(axes[: len(inputs)], inputs, t0)
    ax_beta, ax_valid, ax_err, ax_cdf = axes[len(inputs):]
    ax_beta.plot(truth_t - t0, np.degrees(truth_beta), color=TRUTH_COLOUR, lw=2.0,
                 label="truth", zorder=1)
    for row, (name, (t, out)) in enumerate(estimates.items()):
        st = style(name)
        valid = _valid(out)
        tr = t - t0
        ax_beta.plot(tr, np.where(valid, np.degrees(out[:, Out.BETA]), np.nan), lw=1.3,
                     label=name, zorder=2, **st)
        err = _error_deg(t, out, truth_t, truth_beta)
        ax_err.plot(tr, np.where(valid, err, np.nan), lw=1.0, **st)
        y = n - 1 - row
        ax_valid.broken_barh([(a - t0, w) for a, w in _spans(t, valid)], (y + 0.15, 0.7),
                             color=st["color"], hatch=HATCHES[st["linestyle"]],
                             edgecolor="white", linewidth=0)
        ax_valid.broken_barh([(a - t0, w) for a, w in _spans(t, ~valid)], (y + 0.15, 0.7),
                             color=INVALID_SHADE)
        _cdf(ax_cdf, errors.get(name), label=name, **st)
    ax_beta.set_ylabel("sideslip beta [deg]")
    ax_beta.set_title("estimates where VALID (not drawn where not)", fontsize=8, loc="right")
    ax_beta.legend(loc="lower left", bbox_to_anchor=(0.0, 1.0), fontsize=8, ncol=n + 1,
                   frameon=False, borderaxespad=0.2)
    ax_valid.set_yticks(np.arange(n) + 0.5, list(estimates)[::-1], fontsize=7)
    ax_valid.set_ylim(0, max(n, 1))
    ax_valid.set_title("VALID (colour) / not VALID (grey)", fontsize=8, loc="left")
    ax_err.set_ylabel("beta error [deg]\nVALID ticks")
    for level in (-5, -2, 2, 5):
        ax_err.axhline(level, color="0.5", lw=0.6, ls="--")
    ax_err.axhline(0.0, color="0.3", lw=0.6)
    ax_err.set_xlabel("time [s]")
    for ax in (*time_axes[: len(inputs)], ax_beta, ax_err):
        ax.grid(True, alpha=0.3)
    for ax in time_axes[:-1]:
        ax.tick_params(labelbottom=False)
    _format_cdf(ax_cdf, bool(ax_cdf.lines))
    if ax_cdf.lines:
        ax_cdf.legend(loc="upper left", fontsize=8)
    return fig


def _small_multiples(truth_t, truth_beta, estimates, errors, inputs, t0):
    names = list(estimates)
    cols = 2
    rows = math.ceil(len(names) / cols)
    top = len(inputs) + 1
    heights = [1.0] * len(inputs) + [1.6] + [1.3] * rows + [2.6]
    fig = _figure(figsize=(12, 1.0 + 0.9 * sum(heights)))
    grid = fig.add_gridspec(len(heights), cols, height_ratios=heights)
    first = fig.add_subplot(grid[0, :])
    shared = [first] + [fig.add_subplot(grid[k, :], sharex=first) for k in range(1, top)]
    _input_panels(shared[: len(inputs)], inputs, t0)
    ax_truth = shared[-1]
    ax_truth.plot(truth_t - t0, np.degrees(truth_beta), color=TRUTH_COLOUR, lw=1.5)
    ax_truth.set_ylabel("truth beta [deg]", fontsize=8)
    ax_truth.set_title("the truth; below, each method's beta error on its VALID ticks (grey: "
                       "not VALID, nothing a controller may use)", fontsize=8)
    ax_truth.grid(True, alpha=0.3)
    for ax in shared:
        ax.tick_params(labelbottom=False)
    valid_err = [np.abs(_error_deg(t, o, truth_t, truth_beta))[_valid(o)]
                 for t, o in estimates.values()]
    pooled = np.concatenate([e[np.isfinite(e)] for e in valid_err]) if valid_err else []
    limit = float(np.clip(np.percentile(pooled, 99.5) * 1.15, 2.5, 15.0)) if len(pooled) else 5
    ax_cdf = fig.add_subplot(grid[-1, :])
    for k, name in enumerate(names):
        t, out = estimates[name]
        ax = fig.add_subplot(grid[top + k // cols, k % cols], sharex=first)
        st = style(name)
        valid = _valid(out)
        err = _error_deg(t, out, truth_t, truth_beta)
        for a, w in _spans(t, ~valid):
            ax.axvspan(a - t0, a - t0 + w, color=INVALID_SHADE, lw=0)
        ax.plot(t - t0, np.where(valid, err, np.nan), lw=0.9, **st)
        for level in (-5, -2, 2, 5):
            ax.axhline(level, color="0.6", lw=0.5, ls="--")
        ax.axhline(0.0, color="0.3", lw=0.5)
        ax.set_ylim(-limit, limit)
        ax.grid(True, alpha=0.25)
        scores = errors[name].scores() if name in errors else None
        ax.text(0.005, 0.97, _panel_label(name, scores), transform=ax.transAxes, fontsize=7,
                va="top", ha="left", bbox={"facecolor": "white", "alpha": 0.8, "lw": 0})
        if k // cols < rows - 1 and k + cols < len(names):
            ax.tick_params(labelbottom=False)
        else:
            ax.set_xlabel("time [s]", fontsize=8)
        if k % cols == 0:
            ax.set_ylabel("error [deg]", fontsize=8)
        _cdf(ax_cdf, errors.get(name), label=name, **st)
    _format_cdf(ax_cdf, bool(ax_cdf.lines))
    if ax_cdf.lines:
        ax_cdf.legend(loc="upper left", fontsize=7, ncol=2)
    return fig


def _panel_label(name: str, s: Scores | None) -> str:
    if s is None:
        return name
    def pct(v: float) -> str:
        return "-" if math.isnan(v) else f"{100 * v:.1f} %"
    rms = "-" if math.isnan(s.beta_rms_deg) else f"{s.beta_rms_deg:.2f}"
    return f"{name}: RMS {rms} deg, VALID {pct(s.valid_fraction)}, " \
           f"VALID>5deg {pct(s.valid_err_over_5deg)}"


def plot_summary(path: str | Path | None, groups: Mapping[str, Mapping[str, Scores]],
                 title: str = "", pooled: Mapping[str, Scores] | None = None):
    """Two heatmaps, one row per scenario (or mismatch case) and one column per method:
    beta RMS over the scored ticks [deg] (log colour scale) and the share of VALID ticks
    more than 5 deg off [%]; each cell carries its value ('never' where the method was
    never VALID). ``pooled`` adds a last row. Returns the Figure (written to ``path``)."""
    if path is not None:
        check_suffix(path)
    rows = dict(groups)
    if pooled is not None:
        rows["pooled"] = pooled
    names = list(rows)
    methods = list(dict.fromkeys(m for r in rows.values() for m in r))
    rms = np.array([[rows[g][m].beta_rms_deg if m in rows[g] else math.nan for m in methods]
                    for g in names])
    bad = np.array([[100 * rows[g][m].valid_err_over_5deg if m in rows[g] else math.nan
                     for m in methods] for g in names])
    never = np.array([[m in rows[g] and rows[g][m].valid_samples == 0 for m in methods]
                      for g in names])
    from matplotlib.colors import LogNorm, Normalize

    fig = _figure(figsize=(3.0 + 0.62 * len(methods), 2.6 + 0.56 * len(names)))
    ax_rms, ax_bad = fig.subplots(2, 1, sharex=True)
    finite = rms[np.isfinite(rms) & (rms > 0)]
    norm = LogNorm(vmin=max(finite.min(), 1e-2), vmax=finite.max()) if finite.size else None
    _heatmap(ax_rms, rms, "viridis_r", norm, "{:.2f}", None, fig, "beta RMS [deg]")
    _heatmap(ax_bad, bad, "magma_r", Normalize(0, max(5.0, np.nanmax(bad) if np.isfinite(
        bad).any() else 5.0)), "{:.1f}", never, fig, "VALID ticks > 5 deg off [%]")
    ax_bad.set_xticks(np.arange(len(methods)), methods, rotation=40, ha="right", fontsize=8)
    for ax in (ax_rms, ax_bad):
        ax.set_yticks(np.arange(len(names)), names, fontsize=8)
    if pooled is not None:
        for ax in (ax_rms, ax_bad):
            ax.axhline(len(names) - 1.5, color="white", lw=2)
    if title:
        fig.suptitle(title, fontsize=11)
    save(fig, path)
    return fig


def _heatmap(ax, values, cmap, norm, fmt, never, fig, label) -> None:
    shown = np.ma.masked_invalid(values)
    image = ax.imshow(shown, cmap=cmap, norm=norm, aspect="auto")
    ax.set_facecolor("0.92")
    from matplotlib.ticker import FormatStrFormatter

    bar = fig.colorbar(image, ax=ax, shrink=0.8, pad=0.01)
    bar.set_label(label, fontsize=8)
    bar.ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
    bar.ax.yaxis.set_minor_formatter(FormatStrFormatter("%g"))
    bar.ax.tick_params(labelsize=7, which="both")
    ax.set_title(label, fontsize=9)
    cmap_obj = image.cmap
    for (i, j), v in np.ndenumerate(values):
        if never is not None and never[i, j]:
            text, dark = "never", False
        elif not np.isfinite(v):
            text, dark = "-", False
        else:
            text = fmt.format(v)
            r, g, b, _ = cmap_obj(image.norm(v))
            dark = 0.299 * r + 0.587 * g + 0.114 * b < 0.5
        ax.text(j, i, text, ha="center", va="center", fontsize=6.5,
                color="white" if dark else "black")


def plot_summary_cdf(path: str | Path | None, pooled: Mapping[str, Accumulator],
                     title: str = "", methods: Sequence[str] | None = None):
    """The pooled CDF of |beta error| per method from the accumulators' histograms: over all
    scored ticks and, for up to OVERLAY_MAX methods, over the VALID ticks only (dotted).
    Returns the Figure (written to ``path``)."""
    if path is not None:
        check_suffix(path)
    fig = _figure(figsize=(10, 5.5))
    ax = fig.subplots()
    names = list(methods or pooled)
    valid_too = len(names) <= OVERLAY_MAX
    for name in names:
        st = style(name)
        x, f = pooled[name].cdf()
        if x.size:
            ax.plot(np.maximum(x, CDF_FLOOR_DEG), f, lw=1.4, label=name, **st)
        xv, fv = pooled[name].cdf(valid_only=True)
        if valid_too and xv.size:
            ax.plot(np.maximum(xv, CDF_FLOOR_DEG), fv, lw=0.9, color=st["color"], linestyle=":")
    _format_cdf(ax, bool(ax.lines))
    ax.set_xlabel("|beta error| [deg], all scored ticks" + (
        " (line) and VALID ticks only (dotted)" if valid_too else ""))
    if ax.lines:
        ax.legend(loc="upper left", fontsize=8, ncol=2)
    if title:
        ax.set_title(title, fontsize=10)
    save(fig, path)
    return fig
