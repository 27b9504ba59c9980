"""Profile of the fused numba UKF kernel (bondgraph.inference.ukf_numba).

Times the kernel alone (``settings["run_s"]`` of :func:`ukf_nll`, compile
excluded) on the quick record of bench/estimation.py (vehicle_full,
vehicle_throttle_steps_high, 10 s at 40 Hz = 401 samples) for 80 parameter
sets from the box, ROS2 x 1 (the bench's setting), and splits the time:

* ``model``: the model's own point kernels (real f, h, f_dfdx);
* ``trivial``: the same filter with trivial point kernels of the same
  signature and sizes (f = -x, h = x[:n_y], J = -I): the filter's own
  arithmetic and call overhead;
* each with 1 thread and with all numba threads (does the kernel's thread pool use both?);
* the point kernels alone, called in a loop (cost per call).

Reports µs per particle-step (one predict + update of one set), wall and
process CPU time, best of ``--repeat`` runs (the machine is shared: say the
load, printed as ``load``; with one thread the CPU time is the steadier
figure under load).
Last line: JSON.

Usage::

    .venv/bin/python bench/kernel_profile.py [--repeat 5] [--method ros2] [--jacobian mean]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numba
import numpy as np
from numba import njit

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bondgraph.inference import ukf as ukf_module  # noqa: E402
from bondgraph.inference.options import UKFOptions  # noqa: E402
from bondgraph.inference.ukf import default_P0, ukf_nll  # noqa: E402
from bondgraph.numerics.compiled import point_kernels  # noqa: E402
from bondgraph.numerics.model import Model  # noqa: E402

sys.path.insert(0, str(ROOT / "bench"))
from estimation import PARAMS, load_record  # noqa: E402

RESULT = Path(__file__).with_name("results") / "kernel_profile.json"   # the current result


class _Trivial:
    """Point kernels of the same signatures as the generated ones."""

    def __init__(self, ny):
        V, M = numba.types.float64[::1], numba.types.float64[:, ::1]
        SIG_POINT, SIG_F_DFDX = numba.types.void(V, V, V, V), numba.types.void(V, V, V, V, M)

        @njit(SIG_POINT, nogil=True, error_model="numpy")
        def f(x, u, th, out):
            for a in range(x.shape[0]):
                out[a] = -x[a]

        @njit(SIG_POINT, nogil=True, error_model="numpy")
        def h(x, u, th, out):
            for b in range(out.shape[0]):
                out[b] = x[b]

        @njit(SIG_F_DFDX, nogil=True, error_model="numpy")
        def fj(x, u, th, out, J):
            n = x.shape[0]
            for a in range(n):
                out[a] = -x[a]
                for b in range(n):
                    J[a, b] = -1.0 if a == b else 0.0

        @njit(SIG_POINT, nogil=True, error_model="numpy")
        def f_cols(X, u, th, F):
            for i in range(X.shape[0]):
                F[i] = -X[i]

        @njit(SIG_POINT, nogil=True, error_model="numpy")
        def h_cols(X, u, th, Y):
            for i in range(Y.shape[0]):
                Y[i] = X[i]

        self.f, self.h, self.f_dfdx, self.f_cols, self.h_cols = f, h, fj, f_cols, h_cols


def time_kernel(model, kernels, t, u, y, th, x0, P0, opts, repeat):
    orig = ukf_module._backend_for
    ukf_module._backend_for = lambda *a, **k: (kernels, None, 0.0)
    try:
        best, cpu, nll = np.inf, np.inf, None
        for _ in range(repeat):
            c0 = time.process_time()
            res = ukf_nll(model, t, u, y, th, x0, P0, options=opts)
            cpu = min(cpu, time.process_time() - c0)
            best = min(best, res.settings["run_s"])
            nll = res.nll
    finally:
        ukf_module._backend_for = orig
    return best, cpu, nll


def time_points(pk, model, x0, th, n=20000):
    """µs per call of f, h and f_dfdx at one point (loop in numba)."""
    @njit
    def loop(fn, x, u, p, out, n):
        for _ in range(n):
            fn(x, u, p, out)

    @njit
    def loopj(fn, x, u, p, out, J, n):
        for _ in range(n):
            fn(x, u, p, out, J)

    x, u, p = x0.copy(), model.u0.copy(), th[0].copy()
    out, yv, J = np.zeros(model.n_x), np.zeros(model.n_y), np.zeros((model.n_x, model.n_x))
    res = {}
    for name, args in (("f", (pk.f, x, u, p, out)), ("h", (pk.h, x, u, p, yv))):
        loop(*args, 10)
        t0 = time.perf_counter()
        loop(*args, n)
        res[name] = (time.perf_counter() - t0) / n * 1e6
    loopj(pk.f_dfdx, x, u, p, out, J, 10)
    t0 = time.perf_counter()
    loopj(pk.f_dfdx, x, u, p, out, J, n)
    res["f_dfdx"] = (time.perf_counter() - t0) / n * 1e6
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--particles", type=int, default=80)
    ap.add_argument("--method", default="ros2")
    ap.add_argument("--substeps", type=int, default=1)
    ap.add_argument("--jacobian", default="mean")
    ap.add_argument("--result", default=str(RESULT),
                    help="where the result goes ('' for nowhere)")
    args = ap.parse_args(argv)
    model = Model.load("vehicle_full")
    t, u, y, truth, x0 = load_record("vehicle_throttle_steps_high", model, 10.0)
    P0 = default_P0(model, x0, 0.01)
    lo, hi = model.bounds(PARAMS)
    rng = np.random.default_rng(0)
    th = model.expand_theta(PARAMS, lo + rng.random((args.particles, len(PARAMS))) * (hi - lo),
                            truth)
    opts = UKFOptions(method=args.method, substeps=args.substeps, jacobian=args.jacobian,
                      backend="numba")
    pk = point_kernels(model)
    steps = args.particles * t.size
    out = dict(load=os.getloadavg()[0], particles=args.particles, samples=int(t.size),
               method=args.method, substeps=args.substeps, jacobian=args.jacobian,
               threads_max=numba.config.NUMBA_NUM_THREADS)
    for label, kern in (("model", pk), ("trivial", _Trivial(model.n_y))):
        for nt in (1, numba.config.NUMBA_NUM_THREADS):
            numba.set_num_threads(nt)
            ukf_nll(model, t[:3], u[:3], y[:3], th[:2], x0, P0, options=opts)  # warm
            s, cpu, nll = time_kernel(model, kern, t, u, y, th, x0, P0, opts, args.repeat)
            out[f"{label}_us_per_particle_step_{nt}thr"] = s / steps * 1e6
            out[f"{label}_cpu_us_per_particle_step_{nt}thr"] = cpu / steps * 1e6
            out[f"{label}_ms_per_eval_{nt}thr"] = s / args.particles * 1e3
            if label == "model" and nt == 1:
                out["nll_sum_finite"] = float(np.sum(nll[np.isfinite(nll)]))
                out["n_inf"] = int(np.sum(~np.isfinite(nll)))
    out["point_us"] = time_points(pk, model, x0, th)
    for k, v in out.items():
        print(f"{k}: {v}")
    text = json.dumps(out)
    if args.result:
        Path(args.result).write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
