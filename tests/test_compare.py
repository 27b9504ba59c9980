"""``bondgraph compare``: a fitted model judged on a record it was not
fitted to (:func:`bondgraph.diagnose.compare.compare`).

The reference is the truth the records were simulated from: a mass on
viscous friction pushed by a multisine force plus a constant force offset,
integrated by scipy's solve_ivp at tight tolerances, the position measured
with 1 mm Gaussian noise whose draw the tests know. The errors, the NRMSE
fit and the NLL are checked against numbers computed here by hand: the RMS
of the known noise draw, of the difference of two scipy runs, and the
entropy of the noise (an exact model's one-step NLL per measurement
approaches ½ log(2πσ²) + ½).
"""

import json
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph import BondGraph
from bondgraph.data.records import Experiment
from bondgraph.diagnose.compare import compare, output_errors
from bondgraph.errors import OptionError
from bondgraph.export.params import read_noise_levels

M, FV, F0, NOISE, DT, N = 2.0, 4.0, 0.5, 1e-3, 0.01, 1000
Q0, V0 = 0.1, 0.2


def drive(offset: bool = False) -> BondGraph:
    g = BondGraph("drive_cmp" + ("_offset" if offset else ""), "a mass on viscous friction")
    f = g.input("F", "N", 0.0, "force")
    m = g.param("M", M, "kg", (0.1, 10.0), "mass")
    c = g.param("Fv", FV, "N*s/m", (0.01, 100.0), "viscous friction")
    v = g.one("v")
    g.connect(g.Se("push", f), v)
    if offset:
        g.connect(g.Se("offset", g.param("F0", F0, "N", (-5.0, 5.0), "force offset")), v)
    g.connect(v, g.I("mass", m))
    g.connect(v, g.R("friction", c))
    q = g.displacement(v, name="q", unit="m")
    g.sensor("qm", q, unit="m", noise_std=0.05, description="position")
    return g


def _force(t):
    fr = np.array([0.13, 0.41, 0.97])
    return 3.0 * np.sum(np.sin(2 * np.pi * fr * np.asarray(t)[..., None] + np.arange(3)), axis=-1)


def _truth(offset: float, x0=(Q0, V0)):
    t = np.arange(N) * DT
    sol = solve_ivp(lambda tt, z: [z[1], (_force(tt) + offset - FV * z[1]) / M], (0.0, t[-1]),
                    list(x0), t_eval=t, rtol=1e-11, atol=1e-13)
    return t, sol.y[0]


def _write(path, t, y, sidecar=None):
    with open(path, "w") as fh:
        fh.write("t [s],F [N],qm [m]\n")
        for row in zip(t.tolist(), _force(t).tolist(), y.tolist()):
            fh.write("%r,%r,%r\n" % row)
    if sidecar is not None:
        path.with_suffix(".json").write_text(json.dumps({"format": "bondgraph-experiment/1",
                                                         **sidecar}))
    return Experiment.load(path)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("compare")
    t, q = _truth(F0)
    noise = NOISE * np.random.default_rng(7).standard_normal(N)
    known = _write(d / "known.csv", t, q + noise, {"x0": {"q": Q0, "p_mass": M * V0}})
    unknown = _write(d / "unknown.csv", t, q + noise)
    return {"dir": d, "t": t, "q": q, "noise": noise, "known": known, "unknown": unknown}


def _one(graph, rec, **kw):
    kw.setdefault("noise", {"qm": NOISE})
    return compare(graph, [rec], log=lambda _m: None, **kw)[0]


