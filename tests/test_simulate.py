"""Simulation (bondgraph/numerics/simulate.py) against independent references: scipy
solve_ivp of hand-written ODEs, matrix exponentials of linear models, analytic
eigenvalues; convergence order and L-stability of the fixed-step methods."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from bondgraph.numerics import integrators
from bondgraph.data.records import Experiment
from bondgraph.errors import DataError, ModelError, NumericalError
from bondgraph.numerics.model import Model
from bondgraph.core.jsonsafe import to_jsonable
from bondgraph.numerics.simulate import InputSignals, simulate, stiffness_report


@pytest.fixture(scope="module")
def msd():
    return Model.load("mass_spring_damper")


@pytest.fixture(scope="module")
def motor():
    return Model.load("dc_motor_compliant")


def msd_matrices(m, k, c):
    """Hand-derived linear MSD: x = [p, q], dx/dt = A x + B F."""
    A = np.array([[-c / m, -k], [1.0 / m, 0.0]])
    B = np.array([1.0, 0.0])
    return A, B


def exact_linear(A, B, x0, u, t):
    """Exact solution for a constant input u (augmented matrix exponential)."""
    n = A.shape[0]
    M = np.zeros((n + 1, n + 1))
    M[:n, :n] = A
    M[:n, n] = B * u
    out = []
    for tk in t:
        z = expm(M * (tk - t[0])) @ np.concatenate([x0, [1.0]])
        out.append(z[:n])
    return np.array(out)


# --------------------------------------------- against hand-written ODEs
@pytest.mark.parametrize("method", ["BDF", "Radau", "LSODA"])
def test_msd_matches_hand_written_ode(msd, method):
    m, k, c = 2.4, 60.0, 1.2
    F = lambda t: 5.0 * np.sin(3.0 * t) + 2.0  # noqa: E731

    def ref_rhs(t, x):
        p, q = x
        return [F(t) - k * q - c * p / m, p / m]

    t = np.linspace(0.0, 6.0, 301)
    x0 = np.array([0.3, -0.01])
    ref = solve_ivp(ref_rhs, (0, 6), x0, t_eval=t, method="DOP853", rtol=1e-12, atol=1e-14)
    res = simulate(msd, t, u={"F": F}, x0=x0, theta={"m": m, "k": k, "c": c}, method=method,
                   rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(res.x, ref.y.T, rtol=0, atol=2e-8 * np.abs(ref.y).max())
    # outputs: position q and velocity p/m
    np.testing.assert_allclose(res.output("x"), ref.y[1], atol=1e-9)
    np.testing.assert_allclose(res.output("v"), ref.y[0] / m, atol=1e-8)
    assert res.stats["nfev"] > 0 and res.method == method


def test_dc_motor_matches_hand_written_ode(motor):
    th = {"R_a": 1.4, "L_a": 0.005, "k_m": 0.08, "J_m": 2e-4, "b_m": 1e-4, "k_s": 40.0,
          "J_L": 6e-3, "b_L": 2e-3}
    V = lambda t: 12.0 * (1.0 - np.exp(-t / 0.01))  # noqa: E731
    TL = lambda t: 0.05 * np.sin(5.0 * t)  # noqa: E731

    def ref_rhs(t, x):
        lam, pm, phi, pl = x
        return [V(t) - th["R_a"] * lam / th["L_a"] - th["k_m"] * pm / th["J_m"],
                th["k_m"] * lam / th["L_a"] - th["b_m"] * pm / th["J_m"] - th["k_s"] * phi,
                pm / th["J_m"] - pl / th["J_L"],
                th["k_s"] * phi - th["b_L"] * pl / th["J_L"] - TL(t)]

    t = np.linspace(0.0, 0.5, 501)
    ref = solve_ivp(ref_rhs, (0, 0.5), np.zeros(4), t_eval=t, method="DOP853", rtol=1e-12,
                    atol=1e-15)
    res = simulate(motor, t, u={"V": V, "T_L": TL}, theta=th, method="BDF", rtol=1e-10,
                   atol=1e-13)
    scale = np.abs(ref.y).max(axis=1)
    np.testing.assert_allclose(res.x / scale, ref.y.T / scale, atol=1e-6)
    np.testing.assert_allclose(res.output("w_L"), ref.y[3] / th["J_L"],
                               atol=1e-6 * np.abs(ref.y[3] / th["J_L"]).max())
    np.testing.assert_allclose(res.output("i"), ref.y[0] / th["L_a"],
                               atol=1e-6 * np.abs(ref.y[0] / th["L_a"]).max())


def test_step_input_zoh_all_methods_agree_with_expm(msd):
    # constant force from t = 0: every method must give the exact solution
    A, B = msd_matrices(2.0, 50.0, 1.5)
    t = np.arange(0, 3.0001, 0.01)
    x0 = np.array([0.0, 0.02])
    exact = exact_linear(A, B, x0, 10.0, t)
    for method, sub, tol in (("BDF", 1, 1e-6), ("LSODA", 1, 1e-6), ("rk4", 4, 1e-8),
                             ("ros2", 16, 1e-4)):
        res = simulate(msd, t, u=np.full((t.size, 1), 10.0), x0=x0, method=method,
                       substeps=sub)
        err = np.abs(res.x - exact).max() / np.abs(exact).max()
        assert err < tol, (method, err)


# --------------------------------------------------- order and stability
def _fixed_errors(msd, method, subs, dt=0.05, T=2.0):
    A, B = msd_matrices(2.0, 50.0, 1.5)
    t = np.arange(0, T + dt / 2, dt)
    x0 = np.array([1.0, 0.05])
    exact = exact_linear(A, B, x0, 3.0, t)
    errs = []
    for s in subs:
        res = simulate(msd, t, u=np.full((t.size, 1), 3.0), x0=x0, method=method, substeps=s)
        errs.append(np.abs(res.x - exact).max())
    return np.array(errs)


def test_ros2_is_second_order(msd):
    errs = _fixed_errors(msd, "ros2", [2, 4, 8, 16])
    ratios = errs[:-1] / errs[1:]
    # halving the step divides the error by ~4 (order 2)
    assert np.all((ratios > 3.5) & (ratios < 4.6)), ratios


def test_rk4_is_fourth_order(msd):
    errs = _fixed_errors(msd, "rk4", [1, 2, 4])
    ratios = errs[:-1] / errs[1:]
    assert np.all((ratios > 13.0) & (ratios < 19.0)), ratios


def test_ros2_l_stable_where_rk4_explodes():
    rr = Model.load("rr_loop")
    # single mode λ = -R1 R2 / ((R1 + R2) L) = -80 1/s at the defaults
    R1, R2, L = rr.theta0[[rr.param_index(n) for n in ("R1", "R2", "L")]]
    lam = -R1 * R2 / ((R1 + R2) * L)
    assert lam == pytest.approx(-80.0)
    h = 1e6 / abs(lam)  # h λ = -1e6
    t = np.arange(20) * h
    res = simulate(rr, t, x0=[1.0], method="ros2")
    x = res.x[:, 0]
    assert np.all(np.isfinite(x))
    # L-stable: |R(hλ)| -> 0 as hλ -> -inf; at -1e6 the mode is damped ~1e6-fold per step
    assert abs(x[1]) < 1e-5 and np.all(np.abs(x[2:]) <= np.abs(x[1:-1]) + 1e-300)
    with pytest.raises(NumericalError, match=r"state 'p_L' .* became .* at t = ") as ei:
        simulate(rr, t, x0=[1.0], method="rk4")
    assert "rk4" in str(ei.value)


# ----------------------------------------------------------- stiffness
def test_stiffness_report_analytic_eigenvalues(msd):
    m, k, c = 2.4, 60.0, 1.2
    t = np.linspace(0, 2, 201)
    res = simulate(msd, t, u={"F": 1.0}, theta={"m": m, "k": k, "c": c}, method="LSODA")
    rep, table = stiffness_report(msd, res)
    # λ = -c/(2m) ± i sqrt(k/m - (c/2m)^2) (characteristic polynomial m s^2 + c s + k)
    re, im = -c / (2 * m), np.sqrt(k / m - (c / (2 * m)) ** 2)
    for s in rep["samples"]:
        np.testing.assert_allclose(sorted(s["eigenvalues"], key=lambda z: z[1]),
                                   [[re, -im], [re, im]], rtol=1e-12)
    assert rep["max_abs_re"] == pytest.approx(abs(re), rel=1e-12)
    h = integrators.rk4_stable_step(np.array([re + 1j * im, re - 1j * im]))
    assert rep["rk4_stable_step"] == pytest.approx(h, rel=1e-12)
    assert rep["rk4_substeps_needed"] == 1
    json.dumps(to_jsonable(rep), allow_nan=False)  # JSON-able by the one policy
    assert "max |Re λ|" in table and f"{abs(re):.6g}" in table


def test_stiffness_report_substeps_are_right():
    rr = Model.load("rr_loop")
    th = rr.theta({"L": 1e-4})  # λ = -8e4 1/s
    t = np.arange(0, 0.2, 1e-3)
    V = np.where(t > 0.05, 1.0, 0.0)
    res = simulate(rr, t, u={"V": V}, theta=th, method="BDF")
    rep, _ = stiffness_report(rr, res)
    assert rep["max_abs_re"] == pytest.approx(8e4, rel=1e-12)
    need = rep["rk4_substeps_needed"]
    assert need == int(np.ceil(1e-3 * 8e4 / 2.785293563))  # RK4 real-axis limit 2.7853
    ok = simulate(rr, t, u={"V": V}, theta=th, method="rk4", substeps=need)
    ref = simulate(rr, t, u={"V": V}, theta=th, method="BDF", hold="zoh")
    # stable (at the edge of the region: |R| ~ 0.99 per sub-step, so slow to
    # damp, bounded, and settled on the steady state by the end)
    assert np.all(np.abs(ok.x) <= np.abs(ref.x).max() * (1 + 1e-9))
    np.testing.assert_allclose(ok.y[-20:], ref.y[-20:], atol=1e-9)
    with pytest.raises(NumericalError, match="substeps per sample"):
        simulate(rr, t, u={"V": V}, theta=th, method="rk4", substeps=need // 2)


# ----------------------------------------------------------- input forms
def test_input_forms_agree():
    cvt = Model.load("toy_cvt")
    t = np.arange(0, 4.0001, 0.05)
    T = lambda tt: np.where(tt >= 0.5, 40.0, 0.0)  # noqa: E731
    r = lambda tt: np.interp(tt, [1.0, 3.0], [0.05, 0.09])  # noqa: E731
    a = InputSignals(cvt, t, {"T": T, "r": r})
    b = InputSignals(cvt, t, {"T": T(t), "r": r(t)})
    c = InputSignals(cvt, t, np.column_stack([T(t), r(t)]))
    d = InputSignals(cvt, t, lambda tt: np.array([T(tt), r(tt)]))
    for s in (a, b, c, d):
        np.testing.assert_array_equal(s.samples[:, :2], a.samples[:, :2])
    inside = (t > 1.06) & (t < 2.94)
    for s in (a, b, c, d):  # der(r) = slope 0.02 inside the ramp, 0 outside
        np.testing.assert_allclose(s.samples[inside, 2], 0.02, rtol=1e-6)
        np.testing.assert_allclose(s.samples[t < 0.94, 2], 0.0, atol=1e-12)
    assert a.source["der(r)"].startswith("central difference")
    assert b.source["der(r)"].startswith("numpy.gradient")
    # full-width array: der(r) taken as given
    full = np.column_stack([T(t), r(t), np.full(t.size, 7.0)])
    np.testing.assert_array_equal(InputSignals(cvt, t, full).samples[:, 2], 7.0)
    # defaults
    e = InputSignals(cvt, t, None)
    np.testing.assert_array_equal(e.samples, np.broadcast_to(cvt.u0, e.samples.shape))


def test_zoh_hold_matches_fixed_step(msd):
    rng = np.random.default_rng(3)
    t = np.arange(0, 2.0001, 0.02)
    F = np.repeat(rng.choice([-5.0, 5.0], size=t.size // 5 + 1), 5)[:t.size]  # PRBS
    a = simulate(msd, t, u={"F": F}, method="BDF", hold="zoh", rtol=1e-10, atol=1e-12)
    b = simulate(msd, t, u={"F": F}, method="rk4", substeps=20)
    assert a.stats["segments"] == np.count_nonzero(np.diff(F[:-1])) + 1
    np.testing.assert_allclose(a.x, b.x, atol=1e-8)
    lin = simulate(msd, t, u={"F": F}, method="BDF", hold="linear")
    assert np.abs(lin.x - a.x).max() > 1e-3  # linear interpolation is a different signal


def test_bad_arguments(msd):
    t = np.linspace(0, 1, 11)
    with pytest.raises(ModelError, match="unknown simulation method 'Euler'"):
        simulate(msd, t, method="Euler")
    with pytest.raises(ModelError, match=r"input array has shape \(11, 3\)"):
        simulate(msd, t, u=np.zeros((11, 3)))
    with pytest.raises(ModelError, match="has no input 'G'"):
        simulate(msd, t, u={"G": 1.0})
    with pytest.raises(DataError, match="input 'F' is nan at sample 4"):
        simulate(msd, t, u={"F": np.where(np.arange(11) == 4, np.nan, 1.0)})
    with pytest.raises(DataError, match="must increase strictly"):
        simulate(msd, [0.0, 0.2, 0.1])
    with pytest.raises(ModelError, match=r"x0 has shape \(3,\)"):
        simulate(msd, t, x0=[0, 0, 0])
    with pytest.raises(ModelError, match="has no parameter 'mass'"):
        simulate(msd, t, theta={"mass": 1.0})


# ------------------------------------------------------- output and CLI
def test_save_csv_round_trip(tmp_path, msd):
    t = np.linspace(0, 1, 51)
    res = simulate(msd, t, u={"F": 3.0}, x0={"q_spring": 0.01}, method="ros2", substeps=4)
    p = Experiment.from_simulation(res, name="sim").save(tmp_path / "sim.csv")
    exp = Experiment.load(p)
    np.testing.assert_array_equal(exp.outputs_for(msd), res.y)
    np.testing.assert_array_equal(exp.inputs_for(msd), res.u)
    np.testing.assert_array_equal(exp["state.q_spring"], res.state("q_spring"))
    assert exp.meta["x0"] == {"p_mass": 0.0, "q_spring": 0.01}
    assert exp.meta["method"] == "ros2"
    df = Experiment.from_simulation(res).to_dataframe()
    assert [c.split(" [")[0] for c in df.columns] == ["t", "F", "x", "v", "state.p_mass",
                                                      "state.q_spring"]


def test_cli_simulate(tmp_path, capsys):
    from bondgraph.cli.main import main

    out = tmp_path / "msd.csv"
    assert main(["simulate", "mass_spring_damper", "--experiment", "msd_force_step", "-o",
                 str(out), "--stiffness"]) == 0
    exp = Experiment.load(out)
    assert len(exp) == 1001 and exp.meta["parameters"]["k"] == 60.0
    rep = json.loads(out.with_suffix(".stiffness.json").read_text())
    assert rep["model"] == "mass_spring_damper"
    # from a record CSV, fixed-step
    out2 = tmp_path / "again.csv"
    assert main(["simulate", "mass_spring_damper", "-e", str(out), "-o", str(out2),
                 "--method", "rk4", "--substeps", "2", "--record-params"]) == 0
    np.testing.assert_allclose(Experiment.load(out2)["x"], exp["x"], atol=1e-6)
    # defaults for a duration, with a constant input
    out3 = tmp_path / "def.csv"
    assert main(["simulate", "mass_spring_damper", "--duration", "1", "--dt", "0.1",
                 "--input", "F=2", "-o", str(out3)]) == 0
    e3 = Experiment.load(out3)
    assert len(e3) == 11 and np.all(e3["F"] == 2.0)
    assert main(["simulate", "mass_spring_damper", "-e", "no_such_experiment"]) == 2
    assert "unknown experiment 'no_such_experiment'" in capsys.readouterr().err
    # --params: a fit's values (its noise level left out), the same run as --param
    fit = tmp_path / "result.json"
    fit.write_text(json.dumps({"params": ["k", "noise.x"], "estimates": [40.0, 0.01],
                               "fixed": {"c": 2.0}}))
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    assert main(["simulate", "mass_spring_damper", "-e", str(out), "--params", str(fit),
                 "-o", str(a)]) == 0
    assert main(["simulate", "mass_spring_damper", "-e", str(out), "--param", "k=40",
                 "--param", "c=2", "-o", str(b)]) == 0
    assert Experiment.load(a).meta["parameters"]["k"] == 40.0
    np.testing.assert_array_equal(Experiment.load(a)["x"], Experiment.load(b)["x"])
    fit.write_text(json.dumps({"params": ["k2"], "estimates": [1.0]}))
    assert main(["simulate", "mass_spring_damper", "-e", str(out), "--params", str(fit),
                 "-o", str(a)]) == 2
    assert "has no parameter(s) k2" in capsys.readouterr().err
    # a value outside the model's box is simulated as given, and said (m's box: [0.5, 8])
    assert main(["simulate", "mass_spring_damper", "--duration", "1", "--param", "m=-2",
                 "--param", "k=40", "-o", str(a)]) == 0
    said = capsys.readouterr().out
    assert "note: m = -2 is outside the model's box [0.5, 8] for it: simulated as given" in said
    assert "k = 40" not in said


def test_cli_simulate_noise_writes_the_experiments_record(tmp_path, capsys):
    """`simulate MODEL -e NAME --noise -o FILE.csv` writes the noisy record of
    run_experiment (the README's msd_force_step.csv): same numbers, the true
    parameters in the sidecar, and noise of the declared size on x."""
    from bondgraph.cli.main import main
    from bondgraph.data.experiments import run_experiment

    out = tmp_path / "msd_force_step.csv"
    assert main(["simulate", "mass_spring_damper", "-e", "msd_force_step", "--noise",
                 "-o", str(out)]) == 0
    got, ref = Experiment.load(out), run_experiment("msd_force_step")
    np.testing.assert_array_equal(got["x"], ref["x"])
    assert got.meta["true_parameters"] == ref.meta["true_parameters"]
    noise = got["x"] - got["state.q_spring"]          # x is the spring's displacement
    assert np.std(noise) == pytest.approx(0.002, rel=0.1)
    assert main(["simulate", "dc_motor", "-e", "msd_force_step", "--noise"]) == 2
    assert "model 'mass_spring_damper'" in capsys.readouterr().err
    # without a registered experiment: the model's own sensor noise (seed 0)
    mine = tmp_path / "mine.csv"
    assert main(["simulate", "mass_spring_damper", "--noise", "--duration", "20", "-o",
                 str(mine)]) == 0
    rec = Experiment.load(mine)
    assert rec.noise_std == {"x": 0.002, "v": 0.01} and rec.meta["seed"] == 0
    assert np.std(rec["x"] - rec["state.q_spring"]) == pytest.approx(0.002, rel=0.1)


@pytest.mark.parametrize("hold", ["linear", "zoh"])
def test_inputs_at_one_time_equal_the_array_evaluation(hold):
    """``InputSignals.at`` (one float per input, what an adaptive solver's
    right-hand side calls) gives bit for bit what the inputs' functions give
    on an array: a sampled array (interpolated or held), a constant and a
    callable; inside a zero-order-hold segment without callables, the held
    sample."""
    model = Model.load("toy_cvt")
    t = np.linspace(0.0, 2.0, 41)
    rng = np.random.default_rng(3)
    samples = rng.normal(size=t.size)
    sig = InputSignals(model, t, {"T": samples, "r": 0.7, "der(r)": lambda tq: np.sin(3 * tq)},
                       hold=hold)
    for tq in np.concatenate([rng.uniform(-0.1, 2.1, 200), t]):
        ref = np.array([float(np.asarray(fn(np.array([tq]))).reshape(-1)[0])
                        for fn in sig._fns])
        assert np.array_equal(sig.at(float(tq)), ref)
    held = InputSignals(model, t, {"T": samples, "r": 0.7, "der(r)": 0.0}, hold="zoh")
    seg = held.segment_input(7, "zoh")
    assert np.array_equal(seg(t[7] + 0.02), [samples[7], 0.7, 0.0])


@pytest.mark.parametrize("hold", ["linear", "zoh", "linear,zoh,linear"])
def test_sampled_inputs_at_one_time_equal_numpy_interp_and_the_held_sample(hold):
    """Without callables ``InputSignals.at`` is one search and one vector
    expression (its sample table); its values are bit for bit
    ``numpy.interp``'s (linear) and the last sample at or before the time
    (zero-order), on an uneven grid of times with values over ten decades,
    at the sample times, between them and outside the record."""
    model = Model.load("toy_cvt")
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.01, 0.3, 300))
    U = rng.standard_normal((t.size, 3)) * 10.0 ** rng.uniform(-5, 5, 3)
    sig = InputSignals(model, t, U, hold=hold)
    assert sig._table is not None
    holds = hold.split(",") * (3 if "," not in hold else 1)
    for tq in np.concatenate([rng.uniform(t[0] - 1, t[-1] + 1, 3000), t, [t[0] - 1, t[-1] + 1]]):
        k = min(max(int(np.searchsorted(t, tq, side="right")) - 1, 0), t.size - 1)
        ref = [float(np.interp(tq, t, U[:, j])) if h == "linear" else U[k, j]
               for j, h in enumerate(holds)]
        assert np.array_equal(sig.at(float(tq)), ref), tq
    v = sig.at(float(t[3]))
    v[:] = 0.0                                  # a fresh vector, not the table's row
    assert np.array_equal(sig.at(float(t[3])), U[3])


@pytest.mark.parametrize("method", ["BDF", "RK45"])
def test_adaptive_solvers_on_the_compiled_point_kernels_equal_numpy(method):
    """``simulate(..., backend="numba")``: the adaptive solvers call the
    compiled f (and f_dfdx as Jacobian) instead of the generated numpy
    functions; the same expressions, so the trajectory agrees to the
    solver's tolerance (reference: the numpy right-hand side; nonlinear
    model: the vehicle coast-down with its tanh, atan and sin)."""
    pytest.importorskip("numba")
    model = Model.load("vehicle_coastdown")
    t = np.linspace(0.0, 20.0, 201)
    brake = np.where((t > 5) & (t < 8), 0.6, 0.0)
    th = dict(zip(model.params, model.theta0))
    x0 = np.zeros(model.n_x)      # rolling at 12 m/s
    x0[model.states.index("body.p_m")] = th["m"] * 12.0
    x0[model.states.index("wheels.p_J")] = th["J_w"] * 12.0 / th["r_dyn"]
    a = simulate(model, t, {"brake": brake}, x0=x0, method=method, rtol=1e-9, atol=1e-12,
                 hold="zoh")
    b = simulate(model, t, {"brake": brake}, x0=x0, method=method, rtol=1e-9, atol=1e-12,
                 hold="zoh", backend="numba")
    assert a.stats["backend"] == "numpy" and b.stats["backend"] == "numba"
    assert np.ptp(a.x[:, 0]) > 0
    np.testing.assert_allclose(b.x, a.x, rtol=1e-6, atol=1e-9 * np.abs(a.x).max())
    with pytest.raises(ModelError, match="backend"):
        simulate(model, t, {"brake": brake}, backend="cuda")


@pytest.mark.parametrize("method", ["LSODA", "BDF", "RK45"])
def test_an_adaptive_run_that_runs_away_stops_with_its_time(msd, method):
    """An unstable model (negative spring, no damping) grows as
    cosh/sinh(λt), λ = sqrt(-k/m) = 5 1/s: p(t) = p0 cosh(5t) passes 1e100
    at t = ln(2e100/p0)/5 = 47.572 s for p0 = 1e-3. The adaptive solvers
    stop there with an error naming the state, instead of returning 1e130
    or cycling (LSODA once made 8 million calls at one t on a cubic spring
    of negative coefficient)."""
    th = dict(zip(msd.params, msd.theta0), k=-50.0, c=0.0)
    assert np.sqrt(50.0 / th["m"]) == pytest.approx(5.0)
    t = np.linspace(0.0, 100.0, 101)
    t_exact = np.log(2e100 / 1e-3) / 5.0
    with pytest.raises(NumericalError, match=rf"{method} ran away .* 'p_mass' = 1\.\d+e\+100") as ei:
        simulate(msd, t, np.zeros((t.size, 1)), x0=[1e-3, 0.0], theta=th, method=method)
    t_stop = float(str(ei.value).split("near t = ")[1].split(" s")[0])
    assert t_stop == pytest.approx(t_exact, abs=0.1)
    assert "unstable" in str(ei.value)


@pytest.mark.parametrize("method", ["LSODA", "BDF"])
def test_an_adaptive_run_that_crawls_stops_and_names_the_fast_mode(msd, method):
    """A mass-spring-damper whose mass is off by ten orders of magnitude
    (m 1e-10 kg, k 1e4 N/m: ω = sqrt(k/m) = 1e7 rad/s, damping ratio
    c/(2 sqrt(k m)) = 5e-4 with c 1e-6 N s/m) sampled at 1 kHz: an adaptive
    solver must resolve every oscillation, some 10⁵ calls per sample, and
    would run for hours on a long record. It stops after CRAWL_CALLS calls
    that did not advance one sample, the fastest mode named from the
    generated Jacobian: ω (to 1 %), its damping ratio and ω·dt."""
    th = dict(zip(msd.params, msd.theta0), m=1e-10, k=1e4, c=1e-6)
    t = np.arange(0.0, 10.0, 1e-3)
    with pytest.raises(NumericalError, match=rf"{method} crawled \(20000 calls") as ei:
        simulate(msd, t, np.ones((t.size, 1)), theta=th, method=method)
    msg = str(ei.value)
    omega = float(msg.split("fastest mode there is ")[1].split(" rad/s")[0])
    assert omega == pytest.approx(1e7, rel=0.01)
    ratio = float(msg.split("damping ratio ")[1].split(")")[0])
    assert ratio == pytest.approx(5e-4, rel=0.05)
    assert "1e+04 times the sampling rate" in msg and "units" in msg
    t_stop = float(msg.split("near t = ")[1].split(" s")[0])
    assert t_stop < 1e-3     # within the first sample interval, not after hours
    # the same model at a sane mass is no crawl: 10 s at 1 kHz, exact steady state
    ok = simulate(msd, t, np.ones((t.size, 1)), theta=dict(th, m=1.0, c=50.0), method=method)
    assert ok.x[-1, 1] == pytest.approx(1.0 / 1e4, rel=1e-6)


def test_lsoda_is_one_odepack_call_per_segment_with_solve_ivps_steps(msd):
    """simulate(method="LSODA") runs ODEPACK's LSODA through odeint, one
    call per zero-order-hold segment (:func:`lsoda_segment`). On a
    staircase force (5 levels, each held 2 s) it takes the steps of scipy's
    solve_ivp(method="LSODA") over the same segments (the same number of
    right-hand-side calls) and meets the exact solution (matrix exponential
    per segment) to its tolerance."""
    m, k, c = 2.4, 60.0, 1.2
    t = np.linspace(0.0, 10.0, 501)
    F = np.repeat([1.0, -2.0, 0.5, 3.0, 0.0], 100)
    F = np.append(F, F[-1])
    res = simulate(msd, t, u=F[:, None], theta={"m": m, "k": k, "c": c}, method="LSODA",
                   rtol=1e-6, atol=1e-9, hold="zoh")
    A, B = msd_matrices(m, k, c)
    ref, nfev, x = [np.zeros(2)], 0, np.zeros(2)
    for a in range(0, 500, 100):
        seg = t[a:a + 101]
        ref.extend(exact_linear(A, B, x, F[a], seg)[1:])
        sol = solve_ivp(lambda tq, xq: A @ xq + B * F[a], (seg[0], seg[-1]), x, method="LSODA",
                        t_eval=seg, rtol=1e-6, atol=1e-9, jac=lambda tq, xq: A)
        nfev += sol.nfev
        x = ref[-1]
    ref = np.array(ref)
    assert res.stats["segments"] == 5 and res.stats["nfev"] == nfev
    scale = np.abs(ref).max(axis=0)
    assert np.max(np.abs(res.x - ref) / scale) < 1e-4


@pytest.mark.filterwarnings("ignore::scipy.integrate.ODEintWarning")
def test_lsoda_segment_returns_the_samples_reached_before_a_failure():
    """y' = y², y(0) = 1 has the solution 1/(1 - t), which leaves every
    bound at t = 1: the samples before it are returned, with status -1 and
    LSODA's message; without a failure all samples come back."""
    from bondgraph.numerics.simulate import lsoda_segment

    ts = np.linspace(0.0, 2.0, 11)
    with np.errstate(all="ignore"):
        sol = lsoda_segment(lambda tq, y: y * y, lambda tq, y: np.array([[2.0 * y[0]]]), ts,
                            np.array([1.0]), 1e-8, 1e-10)
    assert sol.status == -1 and sol.message
    np.testing.assert_array_equal(sol.t, ts[:5])      # t = 0 ... 0.8
    np.testing.assert_allclose(sol.y[0], 1.0 / (1.0 - ts[:5]), rtol=1e-6)
    ok = lsoda_segment(lambda tq, y: -y, lambda tq, y: -np.eye(1), ts, np.array([1.0]),
                       1e-10, 1e-12)
    assert ok.status == 0 and ok.y.shape == (1, 11) and ok.nfev > 0 and ok.njev == ok.nlu
    np.testing.assert_allclose(ok.y[0], np.exp(-ts), rtol=1e-8)


