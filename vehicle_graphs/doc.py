"""Tables of ``docs/vehicle.md`` generated from the graphs, so they stay true.

``python -m vehicle_graphs.doc params`` prints the parameter table (the
test ``tests/test_vehicle_docs.py`` checks that docs/vehicle.md contains
exactly this text); ``python -m vehicle_graphs.doc models`` the state and
output lists of the registered models; ``python -m vehicle_graphs.doc
stiffness`` simulates every registered experiment (noise-free truth) and
prints the largest Jacobian eigenvalue along it and the RK4 sub-steps that
stability needs at 25 ms (takes ~30 s); ``python -m vehicle_graphs.doc update
[params models stiffness]`` rewrites those blocks of docs/vehicle.md.
"""

from __future__ import annotations

import sys

from .params import PARAMS


def _fmt(v: float) -> str:
    return f"{v:.6g}"


def param_table() -> str:
    """Markdown table of every parameter of the vehicle graphs.

    Columns: name, group, meaning, unit, default, bounds, source; the
    models a parameter appears in depend on the configuration (see
    docs/vehicle.md).
    """
    rows = ["| name | group | meaning | unit | default | bounds | source |",
            "|---|---|---|---|---|---|---|"]
    for p in PARAMS:
        unit = p.unit or "-"
        rows.append(f"| `{p.name}` | {p.group} | {p.description} | {unit} | {_fmt(p.default)} | "
                    f"[{_fmt(p.bounds[0])}, {_fmt(p.bounds[1])}] | {p.source} |")
    return "\n".join(rows)


def models_table() -> str:
    """Markdown list of the registered vehicle models: states, inputs,
    outputs, number of parameters (from the generated modules)."""
    from bondgraph.numerics.model import Model

    from . import MODELS

    rows = ["| model | states | inputs | outputs | parameters |", "|---|---|---|---|---|"]
    for name in MODELS:
        m = Model.load(name)
        rows.append(f"| `{name}` | {m.n_x}: {', '.join(m.states)} | {', '.join(m.inputs)} | "
                    f"{', '.join(m.outputs)} | {m.n_theta} |")
    return "\n".join(rows)


def stiffness_table() -> str:
    """Largest |Re lambda| of df/dx along each registered experiment's
    noise-free truth trajectory, and the RK4 sub-steps per 25 ms sample that
    stability needs (maximum and median over the trajectory)."""
    import numpy as np

    from bondgraph.data.experiments import get_experiment, sample_times
    from bondgraph.numerics.model import Model
    from bondgraph.numerics.simulate import simulate, stiffness_report

    from . import EXPERIMENTS

    rows = ["| experiment | model simulated | max abs(Re lambda) [1/s] | at t [s] | "
            "RK4 sub-steps (max / median) |", "|---|---|---|---|---|"]
    for name in EXPERIMENTS:
        spec = get_experiment(name)
        model = Model.load(spec.truth_model or spec.model)
        t = sample_times(spec)
        res = simulate(model, t, u={k: f for k, f in spec.inputs.items() if k in model.inputs},
                       x0=spec.x0, theta=model.theta(spec.params), rtol=1e-6, atol=1e-8)
        rep, _ = stiffness_report(model, res, every=4)
        subs = [s["rk4_substeps"] for s in rep["samples"]]
        rows.append(f"| {name} | {model.name} | {rep['max_abs_re']:.0f} | "
                    f"{rep['t_max_abs_re']:.1f} | {max(subs)} / {int(np.median(subs))} |")
    return "\n".join(rows)


#: blocks of docs/vehicle.md written by :func:`update_docs`
BLOCKS = {"PARAMS": param_table, "MODELS": models_table, "STIFFNESS": stiffness_table}


def doc_path():
    """Path of docs/vehicle.md (next to this package in the checkout)."""
    from pathlib import Path

    return Path(__file__).resolve().parent.parent / "docs" / "vehicle.md"


def _block_match(text: str, block: str):
    import re

    m = re.search(rf"<!-- BEGIN {block}\b[^>]*-->\n(.*?)\n<!-- END {block} -->", text, re.S)
    if not m:
        raise KeyError(f"docs/vehicle.md has no block {block}")
    return m


def doc_block(text: str, block: str) -> str:
    """Content between ``<!-- BEGIN block ... -->`` and ``<!-- END block -->``.

    Raises
    ------
    KeyError
        If the markers are missing.
    """
    return _block_match(text, block).group(1)


def update_docs(blocks=("PARAMS", "MODELS"), path=None) -> list[str]:
    """Rewrite the generated blocks of docs/vehicle.md; returns the blocks
    that changed. ``STIFFNESS`` runs every experiment (~30 s)."""
    path = path or doc_path()
    text = path.read_text()
    changed = []
    for b in blocks:
        m = _block_match(text, b)
        new = BLOCKS[b]()
        if m.group(1) != new:
            text = text[:m.start(1)] + new + text[m.end(1):]
            changed.append(b)
    path.write_text(text)
    return changed


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    what = argv[0] if argv else "params"
    table = {"params": param_table, "models": models_table, "stiffness": stiffness_table}
    if what == "update":
        blocks = [b.upper() for b in argv[1:]] or ["PARAMS", "MODELS"]
        print("updated:", ", ".join(update_docs(blocks)) or "nothing")
        return 0
    if what not in table:
        print(f"usage: python -m vehicle_graphs.doc [{'|'.join(table)}|update [blocks]]",
              file=sys.stderr)
        return 2
    print(table[what]())
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
