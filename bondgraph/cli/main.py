"""The ``bondgraph`` command line.

Each command is a module of :mod:`bondgraph.cli` with ``configure(parser)``
and ``run(args) -> int``; options shared between commands are declared in
:mod:`bondgraph.cli.common`. This module only dispatches (and imports just the
command it runs, so ``bondgraph --help`` is fast).
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import sys
import warnings

from bondgraph import __version__
from bondgraph.core import progress
from bondgraph.errors import BondGraphError, BondGraphWarning, UsageError

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
    "compare": "a fitted model on records it was not fitted to: free-run error per record and output",
    "sensitivity": "local and global sensitivity, identifiability",
    "track": "track parameters over a record (augmented-state UKF) and detect their changes",
    "export": "a standalone FMI 2.0 FMU (Model Exchange and Co-Simulation) of a model",
    "linearize": "A, B, C, D at an operating point or equilibrium: .npz, poles, Bode plot",
}


class _Parser(argparse.ArgumentParser):
    """argparse that raises :class:`~bondgraph.errors.UsageError` instead of
    exiting, so that every user mistake takes the same path (exit code 2)."""

    def error(self, message: str):
        raise UsageError(f"{message} (see `{self.prog} --help`)")

    def parse_args(self, args=None, namespace=None):
        from bondgraph.cli.common import merged_model

        ns = super().parse_args(args, namespace)
        problem = merged_model(ns)
        if problem:
            self.error(problem.replace("COMMAND", self.prog.split()[-1]))
        return ns


def _parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="bondgraph",
        description="Bond-graph modeling with code generation, UKF maximum-likelihood "
                    "estimation and residual tracing.",
        epilog="Run `bondgraph COMMAND --help` for a command's options.\n"
               "example: bondgraph loop    (the main job on the bundled vehicle case)",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"bondgraph {__version__}",
                   help="print the installed version and exit")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, helptext in COMMANDS.items():
        sub.add_parser(name, help=helptext, add_help=False)
    return p


def command_parser(cmd: str) -> argparse.ArgumentParser:
    """The parser of ``bondgraph CMD``: the command module's options, its
    one-line help as description and its ``EXAMPLE`` as the last line of
    ``--help``.

    Raises
    ------
    KeyError
        ``cmd`` is not one of :data:`COMMANDS`.
    """
    parser = _Parser(prog=f"bondgraph {cmd}", **_command_texts(cmd))
    importlib.import_module(f"bondgraph.cli.{cmd}").configure(parser)
    return parser


def _command_texts(cmd: str) -> dict:
    """Description, epilog (the module's ``EXAMPLE``) and formatter of a
    command's parser."""
    example = getattr(importlib.import_module(f"bondgraph.cli.{cmd}"), "EXAMPLE", None)
    return {"description": COMMANDS[cmd],
            "epilog": f"example: {example}" if example else None,
            "formatter_class": argparse.RawDescriptionHelpFormatter}


def full_parser() -> argparse.ArgumentParser:
    """Every command's parser under one ``bondgraph`` parser (the command
    reference of the documentation is generated from it by sphinx-argparse;
    :func:`main` builds only the parser of the command it runs)."""
    p = _Parser(prog="bondgraph", description=_parser().description)
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, helptext in COMMANDS.items():
        importlib.import_module(f"bondgraph.cli.{name}").configure(
            sub.add_parser(name, help=helptext, **_command_texts(name)))
    return p


def _show_warning(cmd: str):
    """``warnings.showwarning`` printing the toolkit's warnings as
    ``bondgraph CMD: warning: ...`` (others as Python does)."""
    default = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, BondGraphWarning):
            print(f"bondgraph {cmd}: warning: {message}", file=sys.stderr)
        else:
            default(message, category, filename, lineno, file, line)
    return show


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``bondgraph`` console script.

    Exit codes: 0 success; 2 a user mistake or a typed error of
    :mod:`bondgraph.errors` (bad option, input, model, data, an output folder
    that is not empty or writable, a failed estimation), printed as
    ``bondgraph CMD: error: MESSAGE``; 1 a check that found a problem
    (``generate --check``: stale code); 130 interrupted. Anything else is a
    bug and shows its traceback.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        _parser().print_help()
        return 0
    cmd = argv[0]
    if cmd in ("--version", "-V"):
        print(f"bondgraph {__version__}")
        return 0
    if cmd not in COMMANDS:
        _parser().print_usage(sys.stderr)
        close = difflib.get_close_matches(cmd, list(COMMANDS), n=1)
        print(f"bondgraph: error: unknown command '{cmd}' (commands: {', '.join(COMMANDS)})"
              + (f"; did you mean '{close[0]}'?" if close else ""), file=sys.stderr)
        return 2
    # the command's module loads numpy, scipy, sympy and numba: 1-3 s, in
    # which the watchdog already says what is happening; one watchdog from
    # here to the end, so that the silence of the loading and that of the
    # command's first set-up add up on its clock (a fresh install's first
    # `bondgraph loop` said nothing for 2.5 s: 1.2 s loading, 1.3 s
    # building the bundled case, each under a watchdog of its own)
    with progress.enabled("--quiet" not in argv), progress.watchdog():
        with progress.phase(f"loading the {cmd} command (numpy, scipy, sympy, numba)"):
            mod = importlib.import_module(f"bondgraph.cli.{cmd}")
            parser = command_parser(cmd)
        return _run_command(cmd, mod, parser, argv)


def _run_command(cmd: str, mod, parser, argv: list) -> int:
    """The command ``cmd`` (its module ``mod`` and ``parser``) on ``argv``;
    a :class:`BondGraphError` printed as ``bondgraph CMD: error: ...``
    (exit code 2), an interrupt as exit code 130."""
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning(cmd)
            args = parser.parse_args(argv[1:])
            _line_buffered()
            with progress.enabled(not getattr(args, "quiet", False)):
                return int(mod.run(args) or 0)
    except BondGraphError as exc:
        print(f"bondgraph {cmd}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"bondgraph {cmd}: interrupted", file=sys.stderr)
        return 130


def _line_buffered() -> None:
    """stdout and stderr flushed at every line, also into a pipe or a log
    file (``bondgraph loop | tee log``), where Python would hold the
    progress lines in 8 kB blocks."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.reconfigure(line_buffering=True)
        except (AttributeError, ValueError, OSError):   # not a text file (a test's capture)
            pass


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
