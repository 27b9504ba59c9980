"""The effect library: attachment points found from the graph, fragments that
derive and keep the power balance, the probe model, and the score test
against a brute-force likelihood ratio."""

import numpy as np
import pytest
import sympy as sp

from bondgraph.catalog import reference as models
from bondgraph.diagnose.effects import (DEFAULT_EFFECTS, Scales, Target, apply_effect, get_effect,
                               probe_graph)
from bondgraph.errors import GraphError
from bondgraph.numerics.model import Model
from bondgraph.core.equations import derive


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
