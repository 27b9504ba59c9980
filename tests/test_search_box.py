"""An effect parameter on the edge of its search box (a box the library set
around the score test's estimate, not a physical limit) is decided by the
box, not the record: the candidate is refused when opening the box gains
the likelihood (issue 26, bounds; :func:`bondgraph.diagnose.runner.search_box_deciding`).

Reference: a mass-spring-damper record simulated (BDF) with damping
c = 1.5 N s/m, declared with c = 1.0 held, so the missing viscous friction
is b = 0.5 N s/m by construction."""

import numpy as np
import pytest

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.diagnose.cases import synthesize
from bondgraph.diagnose.effects.library import apply_effect, get_effect
from bondgraph.diagnose.fit import Context, fit_model, model_of
from bondgraph.diagnose.result import Candidate
from bondgraph.diagnose.runner import chosen_numerics, decided, on_search_edge
from bondgraph.diagnose.settings import LoopSettings

TRUTH = {"m": 2.0, "k": 50.0, "c": 1.5}
B = "viscous.v.b"


@pytest.fixture(scope="module")
def declared():
    g = mass_spring_damper()
    t = np.arange(1500) * 0.01
    force = 10 * np.sin(2.1 * t) + 8 * np.sin(5.3 * t + 1.0) + 6 * np.sin(11.7 * t + 2.0)
    exp = synthesize(g, g, t, {"F": force}, {}, TRUTH, 4, "msd", "")
    d = mass_spring_damper()
    d.params["c"].default = 1.0
    lines: list = []
    settings = chosen_numerics(d, exp, LoopSettings(params=["m", "k"]), log=lambda s: None)
    ctx = Context.on(exp, settings, model_of(d), lines.append, False)
    cur = fit_model(ctx, d, ["m", "k"], {"m": 2.0, "k": 50.0}, "declared")
    return ctx, d, cur, lines


def _refit(declared, b0):
    ctx, d, cur, lines = declared
    eff = get_effect("viscous")
    target = eff.targets(d)[0]
    g = d.copy("msd_viscous")
    apply_effect(g, eff, target, {"b": b0})    # box [0, 10 b0] (effects.base._box)
    after = fit_model(ctx, g, ["m", "k", B], {**cur.estimates(), B: b0}, "refit")
    cand = Candidate("viscous", "viscous friction", target, "score", 100.0, 1, 0.0, 98.0,
                     values={"b": b0})
    return after, decided(ctx, cur, after, 1, True, "viscous @ v", [cand])


def test_a_candidate_its_search_box_stops_is_refused(declared):
    """Started at b = 0.02 (box [0, 0.2]) the refit ends on 0.2; opened
    tenfold it reaches b = 0.5 (the truth, within 2 %) and gains far more
    than BOX_DECIDES: refused although its likelihood ratio is large."""
    ctx, _, cur, lines = declared
    after, d = _refit(declared, 0.02)
    assert after.at_bound == [B] and after.estimates()[B] == pytest.approx(0.2)
    assert 2 * (cur.nll - after.nll) > 100.0
    assert not d.accepted
    assert "viscous.v.b = 0.2 (box [0, 0.2]) ends on the edge of the search box" in d.reason
    assert "the box, not the record, decides it" in d.reason
    said = [ln for ln in lines if "on the edge of its search box; beyond it" in ln]
    assert said, lines
    reached = float(said[-1].split("(at viscous.v.b = ")[1].split(")")[0])
    assert reached == pytest.approx(0.5, rel=0.02)


def test_a_candidate_inside_its_search_box_is_accepted(declared):
    """Started at b = 0.2 (box [0, 2]) the refit ends inside, at the truth
    (within 2 %), and is accepted."""
    after, d = _refit(declared, 0.2)
    assert after.at_bound == []
    assert after.estimates()[B] == pytest.approx(0.5, rel=0.02)
    assert d.accepted, d.reason


def test_zero_of_a_nonnegative_parameter_is_no_search_edge(declared):
    """A viscous coefficient on 0 (the effect switched off: a physical
    limit) is not on a search edge; on its upper edge it is; a declared
    parameter on its box is never on one (its box is the user's)."""
    ctx, _, _, _ = declared
    after, _ = _refit(declared, 0.02)
    assert on_search_edge(ctx, after, [B, "m", "k"]) == [B]
    after.theta = after.theta.copy()
    after.theta[after.model.param_index(B)] = 0.0
    assert on_search_edge(ctx, after, [B]) == []
    after.at_bound = [B, "m"]
    after.theta[after.model.param_index("m")] = after.model.bounds(["m"])[1][0]
    assert on_search_edge(ctx, after, ["m"]) == []


def test_an_r_law_term_its_confirmation_box_stops_is_refused_too(declared):
    """A quadratic damper law β·v|v| (an additive effect whose apply sets no
    box): the confirmation's box is ±20 times its start
    (confirm.widen_boxes). Started at β = 0.001 the refit ends on the box's
    edge, 0.02; the record (a linear 0.5 N s/m missing) asks for far more,
    so opening the box gains the likelihood and the candidate is refused.
    Before, only the friction and sensor effects declared such boxes
    (Effect.search_boxed), and this candidate was accepted on its edge; so
    were structural effects (a power law's β on the top of its grid's
    reach)."""
    from bondgraph.diagnose.confirm import widen_boxes

    ctx, d, cur, lines = declared
    eff = get_effect("r_quadratic")
    target = next(t for t in eff.targets(d) if t.name == "damper")
    assert eff.search_boxed() == ("beta",)
    g = d.copy("msd_rquad")
    P = apply_effect(g, eff, target, {"beta": 0.001})
    widen_boxes(eff, P)
    name = P["beta"].name
    assert g.params[name].bounds == pytest.approx((-0.02, 0.02))
    after = fit_model(ctx, g, ["m", "k", name], {**cur.estimates(), name: 0.001}, "refit")
    assert after.at_bound == [name] and after.estimates()[name] == pytest.approx(0.02)
    assert on_search_edge(ctx, after, [name, "m", "k"]) == [name]
    # a structural effect's box is its start x/÷ 100 within its grid's reach: a
    # search box too; a parameter with a declared box (an exponent) is not
    assert get_effect("r_power").search_boxed() == ("beta",)
    assert get_effect("dahl").search_boxed() == ("Fc", "sigma")
    assert get_effect("sensor_rectification").search_boxed() == ()
    cand = Candidate("r_quadratic", "quadratic law", target, "score", 100.0, 1, 0.0, 98.0,
                     values={"beta": 0.001})
    d1 = decided(ctx, cur, after, 1, True, "r_quadratic @ damper", [cand])
    assert not d1.accepted
    assert f"{name} = 0.02 (box [-0.02, 0.02]) ends on the edge of the search box" in d1.reason
