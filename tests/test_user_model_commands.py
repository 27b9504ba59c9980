"""A user's own graph, named as ``module:function`` (module in the current
directory) or ``path/to/file.py:function``, works in every command that takes a
model: equations, draw, simulate (with a noisy record of its own sensors),
estimate, sensitivity and loop; its generated code goes to the cache folder
keyed by the graph's hash, never into the package's ``generated/``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bondgraph.cli.main import main
from bondgraph.data.records import Experiment

MYMOD = '''
from bondgraph.catalog.reference import mass_spring_damper


def build():
    g = mass_spring_damper()
    g.name = "user_msd"
    return g
'''

GENERATED = Path(__file__).resolve().parents[1] / "generated"


@pytest.fixture()
def user_dir(tmp_path, monkeypatch):
    (tmp_path / "usermod.py").write_text(MYMOD)
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "other.py").write_text(MYMOD)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("BONDGRAPH_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path


def test_every_command_takes_module_function_and_file_function(user_dir, capsys):
    before = sorted(p.name for p in GENERATED.rglob("*"))
    assert main(["equations", "usermod:build"]) == 0
    out = capsys.readouterr().out
    assert "dq_spring/dt = p_mass/m" in out and "v = p_mass/m" in out
    # --model, as loop and estimate take it, names the same model; two differing
    # models, or none, are refused naming them (exit 2)
    assert main(["equations", "--model", "usermod:build"]) == 0
    assert capsys.readouterr().out == out
    assert main(["equations", "usermod:build", "--model", "x:y"]) == 2
    assert "two models given: 'usermod:build' and --model 'x:y'" in capsys.readouterr().err
    assert main(["equations"]) == 2
    assert "the model is required: bondgraph equations MODEL" in capsys.readouterr().err
    assert main(["draw", "models/other.py:build", "-o", "g.png"]) == 0
    assert (user_dir / "g.png").stat().st_size > 1000

    # a noisy record of the user's own sensors: noise_std declared, seed kept
    assert main(["simulate", "models/other.py:build", "--duration", "20", "--dt", "0.01",
                 "--input", "F=2", "--noise", "--seed", "5", "--noise-std", "x=0.004",
                 "--param", "k=40", "-o", "rec.csv"]) == 0
    rec = Experiment.load("rec.csv")
    assert rec.noise_std == {"x": 0.004, "v": 0.01}
    assert rec.meta["seed"] == 5 and rec.meta["true_parameters"]["k"] == 40.0
    # the noise is the declared one: x is the spring's displacement state
    ex = rec.columns["x"] - rec.columns["state.q_spring"]
    ev = rec.columns["v"] - rec.columns["state.p_mass"] / 2.0
    assert np.std(ex) == pytest.approx(0.004, rel=0.06)
    assert np.std(ev) == pytest.approx(0.01, rel=0.06)
    # the same seed gives the same record
    assert main(["simulate", "models/other.py:build", "--duration", "20", "--dt", "0.01",
                 "--input", "F=2", "--noise", "--seed", "5", "--noise-std", "x=0.004",
                 "--param", "k=40", "-o", "rec_again.csv"]) == 0
    assert np.array_equal(Experiment.load("rec_again.csv").columns["x"], rec.columns["x"])

    # output-error estimate through the file spec: the truth within 3 std
    assert main(["estimate", "--model", "models/other.py:build", "--data", "rec.csv",
                 "--params", "k,c", "--fit", "sim", "--out", "est", "--quiet"]) == 0
    res = json.loads((user_dir / "est" / "result.json").read_text())
    for name, truth in (("k", 40.0), ("c", 1.5)):
        value, std = res["estimates"][name], res["std"][name]
        assert abs(value - truth) < 3 * std, (name, value, std)

    # without --params: the parameters declared with a box; m, declared here
    # without one (a known value), is held at it; one line on stderr says so
    (user_dir / "known.py").write_text(MYMOD.replace(
        "    return g", "    g.params['m'].box_declared = False\n    return g"))
    capsys.readouterr()
    assert main(["estimate", "--model", "known:build", "--data", "rec.csv", "--fit", "sim",
                 "--out", "est_default", "--quiet"]) == 0
    assert ("no --params: estimating the 2 parameters declared with a box (k, c); held at their "
            "declared values (declared without a box: known): m") in capsys.readouterr().err
    res = json.loads((user_dir / "est_default" / "result.json").read_text())
    assert sorted(res["std"]) == ["c", "k"]
    for name, truth in (("k", 40.0), ("c", 1.5)):
        value, std = res["estimates"][name], res["std"][name]
        assert abs(value - truth) < 3 * std, (name, value, std)
    # sensitivity without --params analyses the same: m held (it was the
    # first candidate of the user's Camry graph's known heating value)
    assert main(["sensitivity", "--model", "known:build", "--data", "rec.csv", "--out",
                 "sens_default", "--no-plots", "--quiet"]) == 0
    assert ("no --params: analysing the 2 parameters declared with a box (k, c)"
            in capsys.readouterr().err)
    doc = json.loads((user_dir / "sens_default" / "sensitivity.json").read_text())
    assert doc["params"] == ["k", "c"]
    # the output-error information (and the sensitivity plot) weighed by the
    # record's declared noise levels, kept in the report
    assert doc["local"]["output_error"]["sigma"] == pytest.approx([0.004, 0.01])

    assert main(["sensitivity", "--model", "usermod:build", "--data", "rec.csv",
                 "--params", "k,c,m", "--out", "sens", "--no-plots"]) == 0
    out = capsys.readouterr().out
    assert "--model usermod:build" in out          # the hint names what the user typed
    assert (user_dir / "sens" / "sensitivity.json").exists()

    assert sorted(p.name for p in GENERATED.rglob("*")) == before
    # its compiled kernels (written at its first numba run) go
    # to the cache folder, keyed by the graph's code
    from bondgraph.numerics.compiled import kernel_source_path
    from bondgraph.numerics.model import Model

    from bondgraph.catalog.reference import mass_spring_damper

    g = mass_spring_damper()
    g.name = "user_msd"                          # the graph of usermod.build
    path = kernel_source_path(Model.from_graph(g))
    assert path.parent == user_dir / "cache" and path.name.startswith("user_msd_")


def test_loop_takes_its_start_values_from_a_fit_on_another_record(user_dir, capsys):
    """``loop --from``: the values of an estimate's result.json (fitted on
    another record) become the graph's defaults, the loop's start values;
    with ``--params`` the others are held at them (one line says so); noise
    levels of the file are left out; a value outside the graph's box is
    refused naming the box (exit 2, before any fit)."""
    from bondgraph.cli.loop import from_result
    from bondgraph.numerics.registry import graph_builder

    (user_dir / "est").mkdir()
    res = {"params": ["k", "c", "noise.x"], "estimates": [41.5, 1.7, 0.003], "fixed": {"m": 2.2}}
    (user_dir / "est" / "result.json").write_text(json.dumps(res))
    g = from_result(graph_builder("usermod:build")(), "est/result.json", "c")
    assert {n: g.params[n].default for n in ("m", "k", "c")} == {"m": 2.2, "k": 41.5, "c": 1.7}
    assert g.name == "user_msd" and "noise.x" not in g.params
    out = capsys.readouterr().out
    assert ("start values from est/result.json: m = 2.2, k = 41.5, c = 1.7; held at them: "
            "m, k") in out
    # without --params: what the fit estimated is re-estimated (not its fixed
    # m, nor its noise level), the rest held
    from bondgraph.cli.loop import refitted
    from bondgraph.errors import OptionError

    assert refitted(g, "est/result.json") == ["k", "c"]
    assert "re-estimating k, c (what est/result.json estimated" in capsys.readouterr().out
    (user_dir / "est" / "noise.json").write_text(json.dumps(
        {"params": ["noise.x"], "estimates": [0.003], "fixed": {"m": 2.2}}))
    with pytest.raises(OptionError, match="estimated none of the graph's parameters"):
        refitted(g, "est/noise.json")

    res["estimates"][0] = 900.0                       # k's box is [5, 500]
    (user_dir / "est" / "result.json").write_text(json.dumps(res))
    tr = np.arange(0.0, 1.0, 0.01)          # (a constant output is refused when read)
    rec = Experiment.from_arrays(tr, {"F": np.ones(100), "x": 0.01 * np.sin(tr),
                                 "v": 0.01 * np.cos(tr)}, units={"F": "N", "x": "m", "v": "m/s"},
                                 roles={"F": "input", "x": "output", "v": "output"}, name="r")
    rec.save(user_dir / "r.csv")
    assert main(["loop", "--model", "usermod:build", "--data", "r.csv", "--from",
                 "est/result.json", "--quiet"]) == 2
    assert "outside the graph's boxes: k = 900 (box [5, 500])" in capsys.readouterr().err


BARE = '''
from test_noise_default import bare_msd_graph   # the user's sensor without a noise level


def build():
    return bare_msd_graph()
'''


def _bare_record(user_dir, seconds: float):
    """``bare.py`` (:data:`BARE`) and ``r.csv``: its truth (m 2, k 50, c 1.5)
    simulated with scipy over ``seconds`` at 100 Hz, a square wave plus a
    sine pushing, the position measured with noise 0.004 m (no level
    declared). Returns t, the force, the true and the measured position."""
    from scipy.integrate import solve_ivp

    (user_dir / "bare.py").write_text(BARE)
    t = np.arange(0.0, seconds, 0.01)
    f = 5.0 * (np.sin(2 * t) + np.sign(np.sin(0.7 * t)))
    rhs = lambda s, x: [x[1] / 2.0, np.interp(s, t, f) - 50.0 * x[0] - 1.5 * x[1] / 2.0]
    q = solve_ivp(rhs, (0.0, t[-1]), [0.0, 0.0], t_eval=t, rtol=1e-10, atol=1e-12,
                  max_step=0.005).y[0]
    y = q + 0.004 * np.random.default_rng(3).standard_normal(t.size)
    Experiment.from_arrays(t, {"F": f, "x": y}, units={"F": "N", "x": "m"},
                           roles={"F": "input", "x": "output"}, name="bare",
                           meta={"columns": {"F": {"hold": "linear"}}}).save(user_dir / "r.csv")
    return t, f, q, y


def test_track_holds_a_level_for_a_sensor_that_declares_none(user_dir, capsys):
    """track on a user's sensor declared without a noise level, on a record
    that declares none: the tracker estimates no level, so the filter
    failed at sample 0 ("meas_std(theta)**2 not positive") after trying up
    to 128 substeps. It now holds the level the record's second
    differences show (one line says so), and the tracked damping ends
    within 3 std of the truth the record was simulated with (scipy,
    c = 1.5, noise 0.004 m). The inconsistency warning: none for that
    truth; for a truth the graph lacks, on a record shorter than the GLR
    window (where it could never fire), raised."""
    from scipy.integrate import solve_ivp

    t, f, q, y = _bare_record(user_dir, 20.0)
    assert main(["track", "--model", "bare:build", "--data", "r.csv", "--track", "c",
                 "--out", "trk", "--no-plots", "--method", "rk4", "--substeps", "2"]) == 0
    captured = capsys.readouterr()
    err = captured.err
    level = float(err.split("measurement-noise std held")[1].split("x = ")[1].split(" ")[0])
    # the record (20 s, two GLR windows less a sample) is cut into 20 windows for the
    # inconsistency warning, which the model the record was simulated with does not raise
    assert "the innovations are larger than the model allows" not in captured.out
    assert level == pytest.approx(0.004, rel=0.1)
    rows = np.genfromtxt(user_dir / "trk" / "track.csv", delimiter=",", skip_header=1)
    head = (user_dir / "trk" / "track.csv").read_text().splitlines()[0].split(",")
    est, sd = rows[-1, head.index("c")], rows[-1, head.index("c.std")]
    assert abs(est - 1.5) < 3 * sd, (est, sd)
    assert "sits on its box" not in captured.out
    # a box far wider than the value (0.01 .. 1e4) carries no scale: c = 1.5 is
    # not "on" it (1e-3 of the width, 10, said so for the whole record)
    (user_dir / "bare_wide.py").write_text(BARE.replace(
        "    return bare_msd_graph()",
        "    g = bare_msd_graph()\n    g.params['c'].bounds = (0.01, 1e4)\n    return g"))
    assert main(["track", "--model", "bare_wide:build", "--data", "r.csv", "--track", "c",
                 "--out", "trk_wide", "--no-plots", "--method", "rk4", "--substeps", "2"]) == 0
    assert "sits on its box" not in capsys.readouterr().out
    # a truth the graph lacks (a cubic spring, 20 % of the linear force at 0.1 m), its
    # first 9 s: within one GLR window (10 s) the warning could never fire; in 20 it does
    rhs3 = lambda s, x: [x[1] / 2.0, np.interp(s, t, f) - 50.0 * x[0] - 1000.0 * x[0] ** 3
                         - 1.5 * x[1] / 2.0]
    q3 = solve_ivp(rhs3, (0.0, t[-1]), [0.0, 0.0], t_eval=t, rtol=1e-10, atol=1e-12,
                   max_step=0.005).y[0]
    n9 = 900
    Experiment.from_arrays(t[:n9], {"F": f[:n9], "x": (q3 + y - q)[:n9]},
                           units={"F": "N", "x": "m"},
                           roles={"F": "input", "x": "output"}, name="bare3",
                           meta={"columns": {"F": {"hold": "linear"}}}).save(user_dir / "r3.csv")
    assert main(["track", "--model", "bare:build", "--data", "r3.csv", "--track", "c",
                 "--out", "trk3", "--no-plots", "--method", "rk4", "--substeps", "2"]) == 0
    assert "the innovations are larger than the model allows" in capsys.readouterr().out


@pytest.mark.parametrize("law, said", [
    ("k * np.sqrt(e)", "ufunc"),
    ("k * math.sqrt(e)", "Cannot convert expression to float"),
    ("k * e if e > 0 else 0", "truth value of Relational"),
])
def test_a_law_written_with_numpy_math_or_if_names_its_line_and_the_fix(user_dir, capsys,
                                                                          law, said):
    """numpy's, math's and Python's ``if`` errors on a sympy symbol name
    neither the law nor the cause: the message gives the user's line, the
    hint what to write."""
    (user_dir / "badlaw.py").write_text(
        "import math\nimport numpy as np\nfrom bondgraph import BondGraph\n\n"
        "def build():\n"
        "    g = BondGraph('badlaw', 'a tank')\n"
        "    k = g.param('k', 0.05, '', (0.001, 1.0))\n"
        "    n = g.zero('n')\n"
        "    g.connect(g.Sf('pump', g.input('u', 'V')), n)\n"
        "    g.connect(n, g.C('tank', 1.0))\n"
        f"    g.connect(n, g.R('orifice', flow=lambda e: {law}))\n"
        "    return g\n")
    assert main(["equations", "badlaw.py:build"]) != 0
    err = capsys.readouterr().err
    assert said in err and "at badlaw.py:11 (g.connect(n, g.R('orifice'" in err
    assert "sp.sqrt" in err and "sp.Piecewise" in err


def test_a_folder_named_generated_beside_the_model_file_does_not_shadow_the_package(tmp_path):
    """A loop's output folder holds its augmented model's code in ``generated/``
    beside ``augmented_model.py``; a user's project may have such a folder too.
    Importing a model file puts its folder first on the import path, where
    that folder (a namespace package) shadowed the toolkit's own generated
    package under an editable install: ``bondgraph sensitivity`` on a loop's
    augmented model crashed drawing its plot (``generated_dir``: 'expected
    str ... not NoneType'). Checked in a fresh interpreter, where the package
    is not imported yet."""
    import subprocess
    import sys

    out = tmp_path / "loop_out"
    (out / "generated").mkdir(parents=True)
    (out / "generated" / "other_model.py").write_text("X = 1\n")
    (out / "usermod.py").write_text(MYMOD)
    code = ("from bondgraph.core.plugins import resolve\n"
            "from bondgraph.numerics import registry\n"
            "from bondgraph.numerics.model import Model\n"
            "resolve('loop_out/usermod.py:build')\n"
            "print(registry.generated_dir())\n"
            "print(Model.load('mass_spring_damper').name)\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=tmp_path, timeout=300)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.split()
    assert Path(lines[0]) == GENERATED
    assert lines[1] == "mass_spring_damper"


STATIC = '''
from bondgraph import BondGraph


def build():
    g = BondGraph("static_user", "an imposed speed on a damper; a power meter")
    v = g.input("v", "m/s", 0.0, "imposed speed")
    c = g.param("c", 3.0, "N*s/m", (0.1, 30.0), "damping")
    p0 = g.param("p0", 1.0, "W", (-10.0, 10.0), "meter offset")
    j = g.one("j")
    drive = g.MSf("drive", v)
    g.connect(drive, j)
    g.connect(j, g.R("damper", c))
    g.sensor("P", p0 + drive.e * v, unit="W", noise_std=0.5)
    return g
'''


def test_a_graph_without_a_state_is_estimated_as_the_static_model_it_is(user_dir, capsys):
    """A user's graph whose outputs are algebraic functions of its inputs
    (an imposed speed on a damper, a power meter P = p0 + c v²; a Camry
    graph whose dyno imposes the speed) has no state: estimate, compare and
    loop failed ("sigma points need a state dimension >= 1"). It gets an
    inert state (registry.with_a_state) and the filter's likelihood is the
    static one: the estimates are the least-squares solution of
    P = p0 + c v² (numpy), their Cramér-Rao std its σ √diag((XᵀX)⁻¹) at
    the noise level's estimate (the RMS residual)."""
    (user_dir / "static_user.py").write_text(STATIC)
    rng = np.random.default_rng(4)
    t = np.arange(0.0, 40.0, 0.1)
    v = 2.0 * np.sin(0.7 * t) + rng.normal(0.0, 0.5, t.size)
    P = 0.8 + 4.0 * v**2 + rng.normal(0.0, 0.5, t.size)
    Experiment.from_arrays(t, {"v": v, "P": P}, units={"v": "m/s", "P": "W"},
                           roles={"v": "input", "P": "output"},
                           name="meter").save(user_dir / "meter.csv")
    assert main(["estimate", "--model", "static_user:build", "--data", "meter.csv",
                 "--out", "est", "--quiet", "--no-plots"]) == 0
    res = json.loads((user_dir / "est" / "result.json").read_text())
    est, std = dict(zip(res["params"], res["estimates"])), dict(zip(res["params"], res["std"]))
    X = np.column_stack([np.ones_like(v), v**2])
    (p0, c), *_ = np.linalg.lstsq(X, P, rcond=None)
    rms = np.sqrt(np.mean((P - X @ [p0, c]) ** 2))      # the noise level's MLE
    sd = rms * np.sqrt(np.diag(np.linalg.inv(X.T @ X)))
    assert est["c"] == pytest.approx(c, rel=1e-5)
    assert est["p0"] == pytest.approx(p0, rel=1e-4)
    assert est["noise.P"] == pytest.approx(rms, rel=1e-4)
    assert std["c"] == pytest.approx(sd[1], rel=1e-3)
    assert std["p0"] == pytest.approx(sd[0], rel=1e-3)
    assert main(["compare", "static_user:build", "--data", "meter.csv", "--params",
                 "est/result.json", "--out", "cmp", "--no-plots"]) == 0
    out = capsys.readouterr().out
    assert f"| meter | P | {rms:.4g} W |" in out, out
    assert main(["loop", "--model", "static_user:build", "--data", "meter.csv", "--out", "lp",
                 "--max-steps", "0", "--no-plots", "--quiet"]) == 0
    # linearised: the inert state is no dynamics (no pole at 0): D alone, dP/dv = 2 c v
    assert main(["linearize", "static_user:build", "--params", "est/result.json",
                 "--at", "v=2", "-o", "lin.npz", "--no-plot"]) == 0
    assert "poles: none (no state" in capsys.readouterr().out
    lin = np.load(user_dir / "lin.npz")
    assert lin["A"].shape == (0, 0) and lin["C"].shape == (1, 0)
    assert lin["D"][0, 0] == pytest.approx(2 * est["c"] * 2.0, rel=1e-9)
    # from Python, the graph as built: the error says what to do
    import importlib

    from bondgraph.errors import ModelError
    from bondgraph.inference.problem import make_problem
    from bondgraph.numerics.model import Model
    from bondgraph.numerics.registry import STATIC_STATE, with_a_state

    bare = importlib.import_module("static_user").build()
    with pytest.raises(ModelError, match="has no state") as err:
        make_problem(Model.from_graph(bare), Experiment.load(user_dir / "meter.csv"))
    assert "with_a_state" in err.value.hint
    assert Model.from_graph(with_a_state(bare)).states == [STATIC_STATE]


def test_global_sensitivity_of_a_sensor_without_a_noise_level(user_dir, capsys):
    """sensitivity --global on a user's sensor declared without a noise
    level (meas_std 0): the local analysis estimates the level, but the
    Sobol' sample ran the filter with the sensor's own 0 ("every evaluation
    of 'NLL' is non-finite"). It holds the analysis' level now: every
    evaluation finite on a record simulated with scipy (truth m 2, k 50,
    c 1.5, noise 0.004 m)."""
    _bare_record(user_dir, 10.0)
    assert main(["sensitivity", "--model", "bare:build", "--data", "r.csv", "--global", "16",
                 "--out", "sg", "--no-plots", "--quiet", "--method", "rk4", "--substeps",
                 "2"]) == 0, capsys.readouterr().err
    g = json.loads((user_dir / "sg" / "sensitivity.json").read_text())["global"]
    assert g["evaluations"] == 16 * (2 * 3 + 2) and g["failed"] == {"NLL": 0}
    assert all(np.isfinite(g["indices"]["NLL"]["ST"]))