def test_the_true_model_from_the_records_start_reads_the_noise_draw(data):
    c = _one(drive(offset=True), data["known"])
    assert c.start.startswith("the record's own initial state")
    rms_noise = float(np.sqrt(np.mean(data["noise"] ** 2)))
    assert c.rms[0] == pytest.approx(rms_noise, rel=2e-3)
    y = data["q"] + data["noise"]
    assert c.nrmse[0] == pytest.approx(rms_noise / np.std(y), rel=2e-3)
    fit = 100 * (1 - np.linalg.norm(data["noise"]) / np.linalg.norm(y - y.mean()))
    assert c.fit_percent[0] == pytest.approx(fit, abs=0.01)
    assert c.metric == pytest.approx(c.nrmse[0], rel=1e-12)
    assert c.bias[0] == pytest.approx(float(np.mean(data["noise"])), abs=2e-3 * NOISE)
    # one-step NLL per measurement of an exact model: the noise's entropy
    # ½ log(2πσ²) + ½ (the draw's own variance in place of σ²), plus the
    # state's own spread in each innovation's variance (the prior's, which
    # shrinks as the record goes on: 0.02 nats per measurement here)
    entropy = 0.5 * math.log(2 * math.pi * NOISE ** 2) + 0.5 * rms_noise ** 2 / NOISE ** 2
    assert 0 < c.nll / c.n_obs - entropy < 0.03
    assert c.trouble is None and c.filter_failure is None


def test_a_model_without_the_offset_reads_its_misfit_by_hand(data):
    c = _one(drive(), data["known"])
    t, q_no = _truth(0.0)
    e = data["q"] + data["noise"] - q_no
    assert c.rms[0] == pytest.approx(float(np.sqrt(np.mean(e ** 2))), rel=1e-3)
    assert c.rms[0] > 50 * NOISE
    assert c.bias[0] == pytest.approx(float(np.mean(e)), rel=1e-3)
    # the free run holds the sampled force linearly between samples (scipy's
    # truth has it continuous): 4e-5 m apart at most over the 10 s
    np.testing.assert_allclose(c.sim_y[:, 0], q_no, rtol=0, atol=0.1 * NOISE)


def test_without_a_given_start_the_smoothed_one_and_the_window(data):
    true = _one(drive(offset=True), data["unknown"])
    assert "whole record" in true.start
    assert true.rms[0] < 1.2 * NOISE
    w = _one(drive(offset=True), data["unknown"], init_samples=20)
    assert w.judged_from == 20 and "first 20 samples" in w.start
    # the window's start is the truth to within what 0.2 s of 1 mm noise
    # tells: the velocity's std σ/(dt·√(n(n²−1)/12)) = 3.9 mm/s leaves a
    # lasting position offset of about that times M/Fv = 0.5 s, 2 mm
    v_std = NOISE / (DT * math.sqrt(20 * (20 ** 2 - 1) / 12))
    assert w.rms[0] < NOISE + 1.5 * v_std * M / FV
    e = w.y[20:, 0] - w.sim_y[20:, 0]
    assert w.rms[0] == pytest.approx(float(np.sqrt(np.mean(e ** 2))), rel=1e-12)
    # a model without the offset: the whole record's start cancels part of
    # its misfit, the window's cannot
    whole, win = (_one(drive(), data["unknown"], init_samples=n) for n in (0, 20))
    assert win.rms[0] > 1.5 * whole.rms[0]


def test_noise_levels_the_record_declares_win_and_undeclared_ones_are_profiled(data, tmp_path):
    t = data["t"]
    y = data["q"] + data["noise"]
    declared = _write(tmp_path / "declared.csv", t, y,
                      {"x0": {"q": Q0, "p_mass": M * V0},
                       "columns": {"qm": {"unit": "m", "role": "output", "noise_std": 2e-3}}})
    c = _one(drive(offset=True), declared, noise={"qm": 0.5})
    assert c.noise["qm"] == (pytest.approx(2e-3), "the record's declaration")
    c = _one(drive(offset=True), data["known"], noise={})
    level, why = c.noise["qm"]
    assert why.startswith("profiled") and level == pytest.approx(NOISE, rel=0.2)


