"""``bondgraph sensitivity``: local and global sensitivity and identifiability
of a record, writing ``sensitivity.json`` and PNG plots."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

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
    default_out,
    default_params,
    estimated_states,
    filtered_record,
    load_model,
    load_record,
    output_folder,
    parse_names,
    parse_pairs,
    problem_from_args,
    published,
)
from bondgraph.core import progress
from bondgraph.errors import OptionError, SensitivityError
from bondgraph.inference.executor import Executor
from bondgraph.numerics.forward_sensitivity import check_params, free_parameters
from bondgraph.report.sensitivity import plot_report
from bondgraph.sensitivity.analysis import LocalOptions, analyse
from bondgraph.sensitivity.sobol import SobolOptions
from bondgraph.sensitivity.identifiability import CORR_MAX, REL_CRB_MAX


#: the example line of ``bondgraph sensitivity --help``
EXAMPLE = "bondgraph sensitivity --model mass_spring_damper --data msd_force_step.csv --params m,k,c"


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph sensitivity``."""
    add_model(p)
    add_data(p)
    p.add_argument("--params", default=None,
                   help="comma-separated candidate parameters (default: those estimate fits "
                        "without --params, the parameters declared with a box, or every "
                        "parameter with a proper box when none is; one line on stderr)")
    p.add_argument("--global", dest="global_N", type=int, default=None, metavar="N",
                   help="also Sobol' indices with base sample N (N (2k+2) UKF evaluations)")
    p.add_argument("--outputs", default="",
                   help="comma-separated outputs whose time-means also get Sobol' indices")
    p.add_argument("--box-rel", type=float, default=None,
                   help="Sobol' box theta*(1 ± BOX_REL) instead of the model bounds")
    p.add_argument("--chunk", type=int, default=256, help="parameter sets per batched UKF run")
    p.add_argument("--workers", type=int, default=1,
                   help="local Dask worker processes that evaluate the Sobol' sample's chunks "
                        "(1: in process; the indices do not depend on it)")
    add_scheduler(p)
    p.add_argument("--nll-transform", choices=("log", "none"), default="log",
                   help="Sobol' indices of ln(1 + NLL - min NLL) (default) or of the NLL")
    p.add_argument("--out", default=None, help="output directory (default "
                                               "sensitivity_<model>_<data>, numbered -2, -3, ... "
                                               "when it holds an earlier result); refused when "
                                               "not empty, unless --overwrite")
    add_overwrite(p)
    add_estimation_scope(p)
    p.add_argument("--at-truth", action="store_true",
                   help="analyse at the record's true parameters (synthetic records)")
    p.add_argument("--from", dest="from_result", default=None, metavar="JSON",
                   help="analyse at the estimates of a `bondgraph estimate` result.json or a "
                        "`bondgraph loop` report.json (its final model's: pass that model, "
                        "REPORT_DIR/augmented_model.py:build) instead of the graph's declared "
                        "values, as `loop --from` and `track --from` start from them; --fixed "
                        "still wins")
    p.add_argument("--seconds", type=float, default=None, help="use only the first SECONDS")
    add_discretisation(p)
    p.add_argument("--rel-crb", type=float, default=REL_CRB_MAX,
                   help="largest relative Cramér-Rao bound of a recommended parameter")
    p.add_argument("--corr-max", type=float, default=CORR_MAX,
                   help="largest abs(correlation) within the recommended set")
    p.add_argument("--no-sensitivities", action="store_true",
                   help="skip the forward sensitivity equations")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-plots", action="store_true")
    add_quiet(p)


