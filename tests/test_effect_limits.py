"""An effect scored at the end of a parameter's span where it is another
effect (``Effect.limits``) is reported equivalent to that effect."""
import pytest

from bondgraph.diagnose.effects import get_effect
from bondgraph.diagnose.effects.base import Target
from bondgraph.diagnose.result import Candidate, rank_of
from bondgraph.diagnose.scoring import at_limits, mark_limits


def _cand(effect, place, stat, kind="score", dof=1, limit_of=(), equivalent=()):
    return Candidate(effect, effect, Target("junction", place), kind, stat, dof, 0.0,
                     stat - 2 * dof, limit_of=list(limit_of), equivalent=list(equivalent))


def test_dahl_at_its_stiffness_limit_is_coulomb():
    """Dahl friction with σ on the top of its span (within 1e-3) is the
    Coulomb friction at the same place; inside the span it is not; a
    parameter without a declared limit never is."""
    dahl = get_effect("dahl")
    tgt = Target("junction", "body.v")
    spans = {"Fc": (10.0, 500.0), "sigma": (3.0, 2748.28)}
    assert at_limits(dahl, tgt, {"Fc": 127.0, "sigma": 2748.0}, spans) == ["coulomb @ body.v"]
    assert at_limits(dahl, tgt, {"Fc": 127.0, "sigma": 2000.0}, spans) == []
    assert at_limits(dahl, tgt, {"Fc": 500.0, "sigma": 20.0}, spans) == []
    assert at_limits(get_effect("coulomb"), tgt, {"Fc": 500.0}, {"Fc": (1.0, 500.0)}) == []


def test_mark_limits_joins_the_whole_group():
    """The vehicle coast-down with a brake drag (measured): Dahl @ body.v
    scored χ² 1675.3 at its stiffness limit, above the Coulomb candidates
    (1672.4; body.v and wheels.w indistinguishable) by its extra parameter;
    the truth, Coulomb @ wheels.w, then ranks 1 with the Dahl candidate."""
    cands = [_cand("dahl", "body.v", 1675.3, "likelihood ratio", 2, ["coulomb @ body.v"]),
             _cand("coulomb", "body.v", 1672.4, equivalent=["coulomb @ wheels.w"]),
             _cand("coulomb", "wheels.w", 1672.39, equivalent=["coulomb @ body.v"]),
             _cand("sensor_gain", "v", 900.0)]
    cands = sorted(cands, key=lambda c: c.rank_key)
    assert rank_of(cands, "coulomb", "wheels.w") == 2
    mark_limits(cands)
    assert set(cands[0].equivalent) == {"coulomb @ body.v", "coulomb @ wheels.w"}
    assert "dahl @ body.v" in cands[2].equivalent
    assert rank_of(cands, "coulomb", "wheels.w") == 1
    assert rank_of(cands, "sensor_gain", "v") == 2


@pytest.mark.parametrize("builder", ["mass_spring_damper", "dc_motor_compliant", "rlc_circuit",
                                     "hydraulic_tanks", "thermal_two_node", "mass_chain_5"])
def test_structural_grid_reaches_the_whole_box(builder):
    """The refits of a structural candidate stay inside its grid's reach
    (:meth:`Effect.grid_span`); every value of the effect's declared box
    (where a truth may lie) must be inside it, or the estimate of a truth
    near the box's edge ends on the span's bound (Dahl: σ was drawn up to
    5 F/x while the grid reached 1.6 F/x; 1933 for 3521)."""
    from bondgraph.catalog import reference
    from bondgraph.diagnose.effects import DEFAULT_EFFECTS, Scales

    g = getattr(reference, builder)()
    checked = 0
    for sc in (Scales(dt=0.01, duration=10.0), Scales(dt=0.2, duration=200.0)):
        for eff in DEFAULT_EFFECTS:
            if eff.additive:
                continue
            for tgt in eff.targets(g)[:2]:
                box = eff.box(g, tgt, sc) or {}
                span = eff.grid_span(g, tgt, sc)
                for p, (lo, hi) in box.items():
                    if p in span:
                        checked += 1
                        assert span[p][0] <= lo * (1 + 1e-12) and hi <= span[p][1] * (1 + 1e-12), \
                            (eff.name, tgt.name, p, (lo, hi), span[p])
    assert checked > 0
