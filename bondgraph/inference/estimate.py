"""Maximum-likelihood parameter estimation: UKF likelihood + PSO/DE + polish + Cramér-Rao.

::

    criterion   θ (S, k) -> NLL (S,)       one batched UKF run (bondgraph.inference.ukf)
    optimizer   pso | de                   (bondgraph.inference.optimize), whole population per call
    start       the declared values; each estimated noise level profiled there (decades)
    polish      the levels profiled again, Levenberg-damped Fisher scoring (summed over
                the records), then bounded L-BFGS-B, central-difference gradients in one
                batched call
    Hessian     central differences of the NLL, all 1 + 2k² points in one batched call
    Cramér-Rao  cov = H⁻¹ (H: observed Fisher information), std = sqrt(diag), correlation

The negative log-likelihood is that of the prediction-error decomposition
(Schweppe 1965; Kristensen, Madsen & Jørgensen 2004), so at the maximum
the inverse Hessian is the asymptotic covariance of the estimate
(Cramér-Rao bound; e.g. Ljung 1999, §9.3).

:func:`two_stage` chains estimations: each stage fixes the parameters
estimated by the stages before it (the coast-down / driving protocol of the
vehicle: stage 1 with the reduced model on the coast-down record, stage 2
with the full model on a driving record).

The ``bondgraph estimate`` command (:mod:`bondgraph.cli.estimate`) writes
``result.json`` and PNG fit plots.

References
----------
Schweppe, F. C. (1965). Evaluation of likelihood functions for Gaussian
signals. IEEE Trans. Inf. Theory 11(1), 61-70.
Kristensen, N. R., Madsen, H., Jørgensen, S. B. (2004). Parameter estimation
in stochastic grey-box models. Automatica 40(2), 225-237.
Ljung, L. (1999). System Identification: Theory for the User, 2nd ed.
"""

from __future__ import annotations

import json
import time
import warnings
from collections import Counter
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from bondgraph.core import progress
from bondgraph.core.jsonsafe import from_jsonable, to_jsonable
from bondgraph.errors import (EstimationError, IdentifiabilityWarning, ModelError, NumericalError,
                              OptionError)
from bondgraph.inference.checkpoint import problem_fingerprint
from bondgraph.inference.estimand import (
    NOISE_PREFIX,
    X0_PREFIX,
    Estimand,
    noise_parameters,
    plan_estimand,
    x0_state_names,
)
from bondgraph.inference.discretise import (
    BIAS_TOLERANCE,
    TOLERANCE,
    check_discretisation,
    choose_discretisation,
    comparison_sigma,
    holds_against,
    no_process_noise,
    record_input_holds,
    step_error,
    supported_hold,
)
from bondgraph.inference.optimize import de, minimize_batched, pso
from bondgraph.inference.options import (
    Evaluation,
    FitOptions,
    ScoringOptions,
    UKFOptions,
    fit_options,
)
from bondgraph.inference.problem import Problem
from bondgraph.inference.fisher import (estimand_scoring, innovation_differences, jacobi_pinv,
                                        joint_scoring, near_bound, relative_changes)
from bondgraph.inference.robust import ROBUST_RATIO, sandwich, score_covariance, step_scores
from bondgraph.inference.executor import Executor
from bondgraph.inference.ukf import (
    GUARD_REL,
    GUARD_SUBSTEPS,
    UKFResult,
    discretisation_check,
    nll_guard,
    ukf_nll,
)


# ----------------------------------------------------------------- criterion
class Criterion:
    """Batched NLL of a subset of parameters: ``crit(X (S, k)) -> (S,)``.

    Parameters
    ----------
    problem : Problem
        The model on the record with its prior (x0, P0), held noise levels
        and filter options (:func:`bondgraph.inference.problem.make_problem`).
    params : sequence of str
        Estimated parameters (k).
    base : array (n_theta,), optional
        Values of all parameters; the estimated ones are overwritten
        (default ``problem.theta``).
    Q, R : arrays, optional
        Extra process-noise covariance, and a measurement-noise covariance
        that replaces the problem's noise levels
        (:func:`bondgraph.inference.ukf.ukf_nll`).
    where : Evaluation, optional
        Chunk size and the Dask workers or scheduler that share each batch
        (:class:`bondgraph.inference.options.Evaluation`); results do not
        depend on it.

    Attributes
    ----------
    evaluations : int
        Parameter sets evaluated so far.
    calls : int
        Batched calls so far.
    failures : Counter
        Failure cause -> count over all evaluations.
    """


    def __init__(self, problem: Problem, params: Sequence[str], base=None, *, Q=None, R=None,
                 where: Evaluation | None = None):
        where = Evaluation() if where is None else where
        self.problem = problem
        self.model = problem.model
        self.t, self.u, self.y = problem.t, problem.u, problem.y
        self.params = list(params)
        self.idx = self.model.param_indices(self.params)
        self.base = np.asarray(problem.theta if base is None else base, dtype=float)
        self.x0, self.P0 = problem.x0, problem.P0
        self.options = problem.ukf
        self.Q, self.R = Q, R
        self.chunk = where.chunk
        self.workers = where.workers
        self._executor = Executor(self.workers, where.scheduler)
        self.evaluations = 0
        self.calls = 0
        self.failures: Counter = Counter()

    def _noise(self, th: np.ndarray):
        """The measurement-noise covariance of the sets ``th``: the given R,
        else the problem's held levels (None: ``meas_std(θ)``)."""
        return self.R if self.R is not None else self.problem.noise.covariance(self.model, th)

    def theta(self, X) -> np.ndarray:
        """Full parameter arrays (S, n_theta) for values X (S, k)."""
        return self.model.expand_theta(self.params, np.atleast_2d(X), self.base)

    def problem_at(self, x) -> tuple:
        """``(θ (n_theta,), x0 (n_x,), P0, R or None)`` of the filter at one point x (k,)."""
        th = self.theta(np.atleast_2d(x))
        R = self._noise(th)
        return th[0], self.x0, self.P0, None if R is None or R is self.R else R[0]

    def run(self, X, store: bool | str = False) -> UKFResult:
        """The UKF result (all arrays) for parameter values X (S, k)."""
        th = self.theta(X)
        return ukf_nll(self.model, self.t, self.u, self.y, th, self.x0, self.P0,
                       options=self.options, Q=self.Q, R=self._noise(th), store=store)

    def _evaluate(self, X):
        S = X.shape[0]
        out = np.empty(S)
        fails: Counter = Counter()
        step = self.chunk or S
        for a in range(0, S, step):
            r = self.run(X[a:a + step])
            out[a:a + step] = r.nll
            fails.update(r.failure_summary())
        return out, fails

    def __call__(self, X) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        S = X.shape[0]
        if self._executor.distributed and S >= 2:
            parts = self._executor.map(_evaluate_chunk, self, _chunks(X, self.chunk,
                                                                       self.workers))
            out = np.concatenate([p[0] for p in parts])
            for p in parts:
                self.failures.update(p[1])
        else:
            out, fails = self._evaluate(X)
            self.failures.update(fails)
        self.evaluations += S
        self.calls += 1
        return out

    def close(self) -> None:
        """Stop the Dask client and the embedded workers (if any)."""
        self._executor.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


#: parameter sets per chunk sent to a worker when no chunk size is given
DEFAULT_CHUNK = 16


