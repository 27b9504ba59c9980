"""Scaled sigma points of the unscented transform, batched over parameter sets.

Weights (Wan & van der Merwe 2000; the scaled points of Julier 2002, in the
parametrisation of ``filterpy.kalman.MerweScaledSigmaPoints``)::

    λ = α²(n + κ) − n,  c = sqrt(n + λ) = α sqrt(n + κ)
    χ_0 = x̂,  χ_i = x̂ + c L_i,  χ_n+i = x̂ − c L_i     (L L^T = P, Cholesky)
    W_0^m = λ/(n+λ),  W_0^c = W_0^m + 1 − α² + β,  W_i = 1/(2(n+λ))

Means and covariances of transformed points are formed from differences to
the central point. With Σ W^m = 1 and equal weights W off the centre, the
weighted sums are exactly (d_i = χ_i − χ_0, m = W Σ d_i)::

    mean = χ_0 + m,   cov = W Σ d_i d_iᵀ + (β − α²) m mᵀ

which is the same quantity as Σ W_i^c (χ_i − mean)(χ_i − mean)ᵀ but does not
subtract numbers of size 1/α² (about 10⁶ at α = 1e-3): the filter stays
accurate and smooth for α from 1e-3 to 1.

Every function works on a leading batch axis (one entry per parameter set):
states ``(B, n)``, covariances ``(B, n, n)``, sigma points ``(B, 2n+1, n)``.

References
----------
Wan, E. A., van der Merwe, R. (2000). The unscented Kalman filter for
nonlinear estimation. Proc. IEEE AS-SPCC, 153-158.
Julier, S. J. (2002). The scaled unscented transformation. Proc. ACC.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bondgraph.errors import OptionError


@dataclass(frozen=True)
class SigmaWeights:
    """Scaled sigma-point weights (Merwe parametrisation).

    Attributes
    ----------
    n : int
        State dimension.
    alpha, beta, kappa : float
    lam : float
        λ = α²(n + κ) − n.
    c : float
        Spread factor sqrt(n + λ): sigma points at x̂ ± c·L_i.
    w : float
        Weight of every non-central point, 1 / (2(n + λ)).
    wm0, wc0 : float
        Central weights for the mean and the covariance.
    """

    n: int
    alpha: float
    beta: float
    kappa: float

    @property
    def lam(self) -> float:
        return self.alpha ** 2 * (self.n + self.kappa) - self.n

    @property
    def c(self) -> float:
        return float(np.sqrt(self.n + self.lam))

    @property
    def w(self) -> float:
        return 0.5 / (self.n + self.lam)

    @property
    def wm0(self) -> float:
        return self.lam / (self.n + self.lam)

    @property
    def wc0(self) -> float:
        return self.wm0 + 1.0 - self.alpha ** 2 + self.beta

    @property
    def center_cov(self) -> float:
        """Coefficient β − α² of m mᵀ in the difference form of the covariance."""
        return self.beta - self.alpha ** 2

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """``(Wm, Wc)`` of length 2n+1, as filterpy's ``MerweScaledSigmaPoints``."""
        Wm = np.full(2 * self.n + 1, self.w)
        Wc = Wm.copy()
        Wm[0] = self.wm0
        Wc[0] = self.wc0
        return Wm, Wc


def merwe_weights(n: int, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0) -> SigmaWeights:
    """Scaled sigma-point weights of Wan & van der Merwe (2000).

    Parameters
    ----------
    n : int
        State dimension (>= 1).
    alpha : float
        Spread, 0 < α <= 1 typically (1e-3 ... 1 supported).
    beta : float
        Prior-distribution term (2 is optimal for a Gaussian).
    kappa : float
        Secondary scaling; n + κ must be positive.

    Returns
    -------
    SigmaWeights

    Raises
    ------
    OptionError
        If α <= 0 or n + κ <= 0.
    """
    if n < 1:
        raise OptionError(f"sigma points need a state dimension >= 1, got {n}")
    if not np.isfinite(alpha) or alpha <= 0:
        raise OptionError(f"UKF alpha must be > 0, got {alpha}")
    if not np.isfinite(kappa) or n + kappa <= 0:
        raise OptionError(f"UKF kappa must make n + kappa > 0 (n = {n}), got kappa = {kappa}")
    if not np.isfinite(beta):
        raise OptionError(f"UKF beta must be finite, got {beta}")
    return SigmaWeights(int(n), float(alpha), float(beta), float(kappa))


