"""Tables of ``docs/vehicle.md`` generated from the graphs, so they stay true.

``python -m vehicle_graphs.doc params`` prints the parameter table (the
test ``tests/test_vehicle_docs.py`` checks that docs/vehicle.md contains
exactly this text); ``python -m vehicle_graphs.doc models`` the state and
output lists of the registered models; ``python -m vehicle_graphs.doc
stiffness`` simulates every registered experiment (noise-free truth) and
prints the largest Jacobian eigenvalue along it and the RK4 sub-steps that
stability needs at 25 ms (takes ~30 s).
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
    from bondgraph.model import Model

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

    from bondgraph.experiments import get_experiment, sample_times
    from bondgraph.model import Model
    from bondgraph.simulate import simulate, stiffness_report

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


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    what = argv[0] if argv else "params"
    table = {"params": param_table, "models": models_table, "stiffness": stiffness_table}
    if what not in table:
        print(f"usage: python -m vehicle_graphs.doc [{'|'.join(table)}]", file=sys.stderr)
        return 2
    print(table[what]())
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
