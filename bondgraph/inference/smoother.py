"""Unscented Rauch-Tung-Striebel smoother: the states of a record given all
of it, and with them the smoothed initial state.

The forward pass is the toolkit's UKF (:func:`bondgraph.inference.ukf.ukf_nll`
with ``store="full"``). The backward pass (Särkkä 2008, Algorithm 3.2)
re-propagates sigma points of each filtered posterior (x̂_k|k, P_k|k)
through the filter's own transition and input hold, and with their
predicted mean m⁻, covariance P⁻ (+ the process noise) and the cross
covariance C_k between x_k and x_k+1::

    G_k = C_k (P⁻_k+1)⁻¹
    x̂_k|N = x̂_k|k + G_k (x̂_k+1|N − m⁻_k+1)
    P_k|N = P_k|k + G_k (P_k+1|N − P⁻_k+1) G_kᵀ

The covariance is computed in the equal Joseph form of the unscented
statistical linearisation (Φ_k = C_kᵀ P_k|k⁻¹, exact on the sigma points:
Φ_k L_k is the central difference of the propagated points, L_k the
Cholesky factor of P_k|k)::

    P_k|N = M_k M_kᵀ + G_k (Q̃_k + P_k+1|N) G_kᵀ,   M_k = L_k − G_k Φ_k L_k

where Q̃_k = P⁻_k+1 − Φ_k P_k|k Φ_kᵀ (the process noise and what the
transition adds beyond its linearisation, the points' second differences)
is computed without that subtraction. A sum of positive semi-definite
terms: no cancellation of P_k|k against G P⁻ Gᵀ, which without process
noise left variances of round-off (a stiff mass-spring-damper,
tests/test_smoother.py: the smoothed std down to 0.015 of the exact one;
in this form 0.18, and below half the exact one only where the filtered
covariance is itself singular to working precision, 4 samples of 6 000).

x̂_0|N, P_0|N is the best estimate of the initial state the model and the
whole record give (a start for estimating x0 jointly with θ).

References
----------
Särkkä, S. (2008). Unscented Rauch-Tung-Striebel smoother. IEEE TAC 53(3),
845-849. Rauch, H. E., Tung, F., Striebel, C. T. (1965). Maximum likelihood
estimates of linear dynamic systems. AIAA J. 3(8), 1445-1450. Higham, N. J.
(1988). Computing a nearest symmetric positive semidefinite matrix. Linear
Algebra Appl. 103, 103-118.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from bondgraph.errors import NumericalError
from bondgraph.inference.options import UKFOptions, ukf_options
from bondgraph.inference.sigma import (
    cholesky_batch,
    merwe_weights,
    sigma_points,
    unscented_moments,
)
from bondgraph.inference.ukf import interval_steps, ukf_nll
from bondgraph.numerics.integrators import hold_inputs


@dataclass
class Smoothed:
    """What :func:`rts_smooth` returns.

    Attributes
    ----------
    x : ndarray (N, n_x)
        Smoothed means x̂_k|N.
    P : ndarray (N, n_x, n_x)
        Smoothed covariances.
    x_filt : ndarray (N, n_x)
        Filtered means x̂_k|k (the forward pass).
    nll : float
        Negative log-likelihood of the forward pass.
    restarts : int
        Samples where the backward recursion diverged and restarted from
        the filtered posterior (:func:`_recursion`); 0 on a regular pass.
    """

    x: np.ndarray
    P: np.ndarray
    x_filt: np.ndarray
    nll: float
    restarts: int = 0

    @property
    def x0(self) -> np.ndarray:
        """The smoothed initial state x̂_0|N (n_x,)."""
        return self.x[0].copy()

    @property
    def P0(self) -> np.ndarray:
        """Its covariance P_0|N (n_x, n_x)."""
        return self.P[0].copy()


def rts_smooth(model, t, u, y, theta, x0, P0, *, options: UKFOptions | None = None,
               R=None) -> Smoothed:
    """UKF forward pass and unscented RTS backward pass at one parameter set.

    Parameters
    ----------
    model : Model
    t, u, y : arrays (N,), (N, n_u), (N, n_y)
        The record (NaN where an output is missing).
    theta : array (n_theta,)
    x0 : array (n_x,)
        Prior mean at ``t[0]``.
    P0 : array (n_x, n_x)
        Prior covariance.
    options : UKFOptions, optional
        The filter's options; the backward pass uses the same sigma points,
        discretisation and input hold.
    R : array (n_y, n_y), optional
        Measurement-noise covariance (default ``diag(meas_std(θ)²)``).

    Returns
    -------
    Smoothed

    Raises
    ------
    NumericalError
        If the forward pass fails (its reason named) or a predicted
        covariance cannot be inverted.
    """
    opts = ukf_options(options)
    th = np.asarray(theta, float)
    res = ukf_nll(model, t, u, y, th[None, :], x0, P0, options=opts, R=R, store="full")
    if not np.isfinite(res.nll[0]):
        raise NumericalError(f"the UKF fails at the smoothing point: {res.reasons[0]}")
    xf, Pf = res.x_filt[:, 0, :], res.P_filt[:, 0, :, :]
    t = np.asarray(t, float)
    u = np.asarray(u, float).reshape(t.size, -1) if model.n_u else np.zeros((t.size, 0))
    xs, Ps, restarts = _backward(model, t, u, th, xf, Pf, opts)
    return Smoothed(xs, Ps, xf.copy(), float(res.nll[0]), restarts)


def rts_backward(model, t, u, theta, x_filt, P_filt, *,
                 options: UKFOptions | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The unscented RTS backward pass alone, over a forward pass already run
    (e.g. one segment of a tracking filter, :mod:`bondgraph.inference.track`).

    Parameters
    ----------
    model : Model
    t : array (N,)
    u : array (N, n_u)
    theta : array (n_theta,)
    x_filt : array (N, n_x)
        Filtered means x̂_k|k.
    P_filt : array (N, n_x, n_x)
        Filtered covariances.
    options : UKFOptions, optional
        The forward pass's options (same sigma points, step and hold).

    Returns
    -------
    (x (N, n_x), P (N, n_x, n_x))
        Smoothed means and covariances (Särkkä 2008, Algorithm 3.2).

    Raises
    ------
    NumericalError
        A covariance that cannot be factored or inverted.
    """
    opts = ukf_options(options)
    t = np.asarray(t, float)
    u = np.asarray(u, float).reshape(t.size, -1) if model.n_u else np.zeros((t.size, 0))
    return _backward(model, t, u, np.asarray(theta, float), np.asarray(x_filt, float),
                     np.asarray(P_filt, float), opts)[:2]


