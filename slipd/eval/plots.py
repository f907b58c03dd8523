"""Plots of an evaluation.

:func:`plot_evaluation` draws the two figures the papers draw (Righetti & Lenzo 2025, Figs. 8-9:
beta estimate vs truth over time, the CDF of |beta error|) plus the error over time; a method's
line is drawn only where its frames said VALID (dotted where not), so a figure shows what a
controller would have trusted. :func:`plot_summary` draws a suite or the mismatch cases as
grouped bars: beta RMS per group and method, and the share of VALID ticks more than 5 deg off.

Colours: the Okabe-Ito colour-blind-safe palette (Okabe & Ito 2008, "Color Universal Design")
with a line style per cycle of it, so 13 methods stay distinguishable in print and in grey.
The file type follows the suffix (PNG, PDF, SVG).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from slipd.channels import Out, Status
from slipd.errors import ConfigError, DependencyError
from slipd.eval.metrics import Errors, Scores

OKABE_ITO = ("#E69F00", "#56B4E9", "#009E73", "#0072B2", "#D55E00", "#CC79A7", "#F0E442",
             "#000000")
LINE_STYLES = ("-", "--", "-.", ":")
SUFFIXES = (".png", ".pdf", ".svg")


def style(i: int) -> dict:
    """Colour and line style of the i-th method (distinct for 32 methods)."""
    return {"color": OKABE_ITO[i % len(OKABE_ITO)],
            "linestyle": LINE_STYLES[(i // len(OKABE_ITO)) % len(LINE_STYLES)]}


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise DependencyError("--plot needs matplotlib: pip install 'slipd[plot]'") from exc
    return plt


def _check_suffix(path: Path) -> None:
    if Path(path).suffix.lower() not in SUFFIXES:
        raise ConfigError(f"--plot {path}: expected a file ending in {', '.join(SUFFIXES)}")


def plot_evaluation(
    path: str | Path,
    truth_t: np.ndarray,
    truth_beta: np.ndarray,
    estimates: dict[str, tuple[np.ndarray, np.ndarray]],
    errors: dict[str, Errors],
    title: str = "",
) -> None:
    """Three panels: beta (deg) over time, truth in black, each method solid where VALID;
    the beta error over time (VALID ticks); the CDF of |beta error| over the scored ticks.

    ``estimates``: name -> (tick times on the truth's time axis, outputs [n, N_OUT]).
    """
    _check_suffix(Path(path))
    plt = _pyplot()
    fig, (ax_t, ax_e, ax_cdf) = plt.subplots(
        3, 1, figsize=(10, 10), constrained_layout=True,
        gridspec_kw={"height_ratios": [3, 2, 2]})
    ax_t.plot(truth_t, np.degrees(truth_beta), color="0.35", lw=2.2, label="truth", zorder=1)
    truth_at = {}
    for i, (name, (t, out)) in enumerate(estimates.items()):
        st = style(i)
        beta = np.degrees(out[:, Out.BETA])
        valid = (np.nan_to_num(out[:, Out.STATUS]).astype(np.int64) & int(Status.VALID)) != 0
        shown = np.where(valid, beta, np.nan)
        ax_t.plot(t, shown, lw=1.0, label=name, **st)
        ax_t.plot(t, np.where(valid, np.nan, beta), lw=0.6, alpha=0.5, color=st["color"],
                  linestyle=":")
        truth_at[name] = np.interp(t, truth_t, np.degrees(truth_beta))
        ax_e.plot(t, shown - truth_at[name], lw=0.8, label=name, **st)
        err = errors.get(name)
        if err is not None and err.beta_err.size:
            e = np.sort(np.degrees(np.abs(err.beta_err)))
            ax_cdf.plot(e, np.arange(1, e.size + 1) / e.size, label=name, **st)
    ax_t.set_ylabel("sideslip beta [deg]")
    ax_t.set_title((title + ": " if title else "")
                   + "estimates solid where VALID, dotted where not")
    ax_e.set_ylabel("beta error, VALID ticks [deg]")
    ax_e.set_xlabel("time [s]")
    for ax in (ax_t, ax_e):
        ax.grid(True, alpha=0.3)
    for level in (-5, -2, 2, 5):
        ax_e.axhline(level, color="0.5", lw=0.6, ls="--")
    ax_t.legend(loc="upper left", fontsize=7, ncol=4)
    ax_cdf.set_xscale("log")
    ax_cdf.set_xlabel("|beta error| [deg], all scored ticks")
    ax_cdf.set_ylabel("cumulative fraction")
    ax_cdf.set_ylim(0.0, 1.0)
    ax_cdf.grid(True, which="both", alpha=0.3)
    if ax_cdf.lines:
        ax_cdf.legend(loc="upper left", fontsize=7, ncol=2)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_summary(path: str | Path, groups: dict[str, dict[str, Scores]], title: str = "") -> None:
    """Grouped bars, one group per scenario (or mismatch case) and one bar per method: beta
    RMS over the scored ticks (top; log scale, the floors zero and linear_kf make the scale)
    and the share of VALID ticks more than 5 deg off (bottom)."""
    _check_suffix(Path(path))
    plt = _pyplot()
    names = list(groups)
    methods = list(dict.fromkeys(m for rows in groups.values() for m in rows))
    width = 0.8 / max(1, len(methods))
    fig, (ax_rms, ax_bad) = plt.subplots(
        2, 1, figsize=(max(10, 0.9 * len(names) * max(1, len(methods)) * 0.25 + 4), 8),
        constrained_layout=True)
    x = np.arange(len(names))
    for i, m in enumerate(methods):
        st = style(i)
        rms = [groups[g][m].beta_rms_deg if m in groups[g] else math.nan for g in names]
        bad = [100.0 * groups[g][m].valid_err_over_5deg if m in groups[g] else math.nan
               for g in names]
        offset = (i - (len(methods) - 1) / 2) * width
        hatch = {"-": None, "--": "//", "-.": "..", ":": "xx"}[st["linestyle"]]
        ax_rms.bar(x + offset, rms, width, color=st["color"], hatch=hatch, label=m,
                   edgecolor="white", linewidth=0.3)
        ax_bad.bar(x + offset, np.nan_to_num(bad), width, color=st["color"], hatch=hatch,
                   edgecolor="white", linewidth=0.3)
    ax_rms.set_yscale("log")
    ax_rms.set_ylabel("beta RMS [deg]")
    ax_bad.set_ylabel("VALID ticks > 5 deg off [%]")
    for ax in (ax_rms, ax_bad):
        ax.set_xticks(x)
        ax.set_xticklabels(names, rotation=30, ha="right", fontsize=8)
        ax.grid(True, axis="y", which="both", alpha=0.3)
    ax_rms.legend(fontsize=7, ncol=min(7, len(methods)), loc="upper left")
    if title:
        ax_rms.set_title(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
