"""``bondgraph simulate``: simulate a model on a registered experiment, a
record's inputs, or constant inputs, and write the trajectory as a record."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from bondgraph.cli.common import (add_model, load_model, parse_pairs, parse_renames,
                                  solver_hold_argument)
from bondgraph.core import atomic
from bondgraph.core.jsonsafe import to_jsonable
from bondgraph.data.experiments import get_experiment, run_experiment
from bondgraph.data.records import Experiment
from bondgraph.errors import ModelError, UsageError
from bondgraph.export.params import read_params
from bondgraph.inference.discretise import record_input_holds, supported_hold
from bondgraph.numerics.simulate import FIXED_METHODS, METHODS, simulate, stiffness_report
from bondgraph.report.plots import plot_record


#: the example line of ``bondgraph simulate --help``
EXAMPLE = "bondgraph simulate mass_spring_damper --experiment msd_force_step --noise -o msd_force_step.csv"


#: the sample interval [s] of a simulation without a record
DEFAULT_DT = 0.025


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph simulate``."""
    add_model(p, positional=True)
    p.add_argument("--experiment", "-e", metavar="NAME",
                   help="registered experiment (its inputs, x0 and parameters) or a record "
                        "CSV (its inputs and time grid); default: model defaults for --duration")
    p.add_argument("-o", "--output", default=None, help="output CSV (default MODEL_sim.csv)")
    p.add_argument("--method", default="BDF", choices=METHODS, help="integration method")
    p.add_argument("--substeps", type=int, default=1, help="rk4/ros2 steps per sample")
    p.add_argument("--duration", type=float, default=10.0,
                   help="record length [s] without --experiment")
    p.add_argument("--dt", type=float, default=None, metavar="SECONDS",
                   help="sample interval [s]: without --experiment the grid's (default "
                        f"{DEFAULT_DT}); with a record CSV, that of a file without a time "
                        "column (read with t = k dt; a time column must agree with it)")
    p.add_argument("--columns", default=None, metavar="COLUMN=NAME,...",
                   help="with a record CSV: its columns renamed to the model's input, output "
                        "or state names as they are read (e.g. Current=I: a logger's names)")
    p.add_argument("--param", action="append", metavar="NAME=VALUE", help="parameter override")
    p.add_argument("--params", default=None, metavar="JSON",
                   help="parameter values of a fit: `bondgraph estimate`'s result.json or a "
                        "loop's report.json (its final fit; noise levels and initial states "
                        "left out); --param overrides them")
    p.add_argument("--record-params", action="store_true",
                   help="with a record CSV: use the parameters stored in its sidecar "
                        "(true_parameters or parameters) that the model has")
    p.add_argument("--input", action="append", metavar="NAME=VALUE",
                   help="constant input (model units) without --experiment")
    p.add_argument("--x0", action="append", metavar="NAME=VALUE",
                   help="initial state (model units; overrides the experiment's x0; default the "
                        "model's X0)")
    p.add_argument("--rtol", type=float, default=1e-8)
    p.add_argument("--atol", type=float, default=1e-10)
    p.add_argument("--max-step", type=float, default=None, help="adaptive solvers' largest step")
    p.add_argument("--hold", type=solver_hold_argument, default=None, metavar="HOLD",
                   help="sampled inputs between samples: linear or zoh, or one of them per "
                        "input comma-joined in the model's input order (zoh,linear); the "
                        "record written declares it per input. Default: with a record CSV, "
                        "the hold it declares for each input (sidecar columns.<input>.hold), "
                        "else the one its samples support (a staircase zoh, a sampled "
                        "continuous signal linear; one line says which); otherwise linear. "
                        "The fixed-step methods (rk4, ros2) hold every input zero-order")
    p.add_argument("--noise", action="store_true",
                   help="write a noisy synthetic record: with a registered experiment its own "
                        "noise and seed (e.g. `bondgraph simulate mass_spring_damper -e "
                        "msd_force_step --noise -o msd_force_step.csv`); otherwise the model's "
                        "sensor noise (or --noise-std) drawn with --seed; the sidecar declares "
                        "each output's noise_std and holds the true parameters and x0")
    p.add_argument("--noise-std", action="append", metavar="OUTPUT=STD",
                   help="with --noise and no registered experiment: an output's noise std "
                        "(model units) instead of its sensor's")
    p.add_argument("--seed", type=int, default=0,
                   help="with --noise and no registered experiment: seed of "
                        "numpy.random.default_rng (default 0)")
    p.add_argument("--plot", metavar="DIR", help="also write PNG plots to DIR")
    p.add_argument("--stiffness", action="store_true",
                   help="print the stiffness report and write OUTPUT.stiffness.json")


