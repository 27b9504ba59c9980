"""Innovation derivatives, the Fisher information of the UKF likelihood, and
Fisher scoring.

With the prediction-error decomposition NLL = ½ Σ_k [ln det S_k + ε_kᵀ S_k⁻¹ ε_k]
(+ const), the derivatives of the innovations ε_k and their covariances S_k
with respect to the parameters give (Åström 1980; Kristensen, Madsen &
Jørgensen 2004, eq. 15-16)::

    ∂NLL/∂θ_i = Σ_k [ ε_kᵀ S_k⁻¹ ∂ε_k/∂θ_i + ½ tr(S_k⁻¹ ∂S_k/∂θ_i)
                      − ½ ε_kᵀ S_k⁻¹ ∂S_k/∂θ_i S_k⁻¹ ε_k ]
    F_ij      = Σ_k [ (∂ε_k/∂θ_i)ᵀ S_k⁻¹ ∂ε_k/∂θ_j
                      + ½ tr(S_k⁻¹ ∂S_k/∂θ_i S_k⁻¹ ∂S_k/∂θ_j) ]

(F is the expected information). One batched UKF run over the parameter set
and its k nudged copies gives all derivatives by forward differences; a
Fisher-scoring (Levenberg-damped Gauss-Newton) step then needs one more
batched run for its line search. Because the UKF's cost per sample hardly
grows with the number of parameter sets on small models, this converges in a
few batched runs where a quasi-Newton method needs dozens.

References
----------
Åström, K. J. (1980). Maximum likelihood and prediction error methods.
Automatica 16(5), 551-574.
Kristensen, N. R., Madsen, H., Jørgensen, S. B. (2004). Parameter estimation
in stochastic grey-box models. Automatica 40(2), 225-237.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from bondgraph.inference.estimand import Estimand
from bondgraph.inference.robust import step_scores
from bondgraph.inference.options import ScoringOptions, UKFOptions, scoring_options
from bondgraph.inference.ukf import ukf_nll


@dataclass
class Derivatives:
    """Innovations, their covariances and their parameter derivatives.

    Attributes
    ----------
    nll : float
    eps : ndarray (N, m)        innovations (0 where not measured)
    S : ndarray (N, m, m)       innovation covariances (identity where not measured)
    dE : ndarray (k, N, m)      ∂ε/∂θ
    dS : ndarray (k, N, m, m)   ∂S/∂θ
    grad : ndarray (k,)         ∂NLL/∂θ
    F : ndarray (k, k)          expected Fisher information
    """

    nll: float
    eps: np.ndarray
    S: np.ndarray
    dE: np.ndarray
    dS: np.ndarray
    grad: np.ndarray
    F: np.ndarray

    def scores(self) -> np.ndarray:
        """Per-sample scores (N, k), whose sum is ``grad``
        (:func:`bondgraph.inference.robust.step_scores`)."""
        return step_scores(self.eps, self.S, self.dE, self.dS)


def _clean(eps, S):
    """Zero the unmeasured entries (NaN) so they drop out of the sums."""
    miss = ~np.isfinite(eps)
    e = np.where(miss, 0.0, eps)
    S = S.copy()
    if miss.any():
        m = S.shape[-1]
        eye = np.eye(m)
        mm = miss[:, :, None] | miss[:, None, :]
        S = np.where(mm, eye, S)
    S = np.where(np.isfinite(S), S, np.eye(S.shape[-1]))
    return e, S, miss


def derivatives(model, t, u, y, theta, index, steps, x0, P0,
                options: UKFOptions | None = None) -> Derivatives:
    """NLL, gradient and Fisher information at ``theta`` for the parameters
    ``index`` (forward differences with ``steps``), from one batched UKF run.

    Parameters
    ----------
    model : Model
    t, u, y : arrays (N,), (N, n_u), (N, n_y)
    theta : array (n_theta,)
    index : sequence of int (k,)
        Parameters differentiated.
    steps : array (k,)
        Difference steps (signed).
    x0, P0 : UKF prior
    options : UKFOptions, optional
        Filter options (:func:`bondgraph.inference.ukf.ukf_nll`).

    Returns
    -------
    Derivatives

    Raises
    ------
    FloatingPointError
        If the UKF fails at ``theta`` itself.
    """
    est = Estimand(model, [model.params[j] for j in index], theta=theta,
                   x0=model.x0 if x0 is None else x0)
    return estimand_derivatives(model, t, u, y, est, steps, P0, options)


def estimand_derivatives(model, t, u, y, est: Estimand, steps, P0,
                         options: UKFOptions | None = None) -> Derivatives:
    """NLL, gradient and Fisher information of the quantities of ``est``
    (parameters, initial states, noise stds; :class:`~bondgraph.inference.estimand.Estimand`)
    at their current values, by forward differences with ``steps`` (k,),
    from one batched UKF run of k + 1 sets.

    Raises
    ------
    FloatingPointError
        If the UKF fails at the expansion point (its reason named).
    """
    th, x0s, R = est.expand(_nudged(est.value(), steps))
    r = ukf_nll(model, t, u, y, th, x0s, est.prior_cov(P0), options=options, R=R, store=True)
    e0, S0, dE, dS = innovation_differences(r, steps)
    return _information(float(r.nll[0]), e0, S0, dE, dS)


def _nudged(z: np.ndarray, steps) -> np.ndarray:
    """The point ``z`` (k,) and its k copies nudged by ``steps`` (k,) along
    each quantity in turn: (k + 1, k)."""
    Z = np.repeat(np.asarray(z, float)[None, :], len(z) + 1, axis=0)
    Z[1:] += np.diag(np.asarray(steps, float))
    return Z


def innovation_differences(r, steps) -> tuple:
    """Innovations, their covariances and their forward differences from one
    stored batched UKF run (``store=True``) of a point and its k nudged
    copies (set 0 the point, set i + 1 nudged by ``steps[i]`` along i).

    Returns
    -------
    (eps (N, m), S (N, m, m), dE (k, N, m), dS (k, N, m, m))
        Unmeasured entries zeroed (:func:`_clean`); a nudge whose run failed
        gives zero differences (no information along it).

    Raises
    ------
    FloatingPointError
        If the UKF failed at the point itself (its reason named).
    """
    if not np.isfinite(r.nll[0]):
        raise FloatingPointError(f"UKF failed at the expansion point: {r.reasons[0]}")
    e0, S0, miss = _clean(r.innovations[:, 0, :], r.S[:, 0])
    N, m = e0.shape
    k = len(steps)
    dE = np.zeros((k, N, m))
    dS = np.zeros((k, N, m, m))
    for i, h in enumerate(steps):
        if not np.isfinite(r.nll[i + 1]):
            continue  # a nudge that fails: no information along it
        ei, Si, _ = _clean(r.innovations[:, i + 1, :], r.S[:, i + 1])
        dE[i] = (ei - e0) / h
        dS[i] = (Si - S0) / h
    dE[:, miss] = 0.0
    return e0, S0, dE, dS


def _information(nll, e0, S0, dE, dS) -> Derivatives:
    """Gradient and expected information from the innovation derivatives
    (module docstring; Kristensen et al. 2004 eq. 15-16)."""
    L = np.linalg.cholesky(S0)
    Sinv = np.linalg.inv(S0)
    a = np.einsum("kij,kj->ki", Sinv, e0)                      # S⁻¹ ε
    SdS = np.einsum("kab,ikbc->ikac", Sinv, dS)                 # S⁻¹ ∂S_i
    grad = (np.einsum("ki,jki->j", a, dE)
            + 0.5 * np.einsum("ikaa->i", SdS)
            - 0.5 * np.einsum("ka,ikab,kb->i", a, dS, a))
    W = np.linalg.solve(L, dE.transpose(1, 2, 0))              # L⁻¹ ∂ε, (N, m, k)
    F = np.einsum("kai,kaj->ij", W, W) + 0.5 * np.einsum("ikab,jkba->ij", SdS, SdS)
    return Derivatives(nll, e0, S0, dE, dS, grad, F)


@dataclass
class Scoring:
    """What :func:`estimand_scoring` returns.

    Attributes
    ----------
    estimand : Estimand
        At the result.
    nll : float
    F : ndarray (k, k) or None
        Fisher information at the result (Cramér-Rao: inv(F)); None when
        not computed (``ScoringOptions.information`` False).
    runs : int
        Batched UKF runs used.
    iterations : int
    converged : bool
        The last accepted step improved the NLL by less than the tolerance,
        or the predicted decrease of a full scoring step at the result,
        ½ gᵀ F⁻¹ g, is below it, in every direction or in every direction
        the record identifies (``flat``); False when ``max_iter`` ran out
        first.
    flat : tuple of str
        The quantities (:attr:`Estimand.names`) along which the likelihood
        is flat where the scoring stopped (:func:`flat_directions`): the
        scoring converged in every other direction and still gained less
        than :data:`FLAT_GAIN` nats per iteration along these, which the
        record does not identify; empty when it converged in all of them.
    derivatives : Derivatives or None
        The derivatives at the result (None with ``F``); their per-sample
        scores (:meth:`Derivatives.scores`) give the robust std
        (:func:`bondgraph.inference.robust.robust_std`).
    """

    estimand: Estimand
    nll: float
    F: np.ndarray
    runs: int
    iterations: int
    converged: bool
    flat: tuple = ()
    derivatives: Derivatives | None = None


#: the scoring of :func:`fisher_scoring` by default: only the relative NLL
#: change stops (no test on the predicted decrease)
FISHER_SCORING = ScoringOptions(atol=0.0)
#: relative eigenvalue of the information in unit-diagonal coordinates
#: below which a direction is not identified (collinearity index
#: γ = 1/√λ > 100; Brun, Reichert & Künsch 2001 read γ > 10-20 as a
#: near-linear dependence)
FLAT_EIGENVALUE = 1e-4
#: NLL decrease [nats] of the last accepted iteration below which a scoring
#: converged in its identified directions stops on a flat ridge
FLAT_GAIN = 0.1
#: loading (norm of a quantity's row of the flat eigenvectors, unit-diagonal
#: coordinates) from which a quantity is named as moving along the ridge
FLAT_LOADING = 0.2


def fisher_scoring(model, t, u, y, theta, index, lower, upper, x0, P0, *,
                   options: UKFOptions | None = None, scoring: ScoringOptions | None = None):
    """Maximise the UKF likelihood over the parameters ``index`` by
    Levenberg-damped Fisher scoring within the box [lower, upper]
    (:func:`estimand_scoring` for parameters only).

    Parameters
    ----------
    model : Model
    t, u, y : arrays
    theta : array (n_theta,)
        Start (all parameters; the others stay fixed).
    index : sequence of int (k,)
    lower, upper : arrays (k,)
    x0, P0 : UKF prior
    options : UKFOptions, optional
        Filter options (:func:`bondgraph.inference.ukf.ukf_nll`).
    scoring : ScoringOptions, optional
        Iteration controls (:class:`~bondgraph.inference.options.ScoringOptions`:
        ``max_iter``, ``rtol``, ``atol``, ``log_scale``, ``information``,
        ``log``). Default :data:`FISHER_SCORING`: 12 iterations, stop when
        the NLL improves by less than 1e-6 (1 + |NLL|) (``atol`` 0); the
        log scale of positive boxes spanning more than two decades.

    Returns
    -------
    theta : array (n_theta,)
    nll : float
    F : array (k, k)
        Fisher information at the result (Cramér-Rao: inv(F); None only
        with ``scoring.information`` False).
    runs : int
        Batched UKF runs used.
    """
    est = Estimand(model, [model.params[j] for j in index], theta=theta,
                   x0=model.x0 if x0 is None else x0)
    r = estimand_scoring(model, t, u, y, est, lower, upper, P0, options=options,
                         scoring=FISHER_SCORING if scoring is None else scoring)
    return r.estimand.theta, r.nll, r.F, r.runs


def estimand_scoring(model, t, u, y, est: Estimand, lower, upper, P0, *,
                     options: UKFOptions | None = None,
                     scoring: ScoringOptions | None = None) -> Scoring:
    """Maximise the UKF likelihood over the quantities of ``est``
    (parameters, initial states, noise stds) by Levenberg-damped Fisher
    scoring within the box [lower, upper] (k,).

    Each iteration: one batched UKF run for the derivatives (k + 1 sets) and
    a line search over damped steps (6 sets, plus decade moves of the
    log-scale quantities), the full and the doubled step first and the rest
    only when these two gain less than half, or more than four times, the
    decrease the quadratic model predicts (:func:`_line_search`). Stops when
    a step improves the NLL by less
    than ``rtol (1 + |NLL|)``, when the predicted decrease of a full step is
    below ``atol`` nats (converged), or after ``max_iter`` iterations
    (``scoring``: :class:`~bondgraph.inference.options.ScoringOptions`,
    default its defaults). With ``scoring.information`` False the
    derivatives are not computed again at a result the last iteration moved
    to (a caller that needs neither F nor the NLL there saves that run):
    ``F`` is then None and ``nll`` the line search's NLL at the result.

    Returns
    -------
    Scoring

    Raises
    ------
    FloatingPointError
        If the UKF fails at the start.
    OptionError
        ``scoring`` is not a :class:`~bondgraph.inference.options.ScoringOptions`.
    """
    sc = scoring_options(scoring)

    def derive(e: Estimand, steps) -> Derivatives:
        return estimand_derivatives(model, t, u, y, e, steps, P0, options)

    def line(cand) -> np.ndarray:
        th, x0s, R = est.expand(cand)
        return ukf_nll(model, t, u, y, th, x0s, est.prior_cov(P0), options=options, R=R).nll

    return _scoring_loop(est, derive, line, lower, upper, sc)


def joint_scoring(records: Sequence[tuple], lower, upper, *,
                  scoring: ScoringOptions | None = None) -> Scoring:
    """:func:`estimand_scoring` on several records of one model: the NLL,
    gradient and Fisher information summed over the records (independent
    experiments), each record with its own initial state and prior.

    Parameters
    ----------
    records : sequence of (model, t, u, y, est, P0, options)
        One per record: its arrays, its :class:`Estimand` (the same names
        and values but for its own initial state), its prior covariance and
        filter options.
    lower, upper : arrays (k,)
        The shared box.
    scoring : ScoringOptions, optional

    Returns
    -------
    Scoring
        ``estimand`` the first record's at the result (the values are
        shared); ``derivatives`` None.

    Raises
    ------
    FloatingPointError
        If the UKF fails at the start on a record.
    """
    sc = scoring_options(scoring)
    recs = list(records)

    def derive(e: Estimand, steps) -> Derivatives:
        z = e.value()
        parts = [estimand_derivatives(m, t, u, y, own.at(z), steps, P0, opts)
                 for m, t, u, y, own, P0, opts in recs]
        first = parts[0]
        return Derivatives(float(sum(d.nll for d in parts)), first.eps, first.S, first.dE,
                           first.dS, np.sum([d.grad for d in parts], axis=0),
                           np.sum([d.F for d in parts], axis=0))

    def line(cand) -> np.ndarray:
        out = np.zeros(len(cand))
        for m, t, u, y, own, P0, opts in recs:
            th, x0s, R = own.expand(cand)
            out += ukf_nll(m, t, u, y, th, x0s, own.prior_cov(P0), options=opts, R=R).nll
        return out

    r = _scoring_loop(recs[0][4], derive, line, lower, upper, sc)
    return replace(r, derivatives=None)


def _scoring_loop(est: Estimand, derive, line, lower, upper, sc: ScoringOptions) -> Scoring:
    """The iterations of :func:`estimand_scoring` on the criterion of
    ``derive(est, steps) -> Derivatives`` and ``line(cand (c, k)) -> NLL
    (c,)``."""
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    z = np.clip(est.value(), lo, hi)
    log_scale = sc.log_scale
    if log_scale is None:
        log_scale = (lo > 0) & (hi > 100 * lo)
    L = np.asarray(log_scale, dtype=bool)
    width = np.maximum(hi - lo, 1e-300)
    start = z.copy()
    runs, lam, converged, it, nll, gain, flat = 0, 1e-3, False, 0, None, np.inf, ()
    # the derivatives at z are kept: after a refused step, and at the end
    # when z did not move, they are not computed again (the same UKF run)
    at, D = None, None
    for it in range(1, sc.max_iter + 1):
        if at is None or not np.array_equal(at, z):
            D = derive(est.at(z), _steps(z, hi, width, start))
            at, runs = z.copy(), runs + 1
        converged, flat, alphas, cand = _proposal(D, z, L, lam, lo, hi, sc.atol, gain)
        if converged:
            break
        nll_c, n_runs = _line_search(line, D, z, L, alphas, cand, sc.rtol)
        runs += n_runs
        best = int(np.argmin(np.where(np.isfinite(nll_c), nll_c, np.inf)))
        f_new = float(nll_c[best])
        if sc.log:
            how = f"step x{alphas[best]:g}" if np.isfinite(alphas[best]) else "scale move"
            sc.log(f"    scoring {it}: NLL {D.nll:.3f} -> {f_new:.3f} ({how})")
        if not np.isfinite(f_new) or f_new >= D.nll:
            lam *= 10.0
            if lam > 1e6:
                converged = True    # no step improves: a stationary point within the box
                break
            continue
        lam, predicted = _damping(lam, D, z, L, alphas, cand, nll_c, best)
        # the ridge test (:func:`_converged`) reads only a predicted step's gain
        z, nll, gain = cand[best], f_new, (D.nll - f_new if predicted else np.inf)
        if predicted and D.nll - f_new < sc.rtol * (1.0 + abs(f_new)):
            converged = True
            break
        if sc.stop is not None and sc.stop(est.at(z), nll):
            break                       # not converged: the caller knows where it heads
    # information at the final point
    est = est.at(z)
    flat = tuple(est.names[i] for i in flat)
    if at is None or not np.array_equal(at, z):
        if not sc.information and at is not None:
            return Scoring(est, nll, None, runs, it, converged, flat)
        D = derive(est, _steps(z, hi, width, start))
        runs += 1
    return Scoring(est, D.nll, D.F, runs, it, converged, flat, D)


def scoring_steps(model, t, u, y, starts: list[Estimand], lower, upper, P0, *,
                  options: UKFOptions | None = None, log_scale=None) -> list:
    """One Levenberg-damped Fisher-scoring iteration from each of several
    starts, batched: what :func:`estimand_scoring` with one iteration
    (``ScoringOptions(max_iter=1, atol=0, information=False)``) gives each
    start, from one UKF run for every start's derivatives (S (k + 1) sets)
    and one for every line search, instead of two runs per start (the
    filter's cost per set falls with the batch).

    Parameters
    ----------
    model : Model
    t, u, y : arrays (N,), (N, n_u), (N, n_y)
    starts : list of Estimand (S)
        The starts: the same quantities (names, states, noises) of ``model``,
        each with its own values of everything else.
    lower, upper : arrays (k,)
        The box of the quantities, shared by the starts.
    P0 : array (n_x, n_x) or None
        The filter's prior covariance.
    options : UKFOptions, optional
    log_scale : array of bool (k,), optional
        Quantities moved in log scale (default: positive boxes spanning more
        than two decades, as :func:`estimand_scoring`).

    Returns
    -------
    list (S) of (Estimand, float) or None
        Per start the estimand at the result and its NLL [nats] (the start
        itself, clipped to the box, and its NLL when no step improves); None
        where the UKF fails at the start or the step cannot be solved.
    """
    if not starts:
        return []
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    L = ((lo > 0) & (hi > 100 * lo)) if log_scale is None else np.asarray(log_scale, bool)
    width = np.maximum(hi - lo, 1e-300)
    k = starts[0].k
    ests = [e.at(np.clip(e.value(), lo, hi)) for e in starts]
    steps = [_steps(e.value(), hi, width) for e in ests]
    nudged = [_nudged(e.value(), h) for e, h in zip(ests, steps)]
    r = _batched_runs(model, t, u, y, ests, nudged, P0, options, store=True)
    out: list = [None] * len(ests)
    lines: dict = {}
    for s, (e, h) in enumerate(zip(ests, steps)):
        z = e.value()
        try:
            D = _information(*_block(r, s * (k + 1), k + 1, h))
            converged, _, alphas, cand = _proposal(D, z, L, 1e-3, lo, hi, 0.0, np.inf)
            if converged:
                out[s] = (e, D.nll)
                continue
        except (FloatingPointError, np.linalg.LinAlgError):
            continue
        out[s] = (e, D.nll)
        lines[s] = (cand, alphas, D, z)
    if lines:
        order = list(lines)
        r = _batched_runs(model, t, u, y, [ests[s] for s in order],
                          [lines[s][0] for s in order], P0, options)
        a = 0
        for s in order:
            cand, alphas, D, z = lines[s]
            nll = np.array(r.nll[a:a + len(cand)], float)
            a += len(cand)
            # the point the iteration's staged search would take
            # (:func:`_line_search`): every point is run here, in one batch
            if _first_points_suffice(nll, D, z, L, alphas, cand, ScoringOptions().rtol):
                nll[~np.isin(alphas, FIRST_ALPHAS)] = np.inf
            best = int(np.argmin(np.where(np.isfinite(nll), nll, np.inf)))
            if np.isfinite(nll[best]) and nll[best] < out[s][1]:
                out[s] = (ests[s].at(cand[best]), float(nll[best]))
    return out


def _batched_runs(model, t, u, y, ests: list[Estimand], values: list, P0, options,
                  store: bool = False):
    """One UKF run of every estimand's values (``values[s]`` (c_s, k) for
    ``ests[s]``), the sets stacked in that order."""
    parts = [e.expand(Z) for e, Z in zip(ests, values)]
    th = np.vstack([p[0] for p in parts])
    x0s = np.vstack([p[1] for p in parts])
    R = None if parts[0][2] is None else np.concatenate([p[2] for p in parts])
    return ukf_nll(model, t, u, y, th, x0s, ests[0].prior_cov(P0), options=options, R=R,
                   store=store)


def _block(r, a: int, n: int, steps) -> tuple:
    """(nll, eps, S, dE, dS) of the point at set ``a`` of a stored run ``r``
    and its nudges (sets a + 1 ... a + n - 1, :func:`innovation_differences`)."""
    view = _RunView(r.nll[a:a + n], r.reasons[a:a + n], r.innovations[:, a:a + n],
                    r.S[:, a:a + n])
    return (float(view.nll[0]),) + innovation_differences(view, steps)


@dataclass
class _RunView:
    """The part of a stored UKF run that :func:`innovation_differences` reads."""

    nll: np.ndarray
    reasons: list
    innovations: np.ndarray
    S: np.ndarray


def _proposal(D: Derivatives, z, L, lam: float, lo, hi, atol: float, gain: float) -> tuple:
    """One scoring iteration's proposal at ``z`` (k,) from its derivatives
    ``D``: ``(converged, flat, alphas, cand)``, the convergence test
    (:func:`_converged`, the parameters held on their bounds left out,
    :func:`pinned`) and, unless converged, the line-search points of the
    Levenberg-damped step (:func:`_scoring_step`, :func:`_candidates`;
    None, None when converged)."""
    free = ~pinned(D.grad, z, lo, hi)
    converged, flat = _converged(D, z, L, free, atol, gain)
    if converged:
        return True, flat, None, None
    alphas, cand = _candidates(z, _scoring_step(D, z, L, lam, free), L, lo, hi)
    return False, flat, alphas, cand


def scoring_step_gain(model, t, u, y, est: Estimand, lower, upper, P0,
                      options: UKFOptions | None = None) -> float:
    """The NLL decrease [nats] that one full Fisher-scoring step from the
    current value of ``est`` predicts, ½ gᵀ F⁻¹ g over the quantities not
    held on a bound of the box [lower, upper] (k,) (:func:`pinned`), from
    one batched UKF run of k + 1 sets (forward differences,
    :func:`estimand_derivatives`). The quadratic model's gain: where the
    likelihood curves away from it (a start far from the optimum) the real
    gain can be several times larger or smaller.

    Raises
    ------
    FloatingPointError
        If the UKF fails at the current value.
    """
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    z = np.clip(est.value(), lo, hi)
    D = estimand_derivatives(model, t, u, y, est.at(z), _steps(z, hi, np.maximum(hi - lo, 1e-300)),
                             P0, options)
    return _predicted_decrease(D, z, np.zeros(z.size, bool), ~pinned(D.grad, z, lo, hi))


def pinned(grad: np.ndarray, x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The parameters (k,) held on a bound of their box: at the lower bound
    with the NLL's gradient ``grad`` (k,) pointing inward-up (the NLL falls
    outwards, ∂NLL/∂θ > 0), or at the upper bound with ∂NLL/∂θ < 0 (the
    active set of a projected Newton method; Bertsekas 1982). A scoring
    step moves the other parameters alone: with them in it, the clipped
    step of the pinned one bends every other step through F⁻¹, and its
    gradient never vanishes, so the predicted decrease never falls below
    the tolerance (a sensor noise level on the bottom of its box kept a
    Silverbox refit going for 80 iterations).

    References
    ----------
    Bertsekas, D. P. (1982). Projected Newton methods for optimization
    problems with simple constraints. SIAM J. Control Optim. 20(2), 221-246.
    """
    x, lo, hi = (np.asarray(a, float) for a in (x, lo, hi))
    # within 1e-12 of the box's width, or of the value where the box is far
    # wider (an effect's nominal [0, 1e15] pinned a stiffness of 3.84 on 0)
    tol = 1e-12 * np.maximum(np.minimum(np.abs(hi - lo), np.maximum(np.abs(x), 1.0)), 1e-300)
    return ((x <= lo + tol) & (grad > 0)) | ((x >= hi - tol) & (grad < 0))


