"""Passivity of a discovered law (bondgraph/diagnose/discover/passivity.py):
hand-built laws at the mass-spring-damper's 1-junction ``v`` (declared
spring k = 50 N/m, damper c = 1.5 N·s/m), checked against hand-derived
powers and energies."""

import numpy as np
import pytest
import sympy as sp

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.diagnose.discover.law import DiscoveredLaw, Term
from bondgraph.diagnose.discover.passivity import make_passive

V, Q, F = sp.Symbol("v.f"), sp.Symbol("q_spring"), sp.Symbol("F")
t = np.linspace(0.0, 10.0, 1001)
VALUES = {"v.f": 0.8 * np.sin(2 * np.pi * 0.3 * t), "q_spring": 0.6 * np.cos(2 * np.pi * 0.3 * t),
          "F": 10 * np.sin(t)}


def law_of(*terms):
    tms = [Term(name, basis, coef, 1.0) for name, basis, coef in terms]
    return DiscoveredLaw("v", "effort", "N", {"v.f": V, "q_spring": Q, "F": F}, tms, [], [],
                         np.zeros(0), np.zeros(0), 1.0, 0.0, {}, [], ["F"])


def check(*terms):
    return make_passive(law_of(*terms), mass_spring_damper(), VALUES)


def test_a_dissipative_law_is_kept():
    rep = check(("|v|v", sp.Abs(V) * V, -3.0), ("tanh", sp.tanh(V / 0.05), -2.0))
    assert not rep.refused
    assert [tm.name for tm in rep.law.terms] == ["|v|v", "tanh"]
    assert rep.checks[0].part == "R" and rep.checks[0].ok
    # −d·v = 3|v|³ + 2 tanh(v/0.05)·v >= 0: the worst power is 0 (at v = 0)
    assert rep.checks[0].worst == pytest.approx(0.0, abs=1e-12)


def test_a_power_generating_term_is_dropped_and_named():
    # with the declared damper in parallel, (c·v − d)·v = 3|v|³ + (1.5 − 5) v²
    # < 0 for |v| < 3.5/3: the +5 v term generates power
    rep = check(("|v|v", sp.Abs(V) * V, -3.0), ("v", V, 5.0))
    assert rep.refused and list(rep.dropped) == ["v"]
    assert "generates power" in rep.dropped["v"]
    assert [tm.name for tm in rep.law.terms] == ["|v|v"] and rep.law.dropped == ["v"]
    w = rep.checks[0]
    assert w.part == "R" and w.ok and w.worst < 0
    assert w.worst == pytest.approx(3 * abs(w.at) ** 3 - 3.5 * w.at ** 2, rel=1e-9)
    assert "NOT passive" not in rep.summary() and "dropped v" in rep.summary()


def test_a_spring_term_that_makes_the_energy_negative_is_dropped():
    # H(q) = 25 q² − 100 q⁴ < 0 for |q| > 0.5 (the record reaches 0.6)
    rep = check(("q^3", Q ** 3, 400.0))
    assert rep.refused and "stored in q_spring" in rep.dropped["q^3"]
    w = rep.checks[0]
    assert w.part == "storage" and w.worst == pytest.approx(25 * w.at ** 2 - 100 * w.at ** 4,
                                                            rel=1e-3)
    # a softening term the declared spring outweighs over the range is kept:
    # H = 25 q² − 6.25 q⁴ >= 0 for |q| <= 2
    assert not check(("q^3", Q ** 3, 25.0)).refused
    assert not check(("q^3", Q ** 3, -400.0)).refused      # hardening


def test_coupled_and_source_terms():
    # −d·v = −2 q v² < 0 wherever q > 0: dropped; the constant and the
    # input term are kept unchecked
    rep = check(("vq", V * Q, 2.0), ("1", sp.Integer(1), 0.5), ("F", F, 0.1))
    assert list(rep.dropped) == ["vq"]
    assert sorted(rep.unchecked) == ["1", "F"]
    assert sorted(tm.name for tm in rep.law.terms) == ["1", "F"]


@pytest.mark.parametrize("coef, kept", [(1.0, True), (2.0, False)])
def test_a_term_lowering_the_declared_resistance_is_judged_with_it(coef, kept):
    """A law +a·v at ``v`` lowers the declared damping c = 1.5: the R part
    dissipates with the damper in parallel when a < c ((1.5 − a)·v² >= 0),
    as the loop's admissibility check judges the two R elements on the
    junction (:func:`bondgraph.numerics.admissible.check_admissible`, the
    law attached by ``DiscoveredEffect``): a = 1 is kept and admissible,
    a = 2 is dropped and, attached anyway, refused (the power
    (1.5 − 2)·v² at the worst v of the range)."""
    from bondgraph.core.equations import derive
    from bondgraph.diagnose.discover.effect import DiscoveredEffect
    from bondgraph.diagnose.effects.base import Target
    from bondgraph.numerics.admissible import check_admissible

    rep = check(("v", V, coef))
    assert rep.refused is not kept
    g = mass_spring_damper()
    DiscoveredEffect(law_of(("v", V, coef))).apply(g, Target("junction", "v"))
    ss = derive(g)
    theta = {p.name: g.params[p.name].default for p in ss.params}
    # states (p_mass, q_spring) along the range of VALUES: p = m·v
    x = np.column_stack([2.0 * VALUES["v.f"] if str(s) == "p_mass" else VALUES["q_spring"]
                         for s in ss.states])
    adm = check_admissible(g, ss, theta, x, VALUES["F"].reshape(-1, 1))
    assert adm.ok is kept
    if not kept:
        (viol,) = adm.violations
        assert viol.value == pytest.approx((1.5 - coef) * viol.at ** 2, rel=1e-9)
