"""The library's ``series_rc`` effect: an RC pair added in series on a
1-junction of the electrical or heat domain (a battery cell's second RC
pair, a Foster stage of a thermal impedance).

References: the two-pair Thevenin model of a Li-ion cell, Plett (2015),
*Battery Management Systems* vol. 1, §2.10; Hu, Li & Peng (2012), J. Power
Sources 198, 359-367. The records are simulated with scipy's LSODA from the
hand-written equations of that model, not with the toolkit.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph import BondGraph
from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.data.records import Experiment
from bondgraph.diagnose.effects import SeriesRC, Target
from bondgraph.diagnose.fit import model_of
from bondgraph.diagnose.runner import chosen_numerics, run_loop
from bondgraph.diagnose.settings import LoopSettings
from bondgraph.errors import GraphError
from bondgraph.numerics.simulate import simulate

# the cell: OCV = V_E + q/C_B (q the charge above empty), R0, two RC pairs
C_B, V_E, R0, R1, C1, R2, C2 = 11250.0, 3.3, 0.05, 0.02, 1000.0, 0.03, 20000.0
NOISE = 0.002


def cell() -> BondGraph:
    """The user's graph: a one-pair Thevenin model; current positive
    charging (a flow source into the terminal's 0-junction)."""
    g = BondGraph("cell", "Li-ion cell, first-order Thevenin model")
    current = g.input("I", "A", 0.0, "cell current, positive charging")
    cb = g.param("C_b", 10000.0, "F", (1000.0, 1e5), "bulk capacitance (OCV slope)")
    ve = g.param("V_e", 3.3, "V", (2.5, 4.5), "open-circuit voltage when empty")
    r0 = g.param("R0", 0.03, "ohm", (1e-4, 1.0), "series resistance")
    r1 = g.param("R1", 0.01, "ohm", (1e-4, 1.0), "charge-transfer resistance")
    c1 = g.param("C1", 2000.0, "F", (10.0, 1e6), "double-layer capacitance")
    term = g.zero("terminal", domain="electrical")
    g.connect(g.Sf("charger", current), term)
    s = g.one("series", domain="electrical")
    g.connect(term, s)
    g.connect(s, g.C("bulk", cb))
    g.connect(s, g.R("R_s", r0))
    rc = g.zero("rc", domain="electrical")
    g.connect(s, rc)
    g.connect(rc, g.C("C_dl", c1))
    g.connect(rc, g.R("R_ct", r1))
    g.sensor("V", term.e + ve, unit="V", noise_std=NOISE, description="terminal voltage")
    return g


def pulses(seed: int, seconds: int) -> tuple[np.ndarray, np.ndarray]:
    """1 Hz samples of a current held 10-120 s at levels in [-3.2, 2.4] A
    (a quarter of them rests)."""
    rng = np.random.default_rng(seed)
    t = np.arange(seconds + 1, dtype=float)
    current = np.zeros_like(t)
    k = 0
    while k < len(t):
        n = int(rng.integers(10, 120))
        current[k:k + n] = 0.0 if rng.random() < 0.25 else rng.uniform(-3.2, 2.4)
        k += n
    return t, current


def truth(t: np.ndarray, current: np.ndarray, soc0: float) -> np.ndarray:
    """Terminal voltage of the two-pair cell (LSODA, rtol 1e-10), the
    current held over each second."""
    def f(tt, x):
        i = current[min(int(tt), len(current) - 1)]
        return [i, i / C1 - x[1] / (R1 * C1), i / C2 - x[2] / (R2 * C2)]

    sol = solve_ivp(f, (0.0, t[-1]), [soc0 * 0.8 * C_B, 0.0, 0.0], t_eval=t, method="LSODA",
                    rtol=1e-10, atol=1e-10, max_step=0.5)
    q, v1, v2 = sol.y
    return V_E + q / C_B + R0 * current + v1 + v2


def record(seed: int, seconds: int, soc0: float) -> Experiment:
    t, current = pulses(seed, seconds)
    y = truth(t, current, soc0) + NOISE * np.random.default_rng(seed + 100).standard_normal(len(t))
    return Experiment.from_arrays(t, model=model_of(cell()), u=current[:, None], y=y[:, None],
                                  name=f"cell{seed}", noise_std={"V": NOISE},
                                  meta={"columns": {"I": {"hold": "zoh"}}})


def test_the_pair_adds_a_relaxing_effort_in_series():
    """The cell with the pair added at its series junction simulates the
    hand-written two-pair model (scipy) to 1e-6 V; the pair's R and C are
    passive (R >= 0, C = τ/R > 0)."""
    g = cell()
    SeriesRC().apply(g, Target("junction", "series"), {"R": R2, "tau": R2 * C2})
    m = model_of(g)
    t, current = pulses(3, 1800)
    sim = simulate(m, t, u=current[:, None], x0={"q_bulk": 0.6 * 0.8 * C_B},
                   theta={"C_b": C_B, "V_e": V_E, "R0": R0, "R1": R1, "C1": C1,
                          "series_rc.series.R": R2, "series_rc.series.tau": R2 * C2},
                   method="LSODA", rtol=1e-11, atol=1e-11, hold="zoh")
    np.testing.assert_allclose(sim.y[:, 0], truth(t, current, 0.6), atol=1e-6)
    lo, hi = m.bounds(["series_rc.series.R"])
    assert lo[0] >= 0.0


def test_a_foster_stage_on_a_heat_path():
    """On a pseudo bond graph of heat transfer (a die, a resistance to the
    room), the pair is a Foster stage: the die's temperature simulates the
    hand-written two-stage network (scipy) to 1e-6 K."""
    c, r1, r2, c2, ta = 8.0, 0.6, 0.9, 300.0, 298.15
    g = BondGraph("chip", "a die on a heat sink")
    power = g.input("P", "W", 0.0)
    node = g.zero("die_node", domain="heat")
    g.connect(g.Sf("losses", power), node)
    g.connect(node, g.C("die", g.param("C_j", c, "J/K")))
    path = g.one("path", domain="heat")
    g.connect(node, path)
    g.connect(path, g.R("sink", g.param("R_th", r1, "K/W")))
    room = g.zero("room", domain="heat")
    g.connect(path, room)
    g.connect(g.Se("ambient", g.param("T_a", ta, "K")), room)
    g.sensor("T", node.e, unit="K")
    assert SeriesRC().targets(g) == [Target("junction", "path")]
    SeriesRC().apply(g, Target("junction", "path"), {"R": r2, "tau": r2 * c2})
    t = np.arange(0.0, 2001.0)
    p = np.where((t // 150) % 2 == 0, 20.0, 5.0)

    def f(tt, x):
        tj, v2 = x[0] / c, x[1] / c2
        q = (tj - ta - v2) / r1
        return [p[min(int(tt), len(p) - 1)] - q, q - v2 / r2]

    ref = solve_ivp(f, (0.0, t[-1]), [c * ta, 0.0], t_eval=t, method="LSODA", rtol=1e-11,
                    atol=1e-11, max_step=0.5).y[0] / c
    sim = simulate(model_of(g), t, u=p[:, None], x0={"q_die": c * ta}, method="LSODA",
                   rtol=1e-11, atol=1e-11, hold="zoh")
    np.testing.assert_allclose(sim.y[:, 0], ref, atol=1e-6)


def test_where_the_pair_attaches():
    """Once per 1-junction of the electrical or heat domain that carries an
    R; not on a mechanical graph (there a spring-damper in series is the
    compliance effect's), not twice, not onto a 0-junction."""
    eff = SeriesRC()
    assert eff.targets(cell()) == [Target("junction", "series")]
    assert eff.targets(mass_spring_damper()) == []
    heat = BondGraph("wall", "a heat path")
    node = heat.zero("node", domain="heat")
    heat.connect(heat.Sf("heater", heat.input("P", "W", 0.0)), node)
    heat.connect(node, heat.C("mass", heat.param("C", 500.0, "J/K")))
    path = heat.one("path", domain="heat")
    heat.connect(node, path)
    heat.connect(path, heat.R("wall", heat.param("R_th", 0.5, "K/W")))
    room = heat.zero("room", domain="heat")
    heat.connect(path, room)
    heat.connect(heat.Se("ambient", heat.param("T_a", 293.15, "K")), room)
    heat.sensor("T", node.e, unit="K")
    assert eff.targets(heat) == [Target("junction", "path")]
    g = cell()
    eff.apply(g, Target("junction", "series"), {"R": 0.01, "tau": 100.0})
    assert eff.present(g, Target("junction", "series"))
    with pytest.raises(GraphError, match="added twice"):
        eff.apply(g, Target("junction", "series"), {"R": 0.01, "tau": 100.0})
    with pytest.raises(GraphError, match="1-junction"):
        eff.apply(cell(), Target("junction", "rc"))


def test_the_loop_finds_the_second_pair_of_a_cell():
    """``bondgraph loop --model --data --validate`` on a one-pair graph of a
    two-pair cell (1 h at 1 Hz fitted, 40 min held out): the pair ranks
    first and is accepted in step 1, nothing after; its R and τ and the
    declared R0, R1, C1, C_b within 3 Cramér-Rao std of the truth; the
    held-out error falls to the sensor's noise."""
    est_rec, val_rec = record(1, 3600, 0.9), record(2, 2400, 0.7)
    base = LoopSettings(params=["C_b", "V_e", "R0", "R1", "C1"], validation=val_rec)
    res = run_loop(cell(), est_rec, chosen_numerics(cell(), est_rec, base, log=lambda s: None),
                   log=lambda s: None, progress=False)
    assert [(s.effect, s.attached_to) for s in res.steps] == [("series_rc", "series")]
    est, std = res.final.estimates, res.final.std
    for n, v in {"series_rc.series.R": R2, "series_rc.series.tau": R2 * C2, "R0": R0,
                 "R1": R1, "C1": C1, "C_b": C_B}.items():
        assert abs(est[n] - v) < 3 * std[n], (n, est[n], v, std[n])
    st = res.steps[0]
    floor = NOISE / float(np.std(val_rec["V"]))
    assert st.validated and st.error_before > 2 * floor and st.error_after < 1.1 * floor
