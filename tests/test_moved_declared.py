"""The loop's note on declared parameters that the accepted effects moved far
from the declared fit (``diagnose.result.moved_declared``): what a user
checks against what they know when the library's effects stand in for a law
it lacks (a heated block's heat capacity 800 -> 112 J/K under an actuator
gain of -0.86 on its heater, each step lowering the held-out error)."""

from __future__ import annotations

from types import SimpleNamespace

from bondgraph import BondGraph
from bondgraph.diagnose.result import MOVED_REL, MOVED_STD, moved_declared, moved_text


def _graph() -> BondGraph:
    g = BondGraph("block", "heated block")
    c = g.param("C_th", 600.0, "J/K", (100.0, 5000.0))
    h = g.param("h", 1.0, "W/K", (0.05, 20.0))
    w = g.param("w", 0.1, "W", (1e-6, 10.0))
    s = g.param("sigma", 0.1, "K", (1e-3, 1.0))
    node = g.zero("block", domain="heat")
    g.connect(g.Sf("heater", g.input("P", "W", 0.0)), node)
    mass = g.C("mass", c)
    g.connect(node, mass)
    g.connect(node, g.R("conv", 1 / h))
    g.set_process_noise(mass.q, w)
    g.sensor("T", node.e, unit="K", noise_std=s)
    return g


def _fit(est, std, robust=None):
    return SimpleNamespace(estimates=est, std=std, std_robust=robust or {})


def test_moves_beyond_a_quarter_and_ten_std_are_named():
    initial = _fit({"C_th": 800.0, "h": 1.5, "w": 0.5, "sigma": 0.1},
                   {"C_th": 2.0, "h": 0.01, "w": 0.01, "sigma": 0.001})
    final = _fit({"C_th": 112.0, "h": 1.2, "w": 0.001, "sigma": 0.01, "gain.g": -0.86},
                 {"C_th": 1.0, "h": 0.02, "w": 1e-4, "sigma": 1e-4, "gain.g": 0.01})
    res = SimpleNamespace(steps=[object()], initial=initial, final=final,
                          declared_graph=_graph())
    # C_th moved 86 % and 344 std; h 20 % (< 25 %); the noise levels are not
    # physical parameters; the effect's own gain was not in the declared fit
    assert MOVED_REL == 0.25 and MOVED_STD == 10.0
    assert moved_declared(res) == [("C_th", 800.0, 112.0)]
    assert "C_th 800 -> 112 (-86 %)" in moved_text(moved_declared(res))
    # a move within ten of its (robust) std is not named
    initial.std_robust = {"C_th": 70.0}
    assert moved_declared(res) == []
    # no accepted effect: nothing to say
    res.steps = []
    assert moved_declared(res) == [] and moved_text([]) == ""
