"""``bondgraph export``: a standalone FMI 2.0 FMU of a model
(:func:`bondgraph.export.fmu.export_fmu`)."""

from __future__ import annotations

import argparse

from bondgraph.cli.common import add_model
from bondgraph.errors import UsageError
from bondgraph.export.fmu import FMUOptions, export_fmu
from bondgraph.export.params import model_graph, read_params


EXAMPLE = "bondgraph export mass_spring_damper --fmu msd.fmu"


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph export``."""
    add_model(p, positional=True)
    p.add_argument("--fmu", default=None, nargs="?", const=None, metavar="OUT.fmu",
                   help="the FMU to write (FMI 2.0, Model Exchange and Co-Simulation; default, "
                        "or --fmu alone: MODEL.fmu, the graph's name, in the current folder)")
    p.add_argument("--params", metavar="JSON",
                   help="estimated parameters: `bondgraph estimate`'s result.json or "
                        "`bondgraph loop`'s report.json (with its augmented_model.py:build)")
    p.add_argument("--compiler", default=None,
                   help="C compiler (default $CC, else cc, gcc or clang on PATH)")
    p.add_argument("--tolerance", type=float, default=1e-8,
                   help="relative tolerance of the default experiment (co-simulation "
                        "integrator without an importer's tolerance)")
    p.add_argument("--stop-time", type=float, default=None,
                   help="stop time [s] of the default experiment")


def run(args) -> int:
    """Write the FMU (see :func:`configure`)."""
    params = read_params(args.params) if args.params else None
    if args.fmu is None:                # the graph's name, as linearize's MODEL_linear.npz
        args.fmu = f"{model_graph(args.model, params).name}.fmu"
    if not args.fmu.endswith(".fmu"):
        raise UsageError(f"--fmu {args.fmu}: the file name must end in .fmu")
    options = FMUOptions(compiler=args.compiler, tolerance=args.tolerance,
                         stop_time=args.stop_time)
    path = export_fmu(args.model, args.fmu, params=params, options=options)
    print(f"wrote {path} (FMI 2.0 Model Exchange and Co-Simulation"
          f"{f'; {len(params)} parameters from {args.params}' if params else ''})")
    return 0
