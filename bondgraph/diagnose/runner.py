"""The residual-tracing loop's orchestration: fit, score, confirm, accept,
repeat (see :mod:`bondgraph.diagnose.loop` for the method), with the log
lines and the ``on_update`` hand-over of the partial :class:`LoopResult`."""

from __future__ import annotations

import copy
import time
from contextlib import contextmanager
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
from typing import Callable, Sequence

from bondgraph.core.causality import assign_causality
from bondgraph.core.deferred import chi2
from bondgraph.core.graph import BondGraph
from bondgraph.core.progress import phase
from bondgraph.data.binding import require_inputs
from bondgraph.diagnose.accept import (
    Decision,
    accepted_step,
    applied_effect,
    confirmed_record,
    decide,
    mark_ties,
    newly_boxed,
    newly_boxed_names,
    pair_member_boxed,
    pair_needed,
    rank_confirmed,
    rejection,
    per_sample_nll,
    robust_std_needed,
    significant,
    unidentified_effect,
    unidentified_new,
    vuong_test,
)
from bondgraph.diagnose.confirm import (
    Confirmation,
    augmented_model,
    confirm,
    confirm_held,
    confirm_pair,
    confirm_same,
    continued,
    same_model_key,
    start_values,
    widen_boxes,
)
from bondgraph.diagnose.effects import Scales, get_effect
from bondgraph.diagnose.fit import (
    Context,
    Fit,
    samples_after,
    admissibility,
    continued_laws,
    FREE_RUN_SHARE,
    noise_absorbing,
    fit_context,
    fit_model,
    likelihood_fit,
    process_noise_absorbing,
    process_noise_floor,
    loop_problem,
    model_of,
    noise_params,
    parameter_std,
    robust_lr,
    robust_std_of,
    planned_noise,
    predicts_by_free_run,
    problem_for,
    recommended_substeps,
    adopted_discretisation,
    refined_discretisation,
    StepCheck,
    SUBSTEP_LADDER,
    validation_problem,
    validation_records,
)
from bondgraph.diagnose.inference_calls import (
    choose_discretisation,
    make_executor,
    output_error,
)
from bondgraph.diagnose.metric import metric_name
from bondgraph.diagnose.parallel import distributed, local_map, run_tasks
from bondgraph.diagnose.residuals import free_run_outlier_warnings, innovation_outlier_warnings
from bondgraph.diagnose.result import Candidate, LoopResult, Rejection, Step, rank_of
from bondgraph.diagnose.scoring import (
    compile_first_step_ahead,
    compile_step_ahead,
    conditional_score,
    mark_limits,
    operating_scales,
    places_of,
    score_additive,
    score_structural,
    structural_candidate,
    structural_todo,
)
from bondgraph.diagnose.screen import SCREEN_LEVEL, free_run_nrmse, global_output_error
from bondgraph.diagnose.settings import LoopSettings
from bondgraph.inference.discretise import (
    HOLD_CHECK_MARGIN,
    alternative_hold,
    hold_check_line,
    hold_verdict,
    moved_most,
    other_hold_warning,
    record_input_holds,
    step_error,
)
from bondgraph.inference.estimate import check_not_fixed
from bondgraph.numerics.admissible import MARGIN as ADMISSIBLE_MARGIN
from bondgraph.numerics.integrators import join_hold, split_hold
from bondgraph.numerics.model import Model
from bondgraph.errors import (
    BondGraphError,
    DeclaredFitError,
    ModelError,
    NumericalError,
    OptionError,
)

#: outcomes of one step
ACCEPTED, NONE_ACCEPTED, NOTHING_SIGNIFICANT = "accepted", "none accepted", "nothing significant"

OnUpdate = Callable[[LoopResult], None]


def run_loop(graph: BondGraph, experiment, settings: LoopSettings, *,
             log: Callable[[str], None] | None = None, progress: bool = True,
             on_update: OnUpdate | None = None) -> LoopResult:
    """Trace residuals to missing effects, add them, re-estimate.

    Parameters
    ----------
    graph : BondGraph
        The declared model (never modified).
    experiment : Experiment
        The measured record (:class:`bondgraph.data.records.Experiment`).
    settings : LoopSettings
        The loop's options, ``settings.params`` the parameters of the
        declared model to estimate (:class:`LoopSettings`: metric,
        criterion, max_steps, significance, effects, prior, filter options ...).
    log : callable, optional
        Line logger (default ``print``); lines are stamped with the time since
        the start.
    progress : bool
        Progress bars on long steps.
    on_update : callable, optional
        ``on_update(result)`` with the current (partial) :class:`LoopResult`,
        called after the initial fit, after every step and at the end
        (``result.finished`` True); the report writer
        (:meth:`bondgraph.report.loop_report.LoopReporter.update`) uses it,
        so that an interrupted run keeps its report.

    Returns
    -------
    LoopResult
        Accepted steps (error before/after, NLL, parameters), rejected
        candidates, the evidence ranking of every step, initial and final fits.

    Notes
    -----
    ``settings``' filter options are taken literally. On your own record,
    :func:`chosen_numerics` first chooses them as ``bondgraph loop --model
    --data`` does (method, substeps and input hold from the discretisation
    check and the record, the free runs held the same way).

    Raises
    ------
    ModelError
        Unknown parameter names.
    OptionError
        ``settings`` not a :class:`LoopSettings`.
    DeclaredFitError
        If the declared model's fit has a non-finite NLL or free-run error
        (on the record or the validation record): no effect is scored.
    BondGraphError
        If the declared model cannot be fitted at all (UKF failure).
    """
    if not isinstance(settings, LoopSettings):
        raise OptionError(f"run_loop needs a LoopSettings, got {type(settings).__name__}")
    require_params(graph, settings.params, settings.fixed)
    records_hold_inputs(graph, experiment, settings)
    experiment, s = held_out(experiment, settings)
    t0 = time.perf_counter()
    stamped = _stamped(log if log is not None else print, t0)
    problem = loop_problem(model_of(graph), experiment, s)
    add, noise = planned_noise(problem, s, stamped)
    ctx = Context(replace(problem, noise=noise), replace(s, params=list(s.params) + add),
                  stamped, progress, executor=make_executor(s.evaluation.workers,
                                                           s.evaluation.scheduler))
    try:
        return _run(ctx, graph, t0, on_update)
    finally:
        ctx.executor.close()


def _run(ctx: Context, graph: BondGraph, t0: float, on_update: OnUpdate | None) -> LoopResult:
    """The loop's steps (:func:`run_loop`)."""
    s = ctx.settings
    compile_first_step_ahead(ctx, graph)    # a first run: while the filter kernel compiles
    with phase("fitting the declared model"):
        initial, warn = resolved_fit(ctx, graph, initial_fit(ctx, graph))
        initial, warn = likelier_hold(ctx, graph, initial, warn)
        initial, warn = free_run_likelihood(ctx, graph, initial, warn)
    _worse_than_mean(ctx, initial)
    result = new_result(ctx, graph, initial, warn)
    publish(ctx, result, initial, initial, on_update)
    current = initial
    condition_on(ctx, initial)
    for step in range(1, s.search.max_steps + 1):
        current, outcome = run_step(ctx, result, current, step, graph.name)
        condition_on(ctx, current)
        if outcome == NOTHING_SIGNIFICANT:
            break
        publish(ctx, result, initial, current, on_update)
        if outcome == NONE_ACCEPTED:
            ctx.log("no confirmed candidate passed the accept rule (criterion, likelihood "
                    "ratio, error): stop")
            break
        if step == s.search.max_steps:
            msg = (f"the loop stopped at its step limit ({step} accepted steps, --max-steps): "
                   f"the record may show more; run it again with a larger limit")
            ctx.log(msg)
            result.warnings.append(msg)
    current = unbiased_final(ctx, result, current)
    if not current.std:
        current.std = parameter_std(ctx, current)
    current.std_robust = robust_std_of(ctx, current)
    with phase("checking the input holds at the final model"):
        hold_at_final(ctx, result, current)
    for w in glitches(ctx, result, current):
        ctx.log(f"warning: {w}")
        result.warnings.append(w)
        result.final_checks.append(w)
    if ctx.problem.ukf.to_dict() != result.settings.get("ukf"):
        result.settings["ukf_final"] = ctx.problem.ukf.to_dict()   # auto_substeps moved it
    result.finished = True
    publish(ctx, result, initial, current, on_update)
    ctx.log(f"done in {time.perf_counter() - t0:.1f} s")
    return result


def condition_on(ctx: Context, fit: Fit) -> None:
    """Later filter runs condition on ``fit``: its estimated initial states
    and measurement-noise stds (score tests use them; confirmations refit
    them): ``ctx.problem`` is replaced by the problem conditioned on them."""
    ctx.problem = ctx.problem.conditioned_on(x0=dict(fit.x0_est),
                                             noise_levels=dict(fit.noise_est))


@contextmanager
def conditioned(ctx: Context, fit: Fit):
    """Within the block, filter runs condition on ``fit`` (another
    candidate's refit: its estimated initial states and measurement-noise
    stds, as :func:`condition_on`); ``ctx.problem`` is restored after."""
    base = ctx.problem
    ctx.problem = base.conditioned_on(x0=dict(fit.x0_est), noise_levels=dict(fit.noise_est))
    try:
        yield
    finally:
        ctx.problem = base


def require_params(graph: BondGraph, params: Sequence[str], fixed=()) -> None:
    """Refuse parameters to estimate that ``graph`` does not declare, or
    that ``fixed`` (the loop's known values) holds: the loop estimated such
    a parameter from its fixed value without a word (``--fixed k4=0.05``
    without ``--params``: k4 ended at 0.0463).

    Raises
    ------
    ModelError
        The unknown names quoted, and the graph's own; the names both fixed
        and estimated.
    """
    unknown = [n for n in params if n not in set(graph.params)]
    if unknown:
        raise ModelError(f"graph '{graph.name}' has no parameter(s) "
                         f"{', '.join(repr(n) for n in unknown)} "
                         f"(known: {', '.join(graph.params)})")
    check_not_fixed(params, fixed)


def records_hold_inputs(graph: BondGraph, experiment, s: LoopSettings) -> None:
    """Refuse a record, or the validation record of ``s``, that lacks one
    of the declared graph's input columns: the loop's problems hold an
    input the record lacks at its default (a candidate's own inputs), and a
    validation record without the drive column was filtered and simulated
    with the drive at 0 and judged the effects without a word.

    Raises
    ------
    DataError
        The record, line 1, every missing column named
        (:func:`bondgraph.data.binding.require_inputs`).
    """
    need = SimpleNamespace(name=graph.name, inputs=list(graph.inputs), derivative_inputs={})
    for rec in (experiment, s.validation, *s.more_validation):
        if rec is not None:
            require_inputs(rec, need)


#: the fewest samples a held-out part may have: fewer judge nothing (a
#: 10-sample record's last quarter, 2 samples, read an error of 2e-8 before
#: and after)
MIN_HELD_OUT = 10


def held_out(experiment, s: LoopSettings):
    """``(record, settings)`` with the last ``s.holdout`` of the record as the
    validation record when none is given (the rest is fitted). The
    validation part's ``meta["follows"]`` names the fitted part: it
    continues that record, so its free run may start from the state the
    fitted part's filter ends in (:func:`bondgraph.diagnose.fit.validation_run`).

    Raises
    ------
    OptionError
        The held-out part or the fitted part would have fewer than
        :data:`MIN_HELD_OUT` samples (the sizes and the remedies named).
    """
    if s.validation is not None or not s.holdout:
        return experiment, window_fits(s)
    n = len(experiment.t)
    cut = int(round(n * (1.0 - s.holdout)))
    if min(cut, n - cut) < MIN_HELD_OUT:
        raise OptionError(
            f"holdout {s.holdout:g} of the {n}-sample record '{experiment.name}' leaves "
            f"{n - cut} samples to judge by and {cut} to fit: at least {MIN_HELD_OUT} each",
            hint="give a longer record, a validation record (--validate), or fit and judge "
                 "on the whole record (--holdout 0)")
    est, val = experiment.segment(0, cut), experiment.segment(cut)
    val.meta["follows"] = est.name
    return est, window_fits(replace(s, validation=val))


def window_fits(s: LoopSettings) -> LoopSettings:
    """``s`` when its free-run window (``s.free_run.init_samples``, the
    benchmark protocol's first samples of the record that judges) leaves
    at least :data:`MIN_HELD_OUT` samples of that record to judge by.

    Raises
    ------
    OptionError
        A window without a record that judges (``holdout`` 0 and no
        ``validation``: the loop then judges on the fitted record, whose
        start is fitted with θ), or one that leaves fewer samples (the
        sizes named).
    """
    n = s.free_run.init_samples
    if not n:
        return s
    if s.validation is None:
        raise OptionError(f"init_samples (--init-samples) {n} sets the start of the record that "
                          f"judges, and with holdout 0 and no validation record there is none",
                          hint="give --validate FILE or --holdout FRACTION, or leave "
                               "--init-samples out")
    for rec in (s.validation, *s.more_validation):
        left = samples_after(rec, n)
        if left < MIN_HELD_OUT:
            size = samples_after(rec, 0)
            raise OptionError(f"init_samples (--init-samples) {n} leaves {left} of the "
                              f"{size}-sample validation record '{rec.name}' to judge by: "
                              f"at least {MIN_HELD_OUT}",
                              hint="a smaller window, or a longer validation record")
    return s


def chosen_numerics(graph: BondGraph, record, settings: LoopSettings, *,
                    given: dict | None = None,
                    log: Callable[[str], None] | None = None) -> LoopSettings:
    """``settings`` with the numerics chosen for a user's graph and record,
    as ``bondgraph loop --model F --data R`` chooses them: the filter's
    method, substeps and input hold that the discretisation check accepts
    at the declared defaults on the estimation part of the record
    (:func:`bondgraph.inference.discretise.choose_discretisation`: the hold
    each input's declaration or shape supports, the cheapest step within 0.1
    noise std per sample), the free runs holding the inputs the same way
    with the same method 4 times finer (``FreeRunOptions(method="fine")``),
    and the check repeated at the declared fit and at every accepted one
    (``SearchOptions(auto_substeps=True)``), and, unless the hold is given,
    each input whose shape chose its hold checked at the final model under
    the other hold (``SearchOptions(check_hold=True)``,
    :func:`hold_at_final`). Call it before :func:`run_loop` on your own record: ``settings``' own filter options are otherwise taken
    literally (``UKFOptions()``: ROS2 with one step per sample, zero-order
    hold).

    Parameters
    ----------
    graph : BondGraph
    record : Experiment
    settings : LoopSettings
    given : dict, optional
        Fields the caller fixes: ``method``, ``substeps``, ``hold`` (all
        three: ``settings`` is returned unchanged).
    log : callable, optional
        Gets the one line that says what was chosen and why (default ``print``).

    Returns
    -------
    LoopSettings

    Raises
    ------
    OptionError
        A bad given value, or a per-input hold of the wrong length.
    """
    given = dict(given or {})
    if len(given) == 3:
        return settings
    records_hold_inputs(graph, record, settings)
    est, s = held_out(record, settings)
    problem = loop_problem(model_of(graph), est, s)
    model = problem.model
    declared = np.asarray(est.noise_std_for(model), float)
    sigma = np.where(np.isfinite(declared) & (declared > 0), declared,
                     np.asarray(model.meas_std(problem.theta[None, :]), float)[0])
    choice = choose_discretisation(problem, problem.theta, given=given, sigma=sigma)
    (log or print)(choice.line("at the declared start θ"))
    other = None if "hold" in given else alternative_hold(choice.inputs, choice.disc.hold)
    if other is not None:
        (log or print)(f"the input's shape does not settle its hold: the declared model is "
                       f"fitted under the {other} hold too, the likelihood decides (--hold to "
                       f"choose)")
    s = with_discretisation(settings, choice.disc)
    return replace(s, search=replace(s.search, auto_substeps=True, other_hold=other,
                                     auto_method="method" not in given,
                                     check_hold="hold" not in given),
                   free_run=replace(s.free_run, method="fine"))


def with_discretisation(settings: LoopSettings, d) -> LoopSettings:
    """``settings`` with the filter's method, substeps and hold of ``d`` (a
    :class:`~bondgraph.inference.options.Discretisation`), the free runs
    holding the inputs alike (unless that hold is not one they have)."""
    hold = d.hold if set(split_hold(d.hold)) <= {"zoh", "linear"} else settings.free_run.hold
    return replace(settings, ukf=replace(settings.ukf, method=d.method, substeps=d.substeps,
                                         hold=d.hold),
                   free_run=replace(settings.free_run, hold=hold))


def new_result(ctx: Context, graph: BondGraph, initial: Fit,
               warn: list[str] | None = None) -> LoopResult:
    """The :class:`LoopResult` after the declared fit: names, settings, a copy
    of the declared graph, the true effect if known, and the warnings (the
    discretisation check's ``warn``, estimates on a bound)."""
    s = ctx.settings
    result = LoopResult(graph.name, graph.source, ctx.problem.name, metric_name(s),
                        s.accept.criterion,
                        settings_summary(ctx))
    result.declared_graph = graph.copy(graph.name)
    te = s.true_effect
    if te is not None:
        result.true_effect = (te.to_dict() if hasattr(te, "to_dict")
                              else {"kind": te[0], "target": te[1], "values": {}})
    result.warnings.extend(check_discretisation(ctx, initial) if warn is None else warn)
    result.warnings.extend(f"initial fit: {n} on a bound of its box (no Cramér-Rao std)"
                           for n in initial.at_bound)
    result.warnings.extend(initial.warnings)
    for w in noise_absorbing(ctx, initial) + continued_laws(ctx, initial):
        ctx.log(f"warning: initial fit: {w}")
        result.warnings.append(f"initial fit: {w}")
    adm = admissibility(ctx, initial)
    if not adm.ok:
        msg = declared_inadmissible(ctx, adm)
        ctx.log(f"warning: {msg}")
        result.warnings.append(f"initial fit: {msg}")
    return result


def declared_inadmissible(ctx: Context, adm) -> str:
    """The declared model's fit breaks what a bond graph promises (``adm``,
    :func:`~bondgraph.diagnose.fit.admissibility`): no model the loop
    accepts could keep it, so by default the loop stops
    (:class:`DeclaredFitError`, exit code 2) naming the law, the range
    checked and what to do; with ``on_failed_fit="continue"``
    (``--keep-going``) the warning's text, and a candidate is then refused
    only for a violation it adds or worsens
    (:func:`~bondgraph.numerics.admissible.without_inherited`)."""
    msg = (f"the declared model is not physically admissible at its fit: {adm.reason()}. "
           f"The range checked is the one the record visits, widened by "
           f"{100 * ADMISSIBLE_MARGIN:.0f} % of its span on each side and made to contain zero; "
           f"rewrite that law so it dissipates (its storage restores towards its well) "
           f"there, for example a constant "
           f"term A of an effort law as A·tanh(f/ε), which changes sign with the flow, or "
           f"narrow the box of the parameter that makes it produce power")
    if ctx.settings.search.on_failed_fit == "stop":
        raise DeclaredFitError(msg + "; no effect is scored",
                               hint="bondgraph loop ... --keep-going scores effects anyway, "
                                    "refusing a candidate only for a violation it adds")
    return msg + ("; going on (--keep-going): a candidate is refused only for a violation it "
                  "adds or worsens")


def settings_summary(ctx: Context) -> dict:
    """What a report records of the run's options: the search options
    (:meth:`LoopSettings.summary`) with the problem's filter options and
    noise levels as the loop resolved them, ``finer_grid`` when the
    record was filtered on a grid twice as fine (a band-limited input,
    :meth:`~bondgraph.data.records.Experiment.on_finer_grid`) and
    ``decimated`` when it was fitted on every K-th sample
    (:meth:`~bondgraph.data.records.Experiment.decimated`)."""
    noise = ctx.problem.noise
    out = {**ctx.settings.summary(), "ukf": ctx.problem.ukf.to_dict(),
           "noise": noise.mode, "noise_levels": dict(noise.held),
           "noise_outputs": list(noise.estimated)}
    meta = getattr(getattr(ctx.problem, "record", None), "meta", None) or {}
    for key in ("finer_grid", "decimated"):
        if meta.get(key):
            out[key] = meta[key]
    return out


def _stamped(log: Callable[[str], None], t0: float) -> Callable[[str], None]:
    """``log`` with each line prefixed by the seconds since ``t0``. An
    indented detail line whose text was already logged since the last
    top-level line (a step, a decision) is not repeated: a confirmation's
    second refit (from the score test's joint step) and the free runs of
    the record and of its held-out part say the same things again (the
    EMPS drive on a user's graph: 55 lines "the record does not identify
    ...", a third of them repeats)."""
    seen: set[str] = set()

    def emit(msg: str) -> None:
        if msg.startswith("  "):
            if msg in seen:
                return
            seen.add(msg)
        else:
            seen.clear()
        log(f"[{time.perf_counter() - t0:7.1f} s] {msg}")
    return emit


def publish(ctx: Context, result: LoopResult, initial: Fit, current: Fit,
            on_update: OnUpdate | None) -> None:
    """Bring ``result`` up to date with the initial and current fits (their
    summaries, the current graph, the record arrays of the current model) and
    hand it to ``on_update``."""
    result.initial = initial.summary()
    result.final = current.summary()
    result.final_graph = current.graph
    problem = problem_for(ctx, current.model)
    t, _, y = problem.arrays
    result.time, result.measured = t, y
    if ctx.settings.validation is not None:
        tv, _, yv = validation_problem(ctx, problem).arrays
        result.validation_time, result.validation_measured = tv, yv
        for i, rec in enumerate(ctx.settings.more_validation, start=1):
            tm, _, ym = validation_problem(ctx, problem, i).arrays
            result.more_measured[rec.name] = (tm, ym)
    result.outputs = list(current.model.outputs)
    result.output_units = list(current.model.output_units)
    if on_update is not None:
        with phase("writing the report"):
            on_update(result)


