"""The discovered law as a loop effect (bondgraph/diagnose/discover/effect.py),
end to end: a mass-spring-damper whose spring has a quintic term −k5·x⁵ the
effect library does not list (it has a cubic stiffness), simulated by
scipy's solve_ivp from hand-written equations."""

import numpy as np
import pytest
import sympy as sp
from scipy.integrate import solve_ivp

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.data.records import Experiment
from bondgraph.diagnose.discover.effect import (
    DiscoveredEffect,
    coefficient_std,
    coefficient_unit,
    loop_with_discovery,
)
from bondgraph.diagnose.discover.law import DiscoveredLaw, Term
from bondgraph.diagnose.effects import Coulomb, CubicStiffness, QuadraticDrag, Viscous
from bondgraph.diagnose.effects.base import Target
from bondgraph.diagnose.settings import LoopSettings, SearchOptions
from bondgraph.errors import GraphError
from bondgraph.inference.options import UKFOptions
from bondgraph.numerics.model import Model

M, K, C, K5 = 2.0, 50.0, 1.5, 3000.0       # the catalog's m, k, c; the missing quintic
NOISE = 0.002
T = np.arange(0.0, 30.0, 0.01)


def force(t):
    return (15 * np.sin(2 * np.pi * 0.3 * t) + 10 * np.sin(2 * np.pi * 1.1 * t + 1)
            + 5 * np.sin(2 * np.pi * 2.3 * t + 2))


def quintic_record():
    def rhs(t, s):
        x, v = s
        return [v, (force(t) - K * x - C * v - K5 * x ** 5) / M]

    sol = solve_ivp(rhs, (T[0], T[-1]), [0.0, 0.0], t_eval=T, method="LSODA", rtol=1e-9,
                    atol=1e-11, max_step=0.005)
    y = sol.y[0] + NOISE * np.random.default_rng(0).standard_normal(T.size)
    return Experiment.from_arrays(T, {"F": force(T), "x": y}, units={"F": "N", "x": "m"},
                                  roles={"F": "input", "x": "output"}, noise_std={"x": NOISE})


def test_loop_accepts_the_discovered_quintic_spring_and_the_held_out_error_falls():
    # the force is smooth: the filter holds it linearly between samples (a
    # zero-order hold delays it by half a sample and biases k and c0)
    settings = LoopSettings(params=["k", "c"], holdout=0.25,
                            ukf=UKFOptions(substeps=4, hold="linear"),
                            effects=(CubicStiffness(), Coulomb(), Viscous(), QuadraticDrag()),
                            search=SearchOptions(max_steps=1))
    logs = []
    record = quintic_record()
    res, disc = loop_with_discovery(mass_spring_damper(), record, settings,
                                    log=logs.append)
    assert disc is not None, "\n".join(logs)
    # the regression's main term is the quintic, within 20 % of the truth
    main = disc.passivity.law.terms[0]
    assert main.name == "q_spring^5" and main.coef == pytest.approx(-K5, rel=0.20)
    assert not disc.passivity.refused
    # the loop accepts it (not the library's cubic look-alike) ...
    assert [(s.effect, s.attached_to) for s in res.steps] == [("discovered", "v")]
    step = res.steps[0]
    # ... refits its coefficient by maximum likelihood within 3 % of the truth
    assert step.parameters["discovered.v.c0"]["estimate"] == pytest.approx(-K5, rel=0.03)
    assert step.parameters["k"]["estimate"] == pytest.approx(K, rel=0.03)
    # ... and the held-out free-run error falls at least tenfold
    assert step.validated and step.error_after < 0.1 * step.error_before
    est = {n: v["estimate"] for n, v in step.parameters.items()}
    std = coefficient_std(mass_spring_damper(), record.segment(0, int(0.75 * T.size)),
                          disc.effect, est, ukf=settings.ukf)
    # a finite Cramér-Rao std for every coefficient; the quintic's is below
    # 1 % of it. (Measured: c0 = -2973 ± 3.5 against -3000: 8 stds off, the
    # std understates the error; the regression's extra cubic term, refitted
    # to -1.6, is correlated with c0.)
    s0 = std["discovered.v.c0"]
    assert all(np.isfinite(v) and v > 0 for v in std.values())
    assert s0 < 0.01 * K5
    text = disc.effect.readable(est, std)
    assert text.startswith("v effort [N] = -") and "(±" in text and "q_spring^5" in text
    print(text)


