"""Residual analysis of a fitted model: what the innovations say.

For each output: bias, RMS, whiteness of the standardised innovations
(Ljung-Box), normalised-innovation-squared (NIS) consistency,
spectral peaks (Welch periodogram, scipy), and where in the record the
residual is large: the correlation ratio η² of the squared standardised
innovation over bins of each operating variable (states, inputs, outputs,
and the sign of flows that change sign).

References
----------
Ljung, G. M., Box, G. E. P. (1978). On a measure of lack of fit in time
series models. Biometrika 65(2), 297-303.
Bar-Shalom, Y., Li, X. R., Kirubarajan, T. (2001). Estimation with
Applications to Tracking and Navigation, §5.4 (NIS consistency test).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from bondgraph.core.deferred import chi2


@dataclass
class OutputResiduals:
    """Residual statistics of one output.

    Attributes
    ----------
    name, unit : str
    n : int
        Number of samples with a measurement.
    bias, rms : float
        Mean and RMS of the innovation [output unit].
    bias_sigma : float
        Bias over its standard error (|z| > 3 is a significant bias).
    ljung_box_q, ljung_box_p : float
        Ljung-Box statistic of the standardised innovation at ``lags`` and
        its p-value (small p: not white).
    lags : int
    nis_mean : float
        Mean of ε²/S for this output (1 for a consistent filter).
    peak_hz, peak_ratio : float
        Frequency of the largest spectral peak of the standardised
        innovation and its power over the median power.
    sim_rms : float or None
        RMS of the free-run simulation error, if a simulation was given.
    """

    name: str
    unit: str
    n: int
    bias: float
    rms: float
    bias_sigma: float
    ljung_box_q: float
    ljung_box_p: float
    lags: int
    nis_mean: float
    peak_hz: float
    peak_ratio: float
    sim_rms: float | None = None
    sim_bias: float | None = None


@dataclass
class Region:
    """Where the residual is large: output, operating variable, bin edges,
    mean squared standardised innovation per bin, η² (fraction of the
    variance of the squared innovation explained by the bins)."""

    output: str
    variable: str
    edges: list[float]
    mean_sq: list[float]
    eta2: float

    def worst_bin(self) -> tuple[float, float, float]:
        """Lower and upper edge and mean ε²/S of the bin with the largest mean."""
        i = int(np.argmax(self.mean_sq))
        return self.edges[i], self.edges[i + 1], self.mean_sq[i]


@dataclass
class ResidualReport:
    """Result of :func:`analyze`."""

    outputs: list[OutputResiduals]
    regions: list[Region]
    nis_mean: float
    nis_dof: float
    nis_bounds: tuple[float, float]
    whiteness: float
    settings: dict = field(default_factory=dict)

    @property
    def whiteness_dof(self) -> float:
        """Degrees of freedom of :attr:`whiteness` (lags x outputs): a sum of
        Ljung-Box statistics of white innovations is about χ²(dof)."""
        return float(self.settings.get("whiteness_dof", 0.0))

    def is_white(self, z: float = 3.0) -> bool:
        """Whiteness statistic within ``z`` standard deviations of its
        expectation under white innovations (χ²(dof): mean dof, var 2 dof)."""
        d = self.whiteness_dof
        return d > 0 and self.whiteness <= d + z * np.sqrt(2 * d)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready statistics (outputs, regions, NIS, whiteness)."""
        return {"outputs": [asdict(o) for o in self.outputs],
                "regions": [asdict(r) for r in self.regions],
                "nis_mean": self.nis_mean, "nis_dof": self.nis_dof,
                "nis_bounds": list(self.nis_bounds), "whiteness": self.whiteness}

    def table(self) -> str:
        """Markdown table of the per-output statistics."""
        rows = ["| output | bias | RMS | bias/σ | Ljung-Box p | NIS | peak Hz |",
                "|---|---|---|---|---|---|---|"]
        for o in self.outputs:
            if not o.n:
                rows.append(f"| {o.name} | not in the record | | | | | |")
                continue
            rows.append(f"| {o.name} | {o.bias:.4g} | {o.rms:.4g} | {o.bias_sigma:.1f} | "
                        f"{o.ljung_box_p:.2g} | {o.nis_mean:.2f} | {o.peak_hz:.3g} |")
        return "\n".join(rows)

    def top_regions(self, k: int = 5) -> list[Region]:
        """The ``k`` regions with the largest η²."""
        return sorted(self.regions, key=lambda r: -r.eta2)[:k]


