"""Benchmark: cost of one UKF NLL evaluation against the number of particles
(parameter sets per call) and against the record length, numba and numpy
backends, and a profile of where the numba kernel's time goes.

Model ``vehicle_full`` on the synthetic ``vehicle_throttle_steps_high``
record (40 Hz), ROS2(1), parameter sets uniform in the box of the eight
stage-2 parameters of bench/estimation.py. Each point is timed once (the
machine is shared: read ratios, not absolute times). Compile time is
excluded (kernels compiled or loaded from numba's cache first).

Profile: per-call time of the generated point kernels f, h and f_dfdx
(a compiled loop over one point), times the calls per particle and sample
of the filter (ROS2: 2 f per sigma point, one f_dfdx at the central point;
one h per sigma point), against the kernel's measured time per particle and
sample with one thread; the rest is the filter's own arithmetic (Cholesky
factors, sigma points, moments, the W inverse, the update).

Usage::

    .venv/bin/python bench/scaling.py [--out bench/results]

Writes ``scaling.png`` and ``scaling.json`` into ``--out``; the last line
printed is JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import matplotlib
import numba
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from estimation import PARAMS, load_record  # noqa: E402

from bondgraph.inference import ukf_numba  # noqa: E402
from bondgraph.inference.options import UKFOptions  # noqa: E402
from bondgraph.inference.ukf import default_P0, ukf_nll  # noqa: E402
from bondgraph.numerics.compiled import point_kernels  # noqa: E402
from bondgraph.numerics.model import Model  # noqa: E402

PARTICLES = (1, 5, 10, 20, 40, 80, 160)
LENGTHS = (100, 200, 400, 800, 1600, 2400)


def timed(m, t, u, y, th, x0, P0, backend: str) -> float:
    """Seconds of one ukf_nll call (the kernels are compiled before: main)."""
    t0 = time.perf_counter()
    ukf_nll(m, t, u, y, th, x0, P0, options=UKFOptions(backend=backend))
    return time.perf_counter() - t0


@numba.njit
def _loop(f, x, u, th, out, n):
    s = 0.0
    for _ in range(n):
        x[0] += 1e-12
        f(x, u, th, out)
        s += out[0]
    return s


@numba.njit
def _loop_j(f, x, u, th, out, J, n):
    s = 0.0
    for _ in range(n):
        x[0] += 1e-12
        f(x, u, th, out, J)
        s += out[0]
    return s


def point_costs(m, x, u, th, n=100_000) -> dict:
    """Seconds per call of the point kernels f, h, f_dfdx."""
    pk = point_kernels(m)
    out, yo, J = np.zeros(m.n_x), np.zeros(m.n_y), np.zeros((m.n_x, m.n_x))
    x = np.ascontiguousarray(x, float).copy()
    res = {}
    for name, fn, o in (("f", pk.f, out), ("h", pk.h, yo)):
        _loop(fn, x, u, th, o, 10)
        t0 = time.perf_counter()
        _loop(fn, x, u, th, o, n)
        res[name] = (time.perf_counter() - t0) / n
    _loop_j(pk.f_dfdx, x, u, th, out, J, 10)
    t0 = time.perf_counter()
    _loop_j(pk.f_dfdx, x, u, th, out, J, n)
    res["f_dfdx"] = (time.perf_counter() - t0) / n
    return res


def profile(m, t, u, y, th, x0, P0) -> dict:
    """Where the kernel's time goes (one thread): point kernels vs the rest."""
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        s = timed(m, t, u, y, th, x0, P0, "numba")
    finally:
        numba.set_num_threads(threads)
    per = s / (th.shape[0] * t.size)
    c = point_costs(m, x0, np.ascontiguousarray(u[0]), np.ascontiguousarray(th[0]))
    npt = 2 * m.n_x + 1
    f_s, h_s, j_s = 2 * npt * c["f"], npt * c["h"], c["f_dfdx"]
    rest = per - f_s - h_s - j_s
    return dict(per_particle_sample_s=per, point_kernel_s=c, f_share=f_s / per,
                h_share=h_s / per, f_dfdx_share=j_s / per, rest_share=rest / per,
                calls_per_particle_sample=dict(f=2 * npt, h=npt, f_dfdx=1))


