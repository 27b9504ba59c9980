"""The error measure the loop reports before and after (``LoopSettings.metric``)."""

from __future__ import annotations

import numpy as np

from bondgraph.diagnose.settings import LoopSettings

_NAMES = {"nrmse_sim": "free-run simulation NRMSE (RMS error / std of the measurement, "
                       "mean over outputs)",
          "rmse_sim": "free-run simulation RMS error (over outputs, output units)",
          "rmse_pred": "RMS of the one-step-ahead innovations (output units)"}


def metric_name(settings: LoopSettings) -> str:
    """Name of the metric in logs and reports: ``settings.metric_name``, the
    ``name`` (or ``__name__``) of a callable metric, or the description of a
    built-in one."""
    if settings.metric_name:
        return settings.metric_name
    m = settings.metric
    if callable(m):
        return getattr(m, "name", getattr(m, "__name__", "custom metric"))
    return _NAMES.get(m, str(m))


def compute_metric(settings: LoopSettings, fit, record) -> float:
    """The reported error of a fit.

    Parameters
    ----------
    settings : LoopSettings
        ``settings.metric``: ``"nrmse_sim"`` (mean over outputs of the RMS
        free-run simulation error over the std of the measurement),
        ``"rmse_sim"`` (RMS over outputs, output units), ``"rmse_pred"``
        (RMS of the one-step innovations), or ``metric(fit, record)``.
    fit : Fit
        Needs ``model``, ``ukf`` (stored run) and ``sim_y`` (N, n_y) or None.
    record : MetricRecord
        The measured record (:class:`bondgraph.diagnose.fit.MetricRecord`).

    Returns
    -------
    float
        The error; inf when the free run failed (``sim_y`` None) or no
        output has two measured samples.
    """
    m = settings.metric
    t, u, y = record.arrays(fit.model)
    if callable(m):
        return float(m(fit, record))
    if m == "rmse_pred":
        e = fit.ukf.innovations[:, 0, :]
        return float(np.sqrt(np.nanmean(e**2)))
    if fit.sim_y is None:
        return float("inf")
    err = y - fit.sim_y
    if m == "rmse_sim":
        return float(np.sqrt(np.nanmean(err**2)))
    return nrmse(y, fit.sim_y)


def nrmse(y: np.ndarray, sim_y: np.ndarray) -> float:
    """``nrmse_sim``: mean over the outputs with two or more finite errors of
    RMS(y − sim_y)/std(y) over those samples; inf when there is none.

    Parameters
    ----------
    y, sim_y : array (N, n_y)
        Measured and simulated outputs (NaN where missing).
    """
    err = y - sim_y
    vals = []
    for i in range(y.shape[1]):
        ok = np.isfinite(err[:, i])
        if ok.sum() < 2:
            continue
        sd = np.nanstd(y[ok, i])
        with np.errstate(over="ignore"):      # a diverging free run: inf
            vals.append(np.sqrt(np.mean(err[ok, i] ** 2)) / (sd if sd > 0 else 1.0))
    return float(np.mean(vals)) if vals else float("inf")


def standardised_errors(y: np.ndarray, sim_y: np.ndarray | None) -> np.ndarray | None:
    """Free-run errors (N, n_y) ``y − sim_y``, each output divided by the std
    of its measurement (the normalisation of ``nrmse_sim``); NaN where a
    sample is missing. None if the free run failed (``sim_y`` None)."""
    if sim_y is None:
        return None
    err = np.asarray(y, dtype=float) - np.asarray(sim_y, dtype=float)
    out = np.full_like(err, np.nan)
    for i in range(err.shape[1]):
        ok = np.isfinite(err[:, i])
        if ok.sum() < 2:
            continue
        sd = np.nanstd(y[ok, i])
        out[:, i] = err[:, i] / (sd if sd > 0 else 1.0)
    return out


def metric_errors(settings: LoopSettings, fit, record) -> np.ndarray | None:
    """Per-sample errors (N, k) of the metric ``settings.metric`` that the
    accept rule's error-decrease test compares between two fits (test 5 of
    :mod:`bondgraph.diagnose.accept`): the standardised free-run errors for
    ``nrmse_sim`` and ``rmse_sim``, the innovations for ``rmse_pred``, and
    for a callable metric its ``errors(fit, record)`` method if it has one.
    None when the metric has no per-sample errors (a callable without
    ``errors``: the test is then not made, rather than made on errors the
    metric does not measure) or the free run failed."""
    m = settings.metric
    if callable(m):
        errors = getattr(m, "errors", None)
        return None if errors is None else np.asarray(errors(fit, record), dtype=float)
    if m == "rmse_pred":
        return np.asarray(fit.ukf.innovations[:, 0, :], dtype=float)
    _, _, y = record.arrays(fit.model)
    return standardised_errors(y, fit.sim_y)
