"""``bondgraph loop``, the main job: trace the residuals of a fitted model to
effects the model lacks, add them, re-estimate, and report the error before
and after. Without ``--model`` it runs a bundled case (default
``vehicle_aero``)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from bondgraph.cli.common import (
    MODEL_HELP,
    add_backend,
    add_overwrite,
    add_quiet,
    load_record,
    parse_params,
)
from bondgraph.diagnose.cases import get_case, registered_cases
from bondgraph.diagnose.loop import run_loop
from bondgraph.diagnose.settings import LoopSettings
from bondgraph.errors import ModelError, OptionError, UsageError
from bondgraph.inference.options import UKFOptions
from bondgraph.numerics.registry import graph_builder
from bondgraph.report.loop_report import LoopReporter

#: the case run by ``bondgraph loop`` without arguments
DEFAULT_CASE = "vehicle_aero"


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph loop``."""
    p.add_argument("--case", default=None,
                   help=f"bundled case (`--case list` lists them; default {DEFAULT_CASE} when "
                        f"no --model is given)")
    p.add_argument("--model", help=MODEL_HELP)
    p.add_argument("--data", help="record (CSV in the experiment format, see docs/data_format.md)")
    p.add_argument("--params", help="comma-separated parameters to estimate (default: the "
                                    "case's, or all parameters of the model)")
    p.add_argument("--out", default="bondgraph-report", help="report directory "
                                                             "(default ./bondgraph-report); "
                                                             "refused when not empty, unless "
                                                             "--overwrite")
    add_overwrite(p)
    p.add_argument("--metric", default=None,
                   help="error measure: nrmse_sim (default), rmse_sim, rmse_pred")
    p.add_argument("--criterion", choices=("aic", "bic"), default="aic")
    p.add_argument("--max-steps", type=int, default=None)
    p.add_argument("--significance", type=float, default=None)
    p.add_argument("--no-structural", action="store_true",
                   help="score only additive effects (faster)")
    add_backend(p)
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
    settings["ukf"] = dataclasses.replace(settings.get("ukf") or UKFOptions(),
                                          backend=args.backend)
    try:                                             # bad settings fail before any output
        LoopSettings.from_options(params, settings)
    except OptionError as exc:                       # named as the options the user typed
        text = str(exc)
        for key in ("metric", "criterion", "max_steps", "significance"):
            text = text.replace(f"LoopSettings.{key}", "--" + key.replace("_", "-"))
        raise OptionError(text) from exc
    reporter = LoopReporter(args.out, echo=None if args.quiet else print,
                            overwrite=args.overwrite)
    res = run_loop(graph, record, params, log=reporter.log, progress=not args.quiet,
                   on_update=reporter.update, **settings)
    print()
    print(f"{name}: {res.metric}")
    print(f"  before: {res.initial.metric:.4g}   after: {res.final.metric:.4g}")
    if res.steps:
        print(res.table())
    else:
        print("  no effect accepted (nothing significant left)")
    print(f"report: {Path(args.out) / 'report.md'} (and report.json, PNG plots, "
          f"augmented_model.py)")
    return 0