def _converged(D: Derivatives, x, L, free, atol: float, gain: float) -> tuple[bool, tuple]:
    """Whether the scoring at ``x`` has converged, and the indices of the
    quantities along the flat directions it stopped on (empty unless it
    stopped on a ridge): the predicted decrease of a full step is below
    ``atol`` (:func:`_predicted_decrease`), or, once the last accepted step
    gained less than :data:`FLAT_GAIN` nats, it is below ``atol`` in the
    directions the information identifies (:func:`flat_directions`)."""
    if _predicted_decrease(D, x, L, free) < atol:
        return True, ()
    if not gain < FLAT_GAIN or atol <= 0:
        return False, ()
    jac = np.where(L, x, 1.0)
    F = D.F * np.outer(jac, jac)
    flat, identified = flat_directions(F, D.grad * jac, free)
    return (True, flat) if flat and identified < atol else (False, ())


def relative_changes(v: np.ndarray, floor: float) -> tuple[np.ndarray, list[int]]:
    """A direction ``v`` (k,) scaled so that its largest component is +1,
    and the indices whose scaled component is at least ``floor`` in size,
    largest first (equal ones to two decimals in index order: the members
    of a scale symmetry keep the parameters' order). Shared by the
    messages that name an unidentified direction
    (:func:`bondgraph.inference.estimate.relative_direction`,
    :func:`bondgraph.sensitivity.identifiability.ridge`)."""
    r = np.asarray(v, float)
    r = r / r[int(np.argmax(np.abs(r)))]
    order = sorted(range(r.size), key=lambda i: (-round(abs(float(r[i])), 2), i))
    return r, [i for i in order if abs(r[i]) >= floor]