def _ljung_box(z: np.ndarray, lags: int) -> tuple[float, float]:
    """The Ljung-Box statistic Q = n (n + 2) Σ_{k=1..h} r_k² / (n − k) of the
    finite samples of ``z`` (n) at ``h = lags``, r_k the sample
    autocorrelation (autocovariances of the demeaned series over n, as
    statsmodels' ``acorr_ljungbox``), and its p-value under χ²(h) (Ljung &
    Box 1978). Each r_k is one dot product, O(n h): statsmodels correlates
    the whole series with itself (O(n²), 0.24 s a call on 18 600 samples).
    NaN, NaN for fewer than h + 5 samples or a constant series."""
    z = z[np.isfinite(z)]
    if z.size < lags + 5 or np.std(z) == 0:
        return float("nan"), float("nan")
    x = z - z.mean()
    x = x - x.mean()
    n = x.size
    c0 = float(np.dot(x, x))
    r = np.array([np.dot(x[:-k], x[k:]) for k in range(1, lags + 1)]) / c0
    q = float(n * (n + 2) * np.sum(r ** 2 / (n - np.arange(1, lags + 1))))
    return q, float(chi2.sf(q, lags))


def _peak(z: np.ndarray, fs: float) -> tuple[float, float]:
    z = z[np.isfinite(z)]
    if z.size < 32:
        return float("nan"), float("nan")
    from scipy.signal import welch      # deferred: scipy.signal costs the command line's start

    f, p = welch(z - z.mean(), fs=fs, nperseg=min(256, z.size // 2))
    if p.size < 3:
        return float("nan"), float("nan")
    i = int(np.argmax(p[1:])) + 1
    med = float(np.median(p[1:])) or 1e-300
    return float(f[i]), float(p[i] / med)


def _eta2(v: np.ndarray, s: np.ndarray, bins: int = 5) -> tuple[float, list, list]:
    ok = np.isfinite(v) & np.isfinite(s)
    v, s = v[ok], s[ok]
    if v.size < 4 * bins or np.ptp(v) == 0 or np.var(s) == 0:
        return 0.0, [], []
    edges = np.unique(np.quantile(v, np.linspace(0, 1, bins + 1)))
    if edges.size < 3:
        return 0.0, [], []
    idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, edges.size - 2)
    means, counts = [], []
    for b in range(edges.size - 1):
        m = idx == b
        means.append(float(s[m].mean()) if m.any() else 0.0)
        counts.append(int(m.sum()))
    grand = s.mean()
    between = sum(c * (m - grand) ** 2 for c, m in zip(counts, means))
    total = float(((s - grand) ** 2).sum())
    return float(between / total) if total > 0 else 0.0, edges.tolist(), means


def analyze(ukf, model, t, u, y, *, p: int = 0, sim_y: np.ndarray | None = None,
            lags: int | None = None) -> ResidualReport:
    """Analyse the innovations of parameter set ``p`` of a stored UKF run.

    Parameters
    ----------
    ukf : UKFResult
        From :func:`bondgraph.inference.ukf.ukf_nll` with ``store=True``.
    model : Model
    t : array (N,)
    u : array (N, n_u)
    y : array (N, n_y)
        Measurements (NaN where missing).
    p : int
        Which parameter set of the run.
    sim_y : array (N, n_y), optional
        Free-run simulated outputs, for simulation-error statistics.
    lags : int, optional
        Ljung-Box lag (default min(20, N/10), at least 5).

    Returns
    -------
    ResidualReport
        Per-output statistics, operating regions, NIS consistency and the
        whiteness total (sum of the Ljung-Box statistics, Ljung & Box 1978).
    """
    eps = ukf.innovations[:, p, :]
    N, ny = eps.shape
    z = standardised_innovations(ukf, p)
    dt = float(np.median(np.diff(t))) if N > 1 else 1.0
    lags = lags or int(max(5, min(20, N // 10)))
    outs = [_output_residuals(model, i, eps[:, i], z[:, i], lags, dt, y, sim_y)
            for i in range(ny)]
    nis_mean, nis_dof, bounds = _nis_consistency(ukf, p, z)
    regions = _regions(model, z, _operating_variables(ukf, model, p, u, y))
    white = float(np.nansum([o.ljung_box_q for o in outs]))
    white_dof = float(lags * sum(1 for o in outs if np.isfinite(o.ljung_box_q)))
    return ResidualReport(outs, regions, nis_mean, nis_dof, bounds, white,
                          {"lags": lags, "p": p, "whiteness_dof": white_dof})


#: an innovation further than this many robust std (1.4826 × the median
#: absolute deviation of the output's standardised innovations) from their
#: median is an outlier when its neighbours are not (:func:`isolated_outliers`):
#: under Gaussian innovations one in 8e14 samples
OUTLIER_Z = 8.0
#: ... and the measured samples before and after it lie within this many
#: robust std (a single-sample glitch; a model error lasts longer)
OUTLIER_NEIGHBOUR = 4.0
#: more isolated outliers than this share of an output's samples are no
#: glitches: the innovations are heavy-tailed (the model's error)
OUTLIER_SHARE = 0.01
#: ... and they are named only when they carry at least this share of the
#: output's squared deviations (they inflate its noise level by that much
#: at least): EMPS's encoder has one isolated sample at 8.2-11 robust std
#: among 4968 at the bundled loop's fits, 1.4-1.9 % of the sum (a reversal
#: the friction law misses, no glitch worth a word); a cart's six 2 m/s
#: speed glitches, 98 %
OUTLIER_WEIGHT = 0.05


def isolated_outliers(z) -> tuple[np.ndarray, float]:
    """The samples of one output whose standardised innovation ``z`` (N,)
    is an isolated outlier: further than :data:`OUTLIER_Z` robust std from
    the median (the scale 1.4826 × the median absolute deviation, which a
    few glitches do not move, unlike the noise std they inflate), the
    measured samples before and after it within :data:`OUTLIER_NEIGHBOUR`.
    A sensor's glitch (a dropped bit, a spike) is such a sample; a missing
    effect shows as runs of large innovations. Empty when there are more
    than :data:`OUTLIER_SHARE` of the measured samples (heavy tails, not
    glitches), when they carry less than :data:`OUTLIER_WEIGHT` of the
    squared deviations (they change nothing), or the scale is 0. Hampel's identifier (Hampel 1974; Pearson
    2002) on the innovations, with the isolation rule added.

    Parameters
    ----------
    z : array (N,)
        Standardised innovations, NaN where nothing was measured.

    Returns
    -------
    (indices, largest) : (array of int, float)
        Sample indices, largest deviation first, and the largest deviation
        in robust std (NaN when there are none).
    """
    z = np.asarray(z, float)
    ok = np.flatnonzero(np.isfinite(z))
    if ok.size < 10:
        return np.zeros(0, int), float("nan")
    v = z[ok]
    med = float(np.median(v))
    scale = 1.4826 * float(np.median(np.abs(v - med)))
    if not scale > 0:
        return np.zeros(0, int), float("nan")
    r = np.abs(v - med) / scale
    big = r > OUTLIER_Z
    prev = np.concatenate([[0.0], r[:-1]])
    nxt = np.concatenate([r[1:], [0.0]])
    hit = np.flatnonzero(big & (prev <= OUTLIER_NEIGHBOUR) & (nxt <= OUTLIER_NEIGHBOUR))
    if hit.size == 0 or hit.size > OUTLIER_SHARE * ok.size \
            or np.sum(r[hit] ** 2) < OUTLIER_WEIGHT * np.sum(r ** 2):
        return np.zeros(0, int), float("nan")
    hit = hit[np.argsort(-r[hit])]
    return ok[hit], float(r[hit[0]])


def standardised_innovations(ukf, p: int = 0) -> np.ndarray:
    """The innovations of parameter set ``p`` of a stored UKF run over
    their predicted std, ε_k / sqrt(S_k,ii) (N, n_y); NaN where nothing was
    measured."""
    S = ukf.S[:, p, :, :]
    sd = np.sqrt(np.maximum(np.einsum("kii->ki", S), 1e-300))
    return ukf.innovations[:, p, :] / sd


def innovation_outlier_warnings(ukf, names, t, where: str = "", p: int = 0) -> list[str]:
    """One warning per output with isolated outliers
    (:func:`isolated_outliers`) in the standardised innovations of a stored
    UKF run (parameter set ``p``): how many, when (the first five times of
    ``t`` (N,) [s]), how large, what they do to the fit and how to leave
    them out (an empty cell is a missing sample the filter skips). ``names``
    are the outputs, ``where`` the record ("" for none). Computed on demand
    (the loop's final model, an estimate), not in every :func:`analyze`."""
    return _column_outliers(standardised_innovations(ukf, p), names, t, where,
                            "the filter's prediction")


def free_run_outlier_warnings(errors, names, t, where: str = "") -> list[str]:
    """:func:`innovation_outlier_warnings` for the free-run errors ``errors`` (N, n_y)
    (measured minus simulated, NaN where nothing was measured) of a record
    the filter does not run on (the loop's held-out record): a glitch there
    moves the error the accept rule judges by."""
    return _column_outliers(errors, names, t, where, "the free run")


def _column_outliers(values, names, t, where: str, against: str) -> list[str]:
    """:func:`_outlier_text` for each column of ``values`` (N, n_y) with
    isolated outliers (:func:`isolated_outliers`)."""
    v = np.asarray(values, float)
    v = v.reshape(v.shape[0], -1)
    out = []
    for j, name in enumerate(names):
        idx, largest = isolated_outliers(v[:, j])
        if idx.size:
            out.append(_outlier_text(name, [int(k) for k in idx], largest, t, where, against))
    return out


def _outlier_text(name: str, idx, largest: float, t, where: str, against: str) -> str:
    """The warning of :func:`innovation_outlier_warnings`."""
    t = np.asarray(t, float)
    n = len(idx)
    when = ", ".join(f"{t[k]:.6g}" for k in sorted(idx)[:5]) + (", ..." if n > 5 else "")
    return (f"{name}{' on ' + where if where else ''}: {n} isolated sample{'s' if n > 1 else ''} "
            f"lie{'' if n > 1 else 's'} more than {OUTLIER_Z:g} robust std from {against}, "
            f"their neighbours within {OUTLIER_NEIGHBOUR:g} (t = {when} s; the largest "
            f"{largest:.3g} std): single-sample glitches of the sensor, or events the model "
            f"lacks. Glitches inflate the estimated noise level and every std, and move the "
            f"errors a model is judged by (in the loop, which effect it finds). If they are "
            f"faults, leave those cells empty (the filter skips a missing sample) and run again")


def _output_residuals(model, i: int, e: np.ndarray, z: np.ndarray, lags: int, dt: float,
                      y: np.ndarray, sim_y: np.ndarray | None) -> OutputResiduals:
    """Statistics of output ``i`` from its innovation ``e`` (N,) and
    standardised innovation ``z`` (N,); simulation error if ``sim_y``."""
    name = model.outputs[i]
    ok = np.isfinite(e)
    n = int(ok.sum())
    if n == 0:
        nan = float("nan")
        return OutputResiduals(name, model.output_units[i], 0, bias=nan, rms=nan,
                               bias_sigma=nan, ljung_box_q=nan, ljung_box_p=nan, lags=lags,
                               nis_mean=nan, peak_hz=nan, peak_ratio=nan)
    bias = float(e[ok].mean())
    rms = float(np.sqrt(np.mean(e[ok] ** 2)))
    se = float(e[ok].std(ddof=1) / np.sqrt(n)) if n > 1 else float("inf")
    q, pv = _ljung_box(z, lags)
    fpk, ratio = _peak(z, 1.0 / dt)
    o = OutputResiduals(name, model.output_units[i], n, bias, rms, bias / se if se > 0 else 0.0,
                        q, pv, lags, float(np.nanmean(z[ok] ** 2)), fpk, ratio)
    if sim_y is not None:
        d = y[:, i] - sim_y[:, i]
        okd = np.isfinite(d)
        if okd.any():
            with np.errstate(over="ignore"):      # a diverging free run: inf
                o.sim_rms = float(np.sqrt(np.mean(d[okd] ** 2)))
            o.sim_bias = float(d[okd].mean())
    return o


def _nis_consistency(ukf, p: int, z: np.ndarray) -> tuple[float, float, tuple[float, float]]:
    """Mean NIS per filter step, its degrees of freedom per step, and the 95 %
    bounds of the mean: N · mean(NIS) ~ χ²(Σ m_k) (Bar-Shalom et al. 2001)."""
    nis = ukf.nis[:, p] if ukf.nis is not None else np.nansum(z**2, axis=1)
    used = ukf.n_obs > 0
    dof = float(ukf.n_obs[used].sum())
    tot = float(np.nansum(nis[used]))
    lo, hi = chi2.ppf([0.025, 0.975], dof) if dof > 0 else (0.0, 0.0)
    nk = max(int(used.sum()), 1)
    return tot / nk, dof / nk, (float(lo / nk), float(hi / nk))


def _operating_variables(ukf, model, p: int, u, y) -> dict[str, np.ndarray]:
    """Filtered states, varying inputs and measured outputs, by name."""
    variables: dict[str, np.ndarray] = {}
    if ukf.x_filt is not None:
        for j, s in enumerate(model.states):
            variables[s] = ukf.x_filt[:, p, j]
    for j, nme in enumerate(model.inputs):
        if u is not None and u.shape[1] > j and np.ptp(u[:, j]) > 0:
            variables[nme] = u[:, j]
    for j, nme in enumerate(model.outputs):
        if np.isfinite(y[:, j]).any():          # an output the record lacks is all NaN
            variables[f"{nme} (measured)"] = y[:, j]
    return variables


def _regions(model, z: np.ndarray, variables: dict[str, np.ndarray]) -> list[Region]:
    """η² of each output's squared standardised innovation over quantile bins
    of each operating variable, and over its sign where it changes sign."""
    regions = []
    for i, name in enumerate(model.outputs):
        s2 = z[:, i] ** 2
        for vname, v in variables.items():
            e2, edges, means = _eta2(v, s2)
            if edges:
                regions.append(Region(name, vname, edges, means, e2))
            if np.nanmin(v) < 0 < np.nanmax(v):
                sgn = np.sign(v)
                e2s, _, means_s = _eta2(sgn + 1e-9 * np.arange(sgn.size) / sgn.size, s2, bins=2)
                if means_s:
                    regions.append(Region(name, f"sign({vname})", [-1.0, 0.0, 1.0], means_s, e2s))
    return regions
