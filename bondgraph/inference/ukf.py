"""Batched unscented Kalman filter and its negative log-likelihood.

One call filters a whole record for ``P`` parameter sets at once: every
array operation works on ``(P, 2n+1, n)`` sigma points (particles x sigma
points), and each stage of the discretisation is one call of the generated
model functions for the whole batch. There is no Python loop over particles
or sigma points; the only loop is over the samples of the record.

Filter (additive process and measurement noise; Wan & van der Merwe 2000),
with the scaled sigma points and the difference form of the unscented
moments of :mod:`bondgraph.inference.sigma` (accurate for α from 1e-3 to 1).
The sequence of operations is that of filterpy 2.0's
``UnscentedKalmanFilter``:

* :func:`predict` propagates sigma points drawn from the posterior through
  the discretised state equations and forms the prior (x⁻, P⁻ + Q);
* :func:`update` re-draws sigma points from the prior, passes them through
  h, forms ŷ, S = P_yy + R, the cross covariance P_xy, K = P_xy S⁻¹,
  x⁺ = x⁻ + K ε, P⁺ = P⁻ − K S Kᵀ, and adds the sample's NLL term.

The prior at ``t[0]`` is ``(x0, P0)``: sample 0 is an update without a
predict.

Likelihood (prediction-error decomposition; Schweppe 1965, Särkkä 2013
ch. 12), over the samples k with at least one measured output::

    NLL = 1/2 Σ_k [ ln det S_k + ε_kᵀ S_k⁻¹ ε_k + m_k ln 2π ]

computed with the Cholesky factor of S_k. A parameter set whose covariance
is not positive definite, whose S is not positive definite or whose state
turns non-finite gets NLL = +inf and a reason; it is dropped from the batch
and the other sets continue unaffected.

Missing samples (NaN in an output) are skipped: the update uses the measured
subset of outputs (rows and columns of R), and no update is made when
nothing is measured.

Discretisation between samples (inputs held over the interval,
:func:`bondgraph.numerics.integrators.hold_inputs`): the transition of
:func:`bondgraph.numerics.integrators.make_step`, ``"rk4"`` (classical
Runge-Kutta with sub-steps) or ``"ros2"`` (the L-stable linearly implicit
Rosenbrock method, generated Jacobian evaluated once per sample interval at
the central sigma point of each parameter set, or at every sigma point).

References
----------
Wan, E. A., van der Merwe, R. (2000). The unscented Kalman filter for
nonlinear estimation. Proc. IEEE AS-SPCC, 153-158.
Julier, S. J. (2002). The scaled unscented transformation. Proc. ACC.
Schweppe, F. C. (1965). Evaluation of likelihood functions for Gaussian
signals. IEEE Trans. Inf. Theory 11(1), 61-70.
Särkkä, S. (2013). Bayesian Filtering and Smoothing. Cambridge UP, ch. 12.
"""

from __future__ import annotations

import time
import warnings
from collections import Counter
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Sequence

import numpy as np

from bondgraph.core.progress import long_range
from bondgraph.errors import BackendWarning, DataError, ModelError, OptionError
from bondgraph.inference import sim_numba, ukf_numba
from bondgraph.inference.options import Discretisation, UKFOptions, interval_substeps, ukf_options
from bondgraph.inference.prior import default_P0, free_run_kernels
from bondgraph.inference.sigma import (
    SigmaWeights,
    cholesky_batch,
    merwe_weights,
    sigma_points,
    unscented_moments,
)
from bondgraph.numerics.compiled import point_kernels
from bondgraph.numerics.integrators import hold_inputs, make_step, rk4_growth

LOG_2PI = float(np.log(2.0 * np.pi))

#: UKFOptions.jacobian -> where integrators.ros2 evaluates df/dx
ROS2_JACOBIAN = {"mean": "shared", "sigma": "once"}
_ROS2_JACOBIAN = ROS2_JACOBIAN


# ---------------------------------------------------------------- result
@dataclass
class UKFResult:
    """What :func:`ukf_nll` returns.

    Arrays are indexed ``[sample k, parameter set p, ...]``. Stored arrays
    (``store=True``) are NaN where nothing was computed: unmeasured outputs,
    skipped updates, and every sample from the failure of a set onwards.

    Attributes
    ----------
    nll : ndarray (P,)
        Negative log-likelihood of each parameter set [nats]; +inf for a
        failed set.
    failed : ndarray of bool (P,)
    reasons : list of (str or None), length P
        Why a set failed (sample index, time and cause), None if it did not.
    fail_step : ndarray of int (P,)
        Sample index at which a set failed, -1 if it did not.
    n_obs : ndarray of int (N,)
        Number of measured outputs used at each sample.
    t : ndarray (N,)
    outputs, states : list of str
    innovations : ndarray (N, P, n_y) or None
        ε_k = y_k − ŷ_k|k−1.
    S : ndarray (N, P, n_y, n_y) or None
        Innovation covariances.
    y_pred : ndarray (N, P, n_y) or None
        Predicted output means ŷ_k|k−1.
    y_filt : ndarray (N, P, n_y) or None
        h(x̂_k|k): outputs at the filtered states.
    x_filt : ndarray (N, P, n_x) or None
        Filtered states x̂_k|k.
    P_filt : ndarray (N, P, n_x, n_x) or None
        Filtered covariances (only with ``store="full"``).
    nll_terms : ndarray (N, P) or None
        Per-sample contributions to the NLL (0 where no update).
    nis : ndarray (N, P) or None
        Normalised innovation squared ε_kᵀ S_k⁻¹ ε_k (χ² with n_obs[k]
        degrees of freedom for a consistent filter).
    settings : dict
    """

    nll: np.ndarray
    failed: np.ndarray
    reasons: list
    fail_step: np.ndarray
    n_obs: np.ndarray
    t: np.ndarray
    outputs: list
    states: list
    innovations: np.ndarray | None = None
    S: np.ndarray | None = None
    y_pred: np.ndarray | None = None
    y_filt: np.ndarray | None = None
    x_filt: np.ndarray | None = None
    P_filt: np.ndarray | None = None
    nll_terms: np.ndarray | None = None
    nis: np.ndarray | None = None
    settings: dict = field(default_factory=dict)

    @property
    def n_failed(self) -> int:
        """Number of parameter sets that failed."""
        return int(np.count_nonzero(self.failed))

    def failure_summary(self) -> dict[str, int]:
        """Count of failed sets per cause (reason without sample index)."""
        out: Counter = Counter()
        for r in self.reasons:
            if r:
                out[r.split(": ", 1)[-1]] += 1
        return dict(out)

    @property
    def log_likelihood(self) -> np.ndarray:
        """−NLL, shape (P,)."""
        return -self.nll


# ---------------------------------------------------------------- helpers
def _as_batch_matrix(M, P: int, n: int, what: str) -> np.ndarray | None:
    if M is None:
        return None
    M = np.asarray(M, dtype=float)
    if M.ndim == 1 and M.shape == (n,):
        M = np.diag(M)
    if M.shape == (n, n):
        return np.broadcast_to(M, (P, n, n))
    if M.shape == (P, n, n):
        return M
    raise OptionError(f"{what} must have shape ({n}, {n}) or ({P}, {n}, {n}) (or ({n},) for a "
                      f"diagonal), got {M.shape}")


