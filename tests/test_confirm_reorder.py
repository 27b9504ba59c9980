"""Refits that reorder the scores (diagnose.runner.reordered): the next round
is confirmed before the loop decides. A user's four-mass chain on a rail,
its nominal values right, the third mass's Coulomb friction missing, no
process noise, the sensors' noise small: the declared fit raises the third
damper to its bound to make up for the friction, and at that fit the score
test ranks two sensor gains and a Stribeck term above the true friction.
Records integrated by scipy from hand-written equations."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph import BondGraph
from bondgraph.data.records import Experiment
from bondgraph.diagnose.effects import Coulomb, SensorGain, Stribeck, Target
from bondgraph.diagnose.fit import model_of
from bondgraph.diagnose.result import Candidate
from bondgraph.diagnose.runner import chosen_numerics, reordered, run_loop
from bondgraph.diagnose.settings import LoopSettings, SearchOptions

M = (1.2, 1.4, 1.6, 1.8)
K, CD, KW, FC, EPS = 400.0, 2.0, 200.0, 1.5, 0.005
DT, N = 0.01, 3000
NOISE = (2e-4, 2e-3)


def chain() -> BondGraph:
    """F on mass 1; spring-damper pairs between the masses; mass 4 tied to
    the wall by a spring. Measured: mass 1's position, mass 4's speed."""
    g = BondGraph("chain4", "four masses on a rail")
    F = g.input("F", "N", 0.0, "applied force")
    v = []
    for i in range(1, 5):
        m = g.param(f"m{i}", M[i - 1], "kg", (0.1, 10.0), f"mass {i}")
        j = g.one(f"v{i}", domain="translation")
        g.connect(j, g.I(f"M{i}", m))
        v.append(j)
    g.connect(g.Se("force", F), v[0])
    for i in range(1, 4):
        k = g.param(f"k{i}", K, "N/m", (10.0, 5000.0), f"spring {i}")
        c = g.param(f"c{i}", CD, "N*s/m", (0.01, 50.0), f"damper {i}")
        s = g.zero(f"s{i}", domain="translation")
        d = g.one(f"dv{i}", domain="translation")
        g.connect(v[i - 1], s)
        g.connect(s, v[i])
        g.connect(s, d)
        g.connect(d, g.C(f"K{i}", stiffness=k))
        g.connect(d, g.R(f"D{i}", c))
    kw = g.param("kw", KW, "N/m", (10.0, 5000.0), "wall spring")
    g.connect(v[3], g.C("wall", stiffness=kw))
    g.sensor("x1", g.displacement(v[0], "x1", "m"), unit="m", noise_std=NOISE[0])
    g.sensor("v4", v[3].f, unit="m/s", noise_std=NOISE[1])
    return g


def record(seed: int = 3, declared: bool = True) -> Experiment:
    """A 15-line multisine force (0.2-6 Hz, 8 N RMS); LSODA (rtol 1e-9) from
    the equations by hand: v_i = p_i/m_i, F_i = k q_i + c (v_i − v_i+1),
    dp_3 gains −Fc tanh(v_3/ε); Gaussian noise at the sensors' levels, which
    the record declares (``declared``) or leaves to the loop to estimate."""
    rng = np.random.default_rng(seed)
    fr, ph = np.linspace(0.2, 6.0, 15), rng.uniform(0, 2 * np.pi, 15)

    def force(t):
        return 8.0 * np.sum(np.sin(2 * np.pi * fr * t + ph)) / np.sqrt(15)

    def f(t, x):
        p, q, qw = x[:4], x[4:7], x[7]
        v = p / np.array(M)
        Fs = K * q + CD * (v[:3] - v[1:])
        return [force(t) - Fs[0], Fs[0] - Fs[1], Fs[1] - Fs[2] - FC * np.tanh(v[2] / EPS),
                Fs[2] - KW * qw, *(v[:3] - v[1:]), v[3], v[0]]

    t = np.arange(N) * DT
    X = solve_ivp(f, (0, t[-1]), np.zeros(9), t_eval=t, method="LSODA", rtol=1e-9, atol=1e-12,
                  max_step=DT).y.T
    y = np.column_stack([X[:, 8], X[:, 3] / M[3]]) + np.array(NOISE) * rng.standard_normal((N, 2))
    u = np.array([force(tk) for tk in t])[:, None]
    return Experiment.from_arrays(t, model=model_of(chain()), u=u, y=y, name="chain",
                                  noise_std={"x1": NOISE[0], "v4": NOISE[1]} if declared else None)


def _cand(label_target: str, stat: float, lr: float) -> Candidate:
    c = Candidate("e", "e", Target("junction", label_target), "score", stat, 1, 0.0, stat - 2,
                  None, {})
    c.confirmed_statistic = lr
    return c


def test_reordered_names_a_refit_that_beats_the_best_scored_by_ten_percent():
    """By hand: scores 100, 90, 80 refitting to 100, 95, 120 reorder (120 − 2
    > 1.1 (100 − 2)); to 100, 95, 105 they do not (within 10 %); nor when
    the best refit is the best-scored candidate's."""
    a, b, c = _cand("a", 100.0, 100.0), _cand("b", 90.0, 95.0), _cand("c", 80.0, 120.0)
    line = reordered([(c, None), (a, None), (b, None)], [a, b, c])
    assert line == "e @ c, scored 3, refits best: LR 120 against 100 for e @ a, scored 1"
    c.confirmed_statistic = 105.0
    assert reordered([(c, None), (a, None), (b, None)], [a, b, c]) is None
    a.confirmed_statistic = 130.0
    assert reordered([(a, None), (c, None), (b, None)], [a, b, c]) is None


