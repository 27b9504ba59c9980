"""The pseudo bond graph of heat transfer (domain ``heat``: temperature [K]
and heat flow [W], Karnopp, Margolis & Rosenberg ch. 12; 20-sim's thermal
library) beside the true thermal bond graph (temperature and entropy flow).

A heated block losing heat to the room, C dT/dt = P − h (T − T_a): with the
heater switched on at t = 0 and the room at a constant temperature the hand
solution is T(t) = T_a + (P/h)(1 − exp(−h t / C)).
"""

from __future__ import annotations

import numpy as np
import pytest

from bondgraph import BondGraph
from bondgraph.core.units import is_power, is_pseudo_power
from bondgraph.errors import UnitMismatchError
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate

C_TH, H, P, T_A = 800.0, 1.5, 200.0, 293.15


def block(domain: str | None = "heat", capacity_unit: str = "J/K") -> BondGraph:
    """The user's block: heater (heat flow source), heat capacity,
    convective conductance to the room (an effort source)."""
    g = BondGraph("block", "heated block, convection to the room")
    p = g.input("P", "W", 0.0, "heater power")
    ta = g.input("T_a", "K", T_A, "room temperature")
    c = g.param("C_th", C_TH, capacity_unit, (100.0, 5000.0), "heat capacity")
    h = g.param("h", H, "W/K", (0.05, 20.0), "convective conductance")
    node = g.zero("block", domain=domain)
    g.connect(g.Sf("heater", p), node)
    g.connect(node, g.C("mass", c))
    loss = g.one("loss", domain=domain)
    g.connect(node, loss)
    g.connect(loss, g.R("conv", 1 / h))
    room = g.zero("room", domain=domain)
    g.connect(loss, room)
    g.connect(g.Se("ambient", ta), room)
    g.sensor("T", node.e, unit="K", noise_std=0.1)
    return g


def test_units_of_a_pseudo_bond():
    assert is_pseudo_power("K", "W") and is_pseudo_power("degK", "J/s")
    assert not is_power("K", "W")
    assert not is_pseudo_power("K", "W/K") and not is_pseudo_power("N", "W")


def test_the_heat_domain_derives_and_simulates_the_hand_solution():
    g = block()
    g.validate()
    model = Model.from_graph(g)
    t = np.linspace(0.0, 3600.0, 361)
    u = np.column_stack([np.full(t.size, P), np.full(t.size, T_A)])
    sim = simulate(model, t, u, x0=[C_TH * T_A], rtol=1e-10, atol=1e-8)
    T = T_A + P / H * (1.0 - np.exp(-H * t / C_TH))
    np.testing.assert_allclose(sim.y[:, 0], T, rtol=0, atol=1e-6)
    # the heat stored is C·T: the state is the heat [J], its rate the net heat flow [W]
    np.testing.assert_allclose(sim.x[:, 0], C_TH * T, rtol=1e-9)


def test_a_thermal_junction_with_heat_flow_laws_names_the_heat_domain():
    with pytest.raises(UnitMismatchError) as exc:
        block("thermal").validate()
    text = str(exc.value)
    assert "R 'conv'" in text or "C 'mass'" in text
    assert "domain='heat'" in text and "entropy" in text


def test_a_wrong_unit_on_a_heat_bond_is_still_refused():
    # a heat capacity in J (not J/K) does not fit the bond temperature/heat flow
    with pytest.raises(UnitMismatchError, match="C 'mass'"):
        block("heat", capacity_unit="J").validate()


def test_a_heater_declared_in_watts_on_a_thermal_junction_names_the_heat_domain():
    """A heat flow source [W] on a true thermal junction (flow: entropy
    flow [W/K]): the unit error's remedy names the heat domain too (a
    user's heated block: the heater was the first element checked, and the
    error came without it)."""
    g = BondGraph("heater_only", "a heater on a thermal node")
    p = g.input("P", "W", 0.0, "heater power")
    node = g.zero("node", domain="thermal")
    g.connect(g.Sf("heater", p), node)
    g.connect(node, g.C("mass", g.param("C_th", 2.7, "J/K^2", (0.1, 100.0), "")))
    with pytest.raises(UnitMismatchError, match="Sf 'heater'") as exc:
        g.validate()
    assert "domain='heat'" in exc.value.hint