def test_output_errors_by_hand():
    y = np.array([[1.0, 2.0], [2.0, np.nan], [4.0, 1.0], [3.0, 5.0]])
    s = np.array([[1.5, 2.0], [2.0, 9.0], [3.0, 1.0], [3.0, np.inf]])
    rms, nr, fit = output_errors(y, s)
    assert rms[0] == pytest.approx(math.sqrt((0.25 + 0 + 1 + 0) / 4))
    assert nr[0] == pytest.approx(rms[0] / np.std([1, 2, 4, 3]))
    assert fit[0] == pytest.approx(100 * (1 - math.sqrt(1.25) / math.sqrt(5.0)))
    assert rms[1] == np.inf and fit[1] == -np.inf     # not finite where measured
    rms, _, _ = output_errors(y, s, first=2)
    assert rms[0] == pytest.approx(math.sqrt(0.5))
    assert np.all(output_errors(y, None)[0] == np.inf)
    # an output the record does not measure: NaN, not an error
    y[:, 1] = np.nan
    rms, nr, fit = output_errors(y, s)
    assert np.isnan([rms[1], nr[1], fit[1]]).all() and np.isfinite(rms[0])


@pytest.mark.parametrize("bad", [1, -2, 2.5, True])
def test_a_bad_window_is_refused_naming_the_option(data, bad):
    with pytest.raises(OptionError, match="--init-samples"):
        _one(drive(), data["known"], init_samples=bad)


def test_a_window_that_leaves_too_few_samples_is_refused(data):
    with pytest.raises(OptionError, match="leaves 5 samples"):
        _one(drive(), data["known"], init_samples=N - 5)


def test_noise_levels_are_read_from_an_estimate_and_a_loop_report(tmp_path):
    est = tmp_path / "result.json"
    est.write_text(json.dumps({"params": ["M", "noise.qm"], "estimates": [2.0, 0.003],
                               "settings": {"noise_levels": {"v": {"std": 0.1, "how": "held"}}}}))
    assert read_noise_levels(est) == {"v": 0.1, "qm": 0.003}
    rep = tmp_path / "report.json"
    rep.write_text(json.dumps({"final_fit": {"estimates": {"M": 2.0},
                                             "noise_estimates": {"qm": 0.004}},
                               "settings": {"noise_levels": {"v": 0.2}}}))
    assert read_noise_levels(rep) == {"v": 0.2, "qm": 0.004}


GRAPH_FILE = '''
import sys
sys.path.insert(0, {tests!r})
from test_compare import drive

def user():
    return drive()
'''


def test_the_command_writes_the_table_and_the_files(data, tmp_path, capsys):
    from bondgraph.cli.main import main
    import os
    (tmp_path / "user_drive.py").write_text(GRAPH_FILE.format(tests=os.path.dirname(__file__)))
    res = tmp_path / "result.json"
    res.write_text(json.dumps({"params": ["M", "Fv", "noise.qm"],
                               "estimates": [M, FV, NOISE], "fixed": {}}))
    out = tmp_path / "cmp"
    spec = f"{tmp_path / 'user_drive.py'}:user"
    code = main(["compare", spec, "--data", str(data["dir"] / "known.csv"),
                 "--params", str(res), "--out", str(out), "--quiet"])
    assert code == 0
    text = capsys.readouterr().out
    assert "| known | qm |" in text
    doc = json.loads((out / "compare.json").read_text())
    rec = doc["records"][0]
    assert rec["outputs"]["qm"]["noise_from"] == "the fit's estimate"
    ref = _one(drive(), data["known"])
    assert rec["metric"] == pytest.approx(ref.metric, rel=1e-9)
    head = (out / "known_compare.csv").read_text().splitlines()[0]
    assert head == "t [s],qm [m],qm.simulated [m],qm.error [m]"
    assert (out / "known_compare.png").stat().st_size > 10000
    # a parameter the graph does not have is named
    res.write_text(json.dumps({"params": ["Mass"], "estimates": [1.0]}))
    code = main(["compare", spec, "--data", str(data["dir"] / "known.csv"), "--params",
                 str(res), "--out", str(tmp_path / "cmp2"), "--quiet"])
    assert code == 2
    assert "Mass" in capsys.readouterr().err


