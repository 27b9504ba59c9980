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
import sympy as sp

from bondgraph.core.graph import BondGraph
from bondgraph.diagnose.inference_calls import (
    NOISE_BOX,
    X0_TOKEN,
    fisher_fit,
    hessian_cramer_rao,
    lbfgsb_polish,
    make_criterion,
    plan_noise,
    prior_covariance,
    run_ukf,
    smoothed_initial_state,
    state_prior,
)
from bondgraph.diagnose.metric import compute_metric, metric_errors
from bondgraph.diagnose.residuals import analyze
from bondgraph.diagnose.result import FitSummary
from bondgraph.diagnose.settings import LoopSettings
from bondgraph.errors import BondGraphError, NumericalError
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate

#: generated functions of every model the loop builds
CANDIDATE_FUNCTIONS = ("f", "h", "dfdx", "f_dfdx")
#: those generated only when first used (most candidates run on their
#: compiled kernels and never need the numpy Jacobians)
LAZY_FUNCTIONS = ("dfdx", "f_dfdx")


class Record:
    """The measured record, resolved for one model at a time.

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
    """What every step of the loop reads: the record, the settings, the
    (time-stamped) line logger, whether progress bars are shown, and a cache
    (the state-scaled priors of the models seen), the initial states
    estimated with the current fit (``settings.estimate_x0``; by name), which
    every later filter run conditions on, and the executor the candidates'
    scoring and confirmations run on (None: in process;
    :mod:`bondgraph.diagnose.parallel`)."""

    record: Record
    settings: LoopSettings
    log: Callable[[str], None] = print
    progress: bool = True
    cache: dict = field(default_factory=dict)
    x0_estimates: dict = field(default_factory=dict)
    executor: Any = None


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
    ``std`` as ``noise.<output>``)."""

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
    noise_est: dict = field(default_factory=dict)

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
                          self.validation_metric, dict(self.x0_est), dict(self.noise_est))

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


def prior_mean(ctx: Context, model: Model) -> np.ndarray:
    """UKF prior mean x0 (n_x,): ``settings.x0`` if it fits the model, else
    the record's initial state (:meth:`bondgraph.data.records.Experiment.initial_state`:
    state columns, else the sidecar's x0, else the model's X0), with
    ``settings.x0_overrides`` (by state name) imposed."""
    x = None
    if ctx.settings.x0 is not None:
        x = np.asarray(ctx.settings.x0, dtype=float)
        x = x.copy() if x.shape == (model.n_x,) else None
    if x is None:
        x = np.asarray(ctx.record.exp.initial_state(model), dtype=float).copy()
    for name, v in {**(ctx.settings.x0_overrides or {}), **ctx.x0_estimates}.items():
        if name in model.states:
            x[model.state_index(name)] = float(v)
    return x


def prior_cov(ctx: Context, model: Model, x0: np.ndarray) -> np.ndarray:
    """UKF prior covariance (n_x, n_x): ``settings.P0`` if it fits the model
    (a vector is a diagonal), else the default (``settings.p0_rel``, default
    5 %, of max(|x0|, 1)), with the
    standard deviations of ``settings.P0_std`` (by state name) imposed, e.g. a
    level test track: {"theta_g": 0.002}."""
    s = ctx.settings
    if s.P0 is not None:
        P = np.asarray(s.P0, dtype=float)
        if P.shape in ((model.n_x,), (model.n_x, model.n_x)):
            return np.diag(P) if P.ndim == 1 else P
        # states added by effects: fall back to the default variance
    if s.p0_scale == "state":
        P = _state_prior(ctx, model, x0)
    else:
        P = prior_covariance(model, x0, s.p0_rel)
    for name, sd in (s.P0_std or {}).items():
        if name in model.states:
            i = model.state_index(name)
            P[i, :] = 0.0
            P[:, i] = 0.0
            P[i, i] = float(sd) ** 2
    return P


