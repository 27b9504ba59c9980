"""Candidates that are one model are refitted once
(diagnose.confirm.same_model_key, confirm_same; diagnose.runner.same_models).

A term added to either of two R elements on one 1-junction gives the same
state equations: the junction sums their efforts. On the bundled vehicle a
quadratic law at the brake's R and at the rolling resistance's R were two
refits of one model, with identical likelihood ratios.

Record: a rotor J dω/dt = T − (b1 + b2) ω − c ω|ω| (a bearing and a seal,
both viscous, and a quadratic drag the graph lacks), a multisine torque held
over each sample, integrated by scipy (LSODA, rtol 1e-9), speed measured
with noise 0.02 rad/s. The loop's library is the quadratic law of a
resistor alone."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph import BondGraph
from bondgraph.data.records import Experiment
from bondgraph.diagnose import runner
from bondgraph.diagnose.confirm import same_model_key
from bondgraph.diagnose.effects import Scales, Target, get_effect
from bondgraph.diagnose.fit import model_of
from bondgraph.diagnose.loop import LoopSettings, run_loop
from bondgraph.diagnose.settings import SearchOptions

J, B1, B2, C, NOISE, DT = 0.5, 0.06, 0.04, 0.08, 0.02, 0.01


def rotor(seal_on_own_junction: bool = False) -> BondGraph:
    g = BondGraph("rotor2", "a rotor on a bearing and a seal")
    j = g.param("J", 0.4, "kg*m**2", (0.05, 5.0), "inertia")
    b1 = g.param("b1", 0.05, "N*m*s/rad", (0.001, 2.0), "bearing friction")
    b2 = g.param("b2", 0.05, "N*m*s/rad", (0.001, 2.0), "seal friction")
    T = g.input("T", "N*m", 0.0, "torque")
    w = g.one("w", domain="rotation")
    g.connect(g.Se("motor", T), w)
    g.connect(w, g.I("inertia", j))
    g.connect(w, g.R("bearing", b1))
    if seal_on_own_junction:          # the seal behind a compliant coupling: another flow
        k = g.param("ck", 0.02, "rad/(N*m)", (1e-4, 1.0), "coupling compliance")
        z = g.zero("z", domain="rotation")
        s = g.one("s", domain="rotation")
        g.connect(w, z)
        g.connect(z, g.C("coupling", k))
        g.connect(z, s)
        g.connect(s, g.I("sleeve", g.param("Js", 0.01, "kg*m**2", (0.001, 1.0), "sleeve")))
        g.connect(s, g.R("seal", b2))
    else:
        g.connect(w, g.R("seal", b2))
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
        return [(u - (B1 + B2) * x[0] - C * x[0] * abs(x[0])) / J]

    X = solve_ivp(f, (0, t[-1]), [0.0], t_eval=t, method="LSODA", rtol=1e-9, atol=1e-12,
                  max_step=DT / 4).y.T
    y = X + NOISE * rng.standard_normal((n, 1))
    return Experiment.from_arrays(t, model=model_of(rotor()), u=torque(t + shift)[:, None], y=y,
                                  name="rotor2", noise_std={"w": NOISE})


def key(graph: BondGraph, effect: str, at: str) -> tuple:
    g = graph.copy(f"{graph.name}_{effect}_{at}")
    eff = get_effect(effect)
    P = eff.apply(g, Target("resistor", at), {}, Scales())
    new = [P[p.name].name for p in eff.params if p.estimated and p.name in P]
    return same_model_key(model_of(g), P, new)


def test_a_law_at_either_resistor_of_one_junction_is_one_model():
    g = rotor()
    assert key(g, "r_quadratic", "bearing") == key(g, "r_quadratic", "seal")
    assert key(g, "r_cubic", "bearing") == key(g, "r_cubic", "seal")
    assert key(g, "r_quadratic", "bearing") != key(g, "r_cubic", "bearing")


def test_a_resistor_on_another_flow_is_another_model():
    g = rotor(seal_on_own_junction=True)
    assert key(g, "r_quadratic", "bearing") != key(g, "r_quadratic", "seal")


def run(dedupe: bool = True, effects=("r_quadratic",)):
    logs: list[str] = []
    settings = LoopSettings(params=["J", "b1", "b2"], validation=record(1000, 7.3, 5),
                            effects=[get_effect(e) for e in effects],
                            search=SearchOptions(max_steps=1, structural=False))
    with pytest.MonkeyPatch.context() as mp:
        if not dedupe:
            mp.setattr(runner, "same_models", lambda *a, **k: {})
        res = run_loop(rotor(), record(1500, 0.0, 3), settings, log=logs.append,
                       progress=False)
    confirmed = {s.split("confirmed ")[1].split(":")[0]: float(s.split("LR ")[1].split()[0])
                 for s in logs if "] " in s and s.split("] ", 1)[1].startswith("  confirmed ")}
    return res, logs, confirmed


def test_the_twin_is_not_refitted_and_reaches_what_its_own_refit_reaches():
    res, logs, lr = run()
    (line,) = [s for s in logs if "the same model as" in s]
    assert "r_quadratic @ seal: the same model as r_quadratic @ bearing" in line
    assert lr["r_quadratic @ seal"] == lr["r_quadratic @ bearing"]
    (step,) = res.steps
    assert step.effect == "r_quadratic"
    # the quadratic drag c = 0.08 found at either resistor (0.0798 +- 0.0005)
    beta = [v for k, v in step.parameters.items() if k.endswith(".beta")]
    assert len(beta) == 1 and abs(beta[0]["estimate"] - C) < 3 * beta[0]["std"], beta
    # the twin says whose model it is and takes no place among the pairs
    by_label = {c.label: c for c in res.rankings[0]}
    twin, rep = by_label["r_quadratic @ seal"], by_label["r_quadratic @ bearing"]
    assert twin.same_as == rep.label and rep.label in twin.equivalent
    assert rep in runner.pair_pool(res.rankings[0])
    assert twin not in runner.pair_pool(res.rankings[0])
    # the reference: both refitted in full, as before
    res0, logs0, lr0 = run(dedupe=False)
    assert not [s for s in logs0 if "equal state equations" in s]
    # the refits' equal likelihoods tell the twin too (runner.rescaled_twins)
    (line0,) = [s for s in logs0 if "the same model as" in s]
    assert "r_quadratic @ seal: the same model as r_quadratic @ bearing up to its " \
           "parameters' scale (equal refitted likelihood" in line0
    assert lr["r_quadratic @ seal"] == pytest.approx(lr0["r_quadratic @ seal"], rel=1e-3)
    assert res0.steps[0].attached_to == step.attached_to
    assert res0.steps[0].error_after == pytest.approx(step.error_after, rel=1e-9)


def _key_at(graph: BondGraph, effect: str, target: Target, new_boxes: bool) -> tuple:
    g = graph.copy(f"{graph.name}_{effect}_{target.name}")
    eff = get_effect(effect)
    P = eff.apply(g, target, {}, Scales())
    new = [P[p.name].name for p in eff.params if p.estimated and p.name in P]
    return same_model_key(model_of(g), P, new, new_boxes=new_boxes)


def test_a_drag_at_the_junction_is_the_law_at_its_resistor_in_another_box():
    """A quadratic drag c >= 0 at the rotor's junction and a quadratic law
    of either sign at the bearing's resistor give one likelihood (the
    junction sums the efforts; the same smoothing width), searched over
    different boxes: equal keys without the new parameters' boxes, not with
    them. In the loop the law's refit (c = 0.08 > 0, inside the drag's box)
    is the drag's too: one refit, the same likelihood ratio as refitting
    both (:func:`bondgraph.diagnose.confirm.refit_inside`); a refit at a
    negative value is not the drag's."""
    from types import SimpleNamespace

    from bondgraph.diagnose.confirm import refit_inside

    g = rotor()
    drag, law = Target("junction", "w"), Target("resistor", "bearing")
    assert _key_at(g, "quadratic_drag", drag, False) == _key_at(g, "r_quadratic", law, False)
    assert _key_at(g, "quadratic_drag", drag, True) != _key_at(g, "r_quadratic", law, True)

    both = ("r_quadratic", "quadratic_drag")
    res, logs, lr = run(True, both)
    twins = [s for s in logs if "quadratic_drag @ w: the same model as r_quadratic @ " in s
             or "the same model as quadratic_drag @ w" in s]
    assert twins, [s for s in logs if "same model" in s]
    assert "refitted in full" not in " ".join(s for s in logs if "quadratic_drag @ w" in s)
    assert len({lr[k] for k in lr if "quadratic" in k}) == 1, lr
    res0, _, lr0 = run(False, both)
    assert lr["quadratic_drag @ w"] == pytest.approx(lr0["quadratic_drag @ w"], rel=1e-3)
    assert res0.steps[0].error_after == pytest.approx(res.steps[0].error_after, rel=1e-6)
    # a refit at a negative value (on no bound of its own box) is not one of
    # a nonnegative box; at a positive value inside it, it is, unless unconverged
    box = (lambda lo, hi: SimpleNamespace(bounds=lambda names: (np.array([lo]), np.array([hi])),
                                          param_index=lambda n: 0))
    f0 = SimpleNamespace(model=box(-1.0, 2.0), theta=np.array([-0.01]), converged=True,
                         at_bound=[])
    assert not refit_inside(f0, box(0.0, 2.0), {"beta": "c"})
    assert refit_inside(f0, box(-1.0, 2.0), {"beta": "c"})      # equal boxes: as before
    f0.theta = np.array([0.5])
    assert refit_inside(f0, box(0.0, 2.0), {"beta": "c"})
    f0.at_bound = ["beta"]
    assert refit_inside(f0, box(-1.0, 2.0), {"beta": "c"})
    assert not refit_inside(f0, box(0.0, 2.0), {"beta": "c"})
    f0.at_bound, f0.converged = [], False
    assert not refit_inside(f0, box(0.0, 2.0), {"beta": "c"})
