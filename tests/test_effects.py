"""The effect library: attachment points found from the graph, fragments that
derive and keep the power balance, the probe model, and the score test
against a brute-force likelihood ratio."""

import numpy as np
import pytest
import sympy as sp
from scipy.optimize import minimize_scalar

from bondgraph.catalog import reference as models
from bondgraph.core.equations import derive
from bondgraph.diagnose.cases import synthesize
from bondgraph.diagnose.effects import (DEFAULT_EFFECTS, Scales, Target, apply_effect, get_effect,
                                        probe_graph)
from bondgraph.diagnose.fit import Context, fit_model, model_of, problem_for
from bondgraph.diagnose.scoring import operating_scales, score_additive
from bondgraph.diagnose.settings import LoopSettings
from bondgraph.errors import GraphError
from bondgraph.inference.options import UKFOptions
from bondgraph.inference.ukf import ukf_nll
from bondgraph.numerics.model import Model


def test_library_has_the_listed_effects():
    names = {e.name for e in DEFAULT_EFFECTS}
    assert names >= {"coulomb", "asymmetric_friction", "stribeck", "viscous", "quadratic_drag",
                     "offset", "actuator_gain", "sensor_offset", "sensor_gain",
                     "actuator_saturation", "end_stop", "actuator_deadzone", "backlash",
                     "compliance", "slip", "sensor_rectification", "sensor_lowpass",
                     "disturbance"}


def test_attachment_points_are_found_from_the_graph():
    g = models.dc_motor_compliant()
    t = {e.name: [x.name for x in e.targets(g)] for e in DEFAULT_EFFECTS}
    # velocity-dependent forces on the junctions that carry an inertia
    assert t["coulomb"] == ["w_L", "w_m"]
    assert "i" not in t["coulomb"]            # electrical junction: no friction
    assert t["viscous"] == ["w_L", "w_m"]
    assert t["actuator_gain"] == ["V", "load"]  # input-driven effort sources
    assert t["offset"] == ["i", "w_L"]         # their junctions
    assert t["sensor_offset"] == ["i", "w_L"]
    assert t["end_stop"] == ["k_s"] and t["backlash"] == ["k_s"]
    # the rigid gear has transmission bonds next to inertias
    gear = models.dc_motor_gear()
    # (not the motor's gyrator: it converts current into torque)
    assert [x.name for x in get_effect("slip").targets(gear)] == [
        "gear.p2 -> w_L", "w_m -> gear.p1"]


def test_capacity_limit_skips_a_compliance_in_derivative_causality():
    """A belt compliance between a massless motor (a gyrator fed by an
    inductor: a flow source for the belt) and a pulley inertia is left in
    derivative causality by SCAP: its q is no state, the capacity limit
    (written in q) is not offered there (it failed to build, "symbols
    ['q_belt'] are not states"), but it is at the pulley's spring; the
    backlash, which splits the bond, is offered at both."""
    from bondgraph import BondGraph
    from bondgraph.core.causality import assign_causality

    g = BondGraph("belt", "motor, belt, pulley")
    ia = g.one("i_a", domain="electrical")
    g.connect(g.Se("supply", g.input("u", "V", 0.0)), ia)
    g.connect(ia, g.I("La", g.param("La", 0.05, "H", (1e-4, 1.0))))
    g.connect(ia, g.R("Ra", g.param("Ra", 1.0, "ohm", (0.1, 10.0))))
    motor = g.GY("motor", g.param("km", 1.0, "N*m/A", (0.1, 10.0)))
    g.connect(ia, motor.p1)
    wm = g.one("w_m", domain="rotation")
    g.connect(motor.p2, wm)
    belt = g.zero("belt_j")
    g.connect(wm, belt)
    g.connect(belt, g.C("belt", stiffness=g.param("kb", 10.0, "N*m/rad", (1.0, 100.0))))
    wp = g.one("w_p", domain="rotation")
    g.connect(belt, wp)
    g.connect(wp, g.I("pulley", g.param("J", 0.05, "kg*m^2", (1e-3, 1.0))))
    g.connect(wp, g.C("spring", stiffness=g.param("ks", 10.0, "N*m/rad", (1.0, 100.0))))
    assert assign_causality(g).derivative == ["belt"]
    assert [t.name for t in get_effect("capacity_limit").targets(g)] == ["spring"]
    assert [t.name for t in get_effect("backlash").targets(g)] == ["belt", "spring"]