def flat_directions(F: np.ndarray, grad: np.ndarray, free=None) -> tuple[tuple, float]:
    """The quantities along which an information F (k, k) is flat, and the
    NLL decrease ½ gᵀ F⁺ g a full scoring step predicts in the other
    directions [nats] (gradient ``grad`` (k,); ``free`` (k,) bool, default
    all: the quantities that may move).

    F is brought to a unit diagonal over the free quantities (Jacobi
    scaling, :func:`jacobi_solve`: the cut does not depend on their units);
    its eigenvectors whose eigenvalue is below :data:`FLAT_EIGENVALUE`
    (collinearity index γ > 100; Brun, Reichert & Künsch 2001) are the
    combinations the record does not identify. A quantity is named when
    its loading on them (the norm of its row of those eigenvectors) is at
    least :data:`FLAT_LOADING`, the largest first. On a user's graph of a
    belt drive, with one speed sensor whose gain is estimated and the
    pulley's spring on the bottom of its box, the motor damping, belt
    stiffness and pulley inertia move together with the armature
    inductance and torque constant: eigenvalues 5e-7 and 4e-6 beside 0.1
    and more, and a
    scoring that gained 0.01-0.05 nats per iteration along them for 120
    iterations, converged in every other direction after 20.

    Returns
    -------
    flat : tuple of int
        Indices into the k quantities, empty if F has no flat direction.
    identified : float
        The predicted decrease outside the flat directions [nats].

    References
    ----------
    Brun, R., Reichert, P., Künsch, H. R. (2001). Practical identifiability
    analysis of large environmental simulation models. Water Resources
    Research 37(4), 1015-1030.
    """
    free = np.ones(np.shape(grad), bool) if free is None else np.asarray(free, bool)
    idx = np.flatnonzero(free)
    if idx.size == 0:
        return (), 0.0
    Ff = F[np.ix_(idx, idx)]
    d = _jacobi(Ff)
    lam, V = np.linalg.eigh(Ff / np.outer(d, d))
    c = V.T @ (grad[idx] / d)
    low = lam < FLAT_EIGENVALUE * max(float(lam[-1]), 1e-300)
    identified = 0.5 * float(np.sum(c[~low] ** 2 / lam[~low]))
    load = np.linalg.norm(V[:, low], axis=1)
    order = np.argsort(-load)
    return tuple(int(idx[i]) for i in order if load[i] >= FLAT_LOADING), identified


