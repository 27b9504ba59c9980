"""A discovered law attached as bond-graph elements (an R on the junction,
a term in the bonded C's law; bondgraph/diagnose/discover/effect.py), so
that the loop's admissibility check judges it after the refit.

The record: a mass-spring-damper (the catalog's m = 2, k = 50, c = 1.5)
with an active element the declared graph lacks, a Rayleigh-type force
d(v) = B·v − A·v³ (B > c: it feeds power in at small speeds), simulated by
scipy's solve_ivp from hand-written equations. The law handed to the loop
is ``c1·v + c0·v³`` at c1 = 0.25 (small enough that make_passive keeps it:
the power −0.25 v² + 0.5 v⁴ dips below zero by less than the tolerance),
its sign box [0, 2.5] from make_passive's sign; the maximum-likelihood
refit moves c1 towards B = 2.2 and the damper + the law then produce
power: refused, with the elements named."""

import numpy as np
import pytest
import sympy as sp
from scipy.integrate import solve_ivp

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.core.equations import derive
from bondgraph.data.records import Experiment
from bondgraph.diagnose.discover.effect import DiscoveredEffect
from bondgraph.diagnose.discover.law import DiscoveredLaw, Term
from bondgraph.diagnose.discover.passivity import make_passive
from bondgraph.diagnose.settings import LoopSettings, SearchOptions
from bondgraph.inference.options import UKFOptions
from bondgraph.numerics.admissible import check_admissible

M, K, C = 2.0, 50.0, 1.5
B, A = 2.2, 0.5               # the active element: B·v − A·v³
NOISE = 0.002
T = np.arange(0.0, 20.0, 0.01)
V, Q = sp.Symbol("v.f"), sp.Symbol("q_spring")


def force(t):
    return 15 * np.sin(2 * np.pi * 0.3 * t) + 10 * np.sin(2 * np.pi * 1.1 * t + 1)


def active_record():
    def rhs(t, s):
        x, v = s
        return [v, (force(t) - K * x - C * v + B * v - A * v ** 3) / M]

    sol = solve_ivp(rhs, (T[0], T[-1]), [0.0, 0.0], t_eval=T, method="LSODA", rtol=1e-9,
                    atol=1e-11, max_step=0.005)
    y = sol.y[0] + NOISE * np.random.default_rng(1).standard_normal(T.size)
    rec = Experiment.from_arrays(T, {"F": force(T), "x": y}, units={"F": "N", "x": "m"},
                                 roles={"F": "input", "x": "output"}, noise_std={"x": NOISE})
    return rec, sol.y


def law():
    return DiscoveredLaw("v", "effort", "N", {"v.f": V, "q_spring": Q},
                         [Term("v.f^3", V ** 3, -A, 1.0, "(m/s)^3"),
                          Term("v.f", V, 0.25, 1.0, "m/s")],
                         [], [], np.zeros(0), np.zeros(0), 1.0, 0.0, {})


def states_of(model_ss, y):
    """The trajectory (N, 2) in the derived model's state order."""
    x, v = y
    cols = {"q_spring": x, "p_mass": M * v}
    return np.column_stack([cols[str(s)] for s in model_ss.states])


def test_the_law_is_placed_as_an_r_element_and_a_spring_term():
    Qs = sp.Symbol("q_spring")
    lw = DiscoveredLaw("v", "effort", "N", {"v.f": V, "q_spring": Qs},
                       [Term("q^5", Qs ** 5, -3000.0, 1.0, "(m)^5"),
                        Term("v", V, -0.5, 1.0, "m/s"),
                        Term("1", sp.Integer(1), 0.2, 1.0, "1")],
                       [], [], np.zeros(0), np.zeros(0), 1.0, 0.0, {})
    eff = DiscoveredEffect(lw)
    g = mass_spring_damper()
    pl = eff.placement(g)
    assert [(p.part, p.element, p.terms) for p in pl] == [
        ("R", "discovered.v.R", (1,)), ("storage", "spring", (0,)),
        ("source", "discovered.v", (2,))]
    eff.apply(g, eff.targets(g)[0])
    spring = g.element("spring")
    q = spring.state
    # the spring's law and energy: k q + 3000 q^5, k q²/2 + 500 q^6
    vals = {g.params[n]: g.params[n].default for n in g.params}
    assert float(spring.law.subs(vals).subs(q, 0.3)) == pytest.approx(K * 0.3 + 3000 * 0.3 ** 5)
    assert float(spring.energy.subs(vals).subs(q, 0.3)) == pytest.approx(
        K * 0.09 / 2 + 500 * 0.3 ** 6)
    r = g.element("discovered.v.R")
    assert r.form == "effort"
    assert float(r.law.subs(vals).subs(r.f, 0.7)) == pytest.approx(0.5 * 0.7)


def test_make_passive_keeps_the_law_and_the_refit_values_are_refused():
    rec, y = active_record()
    variables = {"v.f": y[1], "q_spring": y[0]}
    rep = make_passive(law(), mass_spring_damper(), variables)
    assert not rep.refused, rep.summary()
    eff = DiscoveredEffect(rep.law)
    assert eff.params[1].bounds == (0.0, 2.5)          # c1 keeps its sign: [0, 10·0.25]
    g = mass_spring_damper()
    eff.apply(g, eff.targets(g)[0])
    ss = derive(g)
    theta = {n: p.default for n, p in g.params.items()}
    x = states_of(ss, y)
    u = force(T)[:, None]
    # at the discovered coefficients: admissible
    assert check_admissible(g, ss, theta, x, u).ok
    # at the truth (inside the sign box): the damper and the law produce
    # power together; the check names both. Hand-derived power per unit
    # speed²: (C − B) + A v² < 0 for v² < (B − C)/A
    theta.update({"discovered.v.c0": -A, "discovered.v.c1": B})
    adm = check_admissible(g, ss, theta, x, u)
    assert not adm.ok
    (viol,) = adm.violations
    assert viol.element == "damper + discovered.v.R (in parallel on junction 'v')"
    assert viol.value == pytest.approx((C - B) * viol.at ** 2 + A * viol.at ** 4, rel=1e-6)


def test_the_loop_refuses_the_non_passive_refit_with_the_reason():
    rec, _ = active_record()
    eff = DiscoveredEffect(law())
    settings = LoopSettings(params=["k"], holdout=0.25,
                            ukf=UKFOptions(substeps=4, hold="linear"),
                            effects=(eff,), search=SearchOptions(max_steps=1))
    from bondgraph.diagnose.runner import run_loop

    logs = []
    res = run_loop(mass_spring_damper(), rec, settings, log=logs.append, progress=False)
    assert res.steps == [], "\n".join(logs)
    (rej,) = [r for r in res.rejected if r.candidate.effect == "discovered"]
    assert rej.reason.startswith("the refit is not physically admissible"), rej.reason
    assert "discovered.v.R" in rej.reason and "produces power" in rej.reason
    print(rej.reason)
