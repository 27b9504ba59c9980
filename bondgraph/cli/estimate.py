"""``bondgraph estimate``: maximum-likelihood estimation (batched UKF + PSO or
DE), writing ``result.json`` and PNG fit plots."""

from __future__ import annotations

import argparse
import contextvars
import json
import shutil
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from bondgraph.cli.common import (
    add_data,
    add_discretisation,
    add_estimation_scope,
    add_model,
    add_overwrite,
    add_quiet,
    add_scheduler,
    chosen_at_levels,
    chosen_problem,
    decimated_window,
    default_out,
    default_params,
    discretisation_given,
    estimated_states,
    filtered_record,
    load_model,
    load_record,
    output_folder,
    parse_pairs,
    parse_params,
    problem_from_args,
    published,
    reading_options,
)
from bondgraph.core import progress
from bondgraph.core.jsonsafe import to_jsonable
from bondgraph.errors import (BondGraphError, EstimationError, IdentifiabilityWarning,
                              NumericalError, OptionError, UsageError)
from bondgraph.inference.discretise import (HOLD_CHECK_MARGIN, alternative_hold,
                                            check_discretisation, choose_discretisation,
                                            cost_rank, hold_check_line, hold_verdict,
                                            moved_most, no_process_noise,
                                            other_hold_warning, step_error)
from bondgraph.inference.estimate import check_not_fixed, estimate
from bondgraph.inference.estimand import noise_parameters
from bondgraph.inference.output_error import (OutputErrorOptions, output_error_fit,
                                              output_error_nll, seen_initial_states)
from bondgraph.inference.options import FitOptions
from bondgraph.inference.ukf_numba import compile_in_background
from bondgraph.numerics.integrators import join_hold, split_hold
from bondgraph.report.estimation import plot_fit


#: the example line of ``bondgraph estimate --help``
EXAMPLE = "bondgraph estimate --model mass_spring_damper --data msd_force_step.csv --params m,k,c --out msd_est"


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph estimate``."""
    add_model(p)
    add_data(p, several=True)
    p.add_argument("--params", default=None,
                   help="comma-separated parameters to estimate, or recommended:FILE for the "
                        "set recommended in a `bondgraph sensitivity` result (sensitivity.json "
                        "or its directory). Default: those the graph declares with a box (one "
                        "declared without a box is a known value, held), or all when none has "
                        "one; one line on stderr")
    p.add_argument("--validate", action="append", metavar="FILE",
                   help="a record the estimate is not fitted to: at the end its free run there "
                        "is judged as `bondgraph compare` judges it (RMS error, NRMSE, fit %%; "
                        "compare.json, a CSV and a plot per record in OUT/validation); repeat "
                        "for more records")
    p.add_argument("--init-samples", type=int, default=0, metavar="N",
                   help="with --validate: the free run on each such record starts from the "
                        "smoothed state given its first N samples, the errors over the rest "
                        "(benchmark protocols: Silverbox 50, EMPS 20); default 0: the record's "
                        "own initial state, else the smoothed state given the whole record")
    p.add_argument("--optimizer", choices=("pso", "de"), default="pso")
    p.add_argument("--particles", type=int, default=None, help="swarm / population size (10 k)")
    p.add_argument("--iterations", type=int, default=100,
                   help="iterations of the global search (default 100); 0: its first population "
                        "only (the start is one of it), then the polish (Fisher scoring, "
                        "L-BFGS-B): for a start that is already a fit, such as a loop's "
                        "augmented_model.py (a user's Silverbox model on 16 384 samples: 2 min "
                        "against 9, the same NLL within 1 nat)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None,
                   help="output directory (default estimate_<model>_<data>, numbered -2, -3, "
                        "... when it holds an earlier result; with --resume the last one "
                        "holding a checkpoint); an explicit --out is refused when not empty, "
                        "unless --overwrite")
    add_overwrite(p)
    p.add_argument("--checkpoint", default=None,
                   help="checkpoint file (default .<out>.work/checkpoint.npz beside --out while "
                        "running; copied into <out> at the end)")
    p.add_argument("--resume", action="store_true", help="continue from the checkpoint")
    add_estimation_scope(p)
    add_discretisation(p)
    p.add_argument("--alpha", type=float, default=1.0)
    p.add_argument("--beta", type=float, default=2.0)
    p.add_argument("--kappa", type=float, default=0.0)
    p.add_argument("--stall", type=int, default=None, help="stop after N iterations without progress")
    p.add_argument("--no-polish", action="store_true")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("--workers", type=int, default=1,
                   help="local Dask worker processes per batched evaluation (1: in process)")
    add_scheduler(p)
    p.add_argument("--fit", choices=("nll", "sim"), default="nll",
                   help="criterion: the UKF negative log-likelihood (nll: process noise, "
                        "unmeasured disturbances, global search) or the free-run simulation "
                        "error by least squares (sim: a deterministic model, a local search "
                        "from the defaults; compiled runs of the chosen RK4 or ROS2 step, "
                        "chosen again at the estimate where it fails there, else LSODA with "
                        "forward sensitivities; the initial states the record does not give "
                        "are estimated too)")
    add_quiet(p)


def run(args) -> int:
    """Estimate, then publish ``--out`` as one complete folder (fit plots,
    ``checkpoint.npz``, and ``result.json`` last); print the table.

    The optimizer's checkpoint lives in the working folder ``.OUT.work``
    beside ``--out`` until the result is published, so a killed run leaves
    ``--out`` as it was and ``--resume`` continues from the checkpoint.

    Raises
    ------
    OutputError
        ``--out`` is not empty (without ``--overwrite`` or ``--resume``) or
        not writable; checked before the estimation.
    EstimationError
        No parameter set had a finite NLL.
    """
    if args.fit != "sim" and args.backend == "numba":
        compile_in_background()     # the filter kernel, once per installation, beside the set-up
    paths = list(args.data)
    with progress.phase("loading the model and the records"):
        model = load_model(args.model)
        decimated_window(args)
        exps = [filtered_record(load_record(pth, model, columns=args.columns, dt=args.dt),
                                model, args) for pth in paths]
        vals = [filtered_record(load_record(pth, model, columns=args.columns, dt=args.dt),
                                model, args)
                for pth in args.validate or []]      # a bad file refused before the fit
    _check_judging(args, vals)
    params = (parse_params(args.params, model) if args.params
              else default_params(args.model, model, "estimate",
                                  parse_pairs(args.fixed, "--fixed")))
    check_not_fixed(params, parse_pairs(args.fixed, "--fixed"))   # before any work
    stems = "_".join(Path(pth).stem for pth in paths)
    folder = output_folder(default_out(args, f"estimate_{model.name}_{stems}", "estimate"),
                           args, overwrite=args.overwrite or args.resume)
    ck = (Path(args.checkpoint) if args.checkpoint
          else folder.work_dir(create=False) / "checkpoint.npz")
    states = estimated_states(model, args)
    chosen = [_chosen_at_start(args, problem_from_args(model, exp, args), params, states,
                               _say_for(pth, paths))
              for pth, exp in zip(paths, exps)]
    states = filter_initial_states(args, chosen, states)
    if args.fit == "sim":
        if len(paths) > 1:
            raise UsageError("--fit sim fits one record: give one --data, or leave --fit out "
                             "(the likelihood fits several records together)")
        code = run_output_error(args, chosen[0], params, folder, states)
        judged_elsewhere(args, vals, folder.path)
        return code
    fit = FitOptions(optimizer=args.optimizer, particles=args.particles,
                     iterations=args.iterations, seed=args.seed, checkpoint=ck,
                     resume=args.resume, polish=not args.no_polish, stall_iterations=args.stall,
                     progress=not args.quiet, workers=args.workers,
                     scheduler=args.scheduler)
    if not args.checkpoint:
        _prepare_checkpoint(folder, args.resume)
    try:
        res, problems = _fit(args, chosen, params, fit, states, paths)
    except EstimationError:
        if not args.checkpoint:
            folder.remove_work_dir()      # nothing worth resuming
        raise
    _record_paths(res, paths)
    _glitches(model, res, problems, paths)

    def version(d: Path) -> list:
        pngs = [] if args.no_plots else _plots(model, exps, res, problems, paths, d)
        if ck.exists():
            shutil.copyfile(ck, d / "checkpoint.npz")
        res.to_json(d / "result.json")          # last: its presence means complete
        return pngs
    pngs = folder.publish(version)
    if not args.checkpoint:
        folder.remove_work_dir()
    _print_table(res)
    for pth in [folder.path / "result.json", *published(folder, pngs)]:
        print(f"wrote {pth}")
    free_run_lines(args, exps, folder.path / "result.json")
    judged_elsewhere(args, vals, folder.path)
    return 0


def _record_paths(res, paths) -> None:
    """The records of the fit in ``res.settings``: ``data`` as given, and
    for one record ``data_path``, its absolute path, by which ``bondgraph
    compare`` finds the record the estimated initial states belong to
    (:func:`bondgraph.export.params.read_initial_states`)."""
    res.settings["data"] = str(paths[0]) if len(paths) == 1 else [str(p) for p in paths]
    if len(paths) == 1:
        res.settings["data_path"] = str(Path(paths[0]).resolve())


def _print_table(res) -> None:
    """The estimate's table; where it was refitted, a line with the
    estimation's fits, evaluations and seconds in all (the table counts the
    last fit's: ``settings["estimation_work"]``, :func:`_fit`)."""
    print(res.table())
    work = res.settings.get("estimation_work")
    if work:
        print(f"the estimation in all: {work['fits']} fits (the search, its refits where the "
              f"discretisation or the input hold changed at the estimate), "
              f"{work['evaluations']} evaluations, {work['wall_s']:.1f} s; the line above "
              f"counts the last fit's")