def initial_fit(ctx: Context, graph: BondGraph, again: bool = False) -> Fit:
    """Fit the declared model (``initial_params``, default ``params``) on a
    copy of ``graph``; the returned fit counts all of ``params`` as
    estimated (later steps re-estimate them all). Logs the start, a warning
    when the filter model declares no process noise (not ``again``: a refit
    with other substeps), and the fit."""
    s = ctx.settings
    if not again:
        ctx.log(f"loop on model '{graph.name}', record '{ctx.problem.name}', estimating "
                f"{', '.join(s.params)}")
        for note in getattr(ctx.problem.model, "domain_notes", ()):
            ctx.log(f"note: {note}")
        for note in assign_causality(graph).derivative_notes():
            ctx.log(f"note: {note}")
    if not again and not graph.process_noise and not any(
            ss.process_noise is not None for ss in graph.signal_states.values()):
        ctx.log("warning: the filter model declares no process noise; model errors then "
                "do not show as local innovations and the likelihood is poorly "
                "conditioned. Declare process noise (g.set_process_noise) on the states "
                "where forces are unmodelled, ideally as an estimated parameter.")
    first = list(s.params) if s.initial_params is None else list(s.initial_params)
    start = sim_start(ctx, graph, first) if s.search.fit == "sim" else None
    fit = _declared(ctx, graph, first, start)
    check_declared_fit(fit)
    held = []
    if s.initial_params is None:
        fit, held = held_unidentified(ctx, graph, fit, start)
        s = ctx.settings
        first = list(s.params)
    fit, unmoved, boxed = _restarted(ctx, graph, fit, first, start)
    if s.initial_params is None and ctx.settings.hold_unidentified:
        # the restarts can find the ridge or the box the first fit did not
        again, more = held_unidentified(ctx, graph, fit, start)
        held += more
        if list(ctx.settings.params) != first:
            first = list(ctx.settings.params)
            fit, unmoved, boxed = _restarted(ctx, graph, again, first, start)
        s = ctx.settings
    if unmoved or boxed:
        fit = _declared_fit_verdict(ctx, graph, fit, first, unmoved, boxed)
    fit = _declared_converged(ctx, graph, fit)
    fit.params = list(s.params)
    fit.warnings[:0] = [w for w in held if w not in fit.warnings]
    ctx.log(f"initial fit: NLL {fit.nll:.2f}, {s.accept.criterion.upper()} "
            f"{fit.information(s.accept.criterion):.2f}, whiteness {fit.residuals.whiteness:.1f}, "
            f"{metric_name(s)} = {fit.metric:.4g}")
    return fit


def held_unidentified(ctx: Context, graph: BondGraph, fit: Fit,
                      start: dict | None) -> tuple[Fit, list[str]]:
    """``(fit, messages)``: the declared fit with the parameters of
    ``hold_unidentified`` that it does not identify (``fit.flat``) held at
    their values in the problem (the declared or fixed ones), one at a
    time, the largest loading on the flat directions first, the declared
    model refitted after each; each held parameter leaves
    ``ctx.settings.params`` for ``fixed`` and is named in the log and in the
    messages (for the report). So is one the declared fit leaves on a
    bound of the box set around it (``default``/10 to ``default``·10, or
    ±1 about a default that is not positive,
    :class:`~bondgraph.core.symbols.Parameter`): a known value moved to the
    end of that box is not estimated by the record, and a parameter the record
    cannot tell apart runs there when only the filter's initial covariance
    (in state units) depends on it (a user's thermal graph whose reference
    temperature T0 scales the entropy states: T0 300 -> 30 K, its bound,
    for 4.5 nats); unless holding it costs the declared fit more than
    :data:`HOLD_DISAGREES` nats: the record then disagrees with the value
    (or the graph lacks what it made up for), and it stays estimated, said
    so in the log and the messages. A scale symmetry (a motor
    constant times the mass and friction it drives) leaves the likelihood
    flat along a ridge: a fit then stops anywhere on it, the parameters'
    values mean nothing apart (the EMPS drive declared with its known
    force constant among the estimated ones: M 169 kg where the benchmark
    has 95), and every refit of the loop wanders along it."""
    s = ctx.settings
    msgs = []
    for _ in range(len(s.hold_unidentified)):
        flat = [n for n in (fit.flat or ()) if n in s.hold_unidentified and n in s.params]
        boxed = [n for n in (fit.at_bound or ()) if n in s.hold_unidentified and n in s.params]
        if not flat and not boxed:
            break
        name = (flat or boxed)[0]
        value = float(ctx.problem.theta[fit.model.param_index(name)])
        if flat:
            why = f"the record does not identify {', '.join(fit.flat)} separately"
        else:
            lo, hi = fit.model.bounds([name])
            at = float(fit.theta[fit.model.param_index(name)])
            why = (f"the declared fit moves {name} to {at:.6g}, onto the box [{lo[0]:.6g}, "
                   f"{hi[0]:.6g}] the toolkit sets around a value declared without one (a "
                   f"known value moved to the end of that box is no estimate the record "
                   f"made)")
        msg = (f"{why}; {name} was declared without a box (a known value): held at "
               f"{value:.6g}; the other estimates and their std assume that value (to "
               f"estimate it, declare its box in the graph and list it in --params)")
        rest = tuple(n for n in s.hold_unidentified if n != name)
        held = replace(s, params=[n for n in s.params if n != name],
                       fixed={**s.fixed, name: value}, hold_unidentified=rest)
        ctx.settings = held
        refit = _declared(ctx, graph, list(held.params), start)
        check_declared_fit(refit)
        if not flat and refit.nll - fit.nll > HOLD_DISAGREES:
            at = float(fit.theta[fit.model.param_index(name)])
            msg = (f"{name} was declared without a box (a known value), but the declared fit "
                   f"moves it to {at:.6g}, the end of the box the toolkit sets around it, and "
                   f"held at {value:.6g} the fit's NLL goes {fit.nll:.2f} -> {refit.nll:.2f} "
                   f"(more than {HOLD_DISAGREES:g}): the record disagrees with that value, or "
                   f"the graph lacks what it made up for; {name} stays estimated (on its box: "
                   f"check the value, or declare its box)")
            s = ctx.settings = replace(s, hold_unidentified=rest)
        else:
            if not flat:
                msg += f" (the declared fit's NLL {fit.nll:.2f} -> {refit.nll:.2f})"
            s, fit = held, refit
        ctx.log(f"  {msg}")
        msgs.append(msg)
    return fit, msgs


#: nats the declared fit may lose when a known value it moved onto its box
#: is held; beyond, the record disagrees with the value and it stays
#: estimated (χ²₁ at 1e-6, /2: :func:`held_unidentified`)
HOLD_DISAGREES = 11.96


def _declared_converged(ctx: Context, graph: BondGraph, fit: Fit) -> Fit:
    """The declared fit continued until its scoring converges, as a
    confirmation refit is (:func:`~bondgraph.diagnose.confirm.continued`:
    up to ``CONTINUATIONS`` x ``confirm_iterations`` more iterations at
    ``confirm_tolerance``): every likelihood ratio of the loop is taken
    against it, and a refit's extra iterations on the declared parameters
    otherwise count as the candidate's gain (a viscous damper beside the
    declared one: LR 29.5 against a declared fit 14.3 nats short of its
    optimum after its 10 iterations, LR 1.0 against the converged one; on
    two parallel tanks the unconverged declared fit moved by 7.4 nats with
    the last bit of the kernels' arithmetic, and a never-active overflow
    with it). Still not converged: a warning (log, ``fit.warnings``)."""
    fit = continued(ctx, graph.copy(graph.name), fit, "the declared fit")
    if fit.converged is False:
        msg = (f"the declared fit has not converged after {fit.iterations} iterations: the "
               f"likelihood ratios against it are upper bounds (its parameters may still "
               f"move in any refit)")
        ctx.log(f"  warning: {msg}")
        fit.warnings.append(msg)
    return fit


def _worse_than_mean(ctx: Context, fit: Fit) -> None:
    """Say so (log and ``fit.warnings``) when the declared model's free run
    is worse than the record's mean (free-run NRMSE above 1): the effects
    are then scored against a model that does not describe the record, and
    an effect the record shows plainly (a rectifying sensor on a linear
    drive whose output the fit flattened) can score nothing."""
    if ctx.settings.metric != "nrmse_sim" or not fit.metric > 1.0:
        return
    msg = (f"the declared model's free run is worse than the record's mean (NRMSE "
           f"{fit.metric:.3g} > 1): the effects are scored against a model that does not "
           f"describe the record; check the graph's structure, start values and boxes first")
    ctx.log(f"  warning: {msg}")
    fit.warnings.append(msg)


def _restarted(ctx: Context, graph: BondGraph, fit: Fit, first: list[str],
               start: dict | None) -> tuple[Fit, list[str], list[str]]:
    """``(fit, unmoved, boxed)``: the declared fit ``fit`` of ``first``
    (from ``start``) attempted again where it may not have happened: from
    an output-error fit when a physical parameter never moved or sits on
    its box (:func:`stuck_parameters`), and from a global output-error
    search when its free run is poor (:func:`global_start`); the better
    attempt is kept (logged), with what :func:`stuck_parameters` says of
    it."""
    s = ctx.settings
    unmoved, boxed = stuck_parameters(ctx, fit, first, start, boxes_only=s.search.fit == "sim")
    if (unmoved or boxed) and s.search.fit == "nll":
        ctx.log(f"  the declared fit may not have happened: {stuck_text(fit, unmoved, boxed)}; "
                f"fitting the physical parameters first by output error (the noise held), "
                f"then the likelihood from there")
        start = sim_start(ctx, graph, first)
        again = _second_attempt(ctx, graph, first, start) if start is not None else None
        if again is not None and again.nll <= fit.nll:   # the better attempt is kept
            fit = again
            unmoved, boxed = stuck_parameters(ctx, fit, first, start, boxes_only=True)
    start = global_start(ctx, fit, first) if s.search.fit == "nll" else None
    again = _second_attempt(ctx, graph, first, start) if start is not None else None
    if again is not None:
        better = again.nll < fit.nll and again.metric <= fit.metric
        ctx.log(f"  from the global output-error start: NLL {fit.nll:.2f} -> {again.nll:.2f}, "
                f"error {fit.metric:.4g} -> {again.metric:.4g}; "
                + ("kept" if better else "the first fit stands (both must fall)"))
        if better:
            fit = again
            unmoved, boxed = stuck_parameters(ctx, fit, first, start, boxes_only=True)
    return fit, unmoved, boxed


def _second_attempt(ctx: Context, graph: BondGraph, names: list[str], start: dict) -> Fit | None:
    """The declared fit from the output-error estimates ``start``, or None
    (logged) when it is not usable (the first attempt then stands)."""
    try:
        again = _declared(ctx, graph, names, start)
        check_declared_fit(again)
        return again
    except DeclaredFitError as exc:
        ctx.log(f"  the second attempt is not usable ({str(exc).splitlines()[0]}); the first "
                f"stands")
        return None


def _declared(ctx: Context, graph: BondGraph, names: list[str], start: dict | None) -> Fit:
    """The likelihood fit of the declared model's ``names`` from ``start``
    (:class:`DeclaredFitError` if the filter fails)."""
    try:
        return fit_model(ctx, graph.copy(graph.name), names, start, "initial fit",
                         model=ctx.problem.model)
    except NumericalError as exc:
        raise DeclaredFitError(f"the declared model cannot be fitted: {exc}; no effect is "
                               f"scored") from exc


def stuck_parameters(ctx: Context, fit: Fit, names: list[str], start: dict | None,
                     boxes_only: bool = False) -> tuple[list[str], list[str]]:
    """``(unmoved, boxed)``: the physical (non-noise) parameters of ``names``
    that never left their start values where the likelihood was flat in
    them (the noise intensities explained the record instead; not with
    ``boxes_only``), and those on a bound of their declared box (the record
    asks for a value the box forbids, or a missing effect pushes them
    there). The start is ``start`` over the problem's θ (the defaults and
    fixed values), clipped into the boxes as
    :func:`~bondgraph.diagnose.fit.fit_model` does. A parameter whose
    Cramér-Rao std is below :data:`PINNED_REL` of its value was not in a
    flat likelihood: its start was its optimum (a loop run again on its own
    augmented model starts there; taking that for a fit that did not happen
    cost a user's Silverbox graph a 520-s output-error fit)."""
    model = fit.model
    phys = physical_parameters(fit, names)
    theta0 = ctx.problem.theta.copy()
    for k, v in (start or {}).items():
        if k in model.params:
            theta0[model.param_index(k)] = v
    lo, hi = model.bounds(phys) if phys else ([], [])
    unmoved = [] if boxes_only else [
        n for n, a, b in zip(phys, lo, hi)
        if abs(fit.theta[model.param_index(n)] - np.clip(theta0[model.param_index(n)], a, b))
        <= 1e-9 * max(abs(theta0[model.param_index(n)]), 1e-300) and not pinned_by_record(fit, n)]
    return unmoved, [n for n in phys if n in fit.at_bound]


#: a Cramér-Rao std below this share of a parameter's value: the likelihood
#: is curved there, not flat (:func:`stuck_parameters`)
PINNED_REL = 0.1


def pinned_by_record(fit: Fit, name: str) -> bool:
    """``fit``'s Cramér-Rao std of ``name`` is finite and below
    :data:`PINNED_REL` of its value: the record determines it there."""
    std = fit.std.get(name)
    v = fit.theta[fit.model.param_index(name)]
    return std is not None and bool(np.isfinite(std)) and std < PINNED_REL * abs(v)


def physical_parameters(fit: Fit, names: list[str]) -> list[str]:
    """The parameters of ``names`` in ``fit``'s model that are not noise
    intensities (:func:`~bondgraph.diagnose.fit.noise_params`)."""
    noise = noise_params(fit.model)
    return [n for n in names if n in fit.model.params and n not in noise]


def stuck_text(fit: Fit, unmoved: list[str], boxed: list[str]) -> str:
    """The parameters of :func:`stuck_parameters` in words."""
    model = fit.model
    parts = []
    if unmoved:
        parts.append(f"{', '.join(unmoved)} never left {'its' if len(unmoved) == 1 else 'their'} "
                     f"start value{'' if len(unmoved) == 1 else 's'}")
    if boxed:
        parts.append(", ".join(f"{n} = {fit.theta[model.param_index(n)]:.4g} sits on a bound of "
                               f"[{a:.4g}, {b:.4g}]"
                               for n, a, b in zip(boxed, *model.bounds(boxed))))
    return "; ".join(parts)


def _declared_fit_verdict(ctx: Context, graph: BondGraph, fit: Fit, names: list[str],
                          unmoved: list[str], boxed: list[str]) -> Fit:
    """After the second attempt: when no physical parameter of the declared
    fit found an interior optimum (each never moved or sits on its box), the
    fit did not happen: :class:`DeclaredFitError` naming them, what the
    likelihood would gain beyond the boxes and what to do (unless
    ``on_failed_fit="continue"``, ``--keep-going``). When some did, a
    parameter on its box is a symptom the loop may explain (a missing
    friction drives a viscous coefficient to its top, a missing pump
    saturation a tank's capacitance to its bottom): a warning (logged, and
    in the report through ``fit.warnings``) names the box and its cost.

    When the refit with the boxes opened (:func:`beyond_fit`) ends with
    every opened parameter back inside its declared box and a lower NLL,
    the fit on the box was not the box's optimum (its scoring stopped on
    the bound short of a better interior point): the declared fit is
    refitted in the declared boxes from there and continues from that
    refit when it is better (:func:`_inside_optimum`; logged). A user's
    two-mass EMPS graph: a load friction "on" the bottom of its box, 0.1 N
    s/m, whose opened refit ended at 794.6, 781 nats likelier.

    Returns
    -------
    Fit
        ``fit``, or the better fit inside the declared boxes.
    """
    s = ctx.settings
    opened = beyond_fit(ctx, graph, fit, names)
    better = _inside_optimum(ctx, graph, fit, names, opened)
    if better is not None:
        unmoved = [n for n in unmoved if better.theta[better.model.param_index(n)]
                   == fit.theta[fit.model.param_index(n)]]
        fit = better
        boxed = [n for n in physical_parameters(fit, names) if n in fit.at_bound]
        if not (unmoved or boxed):
            return fit
        opened = beyond_fit(ctx, graph, fit, names)
    text = stuck_text(fit, unmoved, boxed) + _beyond_text(fit, opened)
    failed = set(unmoved) | set(boxed) == set(physical_parameters(fit, names))
    if not failed:
        msg = (f"declared fit: {text}; a missing effect may push a declared parameter onto its "
               f"box: the loop goes on")
        ctx.log(f"  warning: {msg}")
        fit.warnings.append(msg)
        return fit
    msg = (f"the declared fit failed: {text}. Check these parameters' units, start values and "
           f"boxes (a box is your physical knowledge: widen it only if it is wrong), fix the "
           f"ones the record cannot tell (--fixed), or declare the missing process noise")
    if s.search.on_failed_fit == "stop":
        raise DeclaredFitError(msg + "; no effect is scored",
                               hint="bondgraph loop ... --keep-going scores effects anyway")
    ctx.log(f"  warning: {msg}; going on (--keep-going)")
    fit.warnings.append(msg + "; going on (--keep-going)")
    return fit


def _inside_optimum(ctx: Context, graph: BondGraph, fit: Fit, names: list[str],
                    opened: tuple[Fit, list[str]] | None) -> Fit | None:
    """The declared fit refitted in the declared boxes from the opened-box
    refit ``opened`` (:func:`beyond_fit`) when that refit ended with a lower
    NLL and every opened parameter strictly inside its declared box
    (:func:`ended_inside`); None otherwise, or when the refit in the boxes
    is not better than ``fit`` (logged either way when tried)."""
    if opened is None or not ended_inside(fit, *opened):
        return None
    beyond, boxed = opened
    where = _values_text(fit, beyond, boxed)
    try:
        again = fit_model(ctx, graph.copy(graph.name), names, beyond.estimates(), "initial fit",
                          model=fit.model)
    except BondGraphError as exc:
        ctx.log(f"  the refit with the box opened ended inside it ({where}, NLL {fit.nll:.2f} "
                f"-> {beyond.nll:.2f}), but the declared fit from there failed "
                f"({str(exc).splitlines()[0]}): the fit on the box stands")
        return None
    if not again.nll < fit.nll:
        ctx.log(f"  the refit with the box opened ended inside it ({where}, NLL {fit.nll:.2f} "
                f"-> {beyond.nll:.2f}), but the declared fit from there ended at NLL "
                f"{again.nll:.2f}: the fit on the box stands")
        return None
    ctx.log(f"  the refit with the box opened ended inside the declared box ({where}; NLL "
            f"{fit.nll:.2f} -> {beyond.nll:.2f}): the fit on the box was not its optimum; the "
            f"declared fit goes on from there (NLL {again.nll:.2f})")
    return again


def ended_inside(fit: Fit, beyond: Fit, boxed: list[str]) -> bool:
    """Whether the opened-box refit ``beyond`` of ``fit``'s parameters
    ``boxed`` (:func:`beyond_fit`) ended with a lower NLL than ``fit`` and
    each of them strictly inside its declared box (farther from either
    bound than 1e-6 of the box's width): the fit on the box was then not
    the box's optimum."""
    if not (np.isfinite(beyond.nll) and beyond.nll < fit.nll) or not boxed:
        return False
    lo, hi = fit.model.bounds(boxed)
    v = np.array([beyond.theta[fit.model.param_index(n)] for n in boxed], float)
    tol = 1e-6 * (np.asarray(hi, float) - np.asarray(lo, float))
    return bool(np.all((v > np.asarray(lo, float) + tol) & (v < np.asarray(hi, float) - tol)))


#: how far :func:`gain_beyond_box` opens a box on the side the fit sits on
#: (a factor for a positive bound, else widths)
BOX_OPENING = 10.0


def gain_beyond_box(ctx: Context, graph: BondGraph, fit: Fit, names: list[str]) -> str:
    """What the likelihood would gain beyond the declared boxes, or "": the
    parameters of ``fit.at_bound`` refitted with their box opened
    :data:`BOX_OPENING`-fold on the side they sit on (the others' boxes
    kept), as a clause naming the gain [nats] and the values reached
    (:func:`beyond_fit`, :func:`_beyond_text`). The box stays the user's:
    this only reports what it costs."""
    return _beyond_text(fit, beyond_fit(ctx, graph, fit, names))


def _beyond_text(fit: Fit, opened: tuple[Fit, list[str]] | None) -> str:
    """The clause of :func:`gain_beyond_box` for the opened-box refit
    ``opened`` of ``fit`` ("" when there is none or its NLL is not
    finite): the gain and the values reached; a refit that ended better
    and inside the declared boxes (:func:`ended_inside`) is said to show
    that the fit on the box was not the box's optimum."""
    if opened is None or not np.isfinite(fit.nll - opened[0].nll):
        return ""
    beyond, boxed = opened
    gain = float(fit.nll - beyond.nll)
    text = _values_text(fit, beyond, boxed)
    if not gain > 0:    # the refit beyond the box ended no better than the fit on it
        how = (f"a log-likelihood {-gain:.3g} nats lower" if gain < 0 else
               "the same log-likelihood")
        return (f" (beyond the box the likelihood gains nothing: the refit with the box opened "
                f"ended with {how}, at {text})")
    if ended_inside(fit, beyond, boxed):
        return (f" (the refit with the box opened ended inside the declared box, {gain:.6g} nats "
                f"likelier, at {text}: the fit on the box had not reached the box's optimum)")
    return f" (beyond the box the likelihood gains {gain:.6g} nats, at {text})"


def _values_text(fit: Fit, beyond: Fit, boxed: list[str]) -> str:
    """The values the opened-box refit ``beyond`` reached for ``boxed``
    ("K2 = 2.51e-06, ...")."""
    return ", ".join(f"{n} = {beyond.theta[fit.model.param_index(n)]:.4g}" for n in boxed)


def beyond_box(ctx: Context, graph: BondGraph, fit: Fit, names: list[str],
               only: Sequence[str] | None = None) -> tuple[float, dict] | None:
    """The refit of :func:`gain_beyond_box` with the boxes of ``fit.at_bound``
    (those in ``only`` when given; never noise intensities) opened:
    (NLL gain [nats], the opened parameters' values), or None when none is
    boxed or the refit fails (:func:`beyond_fit`)."""
    opened = beyond_fit(ctx, graph, fit, names, only)
    if opened is None:
        return None
    beyond, boxed = opened
    gain = fit.nll - beyond.nll
    if not np.isfinite(gain):
        return None
    return float(gain), {n: float(beyond.theta[fit.model.param_index(n)]) for n in boxed}


def beyond_fit(ctx: Context, graph: BondGraph, fit: Fit, names: list[str],
               only: Sequence[str] | None = None) -> tuple[Fit, list[str]] | None:
    """``(refit, opened)``: ``fit``'s parameters ``names`` refitted from its
    estimates with the boxes of ``fit.at_bound`` (those in ``only`` when
    given; never noise intensities) opened :data:`BOX_OPENING`-fold on the
    side each sits on (the others' boxes kept), and the opened parameters;
    None when none is boxed or the refit fails."""
    model = fit.model
    noise = noise_params(model)
    boxed = [n for n in fit.at_bound if n in names and n not in noise
             and (only is None or n in only)]
    if not boxed:
        return None
    wide = copy.copy(model)
    wide.lower, wide.upper = model.lower.copy(), model.upper.copy()
    for n in boxed:
        j = model.param_index(n)
        lo, hi, v = model.lower[j], model.upper[j], fit.theta[j]
        w = hi - lo
        if hi - v <= v - lo:
            wide.upper[j] = hi * BOX_OPENING if hi > 0 else hi + BOX_OPENING * w
        else:
            wide.lower[j] = lo / BOX_OPENING if lo > 0 else lo - BOX_OPENING * w
    try:
        beyond = fit_model(ctx, graph.copy(graph.name), names, fit.estimates(),
                           "beyond the declared boxes", model=wide)
    except BondGraphError:
        return None
    return beyond, boxed


