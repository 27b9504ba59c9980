"""``bondgraph estimate``: maximum-likelihood estimation (batched UKF + PSO or
DE), writing ``result.json`` and PNG fit plots."""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

from bondgraph.cli.common import (
    add_data,
    add_discretisation,
    add_fixed,
    add_initial_state,
    add_model,
    add_quiet,
    initial_state,
    load_model,
    parse_names,
    parse_pairs,
    parse_params,
)
from bondgraph.data.records import Experiment
from bondgraph.errors import IdentifiabilityWarning
from bondgraph.core.jsonsafe import to_jsonable
from bondgraph.inference.estimate import estimate
from bondgraph.inference.output_error import output_error_fit
from bondgraph.inference.record import as_record, record_arrays
from bondgraph.inference.options import FitOptions, UKFOptions
from bondgraph.inference.ukf import default_P0
from bondgraph.report.estimation import plot_fit


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph estimate``."""
    add_model(p)
    add_data(p)
    p.add_argument("--params", required=True,
                   help="comma-separated parameters to estimate, or recommended:FILE for the "
                        "set recommended in a `bondgraph sensitivity` result (sensitivity.json "
                        "or its directory)")
    p.add_argument("--optimizer", choices=("pso", "de"), default="pso")
    p.add_argument("--particles", type=int, default=None, help="swarm / population size (10 k)")
    p.add_argument("--iterations", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="output directory (default estimate_<model>_<data>)")
    p.add_argument("--checkpoint", default=None, help="checkpoint file (default <out>/checkpoint.npz)")
    p.add_argument("--resume", action="store_true", help="continue from the checkpoint")
    add_fixed(p)
    add_discretisation(p)
    p.add_argument("--alpha", type=float, default=1.0)
    p.add_argument("--beta", type=float, default=2.0)
    p.add_argument("--kappa", type=float, default=0.0)
    p.add_argument("--stall", type=int, default=None, help="stop after N iterations without progress")
    add_initial_state(p)
    p.add_argument("--no-polish", action="store_true")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("--workers", type=int, default=1, help="processes per batched evaluation")
    p.add_argument("--fit", choices=("nll", "sim"), default="nll",
                   help="criterion: the UKF negative log-likelihood (nll: process noise, "
                        "unmeasured disturbances, global search) or the free-run simulation "
                        "error by least squares with forward sensitivities (sim: a "
                        "deterministic model, a local search from the defaults)")
    p.add_argument("--estimate-x0", default=None, metavar="STATES",
                   help="with --fit sim: initial states estimated too (comma-separated, or all)")
    add_quiet(p)


def run(args) -> int:
    """Estimate, write ``result.json`` and the fit plots; print the table."""
    model = load_model(args.model)
    exp = Experiment.load(args.data)
    params = parse_params(args.params, model)
    out = Path(args.out) if args.out else Path(f"estimate_{model.name}_{Path(args.data).stem}")
    out.mkdir(parents=True, exist_ok=True)
    ck = Path(args.checkpoint) if args.checkpoint else out / "checkpoint.npz"
    x0 = initial_state(model, exp, args.x0)
    if args.fit == "sim":
        return run_output_error(args, model, exp, params, x0, out)
    P0 = default_P0(model, x0, args.p0_rel)
    fit = FitOptions(optimizer=args.optimizer, particles=args.particles,
                     iterations=args.iterations, seed=args.seed, checkpoint=ck,
                     resume=args.resume, polish=not args.no_polish, stall_iterations=args.stall,
                     progress=not args.quiet, workers=args.workers)
    ukf = UKFOptions(alpha=args.alpha, beta=args.beta, kappa=args.kappa, method=args.method,
                     substeps=args.substeps, hold=args.hold)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        res = estimate(model, exp, params, fit=fit, ukf=ukf,
                       fixed=parse_pairs(args.fixed, "--fixed"), x0=x0, P0=P0)
    res.settings["data"] = str(args.data)
    rpath = out / "result.json"
    res.to_json(rpath)
    print(res.table())
    print(f"wrote {rpath}")
    if not args.no_plots:
        for pth in plot_fit(model, exp, res, out, P0=P0):
            print(f"wrote {pth}")
    return 0


def run_output_error(args, model, exp, params, x0, out: Path) -> int:
    """``--fit sim``: the output-error fit
    (:func:`bondgraph.inference.output_error.output_error_fit`) from the
    model's defaults with ``--fixed`` and ``--x0``, the initial states of
    ``--estimate-x0`` estimated too; writes ``result.json``."""
    theta = model.theta0.copy()
    for k, v in parse_pairs(args.fixed, "--fixed").items():
        theta[model.param_index(k)] = v
    t, u, y, _, _ = record_arrays(model, as_record(exp))
    states = parse_names(args.estimate_x0, "--estimate-x0") if args.estimate_x0 else []
    if states == ["all"]:
        states = list(model.states)
    r = output_error_fit(model, t, u, y, params, theta=theta, x0=x0, x0_states=states,
                         hold=args.hold)
    doc = {"model": model.name, "data": str(args.data), "fit": "sim", "names": r.names,
           "estimates": r.estimates(), "std": r.std, "at_bound": r.at_bound, "cost": r.cost,
           "rmse": dict(zip(model.outputs, r.rmse.tolist())), "nfev": r.nfev,
           "status": r.status, "message": r.message}
    rpath = out / "result.json"
    rpath.write_text(json.dumps(to_jsonable(doc), indent=2, allow_nan=False))
    for n in r.names:
        sd = r.std.get(n)
        print(f"{n:24s} {r.estimates()[n]:.6g}" + (f" ± {sd:.3g}" if sd is not None else
                                                    " (on a bound)" if n in r.at_bound else ""))
    print(f"free-run RMS error: " + ", ".join(f"{o} {v:.4g}" for o, v in
                                              zip(model.outputs, r.rmse)))
    print(f"wrote {rpath}")
    return 0