def _predicted_decrease(D: Derivatives, x, L, free=None) -> float:
    """½ gᵀ F⁻¹ g in the scoring coordinates (log θ for ``L``) over the
    ``free`` parameters (default all; the others held, :func:`pinned`):
    the NLL decrease a full, undamped scoring step predicts (solved in the
    coordinates that give F a unit diagonal, :func:`jacobi_solve`)."""
    free = np.ones(np.shape(x), bool) if free is None else np.asarray(free, bool)
    if not free.any():
        return 0.0
    jac = np.where(L, x, 1.0)[free]
    g = D.grad[free] * jac
    F = D.F[np.ix_(free, free)] * np.outer(jac, jac)
    try:
        sol = jacobi_solve(F, g, lstsq=True)
    except np.linalg.LinAlgError:
        return float("inf")
    v = 0.5 * float(g @ sol)
    return v if np.isfinite(v) else float("inf")


def jacobi_solve(F: np.ndarray, g: np.ndarray, lstsq: bool = False,
                 rcond: float = 1e-12) -> np.ndarray:
    """F⁻¹ g for a symmetric information matrix F (k, k) and g (k,), solved
    as D⁻¹ (D⁻¹ F D⁻¹)⁻¹ D⁻¹ g with D = sqrt(diag F) (Jacobi scaling, which
    makes the result independent of the parameters' units). Unscaled, the
    information of a coefficient of 1e-9 next to a resistance of 1e5 spans
    30 decades and a least-squares cut at ``rcond`` drops every direction
    but the largest (a confirmation "converged" where the score test
    predicted a gain of 66 nats). ``lstsq``: least squares with the relative
    cut ``rcond`` (singular F) instead of an LU solve.

    Raises
    ------
    numpy.linalg.LinAlgError
        If F is singular (``lstsq`` False) or the SVD does not converge.
    """
    d = _jacobi(F)
    Fs = F / np.outer(d, d)
    if lstsq:
        return np.linalg.lstsq(Fs, g / d, rcond=rcond)[0] / d
    return np.linalg.solve(Fs, g / d) / d