def cholesky_batch(A: np.ndarray, regularise: bool = True, known: bool = False):
    """Lower Cholesky factors of symmetric matrices A (B, n, n).

    A matrix that fails is retried with relative diagonal loading
    A + ε diag(A), ε = 1e-12, 1e-9, 1e-6 (scale-invariant: each state in its
    own units), which absorbs the rounding-level indefiniteness of
    covariances contracted by fast stable modes without process noise.

    With ``known`` (state covariances), a state whose row and column of A
    are exactly zero is taken as known exactly: its row and column of L are
    zero and the rest is factorised as above. Its variance collapsed below
    the rounding of its mean (a stable lag driven by the input alone, without
    process noise: every sigma point of it rounds to the same value), and a
    semidefinite factor keeps its sigma points on the mean (Higham 1990,
    "Analysis of the Cholesky decomposition of a semi-definite matrix").
    Innovation covariances are never taken so: a zero variance there has
    no likelihood.

    Returns
    -------
    (L (B, n, n), ok (B,) bool, n_regularised int)
        Entries of L that failed (not finite, or not positive definite even
        with loading) are the identity.
    """
    ok = np.isfinite(A).all(axis=(-2, -1))
    if ok.all():
        try:
            return np.linalg.cholesky(A), ok, 0
        except np.linalg.LinAlgError:
            pass
    L = np.zeros_like(A)
    nreg = 0
    refused: list = []
    idx = np.flatnonzero(ok)
    if ok.all() and idx.size > STACK_MIN:        # the whole stack was refused above
        h = idx.size // 2
        _stacked_cholesky(A, idx[:h], L, refused)
        _stacked_cholesky(A, idx[h:], L, refused)
    else:
        _stacked_cholesky(A, idx, L, refused)
    for b in sorted(refused):
        loaded = _loaded_cholesky(A[b], known) if regularise else None
        if loaded is None:
            ok[b] = False
        else:
            L[b] = loaded
            nreg += 1
    L[~ok] = np.eye(A.shape[-1])
    return L, ok, nreg


#: a stack of at most this many matrices that holds a refused one is
#: factored one by one (:func:`_stacked_cholesky`)
STACK_MIN = 16


def _stacked_cholesky(A: np.ndarray, idx: np.ndarray, L: np.ndarray, refused: list) -> None:
    """Cholesky factors of ``A[idx]`` into ``L[idx]``, the indices numpy
    refuses appended to ``refused``: one stacked call, and where the stack
    holds a refused matrix its halves apart (one by one below
    :data:`STACK_MIN`), so that a few refused matrices among thousands cost
    a few stacked calls, not a Python call each (numpy factors every matrix
    of a stack alone: the factors are those of single calls)."""
    if idx.size > STACK_MIN:
        try:
            L[idx] = np.linalg.cholesky(A[idx])
            return
        except np.linalg.LinAlgError:
            h = idx.size // 2
            _stacked_cholesky(A, idx[:h], L, refused)
            _stacked_cholesky(A, idx[h:], L, refused)
            return
    for b in idx:
        try:
            L[b] = np.linalg.cholesky(A[b])
        except np.linalg.LinAlgError:
            refused.append(int(b))


def _loaded_cholesky(A: np.ndarray, known: bool = False) -> np.ndarray | None:
    """Cholesky factor of A + ε diag(A) for the first ε of 1e-12, 1e-9, 1e-6
    that works (None if none does or the diagonal is not positive); with
    ``known``, rows and columns that are exactly zero are left out of the
    factorisation (zero in L)."""
    d = np.diagonal(A).copy()
    keep = np.ones(len(d), bool)
    if known:
        keep = (A != 0.0).any(axis=1)
    if not keep.any():
        return np.zeros_like(A)
    if not (d[keep] > 0).all():
        return None
    sub = A[np.ix_(keep, keep)]
    for eps in (1e-12, 1e-9, 1e-6):
        try:
            Ls = np.linalg.cholesky(sub + np.diag(eps * d[keep]))
        except np.linalg.LinAlgError:
            continue
        if keep.all():
            return Ls
        L = np.zeros_like(A)
        L[np.ix_(keep, keep)] = Ls
        return L
    return None


def sigma_points(x: np.ndarray, L: np.ndarray, c: float) -> tuple[np.ndarray, np.ndarray]:
    """The 2n+1 scaled sigma points of means ``x`` (B, n) and Cholesky
    factors ``L`` (B, n, n).

    Returns
    -------
    chi : ndarray (B, 2n+1, n)
        χ_0 = x, χ_i = x + c L_i, χ_n+i = x − c L_i (L_i: column i of L).
    cL : ndarray (B, n, n)
        Rows are the scaled columns c L_i (the offsets of the points).
    """
    n = x.shape[-1]
    cL = c * np.swapaxes(L, -1, -2)
    chi = np.empty((x.shape[0], 2 * n + 1, n))
    chi[:, 0] = x
    chi[:, 1:n + 1] = x[:, None, :] + cL
    chi[:, n + 1:] = x[:, None, :] - cL
    return chi, cL


def unscented_moments(Z: np.ndarray, wts: SigmaWeights
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted mean and covariance of transformed sigma points, in the
    difference form (module docstring).

    Parameters
    ----------
    Z : array (B, 2n+1, m)
        Transformed sigma points (central point first).
    wts : SigmaWeights

    Returns
    -------
    mean : ndarray (B, m)
    cov : ndarray (B, m, m)
        Without any added noise.
    D : ndarray (B, 2n, m)
        Differences to the central point, Z_i − Z_0.
    """
    D = Z[:, 1:] - Z[:, :1]
    m = wts.w * D.sum(axis=1)
    mean = Z[:, 0] + m
    cov = wts.w * (np.swapaxes(D, 1, 2) @ D) + wts.center_cov * (m[:, :, None] * m[:, None, :])
    return mean, cov, D