def _glitches(model, res, problems, paths) -> None:
    """Isolated outliers in the innovations at the estimate, on each record
    (:func:`~bondgraph.diagnose.residuals.innovation_outlier_warnings`: a
    sensor's single-sample glitches inflate the estimated noise level and
    every std), added to ``res.warnings`` (the table, result.json). One
    filter pass per record; nothing when the fit failed."""
    from bondgraph.diagnose.residuals import innovation_outlier_warnings
    from bondgraph.inference.ukf import ukf_nll
    from bondgraph.report.estimation import filter_of

    if not np.isfinite(res.nll):
        return
    for pth, pb in zip(paths, problems):
        x0, P0, R = filter_of(model, res, np.asarray(pb.x0, float), np.asarray(pb.P0, float))
        t, u, y = pb.arrays
        try:
            with np.errstate(all="ignore"):
                r = ukf_nll(model, t, u, y, res.theta[None, :], x0, P0, options=pb.ukf, R=R,
                            store=True)
        except (NumericalError, FloatingPointError, np.linalg.LinAlgError):
            continue
        where = Path(pth).name if len(paths) > 1 else ""
        res.warnings += innovation_outlier_warnings(r, model.outputs, t, where)
        res.warnings += absorbing_warnings(model, pb, res, r, where)


def absorbing_warnings(model, problem, res, run, where: str = "") -> list[str]:
    """A warning per state whose process noise absorbs the model's error at
    the estimate (:func:`bondgraph.diagnose.fit.absorbing_states`: its
    intensity grew more than threefold from the start and its random walk
    over the record exceeds the state's filtered spread): the likelihood
    then explains the record by noise and the physical parameters need not
    fit it (a user's two tanks: the upper tank's noise 69-fold up, the
    sensor noise on its floor, the pump gain 0.139 against the output-error
    fit's 0.070).
    ``run``: the stored filter run at the estimate on ``problem``'s record."""
    from bondgraph.diagnose.fit import absorbing_states

    x = getattr(run, "x_filt", None)
    t = problem.arrays[0]
    if x is None or len(t) < 2:
        return []
    x = np.asarray(x)
    spread = np.array([float(np.nanstd(x[:, 0, i])) for i in range(x.shape[2])])
    found = absorbing_states(model, problem.theta, res.theta, spread, float(t[-1] - t[0]))
    on = f" on {where}" if where else ""
    return [f"{msg}{on}: the estimates are those of a model the noise explains, not of one "
            f"that simulates the record (--fit sim fits the free run; bondgraph loop fits and "
            f"judges by it where the noise absorbs the error)" for _, msg in found]


def _check_judging(args, vals) -> None:
    """Refuse ``--init-samples`` without ``--validate``, or a window that
    leaves a ``--validate`` record too few samples, before the fit.

    Raises
    ------
    UsageError, OptionError
    """
    from bondgraph.diagnose.compare import check_window

    if args.init_samples and not vals:
        raise UsageError("--init-samples sets where the free run on a --validate record starts; "
                         "give --validate FILE, or leave --init-samples out")
    check_window(vals, args.init_samples)