def _gain(Pm: np.ndarray, C: np.ndarray, k: int) -> np.ndarray:
    """The smoother gain G = C (P⁻)⁻¹ (n, n); where P⁻ is singular (a
    direction no process noise reaches has collapsed to round-off) the
    minimum-norm least-squares gain C (P⁻)⁺, the limit of the regular one.

    Raises
    ------
    NumericalError
        Non-finite covariances at sample ``k + 1``.
    """
    if not (np.all(np.isfinite(Pm)) and np.all(np.isfinite(C))):
        raise NumericalError(f"smoother: predicted covariance at sample {k + 1} is not finite")
    try:
        return np.linalg.solve(Pm.T, C.T).T
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(Pm.T, C.T, rcond=None)[0].T


#: relative floor of the eigenvalues of a filtered covariance that round-off
#: has made indefinite (:func:`_factor`)
EIG_FLOOR = 1e-12


def _factor(P: np.ndarray, k: int) -> np.ndarray:
    """A lower Cholesky factor (1, n, n) of the filtered covariance ``P``.

    Without process noise a direction the measurements pin down collapses to
    round-off over a long record, and ``P`` may come out slightly indefinite
    (a negative eigenvalue of order 1e-16 of its largest); it is then
    replaced by the nearest positive definite matrix (symmetric part,
    eigenvalues floored at :data:`EIG_FLOOR` times the largest; Higham
    1988), which changes the sigma points by round-off only.

    A covariance without a positive eigenvalue (it underflowed to zero: the
    state is known exactly) gives the zero factor.

    Raises
    ------
    NumericalError
        A covariance that is not finite, or not positive definite even so.
    """
    L, ok, _ = cholesky_batch(P[None])
    if ok[0]:
        return L
    return _factors(P[None], np.array([k]))


