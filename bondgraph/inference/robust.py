"""Standard deviations that hold when the model is wrong: the sandwich
(robust) covariance of a maximum-likelihood estimate, and the long-run
variance of a serially correlated series.

The Cramér-Rao bound inv(F) is the covariance of the estimate only when the
model and its noise description are right: then the scores (the per-sample
gradients of the NLL) are uncorrelated in time and their sum has the
variance F (the information-matrix equality). When the model lacks an
effect, or its noise levels do not describe the misfit, the innovations are
serially correlated, the scores are too, and inv(F) can understate the
estimate's spread by orders of magnitude (a friction the model lacks,
absorbed into its damper, fitted to ±0.02 % with a true spread of ±1 %).
The sandwich

    cov = H⁻¹ J H⁻¹,   J = Newey-West long-run covariance of the scores g_t

(White 1982 for misspecified models; Newey & West 1987 for the serial
correlation; Bollerslev & Wooldridge 1992 and Watson 1989 for the
prediction-error likelihood of a filter) holds either way, and equals
inv(F) when the model is right. Its ratio to the Cramér-Rao std is a check
of the model: well above 1, the printed precision is not to be trusted.

References
----------
White, H. (1982). Maximum likelihood estimation of misspecified models.
Econometrica 50(1), 1-25.
Newey, W. K., West, K. D. (1987). A simple, positive semi-definite,
heteroskedasticity and autocorrelation consistent covariance matrix.
Econometrica 55(3), 703-708.
Andrews, D. W. K. (1991). Heteroskedasticity and autocorrelation consistent
covariance matrix estimation. Econometrica 59(3), 817-858.
Bollerslev, T., Wooldridge, J. M. (1992). Quasi-maximum likelihood
estimation and inference in dynamic models with time-varying covariances.
Econometric Reviews 11(2), 143-172.
"""

from __future__ import annotations

import numpy as np

#: ratio of the robust to the Cramér-Rao std above which a result warns that
#: its Cramér-Rao std understates the estimate's uncertainty (the model's
#: misfit is serially correlated)
ROBUST_RATIO = 3.0
#: largest lag-1 autocorrelation the AR(1) plug-in uses (a unit root would
#: make the bandwidth infinite)
RHO_MAX = 0.97