def judged_elsewhere(args, vals, out: Path) -> None:
    """The estimate (``out/result.json``) judged on the records of
    ``--validate`` (``vals``, loaded before the fit), as ``bondgraph
    compare`` judges a model (:func:`bondgraph.diagnose.compare.compare`:
    the free run from the record's own initial state, else the smoothed
    one, or from its first ``--init-samples`` samples; the fit's noise
    levels): its table and warnings, and compare.json, a CSV and a plot per
    record in ``out/validation``. Without ``--validate``, the line that
    says how. The estimate is already published: a failure here is one
    line."""
    from bondgraph.cli.compare import _warnings, publish, table

    result = out / "result.json"
    if not vals:
        print(f"on a record it was not fitted to: bondgraph compare {args.model} --data OTHER.csv"
              f"{reading_options(args)} --params {result} (or --validate OTHER.csv here)")
        return
    try:
        comps, values = _compared(args, vals, result, args.init_samples, progress=not args.quiet)
    except (BondGraphError, FloatingPointError, np.linalg.LinAlgError) as exc:
        print(f"the records of --validate: not judged ({str(exc).splitlines()[0]})")
        return
    print("the estimate on the records it was not fitted to (--validate):")
    print(table(comps))
    _warnings([("", c) for c in comps])
    doc = {"model": args.model, "params": str(result), "values": values,
           "init_samples": args.init_samples, "records": [c.to_json() for c in comps]}
    publish(output_folder(out / "validation", args, overwrite=True), doc,
            SimpleNamespace(data=args.validate, no_plots=args.no_plots),
            [(c, None) for c in comps])


def _compared(args, records, result: Path, init_samples: int = 0,
              progress: bool = False) -> tuple[list, dict]:
    """``(comparisons, values)``: the model at the estimate (``result``'s
    values and noise levels) run freely over ``records`` by
    :func:`bondgraph.diagnose.compare.compare`, the prior's state scales from
    the declared graph as the fit took them.

    Raises
    ------
    BondGraphError, FloatingPointError, numpy.linalg.LinAlgError
    """
    from bondgraph.diagnose.compare import compare
    from bondgraph.export.params import model_graph, read_noise_levels, read_params

    values = read_params(result)
    comps = compare(model_graph(args.model, values), records, noise=read_noise_levels(result),
                    init_samples=init_samples, scales_from=model_graph(args.model),
                    log=lambda _m: None, progress=progress)
    return comps, values


def free_run_lines(args, exps, result: Path) -> None:
    """How the estimate simulates: one line per fitted record with its
    free-run error (:func:`bondgraph.diagnose.compare.compare`, from the
    smoothed start as the loop judges a record), and a warning where the
    mean NRMSE reaches :data:`~bondgraph.diagnose.screen.SCREEN_LEVEL`: a
    likelihood fit can explain a record by its noise levels and leave a
    model that does not follow it (a user's CED graph: NRMSE 0.99, fit
    1 %). The estimate is already published; a failure here is one line."""
    from bondgraph.diagnose.screen import SCREEN_LEVEL

    try:
        comps, _ = _compared(args, exps, result)
    except (BondGraphError, FloatingPointError, np.linalg.LinAlgError) as exc:
        print(f"free run at the estimate: not computed ({str(exc).splitlines()[0]})")
        return
    for c in comps:
        errs = ", ".join(f"{o} {r:.4g}{' ' + u if u else ''} (fit {f:.1f} %)"
                         for o, u, r, f in zip(c.outputs, c.units, c.rms, c.fit_percent)
                         if np.isfinite(r))
        print(f"free run at the estimate on {c.record}: RMS error {errs}; NRMSE {c.metric:.4g}")
        if c.metric >= SCREEN_LEVEL:
            print(f"WARNING: the estimate does not simulate {c.record} (NRMSE {c.metric:.3g} >= "
                  f"{SCREEN_LEVEL}): the noise levels explain it; the model lacks an effect "
                  f"(`bondgraph loop` looks for it) or its parameters are in another basin "
                  f"(`--fit sim` fits the free run)")


def _chosen_at_start(args, problem, params, states, say, *, hold: str | None = None,
                     why: str | None = None, where: str = "at the start θ"):
    """:func:`~bondgraph.cli.common.chosen_at_levels` for the estimation
    of ``params`` (with the initial states ``states``): the start's
    discretisation checked against the noise levels profiled there. The
    estimate is checked again with its own levels (:func:`_refined`): a
    fit that gets closer than the start's misfit refits with a finer
    step. ``--fit sim`` estimates no level: the first choice stands."""
    with progress.phase(f"choosing the filter's discretisation {where}"):
        return chosen_at_levels(args, problem, params, states, say, hold=hold, why=why,
                                where=where, profile=args.fit != "sim")


def _say_for(path, paths):
    """The log of one record's lines: prefixed with its file's name when
    there are several records."""
    if len(paths) == 1:
        return _say
    return lambda msg: _say(f"{Path(path).name}: {msg}")


def _plots(model, exps, res, problems, paths, d: Path) -> list:
    """The fit plots (:func:`plot_fit`): one pair per record, prefixed with
    the record's file name when there are several."""
    with progress.phase("drawing the fit plots (a filter pass per record)"):
        if len(exps) == 1:
            return list(plot_fit(model, exps[0], res, d, P0=problems[0].P0))
        out = []
        for pth, exp, pb in zip(paths, exps, problems):
            out += plot_fit(model, exp, res, d, x0=pb.x0, P0=pb.P0, options=pb.ukf,
                            prefix=f"{Path(pth).stem}_")
        return out


#: refits of an estimate after its discretisation failed at the estimate
MAX_REFITS = 3


