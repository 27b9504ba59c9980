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

from bondgraph.errors import NumericalError
from bondgraph.inference.options import UKFOptions, ukf_options
from bondgraph.inference.sigma import (
    cholesky_batch,
    merwe_weights,
    sigma_points,
    unscented_moments,
)
from bondgraph.inference.ukf import ROS2_JACOBIAN, ukf_nll
from bondgraph.numerics.integrators import hold_inputs, make_step


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
    """

    x: np.ndarray
    P: np.ndarray
    x_filt: np.ndarray
    nll: float

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
    xs, Ps = _backward(model, t, u, th, xf, Pf, opts)
    return Smoothed(xs, Ps, xf.copy(), float(res.nll[0]))


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

    Raises
    ------
    NumericalError
        A covariance that is not finite or has no positive eigenvalue.
    """
    L, ok, _ = cholesky_batch(P[None])
    if ok[0]:
        return L
    S = 0.5 * (P + P.T)
    if np.all(np.isfinite(S)):
        w, V = np.linalg.eigh(S)
        if w[-1] > 0:
            L, ok, _ = cholesky_batch(((V * np.maximum(w, EIG_FLOOR * w[-1])) @ V.T)[None])
            if ok[0]:
                return L
    raise NumericalError(f"smoother: filtered covariance at sample {k} is not positive "
                         f"definite")


def _backward(model, t, u, th, xf, Pf, opts: UKFOptions):
    """The RTS backward recursion (module docstring) over the filtered
    means ``xf`` (N, n) and covariances ``Pf`` (N, n, n)."""
    n, N = model.n_x, t.size
    wts = merwe_weights(n, opts.alpha, opts.beta, opts.kappa)
    step = make_step(model, opts.method, opts.substeps, jacobian=ROS2_JACOBIAN[opts.jacobian])
    held = hold_inputs(u, opts.hold)
    with np.errstate(all="ignore"):
        q2 = np.asarray(model.proc_std(th[None, :]), float)[0] ** 2
    xs, Ps = xf.copy(), Pf.copy()
    for k in range(N - 2, -1, -1):
        chi, cL = sigma_points(xf[k][None], _factor(Pf[k], k), wts.c)
        uk, duk = held.interval(k)
        dt = t[k + 1] - t[k]
        with np.errstate(all="ignore"):
            X = step(chi, uk, th[None, None, :], dt, duk)
        m, Pm, D = unscented_moments(X, wts)
        Pm = Pm[0] + np.diag(q2 * dt)
        C = wts.w * (cL[0].T @ (D[0, :n] - D[0, n:]))
        G = _gain(Pm, C, k)
        xs[k] = xf[k] + G @ (xs[k + 1] - m[0])
        Pk = Pf[k] + G @ (Ps[k + 1] - Pm) @ G.T
        Ps[k] = 0.5 * (Pk + Pk.T)
    return xs, Ps