#: the likelihood gain beyond a box [nats] under which the box does not
#: decide a fit: half the 95 % point of χ²(1) (a likelihood-ratio test of
#: the opened box would not reject it)
BOX_DECIDES = 0.5 * 3.841


def box_not_deciding(ctx: Context, current: Fit, after: Fit, label: str) -> list[str]:
    """The parameters a candidate's refit ``after`` newly puts on their
    declared box (:func:`bondgraph.diagnose.accept.newly_boxed_names`) when
    opening those boxes :data:`BOX_OPENING`-fold gains the likelihood less
    than :data:`BOX_DECIDES`: the box then does not decide the fit (a pulley
    spring that the fit drives to the small end of [0.001, 100] N m/rad
    because the record shows none), so they are no reason to reject
    (:func:`bondgraph.diagnose.accept.decide`'s ``box_free``). Logged; []
    when the gain is larger, the refit fails or none is newly boxed."""
    names = newly_boxed_names(current, after)
    if not names:
        return []
    key = ("beyond the box", id(after), after.nll, tuple(names))
    if key not in ctx.cache:     # one refit per fit and parameters: a pair is judged twice
        ctx.cache[key] = beyond_box(ctx, after.graph, after, list(after.params), only=names)
    r = ctx.cache[key]
    if r is None or not r[0] < BOX_DECIDES:
        return []
    ctx.log(f"  {label}: {', '.join(names)} on the box it declared, but beyond it the "
            f"likelihood gains only {r[0]:.3g} nats (< {BOX_DECIDES:.3g}): the box does not "
            f"decide the fit")
    return names


def boxed_after_accept(ctx: Context, result: LoopResult, fit: Fit, names: list[str],
                       label: str) -> list[str]:
    """An accepted fit whose declared physical parameters sit on the boxes
    the user declared: a warning (logged, in ``result.warnings``) per
    parameter naming the box and what the likelihood would gain beyond it
    (:func:`gain_beyond_box`, one refit). The box stays the user's; an
    effect's own parameters are left out (their boxes are the library's).
    Returns the warnings."""
    noise = noise_params(fit.model)
    declared = result.declared_graph.params if result.declared_graph is not None else {}
    boxed = [n for n in fit.at_bound if n in names and n not in noise and n in declared]
    if not boxed:
        return []
    # the effects' parameters held at their accepted values: the gain is
    # what the declared boxes cost
    gain = gain_beyond_box(ctx, fit.graph, fit, [n for n in names if n in declared or n in noise])
    lo, hi = fit.model.bounds(boxed)
    msgs = [f"the fit with {label}: {n} = {fit.theta[fit.model.param_index(n)]:.4g} on a bound "
            f"of its box [{a:.4g}, {b:.4g}]" for n, a, b in zip(boxed, lo, hi)]
    msgs[-1] += gain
    for m in msgs:
        ctx.log("warning: " + m)
    result.warnings.extend(msgs)
    return msgs


def sim_start(ctx: Context, graph: BondGraph, names: list[str]) -> dict | None:
    """Start values of the declared fit from the output-error fit of its
    non-noise parameters ``names`` (``settings.search.fit == "sim"``); None (logged)
    if that fit fails."""
    # all generated functions: the forward sensitivities need ∂f/∂θ and ∂h/∂θ
    model = Model.from_graph(graph, name=f"_loop_sim_{graph.name}")
    noise = noise_params(model)
    phys = [n for n in names if n not in noise]
    if not phys:
        return None
    pb = problem_for(ctx, model)
    try:
        r = output_error(pb, phys, pb.theta)
    except (BondGraphError, ValueError) as exc:   # ValueError: least_squares at a bad start
        ctx.log(f"  output-error fit failed ({str(exc).splitlines()[0]}); the likelihood fit "
                f"starts from the defaults")
        return None
    ctx.log(f"output-error fit: {_oe_summary(r)}")
    return r.estimates()


def _oe_summary(r) -> str:
    """An output-error result's RMS free-run error and estimates, one line."""
    return (f"RMS free-run error {', '.join(f'{v:.4g}' for v in r.rmse)}; estimates "
            f"{', '.join(f'{k} = {v:.4g}' for k, v in r.estimates().items())}")


def global_start(ctx: Context, fit: Fit, names: list[str]) -> dict | None:
    """Start values for the declared fit again from a global output-error
    search (:func:`bondgraph.diagnose.screen.global_output_error`: a particle
    swarm over the declared boxes of the physical parameters of ``names``,
    then least squares from the better of its best and ``fit``'s estimates)
    when the filter
    predicts by the free run (no process noise, or the free-run likelihood's
    floor, :func:`~bondgraph.diagnose.fit.predicts_by_free_run`: its
    likelihood is then the output-error one, up to the filter's
    initial-state correction) and ``fit``'s free run is poor (NRMSE
    at least :data:`~bondgraph.diagnose.screen.SCREEN_LEVEL`): a local fit
    from the declared defaults can settle in a basin whose free run is worse
    than the record's mean (a user's CED graph with its rectifying sensor
    declared: NRMSE 1.42 locally, 0.29 from the global search). None (logged
    when it was tried) otherwise. The caller keeps the attempt from there
    only when both its NLL and its free-run error are lower: without process
    noise both are the model's criterion, and where they disagree (the
    user's CED graph without the rectification: NLL 407.7 -> 402.2, error
    0.967 -> 1.235) neither basin is the record's."""
    noise = noise_params(fit.model)
    pb = problem_for(ctx, fit.model)
    level = free_run_nrmse(fit, pb.y)
    phys = [n for n in names if n not in noise and n in fit.model.params]
    if not predicts_by_free_run(ctx, pb, fit.theta) or not phys or level < SCREEN_LEVEL:
        return None
    ctx.log(f"  the declared fit's free run is poor (NRMSE {level:.3g} >= {SCREEN_LEVEL}) and "
            f"the filter predicts by it ({_free_run_why(ctx)}): {', '.join(phys)} searched "
            f"globally by output error, then the likelihood from there")
    r = global_output_error(ctx, fit.model, pb, phys, fit.theta)
    if r is None:
        return None
    ctx.log(f"  global output-error fit: {_oe_summary(r)}")
    return r.estimates()


def _free_run_why(ctx: Context) -> str:
    """Why the filter predicts by the free run (:func:`predicts_by_free_run`)."""
    if ctx.settings.search.likelihood == "free_run":
        return "the loop fits by the free-run likelihood, the process noise held at its floor"
    return "the model has no process noise"


def check_declared_fit(fit: Fit) -> None:
    """Raise :class:`~bondgraph.errors.DeclaredFitError` when the declared
    model's fit is unusable: a non-finite NLL, free-run error on the record
    or error on the validation record (a negative mass, a box that lets the
    model go unstable ...): effects scored against it would be meaningless."""
    bad = [(what, v) for what, v in (("NLL", fit.nll), ("free-run error", fit.metric),
                                     ("validation error", fit.validation_metric))
           if v is not None and not np.isfinite(v)]
    if bad:
        raise DeclaredFitError(
            f"the declared model's fit is unusable: {', '.join(f'{w} = {v}' for w, v in bad)}; "
            f"no effect is scored. Check the declared parameters and their boxes "
            f"(signs, units) and the initial state",
            hint="fit the declared model alone (bondgraph estimate) and fix it first")


def check_discretisation(ctx: Context, fit: Fit, limit: float = 0.1,
                         checked: StepCheck | None = None,
                         where: str = "the declared fit", taken: str = "") -> list[str]:
    """The filter's discretisation error at ``fit`` (``where``: the declared
    fit, or an accepted one)
    (:func:`bondgraph.inference.ukf.discretisation_check` with the loop's
    method, substeps and hold) in noise stds per sample (the larger of the
    measurement noise and the filter's innovation std,
    :func:`~bondgraph.diagnose.fit.error_scale`), and without process
    noise its free-run bias bound; above ``limit`` (or the bound above its
    own, :class:`~bondgraph.diagnose.fit.StepCheck`) one line (logged and
    returned) with the fewest substeps of
    :data:`SUBSTEP_LADDER` that bring it within (``checked``: the result of
    :func:`recommended_substeps` if already known): a warning recommending
    them, or with ``taken`` (``auto_substeps``: what the loop adopts,
    :func:`~bondgraph.diagnose.fit.adopted_discretisation`'s text) the note
    that the loop takes it from here on."""
    checked = recommended_substeps(ctx, fit, limit) if checked is None else checked
    if not checked.failed:
        return []
    rec = checked.n_unbiased or checked.n
    o = ctx.problem.ukf
    error = (f"discretisation error of {o.method}({o.substeps}) is "
             f"{step_error(o.method, checked.worst, 'noise stds per sample')}{checked.text()} "
             f"at {where}")
    if taken:
        msg = f"auto_substeps: {error}; the filter takes {taken} from {where} on"
        ctx.log(msg)
        return [msg]
    other = "rk4" if o.method == "ros2" else "ros2"
    advice = (f"use --substeps {rec}" if rec else
              f"{o.method} is not within it with {SUBSTEP_LADDER[-1]} substeps: use --method "
              f"{other} and more substeps, or a shorter sample interval")
    if checked.step_failed:
        advice += (" (from Python: chosen_numerics(graph, record, settings) before run_loop, "
                   "or SearchOptions(auto_substeps=True, auto_method=True))")
    elif ctx.settings.search.auto_substeps and checked.n_unbiased:   # the bias alone
        advice = (f"the loop refits its final estimates with the substeps the check asks for "
                  f"there (here {rec}; --substeps {rec} for every fit)")
    else:       # the bias alone: what the loop says, not what it adopts substeps for
        advice += " for estimates the discretisation does not move"
    msg = f"{error} (a model error that biases the fit and the scores); {advice}"
    ctx.log("warning: " + msg)
    return [msg]


def _adopted(ctx: Context, fit: Fit, checked: StepCheck, auto: bool) -> tuple:
    """``(discretisation, text)`` the loop takes when ``auto`` and the
    check failed (``checked``, :func:`recommended_substeps`): those
    substeps on the intervals that need them or throughout, or the other
    method where it is cheaper
    (:func:`~bondgraph.diagnose.fit.adopted_discretisation`); else
    ``(None, "")``."""
    if not (auto and checked.step_failed):
        return None, ""
    return adopted_discretisation(ctx, fit, checked)


def fit_after_discretisation_check(
        ctx: Context, result: LoopResult, fit: Fit, label: str,
        judged: tuple | None = None) -> tuple[Fit | None, Decision | None]:
    """The discretisation check at an accepted fit: an added effect can make
    the model stiff (an end stop's contact, a hysteresis state), and the
    filter's discretisation error then biases its estimates by more than
    their Cramér-Rao std (an end stop of a mass-spring-damper: 0.09 %, 6.6
    std at ROS2(8); 0.4 std at 32 substeps). Above 0.1 measurement-noise std
    per sample a warning (logged, in ``result.warnings``); with
    ``settings.search.auto_substeps`` the recommended substeps for the rest of the
    loop and ``fit`` refitted with them (warm start). The check measures
    the error in ``fit``'s own measurement-noise stds (:func:`conditioned`),
    the ones the loop goes on with, not those of the fit it replaces (an
    end stop's refit: 0.0023 and 0.015 where the declared fit, its noise
    absorbing the missing stop, held 0.059 and 0.44; a check 26 times too
    lenient).

    With ``judged`` = (current fit, new parameters' count, comparable, the
    added candidates) the refit must pass the accept rule against the fit it replaces
    (:func:`decided`), as the coarser fit did: a refit that does not (on the
    user CED graph a pair's held-out error 0.2667 at 2 RK4 substeps became
    0.4975 at 4, above the 0.4706 it replaced) is rejected (logged, in
    ``result.warnings``), the filter's substeps restored, and None returned:
    the acceptance rested on the coarser discretisation. That refit is
    continued until it converges (:func:`~bondgraph.diagnose.confirm.continued`;
    one still not converged is not comparable), as a confirmation is: the
    decision judged whatever ten iterations reached (the user's EMPS graph
    on every tenth sample: Coulomb friction refitted at ROS2(1), not
    converged, NLL −10164.6 and held out 0.01286 before the trust-region
    damping, −10369.3 and 0.0384 after; accepted, then rejected, by where
    the iterations stopped).

    Returns ``(fit, decision)``: the fit to continue from, or None
    (rejected); and with ``judged``, when the fit was refitted, the
    accept rule's :class:`~bondgraph.diagnose.accept.Decision` on that
    refit (the step reports its figures, not the coarser fit's: a user's
    CED graph reported a held-out error 0.39 for a low-pass whose refit at
    2 substeps, the model the loop went on with, read 0.4516), else None."""
    with conditioned(ctx, fit):     # its own noise levels, not the previous fit's
        checked = recommended_substeps(ctx, fit)
        disc, taken = _adopted(ctx, fit, checked, ctx.settings.search.auto_substeps)
        warn = check_discretisation(ctx, fit, checked=checked, where=f"the fit with {label}",
                                    taken=taken)
    result.warnings.extend(warn)
    if disc is None:
        return fit, None
    before = ctx.problem
    refit, disc = _refit_at_adopted(
        ctx, result.warnings, fit, label, disc, checked,
        lambda at: fit_model(ctx, fit.graph, list(fit.params), fit.estimates(), at,
                             model=fit.model))
    if refit is None:
        return (None, None) if judged is not None else (fit, None)
    at = f"{label} at {disc.method}({disc.substeps})"
    if judged is not None:
        current, dof, comparable, added = judged
        refit = continued(ctx, fit.graph, refit, at)
        d = decided(ctx, current, refit, dof, comparable and refit.converged is not False, at,
                    added)
        if not d.accepted:
            msg = (f"{label} refitted at {disc.method}({disc.substeps}) no longer passes the "
                   f"accept rule ({d.reason}; error {d.error_before:.4g} -> "
                   f"{d.error_after:.4g}): its acceptance rested on the coarser "
                   f"discretisation; not accepted, the filter keeps "
                   f"{before.disc.method}({before.disc.substeps})")
            ctx.log("reject " + msg)
            result.warnings.append(msg)
            ctx.problem = before
            ctx.cache.clear()
            return None, d
        return refit, d
    adm = admissibility(ctx, refit)
    trouble = refit.unstable or (None if adm.ok else f"not physically admissible: "
                                                     f"{adm.reason()}")
    if trouble:     # accepted at the coarser step; the finer one disagrees
        msg = (f"the fit with {label} refitted at {disc.method}({disc.substeps}) {trouble}: "
               f"its acceptance rested on the coarser discretisation")
        ctx.log("warning: " + msg)
        result.warnings.append(msg)
    return refit, None


def _refit_at_adopted(ctx: Context, warnings: list, fit: Fit, label: str, disc,
                      checked: StepCheck, refit) -> tuple:
    """``(refit, discretisation)``: ``refit(at)`` (``fit`` refitted, ``at``
    its label) with the filter at ``disc``, the discretisation the check at
    ``fit`` adopted (``ctx.problem`` left at it); where the filter fails
    there and ``disc`` is the other method, at the current method's
    substeps the check asks for (``checked.n``,
    :func:`~bondgraph.diagnose.fit.refined_discretisation`); ``(None,
    None)`` with the filter restored and the reason appended to
    ``warnings`` (logged as a rejection, but for the declared fit, whose
    caller stops the loop) when it fails at each. The check follows one
    trajectory; the filter's sigma points can go where the adopted step is
    not stable (a user's CED graph with Dahl friction at the motor: RK4(3)
    adopted in place of ROS2(16) for a source lag with a cubic sensor term,
    the filter non-finite at its second sample; the loop ended there with
    an error and the pair's step was lost)."""
    before = ctx.problem
    tried, todo = [], [disc]
    while todo:
        d = todo.pop(0)
        ctx.problem = before.conditioned_on(disc=d)
        ctx.cache.clear()
        at = f"{label} at {d.method}({d.substeps})"
        try:
            return refit(at), d
        except NumericalError as exc:
            why = str(exc).splitlines()[0]
            tried.append(f"{d.method}({d.substeps}): {why.removeprefix(at + ': ')}")
        ctx.problem = before
        ctx.cache.clear()
        if d is disc and d.method != before.disc.method and checked.n is not None:
            same = refined_discretisation(ctx, fit, checked.n)[0]
            ctx.log(f"  {'the declared fit' if label == DECLARED else f'the fit with {label}'}"
                    f": the filter fails at {tried[-1]}; refitted at "
                    f"{same.method}({same.substeps}) instead")
            todo.append(same)
    what = "the declared fit" if label == DECLARED else f"the fit with {label}"
    msg = (f"{what} cannot be refitted at the step its discretisation check asks for (the "
           f"filter fails at {'; at '.join(tried)})")
    if label != DECLARED:       # the declared fit's caller raises it
        msg += f": not accepted, the filter keeps {before.disc.method}({before.disc.substeps})"
        ctx.log("reject " + msg)
    warnings.append(msg)
    return None, None


def unbiased_final(ctx: Context, result: LoopResult, current: Fit) -> Fit:
    """The loop's final estimates at numerics within the free-run bias
    bound: with ``settings.search.auto_substeps``, where the check at the
    final fit (:func:`~bondgraph.diagnose.fit.recommended_substeps`) fails by
    the bias alone (no process noise: the filter predicts by the free run),
    the final model refitted once, warm, with the substeps that bring both
    bounds within (:attr:`~bondgraph.diagnose.fit.StepCheck.n_unbiased`,
    uniform), its Cramér-Rao std at them, and the largest shift of an
    estimate said in those std (logged; in ``result.final_checks`` as a
    ``"note: "``; a refit not kept: a warning, in ``result.warnings`` too). The
    search, its scores and refits, stays at the cheaper step (the bias moves
    an estimate, rarely a ranking: a user's Silverbox graph at RK4(2) and 4
    throughout took 4.5 times the time for the same effects); the figures
    the user takes away are the ones the check accepts (the same graph's
    final model at RK4(1), bias bound 122 std: refitted at RK4(4) its
    estimates moved by up to 7.1 std, its NLL 389 nats lower, its free-run
    error 7 % lower on the record and on the held-out quarter).

    The refit is kept only where it converges, simulates, is physically
    admissible and its free-run error is not larger on the record or on
    any validation record; else ``current`` (said, with why). Where no
    substeps of :data:`SUBSTEP_LADDER` bring the bias within, a warning
    says so (in ``result.final_checks`` too) and ``current`` is kept.
    """
    if not ctx.settings.search.auto_substeps:
        return current
    checked = recommended_substeps(ctx, current)
    n = checked.n_unbiased
    before, d = ctx.problem, ctx.problem.disc
    coarse = f"{d.method}({d.substeps})"
    if checked.step_failed or not checked.bias > checked.bias_limit:
        return current
    if n is None:       # the summary says it too, not only the accepted steps' warnings
        msg = (f"final estimates: the free-run bias bound at {coarse} is {checked.bias:.3g} "
               f"Cramér-Rao std (above {checked.bias_limit:g}) and no substeps up to "
               f"{SUBSTEP_LADDER[-1]} bring it within: the estimates may be off by up to that "
               f"(try --method {'rk4' if d.method == 'ros2' else 'ros2'} or a shorter "
               f"sample interval)")
        ctx.log("warning: " + msg)
        result.warnings.append(msg)
        result.final_checks.append(msg)
        return current
    ctx.problem = before.conditioned_on(disc=replace(d, substeps=int(n), refine=()))
    ctx.cache.clear()
    at = f"the final model at {d.method}({n})"
    with phase(f"refitting the final model at {d.method}({n}) (its free-run bias bound)"):
        try:
            refit = fit_model(ctx, current.graph, list(current.params), current.estimates(),
                              at, model=current.model)
            refit = continued(ctx, current.graph, refit, at)
            trouble = final_refit_trouble(ctx, current, refit)
            if trouble is None:
                refit.std = parameter_std(ctx, refit)
        except (BondGraphError, FloatingPointError, np.linalg.LinAlgError) as exc:
            trouble = f"failed ({str(exc).splitlines()[0]})"
    head = (f"final estimates: the free-run bias bound at {coarse} is {checked.bias:.3g} "
            f"Cramér-Rao std (above {checked.bias_limit:g}; {n} substeps bring it within)")
    if trouble is None:
        msg = f"note: {head}; refitted at {d.method}({n}): {shift_text(current, refit)}"
        ctx.log(msg)
        result.final_checks.append(msg)
        return refit
    ctx.problem = before
    ctx.cache.clear()
    msg = (f"{head}; refitted at {d.method}({n}) it {trouble}: the estimates at {coarse} are "
           f"kept (they may be off by up to that bound; --substeps {n} for every fit)")
    ctx.log("warning: " + msg)
    result.warnings.append(msg)
    result.final_checks.append(msg)
    return current


def final_refit_trouble(ctx: Context, current: Fit, refit: Fit) -> str | None:
    """Why :func:`unbiased_final` does not keep ``refit`` of ``current``
    (not finite, not converged, does not simulate, not admissible, a larger
    free-run error on the record or on any validation record), or None."""
    if not np.isfinite(refit.nll):
        return "has no finite likelihood"
    if refit.converged is False:
        return "did not converge"
    if refit.unstable:
        return f"does not simulate ({refit.unstable})"
    adm = admissibility(ctx, refit)
    if not adm.ok:
        return f"is not physically admissible ({adm.reason()})"
    judged = [("record", current.metric, refit.metric),
              ("validation record", current.validation_metric, refit.validation_metric)]
    judged += [(f"validation record {k}", v, (refit.more_metrics or {}).get(k))
               for k, v in (current.more_metrics or {}).items()]
    for what, a, b in judged:
        if a is not None and np.isfinite(a) and not (b is not None and b <= a):
            return f"simulates worse on the {what} ({a:.4g} -> {b if b is None else f'{b:.4g}'})"
    return None


def shift_text(current: Fit, refit: Fit) -> str:
    """``"NLL a -> b, free-run error c -> d (validation e -> f); the
    estimates moved by at most 8.4 Cramér-Rao std (beta: x -> y)"``:
    ``refit`` against ``current`` (its std, ``refit.std``)."""
    old, new = current.estimates(), refit.estimates()
    z = {k: abs(new[k] - old[k]) / refit.std[k] for k in new
         if k in old and refit.std.get(k) and np.isfinite(refit.std[k]) and refit.std[k] > 0}
    out = (f"NLL {current.nll:.2f} -> {refit.nll:.2f}, free-run error {current.metric:.4g} -> "
           f"{refit.metric:.4g}")
    if current.validation_metric is not None and refit.validation_metric is not None:
        out += f" (validation {current.validation_metric:.4g} -> {refit.validation_metric:.4g})"
    if z:
        k = max(z, key=z.get)
        out += (f"; the estimates moved by at most {z[k]:.3g} Cramér-Rao std ({k}: "
                f"{old[k]:.6g} -> {new[k]:.6g}); these are reported")
    return out


