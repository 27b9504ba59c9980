"""``bondgraph generate``: (re)generate the code of the registered models, or
check that it is up to date."""

from __future__ import annotations

import argparse
import sys

from bondgraph.numerics.registry import COMMAND, generate


#: the example line of ``bondgraph generate --help``
EXAMPLE = "bondgraph generate --check"


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph generate``."""
    p.add_argument("models", nargs="*", help="models to generate (default: all registered)")
    p.add_argument("--check", action="store_true",
                   help="do not write; exit 1 naming each model whose file is stale")
    p.add_argument("--out", default=None, help="target directory (default: the registered "
                                               "generated-code package)")


def run(args) -> int:
    """Write (or check) the generated modules; 1 if ``--check`` finds stale ones."""
    if args.check:
        stale = generate(args.models or None, check=True, directory=args.out)
        if stale:
            print(f"stale generated code: {', '.join(stale)} (run `{COMMAND}`)", file=sys.stderr)
            return 1
        return 0
    generate(args.models or None, directory=args.out)
    return 0
