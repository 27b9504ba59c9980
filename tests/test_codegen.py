"""Generated code: batching, the filterpy adapter, metadata, and the check
that generated/ is exactly what the registered graphs produce."""

import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import sympy as sp

from bondgraph.core import codegen
from bondgraph.catalog import reference as models
from bondgraph.numerics import registry
from bondgraph.numerics.model import Model
from bondgraph.core.equations import derive


def test_generated_dir_is_up_to_date():
    """`bondgraph generate --check` in-process: every registered model's file
    equals what its graph produces now."""
    stale = registry.generate(check=True, verbose=False)
    assert stale == [], f"stale generated code: {stale}; run `bondgraph generate`"


def test_check_detects_a_stale_file(tmp_path):
    registry.generate(["mass_spring_damper"], directory=tmp_path, verbose=False)
    assert registry.generate(["mass_spring_damper"], check=True, directory=tmp_path,
                             verbose=False) == []
    p = tmp_path / "mass_spring_damper.py"
    p.write_text(p.read_text().replace("k*q_spring", "k*q_spring*1.0001", 1))
    assert registry.generate(["mass_spring_damper"], check=True, directory=tmp_path,
                             verbose=False) == ["mass_spring_damper"]


def test_cli_check_exits_nonzero_naming_the_stale_model(tmp_path):
    registry.generate(["toy_cvt"], directory=tmp_path, verbose=False)
    (tmp_path / "toy_cvt.py").write_text("# edited by hand\n")
    r = subprocess.run([sys.executable, "-m", "bondgraph.cli.main", "generate", "--check", "toy_cvt",
                        "--out", str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 1
    assert "toy_cvt" in r.stderr


def test_module_imports_only_numpy_and_names_its_source():
    text = Path(registry.generated_dir(), "dc_motor_compliant.py").read_text()
    tree = ast.parse(text)
    imports = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
    assert [a.name for n in imports for a in n.names] == ["numpy"]
    assert "bondgraph.catalog.reference:dc_motor_compliant" in text
    assert "bondgraph generate" in text and "DO NOT EDIT" in text


def test_batching_over_leading_axes_matches_pointwise():
    model = Model.load("dc_motor_compliant")
    rng = np.random.default_rng(3)
    P, S = 7, 9  # 7 parameter sets x 9 sigma points
    x = rng.normal(size=(P, S, model.n_x))
    u = rng.normal(size=(model.n_u,))
    th = model.theta0 * rng.uniform(0.5, 2, size=(P, 1, model.n_theta))
    F = model.f(x, u, th)
    J = model.dfdx(x, u, th)
    Y = model.h(x, u, th)
    assert F.shape == (P, S, model.n_x) and J.shape == (P, S, model.n_x, model.n_x)
    assert Y.shape == (P, S, model.n_y)
    assert model.dfdtheta(x, u, th).shape == (P, S, model.n_x, model.n_theta)
    assert model.energy(x, u, th).shape == (P, S)
    for p in (0, 6):
        for s in (0, 4, 8):
            np.testing.assert_allclose(F[p, s], model.f(x[p, s], u, th[p, 0]), rtol=1e-14)
            np.testing.assert_allclose(J[p, s], model.dfdx(x[p, s], u, th[p, 0]), rtol=1e-14)


def test_generated_f_equals_lambdify_of_the_state_space():
    g = models.toy_cvt()
    ss = derive(g)
    model = Model.load("toy_cvt")
    fn = sp.lambdify((ss.states, ss.inputs, ss.params), ss.f, "numpy")
    rng = np.random.default_rng(4)
    for _ in range(5):
        x = rng.normal(size=model.n_x) * 100
        u = np.array([rng.uniform(0, 60), rng.uniform(0.02, 0.1), rng.normal()])
        th = model.theta0 * rng.uniform(0.5, 2, size=model.n_theta)
        np.testing.assert_allclose(model.f(x, u, th), np.array(fn(x, u, th), dtype=float),
                                   rtol=1e-12)


def test_metadata_and_noise_functions():
    model = Model.load("mass_spring_damper")
    assert model.states == ["p_mass", "q_spring"]
    assert model.inputs == ["F"] and model.outputs == ["x", "v"]
    assert model.param_units == ["kg", "N/m", "N*s/m"]
    np.testing.assert_array_equal(model.theta0, [2.0, 50.0, 1.5])
    np.testing.assert_array_equal(model.lower, [0.5, 5.0, 0.1])
    np.testing.assert_allclose(model.meas_std(model.theta0), [0.002, 0.01])
    assert model.proc_std(np.ones((3, 3))).shape == (3, 2)
    th = model.theta(m=3.0)
    assert th[0] == 3.0 and th[1] == 50.0
    full = model.expand_theta(["k"], np.array([[10.0], [20.0]]))
    assert full.shape == (2, 3) and full[1, 1] == 20.0 and full[1, 0] == 2.0


def test_filterpy_adapter_matches_rk4():
    from bondgraph.numerics.integrators import rk4

    model = Model.load("mass_spring_damper")
    x = np.array([0.3, -0.01])
    u = np.array([2.0])
    a = model.fx(x, 0.01, u=u, theta=model.theta0, substeps=4)
    b = rk4(model.f, x, u, model.theta0, 0.01, 4)
    np.testing.assert_allclose(a, b, rtol=1e-15)
    np.testing.assert_allclose(model.hx(x, u=u), model.h(x, u, model.theta0))


def test_identifier_collisions_are_resolved():
    import bondgraph as bg

    g = bg.BondGraph("clash")
    a = g.param("a.b", 1.0)
    b = g.param("a__b", 2.0)
    x = g.param("x", 3.0)  # collides with the argument name
    j = g.one("j")
    g.connect(g.Se("s", a + b + x), j)
    g.connect(j, g.I("m", 1.0))
    m = Model.from_graph(g)
    np.testing.assert_allclose(m.f(np.zeros(1), np.zeros(0), m.theta0), [6.0])


def test_in_memory_model_and_written_module_agree(tmp_path):
    g = models.dc_motor_gear()
    ss = derive(g)
    path = codegen.write_module(ss, tmp_path / "dcg.py", source="test")
    mod = codegen.load_module(path)
    m1, m2 = Model(mod), Model.from_graph(models.dc_motor_gear())
    x = np.array([[0.1, 0.2]])
    u = np.array([[3.0]])
    np.testing.assert_array_equal(m1.f(x, u, m1.theta0), m2.f(x, u, m2.theta0))


def test_cli_draw_and_equations(tmp_path):
    out = tmp_path / "g.png"
    r = subprocess.run([sys.executable, "-m", "bondgraph.cli.main", "draw", "dc_motor_gear", "-o",
                        str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert out.stat().st_size > 10_000
    r = subprocess.run([sys.executable, "-m", "bondgraph.cli.main", "equations", "rr_loop",
                        "--causality"], capture_output=True, text=True)
    assert r.returncode == 0 and "dp_L/dt" in r.stdout and "stroke at" in r.stdout


def test_cli_unknown_model_is_a_clear_error():
    r = subprocess.run([sys.executable, "-m", "bondgraph.cli.main", "equations", "no_such_model"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "unknown model 'no_such_model'" in r.stderr
