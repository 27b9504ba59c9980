"""``bondgraph models``: the registered models, one model's parameter table,
or the effect library the loop scores."""

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
    p.add_argument("--effects", action="store_true",
                   help="list the effect library: each effect's name (for `bondgraph loop "
                        "--skip-effects` and `--add-effects`), where it attaches and what it is")


def run(args) -> int:
    """Print the registered models or a parameter table."""
    if args.params:
        print(load_model(args.params).param_table())
        return 0
    if args.effects:
        print(effect_table())
        return 0
    for name, spec in sorted(registered().items()):
        print(f"{name:28s} {spec}")
    return 0


def effect_table() -> str:
    """The effect library as text: one line per effect, its name, the kind
    of place it attaches to (junction, bond, storage, resistor, source,
    sensor, input), additive (scored by a score test) or structural (on a
    grid), and its title; the optional effects (scored only with
    ``--add-effects``) and the last resorts marked."""
    from bondgraph.diagnose.effects.library import DEFAULT_EFFECTS, OPTIONAL_EFFECTS

    lines = [f"{'effect':24s} {'attaches to':12s} {'scored':11s} what it is"]
    for eff in tuple(DEFAULT_EFFECTS) + tuple(OPTIONAL_EFFECTS):
        notes = []
        if eff in OPTIONAL_EFFECTS:
            notes.append("optional: --add-effects")
        if getattr(eff, "last_resort", False):
            notes.append("last resort")
        kind = "additive" if getattr(eff, "additive", False) else "structural"
        lines.append(f"{eff.name:24s} {str(getattr(eff, 'target_kind', '')):12s} {kind:11s} "
                     f"{eff.title}" + (f" ({'; '.join(notes)})" if notes else ""))
    return "\n".join(lines)