def test_a_file_without_time_column_is_judged_at_the_given_dt(data, tmp_path, capsys):
    """The record written as a published benchmark file is (no time
    column, a logger's column names, a trailing comma), read with ``--dt``
    and ``--columns``: the same table as the record with its time column."""
    from bondgraph.cli.main import main
    import os
    (tmp_path / "user_drive.py").write_text(GRAPH_FILE.format(tests=os.path.dirname(__file__)))
    res = tmp_path / "result.json"
    res.write_text(json.dumps({"params": ["M", "Fv", "noise.qm"],
                               "estimates": [M, FV, NOISE], "fixed": {}}))
    y = data["q"] + data["noise"]
    bare = tmp_path / "bare.csv"
    with open(bare, "w") as fh:
        fh.write('"force","pos",\n')
        for row in zip(_force(data["t"]).tolist(), y.tolist()):
            fh.write("%r,%r,\n" % row)
    spec = f"{tmp_path / 'user_drive.py'}:user"
    docs = []
    for name, extra in (("unknown.csv", []), ("bare.csv", ["--dt", str(DT), "--columns",
                                                            "force=F,pos=qm"])):
        path = data["dir"] / name if name == "unknown.csv" else bare
        out = tmp_path / name.replace(".csv", "_out")
        assert main(["compare", spec, "--data", str(path), "--params", str(res), "--out",
                     str(out), "--quiet", "--no-plots", *extra]) == 0
        docs.append(json.loads((out / "compare.json").read_text())["records"][0])
    assert docs[1]["outputs"]["qm"]["rms"] == pytest.approx(docs[0]["outputs"]["qm"]["rms"],
                                                            rel=1e-12)
    assert docs[1]["nll"] == pytest.approx(docs[0]["nll"], rel=1e-12)
    # without --dt the error says how to read such a file
    assert main(["compare", spec, "--data", str(bare), "--params", str(res), "--out",
                 str(tmp_path / "no_dt"), "--quiet", "--no-plots"]) == 2
    assert "--dt SECONDS" in capsys.readouterr().err
    # the loop's closing line passes the options that read its record on to compare
    from types import SimpleNamespace

    from bondgraph.cli.loop import another_day
    line = another_day(SimpleNamespace(columns="force=F,pos=qm", dt=DT, model=spec), tmp_path)
    # no augmented_model.py (no effect accepted): the declared model at the report's estimates
    assert f"compare {spec} --data OTHER.csv --columns force=F,pos=qm --dt {DT} --params " \
        f"{tmp_path / 'report.json'}" in line
    assert "--columns" not in another_day(SimpleNamespace(columns=None, dt=None, model=spec),
                                          tmp_path)
    # with it: the report folder, before and after (a file that is not there never named)
    (tmp_path / "augmented_model.py").write_text("")
    line = another_day(SimpleNamespace(columns="force=F,pos=qm", dt=DT, model=spec), tmp_path)
    assert f"compare {tmp_path} --data OTHER.csv --columns force=F,pos=qm --dt {DT} (" in line
    (tmp_path / "augmented_model.py").unlink()
    # and so does estimate's
    assert main(["estimate", "--model", spec, "--data", str(bare), "--dt", str(DT), "--columns",
                 "force=F,pos=qm", "--params", "M,Fv", "--out", str(tmp_path / "est"),
                 "--quiet"]) == 0
    assert f"--data OTHER.csv --columns force=F,pos=qm --dt {DT} --params" in \
        capsys.readouterr().out
    # simulate reads the bare file the same way: the same time grid and outputs
    sims = []
    for path, extra in ((data["dir"] / "unknown.csv", []),
                        (bare, ["--dt", str(DT), "--columns", "force=F,pos=qm"])):
        csv = tmp_path / f"sim_{path.stem}.csv"
        assert main(["simulate", spec, "--experiment", str(path), "--params", str(res),
                     "-o", str(csv), *extra]) == 0
        sims.append(np.loadtxt(csv, delimiter=",", skiprows=1))
    assert sims[1].shape == sims[0].shape and sims[0].shape[0] == data["t"].size
    assert np.allclose(sims[1], sims[0], rtol=1e-12, atol=1e-15)
    capsys.readouterr()
    assert main(["simulate", spec, "--experiment", str(bare), "-o",
                 str(tmp_path / "x.csv")]) == 2
    assert "--dt SECONDS" in capsys.readouterr().err
    assert main(["simulate", spec, "--dt", "0", "-o", str(tmp_path / "x.csv")]) == 2
    assert "--dt 0: the sample interval must be positive" in capsys.readouterr().err
    assert main(["simulate", spec, "--columns", "force=F", "-o", str(tmp_path / "x.csv")]) == 2
    assert "--columns renames the columns of a record CSV" in capsys.readouterr().err


