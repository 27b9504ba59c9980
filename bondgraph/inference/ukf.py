"""Batched unscented Kalman filter and its negative log-likelihood.

One call filters a whole record for ``P`` parameter sets at once: every
array operation works on ``(P, 2n+1, n)`` sigma points (particles x sigma
points), and each stage of the discretisation is one call of the generated
model functions for the whole batch. There is no Python loop over particles
or sigma points; the only loop is over the samples of the record.

Filter (additive process and measurement noise; Wan & van der Merwe 2000,
scaled sigma points of Julier 2002, the parametrisation of
``filterpy.kalman.MerweScaledSigmaPoints``)::

    λ = α²(n + κ) − n,  c = sqrt(n + λ) = α sqrt(n + κ)
    χ_0 = x̂,  χ_i = x̂ + c L_i,  χ_n+i = x̂ − c L_i     (L L^T = P, Cholesky)
    W_0^m = λ/(n+λ),  W_0^c = W_0^m + 1 − α² + β,  W_i = 1/(2(n+λ))

The sequence of operations is that of filterpy 2.0's
``UnscentedKalmanFilter``: ``predict`` propagates sigma points drawn from the
posterior and forms the prior (x⁻, P⁻ + Q); ``update`` re-draws sigma points
from the prior, passes them through h, forms ŷ, S = P_yy + R, the cross
covariance P_xy, K = P_xy S⁻¹, x⁺ = x⁻ + K ε, P⁺ = P⁻ − K S Kᵀ. The prior at
``t[0]`` is ``(x0, P0)``: sample 0 is an update without a predict.

Means and covariances are formed from differences to the central sigma
point. With Σ W^m = 1 and equal weights W off the centre, the weighted sums
are exactly (d_i = χ_i − χ_0, m = W Σ d_i)::

    mean = χ_0 + m,   cov = W Σ d_i d_iᵀ + (β − α²) m mᵀ

which is the same quantity as Σ W_i^c (χ_i − mean)(χ_i − mean)ᵀ but does not
subtract numbers of size 1/α² (about 10⁶ at α = 1e-3): the criterion stays
accurate and smooth for α from 1e-3 to 1.

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

Discretisation between samples (inputs held over the interval):
``"rk4"`` (classical Runge-Kutta with sub-steps) or ``"ros2"`` (the L-stable
linearly implicit Rosenbrock method of :func:`bondgraph.numerics.integrators.ros2`,
generated Jacobian evaluated once per sample interval).

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

from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bondgraph.errors import DataError, ModelError, OptionError
from bondgraph.inference.options import UKFOptions, ukf_options
from bondgraph.numerics.integrators import GAMMA

LOG_2PI = float(np.log(2.0 * np.pi))




# --------------------------------------------------------------- weights
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
def _cholesky_batch(A: np.ndarray, regularise: bool = True):
    """Lower Cholesky factors of symmetric A (B, n, n).

    A matrix that fails is retried with relative diagonal loading
    A + ε diag(A), ε = 1e-12, 1e-9, 1e-6 (scale-invariant: each state in its own
    units), which absorbs the rounding-level indefiniteness of covariances
    contracted by fast stable modes without process noise. Returns
    ``(L, ok (B,), n_regularised)``; failing entries of L are identity.
    """
    ok = np.isfinite(A).all(axis=(-2, -1))
    if ok.all():
        try:
            return np.linalg.cholesky(A), ok, 0
        except np.linalg.LinAlgError:
            pass
    L = np.zeros_like(A)
    n = A.shape[-1]
    nreg = 0
    for b in np.flatnonzero(ok):
        try:
            L[b] = np.linalg.cholesky(A[b])
            continue
        except np.linalg.LinAlgError:
            pass
        done = False
        if regularise:
            d = np.diagonal(A[b]).copy()
            if (d > 0).all():
                for eps in (1e-12, 1e-9, 1e-6):
                    try:
                        L[b] = np.linalg.cholesky(A[b] + np.diag(eps * d))
                        done = True
                        nreg += 1
                        break
                    except np.linalg.LinAlgError:
                        pass
        if not done:
            ok[b] = False
    L[~ok] = np.eye(n)
    return L, ok, nreg


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


def default_P0(model, x0: np.ndarray | None = None, rel: float = 0.05) -> np.ndarray:
    """A diagonal initial covariance: (rel·max(|x0_i|, 1))² on the diagonal.

    Parameters
    ----------
    model : Model
    x0 : array (n_x,), optional
        Initial state (default ``model.x0``).
    rel : float
        Relative standard deviation.

    Returns
    -------
    ndarray (n_x, n_x)
    """
    x0 = model.x0 if x0 is None else np.asarray(x0, dtype=float)
    sd = rel * np.maximum(np.abs(x0), 1.0)
    return np.diag(sd ** 2)


def _transition(model, method: str, substeps: int, jacobian: str = "mean"):
    """Batched x(t+dt) for sigma points; see :mod:`bondgraph.numerics.integrators`."""
    if substeps < 1:
        raise OptionError(f"substeps must be >= 1, got {substeps}")
    f = model.f
    if method == "rk4":
        def step(x, u, th, dt):
            h = dt / substeps
            for _ in range(substeps):
                k1 = f(x, u, th)
                k2 = f(x + (0.5 * h) * k1, u, th)
                k3 = f(x + (0.5 * h) * k2, u, th)
                k4 = f(x + h * k3, u, th)
                x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
            return x
        return step
    if method == "ros2":
        f_dfdx = model.f_dfdx
        n = model.n_x
        eye = np.eye(n)
        if jacobian not in ("mean", "sigma"):
            raise OptionError(f"unknown ROS2 Jacobian option '{jacobian}' (use 'mean' or 'sigma')")

        def step(x, u, th, dt):
            h = dt / substeps
            if jacobian == "sigma" or x.ndim < 3:
                F0, J = f_dfdx(x, u, th)
                Winv = np.linalg.inv(eye - (GAMMA * h) * J)          # (..., n, n)
                def solve(r):
                    return (Winv @ r[..., None])[..., 0]
            else:
                # W-method: one Jacobian per parameter set, at the central
                # sigma point, shared by all its sigma points
                _, J = f_dfdx(x[:, 0], u, th[:, 0])                 # (P, n, n)
                WinvT = np.swapaxes(np.linalg.inv(eye - (GAMMA * h) * J), -1, -2)
                F0 = f(x, u, th)

                def solve(r):
                    return r @ WinvT                                # (P, 2n+1, n)
            for s_ in range(substeps):
                if s_ > 0:
                    F0 = f(x, u, th)
                # W k1 = F0 ; W k2 = f(x + h k1) - 2 k1  (ROS2, frozen W)
                k1 = solve(F0)
                F1 = f(x + h * k1, u, th)
                k2 = solve(F1 - 2.0 * k1)
                x = x + (1.5 * h) * k1 + (0.5 * h) * k2
            return x
        return step
    raise OptionError(f"unknown discretisation method '{method}' (use 'rk4' or 'ros2')")


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
        Inputs at the samples in model units, held constant from t_k to
        t_k+1 (zero-order hold). None: the model's default inputs.
    y : array (N, n_y)
        Measured outputs in model units; NaN marks a missing sample.
    theta : array (P, n_theta) or (n_theta,)
        Full parameter vectors, one row per parameter set.
    x0 : array (n_x,) or (P, n_x), optional
        Prior mean of the state at ``t[0]`` (default ``model.x0``).
    P0 : array (n_x, n_x), (P, n_x, n_x) or (n_x,) (diagonal), optional
        Prior covariance at ``t[0]`` (default :func:`default_P0`).
    Q : array (n_x, n_x) or (P, n_x, n_x), optional
        Extra discrete process-noise covariance added at every predict, on
        top of ``diag(proc_std(theta)**2) * dt``.
    R : array (n_y, n_y) or (P, n_y, n_y), optional
        Measurement-noise covariance (default ``diag(meas_std(theta)**2)``).
    options : UKFOptions, optional
        Sigma-point scaling (α, β, κ), discretisation (``method``,
        ``substeps``, ROS2 ``jacobian``) and input ``hold``; default
        ``UKFOptions()`` (α = 1, β = 2, κ = 0, ROS2 with one step per sample,
        Jacobian at the central sigma point, zero-order hold).
    store : bool or "full"
        Keep innovations, S, predicted and filtered outputs, filtered
        states, per-sample NLL terms and NIS (``"full"``: also the filtered
        covariances).

    Returns
    -------
    UKFResult
        ``nll`` (P,) and, when stored, arrays (N, P, ...).

    Raises
    ------
    DataError
        Non-increasing or non-finite times, non-finite inputs, infinite
        outputs or wrong array shapes.
    OptionError
        ``options`` not a :class:`UKFOptions`, n + κ <= 0, or wrong shapes
        of ``x0``, ``P0``, ``Q``, ``R``.

    Notes
    -----
    A parameter set that fails (non-finite parameter, non-finite propagated
    sigma point, a covariance P or an innovation covariance S that is not
    positive definite) gets +inf and a reason; the failure never raises.
    Cost per sample: one Cholesky of (P, n, n) for the prior sigma points,
    one for the update, one of (P, m, m) for S, and ``substeps`` x 2 (ROS2)
    or x 4 (RK4) calls of ``f`` on (P, 2n+1, n) arrays.
    """
    opts = ukf_options(options)
    alpha, beta, kappa = opts.alpha, opts.beta, opts.kappa
    method, substeps, jacobian, hold = opts.method, opts.substeps, opts.jacobian, opts.hold
    t, u, y = _check_inputs(model, t, u, y)
    if hold == "zoh":
        u_pred = u
    elif hold == "mean":
        u_pred = u.copy()
        u_pred[:-1] = 0.5 * (u[:-1] + u[1:])
    else:
        raise OptionError(f"unknown input hold '{hold}' (use 'zoh' or 'mean')")
    th = np.asarray(theta, dtype=float)
    if th.ndim == 1:
        th = th[None, :]
    if th.ndim != 2 or th.shape[1] != model.n_theta:
        raise ModelError(f"theta must have shape (P, {model.n_theta}) for model '{model.name}' "
                         f"(parameters {model.params}), got {np.shape(theta)}")
    Pn, n, ny, N = th.shape[0], model.n_x, model.n_y, t.size
    wts = merwe_weights(n, alpha, beta, kappa)
    step = _transition(model, method, int(substeps), jacobian)
    c, w, cc = wts.c, wts.w, wts.center_cov

    # ---- priors
    x0 = model.x0 if x0 is None else np.asarray(x0, dtype=float)
    if x0.shape == (n,):
        x = np.broadcast_to(x0, (Pn, n)).copy()
    elif x0.shape == (Pn, n):
        x = x0.copy()
    else:
        raise OptionError(f"x0 must have shape ({n},) or ({Pn}, {n}), got {x0.shape}")
    P0 = default_P0(model, x0 if x0.ndim == 1 else None) if P0 is None else P0
    Pc = np.array(_as_batch_matrix(P0, Pn, n, "P0"), dtype=float)
    Qx = _as_batch_matrix(Q, Pn, n, "Q")
    Rfix = _as_batch_matrix(R, Pn, ny, "R")

    # ---- bookkeeping
    nll = np.zeros(Pn)
    failed = np.zeros(Pn, dtype=bool)
    fail_step = np.full(Pn, -1, dtype=int)
    reasons: list[Any] = [None] * Pn
    bad_th = ~np.isfinite(th).all(axis=1)
    for p in np.flatnonzero(bad_th):
        j = int(np.flatnonzero(~np.isfinite(th[p]))[0])
        failed[p], fail_step[p] = True, 0
        reasons[p] = f"sample 0: non-finite parameter '{model.params[j]}' = {th[p, j]}"
    with np.errstate(all="ignore"):
        q2 = np.asarray(model.proc_std(th), dtype=float) ** 2          # (P, n)
        Rdiag = np.asarray(model.meas_std(th), dtype=float) ** 2 if Rfix is None else None
    bad_q = ~np.isfinite(q2).all(axis=1) & ~failed
    for p in np.flatnonzero(bad_q):
        failed[p], fail_step[p] = True, 0
        reasons[p] = "sample 0: non-finite process-noise intensity proc_std(theta)"
    if Rdiag is not None:
        bad_r = (~np.isfinite(Rdiag).all(axis=1) | (Rdiag <= 0).any(axis=1)) & ~failed
        for p in np.flatnonzero(bad_r):
            failed[p], fail_step[p] = True, 0
            reasons[p] = "sample 0: measurement-noise variance meas_std(theta)**2 not positive"
    act = np.flatnonzero(~failed)                                      # active set indices

    obs = np.isfinite(y)
    n_obs = obs.sum(axis=1)
    full_obs = n_obs == ny
    dts = np.diff(t)

    st = bool(store)
    if st:
        nanf = np.full
        inn = nanf((N, Pn, ny), np.nan)
        S_st = nanf((N, Pn, ny, ny), np.nan)
        yp_st = nanf((N, Pn, ny), np.nan)
        yf_st = nanf((N, Pn, ny), np.nan)
        xf_st = nanf((N, Pn, n), np.nan)
        Pf_st = nanf((N, Pn, n, n), np.nan) if store == "full" else None
        terms = np.zeros((N, Pn))
        nis = nanf((N, Pn), np.nan)

    # active working arrays
    x = x[act]
    Pc = Pc[act]
    tha = th[act]
    th_b = tha[:, None, :]                                             # (A, 1, nθ)
    q2a = q2[act]
    Qa = None if Qx is None else np.asarray(Qx)[act]
    Ra_full = None if Rfix is None else np.asarray(Rfix)[act]
    Rda = None if Rdiag is None else Rdiag[act]
    n_reg = 0

    def drop(mask_bad, k, why):
        """Mark active sets (mask over the active arrays) as failed."""
        nonlocal act, x, Pc, tha, th_b, q2a, Qa, Ra_full, Rda
        for a in np.flatnonzero(mask_bad):
            p = act[a]
            failed[p], fail_step[p] = True, k
            nll[p] = np.inf
            reasons[p] = f"sample {k} (t = {t[k]:.6g} s): {why}"
        keep = ~mask_bad
        act = act[keep]
        x, Pc, tha = x[keep], Pc[keep], tha[keep]
        th_b = tha[:, None, :]
        q2a = q2a[keep]
        Qa = None if Qa is None else Qa[keep]
        Ra_full = None if Ra_full is None else Ra_full[keep]
        Rda = None if Rda is None else Rda[keep]
        return keep

    def sigma_points(k, what):
        nonlocal n_reg
        L, ok, nr = _cholesky_batch(Pc)
        n_reg += nr
        if not ok.all():
            keep = drop(~ok, k, f"{what} covariance P not positive definite")
            L = L[keep]
        cL = c * np.swapaxes(L, -1, -2)                                # rows = scaled columns of L
        chi = np.empty((x.shape[0], 2 * n + 1, n))
        chi[:, 0] = x
        chi[:, 1:n + 1] = x[:, None, :] + cL
        chi[:, n + 1:] = x[:, None, :] - cL
        return chi, cL

    for k in range(N):
        if act.size == 0:
            break
        # ------------------------------------------------ predict (k-1 -> k)
        if k > 0:
            dt = dts[k - 1]
            chi, _ = sigma_points(k, "posterior")
            if act.size == 0:
                break
            with np.errstate(all="ignore"):
                X = step(chi, u_pred[k - 1], th_b, dt)
            fin = np.isfinite(X).all(axis=(1, 2))
            if not fin.all():
                keep = drop(~fin, k, "non-finite state in the prediction (sigma point diverged)")
                X = X[keep]
                if act.size == 0:
                    break
            D = X[:, 1:] - X[:, :1]                                    # (A, 2n, n)
            m = w * D.sum(axis=1)                                      # (A, n)
            x = X[:, 0] + m
            Pc = w * (np.swapaxes(D, 1, 2) @ D) + cc * (m[:, :, None] * m[:, None, :])
            Pc.reshape(Pc.shape[0], n * n)[:, ::n + 1] += q2a * dt
            if Qa is not None:
                Pc += Qa
        # ------------------------------------------------ update at k
        if n_obs[k] > 0:
            chi, cL = sigma_points(k, "prior")
            if act.size == 0:
                break
            with np.errstate(all="ignore"):
                Y = model.h(chi, u[k], th_b)                           # (A, 2n+1, ny)
            if full_obs[k]:
                idx = None
                yk = y[k]
            else:
                idx = np.flatnonzero(obs[k])
                Y = Y[..., idx]
                yk = y[k, idx]
            fin = np.isfinite(Y).all(axis=(1, 2))
            if not fin.all():
                keep = drop(~fin, k, "non-finite predicted output h(sigma point)")
                Y, cL = Y[keep], cL[keep]
                if act.size == 0:
                    break
            E = Y[:, 1:] - Y[:, :1]                                    # (A, 2n, m)
            my = w * E.sum(axis=1)
            yhat = Y[:, 0] + my
            S = w * (np.swapaxes(E, 1, 2) @ E) + cc * (my[:, :, None] * my[:, None, :])
            if Rda is not None:
                rd = Rda if idx is None else Rda[:, idx]
                mm = rd.shape[1]
                S.reshape(S.shape[0], mm * mm)[:, ::mm + 1] += rd
            else:
                S += Ra_full if idx is None else Ra_full[:, idx][:, :, idx]
            # cross covariance: sigma points are symmetric about x, so
            # P_xy = W Σ_i cL_i (E_+i − E_−i)ᵀ exactly (the mean term vanishes)
            Pxy = w * (np.swapaxes(cL, 1, 2) @ (E[:, :n] - E[:, n:]))
            Ls, ok, nr = _cholesky_batch(S)
            n_reg += nr
            if not ok.all():
                keep = drop(~ok, k, "innovation covariance S not positive definite")
                Ls, S, Pxy, yhat = Ls[keep], S[keep], Pxy[keep], yhat[keep]
                if act.size == 0:
                    break
            eps = yk - yhat                                            # (A, m)
            mm = eps.shape[1]
            # one triangular solve for [Pxyᵀ | ε]: G = Pxy Ls⁻ᵀ, z = Ls⁻¹ ε
            rhs = np.concatenate([np.swapaxes(Pxy, 1, 2), eps[:, :, None]], axis=2)
            sol = np.linalg.solve(Ls, rhs)
            Gt, z = sol[:, :, :n], sol[:, :, n]
            logdet = 2.0 * np.log(np.diagonal(Ls, axis1=1, axis2=2)).sum(axis=1)
            maha = (z * z).sum(axis=1)
            term = 0.5 * (logdet + maha + mm * LOG_2PI)
            nll[act] += term
            GtT = np.swapaxes(Gt, 1, 2)
            x = x + (GtT @ z[:, :, None])[:, :, 0]
            Pc = Pc - GtT @ Gt
            Pc = 0.5 * (Pc + np.swapaxes(Pc, 1, 2))
            if st:
                sel = slice(None) if idx is None else idx
                if idx is None:
                    inn[k, act] = eps
                    yp_st[k, act] = yhat
                    S_st[k, act] = S
                else:
                    tmp = np.full((act.size, ny), np.nan)
                    tmp[:, idx] = eps
                    inn[k, act] = tmp
                    tmp = np.full((act.size, ny), np.nan)
                    tmp[:, idx] = yhat
                    yp_st[k, act] = tmp
                    tmpS = np.full((act.size, ny, ny), np.nan)
                    tmpS[:, sel[:, None], sel[None, :]] = S
                    S_st[k, act] = tmpS
                terms[k, act] = term
                nis[k, act] = maha
        if st:
            xf_st[k, act] = x
            with np.errstate(all="ignore"):
                yf_st[k, act] = model.h(x, u[k], tha)
            if Pf_st is not None:
                Pf_st[k, act] = Pc
        # a non-finite posterior is caught by the next Cholesky (finite check)

    nll[failed] = np.inf
    res = UKFResult(nll=nll, failed=failed, reasons=reasons, fail_step=fail_step, n_obs=n_obs,
                    t=t, outputs=list(model.outputs), states=list(model.states),
                    settings=dict(opts.to_dict(), n_regularised=int(n_reg)))
    if st:
        for arr in (inn, S_st, yp_st, yf_st, xf_st, nis):
            for p in np.flatnonzero(failed):
                arr[fail_step[p]:, p] = np.nan
        res.innovations, res.S, res.y_pred, res.y_filt = inn, S_st, yp_st, yf_st
        res.x_filt, res.P_filt, res.nll_terms, res.nis = xf_st, Pf_st, terms, nis
    return res


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