def _line(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _default_params(spec: str, model, fixed=()) -> list[str] | None:
    """The candidates without ``--params``: what ``bondgraph estimate`` fits
    without it (:func:`~bondgraph.cli.common.default_params`: the
    parameters declared with a box; one declared without one is a known
    value), those with a proper box; None (every parameter with a proper
    box) when that leaves none."""
    free = set(free_parameters(model))
    names = [n for n in default_params(spec, model, "sensitivity", fixed) if n in free]
    return names or None


def run(args) -> int:
    """Analyse, write ``sensitivity.json`` and the PNGs; print the table.

    What of ``--method``, ``--substeps``, ``--hold`` is not given is chosen
    at the analysed θ (:func:`bondgraph.cli.common.chosen_problem`), against
    the noise levels profiled there where a level is estimated
    (:func:`bondgraph.cli.common.chosen_at_levels`), one line on stderr
    saying what and why; an input whose shape is ambiguous is held as the
    filter's likelihood at the analysed θ prefers."""
    with progress.phase("loading the model and the record"):
        model = load_model(args.model)
        exp = filtered_record(load_record(args.data, model, columns=args.columns, dt=args.dt),
                              model, args)
    if args.seconds is not None:
        n = int(np.searchsorted(exp.t, exp.t[0] + args.seconds, side="right"))
        if n < 2:
            raise SensitivityError(f"--seconds {args.seconds} leaves fewer than 2 samples")
        exp = exp.segment(0, n, name=exp.name)
    params = parse_names(args.params, "--params") or _default_params(
        args.model, model, parse_pairs(args.fixed, "--fixed"))
    values = _truth_values(args, exp, model)
    model = _model_at(args, model)
    with progress.phase("choosing the filter's discretisation at the analysed θ"):
        problem, choice = chosen_at_levels(
            args, problem_from_args(model, exp, args, values),
            params or check_params(model, None), estimated_states(model, args), _line,
            where="at the analysed θ", likelihood=True)
    outputs = [s.strip() for s in args.outputs.split(",") if s.strip()]
    for o in outputs:
        model.output_index(o)
    folder = output_folder(default_out(args, f"sensitivity_{model.name}_{Path(args.data).stem}",
                                       "sensitivity"), args)
    log = None if args.quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    t0 = time.perf_counter()
    Executor(args.workers, args.scheduler)   # a bad --workers/--scheduler fails before any work
    local = LocalOptions(rel_crb_max=args.rel_crb, corr_max=args.corr_max,
                         sensitivities=not args.no_sensitivities)
    sobol = None if args.global_N is None else SobolOptions(
        N=args.global_N, outputs=tuple(outputs), box_rel=args.box_rel, chunk=args.chunk,
        seed=args.seed, progress=not args.quiet, nll_transform=args.nll_transform,
        workers=args.workers, scheduler=args.scheduler)
    with progress.phase("the sensitivity analysis"):
        rep = analyse(problem, params, local=local, sobol=sobol,
                      x0_states=estimated_states(model, args),
                      fixed=list(parse_pairs(args.fixed, "--fixed")), log=log)
    rep.settings["data"] = str(args.data)
    rep.settings["discretisation_choice"] = None if choice is None else choice.to_dict()
    rep.settings["wall_s"] = time.perf_counter() - t0

    def version(d: Path) -> list:
        with progress.phase("drawing the plots"):
            pngs = [] if args.no_plots else list(plot_report(rep, d))
        rep.to_json(d / "sensitivity.json")      # last
        return pngs
    pngs = folder.publish(version)
    path = folder.path / "sensitivity.json"
    print(rep.table())
    for p in [path, *published(folder, pngs)]:
        print(f"wrote {p}")
    dec = f" --decimate {args.decimate}" if getattr(args, "decimate", 1) > 1 else ""
    print(f"estimate these with: bondgraph estimate --model {args.model} --data {args.data}{dec} "
          f"--params recommended:{path}")
    misfit = rep.settings.get("misfit") or {}
    if misfit and args.from_result is None and not args.at_truth:
        print(f"note: at the graph's declared values the model misses the record by more than "
              f"its noise ({', '.join(f'{o}: {r:.3g} times its level' for o, r in misfit.items())}"
              f"); the ranking above is that misfit's: fit first (bondgraph estimate ... --out "
              f"FIT) and analyse at the fit with --from FIT/result.json")
    return 0


def _truth_values(args, exp, model) -> dict:
    """The record's true parameters (``--at-truth``; else none), as values
    over the graph's declared ones (``--fixed`` goes over them,
    :func:`~bondgraph.cli.common.problem_from_args`).

    Raises
    ------
    OptionError
        ``--from`` with ``--at-truth``.
    SensitivityError
        A record without true parameters.
    """
    if args.from_result is not None and args.at_truth:
        raise OptionError("--from and --at-truth both give the analysed θ: pass one")
    if not args.at_truth:
        return {}
    tp = (exp.meta or {}).get("true_parameters") or {}
    if not tp:
        raise SensitivityError(f"--at-truth: the record {args.data} has no true_parameters")
    return {k: float(v) for k, v in tp.items() if k in model.params}


def _model_at(args, model):
    """``model``, or with ``--from`` the graph's model with the estimates of
    that result or loop report as its defaults
    (:func:`bondgraph.export.params.read_params`): the analysed θ is then
    a start like the declared one, so the noise levels the analysis
    estimates are profiled there as at any start (fixed values would be
    the point of the analysis and keep the record's levels); one line on
    stderr names the values.

    Raises
    ------
    SensitivityError
        Estimates of parameters the model does not have (named; a loop's
        report goes with its ``augmented_model.py:build``).
    ExportError
        The file is not a result or a report.
    """
    if args.from_result is None:
        return model
    from bondgraph.export.params import model_graph, read_params
    from bondgraph.numerics.model import Model

    values = read_params(args.from_result)
    unknown = [n for n in values if n not in model.params]
    if unknown:
        raise SensitivityError(
            f"--from {args.from_result}: {', '.join(unknown)} not parameters of "
            f"'{model.name}' (a loop's report holds its final model's estimates: analyse that "
            f"model, --model REPORT_DIR/augmented_model.py:build)")
    _line(f"analysed at the estimates of {args.from_result}: "
          + ", ".join(f"{n} = {v:.6g}" for n, v in values.items()))
    return Model.from_graph(model_graph(args.model, values))
