"""Speed of the tracker: the batch tracker (compiled UKF kernel, detection,
smoothing) and the streaming ``Tracker.update`` (numpy), as multiples of real
time, on the mass-spring-damper tracking two parameters (c, k), 10 min at 100 Hz.

Usage: .venv/bin/python bench/tracking.py [--minutes M]
The last line is JSON.
"""

import argparse
import json
import time

import numpy as np

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.inference.options import TrackOptions, UKFOptions
from bondgraph.inference.problem import make_problem
from bondgraph.inference.track import Tracker, TrackingModel, track
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=10.0)
    a = ap.parse_args()
    g = mass_spring_damper()
    base = Model.from_graph(g)
    rng = np.random.default_rng(0)
    dt, T = 0.01, 60.0 * a.minutes
    t = np.arange(0.0, T, dt)
    F = np.repeat(rng.normal(0, 5, int(T / 0.5) + 1), 50)[:t.size, None]
    y = simulate(base, t, F, hold="zoh", method="rk4", substeps=4).y
    y = y + rng.normal(0, 1, y.shape) * np.array([0.002, 0.01])
    tm = TrackingModel.from_graph(g, ["c", "k"], {"c": 0.01, "k": 0.1})
    pr = make_problem(base, (t, F, y), ukf=UKFOptions(method="rk4", substeps=2))
    track(make_problem(base, (t[:200], F[:200], y[:200]), ukf=pr.ukf), tm)   # compile
    out = {}
    for smooth in (False, True):
        t0 = time.perf_counter()
        res = track(pr, tm, options=TrackOptions(smooth=smooth))
        wall = time.perf_counter() - t0
        key = "batch_smoothed" if smooth else "batch_filtered"
        out[key] = dict(wall_s=wall, realtime_x=T / wall, changes=len(res.changes))
        print(f"{key}: {wall:.3f} s for {T:.0f} s of record = {T / wall:.0f}x real time, "
              f"{len(res.changes)} changes")
    n = min(t.size, 6000)
    trk = Tracker.from_problem(pr, tm)
    t0 = time.perf_counter()
    for k in range(n):
        trk.update(t[k], F[k], y[k])
    wall = time.perf_counter() - t0
    out["update_numpy"] = dict(wall_s=wall, samples=n, us_per_sample=1e6 * wall / n,
                               realtime_x=n * dt / wall)
    print(f"Tracker.update (numpy): {1e6 * wall / n:.0f} us/sample = {n * dt / wall:.1f}x real "
          f"time at {1 / dt:.0f} Hz")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