def test_discovered_effect_builds_a_graph_with_checked_units():
    V, Q = sp.Symbol("v.f"), sp.Symbol("q_spring")
    law = DiscoveredLaw("v", "effort", "N", {"v.f": V, "q_spring": Q},
                        [Term("q_spring^5", Q ** 5, -3000.0, 1.0, "(m)^5"),
                         Term("|v.f|·v.f", sp.Abs(V) * V, -0.5, 1.0, "(m/s)^2")],
                        [], [], np.zeros(0), np.zeros(0), 1.0, 0.0, {})
    eff = DiscoveredEffect(law)
    g = mass_spring_damper()
    (tgt,) = eff.targets(g)
    assert tgt == Target("junction", "v")
    P = eff.apply(g, tgt, {"c0": -2000.0})
    assert P["c0"].unit == "N/m**5" and P["c1"].unit == "N*s**2/m**2"
    assert P["c0"].default == -2000.0 and P["c1"].default == -0.5
    assert P["c0"].bounds == (-30000.0, 0.0)               # from the law's -3000: its sign kept
    # the generated model's force balance, against the hand-written one
    m = Model.from_graph(g)
    i_p, i_q = m.states.index("p_mass"), m.states.index("q_spring")
    xs = np.zeros((1, 2))
    xs[0, i_p], xs[0, i_q] = 0.4, 0.3
    u = np.array([[1.0]])
    dp = float(m.f(xs, u, m.theta0[None, :])[0, i_p])
    v = 0.4 / M
    assert dp == pytest.approx(1.0 - K * 0.3 - C * v - 2000.0 * 0.3 ** 5 - 0.5 * abs(v) * v,
                               rel=1e-12)
    assert coefficient_unit("N", "1") == "N"
    with pytest.raises(GraphError):
        DiscoveredEffect(DiscoveredLaw("v", "effort", "N", {}, [], [], [], np.zeros(0),
                                       np.zeros(0), 1.0, 0.0, {}))


def test_discovered_flow_law_at_a_zero_junction():
    """A law of the shaft's torque entering the 0-junction of the compliant
    shaft as a flow: dφ/dt = p_m/J_m − p_L/J_L + c·(k_s φ)³ (hand-derived)."""
    from bondgraph.catalog.reference import dc_motor_compliant
    from bondgraph.core import units

    E = sp.Symbol("shaft.e")
    law = DiscoveredLaw("shaft", "flow", "rad/s", {"shaft.e": E},
                        [Term("shaft.e^3", E ** 3, 2e-3, 1.0, "(N*m)^3")],
                        [], [], np.zeros(0), np.zeros(0), 1.0, 0.0, {})
    eff = DiscoveredEffect(law)
    g = dc_motor_compliant()
    assert eff.targets(mass_spring_damper()) == []           # no 0-junction 'shaft' there
    (tgt,) = eff.targets(g)
    P = eff.apply(g, tgt)
    assert units.factor(P["c0"].unit, "rad/s/N^3/m^3") == pytest.approx(1.0)
    m = Model.from_graph(g)
    th = m.theta0
    val = {n: th[m.param_index(n)] for n in ("J_m", "J_L", "k_s")}
    xs = np.zeros((1, len(m.states)))
    phi_name = next(s for s in m.states if "k_s" in s)
    pm, pl = next(s for s in m.states if s.endswith("J_m")), next(s for s in m.states
                                                                    if s.endswith("J_L"))
    xs[0, m.states.index(phi_name)], xs[0, m.states.index(pm)] = 0.01, 3e-3
    xs[0, m.states.index(pl)] = 1e-2
    dphi = float(m.f(xs, np.zeros((1, len(m.inputs))), th[None, :])[0, m.states.index(phi_name)])
    want = 3e-3 / val["J_m"] - 1e-2 / val["J_L"] + 2e-3 * (val["k_s"] * 0.01) ** 3
    assert dphi == pytest.approx(want, rel=1e-12)


def test_the_command_lines_discover_option_runs_the_loop_again_with_the_law(tmp_path):
    """`bondgraph loop --discover` (cli/loop._with_discovery): after a loop
    that accepted the library's cubic look-alike and left coloured
    innovations, the law found at the spring's 1-junction joins the effects
    and the second loop accepts it; its report replaces the first."""
    from types import SimpleNamespace

    from bondgraph.cli.loop import _with_discovery
    from bondgraph.diagnose.runner import run_loop

    settings = LoopSettings(params=["k", "c"], holdout=0.25,
                            ukf=UKFOptions(substeps=4, hold="linear"),
                            effects=(CubicStiffness(), Coulomb()),
                            search=SearchOptions(max_steps=1))
    record = quintic_record()
    first = run_loop(mass_spring_damper(), record, settings, log=lambda m: None,
                     progress=False)
    assert [s.effect for s in first.steps] == ["cubic_stiffness"]
    assert not first.final.residuals.is_white()
    res = _with_discovery(SimpleNamespace(quiet=True), mass_spring_damper(), record, settings,
                          first, tmp_path / "report")
    assert [(s.effect, s.attached_to) for s in res.steps] == [("discovered", "v")]
    assert res.final.validation_metric < 0.1 * first.final.validation_metric
    assert (tmp_path / "report" / "report.md").exists()
    assert not (tmp_path / "report-discover").exists()      # republished in report/
    assert "discovered" in (tmp_path / "report" / "loop.log").read_text()
    # the report shows the reconstruction against the accepted law
    assert res.discovery is not None and res.discovery.accepted
    md = (tmp_path / "report" / "report.md").read_text()
    assert "![discovery.png](discovery.png)" in md and res.discovery.text in md
    assert (tmp_path / "report" / "discovery.png").exists()
    assert "discovery" in (tmp_path / "report" / "report.html").read_text()
    # augmented_model.py rebuilds the augmented graph (the discovered law is
    # data: from its pickle); its model equals the loop's final one
    from bondgraph.core.plugins import resolve

    g = resolve(f"{tmp_path / 'report' / 'augmented_model.py'}:build")()
    m, ref = Model.from_graph(g), Model.from_graph(res.final_graph)
    assert m.states == ref.states and set(m.params) == set(ref.params)
    rng = np.random.default_rng(3)
    x = rng.normal(0.0, 0.2, (4, len(m.states)))
    u = rng.normal(0.0, 5.0, (4, 1))
    th = np.array([[res.final.estimates.get(n, ref.theta0[ref.param_index(n)])
                    for n in ref.params]])
    th_m = np.array([[th[0, ref.param_index(n)] for n in m.params]])
    np.testing.assert_allclose(m.f(x, u, np.repeat(th_m, 4, 0)),
                               ref.f(x, u, np.repeat(th, 4, 0)), rtol=1e-12)
    # its defaults are the final estimates
    for n, v in res.final.estimates.items():
        assert g.params[n].default == pytest.approx(v, rel=1e-12)


