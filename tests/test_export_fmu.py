"""FMU export (issue 31): the generated C against the numpy modules, fmpy's
validation of exported FMUs, and fmpy's simulations of them (Model
Exchange with its CVode, Co-Simulation with the FMU's own Dormand-Prince
stepping) against ``bondgraph.numerics.simulate`` on the same sampled
inputs (a zero-order hold between samples, as fmpy applies inputs at
communication points and co-simulation holds them over a step)."""

from __future__ import annotations

import ctypes
import shutil
import subprocess
import zipfile

import numpy as np
import pytest

from bondgraph.core.equations import derive
from bondgraph.data.experiments import get_experiment
from bondgraph.errors import ExportError
from bondgraph.export.fmu import FMUOptions, export_fmu, find_compiler
from bondgraph.export.linearize import linear_model
from bondgraph.numerics import registry
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate

fmpy = pytest.importorskip("fmpy", reason="fmpy is not installed (pip install -e '.[dev]')")
from fmpy import simulate_fmu  # noqa: E402
from fmpy.validation import validate_fmu  # noqa: E402

if not any(shutil.which(c) for c in ("cc", "gcc", "clang")):  # pragma: no cover
    pytest.skip("no C compiler on this machine: FMUs are compiled at export",
                allow_module_level=True)

#: relative agreement asked by issue 31 (max error over a trajectory / the
#: output's largest magnitude)
REL = 1e-6

_WRAP = """
#include "{model}.c"
void f(const double *x, const double *u, const double *p, double *o) {{ bg_f(x, u, p, o); }}
void h(const double *x, const double *u, const double *p, double *o) {{ bg_h(x, u, p, o); }}
void dfdx(const double *x, const double *u, const double *p, double *o) {{ bg_dfdx(x, u, p, o); }}
void dfdu(const double *x, const double *u, const double *p, double *o) {{ bg_dfdu(x, u, p, o); }}
void dhdx(const double *x, const double *u, const double *p, double *o) {{ bg_dhdx(x, u, p, o); }}
void dhdu(const double *x, const double *u, const double *p, double *o) {{ bg_dhdu(x, u, p, o); }}
"""


