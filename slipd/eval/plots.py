"""Plots of an evaluation, the two the papers draw: beta estimate vs truth over time and the
cumulative distribution of the absolute beta error (Righetti & Lenzo 2025, Figs. 8-9)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slipd.errors import DependencyError
from slipd.eval.metrics import Errors


def plot_evaluation(
    path: str | Path,
    truth_t: np.ndarray,
    truth_beta: np.ndarray,
    estimates: dict[str, tuple[np.ndarray, np.ndarray]],
    errors: dict[str, Errors],
    title: str = "",
) -> None:
    """Write a PNG: top, beta (deg) over time, truth in black and one colour per estimator;
    bottom, the CDF of |beta error| (deg) over the scored samples.

    ``estimates``: name -> (tick times, beta in rad) on the truth's time axis.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise DependencyError("--plot needs matplotlib: pip install 'slipd[plot]'") from exc

    fig, (ax_t, ax_cdf) = plt.subplots(2, 1, figsize=(10, 7.5), constrained_layout=True)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    ax_t.plot(truth_t, np.degrees(truth_beta), color="black", lw=1.6, label="truth")
    for i, (name, (t, beta)) in enumerate(estimates.items()):
        colour = colours[i % len(colours)]
        ax_t.plot(t, np.degrees(beta), color=colour, lw=1.0, label=name)
        err = errors.get(name)
        if err is not None and err.beta_err.size:
            e = np.sort(np.degrees(np.abs(err.beta_err)))
            ax_cdf.plot(e, np.arange(1, e.size + 1) / e.size, color=colour, label=name)
    ax_t.set_xlabel("time [s]")
    ax_t.set_ylabel("sideslip beta [deg]")
    ax_t.grid(True, alpha=0.3)
    ax_t.legend(loc="best", fontsize=8)
    if title:
        ax_t.set_title(title)
    ax_cdf.set_xlabel("|beta error| [deg]")
    ax_cdf.set_ylabel("cumulative fraction of samples")
    ax_cdf.set_ylim(0.0, 1.0)
    ax_cdf.grid(True, alpha=0.3)
    if ax_cdf.lines:
        ax_cdf.legend(loc="lower right", fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