def _check_inputs(model, t, u, y):
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or t.size < 1:
        raise DataError(f"t must be a 1-D array of sample times, got shape {t.shape}")
    N = t.size
    if not np.isfinite(t).all():
        k = int(np.flatnonzero(~np.isfinite(t))[0])
        raise DataError(f"non-finite time at sample {k}", column="t")
    dts = np.diff(t)
    if np.any(dts <= 0):
        k = int(np.flatnonzero(dts <= 0)[0])
        raise DataError(f"time is not strictly increasing at sample {k + 1} "
                        f"(t = {t[k]!r} then {t[k + 1]!r})", column="t")
    if u is None:
        u = np.broadcast_to(model.u0, (N, model.n_u))
    u = np.asarray(u, dtype=float)
    if u.ndim == 1 and model.n_u == 1:
        u = u[:, None]
    if u.shape != (N, model.n_u):
        raise DataError(f"inputs must have shape ({N}, {model.n_u}) for model '{model.name}' "
                        f"(inputs {model.inputs}), got {u.shape}")
    bad = ~np.isfinite(u)
    if bad.any():
        k, j = map(int, np.argwhere(bad)[0])
        raise DataError(f"non-finite input at sample {k}", column=model.inputs[j])
    y = np.asarray(y, dtype=float)
    if y.ndim == 1 and model.n_y == 1:
        y = y[:, None]
    if y.shape != (N, model.n_y):
        raise DataError(f"outputs must have shape ({N}, {model.n_y}) for model '{model.name}' "
                        f"(outputs {model.outputs}), got {y.shape}")
    if np.isinf(y).any():
        k, j = map(int, np.argwhere(np.isinf(y))[0])
        raise DataError(f"infinite output value at sample {k} (use NaN for a missing sample)",
                        column=model.outputs[j])
    return t, u, y


def _check_theta(model, theta) -> np.ndarray:
    """Parameter sets as an array (P, n_theta).

    Raises
    ------
    ModelError
        Wrong shape.
    """
    th = np.asarray(theta, dtype=float)
    if th.ndim == 1:
        th = th[None, :]
    if th.ndim != 2 or th.shape[1] != model.n_theta:
        raise ModelError(f"theta must have shape (P, {model.n_theta}) for model '{model.name}' "
                         f"(parameters {model.params}), got {np.shape(theta)}")
    return th


def _priors(model, Pn: int, x0, P0, Q, R):
    """Prior mean (P, n) and covariance (P, n, n) at t[0], and the noise
    matrices Q (P, n, n), R (P, n_y, n_y) (None when not given).

    Raises
    ------
    OptionError
        Wrong shapes.
    """
    n = model.n_x
    x0 = model.x0 if x0 is None else np.asarray(x0, dtype=float)
    if x0.shape == (n,):
        x = np.broadcast_to(x0, (Pn, n)).copy()
    elif x0.shape == (Pn, n):
        x = x0.copy()
    else:
        raise OptionError(f"x0 must have shape ({n},) or ({Pn}, {n}), got {x0.shape}")
    P0 = default_P0(model, x0 if x0.ndim == 1 else None) if P0 is None else P0
    P = np.array(_as_batch_matrix(P0, Pn, n, "P0"), dtype=float)
    return x, P, _as_batch_matrix(Q, Pn, n, "Q"), _as_batch_matrix(R, Pn, model.n_y, "R")


# ------------------------------------------------------------- the batch
class FilterBatch:
    """The parameter sets of one filter run: the working arrays of the sets
    still active and the bookkeeping of the failed ones.

    The working arrays hold the active sets only, in the order of ``act``
    (indices into the whole batch); a failing set is dropped from all of
    them at once by :meth:`drop`, which records when and why it failed.

    Attributes
    ----------
    act : ndarray of int (A,)
        Active sets.
    x, P : ndarray (A, n), (A, n, n)
        Current mean and covariance of the active sets.
    th : ndarray (A, n_theta)
    q2 : ndarray (A, n)
        Process-noise intensities proc_std(θ)² (variance per second).
    Q, R : ndarray (A, n, n), (A, n_y, n_y) or None
        Given noise matrices.
    Rd : ndarray (A, n_y) or None
        Measurement-noise variances meas_std(θ)² (when R is not given).
    nll : ndarray (P,)
        Accumulated NLL of every set (+inf once failed).
    failed, fail_step, reasons :
        Which set failed, at which sample index (-1: did not) and why.
    n_reg : int
        Covariances that needed diagonal loading to factorise.
    """

    def __init__(self, model, t: np.ndarray, th: np.ndarray, x, P, Q, R):
        Pn = th.shape[0]
        self.t = t
        self.nll = np.zeros(Pn)
        self.failed = np.zeros(Pn, dtype=bool)
        self.fail_step = np.full(Pn, -1, dtype=int)
        self.reasons: list[Any] = [None] * Pn
        self.n_reg = 0
        q2, Rd = self._check_parameters(model, th, R is None)
        act = np.flatnonzero(~self.failed)
        self.act = act
        self.x, self.P, self.th, self.q2 = x[act], P[act], th[act], q2[act]
        self.Q = None if Q is None else np.asarray(Q)[act]
        self.R = None if R is None else np.asarray(R)[act]
        self.Rd = None if Rd is None else Rd[act]

    def _check_parameters(self, model, th, need_r: bool):
        """Fail (at sample 0) the sets with a non-finite parameter, process
        noise or measurement-noise variance; returns ``(q2, Rd)``."""
        for p in np.flatnonzero(~np.isfinite(th).all(axis=1)):
            j = int(np.flatnonzero(~np.isfinite(th[p]))[0])
            self._fail_at_start(p, f"non-finite parameter '{model.params[j]}' = {th[p, j]}")
        with np.errstate(all="ignore"):
            q2 = np.asarray(model.proc_std(th), dtype=float) ** 2          # (P, n)
            Rd = np.asarray(model.meas_std(th), dtype=float) ** 2 if need_r else None
        for p in np.flatnonzero(~np.isfinite(q2).all(axis=1) & ~self.failed):
            self._fail_at_start(p, "non-finite process-noise intensity proc_std(theta)")
        if Rd is not None:
            bad = ~np.isfinite(Rd).all(axis=1) | (Rd <= 0).any(axis=1)
            for p in np.flatnonzero(bad & ~self.failed):
                self._fail_at_start(p, "measurement-noise variance meas_std(theta)**2 not "
                                       "positive")
        return q2, Rd

    def _fail_at_start(self, p: int, why: str) -> None:
        self.failed[p], self.fail_step[p] = True, 0
        self.reasons[p] = f"sample 0: {why}"

    @property
    def size(self) -> int:
        """Number of active sets."""
        return int(self.act.size)

    @property
    def th_b(self) -> np.ndarray:
        """Parameters of the active sets with a sigma-point axis, (A, 1, n_theta)."""
        return self.th[:, None, :]

    def drop(self, bad: np.ndarray, k: int, why: str) -> np.ndarray:
        """Fail the active sets where ``bad`` (A,) at sample ``k``; returns
        the mask of the sets kept (to filter the caller's own arrays)."""
        for a in np.flatnonzero(bad):
            p = self.act[a]
            self.failed[p], self.fail_step[p] = True, k
            self.nll[p] = np.inf
            self.reasons[p] = f"sample {k} (t = {self.t[k]:.6g} s): {why}"
        keep = ~bad
        self.act = self.act[keep]
        for name in ("x", "P", "th", "q2", "Q", "R", "Rd"):
            v = getattr(self, name)
            if v is not None:
                setattr(self, name, v[keep])
        return keep

    def result(self, model, t: np.ndarray, y: np.ndarray, settings: dict) -> UKFResult:
        """The :class:`UKFResult` of the run (NLL +inf for the failed sets)."""
        self.nll[self.failed] = np.inf
        return UKFResult(nll=self.nll, failed=self.failed, reasons=self.reasons,
                         fail_step=self.fail_step, n_obs=np.isfinite(y).sum(axis=1), t=t,
                         outputs=list(model.outputs), states=list(model.states),
                         settings=settings)

    def sigma_points(self, k: int, what: str, c: float) -> tuple[np.ndarray, np.ndarray]:
        """Sigma points of the active sets (:func:`bondgraph.inference.sigma.sigma_points`);
        a set whose covariance cannot be factorised is dropped first."""
        L, ok, nr = cholesky_batch(self.P, known=True)
        self.n_reg += nr
        if not ok.all():
            L = L[self.drop(~ok, k, f"{what} covariance P not positive definite")]
        return sigma_points(self.x, L, c)