def discretisation_check(model, t, u, theta, x0=None, *, method: str = "ros2", substeps: int = 1,
                         reference_substeps: int = 32, reference_method: str | None = None) -> dict:
    """Error of the filter's discretisation along a noise-free trajectory, in
    units of the measurement-noise standard deviation.

    The trajectory from ``x0`` is propagated sample by sample with the
    filter's step (``method``, ``substeps``) and with a fine reference
    (``reference_method`` with ``reference_substeps``, default: RK4 if it is
    stable there, i.e. finite, else ROS2), both restarted from the reference
    state at every sample, as inside the filter. The one-step output error is
    compared with ``meas_std(theta)``.

    Parameters
    ----------
    model : Model
    t : array (N,)
    u : array (N, n_u)
    theta : array (n_theta,)
    x0 : array (n_x,), optional
    method, substeps : discretisation under test
    reference_substeps : int
    reference_method : {"rk4", "ros2"}, optional

    Returns
    -------
    dict
        ``one_step (n_y,)``: max over samples of |Δy|/σ for one step from
        the reference state; ``free_run (n_y,)``: max |Δy|/σ of the free
        run (accumulated error, an upper bound of what process noise has to
        absorb); ``reference``: the reference used.
    """
    t = np.asarray(t, float)
    u = np.asarray(u, float)
    th = np.asarray(theta, float)[None, :]
    x = (model.x0 if x0 is None else np.asarray(x0, float))[None, :]
    step = _transition(model, method, substeps)
    refm = reference_method
    ref = None
    with np.errstate(all="ignore"):
        for cand in ([refm] if refm else ["rk4", "ros2"]):
            rstep = _transition(model, cand, reference_substeps)
            xr = [x]
            for k in range(t.size - 1):
                xr.append(rstep(xr[-1], u[k], th, t[k + 1] - t[k]))
            xr = np.concatenate(xr)
            if np.isfinite(xr).all():
                ref = cand
                break
        if ref is None:
            return dict(one_step=np.full(model.n_y, np.inf), free_run=np.full(model.n_y, np.inf),
                        reference=None)
        sig = np.asarray(model.meas_std(th), float)[0]
        one = np.zeros(model.n_y)
        free = np.zeros(model.n_y)
        xf = x
        for k in range(t.size - 1):
            dt = t[k + 1] - t[k]
            xs = step(xr[k:k + 1], u[k], th, dt)
            xf = step(xf, u[k], th, dt)
            yr = model.h(xr[k + 1:k + 2], u[k + 1], th)[0]
            one = np.maximum(one, np.abs(model.h(xs, u[k + 1], th)[0] - yr) / sig)
            free = np.maximum(free, np.abs(model.h(xf, u[k + 1], th)[0] - yr) / sig)
    return dict(one_step=one, free_run=np.where(np.isfinite(free), free, np.inf), reference=ref)
