"""Which structural candidates the loop profiles (issue 27): the gain a
Fisher-scoring step predicts, checked against the exact likelihood where
the likelihood is quadratic, and the rule built on it
(:func:`bondgraph.diagnose.scoring.worth_profiling`)."""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import chi2

from bondgraph import BondGraph
from bondgraph.diagnose import scoring
from bondgraph.diagnose.inference_calls import predicted_step_gain
from bondgraph.inference.problem import PriorSpec, make_problem
from bondgraph.numerics.model import Model


def _offset_problem():
    """A mass and damper driven by a multisine force, its velocity measured
    with an offset b (noise 0.01 m/s). The Kalman filter's innovations are
    linear in b and their covariance does not depend on it, so the NLL is
    exactly quadratic in b."""
    g = BondGraph("offset", "damped mass, velocity sensor with an offset")
    F = g.input("F", "N", 0.0, "force")
    m = g.param("m", 2.0, "kg", (0.1, 10.0), "mass")
    c = g.param("c", 1.5, "N*s/m", (0.1, 10.0), "damping")
    b = g.param("b", 0.0, "m/s", (-1.0, 1.0), "sensor offset")
    v = g.one("v")
    g.connect(g.Se("force", F), v)
    g.connect(v, g.I("mass", m))
    g.connect(v, g.R("damper", c))
    g.sensor("vel", v.f + b, unit="m/s", noise_std=0.01)
    model = Model.from_graph(g)
    t = np.arange(800) * 0.02
    u = (np.sin(0.7 * t) + 0.5 * np.sin(2.3 * t + 1.0))[:, None]
    vel, y = 0.0, np.empty((t.size, 1))
    rng = np.random.default_rng(3)
    for i in range(t.size):                 # exact zero-order-hold solution
        y[i, 0] = vel + 0.3 + 0.01 * rng.standard_normal()
        a = np.exp(-1.5 / 2.0 * 0.02)
        vel = a * vel + (1 - a) * u[i, 0] / 1.5
    pb = make_problem(model, (t, u, y), prior=PriorSpec(x0=np.zeros(1), P0=np.eye(1) * 1e-4))
    return model, pb


def _stub_gain(calls: list):
    """A stand-in factory for ``predicted_step_gain``: ``gain_of(value)``
    returns that value (None: the UKF fails), recording the parameter
    indices of each call in ``calls``."""
    def gain_of(value):
        def f(pb, th, idx, box):
            calls.append(idx)
            if value is None:
                raise FloatingPointError("the UKF failed")
            return value
        return f
    return gain_of


def test_the_predicted_gain_of_a_scoring_step_is_exact_where_the_nll_is_quadratic():
    """½gᵀF⁻¹g at b = 0 against the decrease to the minimum of the exact
    quadratic through three filter runs at b = 0, ±0.05: g²/(2a) with
    g = (f₊ − f₋)/(2δ), a = (f₊ − 2f₀ + f₋)/δ²."""
    model, pb = _offset_problem()
    th = model.theta0.copy()
    j = model.param_index("b")
    gain = predicted_step_gain(pb, th, [j], (np.array([-1.0]), np.array([1.0])))
    d = 0.05
    sets = np.repeat(th[None, :], 3, axis=0)
    sets[1, j], sets[2, j] = d, -d
    f0, fp, fm = pb.nll(sets).nll
    g, a = (fp - fm) / (2 * d), (fp - 2 * f0 + fm) / d**2
    exact = g**2 / (2 * a)
    assert exact > 100.0                      # an offset of 0.3 against noise 0.01
    assert gain == pytest.approx(exact, rel=1e-3)
    # at the minimum nothing is left to gain
    sets[0, j] = -g / a
    assert predicted_step_gain(pb, sets[0], [j], (np.array([-1.0]), np.array([1.0]))) \
        == pytest.approx(0.0, abs=1e-3 * exact)