# -------------------------------------------------------- predict / update
def predict(batch: FilterBatch, step: Callable, u: np.ndarray, dt: float, wts: SigmaWeights,
            k: int, du: np.ndarray | None = None) -> None:
    """Prediction from sample k−1 to k (Wan & van der Merwe 2000).

    Sigma points of the posterior at k−1 go through the transition ``step``
    (input ``u`` at the start of the interval ``dt``, changing by ``du`` over
    it with a first-order hold); their unscented mean and
    covariance plus the process noise, ``diag(proc_std(θ)²)·dt`` and the
    given ``Q``, are the prior at k (``batch.x``, ``batch.P``). Sets whose
    posterior covariance is not positive definite or whose propagated
    sigma points are not finite are dropped.
    """
    chi, _ = batch.sigma_points(k, "posterior", wts.c)
    if not batch.size:
        return
    with np.errstate(all="ignore"):
        X = step(chi, u, batch.th_b, dt, du)
    fin = np.isfinite(X).all(axis=(1, 2))
    if not fin.all():
        X = X[batch.drop(~fin, k, ukf_numba.FAIL_REASONS[3])]
        if not batch.size:
            return
    x, P, _ = unscented_moments(X, wts)
    n = x.shape[1]
    P.reshape(P.shape[0], n * n)[:, ::n + 1] += batch.q2 * dt
    if batch.Q is not None:
        P += batch.Q
    batch.x, batch.P = x, P


@dataclass
class Innovation:
    """What one :func:`update` computed for the active sets (A) over the
    measured outputs (m).

    Attributes
    ----------
    idx : ndarray of int (m,) or None
        The measured outputs (None: all of them).
    eps, yhat : ndarray (A, m)
        Innovations ε = y − ŷ and predicted outputs ŷ.
    S : ndarray (A, m, m)
        Innovation covariances.
    term, maha : ndarray (A,)
        NLL contributions and ε S⁻¹ ε.
    """

    idx: np.ndarray | None
    eps: np.ndarray
    yhat: np.ndarray
    S: np.ndarray
    term: np.ndarray
    maha: np.ndarray


def update(batch: FilterBatch, model, u: np.ndarray, y: np.ndarray, wts: SigmaWeights,
           k: int) -> Innovation | None:
    """Measurement update at sample k with the measured outputs of ``y`` (n_y,).

    Sigma points of the prior go through h; the unscented mean ŷ, the
    innovation covariance S = P_yy + R and the cross covariance P_xy give
    the gain; the sample's NLL term is added to ``batch.nll``. Sets with a
    non-finite h or an S that is not positive definite are dropped.

    Returns
    -------
    Innovation, or None when no set is left.
    """
    chi, cL = batch.sigma_points(k, "prior", wts.c)
    if not batch.size:
        return None
    with np.errstate(all="ignore"):
        Y = model.h(chi, u, batch.th_b)                               # (A, 2n+1, ny)
    obs = np.isfinite(y)
    idx = None if obs.all() else np.flatnonzero(obs)
    if idx is not None:
        Y, y = Y[..., idx], y[idx]
    fin = np.isfinite(Y).all(axis=(1, 2))
    if not fin.all():
        keep = batch.drop(~fin, k, "non-finite predicted output h(sigma point)")
        Y, cL = Y[keep], cL[keep]
        if not batch.size:
            return None
    yhat, S, E = unscented_moments(Y, wts)
    _add_measurement_noise(S, batch, idx)
    # cross covariance: sigma points are symmetric about x, so
    # P_xy = W Σ_i cL_i (E_+i − E_−i)ᵀ exactly (the mean term vanishes)
    n = cL.shape[1]
    Pxy = wts.w * (np.swapaxes(cL, 1, 2) @ (E[:, :n] - E[:, n:]))
    Ls, ok, nr = cholesky_batch(S)
    batch.n_reg += nr
    if not ok.all():
        keep = batch.drop(~ok, k, "innovation covariance S not positive definite")
        Ls, S, Pxy, yhat = Ls[keep], S[keep], Pxy[keep], yhat[keep]
        if not batch.size:
            return None
    return _correct(batch, Ls, S, Pxy, y - yhat, yhat, idx)


def _add_measurement_noise(S: np.ndarray, batch: FilterBatch, idx) -> None:
    """S += R over the measured outputs ``idx`` (in place)."""
    if batch.Rd is not None:
        rd = batch.Rd if idx is None else batch.Rd[:, idx]
        mm = rd.shape[1]
        S.reshape(S.shape[0], mm * mm)[:, ::mm + 1] += rd
    else:
        S += batch.R if idx is None else batch.R[:, idx][:, :, idx]


def _correct(batch: FilterBatch, Ls, S, Pxy, eps, yhat, idx) -> Innovation:
    """Kalman correction and NLL term from the Cholesky factor Ls of S."""
    n, mm = Pxy.shape[1], eps.shape[1]
    # one triangular solve for [Pxyᵀ | ε]: G = Pxy Ls⁻ᵀ, z = Ls⁻¹ ε
    rhs = np.concatenate([np.swapaxes(Pxy, 1, 2), eps[:, :, None]], axis=2)
    sol = np.linalg.solve(Ls, rhs)
    Gt, z = sol[:, :, :n], sol[:, :, n]
    logdet = 2.0 * np.log(np.diagonal(Ls, axis1=1, axis2=2)).sum(axis=1)
    maha = (z * z).sum(axis=1)
    term = 0.5 * (logdet + maha + mm * LOG_2PI)
    batch.nll[batch.act] += term
    GtT = np.swapaxes(Gt, 1, 2)
    batch.x = batch.x + (GtT @ z[:, :, None])[:, :, 0]
    P = batch.P - GtT @ Gt
    batch.P = 0.5 * (P + np.swapaxes(P, 1, 2))
    return Innovation(idx, eps, yhat, S, term, maha)


# ------------------------------------------------------------------ storage
class FilterStorage:
    """The per-sample arrays of ``store=True`` (see :class:`UKFResult`):
    NaN where nothing was computed."""

    def __init__(self, N: int, Pn: int, model, *, full: bool):
        n, ny = model.n_x, model.n_y
        self.innovations = np.full((N, Pn, ny), np.nan)
        self.S = np.full((N, Pn, ny, ny), np.nan)
        self.y_pred = np.full((N, Pn, ny), np.nan)
        self.y_filt = np.full((N, Pn, ny), np.nan)
        self.x_filt = np.full((N, Pn, n), np.nan)
        self.P_filt = np.full((N, Pn, n, n), np.nan) if full else None
        self.nll_terms = np.zeros((N, Pn))
        self.nis = np.full((N, Pn), np.nan)

    def innovation(self, k: int, act: np.ndarray, inn: Innovation) -> None:
        """Store an update's innovations, predictions, S, NLL terms and NIS."""
        if inn.idx is None:
            self.innovations[k, act] = inn.eps
            self.y_pred[k, act] = inn.yhat
            self.S[k, act] = inn.S
        else:
            ny, idx = self.innovations.shape[2], inn.idx
            tmp = np.full((act.size, ny), np.nan)
            tmp[:, idx] = inn.eps
            self.innovations[k, act] = tmp
            tmp = np.full((act.size, ny), np.nan)
            tmp[:, idx] = inn.yhat
            self.y_pred[k, act] = tmp
            tmpS = np.full((act.size, ny, ny), np.nan)
            tmpS[:, idx[:, None], idx[None, :]] = inn.S
            self.S[k, act] = tmpS
        self.nll_terms[k, act] = inn.term
        self.nis[k, act] = inn.maha

    def filtered(self, k: int, batch: FilterBatch, model, u: np.ndarray) -> None:
        """Store the filtered states, their outputs and covariances at k."""
        self.x_filt[k, batch.act] = batch.x
        with np.errstate(all="ignore"):
            self.y_filt[k, batch.act] = model.h(batch.x, u, batch.th)
        if self.P_filt is not None:
            self.P_filt[k, batch.act] = batch.P

    def into(self, res: UKFResult) -> None:
        """Blank every sample from a set's failure on and attach the arrays to ``res``."""
        for arr in (self.innovations, self.S, self.y_pred, self.y_filt, self.x_filt, self.nis):
            for p in np.flatnonzero(res.failed):
                arr[res.fail_step[p]:, p] = np.nan
        res.innovations, res.S, res.y_pred, res.y_filt = (self.innovations, self.S,
                                                          self.y_pred, self.y_filt)
        res.x_filt, res.P_filt = self.x_filt, self.P_filt
        res.nll_terms, res.nis = self.nll_terms, self.nis