def _state_prior(ctx: Context, model: Model, x0: np.ndarray) -> np.ndarray:
    """:func:`~bondgraph.diagnose.inference_calls.state_prior` at the model's
    defaults with ``settings.fixed``, the states of :func:`unknown_states`
    with the spread of their whole scale, cached per model and prior mean
    (every candidate's model asks again)."""
    key = (id(model), x0.tobytes())
    if key not in ctx.cache:
        theta = model.theta0.copy()
        for k, v in ctx.settings.fixed.items():
            if k in model.params:
                theta[model.param_index(k)] = v
        t, u, y = ctx.record.arrays(model)
        ctx.cache[key] = (model, state_prior(model, t, u, y, theta, x0, ctx.settings,
                                             ctx.record.exp.initial_state_std(model),
                                             unknown_states(ctx, model)))
    return ctx.cache[key][1].copy()


def unknown_states(ctx: Context, model: Model) -> list[str]:
    """The states of ``model`` whose initial value on ``ctx.record`` nothing
    gives: not in the record (state column, sidecar ``x0``/``x0_std``), not
    set by the user (``settings.x0``, ``x0_overrides``) nor declared
    (``settings.P0_std``). Their prior mean is the model's X0, a guess."""
    s = ctx.settings
    if s.x0 is not None:
        return []
    given = set(ctx.record.exp.given_initial_states(model)) | set(s.x0_overrides or {}) \
        | set(s.P0_std or {})
    return [n for n in model.states if n not in given]


