"""The ``bondgraph`` command line.

Each sub-command lives in the module of its stage of the data flow and
provides ``configure_<command>(parser)`` and ``run_<command>(args) -> int``;
this module only dispatches (and imports just the module it needs, so
``bondgraph --help`` is fast).
"""

from __future__ import annotations

import argparse
import importlib
import sys

#: command -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "loop": ("bondgraph.diagnose.loop", "main job: trace residuals to missing effects, add them, "
                               "re-estimate, report before/after"),
    "generate": ("bondgraph.cli.main", "(re)generate generated/ from the registered graphs "
                                  "(--check: fail on stale files)"),
    "models": ("bondgraph.cli.main", "list the registered models"),
    "draw": ("bondgraph.cli.main", "draw a model's bond graph with causal strokes"),
    "equations": ("bondgraph.cli.main", "print a model's derived state equations"),
    "simulate": ("bondgraph.numerics.simulate", "simulate a model / experiment to CSV"),
    "plot": ("bondgraph.report.plots", "plot a simulation or experiment CSV to PNGs"),
    "estimate": ("bondgraph.inference.estimate", "maximum-likelihood estimation (UKF + PSO/DE)"),
    "sensitivity": ("bondgraph.sensitivity.analysis", "local and global sensitivity, identifiability"),
}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="bondgraph",
        description="Bond-graph modeling with code generation, UKF maximum-likelihood "
                    "estimation and residual tracing.",
        epilog="Run `bondgraph COMMAND --help` for a command's options.")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, helptext) in COMMANDS.items():
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
        from bondgraph import __version__

        print(__version__)
        return 0
    if cmd not in COMMANDS:
        _parser().print_usage(sys.stderr)
        print(f"bondgraph: unknown command '{cmd}' (commands: {', '.join(COMMANDS)})",
              file=sys.stderr)
        return 2
    modname, helptext = COMMANDS[cmd]
    try:
        mod = importlib.import_module(modname)
        configure = getattr(mod, f"configure_{cmd}")
        # a module may name its handler run_<cmd>_cli when run_<cmd> is its API
        run = getattr(mod, f"run_{cmd}_cli", None) or getattr(mod, f"run_{cmd}")
    except (ImportError, AttributeError) as exc:
        print(f"bondgraph {cmd}: not available in this installation ({exc})", file=sys.stderr)
        return 2
    parser = argparse.ArgumentParser(prog=f"bondgraph {cmd}", description=helptext)
    configure(parser)
    args = parser.parse_args(argv[1:])
    from bondgraph.errors import BondGraphError

    try:
        return int(run(args) or 0)
    except BondGraphError as exc:
        print(f"bondgraph {cmd}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"bondgraph {cmd}: interrupted", file=sys.stderr)
        return 130


# ---------------------------------------------------------------- generate
def configure_generate(p: argparse.ArgumentParser) -> None:
    p.add_argument("models", nargs="*", help="models to generate (default: all registered)")
    p.add_argument("--check", action="store_true",
                   help="do not write; exit 1 naming each model whose file is stale")
    p.add_argument("--out", default=None, help="target directory (default: the generated/ package)")


def run_generate(args) -> int:
    from bondgraph.numerics.registry import generate

    if args.check:
        stale = generate(args.models or None, check=True, directory=args.out)
        if stale:
            print(f"stale generated code: {', '.join(stale)} (run `bondgraph generate`)",
                  file=sys.stderr)
            return 1
        return 0
    generate(args.models or None, directory=args.out)
    return 0


# ------------------------------------------------------------------ models
def configure_models(p: argparse.ArgumentParser) -> None:
    p.add_argument("--params", metavar="MODEL", help="print the parameter table of MODEL")


def run_models(args) -> int:
    from bondgraph.numerics.registry import registered

    if args.params:
        from bondgraph.numerics.model import Model

        print(Model.load(args.params).param_table())
        return 0
    for name, spec in sorted(registered().items()):
        print(f"{name:28s} {spec}")
    return 0


# -------------------------------------------------------------------- draw
def configure_draw(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", help="registered model name")
    p.add_argument("-o", "--output", default=None, help="output file (default MODEL.png)")


def run_draw(args) -> int:
    from bondgraph.report.drawing import draw
    from bondgraph.numerics.registry import build

    g = build(args.model)
    out = args.output or f"{args.model}.png"
    draw(g, out)
    print(f"wrote {out}")
    return 0


# --------------------------------------------------------------- equations
def configure_equations(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", help="registered model name")
    p.add_argument("--causality", action="store_true", help="also print the causal strokes")


def run_equations(args) -> int:
    from bondgraph.numerics.registry import build

    g = build(args.model)
    ss = g.derive()
    if args.causality:
        print(ss.causality.table())
    print(ss.describe())
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
