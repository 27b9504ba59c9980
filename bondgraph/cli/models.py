"""``bondgraph models``: the registered models, or one model's parameter table."""

from __future__ import annotations

import argparse

from bondgraph.cli.common import load_model
from bondgraph.numerics.registry import registered


#: the example line of ``bondgraph models --help``
EXAMPLE = "bondgraph models --params mass_spring_damper"


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph models``."""
    p.add_argument("--params", metavar="MODEL",
                   help="print the parameter table of MODEL (a registered name, module:function "
                        "or path/to/file.py:function)")


def run(args) -> int:
    """Print the registered models or a parameter table."""
    if args.params:
        print(load_model(args.params).param_table())
        return 0
    for name, spec in sorted(registered().items()):
        print(f"{name:28s} {spec}")
    return 0
