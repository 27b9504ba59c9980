"""``bondgraph draw``: a model's bond graph with its causal strokes, as an image."""

from __future__ import annotations

import argparse

from bondgraph.cli.common import add_model
from bondgraph.numerics.registry import graph_builder
from bondgraph.report.drawing import draw


#: the example line of ``bondgraph draw --help``
EXAMPLE = "bondgraph draw toy_cvt -o toy_cvt.png"


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph draw``."""
    add_model(p, positional=True)
    p.add_argument("-o", "--output", default=None, help="output file (default GRAPH.png)")


def run(args) -> int:
    """Draw the graph to a file."""
    g = graph_builder(args.model)()
    out = args.output or f"{g.name}.png"
    draw(g, out)
    print(f"wrote {out}")
    return 0