@pytest.mark.parametrize("effect,target", [
    ("coulomb", ("junction", "w_L")), ("asymmetric_friction", ("junction", "w_m")),
    ("stribeck", ("junction", "w_L")), ("quadratic_drag", ("junction", "w_L")),
    ("viscous", ("junction", "w_m")), ("offset", ("junction", "w_L")),
    ("actuator_gain", ("source", "V")), ("actuator_saturation", ("source", "V")),
    ("actuator_deadzone", ("source", "V")), ("end_stop", ("storage", "k_s")),
    ("backlash", ("storage", "k_s")), ("sensor_offset", ("sensor", "w_L")),
    ("sensor_gain", ("sensor", "i")), ("sensor_rectification", ("sensor", "w_L")),
    ("sensor_lowpass", ("sensor", "w_L")), ("disturbance", ("junction", "w_L")),
])
def test_effect_fragments_derive_and_keep_the_power_balance(effect, target):
    g = models.dc_motor_compliant()
    eff = get_effect(effect)
    P = apply_effect(g, effect, Target(*target), {p.name: 0.3 for p in eff.params})
    assert all(p.name.startswith(f"{effect}.") for p in P.values())
    m = Model.from_graph(g)
    assert all(p.name in m.params for p in P.values())
    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, m.n_x))
    u = rng.normal(size=(50, m.n_u))
    th = m.theta0
    rate, ps, pd = m.energy_rate(x, u, th), m.power_sources(x, u, th), m.power_dissipated(x, u, th)
    scale = np.abs(rate) + np.abs(ps) + np.abs(pd)
    assert np.all(np.abs(rate - (ps - pd)) <= 1e-9 * scale + 1e-12)


@pytest.mark.parametrize("effect,target", [("slip", "gear.p2 -> w_L"),
                                           ("compliance", "gear.p2 -> w_L")])
def test_slip_and_compliance_free_the_rigid_coupling(effect, target):
    g = models.dc_motor_gear()
    assert len(derive(g).states) == 2  # J_m lumped by derivative causality
    apply_effect(g, effect, Target("bond", target), {"cs": 5.0, "k": 200.0})
    ss = derive(g)
    assert not ss.derivative_elements  # both inertias keep their state now
    # slip: λ, p_J_m, p_J_L; compliance adds the twist
    assert len(ss.states) == (3 if effect == "slip" else 4)


def test_user_graph_is_not_modified_and_effects_are_not_added_twice():
    g = models.mass_spring_damper()
    before = set(g.elements)
    h = g.copy("aug")
    apply_effect(h, "coulomb", ("junction", "v"), {"Fc": 1.0})
    assert set(g.elements) == before and "coulomb.v" in h.elements
    with pytest.raises(GraphError, match="added twice"):
        apply_effect(h, "coulomb", ("junction", "v"), {"Fc": 1.0})


@pytest.mark.parametrize("g0, expected", [(-8.02, -0.9), (5.0, 2.0), (0.3, 0.3)])
def test_a_start_outside_the_effects_box_starts_on_its_edge(g0, expected):
    """A score step's guess outside an effect's fixed box (the actuator
    gain's g ∈ [−0.9, 2]) starts on the nearer edge; before, the effect
    could not be applied ("default lies outside its bounds") and the
    candidate was dropped."""
    h = models.dc_motor_compliant().copy("aug")
    P = apply_effect(h, "actuator_gain", ("source", "V"), {"g": g0})
    assert P["g"].bounds == (-0.9, 2.0)
    assert P["g"].default == expected


def test_probe_model_at_neutral_values_equals_the_base_model():
    g = models.dc_motor_compliant()
    pg, cols = probe_graph(g, DEFAULT_EFFECTS, Scales(flow_rms={"w_L": 50.0, "w_m": 100.0},
                                                      output_rms={"i": 2.0, "w_L": 50.0}))
    assert cols and all(c.param.startswith("probe.") for c in cols)
    base, probe = Model.from_graph(g), Model.from_graph(pg)
    th = probe.theta0.copy()
    assert np.all(th[[probe.param_index(c.param) for c in cols]] == 0.0)
    rng = np.random.default_rng(1)
    x = rng.normal(size=(20, base.n_x))
    u = rng.normal(size=(20, base.n_u))
    np.testing.assert_allclose(probe.f(x, u, th), base.f(x, u, base.theta0), rtol=1e-13)
    np.testing.assert_allclose(probe.h(x, u, th), base.h(x, u, base.theta0), rtol=1e-13)
    # a nudged Coulomb column adds -beta*tanh(w/eps) to the load torque balance
    col = [c for c in cols if c.effect == "coulomb" and c.target.name == "w_L"][0]
    th[probe.param_index(col.param)] = 0.7
    d = probe.f(x, u, th) - base.f(x, u, base.theta0)
    j = base.state_index("p_J_L")
    wL = x[:, j] / base.theta0[base.param_index("J_L")]
    eps = float(col.basis.atoms(sp.Float).pop()) if col.basis.atoms(sp.Float) else None
    np.testing.assert_allclose(d[:, j], -0.7 * np.tanh(wL / eps), rtol=1e-10)