# ------------------------------------------------------------------ filter
def ukf_nll(model, t, u, y, theta, x0=None, P0=None, *, options: UKFOptions | None = None,
            Q=None, R=None, store: bool | str = False) -> UKFResult:
    """Run the batched UKF over a record and return the NLL of each parameter set.

    Parameters
    ----------
    model : Model
        Generated model (:class:`bondgraph.numerics.model.Model`); uses ``f``,
        ``f_dfdx`` (ROS2), ``h``, ``meas_std``, ``proc_std``.
    t : array (N,)
        Sample times [s], strictly increasing (the step may vary).
    u : array (N, n_u) or None
        Inputs at the samples in model units (None: the model's defaults),
        held over each interval as ``options.hold`` says.
    y : array (N, n_y)
        Measured outputs in model units; NaN marks a missing sample.
    theta : array (P, n_theta) or (n_theta,)
        Full parameter vectors, one row per parameter set.
    x0 : array (n_x,) or (P, n_x), optional
        Prior mean of the state at ``t[0]`` (default ``model.x0``).
    P0 : array (n_x, n_x), (P, n_x, n_x) or (n_x,) (diagonal), optional
        Prior covariance at ``t[0]`` (default :func:`default_P0`).
    options : UKFOptions, optional
        Sigma-point scaling, discretisation and input hold (default
        ``UKFOptions()``: α = 1, β = 2, κ = 0, ROS2 with one step per
        sample and the Jacobian at the central sigma point, zero-order hold).
    Q : array (n_x, n_x) or (P, n_x, n_x), optional
        Extra discrete process-noise covariance added at every predict, on
        top of ``diag(proc_std(theta)**2) * dt``.
    R : array (n_y, n_y) or (P, n_y, n_y), optional
        Measurement-noise covariance (default ``diag(meas_std(theta)**2)``).
    store : bool or "full"
        Keep innovations, S, predicted and filtered outputs, filtered
        states, per-sample NLL terms and NIS (``"full"``: also the filtered
        covariances).

    Returns
    -------
    UKFResult
        ``nll`` (P,) and, when stored, arrays (N, P, ...). A set that fails
        gets +inf and a reason; the failure never raises.

    Raises
    ------
    DataError
        Non-increasing or non-finite times, non-finite inputs, infinite
        outputs or wrong array shapes.
    ModelError
        ``theta`` of the wrong shape.
    OptionError
        ``options`` not a :class:`UKFOptions`, n + κ <= 0, or wrong shapes
        of ``x0``, ``P0``, ``Q``, ``R``.
    """
    opts = ukf_options(options)
    t, u, y = _check_inputs(model, t, u, y)
    th = _check_theta(model, theta)
    wts = merwe_weights(model.n_x, opts.alpha, opts.beta, opts.kappa)
    step = interval_steps(model, opts, t.size - 1)
    u_held = hold_inputs(u, opts.hold)
    batch = FilterBatch(model, t, th, *_priors(model, th.shape[0], x0, P0, Q, R))
    kept = FilterStorage(t.size, th.shape[0], model, full=store == "full") if store else None
    kernels, note, compile_s = _backend_for(model, opts)
    t0 = time.perf_counter()
    if kernels is not None:
        compile_s += ukf_numba.run(kernels, t, u, y, batch, opts, wts, kept)
    else:
        _filter_numpy(model, batch, step, t, u, u_held, y, wts, kept)
    settings = dict(opts.to_dict(), n_regularised=batch.n_reg,
                    backend_used="numba" if kernels is not None else "numpy",
                    compile_s=compile_s, run_s=time.perf_counter() - t0 - compile_s)
    if note:
        settings["backend_note"] = note
    res = batch.result(model, t, y, settings=settings)
    if kept is not None:
        kept.into(res)
    return res


class IntervalSteps:
    """The transitions over a record's intervals of ``opts`` (a UKFOptions
    or Discretisation: method, substeps, refined runs): ``self(k)`` the
    step over interval k (:func:`bondgraph.numerics.integrators.make_step`
    with ``jacobian``); ``per`` (intervals,) the substeps of each interval
    (:func:`~bondgraph.inference.options.interval_substeps`)."""

    def __init__(self, model, opts, intervals: int, jacobian: str = "once"):
        self.per = interval_substeps(opts, intervals)
        self.steps = {int(n): make_step(model, opts.method, int(n), jacobian=jacobian)
                      for n in set(self.per.tolist()) | {int(opts.substeps)}}

    def __call__(self, k: int) -> Callable:
        return self.steps[int(self.per[k])]


def interval_steps(model, opts, intervals: int) -> IntervalSteps:
    """:class:`IntervalSteps` of ``opts`` (UKFOptions: its method, Jacobian,
    substeps and refined runs, :attr:`~bondgraph.inference.options.UKFOptions.refine`;
    a Discretisation: make_step's Jacobian once per step) over
    ``intervals`` intervals.

    Raises
    ------
    OptionError
        A refined run beyond the record (:func:`~bondgraph.inference.options.interval_substeps`).
    """
    jac = _ROS2_JACOBIAN[opts.jacobian] if hasattr(opts, "jacobian") else "once"
    return IntervalSteps(model, opts, intervals, jac)


def _filter_numpy(model, batch: FilterBatch, step_of: IntervalSteps, t, u, u_held, y,
                  wts: SigmaWeights, kept: "FilterStorage | None") -> None:
    """The numpy filter over the record (predict/update per sample for the
    whole batch; ``step_of(k)`` the transition over interval k,
    :func:`interval_steps`), filling ``batch`` and ``kept``."""
    dts = np.diff(t)
    for k in long_range(t.size, f"UKF pass: {batch.nll.size} parameter sets x {t.size} samples"):
        if k > 0 and batch.size:
            u_k, du_k = u_held.interval(k - 1)
            predict(batch, step_of(k - 1), u_k, dts[k - 1], wts, k, du_k)
        if not batch.size:
            break
        if np.isfinite(y[k]).any():
            inn = update(batch, model, u[k], y[k], wts, k)
            if inn is None:
                break
            if kept is not None:
                kept.innovation(k, batch.act, inn)
        if kept is not None:
            kept.filtered(k, batch, model, u[k])


#: models already warned about (BackendWarning once per model and cause)
_WARNED: set = set()


def _backend_for(model, opts: UKFOptions):
    """``(point kernels or None, note, compile seconds)``: the numba kernels
    of ``model`` when ``opts.backend`` is numba (compiled now if they are not
    in the cache: the backend is the caller's choice, taken literally, so
    that a result never depends on the calls before it or on the cache);
    None (numpy) for backend numpy, or with the reason when the kernel lacks
    an option or the model's kernels cannot be had (numba missing, a
    function numba cannot compile). A model numba cannot serve warns
    (:class:`~bondgraph.errors.BackendWarning`) once."""
    if opts.backend != "numba":
        return None, None, 0.0
    unsupported = ukf_numba.unsupported(opts)
    if unsupported:
        return None, unsupported, 0.0
    try:
        pk = point_kernels(model)
    except Exception as exc:  # numba missing or unable to compile a function
        note = f"numba kernels of '{model.name}' unavailable ({type(exc).__name__}: " \
               f"{str(exc).splitlines()[0] if str(exc) else ''}); numpy ran instead"
        if (model.name, type(exc).__name__) not in _WARNED:
            _WARNED.add((model.name, type(exc).__name__))
            warnings.warn(note, BackendWarning, stacklevel=3)
        return None, note, 0.0
    first = not getattr(pk, "_reported", False)
    pk._reported = True
    return pk, None, pk.compile_s if first else 0.0


