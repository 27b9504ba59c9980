"""``bondgraph linearize``: A, B, C, D of a model at an operating point or an
equilibrium (:func:`bondgraph.export.linearize.linearize`), written as
``.npz`` with a Bode plot."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bondgraph.cli.common import add_model, parse_pairs
from bondgraph.export.linearize import linearize
from bondgraph.export.params import read_params
from bondgraph.report.linearization import bode_plot


EXAMPLE = "bondgraph linearize hydraulic_tanks --at Q=1e-4 -o tanks.npz"


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph linearize``."""
    add_model(p, positional=True)
    p.add_argument("--at", default=None, metavar="NAME=VALUE,...",
                   help="states and inputs of the operating point (model units); inputs not "
                        "given: their defaults; states not all given: an equilibrium "
                        "f(x, u) = 0 for the inputs")
    p.add_argument("--params", metavar="JSON",
                   help="estimated parameters: `bondgraph estimate`'s result.json or "
                        "`bondgraph loop`'s report.json")
    p.add_argument("-o", "--output", default=None,
                   help="the .npz to write (default MODEL_linear.npz); the Bode plot goes "
                        "beside it as .png")
    p.add_argument("--no-plot", action="store_true", help="do not write the Bode plot")


def run(args) -> int:
    """Linearise, write the .npz (and the Bode PNG), print the poles."""
    params = read_params(args.params) if args.params else None
    lin = linearize(args.model, parse_pairs(args.at, "--at"), params=params)
    out = Path(args.output or f"{lin.model}_linear.npz")
    if out.suffix != ".npz":        # np.load and the Bode plot beside it expect it
        out = out.with_name(out.name + ".npz")
    lin.save(out)
    where = "equilibrium" if lin.equilibrium else "operating point"
    print(f"{lin.model}: {len(lin.states)} states, {len(lin.inputs)} inputs, "
          f"{len(lin.outputs)} outputs; {where} (max |dx/dt| = {lin.residual:.3g})")
    for name, value in zip(lin.states, lin.x):
        print(f"  {name} = {value:.10g}")
    for name, value in zip(lin.inputs, lin.u):
        print(f"  {name} = {value:.10g}")
    print("poles [1/s]:" if lin.states else
          "poles: none (no state: the outputs are algebraic functions of the inputs, D alone)")
    for p in lin.poles():
        print(f"  {p.real:.6g} {'+' if p.imag >= 0 else '-'} {abs(p.imag):.6g}j")
    for w in lin.warnings:
        print(f"warning: {w}", file=sys.stderr)
    print(f"wrote {out}")
    if not args.no_plot:
        png = bode_plot(lin, out.with_suffix(".png"))
        print(f"wrote {png}")
    return 0
