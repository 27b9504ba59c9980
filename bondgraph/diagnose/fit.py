"""Fitting one model of the loop: the :class:`Fit` record, the UKF prior
(x0/P0 policy), the warm-started maximum-likelihood fit (Fisher scoring,
L-BFGS-B if it fails), the free-run simulation, Cramér-Rao standard
deviations and the detection of noise-intensity parameters.

The likelihood is the batched UKF's (Wan & van der Merwe 2000); the fit is
Levenberg-damped Fisher scoring on it (Rao 1973, §5g; Cramér 1946 and Rao
1945 for the bound), all through :mod:`bondgraph.diagnose.inference_calls`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from bondgraph.core.deferred import chi2
from bondgraph.core.domains import continued_share, dpow
from bondgraph.core.graph import BondGraph
from bondgraph.diagnose.inference_calls import (
    FINE_SUBSTEPS,
    fine_free_run,
    FLAT_GAIN,
    flat_directions,
    NOISE_BOX,
    NoiseSpec,
    Problem,
    fisher_fit,
    noise_box,
    hessian_cramer_rao,
    interval_errors,
    lbfgsb_polish,
    lr_scale,
    make_criterion,
    make_problem,
    moves_meas_std,
    no_process_noise,
    noise_parameters,
    plan_noise,
    step_errors,
    relative_direction,
    robust_std,
    run_ukf,
    smoothed_initial_state,
)
from bondgraph.diagnose.metric import compute_metric, metric_errors, nrmse
from bondgraph.diagnose.residuals import analyze
from bondgraph.diagnose.result import FitSummary
from bondgraph.diagnose.settings import LoopSettings
from bondgraph.errors import BondGraphError, NumericalError, SmootherRestartError
from bondgraph.inference.discretise import (BIAS_TOLERANCE, REFINE_MARGIN, SUBSTEPS, refined_runs,
                                            step_cost)
from bondgraph.inference.fisher import near_bound
from bondgraph.inference.options import Discretisation, most_substeps
from bondgraph.core.equations import derive
from bondgraph.numerics.admissible import Admissibility, check_admissible, without_inherited
from bondgraph.numerics.model import Model
from bondgraph.numerics.integrators import hold_inputs, join_hold, make_step, split_hold
from bondgraph.numerics.simulate import simulate

#: generated functions of every model the loop builds
CANDIDATE_FUNCTIONS = ("f", "h", "dfdx", "f_dfdx")
#: those generated only when first used (most candidates run on their
#: compiled kernels and never need the numpy Jacobians)
LAZY_FUNCTIONS = ("dfdx", "f_dfdx")


class MetricRecord:
    """The measured record as a user metric sees it (``metric(fit, data)``,
    ``data`` this view), resolved for one model at a time.

    Attributes
    ----------
    exp : Experiment
        The record (:class:`bondgraph.data.records.Experiment`).
    """

    def __init__(self, experiment):
        self.exp = experiment

    @property
    def name(self) -> str | None:
        """The record's name (None if it has none)."""
        return getattr(self.exp, "name", None)

    def arrays(self, model: Model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Times t (N,) [s], inputs u (N, n_u) and measured outputs y (N, n_y)
        in the order and units of ``model`` (inputs the record lacks at their
        defaults; NaN where an output is missing)."""
        t = np.asarray(self.exp.t, dtype=float)
        u = self.exp.inputs_for(model, defaults_ok=True) if model.n_u else np.zeros((t.size, 0))
        y = self.exp.outputs_for(model)
        return t, u, y


@dataclass
class Context:
    """What every step of the loop reads: the problem (the declared model
    bound to the estimation record, with the prior, the held noise levels
    and the filter's options, conditioned on what the loop has learned: a
    :class:`~bondgraph.inference.problem.Problem`, replaced, never changed),
    the search options (never changed), the (time-stamped) line logger,
    whether progress bars are shown, a cache of the problems of the other
    models seen (their arrays and priors), and the executor the candidates'
    scoring and confirmations run on (None: in process;
    :mod:`bondgraph.diagnose.parallel`)."""

    problem: Problem | None
    settings: LoopSettings
    log: Callable[[str], None] = print
    progress: bool = True
    cache: dict = field(default_factory=dict)
    executor: Any = None
    said: set = field(default_factory=set)

    def log_once(self, kind: str, msg: str) -> None:
        """Log ``msg`` the first time a message of ``kind`` comes, saying
        that later ones are not logged; nothing after that (a message that
        every refit repeats, whose first instance says what the user needs)."""
        if kind in self.said:
            return
        self.said.add(kind)
        self.log(f"{msg} (said once: the like is not logged again)")

    @property
    def record(self) -> MetricRecord:
        """The estimation record as a user metric sees it (:class:`MetricRecord`)."""
        return MetricRecord(self.problem.record)

    @classmethod
    def on(cls, experiment, settings: LoopSettings, model: Model,
           log: Callable[[str], None] = print, progress: bool = True) -> "Context":
        """A context for ``model`` on ``experiment`` with the loop's options
        (:func:`loop_problem`; the noise policy not planned: no level held
        beyond the model's own), for running the loop's steps one by one."""
        return cls(loop_problem(model, experiment, settings), settings, log, progress)


@dataclass
class Fit:
    """A fitted model: graph, generated model, estimated names, full θ
    (n_theta,), NLL, stored UKF run, residual report, metric value, free-run
    outputs (N, n_y) or None, Cramér-Rao std by name (None for an estimate
    at a bound), number of scalar observations; the estimates on a bound of
    their box (``at_bound``), whether the scoring converged and in how many
    iterations (None: not fitted by scoring), the free-run error on the
    validation record (None without one), and the per-sample standardised
    free-run errors (N, n_y) of the record and of the validation record
    (:func:`~bondgraph.diagnose.metric.metric_errors`; None if the free
    run failed or there is no validation record), and the measurement-noise
    stds estimated with θ by output (``noise_est``; their Cramér-Rao std in
    ``std`` as ``noise.<output>``), and why the model does not simulate
    (``unstable``: its free run fails or leaves the plausible range on the
    record or on the validation record, :func:`free_run_trouble`; None when
    it simulates on both), and warnings about the fit that the report
    carries (``warnings``: a declared parameter on its box and what the box
    costs), and the quantities along which the likelihood is flat where
    the scoring stopped, converged in every other direction (``flat``,
    :attr:`bondgraph.inference.fisher.Scoring.flat`), and, for the loop's
    final model and for a refit whose identification the accept rule judges
    by it (:func:`bondgraph.diagnose.accept.robust_std_needed`), the robust
    (sandwich) std by name (``std_robust``, :func:`robust_std_of`)."""

    graph: BondGraph
    model: Model
    params: list[str]
    theta: np.ndarray
    nll: float
    ukf: Any
    residuals: Any
    metric: float
    sim_y: np.ndarray | None
    std: dict = field(default_factory=dict)
    n_obs: int = 0
    at_bound: list = field(default_factory=list)
    x0_est: dict = field(default_factory=dict)
    converged: bool | None = None
    iterations: int | None = None
    validation_metric: float | None = None
    sim_errors: np.ndarray | None = None
    validation_errors: np.ndarray | None = None
    #: the free run on the validation record (N_v, n_y), None without one or where it failed
    validation_sim_y: np.ndarray | None = None
    #: the free-run error on each further validation record
    #: (``settings.more_validation``), record name -> error
    more_metrics: dict = field(default_factory=dict)
    #: ... and its per-sample standardised errors (N_r, n_y), None where the free run failed
    more_errors: dict = field(default_factory=dict)
    #: ... and the free run's outputs (N_r, n_y), None where it failed
    more_sim_y: dict = field(default_factory=dict)
    noise_est: dict = field(default_factory=dict)
    unstable: str | None = None
    warnings: list = field(default_factory=list)
    flat: tuple = ()
    std_robust: dict = field(default_factory=dict)
    #: the unidentified combination as relative changes when it is a scale
    #: symmetry (:func:`ridge_changes`: "; as relative changes: ms +1.00, ..."), else ""
    ridge: str = ""
    #: the discretisation the fit was made at where it is not the loop's (a
    #: confirmation refitted at a step stable for its law,
    #: :func:`bondgraph.diagnose.confirm.stable_refit`); None: the loop's.
    #: What is computed again at the fit (:func:`fit_context`) uses it.
    step: Any = None

    @property
    def k(self) -> int:
        """Number of estimated parameters."""
        return len(self.params)

    def aic(self) -> float:
        """Akaike's criterion 2 NLL + 2k (Akaike 1974)."""
        return 2 * self.nll + 2 * self.k

    def bic(self) -> float:
        """Schwarz's criterion 2 NLL + k log n (Schwarz 1978)."""
        return 2 * self.nll + self.k * math.log(max(self.n_obs, 1))

    def information(self, criterion: str) -> float:
        """:meth:`bic` if ``criterion`` is ``"bic"``, else :meth:`aic`."""
        return self.bic() if criterion == "bic" else self.aic()

    def estimates(self) -> dict:
        """Estimated parameters, name -> value."""
        return {n: float(self.theta[self.model.param_index(n)]) for n in self.params}

    def summary(self) -> FitSummary:
        """The fit as a report sees it (:class:`FitSummary`)."""
        S = self.ukf.S[:, 0, :, :]
        return FitSummary(self.graph.name, self.nll, self.aic(), self.bic(), self.metric,
                          self.residuals.whiteness, self.estimates(), dict(self.std),
                          self.residuals, self.sim_y, self.ukf.innovations[:, 0, :],
                          np.diagonal(S, axis1=1, axis2=2).copy(), list(self.at_bound),
                          self.validation_metric, dict(self.x0_est), dict(self.noise_est),
                          list(self.flat), dict(self.std_robust), self.ridge,
                          self.validation_sim_y,
                          process_noise_at_floor(self.model, list(self.at_bound), self.theta),
                          dict(self.more_metrics), dict(self.more_sim_y))

    @property
    def accept_metric(self) -> float:
        """The error the accept decision compares: the validation error if
        there is a validation record, else the record's free-run error."""
        return self.metric if self.validation_metric is None else self.validation_metric

    @property
    def accept_errors(self) -> np.ndarray | None:
        """The per-sample standardised free-run errors (N, n_y) behind
        :attr:`accept_metric` (validation record if any, else the record)."""
        return self.sim_errors if self.validation_metric is None else self.validation_errors


# ----------------------------------------------------------------- models
def model_of(graph: BondGraph) -> Model:
    """Generate the model of one of the loop's graphs (in memory)."""
    return Model.from_graph(graph, functions=CANDIDATE_FUNCTIONS, name=f"_loop_{graph.name}",
                            lazy=LAZY_FUNCTIONS)


def loop_problem(model: Model, experiment, settings: LoopSettings,
                 noise: NoiseSpec | None = None) -> Problem:
    """The declared model bound to the estimation record with the loop's
    prior, noise levels, fixed values and filter options
    (:func:`bondgraph.inference.problem.make_problem`; inputs the record
    lacks at the model's defaults)."""
    return make_problem(model, experiment, prior=settings.prior,
                        noise=NoiseSpec(settings.noise) if noise is None else noise,
                        ukf=settings.ukf, fixed=settings.fixed, defaults_ok=True)


def at_step(ctx: Context, disc) -> Context:
    """``ctx`` with its problem filtered at the discretisation ``disc`` (a
    :class:`~bondgraph.inference.options.Discretisation`) and a cache of its
    own: where a fit, a confirmation or a candidate's scoring runs at a step
    other than the loop's (:func:`fit_context`,
    :func:`bondgraph.diagnose.confirm.stable_context`,
    :func:`bondgraph.diagnose.scoring.finer_if_failed`)."""
    return replace(ctx, problem=ctx.problem.conditioned_on(disc=disc), cache={})


def fit_context(ctx: Context, fit: Fit) -> Context:
    """``ctx``, or, where ``fit`` was made at another discretisation than the
    loop's (``fit.step``: a confirmation refitted at a step stable for its
    law), ``ctx`` with that step (cached in ``ctx.cache`` per step): what is
    computed again at the fit (its robust std and scores, the scores of a
    pair's partner given it) is computed where its filter is stable, not at
    the loop's step, where the law's fast mode makes the likelihood rough
    (:func:`bondgraph.diagnose.confirm.stable_context`)."""
    step = getattr(fit, "step", None)
    if step is None or step == ctx.problem.disc:
        return ctx
    hit = ctx.cache.get(("fit_step", step))
    if hit is not None and hit[0] is ctx.problem:
        return hit[1]
    sub = at_step(ctx, step)
    ctx.cache[("fit_step", step)] = (ctx.problem, sub)
    return sub


def problem_for(ctx: Context, model: Model) -> Problem:
    """The loop's problem (``ctx.problem``) for ``model``: the same record,
    prior, noise levels, fixed values and options (:meth:`Problem.with_model`,
    cached per model, :func:`_cached`)."""
    base = ctx.problem
    if model is base.model:
        return base
    return _cached(ctx, ("problem", model), base, lambda: base.with_model(model))


def validation_problem(ctx: Context, problem: Problem, which: int = 0) -> Problem:
    """``problem`` on the validation record (``settings.validation``; with
    ``which`` = i > 0 the i-th of ``settings.more_validation``): its own
    initial state, the loop's covariance policy (:meth:`Problem.on_record`;
    cached per model and record, :func:`_cached`). A candidate's problem
    inherits the state scales of the loop's problem on that record, as it
    does on the estimation record (:meth:`Problem.with_model`)."""
    base = ctx.problem
    record = validation_records(ctx.settings)[which]

    def build() -> Problem:
        if problem.model is base.model:
            return problem.on_record(record)
        return problem.on_record(record, validation_problem(ctx, base, which).scales)

    return _cached(ctx, (f"validation{which or ''}", problem.model), problem, build)


def validation_records(settings) -> list:
    """The records that judge the accept decision: ``settings.validation``
    and then ``settings.more_validation`` (empty without a validation record)."""
    if getattr(settings, "validation", None) is None:
        return []
    return [settings.validation, *getattr(settings, "more_validation", ())]


def _cached(ctx: Context, key: tuple, base: Problem, build) -> Problem:
    """The problem ``build()`` derived from ``base``, cached in ``ctx.cache``
    under ``key`` (a kind and a model) while ``base``'s prior and options stay
    (a change of the held noise levels only is carried over without
    recomputing the prior's free run)."""
    kind, model = key
    hit = ctx.cache.get((kind, id(model)))
    if hit is not None and hit[0] is model and hit[1] is base.prior and hit[2] == base.ukf:
        p = hit[3]
        return p if p.noise == base.noise else replace(p, noise=base.noise)
    p = build()
    ctx.cache[(kind, id(model))] = (model, base.prior, base.ukf, p)
    return p


def x0_states(ctx: Context, model: Model) -> list[str]:
    """The initial states of ``model`` estimated with θ (``settings.estimate_x0``;
    ``["all"]``: every state)."""
    want = list(ctx.settings.estimate_x0 or [])
    if want == ["all"]:
        return list(model.states)
    return [s for s in want if s in model.states]


def noise_start(problem: Problem, theta: np.ndarray) -> dict:
    """Output -> start of its estimated noise std in a fit (the held level,
    else ``meas_std(θ)``)."""
    model = problem.model
    meas = np.asarray(model.meas_std(theta[None, :]), float)[0]
    return {o: float(problem.noise.held.get(o, meas[model.output_index(o)]))
            for o in problem.noise.outputs(model)}


def noise_boxes(problem: Problem, start: dict) -> dict:
    """Output -> ``(lower, upper, centre, of the record)`` of its estimated
    noise std's box in a fit from ``start`` (:func:`noise_start`): ×/÷
    NOISE_BOX around the record's level where the problem keeps it
    (:attr:`NoiseSpec.centre`), else around the start; reaching the start
    (:meth:`~bondgraph.inference.estimand.Estimand.bounds`)."""
    out = {}
    for o, s in start.items():
        c = problem.noise.centre.get(o)
        ctr = s if c is None else c
        out[o] = (*(float(v) for v in noise_box(ctr, s)), ctr, c is not None)
    return out


def _noise_bound_warning(ctx: Context, what: str, est: dict, boxes: dict, std: dict,
                         process_noise: bool = True) -> None:
    """Log a warning for estimated noise stds on a bound of their box
    (``boxes``: :func:`noise_boxes`); their Cramér-Rao std becomes None. On
    the bottom of the box the likelihood puts the output's variance
    elsewhere (into process noise); on the top the model's misfit sets it
    (without ``process_noise``, the filter's prediction is the free run and
    its whole error reads as sensor noise). Each output and side is said
    once per loop (``ctx.said``): a level on the bottom of its box is there
    in every refit (a user's closed-loop EMPS graph: 40 lines)."""
    box = {o: b for o, b in boxes.items() if o in est and b[0] > 0}
    lo = [o for o in box if not box[o][0] * (1 + 1e-6) < est[o]]
    hi = [o for o in box if o not in lo and not est[o] < box[o][1] * (1 - 1e-6)]
    for o in lo + hi:
        std[f"noise.{o}"] = None
    said = getattr(ctx, "said", None)
    if said is not None:        # each output and side said once per loop (every refit repeats it)
        lo = [o for o in lo if f"noise-low:{o}" not in said]
        hi = [o for o in hi if f"noise-high:{o}" not in said]
        said.update([f"noise-low:{o}" for o in lo] + [f"noise-high:{o}" for o in hi])

    def listed(outs):
        return ", ".join(f"{o} = {est[o]:.3g}" for o in outs)

    def centred(outs):      # the box's centre: the record's level, or the fit's start
        rec = [o for o in outs if box[o][3]]
        parts = [f"{NOISE_BOX:g} times the record's level ("
                 + ", ".join(f"{box[o][2]:.3g}" for o in rec) + ")"] if rec else []
        if len(rec) < len(outs):
            parts.append(f"{NOISE_BOX:g} times the level the fit started from ("
                         + ", ".join(f"{box[o][2]:.3g}" for o in outs if o not in rec) + ")")
        return "; ".join(parts)

    if lo:
        ctx.log(f"  warning: {what}: measurement-noise std on the bottom of its box: "
                f"{listed(lo)} (not identified by the record beside the process noise; "
                f"declare it in the record or use noise='model'; said once per output)")
    if hi:
        where = ("the model's error, which the filter reads as sensor noise (no process noise "
                 "is declared: declare it on the states where efforts or flows are "
                 "unmodelled)") if not process_noise else \
            "the model's error, which the filter reads as sensor noise"
        ctx.log(f"  warning: {what}: measurement-noise std on the top of its box: "
                f"{listed(hi)}, {centred(hi)}: not the sensor but {where}; declare the "
                f"sensor's level in the record to hold it (said once per output)")


def planned_noise(problem: Problem, settings: LoopSettings,
                  log: Callable[[str], None]) -> tuple[list[str], NoiseSpec]:
    """The noise policy resolved for the declared model (``settings.noise``):
    under ``"auto"``, the record's declared levels held, the undeclared
    fixed sensor noises estimated and the undeclared noise-intensity
    parameters to be added to ``params``
    (:func:`bondgraph.inference.estimand.noise_plan`); the plan's notes
    logged. Returns ``(parameters to add, NoiseSpec)``."""
    if settings.noise == "model":
        log("noise levels: the model's own (noise='model')")
        return [], NoiseSpec("model")
    model = problem.model
    declared = problem.record.noise_std_for(model)
    add, outs, sigma, notes = plan_noise(model, problem.theta, settings.params,
                                         list(settings.fixed), declared, problem.y)
    # an estimated output's entry is the start of its estimate (a level no
    # sensor declares, seen in the record): held until a fit estimates it
    held = {o: float(sigma[j]) for j, o in enumerate(model.outputs) if np.isfinite(sigma[j])}
    if any(o not in outs for o in held):
        notes.append("measurement-noise std held at the record's declaration: " + ", ".join(
            f"{o} = {v:.4g}" for o, v in held.items() if o not in outs))
    for note in notes or ["noise levels: the model's own (nothing to estimate or hold)"]:
        log(note)
    # the record's level stays the centre of an estimated level's box in
    # every refit (a refit starts from the earlier fit's estimate)
    return add, NoiseSpec("auto", held=held, estimated=outs,
                          centre={o: held[o] for o in outs if o in held})


def criterion_for(ctx: Context, model: Model, names: Sequence[str], base: np.ndarray):
    """Batched NLL of ``names`` (others at ``base`` (n_theta,)) on the record,
    with the loop's prior, held noise levels and UKF options
    (:func:`problem_for`), ``settings.evaluation.chunk`` sets per UKF run."""
    return make_criterion(problem_for(ctx, model), names, base, ctx.settings.evaluation.chunk)


def bounds_around(model: Model, names: Sequence[str], theta: np.ndarray):
    """The declared boxes (k,) of ``names`` (never widened: a start value
    outside its box is clipped into it by :func:`clip_into_box`; ``theta``
    is accepted for the callers' convenience)."""
    return model.bounds(names)


def start_theta(ctx: Context, problem: Problem, params: Sequence[str],
                start: Mapping[str, float] | None, what: str) -> np.ndarray:
    """``problem``'s θ (n_theta,) with the values of ``start`` its model has,
    ``params`` clipped into their declared boxes (:func:`clip_into_box`)."""
    model = problem.model
    theta = problem.theta.copy()
    for k, v in (start or {}).items():
        if k in model.params:
            theta[model.param_index(k)] = v
    return clip_into_box(ctx, model, params, theta, what)


def clip_into_box(ctx: Context, model: Model, names: Sequence[str], theta: np.ndarray,
                  what: str) -> np.ndarray:
    """``theta`` (n_theta,) with the values of ``names`` clipped into their
    declared boxes (each move logged)."""
    theta = theta.copy()
    lo, hi = model.bounds(names)
    for n, a, b in zip(names, lo, hi):
        j = model.param_index(n)
        v = float(np.clip(theta[j], a, b))
        if v != theta[j]:
            ctx.log(f"  {what}: start {n} = {theta[j]:.4g} outside its box [{a:.4g}, {b:.4g}]; "
                    f"clipped to {v:.4g}")
            theta[j] = v
    return theta


def on_bound(model: Model, names: Sequence[str], theta: np.ndarray,
             rel: float = 1e-6) -> list[str]:
    """Names whose value in ``theta`` lies within ``rel`` of a bound of its
    box, relative to the smaller of the box's width and the magnitude there
    (the largest of the value's, the model's default's and that bound's;
    :func:`~bondgraph.inference.fisher.near_bound`):
    a box far wider than the value carries no scale (an effect's nominal
    box [0, 1e15] of a damping coefficient 1e-5 is not "on" 0, which a
    tolerance of the width, 1e9, said; nor an unbounded side)."""
    lo, hi = model.bounds(names)
    idx = [model.param_index(n) for n in names]
    v = np.asarray(theta, float)[idx]
    mag = np.maximum(np.maximum(np.abs(v), np.abs(model.theta0[idx])), 1e-300)
    near_lo, near_hi = near_bound(v, lo, hi, rel, mag)
    return [n for n, a, b in zip(names, near_lo, near_hi) if a or b]


def process_noise_at_floor(model: Model, names: Sequence[str], theta: np.ndarray) -> list[str]:
    """Those of ``names`` that are process-noise intensities (noise
    intensities, :func:`noise_params`, that leave ``meas_std`` unchanged:
    :func:`~bondgraph.inference.estimand.moves_meas_std`)
    on the lower bound of their box in ``theta`` (:func:`on_bound`): a
    random walk the record does not ask for, not a box too narrow (a
    coast-down's grade noise q_grade at 1e-5 once the drag explains the
    deceleration). A sensor noise on its floor is not among them: a model
    that fits below the sensor's noise is suspect."""
    noise, out = noise_params(model), []
    th = np.asarray(theta, float)
    for n in names:
        if n not in noise or not on_bound(model, [n], th):
            continue
        (a,), (b,) = model.bounds([n])
        j = model.param_index(n)
        v = float(th[j])
        if not (np.isfinite(a) and (not np.isfinite(b) or v - a <= b - v)):
            continue                # on its upper bound
        if not moves_meas_std(model, th, n):
            out.append(n)
    return out


def noise_params(model: Model) -> set:
    """Names of the noise-intensity parameters of ``model`` (scale
    parameters of the filter: fitted in log scale, profiled by decades when
    candidates are screened): the toolkit's one detector,
    :func:`bondgraph.inference.estimand.noise_parameters`, at the model's
    defaults.

    Kept on the model with the defaults, initial state and input it was
    found at, and found again when one of them changed (the loop asks about
    900 times per run of the bundled default: 5.6 of its 128 s)."""
    key = tuple(np.asarray(v, dtype=float).tobytes() for v in (model.theta0, model.x0, model.u0))
    got = getattr(model, "_noise_params", None)
    if got is None or got[0] != key:
        got = (key, frozenset(noise_parameters(model, model.theta0)))
        model._noise_params = got
    return set(got[1])


#: eigenvalues of the unit-diagonal Fisher information below this fraction
#: of the largest are its null space (singular to rounding): :func:`cr_std`
SINGULAR_REL = 1e-12


def cr_std(F: np.ndarray, names: Sequence[str]) -> dict:
    """Cramér-Rao standard deviations sqrt(diag(F⁻¹)) from the Fisher
    information F (k, k); None where F is singular or a variance is not
    positive (Cramér 1946; Rao 1945).

    Where F is singular to rounding (an eigenvalue of its unit-diagonal
    scaling below :data:`SINGULAR_REL` of the largest: two parallel dampers
    the record sees only as their sum), its inverse is rounding noise, and
    so were the stds read from it, the others' too (a mass's std 23 % apart
    between two fits at the same estimate). Then the quantities that load on
    the null space get None, and the others the std of the pseudo-inverse,
    which is their bound with the unidentified combination left free: the
    same as in the model reparametrised without it (Stoica & Marzetta 2001,
    IEEE Trans. Signal Process. 49(1), 87-90)."""
    F = np.asarray(F, float)
    d = np.diag(F)
    if F.size and np.all(np.isfinite(F)) and np.all(d > 0):
        D = np.sqrt(d)
        w, V = np.linalg.eigh(F / np.outer(D, D))
        null = w < SINGULAR_REL * w[-1]
        if null.any():
            keep = ~null
            C = (V[:, keep] / w[keep]) @ V[:, keep].T / np.outer(D, D)
            loads = np.abs(V[:, null]).max(axis=1) > np.sqrt(SINGULAR_REL)
            return {n: (None if lo or not c > 0 else float(np.sqrt(c)))
                    for n, c, lo in zip(names, np.diag(C), loads)}
    try:
        C = np.linalg.inv(F)
        d = np.diag(C)
        return {n: (float(np.sqrt(v)) if v > 0 and np.isfinite(v) else None)
                for n, v in zip(names, d)}
    except np.linalg.LinAlgError:
        return {n: None for n in names}


def robust_std_of(ctx: Context, fit: Fit) -> dict:
    """Robust (sandwich) standard deviations of ``fit``'s parameters by name
    (:func:`bondgraph.inference.robust.robust_std`; White 1982, Newey &
    West 1987): the Fisher information, standing in for the Hessian, and
    the per-sample scores from one batched UKF run at the estimate, with
    the problem conditioned on the loop's current fit (its initial states
    and noise levels held). {} where it cannot be computed; parameters on a
    bound or without a Cramér-Rao std get none. A run of k + 1 sets, not
    worth its cost on every refit: for the final model, and for a refit
    whose identification the accept rule judges by it
    (:func:`bondgraph.diagnose.accept.robust_std_needed`)."""
    got = _scores_at(ctx, fit)
    if got is None:
        return {}
    params, F, G = got
    return {n: float(v) for n, v in zip(params, robust_std(F, G)) if np.isfinite(v)}


def robust_lr(ctx: Context, fit: Fit, new: list[str], lr: float, dof: int) -> dict:
    """The likelihood ratio ``lr`` of an accepted refit ``fit`` against the
    model before it, scaled for serially correlated innovations: divided by
    the mean weight c of its limiting distribution, Σ λ_j χ²₁ (Kent 1982;
    Satorra & Bentler 1994; :func:`bondgraph.inference.robust.lr_scale`),
    from the block of ``fit``'s effect parameters ``new``, and referred to
    χ²(``dof``) as the accept rule's test is. Information for the report
    (the accept rule keeps the plain χ² test and judges by the error on
    the held-out record, whose test allows for the correlation itself): on
    a record whose innovations are far from white the plain p-value is
    far too small. One batched UKF run of k + 1 sets at the estimate
    (:func:`robust_std_of`'s).

    The statistic is divided by max(c, 1): a scale below 1 (0.63 on a
    user's cascaded tanks under the free-run likelihood, where the Fisher
    information stands in for the Hessian of a misspecified fit and the
    HAC estimate is biased low) would make the evidence look stronger than
    the plain χ² test says, which this report never does.

    Returns
    -------
    dict
        ``scale`` (c as estimated), ``lr`` (lr / max(c, 1)), ``p_value``;
        {} where it cannot be computed (an effect parameter on a bound or
        without a Cramér-Rao std, a failed run, an information matrix that
        is not positive definite).
    """
    if not (new and np.isfinite(lr)):
        return {}
    got = _scores_at(ctx, fit)
    if got is None or not set(new) <= set(got[0]):
        return {}
    params, F, G = got
    scaled = lr_scale(F, G, [params.index(n) for n in new])
    if scaled is None:
        return {}
    c = scaled[0]
    r = lr / max(c, 1.0)
    return {"scale": c, "lr": r, "p_value": float(chi2.sf(r, max(int(dof), 1)))}


def _scores_at(ctx: Context, fit: Fit) -> tuple[list[str], np.ndarray, np.ndarray] | None:
    """``(params, F (k, k), G (N, k))``: the Fisher information and the
    per-sample scores of ``fit``'s parameters that are off their bounds and
    have a Cramér-Rao std, from one stored batched run at the estimate (at
    the fit's own step, :func:`fit_context`); None where there are none or
    it fails. Kept on ``fit`` for the same
    problem, parameters and θ: the accepted step's scaled likelihood ratio
    (:func:`robust_lr`) and the robust std of the same fit (a refit judged
    by it, or the final model) share the run."""
    params = [n for n in fit.params if n not in fit.at_bound and fit.std.get(n) is not None]
    if not params:
        return None
    model = fit.model
    pb = problem_for(fit_context(ctx, fit), model)
    key = (tuple(params), np.asarray(fit.theta, float).tobytes())
    memo = getattr(fit, "_scores_memo", None)
    if memo is not None and memo[0] is pb and memo[1] == key:
        return memo[2]
    idx = [model.param_index(n) for n in params]
    lo, hi = bounds_around(model, params, fit.theta)
    noise = noise_params(model)
    scale = np.array([n in noise and lo[i] > 0 for i, n in enumerate(params)])
    try:
        got = fisher_fit(pb, fit.theta, idx, (lo, hi), 0, log_scale=scale, information=True,
                         scores=True)
    except (FloatingPointError, np.linalg.LinAlgError):
        got = None
    F, G = (None, None) if got is None else (got[1], got[-1])
    out = None if F is None or G is None else (params, F, G)
    fit._scores_memo = (pb, key, out)
    return out


# ----------------------------------------------------------------- fitting
def say_ridge(ctx: Context, kind: str, names, msg: str) -> None:
    """Log ``msg`` about the parameters ``names`` (a ridge of the
    likelihood, ``kind`` "flat" or "unidentified") once per loop
    (:meth:`Context.log_once`), and not at all when a ridge of the same
    kind said before already names them, or two of them: every refit of a
    candidate meets the declared fit's ridge again, with its own
    parameters beside it or along part of it (a user's series RLC whose
    record tells only L·C: 12 lines "does not identify L, Cc"; a user's CED
    graph, whose declared fit named seven motor, belt and pulley
    parameters: 36 such lines over ten confirmations, each naming three to
    nine of them). A candidate whose own parameter is not identified apart
    from the current model's is refused as such, with its own line
    (:mod:`bondgraph.diagnose.accept`)."""
    key = set(names)
    for said in ctx.said:
        if said.startswith(f"{kind}:"):
            known = set(said[len(kind) + 1:].split("|"))
            if key <= known or len(key & known) >= 2:
                return
    ctx.log_once(f"{kind}:{'|'.join(sorted(key))}", msg)


def fit_model(ctx: Context, graph: BondGraph, params: list[str],
              start: Mapping[str, float] | None, what: str, model: Model | None = None,
              iterations: int | None = None, tolerance: float = 0.0, stop=None) -> Fit:
    """Warm-started maximum-likelihood fit of ``params``, everything else fixed.

    Parameters
    ----------
    ctx : Context
    graph : BondGraph
    params : list of str
        Parameters to estimate (those ``graph`` lacks are dropped).
    start : dict, optional
        Start values by name (over ``settings.fixed``, over the defaults).
    what : str
        Name of the fit in log lines and errors.
    model : Model, optional
        ``graph``'s generated model, if already built.
    iterations : int, optional
        Maximum Fisher-scoring iterations (default ``settings.search.fit_iterations``;
        0: evaluate at the start).
    tolerance : float
        Convergence of the scoring [nats] (:func:`~bondgraph.diagnose.inference_calls.fisher_fit`).
    stop : callable, optional
        ``stop(estimand, nll)``: True ends the scoring there, not converged
        (:func:`~bondgraph.diagnose.inference_calls.fisher_fit`).

    Returns
    -------
    Fit
        Start values outside their declared boxes are clipped into them;
        estimates on a bound are listed in ``at_bound`` (logged) and get no
        Cramér-Rao std.

    Raises
    ------
    BondGraphError
        If the UKF fails at the fitted parameters.
    """
    model = model or model_of(graph)
    pb = problem_for(ctx, model)
    params = [p for p in params if p in model.params]
    theta = start_theta(ctx, pb, params, start, what)
    iters = ctx.settings.search.fit_iterations if iterations is None else int(iterations)
    fitted, theta, std, conv, x0_est, noise_est = _fitted(ctx, pb, params, theta, iters, what,
                                                          tolerance, stop)
    fit = evaluate_fit(ctx, fitted, graph, params, theta, what, std)
    fit.converged, fit.iterations, fit.flat, fit.ridge = conv
    fit.x0_est, fit.noise_est = x0_est, noise_est
    fit.at_bound = on_bound(model, params, theta)
    if fit.at_bound:
        # each boxed parameter said once per loop: a declared parameter the
        # accepted fit left on its box is on it in every later refit (a
        # user's CED graph: "b_m = 0.0001" in 25 lines)
        new = [n for n in fit.at_bound if f"boxed:{n}" not in ctx.said]
        ctx.said.update(f"boxed:{n}" for n in new)
        floor = process_noise_at_floor(model, new, fit.theta)
        rest = [n for n in new if n not in floor]
        if rest:
            values = ", ".join(f"{n} = {fit.theta[model.param_index(n)]:.4g}" for n in rest)
            ctx.log(f"  warning: {what}: estimate(s) on a bound of their box: {values} (no "
                    f"Cramér-Rao std; widen the box or fix the parameter; said once per "
                    f"parameter)")
        if floor:
            values = ", ".join(f"{n} = {fit.theta[model.param_index(n)]:.4g}" for n in floor)
            ctx.log(f"  {what}: process-noise intensit{'y' if len(floor) == 1 else 'ies'} on "
                    f"the floor of {'its' if len(floor) == 1 else 'their'} box: {values} (the "
                    f"record asks for no random walk there; no Cramér-Rao std; said once per "
                    f"parameter)")
        for n in fit.at_bound:
            fit.std[n] = None
    return fit


def _fitted(ctx: Context, pb: Problem, params: list[str], theta: np.ndarray, iters: int,
            what: str, tolerance: float = 0.0, stop=None) -> tuple:
    """The likelihood fit of :func:`fit_model` without its evaluation:
    ``(problem conditioned on the estimated initial states and noise stds,
    θ, std, (converged, iterations, flat, ridge), x0_est, noise_est)``."""
    model = pb.model
    std: dict = {}
    conv: tuple = (None, None, (), "")
    x0_est = {s: pb.prior.estimated[s] for s in x0_states(ctx, model) if s in pb.prior.estimated}
    noise_est = {o: pb.noise.held[o] for o in pb.noise.outputs(model) if o in pb.noise.held}
    if params and iters > 0:
        start_sigma = noise_start(pb, theta)
        theta = _settle_theta(ctx, pb, params, theta, iters, what, start_sigma)
        theta, std, conv, x0_new, noise_new = _maximize(ctx, pb, params, theta, iters, what,
                                                        tolerance, stop)
        x0_est.update(x0_new)
        noise_est.update(noise_new)
        _noise_bound_warning(ctx, what, noise_new, noise_boxes(pb, start_sigma), std,
                             not no_process_noise(model, theta))
    fitted = pb.conditioned_on(x0={**pb.prior.estimated, **x0_est}, noise_levels=noise_est)
    return fitted, theta, std, conv, x0_est, noise_est


def likelihood_fit(ctx: Context, model: Model, params: list[str], theta: np.ndarray,
                   what: str) -> tuple[np.ndarray, float, dict]:
    """The maximum-likelihood fit of ``params`` of ``model`` from ``theta``
    as :func:`fit_model` makes it (``settings.search.fit_iterations`` of
    Fisher scoring with the initial states and noise stds), without the free
    runs and residual analysis of a :class:`Fit`: for comparing a model's
    likelihood under other filter options (the loop's final check of the
    input holds, :func:`bondgraph.diagnose.runner.hold_at_final`).

    Parameters
    ----------
    ctx : Context
        Its problem carries the filter options compared.
    model : Model
    params : list of str
    theta : array (n_theta,)
        The start.
    what : str
        Name of the fit in log lines.

    Returns
    -------
    (theta, nll, std) : (array (n_theta,), float, dict)
        The estimate, its NLL [nat] (inf when the filter fails there) and
        the Cramér-Rao std by name.

    Raises
    ------
    NumericalError
        The filter fails at the start.
    """
    pb = problem_for(ctx, model)
    params = [p for p in params if p in model.params]
    fitted, theta, std, *_ = _fitted(ctx, pb, params, np.asarray(theta, float).copy(),
                                     ctx.settings.search.fit_iterations, what)
    nll = float(run_ukf(fitted, theta[None, :]).nll[0])
    return theta, (nll if np.isfinite(nll) else float("inf")), std


def _settle_theta(ctx: Context, problem: Problem, params: list[str], theta: np.ndarray,
                  iters: int, what: str, start_sigma: dict) -> np.ndarray:
    """θ fitted with the measurement noise held at its start, before a fit
    that estimates noise stds no fit has set yet (the declared fit under
    ``noise="auto"``). From a start far from the optimum a joint fit lets the
    noise std absorb the misfit, the likelihood flattens in θ and the scoring
    stalls in a poor point (a user's two-tank graph: free-run NRMSE 0.063
    against 0.017 in two stages, and the loop then "found" a dead zone that
    only made up for it). ``theta`` unchanged when every level is set."""
    fresh = [o for o in problem.noise.outputs(problem.model) if o not in problem.noise.held]
    if not fresh:
        return theta
    held = problem.conditioned_on(noise_levels=start_sigma, noise_outputs=[])
    return _maximize(ctx, held, params, theta, iters, f"{what} (noise held)")[0]


def _maximize(ctx: Context, problem: Problem, params: list[str], theta: np.ndarray, iters: int,
              what: str, tolerance: float = 0.0,
              stop=None) -> tuple[np.ndarray, dict, tuple, dict, dict]:
    """Fisher scoring of ``params`` from ``theta`` (noise intensities in log
    scale), the initial states of :func:`x0_states` and the noise stds of
    the problem's estimated outputs jointly, L-BFGS-B (θ only) if it fails
    numerically; returns θ, the Cramér-Rao std (empty after the fallback;
    ``x0.<state>``, ``noise.<output>`` for the others), (converged,
    iterations, the quantities along which the likelihood is flat where it
    stopped), the estimated initial states and noise stds by name."""
    model = problem.model
    states = x0_states(ctx, model)
    noises = problem.noise.outputs(model)
    idx = [model.param_index(n) for n in params]
    lo, hi = bounds_around(model, params, theta)
    # log scale and decade moves for the noise intensities only: a physical
    # parameter with a wide box (R_a in [0.05, 10]) is no scale parameter,
    # and decade jumps strand it on a bound
    noise = noise_params(model)
    scale = np.array([n in noise and lo[i] > 0 for i, n in enumerate(params)])
    try:
        theta, F, conv, used, x0n, sig, flat, _, _ = fisher_fit(
            problem, theta, idx, (lo, hi), iters, log_scale=scale, tolerance=tolerance,
            states=states, noises=noises, stop=stop)
        names = list(params) + [f"x0.{s_}" for s_ in states] + [f"noise.{o}" for o in noises]
        moves = ""
        if flat:
            say_ridge(ctx, "flat", flat,
                      f"  {what}: converged in the directions the record identifies; the "
                      f"likelihood is flat along {', '.join(flat)} together (gaining < "
                      f"{FLAT_GAIN:g} nats per iteration): not identified by this record")
        else:
            flat = unidentified(F, names)
            if flat:
                moves = ridge_changes(F, list(params), theta[idx])
                say_ridge(ctx, "unidentified", flat,
                          f"  {what}: the record does not identify {', '.join(flat)} "
                          f"separately (the Fisher information is flat along a "
                          f"combination of them: collinearity index > 100){moves}; fix "
                          f"one (bondgraph sensitivity recommends which to estimate), or "
                          f"use a record that excites them apart")
        return (theta, cr_std(F, names), (conv, used, flat, moves),
                {s_: float(x0n[model.state_index(s_)]) for s_ in states}, sig)
    except (FloatingPointError, np.linalg.LinAlgError) as exc:
        ctx.log(f"  {what}: Fisher scoring failed ({exc}); falling back to L-BFGS-B")
        crit = make_criterion(problem, params, theta, ctx.settings.evaluation.chunk)
        xs = np.array([theta[model.param_index(n)] for n in params])
        x = lbfgsb_polish(crit, xs, lo, hi, iters)
        theta = crit.theta(x[None, :])[0]
        std, flat = _information_at(problem, params, theta, idx, (lo, hi), scale)
        return theta, std, (None, None, flat, ""), {}, {}


def _information_at(problem: Problem, params: list[str], theta: np.ndarray, idx, box,
                    scale) -> tuple[dict, tuple]:
    """The Cramér-Rao std of ``params`` and the ones the Fisher information
    does not identify apart (:func:`unidentified`) at ``theta``, after an
    L-BFGS-B fallback (no scoring, so no information of its own; ``({}, ())``
    when it cannot be computed there either). Without it a refit whose
    scoring failed on a ridge reported no std and no flat direction, and
    the accept rule could not see what it left undetermined (a user's DC
    motor: a speed-sensor gain with a Stribeck term, k_t at half its value,
    accepted)."""
    try:
        F = fisher_fit(problem, theta, idx, box, 0, log_scale=scale, information=True)[1]
    except (FloatingPointError, np.linalg.LinAlgError):
        return {}, ()
    if F is None or not np.all(np.isfinite(F)):
        return {}, ()
    return cr_std(F, list(params)), unidentified(F, list(params))


def ridge_changes(F: np.ndarray | None, params: list[str], values: np.ndarray) -> str:
    """A fit's least identified direction among its parameters as relative
    changes, for its log line (:func:`~bondgraph.inference.estimate.relative_direction`):
    the weakest eigenvector of their efficient information (the initial
    states' and noise stds' rows profiled out, F_pp − F_pn F_nn⁺ F_np) in
    coordinates θ_i / abs(θ_i). The unit-diagonal loadings of
    :func:`unidentified` name a scale symmetry only in part (a user's
    quarter-car: "ms, ks, cs" of the five that scale together, ms, mu, ks,
    kt, cs +1.00 each here).

    Parameters
    ----------
    F : array (k + m, k + m) or None
        The fit's Fisher information, its first k rows the parameters.
    params : list of str (k)
    values : array (k,)
        The parameters' estimates.

    Returns
    -------
    str
        ``"; as relative changes: ... (... scale together: ...)"`` when the
        direction is a scale symmetry, else "" (also when F is missing or
        not finite, or a parameter is zero: a parameter near zero, a sensor
        offset, would dominate any relative direction).
    """
    k = len(params)
    th = np.asarray(values, float)
    if F is None or k < 2 or th.shape != (k,) or not np.all(th != 0):
        return ""
    F = np.asarray(F, float)
    if F.shape[0] < k or not np.all(np.isfinite(F)):
        return ""
    Fe = F[:k, :k]
    sc = np.abs(th)
    try:                    # a message: it never stops the fit it describes
        if F.shape[0] > k:
            Fe = Fe - F[:k, k:] @ np.linalg.pinv(F[k:, k:]) @ F[k:, :k]
        _, V = np.linalg.eigh(0.5 * (Fe + Fe.T) * np.outer(sc, sc))
    except (np.linalg.LinAlgError, ValueError):
        return ""
    return relative_direction(V[:, 0] * sc, th, params, scale_only=True)


def unidentified(F: np.ndarray | None, names: list[str]) -> tuple:
    """The quantities ``names`` (k) that a fit's Fisher information F (k, k)
    does not identify separately: those loading on its flat directions
    (:func:`bondgraph.inference.fisher.flat_directions`, unit-diagonal
    scaling, eigenvalues below 1e-4 of the largest; Brun, Reichert & Künsch
    2001); a quantity with no information at all (a zero or non-finite
    diagonal) is left out of the analysis. Empty when F is None or not
    finite."""
    if F is None or len(names) != len(F):
        return ()
    free = np.isfinite(np.diag(F)) & (np.diag(F) > 0)
    if not np.all(np.isfinite(F[np.ix_(free, free)])):
        return ()
    found, _ = flat_directions(F, np.zeros(len(names)), free)
    return tuple(names[i] for i in found)


def evaluate_fit(ctx: Context, problem: Problem, graph: BondGraph, params: list[str],
                 theta: np.ndarray, what: str, std: dict) -> Fit:
    """The :class:`Fit` of ``problem``'s model at ``theta``: one stored UKF
    run, the free-run simulation, the residual analysis and the metric (on
    the validation record too, if there is one).

    Raises
    ------
    NumericalError
        If the UKF fails at ``theta`` (the reason is named).
    """
    model = problem.model
    res = run_ukf(problem, theta[None, :], store=True)
    nll = float(res.nll[0])
    if not np.isfinite(nll):
        raise NumericalError(f"{what}: the UKF failed at the fitted parameters "
                             f"({res.reasons[0]})")
    sim_y = free_run(ctx, problem, theta)
    rep = analyze(res, model, *problem.arrays, sim_y=sim_y)
    fit = Fit(graph, model, list(params), theta, nll, res, rep, float("nan"), sim_y,
              std=std, n_obs=int(res.n_obs.sum()))
    record = MetricRecord(problem.record)
    fit.metric = compute_metric(ctx.settings, fit, record)
    fit.sim_errors = metric_errors(ctx.settings, fit, record)
    trouble = free_run_trouble(sim_y, problem.arrays[2], model.outputs)
    if ctx.settings.validation is not None:
        (fit.validation_metric, fit.validation_errors, v_trouble,
         fit.validation_sim_y) = validation_run(ctx, problem, theta, filtered=res)
        trouble = trouble or (v_trouble and f"{v_trouble} on the validation record")
    for i, rec in enumerate(validation_records(ctx.settings)[1:], start=1):
        m, errors, v_trouble, sim = validation_run(ctx, problem, theta, which=i)
        fit.more_metrics[rec.name], fit.more_errors[rec.name] = m, errors
        fit.more_sim_y[rec.name] = sim
        trouble = trouble or (v_trouble and f"{v_trouble} on the validation record "
                                            f"'{rec.name}'")
    fit.unstable = trouble
    return fit


def validation_run(ctx: Context, problem: Problem, theta: np.ndarray, *,
                   filtered=None, which: int = 0
                   ) -> tuple[float, np.ndarray | None, str | None, np.ndarray | None]:
    """The loop's metric on the validation record (``settings.validation``,
    or with ``which`` = i > 0 the i-th of ``settings.more_validation``:
    the model runs freely with the record's inputs from its initial state,
    :func:`free_run`), the standardised free-run errors (N, n_y), why the
    free run is not plausible there (:func:`free_run_trouble`) and the free
    run's outputs (N, n_y; None where it failed, the report draws them); inf,
    None, the reason and None if the filter fails there.

    Where the validation record continues ``problem``'s (the held-out last
    part of one record, ``meta["follows"]``) and ``filtered`` (the stored
    filter run of ``problem`` at ``theta``) is given, the state the filter
    ends in, carried over the one interval between the records
    (:func:`continued_state`), is one more start: the run from it is taken
    where its error is lower, or where it fails (the stability checks see
    it), as :func:`_better_start` decides for every start. With
    ``settings.free_run.init_samples`` = n the start is set by the record's
    first n samples (:func:`window_start`), not continued, and the free-run
    metric and its per-sample errors run over the samples after them (the
    benchmark protocol)."""
    vp = validation_problem(ctx, problem, which)
    res = run_ukf(vp, theta[None, :], store=True)
    if not np.isfinite(res.nll[0]):
        vp, res = _finer_filter(ctx, vp, theta, res)
    if not np.isfinite(res.nll[0]):
        return float("inf"), None, f"the filter fails ({res.reasons[0]})", None
    sim_y = free_run(ctx, vp, theta, own=False)
    n_init = init_samples(ctx, vp.record)
    xc = None if n_init else continued_state(ctx, problem, vp, theta, filtered)
    if xc is not None:
        held = sim_inputs(ctx.settings, vp.disc.hold, vp.arrays[1])
        sim_y = _better_start(ctx, vp, theta, held, xc, vp.x0, quiet=True, y0=sim_y)[0] \
            if sim_y is not None else _free_run_from(ctx, vp, theta, held, xc, quiet=True)
    judged = sim_y
    if n_init and sim_y is not None:       # the window set the start: the error is the rest's
        judged = np.array(sim_y, dtype=float)
        judged[:n_init] = np.nan
    view = SimpleNamespace(model=vp.model, theta=theta, ukf=res, sim_y=judged)
    rec = MetricRecord(vp.record)
    return (compute_metric(ctx.settings, view, rec), metric_errors(ctx.settings, view, rec),
            free_run_trouble(sim_y, vp.arrays[2], vp.model.outputs), sim_y)


def continued_state(ctx: Context, problem: Problem, vp: Problem, theta: np.ndarray,
                    filtered) -> np.ndarray | None:
    """The start (n_x,) of the validation record ``vp`` that continues
    ``problem``'s record: the state the stored filter run ``filtered`` ends
    in (x̂ at the last sample), carried over the interval to the validation
    record's first sample by the filter's method at
    :data:`~bondgraph.diagnose.inference_calls.FINE_SUBSTEPS` times its
    substeps, the inputs held across it as the free runs hold them
    (:func:`sim_inputs`); the states the validation record gives itself
    (state columns) stay at its prior mean. None where the validation
    record does not follow ``problem``'s (``meta["follows"]``, set by
    :func:`bondgraph.diagnose.runner.held_out`), no record state is unknown,
    or no finite state is at hand.

    Without process noise the smoother's backward pass diverges through a
    contracting mode, and the start fitted to the held-out outputs can stop
    in a local minimum: on a user's CED graph (rectified sensor, low-pass,
    Dahl friction, source lag) it put the Dahl state at −71 and the lag's at
    265, and the held-out NRMSE read 0.348; from the state the fitted
    part's filter ends in it reads 0.114, as the free run of the whole
    record does over that part."""
    if filtered is None or vp.record.meta.get("follows") != problem.record.name:
        return None
    x_filt = getattr(filtered, "x_filt", None)
    model = vp.model
    unknown = vp.prior.unknown(model, vp.record)
    if x_filt is None or not unknown:
        return None
    x = np.asarray(x_filt[-1, 0], float)
    t, u, _ = problem.arrays
    tv, uv, _ = vp.arrays
    if not (np.all(np.isfinite(x)) and tv[0] > t[-1]):
        return None
    hold, u2 = sim_inputs(ctx.settings, vp.disc.hold, np.vstack([u[-1:], uv[:1]]))
    uk, duk = hold_inputs(u2, hold).interval(0)
    step = make_step(model, vp.disc.method, FINE_SUBSTEPS * most_substeps(vp.disc))
    th = np.asarray(theta, float)[None, :]
    with np.errstate(all="ignore"):
        x1 = step(x[None, :], uk[None], th, float(tv[0] - t[-1]),
                  None if duk is None else duk[None])[0]
    if not np.all(np.isfinite(x1)):
        return None
    start = np.asarray(vp.x0, float).copy()
    idx = [model.states.index(n) for n in unknown]
    start[idx] = x1[idx]
    return start


#: substeps (times the problem's) at which a filter that fails on the
#: validation record is run again (:func:`_finer_filter`)
FINER_SUBSTEPS = (4, 16)


def _finer_filter(ctx: Context, vp: Problem, theta: np.ndarray, res):
    """``(problem, result)``: the validation problem ``vp`` and its filter
    run at ``theta`` with more substeps (:data:`FINER_SUBSTEPS` times its
    own), where the run at its own step failed: the first that runs; else
    ``vp`` and the failed ``res``. A step that suits the estimation record
    can leave the explicit method's stability region on a validation record
    that moves faster: a user's two-mass drive with a Dahl friction (rest
    stiffness 262 N m/rad) failed at RK4(2) on its held-out quarter
    ("posterior covariance P not positive definite") and was refused as
    "does not simulate", while RK4(8) runs (NLL 6624.1, 6624.1 at RK4(32)).
    The validation filter enters no likelihood ratio (the accept decision
    reads the free run's error there), so its step is free; logged."""
    for k in FINER_SUBSTEPS:
        n = vp.disc.substeps * k
        fine = vp.conditioned_on(disc=replace(vp.disc, substeps=n))
        r = run_ukf(fine, theta[None, :], store=True)
        if np.isfinite(r.nll[0]):
            ctx.log(f"  the filter fails on the validation record at {vp.disc.method}"
                    f"({vp.disc.substeps}) ({res.reasons[0]}); it runs at {n} substeps")
            return fine, r
    return vp, res


#: a free run whose output leaves the measured range by more than this many
#: times the range's width is taken for a diverging model
PLAUSIBLE_SPANS = 3.0


def free_run_trouble(sim_y: np.ndarray | None, y: np.ndarray,
                     outputs: Sequence[str]) -> str | None:
    """Why a free run (N, n_y) does not show a model that simulates, or None.

    A free run that failed (``sim_y`` None: the solver stopped), that is not
    finite, or whose output leaves the measured range [min, max] of ``y``
    (N, n_y) by more than :data:`PLAUSIBLE_SPANS` times its width (an
    orifice law turned active whose level grows without bound; a softening
    spring past its turning point) is not a model the loop may accept, even
    where its error on another record falls."""
    if sim_y is None:
        return "the free run fails (the solver stops)"
    sim_y, y = np.asarray(sim_y, float), np.asarray(y, float)
    for i, o in enumerate(outputs):
        s = sim_y[:, i]
        if not np.all(np.isfinite(s)):
            return f"the free run of {o} is not finite"
        m = y[np.isfinite(y[:, i]), i]
        if m.size < 2:
            continue
        lo, hi = float(m.min()), float(m.max())
        w = (hi - lo) or max(abs(hi), 1e-300)
        worst = float(s[np.argmax(np.abs(s - 0.5 * (lo + hi)))])
        if worst < lo - PLAUSIBLE_SPANS * w or worst > hi + PLAUSIBLE_SPANS * w:
            return (f"the free run of {o} reaches {worst:.4g}, beyond {PLAUSIBLE_SPANS:g} "
                    f"times the measured range [{lo:.4g}, {hi:.4g}]")
    return None


#: a sensor noise estimated below this fraction of the record's declaration,
#: or a process noise grown by more than its inverse, is named (:func:`noise_absorbing`)
NOISE_FACTOR = 3.0


def noise_absorbing(ctx: Context, fit: Fit) -> list[str]:
    """Noise levels of ``fit`` that absorb the model's error rather than
    describe the noise, as warnings: a measurement-noise std estimated
    below 1/:data:`NOISE_FACTOR` of the record's declaration (a level the
    problem holds is not estimated and is never named), and a
    process-noise intensity q (state unit/√s) that grew more than
    :data:`NOISE_FACTOR`-fold from its start and whose random walk over the
    record, q·√T, exceeds the state's own spread along it (the std of its
    filtered trajectory): the likelihood then explains the record by noise,
    and the physical parameters need not move (a user's two tanks: the
    process noise 30-fold up, the sensor noise at the bottom of its box,
    the orifice coefficients at their start values)."""
    model, th = fit.model, fit.theta
    out = []
    declared = np.asarray(ctx.problem.record.noise_std_for(model), float)
    meas = np.asarray(model.meas_std(th[None, :]), float).reshape(-1)
    held = ctx.problem.noise.held
    for j, o in enumerate(model.outputs):
        if o not in fit.noise_est and o in held:
            continue        # held at a level, not estimated: it absorbs nothing
        v, d = float(fit.noise_est.get(o, meas[j])), declared[j]
        if np.isfinite(d) and d > 0 and v < d / NOISE_FACTOR:
            out.append(f"the measurement noise of {o} is estimated at {v:.3g}, below a third of "
                       f"the record's declaration {d:.3g}: the model's errors are passed to "
                       f"the process noise")
    return out + [msg for _, msg in process_noise_absorbing(ctx, fit)]


def state_spreads(ctx: Context, fit: Fit) -> tuple[np.ndarray, float] | None:
    """``(spread (n_x,), span)``: the std of each state's filtered trajectory
    in ``fit`` and the record's duration [s]; None without a stored filter
    run or a record of two samples."""
    x = getattr(fit.ukf, "x_filt", None)
    t = ctx.problem.arrays[0]
    if x is None or len(t) < 2:
        return None
    x = np.asarray(x)
    return (np.array([float(np.nanstd(x[:, 0, i])) for i in range(x.shape[2])]),
            float(t[-1] - t[0]))


def process_noise_absorbing(ctx: Context, fit: Fit) -> list[tuple[str, str]]:
    """``[(state, message)]``: the process-noise part of
    :func:`noise_absorbing`, the states whose intensity grew more than
    :data:`NOISE_FACTOR`-fold from its start and whose random walk over the
    record exceeds the state's own spread."""
    spreads = state_spreads(ctx, fit)
    if spreads is None:
        return []
    return absorbing_states(fit.model, ctx.problem.theta, fit.theta, *spreads)


def absorbing_states(model: Model, start: np.ndarray, theta: np.ndarray, spread: np.ndarray,
                     span: float) -> list[tuple[str, str]]:
    """``[(state, message)]``: the states whose process-noise intensity
    (``model.proc_std``, state unit/√s) grew more than :data:`NOISE_FACTOR`-fold
    from ``start`` to ``theta`` (each (n_theta,)) and whose random walk over
    the record, q·√``span`` (``span`` its duration [s]), exceeds the state's
    own spread ``spread`` (n_x,: the std of its filtered trajectory at
    ``theta``); empty for a model without process noise
    (:func:`process_noise_absorbing`; ``bondgraph estimate`` warns with it)."""
    proc = getattr(model, "proc_std", None)
    if proc is None:
        return []
    q1 = np.asarray(proc(np.asarray(theta, float)[None, :]), float).reshape(-1)
    q0 = np.asarray(proc(np.asarray(start, float)[None, :]), float).reshape(-1)
    out = []
    for i, st in enumerate(model.states):
        walk = q1[i] * np.sqrt(span)
        if q1[i] > NOISE_FACTOR * q0[i] and walk > spread[i] > 0:
            out.append((st, f"the process noise of {st} grew from {q0[i]:.3g} to {q1[i]:.3g} per "
                            f"√s: its random walk over the record ({walk:.3g}) exceeds the "
                            f"state's own spread ({spread[i]:.3g}); the noise absorbs the "
                            f"model's error"))
    return out


#: under the free-run likelihood, a process-noise intensity is held where its
#: random walk over the record is this share of its state's spread: small
#: enough that the filter's prediction is the free run, not so small that its
#: covariance loses rank (:func:`process_noise_floor`). Small enough, too, that
#: a fit cannot make it large again by shrinking an unmeasured state along a
#: scale symmetry: on a user's two tanks at 1 % the fit moved the pump gain
#: 50-fold down to its box (the upper level 50 times smaller, its held noise
#: 50 times larger relative to it) and the free run's error doubled
FREE_RUN_SHARE = 1e-3


def process_noise_floor(ctx: Context, fit: Fit, names: Sequence[str]) -> dict:
    """Name -> value of the process-noise intensity parameters among
    ``names`` held for the free-run likelihood: each scaled down until the
    random walk q·√T of every state it drives is :data:`FREE_RUN_SHARE` of
    that state's spread in ``fit`` (never up; not below the lower end of
    the parameter's box, the user's own bound; a state that does not move
    in ``fit`` gives no spread: its driver is scaled by the share itself).
    A parameter that drives no state's process noise (a sensor-noise std)
    is left out."""
    model, th = fit.model, fit.theta
    proc = getattr(model, "proc_std", None)
    spreads = state_spreads(ctx, fit)
    if proc is None or spreads is None:
        return {}
    spread, span = spreads
    q = np.asarray(proc(th[None, :]), float).reshape(-1)
    out = {}
    for n in names:
        j = model.param_index(n)
        bumped = th.copy()
        bumped[j] = 2.0 * th[j] if th[j] != 0 else 1e-6
        driven = np.abs(np.asarray(proc(bumped[None, :]), float).reshape(-1) - q) > 0
        if not driven.any():
            continue
        ok = driven & (q > 0) & (spread > 0)
        factor = min([FREE_RUN_SHARE * spread[i] / (q[i] * np.sqrt(span))
                      for i in np.flatnonzero(ok)] or [FREE_RUN_SHARE])
        lo, _ = model.bounds([n])
        value = float(th[j]) * min(factor, 1.0)
        out[n] = float(max(value, lo[0])) if np.isfinite(lo[0]) else value
    return out


def continued_laws(ctx: Context, fit: Fit) -> list[str]:
    """Laws of ``fit``'s graph continued with 0 past their domain
    (:mod:`bondgraph.core.domains`: ``sqrt(e)`` taken as 0 for e < 0) whose
    base the filtered states and the record's inputs put below 0 on more
    than :data:`~bondgraph.core.domains.CONTINUED_SHARE` of the samples, as
    warnings: there the model is a check valve where the user may have
    meant a law for both signs (an orifice between two tanks whose flow
    reverses)."""
    x = getattr(fit.ukf, "x_filt", None)
    if x is None or not getattr(fit.model, "domain_notes", None):
        return []                   # no law continued: no derivation needed
    ss = derive(fit.graph)
    exprs = list(ss.f) + list(ss.h)
    if not any(getattr(e, "has", None) and e.has(dpow) for e in exprs):
        return []
    t, u, _ = problem_for(ctx, fit.model).arrays
    X = np.asarray(x)[:, 0, :]
    syms = list(ss.states) + list(ss.inputs) + list(ss.params)
    vals = ([X[:, i] for i in range(X.shape[1])]
            + [u[:, j] if u.size else np.zeros(len(t)) for j in range(len(ss.inputs))]
            + [float(v) for v in fit.theta])
    return [f"the filtered states put {base} below 0 on {share:.0%} of the samples, where "
            f"{law} is taken as 0 (its domain ends there): if the law holds for both signs, "
            f"write it so (k*sign(e)*sqrt(abs(e)) for an orifice whose flow reverses)"
            for law, base, share in continued_share(exprs, syms, vals)]


def error_scale(problem: Problem, fit: Fit) -> np.ndarray:
    """The std (n_y,, output units) that a model error per sample is
    measured against at ``fit``: the larger of the measurement-noise std
    (:meth:`Problem.noise_scale`) and the median over the record of the
    filter's one-step innovation std √S_jj (``fit.ukf``, when stored).

    The likelihood weighs a prediction error by S⁻¹, and the Cramér-Rao
    std scales with √S: an error of one innovation std per sample moves the
    estimates by about their std whatever part of S the sensor and the
    process noise make. With a sensor noise estimated on the floor of its
    box and the record explained by process noise (Silverbox: 1e-6 V against
    innovations of tenths of a millivolt), the measurement-noise std alone
    would call an error of microvolts "13 noise stds". A model error that
    the process noise absorbs still shows: it is then a large part of √S.
    """
    sig = np.asarray(problem.noise_scale(fit.theta), float).reshape(-1)
    S = getattr(fit.ukf, "S", None)
    if S is None:
        return sig
    with np.errstate(all="ignore"):
        d = np.sqrt(np.diagonal(np.asarray(S)[:, 0], axis1=-2, axis2=-1))
    ok = np.isfinite(d)
    innov = np.full(d.shape[-1], np.nan)
    # an output the record never has (an all-NaN column) keeps its noise std
    # without numpy's "All-NaN slice" warning: a filter of warnings is
    # process-wide and another task thread may restore it meanwhile
    # (:func:`bondgraph.diagnose.parallel.local_map`)
    cols = ok.any(axis=0)
    if cols.any():
        innov[cols] = np.nanmedian(np.where(ok, d, np.nan)[:, cols], axis=0)
    return np.where(np.isfinite(innov) & (innov > sig), innov, sig)


def admissibility(ctx: Context, fit: Fit, before=None, placed=(),
                  against: Fit | None = None) -> Admissibility:
    """Whether ``fit``'s graph keeps what a bond graph promises at its
    estimates (every R dissipates, every C and I stores non-negative
    energy) over the range its filtered states visit on the record plus a
    margin (:func:`bondgraph.numerics.admissible.check_admissible`), and
    what the effects ``placed`` ((Effect, Target) pairs added to the graph
    ``before``) find at the refit beyond that
    (:meth:`~bondgraph.diagnose.effects.base.Effect.refit_violations`: a
    discovered law's memory term by the dissipation inequality). With
    ``against`` (the fit ``fit`` is compared with), the violations that fit
    already has are left out (:func:`~bondgraph.numerics.admissible.without_inherited`;
    only a declared model the user let the loop go on with, ``--keep-going``,
    has any)."""
    adm = _admissibility(ctx, fit, before, placed)
    if against is None or adm.ok:
        return adm
    key = ("admissibility", id(against), against.nll)
    if key not in ctx.cache:
        ctx.cache[key] = _admissibility(ctx, against, None, ())
    return without_inherited(adm, ctx.cache[key])


def _admissibility(ctx: Context, fit: Fit, before, placed) -> Admissibility:
    """:func:`admissibility` without ``against``."""
    model = fit.model
    ss = getattr(model.module, "__state_space__", None) or derive(fit.graph)
    x = getattr(fit.ukf, "x_filt", None)
    if x is None:
        return Admissibility(unchecked=["(no filtered states stored)"])
    t, u, _ = problem_for(ctx, model).arrays
    theta = {n: float(fit.theta[model.param_index(n)]) for n in model.params}
    adm = check_admissible(fit.graph, ss, theta, np.asarray(x)[:, 0, :], u)
    for eff, target in placed:
        adm.violations.extend(eff.refit_violations(before, target, fit, u, t))
    return adm


def sim_inputs(settings: LoopSettings, filter_hold: str, u: np.ndarray) -> tuple[str, np.ndarray]:
    """The input hold of the free-run simulations and the inputs (N, n_u) it
    holds: ``settings.free_run.hold`` (``"linear"`` or ``"zoh"``), or with
    ``"filter"`` the filter's own hold (``filter_hold``; its ``"mean"``
    hold, (u_k + u_k+1)/2 over each interval, is the zero-order hold of the
    interval means, the last sample held), so that the free run sees the
    inputs between samples as the likelihood fit did."""
    hold = settings.free_run.hold if settings.free_run.hold != "filter" else filter_hold
    u = np.asarray(u, dtype=float)
    holds = split_hold(hold, u.shape[1])
    if "mean" not in holds:
        return hold, u
    um = u.copy()
    for j, h in enumerate(holds):
        if h == "mean" and len(um) > 1:
            um[:-1, j] = 0.5 * (u[:-1, j] + u[1:, j])
    return join_hold("zoh" if h == "mean" else h for h in holds), um


def free_run(ctx: Context, problem: Problem, theta: np.ndarray, *,
             own: bool = True) -> np.ndarray | None:
    """Free-run simulation (N, n_y) of ``problem``'s record with the measured
    inputs (``settings.free_run.method``, rtol 1e-6, atol 1e-9, or ``"fine"``:
    :func:`~bondgraph.diagnose.inference_calls.fine_free_run`; the input hold of
    :func:`sim_inputs`) from its prior mean (state columns, sidecar ``x0``,
    ``--x0``, the jointly estimated initial states), or, when the record
    does not give some initial states (:meth:`PriorSpec.unknown`; on the
    estimation record (``own``), those not estimated with θ), from the
    RTS-smoothed initial state x̂_0|N (Särkkä 2008): the best start the
    model and the whole record give; where the prior does not allow it, the
    start fitted to the record's outputs (:func:`_fitted_start`), which is
    also tried where the better of the smoothed start's and the prior
    mean's free runs starts with a transient (:func:`startup_transient`; a
    user's DC motor whose held-out quarter starts mid-motion: its
    Coulomb-friction refit read 0.0643 from rest, 0.0096 from a fitted
    start; a user's oven, whose temperatures start at the room's while its
    prior mean, heat 0 J, reads 0 °C: without process noise the smoother put
    its case at −4 °C, and the declared fit's error on its record read
    0.2773). A taken smoothed start is refined so only on the estimation
    record and only when a validation record judges the accept decision: on
    the record that judges, every model compared keeps the same rule (on
    CED the refined start let a cold start be accepted on the start fitted
    to the held-out record). After a smoothed start only the declared graph's states
    (``ctx.problem``'s model) are fitted, from the smoothed start: an
    effect's own state (a cold start's initial excess) fitted to a record's
    outputs fits that record's start, not the effect (on CED a cold start
    was accepted so). Each is kept only where its free run beats the one it
    would replace (:func:`_better_start`). The filter's prior spread does not
    enter (the first filtered state did: one measurement update of it moved
    the start by its own P0). None (logged) if the model cannot be simulated
    freely."""
    model = problem.model
    t, u, _ = problem.arrays
    hold, u_sim = sim_inputs(ctx.settings, problem.disc.hold, u)
    x0 = problem.x0
    unknown = problem.prior.unknown(model, problem.record)
    free = [n for n in unknown if not own or n not in problem.prior.estimated]
    n_init = init_samples(ctx, problem.record)
    if free and not own and n_init:
        return _free_run_from(ctx, problem, theta, (hold, u_sim),
                              window_start(ctx, problem, theta, n_init))
    if free:
        xs, why = _smoothed_start(problem, theta, x0)
        y0, base, what = None, x0, "the prior mean"
        if xs is not x0:
            sim, taken = _better_start(ctx, problem, theta, (hold, u_sim), xs, x0, quiet=True)
            # a taken start is refined only where the record does not judge the
            # accept decision: there every model it compares keeps the smoothed start
            judged = not own or getattr(ctx.settings, "validation", None) is None
            if not startup_transient(problem.arrays[2], sim) or (taken and judged):
                return sim
            y0 = sim                # the better of the smoothed and prior-mean runs
            if taken:
                # the declared graph's states only: an effect's own state (a
                # cold start's initial excess) fitted to a record's outputs
                # would fit that record's start, not the effect
                declared = (ctx.problem or problem).model.states
                free = [n for n in free if n in declared]
                if not free:
                    return sim
                base, what = xs, "the smoothed initial state"
                why = "the free run from the smoothed initial state starts with a transient"
            else:
                why = "the free run from the smoothed initial state fits the record worse " \
                      "than from the prior mean, which starts with a transient"
        # no smoothed start the prior allows, or a poor one: fit one to the outputs
        xs = _fitted_start(ctx, problem, theta, (hold, u_sim), base, free, why, what)
        if xs is not base:
            return _better_start(ctx, problem, theta, (hold, u_sim), xs, base, y0=y0,
                                 y0_from=what)[0]
        if y0 is not None:
            return y0
    return _free_run_from(ctx, problem, theta, (hold, u_sim), x0)


def init_samples(ctx: Context, record=None) -> int:
    """``settings.free_run.init_samples`` (0 where the context's settings
    have no free-run options: a bare context of a caller or a test), as the
    points of ``record`` those first samples span (:func:`window_points`)."""
    n = int(getattr(getattr(ctx.settings, "free_run", None), "init_samples", 0) or 0)
    return window_points(record, n)


def _grid_factor(record) -> int:
    """How many grid points ``record`` has per sample interval: f for a
    record filtered on a grid f times finer than its samples
    (``meta["finer_grid"]``, :meth:`~bondgraph.data.records.Experiment.on_finer_grid`:
    band-limited inputs interpolated, the outputs at every f-th point), else 1."""
    grid = ((getattr(record, "meta", None) or {}).get("finer_grid") or {})
    return max(int(grid.get("factor", 1)), 1)


def window_points(record, n: int) -> int:
    """The points of ``record`` that its first ``n`` samples span: ``n``, or
    (n − 1)·f + 1 on a record on a grid f times finer than its samples
    (:func:`_grid_factor`; a window of 20 samples counted in grid points
    would set the start from 10)."""
    f = _grid_factor(record)
    return (n - 1) * f + 1 if n and f > 1 else n


def samples_after(record, n: int) -> int:
    """The samples of ``record`` after its first ``n`` (grid points of a
    finer grid, :func:`_grid_factor`, not counted)."""
    f = _grid_factor(record)
    return max((len(record.t) - window_points(record, n) + f - 1) // f, 0)


def window_start(ctx: Context, problem: Problem, theta: np.ndarray, n: int) -> np.ndarray:
    """The start (n_x,) of a free run on a record that judges, given only its
    first ``n`` samples (``settings.free_run.init_samples``; the benchmark
    protocol of nonlinearbenchmark.org, whose ``n_init`` samples may set
    the state and whose error runs over the rest): x̂_0 of the unscented
    RTS smoother (Särkkä 2008) over those samples at ``theta``, with the
    whole record's prior (mean and spread), for the states the record does
    not give; the prior mean where that smoother fails or its start lies
    where the prior puts no weight (:func:`_smoothed_start`; logged).

    The loop's own rule (:func:`free_run`) smooths over the whole judging
    record; without process noise that is a least-squares start over every
    sample, which moves a measured state away from its reading to cancel a
    model's misfit (the EMPS pulses run: a position start 1.3 cm from the
    encoder's reading for a model without Coulomb friction)."""
    n = int(min(n, problem.t.size))
    ukf = problem.ukf.uniform() if problem.ukf.refine else problem.ukf
    head = replace(problem, t=problem.t[:n], u=problem.u[:n], y=problem.y[:n], ukf=ukf)
    xs, why = _smoothed_start(head, theta, problem.x0)
    if xs is problem.x0:
        ctx.log_once("window start", f"  {problem.name}: no start from its first {n} samples"
                     f"{' (' + why + ')' if why else ''}: the free run starts at the prior mean")
    return xs


#: most free runs of the output-error fit of an initial state (:func:`_fitted_start`)
START_FIT_NFEV = 30
#: that fit runs the compiled fixed-step free run (:func:`fine_free_run`) where,
#: from the start it moves from, its residuals agree with the loop's own free
#: run's within this RMS (in output std): the LSODA runs with a Python
#: right-hand side were 89 % of a discovery loop's time; where they differ
#: more, the loop's own run polishes the start found, with at most
#: START_POLISH_NFEV runs
FAST_START_AGREEMENT, START_POLISH_NFEV = 1e-3, 5
#: a free run starts with a transient when its RMS error over the first
#: START_HEAD of the record exceeds START_RATIO times that over the rest
START_HEAD, START_RATIO = 0.1, 2.0


def _mean_square(e: np.ndarray) -> float:
    """Mean of ``e``² over its finite entries (NaN when it has none,
    without numpy's "Mean of empty slice" warning: a free run that failed
    over a whole part of the record has no error there)."""
    e = e[np.isfinite(e)]
    return float(np.mean(e * e)) if e.size else float("nan")


def startup_transient(y: np.ndarray, sim: np.ndarray | None) -> bool:
    """Whether the free run ``sim`` (N, n_y) of the record ``y`` (N, n_y;
    NaN where missing) starts with a transient its start caused: its RMS
    error, each output in units of its std, over the first
    :data:`START_HEAD` of the samples exceeds :data:`START_RATIO` times the
    RMS over the rest (a wrong initial state shows as an error that decays
    with the model's own time constants). A run that failed: False (the
    stability checks judge it)."""
    if sim is None or len(y) < 20:
        return False
    h = max(int(START_HEAD * len(y)), 2)
    seen = np.isfinite(y)
    cols = [j for j in range(y.shape[1]) if seen[:h, j].any() and seen[h:, j].sum() > 1]
    if not cols:
        return False
    y, sim = y[:, cols], np.asarray(sim, float)[:, cols]
    with np.errstate(all="ignore"):
        sd = np.nanstd(y, axis=0)
        e = (sim - y) / np.where(sd > 0, sd, 1.0)
        head, tail = _mean_square(e[:h]), _mean_square(e[h:])
    if not (np.isfinite(head) and np.isfinite(tail)):
        return False
    return bool(head > START_RATIO ** 2 * tail)


def _fitted_start(ctx: Context, problem: Problem, theta: np.ndarray, held: tuple,
                  x0: np.ndarray, states: Sequence[str], why: str | None,
                  x0_is: str = "the prior mean") -> np.ndarray:
    """The initial state whose free run fits the record's outputs best:
    the states ``states`` (those nothing gives) by nonlinear least
    squares (:func:`scipy.optimize.least_squares`, trust-region reflective,
    forward-difference Jacobian, at most :data:`START_FIT_NFEV` runs; started
    again off a kink that holds the prior mean, :func:`_restarted_search`) on the
    free-run error over the whole record, each output weighted by its std
    (the NRMSE's weights; :func:`_start_residuals`); the others stay at
    the prior mean ``x0``. This is the initial-condition estimate of
    prediction-error validation (Ljung 1999, §14.3; MATLAB's ``compare``
    estimates it by default). Used when the RTS-smoothed start is
    unavailable or beyond the prior's gate (:func:`_smoothed_start`):
    without process noise a smoother run backwards through contracting
    dynamics amplifies its gains (a user's DC motor: p_J = 6.5e9 against a
    spread of 0.1 on a held-out quarter that starts mid-motion), and the
    prior mean (at rest) then charged the model a start-up transient that
    was not its own: a Stribeck refit's held-out error read 0.064 where
    the Coulomb model it was judged against read 0.0097 from a smoothed
    start. The runs are the loop's own free run
    (:func:`_free_run_from`, the same method and hold as the error it
    starts): the start must be the best for the error reported; the search
    runs the compiled fixed-step one (:func:`fine_free_run`), and the
    loop's own polishes and judges the start it finds
    (:func:`_start_search`). ``x0`` is the start the fit
    moves from (the prior mean, or a smoothed start: ``x0_is`` names it in
    the log). Returns ``x0`` itself when the fit fails or does not improve
    on it. One line logged when ``why`` (the smoothed start's fault) is
    given: why, and the start taken."""
    idx = [problem.model.states.index(n) for n in states]
    residuals = _start_residuals(ctx, problem, theta, held, x0, idx)
    if residuals is None:
        return x0
    r0 = residuals(np.zeros(len(idx)))
    try:
        z, cost, runs = _start_search(ctx, residuals, len(idx), r0)
        improved = bool(np.all(np.isfinite(z)) and cost < 0.5 * float(r0 @ r0))
        if not improved or np.any(np.abs(z) < STUCK_START):
            z, cost, runs = _restarted_search(ctx, residuals, len(idx), r0, (z, cost, runs),
                                              improved)
    except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
        if why:
            ctx.log(f"  {why}; fitting one to the outputs failed ({str(exc).splitlines()[0]}): "
                    f"the free run starts from {x0_is}")
        return x0
    if not (np.all(np.isfinite(z)) and cost < 0.5 * float(r0 @ r0)):
        if why:
            ctx.log(f"  {why}; the one fitted to the outputs does not improve on {x0_is}: "
                    f"the free run starts there")
        return x0
    xi = x0.copy()
    xi[idx] = x0[idx] + z * _prior_sd(problem, idx)
    if why:
        ctx.log_once(f"fitted start: {why.split(' (')[0]}",
                     f"  {why}; the free run starts from the one fitted to the outputs "
                     f"{prior_distance_text(problem, xi)} (output error, {runs} runs)")
    return xi


#: the steps [prior std] of :func:`_restarted_search`'s sweep along each
#: state, the next tried where neither way of the first lowers the error
RESTART_STEPS = (1.0, 0.5, 0.25)
#: at most this many sweeps of :func:`_restarted_search`
RESTART_ROUNDS = 3
#: a state the fitted start's least squares moved by less than this many
#: prior std from the prior mean is taken as held there by a kink
#: (:func:`_restarted_search`)
STUCK_START = 1e-6


def _restarted_search(ctx: Context, residuals, n: int, r0: np.ndarray, first: tuple,
                      improved: bool = False) -> tuple:
    """``(z, cost, runs)``: :func:`_fitted_start`'s least squares again,
    where the search from z = 0 (``first``, its ``(z, cost, runs)``) did
    not lower the error or left a state within :data:`STUCK_START` of its
    prior mean (``improved``: it lowered the error; the sweep then starts
    from its end and runs along those states only), from the point an
    exploratory sweep reaches (Hooke & Jeeves 1961): along each state in
    turn, a step of one prior
    std either way (where neither lowers the error, half and a quarter of
    it, :data:`RESTART_STEPS`) is kept where it lowers the error (the
    compiled run where it runs, else the loop's own); at most
    :data:`RESTART_ROUNDS` sweeps, each followed by the least squares, while
    they lower the error. A prior mean on the boundary of a law's domain
    is a kink where the error rises for any small step, so that no local
    search leaves it (a user's two tanks, the prior mean empty, outflows
    a·√q: a step of 1e-7 prior std along the lower tank's level raised the
    error, one of 0.1 lowered it; the search stopped at 0 after 19 runs,
    and the held-out free run from empty tanks read NRMSE 0.427 where a
    start at the record's level reads 0.209); a search that moves the other
    states stays on the kink of one. ``first`` is returned where no sweep
    lowers the error."""
    fast = residuals(np.zeros(n), True)
    fast = fast is not None and bool(np.all(np.abs(fast) < 1e6))
    z, cost = (np.asarray(first[0], float), first[1]) if improved else \
        (np.zeros(n), 0.5 * float(r0 @ r0))
    axes = np.flatnonzero(np.abs(z) < STUCK_START) if improved else np.arange(n)
    runs, found = first[2], False
    for _ in range(RESTART_ROUNDS):
        zs, _, k = _sweep(residuals, z, cost, fast, axes)
        runs += k
        if zs is None:
            break
        zn, cn, more = _start_search(ctx, residuals, n, residuals(zs), zs)
        runs += more + 1
        if not (np.all(np.isfinite(zn)) and cn < cost):
            break
        z, cost, found = zn, cn, True
    return (z, cost, runs) if found else (first[0], first[1], runs)


def _sweep(residuals, z: np.ndarray, cost: float, fast: bool, axes) -> tuple:
    """``(z', cost', runs)``: :func:`_restarted_search`'s exploratory sweep
    from ``z`` (its error ``cost`` = ½‖r‖²) along the states ``axes``; z'
    None where no step lowers the error."""
    z, runs, moved = z.copy(), 0, False
    for i in axes:
        for h in RESTART_STEPS:
            best = None
            for step in (h, -h):
                zi = z.copy()
                zi[i] += step
                r = residuals(zi, fast)
                runs += 1
                c = 0.5 * float(r @ r) if np.all(np.isfinite(r)) else np.inf
                if c < cost:
                    best, cost = zi, c
            if best is not None:
                z, moved = best, True
                break
    return (z if moved else None), cost, runs


def _start_search(ctx: Context, residuals, n: int, r0: np.ndarray,
                  z0: np.ndarray | None = None) -> tuple:
    """``(z, cost, runs)`` of :func:`_fitted_start`'s least squares from
    ``z0`` (default z = 0; ``r0``: the loop's own run's residuals there):
    where the compiled fixed-step run (``residuals(z, True)``) is finite at
    ``z0``, the search runs it (:data:`START_FIT_NFEV`); its end is taken as
    it is where that run agrees with the loop's own at ``z0`` within
    :data:`FAST_START_AGREEMENT` or the loop's own fails there, else the
    loop's own polishes it (:data:`START_POLISH_NFEV`). Without it, the
    loop's own searches from ``z0``. ``cost`` is ½‖r‖² of the loop's own run.

    Raises
    ------
    ValueError, LinAlgError, FloatingPointError
        The least squares fails.
    """
    from scipy.optimize import least_squares

    z, runs, most = (np.zeros(n) if z0 is None else np.asarray(z0, float)), 0, START_FIT_NFEV
    own = getattr(getattr(getattr(ctx, "settings", None), "free_run", None), "method", None)
    rf = residuals(z, True) if own != "fine" else None
    if rf is not None and np.all(np.abs(rf) < 1e6):
        with np.errstate(over="ignore"):    # a far trial step's residuals: its cost is inf
            fit = least_squares(lambda v: residuals(v, True), z, method="trf", x_scale="jac",
                                max_nfev=START_FIT_NFEV)
        if np.all(np.isfinite(fit.x)):
            z, runs, most = fit.x, fit.nfev, START_POLISH_NFEV
            if np.any(np.abs(r0) >= 1e6) or _rms(rf - r0) <= FAST_START_AGREEMENT:
                r = residuals(z)
                return z, 0.5 * float(r @ r), runs + 1
    with np.errstate(over="ignore"):
        fit = least_squares(residuals, z, method="trf", x_scale="jac", max_nfev=most)
    return fit.x, fit.cost, runs + fit.nfev


def _rms(r: np.ndarray) -> float:
    """RMS of a residual vector (inf where it is not finite or empty)."""
    r = np.asarray(r, float)
    return float(np.sqrt(np.mean(r * r))) if r.size and np.all(np.isfinite(r)) else np.inf


def _prior_sd(problem: Problem, idx) -> np.ndarray:
    """The prior std of the states ``idx`` (the unit of the start's search)."""
    return np.sqrt(np.maximum(np.diag(problem.P0)[idx], 1e-300))


def _start_residuals(ctx: Context, problem: Problem, theta: np.ndarray, held: tuple,
                     x0: np.ndarray, idx: list):
    """``residuals(z, fast=False)`` of :func:`_fitted_start`: the free-run
    error on the measured samples from ``x0`` with the states ``idx`` moved
    by ``z`` prior std, each output over its std (1e6 where the run fails
    or is not finite); the loop's own free run (:func:`_free_run_from`), or
    with ``fast`` the compiled fixed-step one (:func:`fine_free_run`).
    None when nothing is measured."""
    y = problem.arrays[2]
    mask = np.isfinite(y)
    if not mask.any():
        return None
    scale = np.array([np.nanstd(y[:, i]) if mask[:, i].sum() > 1 else 1.0
                      for i in range(y.shape[1])])
    scale = np.where(np.isfinite(scale) & (scale > 0), scale, 1.0)
    sd = _prior_sd(problem, idx)

    def residuals(z, fast: bool = False):
        xi = x0.copy()
        xi[idx] = x0[idx] + z * sd
        with np.errstate(all="ignore"):
            if fast:
                try:
                    sim = fine_free_run(problem, held[1], held[0], theta, xi)
                except Exception:   # a model the compiled run cannot step
                    sim = None
            else:
                sim = _free_run_from(ctx, problem, theta, held, xi, quiet=True)
        if sim is None:
            return np.full(int(mask.sum()), 1e6)
        r = ((sim - y) / scale)[mask]
        return np.where(np.isfinite(r), r, 1e6)
    return residuals


def _free_run_from(ctx: Context, problem: Problem, theta: np.ndarray, held: tuple,
                   x0: np.ndarray, quiet: bool = False) -> np.ndarray | None:
    """The free run (N, n_y) of :func:`free_run` from ``x0`` (n_x,), inputs
    ``held`` = (hold, u); None (logged unless ``quiet``) if it fails."""
    t = problem.arrays[0]
    hold, u_sim = held
    try:
        if ctx.settings.free_run.method == "fine":
            return fine_free_run(problem, u_sim, hold, theta, x0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sim = simulate(problem.model, t, u_sim, x0=x0, theta=theta,
                           method=ctx.settings.free_run.method,
                           rtol=1e-6, atol=1e-9, hold=hold, backend=problem.disc.backend)
        return sim.y
    except Exception as exc:  # a model that cannot be simulated freely
        if not quiet:
            ctx.log(f"  free-run simulation failed ({str(exc).splitlines()[0]})")
        return None


def _better_start(ctx: Context, problem: Problem, theta: np.ndarray, held: tuple,
                  xs: np.ndarray, x0: np.ndarray, quiet: bool = False,
                  y0: np.ndarray | None = None,
                  y0_from: str = "the prior mean") -> tuple[np.ndarray | None, bool]:
    """``(sim, True)``: the free run from the start ``xs``, unless the one
    from ``x0`` (the prior mean, or the start ``y0_from`` names; ``y0``, its
    run, when already made) has the lower free-run NRMSE on the record's outputs
    (:func:`~bondgraph.diagnose.metric.nrmse`): then ``(its run, False)``,
    logged unless ``quiet``. A run from ``xs``
    that fails or is not finite where the record is measured is returned as
    it is: the stability checks see it, a finite run from elsewhere does not
    hide it. The smoother's start is the best in the filter's sense, but
    without process noise, through strongly contracting dynamics, it can be
    far off while still inside the prior's gate of :func:`_smoothed_start`:
    on two overflowing tanks the same fit's held-out free-run error was
    0.021 or 0.109 depending on the last bit of the kernels' arithmetic,
    which put the smoothed start on one side of that gate or the other."""
    y = problem.arrays[2]

    def failed(sim) -> bool:
        return sim is None or bool((np.isfinite(y) & ~np.isfinite(sim)).any())

    ys = _free_run_from(ctx, problem, theta, held, xs)
    if failed(ys):
        return ys, True
    if y0 is None:
        y0 = _free_run_from(ctx, problem, theta, held, x0, quiet=True)
    if failed(y0):
        return ys, True
    with np.errstate(all="ignore"):
        if nrmse(y, y0) < nrmse(y, ys):
            if not quiet:
                ctx.log(f"  the free run from {y0_from} fits the record better than from "
                        f"the fitted initial state: it starts there")
            return y0, False
    return ys, True


#: a smoothed initial state whose squared Mahalanobis distance from the prior
#: mean exceeds χ²(n_x) at this tail probability is not a start the model's
#: prior allows (:func:`_smoothed_start`)
SMOOTHED_START_LEVEL = 1e-20


def _smoothed_start(problem: Problem, theta: np.ndarray,
                    fallback: np.ndarray) -> tuple[np.ndarray, str | None]:
    """``(x̂_0|N, None)`` of ``problem``'s record at ``theta``
    (:func:`~bondgraph.diagnose.inference_calls.smoothed_initial_state`);
    ``(fallback, why)`` if the smoother fails, is not finite (``why`` empty:
    a backward pass that blew up, said nowhere), or lies
    where the prior N(``problem.x0``, ``problem.P0``) puts no weight: its
    squared Mahalanobis distance over the states not estimated with θ
    beyond χ²(their number) at
    :data:`SMOOTHED_START_LEVEL`. Without process noise, a smoother that
    runs backwards through strongly contracting dynamics (an overflow that
    drains any excess within one sample) amplifies its gains: on two
    overflowing tanks into a measured collector it put the tanks at 13.5
    and −11.9 m³ (213 and 370 prior std; their flows cancel in the
    collector), and the free run from there left the measured range 35-fold
    although from the prior mean it fits the record."""
    try:
        xs = smoothed_initial_state(problem, theta)
    except SmootherRestartError as exc:     # expected without process noise: said as such
        return fallback, str(exc).splitlines()[0]
    except BondGraphError as exc:
        return fallback, f"smoothed initial state unavailable ({str(exc).splitlines()[0]})"
    if not np.all(np.isfinite(xs)):
        return fallback, ""         # a blown-up backward pass: nothing to say (as before)
    free = [i for i, n in enumerate(problem.model.states) if n not in problem.prior.estimated]
    d = (xs - problem.x0)[free]
    with np.errstate(over="ignore", invalid="ignore"):   # a far start: inf, refused below
        d2 = float(d @ np.linalg.pinv(problem.P0[np.ix_(free, free)]) @ d)
    d2 = d2 if np.isfinite(d2) else np.inf
    if d2 > chi2.isf(SMOOTHED_START_LEVEL, max(len(free), 1)):
        return fallback, (f"smoothed initial state {prior_distance_text(problem, xs)} is "
                          f"{np.sqrt(d2):.3g} prior std from the prior mean (beyond "
                          f"χ²({len(free)}) at {SMOOTHED_START_LEVEL:g})")
    return xs, None


def prior_distance_text(problem: Problem, xs: np.ndarray) -> str:
    """``x̂_0|N`` (n_x,) as ``"(state = value, ...)"`` for the states furthest
    from the prior mean (at most 3, by prior std)."""
    z = np.abs(xs - problem.x0) / np.sqrt(np.maximum(np.diag(problem.P0), 1e-300))
    top = np.argsort(-z)[:3]
    return "(" + ", ".join(f"{problem.model.states[i]} = {xs[i]:.4g}" for i in top) + ")"


def parameter_std(ctx: Context, fit: Fit) -> dict:
    """Cramér-Rao standard deviations of the estimated parameters: those of
    the last scoring step if complete, else from a batched difference Hessian
    (relative step 1e-4); {} (logged) if unavailable."""
    if not fit.params:
        return {}
    if fit.std and all(n in fit.std for n in fit.params):
        return fit.std
    crit = criterion_for(ctx, fit.model, fit.params, fit.theta)
    x = np.array([fit.theta[fit.model.param_index(n)] for n in fit.params])
    h = 1e-4 * np.maximum(np.abs(x), 1e-6)
    try:
        cr = hessian_cramer_rao(crit, x, h, fit.params)
        return {n: (float(v) if v is not None and np.isfinite(v) and n not in fit.at_bound
                    else None)
                for n, v in zip(fit.params, cr.get("std", [None] * len(fit.params)))}
    except Exception as exc:
        ctx.log(f"  Cramér-Rao bounds unavailable ({str(exc).splitlines()[0]})")
        return {}


#: the substeps :func:`recommended_substeps` tries: those of the first
#: choice (:data:`bondgraph.inference.discretise.SUBSTEPS`, steps of 1.5 and
#: 2), then 24 and 32 (one step per sample of ROS2 at 0.3 noise stds on the
#: coast-down record needs 3 substeps, 0.088 σ, where the powers of two took
#: 4: a quarter of every later filter run saved)
SUBSTEP_LADDER = tuple(n for n in SUBSTEPS if n > 1) + (24, 32)


@dataclass(frozen=True)
class StepCheck:
    """The loop's discretisation check at a fit (:func:`recommended_substeps`).

    Attributes
    ----------
    worst : float
        The filter's largest one-step output error [noise stds per sample].
    n : int or None
        The fewest substeps of :data:`SUBSTEP_LADDER` (above the current
        ones) within the check; None when it passes already or none does.
    bias : float
        The free run's bias [Cramér-Rao std] where the filter predicts by
        the free run (:func:`predicts_by_free_run`: no process noise, or
        the free-run likelihood's floor); NaN where it does not (not a
        criterion). Its output error projected onto the sensitivities of
        the parameters the fit estimates (:func:`bias_directions`; the
        error's whole norm where the fit does not say), a bound of each
        one's shift. A one-step error of a few hundredths of σ adds up over
        the record: a mass-spring-damper at ω·dt = 0.25, ROS2(8) 0.068 σ
        per sample, bias 35.4, its stiffness estimated 34 std off.
    limit, bias_limit : float
        The check's bounds.
    n_unbiased : int or None
        Where the bias is above its bound: the fewest substeps of the ladder
        that bring both within (None if none up to 32 do). The loop adopts
        ``n`` (the one-step bound: on a long precise record the bias in
        Cramér-Rao std grows as √N, and the user's Silverbox graph took
        RK4(2), then 4, for a bias of 3-6 std: 4.5 times the time, the
        held-out errors no lower); the bias is said, with these substeps.
    """

    worst: float
    n: int | None = None
    bias: float = float("nan")
    limit: float = 0.1
    bias_limit: float = BIAS_TOLERANCE
    n_unbiased: int | None = None

    @property
    def failed(self) -> bool:
        """The current discretisation is outside the check."""
        return bool(self.worst > self.limit or self.bias > self.bias_limit)

    @property
    def step_failed(self) -> bool:
        """Outside the one-step bound (what the loop adopts substeps for)."""
        return bool(self.worst > self.limit)

    def text(self) -> str:
        """``", its free-run bias bound 35.7 Cramér-Rao std"`` where that
        fails the check, else empty."""
        if not self.bias > self.bias_limit:
            return ""
        out = (f" and its free-run bias bound {self.bias:.3g} Cramér-Rao std (above "
               f"{self.bias_limit:g}: without process noise the filter predicts by the free "
               f"run, and the estimates may be off by up to that; ")
        return out + (f"{self.n_unbiased} substeps bring it within)" if self.n_unbiased
                      else f"no substeps up to {SUBSTEP_LADDER[-1]} bring it within)")


def predicts_by_free_run(ctx: Context, pb: Problem, theta: np.ndarray) -> bool:
    """The filter of ``pb`` at ``theta`` predicts by the free run: it has no
    process noise, or the loop fits by the free-run likelihood (its process
    noise held at a floor, :func:`process_noise_floor`); the discretisation
    check then bounds the free run's bias too (:class:`StepCheck`)."""
    return ctx.settings.search.likelihood == "free_run" or no_process_noise(pb.model, theta)


#: the forward-difference step of the free-run bias's sensitivities, relative
#: to a parameter's magnitude (or, at 0, to its box's width)
SENSITIVITY_STEP = 1e-6


def bias_directions(pb: Problem, fit) -> np.ndarray | None:
    """The steps (p, n_theta) along which :func:`first_within` projects the
    free run's error: one per parameter ``fit`` estimates that the model has
    (:data:`SENSITIVITY_STEP` of its magnitude, of its box's width at 0);
    None when ``fit`` does not say what it estimates (the bias is then the
    bound, the error's whole norm)."""
    names = [n for n in (getattr(fit, "params", None) or []) if n in pb.model.params]
    if not names:
        return None
    th = np.asarray(fit.theta, float)
    lo, hi = pb.model.bounds(names)
    out = np.zeros((len(names), th.size))
    for i, (n, a, b) in enumerate(zip(names, lo, hi)):
        j = pb.model.params.index(n)
        width = b - a if np.isfinite(b - a) and b > a else 1.0
        out[i, j] = SENSITIVITY_STEP * (abs(th[j]) if th[j] != 0 else width)
    return out


def first_within(pb: Problem, theta: np.ndarray, discs: list, sig: np.ndarray, ref: dict,
                 free: bool, limit: float = 0.1, bias: float = BIAS_TOLERANCE,
                 directions=None) -> tuple[Discretisation | None, list]:
    """``(disc, one_step)``: the first of ``discs`` whose one-step error at
    ``theta`` is within ``limit`` noise stds per sample and, with ``free``
    (:func:`predicts_by_free_run`), whose free-run bias is within ``bias``
    Cramér-Rao std (computed only for those within the first; projected
    onto the sensitivities along ``directions``, :func:`bias_directions`),
    or None; and every candidate's one-step error."""
    ones = [o for o, _ in step_errors(pb, theta, discs, sig, ref)] if discs else []
    for d, o in zip(discs, ones):
        if o <= limit and (not free or step_errors(pb, theta, [d], sig, ref, True,
                                                   directions)[0][1] <= bias):
            return d, ones
    return None, ones


def recommended_substeps(ctx: Context, fit: Fit, limit: float = 0.1) -> StepCheck:
    """The discretisation check at ``fit`` (:class:`StepCheck`): the
    filter's largest one-step discretisation error in noise stds per sample
    (:func:`~bondgraph.diagnose.fit.error_scale`), where the filter predicts
    by the free run (:func:`predicts_by_free_run`) its free-run bias bound
    too (the criteria of
    :func:`bondgraph.inference.discretise.choose_discretisation`), and the
    fewest substeps of :data:`SUBSTEP_LADDER` (above the current ones) that
    bring the one-step error within (None if it is already, or none does;
    the loop adopts those) and, where the bias is above its bound, both
    (:attr:`StepCheck.n_unbiased`, said)."""
    pb = problem_for(ctx, fit.model)
    sig, ref = error_scale(pb, fit), {}      # one fine reference for every substeps tried
    free = predicts_by_free_run(ctx, pb, fit.theta)
    dirs = bias_directions(pb, fit) if free else None
    worst, bias = step_errors(pb, fit.theta, [pb.disc], sig, ref, free, dirs)[0]
    check = StepCheck(worst, None, bias if free else float("nan"), limit)
    if not check.failed:
        return check
    more = [replace(pb.disc, substeps=n) for n in SUBSTEP_LADDER if n > pb.disc.substeps]
    step = first_within(pb, fit.theta, more, sig, ref, False, limit)[0] if worst > limit else None
    both = (first_within(pb, fit.theta, more, sig, ref, True, limit, directions=dirs)[0]
            if check.bias > check.bias_limit else None)
    return replace(check, n=None if step is None else step.substeps,
                   n_unbiased=None if both is None else both.substeps)


def disc_cost(disc: Discretisation, intervals: int) -> float:
    """``disc``'s cost per sample in f evaluations
    (:func:`~bondgraph.inference.discretise.step_cost`) over ``intervals``
    sample intervals: a refinement's mean substeps."""
    mean = float(np.mean(disc.interval_substeps(intervals))) if disc.refine else disc.substeps
    return step_cost(disc.method, mean)


def other_method_step(ctx: Context, fit: Fit, below: float, limit: float = 0.1,
                      unbiased: bool = False) -> Discretisation | None:
    """With ``settings.search.auto_method``: the other method (RK4 for ROS2,
    ROS2 for RK4) with the fewest substeps (1, then
    :data:`SUBSTEP_LADDER`) whose one-step discretisation error at ``fit`` is
    within ``limit`` noise stds per sample (the bound the loop adopts
    substeps for, as :func:`recommended_substeps` measures it), with
    ``unbiased`` whose free-run bias is within its bound too (where the
    filter predicts by the free run, :func:`first_within`), and whose cost per sample
    (:func:`~bondgraph.inference.discretise.step_cost`) is below ``below``;
    uniform (no refinement), the hold and backend kept. None when the method
    may not change, or none is cheaper and within. A step RK4 cannot take
    (a fast mode outside its stability region) is not finite and fails the
    check. The order of an RK4 step (4) makes it the cheaper one where the
    error, not the stiffness, sets ROS2's substeps: on the CED drive with its
    sensor low-pass at 17 ms, ROS2 needed 16 substeps per 20 ms sample (0.095
    σ), RK4 3 (0.06 σ)."""
    if not ctx.settings.search.auto_method:
        return None
    pb = problem_for(ctx, fit.model)
    d = pb.disc
    other = {"ros2": "rk4", "rk4": "ros2"}.get(d.method)
    ladder = [n for n in (1,) + SUBSTEP_LADDER if step_cost(other, n) < below] if other else []
    if not ladder:
        return None
    discs = [replace(d, method=other, substeps=int(n), refine=()) for n in ladder]
    free = unbiased and predicts_by_free_run(ctx, pb, fit.theta)
    with np.errstate(all="ignore"):
        found, _ = first_within(pb, fit.theta, discs, error_scale(pb, fit), {}, free, limit,
                                directions=bias_directions(pb, fit) if free else None)
    return found


def adopted_discretisation(ctx: Context, fit: Fit,
                           check: StepCheck) -> tuple[Discretisation | None, str]:
    """``(discretisation, text)`` the loop takes when the check at ``fit``
    fails (``check``, :func:`recommended_substeps`: ``check.n`` substeps of
    the current method within it, None if none): ``n`` on the intervals that
    need them or throughout (:func:`refined_discretisation`), or the other
    method where it meets the check at a lower cost per sample
    (:func:`other_method_step`, with ``settings.search.auto_method``);
    ``text`` says what (``"16 substeps per sample"``, ``"rk4 with 3
    substeps per sample in place of ros2 ..."``).
    ``(None, "")`` when neither meets the check.

    The other method replaces those substeps only where it meets every
    bound they meet: where ``n`` substeps bring the free-run bias within
    its bound too (``check.n_unbiased`` ≤ ``n``), the other method must as
    well. A step within the one-step bound alone can still shift the
    estimates by many Cramér-Rao std (a user's EMPS graph on every tenth
    sample with a Coulomb friction: RK4 stable and unbiased from 6
    substeps, ROS2(1) within the one-step bound, 4 f evaluations per
    sample instead of 24; the refit at ROS2(1) moved the friction law's
    width, its held-out error decrease fell from significant to z 0.69, and
    the loop rejected the friction the record needs)."""
    n = check.n
    disc, how = refined_discretisation(ctx, fit, n) if n is not None else (None, "")
    text = f"{n} substeps per sample{how}" if disc is not None else ""
    if not ctx.settings.search.auto_method:
        return disc, text
    pb = problem_for(ctx, fit.model)
    M = pb.t.size - 1
    unbiased = n is not None and check.n_unbiased is not None and check.n_unbiased <= n
    alt = other_method_step(ctx, fit, np.inf if disc is None else disc_cost(disc, M),
                            unbiased=unbiased)
    if alt is None:
        return disc, text
    d = pb.disc
    instead = (f"{d.method}({n}) {disc_cost(disc, M):g}" if disc is not None
               else f"{d.method} not within the check with {SUBSTEP_LADDER[-1]} substeps")
    return alt, (f"{alt.method} with {alt.substeps} substep{'s' if alt.substeps > 1 else ''} "
                 f"per sample in place of {d.method}, the cheaper step within the check "
                 f"({disc_cost(alt, M):g} f evaluations per sample; {instead})")


#: a refined discretisation is taken where its intervals' substeps average
#: at most this share of the uniform choice's (:func:`refined_discretisation`)
REFINE_SHARE = 0.75
#: the largest one-step error of an interval at the filter's sigma points
#: that the refinement leaves, in noise stds (a third of the check's 0.1:
#: the uniform choice leaves most intervals far below it)
REFINE_LIMIT = 0.03
#: ... and where its NLL at the fit is within this many nats of the uniform
#: choice's (the likelihood ratio of one degree of freedom at 5 % is 3.84)
REFINE_NLL_TOL = 0.25
#: the margins (intervals either side) tried in turn
REFINE_MARGINS = (REFINE_MARGIN, 4 * REFINE_MARGIN)


def refined_discretisation(ctx: Context, fit: Fit, n: int, limit: float = REFINE_LIMIT,
                           check: float = 0.1) -> tuple[Discretisation, str]:
    """``(discretisation, note)``: what the filter takes where
    :func:`recommended_substeps` asks for ``n`` substeps at ``fit``: the
    current substeps with ``n`` or fewer on the intervals that need them
    (:func:`bondgraph.inference.discretise.refined_runs`, each interval's
    own error at the filter's sigma points within ``limit`` and along the
    check's reference trajectory within ``check``,
    :meth:`Problem.interval_errors`, with a margin either side), where that
    saves at least a quarter of the filter's steps
    (:data:`REFINE_SHARE`) and its NLL at ``fit`` agrees with ``n``
    substeps throughout within :data:`REFINE_NLL_TOL` (errors spread thinly
    over the whole record add up in the NLL where no interval reaches the
    limit: on the coast-down record ROS2(1) is 16 nats from ROS2(3); a
    wider margin is tried before giving up, :data:`REFINE_MARGINS`), and
    where the refined discretisation meets the loop's own check
    (:func:`recommended_substeps`'s largest error within ``check``: the
    loop never goes on with numerics that fail it); else ``n`` throughout.
    ``note`` says which, for the log line (empty for ``n`` throughout)."""
    pb = problem_for(ctx, fit.model)
    d = pb.disc
    uniform = replace(d, substeps=int(n))
    M = pb.t.size - 1
    ladder = [d.substeps] + [k for k in SUBSTEP_LADDER if d.substeps < k <= n]
    if M < 2 * REFINE_MARGIN + 2 or len(ladder) < 2:
        return uniform, ""
    sig = error_scale(pb, fit)
    with np.errstate(all="ignore"):
        both = interval_errors(pb, fit.theta, ladder, sig)
    if both is None:
        return uniform, ""
    # an interval meets both rules where the larger of the two ratios is <= 1
    errors = np.maximum(both[0] / limit, both[1] / check)
    base = d.interval_substeps(M) if d.refine else None
    full = float(np.mean(uniform.interval_substeps(M)))
    nll_uniform = None
    for margin in REFINE_MARGINS:
        runs = refined_runs(errors, ladder, 1.0, margin=margin, base=base)
        if not runs:
            return uniform, ""
        cand = replace(d, refine=runs)
        per = cand.interval_substeps(M)
        if float(np.mean(per)) > REFINE_SHARE * full:
            return uniform, ""
        if nll_uniform is None:
            nll_uniform = float(run_ukf(pb.conditioned_on(disc=uniform),
                                        fit.theta[None, :]).nll[0])
        refined = pb.conditioned_on(disc=cand)
        nll = float(run_ukf(refined, fit.theta[None, :]).nll[0])
        if (np.isfinite(nll_uniform) and abs(nll - nll_uniform) <= REFINE_NLL_TOL
                and first_within(pb, fit.theta, [cand], sig, {}, False, check)[0] is not None):
            k = int(np.count_nonzero(per > d.substeps))
            return cand, (f" on the {k} of {M} intervals that need them ({len(runs)} "
                          f"run{'s' if len(runs) > 1 else ''}, {margin} intervals either side; "
                          f"{d.substeps} elsewhere: the NLL at the fit {nll:.2f}, "
                          f"{nll_uniform:.2f} with {n} throughout)")
    return uniform, ""