def _one_step(exp: Experiment) -> tuple:
    """One loop step on the first 3/4 of ``exp`` (the rest held out) among
    sensor gains, Stribeck and Coulomb frictions, the numerics chosen as the
    command line chooses them: (result, log lines, the noise floor's NRMSE)."""
    n = int(0.75 * N)
    params = ["m1", "m2", "m3", "m4", "k1", "c1", "k2", "c2", "k3", "c3", "kw"]
    base = LoopSettings(params=params, effects=[SensorGain(), Stribeck(), Coulomb()],
                        validation=exp.segment(n, N), search=SearchOptions(max_steps=1))
    lines: list[str] = []
    est = exp.segment(0, n)
    res = run_loop(chain(), est, chosen_numerics(chain(), est, base, log=lambda m: None),
                   log=lines.append, progress=False)
    y = exp.segment(n, N)
    return res, lines, np.mean([NOISE[0] / np.std(y["x1"]), NOISE[1] / np.std(y["v4"])])


@pytest.mark.long
def test_a_low_scored_true_friction_is_confirmed_before_a_look_alike_is_accepted():
    """(``pytest -m long``: 96 s alone, 136-162 s in the suite on a 2-core
    machine 3-5 times slower than when it was written; the rule's decision
    is tested by hand above.) The holdout's last quarter judges. Round 1 confirms the two sensor
    gains and the Stribeck term (scored 1-3); the Stribeck refit beats the
    gains' by 14 %, so round 2 (the frictions at v3 and v2) is confirmed
    before deciding: the true friction's refit wins (LR 5.4e6 against 2.8e6)
    and is accepted, Fc within 0.5 % of 1.5 N and the held-out
    error at the noise's own level; without the rule a sensor gain was
    accepted (its held-out NRMSE 0.087 against 0.005). The round-1 line
    naming the Stribeck term was gone already at 1795ec9 (the test failed
    there on it); in the 65th session the true friction itself scores
    third, behind the two sensor gains, and its refit (LR 5.38e6 against
    2.46e6) is what reorders the scores; the outcome is as before."""
    res, lines, floor = _one_step(record())
    first = next(s for s in lines if "step 1:" in s and "best:" in s)
    assert "best: sensor_gain" in first, first      # a look-alike scores first
    assert any("the refits reorder the scores (" in s and "scored 3" in s for s in lines)
    assert [(s.effect, s.attached_to) for s in res.steps] == [("coulomb", "v3")]
    # within 0.5 %: the library's tanh width, from the record's speeds, is
    # 1.5 times the truth's, so the Cramér-Rao std (0.04 %) does not bound it
    assert abs(res.final.estimates["coulomb.v3.Fc"] - FC) < 0.005 * FC
    assert res.steps[0].error_after < 1.2 * floor

