"""``bondgraph loop``, the main job: trace the residuals of a fitted model to
effects the model lacks, add them, re-estimate, and report the error before
and after. Without ``--model`` it runs a bundled case (default
``vehicle_aero``)."""

from __future__ import annotations

import argparse
import dataclasses
import re
import shutil
from pathlib import Path
from types import SimpleNamespace

from bondgraph.cli.common import (
    MODEL_HELP,
    Once,
    add_columns,
    add_discretisation,
    add_estimation_scope,
    add_overwrite,
    add_quiet,
    add_scheduler,
    decimated_window,
    discretisation_given,
    filtered_record,
    load_record,
    parse_names,
    parse_pairs,
    parse_params,
    reading_options,
    unused_folder,
)
from bondgraph.core import progress
from bondgraph.core.equations import derive
from bondgraph.diagnose.cases import get_case, registered_cases
from bondgraph.diagnose.effects import get_effect
from bondgraph.diagnose.effects.library import OPTIONAL_EFFECTS
from bondgraph.diagnose.loop import run_loop
from bondgraph.diagnose.result import moved_declared, moved_text, robust_of, understated
from bondgraph.diagnose.runner import chosen_numerics as loop_chosen_numerics, require_params
from bondgraph.diagnose.settings import (
    DEFAULT_HOLDOUT,
    AcceptRule,
    LoopSettings,
    SearchOptions,
)
from bondgraph.errors import ModelError, OptionError, UsageError
from bondgraph.export.params import model_graph, read_params
from bondgraph.inference.estimand import x0_state_names
from bondgraph.inference.options import UKFOptions
from bondgraph.inference.ukf_numba import compile_in_background
from bondgraph.numerics.registry import graph_builder
from bondgraph.report.loop_report import LoopReporter

#: the case run by ``bondgraph loop`` without arguments
DEFAULT_CASE = "vehicle_aero"
#: the report folder without ``--out`` (numbered when it holds an earlier report)
DEFAULT_OUT = "bondgraph-report"


#: what ``bondgraph loop`` says to a second ``--data``
ONE_RECORD = ("the loop fits one record; give another as the held-out --validate FILE, or fit "
              "several with `bondgraph estimate --data A --data B` and start the loop from its "
              "result with --from result.json")

