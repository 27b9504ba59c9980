"""``bondgraph loop``, the main job: trace the residuals of a fitted model to
effects the model lacks, add them, re-estimate, and report the error before
and after. Without ``--model`` it runs a bundled case (default
``vehicle_aero``)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from types import SimpleNamespace

from bondgraph.cli.common import (
    MODEL_HELP,
    add_discretisation,
    add_estimation_scope,
    add_overwrite,
    add_quiet,
    add_scheduler,
    load_record,
    parse_names,
    parse_pairs,
    parse_params,
    unused_folder,
)
from bondgraph.core.equations import derive
from bondgraph.diagnose.cases import get_case, registered_cases
from bondgraph.diagnose.loop import run_loop
from bondgraph.diagnose.settings import DEFAULT_HOLDOUT, LoopSettings
from bondgraph.errors import ModelError, OptionError, UsageError
from bondgraph.inference.estimand import x0_state_names
from bondgraph.inference.options import UKFOptions
from bondgraph.numerics.registry import graph_builder
from bondgraph.report.loop_report import LoopReporter

#: the case run by ``bondgraph loop`` without arguments
DEFAULT_CASE = "vehicle_aero"
#: the report folder without ``--out`` (numbered when it holds an earlier report)
DEFAULT_OUT = "bondgraph-report"


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph loop``."""
    p.add_argument("--case", default=None,
                   help=f"bundled case (`--case list` lists them; default {DEFAULT_CASE} when "
                        f"no --model is given)")
    p.add_argument("--model", help=MODEL_HELP)
    p.add_argument("--data", help="record (CSV in the experiment format, see docs/data_format.md)")
    p.add_argument("--params", help="comma-separated parameters to estimate (default: the "
                                    "case's, or all parameters of the model)")
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
    p.add_argument("--validate", default=None, metavar="FILE",
                   help="held-out record (CSV): the accept decision and the report's error "
                        "before/after use the free-run error on it")
    p.add_argument("--holdout", type=float, default=None, metavar="FRACTION",
                   help="without --validate: the last FRACTION of the record is held out as "
                        "the validation record (the fits use the rest; default "
                        f"{DEFAULT_HOLDOUT} for --model/--data, 0 for a bundled case)")
    p.add_argument("--metric-tolerance", type=float, default=None,
                   help="accept an effect only if the error grows by at most this factor "
                        "(default 1.0: it may not rise)")
    add_estimation_scope(p)            # --fixed --x0 --p0-rel --p0 --estimate-x0 --noise
    p.set_defaults(p0_rel=None, noise=None, p0=None)   # the case's own P0 policy and noise
    p.add_argument("--fit", choices=("nll", "sim"), default=None,
                   help="declared fit: UKF likelihood (nll, default) or an output-error "
                        "(free-run least-squares) fit of the non-noise parameters first, "
                        "whose estimates start the likelihood fit (sim)")
    add_discretisation(p)          # with --backend
    p.set_defaults(method=None, substeps=None, hold=None)   # a case's own options unless given
    p.add_argument("--workers", type=int, default=1,
                   help="local Dask worker processes that score the structural candidates and "
                        "run the confirmation refits, one candidate each (1: in process; the "
                        "result does not depend on it)")
    add_scheduler(p)
    add_quiet(p)


