"""The backward half of the loop's stepwise selection (runner.pruned): an
effect accepted earlier that a later step's refit switches off (a parameter
on the box the library gave it) is removed when the accept rule no longer
wants it, and the model without it is rebuilt from the declared graph
(runner._without)."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.diagnose import runner
from bondgraph.diagnose.effects import Target, get_effect
from bondgraph.diagnose.fit import Context, Fit, model_of, problem_for
from bondgraph.diagnose.residuals import ResidualReport
from bondgraph.diagnose.result import AppliedEffect
from bondgraph.diagnose.settings import AcceptRule, LoopSettings, SearchOptions

sys.path.insert(0, str(Path(__file__).parent))
from test_loop_accept import _msd_record  # noqa: E402

V = Target("junction", "v")
DAMPER = Target("resistor", "damper")


def _graphs():
    """The declared mass-spring-damper; with Coulomb friction at its
    junction (accepted first); with a square-root damper law added too."""
    declared = mass_spring_damper()
    coul, sqrt_ = get_effect("coulomb"), get_effect("r_sqrt")
    g1 = declared.copy("msd_coulomb")
    coul.apply(g1, V, {"Fc": 0.2, "eps": 0.05})
    g2 = g1.copy("msd_coulomb_sqrt")
    sqrt_.apply(g2, DAMPER, {"beta": 0.3, "eps": 0.01})
    return declared, g1, g2


def test_the_model_without_an_effect_is_the_declared_graph_with_the_others():
    """_without: the declared graph with the kept applied effects and the
    added candidate, each at its value in the fit, every box as in the fit,
    refitted from the fit's values (continued until it converges): the same
    refit, to rounding, as that of the same model built by hand from the
    same start (here the square-root
    damper alone, Coulomb friction removed), and a likelihood the filter
    gives for that model at the refit's θ."""
    declared, _, g2 = _graphs()
    g2.params["r_sqrt.damper.beta"].bounds = (0.0, 7.0)
    fit_model = model_of(g2)
    theta = fit_model.theta(m=2.1, k=48.0, c=1.2, **{"coulomb.v.Fc": 0.1,
                                                     "r_sqrt.damper.beta": 0.4})
    fit = SimpleNamespace(graph=g2, model=fit_model, theta=theta,
                          params=["m", "k", "c", "coulomb.v.Fc", "r_sqrt.damper.beta"])
    ctx = Context.on(_msd_record(n=300), LoopSettings(params=["m", "k", "c"],
                                             search=SearchOptions(confirm_iterations=2)),
                     model_of(declared), lambda s: None, False)
    result = SimpleNamespace(declared_graph=declared)
    added = [SimpleNamespace(effect="r_sqrt", target=DAMPER)]
    reduced = runner._without(ctx, result, fit, [], added, "coulomb @ v")
    assert "coulomb.v.Fc" not in reduced.model.params
    assert reduced.params == ["m", "k", "c", "r_sqrt.damper.beta"]
    assert reduced.graph.params["r_sqrt.damper.beta"].bounds == (0.0, 7.0)
    by_hand = mass_spring_damper()
    get_effect("r_sqrt").apply(by_hand, DAMPER, {"beta": 0.4, "eps": 0.01})
    m2 = model_of(by_hand)
    th2 = m2.theta(m=2.1, k=48.0, c=1.2, **{"r_sqrt.damper.beta": 0.4})
    by_hand.params["r_sqrt.damper.beta"].bounds = (0.0, 7.0)
    ref = runner.continued(ctx, by_hand, runner.fit_model(ctx, by_hand, reduced.params,
                                                          dict(zip(m2.params, th2)), "by hand",
                                                          iterations=2), "by hand")
    np.testing.assert_allclose(reduced.theta, ref.theta, rtol=1e-12)
    assert reduced.nll == pytest.approx(ref.nll, rel=1e-12)
    assert reduced.nll == pytest.approx(problem_for(ctx, m2).nll(reduced.theta).nll[0],
                                        rel=1e-9)
    assert reduced.nll < problem_for(ctx, m2).nll(th2).nll[0]


def _fit(graph, theta: dict, nll: float, params, at_bound=()):
    model = model_of(graph)
    rep = ResidualReport([], [], 1.0, 1.0, (0.9, 1.1), 10.0, {"whiteness_dof": 20.0})
    return Fit(graph, model, list(params), model.theta(**theta), nll, None, rep, 1.0, None,
               n_obs=1000, at_bound=list(at_bound), converged=True)