def nll_from_innovations(innovations: np.ndarray, S: np.ndarray) -> np.ndarray:
    """NLL recomputed directly from stored innovations and covariances.

    Parameters
    ----------
    innovations : array (N, P, n_y)
        NaN for unmeasured outputs or skipped samples.
    S : array (N, P, n_y, n_y)

    Returns
    -------
    ndarray (P,)
        1/2 Σ_k [ln det S_k + ε_kᵀ S_k⁻¹ ε_k + m_k ln 2π] over the measured
        subset of each sample, with ``numpy.linalg.slogdet`` and ``solve``
        (an independent check of :func:`ukf_nll`).
    """
    N, Pn, ny = innovations.shape
    out = np.zeros(Pn)
    for k in range(N):
        for p in range(Pn):
            e = innovations[k, p]
            idx = np.flatnonzero(np.isfinite(e))
            if idx.size == 0:
                continue
            Sk = S[k, p][np.ix_(idx, idx)]
            sign, ld = np.linalg.slogdet(Sk)
            out[p] += 0.5 * (ld + e[idx] @ np.linalg.solve(Sk, e[idx]) + idx.size * LOG_2PI)
    return out


def discretisation_check(model, t, u, theta, x0=None, disc: Discretisation | None = None, *,
                         reference_substeps: int = 32, reference_method: str | None = None,
                         sigma=None, free_run: bool = True, states=None) -> dict:
    """Error of the filter's discretisation along a noise-free trajectory, in
    units of the measurement-noise standard deviation.

    The trajectory from ``x0`` is propagated sample by sample with the
    filter's step (``disc``: method and substeps) and with a fine reference
    (``reference_method`` with ``reference_substeps``, default: RK4 if it is
    finite there and agrees with RK4 at half the substeps, else ROS2:
    :func:`_reference_trajectory`), both restarted from the reference
    state at every sample, as inside the filter, and both with the input
    hold of ``disc`` (:func:`bondgraph.numerics.integrators.hold_inputs`). The
    one-step output error is compared with ``sigma`` (default
    ``meas_std(theta)``). The one-step transitions of all samples run as one
    batch (per distinct sample interval); the reference and the free run
    run in the compiled kernels (:func:`bondgraph.inference.sim_numba.rk4_trajectory`,
    :func:`~bondgraph.inference.sim_numba.ros2_trajectory`) when
    ``disc.backend`` is numba.

    Parameters
    ----------
    model : Model
    t : array (N,)
    u : array (N, n_u)
    theta : array (n_theta,)
    x0 : array (n_x,), optional
    disc : Discretisation, optional
        The discretisation under test: method, substeps, input hold
        (default ``Discretisation()``: ROS2, one step, zero-order hold).
    reference_substeps : int
    reference_method : {"rk4", "ros2"}, optional
    sigma : array (n_y,), optional
        Output scale of the comparison (default the measurement-noise std).
    free_run : bool
        Also propagate the free run (sequential; False: ``free_run`` is NaN).
    states : array (N, n_x) or callable, optional
        The filter's states, where an RK4 step must be stable too (as for
        :func:`discretisation_errors`).

    Returns
    -------
    dict
        ``one_step (n_y,)``: max over samples of |Δy|/σ for one step from
        the reference state (inf where an RK4 step is unstable on a mode of
        the Jacobian there, :func:`rk4_unstable`); ``free_run (n_y,)``: max |Δy|/σ of the free
        run (accumulated error, an upper bound of what process noise has to
        absorb); ``reference``: the reference used.
    """
    t = np.asarray(t, float)
    u = np.asarray(u, float).reshape(t.size, -1)
    th = np.asarray(theta, float)[None, :]
    x = (model.x0 if x0 is None else np.asarray(x0, float))[None, :]
    disc = Discretisation() if disc is None else disc
    hold = disc.hold
    step = interval_steps(model, disc, t.size - 1)
    held = hold_inputs(u, hold)
    with np.errstate(all="ignore"):
        xr, ref = _reference_trajectory(model, t, u, hold, th, x, reference_method,
                                        reference_substeps, disc.backend)
        if ref is None:
            return dict(one_step=np.full(model.n_y, np.inf), free_run=np.full(model.n_y, np.inf),
                        reference=None)
        sig = (np.asarray(model.meas_std(th), float)[0] if sigma is None
               else np.broadcast_to(np.asarray(sigma, float), (model.n_y,)))
        yr = model.h(xr[1:], u[1:], th)
        dev = np.abs(model.h(_one_steps(step, xr, held, th, t), u[1:], th) - yr) / sig
        if disc.method == "rk4":        # as discretisation_errors: an unstable step
            dev[_unstable_intervals(model, {}, hold, xr, states, held, th,
                                    np.diff(t) / step.per)] = np.inf
        one = np.maximum(np.zeros(model.n_y), np.max(dev, axis=0, initial=0.0))
        free = np.full(model.n_y, np.nan)
        if free_run:
            dev = np.abs(_free_run_deviations(model, disc, step, held, t, u, th, x, yr, sig))
            free = np.max(dev, axis=0, initial=0.0)
            free = np.where(np.isfinite(free), free, np.inf)
    return dict(one_step=one, free_run=free, reference=ref)


def discretisation_errors(model, t, u, theta, x0, discs, *, sigma=None, free_run: bool = False,
                          reference_substeps: int = 32, cache: dict | None = None,
                          states=None, directions=None) -> list[dict]:
    """The errors of :func:`discretisation_check` for several discretisations
    at once: the fine reference is propagated once per input hold and shared
    by every candidate with that hold (``one_step`` are the same numbers as
    ``discretisation_check(..., free_run=False)["one_step"]``).

    Parameters
    ----------
    model : Model
    t : array (N,)
    u : array (N, n_u)
    theta : array (n_theta,)
    x0 : array (n_x,) or None
        The initial state of the reference and of the free run (None: the
        model's X0).
    discs : sequence of Discretisation
        The candidates.
    sigma : array (n_y,), optional
        Output scale (default ``meas_std(theta)``); an output with σ = inf
        is left out (error 0).
    free_run : bool
        Also propagate each candidate's free run (sequential) and return the
        root sum of squares of its output error.
    reference_substeps : int
        RK4 (else ROS2) substeps of the reference.
    cache : dict, optional
        Hold -> reference, filled and reused across calls with the same
        model, record, θ and x0 (and ``states``).
    states : array (N, n_x) or callable, optional
        More states, one per sample, where an RK4 candidate must be stable
        too (:func:`rk4_unstable`; a callable returning them or None is
        called once, when a candidate is RK4): the filter's
        (:meth:`bondgraph.inference.problem.Problem.filtered_states`),
        which follow the record where the model's free run from x0 does not
        (a coast-down model without drag coasts faster than its record, and
        its tire-slip mode quickens as the speed falls).
    directions : array (p, n_theta), optional
        Steps of the estimated parameters: with ``free_run``,
        ``free_run_bias`` is ``‖P e‖`` of the Notes, the error projected on
        the reference's output sensitivities along them (differences).

    Returns
    -------
    list of dict
        Per candidate: ``one_step`` (n_y,), the max over samples of |Δy|/σ
        for one step from the reference state (inf where an RK4 step is
        unstable, :func:`rk4_unstable`), ``intervals`` (N − 1,) the
        max over outputs of each sample's; ``free_run_rss``, the root
        sum over samples and outputs of (Δy/σ)² of the free run against the
        reference (NaN without ``free_run``); ``free_run_bias``, its
        projection (``directions``; else ``free_run_rss``); ``reference``, the reference
        method (None when none was finite: the errors are inf). A value that
        is not finite is inf.

    Notes
    -----
    ``free_run_rss`` bounds the bias of any least-squares estimate that the
    free run's error causes, in Cramér-Rao standard deviations: with white
    output noise of std σ the bias is Δθ = (JᵀJ)⁻¹Jᵀe for the error e (in σ
    units) and the sensitivities J, and ‖(JᵀJ)^½ Δθ‖ = ‖P e‖ <= ‖e‖ for the
    projection P onto the range of J. A filter without process noise
    predicts by the free run once its state covariance has collapsed.
    """
    t = np.asarray(t, float)
    u = np.asarray(u, float).reshape(t.size, -1)
    th = np.asarray(theta, float)[None, :]
    x = (model.x0 if x0 is None else np.asarray(x0, float))[None, :]
    sig = (np.asarray(model.meas_std(th), float)[0] if sigma is None
           else np.broadcast_to(np.asarray(sigma, float), (model.n_y,)))
    refs = {} if cache is None else cache
    with np.errstate(all="ignore"):
        out = [_candidate_errors(model, disc, refs, t, u, th, x, sig, free_run,
                                 reference_substeps, states) for disc in discs]
        for disc, r in zip(discs, out):
            r["free_run_bias"] = _free_run_bias(model, refs, disc, r, (t, u, th, x, sig),
                                                directions, reference_substeps)
    return out