def test_a_step_whose_nll_is_off_takes_the_substeps_that_agree(data, monkeypatch):
    """The NLL guard of :func:`bondgraph.inference.ukf.nll_guard`, on a
    filter whose NLL is 100 + 10/s² at s substeps (the check's choice
    forced to rk4(1)): RK4(40) reads 100.00625; 1e-3 relative of it needs
    10/s² − 10/1600 <= 0.1, s >= 10, so the doubling 1, 2, 4, 8 stops at 16."""
    from types import SimpleNamespace

    from bondgraph.diagnose import compare as C
    from bondgraph.diagnose.fit import loop_problem, model_of
    from bondgraph.diagnose.settings import LoopSettings
    from bondgraph.inference.options import Discretisation, UKFOptions

    class Coarse:
        disc, ok = Discretisation(method="rk4", substeps=1, hold="linear"), True

        def line(self, where=""):
            return f"discretisation {where}: rk4(1) (forced by the test)"
    monkeypatch.setattr(C, "choose_discretisation", lambda *a, **k: Coarse())
    monkeypatch.setattr(C, "likelier_hold_at", lambda p, th, choice, **k: (choice, None))
    monkeypatch.setattr(C, "run_ukf", lambda p, th: SimpleNamespace(
        nll=np.array([100.0 + 10.0 / p.disc.substeps ** 2])))
    problem = loop_problem(model_of(drive()), data["known"], LoopSettings(
        params=[], ukf=UKFOptions(method="rk4", substeps=1, hold="linear")))
    chosen, lines = C._numerics(problem, problem.theta, {}, [NOISE])
    assert (chosen.disc.method, chosen.disc.substeps) == ("rk4", 16)
    assert "rk4(1)'s NLL 110 is 0.1 relative from rk4(40)'s 100.006" in lines[-1]
    # --substeps given: the user's step is kept
    kept, _ = C._numerics(problem, problem.theta, {"substeps": 1}, [NOISE])
    assert kept.disc.substeps == 1
    # ROS2 whose NLL no doubling brings to RK4(40)'s: the reference is taken
    Coarse.disc = Discretisation(method="ros2", substeps=1, hold="linear")
    monkeypatch.setattr(C, "run_ukf", lambda p, th: SimpleNamespace(
        nll=np.array([100.0 + (p.disc.method == "rk4")])))
    ref, lines = C._numerics(problem, problem.theta, {}, [NOISE])
    assert (ref.disc.method, ref.disc.substeps) == ("rk4", 40)
    assert "no finer step of it agrees" in lines[-1]


def test_a_noise_level_that_is_not_positive_is_refused_naming_the_output(data):
    with pytest.raises(OptionError, match="'qm' must be a finite number > 0"):
        _one(drive(), data["known"], noise={"qm": 0.0})