@pytest.mark.parametrize("reduced_nll, current_nll, kept", [
    (-99.9, -50.0, False),     # adding Coulomb back gains 0.2 (< χ²₁ crit): removed
    (-80.0, -50.0, True),      # adding it back gains LR 40: still wanted, kept
    (-50.5, -50.0, True),      # without it the step gains LR 1 only: not accepted, kept
])
def test_a_switched_off_effect_goes_only_when_the_accept_rule_no_longer_wants_it(
        monkeypatch, reduced_nll, current_nll, kept):
    """pruned: Coulomb friction accepted first (Fc inside its box), the
    square-root damper added in this step puts Fc on its box. The model
    without Coulomb replaces the step's refit when adding Coulomb back to it
    would not pass the accept rule and it passes against the model before
    the step (likelihood ratios here; the error rule off); logged, the
    removed effect returned."""
    declared, g1, g2 = _graphs()
    P1 = ["m", "k", "c", "coulomb.v.Fc"]
    P2 = P1 + ["r_sqrt.damper.beta"]
    lo = float(model_of(g2).bounds(["coulomb.v.Fc"])[0][0])
    current = _fit(g1, {"coulomb.v.Fc": 0.2}, current_nll, P1)
    after = _fit(g2, {"coulomb.v.Fc": lo, "r_sqrt.damper.beta": 0.4}, -100.0, P2,
                 ["coulomb.v.Fc"])
    reduced_g = declared.copy("reduced")
    get_effect("r_sqrt").apply(reduced_g, DAMPER, {"beta": 0.4, "eps": 0.01})
    reduced = _fit(reduced_g, {"r_sqrt.damper.beta": 0.4}, reduced_nll,
                   ["m", "k", "c", "r_sqrt.damper.beta"])
    asked = []
    monkeypatch.setattr(runner, "_without",
                        lambda ctx, res, fit, keep, added, what: asked.append((keep, what))
                        or reduced)
    monkeypatch.setattr(runner, "admissibility", lambda *a, **k: SimpleNamespace(ok=True))
    logs = []
    gone = AppliedEffect("coulomb", V, {"Fc": 0.2, "eps": 0.05})
    ctx = SimpleNamespace(settings=SimpleNamespace(accept=AcceptRule(error_level=None),
                                                   effects=None),
                          problem=SimpleNamespace(model=SimpleNamespace(params=["m", "k", "c"])),
                          log=logs.append)
    result = SimpleNamespace(declared_graph=declared, applied=[gone], metric="error")
    added = [SimpleNamespace(effect="r_sqrt", target=DAMPER)]
    fit, removed, d = runner.pruned(ctx, result, current, after, added, "r_sqrt @ damper")
    assert asked == [([], "coulomb @ v")]
    if kept:
        assert fit is after and removed == [] and d is None
        assert "kept" in logs[-1]
    else:
        assert fit is reduced and removed == [gone]
        assert d.accepted and d.lr == pytest.approx(2 * (current_nll - reduced_nll))
        assert logs[-1].startswith("  r_sqrt @ damper puts coulomb @ v on its box and the record "
                                   "no longer wants it") and "removed" in logs[-1]


def test_a_reduced_refit_that_its_search_box_decides_is_not_taken(monkeypatch):
    """pruned: the model without Coulomb friction would be taken (as the
    removal case above, reduced NLL −99.9), but its square-root damper's
    β ends on the edge of a search box that decides the fit: the reduced
    refit is judged by the same rule as any candidate's refit
    (runner.decided) and refused, and Coulomb friction is kept."""
    declared, g1, g2 = _graphs()
    P1 = ["m", "k", "c", "coulomb.v.Fc"]
    lo = float(model_of(g2).bounds(["coulomb.v.Fc"])[0][0])
    current = _fit(g1, {"coulomb.v.Fc": 0.2}, -50.0, P1)
    after = _fit(g2, {"coulomb.v.Fc": lo, "r_sqrt.damper.beta": 0.4}, -100.0,
                 P1 + ["r_sqrt.damper.beta"], ["coulomb.v.Fc"])
    reduced_g = declared.copy("reduced")
    get_effect("r_sqrt").apply(reduced_g, DAMPER, {"beta": 0.4, "eps": 0.01})
    reduced = _fit(reduced_g, {"r_sqrt.damper.beta": 0.4}, -99.9,
                   ["m", "k", "c", "r_sqrt.damper.beta"], ["r_sqrt.damper.beta"])
    monkeypatch.setattr(runner, "_without", lambda *a: reduced)
    monkeypatch.setattr(runner, "admissibility", lambda *a, **k: SimpleNamespace(ok=True))
    edge = []
    monkeypatch.setattr(runner, "on_search_edge",
                        lambda ctx, fit, names: edge.append((fit, list(names)))
                        or (["r_sqrt.damper.beta"] if fit is reduced else []))
    monkeypatch.setattr(runner, "search_box_deciding",
                        lambda ctx, names, fit, label: {n: 40.0 for n in names})
    logs = []
    ctx = SimpleNamespace(settings=SimpleNamespace(accept=AcceptRule(error_level=None),
                                                   effects=None),
                          problem=SimpleNamespace(model=SimpleNamespace(params=["m", "k", "c"])),
                          log=logs.append)
    gone = AppliedEffect("coulomb", V, {"Fc": 0.2, "eps": 0.05})
    result = SimpleNamespace(declared_graph=declared, applied=[gone], metric="error")
    added = [SimpleNamespace(effect="r_sqrt", target=DAMPER)]
    fit, removed, d = runner.pruned(ctx, result, current, after, added, "r_sqrt @ damper")
    assert fit is after and removed == [] and d is None
    assert (reduced, ["r_sqrt.damper.beta", "r_sqrt.damper.eps"]) in edge
    assert logs[-1].startswith("  r_sqrt @ damper without coulomb @ v: not accepted")
    assert "search box" in logs[-1] and logs[-1].endswith("coulomb @ v kept")


