"""A confirmation profiles the tanh width of a friction law's sign function
(diagnose.confirm.profiled_shape): the width is a smoothing, not physics,
and a record with many reversals can tell it. Too wide a width left a
user's geared DC motor with a misfit at every reversal that the loop's next
steps absorbed with a spurious speed-sensor gain. The kept width counts as
one more degree of freedom.

Record: a rotor J dω/dt = T − b ω − Fc tanh(ω/ε) on a multisine torque held
over each sample, integrated by scipy (LSODA, rtol 1e-9), speed measured
with noise 0.02 rad/s; the graph declares J and b only."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph import BondGraph
from bondgraph.data.records import Experiment
from bondgraph.diagnose.confirm import confirm, confirm_pair
from bondgraph.diagnose.effects import Target, get_effect
from bondgraph.diagnose.fit import Context, fit_model, model_of
from bondgraph.diagnose.result import Candidate
from bondgraph.diagnose.scales import operating_scales
from bondgraph.diagnose.settings import LoopSettings

J, B, FC, NOISE, DT = 0.5, 0.1, 0.4, 0.02, 0.01


def rotor() -> BondGraph:
    g = BondGraph("rotor", "a rotor on a viscous bearing driven by a torque")
    j = g.param("J", 0.4, "kg*m**2", (0.05, 5.0), "inertia")
    b = g.param("b", 0.2, "N*m*s/rad", (0.001, 2.0), "viscous friction")
    T = g.input("T", "N*m", 0.0, "torque")
    w = g.one("w", domain="rotation")
    g.connect(g.Se("motor", T), w)
    g.connect(w, g.I("inertia", j))
    g.connect(w, g.R("bearing", b))
    g.sensor("w", w.f, unit="rad/s", noise_std=NOISE)
    return g


def torque(t):
    return sum(a * np.sin(2 * np.pi * f * t + p)
               for a, f, p in ((1.0, 0.13, 0.0), (0.6, 0.31, 1.0), (0.4, 0.77, 2.0)))


def record(eps: float, n: int = 2000) -> Experiment:
    """The rotor with Coulomb friction of tanh width ``eps`` [rad/s], the
    torque held over each sample (the record's zero-order hold is exact)."""
    rng = np.random.default_rng(3)
    t = np.arange(n) * DT

    def f(tt, x):
        u = torque(np.floor(tt / DT + 1e-9) * DT)
        return [(u - B * x[0] - FC * np.tanh(x[0] / eps)) / J]

    X = solve_ivp(f, (0, t[-1]), [0.0], t_eval=t, method="LSODA", rtol=1e-9, atol=1e-12,
                  max_step=DT / 4).y.T
    y = X + NOISE * rng.standard_normal((n, 1))
    return Experiment.from_arrays(t, model=model_of(rotor()), u=torque(t)[:, None], y=y,
                                  name="rotor", noise_std={"w": NOISE})


def confirmed(eps: float):
    g = rotor()
    ctx = Context.on(record(eps), LoopSettings(params=["J", "b"]), model_of(g),
                     lambda s: None, False)
    current = fit_model(ctx, g, ["J", "b"], None, "declared")
    scales = operating_scales(ctx, current)
    cand = Candidate("coulomb", "", Target("junction", "w"), "score", 500.0, 1, 0.0, 498.0,
                     values={"Fc": 0.2})
    width = get_effect("coulomb").shape_values(g, cand.target, scales)["eps"]
    return ctx, current, scales, cand, width, confirm(ctx, current, cand, scales, "alone")


@pytest.fixture(scope="module")
def sharp():
    """The truth's width 0.002 rad/s, a tenth of the data-driven one."""
    return confirmed(0.002)


def test_a_sharper_reversal_than_the_default_width_is_kept_and_counted(sharp):
    _, current, _, _, width, conf = sharp
    assert 0.02 < width < 0.03             # 2 % of the RMS speed (about 1.2 rad/s)
    kept = conf.shape["coulomb.w.eps"]
    assert kept == pytest.approx(conf.values["eps"])
    assert kept in (pytest.approx(0.3 * width), pytest.approx(0.1 * width))
    assert conf.dof == 2 and conf.new_params == ["coulomb.w.Fc"] and conf.comparable
    # the graph the refit judged carries the width
    assert float(conf.fit.graph.params["coulomb.w.eps"].default) == pytest.approx(kept)
    est, std = conf.fit.estimates(), conf.fit.std
    for name, truth in (("coulomb.w.Fc", FC), ("J", J), ("b", B)):
        assert abs(est[name] - truth) < 3 * std[name], name
    assert current.nll - conf.fit.nll > 1000


def test_a_pair_keeps_a_members_width_and_counts_it(sharp):
    ctx, current, scales, cand, _, conf = sharp
    cand.confirmed = {"values": dict(conf.values)}
    offset = Candidate("sensor_offset", "", Target("sensor", "w"), "score", 5.0, 1, 0.02, 3.0,
                       values={"b": 0.0})
    pair = confirm_pair(ctx, current, (cand, offset), scales, "pair")
    assert pair.shape == {"coulomb.w.eps": pytest.approx(conf.shape["coulomb.w.eps"])}
    assert pair.dof == 3


def test_a_softer_reversal_keeps_the_data_driven_width():
    _, _, _, _, width, conf = confirmed(0.05)
    assert conf.shape == {} and conf.dof == 1
    assert conf.values["eps"] == pytest.approx(width)


def test_a_much_softer_reversal_keeps_the_wider_width():
    """The truth's width three times the data-driven one: x3 is kept (a
    law too sharp biases the level and the damping beside it)."""
    _, current, _, _, width, conf = confirmed(0.075)
    assert conf.shape == {"coulomb.w.eps": pytest.approx(3.0 * width)} and conf.dof == 2
    est, std = conf.fit.estimates(), conf.fit.std
    for name, truth in (("coulomb.w.Fc", FC), ("J", J), ("b", B)):
        assert abs(est[name] - truth) < 3 * std[name], name


@pytest.mark.parametrize("nlls, refitted", [
    ((10.0, 12.0, 5.0), [1.0, 0.3]),            # x0.3 did not lower the NLL: x0.1 not refitted
    ((10.0, 8.0, 9.0), [1.0, 0.3, 0.1]),        # x0.3 lowered it: x0.1 refitted
    ((10.0, float("nan"), 9.0), [1.0, 0.3, 0.1]),   # a failed x0.3 settles nothing
    ((10.0, 12.0, 5.0, 9.0), [1.0, 3.0, 0.3]),  # x3 lower than x1: the narrower side stops
    ((10.0, 8.0, 9.0, 9.5), [1.0, 3.0, 0.3, 0.1]),  # ... and goes on where x0.3 is lower still
    # a flat profile: x0.3 lowers x1's NLL by 0.02 (less than 0.1 of the 3.3
    # nats the keep test needs at 0.01): x0.1 not refitted
    ((10.0, 9.98, 5.0), [1.0, 0.3]),
    ((10.0, 9.5, 5.0), [1.0, 0.3, 0.1]),          # 0.5 nats: not flat, x0.1 refitted
    ((10.0, 9.98, 5.0, 9.9), [1.0, 3.0, 0.3]),   # x3 0.1 lower, x0.3 0.08 below it: flat
])
def test_narrower_widths_stop_at_the_first_that_does_not_lower_the_nll(monkeypatch, nlls,
                                                                       refitted):
    """The widths are refitted from the data-driven x1 outwards on each
    side (x3; x0.3, x0.1), whatever order they were built in; on a side, once a
    converged refit
    does not lower the lowest NLL so far, the narrower ones are not refitted
    (the refits are stubs that return the given NLL per width)."""
    from types import SimpleNamespace

    from bondgraph.diagnose import confirm as C

    calls = []
    per = dict(zip((1.0, 0.3, 0.1, 3.0), nlls))

    def fake_fit(ctx, g, names, start, what, **kw):
        calls.append(g)
        return SimpleNamespace(nll=per[g], converged=True)

    monkeypatch.setattr(C, "fit_model", fake_fit)
    monkeypatch.setattr(C, "continued", lambda ctx, g, f, label: f)
    ctx = SimpleNamespace(settings=LoopSettings([]))
    sub = SimpleNamespace()               # another context: x1 is refitted too
    # the data-driven width first, as _width_models builds them
    built = {k: (k, None, None) for k in per}
    conf = SimpleNamespace(fit=SimpleNamespace(estimates=lambda: {}))
    fits, tried = C._width_refits(ctx, sub, built, [], conf, "coulomb @ w")
    assert calls == refitted and list(fits) == refitted
    assert any("not refitted" in t for t in tried) == (len(refitted) < len(per))
    assert any("the profile is flat there" in t for t in tried) == (
        len(refitted) < len(per) and 0 < nlls[0] - min(per[k] for k in refitted) < 0.33), tried


def test_a_later_start_that_reaches_an_earlier_optimum_is_not_refitted_to_the_end(monkeypatch):
    """``confirm.refits_from_starts``: the first start's refit converges
    (θ (1, 2), Cramér-Rao std 0.1, 0.2); the second start's scoring is
    asked, after each accepted step, whether to stop: an iterate more than
    1 std off in a parameter goes on, one within 1 std of each with an NLL
    not 0.1 nats below the optimum's ends it, and that refit is left out
    (logged); the third start, whose iterate stays 2 std off, is kept. A
    start whose earlier refits did not converge is never stopped (the
    refits are stubs that replay the given iterates)."""
    from types import SimpleNamespace

    from bondgraph.diagnose import confirm as C

    model = SimpleNamespace(param_index=lambda n: {"a": 0, "b": 1}[n])
    path = {0: [], 1: [((1.5, 2.0), 10.2), ((1.05, 2.1), 10.05)], 2: [((1.2, 2.4), 10.5)]}
    stopped = []

    def fake_fit(ctx, g, names, start, what, model=None, iterations=None, tolerance=0.0,
                 stop=None):
        j = start["j"]
        end = ((1.0, 2.0), 10.0) if j == 0 else path[j][-1]
        for z, f in path[j]:
            if stop is not None and stop(SimpleNamespace(theta=np.array(z)), f):
                stopped.append(j)
                end = (z, f)
                break
        return SimpleNamespace(nll=end[1], theta=np.array(end[0]), converged=conv[j],
                               std={"a": 0.1, "b": 0.2}, model=model, iterations=len(path[j]))

    monkeypatch.setattr(C, "fit_model", fake_fit)
    lines = []
    ctx = SimpleNamespace(settings=LoopSettings([]), log=lines.append)
    conv = {0: True, 1: True, 2: True}
    fits = C.refits_from_starts(ctx, None, ["a", "b"], [{"j": j} for j in range(3)],
                                "coulomb @ w", model)
    assert stopped == [1] and [f.nll for f in fits] == [10.0, 10.5]
    assert lines == ["  coulomb @ w: the refit from start 2 reached the optimum of start 1 "
                     "(within 1 Cramér-Rao std of each estimate, after 2 iterations): not "
                     "continued"]
    stopped.clear()
    conv = {0: False, 1: True, 2: True}      # nothing converged to stop at
    fits = C.refits_from_starts(ctx, None, ["a", "b"], [{"j": j} for j in range(2)],
                                "coulomb @ w", model)
    assert stopped == [] and len(fits) == 2
    # an iterate below the optimum by more than 0.1 nats goes on
    conv = {0: True, 1: True, 2: True}
    path[1] = [((1.05, 2.1), 9.85)]
    fits = C.refits_from_starts(ctx, None, ["a", "b"], [{"j": j} for j in range(2)],
                                "coulomb @ w", model)
    assert stopped == [] and [f.nll for f in fits] == [10.0, 9.85]