def _record_hold(record, model, u) -> str:
    """The hold of a record's inputs when ``--hold`` is not given: declared
    by the record, else supported by each input's samples
    (:func:`~bondgraph.inference.discretise.supported_hold`), as the
    estimate and loop commands hold them; one line on stderr says which."""
    names = model.inputs
    if not names:
        return "linear"
    hold, why = supported_hold(record_input_holds(
        record, names, np.asarray(u, float).reshape(len(record.t), -1)))
    print(f"input hold {hold} (chosen; --hold to give it): {why}", file=sys.stderr)
    return hold


def _on_record(args, path: Path, model, overrides: dict, notes: list) -> tuple:
    """``(measured, t, u, x0, theta)`` of a simulation on the record CSV at
    ``path`` (read with ``--columns`` and ``--dt``): its time grid and inputs
    (model defaults for the absent ones, noted), the hold its inputs declare
    (into ``args.hold`` unless given), its initial state and, with
    ``--record-params``, its stored parameters under ``overrides``."""
    measured = Experiment.load(path, columns=parse_renames(args.columns) or None, dt=args.dt)
    missing = measured.missing_inputs(model)
    if missing:
        notes.append(f"inputs {', '.join(missing)} not in the record: model defaults")
    u = measured.inputs_for(model, defaults_ok=True)
    if args.hold is None and args.method not in FIXED_METHODS:
        args.hold = _record_hold(measured, model, u)
    x0 = {k: v for k, v in (measured.meta.get("x0") or {}).items() if k in model.states}
    stored = {}
    if args.record_params:
        stored = (measured.meta.get("true_parameters") or measured.meta.get("parameters") or {})
        stored = {k: v for k, v in stored.items() if k in model.params}
        if not stored:
            notes.append("the record stores no parameters of this model")
    return measured, measured.t, u, x0, model.theta({**stored, **overrides})


def run(args) -> int:
    """Run ``bondgraph simulate`` (see :func:`configure`)."""
    if args.noise and _registered_experiment(args.experiment):
        return _noisy_record(args)
    if args.noise_std and not args.noise:
        raise UsageError("--noise-std needs --noise")
    if args.dt is not None and not args.dt > 0:
        raise UsageError(f"--dt {args.dt:g}: the sample interval must be positive (seconds)")
    model = load_model(args.model)
    overrides = {**fitted_values(args.params, model), **parse_pairs(args.param, "--param")}
    measured = None
    notes = _box_notes(model, overrides)
    if args.experiment:
        path = Path(args.experiment)
        if path.suffix.lower() in (".csv", ".json") or path.exists():
            measured, t, u, x0, theta = _on_record(args, path, model, overrides, notes)
        else:
            if args.columns:
                raise UsageError("--columns renames the columns of a record CSV; "
                                 f"'{args.experiment}' is not a file")
            spec = get_experiment(args.experiment)
            n = int(round(spec.duration / spec.dt)) + 1
            t = np.arange(n) * spec.dt
            u = {k: fn for k, fn in spec.inputs.items() if k in model.inputs}
            skipped = [k for k in spec.inputs if k not in model.inputs]
            if skipped:
                notes.append(f"experiment inputs {', '.join(skipped)} are not inputs of "
                             f"{model.name}: ignored")
            x0 = {k: v for k, v in spec.x0.items() if k in model.states}
            params = {k: v for k, v in spec.params.items() if k in model.params}
            theta = model.theta({**params, **overrides})
    else:
        if args.columns:
            raise UsageError("--columns renames the columns of a record CSV: give it with "
                             "--experiment FILE")
        dt = DEFAULT_DT if args.dt is None else args.dt
        n = int(round(args.duration / dt)) + 1
        t = np.arange(n) * dt
        u = parse_pairs(args.input, "--input") or None
        x0 = None
        theta = model.theta(overrides)
    given = parse_pairs(args.x0, "--x0")
    unknown = [k for k in given if k not in model.states]
    if unknown:
        raise ModelError(f"--x0: {', '.join(unknown)} not a state of model '{model.name}' "
                         f"(states: {', '.join(model.states)})")
    x0 = {**(x0 or {}), **given}
    res = simulate(model, t, u=u, x0=x0 or None, theta=theta, method=args.method,
                   rtol=args.rtol, atol=args.atol, substeps=args.substeps,
                   max_step=args.max_step, hold=args.hold or "linear")
    out = Path(args.output or f"{model.name}_sim.csv")
    rec = _with_noise(res, args, out.stem) if args.noise else \
        Experiment.from_simulation(res, name=out.stem)
    rec.save(out)
    for note in notes:
        print(f"note: {note}")
    st = res.stats
    print(f"wrote {out} ({t.size} samples, {t[-1] - t[0]:.6g} s, {args.method}, "
          f"{st.get('nfev', 0)} f evaluations, {st['wall_time_s']:.3g} s)")
    if args.stiffness:
        rep, table = stiffness_report(model, res)
        print(table)
        jpath = out.with_suffix(".stiffness.json")
        atomic.write_text(jpath, json.dumps(to_jsonable(rep), indent=1, allow_nan=False) + "\n")
        print(f"wrote {jpath}")
    if args.plot:
        if measured is not None:
            paths = plot_record(measured, args.plot, simulated=res, model=model)
        else:
            paths = plot_record(res, args.plot)
        for pth in paths:
            print(f"wrote {pth}")
    return 0