def _c_library(name, tmp_path):
    """The committed generated/c/<name>.c compiled with -Wall -Werror into a
    shared library (ctypes)."""
    src = tmp_path / "wrap.c"
    src.write_text(_WRAP.format(model=name))
    lib = tmp_path / f"{name}.so"
    r = subprocess.run([find_compiler(), "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror",
                        "-shared", "-fPIC", "-I", str(registry.c_path(name).parent), str(src),
                        "-o", str(lib), "-lm"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return ctypes.CDLL(str(lib))


@pytest.mark.parametrize("name", ["mass_spring_damper", "emps", "vehicle_coastdown",
                                  "toy_cvt"])
def test_generated_c_matches_the_numpy_module(name, tmp_path):
    """f, h, df/dx, dh/dx of the committed C equal the committed numpy
    module's, and df/du, dh/du the in-memory numpy ones, at random points."""
    lib = _c_library(name, tmp_path)
    m = Model.load(name)
    lin = linear_model(name)
    rng = np.random.default_rng(0)
    dp = ctypes.POINTER(ctypes.c_double)
    for _ in range(5):
        x = m.x0 + rng.normal(size=m.n_x) * (1 + np.abs(m.x0))
        u = m.u0 + rng.uniform(0.5, 1.0, size=m.n_u)
        th = m.theta0 * rng.uniform(0.8, 1.2, size=m.n_theta)
        args = [np.ascontiguousarray(a, dtype=float) for a in (x, u, th)]
        for fn, ref, shape in (("f", m.f, (m.n_x,)), ("h", m.h, (m.n_y,)),
                               ("dfdx", m.dfdx, (m.n_x, m.n_x)),
                               ("dhdx", m.dhdx, (m.n_y, m.n_x)),
                               ("dfdu", lin.dfdu, (m.n_x, m.n_u)),
                               ("dhdu", lin.dhdu, (m.n_y, m.n_u))):
            out = np.zeros(shape)
            getattr(lib, fn)(*[a.ctypes.data_as(dp) for a in args], out.ctypes.data_as(dp))
            want = ref(x, u, th)
            np.testing.assert_allclose(out, want, rtol=1e-12, atol=1e-12 * np.max(
                np.abs(want), initial=1.0), err_msg=f"{name}.{fn}")


def _case(name):
    """(model, t, U, x0, params) of a registered experiment, as `bondgraph
    simulate -e` uses it (inputs, x0 and parameters the model has), or of a
    step experiment for the reference graphs without one."""
    steps = {"rlc_circuit": ("V", 0.01, 5.0, 0.2, 1e-3),
             "hydraulic_tanks": ("Q", 10.0, 1e-4, 200.0, 0.5)}
    if name in steps:
        inp, t0, value, duration, dt = steps[name]
        m = Model.load(name)
        t = np.arange(int(round(duration / dt)) + 1) * dt
        return m, t, np.where(t >= t0, value, 0.0)[:, None], {}, {}
    spec = get_experiment(name)
    m = Model.load(spec.model)
    t = np.arange(int(round(spec.duration / spec.dt)) + 1) * spec.dt
    U = np.column_stack([np.broadcast_to(spec.inputs[k](t), t.shape) if k in spec.inputs
                         else np.full(t.shape, m.u0[j]) for j, k in enumerate(m.inputs)])
    x0 = {k: v for k, v in spec.x0.items() if k in m.states}
    params = {k: v for k, v in spec.params.items() if k in m.params}
    return m, t, U, x0, params


def _rel_error(y, ref):
    return np.max(np.abs(y - ref), axis=0) / np.maximum(np.max(np.abs(ref), axis=0), 1e-300)


def _held_signal(m, t, U):
    """fmpy's input table of the sampled inputs held between samples: where
    an input changes at t_k, a row with the old value at t_k comes first
    (fmpy's mark of a discontinuity: the integrator stops and restarts
    there, as simulate's zero-order hold does)."""
    rows = []
    for k in range(t.size):
        if k and np.any(U[k] != U[k - 1]):
            rows.append((t[k], *U[k - 1]))
        rows.append((t[k], *U[k]))
    return np.array(rows, dtype=[("time", float)] + [(n, float) for n in m.inputs])


def _at_samples(res, t):
    """fmpy's result rows at the sample times ``t``: at an input event it
    records the time twice; the row after the event is the sample."""
    last = {}
    for i, tk in enumerate(res["time"]):
        last[round(float(tk) / t[-1], 9)] = i
    rows = [last[round(float(tk) / t[-1], 9)] for tk in t]
    out = res[rows]
    np.testing.assert_allclose(out["time"], t, rtol=0, atol=1e-9 * t[-1])
    return out


def _check_fmu(fmu, m, t, U, x0, theta):
    """fmpy ME (CVode) and CS against simulate with a zero-order hold."""
    ref = simulate(m, t, u=U, x0=m.state(x0), theta=theta, method="LSODA", rtol=1e-12,
                   atol=1e-14, hold="zoh")
    sig = _held_signal(m, t, U)
    errors = {}
    for kind, tol in (("ModelExchange", 1e-12), ("CoSimulation", 1e-11)):
        res = simulate_fmu(str(fmu), fmi_type=kind, stop_time=t[-1], output_interval=t[1] - t[0],
                           relative_tolerance=tol, input=sig if m.inputs else None,
                           start_values=dict(x0), output=list(m.outputs))
        res = _at_samples(res, t)
        y = np.column_stack([res[o] for o in m.outputs])
        errors[kind] = _rel_error(y, ref.y)
    return errors


@pytest.mark.parametrize("name", ["msd_force_step", "rlc_circuit", "hydraulic_tanks",
                                  "dc_motor_voltage_step", "vehicle_coastdown"])
def test_fmu_validates_and_matches_simulate(name, tmp_path):
    """fmpy's validation passes; ME and CS outputs match simulate within 1e-6
    relative of each output's largest magnitude."""
    m, t, U, x0, params = _case(name)
    fmu = export_fmu(m.name, tmp_path / f"{m.name}.fmu", params=params)
    assert validate_fmu(str(fmu)) == []
    md = fmpy.read_model_description(str(fmu))
    starts = {v.name: float(v.start) for v in md.modelVariables if v.causality == "parameter"}
    assert starts == pytest.approx({**dict(zip(m.params, m.theta0)), **params}, rel=1e-15)
    errors = _check_fmu(fmu, m, t, U, x0, m.theta(params))
    for kind, err in errors.items():
        assert np.all(err < REL), f"{name} {kind}: relative errors {dict(zip(m.outputs, err))}"


def test_fmu_units_and_causalities(tmp_path):
    """modelDescription: every variable named with its unit (defined with its
    SI base units), inputs with causality input, outputs output."""
    fmu = export_fmu("dc_motor_compliant", tmp_path / "m.fmu", params={"R_a": 1.25})
    md = fmpy.read_model_description(str(fmu))
    by = {v.name: v for v in md.modelVariables}
    ss = derive(registry.build("dc_motor_compliant"))
    for p in ss.params:
        assert by[p.name].causality == "parameter" and by[p.name].unit == (p.unit or None)
    assert float(by["R_a"].start) == 1.25
    assert [v.name for v in md.modelVariables if v.causality == "input"] == ["V", "T_L"]
    assert [v.name for v in md.modelVariables if v.causality == "output"] == \
        [o.name for o in ss.outputs]
    units = {u.name: u for u in md.unitDefinitions}
    assert units["N*m"].baseUnit.kg == 1 and units["N*m"].baseUnit.m == 2 \
        and units["N*m"].baseUnit.s == -2
    assert [d.variable.name for d in md.derivatives] == [f"der({s.name})" for s in ss.states]
    with zipfile.ZipFile(fmu) as zf:
        names = zf.namelist()
    assert "binaries/linux64/dc_motor_compliant.so" in names and "sources/model.c" in names


def test_missing_compiler_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("CC", raising=False)
    with pytest.raises(ExportError, match="no C compiler found"):
        export_fmu("rlc_circuit", tmp_path / "x.fmu")
    assert not (tmp_path / "x.fmu").exists()


def test_unknown_parameter_and_bad_options_are_named(tmp_path):
    with pytest.raises(ExportError, match="no parameter.*'?bogus"):
        export_fmu("rlc_circuit", tmp_path / "x.fmu", params={"bogus": 1.0})
    from bondgraph.errors import OptionError
    with pytest.raises(OptionError, match="tolerance"):
        FMUOptions(tolerance=0.0)


def test_cli_export_with_estimate_result(tmp_path, capsys):
    """`bondgraph export MODEL --fmu OUT --params result.json`: the estimates
    are the parameters' start values (and compiled defaults)."""
    import json

    from bondgraph.cli.main import main

    (tmp_path / "result.json").write_text(json.dumps(
        {"model": "rlc_circuit", "params": ["R", "L"], "estimates": [12.5, 0.2],
         "fixed": {"C": 2e-3}}))
    out = tmp_path / "rlc.fmu"
    assert main(["export", "rlc_circuit", "--fmu", str(out), "--params",
                 str(tmp_path / "result.json")]) == 0
    assert "3 parameters" in capsys.readouterr().out
    md = fmpy.read_model_description(str(out))
    starts = {v.name: float(v.start) for v in md.modelVariables if v.causality == "parameter"}
    assert starts == {"R": 12.5, "L": 0.2, "C": 2e-3}
    # the compiled defaults are the estimates too: fmpy sets no start values here
    res = simulate_fmu(str(out), stop_time=0.05, output_interval=1e-3, relative_tolerance=1e-12,
                       start_values={"q_capacitor": 1e-3}, output=["v_C"])
    m = Model.load("rlc_circuit")
    t = np.arange(51) * 1e-3
    ref = simulate(m, t, x0={"q_capacitor": 1e-3}, theta=m.theta(R=12.5, L=0.2, C=2e-3),
                   method="LSODA", rtol=1e-12, atol=1e-14)
    assert _rel_error(res["v_C"][:, None], ref.y[:, [1]])[0] < REL


def test_cli_export_without_fmu_writes_the_graphs_name(tmp_path, capsys, monkeypatch):
    """Without --fmu the FMU is MODEL.fmu (the graph's name) in the current
    folder, as linearize writes MODEL_linear.npz; its model description
    names the model."""
    from bondgraph.cli.main import main

    monkeypatch.chdir(tmp_path)
    assert main(["export", "rlc_circuit"]) == 0
    assert "wrote rlc_circuit.fmu" in capsys.readouterr().out
    assert fmpy.read_model_description("rlc_circuit.fmu").modelName == "rlc_circuit"
    # --fmu alone, as its help reads (a user's `export MODEL --params R --fmu`): the same
    (tmp_path / "rlc_circuit.fmu").unlink()
    assert main(["export", "rlc_circuit", "--fmu"]) == 0
    assert "wrote rlc_circuit.fmu" in capsys.readouterr().out


def test_loop_augmented_model_exports_and_matches(tmp_path):
    """The loop's augmented model of the default case (vehicle_coastdown_noaero
    + quadratic_drag @ body.v, as `bondgraph loop` accepts it), written by the
    loop's own writer with its report.json: exported as
    augmented_model.py:build with --params report.json, it validates and
    matches simulate on the coast-down experiment's inputs and initial state."""
    import json
    from types import SimpleNamespace

    from bondgraph.cli.main import main
    from bondgraph.diagnose.effects import Target
    from bondgraph.export.params import model_graph, read_params
    from bondgraph.report.loop_report import augmented_source

    est = {"f_r": 0.021784812962859133, "r_dyn": 0.30501914921360745,
           "theta_off": 0.0085916672988911, "q_grade": 1e-05,
           "quadratic_drag.body.v.c": 1.1448209084778165}
    result = SimpleNamespace(
        model="vehicle_coastdown_noaero", source="vehicle_graphs.cases:vehicle_aero_declared",
        applied=[SimpleNamespace(effect="quadratic_drag", target=Target("junction", "body.v"),
                                 values={"c": 1.1448209084778165, "eps": 0.13928536607548764},
                                 spec=None)],
        final=SimpleNamespace(estimates=est))
    (tmp_path / "augmented_model.py").write_text(augmented_source(result))
    (tmp_path / "report.json").write_text(json.dumps({"final_fit": {"estimates": est}}))
    spec = f"{tmp_path / 'augmented_model.py'}:build"
    fmu = tmp_path / "aug.fmu"
    assert main(["export", spec, "--fmu", str(fmu), "--params",
                 str(tmp_path / "report.json")]) == 0
    assert validate_fmu(str(fmu)) == []
    params = read_params(tmp_path / "report.json")
    m = Model.from_graph(model_graph(spec, params))
    assert "quadratic_drag.body.v.c" in m.params
    exp = get_experiment("vehicle_coastdown")
    t = np.arange(int(round(exp.duration / exp.dt)) + 1) * exp.dt
    U = np.zeros((t.size, m.n_u)) + m.u0
    x0 = {k: v for k, v in exp.x0.items() if k in m.states}
    assert len(x0) >= m.n_x - 1      # the grade state starts at its X0, as in simulate -e
    errors = _check_fmu(fmu, m, t, U, x0, m.theta0)
    for kind, err in errors.items():
        assert np.all(err < REL), f"augmented {kind}: relative errors {dict(zip(m.outputs, err))}"


def test_a_cosimulation_stopped_by_a_jump_names_the_law(tmp_path):
    """Coulomb friction written Fc·sign(v): a mass that sticks makes the
    co-simulation's adaptive step give up; fmi2DoStep's error names the law
    (config.h's BG_STEP_HINT) instead of "too many internal steps" alone. A
    model without jumps gets no hint."""
    import zipfile

    from tests.test_domains import coulomb_msd

    path = export_fmu(coulomb_msd(), tmp_path / "coulomb.fmu")
    with zipfile.ZipFile(path) as zf:
        assert "sign(p_mass/m) jumps at 0" in zf.read("sources/config.h").decode()
    msgs = []
    with pytest.raises(Exception):
        simulate_fmu(str(path), stop_time=2.0, output_interval=0.01, start_values={"F": 5.0},
                     logger=lambda *a: msgs.append(a[-1]))
    text = b" ".join(m if isinstance(m, bytes) else str(m).encode() for m in msgs).decode()
    assert "fmi2DoStep" in text and "sign(p_mass/m) jumps at 0" in text
    plain = export_fmu("mass_spring_damper", tmp_path / "msd.fmu")
    with zipfile.ZipFile(plain) as zf:
        assert "BG_STEP_HINT" not in zf.read("sources/config.h").decode()
