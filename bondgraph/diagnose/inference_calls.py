"""The loop's only door into :mod:`bondgraph.inference`.

Every call of the loop into the batched UKF (Wan & van der Merwe 2000),
its criterion, Fisher scoring, the L-BFGS-B polish, the difference Hessian
and the Cramér-Rao bounds goes through the small functions of this module.
Each takes a :class:`~bondgraph.inference.problem.Problem`: the model bound
to the record, with its prior, held noise levels and filter options, so
that no option travels as a loose keyword.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from bondgraph.errors import NumericalError

from bondgraph.inference.discretise import choose_discretisation, no_process_noise
from bondgraph.inference.estimate import (
    Criterion,
    cramer_rao,
    hessian_batched,
    relative_direction,
)
from bondgraph.inference.executor import Executor
from bondgraph.inference.estimand import (NOISE_BOX, Estimand, moves_meas_std, noise_box,
                                          noise_parameters, noise_plan)
from bondgraph.inference.fisher import (
    FLAT_GAIN,
    estimand_scoring,
    flat_directions,
    scoring_step_gain,
    scoring_steps,
)
from bondgraph.inference.optimize import minimize_batched
from bondgraph.inference.options import Evaluation, ScoringOptions, most_substeps
from bondgraph.inference.output_error import OutputErrorOptions, output_error_fit
from bondgraph.inference.problem import NoiseSpec, Problem, make_problem
from bondgraph.inference.robust import (
    ROBUST_RATIO,
    andrews_bandwidth,
    long_run_variance,
    lr_scale,
    robust_std,
)
from bondgraph.inference.prior import PriorSpec, fixed_step_outputs
from bondgraph.inference.ukf import UKFResult
from bondgraph.inference.ukf_numba import threads as kernel_threads

# re-exported for the loop: the box of an estimated noise std (its start
# times / divided by NOISE_BOX), the problem's parts, the noise detector,
# the robust std and the long-run variance (bondgraph.inference.robust)
__all__ = ["FLAT_GAIN", "flat_directions", "NOISE_BOX", "NoiseSpec", "PriorSpec", "Problem",
           "no_process_noise", "relative_direction",
           "choose_discretisation", "kernel_threads", "make_problem", "moves_meas_std",
           "noise_box", "noise_parameters",
           "ROBUST_RATIO", "andrews_bandwidth", "long_run_variance", "lr_scale", "robust_std"]



#: substeps of the ``"fine"`` free run per substep of the filter
FINE_SUBSTEPS = 4


def fine_free_run(problem: Problem, u: np.ndarray, hold: str, theta: np.ndarray,
                  x0: np.ndarray) -> np.ndarray:
    """Outputs (N, n_y) of the noise-free run of ``problem``'s record from
    ``x0``: the filter's own method (:attr:`Problem.disc`) at
    :data:`FINE_SUBSTEPS` times its substeps, the inputs ``u`` (N, n_u)
    held as ``hold`` says (``"zoh"``, ``"linear"``); NaN from a non-finite
    state on.

    The free run of an error measure must be more accurate than the filter
    (an effect that only fits the filter's discretisation error must not
    lower it) and, on a record sampled from continuous signals, fixed-step:
    an adaptive solver restarts at every kink of the held input (BDF took
    1.2 million steps, 214 s, for the 48 796 samples of the Silverbox
    record). The discretisation check bounds the filter's own one-step
    error (0.1 σ per sample); four times finer divides it by 4⁴ = 256 (RK4)
    or 4² = 16 (ROS2), with the stability of the filter's method (ROS2 stays
    L-stable on a stiff model). Compiled where the prior's free run would
    (:func:`bondgraph.inference.prior.fixed_step_outputs`; RK4 is also the
    catalog metrics' free run), else the numpy steps
    (:func:`bondgraph.numerics.integrators.simulate_batch`).
    """
    model, d = problem.model, problem.disc
    sub = FINE_SUBSTEPS * most_substeps(d)
    return fixed_step_outputs(model, problem.t, u, theta, x0, d.method, sub, hold, d.backend)


def make_executor(workers: int, scheduler: str | None):
    """The executor the loop's candidate tasks run on
    (:class:`bondgraph.inference.executor.Executor`: in process with one
    worker and no scheduler, else on Dask workers)."""
    return Executor(workers, scheduler)

def run_ukf(problem: Problem, thetas: np.ndarray, *, store: bool = False) -> UKFResult:
    """One batched UKF run of ``problem`` (:meth:`Problem.nll`).

    Parameters
    ----------
    problem : Problem
        The model on the record, with its prior, held noise levels and
        filter options.
    thetas : array (P, n_theta)
        Full parameter vectors, one per set.
    store : bool
        Keep innovations, their covariances and the filtered states.

    Returns
    -------
    UKFResult
        :func:`bondgraph.inference.ukf.ukf_nll`'s result (NLL per set).
    """
    return problem.nll(thetas, store=store)


def plan_noise(model, theta, params: Sequence[str], fixed: Sequence[str], declared, y=None):
    """The loop's noise policy under ``noise="auto"``
    (:func:`bondgraph.inference.estimand.noise_plan`): ``(noise-intensity
    parameters to add, outputs whose std is estimated, held σ (n_y,), notes)``;
    ``y`` (N, n_y) the record's outputs (the start of a level no sensor declares)."""
    return noise_plan(model, theta, params, fixed, declared, y)


def make_criterion(problem: Problem, names: Sequence[str], base: np.ndarray,
                   chunk: int) -> Criterion:
    """Batched NLL of the parameters ``names`` (everything else at ``base``
    (n_theta,)), ``crit(X (S, k)) -> (S,)``, evaluated ``chunk`` sets per UKF
    run (:class:`bondgraph.inference.estimate.Criterion`), with the
    problem's prior and held noise levels."""
    return Criterion(problem, names, base, where=Evaluation(chunk=chunk))


def fisher_fit(problem: Problem, theta: np.ndarray, index: Sequence[int], box, iterations: int,
               *, log_scale, tolerance: float = 0.0, states: Sequence[str] = (),
               noises: Sequence[str] = (), information: bool = True, scores: bool = False,
               stop=None):
    """Maximum-likelihood fit by Levenberg-damped Fisher scoring
    (:func:`bondgraph.inference.fisher.estimand_scoring`), the initial states
    ``states`` estimated jointly (:class:`~bondgraph.inference.estimand.Estimand`).

    Parameters
    ----------
    problem : Problem
        The model on the record; its held noise levels stay fixed except
        for ``noises``.
    theta : array (n_theta,)
        Start; only the entries ``index`` (k) move.
    box : (lower (k,), upper (k,))
        The box of the moving parameters.
    iterations : int
        Maximum scoring iterations.
    log_scale : array of bool (k,)
        Parameters moved in log θ (noise intensities).
    tolerance : float
        Stop when a full scoring step predicts less than this NLL decrease
        [nats] (0: only the relative NLL change, 1e-6 (1 + |NLL|), stops).
    states : sequence of str
        Initial states estimated with θ (the filter holds them at a token
        spread; box: ± 100 of their whole prior std,
        :meth:`Problem.full_prior`).
    noises : sequence of str
        Outputs whose measurement-noise std is estimated with θ (log scale,
        from the held level or ``meas_std(θ)``).
    information : bool
        Compute the Fisher information at the result (False: ``F`` is None
        when the last iteration moved; one batched UKF run fewer).
    scores : bool
        Return the per-sample scores at the result too (the robust std).
    stop : callable, optional
        ``stop(estimand, nll)``: True ends it there (:class:`ScoringOptions`).

    Returns
    -------
    theta : array (n_theta,)
    F : array (k + m + r, k + m + r) or None
        Fisher information at the result (parameters, states, noise stds).
    converged : bool
        Stopped by a convergence criterion (not by ``iterations`` or ``stop``).
    used : int
        Iterations used.
    x0 : array (n_x,), sigma : dict
        The initial state (the estimated entries moved); the estimated noise
        stds by output.
    flat : tuple of str
        The quantities along which the likelihood is flat where the scoring
        stopped, converged in every other direction
        (:attr:`bondgraph.inference.fisher.Scoring.flat`; empty otherwise).
    nll : float
        The NLL at the result [nats] (the scoring's own last run there: a UKF
        run of ``problem`` at ``theta`` when no state or noise std is estimated).
    scores : array (N, k + m + r) or None
        Per-sample scores at the result (None without ``scores`` or ``F``).

    Raises
    ------
    FloatingPointError, numpy.linalg.LinAlgError
        When the scoring fails numerically (the caller falls back to L-BFGS-B).
    """
    model = problem.model
    P0 = problem.full_prior() if states else problem.P0
    est = _estimand(problem, theta, index, P0, states, noises)
    lo, hi = est.bounds(*box)
    scale = np.concatenate([np.asarray(log_scale, bool), np.zeros(len(states), bool),
                            np.ones(len(noises), bool)])
    t, u, y = problem.arrays
    r = estimand_scoring(model, t, u, y, est, lo, hi, P0, options=problem.ukf,
                         scoring=ScoringOptions(max_iter=iterations, atol=tolerance, stop=stop,
                                                log_scale=scale, information=information))
    sig = {o: float(r.estimand.sigma[model.output_index(o)]) for o in noises}
    return (r.estimand.theta, r.F, r.converged, r.iterations, r.estimand.x0, sig, r.flat,
            float(r.nll),
            r.derivatives.scores() if scores and r.derivatives is not None else None)


def fisher_steps(problem: Problem, thetas: Sequence[np.ndarray], index: Sequence[int], box
                 ) -> list[tuple[np.ndarray, float] | None]:
    """One Fisher-scoring iteration over the parameters ``index`` (k) from
    each start of ``thetas`` (each (n_theta,)), inside ``box`` (lower (k,),
    upper (k,)), linear scale, with ``problem``'s prior, held noise levels and
    filter, batched over the starts
    (:func:`bondgraph.inference.fisher.scoring_steps`: two UKF runs in all);
    per start ``(theta, nll)`` or None where the UKF fails at the start. The
    same results as ``fisher_fit(..., 1, information=False)`` per start."""
    starts = [_estimand(problem, np.asarray(th, float), index, problem.P0) for th in thetas]
    t, u, y = problem.arrays
    out = scoring_steps(problem.model, t, u, y, starts, box[0], box[1], problem.P0,
                        options=problem.ukf, log_scale=np.zeros(len(index), bool))
    return [None if o is None else (o[0].theta, float(o[1])) for o in out]


def predicted_step_gain(problem: Problem, theta: np.ndarray, index: Sequence[int], box) -> float:
    """The NLL decrease [nats] one full Fisher-scoring step over the
    parameters ``index`` (k) from ``theta`` (n_theta,) predicts, inside
    ``box`` (lower (k,), upper (k,)), with ``problem``'s prior, held noise
    levels and filter (:func:`bondgraph.inference.fisher.scoring_step_gain`;
    one batched UKF run of k + 1 sets).

    Raises
    ------
    FloatingPointError
        If the UKF fails at ``theta``.
    """
    est = _estimand(problem, theta, index, problem.P0)
    t, u, y = problem.arrays
    return scoring_step_gain(problem.model, t, u, y, est, box[0], box[1], problem.P0,
                             problem.ukf)


def _estimand(problem: Problem, theta: np.ndarray, index: Sequence[int], P0: np.ndarray,
              states: Sequence[str] = (), noises: Sequence[str] = ()) -> Estimand:
    """The :class:`~bondgraph.inference.estimand.Estimand` of the parameters
    ``index`` at ``theta`` (and the initial states ``states``, the noise stds
    of ``noises``) on ``problem``: its prior mean, the initial states scaled
    by the prior ``P0`` (n_x, n_x), its held noise levels and the centres
    of the estimated ones' boxes."""
    model = problem.model
    return Estimand(model, [model.params[j] for j in index], states=list(states), theta=theta,
                    x0=problem.x0, x0_scale=np.sqrt(np.maximum(np.diag(P0), 1e-300)),
                    noises=list(noises), sigma=problem.noise.sigma(model),
                    sigma_centre=problem.noise.centres(model))


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


def smoothed_initial_state(problem: Problem, theta: np.ndarray) -> np.ndarray:
    """The initial state given the whole record, x̂_0|N (n_x,), of the
    unscented RTS smoother at ``theta`` (:meth:`Problem.smoothed_initial_state`,
    Särkkä 2008).

    Raises
    ------
    NumericalError
        If the filter or the backward pass fails.
    """
    return problem.smoothed_initial_state(theta)


def output_error(problem: Problem, names: Sequence[str], theta: np.ndarray):
    """The output-error (free-run least-squares) fit of ``names`` from
    ``theta`` and the problem's prior mean
    (:func:`bondgraph.inference.output_error.output_error_fit`, the
    problem's input hold): an :class:`~bondgraph.inference.output_error.OutputErrorResult`.

    The free runs are the compiled fixed-step RK4 at :data:`FINE_SUBSTEPS`
    times the filter's substeps (as :func:`fine_free_run`), the Jacobian by
    forward differences; where they are not finite somewhere along the
    search (a stiff model), the fit runs again with scipy's LSODA and the
    forward sensitivities. On the EMPS record (4968 samples, a zero-order
    held input: one ``solve_ivp`` per sample) the fit took 14 s by LSODA."""
    t, u, y = problem.arrays
    hold = problem.disc.hold
    fine = OutputErrorOptions(hold=hold, substeps=FINE_SUBSTEPS * most_substeps(problem.disc))
    try:
        return output_error_fit(problem.model, t, u, y, list(names), theta=theta,
                                x0=problem.x0, options=fine)
    except NumericalError:
        return output_error_fit(problem.model, t, u, y, list(names), theta=theta,
                                x0=problem.x0, options=OutputErrorOptions(hold=hold))


def interval_errors(problem: Problem, theta: np.ndarray, substeps, sigma=None):
    """:meth:`Problem.interval_errors`: each interval's one-step
    discretisation error (k, N − 1) with each of ``substeps`` (k,), at the
    filter's sigma points and along the check's reference trajectory, in
    units of ``sigma`` (n_y,); None when the filter fails."""
    return problem.interval_errors(theta, substeps, sigma=sigma)


def step_errors(problem: Problem, theta: np.ndarray, discs, sigma=None,
                cache: dict | None = None, free_run: bool = False,
                directions=None) -> list[tuple[float, float]]:
    """:meth:`Problem.step_errors`: ``(one_step, bias)`` of each of
    ``discs``, the free-run bias (along ``directions``) NaN without
    ``free_run``."""
    return problem.step_errors(theta, discs, sigma=sigma, cache=cache, free_run=free_run,
                               directions=directions)


def one_step_errors(problem: Problem, theta: np.ndarray, substeps, sigma=None,
                    cache: dict | None = None) -> np.ndarray:
    """:meth:`Problem.one_step_errors`: the largest one-step discretisation
    error (k,) of the problem's method with each of ``substeps`` (k,), in
    units of ``sigma`` (n_y,; default the measurement-noise stds), against
    one fine reference (kept in ``cache``)."""
    return problem.one_step_errors(theta, substeps, sigma=sigma, cache=cache)
