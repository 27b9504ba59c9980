"""An effect scored at the end of a parameter's span where it is another
effect (``Effect.limits``) is reported equivalent to that effect."""
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
