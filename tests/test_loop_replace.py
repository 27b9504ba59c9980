"""An effect accepted before what its step's model lacked is replaced by a
rival at its place once that is in (:func:`bondgraph.diagnose.runner.replaced_earlier`).

A user's oven (a heated block, a wall's thermal resistance to ambient, one
thermocouple; a pseudo bond graph of heat transfer). The truth adds thermal
radiation beside the wall's conduction (β = 2.3e-9 W/K⁴) and a 20 s
thermocouple lag, neither declared; the records are simulated with scipy's
BDF (rtol 1e-9) and N(0, 0.2 K) noise: one hour at 1 Hz to fit, half an hour
of another heater sequence to judge. Without the lag a cubic wall law fits
step 1 better than the radiation law (the look-alikes of the T⁴ law at that
place); once the lag is in, the radiation law's refit in its place is far
likelier (NLL 2004.3 -> -653.6), and the loop takes it. Without the
replacement the loop keeps the cubic law, its lag 18.73 ± 0.037 s (34 std
off the truth) and its held-out NRMSE 0.01506 against 0.003919.
"""

from __future__ import annotations

import numpy as np
import pytest

from bondgraph import BondGraph
from bondgraph.data.records import Experiment
from bondgraph.diagnose.effects import Target, apply_effect
from bondgraph.diagnose.effects.laws import Radiation, RCubic, RPower, RQuadratic
from bondgraph.diagnose.effects.sensors import SensorLowPass
from bondgraph.diagnose.loop import LoopSettings, run_loop
from bondgraph.diagnose.settings import AcceptRule, SearchOptions
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate

TRUTH = {"Cb": 800.0, "Rw": 0.5, "radiation.Rwall.beta": 2.3e-9, "sensor_lowpass.T.tau": 20.0}
NOISE = 0.2      # K


def oven() -> BondGraph:
    """A heated block losing heat through a wall to ambient (the user's graph)."""
    g = BondGraph("oven", "heated block, wall loss to ambient")
    P = g.input("P", "W", 0.0, "heater power")
    Ta = g.input("Ta", "K", 295.0, "ambient temperature")
    Cb = g.param("Cb", 800.0, "J/K", (100.0, 1e4), "block heat capacity")
    Rw = g.param("Rw", 0.5, "K/W", (0.05, 5.0), "wall resistance")
    blk = g.zero("block", domain="heat")
    g.connect(g.Sf("heater", P), blk)
    g.connect(blk, g.C("Cblock", Cb))
    wall = g.one("wall", domain="heat")
    g.connect(blk, wall)
    g.connect(wall, g.R("Rwall", Rw))
    amb = g.zero("amb", domain="heat")
    g.connect(wall, amb)
    g.connect(g.Se("ambient", Ta), amb)
    g.sensor("T", blk.e, unit="K", noise_std=NOISE)
    return g