def run(args) -> int:
    """Run the loop on ``--model``/``--data`` or a bundled case; write the report."""
    settings: dict = {}
    if args.case == "list":
        for name, spec in sorted(registered_cases().items()):
            print(f"{name:24s} {spec}")
        return 0
    if args.data and not args.model:
        raise UsageError(f"--data {args.data} needs --model (the model to fit to it); without "
                         f"both, a bundled case runs")
    if args.model:
        if not args.data:
            raise ModelError("--model needs --data FILE.csv (the measured record)")
        graph = graph_builder(args.model)()
        record = load_record(args.data, graph)
        params = parse_params(args.params) if args.params else list(graph.params)
        name = graph.name
    else:
        case = get_case(args.case or DEFAULT_CASE)
        print(f"bondgraph loop: bundled case '{case.name}': {case.description}")
        graph = case.declared()
        record = case.record()
        params = parse_params(args.params) if args.params else case.params
        settings.update(case.settings)
        if case.true_effect is not None:
            settings["true_effect"] = case.true_effect
        name = case.name
    if args.metric:
        settings["metric"] = args.metric
    settings["criterion"] = args.criterion
    if args.max_steps is not None:
        settings["max_steps"] = args.max_steps
    if args.significance is not None:
        settings["significance"] = args.significance
    if args.no_structural:
        settings["structural"] = False
    settings.update(numerics_settings(args, settings, graph))
    if args.model and not args.validate and args.holdout is None:
        settings["holdout"] = DEFAULT_HOLDOUT
        print(f"bondgraph loop: no --validate record: the last {DEFAULT_HOLDOUT:.0%} of "
              f"{args.data} is held out for the accept decision and the error before/after "
              f"(--holdout FRACTION to change, --holdout 0 to fit all of it)")
    settings["ukf"] = dataclasses.replace(settings.get("ukf") or UKFOptions(),
                                          backend=args.backend)
    settings.update(workers=args.workers, scheduler=args.scheduler)
    try:                                             # bad settings fail before any output
        LoopSettings.from_options(params, settings)
    except OptionError as exc:                       # named as the options the user typed
        text = str(exc)
        for key in ("metric", "criterion", "max_steps", "significance", "workers"):
            text = text.replace(f"LoopSettings.{key}", "--" + key.replace("_", "-"))
        raise OptionError(text) from exc
    out = Path(args.out) if args.out else unused_folder(DEFAULT_OUT)
    if not args.out and out != Path(DEFAULT_OUT) and not args.quiet:
        print(f"bondgraph loop: ./{DEFAULT_OUT} holds an earlier report (kept); this one goes "
              f"to ./{out} (--out DIR to choose)")
    reporter = LoopReporter(out, echo=None if args.quiet else print,
                            overwrite=args.overwrite)
    res = run_loop(graph, record, params, log=reporter.log, progress=not args.quiet,
                   on_update=reporter.update, **settings)
    print()
    print(f"{name}: {res.metric}")
    if res.final.validation_metric is not None:
        val = res.settings.get("validation") or "held out"
        print(f"  on the validation record ({val}): before {res.initial.validation_metric:.4g}   "
              f"after {res.final.validation_metric:.4g}")
        print(f"  on the estimation record ({res.record}): before {res.initial.metric:.4g}   "
              f"after {res.final.metric:.4g}")
    else:
        print(f"  before: {res.initial.metric:.4g}   after: {res.final.metric:.4g}")
    if res.steps:
        print(res.table())
    else:
        print("  no effect accepted (nothing significant left)")
    print(f"report: {out / 'report.md'} (and report.json, PNG plots, "
          f"augmented_model.py)")
    return 0


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


def numerics_settings(args, settings: dict, graph) -> dict:
    """Loop settings from the shared options: ``--fixed`` (over the case's),
    ``--x0`` (by state name, over the record's initial state), ``--p0-rel``,
    ``--method``/``--substeps``/``--hold`` (the case's UKF options otherwise
    kept), ``--validate`` and ``--metric-tolerance``.

    Raises
    ------
    OptionError
        Malformed pairs; ModelError: a state the graph lacks.
    """
    out: dict = {}
    fixed = parse_pairs(args.fixed, "--fixed")
    if fixed:
        out["fixed"] = {**settings.get("fixed", {}), **fixed}
    x0 = parse_pairs(args.x0, "--x0")
    if x0:
        out["x0_overrides"] = x0
    if args.p0_rel is not None:
        out["p0_rel"] = float(args.p0_rel)
    if args.p0 is not None:
        out["p0_scale"] = args.p0
    if args.fit is not None:
        out["fit"] = args.fit
    if args.estimate_x0:
        out["estimate_x0"] = loop_states(graph, args.estimate_x0)
    if args.noise is not None:
        out["noise"] = args.noise
    base = settings.get("ukf") or UKFOptions()
    given = {k: getattr(args, k) for k in ("method", "substeps", "hold")
             if getattr(args, k) is not None}
    if given:
        out["ukf"] = UKFOptions(**{**base.to_dict(), **given})
    if args.validate:
        out["validation"] = load_record(args.validate, graph)   # misspelt columns warned
    if args.holdout is not None:
        out["holdout"] = float(args.holdout)
    if args.metric_tolerance is not None:
        out["metric_tolerance"] = float(args.metric_tolerance)
    return out
