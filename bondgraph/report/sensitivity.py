"""Plots of a sensitivity and identifiability analysis."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bondgraph.report.plots import pyplot
from bondgraph.sensitivity.analysis import SensitivityReport


def plot_report(report: SensitivityReport, outdir: str | Path) -> list[Path]:
    """PNG plots of a :class:`SensitivityReport`.

    ``tornado.png``: first-order and total Sobol' indices of the NLL with
    confidence bars (global), or the relative information sqrt(F̃_jj) per
    parameter (local only); ``heatmap_s2.png``: second-order indices
    (global only); ``correlation.png``: |cos| between scaled sensitivity
    directions of all candidates and the Cramér-Rao correlations of the
    recommended set; ``sensitivities.png``: scaled output sensitivities
    s_j ∂y/∂θ_j / σ along the record (when integrated).

    Returns
    -------
    list of Path
    """
    plt = pyplot()
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    title = f"{report.model} on {report.experiment}"
    paths = [_tornado(plt, report, title, outdir / "tornado.png")]
    g = report.global_
    if g and g.get("second_order"):
        paths.append(_heatmap_s2(plt, report, title, outdir / "heatmap_s2.png"))
    paths.append(_correlation(plt, report, title, outdir / "correlation.png"))
    if report.sensitivities is not None:
        paths.append(_sensitivities(plt, report, title, outdir / "sensitivities.png"))
    return paths


def _tornado(plt, report: SensitivityReport, title: str, p: Path) -> Path:
    """Sobol' indices S1 and ST of the NLL with confidence bars (global), or
    the normalised relative information per parameter (local only)."""
    names = report.params
    rec = report.recommendation
    g = report.global_
    k = len(names)
    fig, ax = plt.subplots(figsize=(7.5, 0.38 * k + 1.6))
    if g:
        ind = g["indices"]["NLL"]
        ST, S1 = np.asarray(ind["ST"]), np.asarray(ind["S1"])
        order = np.argsort(ST)
        yy = np.arange(k)
        ax.barh(yy + 0.2, ST[order], 0.4, xerr=np.asarray(ind["ST_conf"])[order], label="total ST",
                color="C1", capsize=2)
        ax.barh(yy - 0.2, S1[order], 0.4, xerr=np.asarray(ind["S1_conf"])[order],
                label="first-order S1", color="C0", capsize=2)
        what = "ln(1 + NLL − min)" if g.get("nll_transform", "none") != "none" else "the NLL"
        ax.set_xlabel(f"Sobol' index of {what} ({int(100 * g['conf_level'])} % confidence bars)")
        ax.set_title(f"{title}\nSobol' indices, N = {g['N']} ({g['evaluations']} UKF runs)",
                     fontsize=9)
        ax.legend(loc="lower right", fontsize=8)
    else:
        v = np.asarray(report.local["relative_information"], float)
        v = v / (v.max() if v.max() > 0 else 1.0)
        order = np.argsort(v)
        yy = np.arange(k)
        est = set(rec["estimate"])
        ax.barh(yy, v[order], color=["C2" if names[i] in est else "0.6" for i in order])
        ax.set_xlabel("relative information sqrt(F̃_jj), normalised (green: recommended)")
        ax.set_title(f"{title}\nlocal sensitivity of the UKF likelihood", fontsize=9)
    ax.set_yticks(yy)
    ax.set_yticklabels([names[i] for i in order])
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def _heatmap_s2(plt, report: SensitivityReport, title: str, p: Path) -> Path:
    """Second-order Sobol' indices (symmetrised); those within their confidence
    interval of 0 in parentheses."""
    names = report.params
    g = report.global_
    k = len(names)
    S2 = np.asarray(g["indices"]["NLL"]["S2"], float)
    C2 = np.asarray(g["indices"]["NLL"]["S2_conf"], float)
    M = np.where(np.isfinite(S2), S2, 0.0)
    M = M + M.T
    Cf = np.where(np.isfinite(C2), C2, 0.0)
    Cf = Cf + Cf.T
    sig = np.abs(M) > Cf                       # outside its confidence interval
    fig, ax = plt.subplots(figsize=(0.45 * k + 3.0, 0.45 * k + 2.4))
    vmax = max(float(np.abs(M).max()), 1e-6)
    im = ax.imshow(M, cmap="RdBu_r", vmin=-vmax, vmax=vmax)
    ax.set_xticks(range(k))
    ax.set_yticks(range(k))
    ax.set_xticklabels(names, rotation=60, ha="right", fontsize=8)
    ax.set_yticklabels(names, fontsize=8)
    for i in range(k):
        for j in range(k):
            if i != j and abs(M[i, j]) >= 0.01:
                ax.text(j, i, f"{M[i, j]:.2f}" if sig[i, j] else f"({M[i, j]:.2f})",
                        ha="center", va="center", fontsize=6,
                        color="k" if sig[i, j] else "0.45")
    fig.colorbar(im, ax=ax, shrink=0.8, label="S2")
    ax.set_title(f"{title}\nsecond-order Sobol' indices of the NLL (in parentheses: "
                 f"within the {int(100 * g['conf_level'])} % confidence interval of 0)",
                 fontsize=8)
    fig.tight_layout()
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def _correlation(plt, report: SensitivityReport, title: str, p: Path) -> Path:
    """|cos| between the scaled sensitivity directions of all candidates and,
    for a recommended set of two or more, its Cramér-Rao correlations."""
    names = report.params
    rec = report.recommendation
    k = len(names)
    C = np.asarray(report.local["identifiability"]["cosine"], float)
    ck = rec.get("check")
    est = rec["estimate"]
    ncol = 2 if ck and len(est) > 1 else 1
    fig, axes = plt.subplots(1, ncol, figsize=(0.42 * k * ncol + 3.5 * ncol, 0.42 * k + 2.6),
                             squeeze=False)
    ax = axes[0, 0]
    im = ax.imshow(C, cmap="RdBu_r", vmin=-1, vmax=1)
    ax.set_xticks(range(k))
    ax.set_yticks(range(k))
    ax.set_xticklabels(names, rotation=60, ha="right", fontsize=7)
    ax.set_yticklabels(names, fontsize=7)
    ax.set_title("cos between scaled sensitivity directions\n(all candidates)", fontsize=9)
    fig.colorbar(im, ax=ax, shrink=0.8)
    if ncol == 2:
        ax = axes[0, 1]
        R = np.asarray(ck["corr"], float)
        im = ax.imshow(R, cmap="RdBu_r", vmin=-1, vmax=1)
        ke = len(est)
        ax.set_xticks(range(ke))
        ax.set_yticks(range(ke))
        ax.set_xticklabels(est, rotation=60, ha="right", fontsize=8)
        ax.set_yticklabels(est, fontsize=8)
        for i in range(ke):
            for j in range(ke):
                ax.text(j, i, f"{R[i, j]:.2f}", ha="center", va="center", fontsize=6)
        ax.set_title("Cramér-Rao correlations\n(recommended set)", fontsize=9)
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def _sensitivities(plt, report: SensitivityReport, title: str, p: Path) -> Path:
    """Scaled output sensitivities θ_j ∂y/∂θ_j / σ_y along the record, the six
    strongest parameters, one axis per output."""
    names = report.params
    s = report.sensitivities
    # the noise levels that weighed the output-error information (a model
    # from a file has no registered name to look its sensors up by)
    oe = (report.local or {}).get("output_error") or {}
    sigma = np.asarray(oe.get("sigma", np.ones(len(s.outputs))), float)
    Z = s.scaled(sigma)
    ny = len(s.outputs)
    strength = np.sqrt(np.nansum(Z ** 2, axis=(0, 1)))
    top = np.argsort(-strength)[:6]
    fig, axes = plt.subplots(ny, 1, figsize=(10, 1.9 * ny + 0.8), sharex=True, squeeze=False)
    for j in range(ny):
        ax = axes[j, 0]
        for c_, i in enumerate(top):
            ax.plot(s.t, Z[:, j, i], lw=0.8, color=f"C{c_}", label=names[i])
        ax.set_ylabel(f"{s.outputs[j]}", fontsize=8)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, ncol=3, loc="best")
    axes[0, 0].set_title(f"{title}: scaled sensitivities θ_j ∂y/∂θ_j / σ_y (largest 6)",
                         fontsize=9)
    axes[-1, 0].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(p, dpi=100)
    plt.close(fig)
    return p