def _fit(args, chosen, params, fit, states, paths):
    """``(result, problems)``: the estimation on the records' problems
    ``chosen`` (``(problem, choice)`` each), refined where its
    discretisation fails at the estimate (:func:`_refined`); where an
    input's hold was chosen by an ambiguous shape, the fit under the other
    hold too, and the likelier kept (:func:`_likelier_hold`)."""
    log = None if args.quiet else _say
    problems = [pb for pb, _ in chosen]
    t0, token = time.perf_counter(), _SPENT.set([])
    try:
        res = _estimate_quiet(problems, params, fit, states, log)
        res, problems, agains = _refined(args, chosen, problems, res, params, fit, states, paths)
        res, problems, chosen, agains = _likelier_hold(args, chosen, problems, res, agains,
                                                       params, fit, states, paths)
        _hold_checked(args, chosen, problems, res, params, fit, states)
        spent = _SPENT.get()
    finally:
        _SPENT.reset(token)
    if len(spent) > 1:
        res.settings["estimation_work"] = dict(fits=len(spent), evaluations=int(sum(spent)),
                                               wall_s=round(time.perf_counter() - t0, 2))
    given = discretisation_given(args)
    choices = [dict(given=given, start=None if c is None else c.to_dict(),
                    estimate=None if a is None else a.to_dict())
               for (_pb, c), a in zip(chosen, agains)]
    res.settings["discretisation_choice"] = choices[0] if len(choices) == 1 else choices
    return res, problems


def _refined(args, chosen, problems, res, params, fit, states, paths):
    """``(result, problems, choices at the estimate)``: where the
    discretisation was chosen (``choice`` of ``chosen``), checked again at
    the estimate (with the fit's noise levels) and, if the chosen one fails
    there on a record, refitted from the estimate with the one chosen at the
    estimate (a local refit: the swarm's first population with the estimate
    in it, then the polish; the result, and its warnings, are then the
    refit's), checked again, at most :data:`MAX_REFITS` times (the estimate
    may move to where the new one fails too: a fast lag's time constant on
    its box). From the second check on, the estimate's drift between the
    last two fits is taken into account (:func:`heading`): each refit had
    moved the estimate to where the next finer step failed again. Where the
    NLL guard failed instead (:func:`_guard_choice`), the whole search runs
    again with the finer step: the estimate lived on the coarse step's
    error and is no start."""
    problems = list(problems)
    agains: list = [None] * len(chosen)
    before = None       # the estimate of the fit before the last refit
    # a local refit: the estimate moves by the discretisation's bias only
    # (the swarm's first population, the whole estimate (noise levels,
    # initial states too) in it, then the polish; a second full search cost
    # as much as the first)
    local = replace(fit, resume=False, iterations=0) if fit.polish else replace(fit, resume=False)
    for _ in range(MAX_REFITS):
        refit, anew = False, False
        for i, (_pb, choice) in enumerate(chosen):
            if choice is None or not np.isfinite(res.nll):
                continue
            ahead = None if before is None else heading(problems[i].model, before, res.theta)
            with progress.phase("checking the filter's discretisation at the estimate"):
                agains[i], redo = _recheck(args, problems[i], res, _say_for(paths[i], paths),
                                           ahead, why=choice.hold_reason)
            if redo:
                problems[i], refit = problems[i].conditioned_on(disc=agains[i].disc), True
                anew = anew or redo == "anew"
        if not refit:
            break
        before = res.theta
        steps = ", ".join(sorted({pb.disc.describe() for pb in problems}))
        if anew:        # the estimate lived on the step's error: no start to polish
            with progress.phase(f"estimating again with {steps} (the search anew)"):
                res = _estimate_quiet(problems, params, replace(fit, resume=False), states,
                                      None)
        else:
            with progress.phase(f"refitting from the estimate with {steps}"):
                res = _estimate_quiet(problems, params, local, states, None,
                                      start=res.estimates)
    return res, problems, agains


def _likelier_hold(args, chosen, problems, res, agains, params, fit, states, paths):
    """``(result, problems, chosen, choices at the estimate)``: where an
    input's hold was chosen by its shape without clear evidence
    (:func:`~bondgraph.inference.discretise.alternative_hold`: a sequence that
    jumps from sample to sample may be a held command or a sampled
    continuous signal with noise) and the user gave no ``--hold``, the same
    estimation again under the other hold (the discretisation chosen for it
    at the start, refined at its estimate), and the fit with the lower NLL
    kept (by more than :data:`~bondgraph.inference.discretise.HOLD_MARGIN`;
    else the shape's). Two lines say why and which; a fit under the other
    hold that fails keeps the first.
    Without an ambiguous input: the arguments."""
    alts = [None if c is None else alternative_hold(c.inputs, pb.disc.hold)
            for pb, c in chosen]
    if "hold" in discretisation_given(args) or not np.isfinite(res.nll) \
            or all(a is None for a in alts):
        return res, problems, chosen, agains
    vague = sorted({h.describe() for _pb, c in chosen if c is not None
                    for h in c.inputs if h.ambiguous})
    _say(f"input hold: the shape does not settle it ({'; '.join(vague)}): fitting under the "
         f"other hold too, the likelihood decides (--hold to choose)")
    why = "the likelihood of the fits under both holds (the shape is ambiguous)"
    other = []
    for (pb, c), alt, pth in zip(chosen, alts, paths):
        if alt is None:
            other.append((pb, c))
            continue
        other.append(_chosen_at_start(args, pb, params, states, _say_for(pth, paths),
                                      hold=alt, why=why, where="at the start θ, the other hold"))
    try:
        with progress.phase("estimating under the other input hold"):
            res2 = _estimate_quiet([pb for pb, _ in other], params,
                                   replace(fit, checkpoint=None, resume=False), states,
                                   None if args.quiet else _say)
        res2, problems2, agains2 = _refined(args, other, [pb for pb, _ in other], res2, params,
                                            fit, states, paths)
    except (EstimationError, NumericalError, np.linalg.LinAlgError) as exc:
        _say(f"input hold: the fit under the other hold failed ({exc}); the shape's kept")
        return res, problems, chosen, agains
    mine = "/".join(sorted({pb.disc.hold for pb in problems}))
    theirs = "/".join(sorted({pb.disc.hold for pb in problems2}))
    better, line = hold_verdict(theirs, res2.nll, mine, res.nll, note="(each fitted)")
    _say(line)
    if not better:
        return res, problems, chosen, agains
    return res2, problems2, other, agains2