def resolved_fit(ctx: Context, graph: BondGraph, initial: Fit) -> tuple[Fit, list[str]]:
    """The declared fit and the discretisation warnings: with
    ``settings.search.auto_substeps``, a filter whose discretisation error at the
    declared fit exceeds 0.1 measurement-noise std per sample takes the
    recommended substeps (for the rest of the loop: the likelihood then
    judges the model, not its discretisation) and the declared model is
    refitted (logged); where the filter fails at the adopted step and at the
    current method's own substeps (:func:`_refit_at_adopted`), the loop
    stops (:class:`~bondgraph.errors.NumericalError`, the steps and reasons
    named) rather than go on with numerics that fail their own check."""
    checked = recommended_substeps(ctx, initial)
    disc, taken = _adopted(ctx, initial, checked, ctx.settings.search.auto_substeps)
    warn = check_discretisation(ctx, initial, checked=checked, taken=taken)
    if disc is None:
        return initial, warn
    refit, _ = _refit_at_adopted(ctx, warn, initial, DECLARED, disc, checked,
                                 lambda at: initial_fit(ctx, graph, again=True))
    if refit is None:       # no numerics within the check that the filter can run
        raise NumericalError(f"{warn[-1]}: the loop does not go on with numerics that fail "
                             f"their own check; give --method and --substeps the filter runs "
                             f"at, or declare process noise on the stiff states")
    return refit, warn


#: the label of the declared fit in :func:`_refit_at_adopted`
DECLARED = "the declared fit"


def free_run_likelihood(ctx: Context, graph: BondGraph, initial: Fit,
                        warn: list[str]) -> tuple[Fit, list[str]]:
    """The declared fit under the likelihood the loop fits and judges by
    (``settings.search.likelihood``). ``"one_step"``: ``initial``.
    ``"free_run"``, or ``"auto"`` when process noise is estimated (its
    reason, :func:`_switch_reason`: it absorbs the model's error,
    :func:`~bondgraph.diagnose.fit.process_noise_absorbing`, or the loop
    judges by the free run): the
    process-noise intensities estimated with θ are held at a floor
    (:func:`~bondgraph.diagnose.fit.process_noise_floor`: their random walk
    0.1 % of each state's spread), the measurement-noise stds the record
    declares are estimated instead (started at the free run's RMS error),
    and the declared model is refitted; every later fit, score test and
    likelihood ratio of the loop uses that problem. The filter's prediction
    is then the free run from the filtered start, and its likelihood that of
    the free-run (output) errors, the error measure the loop reports (Ljung
    1999, ch. 7: the output-error predictor). Under ``"auto"`` the switch is
    kept only if the refit's free-run error on the record is not larger, or
    neither free run describes the record (:func:`_neither_describes`). Said
    in the log and the fit's warnings (the report). Returns the fit and the
    discretisation warnings (``warn``, or the check's at the refit,
    :func:`resolved_fit`, which may refit it with more substeps).

    A user's cascaded tanks (Schoukens & Noël 2017): one-step, the process
    noise explained the overflow and nothing was accepted (held out 0.367);
    free-run, both overflows were accepted as a pair (0.294), 0.200 after."""
    s = ctx.settings
    mode = s.search.likelihood
    if mode == "one_step":
        return initial, warn
    absorbing = process_noise_absorbing(ctx, initial)
    floors = process_noise_floor(ctx, initial, [n for n in s.params if n in noise_params(
        initial.model)])
    tried = absorbing or (floors and s.metric in FREE_RUN_METRICS)
    if mode == "auto" and (not tried or ctx.problem.noise.mode == "model"):
        if absorbing:
            ctx.log("  the process noise absorbs the model's error, but the free-run likelihood "
                    "needs the measurement noise estimated and noise='model' holds the "
                    "graph's own: the one-step likelihood stays")
        ctx.settings = replace(s, search=replace(s.search, likelihood="one_step"))
        return initial, warn
    released, why = _released_noise(ctx, initial), _switch_reason(mode, absorbing, initial)
    if not floors and not released:
        ctx.log(f"  {why}, but the graph's process noise is not estimated: the one-step "
                f"likelihood stays")
        return initial, warn
    base_settings, base_problem = s, ctx.problem
    _hold_for_free_run(ctx, floors, released)
    held = ", ".join(f"{n} = {v:.3g}" for n, v in floors.items())
    ctx.log(f"{why}: the loop fits and judges by the free-run likelihood (the filter's "
            f"prediction is the free run, as the error measure's)"
            + (f"; process noise held at {held} (a random walk of "
               f"{100 * FREE_RUN_SHARE:g} % of each state's spread, not below its box)"
               if floors else "")
            + (f"; the measurement noise of {', '.join(released)} estimated (it now holds the "
               f"model's error)" if released else _held_sensor_note(ctx))
            + "; --likelihood one-step keeps the one-step likelihood")
    try:
        # the numerics checked before the refit is judged: the fit compared is the fit kept
        again, checked = resolved_fit(ctx, graph, initial_fit(ctx, graph, again=True))
    except DeclaredFitError as exc:
        if mode == "free_run":
            raise
        ctx.log(f"  the declared fit under the free-run likelihood failed: {_line(exc)}")
        again = None
    if again is None or (mode == "auto" and not again.metric <= initial.metric
                         and not _neither_describes(ctx, initial, again)):
        ctx.settings, ctx.problem = (replace(base_settings, search=replace(
            base_settings.search, likelihood="one_step")), base_problem)
        ctx.cache.clear()
        ctx.log("  the free-run likelihood's fit is not better on the record ("
                + ("it failed" if again is None else
                   f"free-run error {initial.metric:.4g} -> {again.metric:.4g}")
                + "): the one-step likelihood stays")
        return initial, warn
    msg = (f"{why}: fitted and judged by the free-run likelihood"
           + (f", process noise held at {held}" if floors else "")
           + f" (free-run error on the record {initial.metric:.4g} -> {again.metric:.4g})")
    again.warnings.insert(0, msg)
    return again, checked


def _line(exc: Exception) -> str:
    """The first line of ``exc``'s message."""
    return str(exc).splitlines()[0]


#: the built-in error measures of a free run: where the loop judges by one
#: of them, ``likelihood="auto"`` tries the free-run likelihood whenever
#: process noise is estimated (:func:`_switch_reason`)
FREE_RUN_METRICS = ("nrmse_sim", "rmse_sim")


def _switch_reason(mode: str, absorbing: list, initial: Fit) -> str:
    """Why :func:`free_run_likelihood` tries the free-run likelihood: the
    process noise absorbs the model's error (``absorbing``), the user asked
    (``mode``), or, under ``"auto"``, the process noise is estimated and the
    loop judges by the free run (its metric one of :data:`FREE_RUN_METRICS`;
    a case's own metric, as the EMPS benchmark's inverse-model error, does
    not count): the fit under that criterion is tried and kept where its
    free-run error is not larger (a user's EMPS mass graph
    with an estimated force noise, the noise grown 1.4-fold only: one-step
    held out 0.3951, a power-law viscous term and a cold-start term after,
    0.03948; the free-run fit 0.174, then the direction-dependent and the
    Coulomb friction, 0.01918)."""
    if absorbing:
        return f"the process noise absorbs the model's error ({'; '.join(m for _, m in absorbing)})"
    if mode == "free_run":
        return "--likelihood free-run"
    return (f"the process noise is estimated and the loop judges by the free run (the one-step "
            f"fit's free-run error on the record {initial.metric:.4g})")


def _neither_describes(ctx: Context, initial: Fit, again: Fit) -> bool:
    """Whether neither the one-step fit ``initial`` nor the free-run one
    ``again`` has a free run that describes the record (NRMSE at least
    :data:`~bondgraph.diagnose.screen.SCREEN_LEVEL` each; logged): the
    free-run likelihood is then kept although its error is not lower, for
    under it the output-error screen and search look for the basin the
    declared fit missed, which they cannot under the one-step likelihood's
    process noise. A user's speed graph on a sign-blind counter's record,
    process noise declared: one-step 1.43, free run 1.50; kept, the screen
    found the rectification (held out 4 times lower), where the one-step
    loop accepted a partial one (1.74 -> 1.69)."""
    y = ctx.problem.arrays[2]
    a = free_run_nrmse(initial, y)
    b = free_run_nrmse(again, y) if a >= SCREEN_LEVEL else a
    if not min(a, b) >= SCREEN_LEVEL:
        return False
    ctx.log(f"  neither the one-step fit's free run nor the free-run fit's describes the record "
            f"(NRMSE {a:.4g}, {b:.4g}, each >= {SCREEN_LEVEL}): the free-run likelihood is kept, "
            f"under which the output-error screen looks for the basin the declared fit missed")
    return True


def _hold_for_free_run(ctx: Context, floors: dict, released: dict) -> None:
    """``ctx``'s settings and problem for the free-run likelihood: the
    process-noise parameters ``floors`` (name -> value) fixed, out of
    ``params`` and ``initial_params``; the measurement noises ``released``
    (output -> start std) estimated; the problem cache cleared."""
    s = ctx.settings
    ctx.settings = replace(s, params=[n for n in s.params if n not in floors],
                           initial_params=None if s.initial_params is None else [
                               n for n in s.initial_params if n not in floors],
                           fixed={**s.fixed, **floors},
                           search=replace(s.search, likelihood="free_run"))
    problem = ctx.problem.with_fixed(floors)
    if released:
        problem = problem.conditioned_on(noise_levels=released, noise_outputs=list(
            problem.noise.estimated) + [o for o in released if o not in problem.noise.estimated])
    ctx.problem = problem
    ctx.cache.clear()


def _held_sensor_note(ctx: Context) -> str:
    """The clause of the free-run switch's log line for measurement noise it
    does not estimate: under ``noise='model'`` the graph's own sensor stds
    stay, so the free-run likelihood is a least-squares fit of the free-run
    errors weighted by them (Ljung 1999, §7.3), not the output-error
    likelihood with the noise level concentrated out; "" otherwise."""
    if ctx.problem.noise.mode != "model":
        return ""
    return ("; the measurement noise stays the graph's own (noise='model'): the free-run "
            "errors are weighed by those stds, a weighted least squares, not estimated "
            "(--noise auto estimates them)")


def _released_noise(ctx: Context, fit: Fit) -> dict:
    """Output -> start std of the measurement noises the record declares
    (held by the one-step likelihood) that the free-run likelihood
    estimates: the RMS of the free run's error on that output (where finite
    and > 0)."""
    noise = ctx.problem.noise
    if noise.mode != "auto" or fit.sim_y is None:
        return {}
    y = np.asarray(ctx.problem.arrays[2], float)
    out = {}
    for j, o in enumerate(fit.model.outputs):
        if o in noise.held and o not in noise.estimated:
            e = y[:, j] - np.asarray(fit.sim_y, float)[: len(y), j]
            rms = float(np.sqrt(np.nanmean(e ** 2))) if np.isfinite(e).any() else np.nan
            if np.isfinite(rms) and rms > noise.held[o]:
                out[o] = rms
    return out


def likelier_hold(ctx: Context, graph: BondGraph, initial: Fit,
                  warn: list[str]) -> tuple[Fit, list[str]]:
    """The declared fit under ``settings.search.other_hold`` too (an input
    whose shape is ambiguous, :func:`chosen_numerics`), with the
    discretisation chosen for that hold at the declared fit; when its NLL is
    lower by more than :data:`~bondgraph.inference.discretise.HOLD_MARGIN`,
    the loop goes on under that hold (``ctx``'s problem and the filter's and
    free runs' holds replaced) from that fit. One line says which and why.
    A fit under the other hold that fails keeps the first.

    Returns
    -------
    (Fit, list of str)
        The declared fit and its discretisation warnings.
    """
    s = ctx.settings
    other = s.search.other_hold
    if other is None or not np.isfinite(initial.nll):
        return initial, warn
    mine = ctx.problem.disc.hold
    why = "the likelihood of the declared fits under both holds (the shape is ambiguous)"
    choice = choose_discretisation(ctx.problem, initial.theta, hold=other, why=why)
    search = replace(s.search, other_hold=None)
    alt = Context(ctx.problem.conditioned_on(disc=choice.disc),
                  replace(with_discretisation(s, choice.disc), search=search),
                  ctx.log, ctx.progress, executor=ctx.executor)
    ctx.log(choice.line("at the declared fit, the other hold"))
    try:
        fit2, warn2 = resolved_fit(alt, graph, initial_fit(alt, graph, again=True))
    except (DeclaredFitError, NumericalError, np.linalg.LinAlgError) as exc:
        ctx.log(f"input hold: the declared fit under the {other} hold failed ({exc}); "
                f"{mine} kept")
        ctx.settings = replace(s, search=search)
        return initial, warn
    better, line = hold_verdict(other, fit2.nll, mine, initial.nll, note="(each fitted)")
    ctx.log(line)
    if not better:
        ctx.settings = replace(s, search=search)
        return initial, warn
    ctx.problem, ctx.settings = alt.problem, alt.settings
    ctx.cache.clear()
    return fit2, warn2


def glitches(ctx: Context, result: LoopResult, fit: Fit) -> list[str]:
    """Warnings of isolated outliers at the final model: in its innovations
    on the estimation record (:func:`~bondgraph.diagnose.residuals.innovation_outlier_warnings`)
    and in its free-run errors on each validation record
    (:func:`~bondgraph.diagnose.residuals.free_run_outlier_warnings`). A
    user's cart whose 100 Hz speed sensor has six 2 m/s glitches (noise
    0.01 m/s): the noise estimate 0.085 m/s and every std 8 times too wide,
    until the glitches are named."""
    stored = getattr(fit.ukf, "innovations", None) is not None
    out = innovation_outlier_warnings(fit.ukf, fit.model.outputs, ctx.problem.t,
                                      ctx.problem.name) if stored else []
    runs = []
    if fit.validation_sim_y is not None and result.validation_measured is not None:
        runs.append((validation_records(ctx.settings)[0].name, result.validation_time,
                     result.validation_measured, fit.validation_sim_y))
    for rec in ctx.settings.more_validation:
        if fit.more_sim_y.get(rec.name) is not None and rec.name in result.more_measured:
            runs.append((rec.name, *result.more_measured[rec.name], fit.more_sim_y[rec.name]))
    for name, t, y, sim in runs:
        y, sim = np.asarray(y, float), np.asarray(sim, float)
        n = min(len(y), len(sim), len(t))
        out += free_run_outlier_warnings(y[:n] - sim[:n], fit.model.outputs, t[:n], name)
    return out


def hold_at_final(ctx: Context, result: LoopResult, fit: Fit) -> None:
    """The loop's final model refitted with each input whose hold its shape
    chose (:func:`~bondgraph.inference.discretise.record_input_holds`) held
    the other way (zero-order <-> linear; the step chosen for that hold at
    the final θ, :func:`choose_discretisation`), when
    ``settings.search.check_hold``. Where the record is likelier so by more
    than :data:`~bondgraph.inference.discretise.HOLD_CHECK_MARGIN` nats, a
    warning (logged, in ``result.warnings`` and so in the reports) names the
    input, both NLLs, the estimates that moved most and how to declare the
    hold; the result is not changed (its effects were chosen under the
    shape's hold: run again with the hold declared).

    The shape of a record cannot tell a command held over each sample whose
    steps vary smoothly from a sampled continuous signal, and the declared
    fit's likelihood cannot settle it while the model lacks an effect (a
    choke without its core's saturation was likelier under the wrong hold);
    the final model is where the evidence is best. A mass under a multisine
    force held zero-order over each 10 ms sample: the shape says linear, the
    declared fit under it puts M 42 std off, and zero-order is 749 nats
    likelier (with steps allowed the loop adds an input delay of half a
    sample instead, and the two holds are then within 8 nats: no warning)."""
    if not ctx.settings.search.check_hold or not np.isfinite(fit.nll):
        return
    problem = problem_for(ctx, fit.model)
    inputs = record_input_holds(problem.record, fit.model.inputs, problem.u)
    mine = list(split_hold(problem.disc.hold, len(inputs)))
    for j, h in enumerate(inputs):
        if h.source != "shape" or h.hold is None or mine[j] not in ("zoh", "linear"):
            continue
        flipped = "linear" if mine[j] == "zoh" else "zoh"
        other = join_hold(mine[:j] + [flipped] + mine[j + 1:])
        warning = _other_hold_warning(ctx, fit, problem, h.name, mine[j], flipped, other)
        if warning:
            ctx.log(f"warning: {warning}")
            result.warnings.append(warning)
            result.final_checks.append(warning)


def _other_hold_warning(ctx: Context, fit: Fit, problem, name: str, mine: str, flipped: str,
                        other: str) -> str | None:
    """The warning of :func:`hold_at_final` for one input, or None (the
    shape's hold is as likely, or the refit under the other fails)."""
    s = ctx.settings
    why = f"the final model's likelihood under the other hold of '{name}'"
    try:
        choice = choose_discretisation(problem, fit.theta, hold=other, why=why)
        quiet = Context(ctx.problem.conditioned_on(disc=choice.disc),
                        replace(with_discretisation(s, choice.disc),
                                search=replace(s.search, check_hold=False)),
                        lambda line: None, False, executor=ctx.executor)
        theta, nll, std = likelihood_fit(quiet, fit.model, fit.params, fit.theta,
                                         f"the final model, {name} held {flipped}")
    except (BondGraphError, FloatingPointError, np.linalg.LinAlgError) as exc:
        ctx.log(f"input hold of '{name}': the final model under the {flipped} hold could not "
                f"be fitted ({str(exc).splitlines()[0]}); not compared")
        return None
    better = hold_verdict(flipped, nll, mine, fit.nll, margin=HOLD_CHECK_MARGIN)[0]
    ctx.log(hold_check_line(name, "at the final model", flipped, nll, mine, fit.nll, better))
    if not better:
        return None
    names = fit.params
    moves = moved_most(names, {n: theta[fit.model.param_index(n)] for n in names},
                       {n: fit.theta[fit.model.param_index(n)] for n in names},
                       {n: fit.std.get(n) or std.get(n) for n in names})
    return other_hold_warning(
        name, flipped, mine, nll, fit.nll, "the final model fitted under each", moves,
        f"The estimates and the effects found under {mine} can be off: declare the hold (the "
        f"record's sidecar: columns.{name}.hold = \"{flipped}\") or run again with --hold "
        f"{other}, and compare" + _misfit_clause(fit))


#: innovations whose whiteness statistic exceeds this many times its degrees
#: of freedom are far from white (:func:`_misfit_clause`)
FAR_FROM_WHITE = 10.0


def _misfit_clause(fit: Fit) -> str:
    """A clause for the hold warning when the final model's innovations are
    far from white (the Ljung-Box sum above :data:`FAR_FROM_WHITE` times its
    degrees of freedom): the model's own misfit then weighs in the two
    holds' likelihoods as much as the hold does. A user's swing arm, its
    motor torque held zero-order: the final model without the arm's gravity
    law (whiteness 7.4e4 against about 20) was 83 nats likelier under the
    linear hold; with the law, zero-order was 293 nats likelier."""
    r = getattr(fit, "residuals", None)
    dof = getattr(r, "whiteness_dof", 0) or 0
    if dof <= 0 or not np.isfinite(r.whiteness) or r.whiteness <= FAR_FROM_WHITE * dof:
        return ""
    return (f"; but the final model's innovations are far from white (whiteness "
            f"{r.whiteness:.3g}, about {dof:g} if white): what it lacks weighs in both "
            f"likelihoods, and the hold its shape says may still be the right one")


def run_step(ctx: Context, result: LoopResult, current: Fit, step: int,
             name: str) -> tuple[Fit, str]:
    """One step: score every candidate, confirm the best significant ones,
    accept the best confirmed one that passes :func:`decide`. Appends the
    ranking, the step or the rejections to ``result``.

    Returns
    -------
    (Fit, str)
        The new current fit and the outcome (:data:`ACCEPTED`,
        :data:`NONE_ACCEPTED`, :data:`NOTHING_SIGNIFICANT`).
    """
    t_ev = time.perf_counter()
    with phase(f"step {step}: scoring the candidates"):
        scales = operating_scales(ctx, current)
        ranking, signif = gather_evidence(ctx, current, scales)
    result.rankings.append(ranking)
    if ctx.settings.true_effect is not None:
        kind, target = ctx.settings.true_effect
        result.truth_ranks.append(rank_of(ranking, kind, target))
        rank = result.truth_ranks[-1]
        ctx.log(f"  the true effect {kind} @ {target} ranks {rank}" if rank is not None else
                f"  the true effect {kind} @ {target} is not among the candidates (accepted "
                f"already, or it cannot attach)")
    ctx.log(f"step {step}: {len(ranking)} candidates scored in "
            f"{time.perf_counter() - t_ev:.1f} s; best: " + "; ".join(
                f"{c.label} (χ²={c.statistic:.1f}, k={c.dof})"
                for c in [c for c in ranking if not c.failed][:5]))
    failed = [c for c in ranking if c.failed]
    if failed:
        ctx.log(f"  {len(failed)} candidate(s) could not be scored (filter failed): " + "; ".join(
            f"{c.label}: {c.failed}" for c in failed[:5]))
    if ranking and ranking[0].equivalent:
        ctx.log(f"  note: {ranking[0].label} is indistinguishable in this record from "
                f"{', '.join(ranking[0].equivalent)} (signatures correlated > 0.999)")
    if not signif:
        ctx.log("nothing significant left: stop")
        return current, NOTHING_SIGNIFICANT
    tag = f"{name}_step{len(result.steps) + 1}"
    if structural_skipped(ctx.settings, ranking):
        signif = significant_after_lead_check(ctx, result, current, signif, scales, tag)
    ahead = next_step_ahead(ctx, current, signif, scales, tag, step)
    earlier = {id(a) for a in result.applied}
    try:
        with phase(f"step {step}: confirming the best candidates by refits"):
            after = confirm_in_rounds(ctx, result, current, signif, scales, tag, step)
            if after is None and structural_skipped(ctx.settings, result.rankings[-1]) \
                    and not any(c.kind != "score" for c in result.rankings[-1]):
                after = accepted_among_skipped_structurals(ctx, result, current, scales, tag,
                                                           step)
            if after is None and ctx.settings.accept.pairs:
                after = accepted_pair(ctx, result, current, scales, tag, step)
            if after is not None and earlier:
                after = replaced_earlier(ctx, result, current, after, earlier, scales, tag)
    finally:
        if ahead is not None:
            ahead.set()
    return (after, ACCEPTED) if after is not None else (current, NONE_ACCEPTED)