def _box_notes(model, values: dict) -> list[str]:
    """A note for each given parameter value outside the model's box for it
    (the declared box, or the decade either side of a default declared
    without one; simulated as given: a what-if is the user's to ask, but a
    typo of a sign or a decade should not pass unsaid)."""
    notes = []
    for name, v in values.items():
        lo, hi = (float(b[0]) for b in model.bounds([name]))
        if not lo <= v <= hi:
            notes.append(f"{name} = {v:g} is outside the model's box [{lo:g}, {hi:g}] for it: "
                         f"simulated as given")
    return notes


def fitted_values(path: str | None, model) -> dict[str, float]:
    """``--params``: the parameter values of a fit
    (:func:`~bondgraph.export.params.read_params`); {} without it.

    Raises
    ------
    ExportError
        An unreadable file.
    ModelError
        A parameter the model does not have (named, with the model's).
    """
    if not path:
        return {}
    values = read_params(path)
    unknown = [n for n in values if n not in model.params]
    if unknown:
        raise ModelError(f"--params {path}: model '{model.name}' has no parameter(s) "
                         f"{', '.join(unknown)} (its parameters: {', '.join(model.params)})",
                         hint="a loop's report.json goes with its augmented_model.py:build")
    return values


def _registered_experiment(name: str | None) -> bool:
    """True if ``name`` is a registered experiment (not a record file)."""
    if not name or Path(name).suffix.lower() in (".csv", ".json") or Path(name).exists():
        return False
    return True


def _with_noise(res, args, name: str) -> Experiment:
    """``--noise`` without a registered experiment: the simulated outputs plus
    independent Gaussian noise of each output's sensor std (the model's
    ``meas_std`` at the simulated parameters, or ``--noise-std``), drawn from
    ``numpy.random.default_rng(--seed)``; the sidecar declares each output's
    ``noise_std`` and holds ``true_parameters``, ``x0``, ``noise`` and ``seed``.

    Raises
    ------
    ModelError
        ``--noise-std`` names an output the model does not have.
    UsageError
        A noise std that is not finite and >= 0.
    """
    m = res.model
    std = np.asarray(m.meas_std(res.theta), float).reshape(-1) if m.n_y else np.zeros(0)
    for k, v in parse_pairs(args.noise_std, "--noise-std").items():
        if k not in m.outputs:
            raise ModelError(f"--noise-std: '{k}' is not an output of {m.name} "
                             f"({', '.join(m.outputs)})")
        if not v >= 0:
            raise UsageError(f"--noise-std: {k}={v!r} must be >= 0")
        std[m.output_index(k)] = float(v)
    rng = np.random.default_rng(args.seed)
    y = res.y + rng.standard_normal(res.y.shape) * std
    noise = {o: float(s) for o, s in zip(m.outputs, std)}
    meta = {"description": f"simulation of {m.name} ({res.method}) with Gaussian sensor noise",
            "true_parameters": {p: float(v) for p, v in zip(m.params, res.theta)},
            "x0": {s: float(v) for s, v in zip(m.states, res.x[0])},
            "noise": {"distribution": "gaussian", "independent": True, "mean": 0.0,
                      "std": noise},
            "seed": int(args.seed), "method": res.method,
            "generator": "bondgraph simulate --noise"}
    return Experiment.from_arrays(res.t, model=m, u=res.u, y=y, x=res.x, noise_std=noise,
                                  meta=meta, name=name)


def _noisy_record(args) -> int:
    """``--noise``: the registered experiment's synthetic record
    (:func:`bondgraph.data.experiments.run_experiment`), saved atomically.

    Raises
    ------
    UsageError
        No registered experiment, or options that the record ignores.
    ModelError
        An unknown experiment, or a model other than the experiment's.
    """
    if args.param or args.params or args.input or args.record_params or args.noise_std:
        raise UsageError("--noise writes the experiment's record at its true parameters, "
                         "inputs and noise: --param, --params, --input, --record-params and "
                         "--noise-std do not apply")
    spec = get_experiment(args.experiment)
    if args.model != spec.model:
        raise ModelError(f"experiment '{spec.name}' is a record of model '{spec.model}', "
                         f"not of '{args.model}'")
    exp = run_experiment(spec, method=args.method, rtol=args.rtol, atol=args.atol,
                         max_step=args.max_step)
    out = Path(args.output or f"{spec.name}.csv")
    exp.save(out)
    print(f"wrote {out} and {out.with_suffix('.json')} ({exp.t.size} samples, noise seed "
          f"{spec.seed})")
    if args.plot:
        for pth in plot_record(exp, args.plot):
            print(f"wrote {pth}")
    return 0