def _chunks(X: np.ndarray, chunk: int | None, workers: int) -> list[np.ndarray]:
    """Rows of X in chunks of ``chunk`` rows; without a chunk size, in a
    multiple of ``workers`` chunks (at least two per worker when there are
    enough rows) of at most DEFAULT_CHUNK rows whose sizes differ by one at
    most (80 sets on 2 workers: 6 chunks of 14 or 13 rows, 41 + 39 per
    worker; not 5 chunks of 16, where one worker ran 48)."""
    S = X.shape[0]
    if chunk:
        return [X[a:a + chunk] for a in range(0, S, chunk)]
    w = max(1, int(workers))
    n = min(S, w * max(2, -(-S // (DEFAULT_CHUNK * w)))) if S else 0
    return [p for p in np.array_split(X, n)] if n else []


def _evaluate_chunk(crit: "Criterion", X: np.ndarray):
    """``(nll, failures)`` of one chunk on a worker (:meth:`Criterion._evaluate`)."""
    return crit._evaluate(X)


class EstimandCriterion(Criterion):
    """Batched NLL of the quantities of an :class:`~bondgraph.inference.estimand.Estimand`
    (parameters, initial states ``x0.<state>``, noise stds ``noise.<output>``):
    ``crit(S (P, k)) -> (P,)`` in search coordinates, where a noise std moves
    as its logarithm (a scale parameter: its likelihood is far from
    quadratic near zero, and its box spans eight decades). The initial
    states estimated get a token prior spread, so the likelihood is
    conditional on them (Kristensen, Madsen & Jørgensen 2004).

    Parameters
    ----------
    problem : Problem
        Its prior covariance ``P0`` is the one before the estimated states
        are shrunk.
    est : Estimand
    Q, where :
        As for :class:`Criterion`.

    Attributes
    ----------
    params : list of str
        The estimand's names (k).
    log : ndarray of bool (k,)
        Coordinates searched in log scale.
    """

    def __init__(self, problem: Problem, est: Estimand, *, Q=None,
                 where: Evaluation | None = None):
        super().__init__(problem, est.params, est.theta, Q=Q, R=None, where=where)
        self.x0 = est.x0
        self.est = est
        self.params = est.names
        self.sigma = est.sigma
        self.log = np.array([n.startswith(NOISE_PREFIX) for n in est.names], dtype=bool)

    def to_value(self, S) -> np.ndarray:
        """Estimand values Z (P, k) of search coordinates S (P, k)."""
        Z = np.array(np.atleast_2d(S), dtype=float)
        Z[:, self.log] = np.exp(np.minimum(Z[:, self.log], 700.0))
        return Z

    def to_search(self, Z) -> np.ndarray:
        """Search coordinates (P, k) of estimand values Z (P, k)."""
        S = np.array(np.atleast_2d(Z), dtype=float)
        S[:, self.log] = np.log(np.maximum(S[:, self.log], 1e-300))
        return S

    def theta(self, X) -> np.ndarray:
        """Full parameter arrays (P, n_theta) of search coordinates X (P, k)."""
        return self.est.expand(self.to_value(X))[0]

    def problem_at(self, x) -> tuple:
        """``(θ (n_theta,), x0 (n_x,), P0, R or None)`` of the filter at one
        point x (k,) of search coordinates."""
        th, x0s, R = self.est.expand(self.to_value(x))
        return th[0], x0s[0], self.est.prior_cov(self.P0), None if R is None else R[0]

    def run(self, X, store: bool | str = False) -> UKFResult:
        """The UKF result for search coordinates X (P, k)."""
        th, x0s, R = self.est.expand(self.to_value(X))
        return ukf_nll(self.model, self.t, self.u, self.y, th, x0s, self.est.prior_cov(self.P0),
                       options=self.options, Q=self.Q, R=R, store=store)


class JointCriterion:
    """The NLL of one parameter vector on several records: the sum of each
    record's batched NLL, ``crit(X (S, k)) -> (S,)``.

    The records are independent experiments on the same model: each keeps
    its own initial state, prior, held noise levels and filter options; the
    parameters and the estimated noise levels are shared, so the members
    must search the same quantities in the same coordinates.

    Parameters
    ----------
    members : sequence of Criterion
        One criterion per record (all :class:`Criterion` or
        :class:`EstimandCriterion` of the same names).

    Attributes
    ----------
    members : list of Criterion
    params : list of str
        The shared names (k).
    problem : Problem
        The first record's problem (the model, fixed values, noise policy).

    Raises
    ------
    OptionError
        Fewer than two members, or members that search different quantities.
    """

    def __init__(self, members: Sequence[Criterion]):
        self.members = list(members)
        if len(self.members) < 2:
            raise OptionError("a joint criterion needs at least two records")
        first = self.members[0]
        for m in self.members[1:]:
            if list(m.params) != list(first.params):
                raise OptionError(
                    f"the records estimate different quantities: {m.problem.name} "
                    f"{list(m.params)}, {first.problem.name} {list(first.params)}")
        self.params = list(first.params)
        self.problem, self.model, self.base = first.problem, first.model, first.base
        self.options, self.Q, self.R = first.options, first.Q, first.R
        self.estimand = isinstance(first, EstimandCriterion)
        if self.estimand:
            self.log = first.log

    @property
    def evaluations(self) -> int:
        """Parameter sets evaluated so far (each on every record)."""
        return self.members[0].evaluations

    @property
    def failures(self) -> Counter:
        """Failure cause -> count, over every record."""
        return sum((m.failures for m in self.members), Counter())

    def to_value(self, S) -> np.ndarray:
        """Values of search coordinates S (P, k) (:meth:`EstimandCriterion.to_value`)."""
        return self.members[0].to_value(S)

    def to_search(self, Z) -> np.ndarray:
        """Search coordinates of values Z (P, k)."""
        return self.members[0].to_search(Z)

    def theta(self, X) -> np.ndarray:
        """Full parameter arrays (S, n_theta) of X (S, k)."""
        return self.members[0].theta(X)

    def __call__(self, X) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        out = np.zeros(X.shape[0])
        for m in self.members:
            out += m(X)
        return out

    def close(self) -> None:
        """Stop every member's executor."""
        for m in self.members:
            m.close()


def record_names(problems: Sequence[Problem]) -> list[str]:
    """Each record's name, made unique by its position when two are alike."""
    names = [p.name for p in problems]
    return [f"{n} #{i + 1}" if names.count(n) > 1 else n for i, n in enumerate(names)]


# ------------------------------------------------------------------- Hessian
def hessian_batched(fun: Callable[[np.ndarray], np.ndarray], x, h) -> tuple[np.ndarray, float, int]:
    """Hessian of a batched scalar function by central differences.

    Parameters
    ----------
    fun : callable
        ``fun(X (S, k)) -> (S,)``.
    x : array (k,)
    h : array (k,)
        Step per coordinate.

    Returns
    -------
    (H (k, k), f(x), evaluations)
        All 1 + 2k² points are evaluated in one call. H contains NaN where
        a needed value was not finite.

    Notes
    -----
    H_ii = (f(x+h_i) − 2f(x) + f(x−h_i)) / h_i²;
    H_ij = (f(+,+) − f(+,−) − f(−,+) + f(−,−)) / (4 h_i h_j).
    """
    x = np.asarray(x, dtype=float)
    h = np.asarray(h, dtype=float)
    k = x.size
    E = np.diag(h)
    pts = [x]
    for i in range(k):
        pts += [x + E[i], x - E[i]]
    pairs = [(i, j) for i in range(k) for j in range(i + 1, k)]
    for i, j in pairs:
        pts += [x + E[i] + E[j], x + E[i] - E[j], x - E[i] + E[j], x - E[i] - E[j]]
    F = np.asarray(fun(np.array(pts)), dtype=float)
    f0 = F[0]
    H = np.empty((k, k))
    for i in range(k):
        H[i, i] = (F[1 + 2 * i] - 2.0 * f0 + F[2 + 2 * i]) / h[i] ** 2
    base = 1 + 2 * k
    for n, (i, j) in enumerate(pairs):
        a, b, c, d = F[base + 4 * n: base + 4 * n + 4]
        H[i, j] = H[j, i] = (a - b - c + d) / (4.0 * h[i] * h[j])
    H[~np.isfinite(H)] = np.nan
    return H, float(f0), len(pts)


#: a parameter whose component in an unidentified direction (a unit vector in
#: scaled coordinates) exceeds this moves along it: :func:`cramer_rao` gives it
#: no conditional bound (on the thermal record with T0 estimated the other
#: components were 1e-11)
FLAT_COMPONENT = 1e-3


def cramer_rao(H: np.ndarray, names: Sequence[str], scale=None, rcond: float = 1e-6,
               conditional: bool = False, theta=None) -> dict:
    """Cramér-Rao standard deviations and correlations from the NLL Hessian.

    Parameters
    ----------
    H : array (k, k)
        Hessian of the NLL (observed Fisher information).
    names : sequence of str
    scale : array (k,), optional
        Coordinate scales (e.g. the widths of the search box): the test of
        positive definiteness and the unidentified direction are in
        coordinates θ_i / scale_i (default: 1).
    rcond : float
        A direction is unidentified when its eigenvalue of the Hessian in
        relative coordinates is below ``rcond`` times the largest (the
        difference Hessian of an exactly singular problem has a relative
        eigenvalue of ~1e-8, not 0).
    conditional : bool
        When H is not positive definite: the bounds of the parameters
        outside the unidentified direction (its components above
        :data:`FLAT_COMPONENT`: a parameter that moves at all along it has
        no bound),
        conditional on those in it held at the estimate (the inverse of
        H's block of the others, when that block is positive definite);
        ``conditional_on`` names the held ones, their entries stay NaN.
    theta : array (k,), optional
        The estimate: the unidentified direction is also given as relative
        changes dθ_i/θ_i (the largest +1), and named a scale symmetry when
        those of the named parameters agree within :data:`SCALE_TOLERANCE`
        (a user's quarter-car driven by the road's velocity: both masses,
        stiffnesses and the damping +1.00 each, where the box-scaled
        direction read +0.64, +0.45, +0.42, +0.37, +0.27).

    Returns
    -------
    dict
        ``std (k,)``, ``corr (k, k)``, ``cov (k, k)``, ``eigenvalues``,
        ``positive_definite``, ``warning`` (str or None naming the weakest
        direction), ``conditional_on`` (list of str). Entries are NaN when
        H is not positive definite (but for the conditional bounds).
    """
    k = len(names)
    out = dict(std=np.full(k, np.nan), corr=np.full((k, k), np.nan), cov=np.full((k, k), np.nan),
               eigenvalues=np.full(k, np.nan), positive_definite=False, warning=None,
               conditional_on=[])
    if H is None or not np.isfinite(H).all():
        bad = [names[i] for i in range(k) if not np.isfinite(H[i]).all()] if H is not None else names
        out["warning"] = (f"Hessian of the NLL is not finite for {', '.join(bad)} (a difference "
                          f"point failed); no Cramér-Rao bound")
        return out
    s = np.ones(k) if scale is None else np.where(np.abs(scale) > 0, np.abs(scale), 1.0)
    Hs = H * np.outer(s, s)                       # Hessian in relative coordinates
    Hs = 0.5 * (Hs + Hs.T)
    lam, V = np.linalg.eigh(Hs)
    out["eigenvalues"] = lam
    flat, v = _flat_direction(Hs, lam, V, rcond)
    if flat:
        order = np.argsort(-np.abs(v))
        terms = [f"{v[i]:+.2f}·{names[i]}" for i in order if abs(v[i]) > 0.1]
        out["warning"] = (f"Hessian of the NLL is {_singular_text(Hs, lam, rcond)}: the "
                          f"direction {' '.join(terms)} (scaled coordinates) is not identified "
                          f"by the data{relative_direction(v * s, theta, names)}")
        if conditional:
            _conditional_bounds(out, Hs, s, names, np.abs(v) > FLAT_COMPONENT, rcond)
        return out
    cov = jacobi_pinv(Hs) * np.outer(s, s)      # inverted in unit-curvature coordinates
    std = np.sqrt(np.diag(cov))
    corr = cov / np.outer(std, std)
    out.update(std=std, cov=cov, corr=corr, positive_definite=True)
    iu = np.triu_indices(k, 1)
    strong = [(names[i], names[j], corr[i, j]) for i, j in zip(*iu) if abs(corr[i, j]) > 0.999]
    if strong:
        out["warning"] = "nearly unidentified: " + ", ".join(
            f"corr({a}, {b}) = {c:+.4f}" for a, b, c in strong)
    return out


def _singular_text(Hs: np.ndarray, lam: np.ndarray, rcond: float) -> str:
    """How the Hessian ``Hs`` (k, k; eigenvalues ``lam`` ascending) fails
    :func:`_flat_direction`'s test, for a user: "not positive definite"
    where an eigenvalue is not positive; else "nearly singular" with its
    smallest eigenvalue at unit curvatures relative to its largest (every
    curvature is positive there, so "not positive definite" next to a
    positive smallest eigenvalue read as a contradiction)."""
    diag = np.diag(Hs)
    if lam[0] <= 0.0 or not (diag > 0).all():
        return (f"not positive definite (smallest eigenvalue {lam[0]:.3g}, largest "
                f"{lam[-1]:.3g}, in scaled coordinates)")
    d = 1.0 / np.sqrt(diag)
    lj = np.linalg.eigvalsh(Hs * np.outer(d, d))
    return (f"nearly singular (every curvature positive, but scaled to unit curvatures its "
            f"smallest eigenvalue is {lj[0] / lj[-1]:.2g} of its largest, below {rcond:.0e})")


def _flat_direction(Hs: np.ndarray, lam: np.ndarray, V: np.ndarray,
                    rcond: float) -> tuple[bool, np.ndarray]:
    """``(flat, v)``: whether the Hessian ``Hs`` (k, k; eigenvalues ``lam``
    ascending, eigenvectors ``V``) leaves a direction unidentified, and that
    direction (k,, unit length, in Hs's coordinates).

    Not positive definite where an eigenvalue is not positive (Sylvester's
    inertia: whatever the scaling) or, with every curvature positive, where
    the Hessian scaled to unit curvatures (Jacobi scaling, H as a
    correlation matrix: van der Sluis 1969) has an eigenvalue below
    ``rcond`` times its largest: a near-collinearity of the parameters'
    effects, whatever their units. The box-scaled eigenvalues alone took a
    spread of curvatures for one: a noise level fitted to 1e-5 of its
    signal has a curvature 1e-7 of the parameters' in box coordinates and
    was called "not identified" while its relative std was 1 %."""
    diag = np.diag(Hs)
    if lam[0] <= 0.0 or not (diag > 0).all():
        small = lam[0] <= rcond * max(abs(lam[-1]), 1e-300)
        return bool(small), V[:, 0]
    d = 1.0 / np.sqrt(diag)
    lj, Vj = np.linalg.eigh(Hs * np.outer(d, d))
    if lj[0] > rcond * max(abs(lj[-1]), 1e-300):
        return False, V[:, 0]
    v = Vj[:, 0] * d
    return True, v / np.linalg.norm(v)


#: relative changes along an unidentified direction that agree within this
#: fraction of the largest are a scale symmetry (:func:`cramer_rao`)
SCALE_TOLERANCE = 0.1


def relative_direction(d: np.ndarray, theta, names, scale_only: bool = False) -> str:
    """An unidentified direction ``d`` (k,) in model units as relative
    changes at the estimate ``theta`` (k,), for a user's message.

    Parameters
    ----------
    d : array (k,)
        The direction (e.g. the Hessian's or the Fisher information's
        weakest eigenvector in model units).
    theta : array (k,) or None
        The estimate.
    names : sequence of str (k)
    scale_only : bool
        Return "" unless the direction is a scale symmetry.

    Returns
    -------
    str
        ``"; as relative changes: a +1.00, b +0.98"`` (the largest +1, those
        of at least 0.1 named, largest first), followed by ``" (a, b scale
        together: ...)"`` when all named are within :data:`SCALE_TOLERANCE`
        of +1; "" without ``theta``, or when a change is not finite (a
        parameter at zero).
    """
    if theta is None:
        return ""
    th = np.asarray(theta, float)
    if th.shape != d.shape or not np.all(np.isfinite(th)):
        return ""
    with np.errstate(divide="ignore", invalid="ignore"):
        r = d / th
    if not np.all(np.isfinite(r)) or not np.any(r):
        return ""
    r, named = relative_changes(r, 0.1)
    text = "; as relative changes: " + ", ".join(f"{names[i]} {r[i]:+.2f}" for i in named)
    if len(named) > 1 and np.all(np.abs(r[named] - 1.0) <= SCALE_TOLERANCE):
        return text + (f" ({', '.join(names[i] for i in named)} scale together: the record "
                       f"fixes their ratios, not their size; --fixed one you know)")
    return "" if scale_only else text


def _conditional_bounds(out: dict, Hs: np.ndarray, s: np.ndarray, names, flat: np.ndarray,
                        rcond: float) -> None:
    """Fill ``out`` (of :func:`cramer_rao`) for the parameters outside the
    unidentified direction (``flat`` (k,) marks those in it), conditional on
    those held: the inverse of the others' block of the scaled Hessian
    ``Hs``, when it is positive definite."""
    keep = np.flatnonzero(~flat)
    if keep.size == 0:
        return
    sub = 0.5 * (Hs[np.ix_(keep, keep)] + Hs[np.ix_(keep, keep)].T)
    lam, V = np.linalg.eigh(sub)
    if _flat_direction(sub, lam, V, rcond)[0]:
        return
    cov = jacobi_pinv(sub) * np.outer(s[keep], s[keep])
    std = np.sqrt(np.diag(cov))
    out["std"][keep] = std
    out["cov"][np.ix_(keep, keep)] = cov
    out["corr"][np.ix_(keep, keep)] = cov / np.outer(std, std)
    held = [names[i] for i in np.flatnonzero(flat)]
    out["conditional_on"] = held
    out["warning"] += (f"; the Cramér-Rao std of the others are conditional on "
                       f"{', '.join(held)} held at the estimate (hold "
                       f"{'it' if len(held) == 1 else 'them'} with --fixed, or add a record "
                       f"that tells {'it' if len(held) == 1 else 'them'} apart)")


# -------------------------------------------------------------------- result
@dataclass
class EstimationResult:
    """Outcome of :func:`estimate` (JSON-able with :meth:`to_json`).

    Attributes
    ----------
    model : str
    experiment : str
        Record name.
    params : list of str
    estimates : ndarray (k,)
        Maximum-likelihood estimates (after polish), model units.
    std : ndarray (k,)
        Cramér-Rao standard deviations sqrt(diag(H⁻¹)); NaN if H is not
        positive definite.
    corr : ndarray (k, k)
        Correlation matrix of the estimates.
    hessian : ndarray (k, k)
        Hessian of the NLL at the estimate.
    nll : float
        NLL at the estimate [nats].
    nll_optimizer : float
        Best NLL found by the global optimizer (before polish).
    evaluations : int
        Parameter sets evaluated by the global optimizer (e.g. 8080).
    evaluations_total : int
        Including polish and Hessian.
    wall_s : float
        Wall time of the whole estimation [s].
    optimizer : str
    theta : ndarray (n_theta,)
        Full parameter vector at the estimate.
    fixed : dict
        Parameters held at given values (other than defaults).
    lower, upper : ndarray (k,)
    truth : dict or None
        True values of the estimated parameters (synthetic records).
    z : ndarray (k,) or None
        (estimate − truth) / std.
    std_robust : ndarray (k,) or None
        Robust (sandwich) standard deviations sqrt(diag(H⁻¹ J H⁻¹)), J the
        Newey-West covariance of the per-sample scores
        (:mod:`bondgraph.inference.robust`; White 1982): equal to ``std``
        within sampling error when the model is right, larger when its
        misfit is serially correlated; None when H is not positive definite.
    """

    model: str
    experiment: str
    params: list
    estimates: np.ndarray
    std: np.ndarray
    corr: np.ndarray
    hessian: np.ndarray
    nll: float
    nll_optimizer: float
    evaluations: int
    evaluations_total: int
    wall_s: float
    optimizer: str
    theta: np.ndarray
    fixed: dict = field(default_factory=dict)
    lower: np.ndarray | None = None
    upper: np.ndarray | None = None
    truth: dict | None = None
    z: np.ndarray | None = None
    at_bound: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    failures: dict = field(default_factory=dict)
    optimizer_result: dict = field(default_factory=dict)
    polish: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)
    units: list = field(default_factory=list)
    std_total: np.ndarray | None = None
    propagated: dict = field(default_factory=dict)
    std_robust: np.ndarray | None = None

    def estimate_dict(self) -> dict[str, float]:
        """Parameter name -> estimate."""
        return {p: float(v) for p, v in zip(self.params, self.estimates)}

    def to_dict(self) -> dict:
        d = asdict(self)
        return to_jsonable(d)

    def to_json(self, path: str | Path | None = None, indent: int = 2) -> str:
        """JSON text (also written to ``path`` if given). NaN becomes ``null``,
        ±inf ``"inf"``/``"-inf"`` (:mod:`bondgraph.core.jsonsafe`)."""
        text = json.dumps(self.to_dict(), indent=indent, allow_nan=False)
        if path is not None:
            Path(path).write_text(text + "\n")
        return text

    @classmethod
    def from_json(cls, text_or_path) -> "EstimationResult":
        p = Path(text_or_path) if not str(text_or_path).lstrip().startswith("{") else None
        d = from_jsonable(json.loads(p.read_text() if p is not None else text_or_path))
        for key in ("estimates", "std", "corr", "hessian", "theta", "lower", "upper", "z",
                    "std_total", "std_robust"):
            if d.get(key) is not None:
                d[key] = np.array(d[key], dtype=float)
        return cls(**d)

    def table(self) -> str:
        """Plain-text table of estimates, standard deviations and truth."""
        has_truth = self.truth is not None
        head = f"{'parameter':<22}{'estimate':>14}{'CR std':>12}{'rel std':>9}"
        tot = self.std_total is not None
        rob = self.std_robust is not None
        if rob:
            head += f"{'robust std':>12}"
        if tot:
            head += f"{'total std':>12}"
        if has_truth:
            head += f"{'truth':>14}{'z':>7}"
        lines = [head, "-" * len(head)]
        for i, p in enumerate(self.params):
            e, s = self.estimates[i], self.std[i]
            rel = abs(s / e) if e != 0 and np.isfinite(s) else np.nan
            row = f"{p:<22}{e:>14.6g}{s:>12.3g}{rel:>9.2%}"
            if rob:
                row += f"{self.std_robust[i]:>12.3g}"
            if tot:
                row += f"{self.std_total[i]:>12.3g}"
            if has_truth:
                tv = self.truth.get(p, np.nan)
                zz = self.z[i] if self.z is not None else np.nan
                row += f"{tv:>14.6g}{zz:>7.2f}"
            lines.append(row)
        lines.append(f"NLL {self.nll:.6f} (optimizer {self.nll_optimizer:.6f}); "
                     f"{self.evaluations} optimizer evaluations ({self.optimizer}), "
                     f"{self.evaluations_total} in total; {self.wall_s:.1f} s")
        for w in self.warnings:
            lines.append(f"WARNING: {w}")
        return "\n".join(lines)


# ----------------------------------------------------------------- estimation
def estimate(problem: Problem, params: Sequence[str], *, fit: FitOptions | None = None,
             bounds: Mapping[str, tuple] | None = None, Q=None, R=None, start=None,
             x0_states: Sequence[str] = (), log=None) -> EstimationResult:
    """Maximum-likelihood estimate of ``params`` from one record or several,
    with the initial states ``x0_states`` and the noise levels of the
    problem's noise policy.

    Parameters
    ----------
    problem : Problem or list of Problem
        The model bound to the record (:func:`bondgraph.inference.problem.make_problem`):
        its prior (x0, P0), fixed values, noise policy (``problem.noise.mode``:
        "auto" holds declared levels and estimates the undeclared ones with θ,
        "model" keeps the graph's) and filter options (``problem.ukf``).
        Several (one model, independent records): fitted together
        (:class:`JointCriterion`; ``settings["records"]`` describes each).
    params : sequence of str
        Parameters to estimate (k).
    fit : FitOptions, optional
        How to search (optimizer, swarm, iterations, seed, checkpoint,
        polish ...).
    bounds : dict name -> (lower, upper), optional
        Search box (default: the model's bounds).
    Q, R : arrays, optional
        Extra process-noise / measurement-noise covariance (R: no noise policy).
    start : array (k,) or (k + m + r,), optional
        A starting point placed in the initial population: the parameters
        ``params``, or every estimated quantity in the order of a result's
        ``params`` (the parameters, ``x0.<state>``, ``noise.<output>``).
    x0_states : sequence of str
        Initial states estimated with θ (``x0.<state>``; ``["all"]``): their
        prior shrinks to a token spread (Kristensen, Madsen & Jørgensen 2004).
    log : callable, optional
        Receives the noise policy's notes (which levels are estimated, why).

    Returns
    -------
    EstimationResult
        ``params`` lists every estimated quantity: the parameters, then
        ``x0.<state>``, then ``noise.<output>`` (measurement-noise std,
        output units); ``settings["noise_levels"]`` the level of every
        output in the filter and how it was set.

    Raises
    ------
    ModelError
        Unknown parameter names, or a fixed parameter that is also estimated.
    OptionError, DataError, EstimationError
        Bad options or state names, a checkpoint of another problem; a bad record; no finite NLL;
        records that cannot share the fit (:func:`_problems`, :func:`_joint`).

    Warns
    -----
    IdentifiabilityWarning
        Hessian not positive definite (direction named), an estimate on a bound, a
        discretisation error > 0.1 σ, or an NLL 1e-3 off RK4(40) (nll_guard).

    References
    ----------
    Kennedy & Eberhart (1995) for the swarm; Wan & van der Merwe (2000) for
    the UKF likelihood; Åström (1980) for the scoring polish (the Fisher
    information of the innovations); Cramér (1946), Rao (1945) for the bound.
    """
    t_start = time.perf_counter()
    fit = fit_options(fit)
    problems = _problems(problem, x0_states)
    plan, crit = _joint(problems, params, bounds, R, x0_states, fit, Q, log)
    lo, hi = plan.lo, plan.hi
    try:
        opt, x_best, f_best, pol, (slo, shi) = _search(crit, plan, fit, start, log)
        warn_list = _bound_warnings(crit.params, x_best, lo, hi, sampled=(slo, shi))
        H, cr, disc = _checked_at(crit, (x_best, f_best), (lo, hi), (slo, shi), fit,
                                  problems[0].ukf, warn_list)
    finally:
        crit.close()
    for w in warn_list:
        warnings.warn(w, IdentifiabilityWarning, stacklevel=2)
    z_best, lo_v, hi_v, H, cr = _to_values(crit, x_best, lo, hi, H, cr)
    found = _Found(opt, z_best, f_best, pol, H, cr, lo_v, hi_v, warn_list, disc)
    return _result(problems, plan, crit, fit, found, Q, R, time.perf_counter() - t_start)


def _checked_at(crit, best, box, sampled, fit: FitOptions, ukf: UKFOptions, warn_list: list):
    """``(H, cr, disc)`` at the estimate ``best`` = ``(x, f)``: the Hessian
    and the standard errors (:func:`_hessian_at`, within ``box`` = ``(lo,
    hi)``, scaled by the ``sampled`` region), then the filter's
    discretisation there (:func:`_discretisation_at`), each a named
    :func:`bondgraph.core.progress.phase`; warnings appended to
    ``warn_list``."""
    (x_best, f_best), (lo, hi) = best, box
    with progress.phase("the Hessian and the standard errors at the estimate"):
        H, cr = _hessian_at(crit, x_best, f_best, lo, hi, fit, warn_list, scale_box=sampled)
    with progress.phase("checking the filter's discretisation at the estimate"):
        disc = _discretisation_at(crit, x_best, f_best, fit, ukf, warn_list,
                                  floor=_levels_on_floor(crit, x_best, lo, hi))
    return H, cr, disc


def _levels_on_floor(crit, x, lo, hi) -> dict[int, str]:
    """The estimated measurement-noise levels on the lower bound of their
    box at ``x``, by the output they are the level of: ``noise.<output>``,
    or a parameter that moves that output's ``meas_std`` (and neither f
    nor h). Levels the box sets, not the record."""
    near_lo, _ = near_bound(x, lo, hi)
    on = [p for i, p in enumerate(crit.params) if near_lo[i]]
    if not on:
        return {}
    one = crit.members[0] if isinstance(crit, JointCriterion) else crit
    model = one.problem.model
    th = np.asarray(one.problem_at(x)[0], float)
    noise = set(noise_parameters(model, th))
    out = {}
    for p in on:
        if p.startswith(NOISE_PREFIX):
            out[model.output_index(p[len(NOISE_PREFIX):])] = p
        elif p in noise:
            th2 = th.copy()
            th2[model.param_index(p)] *= 2.0
            with np.errstate(all="ignore"):
                moved = np.asarray(model.meas_std(th2[None, :]), float).reshape(-1) != \
                    np.asarray(model.meas_std(th[None, :]), float).reshape(-1)
            out.update({int(j): p for j in np.flatnonzero(moved)})
    return out


def _problems(problem, x0_states) -> list[Problem]:
    """The records of an estimation: one problem, or several of one model
    with the same fixed values and no estimated initial states.

    Raises
    ------
    OptionError
        No problem, problems of different models or fixed values, or
        initial states estimated on several records.
    """
    problems = list(problem) if isinstance(problem, (list, tuple)) else [problem]
    for p in problems:
        if not isinstance(p, Problem):
            raise OptionError(f"estimate needs a Problem (bondgraph.inference.problem."
                              f"make_problem) or a list of them, got {type(p).__name__}")
    if len(problems) <= 1:
        if not problems:
            raise OptionError("estimate needs a Problem, got an empty list")
        return problems
    first = problems[0]
    for p in problems:
        if p.model.name != first.model.name or p.model.params != first.model.params:
            raise OptionError(f"the records are bound to different models: "
                              f"{first.model.name!r} and {p.model.name!r}")
        if dict(p.fixed) != dict(first.fixed):
            raise OptionError(f"the records hold different fixed values: {first.name} "
                              f"{dict(first.fixed)}, {p.name} {dict(p.fixed)}")
    if list(x0_states):
        raise OptionError(
            "initial states are estimated on one record only: with several records each keeps "
            "its own initial state (its state columns or sidecar x0, else the model's), "
            "leave --estimate-x0 out or fit the records one by one")
    return problems


def _joint(problems, params, bounds, R, x0_states, fit, Q, log):
    """``(plan, criterion)`` of an estimation on one or several records: one
    record's :class:`_Plan` and criterion; several records' shared plan (the
    first record's, its search box the union of the records' boxes: a noise
    level's box is centred on each record's own start) and their
    :class:`JointCriterion`. The noise policy's notes go to ``log``, a
    record's own prefixed with its name when they differ from the first's.

    Raises
    ------
    OptionError
        The records' noise policies estimate different quantities (a level
        one record declares and another does not).
    """
    say = log or (lambda _m: None)
    plans = [_plan(p, params, bounds, R, x0_states) for p in problems]
    names = record_names(problems)
    for note in plans[0].notes:
        say(note if len(plans) == 1 else f"{names[0]}: {note}")
    for nm, pl in zip(names[1:], plans[1:]):
        for note in pl.notes:
            say(f"{nm}: {note}")
    crits = [_criterion(p, pl, fit, Q, R) for p, pl in zip(problems, plans)]
    if len(crits) == 1:
        return plans[0], crits[0]
    try:
        crit = JointCriterion(crits)
    except OptionError as e:
        for c in crits:
            c.close()
        raise OptionError(f"{e}; declare the same noise levels in every record "
                          f"(sidecar noise_std) or none") from None
    lo = np.min([pl.lo for pl in plans], axis=0)
    hi = np.max([pl.hi for pl in plans], axis=0)
    return replace(plans[0], lo=lo, hi=hi), crit


def _joint_settings(res: EstimationResult, problems: Sequence[Problem]) -> None:
    """A joint estimate's settings: ``records``, each record's name, length,
    initial state, its rule and filter options; ``samples`` and
    ``duration_s`` summed; the experiment named by the records."""
    names = record_names(problems)
    res.experiment = " + ".join(names)
    res.settings["records"] = [
        dict(name=n, samples=int(p.t.size), duration_s=float(p.t[-1] - p.t[0]),
             x0=p.x0.tolist(), P0=np.asarray(p.P0, float).tolist(), x0_rule=p.x0_rule,
             ukf=p.ukf.to_dict()) for n, p in zip(names, problems)]
    res.settings["samples"] = int(sum(p.t.size for p in problems))
    res.settings["duration_s"] = float(sum(p.t[-1] - p.t[0] for p in problems))


@dataclass(frozen=True)
class _Plan:
    """What an estimation moves: the user's parameters, the values of all
    (base θ), the :class:`~bondgraph.inference.estimand.Estimand` (None for
    parameters only under the "model" noise policy without initial states),
    the noise notes and the search box in search coordinates."""

    params: list
    base: np.ndarray
    est: Estimand | None
    notes: list
    lo: np.ndarray
    hi: np.ndarray


@dataclass(frozen=True)
class _Found:
    """What the search found: the optimizer's result, the estimate (values),
    its NLL, the polish summary, the Hessian and Cramér-Rao bounds (values),
    the box (values), the warnings and the discretisation check."""

    opt: Any
    z: np.ndarray
    nll: float
    polish: dict
    H: np.ndarray
    cr: dict
    lo: np.ndarray
    hi: np.ndarray
    warnings: list
    disc: dict | None


def _plan(problem: Problem, params, bounds, R, x0_states) -> _Plan:
    """The :class:`_Plan` of an estimation on ``problem``."""
    if not isinstance(problem, Problem):
        raise OptionError(f"estimate needs a Problem (bondgraph.inference.problem.make_problem), "
                          f"got {type(problem).__name__}")
    model = problem.model
    params, lo, hi = _search_box(model, params, problem.fixed, bounds)
    base = problem.theta.copy()
    states = x0_state_names(model, x0_states)
    declared = None if problem.record is None else problem.record.noise_std_for(model)
    mode = "model" if R is not None else problem.noise.mode
    scale = np.sqrt(np.diag(problem.P0))
    est, notes = plan_estimand(model, base, params, list(problem.fixed), declared, noise=mode,
                               states=states, x0=problem.x0, x0_scale=np.maximum(scale, 1e-12),
                               y=problem.y)
    if R is not None:
        notes = ["noise levels: the given R"]
    if est.k == len(params) and not est.uses_R:
        return _Plan(params, base, None, notes, lo, hi)
    extra = est.params[len(params):]
    lo_e, hi_e = model.bounds(extra) if extra else (np.zeros(0), np.zeros(0))
    lo_v, hi_v = est.bounds(np.concatenate([lo, lo_e]), np.concatenate([hi, hi_e]))
    log = np.array([n.startswith(NOISE_PREFIX) for n in est.names], dtype=bool)
    lo_v[log], hi_v[log] = np.log(lo_v[log]), np.log(hi_v[log])
    return _Plan(params, base, est, notes, lo_v, hi_v)


def _criterion(problem: Problem, plan: _Plan, fit: FitOptions, Q, R) -> Criterion:
    """The batched NLL of the problem: a :class:`Criterion` of the parameters,
    or an :class:`EstimandCriterion` when initial states or noise levels
    take part."""
    where = Evaluation(chunk=fit.chunk, workers=fit.workers, scheduler=fit.scheduler)
    if plan.est is None:
        return Criterion(problem, plan.params, plan.base, Q=Q, R=R, where=where)
    return EstimandCriterion(problem, plan.est, Q=Q, where=where)


def _start(crit: Criterion, plan: _Plan, start):
    """The optimizer's start (search coordinates): ``start`` (k user
    parameters) completed with the current values of the other estimated
    quantities, or every estimated quantity when ``start`` has them all (a
    result's ``estimates``); without ``start``, the problem's own values
    (the declared defaults, the noise levels' starts). The swarm holds it
    as a particle, so the search never ends worse than the values it was
    given (a user's declared values, or a loop's estimates in its
    ``augmented_model.py``); before, no particle was there."""
    if start is None:
        if plan.est is None:
            return np.asarray(plan.base, float)[crit.model.param_indices(plan.params)]
        return crit.to_search(plan.est.value())[0]
    if plan.est is None:
        return start
    z = plan.est.value()
    s = np.asarray(start, float).reshape(-1)
    if s.size == z.size:
        z = s.copy()
    else:
        z[:len(plan.params)] = s
    return crit.to_search(z)[0]


def _to_values(crit: Criterion, x, lo, hi, H, cr):
    """Search coordinates back to estimand values: the estimate (k,), the
    box (k,), and the Hessian and Cramér-Rao bounds by the delta method
    (a log-scale coordinate s = ln z: ∂z/∂s = z)."""
    if not (isinstance(crit, EstimandCriterion) or getattr(crit, "estimand", False)):
        return x, lo, hi, H, cr
    z = crit.to_value(x)[0]
    lo_v, hi_v = crit.to_value(lo)[0], crit.to_value(hi)[0]
    J = np.where(crit.log, z, 1.0)
    cr = dict(cr)
    cr["std"] = np.asarray(cr["std"], float) * J
    if cr.get("std_robust") is not None:
        cr["std_robust"] = np.asarray(cr["std_robust"], float) * J
    if cr.get("cov") is not None:
        cr["cov"] = np.asarray(cr["cov"], float) * np.outer(J, J)
    return z, lo_v, hi_v, np.asarray(H, float) / np.outer(J, J), cr


def _result(problems: list[Problem], plan: _Plan, crit, fit: FitOptions, found: _Found, Q, R,
            wall: float) -> EstimationResult:
    """The :class:`EstimationResult` of an estimation on ``problems`` at the
    estimate ``found.z`` (k,)."""
    problem = problems[0]
    model, names, est, z, cr = problem.model, list(crit.params), plan.est, found.z, found.cr
    theta = (_full_theta(model, names, plan.base, z) if est is None
             else est.expand(z[None, :])[0][0])
    truth, zs = _truth(problem.meta, names, z, cr["std"])
    settings = _settings(fit, problem, Q, R, len(names), found.disc)
    settings.update(noise=problem.noise.mode if R is None else "R", noise_notes=list(plan.notes),
                    noise_levels=_noise_levels(model, est, z, cr["std"], theta),
                    x0_states=[] if est is None else list(est.states))
    res = EstimationResult(
        model=model.name, experiment=problem.name, params=names, estimates=z, std=cr["std"],
        std_robust=cr.get("std_robust"),
        corr=cr["corr"], hessian=found.H, nll=float(found.nll), nll_optimizer=float(found.opt.fun),
        evaluations=int(found.opt.nfev), evaluations_total=int(crit.evaluations), wall_s=wall,
        optimizer=fit.optimizer, theta=theta, fixed=dict(problem.fixed), lower=found.lo,
        upper=found.hi, truth=truth, z=zs, at_bound=_at_bound(names, z, found.lo, found.hi),
        warnings=found.warnings, failures=dict(crit.failures),
        optimizer_result=found.opt.to_dict(), polish=found.polish, settings=settings,
        units=_units(model, names))
    if len(problems) > 1:
        _joint_settings(res, problems)
    return res


def _units(model, names: Sequence[str]) -> list[str]:
    """Units of the estimated quantities: parameter, state or output units."""
    out = []
    for n in names:
        if n.startswith(X0_PREFIX):
            out.append(model.state_units[model.state_index(n[len(X0_PREFIX):])])
        elif n.startswith(NOISE_PREFIX):
            out.append(model.output_units[model.output_index(n[len(NOISE_PREFIX):])])
        else:
            out.append(model.param_units[model.param_index(n)])
    return out


def _noise_levels(model, est: Estimand | None, z, std, theta) -> dict:
    """Output -> ``{"std": level in the filter (output units), "how":
    "estimated" | "declared" | "model", "crb": Cramér-Rao std or None}``."""
    with np.errstate(all="ignore"):
        meas = np.asarray(model.meas_std(np.asarray(theta, float)[None, :]), float)[0]
    sig = np.full(model.n_y, np.nan) if est is None else est.at(z).sigma
    names = [] if est is None else est.names
    out = {}
    for j, o in enumerate(model.outputs):
        key = NOISE_PREFIX + o
        if key in names:
            sd = float(std[names.index(key)])
            out[o] = dict(std=float(sig[j]), how="estimated", crb=sd if np.isfinite(sd) else None)
        elif np.isfinite(sig[j]):
            out[o] = dict(std=float(sig[j]), how="declared", crb=None)
        else:
            out[o] = dict(std=float(meas[j]), how="model", crb=None)
    return out


def _settings(fit: FitOptions, problem: Problem, Q, R, k: int, disc) -> dict:
    """``EstimationResult.settings``: the UKF options as a dict, the search's
    size, the record's length, the prior and the discretisation check."""
    t = problem.t
    return dict(ukf=problem.ukf.to_dict(), Q_given=Q is not None, R_given=R is not None,
                samples=int(t.size), duration_s=float(t[-1] - t[0]),
                particles=_swarm_size(fit, k), iterations=fit.iterations, seed=fit.seed,
                x0=problem.x0.tolist(), P0=np.asarray(problem.P0, float).tolist(),
                x0_rule=problem.x0_rule, discretisation=disc)


def check_not_fixed(params: Sequence[str], fixed) -> None:
    """Raise when a parameter to estimate is also given a fixed value.

    Raises
    ------
    ModelError
        The parameters both fixed and estimated named.
    """
    both = sorted(set(fixed or {}) & set(params))
    if both:
        raise ModelError(f"parameter(s) {', '.join(both)} both fixed and estimated",
                         hint="leave them out of --params, or out of --fixed")


def _search_box(model, params, fixed, bounds):
    """``(params, lower, upper)`` of an estimation, checked against the
    problem's ``fixed`` values."""
    params = list(params)
    if not params:
        raise OptionError("no parameters to estimate")
    if len(set(params)) != len(params):
        raise OptionError(f"parameter listed twice in {params}")
    model.param_indices(params)                    # ModelError for unknown names
    check_not_fixed(params, fixed)
    lo, hi = model.bounds(params)
    for name, (a, b) in (bounds or {}).items():
        if name not in params:
            raise ModelError(f"bounds given for '{name}', which is not estimated ({params})")
        i = params.index(name)
        lo[i], hi[i] = float(a), float(b)
    return params, lo, hi


def _full_theta(model, params, base, x) -> np.ndarray:
    """The full parameter vector: ``base`` with the estimated ``params`` set to ``x``."""
    theta = base.copy()
    theta[model.param_indices(params)] = x
    return theta


def _swarm_size(fit: FitOptions, k: int) -> int:
    """PSO particles / DE members: ``fit.particles``, default 10 k."""
    return int(fit.particles) if fit.particles else 10 * k


#: a parameter box wider than this many times its start's magnitude is too
#: wide for a swarm to sample (an effect's offset or calibration term in
#: (-1e9, 1e9), a lag's time constant in (1e-9, 1e9)): :func:`sampled_box`
TOO_WIDE = 1e6
#: the region the swarm samples instead: the start ×/÷ SAMPLED (a positive
#: box) or the start ± SAMPLED times its magnitude (the effect library's own
#: search box, :func:`bondgraph.diagnose.effects.base._box`)
SAMPLED = 10.0
#: times the polish may widen a sampled region whose edge the estimate reached
WIDENINGS = 4


def sampled_box(model, plan, lo, hi, x_start, log=None) -> tuple[np.ndarray, np.ndarray]:
    """The region ``(lower, upper)`` (search coordinates, like ``lo``/``hi``)
    the swarm samples and the polish starts in: the box ``lo``/``hi``,
    except for a parameter whose box is more than :data:`TOO_WIDE` times
    wider than its start's magnitude: that one is sampled around its start
    (its value in ``x_start``, else the problem's θ), within ×/÷
    :data:`SAMPLED` of it for a box of one sign, ± :data:`SAMPLED` times its
    magnitude otherwise (:func:`_beyond_sampled` lets the estimate leave it,
    within the box). A swarm spread uniformly over (-1e9, 1e9) puts every
    particle at an absurd value: on the EMPS record, a force
    offset's box (the effect library's) left ``bondgraph estimate`` stuck
    from its fourth iteration at NLL -31 540 with the sensor noise on the
    top of its box (the whole output's spread), against -100 164 from a
    box of ±30 N. One line to ``log`` names each such parameter; a start
    of 0 cannot be sampled around: where its box is wider than
    :data:`TOO_WIDE` itself, a line says to give it a box."""
    names = list(plan.params)
    k = len(names)
    centre = (np.asarray(x_start, float)[:k] if x_start is not None
              else np.asarray(plan.base, float)[model.param_indices(names)])
    slo, shi = np.array(lo, float), np.array(hi, float)
    around, unknown = [], []
    for i, n in enumerate(names):
        c, width = float(centre[i]), float(hi[i] - lo[i])
        if not width > TOO_WIDE * abs(c):
            continue
        if c == 0.0 or not np.isfinite(c):
            if width > TOO_WIDE:        # a start of 0 in (-1, 1) is nothing to say
                unknown.append(n)
            continue
        if lo[i] >= 0.0 or hi[i] <= 0.0:
            a, b = sorted((c / SAMPLED, c * SAMPLED))
        else:
            a, b = c - SAMPLED * abs(c), c + SAMPLED * abs(c)
        slo[i], shi[i] = max(lo[i], a), min(hi[i], b)
        around.append(f"{n} in [{slo[i]:.4g}, {shi[i]:.4g}] (box [{lo[i]:.4g}, {hi[i]:.4g}])")
    if log and around:
        log(f"box too wide to sample: the swarm searches {'; '.join(around)} around the "
            f"start; the estimate may leave that region within the box")
    if log and unknown:
        log(f"box too wide to sample around a start of 0: {', '.join(unknown)} (give "
            f"{'it' if len(unknown) == 1 else 'them'} a box of the plausible values, or a "
            f"start of the right magnitude)")
    return slo, shi


def _beyond_sampled(crit, found: tuple, sampled: tuple, box: tuple, fit: FitOptions, log=None):
    """``(x, f, lower, upper)``: the polished estimate ``found`` = ``(x, f,
    polish summary)`` polished again (L-BFGS-B, :func:`minimize_batched`)
    where it sits on an edge of the sampled region ``sampled`` that lies
    inside the box ``box`` (:func:`sampled_box`), that edge moved
    :data:`SAMPLED` times further out (within the box), at most
    :data:`WIDENINGS` times; kept where the NLL does not rise. The polish
    summary's ``nfev`` counts the extra runs."""
    x, f, pol = found
    slo, shi = (np.array(a, float) for a in sampled)
    lo, hi = box
    if not fit.polish or not np.isfinite(f):
        return x, f, slo, shi
    for _ in range(WIDENINGS):
        width = shi - slo
        low, high = _sampled_edges(x, (slo, shi), box)
        if not (low.any() or high.any()):
            break
        pos = lo >= 0.0
        for i in np.flatnonzero(low):
            slo[i] = max(lo[i], slo[i] / SAMPLED if pos[i] and slo[i] > 0 else
                         slo[i] - (SAMPLED - 1.0) * width[i])
        for i in np.flatnonzero(high):
            shi[i] = min(hi[i], shi[i] * SAMPLED if pos[i] and shi[i] > 0 else
                         shi[i] + (SAMPLED - 1.0) * width[i])
        if log:
            log("the estimate reached the edge of the sampled region of "
                + ", ".join(crit.params[i] for i in np.flatnonzero(low | high))
                + ": polishing again in a wider one")
        xp, fp, nfp, _msg = minimize_batched(crit, x, slo, shi, maxiter=fit.polish_maxiter)
        pol["nfev"] = pol.get("nfev", 0) + nfp
        if not fp <= f:
            break
        x, f = xp, fp
        pol["nll_after"] = fp
    return x, f, slo, shi


def _sampled_edges(x, sampled: tuple, box: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Masks (k,) of the coordinates of ``x`` on the lower and on the upper
    edge of the sampled region ``sampled`` (within 1e-6 of its width) where
    that edge lies inside the box ``box``."""
    (slo, shi), (lo, hi) = sampled, box
    width = shi - slo
    return ((x - slo <= 1e-6 * width) & (slo > lo),
            (shi - x <= 1e-6 * width) & (shi < hi))


def _search(crit, plan, fit: FitOptions, start, log):
    """``(optimizer result, x, f, polish summary, (lower, upper))``: the
    global search over the region the swarm samples (:func:`sampled_box`),
    the polish from its best point (:func:`_polish`), and again beyond that
    region's edges where the estimate reached them (:func:`_beyond_sampled`);
    ``(lower, upper)`` the region at the end (search coordinates)."""
    x_start = _start(crit, plan, start)
    if start is None or np.asarray(start).size == len(plan.params):
        with progress.phase("profiling the start's noise levels"):
            x_start = profiled_levels(crit, x_start, plan.lo, plan.hi, log)
    slo, shi = sampled_box(crit.model, plan, plan.lo, plan.hi, x_start, log)
    with progress.phase(search_text(fit, slo.size)):
        opt = _global_search(crit, slo, shi, fit, x_start)
    with progress.phase("polishing the search's best point (Fisher scoring, then L-BFGS-B)"):
        x_best, f_best, pol = _polish(crit, opt, slo, shi, fit)
    x_best, f_best, slo, shi = _beyond_sampled(crit, (x_best, f_best, pol), (slo, shi),
                                               (plan.lo, plan.hi), fit, log)
    return opt, x_best, f_best, pol, (slo, shi)


#: the moves (decades, log10) of each estimated noise level that
#: :func:`profiled_levels` tries at the start, then the thirds of a decade
#: about the best
LEVEL_DECADES = (-4.0, -3.0, -2.0, -1.0, 1.0, 2.0, 3.0, 4.0)
LEVEL_THIRDS = (-1.0 / 3.0, 1.0 / 3.0)


def profiled_levels(crit, x_start, lo, hi, log=None) -> np.ndarray:
    """The start ``x_start`` (search coordinates, k) with each estimated
    measurement-noise level (``noise.<output>``) moved to where the NLL at
    the start's parameters is least: decades (:data:`LEVEL_DECADES`) of each
    level alone, then the best of each level together, then thirds of a
    decade about it; the start is returned unchanged where nothing is
    better (or no level is estimated).

    A level that nothing declares starts from the record's second
    differences (:func:`bondgraph.inference.estimand.start_levels`), which
    show the sensor's noise, not the model's misfit: on a record that a
    model fits to 1 mm the start particle then sat at 8e-6 m, its NLL
    hundreds of times the model's best, and the swarm, which holds the
    start as a particle, could not use it (the EMPS pulses run refitted with
    the loop's model: the swarm's best NLL -39 084, the polish -135 671).
    The NLL is smooth and one-dimensional in each level (N log σ + S/σ²
    for a Gaussian innovation), so decades and their thirds find its
    minimum within a third of a decade. With the level profiled, the same
    refit (3 swarm iterations) ended at -146 529 in 52 s instead of
    -127 886 in 582 s (with :func:`_polish`'s scoring and the check of the
    start's discretisation against the profiled level,
    :func:`bondgraph.cli.estimate._chosen_at_start`). :func:`_polish`
    profiles the swarm's best the same way.

    Parameters
    ----------
    crit : EstimandCriterion or JointCriterion or Criterion
        The batched NLL (search coordinates; ``crit.log`` marks the levels,
        log of the std in output units).
    x_start : array (k,)
    lo, hi : arrays (k,)
        The box (search coordinates); a move beyond it stops on its edge.
    log : callable, optional
        One line when a level moves: from, to, and the NLL gained.

    Returns
    -------
    ndarray (k,)
    """
    x, f, f0 = _profiled(crit, x_start, lo, hi)
    moved = [j for j in range(x.size) if x[j] != x_start[j]]
    if log and moved:
        log("the start's noise levels, profiled at the start's parameters (decades, then "
            "thirds): " + ", ".join(f"{crit.params[j]} {np.exp(x_start[j]):.4g} -> "
                                    f"{np.exp(x[j]):.4g}" for j in moved)
            + f" (NLL {f0:.6g} -> {f:.6g})")
    return x


def _profiled(crit, x_start, lo, hi) -> tuple[np.ndarray, float, float]:
    """``(x, f, f0)``: :func:`profiled_levels`'s point, its NLL and the
    NLL at ``x_start`` (x is ``x_start`` where nothing is better)."""
    mask = getattr(crit, "log", None)
    x0 = np.asarray(x_start, float)
    if mask is None or not np.any(mask):
        return x0, np.nan, np.nan
    idx = np.flatnonzero(mask)
    ln10 = np.log(10.0)

    def moved(base, j, steps):
        out = []
        for d in steps:        # a move beyond the box stops on its edge
            x = base.copy()
            x[j] = min(max(base[j] + d * ln10, lo[j]), hi[j])
            if x[j] != base[j] and not any(x[j] == o[j] for o in out):
                out.append(x)
        return out

    X = [x0] + [x for j in idx for x in moved(x0, j, LEVEL_DECADES)]
    f = np.asarray(crit(np.array(X)), float)
    f0 = float(f[0])
    best = x0.copy()
    for j in idx:       # the best decade of each level alone (separable start)
        rows = [i for i, x in enumerate(X) if i == 0 or x[j] != x0[j]]
        i = min(rows, key=lambda r: f[r] if np.isfinite(f[r]) else np.inf)
        best[j] = X[i][j]
    X2 = [best] + [x for j in idx for x in moved(best, j, LEVEL_THIRDS)]
    f2 = np.asarray(crit(np.array(X2)), float)
    cands = X + X2
    fall = np.concatenate([f, f2])
    fall = np.where(np.isfinite(fall), fall, np.inf)
    i = int(np.argmin(fall))
    if not (np.isfinite(fall[i]) and (fall[i] < f0 or not np.isfinite(f0))):
        return x0, f0, f0
    return cands[i], float(fall[i]), f0


def start_levels_profiled(problem: Problem, params: Sequence[str], *,
                          x0_states: Sequence[str] = ()) -> np.ndarray:
    """The measurement-noise level (std, output units) of each output that
    an estimation of ``params`` on ``problem`` estimates, profiled at the
    start (the problem's θ and the noise policy's start levels) as the
    estimation's own start is (:func:`profiled_levels`): what a check of
    the discretisation at the start should measure its error against
    before the fit has a level of its own (the record's second differences
    show a quantised encoder's 1e-8 m where the model's one-step misfit is
    1e-3 m, and a check against the former asks for 16 RK4 substeps).

    Parameters
    ----------
    problem : Problem
    params : sequence of str
        The parameters the estimation moves (k).
    x0_states : sequence of str
        Initial states estimated with θ.

    Returns
    -------
    ndarray (n_y,)
        NaN where the estimation does not estimate the output's level (the
        record or the sensor declares it, or the "model" noise policy).

    Raises
    ------
    ModelError, OptionError
        As :func:`estimate` for unknown parameters or states.
    """
    model = problem.model
    out = np.full(model.n_y, np.nan)
    # the problem's fixed values (a sensitivity analysis at the truth) are
    # the point, not quantities withheld from the estimation
    free = [p for p in params if p not in problem.fixed]
    if not free:
        return out
    plan, crit = _joint([problem], free, None, None, x0_states, fit_options(None), None, None)
    try:
        if plan.est is None:
            return out
        x = profiled_levels(crit, _start(crit, plan, None), plan.lo, plan.hi)
        z = crit.to_value(x[None])[0]
    finally:
        crit.close()
    for j, n in enumerate(crit.params):
        if n.startswith(NOISE_PREFIX):
            out[model.output_index(n[len(NOISE_PREFIX):])] = z[j]
    return out


def search_text(fit: FitOptions, k: int) -> str:
    """What the global search of ``fit`` over ``k`` quantities does, in
    words (the :func:`bondgraph.core.progress.phase` that names it in a
    log): the optimizer, its population and its iterations."""
    S = _swarm_size(fit, k)
    if fit.optimizer == "pso":
        who = f"particle swarm, {S} particles"
    else:
        who = f"differential evolution, {max(1, S // k) * k} members"
    its = "its first population only" if fit.iterations == 0 else \
        f"up to {fit.iterations} iterations"
    return f"global search over {k} quantities ({who}, {its})"


def _global_search(crit, lo, hi, fit: FitOptions, start):
    """The optimizer's run (:func:`pso` or :func:`de`) over the box; its
    checkpoint carries the problem's fingerprint
    (:func:`bondgraph.inference.checkpoint.problem_fingerprint`), and long
    UKF passes show bars when ``fit.progress`` (:mod:`bondgraph.core.progress`).

    Raises
    ------
    EstimationError
        No evaluated parameter set had a finite NLL (the causes are listed).
    """
    S = _swarm_size(fit, lo.size)
    fp = problem_fingerprint(crit)
    with progress.enabled(fit.progress):
        if fit.optimizer == "pso":
            opt = pso(crit, lo, hi, swarm=fit.swarm(S), checkpointing=fit.checkpointing(fp),
                      progress=fit.progress, x0=start)
        else:
            opt = de(crit, lo, hi, evolution=fit.evolution(max(1, S // lo.size)),
                     checkpointing=fit.checkpointing(fp), progress=fit.progress, x0=start)
    if not np.isfinite(opt.fun):
        causes = ", ".join(f"{k}: {v}" for k, v in crit.failures.most_common()) or "none recorded"
        raise EstimationError(
            f"no finite NLL: all {opt.nfev} parameter sets evaluated for "
            f"{', '.join(crit.params)} of model '{crit.model.name}' failed (causes: {causes})",
            hint="check the search box (bounds), the prior x0/P0 and the record's units")
    return opt


def _polish(crit, opt, lo, hi, fit: FitOptions):
    """From the optimizer's best point: its noise levels profiled there
    (:func:`profiled_levels`), Fisher scoring (:func:`_scored`), then
    L-BFGS-B (:func:`minimize_batched`): ``(x, f, polish summary)``; each
    stage's point is kept only if it is not worse.

    A swarm's best may hold a level far above what its parameters leave
    (the swarm moves the levels as it moves the rest); towards the optimum
    the NLL's valley then narrows by orders of magnitude (a funnel: N log σ
    with σ the misfit), where L-BFGS-B's first step, the gradient projected
    onto the box, overshoots and its 50 iterations end far short: a mass on
    viscous friction, 4001 samples, stopped at NLL -11 073 (the level 0.016)
    against -40 371 (the sensor's 1e-5), which scoring reaches in 0.5 s
    from there (Gauss-Newton steps scaled by the Fisher information)."""
    x_best, f_best = opt.x.copy(), opt.fun
    pol: dict = {}
    if fit.polish and np.isfinite(f_best):
        xq, fq, _f0 = _profiled(crit, x_best, lo, hi)
        start, f_start = (xq, fq) if fq < f_best else (x_best, f_best)
        start, f_start, scored = _scored(crit, start, f_start, lo, hi)
        xp, fp, nfp, msg = minimize_batched(crit, start, lo, hi, maxiter=fit.polish_maxiter)
        if fp > f_start:
            xp, fp = start, f_start
        pol = dict(nfev=nfp, message=msg, nll_before=f_best, nll_after=fp, scoring=scored)
        if fp <= f_best:
            x_best, f_best = xp, fp
    return x_best, f_best, pol


#: iterations of the Fisher scoring of :func:`_polish`
SCORING_ITERATIONS = 30


def _scored(crit, x, f, lo, hi) -> tuple[np.ndarray, float, dict]:
    """``(x, f, summary)``: Levenberg-damped Fisher scoring
    (:func:`bondgraph.inference.fisher.estimand_scoring`; on several
    records :func:`~bondgraph.inference.fisher.joint_scoring`) from ``x``
    (search coordinates, NLL ``f``) within ``lo``/``hi``, kept where the
    criterion finds it lower; ``x``, ``f`` otherwise, and for what scoring
    does not cover (a given Q or R). The summary: the scoring's runs,
    iterations, whether it converged, the NLL after (empty when not run)."""
    members = list(getattr(crit, "members", [crit]))
    if any(m.Q is not None or m.R is not None for m in members):
        return x, f, {}
    estimand = isinstance(members[0], EstimandCriterion)
    if estimand:
        z0 = crit.to_value(x[None])[0]
        lo_v, hi_v = crit.to_value(lo[None])[0], crit.to_value(hi[None])[0]
        log_scale = members[0].log | ((lo_v > 0) & (hi_v > 100 * lo_v))
    else:
        lo_v, hi_v = np.asarray(lo, float), np.asarray(hi, float)
        log_scale = (lo_v > 0) & (hi_v > 100 * lo_v)
    records = [(m.model, m.t, m.u, m.y,
                m.est.at(z0) if estimand else
                Estimand(m.model, list(m.params), theta=m.theta(x[None])[0], x0=m.x0),
                m.P0, m.options) for m in members]
    options = ScoringOptions(max_iter=SCORING_ITERATIONS,
                             log_scale=tuple(bool(v) for v in log_scale), information=False)
    try:
        with np.errstate(all="ignore"):
            if len(records) == 1:
                mo, t, u, y, est, P0, opts = records[0]
                r = estimand_scoring(mo, t, u, y, est, lo_v, hi_v, P0, options=opts,
                                     scoring=options)
            else:
                r = joint_scoring(records, lo_v, hi_v, scoring=options)
    except (FloatingPointError, np.linalg.LinAlgError, NumericalError):
        return x, f, {}
    z = r.estimand.value()
    xs = np.clip(crit.to_search(z[None])[0] if estimand else z, lo, hi)
    fs = float(crit(xs[None])[0])
    summary = dict(runs=int(r.runs), iterations=int(r.iterations), converged=bool(r.converged),
                   nll_after=fs)
    if np.isfinite(fs) and fs < f:
        return xs, fs, summary
    return x, f, summary


def _at_bound(params, x, lo, hi) -> list[str]:
    """Parameters whose estimate is within 1e-6 of a bound, relative to the
    smaller of the box's width and the magnitude there (the estimate's or
    the bound's): a box far wider than the value carries no scale (a mass
    of 5.5e-6 s² in a user's box (0, 1e9) is not "at" 0)."""
    near_lo, near_hi = near_bound(x, lo, hi)
    return [p for i, p in enumerate(params) if near_lo[i] or near_hi[i]]


def _bound_warnings(params, x, lo, hi, sampled: tuple | None = None) -> list[str]:
    """The warnings of an estimate ``x`` on the bound of its box ``lo``,
    ``hi``, and (``sampled``, the region of :func:`sampled_box` at the end)
    on an edge of that region inside the box, which the polish could not
    widen further: not a minimum either."""
    out = []
    at_bound = _at_bound(params, x, lo, hi)
    if at_bound:
        out.append(f"estimate at the bound of the search box for {', '.join(at_bound)}; "
                   f"the Cramér-Rao bound does not apply there")
    if sampled is not None:
        low, high = _sampled_edges(x, sampled, (lo, hi))
        edge = [params[i] for i in np.flatnonzero(low | high)]
        if edge:
            out.append(f"estimate on the edge of the region the swarm sampled for "
                       f"{', '.join(edge)} (inside the box, widened {WIDENINGS} times): not a "
                       f"minimum, the Cramér-Rao bound does not apply; give "
                       f"{'it' if len(edge) == 1 else 'them'} a box of the plausible values")
    return out


def _hessian_at(crit, x_best, f_best, lo, hi, fit: FitOptions, warn_list: list,
                scale_box: tuple | None = None):
    """Hessian of the NLL and Cramér-Rao bounds at the estimate, and the
    robust std (:func:`_robust_at`).

    A first pass with steps of 1e-4 of the parameter (or box) scale; when it
    is positive definite, a second pass with steps of 0.1 standard deviation,
    where the NLL changes by O(0.01) nats (truncation and rounding balanced).
    Appends the warnings to ``warn_list``. ``scale_box`` (lower, upper):
    the region whose widths scale the coordinates (default the box ``lo``,
    ``hi``; the sampled region of :func:`sampled_box`: a box of ±1e9 made
    every other direction look flat beside it).
    """
    k = x_best.size
    H = np.full((k, k), np.nan)
    cr = dict(std=np.full(k, np.nan), corr=np.full((k, k), np.nan), warning=None)
    if not np.isfinite(f_best):
        warn_list.append("no finite NLL found: every evaluated parameter set failed "
                         f"({dict(crit.failures)})")
        return H, cr
    if not fit.hessian:
        return H, cr
    width = hi - lo if scale_box is None else scale_box[1] - scale_box[0]
    mag = np.where(np.abs(x_best) > 0, np.abs(x_best), width)
    H, _, _ = hessian_batched(crit, x_best, 1e-4 * np.minimum(mag, width))
    cr = cramer_rao(H, crit.params, width, conditional=True, theta=x_best)
    if cr["positive_definite"]:
        h2 = np.clip(0.1 * cr["std"], 1e-8 * mag, 0.05 * width)
        H2, _, _ = hessian_batched(crit, x_best, h2)
        cr2 = cramer_rao(H2, crit.params, width)
        if cr2["positive_definite"]:
            H, cr = H2, cr2
    else:
        _on_box(cr, H, width, crit.params, _at_bound(crit.params, x_best, lo, hi))
    if cr["warning"]:
        warn_list.append(cr["warning"])
    _robust_at(crit, x_best, H, cr, warn_list)
    return H, cr


def _robust_at(crit, x_best: np.ndarray, H: np.ndarray, cr: dict, warn_list: list) -> None:
    """The robust (sandwich) std of the estimate, ``cr["std_robust"]`` (k,),
    search coordinates (:mod:`bondgraph.inference.robust`: H⁻¹ J H⁻¹, J the
    Newey-West covariance of the per-sample scores, summed over the
    records), from one stored batched run per record of the estimate and
    its k nudges of 0.1 Cramér-Rao std. Not computed (None) when the
    Hessian is not positive definite or a run fails. Appends a warning when
    it exceeds the Cramér-Rao std by more than :data:`ROBUST_RATIO`."""
    cr["std_robust"] = None
    if not cr.get("positive_definite"):
        return
    std = np.asarray(cr["std"], float)
    h = np.where(std > 0, 0.1 * std, 1e-8)
    X = np.repeat(x_best[None, :], x_best.size + 1, axis=0)
    X[1:] += np.diag(h)
    J = np.zeros((x_best.size, x_best.size))
    for member in getattr(crit, "members", [crit]):
        r = member.run(X, store=True)
        if not np.isfinite(r.nll).all():
            return
        J += score_covariance(step_scores(*innovation_differences(r, h)))
    C = sandwich(H, J)
    if C is None:
        return
    robust = np.sqrt(np.maximum(np.diag(C), 0.0))
    cr["std_robust"] = robust
    ratio = robust / np.where(std > 0, std, np.inf)
    loose = [f"{crit.params[i]} ({ratio[i]:.3g}x)" for i in np.argsort(-ratio)
             if ratio[i] > ROBUST_RATIO]
    if loose:
        warn_list.append(
            f"the Cramér-Rao std understates the uncertainty of {', '.join(loose)}: the robust "
            f"(sandwich) std is that many times larger. The innovations are serially "
            f"correlated: the model lacks an effect, or its noise levels do not describe the "
            f"misfit (White 1982). Quote the robust std (column 'robust std'); "
            f"`bondgraph loop` looks for the missing effect")


def _on_box(cr: dict, H: np.ndarray, width: np.ndarray, names, held: list[str]) -> None:
    """When the Hessian ``H`` (k, k) is not positive definite and the
    parameters ``held`` sit on their box: the others' Cramér-Rao bounds
    conditional on those held there, from the others' block of ``H`` when
    it is positive definite (an active bound: the estimate does not move
    along it, and the difference Hessian there reads the NLL beyond the box,
    where its slope is not zero). Unless :func:`cramer_rao` found
    conditional bounds already; fills ``cr`` in place, its warning then
    naming the bound as the cause."""
    if not held or cr.get("conditional_on") or cr["warning"] is None:
        return
    free = np.array([i for i, n in enumerate(names) if n not in held], dtype=int)
    if free.size == 0:
        return
    sub = cramer_rao(H[np.ix_(free, free)], [names[i] for i in free], width[free])
    if not sub["positive_definite"]:
        return
    cr["std"][free] = sub["std"]
    cr["cov"][np.ix_(free, free)] = sub["cov"]
    cr["corr"][np.ix_(free, free)] = sub["corr"]
    cr["conditional_on"] = list(held)
    names_ = ", ".join(held)
    its = "its" if len(held) == 1 else "their"
    cr["warning"] = (f"Hessian of the NLL is not positive definite, and positive definite without "
                     f"{names_} on {its} bound (the NLL still falls beyond the box there, so its "
                     f"curvature says nothing of {names_}): the Cramér-Rao std of the others are "
                     f"conditional on {names_} held on {its} bound")


def _discretisation_at(crit, x_best, f_best, fit: FitOptions, ukf: UKFOptions,
                       warn_list: list, floor: dict | None = None) -> dict | None:
    """:func:`discretisation_check` at the estimate (summary dict, or None);
    a warning above 0.1 measurement-noise standard deviations per sample
    naming the step as the cause and the cheapest discretisation within
    (:func:`bondgraph.inference.discretise.choose_discretisation` with the
    filter's hold and noise levels); a warning when the filter's hold
    contradicts what the record supports (:func:`hold_warning`); the NLL
    guard's (:func:`nll_guard`). ``floor``: the outputs whose
    measurement-noise level sits on the lower bound of its box
    (:func:`_levels_on_floor`); where the worst one is such an output, the
    warning gives the error in the output's unit and the sensor noise it
    would be within for, not a step chosen against the box's level."""
    if not (fit.check_discretisation and np.isfinite(f_best)):
        return None
    if isinstance(crit, JointCriterion):
        return _joint_discretisation_at(crit, x_best, fit, warn_list, floor)
    th_best, x0, P0, R = crit.problem_at(x_best)
    # the filter's levels at the estimate (estimated or declared), else
    # meas_std(θ), else the level seen in the record
    sigma = None if R is None else np.sqrt(np.diagonal(np.asarray(R, float)).reshape(-1))
    try:
        sigma = comparison_sigma(crit.problem, th_best, sigma)
    except OptionError:
        pass
    dc = discretisation_check(crit.model, crit.t, crit.u, th_best, x0, ukf.discretisation,
                              sigma=sigma, states=lambda: crit.problem.filtered_states(th_best))
    worst = float(np.max(dc["one_step"]))
    hold = hold_warning(crit.problem, ukf.hold)
    if hold:
        warn_list.append(hold)
    if worst > 0.1:
        j = int(np.argmax(dc["one_step"]))
        if floor and j in floor and sigma is not None:
            warn_list.append(_floor_message(crit.model, ukf, worst, float(sigma[j]), j,
                                            floor[j]))
        else:
            warn_list.append(_step_message(crit.problem, th_best, ukf, worst, sigma))
    elif no_process_noise(crit.model, th_best):
        _, _, bound = check_discretisation(crit.problem, th_best, ukf.discretisation,
                                           sigma=sigma, free_run=True)
        if bound > BIAS_TOLERANCE:
            warn_list.append(_step_message(crit.problem, th_best, ukf, worst, sigma, bound))
    guard = nll_guard(crit.model, crit.t, crit.u, crit.y, th_best, x0, P0,
                      options=ukf, Q=crit.Q, R=R, nll=f_best)
    if not guard["ok"]:
        warn_list.append(_guard_message(guard, ukf))
    return dict(one_step=dc["one_step"].tolist(), free_run=dc["free_run"].tolist(),
                reference=dc["reference"], nll_guard=guard)


def _joint_discretisation_at(crit: JointCriterion, x_best, fit: FitOptions,
                             warn_list: list, floor: dict | None = None) -> dict:
    """:func:`_discretisation_at` on each record of a joint estimate, at its
    own NLL there: ``{"records": {name: summary}}``; each warning prefixed
    with its record's name."""
    names = record_names([m.problem for m in crit.members])
    out = {}
    for name, m in zip(names, crit.members):
        own: list = []
        f = float(m(np.atleast_2d(x_best))[0])
        out[name] = _discretisation_at(m, x_best, f, fit, m.options, own, floor)
        warn_list.extend(f"{name}: {w}" for w in own)
    return dict(records=out)


def _floor_message(model, ukf: UKFOptions, worst: float, sigma: float, j: int,
                   level: str) -> str:
    """The warning of a discretisation error above 0.1 σ per sample where σ
    is a level ``level`` on the lower bound of its box (output ``j``): the
    process noise explains the record, so σ says nothing of the sensor;
    the error in the output's unit, the sensor noise it is within 0.1 std
    of, and the option that lets the step be chosen against the sensor."""
    err, unit = worst * sigma, model.output_units[j]
    return (f"discretisation error of {ukf.method}({ukf.substeps}) with the {ukf.hold} hold is "
            f"{err:.2g} {unit} per sample on {model.outputs[j]} at the estimate, {worst:.2g} "
            f"times its noise level {level} = {sigma:.2g} {unit}, which sits on the lower bound "
            f"of its box: the process noise explains the record, and the box, not the record, "
            f"sets that level. The step is within 0.1 noise std for a sensor noise of "
            f"{10 * err:.2g} {unit} or more; hold the level at the sensor's known noise "
            f"(--fixed {level}=VALUE) to have the step checked and chosen against it")


def _step_message(problem: Problem, theta, ukf: UKFOptions, worst: float, sigma,
                  bound: float | None = None) -> str:
    """The warning of a discretisation error above 0.1 σ per sample (or, with
    ``bound``, of a free run whose error may bias an estimate by more than
    :data:`BIAS_TOLERANCE` std): the step is the cause (the check's
    reference holds the input alike); the fix is the cheapest method and
    substeps within, with the filter's hold."""
    what = (step_error(ukf.method, worst, "measurement-noise standard deviations per sample")
            if bound is None else f"{worst:.2g} measurement-noise standard deviations per sample, but without "
                 f"process noise the filter predicts by the free run, whose error may bias an "
                 f"estimate by up to {bound:.2g} Cramér-Rao standard deviations")
    text = (f"discretisation error of {ukf.method}({ukf.substeps}) with the {ukf.hold} hold is "
            f"{what} at the estimate: the step is too coarse, a model error that biases the "
            f"estimate; ")
    try:
        adv = choose_discretisation(problem, theta, given={"hold": ukf.hold}, sigma=sigma)
    except OptionError:
        adv = None
    if adv is None or not adv.ok:
        return text + (f"no method within {TOLERANCE:g} σ up to 16 substeps: use method='rk4' "
                       f"with more substeps (--method rk4 --substeps N)")
    d = adv.disc
    return text + (f"{d.method}({d.substeps}) is within ({adv.error:.2g} σ): use "
                   f"method='{d.method}', substeps={d.substeps} (--method {d.method} "
                   f"--substeps {d.substeps}, or leave --method/--substeps/--hold out to have "
                   f"them chosen)")


def hold_warning(problem: Problem, hold: str) -> str | None:
    """A warning when the filter's input ``hold`` contradicts the hold the
    record supports (its declarations, else its inputs' shape:
    :func:`bondgraph.inference.discretise.input_holds`), naming the cause and
    the option that fixes it; None when they agree or no input changes.

    The discretisation check and the NLL guard cannot see a wrong hold (their
    references hold the inputs alike), so this is the only warning of it.

    Parameters
    ----------
    problem : Problem
    hold : str
        The filter's hold, one name or one per input (``"mean"`` counts as
        an interpolating hold).

    Returns
    -------
    str or None
    """
    names = problem.model.inputs
    inputs = record_input_holds(problem.record, names, problem.u)
    against = holds_against(inputs, hold)
    if not against:
        return None
    support, _ = supported_hold(inputs)
    fix = f"use hold='{support}' (--hold {support}, or leave --hold out to have it chosen)"
    lagged = [h for h in against if h.hold == "linear"]
    if lagged:
        return (f"the filter holds {', '.join(h.name for h in lagged)} zoh, but "
                f"{'; '.join(h.describe() for h in against)}: the zero-order hold lags such an "
                f"input by half a sample, a model error that biases the estimate and that "
                f"neither the discretisation check nor the NLL guard can see (their references "
                f"hold the input alike); {fix}")
    return (f"the filter interpolates {', '.join(h.name for h in against)} ({hold}), but "
            f"{'; '.join(h.describe() for h in against)}: that hold spreads each step of a "
            f"held input over the sample before it, a model error that biases the estimate "
            f"and that neither the discretisation check nor the NLL guard can see; {fix}")


def _guard_message(guard: dict, ukf: UKFOptions) -> str:
    """The warning of the NLL discretisation guard (:func:`nll_guard`): the
    step is the cause (the reference holds the inputs as the filter does)."""
    if not np.isfinite(guard["nll_reference"]):
        return (f"the {guard['reference']} reference of the NLL failed at the estimate (NLL "
                f"{guard['nll']:.10g} with {ukf.method}({ukf.substeps})): the discretisation "
                f"could not be checked")
    need = (f"{ukf.method} needs {guard['substeps_needed']} substeps to agree (--substeps "
            f"{guard['substeps_needed']})"
            if guard["substeps_needed"] else
            f"{ukf.method} does not agree even with {GUARD_SUBSTEPS} substeps (use "
            f"{guard['reference']}: --method {guard['reference'].split('(')[0]} --substeps "
            f"{GUARD_SUBSTEPS})")
    return (f"NLL at the estimate with {ukf.method}({ukf.substeps}) and the {ukf.hold} hold is "
            f"{guard['nll']:.10g}, {guard['rel_diff']:.2g} relative from the "
            f"{guard['reference']} reference {guard['nll_reference']:.10g} with the same hold "
            f"(> {GUARD_REL:g}): the step; {need}")


def _truth(meta, params, x, std):
    """True values of the estimated parameters (synthetic records) and
    z = (estimate − truth) / std; ``(None, None)`` without truth."""
    tp = meta.get("true_parameters") if isinstance(meta, Mapping) else None
    if not tp:
        return None, None
    truth = {p: float(tp[p]) for p in params if p in tp}
    if not truth:
        return truth, None
    z = np.array([(x[i] - truth[p]) / std[i] if p in truth else np.nan
                  for i, p in enumerate(params)])
    return truth, z


# ---------------------------------------------------------------- two stages
@dataclass
class Stage:
    """One stage of a multi-stage estimation.

    Parameters
    ----------
    name : str
    problem : Problem
        This stage's model on its record, with its prior and filter options
        (:func:`bondgraph.inference.problem.make_problem`); the values the
        earlier stages estimated are fixed on it by :func:`two_stage`.
    params : list of str
    fit : FitOptions, optional
        This stage's search options (default: those given to :func:`two_stage`).
    Q, R, bounds, start : optional
        As for :func:`estimate`.
    """

    name: str
    problem: Problem
    params: list
    fit: FitOptions | None = None
    Q: Any = None
    R: Any = None
    bounds: Mapping | None = None
    start: Any = None


def two_stage(stages: Sequence[Stage], *, fixed: Mapping[str, float] | None = None,
              propagate: bool = True, fit: FitOptions | None = None) -> list[EstimationResult]:
    """Run stages in order; each fixes what the earlier stages estimated.

    Parameters
    ----------
    stages : sequence of Stage
        Typically two: the coast-down parameters with the reduced model on
        the coast-down record, then the drive-line parameters with the full
        model on a driving record (Auby 2016).
    fixed : dict, optional
        Values fixed in every stage (where the stage's model has them).
    propagate : bool
        Propagate the uncertainty of the carried estimates into each later
        stage (see Notes); sets ``result.std_total``, and ``result.z`` uses it.
    fit : FitOptions, optional
        Search options of every stage that does not set its own.

    Returns
    -------
    list of EstimationResult
        One per stage; ``result.fixed`` shows what each stage held fixed.

    Notes
    -----
    A later stage's Cramér-Rao bound ``std`` is conditional on the fixed
    values of the earlier stages. Their estimation errors δθ₁ shift the
    later estimate by G δθ₁ with G = −H₂₂⁻¹ H₂₁, the mixed second derivatives
    of the later stage's NLL (implicit-function theorem; the two-step
    estimator covariance of Murphy & Topel 1985). So
    ``cov_total = H₂₂⁻¹ + G Σ₁ Gᵀ`` with Σ₁ the covariance of the carried
    estimates. Ignoring this term makes the second stage look biased by
    several standard deviations even on synthetic data (tests/test_estimate.py).
    """
    carried: dict[str, float] = dict(fixed or {})
    cov_all: dict[tuple[str, str], float] = {}
    out = []
    for st in stages:
        model = st.problem.model
        fx = {p: v for p, v in carried.items() if p in model.params and p not in st.params}
        problem = st.problem.with_fixed(fx)
        res = estimate(problem, st.params, fit=st.fit if st.fit is not None else fit,
                       bounds=st.bounds, Q=st.Q, R=st.R, start=st.start)
        res.settings["stage"] = st.name
        prop = [p for p in fx if (p, p) in cov_all]
        if propagate and prop and np.isfinite(res.std).all():
            _propagate(problem, st, res, prop, cov_all)
        # covariance of this stage's estimates (total if propagated)
        cov = res.propagated.get("cov_total") if res.propagated else None
        cov = np.asarray(cov) if cov is not None else (
            np.outer(res.std, res.std) * res.corr if np.isfinite(res.std).all() else None)
        if cov is not None:
            for i, a_ in enumerate(res.params):
                for j, b_ in enumerate(res.params):
                    cov_all[(a_, b_)] = float(cov[i, j])
        out.append(res)
        carried.update(res.estimate_dict())
    return out


def _propagate(problem: Problem, st: Stage, res, prop, cov_all):
    """Add the carried parameters' covariance to a stage's Cramér-Rao bound."""
    model = problem.model
    names = list(res.params) + list(prop)
    crit = Criterion(problem, names, res.theta, Q=st.Q, R=st.R)
    x = res.theta[model.param_indices(names)]
    S1 = np.array([[cov_all[(a, b)] for b in prop] for a in prop])
    h = np.concatenate([0.1 * res.std, 0.1 * np.sqrt(np.diag(S1))])
    H, _, _ = hessian_batched(crit, x, h)
    k2 = len(res.params)
    H22, H21 = H[:k2, :k2], H[:k2, k2:]
    if not np.isfinite(H).all():
        res.warnings.append("uncertainty of the fixed parameters not propagated: the mixed "
                            "Hessian is not finite")
        return
    G = -np.linalg.solve(H22, H21)
    cov_total = np.linalg.inv(H22) + G @ S1 @ G.T
    std_total = np.sqrt(np.diag(cov_total))
    res.std_total = std_total
    res.propagated = dict(from_params=list(prop), sensitivity=G.tolist(),
                          cov_total=cov_total.tolist(), evaluations=int(crit.evaluations))
    res.evaluations_total += int(crit.evaluations)
    if res.truth:
        res.z = np.array([(res.estimates[i] - res.truth[p]) / std_total[i] if p in res.truth
                          else np.nan for i, p in enumerate(res.params)])