def _free_run_bias(model, refs: dict, disc, r: dict, run: tuple, directions,
                   substeps: int) -> float:
    """``free_run_bias`` of one candidate's entry ``r`` of
    :func:`discretisation_errors`: its free-run deviations projected onto
    the sensitivities along ``directions`` (``run`` = (t, u, θ, x0, σ)),
    else its ``free_run_rss``."""
    if directions is None or r.get("deviations") is None or not np.isfinite(r["free_run_rss"]):
        return r["free_run_rss"]
    J = _output_sensitivities(model, refs, disc.hold, *run, np.asarray(directions, float),
                              substeps, disc.backend)
    if J is None or not np.isfinite(J).all():      # no sensitivities: the bound, not 0
        return r["free_run_rss"]
    return _projected_norm(r["deviations"], J)


def _output_sensitivities(model, refs: dict, hold: str, t, u, th, x, sig, directions,
                          substeps: int, backend: str) -> np.ndarray | None:
    """The reference's output sensitivities ((N − 1)·n_y, p) in σ units along
    each row of ``directions`` (forward differences of the reference run by
    its own method; kept in ``refs`` under ``("sensitivities", hold)`` and
    the directions); None without a reference."""
    key = ("sensitivities", hold, directions.tobytes())
    if key not in refs:
        xr, ref = refs[hold]
        if ref is None:
            refs[key] = None
            return None
        held = hold_inputs(u, hold)
        y0 = model.h(xr[1:], u[1:], th)
        cols = []
        for d in directions:
            xd = _trajectory(model, t, u, hold, held, th + d[None, :], x, ref, substeps, backend)
            scale = float(np.linalg.norm(d))
            cols.append(((model.h(xd[1:], u[1:], th + d[None, :]) - y0) / sig).ravel()
                        * (1.0 / scale if scale > 0 else 0.0))
        refs[key] = np.stack(cols, axis=1) if cols else None
    return refs[key]


def _projected_norm(dev: np.ndarray, J: np.ndarray | None) -> float:
    """‖P e‖: the norm of ``dev`` (M, n_y), raveled, projected onto the span
    of the nonzero columns of ``J`` (M·n_y, p) (least squares); 0 without
    any (no estimated parameter moves the outputs)."""
    e = np.nan_to_num(np.asarray(dev, float).ravel(), nan=0.0, posinf=0.0, neginf=0.0)
    if J is None:
        return 0.0
    J = J[:, np.isfinite(J).all(axis=0) & (np.abs(J).sum(axis=0) > 0)]
    if J.shape[1] == 0:
        return 0.0
    coef = np.linalg.lstsq(J, e, rcond=None)[0]
    return float(np.linalg.norm(J @ coef))


def _candidate_errors(model, disc, refs: dict, t, u, th, x, sig, free_run: bool,
                      reference_substeps: int, states) -> dict:
    """One candidate's entry of :func:`discretisation_errors` (``refs``
    its cache of references and modes)."""
    if disc.hold not in refs:
        refs[disc.hold] = _reference_trajectory(model, t, u, disc.hold, th, x, None,
                                                reference_substeps, disc.backend)
    xr, ref = refs[disc.hold]
    if ref is None:
        return dict(one_step=np.full(model.n_y, np.inf), free_run_rss=np.inf, reference=None,
                    intervals=np.full(t.size - 1, np.inf))
    yr = model.h(xr[1:], u[1:], th)
    step = interval_steps(model, disc, t.size - 1)
    held = hold_inputs(u, disc.hold)
    dev = np.abs(model.h(_one_steps(step, xr, held, th, t), u[1:], th) - yr) / sig
    dev = np.where(np.isnan(dev), np.inf, dev)
    if disc.method == "rk4":
        dev[_unstable_intervals(model, refs, disc.hold, xr, states, held, th,
                                np.diff(t) / step.per)] = np.inf
    free = (_free_run_deviations(model, disc, step, held, t, u, th, x, yr, sig) if free_run
            else None)
    rss = np.nan
    if free is not None:
        ss = float(np.sum(free ** 2))
        rss = float(np.sqrt(ss)) if np.isfinite(ss) else float("inf")
    return dict(one_step=np.max(dev, axis=0, initial=0.0), free_run_rss=rss, reference=ref,
                intervals=np.max(dev, axis=1, initial=0.0), deviations=free)


def _unstable_intervals(model, refs: dict, hold: str, xr, states, held, th, h) -> np.ndarray:
    """Intervals (N − 1,) where an RK4 substep ``h`` is unstable along the
    reference ``xr`` or ``states`` (array, callable or None), their modes
    kept in ``refs`` under ``("modes", hold)`` (:func:`rk4_unstable`)."""
    if ("modes", hold) not in refs:
        more = states() if callable(states) else states
        refs["modes", hold] = [reference_modes(model, np.asarray(xs, float), held, th)
                               for xs in (xr, more) if xs is not None]
    bad = np.zeros(np.size(h), bool)
    for modes in refs["modes", hold]:
        bad |= rk4_unstable(modes, h)
    return bad


#: the most Jacobians whose eigenvalues :func:`reference_modes` takes along a
#: record (evenly spread; every interval is judged by the nearest one), and
#: the most scalar operations their eigenvalues may cost (n_x³ each): every
#: sample of a small model's record (a friction law's stiff mode lasts the
#: few samples of a reversal), some hundreds of a large one's
MODE_POINTS = 200_000
MODE_FLOPS = 5e8