def _hold_checked(args, chosen, problems, res, params, fit, states) -> None:
    """Each input whose hold its shape chose clearly on every record (not
    declared, not ambiguous: those fits were compared already) held the
    other way, the estimate refitted from itself (the swarm's first
    population with the estimate in it, then the polish; the step chosen
    for that hold at the estimate), and a warning in ``res.warnings`` (the
    table, result.json) when the record is likelier so by more than
    :data:`~bondgraph.inference.discretise.HOLD_CHECK_MARGIN` nats. The
    result is not changed: a model that lacks an effect can be likelier
    under the wrong hold (a choke without its core's saturation, driven by
    held voltage steps, was likelier under linear), which ``bondgraph loop``
    tells apart by checking at its final model. Nothing when ``--hold`` is
    given or the fit failed."""
    if "hold" in discretisation_given(args) or not np.isfinite(res.nll) \
            or any(c is None for _pb, c in chosen):
        return
    model = problems[0].model
    levels = res.settings.get("noise_levels") or {}
    sigma = [float((levels.get(o) or {}).get("std", np.nan)) for o in model.outputs]
    local = replace(fit, checkpoint=None, resume=False,
                    **({"iterations": 0} if fit.polish else {}))
    for j, name in enumerate(model.inputs):
        evidence = [c.inputs[j] for _pb, c in chosen]
        holds = [list(split_hold(pb.disc.hold, model.n_u)) for pb in problems]
        mine = {h[j] for h in holds}
        if any(h.source != "shape" or h.hold is None or h.ambiguous for h in evidence) \
                or len(mine) != 1 or not mine <= {"zoh", "linear"}:
            continue
        mine = mine.pop()
        flipped = "linear" if mine == "zoh" else "zoh"
        why = f"the likelihood under the other hold of '{name}'"
        try:
            with progress.phase(f"refitting with input '{name}' held {flipped} (the hold check)"):
                other = []
                for pb, h in zip(problems, holds):
                    hold = join_hold(h[:j] + [flipped] + h[j + 1:])
                    c = choose_discretisation(pb, res.theta, sigma=sigma, hold=hold, why=why)
                    other.append(pb.conditioned_on(disc=c.disc))
                res2 = _estimate_quiet(other, params, local, states, None, start=res.estimates)
        except (EstimationError, NumericalError, OptionError, np.linalg.LinAlgError) as exc:
            _say(f"input hold of '{name}': the fit under the {flipped} hold failed "
                 f"({str(exc).splitlines()[0]}); not compared")
            continue
        better = hold_verdict(flipped, res2.nll, mine, res.nll, margin=HOLD_CHECK_MARGIN)[0]
        _say(hold_check_line(name, "at the estimate", flipped, res2.nll, mine, res.nll, better))
        if not better:
            continue
        std = {p: float(v) for p, v in zip(res.params, res.std)}
        moves = moved_most(res.params, res2.estimate_dict(), res.estimate_dict(), std)
        res.warnings.append(other_hold_warning(
            name, flipped, mine, res2.nll, res.nll, "refitted from the estimate", moves,
            f"If so, declare its hold (the record's sidecar: columns.{name}.hold = "
            f"\"{flipped}\") or give --hold "
            f"{join_hold(holds[0][:j] + [flipped] + holds[0][j + 1:])}; "
            f"if not, the model may lack an effect that the other hold imitates: `bondgraph "
            f"loop` checks the hold at its final model"))