def test_a_record_on_a_finer_grid_counts_its_window_in_samples(data):
    """A band-limited input's record is filtered on a grid twice as fine
    (the outputs at every other point): 20 samples of it span 39 points, and
    the errors run over its samples after the 20th."""
    from bondgraph.diagnose.fit import samples_after, window_points
    from bondgraph.diagnose.runner import window_fits
    from bondgraph.diagnose.settings import FreeRunOptions, LoopSettings

    rec = data["unknown"]
    tm = 0.5 * (rec.t[1:] + rec.t[:-1])
    fine = rec.on_finer_grid({"F": _force(tm)}, linear=["F"])
    assert len(fine.t) == 2 * N - 1
    assert window_points(fine, 20) == 39 and window_points(rec, 20) == 20
    assert samples_after(fine, 20) == N - 20 == samples_after(rec, 20)
    w = _one(drive(offset=True), fine, init_samples=20)
    assert w.judged_from == 39 and w.window == 20
    e = (w.y - w.sim_y)[39:, 0]
    e = e[np.isfinite(e)]
    assert e.size == N - 20
    assert w.rms[0] == pytest.approx(float(np.sqrt(np.mean(e ** 2))), rel=1e-12)
    # the loop's check of its window counts samples too
    with pytest.raises(OptionError, match="leaves 5 of the 1000-sample"):
        window_fits(LoopSettings(params=[], validation=fine,
                                 free_run=FreeRunOptions(init_samples=N - 5)))


def test_an_output_error_fit_is_judged_from_its_result(data, tmp_path, capsys):
    """``bondgraph estimate --fit sim`` writes its own result format (names,
    estimates by name, the noise levels it reports); compare reads it: the
    offset model fitted on the record with the known start reads the noise
    on the record whose start it does not know."""
    import os

    from bondgraph.cli.main import main
    (tmp_path / "user_drive.py").write_text(GRAPH_FILE.format(tests=os.path.dirname(__file__))
                                            .replace("drive()", "drive(offset=True)"))
    spec = f"{tmp_path / 'user_drive.py'}:user"
    est = tmp_path / "est"
    assert main(["estimate", "--model", spec, "--data", str(data["dir"] / "known.csv"),
                 "--fit", "sim", "--params", "M,Fv,F0", "--out", str(est), "--quiet"]) == 0
    assert "bondgraph compare" in capsys.readouterr().out
    out = tmp_path / "cmp"
    assert main(["compare", spec, "--data", str(data["dir"] / "unknown.csv"), "--params",
                 str(est / "result.json"), "--out", str(out), "--quiet", "--no-plots"]) == 0
    rec = json.loads((out / "compare.json").read_text())["records"][0]
    assert rec["outputs"]["qm"]["noise_from"] == "the fit's estimate"
    assert rec["outputs"]["qm"]["noise_std"] == pytest.approx(NOISE, rel=0.1)
    assert rec["outputs"]["qm"]["rms"] < 1.2 * NOISE


def test_records_of_the_same_name_keep_their_own_files():
    from bondgraph.cli.compare import _stems
    assert _stems(["a/run.csv", "b/run.csv", "c/other.csv", "d/run.csv"]) == \
        ["run", "run-2", "other", "run-3"]