def next_step_ahead(ctx: Context, current: Fit, signif: list[Candidate], scales: Scales,
                    tag: str, step: int):
    """While step ``step`` confirms its candidates, compile the next step's
    structural candidates on the graph it most likely accepts: ``current``'s
    plus the best-scored significant candidate, named ``tag`` as the step's
    refits name their graphs (the kernels' cache key holds the model's name,
    not its values; :func:`bondgraph.diagnose.scoring.compile_step_ahead`).
    Returns the event that stops the work, or None (the last step, or
    nothing to do)."""
    s = ctx.settings
    if step >= s.search.max_steps or not signif:
        return None
    try:
        best = max(signif, key=lambda c: c.score)
        eff = get_effect(best.effect, s.effects)
        g = current.graph.copy(tag)
        eff.apply(g, best.target, start_values(eff, best), scales)
    except Exception:   # noqa: BLE001 - work ahead of need: the step goes on without it
        return None
    return compile_step_ahead(ctx, g)


#: the best confirmed candidates whose pairs are refitted when no single one
#: passes the accept rule (at most PAIR_TOP·(PAIR_TOP − 1)/2 refits)
PAIR_TOP = 3
#: rejections that no partner can mend: the refit itself is unusable, or the
#: record does not identify the candidate's terms apart from the current
#: model's parameters (:func:`bondgraph.diagnose.accept.unidentified_effect`):
#: a partner's parameters only lower the information about those terms given
#: the others (a Schur complement of the Fisher information shrinks as
#: nuisance parameters are added), so a pair with it leaves them undetermined
#: too. On the EMPS benchmark's protocol with a user's graph, five pairs led by
#: the direction-dependent friction (its Coulomb half-difference is the
#: force offset wherever the drive moves) took 366 of the loop's 1159 s and
#: were all refused (three crawled along that ridge without converging, two
#: produced power)
_UNUSABLE = ("the refit did not converge", "the refit is not physically admissible",
             "the refitted model does not simulate", "the refit is not finite",
             "the record does not identify")


def pair_pool(ranking: list[Candidate]) -> list[Candidate]:
    """The confirmed candidates of a step that a partner could complete: a
    usable refit (converged, admissible, simulating, finite) with a positive
    likelihood ratio, rejected on the evidence (criterion, likelihood ratio
    or error; not for terms the record does not identify apart from the
    current model, :data:`_UNUSABLE`), not the twin of a better-ranked one (``same_as``: a pair with
    it is the pair with that one); at most :data:`PAIR_TOP`, by decreasing
    likelihood ratio."""
    pool = [c for c in ranking if c.confirmed and c.confirmed.get("comparable", True)
            and (c.confirmed_statistic or 0.0) > 0 and not getattr(c, "same_as", None)
            and not str(c.confirmed.get("reason") or "").startswith(_UNUSABLE)]
    return sorted(pool, key=lambda c: -c.confirmed_statistic)[:PAIR_TOP]


def accepted_pair(ctx: Context, result: LoopResult, current: Fit, scales: Scales, tag: str,
                  step: int) -> Fit | None:
    """No confirmed candidate passed the accept rule alone: refit every pair
    of the best ones (:func:`pair_pool`, at different places) together and
    accept, best joint refit first (:func:`rank_pairs`), the first pair that
    passes the accept rule against the current fit (its dof the two
    effects' new parameters) *and* needs both members
    (:func:`bondgraph.diagnose.accept.pair_needed`: the pair beats each
    member's own refit by a significant likelihood ratio). Two effects that
    act together (the overflows of two tanks into one measured collector)
    can each fail alone, the other one's misfit raising the held-out error.
    The pairs are all refitted before any is judged: a pair of look-alikes
    met first in the pool's order (a collector overflow beside one tank's)
    is not preferred to a pair whose joint refit is better. The pair is one
    step (the first member's, the second in its ``together_with``; both
    effects applied). Returns the accepted fit, or None."""
    pool = pair_pool(result.rankings[-1])
    pairs = [(a, b) for i, a in enumerate(pool) for b in pool[i + 1:]
             if a.target.name != b.target.name]
    if pool:
        pairs += [(pool[0], c) for c in partners_of(ctx, current, pool[0], pool, scales, tag)]
    if not pairs:
        return None
    ctx.log(f"  no single candidate passed: refitting {len(pairs)} pair(s): "
            f"{'; '.join(f'{a.label} + {b.label}' for a, b in pairs)}")
    refits = pair_refits(ctx, current, pairs, scales, tag)
    done = [(pair, conf) for pair, conf in zip(pairs, refits) if conf is not None]
    for (a, b), conf in done:
        ctx.log(f"  confirmed pair {a.label} + {b.label}: LR "
                f"{2 * (current.nll - conf.fit.nll):.1f} (k {conf.dof}, "
                f"{'converged' if conf.comparable else 'NOT converged'})")
    for pair, conf in rank_pairs(done):
        after = accepted_pair_fit(ctx, result, current, pair, conf, step)
        if after is not None:
            return after
    return None


def pair_before_single(ctx: Context, result: LoopResult, current: Fit, single: tuple,
                       confirmed: list[tuple[Candidate, Confirmation]], pairing: tuple,
                       step: int) -> Fit | None:
    """Before the confirmed candidate ``single`` ``(candidate, confirmation)``,
    which passes the accept rule, is accepted: when two or more confirmed
    candidates at different places are each significant (their own refit's
    likelihood ratio over ``current`` at ``settings.accept.significance``;
    at most :data:`PAIR_TOP`, by likelihood ratio, twins ``same_as`` a
    better-ranked one left out), refit their pairs
    together and accept the best one (:func:`rank_pairs`) that beats the
    single (:func:`pair_against_single`: the pair's own tests, then the
    accept rule for the partner added to the single, or, for a pair without
    the single, a lower free-run error and a better Akaike-penalised
    likelihood). Pairs whose conditional score test says a member adds
    nothing given the other are not refitted (:func:`pair_screened_out`).
    Two effects that act together can each be significant while the best
    one alone, a look-alike of both, absorbs their misfit; one step then
    adds both.

    ``pairing`` is ``(scales, tag)``: the operating scales and the refits'
    graph-name tag. Returns the pair's fit, or None (the single stands).
    """
    scales, tag = pairing
    lead, lead_conf = single
    # a candidate refitted with terms held (held_retry) stands for the whole one
    held = {(c.effect, c.target.name) for c, _ in confirmed if c.held}
    pool = [(c, r) for c, r in confirmed if r.comparable and np.isfinite(r.fit.nll)
            and chi2.sf(2.0 * (current.nll - r.fit.nll), max(r.dof, 1))
            < ctx.settings.accept.significance
            and not str((c.confirmed or {}).get("reason") or "").startswith(_UNUSABLE)
            and (c.held or (c.effect, c.target.name) not in held)
            and not getattr(c, "same_as", None)]
    pool = sorted(pool, key=lambda z: z[1].fit.nll)[:PAIR_TOP]
    pairs = [(a, b) for i, (a, _) in enumerate(pool) for b, _ in pool[i + 1:]
             if a.target.name != b.target.name]
    screened = [p for p in pairs if not pair_screened_out(ctx, current, p, single, scales)]
    if len(screened) < len(pairs):
        ctx.log("  pair(s) not refitted, a member adds nothing given the other (score test): "
                + "; ".join(f"{a.label} + {b.label}" for a, b in pairs if (a, b) not in screened))
    pairs = screened
    if not pairs:
        return None
    ctx.log(f"  {len(pool)} candidates significant: refitting {len(pairs)} pair(s) before "
            f"accepting {lead.label}: {'; '.join(f'{a.label} + {b.label}' for a, b in pairs)}")
    refits = pair_refits(ctx, current, pairs, scales, tag)
    for pair, conf in rank_pairs([(p, r) for p, r in zip(pairs, refits) if r is not None]):
        d, reason = pair_against_single(ctx, current, single, pair, conf)
        ctx.log(f"  pair {pair[0].label} + {pair[1].label}: LR "
                f"{2 * (current.nll - conf.fit.nll):.1f} (k {conf.dof}), "
                + (f"not preferred: {reason}" if reason else "beats the single"))
        if not reason:
            return committed_pair(ctx, result, current, pair, conf, d, step)
    return None


def pair_against_single(ctx: Context, current: Fit, single: tuple, pair: tuple,
                        conf: Confirmation):
    """Judge the refit ``conf`` of ``pair`` against the single
    ``(candidate, confirmation)`` that passed alone (:func:`pair_before_single`):
    the pair's own tests against ``current`` (:func:`judged_pair`), then,
    when the single is a member, the accept rule for adding the partner to
    the single's refit (:func:`decided` with the single's fit as the current
    one: the rule the next step would apply, with its exemption of a box
    that does not decide the fit),
    else (another pair, the single a look-alike of both) a free-run error
    not above the single's and a better Akaike-penalised likelihood.

    Returns
    -------
    (Decision, str or None)
        The decision against ``current`` and the reason the pair is not
        preferred (None: it beats the single).
    """
    lead, lead_conf = single
    d, reason = judged_pair(ctx, current, pair, conf)
    if reason:
        return d, reason
    if lead in pair:
        partner = [c for c in pair if c is not lead]
        d2 = decided(ctx, lead_conf.fit, conf.fit, conf.dof - lead_conf.dof, conf.comparable,
                     f"{partner[0].label} added to {lead.label}", partner)
        return d, (None if d2.accepted else f"added to {lead.label} alone: {d2.reason}")
    if not conf.fit.accept_metric <= lead_conf.fit.accept_metric:
        return d, (f"its error {conf.fit.accept_metric:.4g} is above {lead.label}'s alone "
                   f"({lead_conf.fit.accept_metric:.4g})")
    if not conf.fit.nll + conf.dof < lead_conf.fit.nll + lead_conf.dof:
        return d, f"its penalised likelihood is not better than {lead.label}'s alone"
    return d, None


def pair_screened_out(ctx: Context, current: Fit, pair: tuple, single: tuple,
                      scales: Scales) -> bool:
    """True when a score test says the pair cannot be needed, so it is not
    refitted. A pair with the ``single`` ``(candidate, confirmation)``:
    the partner's score test at the single's refit
    (the test the next step would make first, :func:`score_given`) is not
    significant at ``settings.accept.significance``. Any other pair of two
    additive candidates: one adds no significant score given the other at
    ``current`` (:func:`~bondgraph.diagnose.scoring.conditional_score`;
    look-alikes such as a drag on the body or on the wheels); a structural
    member of such a pair is never screened out (its score needs its grid,
    on a fit with the other). A structural partner of the single is scored
    by its grid at the single's refit, profiled where it could be
    significant (:func:`score_given`: the statistic the next step reads).
    A user's DC motor with Coulomb friction: ``r_power @ b_rot`` beside the
    confirmed ``coulomb @ rotor`` was refitted as a pair (22 of the run's
    107 s) to gain 0.9 in LR; its grid at the Coulomb refit scores 0."""
    a, b = pair
    level = ctx.settings.accept.significance
    lead, conf = single
    if lead in pair:
        other = b if a is lead else a
        scored = score_given(ctx, conf.fit, other, scales)
        return scored is not None and not scored.p_value < level
    for given, other in ((a, b), (b, a)):
        z = conditional_score(ctx, current, given, other)
        if z is not None and not chi2.sf(z[0], max(z[1], 1)) < level:
            return True
    return False


def score_given(ctx: Context, fit: Fit, cand: Candidate, scales: Scales) -> Candidate | None:
    """The candidate ``cand`` scored at ``fit`` (another candidate's refit;
    the filter conditioned on its initial states and noise levels, as
    :func:`partners_of` scores): an additive effect by one probe run of
    :func:`~bondgraph.diagnose.scoring.score_additive`, a structural one by
    its grid at ``cand``'s place alone
    (:func:`~bondgraph.diagnose.scoring.structural_candidate` in a family of
    one, profiled when it could be significant). None when structural
    effects are not scored (``--no-structural``), when the target is not
    among those scored or the candidate cannot be built there."""
    eff = get_effect(cand.effect, ctx.settings.effects)
    if not (eff.additive or ctx.settings.search.structural):
        return None
    ctx = fit_context(ctx, fit)     # a refit at a step stable for its law: scored there
    try:
        with conditioned(ctx, fit):
            if eff.additive:
                found = score_additive(ctx, fit, scales, [eff])
            else:       # its grid alone, a family of one (no Bonferroni: kept if in doubt)
                todo = structural_todo(ctx, fit, scales, [eff],
                                       {(cand.target.kind, cand.target.name)})
                found = [structural_candidate(ctx, fit, scales, *item, family=1)
                         for item in todo]
    except BondGraphError:      # not scored: the pair is refitted
        return None
    found = [c for c in found if c is not None and c.effect == cand.effect
             and c.target == cand.target]
    return found[0] if found and np.isfinite(found[0].p_value) else None


def partners_of(ctx: Context, current: Fit, lead: Candidate, pool: list[Candidate],
                scales: Scales, tag: str) -> list[Candidate]:
    """The candidates significant *given* the lead's refit: every effect
    scored against the fit with ``lead`` (the best usable single refit of
    :func:`pair_pool`; the filter conditioned on its initial states and
    noise levels) at the other places, Bonferroni over them; at most
    :data:`PAIR_TOP`, those already in ``pool`` left out. Each is confirmed
    alone against ``current`` (its own refit, which
    :func:`~bondgraph.diagnose.accept.pair_needed` compares the pair with);
    one whose own refit the record does not determine apart from the
    current model (:func:`~bondgraph.diagnose.accept.unidentified_effect`)
    is left out, as the pool leaves it out (:data:`_UNUSABLE`).

    A partner of an interacting pair can be invisible against the declared
    fit: two overflows into one measured collector, the declared orifices
    compensate both, and one tank's overflow alone scores χ² = 0 (capping
    it only removes flow the compensated model needs); once the other
    tank's overflow is in, its own shows.

    The output-error screen (:mod:`bondgraph.diagnose.screen`) runs only
    where the current fit's own free run is poor: a lead whose refit broke
    the free run of a model that simulated is not rescued by a global
    search around it (a user's EMPS graph: a Stribeck refit with the
    validation error 0.044 -> 1.8, whose screen took 100 of the step's 290 s
    and found nothing accepted). Returns the partners."""
    s = ctx.settings
    conf = ctx.cache.get(("confirmation", id(current), current.nll, lead.label))
    if conf is None:
        return []
    screen = free_run_nrmse(current, ctx.problem.arrays[2]) >= SCREEN_LEVEL
    with conditioned(ctx, conf.fit):
        cands = score_additive(ctx, conf.fit, scales, s.effects, screen=screen)
        if s.search.structural:
            physical = [e for e in s.effects if not getattr(e, "last_resort", False)]
            cands += score_structural(ctx, conf.fit, scales, physical, others=len(cands))
    cands = [c for c in cands if c.target.name != lead.target.name]
    cands = attachable(current.graph, cands, s.effects)
    taken = {c.label for c in pool}
    found = sorted([c for c in significant(cands, s.accept.significance) if c.label not in taken],
                   key=lambda c: c.rank_key)[:PAIR_TOP]
    ctx.log(f"  given {lead.label}: " + ("; ".join(
        f"{c.label} (χ²={c.statistic:.1f}, k={c.dof})" for c in found) or "nothing significant "
        "at the other places"))
    out = []
    for c in found:
        key = ("confirmation", id(current), current.nll, c.label)
        if key not in ctx.cache:
            ctx.cache[key] = confirm(ctx, current, c, scales, f"{tag}_alone")
        if ctx.cache[key] is None:
            continue
        if why := unidentified_effect(current, ctx.cache[key].fit):
            # as in the pool (_UNUSABLE): no partner mends what its own refit leaves undetermined
            ctx.log(f"  {c.label} is not paired: {why}")
            continue
        c.confirmed = {"values": dict(c.values)}
        out.append(c)
    return out


def attachable(graph, cands: list[Candidate], effects) -> list[Candidate]:
    """The candidates of ``cands`` whose effect can attach at their target in
    ``graph``: scored given a lead, a candidate may sit on what the lead's
    effect added (``cold_start @ dahl.rotor``, the source of a Dahl
    friction), which the graph without the lead does not have, so it cannot
    be confirmed alone."""
    places: dict = {}
    out = []
    for c in cands:
        if c.effect not in places:
            places[c.effect] = {(t.kind, t.name)
                                for t in get_effect(c.effect, effects).targets(graph)}
        if (c.target.kind, c.target.name) in places[c.effect]:
            out.append(c)
    return out


def rank_pairs(refits: list[tuple[tuple, Confirmation]]) -> list[tuple[tuple, Confirmation]]:
    """The refitted pairs ``(pair, confirmation)`` best first: converged
    (``comparable``) before not converged, each group by increasing
    NLL + k (k the pair's new parameters: by decreasing LR − 2k over the
    current fit, Akaike's penalty, as :func:`rank_confirmed` orders
    singles)."""
    return sorted(refits, key=lambda z: (not z[1].comparable,
                                         z[1].fit.nll + z[1].dof))


def pair_refits(ctx: Context, current: Fit, pairs: list[tuple], scales: Scales,
                tag: str) -> list[Confirmation | None]:
    """The joint refits of ``pairs`` (:func:`~bondgraph.diagnose.confirm.confirm_pair`,
    on the executor), each one that ended with a member on its box, not
    converged, above a member's own refit, or that has a structural member,
    tried again from a member's refit (:func:`sequential_pair`; the pairs'
    second tries on threads of this process, :func:`local_map`: they read
    the members' refits from ``ctx.cache``, and each depends only on its own
    pair, so the results and the log's order are those of one after the
    other)."""
    refits = run_tasks(ctx, _confirm_pair_task, (current, scales, f"{tag}_pair"), pairs)
    return list(local_map(ctx, lambda c, z: sequential_pair(c, current, z[0], z[1], tag, scales),
                          list(zip(pairs, refits))))


#: a pair's joint refit that ends more than this many nats above a member's
#: own refit (which it nests) stopped in a poorer basin (:func:`sequential_pair`)
NESTED_SLACK = 0.5


def member_refits(ctx: Context, current: Fit, pair: tuple) -> list:
    """The members' own confirmations of ``pair`` (None where there is none)."""
    return [ctx.cache.get(("confirmation", id(current), current.nll, c.label)) for c in pair]


def below_member(conf: Confirmation, members: list) -> bool:
    """Whether the pair's refit ``conf`` ends more than :data:`NESTED_SLACK`
    nats above the NLL of a member's own refit (of ``members``), a point
    the pair contains."""
    own = [m.fit.nll for m in members if m is not None and np.isfinite(m.fit.nll)]
    return bool(own) and conf.fit.nll > min(own) + NESTED_SLACK


def sequential_pair(ctx: Context, current: Fit, pair: tuple, conf: Confirmation | None,
                    tag: str, scales: Scales | None = None) -> Confirmation | None:
    """``conf``, the joint refit of ``pair`` from the current estimates and
    each member's own confirmed values, or a better refit of the same pair
    reached in two steps: from one member's own refit, the other
    (structural) member scored on its grid at that refit's operating scales
    (the filter conditioned on it, as :func:`partners_of` scores), then
    confirmed there (:func:`~bondgraph.diagnose.confirm.confirm`: every
    parameter refitted).

    Tried when ``conf`` is missing, not converged, or has a member's
    parameter on its box. Why: a structural member's grid and box come from
    the current fit's scales, which the declared fit has compensated (two
    tank overflows into one measured collector: the declared orifices
    narrowed, the tanks' simulated peaks five times the true overflow
    level, so that level lies below the member's box); at the other
    member's refit the scales are the ones the sequential loop would use
    next. The better refit (converged first, then by NLL) is returned.

    Tried whenever a member is structural: a converged joint refit, no
    member on its box, can still stop in a poorer basin than the two steps
    reach (the two overflowing tanks of ``tests/test_loop_pairs.py`` on an
    AMD EPYC machine: the joint refit converged to levels that left the
    held-out error at 0.165, the two steps reach 0.063, the noise floor
    0.015; on another machine the same joint refit pinned a level on its
    box and the two steps ran). Also tried when the joint refit ends above
    a member's own refit
    (:func:`below_member`), which the pair nests: then, for an additive
    other member, from that member's refit with the other's coefficients at
    0 (:func:`~bondgraph.diagnose.confirm.confirm_pair` with ``base``). The
    joint start mixes the current fit's estimates with both members'
    values, which the members' own refits found at different declared
    parameters: on a user's four-mass chain (noise levels estimated) a
    sensor gain refitted to LR 3383 alone, and with a Stribeck term beside
    it to LR −4101."""
    members = member_refits(ctx, current, pair)
    structural = any(not get_effect(c.effect, ctx.settings.effects).additive for c in pair)
    if conf is not None and conf.comparable and not pair_member_boxed(conf.fit, conf.new_params) \
            and not below_member(conf, members) and not structural:
        return conf
    best, how = conf, ""
    for (first, second), one in zip((pair, pair[::-1]), members):
        eff = get_effect(second.effect, ctx.settings.effects)
        if one is None or not np.isfinite(one.fit.nll):
            continue
        if eff.additive:
            if scales is None or conf is None or not below_member(conf, [one]):
                continue
            alt = confirm_pair(ctx, current, pair, scales, f"{tag}_pair_nested", base=one.fit,
                               off=second)
            way = f"from {first.label}'s own refit (NLL {one.fit.nll:.2f})"
        else:
            alt = _two_steps(ctx, (first, one), second, eff, tag)
            way = "in two steps"
        if alt is not None and (best is None or (not alt.comparable, alt.fit.nll)
                                < (not best.comparable, best.fit.nll)):
            best, how = alt, way
    if best is not conf and best is not None:
        ctx.log(f"  pair {pair[0].label} + {pair[1].label} refitted {how}: NLL "
                f"{best.fit.nll:.2f} (joint refit: "
                f"{'failed' if conf is None else f'{conf.fit.nll:.2f}'})")
    return best


def _two_steps(ctx: Context, first: tuple, second: Candidate, eff, tag: str):
    """The pair ``first`` ``(candidate, its own confirmation)`` + ``second``
    refitted from ``first``'s refit (:func:`sequential_pair`), as a pair's
    :class:`Confirmation` (values keyed ``"<label>.<local name>"``, the new
    parameters of both). None when ``second`` cannot be scored or
    confirmed there."""
    cand, one = first
    with conditioned(ctx, one.fit):
        sc = operating_scales(ctx, one.fit)
        given = structural_candidate(ctx, one.fit, sc, eff, second.target)
    if given is None or not np.isfinite(given.statistic):
        return None
    conf = confirm(ctx, one.fit, given, sc, f"{tag}_pair_seq")
    if conf is None:
        return None
    f = conf.fit
    values = {}
    for c in (cand, second):
        e = get_effect(c.effect, ctx.settings.effects)
        values.update({f"{c.label}.{p.name}": float(f.theta[f.model.param_index(
            e.pname(c.target, p.name))]) for p in e.params if e.pname(c.target, p.name)
            in f.model.params})
    return Confirmation(f, values, list(one.new_params) + list(conf.new_params),
                        conf.comparable, {**one.shape, **conf.shape})