def test_worth_profiling_compares_grid_plus_reach_times_the_predicted_gain_with_the_critical_value(
        monkeypatch):
    """Family 10 at significance 0.01: χ²(1) critical 10.83. A grid LR of
    2 (NLL 1 below the fit's) with a predicted NLL gain of 1 reaches
    2 + 4·2 = 10 < 10.83: not profiled; with 1.2, 2 + 9.6 = 11.6: profiled.
    A grid LR at or above the critical value needs no prediction; a
    prediction that fails profiles."""
    crit = chi2.isf(0.01 / 10, 1)
    assert crit == pytest.approx(10.83, abs=0.01)
    calls = []
    gain_of = _stub_gain(calls)

    ctx = SimpleNamespace(settings=SimpleNamespace(accept=SimpleNamespace(significance=0.01)))
    model = SimpleNamespace(params=["m", "c", "q", "L"], param_index=["m", "c", "q", "L"].index,
                            bounds=lambda names: (np.zeros(len(names)), np.ones(len(names))))
    fit = SimpleNamespace(nll=100.0, params=["m", "c", "q"], model=None)
    monkeypatch.setattr(scoring, "noise_params", lambda m: {"q"})
    monkeypatch.setattr(scoring, "problem_for", lambda ctx, m: None)
    th = np.zeros(4)
    for value, want in ((1.0, False), (1.2, True), (None, True)):
        monkeypatch.setattr(scoring, "predicted_step_gain", gain_of(value))
        assert scoring.worth_profiling(ctx, fit, model, th, ["L"], 99.0, 1, 10) is want
    assert calls == [[0, 1, 3]] * 3            # m, c and the effect's L; not the noise q
    calls.clear()
    assert scoring.worth_profiling(ctx, fit, model, th, ["L"], 100.0 - crit / 2 - 1e-6, 1, 10)
    assert calls == []


def test_a_grid_that_cannot_reach_the_steps_confirmations_is_not_profiled(monkeypatch):
    """``confirm_bar``: with confirm_top 1 and confirm_rounds 2 a step
    confirms at most two candidates, so the bar is the second-best score
    (statistic − 2k) among the significant candidates scored before (family
    10 at 0.01: p < 0.001; the insignificant and the failed ones do not
    count). A grid LR of 50 (k 1) with a predicted NLL gain of 5 reaches
    50 + 4·10 − 2 = 88: below a bar of 90 it is not profiled, above a bar
    of 80 it is; a grid already above the bar needs no prediction; with
    fewer significant candidates than confirmations there is no bar."""
    from bondgraph.diagnose.result import Candidate
    from bondgraph.diagnose.effects import Target

    def cand(score, p):
        return Candidate("e", "", Target("junction", "v"), "score", score + 2, 1, p, score)

    settings = SimpleNamespace(accept=SimpleNamespace(significance=0.01),
                               search=SimpleNamespace(confirm_top=1, confirm_rounds=2))
    ctx = SimpleNamespace(settings=settings)
    ahead = [cand(120.0, 1e-9), cand(95.0, 1e-6), cand(200.0, 0.5), cand(90.0, 1e-5),
             cand(float("nan"), float("nan"))]
    assert scoring.confirm_bar(ctx, ahead, 10) == 95.0
    assert scoring.confirm_bar(ctx, ahead[:1], 10) == -np.inf
    assert scoring.confirm_bar(ctx, ahead, 10**6) == -np.inf      # none significant then
    calls = []

    def gain(pb, th, idx, box):
        calls.append(idx)
        return 5.0

    model = SimpleNamespace(params=["m", "L"], param_index=["m", "L"].index,
                            bounds=lambda names: (np.zeros(len(names)), np.ones(len(names))))
    fit = SimpleNamespace(nll=100.0, params=["m"], model=None)
    monkeypatch.setattr(scoring, "noise_params", lambda m: set())
    monkeypatch.setattr(scoring, "problem_for", lambda ctx, m: None)
    monkeypatch.setattr(scoring, "predicted_step_gain", gain)
    th = np.zeros(2)
    assert not scoring.worth_profiling(ctx, fit, model, th, ["L"], 75.0, 1, 10, bar=90.0)
    assert scoring.worth_profiling(ctx, fit, model, th, ["L"], 75.0, 1, 10, bar=80.0)
    assert calls == [[0, 1]] * 2
    calls.clear()
    assert scoring.worth_profiling(ctx, fit, model, th, ["L"], 50.0, 1, 10, bar=90.0)
    assert calls == []


