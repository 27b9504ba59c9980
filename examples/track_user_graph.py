"""Track a parameter of your own bond graph and detect when it changes.

A damper whose coefficient doubles at t = 30 s (simulated here): the batch
tracker over the whole record, then the streaming tracker fed one sample at a
time, as on-line (its alarm raised at the sample that shows the change).
Replace ``build`` and the record with your own graph and data.

Run: .venv/bin/python examples/track_user_graph.py
"""

import numpy as np

from bondgraph.core.graph import BondGraph
from bondgraph.inference.options import TrackOptions, UKFOptions
from bondgraph.inference.problem import make_problem
from bondgraph.inference.track import Tracker, TrackingModel, track
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate


def build() -> BondGraph:
    g = BondGraph("my_damper")
    m = g.param("m", 2.0, "kg", (0.5, 8.0))
    k = g.param("k", 50.0, "N/m", (5.0, 500.0))
    c = g.param("c", 1.5, "N*s/m", (0.1, 20.0))
    v = g.one("v", domain="translation")
    g.connect(g.Se("force", g.input("F", "N")), v)
    g.connect(v, g.I("mass", m))
    spring = g.C("spring", stiffness=k)
    g.connect(v, spring)
    g.connect(v, g.R("damper", c))
    g.sensor("x", spring.q, unit="m", noise_std=0.002)
    g.sensor("v", v.f, unit="m/s", noise_std=0.01)
    return g


def main():
    g = build()
    model = Model.from_graph(g)
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 60.0, 0.01)
    F = np.repeat(rng.normal(0, 5, 121), 50)[:t.size, None]
    i = t.size // 2
    s1 = simulate(model, t[:i + 1], F[:i + 1], theta={"c": 1.5}, hold="zoh")
    s2 = simulate(model, t[i:], F[i:], x0=s1.x[-1], theta={"c": 3.0}, hold="zoh")
    y = np.vstack([s1.y[:-1], s2.y]) + rng.normal(0, 1, (t.size, 2)) * [0.002, 0.01]

    problem = make_problem(model, (t, F, y), ukf=UKFOptions(method="rk4", substeps=2))
    tm = TrackingModel.from_graph(g, ["c"], drift={"c": 0.0})      # c becomes a state
    res = track(problem, tm, options=TrackOptions(false_alarm_hours=10.0))
    for ch in res.changes:
        print(f"change of {ch.parameter} at t = {ch.time:.2f} s (alarm {ch.alarm_time:.2f} s): "
              f"{ch.before:.4f} ± {ch.before_std:.2g} -> {ch.after:.4f} ± {ch.after_std:.2g}")
    # on-line: one sample at a time as they arrive, the same test (one false alarm per 10 h)
    trk = Tracker.from_problem(problem, tm, options=TrackOptions(false_alarm_hours=10.0))
    for k in range(t.size):
        est, sd = trk.update(t[k], F[k], y[k])
        if k == 200:
            print(f"streaming after 2 s: c = {est[0]:.4f} ± {sd[0]:.2g}")
        if trk.alarm is not None:                                   # raised at this sample
            ch = trk.alarm
            print(f"on-line at t = {t[k]:.2f} s: {ch.parameter} changed at {ch.time:.2f} s: "
                  f"{ch.before:.4f} -> {est[0]:.4f} ± {sd[0]:.2g}")
    print(f"streaming at the end: c = {est[0]:.4f} ± {sd[0]:.2g}")


if __name__ == "__main__":
    main()
