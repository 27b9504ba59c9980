"""The free run on the record that judges may start from its first N
samples only (``FreeRunOptions.init_samples``, ``bondgraph loop
--init-samples N``): the benchmark protocol of nonlinearbenchmark.org
(EMPS: the first 20 test samples set the state, the error runs over the
rest), so that the judging record's later samples cannot move the start to
cancel a model's misfit.

The reference is the truth the records were simulated from: a mass on
viscous friction pushed by a multisine force plus a constant force offset
that the user's graph lacks (the EMPS drive's missing offset), integrated
by scipy's solve_ivp at tight tolerances, position measured with 1 mm
noise, the judging record's true start (q, v) = (0.1 m, 0.2 m/s).
"""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph import BondGraph
from bondgraph.data.records import Experiment
from bondgraph.diagnose import fit as F
from bondgraph.diagnose.settings import FreeRunOptions, LoopSettings
from bondgraph.errors import OptionError
from bondgraph.inference.options import UKFOptions
from bondgraph.numerics.model import Model

M, FV, F0, NOISE, DT, N = 2.0, 4.0, 0.5, 1e-3, 0.01, 1000
Q0, V0 = 0.1, 0.2


def drive(offset: bool = False) -> BondGraph:
    g = BondGraph("drive_user" + ("_offset" if offset else ""), "a mass on viscous friction")
    f = g.input("F", "N", 0.0, "force")
    m = g.param("M", 1.0, "kg", (0.1, 10.0), "mass")
    c = g.param("Fv", 1.0, "N*s/m", (0.01, 100.0), "viscous friction")
    v = g.one("v")
    g.connect(g.Se("push", f), v)
    if offset:
        g.connect(g.Se("offset", g.param("F0", 0.0, "N", (-5.0, 5.0), "force offset")), v)
    g.connect(v, g.I("mass", m))
    g.connect(v, g.R("friction", c))
    q = g.displacement(v, name="q", unit="m")
    g.sensor("qm", q, unit="m", noise_std=NOISE, description="position")
    return g


def _force(t):
    fr = np.array([0.13, 0.41, 0.97])
    return 3.0 * np.sum(np.sin(2 * np.pi * fr * np.asarray(t)[..., None] + np.arange(3)), axis=-1)


def _record(path, seed, x0):
    t = np.arange(N) * DT
    sol = solve_ivp(lambda tt, z: [z[1], (_force(tt) + F0 - FV * z[1]) / M], (0.0, t[-1]),
                    list(x0), t_eval=t, rtol=1e-10, atol=1e-12)
    y = sol.y[0] + NOISE * np.random.default_rng(seed).standard_normal(N)
    with open(path, "w") as fh:
        fh.write("t [s],F [N],qm [m]\n")
        for row in zip(t.tolist(), _force(t).tolist(), y.tolist()):
            fh.write("%r,%r,%r\n" % row)
    return Experiment.load(path)


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    d = tmp_path_factory.mktemp("init_window")
    return _record(d / "est.csv", 1, (0.0, 0.0)), _record(d / "val.csv", 2, (Q0, V0))


def _context(records, graph, n_init):
    est, val = records
    s = LoopSettings(params=["M", "Fv"], validation=val,
                     free_run=FreeRunOptions(init_samples=n_init),
                     ukf=UKFOptions(method="rk4", substeps=2, hold="linear"))
    model = Model.from_graph(graph)
    ctx = F.Context.on(est, s, model, log=lambda _m: None, progress=False)
    return ctx, model, F.validation_problem(ctx, ctx.problem)


def test_the_window_start_is_the_truth_where_the_whole_record_start_cancels_the_misfit(records):
    ctx, model, vp = _context(records, drive(), 20)
    theta = model.theta({"M": M, "Fv": FV})
    i_p, i_q = model.states.index("p_mass"), model.states.index("q")
    xw = F.window_start(ctx, vp, theta, 20)
    # the first 20 samples (0.2 s) give the true start: the missing offset
    # moves the position by F0/M·t²/2 = 5 mm at most over the window
    assert xw[i_q] == pytest.approx(Q0, abs=3 * NOISE)
    assert xw[i_p] == pytest.approx(M * V0, abs=0.15 * M * V0)
    # the whole judging record moves it half a metre to cancel the drift the
    # offset leaves (0.125 m/s over 10 s): the start absorbs the misfit
    xs, why = F._smoothed_start(vp, theta, vp.x0)
    assert why is None and abs(xs[i_q] - Q0) > 100 * NOISE
    # and the free run the loop judges by starts at the window's start
    sim = F.free_run(ctx, vp, theta, own=False)
    ref = F._free_run_from(ctx, vp, theta, F.sim_inputs(ctx.settings, vp.disc.hold,
                                                         vp.arrays[1]), xw)
    np.testing.assert_allclose(sim, ref, rtol=0, atol=1e-12)
    whole = F.free_run(_context(records, drive(), 0)[0], vp, theta, own=False)
    rms = lambda s: float(np.sqrt(np.mean((s[:, 0] - vp.y[:, 0]) ** 2)))
    assert rms(sim) > 1.5 * rms(whole)          # the misfit shows instead of being cancelled


def test_the_true_model_from_the_window_start_reads_the_noise(records):
    ctx, model, vp = _context(records, drive(offset=True), 20)
    theta = model.theta({"M": M, "Fv": FV, "F0": F0})
    sim = F.free_run(ctx, vp, theta, own=False)
    err = sim[:, 0] - vp.y[:, 0]
    assert np.sqrt(np.mean(err ** 2)) < 2 * NOISE


