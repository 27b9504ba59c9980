"""``bondgraph plot``: PNG plots of a record or simulation CSV."""

from __future__ import annotations

import argparse
from pathlib import Path

from bondgraph.report.plots import plot_record


#: the example line of ``bondgraph plot --help``
EXAMPLE = "bondgraph plot msd_force_step.csv -o msd_plots"


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph plot``."""
    p.add_argument("record", help="record CSV (experiment or simulation)")
    p.add_argument("-o", "--output", default=None, metavar="DIR",
                   help="output directory (default RECORD_plots)")
    p.add_argument("--simulated", default=None, metavar="CSV",
                   help="a simulation CSV to draw over the record")
    p.add_argument("--model", default=None, help="model classifying columns without a role")


def run(args) -> int:
    """Run ``bondgraph plot``."""
    rec = Path(args.record)
    out = args.output or str(rec.with_suffix("")) + "_plots"
    for p in plot_record(rec, out, simulated=args.simulated, model=args.model):
        print(f"wrote {p}")
    return 0