def test_nothing_is_refitted_when_no_earlier_effect_is_switched_off(monkeypatch):
    """pruned: a declared parameter newly on its box is the accept rule's
    business, not a removal; nothing is refitted."""
    declared, g1, g2 = _graphs()
    lo = float(model_of(g2).bounds(["c"])[0][0])
    current = _fit(g1, {}, -50.0, ["m", "k", "c", "coulomb.v.Fc"])
    after = _fit(g2, {"c": lo}, -100.0, ["m", "k", "c", "coulomb.v.Fc", "r_sqrt.damper.beta"],
                 ["c"])
    monkeypatch.setattr(runner, "_without", lambda *a: pytest.fail("refitted"))
    ctx = SimpleNamespace(settings=SimpleNamespace(accept=AcceptRule(), effects=None),
                          problem=SimpleNamespace(model=SimpleNamespace(params=["m", "k", "c"])),
                          log=lambda s: None)
    result = SimpleNamespace(declared_graph=declared,
                             applied=[AppliedEffect("coulomb", V, {"Fc": 0.2})], metric="e")
    assert runner.pruned(ctx, result, current, after, [], "x") == (after, [], None)


@pytest.mark.parametrize("nll, taken", [(-99.99996, True), (-100.5, True), (-99.5, False)])
def test_a_continuation_that_converges_where_it_started_is_taken(monkeypatch, nll, taken):
    """confirm.continued: a refit stopped at its iteration limit (NLL −100)
    is continued; a continuation that converges is taken when its NLL is
    below the start's or above it by at most CONTINUE_SLACK (0.01 nats:
    the fit had converged there; a user's oven graph's declared fit
    converged 4.6e-5 nats above its start and was dropped, with a warning
    that every likelihood ratio was an upper bound); 0.5 nats above, the
    earlier fit stands and is still not converged."""
    from bondgraph.diagnose import confirm

    first = SimpleNamespace(converged=False, iterations=10, nll=-100.0, params=["a"],
                            estimates=lambda: {"a": 1.0}, model=None)
    nxt = SimpleNamespace(converged=True, iterations=3, nll=nll)
    monkeypatch.setattr(confirm, "fit_model", lambda *a, **k: nxt)
    ctx = SimpleNamespace(log=lambda s: None,
                          settings=SimpleNamespace(search=SimpleNamespace(confirm_iterations=40,
                                                                          confirm_tolerance=0.01)))
    got = confirm.continued(ctx, None, first, "x")
    assert (got is nxt) == taken and got.iterations == 13
    assert got.converged is (True if taken else False)


def test_candidates_scored_within_reach_of_the_best_refit_are_confirmed_too():
    """runner.within_reach: on a user's drive the load's true Coulomb
    friction scored 1.851e6, fourth behind three Dahl frictions whose best
    refit reached 1.936e6 (LR less 2k); its own refit reaches 1.958e6. A
    candidate whose statistic less 2k is at least 0.9 of the best confirmed
    LR less 2k is confirmed in the same round (here it and r_sqrt at
    1.832e6, not 1.60e6), at most as many as were confirmed; none when no
    refit is confirmed or the best gains nothing."""
    def cand(label, stat, k, conf=None):
        return SimpleNamespace(label=label, statistic=stat, dof=k, confirmed_statistic=conf)

    confirmed = [(cand("dahl @ w_g", 1.913e6, 2, 1.9356e6), None),
                 (cand("dahl @ w_m", 1.934e6, 2, 1.9356e6), None),
                 (cand("dahl @ w_L", 1.882e6, 2, 1.8957e6), None)]
    rest = [cand("coulomb @ w_L", 1.851e6, 1), cand("r_sqrt @ b_L", 1.832e6, 1),
            cand("r_cubic @ b_L", 1.60e6, 1)]
    got = runner.within_reach(confirmed, rest)
    assert [c.label for c in got] == ["coulomb @ w_L", "r_sqrt @ b_L"]
    assert runner.within_reach(confirmed[:1], rest) == rest[:1]
    assert runner.within_reach([], rest) == []
    assert runner.within_reach([(cand("a", 1.0, 1, 1.5), None)], rest) == []   # 1.5 - 2 <= 0
