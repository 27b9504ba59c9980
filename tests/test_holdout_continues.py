"""The held-out last part of a record continues the fitted part
(``runner.held_out`` marks it, ``meta["follows"]``): its free run may start
from the state the fitted part's filter ends in, carried over the one
interval between them (``fit.continued_state``), as well as from the start
fitted to its own outputs; the run with the lower error is taken.

The reference is the truth the record was simulated from: a user's
mass-spring-damper (position measured, velocity not) driven by a multisine
force, integrated by scipy's solve_ivp at tight tolerances with a dense
solution, so the true state at the held-out part's first sample is known.
"""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph import BondGraph
from bondgraph.data.records import Experiment
from bondgraph.diagnose import fit as F
from bondgraph.diagnose.metric import nrmse
from bondgraph.diagnose.runner import held_out
from bondgraph.diagnose.settings import LoopSettings
from bondgraph.inference.options import UKFOptions
from bondgraph.numerics.model import Model

TRUTH = {"m": 1.0, "k": 40.0, "c": 0.8}
NOISE, DT, N = 0.01, 0.02, 1000


def msd() -> BondGraph:
    g = BondGraph("msd_user", "a mass on a spring and a damper, pushed")
    f = g.input("F", "N", 0.0, "force")
    m = g.param("m", 1.0, "kg", (0.1, 10.0), "mass")
    k = g.param("k", 30.0, "N/m", (1.0, 500.0), "stiffness")
    c = g.param("c", 1.0, "N*s/m", (0.01, 10.0), "damping")
    v = g.one("v")
    g.connect(g.Se("push", f), v)
    g.connect(v, g.I("mass", m))
    spring = g.C("spring", stiffness=k)
    g.connect(v, spring)
    g.connect(v, g.R("damper", c))
    g.sensor("x", spring.q, unit="m", noise_std=NOISE, description="position")
    return g


def _force(t):
    fr = np.array([0.11, 0.37, 0.83, 1.3])
    return np.sum(np.sin(2 * np.pi * fr * np.asarray(t)[..., None] + np.arange(4)), axis=-1)


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    m, k, c = TRUTH["m"], TRUTH["k"], TRUTH["c"]
    t = np.arange(N) * DT

    def f(tt, z):      # z = (x, v); a continuous force (the filter holds it linearly)
        return [z[1], (_force(tt) - c * z[1] - k * z[0]) / m]

    sol = solve_ivp(f, (0.0, t[-1]), [0.05, 0.0], t_eval=t, rtol=1e-10, atol=1e-12,
                    dense_output=True)
    y = sol.y[0] + NOISE * np.random.default_rng(4).standard_normal(N)
    path = tmp_path_factory.mktemp("holdout") / "rec.csv"
    with open(path, "w") as fh:
        fh.write("t [s],F [N],x [m]\n")
        for row in zip(t.tolist(), _force(t).tolist(), y.tolist()):
            fh.write("%r,%r,%r\n" % row)
    return Experiment.load(path), sol


def _context(exp):
    s = LoopSettings(params=["k", "c"], holdout=0.25,
                     ukf=UKFOptions(method="rk4", substeps=2, hold="linear"))
    est, s = held_out(exp, s)
    model = Model.from_graph(msd())
    return F.Context.on(est, s, model, log=lambda _m: None, progress=False), model


def test_the_held_out_part_starts_where_the_fitted_part_ends(record):
    exp, sol = record
    ctx, model = _context(exp)
    val = ctx.settings.validation
    assert val.meta["follows"] == ctx.problem.record.name
    theta = model.theta(TRUTH)
    res = F.run_ukf(ctx.problem, theta[None, :], store=True)
    vp = F.validation_problem(ctx, ctx.problem)
    xc = F.continued_state(ctx, ctx.problem, vp, theta, res)
    # the truth at the held-out part's first sample: p = m·v, q = x
    x, v = sol.sol(val.t[0])
    truth = {"p_mass": TRUTH["m"] * v, "q_spring": x}
    got = dict(zip(model.states, xc))
    assert got["q_spring"] == pytest.approx(truth["q_spring"], abs=3 * NOISE)
    assert got["p_mass"] == pytest.approx(truth["p_mass"], abs=0.05 * np.ptp(sol.y[1]))
    # the loop's validation error takes that start where it is the better one:
    # never above the run from it, and at the noise level (the model is the truth)
    fit = F.evaluate_fit(ctx, ctx.problem, msd(), ["k", "c"], theta, "truth", {})
    held = F.sim_inputs(ctx.settings, vp.disc.hold, vp.arrays[1])
    yc = F._free_run_from(ctx, vp, theta, held, xc)
    y = vp.arrays[2]
    assert fit.validation_metric <= nrmse(y, yc) + 1e-12
    assert fit.validation_metric < 2 * NOISE / np.std(y)
    np.testing.assert_array_equal(fit.validation_sim_y.shape, y.shape)


def test_a_separate_validation_record_is_not_continued(record):
    """A validation record of its own (``--validate``) does not follow the
    fitted one: no continued start."""
    exp, _ = record
    ctx, model = _context(exp)
    other = exp.segment(800)            # not marked: as a record loaded on its own
    assert "follows" not in other.meta
    ctx.settings = LoopSettings(params=["k", "c"], validation=other,
                                ukf=ctx.settings.ukf)
    theta = model.theta(TRUTH)
    res = F.run_ukf(ctx.problem, theta[None, :], store=True)
    vp = F.validation_problem(ctx, ctx.problem)
    assert F.continued_state(ctx, ctx.problem, vp, theta, res) is None