def andrews_bandwidth(d: np.ndarray) -> int:
    """Bandwidth of the Bartlett kernel by Andrews' (1991) AR(1) plug-in rule.

    L = ⌊1.1447 (α n)^(1/3)⌋ with, for the columns a of ``d`` standardised,
    their lag-1 autocorrelations ρ_a (clipped to ±:data:`RHO_MAX`) and unit
    weights, α = Σ_a 4ρ_a²σ_a⁴/((1−ρ_a)⁶(1+ρ_a)²) / Σ_a σ_a⁴/(1−ρ_a)⁴,
    σ_a² = 1 − ρ_a² (Andrews 1991, eq. 6.4); for one series α = 4ρ²/(1 − ρ²)².

    Parameters
    ----------
    d : array (n,) or (n, k)
        The series (rows in time).

    Returns
    -------
    int
        0 ≤ L < n/2 (0 for fewer than 4 rows or no variance).
    """
    x = np.asarray(d, float)
    x = x.reshape(x.shape[0], -1)
    n = x.shape[0]
    x = x - x.mean(axis=0)
    g0 = np.einsum("na,na->a", x, x) / n
    keep = g0 > 0
    if n < 4 or not keep.any():
        return 0
    x, g0 = x[:, keep], g0[keep]
    rho = np.clip(np.einsum("na,na->a", x[1:], x[:-1]) / n / g0, -RHO_MAX, RHO_MAX)
    s4 = (1 - rho**2) ** 2                       # innovation variance², unit-variance AR(1)
    num = np.sum(4 * rho**2 * s4 / ((1 - rho) ** 6 * (1 + rho) ** 2))
    den = np.sum(s4 / (1 - rho) ** 4)
    alpha = num / den
    return int(max(min(np.floor(1.1447 * (alpha * n) ** (1 / 3)), n // 2 - 1), 0))


def long_run_variance(d: np.ndarray, bandwidth: int | None = None) -> float:
    """Newey-West (1987) long-run variance of the series ``d`` (n,):
    γ₀ + 2 Σ_{l≤L} (1 − l/(L+1)) γ_l (autocovariances with divisor n),
    L = ``bandwidth`` or :func:`andrews_bandwidth`. n·Var(d̄) for a
    stationary series."""
    n = d.size
    x = d - d.mean()
    g0 = float(x @ x) / n
    if n < 3 or g0 <= 0:
        return g0
    L = andrews_bandwidth(d) if bandwidth is None else int(bandwidth)
    lrv = g0
    for lag in range(1, max(L, 0) + 1):
        lrv += 2 * (1 - lag / (L + 1)) * float(x[lag:] @ x[:-lag]) / n
    return max(lrv, 0.0)


def step_scores(eps: np.ndarray, S: np.ndarray, dE: np.ndarray, dS: np.ndarray) -> np.ndarray:
    """Per-sample scores of the prediction-error NLL, ½ Σ_t [ln det S_t + ε_tᵀ S_t⁻¹ ε_t].

    g_ti = ε_tᵀ S_t⁻¹ ∂ε_t/∂θ_i + ½ tr(S_t⁻¹ ∂S_t/∂θ_i) − ½ ε_tᵀ S_t⁻¹ ∂S_t/∂θ_i S_t⁻¹ ε_t
    (Kristensen, Madsen & Jørgensen 2004, eq. 15); Σ_t g_t is the gradient.

    Parameters
    ----------
    eps : array (N, m)
        Innovations (0 where not measured).
    S : array (N, m, m)
        Their covariances (identity where not measured).
    dE : array (k, N, m)
        ∂ε/∂θ.
    dS : array (k, N, m, m)
        ∂S/∂θ.

    Returns
    -------
    array (N, k)
    """
    Sinv = np.linalg.inv(S)
    a = np.einsum("nij,nj->ni", Sinv, eps)
    SdS = np.einsum("nab,knbc->knac", Sinv, dS)
    return (np.einsum("na,kna->nk", a, dE) + 0.5 * np.einsum("knaa->nk", SdS)
            - 0.5 * np.einsum("na,knab,nb->nk", a, dS, a))


def score_covariance(G: np.ndarray, bandwidth: int | None = None) -> np.ndarray:
    """Newey-West long-run covariance of the scores, J = Σ_{|l|≤L} w_l Σ_t g_t g_{t−l}ᵀ.

    Parameters
    ----------
    G : array (N, k)
        Per-sample scores (:func:`step_scores`), rows in time; the scores of
        independent records are summed over records by the caller.
    bandwidth : int, optional
        L (default :func:`andrews_bandwidth` of G); Bartlett weights
        w_l = 1 − l/(L+1) (statsmodels' ``S_hac_simple``).

    Returns
    -------
    array (k, k)
        The variance of Σ_t g_t (not divided by N).
    """
    G = np.asarray(G, float)
    L = andrews_bandwidth(G) if bandwidth is None else int(bandwidth)
    # deferred: statsmodels (and pandas under it) cost the command line's start ~0.7 s
    from statsmodels.stats.sandwich_covariance import S_hac_simple, weights_bartlett

    return S_hac_simple(G, nlags=L, weights_func=weights_bartlett)


def sandwich(H: np.ndarray, J: np.ndarray) -> np.ndarray | None:
    """The robust covariance H⁻¹ J H⁻¹ (White 1982).

    Parameters
    ----------
    H : array (k, k)
        Hessian of the NLL at the estimate (or the Fisher information).
    J : array (k, k)
        Long-run covariance of the scores (:func:`score_covariance`).

    Returns
    -------
    array (k, k) or None
        None when H is not finite or not positive definite.
    """
    H = 0.5 * (np.asarray(H, float) + np.asarray(H, float).T)
    if not (np.isfinite(H).all() and np.isfinite(J).all()):
        return None
    d = np.sqrt(np.abs(np.diag(H)))
    if not (d > 0).all():
        return None
    Hs = H / np.outer(d, d)
    try:
        np.linalg.cholesky(Hs)
    except np.linalg.LinAlgError:
        return None
    Hinv = np.linalg.inv(Hs) / np.outer(d, d)
    C = Hinv @ J @ Hinv
    return 0.5 * (C + C.T)


def lr_scale(H: np.ndarray, G: np.ndarray, idx) -> tuple[float, np.ndarray] | None:
    """How far serially correlated scores inflate the likelihood-ratio
    statistic of the parameters ``idx`` (q of the k).

    Where the model or its noise description is wrong, 2 (NLL₀ − NLL₁) of
    nested models is not χ²(q) but Σ λ_j χ²₁ (independent), λ the
    eigenvalues of [(H⁻¹)_qq]⁻¹ (H⁻¹ J H⁻¹)_qq, the tested block of the
    robust covariance over that of the Cramér-Rao bound (Kent 1982; Vuong
    1989, Theorem 3.3). The mean scale c = Σλ/q divides the statistic, and
    LR/c is referred to χ²(q) (Satorra & Bentler 1994). A right model gives
    J = H and c = 1; for q = 1, c is the squared ratio of the robust to the
    Cramér-Rao std (:func:`robust_std`).

    Parameters
    ----------
    H : array (k, k)
        Hessian of the NLL at the larger model's estimate (or its Fisher
        information).
    G : array (N, k)
        Its per-sample scores (:func:`step_scores`).
    idx : sequence of int
        The tested parameters' positions in H.

    Returns
    -------
    (c, λ (q,)) or None
        None when H is not positive definite (:func:`sandwich`) or the
        tested block cannot be solved.

    References
    ----------
    Kent, J. T. (1982). Robust properties of likelihood ratio tests.
    Biometrika 69(1), 19-27. Vuong, Q. H. (1989). Likelihood ratio tests for
    model selection and non-nested hypotheses. Econometrica 57(2), 307-333.
    Satorra, A., Bentler, P. M. (1994). Corrections to test statistics and
    standard errors in covariance structure analysis. In Latent Variables
    Analysis (von Eye & Clogg, eds.), 399-419.
    """
    idx = list(idx)
    V = sandwich(H, score_covariance(G))
    if V is None or not idx:
        return None
    H = 0.5 * (np.asarray(H, float) + np.asarray(H, float).T)
    d = np.sqrt(np.diag(H))
    Hinv = np.linalg.inv(H / np.outer(d, d)) / np.outer(d, d)
    A, B = Hinv[np.ix_(idx, idx)], V[np.ix_(idx, idx)]
    try:
        M = np.linalg.solve(A, B)
    except np.linalg.LinAlgError:
        return None
    lam = np.sort(np.linalg.eigvals(M).real)
    c = float(np.trace(M)) / len(idx)
    return (c, lam) if np.isfinite(c) and c > 0 else None


def robust_std(H: np.ndarray, G: np.ndarray) -> np.ndarray:
    """Robust (sandwich) standard deviations, (k,), NaN when H is not
    positive definite (:func:`sandwich` of H and :func:`score_covariance` of G)."""
    C = sandwich(H, score_covariance(G))
    k = np.asarray(H).shape[0]
    return np.full(k, np.nan) if C is None else np.sqrt(np.maximum(np.diag(C), 0.0))
