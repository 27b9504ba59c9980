"""Benchmark: 8080 UKF negative log-likelihood evaluations of the vehicle filter model.

The estimation the original work abandoned: 8 parameters, a particle swarm of
80 particles x 100 iterations plus the initial swarm = 8080 evaluations of a
UKF likelihood over a 60 s, 40 Hz record of the full vehicle model.

Measured in the same run:

* the toolkit: :func:`bondgraph.inference.estimate.Criterion` (batched UKF, one call per
  swarm) inside :func:`bondgraph.inference.optimize.pso`, the full 8080 evaluations;
* the baseline: filterpy's ``UnscentedKalmanFilter`` (``MerweScaledSigmaPoints``)
  evaluated particle by particle over the same model and data, as a user
  would write it: ``fx`` = RK4 with 8 sub-steps over the generated model
  function (the filterpy + RK4 set-up of the original work); and, for a
  like-for-like ratio, ``fx`` = ROS2 (bondgraph.numerics.integrators.ros2, Jacobian at
  each sigma point). A few particles over the first samples are timed and
  scaled to the full record.

Also writes a PNG of the NLL along a line through the parameter box for
α = 1e-3, 1e-2, 0.1, 1 (``--line-plot``).

``--backend numba|numpy`` chooses the toolkit's likelihood (default: numba
when it imports). The numba kernels are compiled (or loaded from numba's
on-disk cache) before the timing starts; that time is reported separately
as ``compile_s`` (``compile_from_cache`` says whether it was a cache load).
``cpu_s`` is the process CPU time of the timed run (all threads of this
process; not the Dask workers'), ``load_start``/``load_end`` the load average.
With ``--workers`` > 1 one warm-up batch at the box centre starts the worker
processes and loads their kernels before the timing too (``warmup_s``).

Usage::

    .venv/bin/python bench/estimation.py            # full: 8080 evaluations
    .venv/bin/python bench/estimation.py --quick    # CI: < 1 min, same keys
    .venv/bin/python bench/estimation.py --backend numpy

The last line printed is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bondgraph.inference.estimate import Criterion  # noqa: E402
from bondgraph.inference import ukf_numba  # noqa: E402
from bondgraph.inference.options import (  # noqa: E402
    DEFAULT_BACKEND,
    Discretisation,
    Evaluation,
    FitOptions,
    SwarmOptions,
    UKFOptions,
)
from bondgraph.inference.prior import PriorSpec  # noqa: E402
from bondgraph.inference.problem import NoiseSpec, make_problem  # noqa: E402
from bondgraph.numerics.compiled import point_kernels  # noqa: E402
from bondgraph.numerics.model import Model  # noqa: E402
from bondgraph.inference.optimize import pso  # noqa: E402
from bondgraph.inference.ukf import default_P0, discretisation_check  # noqa: E402

RESULT = Path(__file__).with_name("results") / "estimation.json"   # the current result

#: stage-2 candidates of the vehicle (engine map, clutch, CVT shift, tire)
PARAMS = ["T_pk", "k_fw", "k_h", "w_eng", "mu_cl", "c_cl", "k_slip", "J_e"]


def load_record(experiment: str, model: Model, seconds: float | None):
    from bondgraph.data.experiments import run_experiment

    exp = run_experiment(experiment)
    t, u, y = exp.t, exp.inputs_for(model), exp.outputs_for(model)
    if seconds is not None:
        n = int(round(seconds / float(np.median(np.diff(t))))) + 1
        t, u, y = t[:n], u[:n], y[:n]
    meta = exp.meta
    truth = {k: v for k, v in (meta.get("true_parameters") or {}).items() if k in model.params}
    x0 = model.state({k: v for k, v in (meta.get("x0") or {}).items() if k in model.states})
    return t, u, y, model.theta(truth), x0


def baseline_seconds(model, t, u, y, thetas, x0, P0, fx_kind, n_steps, alpha=1.0):
    """Seconds per NLL evaluation of filterpy's UKF over the whole record,
    from timing ``len(thetas)`` particles over the first ``n_steps`` samples."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    from bondgraph.numerics.integrators import ros2

    n = model.n_x
    mod = model.module
    total = 0.0
    steps = 0
    crashes = [0]
    lls = []
    for th in thetas:
        pts = MerweScaledSigmaPoints(n, alpha, 2.0, 0.0)
        R = np.diag(model.meas_std(th) ** 2)
        Qc = model.proc_std(th) ** 2
        if fx_kind == "rk4":
            def fx(s, dt, u):
                return mod.fx(s, dt, u, th, 8)
        else:
            def fx(s, dt, u):
                return ros2(model.f_dfdx, s, u, th, dt, 1, f=model.f)

        def hx(s, u):
            return model.h(s, u, th)

        ukf = UnscentedKalmanFilter(n, model.n_y, t[1] - t[0], hx=hx, fx=fx, points=pts)
        ukf.x, ukf.P, ukf.R = x0.copy(), P0.copy(), R
        ukf.sigmas_f = pts.sigma_points(ukf.x, ukf.P)
        ll = 0.0
        t0 = time.perf_counter()
        done = 0
        try:
            for k in range(n_steps):
                if k > 0:
                    dt = t[k] - t[k - 1]
                    ukf.Q = np.diag(Qc * dt)
                    ukf.predict(dt=dt, u=u[k - 1])
                ukf.update(y[k], hx=hx, u=u[k])
                ll += ukf.log_likelihood
                done += 1
        except np.linalg.LinAlgError:
            # filterpy has no guard: its Cholesky raises for this particle;
            # keep the time of the completed samples
            ll = np.nan
            crashes[0] += 1
        total += time.perf_counter() - t0
        steps += max(done, 1)
        lls.append(ll)
    per_eval = total / steps * len(t)
    return per_eval, lls, crashes[0]