def test_the_compiled_right_hand_side_equals_the_python_guard_to_the_bit(monkeypatch):
    """An adaptive solver on a model's C kernels calls one compiled
    function per right-hand side (:func:`simulate.compiled_rhs`: the
    guard's checks, the inputs over the sample table, the kernel). Its
    trajectories equal those of the Python path (:func:`simulate.guard_rhs`
    over :meth:`InputSignals.segment_input`) to the bit, with the same
    number of calls, for every hold (zero-order, linear, one of each per
    input, a constant input) and solver; and the guard's outcomes are the
    same: a non-finite derivative at a finite state kept with its
    component, a state that ran away raised."""
    pytest.importorskip("numba")
    from bondgraph.numerics import simulate as S
    from bondgraph.numerics.compiled import point_kernels

    model = Model.load("thermal_two_node")
    if not hasattr(point_kernels(model).f, "__wrapper_address__"):
        pytest.skip("no C compiler: the model's numba kernels take the Python path")
    t = np.linspace(0.0, 4000.0, 801)
    P = np.repeat(np.random.default_rng(0).uniform(0.0, 500.0, 16), 50)[:t.size]
    P = np.append(P, np.full(t.size - P.size, P[-1]))
    Ta = 20.0 + 5.0 * np.sin(2 * np.pi * t / 1500.0)
    cases = [({"P": P, "T_a": Ta}, h) for h in ("zoh", "linear", "zoh,linear", "linear,zoh")]
    cases.append(({"P": P, "T_a": 20.0}, "zoh"))
    for u, hold in cases:
        for method in ("LSODA", "BDF", "RK45"):
            fast = simulate(model, t, u, method=method, hold=hold, backend="numba",
                            rtol=1e-6, atol=1e-9)
            with monkeypatch.context() as mp:
                mp.setattr(S, "compiled_rhs", lambda *a, **k: None)
                slow = simulate(model, t, u, method=method, hold=hold, backend="numba",
                                rtol=1e-6, atol=1e-9)
            assert np.ptp(fast.x[:, 0]) > 0
            assert np.array_equal(fast.x, slow.x), (hold, method)
            assert fast.stats["nfev"] == slow.stats["nfev"], (hold, method)
    # the guard: k = inf makes dp/dt = F - k q - c v NaN at q = 0 (finite state)
    msd = Model.load("mass_spring_damper")
    th = msd.theta0.copy()
    th[msd.param_index("k")] = np.inf
    tt = np.linspace(0.0, 1.0, 11)
    sig = InputSignals(msd, tt, np.ones((tt.size, 1)), hold="zoh")
    kern = point_kernels(msd)
    fast = S.compiled_rhs(kern, th, sig.segment_table(0, "zoh"), msd.n_x)
    slow = S.guard_rhs(S._point_rhs(msd, kern, th, sig.segment_input(0, "zoh"))[0])
    x = np.zeros(msd.n_x)
    assert np.array_equal(fast(0.1, x), slow(0.1, x), equal_nan=True)
    ip = msd.states.index("p_mass")
    assert fast.undefined.component == slow.undefined.component == ip
    for g in (fast, slow):
        with pytest.raises(S.Runaway, match="became non-finite"):
            g(0.2, np.array([np.nan, 0.0]))
        with pytest.raises(S.Runaway, match="ran away"):
            g(0.3, np.array([1e101, 0.0]))
