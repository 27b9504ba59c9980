"""The ``bondgraph`` command line.

Each command is a module of :mod:`bondgraph.cli` with ``configure(parser)``
and ``run(args) -> int``; options shared between commands are declared in
:mod:`bondgraph.cli.common`. This module only dispatches (and imports just the
command it runs, so ``bondgraph --help`` is fast).
"""

from __future__ import annotations

import argparse
import importlib
import sys

from bondgraph import __version__
from bondgraph.errors import BondGraphError

#: command -> one-line help; the command's module is ``bondgraph.cli.<command>``
COMMANDS: dict[str, str] = {
    "loop": "main job: trace residuals to missing effects, add them, re-estimate, report "
            "before/after",
    "generate": "(re)generate the registered models' code (--check: fail on stale files)",
    "models": "list the registered models",
    "draw": "draw a model's bond graph with causal strokes",
    "equations": "print a model's derived state equations",
    "simulate": "simulate a model / experiment to CSV",
    "plot": "plot a simulation or experiment CSV to PNGs",
    "estimate": "maximum-likelihood estimation (UKF + PSO/DE)",
    "sensitivity": "local and global sensitivity, identifiability",
}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="bondgraph",
        description="Bond-graph modeling with code generation, UKF maximum-likelihood "
                    "estimation and residual tracing.",
        epilog="Run `bondgraph COMMAND --help` for a command's options.")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, helptext in COMMANDS.items():
        sub.add_parser(name, help=helptext, add_help=False)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``bondgraph`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        _parser().print_help()
        return 0
    cmd = argv[0]
    if cmd == "--version":
        print(__version__)
        return 0
    if cmd not in COMMANDS:
        _parser().print_usage(sys.stderr)
        print(f"bondgraph: unknown command '{cmd}' (commands: {', '.join(COMMANDS)})",
              file=sys.stderr)
        return 2
    mod = importlib.import_module(f"bondgraph.cli.{cmd}")
    parser = argparse.ArgumentParser(prog=f"bondgraph {cmd}", description=COMMANDS[cmd])
    mod.configure(parser)
    args = parser.parse_args(argv[1:])
    run = mod.run
    try:
        return int(run(args) or 0)
    except BondGraphError as exc:
        print(f"bondgraph {cmd}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"bondgraph {cmd}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