def jacobi_pinv(F: np.ndarray) -> np.ndarray:
    """Pseudo-inverse (k, k) of a symmetric information matrix F (k, k) in
    the coordinates that give it a unit diagonal (:func:`jacobi_solve`): the
    cut of small singular values then does not depend on the quantities'
    units (initial states in metres beside noise levels in millivolts)."""
    d = _jacobi(F)
    dd = np.outer(d, d)
    return np.linalg.pinv(F / dd) / dd


def _jacobi(F: np.ndarray) -> np.ndarray:
    """sqrt(|diag F|) (k,), 1 where it is zero or not finite."""
    d = np.sqrt(np.abs(np.diag(F)))
    return np.where((d > 0) & np.isfinite(d), d, 1.0)


def typical_magnitude(start, width) -> np.ndarray:
    """The magnitude below which a finite-difference step stops shrinking
    with the value (Dennis & Schnabel 1983, §5.4's typical θ): 1e-3 of the
    box's width, but at most 1000 times the value at the start (1 at a
    start of 0). A box far wider than the value carries no scale: an
    effect's nominal box [0, 1e15] gave a stiffness 3.84 steps of 1e6, its
    derivatives garbage and the parameter never moved.

    Parameters
    ----------
    start, width : arrays (k,)
        The values at the start and the boxes' widths (same units).

    Returns
    -------
    array (k,)

    References
    ----------
    Dennis, J. E., Schnabel, R. B. (1983). Numerical Methods for
    Unconstrained Optimization and Nonlinear Equations. Prentice-Hall.
    """
    z0 = np.abs(np.asarray(start, float))
    return np.minimum(1e-3 * np.asarray(width, float), np.where(z0 > 0, 1e3 * z0, 1.0))


