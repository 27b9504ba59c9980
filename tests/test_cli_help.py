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


@pytest.mark.parametrize("cmd, option, fix", [
    ("loop", "--data", "--validate FILE"),
    ("sensitivity", "--data", "bondgraph estimate --data A --data B"),
    ("track", "--data", "--from")])
def test_a_one_record_option_given_twice_is_refused_not_dropped(cmd, option, fix, capsys):
    # argparse keeps the last of a repeated option: a record would be dropped silently
    base = ["--model", "m"] + (["--track", "c", "--out", "o"] if cmd == "track" else [])
    args = command_parser(cmd).parse_args(base + [option, "a.csv"])   # once is fine
    assert getattr(args, option[2:]) == "a.csv"
    assert main([cmd, *base, option, "a.csv", option, "b.csv"]) == 2
    err = capsys.readouterr().err
    assert f"argument {option}: given twice ('a.csv' and 'b.csv')" in err and fix in err


def test_loop_takes_several_validation_records():
    args = command_parser("loop").parse_args(
        ["--model", "m", "--data", "r.csv", "--validate", "a.csv", "--validate", "b.csv"])
    assert args.validate == ["a.csv", "b.csv"]


def test_estimate_takes_several_records():
    args = command_parser("estimate").parse_args(
        ["--model", "m", "--data", "a.csv", "--data", "b.csv"])
    assert args.data == ["a.csv", "b.csv"]