def record(truth: Model, seed: int, hours: float, name: str) -> Experiment:
    """Heater levels of 0-1000 W held 200-600 s each, ambient 295 ± 2 K over
    an hour; the block starts at ambient."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, hours * 3600.0, 1.0)
    steps = rng.integers(200, 600, 200)
    P = np.concatenate([np.full(s, v) for s, v in
                        zip(steps, rng.choice([0.0, 300.0, 600.0, 1000.0], 200))])[: t.size]
    Ta = 295.0 + 2.0 * np.sin(2 * np.pi * t / 3600.0)
    x0 = {s: 295.0 * TRUTH["Cb"] if s.startswith("q_") else 295.0 for s in truth.states}
    y = simulate(truth, t, np.column_stack([P, Ta]), x0=x0, theta=truth.theta(TRUTH),
                 hold="zoh,linear", rtol=1e-9).y[:, 0]
    return Experiment.from_arrays(t, {"P": P, "Ta": Ta, "T": y + rng.normal(0, NOISE, t.size)},
                                  units={"P": "W", "Ta": "K", "T": "K"},
                                  roles={"P": "input", "Ta": "input", "T": "output"}, name=name)


@pytest.fixture(scope="module")
def loops():
    g = oven()
    apply_effect(g, "radiation", Target("resistor", "Rwall"), {"beta": 2.3e-9})
    apply_effect(g, "sensor_lowpass", Target("sensor", "T"), {"tau": 20.0})
    truth = Model.from_graph(g)
    est, val = record(truth, 1, 1.0, "run1"), record(truth, 2, 0.5, "run2")
    out = {}
    for replace in (True, False):
        lines = []
        out[replace] = run_loop(oven(), est, LoopSettings(
            ["Cb", "Rw"], validation=val,
            effects=(RCubic(), Radiation(), RQuadratic(), RPower(), SensorLowPass()),
            search=SearchOptions(max_steps=2), accept=AcceptRule(replace=replace)),
            log=lines.append, progress=False), lines
    return out


def test_the_cubic_wall_law_is_replaced_by_radiation_once_the_lag_is_in(loops):
    res, lines = loops[True]
    assert [s.effect for s in res.steps] == ["r_cubic", "sensor_lowpass"]
    assert res.steps[1].replaced == ["r_cubic @ Rwall by radiation"]
    assert res.steps[1].shown() == "sensor_lowpass (replacing r_cubic @ Rwall by radiation)"
    assert [(a.effect, a.target.name) for a in res.applied] == [("radiation", "Rwall"),
                                                                ("sensor_lowpass", "T")]
    assert any(line.startswith("REPLACE r_cubic @ Rwall by radiation @ Rwall")
               for line in (x.split("] ", 1)[-1] for x in lines))
    est, std = res.final.estimates, res.final.std
    for name, true in TRUTH.items():               # the truth within 3 Cramér-Rao std
        assert abs(est[name] - true) < 3 * std[name], (name, est[name], std[name])
    # the applied effects carry the final fit's values (the augmented model's)
    assert res.applied[1].values["tau"] == pytest.approx(est["sensor_lowpass.T.tau"], rel=1e-12)
    assert res.to_dict()["steps"][1]["replaced"] == ["r_cubic @ Rwall by radiation"]


def test_without_the_replacement_the_cubic_law_stays_and_judges_worse(loops):
    kept, _ = loops[False]
    res, _ = loops[True]
    assert [(a.effect, a.target.name) for a in kept.applied] == [("r_cubic", "Rwall"),
                                                                 ("sensor_lowpass", "T")]
    tau = kept.final.estimates["sensor_lowpass.T.tau"]
    assert abs(tau - 20.0) > 10 * kept.final.std["sensor_lowpass.T.tau"]
    # held out: the replaced model is never worse, here four times better
    assert res.final.validation_metric < 0.3 * kept.final.validation_metric
    assert res.final.metric < kept.final.metric


def _cand(effect, kind, name, lr, **kw):
    """A confirmed candidate of a step's ranking (its refit's LR ``lr``)."""
    from bondgraph.diagnose.result import Candidate
    kw.setdefault("confirmed", {"comparable": True})
    return Candidate(effect, effect, Target(kind, name), "score", lr, 1, 0.0, lr,
                     confirmed_statistic=lr, **kw)


def test_the_rivals_are_close_refits_at_its_place_or_closer_ones_elsewhere():
    """:func:`rivals_of` on a hand-made ranking: at the effect's place a
    refit within 80 % of its likelihood ratio, elsewhere within 95 %; not a
    look-alike of it (``equivalent``), not a refit that did not converge or
    was unusable, not at a place another applied effect holds, not the
    effect an earlier replacement took out; the two best by LR - 2k."""
    from bondgraph.diagnose.result import AppliedEffect, LoopResult, Step
    from bondgraph.diagnose.runner import rivals_of
    lead = _cand("sensor_lowpass", "sensor", "T", 1000.0, equivalent=["sensor_gain @ T"])
    ranking = [
        lead,
        _cand("source_lag", "source", "heater", 960.0),             # elsewhere, 96 %: a rival
        _cand("source_lag", "source", "ambient", 940.0),            # elsewhere, 94 %: no
        _cand("sensor_poly2", "sensor", "T", 850.0),                # its place, 85 %: a rival
        _cand("sensor_gain", "sensor", "T", 990.0),                 # a look-alike: no
        _cand("sensor_poly3", "sensor", "T", 900.0,
              confirmed={"comparable": False}),                     # not converged: no
        _cand("sensor_offset", "sensor", "T", 995.0,
              confirmed={"comparable": True,
                         "reason": "the refit is not physically admissible"}),
        _cand("r_cubic", "resistor", "Rwall", 999.0),               # held by radiation: no
        _cand("sensor_rate", "sensor", "T", 790.0),                 # its place, 79 %: no
    ]
    res = LoopResult("oven", None, None, "nrmse", "aic", {}, rankings=[ranking, []])
    old = AppliedEffect("sensor_lowpass", Target("sensor", "T"), {"tau": 20.0})
    res.applied = [old, AppliedEffect("radiation", Target("resistor", "Rwall"), {"beta": 1e-9})]
    assert [c.label for c in rivals_of(res, old)] == ["source_lag @ heater", "sensor_poly2 @ T"]
    # a rival an earlier replacement took out is not tried again
    step = Step("radiation", "Rwall", "nrmse", *[0.0] * 10, {}, 0.0, 0.0)
    step.replaced = ["source_lag @ heater by sensor_lowpass"]
    res.steps = [step]
    assert [c.label for c in rivals_of(res, old)] == ["sensor_poly2 @ T"]
    # an effect no ranking confirmed has no rivals
    assert rivals_of(res, AppliedEffect("coulomb", Target("junction", "v"), {})) == []