#: the example line of ``bondgraph loop --help``
EXAMPLE = "bondgraph loop --model door.py:door --data door_push.csv --params J,k,c --out door-report"


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph loop``."""
    p.add_argument("--case", default=None,
                   help=f"bundled case (`--case list` lists them; default {DEFAULT_CASE} when "
                        f"no --model is given)")
    p.add_argument("--model", help=MODEL_HELP)
    p.add_argument("--data", action=Once, remedy=ONE_RECORD,
                   help="record (CSV in the experiment format, see docs/data_format.md)")
    add_columns(p)
    p.add_argument("--params", help="comma-separated parameters to estimate (default: the "
                                    "case's, or all parameters of the model; one declared "
                                    "without a box is then held at its value where the "
                                    "record cannot tell it from the others)")
    p.add_argument("--from", dest="from_result", default=None, metavar="JSON",
                   help="start values from a fit on another record: `bondgraph estimate`'s "
                        "result.json or a loop's report.json (its final fit); the parameters "
                        "not in --params are held at them; without --params, what the fit "
                        "estimated is re-estimated and the rest held (e.g. fitted on warm "
                        "records, the loop run on a cold start)")
    p.add_argument("--out", default=None,
                   help=f"report directory (default ./{DEFAULT_OUT}, or ./{DEFAULT_OUT}-2, -3, "
                        f"... when it holds an earlier report); refused when not empty, unless "
                        f"--overwrite")
    add_overwrite(p)
    p.add_argument("--metric", default=None,
                   help="error measure: nrmse_sim (default), rmse_sim, rmse_pred")
    p.add_argument("--criterion", choices=("aic", "bic"), default="aic")
    p.add_argument("--max-steps", type=int, default=None)
    p.add_argument("--significance", type=float, default=None)
    p.add_argument("--no-structural", action="store_true",
                   help="score only additive effects (faster)")
    p.add_argument("--no-replace", action="store_true",
                   help="after an accepted step, do not refit earlier effects' rivals at "
                        "their places (the replacement step)")
    _judging_options(p)
    add_estimation_scope(p)            # --fixed --x0 --p0-rel --p0 --estimate-x0 --noise
    p.set_defaults(p0_rel=None, noise=None, p0=None)   # the case's own P0 policy and noise
    p.add_argument("--fit", choices=("nll", "sim"), default=None,
                   help="declared fit: UKF likelihood (nll, default) or an output-error "
                        "(free-run least-squares) fit of the non-noise parameters first, "
                        "whose estimates start the likelihood fit (sim)")
    p.add_argument("--likelihood", choices=("auto", "one-step", "free-run"), default=None,
                   help="what the loop fits and judges by: the filter's one-step predictions "
                        "with the estimated process noise (one-step), or the free run's errors, "
                        "the process noise held at a floor (free-run); auto (default): "
                        "one-step unless the declared fit's process noise absorbs the model's "
                        "error")
    add_discretisation(p, chosen=False)          # with --backend
    p.set_defaults(method=None, substeps=None, hold=None)   # a case's own options unless given
    p.add_argument("--keep-going", action="store_true",
                   help="score effects even when the declared fit failed (physical parameters "
                        "that never left their start values or sit on their boxes) or breaks "
                        "passivity (an R law that produces power); by default the loop stops "
                        "there with exit code 2 and names them")
    p.add_argument("--add-effects", default=None, metavar="NAME,...",
                   help="effects of the library's optional part to score besides the default "
                        "library (bouc_wen)")
    p.add_argument("--skip-effects", default=None, metavar="NAME,...",
                   help="effects of the library not to score: names or patterns (sensor_* "
                        "when the sensors are calibrated: their offsets, gains and curves "
                        "are then not offered as look-alikes of a missing law, nor does "
                        "--discover seek a law at a sensor); `bondgraph models --effects` "
                        "lists the effects")
    p.add_argument("--discover", action="store_true",
                   help="when no physical effect is accepted, or the accepted ones leave "
                        "innovations that are not white: reconstruct the effort (flow) "
                        "missing at each 1- (0-) junction, discover its law from the port's "
                        "variables (sparse regression, passive terms only) and run the loop "
                        "again with it beside the library")
    p.add_argument("--workers", type=int, default=1,
                   help="local Dask worker processes that score the structural candidates and "
                        "run the confirmation refits, one candidate each (1: in process; the "
                        "result does not depend on it)")
    p.add_argument("--no-plots", action="store_true",
                   help="write report.md, report.html and report.json without the PNG plots "
                        "(each version of the report is then written in a fraction of a "
                        "second; for batch runs)")
    add_scheduler(p)
    add_quiet(p)


def _print_errors(name: str, res) -> None:
    """The summary's error lines: before and after on each validation record
    (the first, then each further ``--validate`` record) and on the
    estimation record, or on the record alone without a validation record."""
    print(f"{name}: {res.metric}")
    if res.final.validation_metric is None:
        print(f"  before: {res.initial.metric:.4g}   after: {res.final.metric:.4g}")
        return
    val = res.settings.get("validation") or "held out"
    print(f"  on the validation record ({val}): before {res.initial.validation_metric:.4g}   "
          f"after {res.final.validation_metric:.4g}")
    for rec, before, after in res.more_validation():
        b = "-" if before is None else f"{before:.4g}"
        print(f"  on the validation record ({rec}): before {b}   after {after:.4g}")
    print(f"  on the estimation record ({res.record}): before {res.initial.metric:.4g}   "
          f"after {res.final.metric:.4g}")


def _judging_options(p: argparse.ArgumentParser) -> None:
    """The record that judges and how: ``--validate``, ``--holdout``,
    ``--init-samples``, ``--metric-tolerance``."""
    p.add_argument("--validate", default=None, metavar="FILE", action="append",
                   help="held-out record (CSV): the accept decision and the report's error "
                        "before/after use the free-run error on it; given again, each further "
                        "record judges too (an accepted model simulates on each and its error "
                        "grows on none)")
    p.add_argument("--holdout", type=float, default=None, metavar="FRACTION",
                   help="the last FRACTION of the record is held out as the validation record "
                        "(the fits use the rest; default without --validate "
                        f"{DEFAULT_HOLDOUT} for --model/--data, 0 for a bundled case); with "
                        "--validate the files judge beside it")
    p.add_argument("--init-samples", type=int, default=None, metavar="N",
                   help="the free run on the record that judges (held out or --validate) "
                        "starts from its first N samples only, as benchmark protocols ask "
                        "(EMPS: 20); default: the smoothed start given that whole record")
    p.add_argument("--metric-tolerance", type=float, default=None,
                   help="accept an effect only if the error grows by at most this factor "
                        "(default 1.0: it may not rise)")


def from_result(graph, path: str, params: str | None):
    """``graph`` with the parameter values of ``--from`` (an estimate's
    result.json or a loop's report.json, :func:`~bondgraph.export.params.read_params`)
    as its defaults, which are the loop's start values and, for the
    parameters not estimated, their held values; noise levels and initial
    states of the file are left out. One line says what was taken.

    Raises
    ------
    ExportError
        An unreadable file, or a parameter the graph does not have.
    OptionError
        A value outside the parameter's box (named with the box).
    """
    values = read_params(path)
    out = model_graph(graph, values)
    outside = [f"{n} = {v:.6g} (box [{graph.params[n].bounds[0]:.6g}, "
               f"{graph.params[n].bounds[1]:.6g}])" for n, v in values.items()
               if not graph.params[n].bounds[0] <= v <= graph.params[n].bounds[1]]
    if outside:
        raise OptionError(f"--from {path}: outside the graph's boxes: {'; '.join(outside)}; "
                          f"widen the box in the graph or leave the value out")
    fitted = set(parse_params(params)) if params else None
    held = [n for n in values if fitted is not None and n not in fitted]
    print(f"bondgraph loop: start values from {path}: "
          + ", ".join(f"{n} = {v:.6g}" for n, v in values.items())
          + (f"; held at them: {', '.join(held)}" if held else ""))
    return out


def _said(msg: str) -> None:
    """A line of the command's set-up on stdout."""
    print(f"bondgraph loop: {msg}")


def refitted(graph, path: str) -> list[str]:
    """The parameters a loop started ``--from`` a fit re-estimates when no
    ``--params`` is given: those the fit estimated (not its fixed values,
    noise levels or initial states), in the graph's order; the others are
    held at their values. One line says so.

    Raises
    ------
    OptionError
        The file estimated none of the graph's parameters.
    """
    names = [n for n in graph.params if n in read_params(path, estimated=True)]
    if not names:
        raise OptionError(f"--from {path} estimated none of the graph's parameters: name them "
                          f"with --params")
    print(f"bondgraph loop: re-estimating {', '.join(names)} (what {path} estimated; the "
          f"others held at their values; --params to choose)")
    return names


def _require_model_for_data(args) -> None:
    """Refuse ``--data`` or ``--decimate`` without ``--model`` (a bundled
    case brings its own record)."""
    if getattr(args, "decimate", 1) > 1 and not args.model:
        raise UsageError(f"--decimate {args.decimate} applies to a --model/--data record; a "
                         f"bundled case filters its record as its protocol says")
    if args.data and not args.model:
        raise UsageError(f"--data {args.data} needs --model (the model to fit to it); without "
                         f"both, a bundled case runs")


def run(args) -> int:
    """Run the loop on ``--model``/``--data`` or a bundled case; write the report."""
    if args.case == "list":
        for name, spec in sorted(registered_cases().items()):
            print(f"{name:24s} {spec}")
        return 0
    compile_in_background()     # the filter kernel, once per installation, beside the set-up
    _require_model_for_data(args)
    if args.model:
        if not args.data:
            raise ModelError("--model needs --data FILE.csv (the measured record)")
        graph = graph_builder(args.model)()
        record = filtered_record(load_record(args.data, graph, _said, args.columns, args.dt),
                                 graph, args, say=_said)
        decimated_window(args, _said)
        fixed = parse_pairs(args.fixed, "--fixed")      # known values: not estimated
        params = parse_params(args.params) if args.params else [n for n in graph.params
                                                                 if n not in fixed]
        # without --params, a parameter declared without a box is a known
        # value: held where the record cannot tell it from others
        hold = () if args.params else tuple(
            n for n, p in graph.params.items() if not getattr(p, "box_declared", True))
        base = LoopSettings(params=params, hold_unidentified=hold)
        name = graph.name
    else:
        with progress.phase(f"building the bundled case '{args.case or DEFAULT_CASE}'"):
            case = get_case(args.case or DEFAULT_CASE)
        print(f"bondgraph loop: bundled case '{case.name}': {case.description}")
        graph = case.declared()
        record = case.record()
        base = case.loop_settings(parse_params(args.params) if args.params else None)
        name = case.name
    if args.from_result:
        graph = from_result(graph, args.from_result, args.params)
        if args.model and not args.params:
            base = dataclasses.replace(base, params=refitted(graph, args.from_result),
                                       hold_unidentified=())
    settings = loop_settings(args, base, graph)
    if args.skip_effects and not args.quiet:
        kept = {e.name for e in settings.effects}
        print(f"bondgraph loop: not scored (--skip-effects): "
              f"{', '.join(e.name for e in base.effects if e.name not in kept)}")
    require_params(graph, settings.params, settings.fixed)  # before the numerics
    if args.model:
        settings = chosen_numerics(args, graph, record, settings)
    if args.model and not args.validate and args.holdout is None:
        print(f"bondgraph loop: no --validate record: the last {DEFAULT_HOLDOUT:.0%} of "
              f"{args.data} is held out for the accept decision and the error before/after "
              f"(--holdout FRACTION to change, --holdout 0 to fit all of it)")
    out = Path(args.out) if args.out else unused_folder(DEFAULT_OUT)
    if not args.out and out != Path(DEFAULT_OUT) and not args.quiet:
        print(f"bondgraph loop: ./{DEFAULT_OUT} holds an earlier report (kept); this one goes "
              f"to ./{out} (--out DIR to choose)")
    reporter = LoopReporter(out, echo=None if args.quiet else print,
                            overwrite=args.overwrite, plots=not getattr(args, "no_plots", False))
    try:
        res = run_loop(graph, record, settings, log=reporter.log, progress=not args.quiet,
                       on_update=reporter.update)
    finally:    # stopped by an error: the intermediate report being written completes
        reporter.wait(raise_failure=False)
    if args.discover:
        res = _with_discovery(args, graph, record, settings, res, out)
    print()
    _print_summary(args, res, name, None if args.model else case, (graph, settings), out)
    return 0


def _print_summary(args, res, name: str, case, declared: tuple, out: Path) -> None:
    """The summary after the loop: the errors (and a bundled case's own
    held-out line), the steps, the final checks and notes, where the report
    is and (a user's model) how to judge it on another record."""
    graph, settings = declared
    _print_errors(name, res)
    if case is not None and case.held_out is not None:
        print(case.held_out(res))
    print(res.table() if res.steps else f"  no effect accepted: {res.none_accepted()}"
          + ("; the reasons are in report.md" if res.rejected else ""))
    for w in getattr(res, "final_checks", ()):
        print(w if w.startswith("note: ") else f"warning: {w}")
    hint = unexplained_hint(res, args.discover, graph, settings.effects)
    if hint:
        print(hint)
    moved = moved_text(moved_declared(res))
    if moved:
        print(f"note: {moved}")
    loose = understated(res.final.std, robust_of(res.final), res.final.estimates)
    if loose:
        print(f"note: the Cramér-Rao std understates the uncertainty of {', '.join(loose)} "
              f"(robust std that many times larger: the innovations are serially correlated); "
              f"the report's parameter table gives the robust std")
    augmented = ", augmented_model.py" if (out / "augmented_model.py").is_file() else ""
    print(f"report: {out / 'report.html'} (and report.md, report.json, PNG plots{augmented})")
    if args.model:
        print(another_day(args, out))


def another_day(args, out: Path) -> str:
    """The line that says how to judge the final model on another record:
    ``bondgraph compare`` with the options that read this record
    (``--columns``, ``--dt``), which read the other day's too: the report
    folder (the declared fit and the final model, before -> after) where the
    loop wrote ``augmented_model.py``, else (no effect accepted, no such
    file) the declared model at the report's estimates."""
    reading = reading_options(args)
    if (out / "augmented_model.py").is_file():
        return (f"on a record of another day: bondgraph compare {out} --data OTHER.csv{reading} "
                f"(the declared fit and the final model, before -> after)")
    return (f"on a record of another day: bondgraph compare {args.model} --data "
            f"OTHER.csv{reading} --params {out / 'report.json'} (no effect accepted: the "
            f"declared model at its fit)")


def unexplained_hint(res, discovered: bool, graph=None, effects=()) -> str | None:
    """One line when the final model's innovations are not white (the
    Ljung-Box sum beyond χ²(dof) + 3 std): the record shows more than the
    accepted effects explain; the optional effects of the library that
    attach to ``graph`` and are not among ``effects`` (:func:`optional_left`);
    without ``--discover``, say what it does."""
    r = getattr(res.final, "residuals", None)
    if r is None or r.whiteness_dof <= 0 or r.is_white():
        return None
    d = r.whiteness_dof
    msg = (f"note: the final model's innovations are not white (whiteness {r.whiteness:.4g}; "
           f"white: about {d:g} ± {3 * (2 * d) ** 0.5:.0f}): the record shows more than the "
           f"accepted effects explain")
    left = optional_left(graph, effects) if graph is not None else {}
    if left:
        msg += ("; not scored: the optional " + "; ".join(
            f"{n} (at {', '.join(t)})" for n, t in left.items())
            + f" (--add-effects {','.join(left)})")
    if not discovered:
        msg += ("; --discover reconstructs the effort (flow) missing at each junction and "
                "seeks its law beyond the effect library")
    return msg


def skipped_effects(effects, patterns) -> tuple:
    """``effects`` without those whose name matches one of ``patterns`` (a
    name, or a shell pattern such as ``sensor_*``, :func:`fnmatch.fnmatchcase`).

    Raises
    ------
    OptionError
        A pattern that matches no effect of ``effects`` nor an optional one
        of the library (the names listed), or patterns that leave no effect
        to score.
    """
    import fnmatch

    names = [e.name for e in effects]
    # an optional effect not asked for (--add-effects) is not scored anyway:
    # skipping it is no mistake (the list of `bondgraph models --effects`
    # copied whole)
    optional = [e.name for e in OPTIONAL_EFFECTS]
    for pat in patterns:
        if not fnmatch.filter(names, pat) and not fnmatch.filter(optional, pat):
            raise OptionError(f"--skip-effects: '{pat}' matches no effect the loop scores "
                              f"(the effects: {', '.join(names)})",
                              hint="give an effect's name or a pattern such as sensor_*")
    kept = tuple(e for e in effects
                 if not any(fnmatch.fnmatchcase(e.name, pat) for pat in patterns))
    if not kept:
        raise OptionError(f"--skip-effects {','.join(patterns)} leaves no effect to score")
    return kept


def optional_left(graph, effects) -> dict[str, list[str]]:
    """The optional effects of the library
    (:data:`~bondgraph.diagnose.effects.library.OPTIONAL_EFFECTS`: scored
    only when asked) that are not in ``effects`` and attach to ``graph``:
    name -> the places they attach to."""
    have = {e.name for e in effects}
    out = {}
    for eff in OPTIONAL_EFFECTS:
        if eff.name in have:
            continue
        places = [t.name for t in eff.targets(graph)]
        if places:
            out[eff.name] = places
    return out


def _with_discovery(args, graph, record, settings, res, out: Path):
    """``--discover``: the loop's result ``res``, or, when it accepted no
    physical effect (or the accepted ones leave coloured innovations) and a
    port gave a passive law
    (:func:`bondgraph.diagnose.discover.effect.discovered_effect`), the
    loop run again with that law and its alternatives as effects, its report
    in ``<out>-discover`` while it runs; when its final model is better
    (:func:`~bondgraph.diagnose.discover.effect.discovery_not_better`) its
    report replaces the first one in ``out``, else the first stands and the
    second stays beside it (said in one line)."""
    from bondgraph.diagnose.discover.effect import (
        discovered_effect,
        discovery_not_better,
        discovery_plot,
        with_discovered,
    )

    echo = (lambda _m: None) if args.quiet else print
    # sensors whose every library effect --skip-effects left out get no
    # discovered output law either: the user said they are calibrated
    calibrated = bool(getattr(args, "skip_effects", None)) and not any(
        getattr(e, "target_kind", None) == "sensor" for e in settings.effects)
    best = discovered_effect(graph, record, settings, res, log=echo,
                             sensors=() if calibrated else None)
    if best is None:
        return res
    side = unused_folder(out.with_name(f"{out.name}-discover"))
    echo(f"bondgraph loop: the loop again, with the law discovered at '{best.law.port}'"
         + (f" and {len(best.alternatives)} alternative(s)" if best.alternatives else "")
         + f" (its report in ./{side} until it is judged against the first)")
    settings = with_discovered(settings, *best.effects())
    plots = not getattr(args, "no_plots", False)
    reporter = LoopReporter(side, echo=None if args.quiet else print, plots=plots)

    def update(result):
        result.discovery = discovery_plot(best.accepted_in(result), result)
        reporter.update(result)

    try:
        again = run_loop(graph, record, settings, log=reporter.log, progress=not args.quiet,
                         on_update=update)
    finally:
        reporter.wait(raise_failure=False)
    why = discovery_not_better(res, again)
    if why is not None:
        echo(f"bondgraph loop: {why} (its report: ./{out}; the discovery run's: ./{side})")
        res.warnings.append(why)
        return res
    final = LoopReporter(out, overwrite=True, plots=plots)
    final.log_path.write_text("".join(p.read_text() for p in (out / "loop.log", side / "loop.log")
                                      if p.exists()))
    final.update(again)          # the report in out, its generated code naming out
    shutil.rmtree(side)
    return again


def loop_states(graph, text: str) -> list[str]:
    """The initial states of ``--estimate-x0`` checked against the declared
    graph's states (``all``: every state of every model of the loop).

    Raises
    ------
    OptionError
        A state the graph does not have (named).
    """
    names = parse_names(text, "--estimate-x0")
    if names == ["all"]:
        return names
    states = SimpleNamespace(name=graph.name, states=[str(x) for x in derive(graph).states])
    return x0_state_names(states, names)


#: the loop's options as the command line spells them (an error of a group's
#: validation names the option the user typed)
_OPTION_NAMES = {"LoopSettings.metric": "--metric", "LoopSettings.noise": "--noise",
                 "LoopSettings.holdout": "--holdout", "LoopSettings.validation": "--validate",
                 "LoopSettings.more_validation": "--validate",
                 "FreeRunOptions.init_samples": "--init-samples",
                 "AcceptRule.criterion": "--criterion",
                 "AcceptRule.significance": "--significance",
                 "AcceptRule.metric_tolerance": "--metric-tolerance",
                 "SearchOptions.max_steps": "--max-steps", "SearchOptions.fit": "--fit",
                 "SearchOptions.likelihood": "--likelihood",
                 "SearchOptions.structural": "--no-structural",
                 "SearchOptions.on_failed_fit": "--keep-going",
                 "PriorSpec.rel (--p0-rel)": "--p0-rel", "PriorSpec.scale (--p0)": "--p0",
                 "Evaluation.workers": "--workers", "Evaluation.scheduler": "--scheduler"}


def _given(value, default):
    """``value`` when the command line gives it (not None), else ``default``."""
    return default if value is None else value


def loop_settings(args, base: LoopSettings, graph) -> LoopSettings:
    """The loop's options: ``base`` (the case's own, or the defaults for
    ``--model``/``--data``) with what the command line gives, each group
    built once from the options and validated there; an error names the
    option as typed (``--max-steps``, not ``SearchOptions.max_steps``).

    Raises
    ------
    OptionError
        A bad value, named as the option the user typed.
    ModelError
        A state or parameter the graph does not have.
    """
    fixed = parse_pairs(args.fixed, "--fixed")
    x0 = parse_pairs(args.x0, "--x0")
    states = loop_states(graph, args.estimate_x0) if args.estimate_x0 else base.estimate_x0
    judging = [filtered_record(load_record(f, graph, _said, args.columns, args.dt), graph, args,
                               say=_said)
               for f in (args.validate or [])]
    names = [r.name for r in judging]
    for f, r in zip(args.validate or [], judging):
        if names.count(r.name) > 1:      # two files of one name: the paths tell them apart
            r.meta["name"] = str(f)
    validation = judging[0] if judging else base.validation
    more = tuple(judging[1:]) if judging else base.more_validation
    if judging and args.holdout:         # the held-out part judges first, the files beside it
        validation, more = None, tuple(judging)
    holdout = args.holdout
    if args.model and not args.validate and holdout is None:
        holdout = DEFAULT_HOLDOUT
    given = {k: getattr(args, k) for k in ("method", "substeps", "hold")
             if getattr(args, k) is not None}
    ukf = ukf_replaced(base.ukf, given, args.backend)
    effects = base.effects
    if args.add_effects:
        have = {e.name for e in effects}
        effects = tuple(effects) + tuple(get_effect(n) for n in parse_names(
            args.add_effects, "--add-effects") if n not in have)
    if args.skip_effects:
        effects = skipped_effects(effects, parse_names(args.skip_effects, "--skip-effects"))
    try:
        return dataclasses.replace(
            base, fixed={**base.fixed, **fixed} if fixed else base.fixed,
            params=base.params if args.params else [n for n in base.params if n not in fixed],
            estimate_x0=states, metric=_given(args.metric, base.metric), effects=effects,
            noise=_given(args.noise, base.noise), validation=validation,
            more_validation=more,
            holdout=_given(None if holdout is None else float(holdout), base.holdout),
            accept=accept_rule(args, base.accept), search=search_options(args, base.search),
            prior=dataclasses.replace(
                base.prior, x0_set=x0 or base.prior.x0_set,
                rel=_given(None if args.p0_rel is None else float(args.p0_rel), base.prior.rel),
                scale=_given(args.p0, base.prior.scale)),
            free_run=(base.free_run if args.init_samples is None else
                      dataclasses.replace(base.free_run, init_samples=args.init_samples)),
            ukf=ukf, evaluation=dataclasses.replace(base.evaluation, workers=args.workers,
                                                    scheduler=args.scheduler))
    except OptionError as exc:
        text = str(exc)
        for key in sorted(_OPTION_NAMES, key=len, reverse=True):
            text = re.sub(re.escape(key) + r"(?!\w)", _OPTION_NAMES[key], text)
        raise OptionError(text) from exc


def accept_rule(args, base: AcceptRule) -> AcceptRule:
    """``base`` with ``--criterion``, ``--significance``, ``--metric-tolerance``
    and ``--no-replace`` where given (validated by :class:`AcceptRule`)."""
    tolerance = None if args.metric_tolerance is None else float(args.metric_tolerance)
    return dataclasses.replace(base, criterion=args.criterion,
                               significance=_given(args.significance, base.significance),
                               metric_tolerance=_given(tolerance, base.metric_tolerance),
                               replace=base.replace and not getattr(args, "no_replace", False))


def search_options(args, base: SearchOptions) -> SearchOptions:
    """``base`` with ``--max-steps``, ``--fit``, ``--likelihood``, ``--no-structural`` and
    ``--keep-going`` where given (validated by :class:`SearchOptions`)."""
    return dataclasses.replace(
        base, max_steps=_given(args.max_steps, base.max_steps), fit=_given(args.fit, base.fit),
        likelihood=(base.likelihood if args.likelihood is None
                    else args.likelihood.replace("-", "_")),
        structural=False if args.no_structural else base.structural,
        on_failed_fit="continue" if args.keep_going else base.on_failed_fit)


def chosen_numerics(args, graph, record, settings: LoopSettings) -> LoopSettings:
    """A user's graph and record (``--model``/``--data``): the numerics
    :func:`bondgraph.diagnose.runner.chosen_numerics` chooses, what of
    ``--method``, ``--substeps``, ``--hold`` the user gave kept; one line
    says what was chosen and why. A bundled case keeps its own options."""
    return loop_chosen_numerics(graph, record, settings, given=discretisation_given(args),
                                log=lambda line: print("bondgraph loop: " + line, flush=True))


def ukf_replaced(base: UKFOptions, given: dict, backend: str) -> UKFOptions:
    """``base`` (the case's filter options) with ``--method``, ``--substeps``,
    ``--hold`` where given and ``--backend``; an error names the option.

    Raises
    ------
    OptionError
        ``--substeps 0`` and the like.
    """
    try:
        return dataclasses.replace(base, backend=backend, **given)
    except OptionError as exc:
        text = str(exc)
        for key in ("method", "substeps", "hold", "backend"):
            text = text.replace(f"UKFOptions.{key}", f"--{key}")
        raise OptionError(text) from exc
