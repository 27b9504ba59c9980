"""A refused candidate whose refit leaves some of its terms undetermined
is refitted with those terms held at 0 and judged in its place
(diagnose.runner.held_retry): on a user's EMPS graph whose loop had
accepted a force offset, the direction-dependent friction was refused
because its Coulomb half-difference dc·tanh²(v/ε) is that offset wherever
the drive moves, and its viscous half-difference went with it.

Record: a rotor J dω/dt = T − off − (b + dv·tanh(ω/ε)) ω (viscous friction
b ± dv for either direction, a torque offset), a multisine torque held over
each sample, integrated by scipy (LSODA, rtol 1e-9), speed measured with
noise 0.02 rad/s; the graph declares J, b and the offset. The loop's library
is the direction-dependent friction alone."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph import BondGraph
from bondgraph.data.records import Experiment
from bondgraph.diagnose.effects import get_effect
from bondgraph.diagnose.fit import model_of
from bondgraph.diagnose.loop import LoopSettings, run_loop
from bondgraph.diagnose.settings import SearchOptions

J, B, DV, OFF, NOISE, DT = 0.5, 0.1, 0.04, 0.15, 0.02, 0.01


def rotor() -> BondGraph:
    g = BondGraph("rotor", "a rotor on a viscous bearing, a torque offset")
    j = g.param("J", 0.4, "kg*m**2", (0.05, 5.0), "inertia")
    b = g.param("b", 0.2, "N*m*s/rad", (0.001, 2.0), "viscous friction")
    off = g.param("off", 0.0, "N*m", (-2.0, 2.0), "torque offset")
    T = g.input("T", "N*m", 0.0, "torque")
    w = g.one("w", domain="rotation")
    g.connect(g.Se("motor", T), w)
    g.connect(g.Se("offset", -off), w)
    g.connect(w, g.I("inertia", j))
    g.connect(w, g.R("bearing", b))
    g.sensor("w", w.f, unit="rad/s", noise_std=NOISE)
    return g


def torque(t):
    return sum(a * np.sin(2 * np.pi * f * t + p)
               for a, f, p in ((1.0, 0.13, 0.0), (0.6, 0.31, 1.0), (0.4, 0.77, 2.0)))


def record(n: int, shift: float, seed: int) -> Experiment:
    """``n`` samples of the rotor, the torque's phase moved by ``shift`` s."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT

    def f(tt, x):
        u = torque(np.floor(tt / DT + 1e-9) * DT + shift)
        return [(u - OFF - (B + DV * np.tanh(x[0] / 0.01)) * x[0]) / J]

    X = solve_ivp(f, (0, t[-1]), [0.0], t_eval=t, method="LSODA", rtol=1e-9, atol=1e-12,
                  max_step=DT / 4).y.T
    y = X + NOISE * rng.standard_normal((n, 1))
    return Experiment.from_arrays(t, model=model_of(rotor()), u=torque(t + shift)[:, None], y=y,
                                  name="rotor", noise_std={"w": NOISE})


@pytest.fixture(scope="module")
def loop():
    logs: list[str] = []
    res = run_loop(rotor(), record(2000, 0.0, 3),
                   LoopSettings(params=["J", "b", "off"], validation=record(1500, 7.3, 5),
                                effects=[get_effect("asymmetric_friction")],
                                search=SearchOptions(max_steps=1)),
                   log=logs.append, progress=False)
    return res, logs


def test_the_viscous_half_difference_is_accepted_with_the_coulomb_one_held(loop):
    res, logs = loop
    (step,) = res.steps
    assert (step.effect, step.attached_to, step.held) == ("asymmetric_friction", "w", {"dc": 0.0})
    assert step.shown() == "asymmetric_friction (dc = 0)"
    P = step.parameters
    assert "asymmetric_friction.w.dc" not in P
    for name, truth in (("asymmetric_friction.w.dv", DV), ("off", OFF), ("b", B), ("J", J)):
        assert abs(P[name]["estimate"] - truth) < 3 * P[name]["std"], name
    assert P["off"]["std"] < 1e-3              # the offset stays determined
    # the augmented model re-applies the effect with dc = 0
    (applied,) = res.applied
    assert applied.values["dc"] == 0.0 and applied.values["dv"] == pytest.approx(
        P["asymmetric_friction.w.dv"]["estimate"])
    assert step.error_after < 0.2 * step.error_before


def test_the_whole_effect_was_refused_first_and_said_why(loop):
    res, logs = loop
    (rej,) = [r for r in res.rejected if r.candidate.label == "asymmetric_friction @ w"]
    assert rej.step == 1
    assert any("  asymmetric_friction @ w: refitted with dc held at 0 (the record does not "
               "tell asymmetric_friction.w.dc apart from off)" in s for s in logs)
    full = rej.candidate.confirmed
    assert full is not None and full["dof"] == 2