def near_bound(x, lo, hi, rel: float = 1e-6, magnitude=None) -> tuple[np.ndarray, np.ndarray]:
    """Masks (k,) of the values ``x`` within ``rel`` of their finite lower
    and of their finite upper bound, relative to the smaller of the box's
    width and the magnitude there (the larger of ``magnitude``, default
    ``|x|``, and that bound's): a box far wider than the value carries no
    scale (a mass of 5.5e-6 s² in a box (0, 1e9) is not "at" 0, which 1e-6
    of the width said). Shared by the estimate's, the loop's, the
    output-error fit's and the tracker's "on a bound"
    (:func:`bondgraph.inference.estimate._at_bound`,
    :func:`bondgraph.diagnose.fit.on_bound`,
    :class:`~bondgraph.inference.output_error.OutputErrorResult`'s
    ``at_bound``, ``bondgraph track``'s "sits on its box" warning).

    Parameters
    ----------
    x, lo, hi : arrays (k,)
        Values and their box (bounds may be infinite: that side is never near).
    rel : float
    magnitude : array (k,), optional

    Returns
    -------
    (near_lo, near_hi) : bool arrays (k,)
    """
    x, lo, hi = (np.asarray(a, float) for a in (x, lo, hi))
    mag = np.abs(x) if magnitude is None else np.asarray(magnitude, float)
    width = hi - lo
    with np.errstate(invalid="ignore"):
        near_lo = np.isfinite(lo) & (x - lo <= rel * np.minimum(width, np.maximum(mag, np.abs(lo))))
        near_hi = np.isfinite(hi) & (hi - x <= rel * np.minimum(width, np.maximum(mag, np.abs(hi))))
    return near_lo, near_hi