def _confirm_pair_task(ctx: Context, shared, pair: tuple) -> Confirmation | None:
    """:func:`bondgraph.diagnose.confirm.confirm_pair` as a task of
    :func:`bondgraph.diagnose.parallel.run_tasks`."""
    current, scales, name = shared
    return confirm_pair(ctx, current, pair, scales, name)


def accepted_pair_fit(ctx: Context, result: LoopResult, current: Fit, pair: tuple,
                      conf: Confirmation, step: int) -> Fit | None:
    """Decide on the refit ``conf`` of ``pair`` (:func:`accepted_pair`):
    record both members as steps and return the fit if accepted, else
    record the rejection and return None."""
    a, b = pair
    d, reason = judged_pair(ctx, current, pair, conf)
    if reason:
        result.rejected.append(Rejection(step, a, f"as a pair with {b.label}: {reason}",
                                         d.criterion_after, d.whiteness_after))
        ctx.log(f"reject pair {a.label} + {b.label} ({reason}): error {d.error_before:.4g} -> "
                f"{d.error_after:.4g}, LR {d.lr:.1f} (p {d.lr_p_value:.2g})")
        return None
    return committed_pair(ctx, result, current, pair, conf, d, step)


def judged_pair(ctx: Context, current: Fit, pair: tuple, conf: Confirmation):
    """The accept rule on the pair's refit ``conf`` against ``current``
    (:func:`~bondgraph.diagnose.accept.decide`, dof the two members' new
    parameters), then the pair's own tests: no member switched off by its
    box (:func:`~bondgraph.diagnose.accept.pair_member_boxed`) and each
    member needed (:func:`~bondgraph.diagnose.accept.pair_needed`, against
    the members' own confirmation refits in ``ctx.cache``).

    Returns
    -------
    (Decision, str or None)
        The decision and the first failed test's reason (None: passed).
    """
    s = ctx.settings
    after = conf.fit
    d = decided(ctx, current, after, conf.dof, conf.comparable,
                " + ".join(c.label for c in pair), pair)
    singles = [ctx.cache.get(("confirmation", id(current), current.nll, c.label)) for c in pair]
    reason = d.reason or pair_member_boxed(after, conf.new_params) or pair_needed(
        after, [None if r is None else r.fit for r in singles],
        [0 if r is None else r.dof for r in singles], s.accept.significance)
    return d, reason


def finer_step_reason(finer) -> str:
    """The rejection's reason where :func:`fit_after_discretisation_check`
    gave no fit: its refit at the step the check asks for failed the accept
    rule (``finer``, that decision), or could not be made (None: the filter
    fails there; the warning names the steps tried)."""
    if finer is not None:
        return f"refitted at the finer step it no longer passes the accept rule ({finer.reason})"
    return ("it cannot be refitted at the step its discretisation check asks for (the filter "
            "fails there; the warning names the steps tried)")


def committed_pair(ctx: Context, result: LoopResult, current: Fit, pair: tuple,
                   conf: Confirmation, d, step: int) -> Fit | None:
    """Record the accepted ``pair`` (refit ``conf``, decision ``d``) as one
    step (the first member's, the second in ``together_with``), both
    effects applied, with the Cramér-Rao std; return the fit (None, a
    rejection recorded, when its refit at the substeps the discretisation
    check asks for no longer passes, :func:`fit_after_discretisation_check`)."""
    s = ctx.settings
    a, b = pair
    label = f"{a.label} + {b.label}"
    after, finer = fit_after_discretisation_check(ctx, result, conf.fit, label,
                                                  (current, conf.dof, conf.comparable,
                                                   pair))
    if after is None:
        result.rejected.append(Rejection(step, a, f"as a pair with {b.label}: "
                                         f"{finer_step_reason(finer)}",
                                         d.criterion_after, d.whiteness_after))
        return None
    d = finer or d
    names = list(current.params) + conf.new_params
    after, removed, dr = pruned(ctx, result, current, after, pair, label)
    if removed:
        d, names = dr, list(after.params)
    std = parameter_std(ctx, after)
    after.std = std
    st = accepted_step(a, d, current, after, names, std, result.metric)
    st.together_with = [b.label]
    st.removed = [f"{r.effect} @ {r.target.name}" for r in removed]
    result.steps.append(st)
    result.applied = [r for r in result.applied if r not in removed]
    for c in pair:
        result.applied.append(applied_effect(get_effect(c.effect, s.effects), c, after))
    scaled = scaled_lr(ctx, st, after, conf.dof if not removed else None)
    boxed_after_accept(ctx, result, after, names, label)
    gone = "".join(f" (removing {r})" for r in st.removed)
    ctx.log(f"ACCEPT pair {label}{gone}: {result.metric} {d.error_before:.4g} -> "
            f"{d.error_after:.4g}, NLL {current.nll:.2f} -> {after.nll:.2f}, LR {d.lr:.1f} "
            f"(p {d.lr_p_value:.2g}{scaled}), error decrease z {d.error_z:.2f} "
            f"(p {d.error_p_value:.2g}); each member needed")
    return after


def scaled_lr(ctx: Context, st: Step, after: Fit, dof: int | None) -> str:
    """The accepted step ``st``'s likelihood ratio scaled for serially
    correlated innovations (:func:`~bondgraph.diagnose.fit.robust_lr`, at
    its refit ``after``; ``dof`` that of its test, None: its effect
    parameters), recorded on ``st`` (``lr_scale``, ``lr_robust_p_value``)
    and as the log's clause ("" where it cannot be computed). On the EMPS
    record with a user's graph (whiteness 370 000 where white innovations
    give about 20) the Coulomb pair's LR 32 156 is scaled by 40.1 (to 801),
    the default case's drag (a right model then) by 1.03; a scale at or
    below 1 leaves it (:func:`~bondgraph.diagnose.fit.robust_lr`)."""
    rob = robust_lr(ctx, after, st.effect_params, st.lr if st.lr is not None else np.nan,
                    len(st.effect_params) if dof is None else dof)
    if not rob:
        return ""
    st.lr_scale, st.lr_robust_p_value = rob["scale"], rob["p_value"]
    if rob["scale"] <= 1.0:
        return f"; not inflated by correlated innovations: scale {rob['scale']:.3g}"
    return (f"; scaled by {rob['scale']:.3g} for correlated innovations: {rob['lr']:.1f}, "
            f"p {rob['p_value']:.2g}")


#: the structural candidates skipped for an additive lead are scored when the
#: lead's refit reaches less than this fraction of its score statistic
LEAD_SHORTFALL = 0.8


def significant_after_lead_check(ctx: Context, result: LoopResult, current: Fit,
                                 signif: list[Candidate], scales: Scales,
                                 tag: str) -> list[Candidate]:
    """The structural candidates were skipped because an additive lead explains
    most of the innovations: confirm the lead, and if its refit's likelihood
    ratio falls short of its score statistic (below ``LEAD_SHORTFALL`` of
    it: the effect's shape fits the residual worse than its first-order
    signature promised) score the skipped structural candidates too. Returns
    the significant candidates of the (possibly grown) ranking. (A full
    vehicle whose engine torque saturates: asymmetric friction at the engine
    led with χ² 32 523 but refitted to LR 19 885; the saturation, scored,
    reaches LR 38 063.)"""
    lead = sorted(signif, key=lambda c: c.rank_key)[0]
    if not confirm_best(ctx, current, [lead], scales, tag) or lead.statistic <= 0:
        return signif
    ratio = lead.confirmed_statistic / lead.statistic
    if ratio >= LEAD_SHORTFALL:
        return signif
    ctx.log(f"  {lead.label}: its refit reaches LR {lead.confirmed_statistic:.1f}, "
            f"{100 * ratio:.0f} % of its score test: scoring the structural candidates "
            f"skipped above")
    ranking = _score_skipped(ctx, result, current, scales)
    return significant(ranking, ctx.settings.accept.significance)


def _score_skipped(ctx: Context, result: LoopResult, current: Fit,
                   scales: Scales) -> list[Candidate]:
    """Score the structural candidates the step skipped (every place), rank
    them with the others in ``result.rankings[-1]`` and return that ranking."""
    physical = [e for e in ctx.settings.effects if not getattr(e, "last_resort", False)]
    seen = {c.label for c in result.rankings[-1]}
    additive = sum(1 for c in result.rankings[-1] if c.kind == "score")
    extra = [c for c in score_structural(ctx, current, scales, physical, others=additive)
             if c.label not in seen]
    ranking = sorted(result.rankings[-1] + extra, key=lambda c: c.rank_key)
    mark_limits(ranking)
    result.rankings[-1] = ranking
    if ctx.settings.true_effect is not None and result.truth_ranks:
        kind, target = ctx.settings.true_effect
        result.truth_ranks[-1] = rank_of(ranking, kind, target)
        ctx.log(f"  the true effect {kind} @ {target} now ranks {result.truth_ranks[-1]}")
    ctx.log(f"  {len(extra)} structural candidates scored; best now: " + "; ".join(
        f"{c.label} (χ²={c.statistic:.1f}, k={c.dof})" for c in ranking[:3]))
    return ranking


def structural_skipped(s: LoopSettings, cands: list[Candidate]) -> bool:
    """True when :func:`gather_evidence` left the structural candidates out
    because an additive one explains more than ``structural_threshold`` of
    the innovation energy."""
    best = max([c.explained or 0.0 for c in cands] + [0.0])
    search = s.search
    return (bool(search.structural) and search.structural != "always"
            and search.structural_threshold is not None and best >= search.structural_threshold)


def accepted_among_skipped_structurals(ctx: Context, result: LoopResult, current: Fit,
                                       scales: Scales, tag: str, step: int) -> Fit | None:
    """No confirmed additive candidate passed the accept rule although one
    explained most of the innovations: the structural candidates skipped
    before are scored now (every place), ranked with the others (the
    significance over all of them) and the significant ones confirmed. An
    additive effect can stand in for a structural one in the innovations and
    still fail on the free run (a user's two tanks whose pump saturates: a
    pump-flow offset explained 70 % of the innovations and raised the
    held-out error). Returns the accepted fit, or None."""
    ctx.log("  none of the confirmed candidates passed the accept rule: scoring the structural "
            "candidates skipped above")
    before = {id(c) for c in result.rankings[-1]}
    ranking = _score_skipped(ctx, result, current, scales)
    signif = [c for c in significant(ranking, ctx.settings.accept.significance)
              if id(c) not in before]
    if not signif:
        return None
    return confirm_in_rounds(ctx, result, current, signif, scales, tag, step)


def confirm_in_rounds(ctx: Context, result: LoopResult, current: Fit, signif: list[Candidate],
                      scales: Scales, name: str, step: int) -> Fit | None:
    """Confirm the significant candidates ``confirm_top`` at a time, best
    first, and accept the first that passes the accept rule
    (:func:`accept_best`); when none of a round does, confirm the next
    ``confirm_top`` (at most ``confirm_rounds`` rounds). A candidate whose
    score test ranks low can then still be accepted when the better-scoring
    ones raise the error (on CED the input delay, below three sensor and
    friction candidates that all raise the free-run error). Unconfirmed
    candidates that score within reach of a round's best refit
    (:func:`within_reach`) are confirmed in that round; they count against
    the step's ``confirm_top`` x ``confirm_rounds`` refits, so a step
    confirms no more candidates than before (each confirmation is one more
    chance of a look-alike passing). When a round's refits reorder its
    scores (:func:`reordered`), the next round is confirmed before any
    decision and the decision takes the best refit of both
    (:func:`merged_confirmations`). Returns the accepted fit, or None."""
    s = ctx.settings
    todo = sorted(signif, key=lambda c: c.rank_key)
    per = s.search.confirm_top
    budget = per * s.search.confirm_rounds      # refits of the step, reach included
    held: list = []         # confirmed in earlier rounds whose refits reordered the scores
    for r in range(s.search.confirm_rounds):
        n = min(per, budget)
        batch, todo = todo[:n], todo[n:]
        if not batch:
            break
        budget -= len(batch)
        if r and not held:
            ctx.log(f"  none of the confirmed candidates passed the accept rule: confirming the "
                    f"next {len(batch)} (round {r + 1} of at most {s.search.confirm_rounds})")
        confirmed = confirm_best(ctx, current, batch, scales, name)
        near = within_reach(confirmed, todo)[:budget]
        budget -= len(near)
        if near:
            rho = underprediction(confirmed)[0]
            best = max(c.confirmed_statistic - 2 * c.dof for c, _ in confirmed
                       if c.confirmed_statistic is not None)
            scaled = (f"; this round's refits exceed their scores, typically {rho:.3g}-fold: "
                      f"the scores are scaled so, against the best refit the accept rule can "
                      f"take" if any(reach_of(c) - 2 * c.dof < CONFIRM_REACH * best
                                     for c in near) else "")
            ctx.log(f"  {', '.join(_reach_label(c) for c in near)}: scored within "
                    f"{100 * (1 - CONFIRM_REACH):.0f} % of the best confirmed refit's likelihood "
                    f"ratio (a score is a lower bound of its refit's{scaled}): confirmed too "
                    f"before deciding")
            todo = [c for c in todo if c not in near]
            confirmed = confirm_best(ctx, current, batch + near, scales, name,
                                     top=len(batch) + len(near),
                                     quiet={c.label for c in batch})
        lead = reordered(confirmed, batch + near)
        if lead is not None and todo and budget > 0 and r + 1 < s.search.confirm_rounds:
            ctx.log(f"  the refits reorder the scores ({lead}): on this record a score is a "
                    f"loose guide to its refit; confirming the next {min(per, budget)} before "
                    f"deciding")
            held += confirmed
            continue
        if held:
            confirmed = merged_confirmations(ctx, held + confirmed)
            held = []
        confirmed = held_first(ctx, current, confirmed, (scales, name))
        after = accept_best(ctx, result, current, confirmed,
                            step, pairing=(scales, name) if s.accept.pairs else None,
                            refit=(scales, name))
        if after is not None:
            return after
    return None


def _reach_label(cand: Candidate) -> str:
    """``cand``'s label, with its reach when that, not its statistic,
    brought it within reach (:func:`reach_of`)."""
    if reach_of(cand) > cand.statistic:
        return (f"{cand.label} (profiled to {cand.statistic:.4g}, its next scoring steps "
                f"predict {reach_of(cand):.4g})")
    return cand.label


#: the refits reorder the scores when the best refit's likelihood ratio (less
#: 2k) exceeds that of the best-scored candidate's refit by more than this
#: fraction of the latter
REORDER = 0.1


def reordered(confirmed: list, batch: list[Candidate]) -> str | None:
    """What says that the refits of a round (``confirmed``, (candidate,
    refit) pairs best first, :func:`confirm_best`) reorder the scores of the
    round's candidates ``batch``: the best refit is not the best-scored
    candidate's and its likelihood ratio less 2k exceeds that one's by more
    than :data:`REORDER` (a label line), else None. Scores are local: where
    the declared fit leaves a large model error and no process noise, a
    candidate's refit can move the declared parameters far (a damping that
    made up for a missing friction returns), and the score ranks it low (a
    user's four-mass chain: the true Coulomb friction scored sixth, 0.94e6,
    its refit reached 5.38e6 while the round's best refit, a Stribeck term
    scored third, reached 2.80e6 and a sensor gain scored first 2.46e6)."""
    done = [(c, c.confirmed_statistic - 2 * c.dof) for c, _ in confirmed
            if c.confirmed_statistic is not None]
    if len(done) < 2:
        return None
    top = min((c for c, _ in done), key=lambda c: c.rank_key)
    best, lr_best = done[0]
    lr_top = dict((id(c), v) for c, v in done)[id(top)]
    if best is top or lr_best <= (1 + REORDER) * max(lr_top, 0.0):
        return None
    order = sorted(batch, key=lambda c: c.rank_key)
    return (f"{best.label}, scored {1 + order.index(best)}, refits best: LR "
            f"{best.confirmed_statistic:.4g} against {top.confirmed_statistic:.4g} for "
            f"{top.label}, scored {1 + order.index(top)}")


def merged_confirmations(ctx: Context, confirmed: list) -> list:
    """(candidate, refit) pairs (of one round, or of several) best first
    (:func:`~bondgraph.diagnose.accept.rank_confirmed`), the candidates the
    record cannot tell from the lead marked and logged
    (:func:`~bondgraph.diagnose.accept.mark_ties`)."""
    ranked = rank_confirmed([(c.confirmed_statistic - 2 * c.dof, c, r) for c, r in confirmed])
    rescaled_twins(ctx, [(c, r) for _, c, r in ranked])
    tied = mark_ties([(c, r.fit, r.dof) for _, c, r in ranked],
                     ctx.settings.accept.tie_level)
    if tied:
        ctx.log(f"  the record cannot tell {ranked[0][1].label} from {', '.join(tied)} "
                f"(Vuong's test, p >= {ctx.settings.accept.tie_level:g}): reported as tied")
    return [(c, r) for _, c, r in ranked]


#: two converged refits of one effect at two places whose NLLs differ by at
#: most this [nats] (plus 1e-9 of the NLL) are one model (:func:`rescaled_twins`)
TWIN_NLL = 1e-4


def rescaled_twins(ctx: Context, ranked: list) -> None:
    """Mark, among (candidate, refit) pairs best first, the later refit of
    the same effect with as many new parameters at another place whose
    converged NLL equals an earlier one's (within :data:`TWIN_NLL`; a
    likelihood ratio above 1: not an effect both refits left off) as its
    twin (``same_as``, ``equivalent``; logged): the same model with its
    parameters rescaled, as an effect is on either side of a rigid
    transmission (a gear without compliance ties the two shafts' speeds by
    its ratio: Coulomb friction on the motor shaft is Coulomb friction on
    the load shaft, its level times the ratio). Symbolic comparison
    (:func:`same_models`) does not see a rescaling. A pair of twins is one
    effect twice (its parameters not identified apart), so the pairs leave
    twins out (:func:`pair_pool`): on the discovery bench's geared drive
    (``gear_brush_drop``) the two shafts' Coulomb frictions refitted to LR
    440.6 each and then as a pair; on a user's EMPS graph with the rotor
    behind the ball screw, the load's and the rotor's asymmetric friction."""
    for i, (c, r) in enumerate(ranked):
        if (getattr(c, "same_as", None) or not r.comparable or not np.isfinite(r.fit.nll)
                or not (c.confirmed_statistic or 0.0) > 1.0):    # an effect the refit left off
            continue
        for a, q in ranked[:i]:
            if (a.effect == c.effect and a.target.name != c.target.name and a.dof == c.dof
                    and q.comparable and not getattr(a, "same_as", None)
                    and abs(q.fit.nll - r.fit.nll) <= TWIN_NLL + 1e-9 * abs(q.fit.nll)):
                c.same_as = a.label
                c.equivalent += [a.label] if a.label not in c.equivalent else []
                a.equivalent += [c.label] if c.label not in a.equivalent else []
                ctx.log(f"  {c.label}: the same model as {a.label} up to its parameters' "
                        f"scale (equal refitted likelihood, NLL {r.fit.nll:.6f}: the places "
                        f"share their variable or are rigidly tied); no pair with it is "
                        f"refitted")
                break


#: an unconfirmed candidate whose statistic (less 2k) reaches this fraction of
#: the best confirmed refit's LR (less 2k) is confirmed before the decision
CONFIRM_REACH = 0.9


def within_reach(confirmed: list, rest: list[Candidate]) -> list[Candidate]:
    """The candidates of ``rest`` (unconfirmed, significant, best first)
    whose statistic less 2k reaches :data:`CONFIRM_REACH` of the best
    confirmed likelihood ratio less 2k among ``confirmed`` ((candidate,
    refit) pairs), at most as many as were confirmed. A score or an
    unprofiled grid is a lower bound of its candidate's refit: on a user's
    two-mass drive the load's true Coulomb friction scored 1.851e6, fourth
    behind three Dahl frictions, yet its refit reaches 1.958e6, above their
    best 1.936e6; confirmed three at a time, a Dahl friction was accepted
    first (and removed again by the backward step, :func:`pruned`). A
    profiled structural candidate counts with its reach (:func:`reach_of`):
    on a user's two tanks the pump saturation, tenth by its profile (3107),
    reaches 10116 against cold_start's refit 8179, and its refit 13317. On
    the bundled default the aerodynamic drag's look-alikes at the wheels'
    R elements come within reach by their scores; on Silverbox, CED and
    EMPS nothing does. Where every refit of the round exceeds its score by
    a factor ρ > 1 (:func:`underprediction`), a candidate whose score times
    ρ less 2k reaches :data:`CONFIRM_REACH` of the best usable refit is
    within reach too (a user's cart: the Coulomb term, ρ 3.25)."""
    stats = [c.confirmed_statistic - 2 * c.dof for c, _ in confirmed
             if c.confirmed_statistic is not None]
    if not stats or not rest or max(stats) <= 0:
        return []
    best = max(stats)
    rho, usable = underprediction(confirmed)
    return [c for c in rest if reach_of(c) - 2 * c.dof >= CONFIRM_REACH * best
            or (rho > 1.0 and rho * reach_of(c) - 2 * c.dof >= CONFIRM_REACH * usable)
            ][:len(confirmed)]


def underprediction(confirmed: list) -> tuple[float, float]:
    """``(ρ, usable)``: the typical factor by which the refits of a round
    (``confirmed``, (candidate, refit) pairs) exceed their candidates'
    scores, the median of LR / statistic over those with both positive (1
    when any refit falls short of its score), and the best likelihood ratio
    less 2k among the usable refits (converged, every new parameter with a
    Cramér-Rao std and off the bounds of its box: those the accept rule can
    take); ρ is 1 (nothing scaled) when no refit is usable.

    A score is the likelihood ratio's local approximation at the current
    model; far from it a round's scores can all fall short of their refits
    by a similar factor. Scaled by that factor, an unconfirmed candidate's
    score predicts its refit better than unscaled (:func:`within_reach`). A
    user's cart with Coulomb friction missing (60 s): a power-law, a Dahl
    and a square-root damper scored 6407, 6251 and 6204 and refitted 3.8,
    3.2 and 3.0 times higher; the Coulomb term, scored 5942, was not
    confirmed, the damper (the round's only usable refit, 18437) was
    accepted, and the Coulomb term came a step later (its refit over the
    declared model 33760, 5.7 times its score). On 30 s of the record
    (``tests/test_prune_insignificant.py``) the ratios are 3.6, 3.2 and 2.9,
    the power law ends on its box and the Dahl friction's refit leaves its
    parameters without a std: the Coulomb term comes in by 2064 × 3.2
    against 0.9 × 6440, the damper's refit."""
    ratios, usable = [], []
    for c, conf in confirmed:
        lr = c.confirmed_statistic
        if lr is None or not np.isfinite(lr):
            continue
        if c.statistic > 0 and lr > 0:
            ratios.append(lr / c.statistic)
        if conf is None:            # no refit to judge by (stand-ins)
            continue
        boxed = set(getattr(conf.fit, "at_bound", ()) or ()) & set(conf.new_params)
        std = getattr(conf.fit, "std", None) or {}
        identified = all(std.get(n) is not None and np.isfinite(std[n]) and std[n] > 0
                         for n in conf.new_params)
        if conf.comparable and not boxed and identified:
            usable.append(lr - 2 * c.dof)
    if not usable or not ratios or min(ratios) < 1.0:
        return 1.0, max(usable, default=0.0)
    return float(np.median(ratios)), max(usable)


