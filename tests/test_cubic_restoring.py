"""A cubic restoring effort beside a measured C (effects.storage.CubicRestoring):
a user's series RLC whose output is the capacitor's voltage, the way the
Silverbox's electronic Duffing oscillator reads as a circuit. The truth: the
cubic acts in the loop, L di/dt + R i + q/C + k3 q³ = V, while the sensor
reads q/C; records integrated by scipy from those hand-written equations."""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

from bondgraph import BondGraph
from bondgraph.catalog.reference import hydraulic_tanks, mass_spring_damper, thermal_two_node
from bondgraph.data.records import Experiment
from bondgraph.diagnose.effects import (
    CubicRestoring,
    CubicStiffness,
    InductorSaturation,
    Target,
    probe_graph,
)
from bondgraph.diagnose.effects.base import Scales
from bondgraph.diagnose.fit import model_of
from bondgraph.diagnose.runner import run_loop
from bondgraph.diagnose.settings import FreeRunOptions, LoopSettings, SearchOptions
from bondgraph.inference.options import UKFOptions
from test_inductor_saturation import voltage_steps

#: the truth: 10 mH, 2 Ω, 100 µF (159 Hz, damping ratio 0.1), the cubic
#: 2e9 V/C³ (a fifth of q/C at 1 mC)
L0, R0, C0, K3 = 0.010, 2.0, 1e-4, 2e9
DT, N, NOISE = 1e-4, 3000, 0.05


def series_rlc(read: str = "e") -> BondGraph:
    """Se(V) → 1 {I coil, R, C cap}; V2 the capacitor's voltage, read as its
    effort (``read="e"``) or as q/C from its charge (``"q"``); C known."""
    g = BondGraph("user_series_rlc", "series RLC, the capacitor's voltage measured")
    V = g.input("V", "V", 0.0, "source voltage")
    L = g.param("L", 0.008, "H", (1e-4, 0.1), "inductance")
    r = g.param("R", 2.5, "ohm", (0.01, 100.0), "resistance")
    c = g.param("C", C0, "F", None, "capacitance")
    i = g.one("i", domain="electrical")
    g.connect(g.Se("source", V), i)
    g.connect(i, g.I("coil", L))
    g.connect(i, g.R("res", r))
    cap = g.C("cap", c)
    g.connect(i, cap)
    g.sensor("V2", cap.e if read == "e" else cap.q / c, unit="V", noise_std=NOISE)
    return g


def record(seed: int) -> Experiment:
    """Voltage steps of ±12, ±6, 0 V held 4-20 ms; LSODA (rtol 1e-10) from
    the hand-written equations, interval by interval; N(0, 0.05 V) noise."""
    rng = np.random.default_rng(seed)
    V = voltage_steps(rng, N)

    def f(_, x, v):
        lam, q = x
        return [v - R0 * lam / L0 - q / C0 - K3 * q**3, lam / L0]

    X, x = np.zeros((N, 2)), np.zeros(2)
    for k in range(N):
        X[k] = x
        if k < N - 1:
            x = solve_ivp(f, (0.0, DT), x, args=(V[k],), method="LSODA", rtol=1e-10,
                          atol=1e-14).y[:, -1]
    y = X[:, 1:] / C0 + NOISE * rng.standard_normal((N, 1))
    return Experiment.from_arrays(np.arange(N) * DT, model=model_of(series_rlc()), u=V[:, None],
                                  y=y, name=f"rlc{seed}")


def test_it_attaches_where_a_sensor_reads_the_c_effort_and_leaves_the_reading():
    """Targets: the capacitor when V2 reads its effort, none when V2 is
    written from its charge (the law's cubic then leaves V2 alone: the same
    model as cubic_stiffness); on a spring a load cell reads, not on a
    thermal or hydraulic C whose effort is measured. Applied with k3: dλ/dt = V − R λ/L − q/C −
    k3 q³ and V2 = q/C, by hand; the probe at β = k3 gives the same f and h."""
    eff = CubicRestoring()
    assert eff.targets(series_rlc("e")) == [Target("storage", "cap")]
    assert eff.targets(series_rlc("q")) == []
    # a load cell on a spring: yes; a measured temperature or tank pressure:
    # no (no such series element in those domains: their law's cubic)
    msd = mass_spring_damper()
    msd.sensor("force", msd.element("spring").e, unit="N")
    assert eff.targets(msd) == [Target("storage", "spring")]
    for g in (thermal_two_node(), hydraulic_tanks()):
        c = CubicStiffness().targets(g)[0].name
        g.sensor("its_effort", g.element(c).e)
        assert eff.targets(g) == []
    g = series_rlc()
    eff.apply(g, Target("storage", "cap"), {"k3": K3})
    m = model_of(g)
    th = m.theta(L=L0, R=R0, C=C0, **{"cubic_restoring.cap.k3": K3})
    x, u = np.array([[2e-3, 8e-4]]), np.array([[5.0]])      # λ [Wb], q [C]
    np.testing.assert_allclose(m.f(x, u, th[None])[0],
                               [5.0 - R0 * 0.2 - 8.0 - K3 * 8e-4**3, 0.2], rtol=1e-12)
    np.testing.assert_allclose(m.h(x, u, th[None])[0], [8.0], rtol=1e-12)
    pg, cols = probe_graph(series_rlc(), [eff], Scales())
    pm = model_of(pg)
    pth = pm.theta(L=L0, R=R0, C=C0, **{cols[0].param: K3})
    np.testing.assert_allclose(pm.f(x, u, pth[None]), m.f(x, u, th[None]), rtol=1e-12)
    np.testing.assert_allclose(pm.h(x, u, pth[None]), m.h(x, u, th[None]), rtol=1e-12)


def test_the_loop_takes_the_cubic_beside_the_measured_capacitor():
    """One loop step among the capacitor's cubic in its law, the cubic beside
    it and the inductor's saturation: the cubic beside ranks first and is
    accepted, k3, L and R within 3 Cramér-Rao std of the truth; the cubic in
    the law (which the sensor would read) explains less; the held-out error
    falls more than fivefold."""
    res = run_loop(series_rlc(), record(1),
                   LoopSettings(params=["L", "R"],
                                effects=[CubicStiffness(), CubicRestoring(), InductorSaturation()],
                                validation=record(2), ukf=UKFOptions(method="rk4"),
                                free_run=FreeRunOptions(hold="zoh"),
                                search=SearchOptions(max_steps=1, auto_substeps=True)),
                   log=lambda s: None, progress=False)
    assert [(s.effect, s.attached_to) for s in res.steps] == [("cubic_restoring", "cap")]
    est, std = res.final.estimates, res.final.std
    for n, v in {"cubic_restoring.cap.k3": K3, "L": L0, "R": R0}.items():
        assert abs(est[n] - v) < 3 * std[n], (n, est[n], v, std[n])
    scored = {c.label: c.statistic for c in res.rankings[0]}
    assert scored["cubic_restoring @ cap"] > scored["cubic_stiffness @ cap"]
    st = res.steps[0]
    assert st.validated and st.error_after < st.error_before / 5