def _factors(P: np.ndarray, ks: np.ndarray) -> np.ndarray:
    """The factors of :func:`_factor` for a batch (B, n, n) of filtered
    covariances (samples ``ks`` (B,)) that the Cholesky factorisation
    refused: their nearest positive definite matrices factored together (one
    stacked eigendecomposition; without process noise most samples of a long
    record can need it, 50 s of a user's loop on 18 600 samples one by one),
    the zero factor where no eigenvalue is positive (the state is known
    exactly: without process noise a damped model forgets its initial
    state, P_k = Φᵏ P0 Φᵏᵀ underflows; the sigma points collapse onto the
    mean, the gain is 0).

    Raises
    ------
    NumericalError
        A covariance that is not finite, or not positive definite even so:
        the latest such sample named.
    """
    S = 0.5 * (P + np.swapaxes(P, 1, 2))
    L = np.zeros_like(P)
    done = np.zeros(len(P), bool)
    fin = np.flatnonzero(np.isfinite(S).all(axis=(1, 2)))
    if fin.size:
        w, V = np.linalg.eigh(S[fin])
        top = w[:, -1]
        zero = ~(top > np.finfo(float).tiny)
        done[fin[zero]] = True               # known exactly: the zero factor
        pos = fin[~zero]
        if pos.size:
            wf = np.maximum(w[~zero], EIG_FLOOR * top[~zero, None])
            Vp = V[~zero]
            Lp, ok, _ = cholesky_batch((Vp * wf[:, None, :]) @ np.swapaxes(Vp, 1, 2))
            L[pos[ok]] = Lp[ok]
            done[pos[ok]] = True
    bad = np.flatnonzero(~done)
    if bad.size:
        raise NumericalError(f"smoother: filtered covariance at sample {int(ks[bad[-1]])} is "
                             f"not positive definite")
    return L


#: intervals whose one-step predictions are propagated in one batch
CHUNK = 4096


def _backward(model, t, u, th, xf, Pf, opts: UKFOptions):
    """The RTS backward recursion (module docstring) over the filtered
    means ``xf`` (N, n) and covariances ``Pf`` (N, n, n).

    The one-step predictions of the filtered posteriors (m⁻, P⁻ and the
    gain G of every interval) do not depend on the recursion: they are
    propagated in batches (:func:`_predictions`); only the recursion itself
    runs sample by sample. Returns ``(xs, Ps, restarts)``: where the
    recursion diverges (gains above one through contracting dynamics
    without process noise, G = Φ⁻¹, amplify round-off sample after sample)
    it restarts from the filtered posterior (:func:`_recursion`; their
    number)."""
    N = t.size
    xs, Ps = np.array(xf, float, order="C"), np.array(Pf, float, order="C")
    if N < 2:
        return xs, Ps, 0
    m, G, M, Qe = _predictions(model, t, u, th, xf, Pf, opts)
    c = np.ascontiguousarray
    with np.errstate(all="ignore"):
        diag = np.diagonal(Pf, axis1=1, axis2=2)
        floor = RESTART_FLOOR * np.max(np.where(np.isfinite(diag), np.abs(diag), 0.0), axis=0)
    restarts = _recursion(c(xf, float), c(Pf, float), c(m, float), c(G, float), c(M, float),
                          c(Qe, float), xs, Ps, c(floor, float))
    return xs, Ps, int(restarts)