def prior(ctx: Context, model: Model, shrink: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The UKF prior (x0, P0) of ``model``: :func:`prior_mean`, :func:`prior_cov`;
    the initial states estimated with the current fit (``ctx.x0_estimates``)
    at their estimates with a token spread (X0_TOKEN of their prior std:
    the likelihood is conditional on them) unless ``shrink`` is False."""
    x0 = prior_mean(ctx, model)
    P = prior_cov(ctx, model, x0)
    if shrink:
        for name in ctx.x0_estimates:
            if name in model.states:
                i = model.state_index(name)
                sd = X0_TOKEN * math.sqrt(max(P[i, i], 0.0))
                P[i, :] = 0.0
                P[:, i] = 0.0
                P[i, i] = sd ** 2
    return x0, P


def x0_states(ctx: Context, model: Model) -> list[str]:
    """The initial states of ``model`` estimated with θ (``settings.estimate_x0``;
    ``["all"]``: every state)."""
    want = list(ctx.settings.estimate_x0 or [])
    if want == ["all"]:
        return list(model.states)
    return [s for s in want if s in model.states]


def noise_outputs(ctx: Context, model: Model) -> list[str]:
    """The outputs of ``model`` whose measurement-noise std every fit
    estimates (``settings.noise_outputs``, resolved by :func:`resolve_noise`)."""
    return [o for o in ctx.settings.noise_outputs if o in model.outputs]


def noise_start(ctx: Context, model: Model, theta: np.ndarray) -> dict:
    """Output -> start of its estimated noise std in a fit (the held level,
    else ``meas_std(θ)``): the centre of its box (×/÷ NOISE_BOX)."""
    meas = np.asarray(model.meas_std(theta[None, :]), float)[0]
    return {o: float(ctx.settings.noise_levels.get(o, meas[model.output_index(o)]))
            for o in noise_outputs(ctx, model)}


def _noise_bound_warning(ctx: Context, what: str, est: dict, start: dict, std: dict) -> None:
    """Log a warning for estimated noise stds on a bound of their box (the
    likelihood puts the output's variance elsewhere, e.g. into process noise);
    their Cramér-Rao std becomes None."""
    bad = [o for o, v in est.items() if o in start and start[o] > 0
           and not start[o] / NOISE_BOX * (1 + 1e-6) < v < start[o] * NOISE_BOX * (1 - 1e-6)]
    for o in bad:
        std[f"noise.{o}"] = None
    if bad:
        ctx.log(f"  warning: {what}: measurement-noise std on a bound of its box: "
                f"{', '.join(f'{o} = {est[o]:.3g}' for o in bad)} (not identified by the record "
                f"beside the process noise; declare it in the record or use noise='model')")


def resolve_noise(ctx: Context, graph: BondGraph) -> LoopSettings:
    """The settings with the noise policy resolved for the declared model
    (``settings.noise``): under ``"auto"``, the record's declared levels held
    (``noise_levels``), the undeclared fixed sensor noises estimated
    (``noise_outputs``) and the undeclared noise-intensity parameters added
    to ``params`` (:func:`bondgraph.inference.estimand.noise_plan`); the
    plan's notes logged."""
    s = ctx.settings
    if s.noise == "model":
        ctx.log("noise levels: the model's own (noise='model')")
        return s
    model = model_of(graph)
    theta = model.theta0.copy()
    for k, v in s.fixed.items():
        if k in model.params:
            theta[model.param_index(k)] = v
    declared = ctx.record.exp.noise_std_for(model)
    add, outs, sigma, notes = plan_noise(model, theta, s.params, list(s.fixed), declared)
    held = {o: float(sigma[j]) for j, o in enumerate(model.outputs) if np.isfinite(sigma[j])}
    if held:
        notes.append("measurement-noise std held at the record's declaration: " + ", ".join(
            f"{o} = {v:.4g}" for o, v in held.items()))
    for note in notes or ["noise levels: the model's own (nothing to estimate or hold)"]:
        ctx.log(note)
    return replace(s, params=list(s.params) + add, noise_levels=held, noise_outputs=outs)


def prior_on(record: Record, settings: LoopSettings, model: Model):
    """The UKF prior (x0, P0) of ``model`` on another record (the validation
    record): its own initial state, the loop's covariance policy (a given
    ``settings.x0`` belongs to the estimation record and is not used)."""
    x0 = record.exp.initial_state(model)
    view = Context(record, replace(settings, x0=None))
    return x0, prior_cov(view, model, x0)


def criterion_for(ctx: Context, model: Model, names: Sequence[str], base: np.ndarray):
    """Batched NLL of ``names`` (others at ``base`` (n_theta,)) on the record,
    with the loop's prior and UKF options."""
    t, u, y = ctx.record.arrays(model)
    x0, P0 = prior(ctx, model)
    return make_criterion(model, t, u, y, names, base, x0, P0, ctx.settings)


def bounds_around(model: Model, names: Sequence[str], theta: np.ndarray):
    """The declared boxes (k,) of ``names`` (never widened: a start value
    outside its box is clipped into it by :func:`clip_into_box`; ``theta``
    is accepted for the callers' convenience)."""
    return model.bounds(names)


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
    """Names whose value in ``theta`` lies within ``rel`` of its box's width
    (or of its own magnitude, for an unbounded side) of a bound of its box."""
    lo, hi = model.bounds(names)
    out = []
    for n, a, b in zip(names, lo, hi):
        v = float(theta[model.param_index(n)])
        tol = rel * (b - a if np.isfinite(b - a) else max(abs(v), 1e-300))
        if (np.isfinite(a) and v - a <= tol) or (np.isfinite(b) and b - v <= tol):
            out.append(n)
    return out


def noise_params(graph: BondGraph) -> set:
    """Names of parameters that appear only in process- or measurement-noise
    declarations (scale parameters of the filter: fitted in log scale,
    profiled by decades when candidates are screened)."""
    used_noise, used_model = set(), set()
    for v in list(graph.process_noise.values()) + [s.noise_std for s in graph.sensors.values()]:
        if isinstance(v, sp.Basic):
            used_noise |= {x.name for x in v.free_symbols}
    for el in graph.elements.values():
        for ex in el.expressions():
            used_model |= {x.name for x in ex.free_symbols}
    for s_ in graph.sensors.values():
        used_model |= {x.name for x in s_.expr.free_symbols}
    for ss in graph.signal_states.values():
        used_model |= {x.name for x in ss.rhs.free_symbols}
    return (used_noise - used_model) & set(graph.params)


def cr_std(F: np.ndarray, names: Sequence[str]) -> dict:
    """Cramér-Rao standard deviations sqrt(diag(F⁻¹)) from the Fisher
    information F (k, k); None where F is singular or a variance is not
    positive (Cramér 1946; Rao 1945)."""
    try:
        C = np.linalg.inv(F)
        d = np.diag(C)
        return {n: (float(np.sqrt(v)) if v > 0 and np.isfinite(v) else None)
                for n, v in zip(names, d)}
    except np.linalg.LinAlgError:
        return {n: None for n in names}


# ----------------------------------------------------------------- fitting
def fit_model(ctx: Context, graph: BondGraph, params: list[str],
              start: Mapping[str, float] | None, what: str, model: Model | None = None,
              iterations: int | None = None, tolerance: float = 0.0) -> Fit:
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
        Maximum Fisher-scoring iterations (default ``settings.fit_iterations``;
        0: evaluate at the start).
    tolerance : float
        Convergence of the scoring [nats] (:func:`~bondgraph.diagnose.inference_calls.fisher_fit`).

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
    theta = model.theta0.copy()
    for k, v in {**ctx.settings.fixed, **(start or {})}.items():
        if k in model.params:
            theta[model.param_index(k)] = v
    params = [p for p in params if p in model.params]
    theta = clip_into_box(ctx, model, params, theta, what)
    iters = ctx.settings.fit_iterations if iterations is None else int(iterations)
    std: dict = {}
    conv: tuple = (None, None)
    x0_est = {s: ctx.x0_estimates[s] for s in x0_states(ctx, model) if s in ctx.x0_estimates}
    noise_est = {o: ctx.settings.noise_levels[o] for o in noise_outputs(ctx, model)
                 if o in ctx.settings.noise_levels}
    if params and iters > 0:
        start_sigma = noise_start(ctx, model, theta)
        theta = _settle_theta(ctx, graph, model, params, theta, iters, what, start_sigma)
        theta, std, conv, x0_new, noise_new = _maximize(ctx, graph, model, params, theta,
                                                        iters, what, tolerance)
        x0_est.update(x0_new)
        noise_est.update(noise_new)
        _noise_bound_warning(ctx, what, noise_new, start_sigma, std)
    kept, kept_s = ctx.x0_estimates, ctx.settings
    ctx.x0_estimates = {**kept, **x0_est}
    ctx.settings = replace(kept_s, noise_levels={**kept_s.noise_levels, **noise_est})
    try:
        fit = evaluate_fit(ctx, graph, model, params, theta, what, std)
    finally:
        ctx.x0_estimates, ctx.settings = kept, kept_s
    fit.converged, fit.iterations = conv
    fit.x0_est, fit.noise_est = x0_est, noise_est
    fit.at_bound = on_bound(model, params, theta)
    if fit.at_bound:
        ctx.log(f"  warning: {what}: estimate(s) on a bound of their box: "
                f"{', '.join(f'{n} = {fit.theta[model.param_index(n)]:.4g}' for n in fit.at_bound)}"
                f" (no Cramér-Rao std; widen the box or fix the parameter)")
        for n in fit.at_bound:
            fit.std[n] = None
    return fit


def _settle_theta(ctx: Context, graph: BondGraph, model: Model, params: list[str],
                  theta: np.ndarray, iters: int, what: str, start_sigma: dict) -> np.ndarray:
    """θ fitted with the measurement noise held at its start, before a fit
    that estimates noise stds no fit has set yet (the declared fit under
    ``noise="auto"``). From a start far from the optimum a joint fit lets the
    noise std absorb the misfit, the likelihood flattens in θ and the scoring
    stalls in a poor point (a user's two-tank graph: free-run NRMSE 0.063
    against 0.017 in two stages, and the loop then "found" a dead zone that
    only made up for it). ``theta`` unchanged when every level is set."""
    fresh = [o for o in noise_outputs(ctx, model) if o not in ctx.settings.noise_levels]
    if not fresh:
        return theta
    kept = ctx.settings
    ctx.settings = replace(kept, noise_outputs=[],
                           noise_levels={**kept.noise_levels, **start_sigma})
    try:
        return _maximize(ctx, graph, model, params, theta, iters, f"{what} (noise held)")[0]
    finally:
        ctx.settings = kept


def _maximize(ctx: Context, graph: BondGraph, model: Model, params: list[str],
              theta: np.ndarray, iters: int, what: str,
              tolerance: float = 0.0) -> tuple[np.ndarray, dict, tuple, dict, dict]:
    """Fisher scoring of ``params`` from ``theta`` (noise intensities in log
    scale), the initial states of :func:`x0_states` and the noise stds of
    :func:`noise_outputs` jointly, L-BFGS-B (θ only) if it fails
    numerically; returns θ, the Cramér-Rao std (empty after the fallback;
    ``x0.<state>``, ``noise.<output>`` for the others), (converged,
    iterations), the estimated initial states and noise stds by name."""
    t, u, y = ctx.record.arrays(model)
    states = x0_states(ctx, model)
    noises = noise_outputs(ctx, model)
    x0, P0 = prior(ctx, model, shrink=not states)
    idx = [model.param_index(n) for n in params]
    lo, hi = bounds_around(model, params, theta)
    # log scale and decade moves for the noise intensities only: a physical
    # parameter with a wide box (R_a in [0.05, 10]) is no scale parameter,
    # and decade jumps strand it on a bound
    noise = noise_params(graph)
    scale = np.array([n in noise and lo[i] > 0 for i, n in enumerate(params)])
    try:
        theta, F, conv, used, x0n, sig = fisher_fit(
            model, t, u, y, theta, idx, lo, hi, x0, P0, ctx.settings, iters, scale, tolerance,
            states, np.sqrt(np.maximum(np.diag(P0), 1e-300)), noises)
        names = list(params) + [f"x0.{s_}" for s_ in states] + [f"noise.{o}" for o in noises]
        return (theta, cr_std(F, names), (conv, used),
                {s_: float(x0n[model.state_index(s_)]) for s_ in states}, sig)
    except (FloatingPointError, np.linalg.LinAlgError) as exc:
        ctx.log(f"  {what}: Fisher scoring failed ({exc}); falling back to L-BFGS-B")
        crit = criterion_for(ctx, model, params, theta)
        xs = np.array([theta[model.param_index(n)] for n in params])
        x = lbfgsb_polish(crit, xs, lo, hi, iters)
        return crit.theta(x[None, :])[0], {}, (None, None), {}, {}


def evaluate_fit(ctx: Context, graph: BondGraph, model: Model, params: list[str],
                 theta: np.ndarray, what: str, std: dict) -> Fit:
    """The :class:`Fit` at ``theta``: one stored UKF run, the free-run
    simulation, the residual analysis and the metric.

    Raises
    ------
    NumericalError
        If the UKF fails at ``theta`` (the reason is named).
    """
    t, u, y = ctx.record.arrays(model)
    x0, P0 = prior(ctx, model)
    res = run_ukf(model, t, u, y, theta[None, :], x0, P0, ctx.settings, store=True)
    nll = float(res.nll[0])
    if not np.isfinite(nll):
        raise NumericalError(f"{what}: the UKF failed at the fitted parameters "
                             f"({res.reasons[0]})")
    sim_y = free_run(ctx, model, theta, res)
    rep = analyze(res, model, t, u, y, sim_y=sim_y)
    fit = Fit(graph, model, list(params), theta, nll, res, rep, float("nan"), sim_y,
              std=std, n_obs=int(res.n_obs.sum()))
    fit.metric = compute_metric(ctx.settings, fit, ctx.record)
    fit.sim_errors = metric_errors(ctx.settings, fit, ctx.record)
    if ctx.settings.validation is not None:
        fit.validation_metric, fit.validation_errors = validation_run(ctx, model, theta)
    return fit


def validation_metric(ctx: Context, model: Model, theta: np.ndarray) -> float:
    """The loop's metric on the validation record (``settings.validation``):
    the model runs freely with the record's inputs from its initial state
    (:func:`free_run`); inf if the filter or the free run fails there."""
    return validation_run(ctx, model, theta)[0]


def validation_run(ctx: Context, model: Model,
                   theta: np.ndarray) -> tuple[float, np.ndarray | None]:
    """:func:`validation_metric` and the standardised free-run errors (N, n_y)
    on the validation record (None if the filter or the free run fails)."""
    rec = Record(ctx.settings.validation)
    t, u, y = rec.arrays(model)
    x0, P0 = prior_on(rec, ctx.settings, model)
    res = run_ukf(model, t, u, y, theta[None, :], x0, P0, ctx.settings, store=True)
    if not np.isfinite(res.nll[0]):
        return float("inf"), None
    sim_y = free_run(ctx, model, theta, res, rec)
    view = SimpleNamespace(model=model, theta=theta, ukf=res, sim_y=sim_y)
    return compute_metric(ctx.settings, view, rec), metric_errors(ctx.settings, view, rec)


def sim_inputs(settings: LoopSettings, u: np.ndarray) -> tuple[str, np.ndarray]:
    """The input hold of the free-run simulations and the inputs (N, n_u) it
    holds: ``settings.sim_hold`` (``"linear"`` or ``"zoh"``), or with
    ``"filter"`` the filter's own hold (``settings.ukf.hold``; its
    ``"mean"`` hold, (u_k + u_k+1)/2 over each interval, is the zero-order
    hold of the interval means, the last sample held), so that the free run
    sees the inputs between samples as the likelihood fit did."""
    hold = settings.sim_hold if settings.sim_hold != "filter" else settings.ukf.hold
    if hold != "mean":
        return hold, u
    um = u.copy()
    if len(um) > 1:
        um[:-1] = 0.5 * (u[:-1] + u[1:])
    return "zoh", um


def free_run(ctx: Context, model: Model, theta: np.ndarray, ukf_res,
             record: Record | None = None) -> np.ndarray | None:
    """Free-run simulation (N, n_y) of ``record`` (default the loop's) with
    the measured inputs (``settings.sim_method``, rtol 1e-6, atol 1e-9, the
    input hold of :func:`sim_inputs`) from the record's initial state (the
    prior mean: state columns, sidecar ``x0``, ``--x0``, the jointly
    estimated initial states), or, when the record does not give some initial
    states (:func:`unknown_states`, not estimated with θ), from the
    RTS-smoothed initial state x̂_0|N (Särkkä 2008): the best start the model
    and the whole record give. The filter's prior spread does not enter
    (the first filtered state did: one measurement update of it moved the
    start by its own P0). None (logged) if the model cannot be simulated
    freely. ``ukf_res`` is kept for the callers' signature."""
    record = ctx.record if record is None else record
    t, u, y = record.arrays(model)
    hold, u_sim = sim_inputs(ctx.settings, u)
    own = record is ctx.record
    view = ctx if own else Context(record, replace(ctx.settings, x0=None))
    x0 = (prior(ctx, model) if own else prior_on(record, ctx.settings, model))[0]
    if [n for n in unknown_states(view, model) if not own or n not in ctx.x0_estimates]:
        x0 = _smoothed_start(ctx, model, theta, record, x0)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sim = simulate(model, t, u_sim, x0=x0, theta=theta, method=ctx.settings.sim_method,
                           rtol=1e-6, atol=1e-9, hold=hold)
        return sim.y
    except Exception as exc:  # a model that cannot be simulated freely
        ctx.log(f"  free-run simulation failed ({str(exc).splitlines()[0]})")
        return None


def _smoothed_start(ctx: Context, model: Model, theta: np.ndarray, record: Record,
                    fallback: np.ndarray) -> np.ndarray:
    """x̂_0|N of ``record`` at ``theta`` from the loop's prior on it
    (:func:`~bondgraph.diagnose.inference_calls.smoothed_initial_state`);
    ``fallback`` (logged) if the smoother fails."""
    t, u, y = record.arrays(model)
    x0, P0 = prior(ctx, model) if record is ctx.record else prior_on(record, ctx.settings, model)
    try:
        xs = smoothed_initial_state(model, t, u, y, theta, x0, P0, ctx.settings)
    except BondGraphError as exc:
        ctx.log(f"  smoothed initial state unavailable ({str(exc).splitlines()[0]}): "
                f"the free run starts from the prior mean")
        return fallback
    return xs if np.all(np.isfinite(xs)) else fallback


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