def _steps(x, hi, width, start=None) -> np.ndarray:
    """Forward-difference steps 1e-6 max(|x|, typical), downwards near the
    upper bound (typical: :func:`typical_magnitude` of ``start``, default
    ``x``, and the box's ``width``)."""
    typical = typical_magnitude(x if start is None else start, width)
    steps = 1e-6 * np.maximum(np.abs(x), typical)
    return np.where(x + steps > hi, -steps, steps)


def _scoring_step(D: Derivatives, x, L, lam: float, free=None) -> np.ndarray:
    """Levenberg-damped scoring step −(F + λ diag F)⁻¹ g, in z = log θ for
    the scale parameters ``L`` (chain rule ∂/∂z = θ ∂/∂θ), over the
    ``free`` parameters (default all); the others (:func:`pinned`) do not
    move."""
    free = np.ones(np.shape(x), bool) if free is None else np.asarray(free, bool)
    step = np.zeros(np.shape(x))
    if not free.any():
        return step
    jac = np.where(L, x, 1.0)[free]
    grad = D.grad[free] * jac
    Fz = D.F[np.ix_(free, free)] * np.outer(jac, jac)
    F = Fz + lam * np.diag(np.diag(Fz) + 1e-300)
    try:
        step[free] = -jacobi_solve(F, grad)
    except np.linalg.LinAlgError:
        step[free] = -jacobi_solve(F, grad, lstsq=True)
    return step


#: the line-search points tried first (the full and the doubled step);
#: the others follow only when the better of these gains less than
#: :data:`FIRST_POINTS_RATIO` of the NLL decrease the quadratic model
#: predicts for the full step (:func:`_line_search`)
FIRST_ALPHAS = (1.0, 2.0)
FIRST_POINTS_RATIO = 0.5
#: ... nor when it gains more than this many times the prediction: the step
#: was far too short (a scale parameter whose curvature the expected
#: information overstates), where a decade move may gain more
FIRST_POINTS_HIGH = 4.0


#: ratio of the full step's NLL decrease to the quadratic model's
#: prediction below which the next step is damped harder (Levenberg λ times
#: :data:`DAMPING_UP`; above it λ / 3), and the largest λ this reaches
DAMPING_RATIO = 0.25
DAMPING_UP = 10.0
DAMPING_MAX = 1e4


def _damping(lam: float, D: Derivatives, z, L, alphas, cand, nll,
             best: int) -> tuple[float, bool]:
    """``(λ, predicted)``: the Levenberg λ of the next scoring iteration
    after a step that lowered the NLL, and whether the quadratic model
    predicted the step (only then may a small gain end the scoring, by the
    relative stop or the ridge test, or a step cut short by the line
    search would stop it before the optimum: the 38th session's damping
    after a short step stopped a sensor gain trading with a torque
    constant 130-150 nats short, docs/background/loop.md):
    λ / 3 (at least 1e-6) when the full step gained at
    least :data:`DAMPING_RATIO` of what the quadratic model at ``z``
    predicts for it (:func:`_model_decrease`) or a full or longer step won,
    else λ x :data:`DAMPING_UP` (at most :data:`DAMPING_MAX`): the trust-region
    rule of Levenberg-Marquardt methods (Moré 1978; Nocedal & Wright 2006,
    Algorithm 4.1), with ``nll`` (c,) the line search's values at
    ``cand`` (c, k) (``alphas`` (c,)) and ``best`` the index of the point
    it took. Without it the damping fell after
    every successful step, also where only a short fraction of the step
    gained (the likelihood curved along a ridge the expected information
    barely sees): the scoring then proposed ever longer steps along the
    ridge, of which 3 % was taken, for dozens of iterations (the Silverbox
    user graph's ``r_power @ damper``: 43 iterations, 1.5 nats each)."""
    full = np.flatnonzero(alphas == 1.0)
    if full.size and not alphas[best] >= 1.0:
        pred = _model_decrease(D, z, cand[full[0]], L)
        f1 = float(nll[full[0]])
        if 0 < pred < np.inf and not (np.isfinite(f1) and D.nll - f1 >= DAMPING_RATIO * pred):
            return min(max(lam, 1e-6) * DAMPING_UP, DAMPING_MAX), False
    return max(lam / 3.0, 1e-6), True