#: a smoothed variance above this many times the filtered one, or below 0,
#: beyond :data:`RESTART_FLOOR` times the state's largest filtered variance
#: over the record, is round-off the recursion amplified, not information:
#: the smoother can only lower a variance (0 ≤ P_k|N ≤ P_k|k)
RESTART_GROWTH = 2.0
RESTART_FLOOR = 1e-12


@njit(cache=True, nogil=True)
def _recursion(xf, Pf, m, G, M, Qe, xs, Ps, floor):  # pragma: no cover - compiled
    """The RTS recursion in place, k = N − 2 … 0 (``xs``, ``Ps`` hold the
    filtered values (N, n), (N, n, n) on entry and the last sample's stay)::

        x̂_k|N = x̂_k|k + G_k (x̂_k+1|N − m⁻_k)
        P_k|N = sym(M_k M_kᵀ + G_k (Q̃_k + P_k+1|N) G_kᵀ)

    with ``m`` (N−1, n), ``G``, ``M`` and ``Qe`` (Q̃) (N−1, n, n) (the
    Joseph form, module docstring). Compiled because the loop is
    sequential: numpy's per-sample products took 0.48 s over 18 600
    samples of 3 states, this loop 0.0024 s. Sums run in index order; the
    result agrees with numpy's matrix products to round-off.

    A sample whose smoothed mean or covariance is not finite, whose
    smoothed variance of a state exceeds :data:`RESTART_GROWTH` times the
    filtered one plus ``floor`` (n,), or falls below −``floor`` (the
    smoother can only lower a variance, and never below 0), keeps its
    filtered posterior, and the recursion goes on from there: without process noise the gain of a contracting mode is
    Φ⁻¹ (its factor above one per sample), which amplifies round-off until
    it overflows (a thermal node of time constant 25 s sampled every 2 s:
    1e183 after 1 100 samples of 2 880, every earlier sample inf). Returns
    the number of such restarts."""
    N, n = xf.shape
    d = np.empty(n)
    A = np.empty((n, n))
    B = np.empty((n, n))
    restarts = 0
    for k in range(N - 2, -1, -1):
        for i in range(n):
            d[i] = xs[k + 1, i] - m[k, i]
        for i in range(n):
            acc = 0.0
            for j in range(n):
                acc += G[k, i, j] * d[j]
            xs[k, i] = xf[k, i] + acc
        for i in range(n):
            for j in range(n):
                B[i, j] = Qe[k, i, j] + Ps[k + 1, i, j]
        for i in range(n):
            for j in range(n):
                acc = 0.0
                for l in range(n):
                    acc += G[k, i, l] * B[l, j]
                A[i, j] = acc
        for i in range(n):
            for j in range(i + 1):
                a = 0.0
                b = 0.0
                mm = 0.0
                for l in range(n):
                    a += A[i, l] * G[k, j, l]
                    b += A[j, l] * G[k, i, l]
                    mm += M[k, i, l] * M[k, j, l]
                v = mm + 0.5 * (a + b)
                Ps[k, i, j] = v
                Ps[k, j, i] = v
        bad = False
        for i in range(n):
            if not (np.isfinite(xs[k, i]) and -floor[i] <= Ps[k, i, i]
                    <= RESTART_GROWTH * Pf[k, i, i] + floor[i]):
                bad = True
            for j in range(n):
                if not np.isfinite(Ps[k, i, j]):
                    bad = True
        if bad:
            restarts += 1
            for i in range(n):
                xs[k, i] = xf[k, i]
                for j in range(n):
                    Ps[k, i, j] = Pf[k, i, j]
    return restarts


