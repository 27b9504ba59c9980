"""The free run's input hold (``LoopSettings.free_run.hold``) and confirmation in
rounds (``LoopSettings.search.confirm_rounds``), against hand-derived references."""

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.signal import cont2discrete

from bondgraph.catalog.benchmarks import EMPS_IDIM_LS, emps, emps_force_relerr
from bondgraph.catalog.cases import EmpsForceError
from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.data.records import Experiment
from bondgraph.diagnose import runner
from bondgraph.diagnose import fit as fit_module
from bondgraph.diagnose.fit import Context, StepCheck, free_run, sim_inputs
from bondgraph.diagnose.settings import FreeRunOptions, LoopSettings, SearchOptions
from bondgraph.errors import OptionError
from bondgraph.inference.options import UKFOptions
from bondgraph.numerics.model import Model


def test_sim_inputs_follow_the_filter_hold():
    u = np.array([[0.0], [2.0], [4.0], [10.0]])
    s = LoopSettings(params=[], free_run=FreeRunOptions(hold="filter"))
    hold, um = sim_inputs(s, "mean", u)
    assert hold == "zoh"
    np.testing.assert_allclose(um[:, 0], [1.0, 3.0, 7.0, 10.0])   # (u_k + u_k+1)/2, last held
    assert sim_inputs(s, "zoh", u)[0] == "zoh"
    assert sim_inputs(LoopSettings(params=[]), "mean", u)[0] == "linear"   # the default
    with pytest.raises(OptionError, match="FreeRunOptions.hold"):
        LoopSettings(params=[], free_run=FreeRunOptions(hold="cubic"))