def test_the_nll_on_the_fitted_record_is_the_estimates_own(data, tmp_path, capsys):
    """The prior spread of the initial states comes from the graph at its
    declared values, as the fit took it: on the record it was fitted to, the
    comparison's NLL is the estimate's (to the NLL guard's 1e-3; the step is
    chosen again here)."""
    import os

    from bondgraph.cli.main import main
    (tmp_path / "user_drive.py").write_text(GRAPH_FILE.format(tests=os.path.dirname(__file__))
                                            .replace("drive()", "drive(offset=True)"))
    spec = f"{tmp_path / 'user_drive.py'}:user"
    est = tmp_path / "est"
    assert main(["estimate", "--model", spec, "--data", str(data["dir"] / "unknown.csv"),
                 "--params", "M,Fv,F0", "--iterations", "20", "--out", str(est),
                 "--quiet", "--no-plots"]) == 0
    res = json.loads((est / "result.json").read_text())
    said = capsys.readouterr().out
    assert "free run at the estimate on unknown: RMS error qm" in said
    assert "WARNING: the estimate does not simulate" not in said
    out = tmp_path / "cmp"
    assert main(["compare", spec, "--data", str(data["dir"] / "unknown.csv"), "--params",
                 str(est / "result.json"), "--out", str(out), "--quiet", "--no-plots"]) == 0
    rec = json.loads((out / "compare.json").read_text())["records"][0]
    assert rec["nll"] == pytest.approx(res["nll"], rel=1e-3)


def test_a_loop_folder_is_judged_before_and_after(data, tmp_path, capsys):
    """``bondgraph compare LOOP_FOLDER --data ...``: the declared fit and the
    final model on each record; on the record the loop judged by, the two
    figures are the loop's own before and after."""
    import os

    from bondgraph.cli.main import main
    (tmp_path / "user_drive.py").write_text(GRAPH_FILE.format(tests=os.path.dirname(__file__)))
    spec = f"{tmp_path / 'user_drive.py'}:user"
    loop = tmp_path / "loop"
    assert main(["loop", "--model", spec, "--data", str(data["dir"] / "known.csv"),
                 "--validate", str(data["dir"] / "unknown.csv"), "--params", "M,Fv",
                 "--max-steps", "1", "--no-structural", "--out", str(loop), "--quiet",
                 "--no-plots"]) == 0
    report = json.loads((loop / "report.json").read_text())
    assert report["steps"], "the loop found the offset"
    capsys.readouterr()
    out = tmp_path / "cmp"
    assert main(["compare", str(loop), "--data", str(data["dir"] / "unknown.csv"),
                 "--out", str(out), "--quiet"]) == 0
    assert "before -> after" in capsys.readouterr().out
    doc = json.loads((out / "compare.json").read_text())
    before, after = doc["before"][0], doc["after"][0]
    assert before["metric"] == pytest.approx(report["validation_error_before"], rel=1e-3)
    assert after["metric"] == pytest.approx(report["validation_error_after"], rel=1e-3)
    assert after["outputs"]["qm"]["rms"] < 1.2 * NOISE < before["outputs"]["qm"]["rms"]
    head = (out / "unknown_compare.csv").read_text().splitlines()[0]
    assert head.endswith("qm.simulated_before [m]")
    # a loop folder carries its own parameters
    assert main(["compare", str(loop), "--data", str(data["dir"] / "unknown.csv"),
                 "--params", str(loop / "report.json"), "--out", str(tmp_path / "c2")]) == 2
    # the final model as the loop's closing line names it reads the loop's figure too:
    # its initial states' priors from the declared graph's scales (cli.compare.scales_graph)
    assert main(["compare", f"{loop / 'augmented_model.py'}:build", "--data",
                 str(data["dir"] / "unknown.csv"), "--params", str(loop / "report.json"),
                 "--out", str(tmp_path / "c3"), "--quiet"]) == 0
    alone = json.loads((tmp_path / "c3" / "compare.json").read_text())["records"][0]
    assert alone["metric"] == pytest.approx(report["validation_error_after"], rel=1e-3)
    from bondgraph.cli.compare import scales_graph
    g = scales_graph(f"{loop / 'augmented_model.py'}:build")
    final = {s["effect"] for s in report["steps"]}
    assert g.name == drive().name and not any(e in n for n in g.params for e in final)
    assert g.params["M"].default == drive().params["M"].default != \
        report["final_fit"]["estimates"]["M"]
    assert scales_graph(spec).params["M"].default == drive().params["M"].default


