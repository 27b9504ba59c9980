"""Plots of an estimation: the fit of the outputs and the innovations."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bondgraph.inference.estimand import X0_PREFIX, Estimand
from bondgraph.inference.estimate import EstimationResult
from bondgraph.inference.options import UKFOptions
from bondgraph.inference.record import record_arrays, state_vector
from bondgraph.inference.ukf import default_P0, ukf_nll
from bondgraph.numerics.model import Model
from bondgraph.report.plots import pyplot


def filter_of(model, result: EstimationResult, x0: np.ndarray, P0: np.ndarray):
    """The filter of the estimate: ``(x0 (n_x,), P0, R (1, n_y, n_y) or
    None)`` with the estimated initial states (``x0.<state>``, token prior
    spread) and the noise levels the estimation used
    (``settings["noise_levels"]``, declared or estimated)."""
    x0 = np.array(x0, dtype=float)
    values = dict(zip(result.params, np.asarray(result.estimates, float).tolist()))
    states = [n[len(X0_PREFIX):] for n in result.params if n.startswith(X0_PREFIX)]
    for s_ in states:
        x0[model.state_index(s_)] = values[X0_PREFIX + s_]
    levels = result.settings.get("noise_levels") or {}
    sigma = np.array([levels[o]["std"] if o in levels and levels[o].get("how") != "model"
                      else np.nan for o in model.outputs], dtype=float)
    P = np.asarray(P0, float)
    scale = np.sqrt(np.diag(P) if P.ndim == 2 else P)
    est = Estimand(model, [], states=states, theta=result.theta, x0=x0, sigma=sigma,
                   x0_scale=scale)
    return x0, (est.prior_cov(P) if states else P), est.expand(est.value()[None, :])[2]


def plot_fit(model, experiment, result: EstimationResult, outdir: str | Path, *,
             x0=None, P0=None, options=None, prefix: str = "") -> list[Path]:
    """PNG plots of the fit at the estimate: measured vs predicted and
    filtered outputs, and innovations with ±2 sqrt(S) bands.

    Parameters
    ----------
    model : Model or str
    experiment : Experiment, path or (t, u, y)
    result : EstimationResult
    outdir : path
    x0, P0 : optional
        As given to :func:`estimate` (default: from ``result.settings``).
    options : UKFOptions, optional
        The filter's options (default: from ``result.settings``; a joint
        estimate's record may have its own).

    Returns
    -------
    list of Path
        ``fit_outputs.png`` and ``innovations.png`` (with ``prefix``).
    """
    plt = pyplot()
    model = Model.from_spec(model)
    t, u, y, name, _ = record_arrays(model, experiment)
    opts = UKFOptions(**result.settings.get("ukf", {})) if options is None else options
    x0a = np.asarray(result.settings.get("x0"), float) if x0 is None else state_vector(model, x0)
    if P0 is None:
        P0 = result.settings.get("P0")
    P0a = default_P0(model, x0a) if P0 is None else np.asarray(P0, float)
    x0a, P0a, R = filter_of(model, result, x0a, P0a)
    r = ukf_nll(model, t, u, y, result.theta[None, :], x0a, P0a, options=opts, R=R,
                store=True)
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    ny = model.n_y
    fig, axes = plt.subplots(ny, 1, figsize=(10, 2.6 * ny + 0.6), sharex=True, squeeze=False)
    for j in range(ny):
        ax = axes[j, 0]
        ax.plot(t, y[:, j], ".", ms=2, color="0.5", label="measured")
        ax.plot(t, r.y_pred[:, 0, j], lw=1.0, label="predicted ŷ(k|k-1)")
        ax.plot(t, r.y_filt[:, 0, j], lw=0.8, ls="--", label="filtered h(x̂(k|k))")
        ax.set_ylabel(f"{model.outputs[j]} [{model.output_units[j] or '-'}]")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="best", fontsize=8)
    axes[0, 0].set_title(f"{model.name} on {name}: NLL {result.nll:.2f}")
    axes[-1, 0].set_xlabel("t [s]")
    fig.tight_layout()
    p1 = outdir / f"{prefix}fit_outputs.png"
    fig.savefig(p1, dpi=110)
    plt.close(fig)
    fig, axes = plt.subplots(ny, 1, figsize=(10, 2.4 * ny + 0.6), sharex=True, squeeze=False)
    for j in range(ny):
        ax = axes[j, 0]
        e = r.innovations[:, 0, j]
        s = np.sqrt(r.S[:, 0, j, j])
        ax.plot(t, e, lw=0.6, label="innovation ε")
        ax.fill_between(t, -2 * s, 2 * s, color="C1", alpha=0.25, label="±2 sqrt(S)")
        inside = np.mean(np.abs(e[np.isfinite(e)]) <= 2 * s[np.isfinite(e)]) if np.isfinite(e).any() else np.nan
        ax.set_ylabel(f"ε {model.outputs[j]} [{model.output_units[j] or '-'}]")
        ax.set_title(f"{model.outputs[j]}: {inside:.1%} within ±2σ", fontsize=9)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="best", fontsize=8)
    axes[-1, 0].set_xlabel("t [s]")
    fig.tight_layout()
    p2 = outdir / f"{prefix}innovations.png"
    fig.savefig(p2, dpi=110)
    plt.close(fig)
    return [p1, p2]
