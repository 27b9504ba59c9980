"""Per-point cost of the generated f (DC motor with compliant shaft) over a batch
of 10,000 points, against sympy.lambdify(cse=True) of the same equations, in the
same run. Target (issue 2): no slower than lambdify (about 0.23 us per point here).

The last line printed is one JSON object.

Usage: python bench/generated_f.py [--batch 10000] [--repeat 200]
"""

from __future__ import annotations

import argparse
import json
import timeit
from pathlib import Path

import numpy as np
import sympy as sp

from bondgraph.numerics.model import Model
from bondgraph.catalog.reference import dc_motor_compliant
from bondgraph.core.equations import derive

RESULT = Path(__file__).with_name("results") / "generated_f.json"   # the current result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=10_000)
    ap.add_argument("--repeat", type=int, default=40)
    ap.add_argument("--result", default=str(RESULT),
                    help="where the result goes ('' for nowhere)")
    args = ap.parse_args()
    model = Model.load("dc_motor_compliant")
    ss = derive(dc_motor_compliant())
    rng = np.random.default_rng(0)
    N = args.batch
    lam = sp.lambdify((ss.states, ss.inputs, ss.params), ss.f, modules="numpy", cse=True)

    def cases():
        x = rng.normal(size=(N, model.n_x))
        u = rng.normal(size=(N, model.n_u))
        th = model.theta0.copy()
        thN = model.theta0 * rng.uniform(0.9, 1.1, size=(N, model.n_theta))
        # (name, x, u, theta): identical arrays for both implementations; batch-major
        # input as a user or data file gives it, and state-major memory (what the
        # generated functions return, e.g. inside an integrator loop)
        yield "batch-major x, one theta", x, u, th
        yield "batch-major x, theta per point", x, u, thN
        yield "state-major x, one theta", np.asfortranarray(x), np.asfortranarray(u), th

    results = []
    for name, x, u, th in cases():
        def run_lambdify():
            # lambdify takes component-first arguments: pass transposed views
            # (no copies) and transpose the result back to (N, n_x)
            return np.array(lam(x.T, u.T, th.T)).T

        def run_generated():
            return model.f(x, u, th)

        np.testing.assert_allclose(run_generated(), run_lambdify(), rtol=1e-12)
        best = {}
        for impl, fn in (("generated", run_generated), ("lambdify_cse", run_lambdify)):
            times = timeit.repeat(fn, number=5, repeat=args.repeat)
            best[impl] = min(times) / 5 / N * 1e6
        ratio = best["lambdify_cse"] / best["generated"]
        results.append({"case": name, "generated_us_per_point": round(best["generated"], 5),
                        "lambdify_us_per_point": round(best["lambdify_cse"], 5),
                        "speed_ratio": round(ratio, 3)})
        print(f"{name:32s} generated {best['generated']:.4f} us/point, lambdify(cse=True) "
              f"{best['lambdify_cse']:.4f} us/point: {ratio:.2f}x")
    worst = min(r["speed_ratio"] for r in results)
    text = json.dumps({"model": "dc_motor_compliant", "batch": N, "cases": results,
                       "worst_speed_ratio": worst, "meets_target": worst >= 1.0})
    if args.result:
        Path(args.result).write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