def line_plot(model, t, u, y, base, x0, P0, path, method, substeps, npts=41):
    """NLL along the diagonal of the box of PARAMS for four values of α."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo, hi = model.bounds(PARAMS)
    s = np.linspace(0.0, 1.0, npts)
    fig, ax = plt.subplots(figsize=(8, 4.5))
    out = {}
    for alpha in (1e-3, 1e-2, 0.1, 1.0):
        crit = Criterion(make_problem(model, (t, u, y), prior=PriorSpec(x0=x0, P0=P0),
                                      ukf=UKFOptions(alpha=alpha, method=method,
                                                     substeps=substeps)), PARAMS, base)
        f = crit(lo + s[:, None] * (hi - lo))
        out[alpha] = f
        ax.plot(s, f, label=f"α = {alpha:g}" + ("" if np.isfinite(f).all() else
                                              f" ({np.count_nonzero(~np.isfinite(f))} inf)"))
    ax.set_xlabel("position on the diagonal of the 8-parameter box (0 = lower, 1 = upper)")
    ax.set_ylabel("NLL [nats]")
    ax.set_title(f"{model.name}: NLL along a line through the box, {method}({substeps})")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return out


def compile_kernels(model, backend: str) -> tuple[float, bool | None]:
    """Compile (or load from numba's cache) the model's point kernels and the
    fused UKF kernel before timing: ``(seconds, loaded from cache)``."""
    if backend != "numba":
        return 0.0, None
    t0 = time.perf_counter()
    pk = point_kernels(model)
    ukf_numba.kernel()
    return time.perf_counter() - t0, bool(pk.from_cache)


#: stage 1: coast-down parameters with the reduced model on the coast-down record
STAGE1 = ["f_r", "C_dA", "r_dyn", "theta_off"]


def protocol(args) -> dict:
    """Two-stage protocol on synthetic vehicle records (bondgraph.inference.estimate.two_stage),
    10 particles per parameter, ``--iterations`` iterations per stage:
    stage 1 = STAGE1 with ``vehicle_coastdown`` on ``vehicle_coastdown``;
    stage 2 = PARAMS with ``vehicle_full`` on ``vehicle_throttle_steps_high``,
    stage-1 values fixed and their uncertainty propagated."""
    from bondgraph.inference.estimate import Stage, two_stage
    from bondgraph.data.experiments import run_experiment

    stages = []
    for name, model_name, exp_name, params in (
            ("coast-down", "vehicle_coastdown", "vehicle_coastdown", STAGE1),
            ("driving", "vehicle_full", "vehicle_throttle_steps_high", PARAMS)):
        from vehicle_graphs.analysis import initial_state

        model = Model.load(model_name)
        exp = run_experiment(exp_name)
        # the filter's own consistent initial state at the first measured
        # speed, from its default parameters (it does not know the truth)
        x0 = model.state(initial_state(model, None, v=float(exp["v_gnss"][0])))
        ukf = UKFOptions(method=args.method, substeps=args.substeps, hold=args.hold,
                         backend=args.backend)
        problem = make_problem(model, exp, prior=PriorSpec(x0=x0, P0=default_P0(model, x0, 0.01)),
                               noise=NoiseSpec("model"), ukf=ukf)
        stages.append(Stage(name, problem, params))
    t0 = time.perf_counter()
    res = two_stage(stages,
                    fit=FitOptions(iterations=args.iterations, seed=args.seed, progress=False,
                                   workers=args.workers))
    out = dict(protocol_wall_s=time.perf_counter() - t0, stages=[])
    for st, r in zip(stages, res):
        print(f"\n== stage {st.name}: {r.model} on {r.experiment}")
        print(r.table())
        std = r.std_total if r.std_total is not None else r.std
        z = {p: (r.estimates[i] - r.truth[p]) / std[i] for i, p in enumerate(r.params)
             if r.truth and p in r.truth}
        out["stages"].append(dict(stage=st.name, model=r.model, experiment=r.experiment,
                                  estimates=r.estimate_dict(), std=r.std.tolist(),
                                  std_total=None if r.std_total is None else r.std_total.tolist(),
                                  truth=r.truth, z=z, nll=r.nll, evaluations=r.evaluations,
                                  evaluations_total=r.evaluations_total, wall_s=r.wall_s,
                                  warnings=r.warnings))
        if args.out:
            Path(args.out).mkdir(parents=True, exist_ok=True)
            r.to_json(Path(args.out) / f"stage_{st.name}.json")
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="CI mode: short record, 3 iterations")
    p.add_argument("--model", default="vehicle_full")
    p.add_argument("--experiment", default="vehicle_throttle_steps_high")
    p.add_argument("--particles", type=int, default=80)
    p.add_argument("--iterations", type=int, default=100)
    p.add_argument("--method", default="ros2")
    p.add_argument("--substeps", type=int, default=1)
    p.add_argument("--baseline-particles", type=int, default=2)
    p.add_argument("--baseline-steps", type=int, default=60)
    p.add_argument("--line-plot", default=None, help="PNG of the NLL along a line (α sweep)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--hold", choices=("zoh", "mean"), default="zoh",
                   help="protocol: UKF input hold (mean: interval mean of ramps)")
    p.add_argument("--workers", type=int, default=1,
                   help="local Dask worker processes per batched evaluation")
    p.add_argument("--backend", choices=("numba", "numpy"), default=DEFAULT_BACKEND,
                   help="the toolkit's UKF likelihood")
    p.add_argument("--protocol", action="store_true",
                   help="run the two-stage protocol on the synthetic vehicle records instead")
    p.add_argument("--out", default=None, help="directory for the protocol's JSON results")
    p.add_argument("--result", default=None,
                   help="the result file (default bench/results/estimation.json for a full run; "
                        "none for --quick)")
    args = p.parse_args(argv)
    warnings.simplefilter("ignore")
    if args.protocol:
        print(json.dumps(protocol(args)))
        return 0

    model = Model.load(args.model)
    seconds = 10.0 if args.quick else None
    iterations = 3 if args.quick else args.iterations
    bsteps = 20 if args.quick else args.baseline_steps
    t, u, y, truth, x0 = load_record(args.experiment, model, seconds)
    P0 = default_P0(model, x0, 0.01)
    record_s = float(t[-1] - t[0] + (t[1] - t[0]))
    print(f"model {model.name}: {model.n_x} states, {model.n_y} outputs; record "
          f"{args.experiment}: {t.size} samples, {record_s:.1f} s")

    dc = discretisation_check(model, t, u, truth, x0,
                              Discretisation(args.method, args.substeps))
    print(f"discretisation {args.method}({args.substeps}) at the truth: one-step error "
          f"{np.max(dc['one_step']):.3g} noise std (worst output)")

    compile_s, from_cache = compile_kernels(model, args.backend)
    crit = Criterion(make_problem(model, (t, u, y), prior=PriorSpec(x0=x0, P0=P0),
                                  ukf=UKFOptions(method=args.method, substeps=args.substeps,
                                                 backend=args.backend)),
                     PARAMS, truth, where=Evaluation(workers=args.workers))
    lo, hi = model.bounds(PARAMS)
    warm_s, load0 = 0.0, os.getloadavg()[0]
    if args.workers > 1:
        # start the worker processes and load their kernels before the timing
        # (one evaluation per chunk; reported as warmup_s, like compile_s)
        t0 = time.perf_counter()
        crit(np.tile(0.5 * (lo + hi), (args.particles, 1)))
        warm_s = time.perf_counter() - t0
    t0, c0 = time.perf_counter(), time.process_time()
    res = pso(crit, lo, hi, progress=False,
              swarm=SwarmOptions(particles=args.particles, iterations=iterations, seed=args.seed))
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    crit.close()
    s_per_eval = wall / res.nfev
    print(f"toolkit: {res.nfev} evaluations in {res.ncalls} calls, {wall:.1f} s, "
          f"{s_per_eval * 1e3:.2f} ms per evaluation; best NLL {res.fun:.3f}; "
          f"{res.n_inf} failed evaluations {dict(crit.failures)}")

    rng = np.random.default_rng(1)
    bthetas = model.expand_theta(PARAMS, lo + rng.random((args.baseline_particles, len(PARAMS)))
                                 * (hi - lo), truth)
    b_rk4, _, c1 = baseline_seconds(model, t, u, y, bthetas, x0, P0, "rk4", bsteps)
    b_ros2, _, c2 = baseline_seconds(model, t, u, y, bthetas, x0, P0, "ros2", bsteps)
    print(f"filterpy UKF, particle by particle: RK4(8) fx {b_rk4:.3f} s per evaluation, "
          f"ROS2 fx {b_ros2:.3f} s per evaluation (timed over {bsteps} samples x "
          f"{args.baseline_particles} particles, scaled to {t.size} samples)")
    out = dict(
        backend=args.backend, compile_s=compile_s, compile_from_cache=from_cache,
        warmup_s=warm_s,
        model=model.name, experiment=args.experiment, record_s=record_s, samples=int(t.size),
        particles=args.particles, iterations=iterations, evaluations=int(res.nfev),
        calls=int(res.ncalls), wall_s=round(wall, 3), s_per_eval=s_per_eval,
        cpu_s=round(cpu, 3), load_start=load0, load_end=os.getloadavg()[0],
        workers=args.workers,
        minutes_for_8080=s_per_eval * 8080 / 60, method=args.method, substeps=args.substeps,
        baseline_s_per_eval=b_rk4, baseline="filterpy UKF, fx = RK4(8) over generated f",
        speedup=b_rk4 / s_per_eval,
        baseline_same_method_s_per_eval=b_ros2, speedup_same_method=b_ros2 / s_per_eval,
        nll_best=float(res.fun), n_inf=int(res.n_inf), baseline_crashes=int(c1 + c2),
        discretisation_one_step_noise_std=float(np.max(dc["one_step"])), quick=bool(args.quick))
    if args.line_plot:
        tl = min(t.size, 401)
        line_plot(model, t[:tl], u[:tl], y[:tl], truth, x0, P0, args.line_plot, args.method,
                  args.substeps, npts=21 if args.quick else 41)
        out["line_plot"] = args.line_plot
    text = json.dumps(out)
    result = args.result if args.result is not None else ("" if args.quick else str(RESULT))
    if result:
        Path(result).write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
