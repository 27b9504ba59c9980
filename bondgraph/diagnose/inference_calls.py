"""The loop's only door into :mod:`bondgraph.inference`.

Every call of the loop into the batched UKF (Wan & van der Merwe 2000),
its criterion, Fisher scoring, the L-BFGS-B polish, the difference Hessian
and the Cramér-Rao bounds goes through the small functions of this module,
which are also the only place where the UKF options of
:class:`~bondgraph.diagnose.settings.LoopSettings` (``settings.ukf``) are
handed to the inference layer (a :class:`~bondgraph.inference.options.UKFOptions`).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from bondgraph.diagnose.settings import LoopSettings
from bondgraph.inference.estimate import (
    Criterion,
    EstimandCriterion,
    cramer_rao,
    hessian_batched,
)
from bondgraph.inference.executor import Executor
from bondgraph.inference.estimand import NOISE_BOX, X0_TOKEN, Estimand, noise_plan
from bondgraph.inference.fisher import estimand_scoring
from bondgraph.inference.optimize import minimize_batched
from bondgraph.inference.output_error import output_error_fit
from bondgraph.inference.prior import record_prior
from bondgraph.inference.smoother import rts_smooth
from bondgraph.inference.ukf import UKFResult, default_P0, discretisation_check, ukf_nll


# re-exported: the token spread of a jointly estimated initial state, and the
# box of an estimated noise std (its start times / divided by NOISE_BOX)
__all__ = ["NOISE_BOX", "X0_TOKEN"]



def make_executor(workers: int, scheduler: str | None):
    """The executor the loop's candidate tasks run on
    (:class:`bondgraph.inference.executor.Executor`: in process with one
    worker and no scheduler, else on Dask workers)."""
    return Executor(workers, scheduler)

def run_ukf(model, t, u, y, thetas: np.ndarray, x0, P0, settings: LoopSettings, *,
            store: bool = False) -> UKFResult:
    """One batched UKF run with the loop's filter options.

    Parameters
    ----------
    model : Model
    t : array (N,)
        Sample times [s].
    u : array (N, n_u)
    y : array (N, n_y)
        Measurements (NaN where missing).
    thetas : array (P, n_theta)
        Full parameter vectors, one per set.
    x0 : array (n_x,)
        Prior state mean.
    P0 : array (n_x, n_x)
        Prior state covariance.
    settings : LoopSettings
        Supplies the UKF options (``settings.ukf``).
    store : bool
        Keep innovations, their covariances and the filtered states.

    Returns
    -------
    UKFResult
        :func:`bondgraph.inference.ukf.ukf_nll`'s result (NLL per set).
    """
    return ukf_nll(model, t, u, y, thetas, x0, P0, options=settings.ukf, store=store,
                   R=noise_cov(model, thetas, settings))


def held_sigma(model, settings: LoopSettings) -> np.ndarray:
    """The measurement-noise stds (n_y,) the loop holds
    (``settings.noise_levels`` by output name; NaN: ``meas_std(θ)``)."""
    lv = settings.noise_levels or {}
    return np.array([float(lv.get(o, np.nan)) for o in model.outputs])


def noise_cov(model, thetas, settings: LoopSettings) -> np.ndarray | None:
    """The filter's measurement-noise covariances R (P, n_y, n_y) with the
    held levels of ``settings.noise_levels`` (``diag(σ²)``, σ from
    ``meas_std(θ)`` for the others), or None when no level is held."""
    sig = held_sigma(model, settings)
    if not np.isfinite(sig).any():
        return None
    return _noise_cov_batch(model, np.atleast_2d(np.asarray(thetas, float)), sig)


def _noise_cov_batch(model, th: np.ndarray, sig: np.ndarray) -> np.ndarray:
    """``diag(σ²)`` (P, n_y, n_y): σ held where finite, ``meas_std(θ)`` elsewhere."""
    with np.errstate(all="ignore"):
        meas = np.asarray(model.meas_std(th), float)
    s = np.where(np.isfinite(sig)[None, :], sig[None, :], meas)
    R = np.zeros(s.shape + (s.shape[1],))
    idx = np.arange(s.shape[1])
    R[:, idx, idx] = s ** 2
    return R


def plan_noise(model, theta, params: Sequence[str], fixed: Sequence[str], declared):
    """The loop's noise policy under ``noise="auto"``
    (:func:`bondgraph.inference.estimand.noise_plan`): ``(noise-intensity
    parameters to add, outputs whose std is estimated, held σ (n_y,), notes)``."""
    return noise_plan(model, theta, params, fixed, declared)


def make_criterion(model, t, u, y, names: Sequence[str], base: np.ndarray, x0, P0,
                   settings: LoopSettings) -> Criterion:
    """Batched NLL of the parameters ``names`` (everything else at ``base``),
    ``crit(X (S, k)) -> (S,)``, evaluated ``settings.chunk`` sets per UKF run
    (:class:`bondgraph.inference.estimate.Criterion`)."""
    sig = held_sigma(model, settings)
    if not np.isfinite(sig).any():
        return Criterion(model, t, u, y, names, base, x0, P0, options=settings.ukf,
                         chunk=settings.chunk)
    est = Estimand(model, list(names), theta=base, x0=x0, sigma=sig)
    return EstimandCriterion(model, t, u, y, est, P0, options=settings.ukf, chunk=settings.chunk)


def fisher_fit(model, t, u, y, theta: np.ndarray, index: Sequence[int], lower, upper, x0, P0,
               settings: LoopSettings, iterations: int, log_scale, tolerance: float = 0.0,
               states: Sequence[str] = (), x0_scale=None, noises: Sequence[str] = (),
               information: bool = True):
    """Maximum-likelihood fit by Levenberg-damped Fisher scoring
    (:func:`bondgraph.inference.fisher.estimand_scoring`), the initial states
    ``states`` estimated jointly (:class:`~bondgraph.inference.estimand.Estimand`).

    Parameters
    ----------
    theta : array (n_theta,)
        Start; only the entries ``index`` (k) move, within [lower, upper].
    iterations : int
        Maximum scoring iterations.
    log_scale : array of bool (k,)
        Parameters moved in log θ (noise intensities).
    tolerance : float
        Stop when a full scoring step predicts less than this NLL decrease
        [nats] (0: only the relative NLL change, 1e-6 (1 + |NLL|), stops).
    states : sequence of str
        Initial states estimated with θ (their prior shrinks to a token
        spread; box: ± 100 of their prior std ``x0_scale`` (n_x,)).
    noises : sequence of str
        Outputs whose measurement-noise std is estimated with θ (log scale,
        from the held level or ``meas_std(θ)``); the other held levels of
        ``settings.noise_levels`` stay fixed.
    information : bool
        Compute the Fisher information at the result (False: ``F`` is None
        when the last iteration moved; one batched UKF run fewer).

    Returns
    -------
    theta : array (n_theta,)
    F : array (k + m + r, k + m + r) or None
        Fisher information at the result (parameters, states, noise stds).
    converged : bool
        Stopped by a convergence criterion rather than by ``iterations``.
    used : int
        Iterations used.
    x0 : array (n_x,)
        The initial state (the estimated entries moved).
    sigma : dict
        The estimated noise stds by output.

    Raises
    ------
    FloatingPointError, numpy.linalg.LinAlgError
        When the scoring fails numerically (the caller falls back to L-BFGS-B).
    """
    est = Estimand(model, [model.params[j] for j in index], states=list(states), theta=theta,
                   x0=x0, x0_scale=x0_scale, noises=list(noises),
                   sigma=held_sigma(model, settings))
    lo, hi = est.bounds(lower, upper)
    scale = np.concatenate([np.asarray(log_scale, bool), np.zeros(len(states), bool),
                            np.ones(len(noises), bool)])
    r = estimand_scoring(model, t, u, y, est, lo, hi, P0, options=settings.ukf,
                         max_iter=iterations, atol=tolerance, log_scale=scale,
                         information=information)
    sig = {o: float(r.estimand.sigma[model.output_index(o)]) for o in noises}
    return r.estimand.theta, r.F, r.converged, r.iterations, r.estimand.x0, sig


def lbfgsb_polish(crit: Criterion, x: np.ndarray, lower, upper, iterations: int) -> np.ndarray:
    """Bounded L-BFGS-B minimisation of ``crit`` from ``x`` (k,), batched
    central-difference gradients (:func:`bondgraph.inference.optimize.minimize_batched`);
    returns the minimiser (k,)."""
    x, _, _, _ = minimize_batched(crit, x, lower, upper, maxiter=iterations)
    return x


def hessian_cramer_rao(crit: Criterion, x: np.ndarray, h: np.ndarray,
                       names: Sequence[str]) -> dict:
    """Cramér-Rao bounds from the batched difference Hessian of ``crit`` at
    ``x`` (k,) with steps ``h`` (k,)
    (:func:`bondgraph.inference.estimate.hessian_batched`,
    :func:`bondgraph.inference.estimate.cramer_rao`): a dict with ``std``
    (k,) among others."""
    H, _, _ = hessian_batched(crit, x, h)
    return cramer_rao(H, names)


def prior_covariance(model, x0: np.ndarray, rel: float | None = None) -> np.ndarray:
    """The default UKF prior covariance (n_x, n_x): ``rel`` (default 5 %) of
    max(|x0|, 1) (:func:`bondgraph.inference.ukf.default_P0`)."""
    return default_P0(model, x0) if rel is None else default_P0(model, x0, float(rel))


def state_prior(model, t, u, y, theta: np.ndarray, x0, settings: LoopSettings,
                x0_std=None, unknown: Sequence[str] = ()) -> np.ndarray:
    """The prior covariance (n_x, n_x) by each state's own scale along the
    record (:func:`bondgraph.inference.prior.record_prior`, the loop's
    discretisation and hold; ``settings.p0_rel``, default 5 %, of it; the
    whole scale for the ``unknown`` states, whose initial value nothing
    gives)."""
    o = settings.ukf
    P0, _ = record_prior(model, t, u, y, theta, x0,
                         rel=0.05 if settings.p0_rel is None else float(settings.p0_rel),
                         x0_std=x0_std, method=o.method, substeps=max(o.substeps, 2),
                         hold=o.hold, unknown=unknown, backend=o.backend)
    return P0


def smoothed_initial_state(model, t, u, y, theta: np.ndarray, x0, P0,
                           settings: LoopSettings) -> np.ndarray:
    """The initial state given the whole record, x̂_0|N (n_x,), of the
    unscented RTS smoother (:func:`bondgraph.inference.smoother.rts_smooth`,
    Särkkä 2008) at ``theta`` with the loop's filter options and held noise
    levels (:func:`noise_cov`).

    Raises
    ------
    NumericalError
        If the filter or the backward pass fails.
    """
    R = noise_cov(model, np.asarray(theta, float)[None, :], settings)
    return rts_smooth(model, t, u, y, theta, x0, P0, options=settings.ukf,
                      R=None if R is None else R[0]).x[0]


def output_error(model, t, u, y, names: Sequence[str], theta: np.ndarray, x0,
                 settings: LoopSettings):
    """The output-error (free-run least-squares) fit of ``names`` from
    ``theta`` (:func:`bondgraph.inference.output_error.output_error_fit`,
    the loop's input hold): an :class:`~bondgraph.inference.output_error.OutputErrorResult`."""
    return output_error_fit(model, t, u, y, list(names), theta=theta, x0=x0,
                            hold=settings.ukf.hold)


def discretisation(model, t, u, theta: np.ndarray, x0, settings: LoopSettings,
                   substeps: int | None = None, free_run: bool = True) -> dict:
    """:func:`bondgraph.inference.ukf.discretisation_check` of the loop's
    filter options (``substeps`` overriding theirs): ``one_step`` and
    ``free_run`` (n_y,, NaN unless ``free_run``) in measurement-noise
    standard deviations."""
    o = settings.ukf
    return discretisation_check(model, t, u, theta, x0, method=o.method,
                                substeps=o.substeps if substeps is None else substeps,
                                hold=o.hold, free_run=free_run)