def test_a_run_that_does_not_simulate_is_named_with_its_model(capsys):
    from types import SimpleNamespace

    from bondgraph.cli.compare import _warnings
    bad = SimpleNamespace(record="u2", trouble="the free run of z is not finite",
                          filter_failure=None)
    good = SimpleNamespace(record="u2", trouble=None, filter_failure="sample 3: P not PD")
    _warnings([("before", bad), ("after", good)])
    out = capsys.readouterr().out.splitlines()
    assert out == ["WARNING: u2 (before): the free run of z is not finite",
                   "WARNING: u2 (after): the filter fails (sample 3: P not PD): NLL inf"]


def test_an_estimate_that_does_not_simulate_its_record_says_so(data, tmp_path, capsys):
    """A likelihood fit that the noise levels carry: the friction held 50
    times too high, the mass barely moves, NRMSE near 1; ``estimate`` ends
    with a warning that names the loop and ``--fit sim``."""
    import os

    from bondgraph.cli.main import main
    (tmp_path / "user_drive.py").write_text(GRAPH_FILE.format(tests=os.path.dirname(__file__)))
    assert main(["estimate", "--model", f"{tmp_path / 'user_drive.py'}:user", "--data",
                 str(data["dir"] / "known.csv"), "--params", "M", "--fixed", "Fv=100",
                 "--iterations", "10", "--out", str(tmp_path / "est"), "--quiet",
                 "--no-plots"]) == 0
    said = capsys.readouterr().out
    assert "WARNING: the estimate does not simulate known (NRMSE" in said
    assert "`--fit sim` fits the free run" in said


def test_initial_states_a_fit_estimated_start_the_comparison_on_its_record(data, tmp_path,
                                                                          capsys, monkeypatch):
    """A fit with ``--estimate-x0 all``: on the record it was fitted to, the
    comparison starts where the fit did (the line says so) and its NLL is
    the estimate's (before, the filter started from the prior and the NLL
    differed: a user's hydraulic record under way read 124550 against the
    fit's 122407); on a copy of that record under another name, or under
    the same relative name in another folder, the prior's start stays."""
    import os
    import shutil

    from bondgraph.cli.main import main
    (tmp_path / "user_drive.py").write_text(GRAPH_FILE.format(tests=os.path.dirname(__file__))
                                            .replace("drive()", "drive(offset=True)"))
    spec = f"{tmp_path / 'user_drive.py'}:user"
    est = tmp_path / "est"
    monkeypatch.chdir(data["dir"])          # the fit names its record relatively
    assert main(["estimate", "--model", spec, "--data", "unknown.csv", "--params", "M,Fv,F0",
                 "--estimate-x0", "all", "--iterations", "20", "--out", str(est),
                 "--quiet", "--no-plots"]) == 0
    res = json.loads((est / "result.json").read_text())
    assert any(n.startswith("x0.") for n in res["params"])
    capsys.readouterr()
    other = tmp_path / "again.csv"
    shutil.copyfile(data["dir"] / "unknown.csv", other)
    out = tmp_path / "cmp"
    assert main(["compare", spec, "--data", "unknown.csv", "--data", str(other), "--params",
                 str(est / "result.json"), "--out", str(out), "--no-plots"]) == 0
    said = capsys.readouterr().out
    assert "unknown: initial states as the fit estimated them on this record" in said
    assert "again: initial states as the fit estimated them" not in said
    fitted, copied = json.loads((out / "compare.json").read_text())["records"]
    assert fitted["nll"] == pytest.approx(res["nll"], rel=1e-3)
    assert copied["nll"] != pytest.approx(res["nll"], rel=1e-3)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    shutil.copyfile(data["dir"] / "unknown.csv", elsewhere / "unknown.csv")
    monkeypatch.chdir(elsewhere)
    assert main(["compare", spec, "--data", "unknown.csv", "--params",
                 str(est / "result.json"), "--out", str(tmp_path / "cmp2"), "--no-plots"]) == 0
    assert "initial states as the fit estimated them" not in capsys.readouterr().out
