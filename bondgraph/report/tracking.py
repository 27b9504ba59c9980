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
        ``t (N,)``, ``estimate``/``std`` (N, k), optional ``smoothed``,
        ``changes`` and ``observable`` (N, k) (its stretches of False shaded grey).
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
        obs = getattr(result, "observable", None)
        if obs is not None:
            for j, (a, b) in enumerate(result.unobservable(name)):
                ax.axvspan(a, b, color="0.6", alpha=0.3, lw=0,
                           label="not observable" if j == 0 else None)
        for ch in result.changes:
            if ch.parameter == name:
                ax.axvline(ch.time, color="r", lw=1.0)
                ax.axvline(ch.alarm_time, color="r", lw=0.8, ls=":")
        ax.set_ylim(*_limits(result, i, truth.get(name) if truth else None))
        ax.set_xlabel("t [s]")
        unit = result.units[i]
        ax.set_ylabel(f"{name} [{unit}]" if unit else name)
        ax.set_title(f"{name}: tracked (red: change, dotted: alarm, grey: not observable)")
        ax.legend(loc="best", fontsize=8)
        path = Path(out_dir) / f"track_{name}.png"
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
        out.append(path)
    return out


def _limits(result, i: int, truth) -> tuple[float, float]:
    """The y range of parameter ``i``: its ±2σ band where it is observable
    (the whole record if it never is; 2nd to 98th percentile) and the
    truth, padded by 10 %; so that the start's and a restart's wide prior
    do not flatten a 1 % change."""
    est, sd = result.estimate[:, i], result.std[:, i]
    obs = getattr(result, "observable", None)
    keep = obs[:, i] if obs is not None and obs[:, i].any() else np.ones(est.size, bool)
    low, high = est[keep] - 2 * sd[keep], est[keep] + 2 * sd[keep]
    low, high = low[np.isfinite(low)], high[np.isfinite(high)]
    if low.size == 0 or high.size == 0:
        return -1.0, 1.0
    # the 2nd and 98th percentiles: a restart's wide prior lasts a few samples
    lo, hi = float(np.percentile(low, 2)), float(np.percentile(high, 98))
    if truth is not None:
        tv = np.broadcast_to(np.asarray(truth, float), est.shape)[keep]
        tv = tv[np.isfinite(tv)]
        if tv.size:
            lo, hi = min(lo, float(tv.min())), max(hi, float(tv.max()))
    pad = 0.1 * (hi - lo) if hi > lo else 0.05 * max(abs(hi), 1e-12)
    return lo - pad, hi + pad