def test_a_ridge_that_ends_on_the_search_box_is_a_ridge_too():
    """runner.ridge_to_search_edge: the Coulomb half-difference dc, whose
    search box the loop set (±20 times the score's estimate), left on that
    box by a refit whose Fisher information is flat along dc and the offset
    (the offset's Cramér-Rao std stays small: on its box dc has none) is
    named with the offset as its partner, so held_retry holds it at 0 (a
    user's EMPS graph: dc ran to −13.36 N, the edge, along the offset). Not
    when dc sits inside its box, nor when the flat direction leaves out
    every parameter the current fit identified."""
    from types import SimpleNamespace

    from bondgraph.diagnose.effects import apply_effect
    from bondgraph.diagnose.fit import Context
    from bondgraph.diagnose.runner import ridge_to_search_edge

    g = rotor()
    eff = get_effect("asymmetric_friction")
    P = apply_effect(g, eff, eff.targets(g)[0], {"dc": 0.1, "dv": 0.01})
    dc, dv = P["dc"].name, P["dv"].name
    g.params[dc].bounds, g.params[dv].bounds = (-2.0, 2.0), (-0.2, 0.2)
    m = model_of(g)
    settings = LoopSettings(params=["J", "b", "off"], effects=[eff])
    ctx = Context.on(record(200, 0.0, 3), settings, m, lambda s: None, False)
    th = m.theta0.copy()
    th[m.param_index(dc)] = -2.0
    current = SimpleNamespace(params=["J", "b", "off"], flat=())
    after = SimpleNamespace(model=m, theta=th, params=["J", "b", "off", dc, dv],
                            at_bound=[dc], flat=("off", dc))
    assert ridge_to_search_edge(ctx, current, after, [dc, dv]) == ([dc], ["off"])
    # the current fit did not identify the offset either: the declared fit's affair
    assert ridge_to_search_edge(ctx, SimpleNamespace(params=current.params, flat=("off",)),
                                after, [dc, dv]) == ([], [])
    inside = th.copy()
    inside[m.param_index(dc)] = -1.0
    assert ridge_to_search_edge(ctx, current, SimpleNamespace(
        **{**vars(after), "theta": inside, "at_bound": []}), [dc, dv]) == ([], [])
    assert ridge_to_search_edge(ctx, current, SimpleNamespace(**{**vars(after), "flat": (dc,)}),
                                [dc, dv]) == ([], [])


def test_a_refit_that_crawls_along_the_ridge_holds_the_terms_that_lead_it():
    """runner.ridge_crawl: a refit that stopped unconverged with its Fisher
    information flat along dc, the offset and dv (ordered by loading, as
    fisher.flat_directions names them) holds dc, which loads on the flat
    direction more than the offset the current fit identified; dv, loading
    less, is judged. When the partner leads, the new term that loads most is
    held. Nothing for a converged refit, for a direction without a new term
    or without a parameter the current fit identified."""
    from types import SimpleNamespace

    from bondgraph.diagnose.runner import ridge_crawl

    current = SimpleNamespace(params=["J", "b", "off"], flat=())
    crawl = SimpleNamespace(converged=False, flat=("dc", "off", "dv"))
    assert ridge_crawl(current, crawl, ["dc", "dv"]) == (["dc"], ["off"])
    lead = SimpleNamespace(converged=False, flat=("off", "dv", "dc"))
    assert ridge_crawl(current, lead, ["dc", "dv"]) == (["dv"], ["off"])
    assert ridge_crawl(current, SimpleNamespace(converged=True, flat=crawl.flat),
                       ["dc", "dv"]) == ([], [])
    assert ridge_crawl(current, SimpleNamespace(converged=None, flat=crawl.flat),
                       ["dc", "dv"]) == ([], [])
    assert ridge_crawl(current, SimpleNamespace(converged=False, flat=("off", "b")),
                       ["dc", "dv"]) == ([], [])
    assert ridge_crawl(SimpleNamespace(params=current.params, flat=("off",)), crawl,
                       ["dc", "dv"]) == ([], [])


def test_the_held_refit_also_starts_where_the_effect_vanishes():
    """confirm.nested_start: the held refit's second start is the current
    model's estimates with the effect's remaining terms at 0 (the model
    without it, so the refit can end no worse than that model): on a user's
    EMPS graph the first start, the full refit's estimates with dc dropped,
    lay 41 N off in force and its refit ran away to a law RK4 no longer
    stepped. None where a term's box excludes 0."""
    from types import SimpleNamespace

    from bondgraph.diagnose.confirm import nested_start
    from bondgraph.diagnose.effects import apply_effect

    g = rotor()
    eff = get_effect("asymmetric_friction")
    P = apply_effect(g, eff, eff.targets(g)[0], {"dc": 0.1, "dv": 0.01})
    dv = P["dv"].name
    g.params[dv].bounds = (-0.2, 0.2)
    current = SimpleNamespace(estimates=lambda: {"J": 0.52, "b": 0.11, "off": 0.149})
    assert nested_start(current, P, [dv]) == [{"J": 0.52, "b": 0.11, "off": 0.149, dv: 0.0}]
    g.params[dv].bounds = (0.001, 0.2)
    assert nested_start(current, P, [dv]) == []