def reach_of(cand: Candidate) -> float:
    """The likelihood ratio ``cand``'s refit could reach: its statistic, or
    for a structural candidate whose profile stopped short of its optimum
    the statistic plus the gain the scoring steps it did not take predict
    (:attr:`~bondgraph.diagnose.result.Candidate.reach`)."""
    reach = getattr(cand, "reach", None)      # stand-ins without one: the statistic
    return max(cand.statistic, reach) if reach is not None else cand.statistic


def gather_evidence(ctx: Context, current: Fit,
                    scales: Scales) -> tuple[list[Candidate], list[Candidate]]:
    """Score the additive candidates; the structural ones too unless an
    additive effect explains more than ``structural_threshold`` of the
    innovation energy; the last-resort ones (unmeasured disturbances) only
    when no physical effect is significant.

    Returns
    -------
    (ranking, significant)
        All candidates by decreasing score, and the significant ones.
    """
    s = ctx.settings
    physical_fx = [e for e in s.effects if not getattr(e, "last_resort", False)]
    resort_fx = [e for e in s.effects if getattr(e, "last_resort", False)]
    early = None            # never skipped: built now, compiled in the background meanwhile
    if s.search.structural and s.search.structural_threshold is None and not distributed(ctx):
        early = structural_todo(ctx, current, scales, physical_fx)
    cands = score_additive(ctx, current, scales, s.effects)
    best_expl = max([c.explained or 0.0 for c in cands] + [0.0])
    if s.search.structural and not structural_skipped(s, cands):
        cands += score_structural(ctx, current, scales, physical_fx, todo=early,
                                  others=len(cands), ahead=cands)
    elif s.search.structural:
        ctx.log(f"  structural candidates not scored: an additive effect explains "
                f"{100 * best_expl:.0f} % of the innovation energy")
        best = sorted(cands, key=lambda c: c.rank_key)[:3]
        if s.search.structural_near_best and best:
            places = set().union(*(places_of(current.graph, c) for c in best))
            ctx.log(f"  ... except at the places of {', '.join(c.label for c in best)}")
            cands += score_structural(ctx, current, scales, physical_fx, places,
                                      others=len(cands), ahead=cands)
    signif = significant(cands, s.accept.significance)
    if not signif and s.search.structural and resort_fx:
        ctx.log("  no physical effect is significant: scoring the last-resort "
                "effects (unmeasured disturbances)")
        cands += score_structural(ctx, current, scales, resort_fx, others=len(cands))
        signif = significant(cands, s.accept.significance)
    mark_limits(cands)
    return sorted(cands, key=lambda c: c.rank_key), signif


def confirm_best(ctx: Context, current: Fit, signif: list[Candidate], scales: Scales,
                 name: str, top: int | None = None, quiet: set | None = None
                 ) -> list[tuple[Candidate, Confirmation]]:
    """Confirm the ``top`` (default ``confirm_top``) best significant
    candidates by refits (:func:`bondgraph.diagnose.confirm.confirm`, graphs
    named ``name``); set their likelihood-ratio statistic; return them by
    decreasing LR − 2k. A candidate already confirmed against the same
    current fit (the lead of :func:`significant_after_lead_check`, or an
    earlier call) is not refitted again; the labels in ``quiet`` are not
    logged again."""
    top = ctx.settings.search.confirm_top if top is None else top
    todo = sorted(signif, key=lambda c: c.rank_key)[:top]
    confirmed = []
    keys = [("confirmation", id(current), current.nll, c.label) for c in todo]  # lead check's
    fresh = [(k, c) for k, c in zip(keys, todo) if k not in ctx.cache]
    same = same_models(ctx, current, scales, name, [c for _, c in fresh])
    first = [(k, c) for k, c in fresh if c.label not in same]
    for (k, _), r in zip(first, run_tasks(ctx, _confirm_task, (current, scales, name),
                                          [c for _, c in first])):
        ctx.cache[k] = r
    twins = [(k, c, same[c.label]) for k, c in fresh if c.label in same]
    for k, c, rep in twins:
        c.same_as = rep.label
        c.equivalent += [rep.label] if rep.label not in c.equivalent else []
        rep.equivalent += [c.label] if c.label not in rep.equivalent else []
        ctx.log(f"  {c.label}: the same model as {rep.label} (equal state equations and "
                f"outputs): {rep.label}'s refit, evaluated on {c.label}'s graph")
    items = [(c, rep, ctx.cache[("confirmation", id(current), current.nll, rep.label)])
             for _, c, rep in twins]
    for (k, _, _), r in zip(twins, run_tasks(ctx, _confirm_same_task, (current, scales, name),
                                             items)):
        ctx.cache[k] = r
    for _, c in fresh:              # the built models are kept in their confirmations
        ctx.cache.pop(("augmented", id(current), current.nll, c.label, name), None)
    for c, key in zip(todo, keys):
        r = ctx.cache[key]
        if r is None:
            continue
        c.confirmed_statistic = max(0.0, 2 * (current.nll - r.fit.nll))
        c.confirmed = confirmed_record(current, r.fit, r.dof, r.values,
                                         ctx.settings.accept)
        c.confirmed["comparable"] = r.comparable
        confirmed.append((c, r))
        if c.label in (quiet or ()):
            continue
        how = _how(r.fit)
        ctx.log(f"  confirmed {c.label}: LR {c.confirmed_statistic:.1f} "
                f"(score test {c.statistic:.1f}), values {r.values} ({how}, "
                f"{r.fit.iterations} iterations)")
    return merged_confirmations(ctx, confirmed)


def _how(fit: Fit) -> str:
    """How a confirmation refit ended, as its log line says it."""
    return ("converged" if fit.converged else
            "NOT converged: not comparable" if fit.converged is False else "L-BFGS-B")


def same_models(ctx: Context, current: Fit, scales: Scales, name: str,
                cands: list[Candidate]) -> dict:
    """The candidates of ``cands`` (best first) whose augmented model is
    that of a better-ranked one, or of one confirmed before against
    ``current`` (:func:`~bondgraph.diagnose.confirm.same_model_key`), label
    -> that one. Each model is refitted once: on the bundled vehicle a
    quadratic law at the brake's R and at the rolling resistance's R were
    two refits of one model (the cubic law too). The new parameters' boxes
    do not count here (a quadratic drag c >= 0 at the junction is that law
    too); :func:`~bondgraph.diagnose.confirm.confirm_same` refits a twin in
    full where its representative's refit is not one of its boxes. A
    candidate whose graph cannot be built has no twin (its confirmation
    says why)."""
    out = {}
    for c in cands:
        try:
            built = augmented_model(ctx, current, c, scales, name)
        except BondGraphError:
            continue
        if built is None:
            continue
        key = ("model", id(current), current.nll,
               same_model_key(built[3], built[1], built[2], new_boxes=False))
        rep = ctx.cache.get(key)
        if rep is None:
            ctx.cache[key] = c
        elif ctx.cache.get(("confirmation", id(current), current.nll, rep.label)) is not None \
                or any(r is rep for r in cands):
            out[c.label] = rep
    return out


def _confirm_same_task(ctx: Context, shared, item: tuple) -> Confirmation | None:
    """:func:`bondgraph.diagnose.confirm.confirm_same` as a task of
    :func:`bondgraph.diagnose.parallel.run_tasks` (``item``: the candidate,
    its twin and the twin's confirmation; refitted in full when the twin's
    failed)."""
    current, scales, name = shared
    cand, rep, conf = item
    if conf is None:
        return confirm(ctx, current, cand, scales, name)
    return confirm_same(ctx, current, cand, scales, name, rep, conf)


def _confirm_task(ctx: Context, shared, cand: Candidate) -> Confirmation | None:
    """:func:`bondgraph.diagnose.confirm.confirm` as a task of
    :func:`bondgraph.diagnose.parallel.run_tasks`."""
    current, scales, name = shared
    return confirm(ctx, current, cand, scales, name)


def decided(ctx: Context, current: Fit, after: Fit, dof: int, comparable: bool,
            label: str, added: Sequence[Candidate] = ()):
    """:func:`bondgraph.diagnose.accept.decide` on a candidate's refit; when
    its only objection is a parameter newly on its box, decided again with
    the parameters whose box does not decide the fit exempt
    (:func:`box_not_deciding`). A parameter of an effect the loop accepted
    earlier (not of the declared graph) is exempt: its box is the
    library's, not the user's physical knowledge (as
    :func:`boxed_after_accept` leaves it out), and a refit that puts it on
    its box switches that effect off in favour of the candidate, which is
    what the record says (logged); unless it ends on the far edge of a
    search box that decides the fit (:func:`search_box_deciding`: a box the
    library set around a score's estimate is no end of the effect's
    range). On a user's two-mass drive whose load
    has Coulomb friction, a Dahl friction accepted first at the gear
    refitted to its smallest rest stiffness once the load's Coulomb
    friction was added (held-out NRMSE 0.01702 -> 0.01365), and that
    candidate was rejected in every later step for "the box, not the
    record". A decision that accepts is decided again when one of the
    candidate's own new parameters ends on a search box that decides the
    fit (``searched``). The admissibility of the refit includes
    what the ``added`` candidates' own effects find at it
    (:func:`bondgraph.diagnose.fit.admissibility`). Where the refit's
    identification of a parameter ``current`` identified hangs on its std
    (:func:`bondgraph.diagnose.accept.robust_std_needed`), its robust
    (sandwich) std is computed first (one batched filter run) and judges it."""
    s = ctx.settings
    placed = [(get_effect(c.effect, s.effects), c.target) for c in added]
    adm = admissibility(ctx, after, current.graph, placed, against=current) if comparable \
        else None
    if comparable and robust_std_needed(current, after):
        after.std_robust = {**after.std_robust, **robust_std_of(ctx, after)}
    inner = interior_params(placed)

    def judge(free=(), searched=None):
        return decide(current, after, s.accept, dof=dof, admissible=adm, comparable=comparable,
                      box_free=free, interior=inner, searched=searched,
                      known=getattr(s, "hold_unidentified", ()))

    d, free = judge(), []
    if not d.accepted and newly_boxed(current, after):
        free = switched_off(ctx, current, after)
        pressed = search_box_deciding(ctx, on_search_edge(ctx, after, free), after, label)
        free = [n for n in free if n not in pressed]
        if free:
            ctx.log(f"  {label}: the refit moves {', '.join(free)} (of an effect accepted earlier) "
                    f"onto a bound of the box the effect library gave it (that effect switched "
                    f"off, or at the end of its range): the library's box, not the user's, is no "
                    f"reason to reject")
        if newly_boxed(current, after, exempt=free + list(pressed)):
            free += [n for n in box_not_deciding(ctx, current, after, label)
                     if n not in free and n not in pressed]
        if not free:
            return d
        d = judge(free)
    if not d.accepted:
        return d
    own = [e.pname(t, p.name) for e, t in placed for p in e.params]
    searched = search_box_deciding(ctx, on_search_edge(ctx, after, own), after, label)
    return judge(free, searched) if searched else d


def search_boxed_param(ctx: Context, name: str):
    """The :class:`~bondgraph.diagnose.effects.base.EffectParam` of the
    effect parameter ``name`` (``<effect>.<target>.<local>``,
    :meth:`~bondgraph.diagnose.effects.base.Effect.pname`) when its effect
    sets its box around a start value
    (:meth:`~bondgraph.diagnose.effects.base.Effect.search_boxed`); None
    for any other parameter (declared, of another effect, or of an effect
    not in the loop's library)."""
    head, _, rest = name.partition(".")
    if not rest:
        return None
    try:
        eff = get_effect(head, ctx.settings.effects)
    except BondGraphError:
        return None
    local = name.rsplit(".", 1)[1]
    if local not in eff.search_boxed():
        return None
    return next((p for p in eff.params if p.name == local), None)


def on_search_edge(ctx: Context, after: Fit, names: Sequence[str]) -> list[str]:
    """The effect parameters among ``names`` that the refit ``after`` leaves
    on the edge of a search box (:func:`search_boxed_param`: a box set
    around a score's estimate, or a structural effect's start ×/÷ 100
    within its grid's reach): either edge, or the upper one for a
    ``nonnegative`` parameter (its 0 switches the effect off, a physical
    limit)."""
    bound = set(after.at_bound or ())
    out = []
    for n in names:
        if n not in bound or n not in after.model.params:
            continue
        spc = search_boxed_param(ctx, n)
        if spc is None:
            continue
        lo, hi = after.model.bounds([n])
        v = float(after.theta[after.model.param_index(n)])
        if not spc.nonnegative or hi[0] - v <= v - lo[0]:
            out.append(n)
    return out


def search_box_deciding(ctx: Context, names: Sequence[str], after: Fit,
                        label: str) -> dict[str, float]:
    """The parameters ``names`` (on the edge of their search box,
    :func:`on_search_edge`) whose search box decides the refit ``after``:
    opened :data:`BOX_OPENING`-fold on the side they sit on
    (:func:`beyond_box`, one refit), the likelihood gains at least
    :data:`BOX_DECIDES`; each mapped to that gain [nats] ({} when ``names``
    is empty, the gain is smaller, or the refit fails). Logged.

    A search box is no physical knowledge: an estimate it stops is not one
    the record made. On a motor whose sensor gain g trades with the torque
    constant along a ridge, an optimiser that follows the ridge ends with g
    on its search box (−0.6, ten times the score's −0.06) and k_t 0.024
    (truth 0.060), and the held-out error still falls: such a candidate is
    refused (:func:`bondgraph.diagnose.accept.decide`, ``searched``), and
    so is one that pushes an earlier effect's parameter there
    (:func:`decided`). A parameter whose box the likelihood does not press
    against (a gain below :data:`BOX_DECIDES` beyond it) is no reason to
    refuse."""
    names = list(names)
    if not names:
        return {}
    r = beyond_box(ctx, after.graph, after, list(after.params), only=names)
    if r is None:
        return {}
    gain, values = r
    text = ", ".join(f"{n} = {v:.4g}" for n, v in values.items())
    if not gain >= BOX_DECIDES:
        ctx.log(f"  {label}: {', '.join(names)} on the edge of its search box, but beyond it the "
                f"likelihood gains only {gain:.3g} nats (< {BOX_DECIDES:.3g}, at {text}): the box "
                f"does not decide the fit")
        return {}
    ctx.log(f"  {label}: {', '.join(names)} on the edge of its search box; beyond it the "
            f"likelihood gains {gain:.3g} nats (at {text}): the box decides the fit")
    return {n: float(gain) for n in names}


def interior_params(placed: list) -> list[str]:
    """The parameters of the placed effects ``placed`` ((effect, target)
    pairs) that their effect declares ``interior`` (the accept rule refuses
    one on a bound of its box, :func:`~bondgraph.diagnose.accept.at_family_edge`)."""
    return [e.pname(t, p.name) for e, t in placed for p in e.params if p.interior]


def switched_off(ctx: Context, current: Fit, after: Fit) -> list[str]:
    """The parameters of effects the loop accepted earlier (not of the
    declared graph) that the refit ``after`` newly puts on a bound of their
    box: it switches those effects off (:func:`decided`, :func:`pruned`)."""
    declared = ctx.problem.model.params
    return [n for n in newly_boxed_names(current, after) if n not in declared]


def pruned(ctx: Context, result: LoopResult, current: Fit, after: Fit,
           added: Sequence[Candidate], label: str):
    """The accepted refit ``after`` (``current`` plus the ``added``
    candidates) without the earlier effects it switches off
    (:func:`switched_off`) or leaves indistinguishable from 0
    (:func:`insignificant_earlier`), when the loop's own accept rule no longer
    wants them: each such effect is removed, the model rebuilt from the
    declared graph with the other applied effects and the ``added`` ones at
    their values in ``after`` (boxes as in ``after``) and refitted
    (continued until it converges). The effect goes when adding it back to
    that refit would not pass :func:`~bondgraph.diagnose.accept.decide`
    (its parameters as the dof) and the refit itself passes
    :func:`decided` against ``current``, as any accepted model must
    (``added``'s parameters less the removed ones as the dof, at least 1;
    its own parameters on a search box that decides the fit refuse it, as
    they refuse any candidate's refit). This is the
    backward half of stepwise selection, with the forward half's rule
    (Efroymson 1960): an effect accepted first because the record's best
    candidate was not yet in the model is dropped once that candidate is.
    On a user's two-mass drive a Dahl friction at the gear was accepted
    before the load's Coulomb friction and then refitted to its smallest
    rest stiffness; without it the held-out NRMSE is 0.01362 (with it
    0.01365) and the load's Coulomb level 0.502 N m (truth 0.5; with it
    0.476).

    Returns
    -------
    (fit, removed, decision)
        The fit to accept, the removed :class:`AppliedEffect` entries and
        the decision of the reduced refit against ``current`` (None when
        nothing was removed: ``after`` itself).
    """
    off = set(switched_off(ctx, current, after))
    weak = insignificant_earlier(ctx, result, after)
    if (not off and not weak) or result.declared_graph is None:
        return after, [], None
    s = ctx.settings
    fit, removed, dec = after, [], None
    for gone in [a for a in result.applied if id(a) in weak
                 or off & set(_param_names(get_effect(a.effect, s.effects), a.target))]:
        eff = get_effect(gone.effect, s.effects)
        what = f"{gone.effect} @ {gone.target.name}"
        does = (f"leaves {what} indistinguishable from 0 ({weak[id(gone)]})" if id(gone) in weak
                else f"puts {what} on its box")
        reduced = _without(ctx, result, fit, [a for a in result.applied
                                              if a is not gone and a not in removed], added, what)
        if reduced is None:
            continue
        k = sum(1 for n in _param_names(eff, gone.target) if n in fit.params)  # held ones not
        back = decide(reduced, fit, s.accept, dof=max(k, 1),
                      admissible=admissibility(ctx, fit, reduced.graph, [(eff, gone.target)],
                                               against=reduced),
                      comparable=reduced.converged is not False and fit.converged is not False)
        if back.accepted:
            ctx.log(f"  {label} {does}, but it still passes the accept rule given the "
                    f"others: kept")
            continue
        dof = max(1, len(set(reduced.params) - set(current.params)))
        d = decided(ctx, current, reduced, dof, reduced.converged is not False,
                    f"{label} without {what}", added)
        if not d.accepted:
            ctx.log(f"  {label} without {what}: not accepted against the model before this "
                    f"step ({d.reason}): {what} kept")
            continue
        ctx.log(f"  {label} {does} and the record no longer wants it ({back.reason}"
                f" when it is added back): removed (NLL {fit.nll:.2f} -> {reduced.nll:.2f}, "
                f"{result.metric} {back.error_after:.4g} -> {back.error_before:.4g})")
        fit, dec = reduced, d
        removed.append(gone)
    return fit, removed, dec


def insignificant_earlier(ctx: Context, result: LoopResult, after: Fit) -> dict[int, str]:
    """The additive effects accepted earlier (``result.applied``; their
    estimated parameters are amplitudes whose 0 switches the effect off)
    that the refit ``after`` leaves indistinguishable from 0: the Wald
    statistic Σ (β_i / σ_i)² of their estimated parameters in ``after``
    (Cramér-Rao std) below the χ²(k) quantile at the accept rule's
    significance. Such an effect was accepted because the record's best
    candidate was not yet in the model (a user's cart on Coulomb friction:
    a square-root damper accepted first, its β = 0.018 ± 0.0106 once the
    Coulomb term is in, z 1.7), and :func:`pruned` asks the accept rule
    whether the record still wants it. An effect with a parameter without a
    finite std is left to the box rule (:func:`switched_off`).

    Returns
    -------
    dict
        ``id(applied effect)`` -> ``"Wald χ² 2.91 on 1 degree of freedom,
        p 0.088"``.
    """
    s = ctx.settings
    out = {}
    for a in result.applied:
        eff = get_effect(a.effect, s.effects)
        if not eff.additive:
            continue
        names = [eff.pname(a.target, p.name) for p in eff.params if p.estimated]
        names = [n for n in names if n in after.params]
        if not names:
            continue
        idx = [after.model.param_index(n) for n in names]
        sd = [after.std.get(n) for n in names]
        if any(v is None or not np.isfinite(v) or v <= 0 for v in sd):
            continue
        w = float(sum((after.theta[i] / v) ** 2 for i, v in zip(idx, sd)))
        k = len(names)
        if w < float(chi2.ppf(1.0 - s.accept.significance, k)):
            out[id(a)] = (f"Wald χ² {w:.3g} on {k} degree{'s' if k > 1 else ''} of freedom, "
                          f"p {float(chi2.sf(w, k)):.2g}")
    return out


def _param_names(eff, target) -> list[str]:
    """The graph names of ``eff``'s parameters at ``target``."""
    return [eff.pname(target, p.name) for p in eff.params]


def _rebuilt(ctx: Context, result: LoopResult, fit: Fit, effects: list, name: str) -> BondGraph:
    """The declared graph (named ``name``) with ``effects`` ((effect name,
    target) pairs) applied at their values in ``fit`` and every parameter
    ``fit``'s graph has boxed as there (:func:`_without`, :func:`_swap_refit`).

    Raises
    ------
    BondGraphError
        If an effect cannot be applied."""
    g = result.declared_graph.copy(name)
    vals = dict(zip(fit.model.params, fit.theta.tolist()))
    for effect, target in effects:
        eff = get_effect(effect, ctx.settings.effects)
        eff.apply(g, target, {p.name: vals[n] for p, n in
                              zip(eff.params, _param_names(eff, target)) if n in vals})
    for n, prm in g.params.items():
        if n in fit.graph.params:
            prm.bounds = fit.graph.params[n].bounds
    return g