def plot(res: dict, path: Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for backend, style in (("numba", "o-"), ("numpy", "s--")):
        P = [r["particles"] for r in res["particles"][backend]]
        axes[0].loglog(P, [r["s_per_eval"] * 1e3 for r in res["particles"][backend]], style,
                       label=backend)
        N = [r["samples"] for r in res["length"][backend]]
        axes[1].loglog(N, [r["s_per_eval"] * 1e3 for r in res["length"][backend]], style,
                       label=backend)
    axes[0].set_xlabel("particles per call")
    axes[0].set_title(f"{res['samples_particles']} samples")
    axes[1].set_xlabel("record length [samples at 40 Hz]")
    axes[1].set_title(f"{res['particles_length']} particles per call")
    for ax in axes:
        ax.set_ylabel("time per NLL evaluation [ms]")
        ax.grid(alpha=0.3, which="both")
        ax.legend()
    fig.suptitle(f"{res['model']}, ROS2(1): cost per evaluation (shared 2-core machine, "
                 f"{res['threads']} numba threads)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default=str(ROOT / "bench" / "results"))
    p.add_argument("--model", default="vehicle_full")
    p.add_argument("--experiment", default="vehicle_throttle_steps_high")
    p.add_argument("--samples", type=int, default=400, help="record length of the particle sweep")
    p.add_argument("--particles", type=int, default=80, help="particles of the length sweep")
    args = p.parse_args(argv)
    warnings.simplefilter("ignore")
    m = Model.load(args.model)
    t, u, y, truth, x0 = load_record(args.experiment, m, None)
    P0 = default_P0(m, x0, 0.01)
    lo, hi = m.bounds(PARAMS)
    rng = np.random.default_rng(0)
    th_all = m.expand_theta(PARAMS, lo + rng.random((max(PARTICLES), len(PARAMS))) * (hi - lo),
                            truth)
    t0 = time.perf_counter()
    point_kernels(m)
    ukf_numba.kernel()
    compile_s = time.perf_counter() - t0
    res = dict(model=m.name, experiment=args.experiment, threads=numba.get_num_threads(),
               compile_s=compile_s, samples_particles=args.samples,
               particles_length=args.particles, particles={}, length={})
    n = args.samples
    for backend in ("numba", "numpy"):
        res["particles"][backend] = [
            dict(particles=P, samples=n,
                 s_per_eval=timed(m, t[:n], u[:n], y[:n], th_all[:P], x0, P0, backend) / P)
            for P in PARTICLES]
        res["length"][backend] = [
            dict(particles=args.particles, samples=N,
                 s_per_eval=timed(m, t[:N], u[:N], y[:N], th_all[:args.particles], x0, P0,
                                  backend) / args.particles)
            for N in LENGTHS if N <= t.size]
        for r in res["particles"][backend] + res["length"][backend]:
            print(f"{backend:5s} P={r['particles']:4d} N={r['samples']:5d}: "
                  f"{r['s_per_eval'] * 1e3:8.2f} ms per evaluation", flush=True)
    res["profile"] = profile(m, t[:n], u[:n], y[:n], th_all[:args.particles], x0, P0)
    pr = res["profile"]
    print(f"profile (1 thread): {pr['per_particle_sample_s'] * 1e6:.1f} us per particle and "
          f"sample; f {pr['f_share']:.0%}, h {pr['h_share']:.0%}, f_dfdx "
          f"{pr['f_dfdx_share']:.0%}, filter arithmetic {pr['rest_share']:.0%}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plot(res, out / "scaling.png")
    (out / "scaling.json").write_text(json.dumps(res, indent=1))
    print(json.dumps(dict(png=str(out / "scaling.png"), profile=pr)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
