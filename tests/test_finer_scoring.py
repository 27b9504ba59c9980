"""A structural candidate whose law is stiffer than the loop's RK4 step is
scored at a finer step, not dropped as "could not be scored"
(:func:`bondgraph.diagnose.scoring.finer_if_failed`; issue 26: numerics that
meet their own check).

On a user's CVT driveline at 20 Hz (engine, torsional shaft, the belt as a
modulated transformer, the vehicle) the compliance and the slip behind the
belt, an end stop on the shaft and Dahl friction in its twist all failed at
the second sample of RK4(2), each grid point alike, and never competed.

Here a mass on a spring and a lightly damped damper, its velocity measured
every 50 ms: with k = 2e5 N/m, m = 1 kg the mode is ω = √(k/m) = 447.2 rad/s.
RK4's stability region meets the imaginary axis at |ωh| = 2√2 = 2.828
(hand-derived from R(iy) = 1 − y²/2 + y⁴/24 + i(y − y³/6)), so RK4(1)
(ωh = 22.4), RK4(2) and RK4(4) (5.59) are unstable and RK4(8) (2.795) is
the first stable step of the doubling.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bondgraph import BondGraph
from bondgraph.data.records import Experiment
from bondgraph.diagnose import scoring
from bondgraph.diagnose.fit import Context, model_of
from bondgraph.diagnose.settings import LoopSettings
from bondgraph.inference.options import UKFOptions
from bondgraph.inference.problem import make_problem

DT, NOISE, STIFF = 0.05, 0.01, 2e5


def spring_mass() -> BondGraph:
    g = BondGraph("spring_mass", "a force-driven mass on a spring and a damper")
    m = g.param("m", 1.0, "kg", (0.1, 10.0), "mass")
    k = g.param("k", 100.0, "N/m", (1.0, 1e7), "spring")
    b = g.param("b", 1.0, "N*s/m", (0.01, 100.0), "damper")
    v = g.one("v", domain="translation")
    g.connect(g.Se("push", g.input("F", "N", 0.0, "force")), v)
    g.connect(v, g.I("mass", m))
    g.connect(v, g.R("damper", b))
    g.connect(v, g.C("spring", stiffness=k))
    g.sensor("v", v.f, unit="m/s", noise_std=NOISE)
    return g


@pytest.fixture(scope="module")
def case():
    model = model_of(spring_mass())
    t = np.arange(400) * DT
    y = NOISE * np.random.default_rng(0).standard_normal((t.size, 1))
    rec = Experiment.from_arrays(t, model=model, u=np.sin(np.pi * t)[:, None], y=y,
                                 name="spring", noise_std={"v": NOISE})
    return model, rec


def context(model, rec, method: str, logs: list) -> Context:
    pb = make_problem(model, rec, ukf=UKFOptions(method=method, substeps=1, hold="linear"))
    return Context(problem=pb, settings=LoopSettings(params=["m"]), log=logs.append)


def test_a_stiff_candidate_is_scored_at_the_first_stable_doubling(case):
    """k = 2e5: RK4(1) fails at every set; the grid runs again at RK4(8),
    the first stable doubling (hand-derived above), its NLL that of a
    problem made at RK4(8) directly, and the line says so."""
    model, rec = case
    logs: list[str] = []
    ctx = context(model, rec, "rk4", logs)
    stiff = np.array([model.theta({"m": 1.0, "k": STIFF, "b": 1.0})])
    assert not np.isfinite(scoring.run_ukf(ctx.problem, stiff).nll).any()
    finer, r = scoring.finer_if_failed(ctx, model, stiff, "spring @ v")
    assert finer.problem.disc.substeps == 8 and ctx.problem.disc.substeps == 1
    direct = scoring.run_ukf(ctx.problem.conditioned_on(
        disc=replace(ctx.problem.disc, substeps=8, refine=())), stiff).nll
    assert np.isfinite(r.nll).all() and r.nll == pytest.approx(direct, rel=1e-9)
    (line,) = logs
    assert "spring @ v: the filter fails at every point of its grid with rk4(1)" in line
    assert line.endswith("scored with rk4(8)")


def test_a_step_that_runs_or_an_l_stable_method_is_kept(case):
    """A soft spring (k = 100: ωh = 0.5) runs at RK4(1): the context is the
    loop's, nothing logged; k = 1e7 (ωh = 19.8 even at RK4(8)) fails at every
    doubling: the loop's context and its failure come back for the candidate
    to be reported as failed; ROS2 is not retried."""
    model, rec = case
    logs: list[str] = []
    ctx = context(model, rec, "rk4", logs)
    soft = np.array([model.theta({"m": 1.0, "k": 100.0, "b": 1.0})])
    same, r = scoring.finer_if_failed(ctx, model, soft, "soft")
    assert same is ctx and np.isfinite(r.nll).all() and not logs
    stiffer = np.array([model.theta({"m": 1.0, "k": 1e7, "b": 1.0})])
    same, r = scoring.finer_if_failed(ctx, model, stiffer, "stiffer")
    assert same is ctx and not np.isfinite(r.nll).any() and not logs
    ros2 = context(model, rec, "ros2", logs)
    same, _ = scoring.finer_if_failed(ros2, model, stiffer, "ros2")
    assert same is ros2 and not logs
