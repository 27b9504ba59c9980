"""Interacting effects accepted as a pair (issue 26): two tanks in parallel
overflow into a measured collector. The held-out record runs the two pumps
apart (one high, the other low, in turn). Two estimation records:

- lockstep (Q2 = 0.9 Q1: both overflow together): a single overflow fitted
  on it absorbs both and misfits the held-out record, each single is
  refused; the record cannot split the overflow between the tanks and the
  orifices either, so the true pair is refused too (its held-out error
  0.523 -> 0.407, z 1.54);
- independent levels (each pump its own staircase, switching together):
  the collector's overflow, a look-alike of both, passes alone, and the
  true pair beats it (refitted in two steps: its joint refit from the
  declared fit's scales pins tank 1's level on its box).

Truth: overflow of tank 1 at 0.6 and of tank 2 at 0.6 of their peak volume
in the declared model's simulation of the estimation record; records by
BDF (rtol 1e-9) of the truth graph plus N(0, 10 Pa) noise."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2
import sympy as sp

from bondgraph import BondGraph
from bondgraph.data.records import Experiment
from bondgraph.diagnose.effects import Target, apply_effect
from bondgraph.diagnose.effects.storage import CapacityLimit
from bondgraph.diagnose.loop import LoopSettings, run_loop
from bondgraph.diagnose.settings import SearchOptions
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate

TRUTH = {"K1": 3e-6, "K2": 2.5e-6, "K3": 4e-6}
NOISE = 10.0          # Pa
LEVEL = 0.6           # each overflow at this fraction of its tank's peak volume
N, DT, SEG = 1501, 2.0, 500.0


def parallel_tanks() -> BondGraph:
    """Two pumped tanks draining through orifices into a collector tank
    (the collector's pressure measured); orifice law K·Δp/(Δp² + 100)^¼."""
    g = BondGraph("parallel_tanks", "Two tanks in parallel into a collector.")
    Qs = [g.input(f"Q{i}", "m^3/s", 0.0, f"pump {i} flow") for i in (1, 2)]
    Cs = [g.param(f"C{i}", v, "m^3/Pa", (5e-6, 5e-4), f"tank {i}")
          for i, v in ((1, 1.2e-5), (2, 1e-5), (3, 1.5e-5))]
    Ks = [g.param(f"K{i}", 3e-6, "m^3/s/Pa^0.5", (3e-7, 3e-5), f"orifice {i}") for i in (1, 2, 3)]
    t3 = g.zero("tank3", domain="hydraulic")
    g.connect(t3, g.C("tank3_C", Cs[2]))
    g.connect(t3, g.R("orifice3", flow=lambda p: Ks[2] * p / (p**2 + 100.0) ** sp.Rational(1, 4)))
    for i in (1, 2):
        t = g.zero(f"tank{i}", domain="hydraulic")
        g.connect(g.Sf(f"pump{i}", Qs[i - 1]), t)
        g.connect(t, g.C(f"tank{i}_C", Cs[i - 1]))
        o = g.one(f"o{i}", domain="hydraulic")
        g.connect(t, o)
        g.connect(o, g.R(f"orifice{i}", flow=lambda dp, K=Ks[i - 1]:
                         K * dp / (dp**2 + 100.0) ** sp.Rational(1, 4)))
        g.connect(o, t3)
    g.sensor("p3", t3.e, unit="Pa", noise_std=NOISE, description="collector pressure")
    return g


def pumps(seed: int, together: bool | None):
    """Staircase pump flows (N,) [m³/s], a level per SEG s: in lockstep
    (``together`` True: Q2 = 0.9 Q1, Q1 ~ U(0, 3e-4)), at independent levels
    (None: Q1 ~ U(0, 3e-4), Q2 ~ 0.9 U(0, 3e-4)), or apart (False: in turn
    one pump at U(1.8e-4, 3e-4), the other at U(0, 6e-5))."""
    rng = np.random.default_rng(seed)
    t = np.arange(N) * DT
    k = (t // SEG).astype(int)
    m = k.max() + 1
    a = rng.uniform(0, 3e-4, size=m)
    b = rng.uniform(0, 3e-4, size=m)
    if together:
        return t, a[k], 0.9 * a[k]
    if together is None:
        return t, a[k], 0.9 * b[k]
    hi, lo = rng.uniform(1.8e-4, 3e-4, size=m), rng.uniform(0, 0.6e-4, size=m)
    odd = np.arange(m) % 2 == 1
    return t, np.where(odd, lo, hi)[k], 0.9 * np.where(odd, hi, lo)[k]


def _run(model, theta, t, q1, q2):
    return simulate(model, t, u={"Q1": q1, "Q2": q2}, x0=np.zeros(model.n_x), theta=theta,
                    method="BDF", hold="zoh", rtol=1e-9, atol=1e-12)


def pair_case(together: bool | None):
    """The loop (one step, only the capacity limit) on an estimation record
    of the design ``together`` (:func:`pumps`), judged on the record of the
    pumps apart. Returns (result, true levels, log lines, the truth's own
    free-run NRMSE on the held-out record: the noise floor)."""
    declared = Model.from_graph(parallel_tanks())
    peak = _run(declared, declared.theta(TRUTH), *pumps(1, together)).x.max(axis=0)
    g = parallel_tanks()
    qmax = {}
    for el in ("tank1_C", "tank2_C"):
        top = peak[declared.states.index(f"q_{el}")]
        qmax[el] = LEVEL * top
        apply_effect(g, "capacity_limit", Target("storage", el),
                     {"qmax": qmax[el], "w": 0.02 * top, "tau": DT})
    truth = Model.from_graph(g)
    floor = []

    def record(seed, together, name):
        t, q1, q2 = pumps(seed, together)
        clean = _run(truth, truth.theta(TRUTH), t, q1, q2).y[:, 0]
        y = clean + np.random.default_rng(seed + 50).standard_normal(N) * NOISE
        floor.append(float(np.sqrt(np.mean((y - clean) ** 2)) / np.std(y)))
        return Experiment.from_arrays(t, {"Q1": q1, "Q2": q2, "p3": y},
                                      units={"Q1": "m^3/s", "Q2": "m^3/s", "p3": "Pa"},
                                      roles={"Q1": "input", "Q2": "input", "p3": "output"},
                                      name=name)

    est, val = record(1, together, "estimation"), record(2, False, "apart")
    lines = []
    res = run_loop(parallel_tanks(), est, LoopSettings(
        ["K1", "K2", "K3"], validation=val, effects=(CapacityLimit(),),
        search=SearchOptions(max_steps=1, structural="always")), log=lines.append,
        progress=False)
    return res, qmax, lines, floor[1]


@pytest.fixture(scope="module")
def case():
    return pair_case(True)


@pytest.fixture(scope="module")
def independent():
    return pair_case(None)


def test_each_single_overflow_is_refused_and_the_partner_shows_given_the_lead(case):
    """Against the declared fit only tank 2's overflow and the collector's
    (a look-alike) are significant; tank 1's scores χ² = 0 (the declared
    orifices compensate both overflows; capping one tank only removes flow
    the compensated model needs). Each single is refused on the held-out
    error; given tank 2's refit, tank 1's overflow is significant and the
    true pair's joint refit ranks first of the pairs."""
    res, _, lines, _ = case
    first = {c.label: c for c in res.rankings[0]}
    # not significant alone (measured 0.0 and, after the codegen's reordering, 2.28)
    assert first["capacity_limit @ tank1_C"].statistic < chi2.isf(0.05, 1)
    singles = {r.candidate.label: r.reason for r in res.rejected if not
               r.reason.startswith("as a pair")}
    assert set(singles) == {"capacity_limit @ tank2_C", "capacity_limit @ tank3_C"}
    for why in singles.values():
        assert why.startswith(("the error grew on the validation record",
                               "the error decrease on the validation record is within"))
    assert any(ln.split("] ", 1)[1].startswith("  given capacity_limit @ tank2_C: "
                                                "capacity_limit @ tank1_C") for ln in lines)
    pair_lr = {ln.split("confirmed pair ")[1].split(":")[0]:
               float(ln.split(": LR ")[1].split(" ")[0]) for ln in lines if "confirmed pair" in ln}
    true_pair = "capacity_limit @ tank2_C + capacity_limit @ tank1_C"
    assert max(pair_lr, key=pair_lr.get) == true_pair


def test_the_lockstep_record_cannot_split_the_overflows(case):
    """On the lockstep record (Q2 = 0.9 Q1) the true pair is refitted (the
    best pair), but the record cannot split the overflow between the two
    tanks and their orifices. Either the held-out error refuses the pair
    (measured until 2026-12-02: 0.521 -> 0.413, z 1.41, p 0.079), or, with
    the held-out record's start fitted by the compiled run's least squares
    that converges (0.5232 -> 0.363, z 2.89, p 0.002; the start's LSODA
    search had stopped on its own difference noise), it is accepted with
    the split wrong: the fitted levels off the truth's by more than 10 % in
    opposite directions (0.0829 and 0.0502 against 0.0696 and 0.0621) and
    the held-out error over ten times the truth's own (0.0119). What else the
    loop may accept is tank 2's overflow with the collector's, a look-alike
    the held-out record supports (measured 0.521 -> 0.199, z 5.73): any
    accepted step must lower the held-out error significantly."""
    res, qmax, lines, floor = case
    true_pair = "capacity_limit @ tank2_C + capacity_limit @ tank1_C"
    refused = [ln for ln in lines if f"reject pair {true_pair}" in ln]
    true_steps = [st for st in res.steps if {st.attached_to, *[
        lab.split(" @ ")[1] for lab in st.together_with]} == {"tank1_C", "tank2_C"}]
    assert bool(refused) != bool(true_steps)
    if refused:
        assert "the error decrease on the validation record is within" in refused[0]
    else:
        est = res.final.estimates
        rel = {el: est[f"capacity_limit.{el}.qmax"] / qmax[el] - 1 for el in qmax}
        assert min(abs(r) for r in rel.values()) > 0.1 and np.prod(list(rel.values())) < 0
        assert true_steps[0].error_after > 10 * floor
    for st in res.steps:
        assert st.error_after < st.error_before
    accepts = [ln for ln in lines if "] ACCEPT " in ln]
    assert len(accepts) == len(res.steps)
    for ln in accepts:          # the error-decrease test's p-value (Diebold-Mariano)
        assert float(ln.split("error decrease z ")[1].split("(p ")[1].split(")")[0]) < 0.05


def test_the_two_overflows_are_accepted_as_one_step(independent):
    """Pumps at independent levels: the collector's overflow passes alone
    (a look-alike of both tanks'), the true pair beats it in the same step.

    Reference: the truth's levels, and its own free-run error on the
    held-out record (the noise floor, 0.0146). The levels and orifices are
    compared at 10 %, not at 3 Cramér-Rao std: the effect's onset width w is
    not estimated (2 % of the fitted storage's largest value: 0.0025 and
    0.0011 m³ against the truth's 0.0021 and 0.0016), and the overflow
    starts about 2 w below q_max at these flows, so the fitted levels and
    orifices absorb the width's difference. Measured: 0.0646 against
    0.0618, 0.0447 against 0.0469 (each ± 0.0002) on one machine; 0.0677 and
    0.0433, the orifices within 8 %, held-out error 0.063, on an AMD EPYC
    machine, where the joint refit converged to a poorer point (error 0.165)
    and the two-step refit of a structural pair (now always tried) reached
    this one."""
    res, qmax, lines, floor = independent
    (step,) = res.steps
    assert {step.attached_to, *[lab.split(" @ ")[1] for lab in step.together_with]} == \
        {"tank1_C", "tank2_C"}
    assert any("beats the single" in ln for ln in lines)
    assert any("refitted in two steps" in ln for ln in lines)
    for el in ("tank1_C", "tank2_C"):
        p = step.parameters[f"capacity_limit.{el}.qmax"]
        assert abs(p["estimate"] - qmax[el]) < 0.10 * qmax[el]
    for k, v in TRUTH.items():
        assert abs(step.parameters[k]["estimate"] - v) < 0.10 * v
    assert step.error_before > 0.5
    assert step.error_after < 5 * floor


@pytest.mark.parametrize("current_sim,screen", [("good", False), ("poor", True)])
def test_partners_are_screened_only_where_the_current_fit_cannot_simulate(monkeypatch,
                                                                          current_sim, screen):
    """partners_of: the output-error screen (a global search, 100 s of a
    user's EMPS step) runs in partner scoring only where the current fit's
    own free run is poor (NRMSE >= SCREEN_LEVEL, computed here from a run
    equal to the record: 0, or a run at rest: 1), not because the lead's
    refit broke it."""
    from contextlib import nullcontext
    from types import SimpleNamespace

    from bondgraph.diagnose import runner

    seen = []
    monkeypatch.setattr(runner, "conditioned", lambda ctx, fit: nullcontext())
    monkeypatch.setattr(runner, "score_additive",
                        lambda ctx, fit, scales, effects, screen=True: seen.append(screen) or [])
    y = np.sin(np.linspace(0.0, 20.0, 400))[:, None]
    current = SimpleNamespace(nll=1.0, sim_y=y.copy() if current_sim == "good" else 0 * y,
                              graph=None)
    lead = SimpleNamespace(label="lead @ x", target=SimpleNamespace(name="x"))
    conf = SimpleNamespace(fit=SimpleNamespace(sim_y=100 * y))      # the lead's broken run
    settings = SimpleNamespace(effects=[], search=SimpleNamespace(structural=False),
                               accept=SimpleNamespace(significance=0.01))
    ctx = SimpleNamespace(settings=settings, problem=SimpleNamespace(arrays=(None, None, y)),
                          cache={("confirmation", id(current), 1.0, "lead @ x"): conf},
                          log=lambda msg: None)
    assert runner.partners_of(ctx, current, lead, [], None, "t") == []
    assert seen == [screen]


def test_a_partner_the_record_does_not_determine_is_not_paired(monkeypatch):
    """partners_of: a partner significant given the lead whose own refit
    the record does not determine apart from the current model
    (accept.unidentified_effect says why) is left out, as pair_pool leaves
    such a candidate out; one it determines is kept."""
    from contextlib import nullcontext
    from types import SimpleNamespace

    from bondgraph.diagnose import runner

    def cand(label, place):
        return SimpleNamespace(label=label, target=SimpleNamespace(name=place), statistic=50.0,
                               dof=1, rank_key=(label,), values={"b": 1.0}, confirmed=None)

    good, ridge = cand("good @ y", "y"), cand("ridge @ z", "z")
    monkeypatch.setattr(runner, "conditioned", lambda ctx, fit: nullcontext())
    monkeypatch.setattr(runner, "score_additive",
                        lambda ctx, fit, scales, effects, screen=True: [good, ridge])
    monkeypatch.setattr(runner, "attachable", lambda graph, cands, effects: cands)
    monkeypatch.setattr(runner, "significant", lambda cands, level: cands)
    fits = {"good @ y": SimpleNamespace(name="g"), "ridge @ z": SimpleNamespace(name="r")}
    monkeypatch.setattr(runner, "confirm", lambda ctx, current, c, scales, tag:
                        SimpleNamespace(fit=fits[c.label]))
    monkeypatch.setattr(runner, "unidentified_effect", lambda current, after: (
        "the record does not identify ridge.b apart from F0" if after.name == "r" else ""))
    y = np.sin(np.linspace(0.0, 20.0, 400))[:, None]
    current = SimpleNamespace(nll=1.0, sim_y=y.copy(), graph=None)
    lead = SimpleNamespace(label="lead @ x", target=SimpleNamespace(name="x"))
    settings = SimpleNamespace(effects=[], search=SimpleNamespace(structural=False),
                               accept=SimpleNamespace(significance=0.01))
    said = []
    ctx = SimpleNamespace(settings=settings, problem=SimpleNamespace(arrays=(None, None, y)),
                          cache={("confirmation", id(current), 1.0, "lead @ x"):
                                 SimpleNamespace(fit=SimpleNamespace(sim_y=y))},
                          log=said.append)
    assert runner.partners_of(ctx, current, lead, [], None, "t") == [good]
    assert said[-1] == ("  ridge @ z is not paired: the record does not identify ridge.b "
                        "apart from F0")


def test_pair_step_shown_with_each_member_at_its_place():
    """A pair's step row names both effects in the effect column and both
    places in the attached-to column, in the same order (it read
    'inductor_saturation + cubic_stiffness @ cap | coil')."""
    from bondgraph.diagnose.result import Step
    s = Step("inductor_saturation", "coil", "nrmse", 1.0, 0.5, 0.0, -1.0, 0.0, -2.0, 9.0, 3.0,
             {}, 10.0, 0.01, together_with=["cubic_stiffness @ cap"],
             removed=["sensor_gain @ V2"])
    assert s.shown() == "inductor_saturation + cubic_stiffness (removing sensor_gain @ V2)"
    assert s.shown_target() == "coil + cap"
    single = Step("cubic_stiffness", "spring", "nrmse", 1.0, 0.5, 0.0, -1.0, 0.0, -2.0, 9.0,
                  3.0, {}, 10.0, 0.01)
    assert (single.shown(), single.shown_target()) == ("cubic_stiffness", "spring")