def _line_search(line, D: Derivatives, z, L, alphas, cand,
                 rtol: float) -> tuple[np.ndarray, int]:
    """The NLL (c,) at the line-search points ``cand`` (c, k) of
    :func:`_candidates` (``alphas`` (c,): their step multiples, NaN for the
    scale moves) and the batched runs spent: first the points of
    :data:`FIRST_ALPHAS`; when the better of them gains between
    :data:`FIRST_POINTS_RATIO` and :data:`FIRST_POINTS_HIGH` times what the
    quadratic model of the NLL at ``z`` (``D``: its gradient and Fisher
    information, in log θ for ``L``) predicts for the full step (a
    trust-region ratio test, Nocedal & Wright 2006, §4.1), the others are
    left at inf, not run; else (a step the model mispredicts: too long, or
    far too short, as for a noise intensity whose curvature the expected
    information overstates, where a decade move may win) they are run too.
    Near an optimum and along a ridge the full or the doubled step wins
    (the bundled loop: 43 of 73 line searches), and a search then costs
    one batch of two points instead of six damped steps and four decade
    moves per scale parameter; without the upper bound the bundled CED
    case's rectifying sensor took 13 scoring iterations instead of 5. A
    gain small enough to end the scoring (below ``rtol`` (1 + |NLL|), the
    relative stop, or :data:`FLAT_GAIN`, the ridge test's) is never taken
    from the first points alone: the scoring stops only on what every
    point gave."""
    nll = np.full(len(cand), np.inf)
    first = np.flatnonzero(np.isin(alphas, FIRST_ALPHAS))
    if first.size == 0 or first.size == len(cand) or 1.0 not in alphas[first]:
        return np.asarray(line(cand), float), 1
    nll[first] = line(cand[first])
    if _first_points_suffice(nll, D, z, L, alphas, cand, rtol):
        return nll, 1
    rest = np.setdiff1d(np.arange(len(cand)), first)
    nll[rest] = line(cand[rest])
    return nll, 2


def _first_points_suffice(nll, D: Derivatives, z, L, alphas, cand, rtol: float) -> bool:
    """Whether the best NLL of ``nll`` (c,) at the points of
    :data:`FIRST_ALPHAS` passes :func:`_line_search`'s ratio test and
    gains more than would end the scoring (False when the search has no
    full step)."""
    first = np.isin(alphas, FIRST_ALPHAS)
    if not first.any() or 1.0 not in alphas[first]:
        return False
    f = float(np.min(np.where(np.isfinite(nll[first]), nll[first], np.inf)))
    gain = D.nll - f
    if not (np.isfinite(gain) and gain >= max(FLAT_GAIN, rtol * (1.0 + abs(f)))):
        return False
    pred = _model_decrease(D, z, cand[int(np.flatnonzero(alphas == 1.0)[0])], L)
    return bool(0 < pred < np.inf and FIRST_POINTS_RATIO * pred <= gain <= FIRST_POINTS_HIGH * pred)


def _model_decrease(D: Derivatives, z, c, L) -> float:
    """The NLL decrease −(gᵀΔ + ½ ΔᵀFΔ) the quadratic model at ``z`` (k,)
    predicts for the point ``c`` (k,), Δ = c − z (in log θ for the scale
    parameters ``L``)."""
    jac = np.where(L, z, 1.0)
    d = np.where(L, np.log(np.maximum(c, 1e-300)) - np.log(np.maximum(z, 1e-300)), c - z)
    g = D.grad * jac
    F = D.F * np.outer(jac, jac)
    v = -(float(g @ d) + 0.5 * float(d @ F @ d))
    return v if np.isfinite(v) else float("inf")


def _candidates(x, step, L, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Line-search points ``(alphas, cand (c, k))``: damped steps, and
    decade-sized coordinate moves of the scale parameters (alpha NaN).

    When the model is misspecified, the expected information of a noise
    intensity overstates its curvature and the scoring step is far too short.
    """
    alphas = np.array([1.0, 0.5, 0.25, 0.1, 0.03, 2.0])
    z = np.where(L, np.log(np.maximum(x, 1e-300)), x)
    zc = z[None, :] + alphas[:, None] * step[None, :]
    cand = np.clip(np.where(L, np.exp(np.minimum(zc, 700.0)), zc), lo, hi)
    moves = [np.clip(np.where(np.arange(x.size) == i, x * f, x), lo, hi)
             for i in np.flatnonzero(L) for f in (0.1, 0.3, 3.0, 10.0)]
    if moves:
        cand = np.vstack([cand, np.array(moves)])
        alphas = np.concatenate([alphas, np.full(len(moves), np.nan)])
    return alphas, cand