def _loop_result(validation, metric=1.0, more=None):
    from types import SimpleNamespace

    final = SimpleNamespace(validation_metric=validation, metric=metric,
                            more_metrics=dict(more or {}))
    return SimpleNamespace(final=final, warnings=[])


def test_the_loop_with_discovered_laws_replaces_the_first_only_when_better():
    """discovery_not_better: the second loop (from the declared graph, with
    the discovered laws beside the library) replaces the first only when
    its final free-run error on the judging record is lower and it is no
    worse on any further validation record; without a validation record
    the estimation record's error judges. A user's cascaded tanks (the
    benchmark's record) with --discover ended at 0.1865 held out where the
    library alone had reached 0.1217, and that model was the one kept."""
    from bondgraph.diagnose.discover.effect import discovery_not_better

    lib = _loop_result(0.1217, more={"val": 0.40})
    assert discovery_not_better(lib, _loop_result(0.1865)) == (
        "the loop with the discovered law(s) ends at 0.1865 on the validation record, the "
        "library's at 0.1217: the library's model stands")
    assert discovery_not_better(lib, _loop_result(0.1217)) is not None     # a tie keeps the first
    assert discovery_not_better(lib, _loop_result(float("nan"))) is not None
    assert discovery_not_better(lib, _loop_result(0.10, more={"val": 0.39})) is None
    assert discovery_not_better(lib, _loop_result(0.10, more={"val": 0.41})) == (
        "the loop with the discovered law(s) ends at 0.41 on the validation record 'val', the "
        "library's at 0.4: the library's model stands")
    # no validation record: the estimation record's error
    assert discovery_not_better(_loop_result(None, 0.3), _loop_result(None, 0.2)) is None
    assert "on the estimation record, the library's at 0.2" in discovery_not_better(
        _loop_result(None, 0.2), _loop_result(None, 0.3))


def test_a_worse_discovery_loop_leaves_the_first_report(tmp_path, monkeypatch):
    """cli/loop._with_discovery: the second loop reports into
    ``<out>-discover`` while it runs; when it ends no better, the first
    loop's report stays in ``out``, untouched, the first result is returned
    with the reason among its warnings and said in one line."""
    from types import SimpleNamespace

    from bondgraph.cli import loop as cli_loop
    from bondgraph.diagnose.discover import effect as eff

    out = tmp_path / "report"
    out.mkdir()
    (out / "report.md").write_text("the first loop's report")
    best = SimpleNamespace(law=SimpleNamespace(port="v"), alternatives=[],
                           effects=lambda: [], accepted_in=lambda r: None)
    monkeypatch.setattr(eff, "discovered_effect", lambda *a, **k: best)
    monkeypatch.setattr(eff, "with_discovered", lambda s, *e: s)
    monkeypatch.setattr(cli_loop, "run_loop", lambda *a, **k: _loop_result(0.1865))
    lines = []
    monkeypatch.setattr("builtins.print", lambda *a, **k: lines.append(" ".join(map(str, a))))
    first = _loop_result(0.1217)
    res = cli_loop._with_discovery(SimpleNamespace(quiet=False), mass_spring_damper(), None,
                                   LoopSettings(params=["k"]), first, out)
    assert res is first and (out / "report.md").read_text() == "the first loop's report"
    assert first.warnings == ["the loop with the discovered law(s) ends at 0.1865 on the "
                              "validation record, the library's at 0.1217: the library's model "
                              "stands"]
    assert any(line.startswith("bondgraph loop: the loop with the discovered law(s) ends at "
                               "0.1865") and "report-discover" in line for line in lines)
