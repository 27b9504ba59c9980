"""``bondgraph equations``: a model's derived state equations (and causal strokes)."""

from __future__ import annotations

import argparse

from bondgraph.cli.common import add_model
from bondgraph.core.equations import derive
from bondgraph.numerics.registry import graph_builder


#: the example line of ``bondgraph equations --help``
EXAMPLE = "bondgraph equations vehicle_coastdown --causality"


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph equations``."""
    add_model(p, positional=True)
    p.add_argument("--causality", action="store_true", help="also print the causal strokes")


def run(args) -> int:
    """Derive and print the state equations."""
    ss = derive(graph_builder(args.model)())
    if args.causality:
        print(ss.causality.table())
    print(ss.describe())
    return 0