def test_score_test_equals_the_likelihood_ratio_of_a_sensor_offset():
    """An output offset on a linear model shifts the UKF innovations linearly
    and leaves S unchanged, so the NLL is quadratic in the offset: the score
    statistic (Rao 1948) equals the brute-force likelihood ratio
    2 (NLL(0) − min_b NLL(b)) (scipy's minimize_scalar over ukf_nll of the
    augmented model), and the one-step estimate is the minimiser."""
    truth = models.mass_spring_damper()
    apply_effect(truth, "sensor_offset", ("sensor", "x"), {"b": 0.003})
    declared = models.mass_spring_damper()
    t = np.arange(0.0, 10.0, 0.01)
    rec = synthesize(truth, declared, t,
                     {"F": lambda t: 5.0 * np.sin(1.3 * t) + 3.0 * np.sign(np.sin(0.4 * t))},
                     {}, {}, 3, "offset", "mass-spring-damper with a position sensor offset")
    ctx = Context.on(rec, LoopSettings(params=[], effects=[get_effect("sensor_offset")]),
                     model_of(declared), log=lambda m: None, progress=False)
    fit = fit_model(ctx, declared, [], None, "declared")
    cands = score_additive(ctx, fit, operating_scales(ctx, fit), ctx.settings.effects)
    assert {c.target.name for c in cands} == {"x", "v"}
    c = next(c for c in cands if c.target.name == "x")
    g = declared.copy("augmented")
    apply_effect(g, "sensor_offset", ("sensor", "x"), {"b": 0.0})
    m = Model.from_graph(g)
    pb = problem_for(ctx, m)
    x0, P0 = pb.x0, pb.P0
    j = m.param_index("sensor_offset.x.b")

    def nll(b):
        th = m.theta0.copy()
        th[j] = b
        return ukf_nll(m, rec.t, rec.inputs_for(m, defaults_ok=True), rec.outputs_for(m),
                       th[None, :], x0, P0, options=UKFOptions(method="ros2", substeps=1,
                                                               alpha=1.0)).nll[0]

    assert nll(0.0) == pytest.approx(fit.nll, rel=1e-12)
    best = minimize_scalar(nll, bracket=(0.0, 0.001), tol=1e-10)
    lr = 2.0 * (fit.nll - best.fun)
    assert lr > 100.0                                    # the offset is plainly there
    assert c.statistic == pytest.approx(lr, rel=1e-6)
    assert c.values["b"] == pytest.approx(best.x, rel=1e-5)
    assert best.x == pytest.approx(0.003, abs=5e-4)


def test_simulation_options_validated_on_construction():
    from bondgraph.diagnose.cases import SimulationOptions
    from bondgraph.errors import OptionError

    with pytest.raises(OptionError, match=r"SimulationOptions\.method = 'Euler' is not one of"):
        SimulationOptions(method="Euler")
    with pytest.raises(OptionError, match=r"SimulationOptions\.substeps must be an integer >= 1"):
        SimulationOptions(substeps=0)
    with pytest.raises(OptionError, match=r"SimulationOptions\.hold = 'mean' is not one of"):
        SimulationOptions(hold="mean")
    with pytest.raises(OptionError, match="simulation must be a SimulationOptions, got dict"):
        synthesize(models.mass_spring_damper(), models.mass_spring_damper(), np.arange(3.0),
                   {}, {}, {}, 0, "x", "", simulation={"hold": "zoh"})


def test_an_effect_does_not_attach_to_what_it_added_itself():
    """A gain error of the gain error's own source, (1 + g1 + g1 g2) u, is a
    reparametrisation of the first (the likelihood flat along g1, g2): the
    effect counts as present there; another effect may still attach."""
    from bondgraph.catalog.reference import mass_spring_damper
    from bondgraph.diagnose.effects import get_effect
    from bondgraph.diagnose.effects.library import apply_effect

    g = mass_spring_damper()
    gain = get_effect("actuator_gain")
    (first,) = gain.targets(g)
    assert not gain.present(g, first)
    apply_effect(g, gain, first, {"g": 0.1})
    names = {t.name: gain.present(g, t) for t in gain.targets(g)}
    assert names == {"force": True, "actuator_gain.force": True}
    lag = get_effect("source_lag")
    assert {t.name: lag.present(g, t) for t in lag.targets(g)} == {
        "force": False, "actuator_gain.force": False}