def _without(ctx: Context, result: LoopResult, fit: Fit, keep: list, added: Sequence[Candidate],
             what: str) -> Fit | None:
    """The declared graph with the applied effects ``keep`` and the ``added``
    candidates at their values in ``fit``, every parameter's box as in
    ``fit``, refitted from ``fit``'s estimates (:func:`pruned`); None
    (logged) when it cannot be built or fitted."""
    s = ctx.settings
    vals = dict(zip(fit.model.params, fit.theta.tolist()))
    try:
        g = _rebuilt(ctx, result, fit, [(a.effect, a.target) for a in keep]
                     + [(c.effect, c.target) for c in added], f"{fit.graph.name}__without")
        model = model_of(g)
        names = [n for n in fit.params if n in model.params]
        start = {n: v for n, v in vals.items() if n in model.params}
        reduced = fit_model(ctx, g, names, start, f"without {what}", model=model,
                            iterations=s.search.confirm_iterations,
                            tolerance=s.search.confirm_tolerance)
        return continued(ctx, g, reduced, f"without {what}")
    except BondGraphError as exc:
        ctx.log(f"  the model without {what} could not be refitted: {str(exc).splitlines()[0]}")
        return None


#: rivals of an earlier effect refitted in its place after an accepted step
#: (:func:`replaced_earlier`): at most this many, by their confirmed
#: likelihood ratio at the effect's own step
REPLACE_TOP = 2
#: ... each of them with a confirmed likelihood ratio at that step of at least
#: this share of the effect's own (a rival the record then told apart by more
#: is not refitted): at the effect's place
REPLACE_SHARE = 0.8
#: ... and at another place (a sensor's low-pass and a source's lag: two
#: places for one linear lag)
REPLACE_SHARE_ELSEWHERE = 0.95


def replaced_earlier(ctx: Context, result: LoopResult, current: Fit, after: Fit,
                     earlier: set, scales: Scales, tag: str) -> Fit:
    """After a step accepted ``after`` (``current`` plus the step's effects),
    each effect accepted at an earlier step (``result.applied`` entries whose
    ``id`` is in ``earlier``) is refitted replaced by its rivals
    (:func:`rivals_of`: the other laws confirmed at its place in its step);
    the best rival refit that the record prefers to ``after``
    (:func:`swap_refused`) takes its place: ``result.applied`` and the
    step's record (``Step.replaced``, its numbers those of the new fit) are
    updated, and the new fit returned (``after`` when none is).

    An effect is chosen against the model of its own step. Where a later
    step adds what that model lacked, a rival can fit better than the chosen
    law; once a law is at a place, no later step scores another one there.
    This is the replacement half of stepwise selection (Miller 2002,
    *Subset selection in regression*, sec. 3.5). A user's oven graph
    (radiation beside the wall's conduction and a thermocouple lag, neither
    declared): a cubic wall law was accepted by 7912 against radiation's
    7621 while the lag was missing; with the lag in, the radiation law's
    refit is 6762 nats better, and without the replacement the loop went on
    to accept a heater offset and an ambient saturation that compensate the
    wrong law.
    """
    s = ctx.settings
    if not s.accept.replace or result.declared_graph is None or not result.steps:
        return after
    step_new = [(a.effect, a.target) for a in result.applied if id(a) not in earlier]
    for old in [a for a in result.applied if id(a) in earlier]:
        best = None
        for alt in rivals_of(result, old):
            label = f"{alt.label} in place of {old.effect} @ {old.target.name}"
            swapped = _swap_refit(ctx, result, after, old, alt, scales, f"{tag}_swap", label)
            if swapped is None:
                continue
            why, d, cands = swap_refused(ctx, result, current, after, swapped, alt, step_new)
            if why:
                ctx.log(f"  {label}: kept {old.effect} ({why})")
            elif best is None or swapped.nll < best[0].nll:
                best = (swapped, alt, d, cands, label)
        if best is not None:
            after = _committed_swap(ctx, result, current, after, old, best) or after
    return after


def rivals_of(result: LoopResult, old) -> list[Candidate]:
    """The rivals of the applied effect ``old`` (:func:`replaced_earlier`):
    in the last ranking where ``old`` was confirmed, the other effects whose
    refit was usable (converged, not refused as :data:`_UNUSABLE`) and
    reached :data:`REPLACE_SHARE` of its likelihood ratio at its place, or
    :data:`REPLACE_SHARE_ELSEWHERE` at another place (not a twin or a
    signature look-alike, ``same_as``, ``equivalent``: the same model), not
    one an earlier replacement took out (the record preferred its rival
    then), none at a place another applied effect holds; at most
    :data:`REPLACE_TOP`, best (LR - 2k) first."""
    out = {r.split(" by ")[0] for st in result.steps for r in getattr(st, "replaced", ())}
    held = {a.target for a in result.applied if a is not old}
    for ranking in reversed(result.rankings):
        own = [c for c in ranking if c.effect == old.effect and c.target == old.target
               and c.confirmed_statistic is not None]
        if not own:
            continue
        lr, me = own[0].confirmed_statistic, own[0]
        pool = [c for c in ranking if c is not me and c.target not in held
                and c.confirmed and c.confirmed.get("comparable", True)
                and c.confirmed_statistic is not None and lr > 0
                and c.confirmed_statistic >= lr * (REPLACE_SHARE if c.target == old.target
                                                   else REPLACE_SHARE_ELSEWHERE)
                and not getattr(c, "same_as", None) and c.label not in out
                and c.label not in me.equivalent and me.label not in c.equivalent
                and not str(c.confirmed.get("reason") or "").startswith(_UNUSABLE)]
        return sorted(pool, key=lambda c: -(c.confirmed_statistic - 2 * c.dof))[:REPLACE_TOP]
    return []


def _swap_refit(ctx: Context, result: LoopResult, fit: Fit, old, alt: Candidate,
                scales: Scales, name: str, label: str) -> Fit | None:
    """The declared graph with every applied effect but ``old`` at its value
    in ``fit`` (boxes as there) and ``alt`` from its confirmed values (boxes
    as its confirmation set them, :func:`~bondgraph.diagnose.confirm.widen_boxes`),
    every parameter refitted (at most ``settings.search.confirm_iterations``
    scoring iterations, at the loop's discretisation); None (logged) when it
    cannot be built or fitted."""
    s = ctx.settings
    vals = dict(zip(fit.model.params, fit.theta.tolist()))
    try:
        g = _rebuilt(ctx, result, fit, [(a.effect, a.target) for a in result.applied
                                        if a is not old], name)
        eff = get_effect(alt.effect, s.effects)
        start_alt = start_values(eff, alt, {**alt.values,
                                            **(alt.confirmed or {}).get("values", {})})
        P = eff.apply(g, alt.target, start_alt, scales)
        widen_boxes(eff, P, eff.grid_span(fit.graph, alt.target, scales)
                    if not eff.additive else {})
        new = [P[p.name].name for p in eff.params
               if p.estimated and p.name in P and p.name not in alt.held]
        start = {n: v for n, v in vals.items() if n in g.params}
        start.update({P[k].name: float(v) for k, v in start_alt.items() if k in P})
        names = [n for n in fit.params if n in g.params] + new
        # one refit of the confirmations' length, not continued: a rival that
        # has not converged by then is refused anyway (on a user's CED graph a
        # power-law armature term in a square-root motor friction's place
        # crawled 15 s through its continuations to be refused)
        return fit_model(ctx, g, names, start, label, model=model_of(g),
                         iterations=s.search.confirm_iterations,
                         tolerance=s.search.confirm_tolerance)
    except BondGraphError as exc:
        ctx.log(f"  {label} could not be refitted: {str(exc).splitlines()[0]}")
        return None


def swap_refused(ctx: Context, result: LoopResult, current: Fit, after: Fit, swapped: Fit,
                 alt: Candidate, step_new: list) -> tuple[str | None, Decision | None, list]:
    """Why the refit ``swapped`` (a rival in an earlier effect's place,
    :func:`replaced_earlier`) does not replace ``after``, or None: it must
    have converged; predict the record better by Vuong's (1989) test of the
    two non-nested models (one-sided at ``settings.accept.significance``,
    Akaike-corrected, Newey-West variance: :func:`~bondgraph.diagnose.accept.vuong_test`);
    have a free-run error on the record and on the judging record no larger
    than ``after``'s (a replacement is never worse on a record it is judged
    on); and pass the accept rule against ``current``, the model before the
    step, as any accepted model must (:func:`decided`, with the step's
    effects, ``step_new`` ((effect, target) pairs), and ``alt`` as the
    added candidates). Returns (reason, decision, added candidates)."""
    s = ctx.settings
    if swapped.converged is False:
        return "its refit did not converge", None, []
    la, lb = per_sample_nll(swapped), per_sample_nll(after)
    if la is None or lb is None or la.shape != lb.shape:
        return "no per-sample likelihood to compare", None, []
    z, p = vuong_test(la, lb, len(swapped.params), len(after.params))
    if not (np.isfinite(z) and z > 0 and p / 2 < s.accept.significance):
        return (f"the record does not prefer it: Vuong's z {z:.2f}, NLL {after.nll:.2f} -> "
                f"{swapped.nll:.2f}"), None, []
    for what, a, b in (("held-out", after.accept_metric, swapped.accept_metric),
                       ("record's", after.metric, swapped.metric)):
        if not b <= a:
            return f"its {what} error {a:.4g} -> {b:.4g} is not lower", None, []
    ranking = result.rankings[-1] if result.rankings else []
    cands = [c for c in ranking if (c.effect, c.target) in step_new] + [alt]
    dof = max(1, len(set(swapped.params) - set(current.params)))
    d = decided(ctx, current, swapped, dof, True, alt.label, cands)
    if not d.accepted:
        return f"against the model before this step: {d.reason}", d, cands
    return None, d, cands


def _committed_swap(ctx: Context, result: LoopResult, current: Fit, after: Fit, old,
                    best: tuple) -> Fit | None:
    """Replace ``old`` by the rival of ``best`` ``(fit, candidate, decision,
    added candidates, label)`` (:func:`replaced_earlier`): the fit after the
    discretisation check (None, logged, when it no longer passes there),
    ``result.applied`` and the step's record updated, logged."""
    swapped, alt, d, cands, label = best
    dof = max(1, len(set(swapped.params) - set(current.params)))
    fit, finer = fit_after_discretisation_check(ctx, result, swapped, label,
                                                (current, dof, True, cands))
    if fit is None:
        ctx.log(f"  {label}: kept {old.effect} ({finer_step_reason(finer)})")
        return None
    d = finer or d
    std = parameter_std(ctx, fit)
    fit.std = std
    result.applied = [applied_effect(get_effect(alt.effect, ctx.settings.effects), alt, fit)
                      if a is old else a for a in result.applied]
    for a in result.applied:       # the others' values are the new fit's too
        eff = get_effect(a.effect, ctx.settings.effects)
        a.values.update({p.name: float(fit.theta[fit.model.param_index(n)]) for p, n in
                         zip(eff.params, _param_names(eff, a.target)) if n in fit.model.params})
    st = result.steps[-1]
    st.replaced.append(f"{old.effect} @ {old.target.name} by {alt.effect}")
    st.error_after, st.nll_after, st.estimation_error_after = d.error_after, fit.nll, fit.metric
    st.criterion_after, st.whiteness_after = d.criterion_after, d.whiteness_after
    st.lr, st.lr_p_value = d.lr, d.lr_p_value
    st.parameters = {n: {"estimate": float(fit.theta[fit.model.param_index(n)]),
                         "std": std.get(n)} for n in fit.params}
    st.more_errors = {k: [current.more_metrics.get(k), v] for k, v in fit.more_metrics.items()}
    ctx.log(f"REPLACE {old.effect} @ {old.target.name} by {alt.label}: NLL {after.nll:.2f} -> "
            f"{fit.nll:.2f}, {result.metric} {after.accept_metric:.4g} -> "
            f"{fit.accept_metric:.4g} (the record prefers it now that the later effects are "
            f"in)")
    return fit


def accept_best(ctx: Context, result: LoopResult, current: Fit,
                confirmed: list[tuple[Candidate, Confirmation]], step: int,
                pairing: tuple | None = None, refit: tuple | None = None) -> Fit | None:
    """Accept the first confirmed candidate that passes
    :func:`bondgraph.diagnose.accept.decide` (its step, applied effect and
    Cramér-Rao std recorded); record and log the rejected ones before it.
    With ``pairing`` ``(scales, tag)`` and ``settings.accept.pairs``, a pair
    of significant confirmed candidates that beats it is accepted instead
    (:func:`pair_before_single`). With ``refit`` ``(scales, tag)``, a
    candidate refused because the record does not identify some of its
    terms apart from the current model is judged next with those terms
    held at 0 (:func:`held_retry`). Returns the accepted fit, or None."""
    s = ctx.settings
    crit = s.accept.criterion.upper()
    confirmed = list(confirmed)
    i = 0
    while i < len(confirmed):
        c, conf = confirmed[i]
        i += 1
        names = list(current.params) + conf.new_params
        after = conf.fit
        d = decided(ctx, current, after, conf.dof, conf.comparable, c.label, [c])
        tie = {k: v for k, v in (c.confirmed or {}).items()
               if k in ("tie_z", "tie_p", "comparable")}
        c.confirmed = {**confirmed_record(current, after, conf.dof, conf.values,
                                          s.accept, d), **tie}
        if d.accepted and pairing is not None:
            better = pair_before_single(ctx, result, current, (c, conf), confirmed, pairing,
                                        step)
            if better is not None:
                return better
        if d.accepted:
            after, finer = fit_after_discretisation_check(ctx, result, after, c.label,
                                                          (current, conf.dof,
                                                           conf.comparable, [c]))
            if after is None:
                result.rejected.append(Rejection(step, c, finer_step_reason(finer),
                                                 d.criterion_after, d.whiteness_after))
                continue
            d = finer or d
            after, removed, dr = pruned(ctx, result, current, after, [c], c.label)
            if removed:
                d, names = dr, list(after.params)
            new_std = parameter_std(ctx, after)
            result.steps.append(accepted_step(c, d, current, after, names, new_std,
                                              result.metric))
            result.steps[-1].removed = [f"{a.effect} @ {a.target.name}" for a in removed]
            result.applied = [a for a in result.applied if a not in removed]
            result.applied.append(applied_effect(get_effect(c.effect, s.effects), c, after))
            after.std = new_std
            scaled = scaled_lr(ctx, result.steps[-1], after, conf.dof if not removed else None)
            boxed_after_accept(ctx, result, after, names, c.label)
            gone = "".join(f" (removing {r})" for r in result.steps[-1].removed)
            ctx.log(f"ACCEPT {c.label}{gone}: {result.metric} {d.error_before:.4g} -> "
                    f"{d.error_after:.4g}, NLL {current.nll:.2f} -> {after.nll:.2f}, {crit} "
                    f"{d.criterion_before:.2f} -> {d.criterion_after:.2f}, whiteness "
                    f"{d.whiteness_before:.1f} -> {d.whiteness_after:.1f} (information only), "
                    f"LR {d.lr:.1f} (p {d.lr_p_value:.2g}{scaled}), error decrease z "
                    f"{d.error_z:.2f} (p {d.error_p_value:.2g})")
            return after
        result.rejected.append(rejection(step, c, d))
        ctx.log(f"reject {c.label} ({d.reason}): {crit} {d.criterion_before:.2f} -> "
                f"{d.criterion_after:.2f}, whiteness {d.whiteness_before:.1f} -> "
                f"{d.whiteness_after:.1f}, error {d.error_before:.4g} -> {d.error_after:.4g}")
        retry = held_retry(ctx, current, c, conf, refit) if refit is not None else None
        if retry is not None:
            confirmed.insert(i, retry)
    return None


def ridge_to_search_edge(ctx: Context, current: Fit, after: Fit,
                         new_params: Sequence[str]) -> tuple[list[str], list[str]]:
    """``(new, partners)``: the candidate's ``new_params`` that its refit
    ``after`` leaves on the edge of their search box (:func:`on_search_edge`)
    along a flat direction of its Fisher information (``after.flat``, the
    collinearity analysis over every estimated parameter, those on a box
    included), and the parameters ``current`` identified (not in
    ``current.flat``) along the same direction; two empty lists when either
    is empty. The optimiser followed a ridge until a box that is no
    physical knowledge stopped it: the record does not tell those new
    parameters apart from the partners, as :func:`unidentified_new` finds
    where the ridge stays inside the boxes (there the partners' Cramér-Rao
    std grows; here the parameter on the box has none and the partners'
    stays small)."""
    flat = set(after.flat or ())
    edge = [n for n in on_search_edge(ctx, after, list(new_params)) if n in flat]
    had = set(current.flat or ())
    partners = [n for n in after.params if n in current.params and n in flat and n not in had]
    return (edge, partners) if edge and partners else ([], [])


def ridge_crawl(current: Fit, after: Fit,
                new_params: Sequence[str]) -> tuple[list[str], list[str]]:
    """``(held, partners)`` for a refit ``after`` that did not converge
    (``converged`` False) while its Fisher information is flat along some of
    the candidate's ``new_params`` together with parameters ``current``
    identified (not in ``current.flat``): the optimiser was crawling along a
    ridge that those parameters span, and whatever point it stopped at
    decides nothing. ``held``: the new parameters that lead the flat
    direction, those loading on it more than any partner (``after.flat``
    is ordered by loading, :func:`bondgraph.inference.fisher.flat_directions`),
    else the new one that loads most; two empty lists when the refit
    converged or the direction has no new parameter or no partner. On a
    user's EMPS graph with a force offset accepted, the direction-dependent
    friction's refit crawled for 112 iterations along dc, F0, dv (dc's
    Coulomb half-difference is the offset wherever the drive moves), not
    comparable, and a quadratic encoder term was accepted before it."""
    if after.converged is not False:
        return [], []
    order = list(after.flat or ())
    had = set(current.flat or ())
    partners = [n for n in order if n in current.params and n not in had]
    new = [n for n in order if n in new_params]
    if not new or not partners:
        return [], []
    first = order.index(partners[0])
    lead = [n for n in new if order.index(n) < first]
    return (lead or new[:1]), partners


def held_first(ctx: Context, current: Fit, confirmed: list, refit: tuple) -> list:
    """``confirmed`` ((candidate, confirmation) pairs, best first) with the
    held refit (:func:`held_retry`) of each candidate whose refit crawled
    along a ridge it shares with the current model (:func:`ridge_crawl`)
    ranked among them (:func:`~bondgraph.diagnose.accept.rank_confirmed`)
    before the accept rule decides: such a refit is not comparable and ranks
    last, so a comparable candidate of a lower likelihood ratio would be
    accepted before its held form is ever judged."""
    extra = []
    for c, conf in confirmed:
        if conf is None or conf.comparable or getattr(c, "held", None) \
                or not ridge_crawl(current, conf.fit, conf.new_params)[0]:
            continue
        retry = held_retry(ctx, current, c, conf, refit)
        if retry is not None:
            extra.append(retry)
    if not extra:
        return confirmed
    ranked = rank_confirmed([(c.confirmed_statistic - 2 * c.dof, c, r)
                             for c, r in confirmed + extra])
    return [(c, r) for _, c, r in ranked]


def held_retry(ctx: Context, current: Fit, cand: Candidate, conf: Confirmation,
               refit: tuple) -> tuple[Candidate, Confirmation] | None:
    """The candidate ``cand`` refitted with the terms its refit ``conf``
    leaves undetermined held at 0, to be judged in its place: ``(candidate,
    confirmation)`` (the candidate a copy with :attr:`Candidate.held` set
    and its degrees of freedom lowered), or None where this does not apply.

    It applies to a refused additive effect (Σ βₖ bₖ, each β = 0
    neutral, 0 inside its box) whose refit does not identify some of its
    new parameters apart from parameters the current fit identified
    (:func:`bondgraph.diagnose.accept.unidentified_new`), while others of
    them remain: those are a smaller effect of the same family that the
    record may determine. Whatever refused the refit (that rule, or one the
    accept rule applies first), its verdict was taken at an arbitrary point
    of the ridge: a Coulomb half-difference that a declared torque offset
    absorbs made the R field a source at low speed (any dc ≠ 0 does, its
    effort dc·tanh² being even in the speed). On a user's EMPS graph whose loop had
    accepted a force offset, the direction-dependent friction's Coulomb
    half-difference dc·tanh²(v/ε) is that offset wherever the drive moves,
    and its viscous half-difference dv·v·tanh(v/ε) (the published
    asymmetric model's 166.7 against 240.4 N s/m) was refused with it.
    Where the optimiser followed that ridge to the edge of the half-difference's
    search box (:func:`ridge_to_search_edge`: on the box the parameter has no
    std, so the offset's stays small and :func:`unidentified_new` sees no
    ridge), the same applies: on that EMPS graph after a Coulomb friction and
    a cubic viscous term, dc ran to −13.36 N (the box's edge) along the
    offset, and the refusal took the viscous half-difference with it.
    A refit that crawled along such a ridge without converging
    (:func:`ridge_crawl`) is held the same way (:func:`held_first` does it
    before the decision).
    Only once per candidate (``cand.held`` empty) and current fit;
    ``refit`` is ``(scales, tag)`` of the step's refits."""
    if cand.held:
        return None
    eff = get_effect(cand.effect, ctx.settings.effects)
    if not eff.additive:
        return None
    once = ("held retry", id(current), current.nll, cand.label)
    if once in ctx.cache:
        return None
    ctx.cache[once] = True
    flat, partners = unidentified_new(current, conf.fit)
    if not flat:
        flat, partners = ridge_to_search_edge(ctx, current, conf.fit, conf.new_params)
    if not flat:
        flat, partners = ridge_crawl(current, conf.fit, conf.new_params)
    local = {eff.pname(cand.target, p.name): p for p in eff.params if p.estimated}
    held = [local[n] for n in flat if n in local]
    rest = [n for n in conf.new_params if n in local and local[n] not in held]
    if not held or not rest or any(p.bounds is not None and not p.bounds[0] <= 0.0 <= p.bounds[1]
                                   for p in held):
        return None
    red = replace(cand, held={p.name: 0.0 for p in held}, dof=len(rest), confirmed=None,
                  confirmed_statistic=None, tied=[])
    ctx.log(f"  {cand.label}: refitted with {', '.join(p.name for p in held)} held at 0 (the "
            f"record does not tell {', '.join(flat)} apart from {', '.join(partners)}): its "
            f"other terms judged alone")
    scales, tag = refit
    r = confirm_held(ctx, current, red, conf, scales, tag)
    if r is None:
        return None
    ctx.cache[("confirmation", id(current), current.nll, red.label)] = r    # as confirm_best's
    red.confirmed_statistic = max(0.0, 2 * (current.nll - r.fit.nll))
    red.confirmed = confirmed_record(current, r.fit, r.dof, r.values, ctx.settings.accept)
    red.confirmed["comparable"] = r.comparable
    how = _how(r.fit)
    ctx.log(f"  confirmed {red.label}: LR {red.confirmed_statistic:.1f}, values {r.values} "
            f"({how}, {r.fit.iterations} iterations)")
    return red, r
