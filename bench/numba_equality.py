"""Benchmark of accuracy: the numba UKF NLL against the numpy reference on
every registered model, ``--sets`` (default 100) random parameter sets drawn
uniformly from each model's box.

The record of each model is the one of tests/test_ukf_numba.py: 120 samples
at 100 Hz from the model's defaults (inputs modulated around INPUT_DEFAULTS,
RK4(8) truth, measurement noise, one missing and one partly missing sample).
The test runs 12 sets per model; this script runs the 100 of the issue.

Reports per model: the largest relative NLL difference over the sets both
backends finish, whether failures (sets, samples, reasons) are identical,
and the time of each backend. A set beyond 1e-9 is compared with the numpy
reference's own conditioning there: how far its NLL moves when the
parameters change by one unit in the last place; a difference within twice
that is rounding the reference itself cannot resolve ("explained"). Last
line: JSON, with ``strict`` (every set within 1e-9) and ``passed`` (every
set within 1e-9 or explained, failures identical).

Usage::

    .venv/bin/python bench/numba_equality.py [--sets 100] [--method ros2] [--substeps 1]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bondgraph.inference.options import UKFOptions  # noqa: E402
from bondgraph.inference.ukf import ukf_nll  # noqa: E402
from bondgraph.numerics import registry  # noqa: E402
from bondgraph.numerics.model import Model  # noqa: E402

RESULT = Path(__file__).with_name("results") / "numba_equality.json"   # the current result


def record(m: Model, N=120, dt=0.01, seed=0):
    """The test record of ``m`` (tests/test_ukf_numba.py::_record)."""
    t = np.arange(N) * dt
    mod = 1.0 + 0.3 * np.sin(np.arange(N) / 7.0)
    u = m.u0[None, :] * mod[:, None] + 0.1 * np.sin(np.arange(N) / 5.0)[:, None]
    x = m.x0[None].copy()
    ys = []
    for k in range(N):
        ys.append(m.h(x, u[k], m.theta0)[0])
        x = m.module.fx(x, dt, u[k], m.theta0, 8)
    rng = np.random.default_rng(seed)
    y = np.array(ys) + rng.normal(size=(N, m.n_y)) * m.meas_std(m.theta0[None])[0]
    y[3] = np.nan
    y[10, 0] = np.nan
    return t, u, y


def box_sets(m: Model, n: int, seed: int) -> np.ndarray:
    """``n`` sets uniform in the finite box (defaults where a bound is infinite)."""
    rng = np.random.default_rng(seed)
    th = np.tile(m.theta0, (n, 1))
    fin = np.isfinite(m.lower) & np.isfinite(m.upper)
    th[:, fin] = m.lower[fin] + rng.random((n, int(fin.sum()))) * (m.upper[fin] - m.lower[fin])
    return th


#: the issue's bound on the relative difference of the two backends' NLL
TOL = 1e-9


def reference_sensitivity(m: Model, rec, th: np.ndarray, nll: np.ndarray, opts: dict,
                          draws: int = 8) -> np.ndarray:
    """How far the numpy reference's own NLL moves when every parameter is
    changed by one unit in the last place (random signs, ``draws`` times):
    the largest relative change per set. A set whose NLL moves by more than
    TOL under a 1-ulp change of its parameters is ill-conditioned (here: a
    diffuse prior against a small measurement noise, whose first updates
    cancel), and no implementation agrees with the reference better than
    about this much."""
    if len(th) == 0:
        return np.zeros(0)
    t, u, y = rec
    rng = np.random.default_rng(11)
    worst = np.zeros(len(th))
    for _ in range(draws):
        th2 = th * (1.0 + rng.choice([-1.0, 1.0], th.shape) * np.finfo(float).eps)
        r = ukf_nll(m, t, u, y, th2, options=UKFOptions(backend="numpy", **opts))
        worst = np.maximum(worst, np.abs(r.nll - nll) / np.abs(nll))
    return worst


def compare(name: str, sets: int, opts: dict) -> dict:
    """Both backends on one model: largest relative difference, failures."""
    m = Model.load(name)
    t, u, y = record(m)
    th = box_sets(m, sets, seed=7)
    t0 = time.perf_counter()
    a = ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numpy", **opts))
    t1 = time.perf_counter()
    b = ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numba", **opts))
    t2 = time.perf_counter()
    ok = ~a.failed & ~b.failed
    rel = np.zeros(sets)
    rel[ok] = np.abs(a.nll[ok] - b.nll[ok]) / np.abs(a.nll[ok])
    same = (bool(np.array_equal(a.failed, b.failed)) and bool(np.array_equal(a.fail_step,
                                                                            b.fail_step))
            and a.reasons == b.reasons)
    over = np.flatnonzero(rel > TOL)
    ulp = reference_sensitivity(m, (t, u, y), th[over], a.nll[over], opts)
    unexplained = [int(i) for i, s in zip(over, ulp) if rel[i] > 2.0 * s]
    return dict(model=name, sets=sets, failed=int(a.failed.sum()), max_rel=float(rel.max()),
                n_over_1e9=len(over), ulp_sensitivity=[float(s) for s in ulp],
                unexplained=unexplained, same_failures=same,
                numpy_s=t1 - t0, numba_s=t2 - t1 - b.settings["compile_s"],
                compile_s=b.settings["compile_s"], backend_used=b.settings["backend_used"])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sets", type=int, default=100)
    p.add_argument("--method", default="ros2")
    p.add_argument("--substeps", type=int, default=1)
    p.add_argument("--models", default=None, help="comma-separated (default: all registered)")
    p.add_argument("--result", default=str(RESULT),
                   help="where the result goes ('' for nowhere)")
    args = p.parse_args(argv)
    names = args.models.split(",") if args.models else sorted(registry.registered())
    rows = []
    for name in names:
        r = compare(name, args.sets, dict(method=args.method, substeps=args.substeps))
        rows.append(r)
        ulp = (f" (numpy's own 1-ulp sensitivity there {max(r['ulp_sensitivity']):.2e}, "
               f"unexplained {len(r['unexplained'])})" if r["n_over_1e9"] else "")
        print(f"{name:26s} max rel {r['max_rel']:.2e}  >1e-9: {r['n_over_1e9']:3d}{ulp}  "
              f"failed {r['failed']:3d}  same failures {r['same_failures']}  "
              f"numpy {r['numpy_s']:.2f} s  numba {r['numba_s']:.2f} s "
              f"(+{r['compile_s']:.1f} s compile)", flush=True)
    passed = all(not r["unexplained"] and r["same_failures"] for r in rows)
    strict = all(r["max_rel"] <= TOL and r["same_failures"] for r in rows)
    text = json.dumps(dict(passed=passed, strict=strict, sets=args.sets, method=args.method,
                           substeps=args.substeps, worst=max(r["max_rel"] for r in rows),
                           models=rows))
    if args.result:
        Path(args.result).write_text(text + "\n")
    print(text)
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