def heading(model, before: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Where an estimate that moved from ``before`` to ``theta`` (both
    (n_theta,)) is heading: one more step of the same kind, by the same
    factor where both values are positive (a time constant shrinking
    towards its box keeps its sign), else by the same difference, inside
    the parameters' boxes."""
    b, t = np.asarray(before, float), np.asarray(theta, float)
    with np.errstate(all="ignore"):
        nxt = np.where((b > 0) & (t > 0), t * (t / np.where(b > 0, b, 1.0)), 2 * t - b)
    nxt = np.where(np.isfinite(nxt), nxt, t)
    return np.clip(nxt, model.lower, model.upper)



def _recheck(args, problem, res, say, ahead: np.ndarray | None = None, why: str | None = None):
    """``(choice at the estimate, refit)``: the discretisation chosen at
    the estimate with its noise levels; ``refit`` True (a refit from the
    estimate) when the start's fails there and another was chosen,
    ``"anew"`` (the search again) when it passes but the NLL guard names
    finer substeps (:func:`_guard_choice`), else False (one line on
    ``say`` either way). With
    ``ahead`` (:func:`heading`, after a refit that failed again), the
    choice there is taken instead when it is finer and also meets the check
    at the estimate: the refit then need not chase the estimate (a user's
    fuel-flow lag of 1 s shrinking towards 0.05 s on 1 Hz records: rk4(1),
    (2), (3), (4) each failed at the next estimate). The problem's hold is
    kept (``why`` its reason)."""
    levels = res.settings.get("noise_levels") or {}
    sigma = [float((levels.get(o) or {}).get("std", np.nan)) for o in problem.model.outputs]
    given = discretisation_given(args)
    hold = dict(hold=problem.disc.hold, why=why)
    again = choose_discretisation(problem, res.theta, given=given, sigma=sigma, **hold)
    ok, now, bound = check_discretisation(problem, res.theta, sigma=again.sigma)
    if ok:
        guarded = _guard_choice(problem, res, given, sigma, hold, now, say)
        if guarded is not None:
            return guarded, "anew"
    if not ok and again.disc != problem.disc:
        now_text = step_error(problem.disc.method, now, "σ per sample")
        why = (f"the start's {problem.disc.describe()} fails {{}}: {now_text}, "
               f"bias bound {bound:.2g} std; refitting from the estimate")
        further = _choice_ahead(problem, ahead, given, sigma, res.theta, again, hold)
        if further is None:
            say(again.line(f"at the estimate ({why.format('there')})"))
            return again, True
        say(further.line(f"where the estimate is heading, the way it moved with the last refit "
                         f"({why.format('at the estimate')})"))
        return further, True
    say(f"discretisation at the estimate: {problem.disc.describe()} still within "
        f"({now:.2g} σ per sample" + (f", free-run bias bound {bound:.2g} std)"
                                     if np.isfinite(bound) else ")")
        if ok else again.line("at the estimate (no better candidate)"))
    return again, False


def _guard_choice(problem, res, given: dict, sigma, hold: dict, now: float, say):
    """The discretisation to refit with when the estimate's step passes its
    check (``now`` σ per sample) but the NLL guard
    (:func:`bondgraph.inference.ukf.nll_guard`, in ``res.settings``) finds
    its NLL more than 1e-3 relative from RK4(40)'s and names the substeps
    that agree: the filter's covariance propagation, not the free run that
    the check follows, feels the step. A user's CED graph on its PRBS
    record: RK4(1) passed at 0.0016 σ per sample, its NLL 535.65 against
    1444.67 with 2 substeps: an estimate that lived on the step's error
    (a stiff armature mode whose covariance RK4(1) decays too slowly, a
    process noise the graph does not have); the search runs again with it
    (:func:`_refined`), not from that estimate. None when the guard agrees,
    names no substeps, or the user gave ``--substeps``; one line on
    ``say`` otherwise."""
    guard = (res.settings.get("discretisation") or {}).get("nll_guard") or {}
    needed = guard.get("substeps_needed")
    if guard.get("ok", True) or not needed or "substeps" in given:
        return None
    fixed = dict(given, method=problem.disc.method, substeps=int(needed))
    try:
        choice = choose_discretisation(problem, res.theta, given=fixed, sigma=sigma, **hold)
    except (OptionError, FloatingPointError, np.linalg.LinAlgError, NumericalError):
        return None
    if choice.disc == problem.disc:
        return None
    choice = replace(choice, given=dict(given))
    say(choice.line(f"at the estimate (the start's {problem.disc.describe()} passes its check, "
                    f"{now:.2g} σ per sample, but its NLL {guard['nll']:.6g} is "
                    f"{guard['rel_diff']:.2g} relative from {guard['reference']}'s "
                    f"{guard['nll_reference']:.6g}; an estimate that lives on the step's "
                    f"error: searching again)"))
    return choice


def _choice_ahead(problem, ahead, given, sigma, theta, again, hold: dict):
    """The discretisation chosen at ``ahead`` (with ``hold``: the problem's
    hold and its reason) when it is costlier than ``again`` (the choice at
    the estimate ``theta``) and meets the check at ``theta`` too, else None."""
    if ahead is None:
        return None
    try:
        further = choose_discretisation(problem, ahead, given=given, sigma=sigma, **hold)
        if not further.ok or cost_rank(further.disc) <= cost_rank(again.disc):
            return None
        ok = check_discretisation(problem, theta, further.disc, sigma=again.sigma)[0]
    except (FloatingPointError, np.linalg.LinAlgError, NumericalError):
        return None
    return further if ok else None


#: the evaluations of each :func:`_estimate_quiet` of the running :func:`_fit`
#: (its search, the refits at the estimate's discretisation, the other input hold)
_SPENT: contextvars.ContextVar = contextvars.ContextVar("bondgraph_estimate_spent",
                                                        default=None)


def _estimate_quiet(problem, params, fit, states, log, start=None):
    """:func:`estimate` without its :class:`IdentifiabilityWarning` s (the
    table prints the result's warnings); its evaluations counted in
    :data:`_SPENT` while :func:`_fit` runs."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        one = problem[0] if isinstance(problem, list) and len(problem) == 1 else problem
        res = estimate(one, params, fit=fit, x0_states=states, log=log, start=start)
    spent = _SPENT.get()
    if spent is not None:
        spent.append(int(res.evaluations_total))
    return res


def _say(msg: str) -> None:
    """A log line of the estimation (the noise policy) on stderr."""
    print(msg, file=sys.stderr, flush=True)


def _prepare_checkpoint(folder, resume: bool) -> None:
    """Create the working folder of the default checkpoint
    ``.OUT.work/checkpoint.npz``; with ``--resume`` and no such file, the
    published ``OUT/checkpoint.npz`` of a finished run is copied there."""
    ck = folder.work_dir() / "checkpoint.npz"
    done = folder.path / "checkpoint.npz"
    if resume and not ck.exists() and done.exists():
        shutil.copyfile(done, ck)


def _without_noise_levels(problem, params: list[str]) -> list[str]:
    """``params`` less the noise levels (process-noise intensities, sensor
    noise stds: :func:`~bondgraph.inference.estimand.noise_parameters`),
    which the output-error criterion does not see: the least-squares fit
    moved them anywhere (a user's tanks: a process-noise intensity from 0.01
    to 0.69, printed as an estimate). One line says they are held."""
    noise = set(noise_parameters(problem.model, problem.theta))
    held = [p for p in params if p in noise]
    if held:
        vals = ", ".join(f"{p} = {problem.theta[problem.model.param_index(p)]:.4g}" for p in held)
        _say(f"--fit sim: {', '.join(held)} are noise levels, which the free-run criterion does "
             f"not see: held ({vals}); the RMS free-run error is reported as the noise level")
    return [p for p in params if p not in noise]


def run_output_error(args, chosen, params, folder, states) -> int:
    """``--fit sim``: the output-error fit
    (:func:`bondgraph.inference.output_error.output_error_fit`) on
    ``chosen`` = ``(problem, choice)`` from the model's defaults with
    ``--fixed`` and ``--x0``, the initial states of ``--estimate-x0``
    estimated too (:func:`_sim_fit`; under both holds where an input's shape
    is ambiguous, :func:`_likelier_sim`); writes ``result.json``. The
    output-error criterion needs no noise level: ``--noise`` only decides
    what is reported (the declared levels, or the RMS free-run error as the
    estimate of an undeclared one)."""
    problem, states = sim_initial_states(*chosen[:1], states)
    params = _without_noise_levels(problem, params)
    r, problem = _likelier_sim(args, problem, chosen[1], params, states)
    model, exp, theta = problem.model, problem.record, problem.theta
    noise = _sim_noise_levels(model, exp, r, theta, problem.noise.mode)
    doc = {"model": model.name, "data": str(args.data), "fit": "sim", "names": r.names,
           "estimates": r.estimates(), "fixed": dict(problem.fixed), "std": r.std, "at_bound": r.at_bound, "cost": r.cost,
           "rmse": dict(zip(model.outputs, r.rmse.tolist())), "nfev": r.nfev,
           "status": r.status, "message": r.message, "noise": args.noise,
           "noise_levels": noise, "hold": problem.disc.hold, "warnings": list(r.warnings)}
    text = json.dumps(to_jsonable(doc), indent=2, allow_nan=False)
    folder.publish(lambda d: (d / "result.json").write_text(text))
    rpath = folder.path / "result.json"
    for n in r.names:
        sd = r.std.get(n)
        print(f"{n:24s} {r.estimates()[n]:.6g}" + (f" ± {sd:.3g}" if sd is not None else
                                                    " (on a bound)" if n in r.at_bound else ""))
    print("free-run RMS error: " + ", ".join(f"{o} {v:.4g}" for o, v in
                                              zip(model.outputs, r.rmse)))
    print("noise levels: " + ", ".join(f"{o} {d['std']:.4g} ({d['how']})"
                                       for o, d in noise.items()))
    for w in r.warnings:
        print(f"warning: {w}")
    print(f"wrote {rpath}")
    return 0


#: at most this many unknown initial states are estimated with the parameters
#: by ``--fit sim`` (each is one more free run per Jacobian); beyond, the
#: free runs start from the prior mean and one line names ``--estimate-x0``
SIM_X0_MAX = 12


def sim_initial_states(problem, states: list[str]):
    """``(problem, states)`` of an output-error fit: the initial states that
    nothing gives (:meth:`~bondgraph.inference.prior.PriorSpec.unknown`: no
    state column, sidecar ``x0`` or ``--x0``) are estimated with the
    parameters, from the RTS-smoothed x̂_0|N at the start θ (Särkkä 2008;
    the prior mean where the smoother fails); one line says which. A free
    run from a guessed start carries its transient into the criterion: a
    fast lag at 1 Hz started at rest read a free-run RMS error (and an
    estimated noise level) of 0.040 where the noise was 0.020. More than
    :data:`SIM_X0_MAX` such states are left at the prior mean (one line
    names ``--estimate-x0``)."""
    model = problem.model
    unknown = [n for n in problem.prior.unknown(model, problem.record) if n not in states]
    if not unknown:
        return problem, states
    if len(unknown) > SIM_X0_MAX:
        _say(f"--fit sim: the record gives no initial value of {len(unknown)} states: the free "
             f"runs start from the prior mean ({problem.x0_rule}); --estimate-x0 NAMES "
             f"estimates them with the parameters")
        return problem, states
    try:
        xs = problem.smoothed_initial_state(problem.theta)
        start = "the RTS-smoothed x̂0|N at the start θ"
    except (NumericalError, FloatingPointError, np.linalg.LinAlgError):
        xs, start = problem.x0, "the prior mean (the smoother failed)"
    x0 = {n: float(xs[model.state_index(n)]) for n in unknown if np.isfinite(
        xs[model.state_index(n)])}
    start_x = problem.conditioned_on(x0=x0).x0 if x0 else problem.x0
    seen = _seen(problem, unknown, start_x)
    unseen = [n for n in unknown if n not in seen]
    _say(f"--fit sim: the record gives no initial value of {', '.join(unknown)}: "
         + (f"{', '.join(seen)} estimated with the parameters from {start}" if seen else "")
         + ("; " if seen and unseen else "")
         + (f"{', '.join(unseen)} not seen by the outputs (left at {start})" if unseen else "")
         + " (--x0 to give it)")
    return problem.conditioned_on(x0=x0), states + seen


def filter_initial_states(args, chosen: list, states: list[str]) -> list[str]:
    """``states`` and, for a likelihood fit of one record without
    ``--estimate-x0`` whose model declares no process noise, the initial
    states that nothing gives (no state column, sidecar ``x0`` or ``--x0``)
    and the outputs see (:func:`seen_initial_states`), estimated with θ
    (one line says which; ``--estimate-x0 none`` keeps them at the prior);
    ``states`` unchanged otherwise, or when there are more than
    :data:`SIM_X0_MAX` such states. ``bondgraph compare`` then starts from
    them on that record (:func:`bondgraph.export.params.read_initial_states`).

    Without process noise the filter's prediction is the free run, and it
    does not recover from its first updates through a nonlinear law from a
    guessed start (a linear filter would marginalise the unknown start
    exactly): a user's hydraulic record that starts under pressure, its
    hose's cubic stiffness half the pressure at the peaks, started from the
    model's X0 with the state's whole scale as prior std, read the sensor
    noise as 77 kPa (the truth 50 kPa; NLL 124713, the robust std 7 to 28
    times the Cramér-Rao std); with the initial states estimated, 50.3 kPa,
    NLL 122407.

    Parameters
    ----------
    args : argparse.Namespace
        The command's options (``fit``, ``estimate_x0``).
    chosen : list
        One ``(problem, ...)`` per record (:func:`_chosen_at_start`).
    states : list of str
        The initial states of ``--estimate-x0``.

    Returns
    -------
    list of str
    """
    if args.fit == "sim" or args.estimate_x0 or len(chosen) != 1:
        return states
    problem = chosen[0][0]
    model = problem.model
    if not no_process_noise(model, problem.theta):
        return states
    unknown = [n for n in problem.prior.unknown(model, problem.record) if n not in states]
    if not unknown or len(unknown) > SIM_X0_MAX:
        return states
    try:
        seen = _seen(problem, unknown, problem.x0)
    except (NumericalError, FloatingPointError, np.linalg.LinAlgError):
        return states
    if seen:
        _say(f"the record gives no initial value of {', '.join(seen)} and the model declares "
             f"no process noise (the filter predicts by the free run): estimated with the "
             f"parameters (--x0 NAME=VALUE gives one; --estimate-x0 none keeps the prior)")
    return states + seen


def _seen(problem, unknown: list[str], start_x) -> list[str]:
    """The states of ``unknown`` whose initial value ``problem``'s outputs
    see from ``start_x`` (:func:`seen_initial_states`, by the problem's own
    step and hold)."""
    d = problem.disc
    return seen_initial_states(problem.model, problem.t, problem.u, problem.theta, start_x,
                               unknown, method=d.method, substeps=d.substeps, hold=d.hold)


def _sim_fit(problem, params, states, given: bool = False, method_free: bool = True):
    """``(result, problem)``: the output-error fit of ``problem`` (its free
    runs as :func:`sim_options` says). Where the chosen step fails at the
    estimate (:func:`_sim_step_holds`: the estimate moved where the model is
    faster), the step is chosen again there and the fit continued from the
    estimate with it (:func:`_finer_step`; ROS2 where no RK4 step passes and
    ``method_free``), at most :data:`MAX_REFITS` times; LSODA with the
    forward sensitivities from the start when no step meets the check (a
    fast lag at 1 Hz: the command took 3 s where the LSODA fit took 43 s).
    With ``given`` (the user gave ``--substeps``) the step is kept and a
    failed check only said."""
    t, u, y = problem.arrays
    r = output_error_fit(problem.model, t, u, y, params, theta=problem.theta, x0=problem.x0,
                         x0_states=states, options=sim_options(problem.disc))
    for i in range(MAX_REFITS + 1):
        if _sim_step_holds(problem, params, r, given):
            return r, problem
        finer = None if i == MAX_REFITS else _finer_step(problem, params, r, method_free)
        if finer is None:
            break
        _say(f"--fit sim: continuing from the estimate with {finer.describe()}")
        problem = problem.conditioned_on(disc=finer)
        r = output_error_fit(problem.model, t, u, y, params, theta=r.theta, x0=r.x0,
                             x0_states=states, options=sim_options(finer))
    _say(f"--fit sim: no {'RK4 or ROS2' if method_free else problem.disc.method.upper()} "
         f"step meets its check at the estimate: refitting with LSODA and the forward "
         f"sensitivities")
    return output_error_fit(problem.model, t, u, y, params, theta=problem.theta, x0=problem.x0,
                            x0_states=states, options=OutputErrorOptions(hold=problem.disc.hold)
                            ), problem


def _finer_step(problem, params, r, method_free: bool = True):
    """The discretisation (the problem's hold) that
    :func:`~bondgraph.inference.discretise.choose_discretisation` chooses at
    the output-error estimate ``r``: with the problem's method and more
    substeps, else (``method_free``: the user gave no ``--method``) the
    other method (ROS2 where the model became stiff); None when none meets
    the check."""
    th = _estimate_theta(problem, params, r)
    tries = [{"method": problem.disc.method}] + ([{}] if method_free else [])
    for given in tries:
        try:
            c = choose_discretisation(problem, th, given={**given, "hold": problem.disc.hold},
                                      free_run=True)
        except (FloatingPointError, np.linalg.LinAlgError, NumericalError):
            return None
        if c.ok and c.disc != problem.disc:
            return c.disc
    return None


def _estimate_theta(problem, params, r) -> np.ndarray:
    """The full θ (n_theta,) at the output-error estimate ``r``."""
    est = r.estimates()
    return problem.model.expand_theta(list(params), np.array([[est[p] for p in params]]),
                                      problem.theta)[0]


def _likelier_sim(args, problem, choice, params, states):
    """``(result, problem)``: the output-error fit (:func:`_sim_fit`); where
    an input's hold was chosen by an ambiguous shape
    (:func:`~bondgraph.inference.discretise.alternative_hold`) and no
    ``--hold`` given, the fit under the other hold too (its discretisation
    chosen at the start), and the one whose output-error likelihood
    (:func:`~bondgraph.inference.output_error.output_error_nll`) is lower by
    more than :data:`~bondgraph.inference.discretise.HOLD_MARGIN` kept (else the shape's,
    :func:`~bondgraph.inference.discretise.hold_verdict`); a fit under the
    other hold that fails keeps the first. Two lines say why and which."""
    given = "substeps" in discretisation_given(args)
    free = "method" not in discretisation_given(args)
    r, fitted = _sim_fit(problem, params, states, given, free)
    alt = None if choice is None else alternative_hold(choice.inputs, problem.disc.hold)
    if alt is None or "hold" in discretisation_given(args):
        return r, fitted
    vague = "; ".join(h.describe() for h in choice.inputs if h.ambiguous)
    _say(f"input hold: the shape does not settle it ({vague}): fitting under the other hold "
         f"too, the output-error likelihood decides (--hold to choose)")
    why = "the output-error likelihood of the fits under both holds (the shape is ambiguous)"
    other, _ = chosen_problem(problem, args, where="at the start θ, the other hold", hold=alt,
                              why=why)
    try:
        r2, other = _sim_fit(other, params, states, given, free)
    except (NumericalError, np.linalg.LinAlgError, FloatingPointError) as exc:
        _say(f"input hold: the fit under the other hold failed ({exc}); the shape's kept")
        return r, fitted
    y = problem.arrays[2]
    mine, theirs = output_error_nll(y, r.rmse), output_error_nll(y, r2.rmse)
    better, line = hold_verdict(other.disc.hold, theirs, fitted.disc.hold, mine,
                                criterion="output-error likelihood", note="(each fitted)")
    _say(line)
    return (r2, other) if better else (r, fitted)


def sim_options(disc) -> OutputErrorOptions:
    """The free runs of ``--fit sim``: compiled fixed-step runs of the
    chosen (or given) method, RK4 or ROS2 (a stiff model), at 4 times its
    substeps with forward-difference Jacobians, as the loop's free runs
    (the forward sensitivities by LSODA took over 15 min on the 65 062
    Silverbox samples, the compiled runs 1.2 s), checked at the estimate
    (:func:`_sim_step_holds`); four times finer divides the checked one-step
    error by 256 (RK4) or 16 (ROS2). The input hold is the filter's."""
    return OutputErrorOptions(hold=disc.hold, substeps=4 * int(disc.substeps),
                              fixed_method=disc.method)


def _sim_step_holds(problem, params, r, given: bool = False) -> bool:
    """Does the chosen step still meet its check (one-step error and
    free-run bias bound, :func:`check_discretisation`) at the output-error
    estimate ``r``? The fit's runs took 4 times its substeps, within
    whenever it is; if not (the estimate moved where the model is faster),
    one line says so. With ``given`` (the step is the user's) True after
    that line, kept in ``r.warnings`` (result.json, the table): the user's
    options win, and the result says what it rests on."""
    ok, now, bound = check_discretisation(problem, _estimate_theta(problem, params, r),
                                          free_run=True)
    if not ok:
        line = (f"--fit sim: {problem.disc.describe()} fails its check at the estimate "
                f"({step_error(problem.disc.method, now, 'σ per sample')}, free-run bias bound "
                f"{bound:.2g} std)"
                + ("; the given --substeps kept (leave it out to have the step chosen again "
                   "at the estimate): the estimates and their std rest on it" if given else ""))
        _say(line)
        if given:
            r.warnings.append(line)
    return ok or given


def _sim_noise_levels(model, exp, r, theta, mode: str) -> dict:
    """Output -> ``{"std", "how"}`` reported by the output-error fit: the
    record's declaration (``declared``), else with ``--noise auto`` the RMS
    free-run error (``estimated``: the output-error estimate of the noise std
    when the model is right), else the model's sensor noise (``model``)."""
    declared = exp.noise_std_for(model)
    meas = np.asarray(model.meas_std(np.asarray(theta, float)[None, :]), float)[0]
    out = {}
    for j, o in enumerate(model.outputs):
        if mode == "auto" and np.isfinite(declared[j]):
            out[o] = dict(std=float(declared[j]), how="declared")
        elif mode == "auto":
            out[o] = dict(std=float(r.rmse[j]), how="estimated")
        else:
            out[o] = dict(std=float(meas[j]), how="model")
    return out
