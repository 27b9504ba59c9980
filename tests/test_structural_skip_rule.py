"""The option that skips the structural candidates while an additive one
explains most of the innovation energy (``SearchOptions.structural_threshold``,
off by default), by its decisions: :func:`runner.structural_skipped`, which
scoring :func:`runner.gather_evidence` runs, and the fallback that scores the
skipped ones when no confirmed candidate passes the accept rule
(:func:`runner.accepted_among_skipped_structurals`). The end-to-end case (a
user's two tanks whose pump saturates) runs with ``pytest -m long``
(``tests/test_unknown_x0.py``); these stubs keep the rule in the default run."""

from types import SimpleNamespace

import pytest

from bondgraph.diagnose import runner
from bondgraph.diagnose.effects import Target
from bondgraph.diagnose.result import Candidate
from bondgraph.diagnose.settings import LoopSettings, SearchOptions


def cand(name, kind="score", statistic=50.0, p=1e-9, explained=None, place="pump"):
    return Candidate(name, "", Target("source", place), kind, statistic, 1, p, statistic - 2,
                     explained=explained)


def settings(**search):
    return LoopSettings(params=[], search=SearchOptions(**search))


@pytest.mark.parametrize("search, explained, skipped", [
    ({}, 0.9, False),                                       # off by default
    ({"structural_threshold": 0.5}, 0.7, True),
    ({"structural_threshold": 0.5}, 0.5, True),             # at the threshold
    ({"structural_threshold": 0.5}, 0.3, False),
    ({"structural_threshold": 0.5, "structural": "always"}, 0.7, False),
    ({"structural_threshold": 0.5, "structural": False}, 0.7, False),
])
def test_structural_skipped(search, explained, skipped):
    cands = [cand("offset", explained=explained), cand("gain", explained=0.1),
             cand("delay", kind="likelihood ratio")]
    assert runner.structural_skipped(settings(**search), cands) is skipped


def _gather(monkeypatch, s, explained):
    """gather_evidence with the scorers stubbed: three additive candidates,
    the best explaining ``explained``; each structural call recorded."""
    calls = []
    additive = [cand("offset", explained=explained, statistic=90.0), cand("gain", explained=0.2),
                cand("lag", explained=0.1, place="tank")]
    monkeypatch.setattr(runner, "structural_todo", lambda *a, **k: ["early"])
    monkeypatch.setattr(runner, "score_additive", lambda *a, **k: list(additive))

    def structural(ctx, current, scales, effects, places=None, todo=None, others=0, ahead=()):
        calls.append((places, todo, others))
        return [cand("saturation", kind="likelihood ratio", statistic=80.0)]

    monkeypatch.setattr(runner, "score_structural", structural)
    monkeypatch.setattr(runner, "places_of", lambda graph, c: {(c.target.kind, c.target.name)})
    monkeypatch.setattr(runner, "mark_limits", lambda cands: None)
    logs = []
    ctx = SimpleNamespace(settings=s, log=logs.append)
    monkeypatch.setattr(runner, "distributed", lambda ctx: False)
    ranking, signif = runner.gather_evidence(ctx, SimpleNamespace(graph=None), None)
    return ranking, signif, calls, logs


def test_below_the_threshold_or_off_the_structural_candidates_are_scored(monkeypatch):
    for s, explained in ((settings(), 0.9), (settings(structural_threshold=0.5), 0.3)):
        ranking, signif, calls, logs = _gather(monkeypatch, s, explained)
        assert [c.effect for c in ranking] == ["offset", "saturation", "gain", "lag"]
        assert calls == [(None, ["early"] if s.search.structural_threshold is None else None, 3)]
        assert not any("not scored" in m for m in logs)


def test_above_the_threshold_they_are_skipped_and_said_so(monkeypatch):
    ranking, signif, calls, logs = _gather(monkeypatch, settings(structural_threshold=0.5), 0.7)
    assert [c.effect for c in ranking] == ["offset", "gain", "lag"] and calls == []
    assert logs == ["  structural candidates not scored: an additive effect explains 70 % of "
                    "the innovation energy"]
    # near the best: scored at the places of the three best additive ones only
    ranking, signif, calls, logs = _gather(
        monkeypatch, settings(structural_threshold=0.5, structural_near_best=True), 0.7)
    assert calls == [({("source", "pump"), ("source", "tank")}, None, 3)]
    assert "saturation" in [c.effect for c in ranking]


def test_when_no_confirmed_candidate_passes_the_skipped_ones_are_scored_and_confirmed(
        monkeypatch):
    """The fallback scores the structural candidates (every place) with the
    step's additive ones as the family, and confirms only the significant
    newcomers; with none significant it accepts nothing."""
    additive = [cand("offset", explained=0.7), cand("gain", explained=0.2)]
    result = SimpleNamespace(rankings=[list(additive)], truth_ranks=[])
    scored, confirmed = [], []

    def structural(ctx, current, scales, effects, places=None, todo=None, others=0, ahead=()):
        scored.append((places, others))
        return [cand("saturation", kind="likelihood ratio", statistic=80.0, p=p_sat),
                cand("offset", statistic=1.0)]           # already ranked: left out

    def rounds(ctx, result, current, signif, scales, tag, step):
        confirmed.append([c.effect for c in signif])
        return "fit"

    monkeypatch.setattr(runner, "score_structural", structural)
    monkeypatch.setattr(runner, "confirm_in_rounds", rounds)
    monkeypatch.setattr(runner, "mark_limits", lambda cands: None)
    logs = []
    ctx = SimpleNamespace(settings=settings(structural_threshold=0.5), log=logs.append)
    p_sat = 1e-9
    assert runner.accepted_among_skipped_structurals(ctx, result, None, None, "t", 1) == "fit"
    assert scored == [(None, 2)] and confirmed == [["saturation"]]
    assert [c.effect for c in result.rankings[-1]] == ["saturation", "offset", "gain"]
    assert logs[0] == ("  none of the confirmed candidates passed the accept rule: scoring the "
                       "structural candidates skipped above")
    p_sat = 0.5                                          # not significant: nothing confirmed
    result.rankings = [list(additive)]
    confirmed.clear()
    assert runner.accepted_among_skipped_structurals(ctx, result, None, None, "t", 1) is None
    assert confirmed == []
