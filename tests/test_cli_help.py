"""`bondgraph --version` and the example line every command's --help ends with."""

from __future__ import annotations

import importlib.metadata
import shlex

import pytest

from bondgraph.cli.main import COMMANDS, command_parser, full_parser, main


def test_version_is_the_installed_distribution(capsys):
    assert main(["--version"]) == 0
    out = capsys.readouterr().out.strip()
    assert out == f"bondgraph {importlib.metadata.version('bondgraph-toolkit')}"


@pytest.mark.parametrize("cmd", list(COMMANDS))
def test_help_ends_with_an_example_that_parses(cmd, capsys):
    with pytest.raises(SystemExit) as exc:
        main([cmd, "--help"])
    assert exc.value.code == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.strip()]
    assert lines[-1].startswith(f"example: bondgraph {cmd}"), lines[-1]
    # the example uses only options the command has (argparse raises otherwise)
    argv = shlex.split(lines[-1].removeprefix("example: "))[2:]
    command_parser(cmd).parse_args(argv)


def test_full_parser_holds_every_command():
    sub = full_parser()._subparsers._group_actions[0]
    assert list(sub.choices) == list(COMMANDS)
    assert sub.choices["loop"].epilog.startswith("example: bondgraph loop")
