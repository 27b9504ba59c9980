"""Bode plot of a linearisation (:class:`bondgraph.export.linearize.Linearization`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bondgraph.report.plots import pyplot


def bode_frequencies(lin, n: int = 400) -> np.ndarray:
    """Angular frequencies [rad/s], shape (n,): two decades either side of
    the poles' magnitudes (0.1 to 10 rad/s without poles)."""
    mags = np.abs(lin.poles())
    mags = mags[mags > 0]
    lo, hi = (mags.min() / 100, mags.max() * 100) if mags.size else (0.1, 10.0)
    return np.logspace(np.log10(lo), np.log10(hi), n)


def bode_plot(lin, path: str | Path, w=None) -> Path:
    """Write the Bode plot (magnitude in dB, phase in degrees against ω in
    rad/s) of every input-output pair of ``lin`` as a PNG.

    Parameters
    ----------
    lin : Linearization
    path : str or Path
        The PNG to write.
    w : array (n_w,), optional
        Angular frequencies [rad/s] (default :func:`bode_frequencies`).

    Returns
    -------
    Path
    """
    plt = pyplot()
    w = bode_frequencies(lin) if w is None else np.asarray(w, dtype=float)
    G = lin.freqresp(w)
    fig, (ax_m, ax_p) = plt.subplots(2, 1, sharex=True, figsize=(8, 6))
    for i, out in enumerate(lin.outputs):
        for j, inp in enumerate(lin.inputs):
            g = G[:, i, j]
            if not np.any(np.abs(g) > 0):
                continue
            with np.errstate(divide="ignore"):
                ax_m.semilogx(w, 20 * np.log10(np.abs(g)), label=f"{inp} -> {out}")
            ax_p.semilogx(w, np.degrees(np.unwrap(np.angle(g))))
    ax_m.set_ylabel("magnitude [dB]")
    ax_p.set_ylabel("phase [deg]")
    ax_p.set_xlabel("angular frequency [rad/s]")
    ax_m.set_title(f"{lin.model}: linearised at "
                   f"{'an equilibrium' if lin.equilibrium else 'the given point'}")
    if ax_m.lines:
        ax_m.legend(fontsize="small")
    for ax in (ax_m, ax_p):
        ax.grid(True, which="both", alpha=0.3)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