def _predictions(model, t, u, th, xf, Pf, opts: UKFOptions):
    """``(m⁻ (N-1, n), G, M, Q̃ (N-1, n, n))``: for every interval k the
    sigma points of (x̂_k|k, P_k|k) through the filter's own step and input
    hold, their mean, the smoother gain (:func:`_gain`, from their
    covariance + the process noise) and the Joseph form's factors (module
    docstring): with D±_j the propagated points ±j less the central one,
    Φ_k L_k has the columns (D+_j − D−_j)/(2c) (c = √(n+λ)), M = L − G Φ L,
    and Q̃ = diag(q²)·dt + (w/2) Σ_j S_j S_jᵀ + (β − α²) μ μᵀ with
    S_j = D+_j + D−_j and μ = w Σ_i D_i (the unscented covariance less
    (ΦL)(ΦL)ᵀ, term by term); in batches of :data:`CHUNK` intervals of equal
    length.

    Raises
    ------
    NumericalError
        A filtered covariance that cannot be factored (:func:`_factor`) or
        a non-finite prediction (the latest sample named, as the recursion
        meets it first).
    """
    n, N = model.n_x, t.size
    wts = merwe_weights(n, opts.alpha, opts.beta, opts.kappa)
    step_of = interval_steps(model, opts, N - 1)
    per = step_of.per
    held = hold_inputs(u, opts.hold)
    with np.errstate(all="ignore"):
        q2 = np.asarray(model.proc_std(th[None, :]), float)[0] ** 2
    m, G = np.empty((N - 1, n)), np.empty((N - 1, n, n))
    M, Qe = np.empty((N - 1, n, n)), np.empty((N - 1, n, n))
    dts = np.diff(t)
    for a in range(0, N - 1, CHUNK):
        ks = np.arange(a, min(a + CHUNK, N - 1))
        L, ok, _ = cholesky_batch(Pf[ks])
        if not ok.all():
            L[~ok] = _factors(Pf[ks[~ok]], ks[~ok])
        chi, cL = sigma_points(xf[ks], L, wts.c)
        for dt, nsub in sorted(set(zip(dts[ks].tolist(), per[ks].tolist()))):
            sel = np.flatnonzero((dts[ks] == dt) & (per[ks] == nsub))
            k_sel = ks[sel]
            du = None if held.change is None else held.change[k_sel][:, None, :]
            with np.errstate(all="ignore"):
                X = step_of(int(k_sel[0]))(chi[sel], held.start[k_sel][:, None, :],
                                           th[None, None, :], dt, du)
            mm, P, D = unscented_moments(X, wts)
            m[k_sel] = mm
            Q = np.diag(q2 * dt)
            Dd = D[:, :n] - D[:, n:]                     # rows D+_j − D−_j
            C = wts.w * (np.swapaxes(cL[sel], -1, -2) @ Dd)
            G[k_sel] = _gains(P + Q, C, k_sel)
            Sj = D[:, :n] + D[:, n:]
            mu = wts.w * D.sum(axis=1)
            Qe[k_sel] = (Q + 0.5 * wts.w * (np.swapaxes(Sj, 1, 2) @ Sj)
                         + wts.center_cov * (mu[:, :, None] * mu[:, None, :]))
            M[k_sel] = L[sel] - G[k_sel] @ ((wts.w * wts.c) * np.swapaxes(Dd, 1, 2))
    return m, G, M, Qe


def _gains(Pm: np.ndarray, C: np.ndarray, ks: np.ndarray) -> np.ndarray:
    """:func:`_gain` of a batch (B, n, n) of intervals ``ks``."""
    bad = ~(np.isfinite(Pm).all(axis=(1, 2)) & np.isfinite(C).all(axis=(1, 2)))
    if bad.any():
        k = int(ks[np.flatnonzero(bad)[-1]])
        raise NumericalError(f"smoother: predicted covariance at sample {k + 1} is not finite")
    try:
        return np.swapaxes(np.linalg.solve(np.swapaxes(Pm, 1, 2), np.swapaxes(C, 1, 2)), 1, 2)
    except np.linalg.LinAlgError:
        return np.stack([_gain(Pm[j], C[j], int(k)) for j, k in enumerate(ks)])