def test_the_reach_of_a_profile_is_its_ratio_plus_four_predicted_gains(monkeypatch):
    """``profile_reach``: LR 3107 at the profiled point, a next scoring step
    predicting an NLL gain of 876 (LR 1752, the user's tanks' pump
    saturation) reaches 3107 + 4·1752 = 10115; a converged profile (no gain
    predicted) reaches its own LR; no profiling (``structural_refit`` 0) or a
    failed prediction gives None. The prediction steps over the declared
    parameters (noise excepted) and the effect's."""
    calls = []
    gain_of = _stub_gain(calls)

    def ctx(refit):
        return SimpleNamespace(settings=SimpleNamespace(search=SimpleNamespace(
            structural_refit=refit)))

    model = SimpleNamespace(params=["m", "c", "q", "L"], param_index=["m", "c", "q", "L"].index,
                            bounds=lambda names: (np.zeros(len(names)), np.ones(len(names))))
    fit = SimpleNamespace(params=["m", "c", "q"], model=None)
    monkeypatch.setattr(scoring, "noise_params", lambda m: {"q"})
    monkeypatch.setattr(scoring, "problem_for", lambda ctx, m: None)
    th = np.zeros(4)
    monkeypatch.setattr(scoring, "predicted_step_gain", gain_of(876.0))
    assert scoring.profile_reach(ctx(2), fit, model, th, ["L"], 3107.0) == 3107.0 + 4 * 1752.0
    assert calls == [[0, 1, 3]]
    monkeypatch.setattr(scoring, "predicted_step_gain", gain_of(0.0))
    assert scoring.profile_reach(ctx(2), fit, model, th, ["L"], 3107.0) == 3107.0
    monkeypatch.setattr(scoring, "predicted_step_gain", gain_of(None))
    assert scoring.profile_reach(ctx(2), fit, model, th, ["L"], 3107.0) is None
    assert scoring.profile_reach(ctx(0), fit, model, th, ["L"], 3107.0) is None


def test_an_unconfirmed_profile_whose_reach_nears_the_best_refit_is_confirmed_too():
    """``within_reach``: the best confirmed refit LR 8179 (k 2: 8175 less
    2k) sets the bar at 0.9·8175 = 7357.5. A structural candidate profiled
    to 3107 (k 1) whose reach is 10115 is brought in; one whose reach is
    7000 is not, nor an additive score of 7000; a score of 7400 is. At most
    as many as were confirmed, best ranked first."""
    from bondgraph.diagnose.effects import Target
    from bondgraph.diagnose.result import Candidate
    from bondgraph.diagnose.runner import reach_of, within_reach

    def cand(name, stat, k=1, reach=None, lr=None):
        c = Candidate(name, "", Target("junction", "v"), "score", stat, k, 0.0, stat - 2 * k,
                      reach=reach)
        c.confirmed_statistic = lr
        return c

    lead = cand("cold_start", 4201.0, 2, lr=8179.0)
    other = cand("r_quadratic", 3914.0, lr=7639.0)
    sat = cand("actuator_saturation", 3107.0, reach=10115.0)
    short = cand("end_stop", 514.0, reach=7000.0)
    score = cand("sensor_offset", 7000.0)
    high = cand("source_offset", 7400.0)
    assert reach_of(sat) == 10115.0 and reach_of(score) == 7000.0
    assert reach_of(cand("x", 50.0, reach=20.0)) == 50.0       # a reach never lowers
    confirmed = [(lead, None), (other, None)]
    assert within_reach(confirmed, [high, short, score, sat]) == [high, sat]
    assert within_reach(confirmed[:1], [high, short, score, sat]) == [high]
    assert within_reach(confirmed, [short, score]) == []