@pytest.mark.parametrize("bad", [1, -3, 2.5, True])
def test_a_window_of_fewer_than_two_samples_is_refused(bad):
    with pytest.raises(OptionError, match="init_samples"):
        FreeRunOptions(init_samples=bad)


def test_the_command_line_names_its_option(tmp_path, capsys):
    from bondgraph.cli.main import main
    code = main(["loop", "--init-samples", "1", "--max-steps", "0"])
    assert code == 2
    assert "--init-samples must be 0" in capsys.readouterr().err


def test_the_held_out_error_runs_after_the_window(records):
    """``validation_run``'s metric leaves the window's samples out: the
    NRMSE over the rest, by hand, from the free run it returns."""
    ctx, model, vp = _context(records, drive(), 20)
    theta = model.theta({"M": M, "Fv": FV})
    metric, errors, _trouble, sim = F.validation_run(ctx, ctx.problem, theta)
    y = vp.y[:, 0]
    e = y[20:] - sim[20:, 0]
    assert metric == pytest.approx(np.sqrt(np.mean(e ** 2)) / np.std(y[20:]), rel=1e-12)
    assert np.all(np.isnan(errors[:20])) and np.all(np.isfinite(errors[20:]))


def test_the_report_says_how_the_validation_record_was_judged():
    from bondgraph.diagnose.result import LoopResult
    res = LoopResult("m", None, "est", "NRMSE", "aic",
                     {"validation": "val", "free_run": {"method": "LSODA", "init_samples": 20}})
    assert res.records() == ("Record: `est`. Validation record: `val`, not fitted. Its free "
                             "runs start from its first 20 samples only and are judged on the "
                             "samples after them.")


def test_a_held_out_part_is_not_continued_under_the_window_rule(records):
    """The held-out last part continues the fitted part (``meta["follows"]``),
    but with ``init_samples`` its start comes from its own first samples
    only, as a separate record's: the run ``validation_run`` returns is the
    one from :func:`window_start`, not from the fitted part's last state."""
    from bondgraph.diagnose.runner import held_out
    est, _ = records
    s = LoopSettings(params=["M", "Fv"], holdout=0.25, free_run=FreeRunOptions(init_samples=20),
                     ukf=UKFOptions(method="rk4", substeps=2, hold="linear"))
    fitted, s = held_out(est, s)
    assert s.validation.meta["follows"] == fitted.name
    model = Model.from_graph(drive())
    ctx = F.Context.on(fitted, s, model, log=lambda _m: None, progress=False)
    theta = model.theta({"M": M, "Fv": FV})
    res = F.run_ukf(ctx.problem, theta[None, :], store=True)
    vp = F.validation_problem(ctx, ctx.problem)
    _m, _e, _t, sim = F.validation_run(ctx, ctx.problem, theta, filtered=res)
    held = F.sim_inputs(ctx.settings, vp.disc.hold, vp.arrays[1])
    ref = F._free_run_from(ctx, vp, theta, held, F.window_start(ctx, vp, theta, 20))
    np.testing.assert_allclose(sim, ref, rtol=0, atol=1e-12)
    xc = F.continued_state(ctx, ctx.problem, vp, theta, res)
    cont = F._free_run_from(ctx, vp, theta, held, xc)
    assert np.max(np.abs(cont - ref)) > 10 * NOISE     # the continued run is another run


def test_a_window_needs_a_record_that_judges_and_samples_after_it(records):
    from bondgraph.diagnose.runner import MIN_HELD_OUT, held_out
    est, val = records
    base = dict(params=["M", "Fv"], ukf=UKFOptions(method="rk4", substeps=2, hold="linear"))
    with pytest.raises(OptionError, match=r"--init-samples\) 20 .* holdout 0 and no validation"):
        held_out(est, LoopSettings(**base, free_run=FreeRunOptions(init_samples=20)))
    n = len(val.t) - MIN_HELD_OUT + 1
    with pytest.raises(OptionError, match=rf"leaves {MIN_HELD_OUT - 1} of the {len(val.t)}-sample"):
        held_out(est, LoopSettings(**base, validation=val,
                                   free_run=FreeRunOptions(init_samples=n)))
    # the held-out quarter of the record (250 samples) is checked the same way
    with pytest.raises(OptionError, match="leaves 0 of the 250-sample validation record"):
        held_out(est, LoopSettings(**base, holdout=0.25, free_run=FreeRunOptions(init_samples=300)))
    ok = LoopSettings(**base, validation=val, free_run=FreeRunOptions(init_samples=20))
    assert held_out(est, ok) == (est, ok)
    assert FreeRunOptions(init_samples=np.int64(20)).init_samples == 20


def test_unknown_parameters_are_refused_with_their_names_quoted(records):
    """run_loop and the command line refuse them alike (runner.require_params),
    the command line before the numerics are chosen."""
    from bondgraph.diagnose.runner import require_params, run_loop
    from bondgraph.errors import ModelError
    with pytest.raises(ModelError, match=r"has no parameter\(s\) 'Mx', 'k' \(known: M, Fv\)"):
        require_params(drive(), ["M", "Mx", "k"])
    est, _ = records
    with pytest.raises(ModelError, match=r"no parameter\(s\) 'Mx'"):
        run_loop(drive(), est, LoopSettings(params=["M", "Mx"]), log=lambda _m: None)
