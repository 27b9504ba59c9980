"""Plots of a tracking result (:class:`bondgraph.inference.track.TrackResult`):
each tracked parameter with its ±2σ band, the detected changes and the truth."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from bondgraph.report.plots import pyplot


def plot_track(result, out_dir, *, truth: Mapping[str, float] | None = None) -> list[Path]:
    """One PNG per tracked parameter, ``track_<name>.png``.

    Parameters
    ----------
    result : TrackResult
        ``t (N,)``, ``estimate``/``std`` (N, k), optional ``smoothed``, ``changes``.
    out_dir : path
        Existing folder.
    truth : dict, optional
        Parameter -> a constant true value, or an array (N,) of its value
        per sample (a record's sidecar ``true_parameters``).

    Returns
    -------
    list of Path
    """
    plt = pyplot()
    out = []
    for i, name in enumerate(result.names):
        fig, ax = plt.subplots(figsize=(9, 4))
        est, sd = result.estimate[:, i], result.std[:, i]
        ax.fill_between(result.t, est - 2 * sd, est + 2 * sd, alpha=0.25, label="filtered ±2σ")
        ax.plot(result.t, est, lw=1.0, label="filtered")
        if result.smoothed is not None:
            ax.plot(result.t, result.smoothed[:, i], lw=1.0, ls="--", label="smoothed")
        if truth and name in truth:
            tv = np.broadcast_to(np.asarray(truth[name], float), result.t.shape)
            ax.plot(result.t, tv, color="k", lw=1.0, label="truth")
        for ch in result.changes:
            if ch.parameter == name:
                ax.axvline(ch.time, color="r", lw=1.0)
                ax.axvline(ch.alarm_time, color="r", lw=0.8, ls=":")
        ax.set_xlabel("t [s]")
        unit = result.units[i]
        ax.set_ylabel(f"{name} [{unit}]" if unit else name)
        ax.set_title(f"{name}: tracked (red: change, dotted: alarm)")
        ax.legend(loc="best", fontsize=8)
        path = Path(out_dir) / f"track_{name}.png"
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
        out.append(path)
    return out
