"""Noise levels estimated by default, x0 estimated jointly with θ, in
estimate and sensitivity (the noise/x0 issue).

Every test uses the mass-spring-damper (two outputs with fixed sensor noise
x 0.002 m, v 0.01 m/s, no process noise) on short records written with
:meth:`Experiment.from_arrays`, and asserts numbers against an independent
reference: the truth the record was simulated with, the noise std it was
drawn with, or the output-error information Σ JᵀR⁻¹J of the forward
sensitivity equations.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import bondgraph.inference.estimate as est_mod
from bondgraph.cli.main import main
from bondgraph.data.records import Experiment
from bondgraph.inference.estimate import estimate
from bondgraph.inference.options import FitOptions, UKFOptions
from bondgraph.inference.prior import PriorSpec
from bondgraph.inference.problem import NoiseSpec, make_problem
from bondgraph.numerics.forward_sensitivity import SolverOptions, output_sensitivities
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate
from bondgraph.diagnose.settings import SearchOptions

TRUTH = {"m": 2.0, "k": 50.0, "c": 1.5}
#: the graph's sensor noise (x, v) and the record's true noise: 4 times it
MODEL_SD = np.array([0.002, 0.01])
TRUE_SD = 4 * MODEL_SD
UKF = UKFOptions(method="rk4")


@pytest.fixture(scope="module")
def msd():
    return Model.from_spec("mass_spring_damper")


def _record(model, *, x0=None, sd=TRUE_SD, declare=None, seed=1, T=6.0):
    """A record of the msd under a step-plus-sine force, noise ``sd``,
    optionally declaring ``declare`` (column -> noise_std)."""
    t = np.arange(0.0, T, 0.01)
    u = 5.0 * (np.sin(2 * t) + (t > 1)).reshape(-1, 1)
    x0 = model.x0 if x0 is None else np.asarray(x0, float)
    sim = simulate(model, t, u, x0=x0, theta=model.theta(TRUTH), hold="zoh")
    y = sim.y + sd * np.random.default_rng(seed).standard_normal(sim.y.shape)
    return Experiment.from_arrays(t, model=model, u=u, y=y, noise_std=declare,
                                  meta={"name": "msd_noise", "true_parameters": TRUTH,
                                        "columns": {"F": {"hold": "zoh"}}})   # as simulated


def _fit():
    return FitOptions(particles=30, iterations=30, seed=0, progress=False)


def _problem(model, exp, noise):
    """``model`` on ``exp`` with the noise policy ``noise`` and the prior
    5 % of max(|x0|, 1)."""
    return make_problem(model, exp, prior=PriorSpec(scale="magnitude"), noise=NoiseSpec(noise),
                        ukf=UKF)


def test_declared_noise_is_held_at_the_declared_value(msd, monkeypatch):
    declared = {"x": 0.0065, "v": 0.031}
    exp = _record(msd, declare=declared)
    seen = []
    real = est_mod.ukf_nll

    def spy(*a, **kw):
        seen.append(kw.get("R"))
        return real(*a, **kw)
    monkeypatch.setattr(est_mod, "ukf_nll", spy)
    r = estimate(_problem(msd, exp, "auto"), ["k"],
                 fit=FitOptions(particles=4, iterations=1, seed=0, progress=False, polish=False))
    assert r.params == ["k"]                        # nothing estimated besides k
    assert r.settings["noise_levels"]["x"] == {"std": 0.0065, "how": "declared", "crb": None}
    assert r.settings["noise_levels"]["v"]["std"] == 0.031
    # the filter's R is diag(declared²) in every evaluation
    want = np.diag([0.0065 ** 2, 0.031 ** 2])
    Rs = [R for R in seen if R is not None]
    assert Rs and len(Rs) == len(seen)
    for R in Rs:
        np.testing.assert_allclose(R, np.broadcast_to(want, R.shape), rtol=1e-12)


def test_undeclared_noise_is_estimated_and_improves_the_parameters(msd):
    exp = _record(msd)
    auto = estimate(_problem(msd, exp, "auto"), ["m", "k", "c"], fit=_fit())
    model = estimate(_problem(msd, exp, "model"), ["m", "k", "c"], fit=_fit())
    assert auto.params == ["m", "k", "c", "noise.x", "noise.v"]
    assert model.params == ["m", "k", "c"]
    for j, o in enumerate(("x", "v")):
        i = auto.params.index(f"noise.{o}")
        # within 3 Cramér-Rao std of the std the noise was drawn with
        assert abs(auto.estimates[i] - TRUE_SD[j]) < 3 * auto.std[i], (o, auto.estimates[i])
        assert auto.settings["noise_levels"][o]["how"] == "estimated"
    # the model's noise (4x too small) makes the parameters' z-scores larger
    za, zm = np.abs(auto.z[:3]), np.abs(model.z[:3])
    assert np.all(za <= zm + 1e-9), (za, zm)
    assert np.max(za) < 3.5 and np.max(zm) > 6.0, (za, zm)


def test_cli_estimates_an_unmeasured_initial_state(msd, tmp_path, capsys):
    p0 = 0.6                                       # true momentum p_mass at t0 (model X0: 0)
    exp = _record(msd, x0=[p0, 0.0], sd=MODEL_SD, declare={"x": 0.002, "v": 0.01}, T=4.0)
    exp.save(tmp_path / "rec.csv")
    rc = main(["estimate", "--model", "mass_spring_damper", "--data", str(tmp_path / "rec.csv"),
               "--params", "k,c", "--fit", "nll", "--estimate-x0", "p_mass", "--method", "rk4",
               "--particles", "20", "--iterations", "20", "--quiet",
               "--fixed", "m=2", "--out", str(tmp_path / "out")])
    assert rc == 0, capsys.readouterr().err
    res = json.loads((tmp_path / "out" / "result.json").read_text())
    assert res["params"] == ["k", "c", "x0.p_mass"]
    i = res["params"].index("x0.p_mass")
    est, sd = res["estimates"][i], res["std"][i]
    assert sd is not None and 0 < sd < 0.05
    assert abs(est - p0) < 3 * sd, (est, sd)
    assert res["settings"]["x0_states"] == ["p_mass"]
    assert res["settings"]["noise_levels"]["x"]["how"] == "declared"
    assert (tmp_path / "out" / "fit_outputs.png").stat().st_size > 1000
    # the plots' filter is the estimate's: x0 estimated (token spread), R as declared
    from bondgraph.inference.estimate import EstimationResult
    from bondgraph.report.estimation import filter_of

    r = EstimationResult.from_json(tmp_path / "out" / "result.json")
    x0, P0, R = filter_of(msd, r, np.zeros(2), np.diag([0.05 ** 2, 0.05 ** 2]))
    assert x0[0] == est and P0[0, 0] == pytest.approx((1e-6 * 0.05) ** 2)
    np.testing.assert_allclose(R[0], np.diag([0.002 ** 2, 0.01 ** 2]))


def test_sensitivity_x0_crb_matches_forward_sensitivities(msd, tmp_path):
    exp = _record(msd, x0=[0.6, 0.01], sd=MODEL_SD, declare={"x": 0.002, "v": 0.01}, T=3.0)
    exp.save(tmp_path / "rec.csv")
    rc = main(["sensitivity", "--model", "mass_spring_damper", "--data",
               str(tmp_path / "rec.csv"), "--params", "m,k,c", "--estimate-x0", "all",
               "--x0", "p_mass=0.6,q_spring=0.01", "--method", "rk4", "--substeps", "4",
               "--no-plots", "--quiet", "--no-sensitivities", "--out", str(tmp_path / "s")])
    assert rc == 0
    nu = json.loads((tmp_path / "s" / "sensitivity.json").read_text())["local"]["nuisance"]
    assert nu["names"] == ["x0.p_mass", "x0.q_spring"]
    # reference: F = Σ_k J_kᵀ R⁻¹ J_k, J = [∂y/∂θ, ∂y/∂x0] (forward sensitivity equations)
    th = msd.theta()
    s = output_sensitivities(msd, exp.t, exp.inputs_for(msd), th, np.array([0.6, 0.01]),
                             ["m", "k", "c"], x0_states=["p_mass", "q_spring"],
                             solver=SolverOptions(hold="zoh", rtol=1e-9, atol=1e-12))
    J = np.concatenate([s.dydtheta, s.dydx0], axis=2)          # (N, n_y, 5)
    F = np.einsum("nik,i,nil->kl", J, 1.0 / MODEL_SD ** 2, J)
    crb = np.sqrt(np.diag(np.linalg.inv(F)))[3:]
    np.testing.assert_allclose(nu["std"], crb, rtol=1e-3)      # measured: 2e-8


@pytest.mark.parametrize("argv, needle", [
    (["--estimate-x0", "p_mas"], "p_mas"),
    (["--noise", "bogus"], "bogus"),
])
@pytest.mark.parametrize("cmd", ["estimate", "sensitivity", "loop"])
def test_bad_state_or_noise_mode_is_a_clean_error(msd, tmp_path, capsys, cmd, argv, needle):
    exp = _record(msd, sd=MODEL_SD, T=1.0)
    exp.save(tmp_path / "rec.csv")
    base = [cmd, "--model", "mass_spring_damper", "--data", str(tmp_path / "rec.csv"),
            "--quiet", "--out", str(tmp_path / "o")]
    if cmd != "sensitivity":
        base += ["--params", "m,k,c"]
    rc = main(base + argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err
    assert f"bondgraph {cmd}: error:" in err and needle in err, err


def test_loop_estimates_undeclared_noise_in_the_declared_fit(msd):
    from bondgraph.catalog.reference import mass_spring_damper
    from bondgraph.diagnose.loop import LoopSettings, run_loop

    exp = _record(msd)
    logs = []
    res = run_loop(mass_spring_damper(), exp, LoopSettings(params=["m", "k", "c"], ukf=UKF, search=SearchOptions(max_steps=1, structural=False)), progress=False, log=logs.append)
    assert any("measurement-noise std estimated" in ln and "x, v" in ln for ln in logs)
    d = res.initial.to_dict()
    for j, o in enumerate(("x", "v")):
        sd = d["std"][f"noise.{o}"]
        assert abs(d["noise_estimates"][o] - TRUE_SD[j]) < 3 * sd, (o, d["noise_estimates"][o])
    assert res.settings["noise"] == "auto" and res.settings["noise_outputs"] == ["x", "v"]


def _bare_msd():
    """The model of :func:`bare_msd_graph`."""
    return Model.from_graph(bare_msd_graph())


def bare_msd_graph():
    """The mass-spring-damper with a position sensor that declares no noise
    level (``noise_std`` not given: meas_std is 0), as a user may write it."""
    from bondgraph import BondGraph
    g = BondGraph("msd_bare_sensor", "mass-spring-damper, sensor without a noise level")
    F = g.input("F", "N", 0.0, "force")
    m, k, c = (g.param(n, TRUTH[n], u, b, n) for n, u, b in
               (("m", "kg", (0.1, 10.0)), ("k", "N/m", (1.0, 500.0)),
                ("c", "N*s/m", (0.01, 20.0))))
    v = g.one("v")
    g.connect(g.Se("force", F), v)
    g.connect(v, g.I("mass", m))
    spring = g.C("spring", stiffness=k)
    g.connect(v, spring)
    g.connect(v, g.R("damper", c))
    g.sensor("x", spring.q, unit="m")
    return g


def test_record_noise_level_is_the_noise_of_an_oversampled_signal():
    """Second-difference pseudo-residuals (Gasser, Sroka & Jennen-Steinmetz
    1986): white noise of std 0.004 on a slow sine (and a step) is seen as
    0.004 within 5 %; missing samples are skipped; a constant output shows
    no level (NaN)."""
    from bondgraph.inference.estimand import record_noise_level
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 20.0, 0.01)
    y = np.column_stack([0.3 * np.sin(0.5 * t) + 0.1 * (t > 7) + 0.004 * rng.standard_normal(t.size),
                         np.full(t.size, 2.0)])
    y[::3, 0] = np.nan
    got = record_noise_level(y)
    assert got[0] == pytest.approx(0.004, rel=0.05)
    assert np.isnan(got[1])


def test_a_sensor_without_a_noise_level_gets_one_estimated_from_the_record():
    """A user's sensor that declares no noise (meas_std 0) on a record that
    declares none: the estimate starts from the level seen in the record and
    estimates it (it raised "bound 3: need finite lower < upper, got [-inf,
    -inf]" before). Truth simulated by scipy's solve_ivp (the msd's hand
    equations), noise std 0.004 m: the estimated std within 10 %, k within
    3 of its Cramér-Rao std."""
    from scipy.integrate import solve_ivp
    model = _bare_msd()
    t = np.arange(0.0, 8.0, 0.01)
    force = lambda s: 5.0 * (np.sin(2 * s) + (s > 1))
    rhs = lambda s, x: [x[1] / TRUTH["m"], force(s) - TRUTH["k"] * x[0]
                        - TRUTH["c"] * x[1] / TRUTH["m"]]   # x = (q, p)
    sol = solve_ivp(rhs, (0.0, t[-1]), [0.0, 0.0], t_eval=t, rtol=1e-10, atol=1e-12,
                    max_step=0.005)
    y = sol.y[0] + 0.004 * np.random.default_rng(5).standard_normal(t.size)
    exp = Experiment.from_arrays(t, model=model, u=force(t).reshape(-1, 1), y=y.reshape(-1, 1),
                                 meta={"name": "bare", "columns": {"F": {"hold": "linear"}}})
    pb = make_problem(model, exp, prior=PriorSpec(scale="magnitude"),
                      ukf=UKFOptions(method="rk4", substeps=2, hold="linear"))
    r = estimate(pb, ["k"], fit=FitOptions(particles=8, iterations=5, seed=0, progress=False))
    lvl = r.settings["noise_levels"]["x"]
    assert lvl["how"] == "estimated"
    assert lvl["std"] == pytest.approx(0.004, rel=0.10)
    k = r.params.index("k")
    assert abs(r.theta[model.param_index("k")] - TRUTH["k"]) < 3 * r.std[k]
    assert not any("discretisation error" in w for w in r.warnings)
    # a start with every estimated quantity (the local refit of `estimate`
    # after a new discretisation) places the whole estimate, the noise level
    # included, in the population: no search step, no polish, and the best
    # is the estimate itself (the noise level restarting from the record's
    # 0.004-ish second-difference level would score worse)
    again = estimate(pb, ["k"], start=r.estimates,
                     fit=FitOptions(particles=8, iterations=0, seed=1, progress=False,
                                    polish=False, hessian=False))
    assert again.nll == pytest.approx(r.nll, abs=1e-6)
    np.testing.assert_allclose(again.estimates, r.estimates, rtol=1e-12)


def test_no_level_anywhere_is_a_clean_error():
    """Neither the sensor, nor the record, nor the record's values (a
    constant output) give a noise level: the error names the output."""
    from bondgraph.errors import OptionError
    from bondgraph.inference.estimand import noise_plan
    model = _bare_msd()
    with pytest.raises(OptionError, match=r"'x'.*declare one of them"):
        noise_plan(model, model.theta0, ["k"], [], np.full(1, np.nan), np.ones((50, 1)))


@pytest.mark.parametrize("method,backend", [("rk4", "numba"), ("rk4", "numpy"), ("ros2", "numba"),
                                            ("ros2", "numpy")])
def test_the_fine_free_run_agrees_with_scipy(method, backend):
    """The loop's ``"fine"`` free run (the filter's method at 4 times its
    substeps, fixed-step, the input held linearly) against scipy's
    solve_ivp of the msd's hand equations with the same piecewise-linear
    force (rtol 1e-10): within 1e-5 of the response's range with RK4,
    1e-3 with ROS2 (order 2), compiled or numpy."""
    from scipy.integrate import solve_ivp

    from bondgraph.diagnose.inference_calls import fine_free_run
    model = _bare_msd()
    t = np.arange(0.0, 6.0, 0.02)
    F = 5.0 * np.sin(3.0 * t) + 2.0 * (t > 1.0)
    x0 = np.array([0.05, -0.01])             # (p_mass, q_spring)
    rhs = lambda s, x: [np.interp(s, t, F) - TRUTH["k"] * x[1] - TRUTH["c"] * x[0] / TRUTH["m"],
                        x[0] / TRUTH["m"]]
    ref = solve_ivp(rhs, (0.0, t[-1]), x0, t_eval=t, rtol=1e-10, atol=1e-12, max_step=0.005)
    assert model.states == ["p_mass", "q_spring"]
    exp = Experiment.from_arrays(t, model=model, u=F.reshape(-1, 1), y=np.zeros((t.size, 1)),
                                 meta={"name": "fine"})
    pb = make_problem(model, exp, ukf=UKFOptions(method=method, substeps=2, hold="linear",
                                                 backend=backend))
    y = fine_free_run(pb, F.reshape(-1, 1), "linear", model.theta0, x0)
    q = ref.y[1]
    assert y.shape == (t.size, 1)
    assert np.max(np.abs(y[:, 0] - q)) < {"rk4": 1e-5, "ros2": 1e-3}[method] * np.ptp(q)


@pytest.mark.parametrize("hold", ["zoh", "linear"])
def test_the_compiled_ros2_free_run_equals_the_numpy_steps(hold):
    """The compiled ROS2 trajectory (``sim_numba.ros2_trajectory``, the
    Jacobian at the start of each interval, frozen over its substeps) gives
    the outputs of the numpy steps (``simulate_batch``) to rounding (W
    inverted by elimination, not LAPACK), and NaN from the sample where the
    state turns non-finite, as they do (a spring of k = -5e4 on a 1-D mass:
    e^(224 t) overflows within the record)."""
    from bondgraph.inference.prior import fixed_step_outputs
    from bondgraph.numerics.integrators import simulate_batch

    model = _bare_msd()
    t = np.arange(0.0, 6.0, 0.02)
    F = (5.0 * np.sin(3.0 * t) + 2.0 * (t > 1.0)).reshape(-1, 1)
    x0 = np.array([0.05, -0.01])
    for k in (TRUTH["k"], -5e4):
        th = model.theta({**TRUTH, "k": k})
        ref = simulate_batch(model, t, F, th[None, :], x0, method="ros2", substeps=3,
                             hold=hold)[:, 0, :]
        got = fixed_step_outputs(model, t, F, th, x0, "ros2", 3, hold)
        assert got.shape == ref.shape == (t.size, 1)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
        ok = np.isfinite(ref)
        assert ok.sum() > (10 if k < 0 else t.size - 1)
        scale = np.max(np.abs(ref[ok]))
        assert np.max(np.abs(got[ok] - ref[ok])) <= 1e-12 * scale
    assert not np.isfinite(ref[-1]).any()          # the unstable spring overflowed


def test_an_output_the_record_lacks_gets_no_noise_level(msd):
    """The record holds no sample of ``v`` (its column all NaN), declares no
    noise: only ``noise.x`` is estimated (``v``'s level has zero Fisher
    information; estimated, it made the Fisher matrix singular and no
    Cramér-Rao std was reported), and the stds of k and c equal the
    Cramér-Rao bound of the forward sensitivity equations on x alone, with
    the initial state as a nuisance under the filter's prior (std 0.05),
    at the estimated noise level: within 3 % (measured 0.5 % and 1.7 %)."""
    from bondgraph.inference.estimand import noise_plan
    full = _record(msd)
    y = full.outputs_for(msd).copy()
    y[:, 1] = np.nan
    exp = Experiment.from_arrays(full.t, model=msd, u=full.inputs_for(msd), y=y,
                                 meta={"name": "x_only", "columns": {"F": {"hold": "zoh"}}})
    add, outs, sigma, notes = noise_plan(msd, msd.theta0, ["k", "c"], [], np.full(2, np.nan), y)
    assert add == [] and outs == ["x"] and np.isnan(sigma).all()
    assert any("no finite sample of output(s) v" in n for n in notes)
    r = estimate(_problem(msd, exp, "auto"), ["k", "c"],
                 fit=FitOptions(particles=10, iterations=10, seed=0, progress=False))
    assert r.params == ["k", "c", "noise.x"]
    assert r.settings["noise_levels"]["x"]["how"] == "estimated"
    assert abs(r.estimates[2] - TRUE_SD[0]) < 3 * r.std[2]
    th = msd.theta(dict(zip(["k", "c"], r.estimates[:2])))
    s = output_sensitivities(msd, exp.t, exp.inputs_for(msd), th, msd.x0, ["k", "c"],
                             x0_states=list(msd.states),
                             solver=SolverOptions(hold="zoh", rtol=1e-9, atol=1e-12))
    J = np.concatenate([s.dydtheta, s.dydx0], axis=2)[:, 0, :]        # output x only
    F = J.T @ J / r.estimates[2] ** 2
    F[2:, 2:] += np.eye(2) / 0.05 ** 2                                 # the prior on x0
    crb = np.sqrt(np.diag(np.linalg.inv(F)))[:2]
    np.testing.assert_allclose(r.std[:2], crb, rtol=0.03)


def test_a_quantised_record_starts_its_noise_level_where_its_box_reaches_the_spread():
    """A quantised encoder oversampled (most second differences exactly 0):
    the robust second-difference level is far below the signal (by hand:
    a slow sine of amplitude 0.1 m quantised at 1 µm and sampled at 1 kHz,
    1.4826 x MAD of the second differences, is 0). The estimated level then
    starts at the output's std / NOISE_BOX, so that its box (start x/÷
    NOISE_BOX) reaches the output's own spread: on a user's EMPS graph the
    old start (3.0e-8 m) capped the level at 3e-4 m against a 0.026 m
    misfit of the declared model, and every likelihood ratio read 5e8."""
    from bondgraph.inference.estimand import NOISE_BOX, noise_plan, record_noise_level
    model = _bare_msd()
    t = np.arange(0.0, 20.0, 0.001)
    y = (np.round(0.1 * np.sin(0.5 * t) / 1e-6) * 1e-6).reshape(-1, 1)
    seen = record_noise_level(y)[0]
    spread = float(np.std(y))
    assert seen < spread / NOISE_BOX               # the case: the box would end below
    add, outs, sigma, notes = noise_plan(model, model.theta0, ["k"], [], np.full(1, np.nan), y)
    assert outs == ["x"] and sigma[0] == pytest.approx(spread / NOISE_BOX, rel=1e-12)
    assert "raised to the output's std / 10000" in notes[-1]
    # an ordinary record keeps its second-difference start
    noisy = y + 0.004 * np.random.default_rng(1).standard_normal(y.shape)
    _, _, sigma, notes = noise_plan(model, model.theta0, ["k"], [], np.full(1, np.nan), noisy)
    assert sigma[0] == pytest.approx(record_noise_level(noisy)[0]) and "raised" not in notes[-1]
    assert sigma[0] == pytest.approx(0.004, rel=0.05)


def test_sensitivity_of_a_sensor_without_a_noise_level_weighs_by_the_record_level(tmp_path):
    """A user's sensor declared without a noise level (meas_std 0) on a record
    that declares none: the output-error information weighs the output by
    the level the analysis estimates (the record's second-difference level),
    not by 0 (a user's CED graph crashed: "Eigenvalues did not converge").
    Reference: F = Σ_k (∂y_k/∂θ)² / σ² from scipy's solve_ivp of the hand
    equations (the input linear between samples, as held), ∂y/∂θ by central
    differences, in the analysis' relative coordinates (∂θ = θ)."""
    from scipy.integrate import solve_ivp

    from bondgraph.inference.estimand import record_noise_level

    model = _bare_msd()
    t = np.arange(0.0, 8.0, 0.01)
    force = lambda s: 5.0 * (np.sin(2 * s) + (s > 1))

    fs = force(t)

    def run(p):             # the input as the filter holds it: linear between samples
        rhs = lambda s, x: [x[1] / p["m"], np.interp(s, t, fs) - p["k"] * x[0]
                            - p["c"] * x[1] / p["m"]]
        return solve_ivp(rhs, (0.0, t[-1]), x0, t_eval=t, rtol=1e-11, atol=1e-13,
                         max_step=0.005).y[0]

    x0 = [0.0, 0.0]
    y = run(TRUTH) + 0.004 * np.random.default_rng(5).standard_normal(t.size)
    exp = Experiment.from_arrays(t, model=model, u=force(t).reshape(-1, 1), y=y.reshape(-1, 1),
                                 meta={"name": "bare", "columns": {"F": {"hold": "linear"}}})
    from bondgraph.sensitivity.analysis import LocalOptions, analyse
    pb = make_problem(model, exp, ukf=UKFOptions(method="rk4", substeps=4, hold="linear"))
    rep = analyse(pb, ["k", "c"], local=LocalOptions(sens_rtol=1e-10, sens_atol=1e-13))
    x0 = [pb.x0[model.state_index("q_spring")], pb.x0[model.state_index("p_mass")]]
    F = np.asarray(rep.local["output_error"]["fisher_rel"], float)
    sigma = record_noise_level(y.reshape(-1, 1))[0]
    J = []
    for n in ("k", "c"):
        up, dn = dict(TRUTH), dict(TRUTH)
        up[n], dn[n] = TRUTH[n] * (1 + 1e-5), TRUTH[n] * (1 - 1e-5)
        J.append((run(up) - run(dn)) / 2e-5)                    # ∂y/∂ln θ
    J = np.array(J).T
    ref = J.T @ J / sigma ** 2
    np.testing.assert_allclose(np.diag(F), np.diag(ref), rtol=1e-2)    # measured: 0.02 %
    # the cross term is a cancellation (the correlation of k and c is 0.008):
    # judged on the scale that matters, the correlation √(F_kk F_cc); measured
    # 4.7e-4 of it on one machine, 3e-5 on another
    scale = np.sqrt(np.outer(np.diag(ref), np.diag(ref)))
    assert np.all(np.abs(F - ref) <= 1e-2 * scale)


def test_a_noise_std_on_its_box_is_named_with_the_side_and_the_cause():
    """A sensor noise std estimated to the top of its box (NOISE_BOX times
    the level the fit started from: a user's ball-screw graph without process noise,
    1e-6 m declared, 0.01 m estimated) is the model's error, not the
    sensor: the warning says so and, without process noise, where to
    declare it; on the bottom of the box the variance went into the process
    noise. Both lose their Cramér-Rao std."""
    from types import SimpleNamespace

    from bondgraph.diagnose.fit import _noise_bound_warning
    from bondgraph.inference.estimand import NOISE_BOX

    logs = []
    ctx = SimpleNamespace(log=logs.append, said=set())
    start = {"qm": 1e-6, "v": 0.1, "w": 0.2}
    boxes = {o: (v / NOISE_BOX, v * NOISE_BOX, v, True) for o, v in start.items()}
    est = {"qm": 1e-6 * NOISE_BOX, "v": 0.1 / NOISE_BOX, "w": 0.3}
    std = {"noise.qm": 1.0, "noise.v": 1.0, "noise.w": 0.01}
    _noise_bound_warning(ctx, "the declared fit", est, boxes, std, process_noise=False)
    assert std == {"noise.qm": None, "noise.v": None, "noise.w": 0.01}
    assert logs == [
        "  warning: the declared fit: measurement-noise std on the bottom of its box: v = 1e-05 "
        "(not identified by the record beside the process noise; declare it in the record or "
        "use noise='model'; said once per output)",
        "  warning: the declared fit: measurement-noise std on the top of its box: qm = 0.01, "
        "10000 times the record's level (1e-06): not the sensor but the model's "
        "error, which the filter reads as sensor noise (no process noise is declared: declare "
        "it on the states where efforts or flows are unmodelled); declare the sensor's level in "
        "the record to hold it (said once per output)"]
    # a refit that ends there again is not said again, its std still dropped
    logs.clear()
    std = {"noise.qm": 1.0, "noise.v": 1.0}
    _noise_bound_warning(ctx, "a refit", est, boxes, std, process_noise=False)
    assert logs == [] and std == {"noise.qm": None, "noise.v": None}
    ctx.said.clear()
    _noise_bound_warning(ctx, "a refit", {"qm": 0.01}, {"qm": (1e-10, 0.01, 1e-6, False)}, {},
                         process_noise=True)
    # a box not kept on the record's level (a problem made without one) is
    # centred on the fit's start, and the line names that start
    assert logs[0].endswith("qm = 0.01, 10000 times the level the fit started from (1e-06): not "
                            "the sensor but the model's error, which the filter reads as sensor "
                            "noise; declare the sensor's level in the record to hold it (said "
                            "once per output)")


def test_a_refit_from_a_drifted_noise_level_reaches_the_records_level_again():
    """The loop's refits start from the previous fit's noise estimate. A
    box ×/÷ NOISE_BOX around that start drifted away from the record one
    refit at a time (a user's closed-loop graph: a level on the bottom of
    its box, refitted twice, ended at 1.79e-11 V and could no longer reach
    the record's 0.040 V). The planned noise keeps the record's level as
    the box's centre: a refit started 1e5 below the truth returns to it
    (within 3 Cramér-Rao std of the std the record was drawn with); the
    box centred on the start ends on its top, a factor 10 short."""
    from dataclasses import replace

    from bondgraph.diagnose.fit import noise_boxes, noise_start, planned_noise
    from bondgraph.diagnose.inference_calls import fisher_fit
    from bondgraph.diagnose.settings import LoopSettings

    model = _bare_msd()
    sd = 0.004
    exp = _record(model, sd=np.array([sd]), seed=3)
    settings = LoopSettings(params=["k"], ukf=UKF)
    _, spec = planned_noise(make_problem(model, exp, noise=NoiseSpec("auto"), ukf=UKF),
                            settings, log=lambda _m: None)
    assert spec.outputs(model) == ["x"] and spec.centre["x"] == spec.held["x"]
    base = make_problem(model, exp, prior=PriorSpec(scale="magnitude"), noise=spec, ukf=UKF)
    drifted = base.conditioned_on(noise_levels={"x": sd / 1e5})
    assert drifted.noise.centre == spec.centre           # kept over the refits' levels
    j = [model.param_index("k")]
    box = model.bounds(["k"])
    found = {}
    centred_on_start = replace(drifted, noise=replace(drifted.noise, centre={}))
    for name, pb in (("anchored", drifted), ("start", centred_on_start)):
        th, F, conv, _, _, sig, *_ = fisher_fit(pb, model.theta0, j, box, 40,
                                                log_scale=[False], noises=["x"])
        found[name] = (sig["x"], F)
    s, F = found["anchored"]
    crb = np.sqrt(np.linalg.inv(F)[-1, -1])              # noise std last
    assert abs(s - sd) < 3 * crb, (s, sd, crb)
    (lo, hi, centre, of_record), = noise_boxes(drifted, noise_start(drifted, model.theta0)).values()
    assert of_record and centre == spec.centre["x"] and lo == pytest.approx(sd / 1e5)
    assert found["start"][0] == pytest.approx(sd / 1e5 * 1e4, rel=1e-6)   # its box's top