def reference_modes(model, xr: np.ndarray, held, th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(samples (m,), eigenvalues (m, n_x))``: the modes of the state
    equations' Jacobian df/dx at reference states ``xr`` (N, n_x) with the
    inputs held at each interval's start, at most :data:`MODE_POINTS`
    samples evenly spread over the N − 1 intervals (fewer for a large state,
    :data:`MODE_FLOPS`). A Jacobian that cannot be had or is not finite
    gives no eigenvalues there (NaN, ignored)."""
    N, n = xr.shape[0] - 1, xr.shape[1]
    m = int(max(2, min(MODE_POINTS, N, MODE_FLOPS // max(n, 1) ** 3)))
    ks = np.unique(np.linspace(0, N - 1, m).round().astype(int))
    ev = np.full((ks.size, n), np.nan + 0j)
    with np.errstate(all="ignore"):
        try:
            J = np.asarray(model.dfdx(xr[ks], held.start[ks], np.repeat(th, ks.size, axis=0)),
                           float)[:, :n, :n]
        except (FloatingPointError, ValueError, ZeroDivisionError, OverflowError,
                AttributeError):        # no Jacobian: no modes, the one-step error stands
            return ks, ev
        ok = np.isfinite(J).all(axis=(1, 2))
        if ok.any():
            ev[ok] = np.linalg.eigvals(J[ok])
    return ks, ev


def rk4_unstable(modes: tuple[np.ndarray, np.ndarray], h: np.ndarray) -> np.ndarray:
    """Intervals (N − 1,) bool where an RK4 substep of length ``h`` (N − 1,)
    [s] puts a decaying or undamped mode of ``modes`` (:func:`reference_modes`;
    each interval judged by the nearest sample) outside RK4's stability
    region, |R(hλ)| > 1 (:func:`bondgraph.numerics.integrators.rk4_growth`;
    Hairer & Wanner 1996, IV.2): the step then amplifies every deviation from the
    reference — the filter's sigma points, the process noise — by |R| per
    substep, which a one-step error measured from the reference itself does
    not show. A coast-down graph's tire-slip mode at λ·dt = −10.3 (40 Hz):
    RK4 with 2 substeps met the one-step check (0.06 noise std) and grew the
    mode 16-fold per substep (its NLL 24 666 at 3 substeps against −577 by
    ROS2). Growing modes (Re λ > 0) are the model's own, not the step's."""
    ks, ev = modes
    h = np.asarray(h, float)
    if ks.size == 0 or h.size == 0:
        return np.zeros(h.size, bool)
    lam = np.where(np.isfinite(ev) & (ev.real <= 1e-12 * np.abs(ev)), ev, 0.0)
    k = np.arange(h.size)
    hi = np.minimum(np.searchsorted(ks, k), ks.size - 1)
    lo = np.maximum(hi - 1, 0)
    nearest = np.where(np.abs(ks[lo] - k) <= np.abs(ks[hi] - k), lo, hi)
    return rk4_growth(h[:, None] * lam[nearest]).max(axis=1, initial=0.0) > 1.0 + 1e-9


#: the substeps :func:`rk4_stable_substeps` tries, beyond the current ones
STABLE_SUBSTEPS = (2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64)


def rk4_stable_substeps(model, t, u, disc, theta, states) -> int | None:
    """The fewest substeps per interval, throughout, at which an RK4 filter
    step keeps every decaying or undamped mode of the state equations'
    Jacobian inside its stability region (:func:`rk4_unstable`) along
    ``states`` (N, n_x): None when ``disc``'s own (its refined runs
    included) already do, or its method is not RK4 (ROS2 is L-stable);
    ``0`` when none of :data:`STABLE_SUBSTEPS` does.

    A stiff law a candidate brings (a Stribeck or Coulomb friction's
    narrow tanh at a large level) can put its mode outside the stability
    region of the step the model without it needed: the filter's NLL is
    then the unstable step's, rough in the parameters, and the Fisher
    scoring stops on it (a user's EMPS graph at 1 kHz, RK4(1): a Stribeck
    refit of ds = 1026 N over a 0.7 mm/s width, mode ≈ −1e4 1/s, ended
    17 000 nats above the model without it, its line searches refused at
    every damping).

    Parameters
    ----------
    model : Model
    t : array (N,) [s]
    u : array (N, n_u)
    disc : Discretisation or UKFOptions
        Its ``method``, ``substeps``, refined runs and ``hold``.
    theta : array (n_theta,)
    states : array (N, n_x) or None
        Where the filter's states go (e.g. its estimates by an L-stable
        method, :meth:`bondgraph.inference.problem.Problem.filtered_states`);
        None: not judged (None returned).

    Returns
    -------
    int or None
    """
    if disc.method != "rk4" or states is None or t.size < 2:
        return None
    held = hold_inputs(u, disc.hold)
    th = np.asarray(theta, float).reshape(1, -1)
    modes = reference_modes(model, np.asarray(states, float), held, th)
    dt = np.diff(t)
    per = interval_substeps(disc, t.size - 1)
    if not rk4_unstable(modes, dt / per).any():
        return None
    return next((n for n in STABLE_SUBSTEPS if n > int(np.max(per))
                 and not rk4_unstable(modes, dt / n).any()), 0)


def _free_run_deviations(model, disc, step, held, t, u, th, x, yr, sig) -> np.ndarray:
    """(y_free − y_ref)/σ (N − 1, n_y) of the free run of ``disc`` from ``x``
    against the reference outputs ``yr`` of samples 1..N−1: compiled when
    ``disc.backend`` is numba (:func:`_compiled_run`, a refined
    discretisation's runs one stretch of equal substeps at a time; the
    numpy steps took 0.2-1 ms a sample, the choice of a long record's
    discretisation tries several), else ``step`` (:func:`interval_steps`)
    sample by sample (the same steps; ROS2 agrees to rounding)."""
    X = (_compiled_stretches(model, t, u, disc, th, x) if disc.backend == "numba" else None)
    if X is None:
        xs, xf = [], x
        for k in range(t.size - 1):
            uk, duk = held.interval(k)
            xf = step(k)(xf, uk, th, t[k + 1] - t[k], duk)
            xs.append(xf)
        X = np.concatenate([x] + xs)
    return (model.h(X[1:], u[1:], th) - yr) / sig


def _compiled_stretches(model, t, u, disc: Discretisation, th, x) -> np.ndarray | None:
    """:func:`_compiled_run` of ``disc`` over the record, a refined
    discretisation's intervals one stretch of equal substeps at a time
    (each stretch from the state the one before it ended in)."""
    if not disc.refine:
        return _compiled_run(model, t, u, disc.hold, th, x, disc.method, disc.substeps)
    per = disc.interval_substeps(t.size - 1)
    cuts = np.flatnonzero(np.diff(per)) + 1
    parts, xs = [x[0][None, :]], x
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, per.size]):
        X = _compiled_run(model, t[a:b + 1], u[a:b + 1], disc.hold, th, xs, disc.method,
                          int(per[a]))
        if X is None:
            return None
        parts.append(X[1:])
        xs = X[-1:]
    return np.concatenate(parts)


def _one_steps(step: IntervalSteps, xr: np.ndarray, held, th: np.ndarray,
               t: np.ndarray) -> np.ndarray:
    """States (N-1, n_x) one step (``step(k)``) after each reference state
    ``xr[k]`` (k < N-1), over its own interval: one batched call per
    distinct interval length and substeps (the same arithmetic as a call
    per sample)."""
    dts = np.diff(t)
    out = np.empty((dts.size, xr.shape[1]))
    per = step.per
    for dt in np.unique(dts):
        for n in np.unique(per[dts == dt]):
            ks = np.flatnonzero((dts == dt) & (per == n))
            du = None if held.change is None else held.change[ks]
            out[ks] = step(int(ks[0]))(xr[ks], held.start[ks], th, dt, du)
    return out


#: the reference of :func:`sigma_point_errors`: the filter's method at this
#: many times the largest substeps under test
SIGMA_REFERENCE_FACTOR = 8
#: intervals per batch of :func:`sigma_point_errors` (memory bound)
SIGMA_CHUNK = 2048


def sigma_point_errors(model, t, u, theta, x_filt, P_filt, options: UKFOptions,
                       substeps: Sequence[int], sigma) -> np.ndarray:
    """Each interval's one-step output error at the filter's own sigma points.

    The posterior sigma points at every sample k < N − 1 (the filtered
    means ``x_filt`` and covariances ``P_filt`` of a stored run, the
    filter's weights) go over interval k with each of ``substeps`` and
    with a fine reference (the filter's method at
    :data:`SIGMA_REFERENCE_FACTOR` times the largest of ``substeps``), the
    inputs held as ``options`` say; the error of an interval is the
    largest over its sigma points and the outputs of |Δh|/σ at sample
    k + 1. Unlike :func:`discretisation_check`, measured along a
    noise-free trajectory, this sees where the filter's sigma points
    meet a stiff or non-smooth stretch (a friction law's zero crossing
    that the mean passes by but its spread reaches).

    Parameters
    ----------
    model : Model
    t : array (N,)
    u : array (N, n_u)
    theta : array (n_theta,)
    x_filt : array (N, n_x)
    P_filt : array (N, n_x, n_x)
    options : UKFOptions
        The filter's sigma-point scaling, method, Jacobian and hold.
    substeps : sequence of int (k,)
    sigma : array (n_y,)
        Output scale (noise std); an output with σ = inf is left out.

    Returns
    -------
    ndarray (k, N − 1)
        Errors in units of σ; inf where a propagation is not finite or a
        posterior covariance cannot be factored.
    """
    opts = ukf_options(options)
    t = np.asarray(t, float)
    u = np.asarray(u, float).reshape(t.size, -1)
    th = np.asarray(theta, float)[None, :]
    sig = np.broadcast_to(np.asarray(sigma, float), (model.n_y,))
    wts = merwe_weights(model.n_x, opts.alpha, opts.beta, opts.kappa)
    jac = _ROS2_JACOBIAN[opts.jacobian]
    counts = [int(n) for n in substeps]
    steps = [make_step(model, opts.method, n, jacobian=jac) for n in counts]
    ref_step = make_step(model, opts.method, SIGMA_REFERENCE_FACTOR * max(counts), jacobian=jac)
    held = hold_inputs(u, opts.hold)
    M, B = t.size - 1, 2 * model.n_x + 1
    out = np.full((len(counts), M), np.inf)
    dts = np.diff(t)
    with np.errstate(all="ignore"):
        for a in range(0, M, SIGMA_CHUNK):
            ks = np.arange(a, min(a + SIGMA_CHUNK, M))
            L, ok, _ = cholesky_batch(np.asarray(P_filt[ks], float), known=True)
            chi, _ = sigma_points(np.asarray(x_filt[ks], float), L, wts.c)
            for dt in np.unique(dts[ks]):
                sel = np.flatnonzero((dts[ks] == dt) & ok)
                if not sel.size:
                    continue
                k_sel = ks[sel]
                X = chi[sel].reshape(-1, model.n_x)
                U = np.repeat(held.start[k_sel], B, axis=0)
                dU = None if held.change is None else np.repeat(held.change[k_sel], B, axis=0)
                u1 = np.repeat(u[k_sel + 1], B, axis=0)
                y_ref = model.h(ref_step(X, U, th, dt, dU), u1, th)
                for i, step in enumerate(steps):
                    d = np.abs(model.h(step(X, U, th, dt, dU), u1, th) - y_ref) / sig
                    d = np.where(np.isnan(d), np.inf, d).max(axis=1).reshape(sel.size, B)
                    out[i, k_sel] = d.max(axis=1)
    return out


#: an RK4 reference is trusted when the same run at half its substeps is
#: finite and within this fraction of each state's largest magnitude of it
REFERENCE_AGREEMENT = 1e-3


def _reference_trajectory(model, t, u, hold, th, x, method, substeps, backend):
    """``(states (N, n_x), method)`` of the fine reference of
    :func:`discretisation_check`: ``method`` with ``substeps`` and the inputs
    ``u`` held as ``hold`` says, or by default RK4 when its trajectory is
    finite and agrees with RK4 at half the substeps
    (:data:`REFERENCE_AGREEMENT`), else ROS2 (L-stable); either in the
    compiled kernels when ``backend`` is numba (:func:`_compiled_run`);
    ``(None, None)`` if none is finite.

    The agreement test catches an RK4 at the edge of its stability region:
    on a stiff belt-creep model (12 states, 40 Hz) RK4 with 8 and 16
    substeps overflowed and with 32 ran finite but wrong (a state's peak
    103 against 139 by ROS2 with 8, 16 and 32 substeps alike), and every
    one-step error measured from it came out 1e12 noise stds."""
    held = hold_inputs(u, hold)
    for cand in ([method] if method else ["rk4", "ros2"]):
        xr = _trajectory(model, t, u, hold, held, th, x, cand, substeps, backend)
        if not np.isfinite(xr).all():
            continue
        if method is None and cand == "rk4" and substeps > 1 and not _agree(
                xr, _trajectory(model, t, u, hold, held, th, x, cand, substeps // 2, backend)):
            continue
        return xr, cand
    return None, None


def _trajectory(model, t, u, hold, held, th, x, method, substeps, backend) -> np.ndarray:
    """States (N, n_x) from ``x`` (1, n_x) by ``method`` with ``substeps``
    (:func:`_reference_trajectory`'s run)."""
    xr = (_compiled_run(model, t, u, hold, th, x, method, substeps)
          if backend == "numba" else None)
    if xr is not None:
        return xr
    rstep = make_step(model, method, substeps)
    xs = [x]
    with np.errstate(all="ignore"):
        for k in range(t.size - 1):
            uk, duk = held.interval(k)
            xs.append(rstep(xs[-1], uk, th, t[k + 1] - t[k], duk))
    return np.concatenate(xs)


def _agree(fine: np.ndarray, coarse: np.ndarray) -> bool:
    """Whether two trajectories (N, n_x) agree within
    :data:`REFERENCE_AGREEMENT` of each state's largest magnitude in
    ``fine`` (non-finite ``coarse``: no)."""
    if not np.isfinite(coarse).all():
        return False
    scale = np.max(np.abs(fine), axis=0) + 1e-300
    return bool(np.all(np.max(np.abs(fine - coarse), axis=0) <= REFERENCE_AGREEMENT * scale))


def _compiled_run(model, t, u, hold, th, x, method, substeps) -> np.ndarray | None:
    """States (N, n_x) from ``x`` (1, n_x) by ``method`` ("rk4" or "ros2")
    with ``substeps``, the inputs held as ``hold`` says, in the compiled
    trajectory kernels (:func:`bondgraph.inference.sim_numba.trajectory`), or
    None (numpy then) when numba, the model's kernels or the hold are
    unavailable (:func:`bondgraph.inference.prior.free_run_kernels`)."""
    kernels = free_run_kernels(model, "numba", method, hold)
    if kernels is None:
        return None
    return sim_numba.trajectory(kernels, t, u, hold, th[0], x[0], method, substeps)


#: the discretisation guard's reference: RK4 with this many sub-steps per sample
GUARD_SUBSTEPS = 40
#: relative NLL difference above which the guard warns
GUARD_REL = 1e-3


def nll_guard(model, t, u, y, theta, x0=None, P0=None, *, options: UKFOptions | None = None,
              Q=None, R=None, nll: float | None = None) -> dict:
    """Discretisation guard of the likelihood: the NLL at ``theta`` with the
    filter's discretisation against a reference with RK4 and
    :data:`GUARD_SUBSTEPS` sub-steps per sample (everything else equal;
    ROS2, L-stable, with as many where RK4's is not finite: a user's CED
    graph at an estimate with L_a 0.001 H and R_a 100 Ω, an armature mode at
    1e5 1/s sampled at 50 Hz).

    If they differ by more than :data:`GUARD_REL` relative, the filter's
    method is tried with 2, 4, 8 ... times its sub-steps (up to
    GUARD_SUBSTEPS) until its NLL is within GUARD_REL of the reference.

    Parameters
    ----------
    model, t, u, y, x0, P0, Q, R :
        As for :func:`ukf_nll`.
    theta : array (n_theta,)
        One full parameter vector (the estimate).
    options : UKFOptions, optional
        The filter's options (method, substeps, backend ...).
    nll : float, optional
        The NLL at ``theta`` with ``options`` if already known.

    Returns
    -------
    dict
        ``nll``, ``nll_reference`` (RK4(40), else ROS2(40): ``reference``
        names it), ``rel_diff`` (|Δ| / |reference|,
        inf when only one is finite), ``ok`` (rel_diff <= GUARD_REL),
        ``substeps_needed`` (int, or None when ok, when GUARD_SUBSTEPS of
        the method are not enough, or when the reference failed: then no
        sub-steps are tried), ``tried`` {substeps: nll}.
    """
    opts = ukf_options(options)
    th = np.asarray(theta, float)[None, :]

    def at(o):
        return float(ukf_nll(model, t, u, y, th, x0, P0, options=o, Q=Q, R=R).nll[0])

    value = at(opts) if nll is None else float(nll)
    method = "rk4"
    ref = at(replace(opts, method=method, substeps=GUARD_SUBSTEPS, refine=()))
    if not np.isfinite(ref):        # a mode too fast for RK4 even so: the L-stable ROS2
        method = "ros2"
        ref = at(replace(opts, method=method, substeps=GUARD_SUBSTEPS, refine=()))
    out = dict(nll=value, nll_reference=ref, rel_diff=_rel_diff(value, ref), ok=True,
               substeps_needed=None, tried={}, reference=f"{method}({GUARD_SUBSTEPS})")
    out["ok"] = bool(out["rel_diff"] <= GUARD_REL)
    s = opts.substeps
    while not out["ok"] and np.isfinite(ref) and s < GUARD_SUBSTEPS:
        s = min(2 * s, GUARD_SUBSTEPS)
        out["tried"][s] = at(replace(opts, substeps=s))
        if _rel_diff(out["tried"][s], ref) <= GUARD_REL:
            out["substeps_needed"] = s
            break
    return out


def _rel_diff(a: float, ref: float) -> float:
    """|a − ref| / |ref|; 0 when both are the same infinity, inf when only one is finite."""
    if not (np.isfinite(a) and np.isfinite(ref)):
        return 0.0 if a == ref else float("inf")
    return abs(a - ref) / max(abs(ref), np.finfo(float).tiny)
