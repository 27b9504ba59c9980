"""Estimate the EMPS drive (M, Fv, Fc, offset) with the UKF likelihood and
compare with the published IDIM-LS values (Janot, Gautier & Brunot 2019).

The filter model is the ``emps`` bond graph (bondgraph/catalog/benchmarks.py):
force source gtau·vir, mass M, viscous friction Fv, Coulomb friction
Fc·tanh(v/1 mm/s), force offset; position sensor qm. Unmodelled forces
enter as process noise of intensity q_F on the momentum (estimated with the
others); the encoder noise is fixed at 1.5e-8 m (quantisation step 5e-8 m
over sqrt(12)).

The 1-kHz record is decimated (position every k-th sample, input averaged
over each interval). The first decimation runs the particle swarm; the
next ones start from its estimate (polish only), to show how the estimate
moves with the sampling rate.

Usage::

    .venv/bin/python examples/estimate_emps.py --decimate 10,5 --out emps_out
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bondgraph.catalog.benchmarks import (EMPS_IDIM_LS, EMPS_IDIM_RELERR, emps_arrays,  # noqa: E402
                                        emps_filtered_signals, emps_force_relerr, emps_idim_ls)
from bondgraph.inference.estimate import estimate  # noqa: E402
from bondgraph.inference.options import FitOptions, UKFOptions  # noqa: E402
from bondgraph.inference.prior import PriorSpec  # noqa: E402
from bondgraph.inference.problem import make_problem  # noqa: E402
from bondgraph.report.estimation import plot_fit  # noqa: E402
from bondgraph.numerics.model import Model  # noqa: E402

PARAMS = ["M", "Fv", "Fc", "offset", "q_F"]
FIXED = {"sigma_q": 1.5e-8}


def run(decimations, particles, iterations, out: Path, seed=0):
    from bondgraph.data.datasets import emps

    exp = emps("estimation", download=False)
    model = Model.load("emps")
    sig = emps_filtered_signals(exp)
    ls = emps_idim_ls(sig)
    rows = {"IDIM-LS published": dict(EMPS_IDIM_LS, relerr=emps_force_relerr(**EMPS_IDIM_LS,
                                                                            signals=sig)),
            "IDIM-LS (this code)": dict(ls, relerr=emps_force_relerr(**ls, signals=sig))}
    start = None
    results = {}
    for k in decimations:
        t, u, y = emps_arrays(exp, k)
        substeps = max(1, 20 // k)                    # ~1 ms integration step
        x0 = np.array([0.0, y[0, 0]])
        P0 = np.diag([1.0, 1e-10])
        t0 = time.perf_counter()
        fit = FitOptions(particles=particles, iterations=iterations if start is None else 0,
                         seed=seed, progress=False)
        problem = make_problem(model, (t, u, y), prior=PriorSpec(x0=x0, P0=P0),
                               ukf=UKFOptions(method="rk4", substeps=substeps), fixed=FIXED)
        res = estimate(problem, PARAMS, fit=fit, bounds={"q_F": (0.01, 20.0)}, start=start)
        res.settings["decimate"] = k
        res.settings["rate_hz"] = 1.0 / float(np.median(np.diff(t)))
        e = res.estimate_dict()
        rel = emps_force_relerr(e["M"], e["Fv"], e["Fc"], e["offset"], sig)
        rows[f"UKF ML, {res.settings['rate_hz']:.0f} Hz"] = dict(
            {p: e[p] for p in ("M", "Fv", "Fc", "offset")}, relerr=rel, q_F=e["q_F"],
            std={p: float(s) for p, s in zip(res.params, res.std)}, wall_s=time.perf_counter() - t0,
            evaluations=res.evaluations_total)
        start = res.estimates
        res.to_json(out / f"emps_result_{k}.json")
        plot_fit(model, (t, u, y), res, out, x0=x0, P0=P0, prefix=f"emps_{k}_")
        results[k] = res
        print(res.table(), flush=True)
    return rows, results


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--decimate", default="5", help="comma-separated decimation factors")
    p.add_argument("--particles", type=int, default=30)
    p.add_argument("--iterations", type=int, default=25)
    p.add_argument("--out", default="emps_out")
    args = p.parse_args(argv)
    warnings.simplefilter("ignore")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, _ = run([int(s) for s in args.decimate.split(",")], args.particles, args.iterations, out)
    print(f"\n{'':24}{'M [kg]':>9}{'Fv [Ns/m]':>11}{'Fc [N]':>8}{'offset [N]':>11}{'relerr':>8}")
    for name, r in rows.items():
        print(f"{name:24}{r['M']:>9.2f}{r['Fv']:>11.2f}{r['Fc']:>8.2f}{r['offset']:>11.3f}"
              f"{r['relerr']:>7.2f}%")
    print(f"(published relerr of IDIM-LS: {EMPS_IDIM_RELERR} %)")
    (out / "emps_summary.json").write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
