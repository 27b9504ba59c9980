"""Per-phase cost of one particle-step of the fused numba UKF kernel.

Runs the kernel's own inlined steps (:mod:`bondgraph.inference.ukf_numba`)
for one parameter set of vehicle_full (ROS2 x 1, shared Jacobian) in a
compiled loop, cumulatively, phase by phase, from the same state each
repetition (x0, P0 of bench/kernel_profile.py at the true parameters); the
difference of consecutive levels is the cost of a phase. Process CPU time,
best of ``--repeat``; with the model's point kernels and with trivial ones
(f = -x, h = x[:n_y], J = -I), so the filter's own arithmetic is separated
from the model's. The machine is shared: ``load`` is printed. Last line: JSON.

Under load the differences of times are noisy (a phase of 0.2 µs can read
±0.2 µs at load 6): compare variants of one helper in one process instead.
``--record FILE`` caches the record (npz).

Usage::

    .venv/bin/python bench/kernel_phases.py [--reps 20000] [--repeat 5]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from numba import njit

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bondgraph.inference import ukf_numba as K  # noqa: E402
from bondgraph.inference.ukf import default_P0  # noqa: E402
from bondgraph.numerics.compiled import point_kernels  # noqa: E402
from bondgraph.numerics.model import Model  # noqa: E402

sys.path.insert(0, str(ROOT / "bench"))
from estimation import load_record  # noqa: E402
from kernel_profile import _Trivial  # noqa: E402

RESULT = Path(__file__).with_name("results") / "kernel_phases.json"   # the current result

#: cumulative levels: level i runs phases 1..i
PHASES = ("reset x, P", "chol P + sigma (predict)", "f_dfdx at the centre",
          "W: LU factors", "ROS2 2 stages x 21 points", "finite check + moments(X) + q",
          "chol P + sigma + 21 h (update)", "moments(Y) + R", "Pxy",
          "chol S + innovation", "gain, x, P update, NLL term")


@njit(error_model="numpy", fastmath=getattr(K, "FASTMATH", False), cache=True)
def _levels(level, reps, f, h, fj, fcols, hcols, u, y, th, x0, P0, q2, Rd, ip, fp, buf, ibuf):
    n, ny, nu = x0.shape[0], y.shape[1], u.shape[1]
    wk, x, P, tha = K._work(buf, ibuf, n, ny, nu, th.shape[0])
    for i in range(th.shape[0]):
        tha[i] = th[i]
    k, dt = 5, 0.025
    hs = dt / ip[1]
    uk, yk = wk.uk, wk.yk
    for j in range(nu):
        uk[j] = u[k, j]
    for j in range(ny):
        yk[j] = y[k, j]
    acc = 0.0
    for _ in range(reps):
        for i in range(n):
            x[i] = x0[i]
            for j in range(n):
                P[i, j] = P0[i, j]
        lu = False
        if level >= 1:
            K._chol(P, n, wk.L, True, wk.skip)
            K._sigma(x, wk.L, fp[0], wk.XT)
        if level >= 2:
            K._held_input(u, k, 0.0, ip[3], wk.ub)
            fj(x, wk.ub, tha, wk.F0, wk.J)
        if level >= 3:
            lu = K._lu_w(wk.J, hs, wk.A, wk.cols)
            if not lu:
                K._inverse_w(wk.J, hs, wk.A, wk.Winv, wk.cols)
        if level >= 4:
            K._ros2_shared(fcols, u, k, ip[3], tha, hs, ip[1], wk, lu)
        if level >= 5:
            bad = not K._all_finite(wk.XT, n, wk.XT.shape[1])
            K._moments(wk.XT, n, fp[1], fp[2], x, P, wk.D)
            for a in range(n):
                P[a, a] += q2[a] * dt
            acc += bad
        m = ny
        if level >= 6:
            m, code = K._measured_outputs(hcols, x, P, tha, uk, yk, fp, wk)
        if level >= 7:
            K._moments(wk.Ym if m < ny else wk.YT, m, fp[1], fp[2], wk.yf, wk.cov, wk.D)
            for a in range(m):
                wk.cov[a, a] += Rd[wk.idx[a]]
        if level >= 8:
            K._cross_cov(n, m, fp[1], fp[0], wk)
        if level >= 9:
            K._chol(wk.cov, m, wk.Ls, False, wk.skip)
            for b in range(m):
                wk.eps[b] = yk[wk.idx[b]] - wk.yf[b]
        if level >= 10:
            term, maha = K._correct(x, P, m, wk)
            acc += term
        acc += x[0] + P[1, 1]
    return acc


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=20000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--record", default=None, help="npz cache of the record")
    ap.add_argument("--labels", default="model,trivial", help="point kernels: model, trivial")
    ap.add_argument("--result", default=str(RESULT),
                    help="where the result goes ('' for nowhere)")
    args = ap.parse_args(argv)
    model = Model.load("vehicle_full")
    if args.record and Path(args.record).exists():
        z = np.load(args.record)
        u, y, truth, x0 = z["u"], z["y"], z["truth"], z["x0"]
    else:
        t, u, y, truth, x0 = load_record("vehicle_throttle_steps_high", model, 10.0)
        if args.record:
            np.savez(args.record, u=u, y=y, truth=truth, x0=x0)
    P0 = default_P0(model, x0, 0.01)
    th = np.ascontiguousarray(truth, dtype=float)
    q2 = model.proc_std(th[None])[0] ** 2
    Rd = model.meas_std(th[None])[0] ** 2
    ip = np.array([1, 1, 0, 0, 0, 0, 0], dtype=np.int64)
    n = model.n_x
    c = np.sqrt(n + 1e-6 * 0 + 1.0)  # any scale: the cost does not depend on it
    w = 0.5 / (c * c)
    fp = np.array([c, w, 1.0])
    nf, ni = K._work_size(n, model.n_y, u.shape[1], th.size)
    out = dict(load=os.getloadavg()[0], reps=args.reps, repeat=args.repeat)
    kerns = {"model": lambda: point_kernels(model), "trivial": lambda: _Trivial(model.n_y)}
    for label in args.labels.split(","):
        kern = kerns[label]()
        cum = []
        for level in range(len(PHASES)):
            buf, ibuf = np.zeros(nf), np.zeros(ni, dtype=np.int64)
            a = (kern.f, kern.h, kern.f_dfdx, kern.f_cols, kern.h_cols, np.ascontiguousarray(u),
                 np.ascontiguousarray(y), th, np.ascontiguousarray(x0, dtype=float),
                 np.ascontiguousarray(P0), q2, Rd, ip, fp, buf, ibuf)
            _levels(level, 10, *a)
            best = np.inf
            for _ in range(args.repeat):
                c0 = time.process_time()
                _levels(level, args.reps, *a)
                best = min(best, time.process_time() - c0)
            cum.append(best / args.reps * 1e6)
        ph = {PHASES[0]: cum[0]}
        ph.update({PHASES[i]: cum[i] - cum[i - 1] for i in range(1, len(PHASES))})
        out[label] = ph
        out[label + "_total_us"] = cum[-1] - cum[0]
    out["load_end"] = os.getloadavg()[0]
    for p in PHASES:
        print(f"{p:34s}" + "".join(f" {lb} {out[lb][p]:7.3f} us" for lb in args.labels.split(",")))
    print(f"{'total (without reset)':34s}" + "".join(f" {lb} {out[lb + '_total_us']:7.3f} us"
                                                  for lb in args.labels.split(","))
          + f"   load {out['load']:.1f}")
    text = json.dumps(out)
    if args.result:
        Path(args.result).write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