def test_free_run_with_zero_order_hold_matches_the_exact_discretisation():
    """Mass-spring-damper (m 2, k 50, c 1.5) under a held step sequence: the
    free run with ``sim_hold="zoh"`` equals the exact zero-order-hold
    discretisation of dp/dt = F − k q − c p/m, dq/dt = p/m (scipy
    ``cont2discrete``); the linear hold does not."""
    m, k, c, dt = 2.0, 50.0, 1.5, 0.05
    t = np.arange(40) * dt
    F = np.where((np.arange(40) // 5) % 2 == 0, 1.0, -1.0)
    model = Model.from_graph(mass_spring_damper())
    A = np.array([[-c / m, -k], [1.0 / m, 0.0]])                       # x = (p, q)
    B = np.array([[1.0], [0.0]])
    Ad, Bd, *_ = cont2discrete((A, B, np.eye(2), np.zeros((2, 1))), dt, method="zoh")
    x, q_ref = np.zeros(2), []
    for f in F:
        q_ref.append(x[1])
        x = Ad @ x + Bd[:, 0] * f
    exp = Experiment.from_arrays(t, model=model, u=F[:, None], y=np.zeros((40, 2)), name="steps",
                                 meta={"x0": {"p_mass": 0.0, "q_spring": 0.0}})   # from rest
    ukf_run = SimpleNamespace(x_filt=np.zeros((1, 1, model.n_x)))
    ix = model.output_index("x")
    out = {}
    for hold in ("zoh", "linear"):
        ctx = Context.on(exp, LoopSettings(params=[], free_run=FreeRunOptions(hold=hold)), model, lambda s: None,
                         False)
        y = free_run(ctx, ctx.problem, model.theta0.copy())
        out[hold] = y[:, ix]
    np.testing.assert_allclose(out["zoh"], q_ref, atol=2e-6)
    assert np.max(np.abs(out["linear"] - q_ref)) > 1e-3


def test_confirmation_goes_on_in_rounds_until_one_is_accepted(monkeypatch):
    """With confirm_top 2 and confirm_rounds 3, seven significant candidates:
    rounds {a, b}, {c, d} are refused, {e, f} has the accepted one; g is
    never confirmed. With one round nothing is accepted."""
    cands = [SimpleNamespace(label=n, rank_key=i, statistic=10.0, dof=1,
                             confirmed_statistic=None) for i, n in enumerate("abcdefg")]
    seen = []

    def fake_confirm(ctx, current, batch, scales, name):
        seen.append([c.label for c in batch])
        return [(c, None) for c in batch]

    def fake_accept(ctx, result, current, confirmed, step, pairing=None, refit=None):
        return "fit-e" if any(c.label == "e" for c, _ in confirmed) else None

    monkeypatch.setattr(runner, "confirm_best", fake_confirm)
    monkeypatch.setattr(runner, "accept_best", fake_accept)
    ctx = SimpleNamespace(settings=LoopSettings(params=[], search=SearchOptions(confirm_top=2, confirm_rounds=3)),
                          log=lambda s: None)
    got = runner.confirm_in_rounds(ctx, None, None, cands[::-1], None, "g", 1)
    assert got == "fit-e" and seen == [["a", "b"], ["c", "d"], ["e", "f"]]
    seen.clear()
    ctx.settings = LoopSettings(params=[], search=SearchOptions(confirm_top=2, confirm_rounds=1))
    assert runner.confirm_in_rounds(ctx, None, None, cands, None, "g", 1) is None
    assert seen == [["a", "b"]]
    with pytest.raises(OptionError, match="confirm_rounds"):
        LoopSettings(params=[], search=SearchOptions(confirm_rounds=0))


def test_a_candidate_within_reach_is_confirmed_in_the_round_within_the_budget(monkeypatch):
    """confirm_top 2, confirm_rounds 3 (six refits): a and b refit to LR 100
    (less 2k: 98); c scored 95 (93 >= 0.9·98) is confirmed with them in
    round 1, d (50) is not. Nothing passes, so round 2 takes d and e and
    round 3 only f: six refits in all, as without c's early turn; g never."""
    stats = dict(zip("abcdefg", [99.0, 97.0, 95.0, 50.0, 40.0, 30.0, 20.0]))
    cands = [SimpleNamespace(label=n, rank_key=i, statistic=stats[n], dof=1,
                             confirmed_statistic=None) for i, n in enumerate("abcdefg")]
    seen, logs = [], []

    def fake_confirm(ctx, current, batch, scales, name, top=None, quiet=None):
        seen.append([c.label for c in batch])
        for c in batch:
            c.confirmed_statistic = 100.0
        return [(c, None) for c in batch]

    monkeypatch.setattr(runner, "confirm_best", fake_confirm)
    monkeypatch.setattr(runner, "accept_best", lambda *a, **k: None)
    ctx = SimpleNamespace(settings=LoopSettings(params=[], search=SearchOptions(
        confirm_top=2, confirm_rounds=3)), log=logs.append)
    assert runner.confirm_in_rounds(ctx, None, None, cands, None, "g", 1) is None
    assert seen == [["a", "b"], ["a", "b", "c"], ["d", "e"], ["f"]]
    assert any(s.startswith("  c: scored within 10 % of the best confirmed") for s in logs)


DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.mark.skipif(not (DATA / "emps").exists(), reason=f"real data folder {DATA} is absent")
def test_emps_force_error_at_the_sign_limit_is_the_published_protocol():
    """The EMPS case metric on the full EMPS graph (tanh-regularised Coulomb
    law, width v_eps) with the published symmetric IDIM-LS parameters equals
    the hand-written inverse model τ̂ = M q̈ + Fv q̇ + Fc sign(q̇) + offset
    (:func:`emps_force_relerr`) at the sign limit, on the estimation run and
    on the force-pulse validation run; the smooth law reads higher."""
    model = Model.from_graph(emps())
    theta = model.theta(dict(EMPS_IDIM_LS))
    fit = SimpleNamespace(model=model, theta=theta)
    metric = EmpsForceError()
    for part in ("estimation", "validation"):
        data = SimpleNamespace(exp=SimpleNamespace(meta={"emps_part": part}))
        ref = emps_force_relerr(**EMPS_IDIM_LS, signals=metric.signals(part))
        assert metric(fit, data) == pytest.approx(ref, rel=1e-9)
    smooth = EmpsForceError(sign_limit=False)(fit, SimpleNamespace(exp=SimpleNamespace(meta={})))
    assert smooth > metric(fit, SimpleNamespace(exp=SimpleNamespace(meta={}))) + 0.1


def test_auto_substeps_adopts_the_recommended_substeps(monkeypatch):
    """With ``auto_substeps`` a declared fit whose discretisation check
    recommends 16 substeps is refitted with them (the settings of the rest of
    the loop carry them), said in one line; without it the loop only warns."""
    calls = []
    monkeypatch.setattr(runner, "recommended_substeps", lambda ctx, fit, limit=0.1:
                        StepCheck(6.7, 16) if ctx.problem.disc.substeps == 1 else StepCheck(0.05))
    monkeypatch.setattr(fit_module, "refined_discretisation", lambda ctx, fit, n:
                        (replace(ctx.problem.disc, substeps=n), ""))
    monkeypatch.setattr(runner, "initial_fit",
                        lambda ctx, graph, again=False: calls.append(ctx.problem.disc.substeps) or "refit")
    model = Model.from_graph(mass_spring_damper())
    exp = Experiment.from_arrays(np.arange(20) * 0.05, model=model, u=np.zeros((20, 1)),
                                 y=np.zeros((20, 2)), name="rest")
    for auto, want in ((True, "refit"), (False, "declared")):
        calls.clear()
        ctx = Context.on(exp, LoopSettings(params=[], search=SearchOptions(auto_substeps=auto)), model,
                         lambda s: None, False)
        fit, warn = runner.resolved_fit(ctx, None, "declared")
        assert fit == want and "6.7 noise stds" in warn[0] and len(warn) == 1
        assert (warn[0].startswith("auto_substeps: ") and "takes 16 substeps" in warn[0]
                if auto else "use --substeps 16" in warn[0])
        assert (ctx.problem.disc.substeps, calls) == ((16, [16]) if auto else (1, []))


def test_auto_substeps_adopts_refined_runs_and_says_where(monkeypatch):
    """Where the refinement meets the check (:func:`refined_discretisation`),
    the loop keeps its substeps and takes the recommended ones on the runs
    of intervals that need them: the problem carries the runs, the refit
    runs on it, and the line says where."""
    runs = ((3, 9, 16),)
    note = " on the 6 of 19 intervals that need them"
    seen = []
    monkeypatch.setattr(runner, "recommended_substeps", lambda ctx, fit, limit=0.1:
                        StepCheck(6.7, 16) if not ctx.problem.disc.refine else StepCheck(0.05))
    monkeypatch.setattr(fit_module, "refined_discretisation", lambda ctx, fit, n:
                        (replace(ctx.problem.disc, refine=runs), note))
    monkeypatch.setattr(runner, "initial_fit", lambda ctx, graph, again=False:
                        seen.append(ctx.problem.disc) or "refit")
    model = Model.from_graph(mass_spring_damper())
    exp = Experiment.from_arrays(np.arange(20) * 0.05, model=model, u=np.zeros((20, 1)),
                                 y=np.zeros((20, 2)), name="rest")
    ctx = Context.on(exp, LoopSettings(params=[], search=SearchOptions(auto_substeps=True)), model,
                     lambda s: None, False)
    fit, warn = runner.resolved_fit(ctx, None, "declared")
    assert fit == "refit" and f"takes 16 substeps per sample{note} from the declared" in warn[0]
    assert ctx.problem.disc.substeps == 1 and ctx.problem.disc.refine == runs
    assert seen == [ctx.problem.disc]
    assert ctx.problem.disc.interval_substeps(19).tolist() == [1] * 3 + [16] * 6 + [1] * 10


def test_discretisation_error_is_measured_in_the_innovation_std_when_it_is_larger():
    """:func:`error_scale`: per output the larger of the measurement-noise std
    and the median one-step innovation std √S_jj of the fit's stored filter
    run. Hand-made S: output x has innovation variances 4e-6, 9e-6, 1e-4 (+
    one NaN sample) → median std 3e-3 > its noise 1e-3; output v's innovation
    std 1e-4 is below its noise 2e-3, which stays."""
    from bondgraph.diagnose.fit import error_scale

    S = np.full((4, 1, 2, 2), 0.0)
    S[:, 0, 0, 0] = [4e-6, 9e-6, 1e-4, np.nan]
    S[:, 0, 1, 1] = 1e-8
    problem = SimpleNamespace(noise_scale=lambda theta: np.array([1e-3, 2e-3]))
    fit = SimpleNamespace(theta=np.zeros(3), ukf=SimpleNamespace(S=S))
    np.testing.assert_allclose(error_scale(problem, fit), [3e-3, 2e-3], rtol=1e-12)
    # no stored run: the measurement-noise std
    no_run = SimpleNamespace(theta=np.zeros(3), ukf=SimpleNamespace())
    np.testing.assert_allclose(error_scale(problem, no_run), [1e-3, 2e-3])
