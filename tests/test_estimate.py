"""Maximum-likelihood estimation (bondgraph.inference.estimate): synthetic records
simulated with scipy's solve_ivp (independent of the filter's integrators),
truth recovered within 3 Cramér-Rao standard deviations, Cramér-Rao bounds
against the analytic Fisher information of the output-error model, DE path,
two-stage protocol, CLI with JSON + PNG output and --resume."""

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph.inference.estimate import (EstimationResult, Stage, cramer_rao, estimate, hessian_batched, two_stage)
from bondgraph.errors import IdentifiabilityWarning, OptionError
from bondgraph.inference.options import DEFAULT_BACKEND, FitOptions, UKFOptions
from bondgraph.inference.prior import PriorSpec
from bondgraph.inference.problem import NoiseSpec, make_problem
from bondgraph.core.graph import BondGraph
from bondgraph.numerics.model import Model


def simulate_zoh(model, t, u, theta, x0):
    """Noise-free outputs with inputs held over each interval (scipy LSODA,
    tight tolerances)."""
    x = np.asarray(x0, float)
    ys = [model.h(x[None], u[0], theta)[0]]
    for k in range(len(t) - 1):
        sol = solve_ivp(lambda _, z: model.f(z[None], u[k], theta)[0], (t[k], t[k + 1]), x,
                        method="LSODA", rtol=1e-10, atol=1e-12)
        x = sol.y[:, -1]
        ys.append(model.h(x[None], u[k + 1], theta)[0])
    return np.array(ys)


@pytest.fixture(scope="module")
def msd_record():
    m = Model.load("mass_spring_damper")
    dt, N = 0.02, 300
    t = np.arange(N) * dt
    rng = np.random.default_rng(0)
    u = np.repeat(rng.normal(0.0, 20.0, N // 20), 20)[:, None]
    truth = {"m": 2.5, "k": 80.0, "c": 2.0}
    th = m.theta(truth)
    y0 = simulate_zoh(m, t, u, th, np.zeros(m.n_x))
    y = y0 + rng.normal(size=y0.shape) * m.meas_std(th)
    return m, t, u, y, y0, truth


UKF = UKFOptions(method="rk4", substeps=2)
P0 = np.diag([1e-8, 1e-10])


def problem(m, rec, *, P0=None, ukf=UKF, x0=None, fixed=None):
    """The test's problem: the given prior covariance (else 5 % of max(|x0|, 1)),
    the graph's own noise levels."""
    prior = PriorSpec(x0=x0, P0=P0) if P0 is not None else PriorSpec(scale="magnitude", x0=x0)
    return make_problem(m, rec, prior=prior, noise=NoiseSpec("model"), ukf=ukf, fixed=fixed)


def test_pso_recovers_truth_within_3_cramer_rao(msd_record):
    m, t, u, y, _, truth = msd_record
    r = estimate(problem(m, (t, u, y), P0=P0), ["m", "k", "c"],
                 fit=FitOptions(particles=30, iterations=40, seed=2, progress=False))
    assert r.evaluations == 30 * 41
    assert r.evaluations_total > r.evaluations
    assert np.isfinite(r.std).all() and (r.std > 0).all()
    est = r.estimate_dict()
    for i, p in enumerate(r.params):
        assert abs(est[p] - truth[p]) < 3 * r.std[i], (p, est[p], truth[p], r.std[i])
    assert r.nll <= r.nll_optimizer
    np.testing.assert_allclose(np.diag(r.corr), 1.0)
    assert r.settings["discretisation"]["one_step"][0] < 0.1
    # JSON round trip
    back = EstimationResult.from_json(r.to_json())
    np.testing.assert_allclose(back.estimates, r.estimates)
    assert back.params == r.params


def test_cramer_rao_matches_fisher_information(msd_record):
    """No process noise and a known initial state: the UKF NLL is the exact
    output-error likelihood, whose expected Fisher information is
    Σ_k J_kᵀ R⁻¹ J_k with J_k = ∂y_k/∂θ (here from scipy simulations)."""
    m, t, u, y, y0, truth = msd_record
    names = ["m", "k", "c"]
    th = m.theta(truth)
    J = []
    for p in names:
        i = m.param_index(p)
        h = 1e-5 * th[i]
        tp, tm = th.copy(), th.copy()
        tp[i] += h
        tm[i] -= h
        J.append((simulate_zoh(m, t, u, tp, np.zeros(2)) - simulate_zoh(m, t, u, tm, np.zeros(2)))
                 / (2 * h))
    J = np.stack(J, axis=-1)                              # (N, n_y, k)
    Rinv = 1.0 / m.meas_std(th) ** 2
    fim = np.einsum("nyi,y,nyj->ij", J, Rinv, J)
    std_fim = np.sqrt(np.diag(np.linalg.inv(fim)))
    r = estimate(problem(m, (t, u, y), P0=P0), names, start=list(truth.values()),
                 fit=FitOptions(particles=20, iterations=10, seed=1, progress=False))
    np.testing.assert_allclose(r.std, std_fim, rtol=0.1)


def test_de_path(msd_record):
    m, t, u, y, _, truth = msd_record
    r = estimate(problem(m, (t, u, y), P0=P0, fixed={"m": truth["m"]}), ["k", "c"],
                 fit=FitOptions(optimizer="de", particles=20, iterations=15, seed=3,
                                progress=False))
    assert r.optimizer == "de" and r.evaluations == 20 * 16
    for i, p in enumerate(r.params):
        assert abs(r.estimates[i] - truth[p]) < 3 * r.std[i]
    assert r.fixed == {"m": 2.5} and r.theta[m.param_index("m")] == 2.5


def test_a_scale_symmetry_is_named_as_relative_changes():
    """NLL curvature from relative sensitivities S (N, 3) with S @ (1, 1, 1)
    = 0 at θ = (2, 50, 1.5): H = Jᵀ J with J = S / θ (model units). Scaling
    all three by one factor changes nothing, so the unidentified direction
    in relative changes is (1, 1, 1) exactly, whatever the box widths that
    scale the reported one; a direction that is not a scale (one parameter
    alone) is given as relative changes without that name."""
    rng = np.random.default_rng(4)
    S = rng.normal(size=(100, 3))
    S[:, 2] = -(S[:, 0] + S[:, 1])
    th = np.array([2.0, 50.0, 1.5])
    H = (S / th).T @ (S / th)
    cr = cramer_rao(H, ["m", "k", "c"], scale=np.array([10.0, 400.0, 4.0]), theta=th)
    assert not cr["positive_definite"]
    assert "as relative changes: m +1.00, k +1.00, c +1.00 (m, k, c scale together" \
        in cr["warning"]
    assert "relative changes" not in cramer_rao(H, ["m", "k", "c"], np.array([10.0, 400.0, 4.0]))[
        "warning"]
    H1 = np.diag([4.0, 1.0, 0.0])
    one = cramer_rao(H1, ["m", "k", "c"], theta=th)
    assert "as relative changes: c +1.00" in one["warning"] and "scale together" not in one["warning"]


def test_hessian_and_unidentified_direction():
    H, f0, n = hessian_batched(lambda X: (X[:, 0] - 1) ** 2 + 3 * X[:, 0] * X[:, 1] + 5 * X[:, 1] ** 2,
                               np.array([0.5, 0.2]), np.array([1e-3, 1e-3]))
    np.testing.assert_allclose(H, [[2.0, 3.0], [3.0, 10.0]], rtol=1e-6)
    assert n == 1 + 2 * 2 ** 2
    cr = cramer_rao(H, ["a", "b"])
    np.testing.assert_allclose(cr["cov"], np.linalg.inv(H), rtol=1e-10)
    bad = cramer_rao(np.array([[1.0, 1.0], [1.0, 1.0]]), ["a", "b"])
    assert not bad["positive_definite"] and "0.71·a" in bad["warning"] and "0.71·b" in bad["warning"]
    assert "not positive definite (smallest eigenvalue" in bad["warning"]
    # every curvature positive, the correlation 1 - 1e-7: nearly singular, not "not positive
    # definite"; the unit-curvature eigenvalues are 1 -+ r, their ratio (1 - r)/(1 + r) = 5e-8
    r = 1.0 - 1e-7
    D = np.diag([100.0, 200.0])
    near = cramer_rao(D @ np.array([[1.0, r], [r, 1.0]]) @ D, ["a", "b"])
    assert not near["positive_definite"]
    assert near["warning"].startswith("Hessian of the NLL is nearly singular (every curvature "
                                      "positive, but scaled to unit curvatures its smallest "
                                      "eigenvalue is 5e-08 of its largest, below 1e-06)")
    # conditional bounds: c is not identified (no curvature); the bounds of a
    # and b with c held are the inverse of their 2x2 block, 1/7 [[2, -1], [-1, 4]]
    H3 = np.array([[4.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 0.0]])
    plain = cramer_rao(H3, ["a", "b", "c"])
    assert np.isnan(plain["std"]).all() and plain["conditional_on"] == []
    cond = cramer_rao(H3, ["a", "b", "c"], scale=np.array([2.0, 0.5, 3.0]), conditional=True)
    assert not cond["positive_definite"] and cond["conditional_on"] == ["c"]
    np.testing.assert_allclose(cond["std"][:2], np.sqrt([2 / 7, 4 / 7]), rtol=1e-12)
    np.testing.assert_allclose(cond["cov"][:2, :2], np.array([[2, -1], [-1, 4]]) / 7, rtol=1e-12)
    assert np.isnan(cond["std"][2]) and "conditional on c held at the estimate" in cond["warning"]
    # a direction through every parameter leaves none to bound
    both = cramer_rao(np.array([[1.0, 1.0], [1.0, 1.0]]), ["a", "b"], conditional=True)
    assert np.isnan(both["std"]).all() and both["conditional_on"] == []
    # a parameter with a small share of the flat direction moves along it: no bound
    c, sn = np.cos(0.05), np.sin(0.05)              # flat direction 0.9988·c + 0.05·b
    R = np.array([[1, 0, 0], [0, c, -sn], [0, sn, c]])
    tilt = R.T @ np.diag([4.0, 2.0, 0.0]) @ R
    part = cramer_rao(tilt, ["a", "b", "c"], conditional=True)
    assert part["conditional_on"] == ["b", "c"] and np.isnan(part["std"][1:]).all()
    np.testing.assert_allclose(part["std"][0], 0.5, rtol=1e-12)


def test_unidentifiable_pair_warns(msd_record):
    """Only k/m enters a free oscillation... here: c and a duplicate of c."""
    g = BondGraph("two_dampers")
    F = g.input("F", "N")
    m_ = g.param("m", 1.0, "kg", (0.5, 2.0))
    c1 = g.param("c1", 1.0, "N*s/m", (0.1, 3.0))
    c2 = g.param("c2", 1.0, "N*s/m", (0.1, 3.0))
    v = g.one("v", domain="translation")
    g.connect(g.Se("F", F), v)
    g.connect(v, g.I("m", m_))
    g.connect(v, g.R("d1", c1))
    g.connect(v, g.R("d2", c2))
    g.sensor("v", v.f, unit="m/s", noise_std=0.01)
    model = Model.from_graph(g)
    t = np.arange(200) * 0.02
    u = np.sign(np.sin(2 * t))[:, None]
    y = simulate_zoh(model, t, u, model.theta0, np.zeros(1))
    y = y + np.random.default_rng(0).normal(size=y.shape) * 0.01
    with pytest.warns(IdentifiabilityWarning, match="not identified"):
        r = estimate(problem(model, (t, u, y), P0=np.diag([1e-8]), ukf=UKFOptions(method="rk4")),
                     ["c1", "c2"], fit=FitOptions(particles=10, iterations=5, progress=False))
    assert any("c1" in w and "c2" in w for w in r.warnings)


# ----------------------------------------------------------------- two stages
def _vehicle_pair():
    """A reduced 'coast-down' graph (mass, drag, rolling resistance; no
    engine) and a 'full' graph (engine inertia and torque gain through a
    ratio r, plus the same body): the protocol's structure at toy scale."""
    def body(g):
        m = g.param("m", 1200.0, "kg", (600.0, 2400.0), "mass")
        cd = g.param("c_d", 0.4, "N*s^2/m^2", (0.05, 2.0), "quadratic drag")
        F0 = g.param("F_0", 150.0, "N", (10.0, 500.0), "rolling resistance")
        v = g.one("v", domain="translation")
        g.connect(v, g.I("m", m, priority=-1))
        g.connect(v, g.R("drag", effort=lambda f: cd * f * abs(f)))
        g.connect(v, g.R("roll", effort=lambda f: F0 * __import__("sympy").tanh(f / 0.1)))
        g.sensor("v", v.f, unit="m/s", noise_std=0.05)
        return v

    red = BondGraph("coast")
    body(red)
    full = BondGraph("drive")
    v = body(full)
    T = full.input("thr", "")
    r = full.input("r", "m/rad", 0.05)
    Je = full.param("J_e", 0.15, "kg*m^2", (0.02, 0.5), "engine inertia")
    Tm = full.param("T_max", 60.0, "N*m", (20.0, 120.0), "torque at full throttle")
    we = full.one("w_e", domain="rotation")
    full.connect(full.Se("engine", Tm * T), we)
    full.connect(we, full.I("J_e", Je))
    tf = full.MTF("cvt", r)
    full.connect(we, tf.p1)
    full.connect(tf.p2, v)
    full.sensor("w_e", we.f, unit="rad/s", noise_std=1.0)
    return Model.from_graph(red), Model.from_graph(full)


@pytest.mark.slow
def test_two_stage_protocol_on_reduced_models():
    red, full = _vehicle_pair()
    truth = {"c_d": 0.55, "F_0": 180.0, "J_e": 0.12, "T_max": 75.0}
    rng = np.random.default_rng(5)
    # stage-1 record: coast-down from 20 m/s, 40 s at 10 Hz
    t1 = np.arange(400) * 0.1
    th1 = red.theta({p: v for p, v in truth.items() if p in red.params})
    y1 = simulate_zoh(red, t1, np.zeros((400, 0)), th1, np.array([1200.0 * 20.0]))
    y1 = y1 + rng.normal(size=y1.shape) * 0.05
    # stage-2 record: throttle steps with a varying ratio, 30 s at 20 Hz
    t2 = np.arange(600) * 0.05
    thr = np.clip(0.5 + 0.5 * np.sign(np.sin(0.6 * t2)), 0, 1) * 0.8 + 0.1
    r = 0.03 + 0.02 * (1 + np.sin(0.25 * t2)) / 2
    dr = np.gradient(r, t2)
    u2 = np.column_stack([thr, r, dr])
    assert full.inputs == ["thr", "r", "der(r)"]
    th2 = full.theta(truth)
    x20 = full.state({full.states[0]: 1200.0 * 5.0})
    y2 = simulate_zoh(full, t2, u2, th2, x20)
    y2 = y2 + rng.normal(size=y2.shape) * full.meas_std(th2)
    res = two_stage([
        Stage("coast-down", problem(red, (t1, np.zeros((400, 0)), y1), x0=[1200.0 * 20.0],
                                    P0=np.diag([100.0 ** 2]), ukf=UKFOptions(method="rk4")),
              ["c_d", "F_0"]),
        Stage("driving", problem(full, (t2, u2, y2), x0=x20, P0=np.diag([100.0 ** 2]),
                                 ukf=UKFOptions(method="rk4")), ["J_e", "T_max"]),
    ], fit=FitOptions(particles=16, iterations=20, seed=0, progress=False))
    s1, s2 = res
    assert s2.fixed == {"c_d": s1.estimates[0], "F_0": s1.estimates[1]}
    for i, p in enumerate(s1.params):
        assert abs(s1.estimates[i] - truth[p]) < 3 * s1.std[i], (p, s1.estimates[i], s1.std[i])
    # stage 2: the stage-1 errors shift J_e and T_max (with this seed the
    # conditional bound alone puts them ~4 std away); the propagated bound
    # std_total = sqrt(diag(H22⁻¹ + G Σ1 Gᵀ)) accounts for it
    assert s2.propagated["from_params"] == ["c_d", "F_0"]
    assert (s2.std_total >= s2.std).all()
    for i, p in enumerate(s2.params):
        assert abs(s2.estimates[i] - truth[p]) < 3 * s2.std_total[i], (p, s2.estimates[i],
                                                                      s2.std_total[i])
    z_cond = (s2.estimates - [truth[p] for p in s2.params]) / s2.std
    z_total = (s2.estimates - [truth[p] for p in s2.params]) / s2.std_total
    assert np.abs(z_total).max() < np.abs(z_cond).max()


# ----------------------------------------------------------------------- CLI
@pytest.fixture()
def msd_csv(tmp_path, msd_record):
    from bondgraph.data.records import Experiment

    m, t, u, y, _, truth = msd_record
    exp = Experiment.from_arrays(t, model=m, u=u, y=y, meta={"name": "msd_synth",
                                                           "true_parameters": truth})
    path = tmp_path / "msd.csv"
    exp.save(path)
    return path


def test_cli_writes_json_and_plots_and_resumes(tmp_path, msd_csv, capsys):
    from bondgraph.cli.main import main

    base = ["estimate", "--model", "mass_spring_damper", "--data", str(msd_csv),
            "--params", "m,k,c", "--particles", "12", "--seed", "4", "--method", "rk4",
            "--substeps", "2", "--quiet", "--no-polish"]
    a = tmp_path / "a"
    assert main(base + ["--iterations", "6", "--out", str(a)]) == 0
    out = capsys.readouterr().out
    assert "parameter" in out and "CR std" in out and "truth" in out
    res = json.loads((a / "result.json").read_text())
    for key in ("estimates", "std", "nll", "evaluations", "wall_s", "params", "corr"):
        assert key in res
    assert res["evaluations"] == 12 * 7
    assert (a / "fit_outputs.png").stat().st_size > 10_000
    assert (a / "innovations.png").stat().st_size > 10_000
    # interrupted run: 3 iterations, then --resume to 6 gives the same optimizer result
    b = tmp_path / "b"
    assert main(base + ["--iterations", "3", "--out", str(b), "--no-plots"]) == 0
    assert main(base + ["--iterations", "6", "--out", str(b), "--no-plots", "--resume"]) == 0
    rb = json.loads((b / "result.json").read_text())
    assert rb["optimizer_result"]["x"] == res["optimizer_result"]["x"]
    assert rb["optimizer_result"]["history"] == res["optimizer_result"]["history"]
    assert rb["evaluations"] == 12 * 7 and rb["optimizer_result"]["resumed_from"] == 3


def test_cli_counts_every_fit_of_the_estimation(tmp_path, msd_csv, capsys, monkeypatch):
    """Where the estimate is refitted (a discretisation or an input hold
    that changed at the estimate), the table's line counts the last fit's
    evaluations only; one more line and ``settings.estimation_work`` give
    the estimation's fits, evaluations and seconds in all (a user's CVT
    driveline: "80 optimizer evaluations (pso), 605 in total; 3.4 s" after
    a search of 8080 and three refits, 10238 evaluations in 32.5 s). Here
    one refit from the estimate is forced."""
    from bondgraph.cli import estimate as cli
    from bondgraph.cli.main import main

    own, seen = cli._refined, []

    def refined(args, chosen, problems, res, params, fit, states, paths):
        res, problems, agains = own(args, chosen, problems, res, params, fit, states, paths)
        seen.append(res.evaluations_total)
        again = cli._estimate_quiet(problems, params, replace(fit, iterations=0), states, None,
                                    start=res.estimates)
        seen.append(again.evaluations_total)
        return again, problems, agains

    monkeypatch.setattr(cli, "_refined", refined)
    out = tmp_path / "e"
    assert main(["estimate", "--model", "mass_spring_damper", "--data", str(msd_csv),
                 "--params", "m,k,c", "--particles", "12", "--iterations", "4", "--seed", "4",
                 "--method", "rk4", "--substeps", "2", "--hold", "zoh", "--quiet",
                 "--no-plots", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    res = json.loads((out / "result.json").read_text())
    work = res["settings"]["estimation_work"]
    assert len(seen) == 2 and seen[0] >= 12 * 5 and work["fits"] == 2
    assert work["evaluations"] == sum(seen) and res["evaluations_total"] == seen[1]
    assert "the estimation in all: 2 fits" in text and f"{sum(seen)} evaluations" in text


def test_cli_bad_parameter_name(msd_csv, capsys):
    from bondgraph.cli.main import main

    rc = main(["estimate", "--model", "mass_spring_damper", "--data", str(msd_csv),
               "--params", "m,stiffness", "--quiet"])
    assert rc == 2
    assert "stiffness" in capsys.readouterr().err


def test_workers_give_identical_results(msd_record):
    """The criterion split over 2 processes returns exactly the in-process values."""
    from bondgraph.inference.estimate import Criterion

    m, t, u, y, _, truth = msd_record
    X = np.array([[2.5, 80.0, 2.0], [2.0, 60.0, 1.0], [3.0, 90.0, 3.0], [2.2, 70.0, np.nan],
                  [2.6, 85.0, 2.5]])
    from bondgraph.inference.options import Evaluation

    pb = problem(m, (t, u, y), P0=np.diag([1e-8, 1e-10]), x0=np.zeros(2))
    a = Criterion(pb, ["m", "k", "c"], m.theta0)
    b = Criterion(pb, ["m", "k", "c"], m.theta0, where=Evaluation(workers=2))
    fa, fb = a(X), b(X)
    b.close()
    assert np.array_equal(fa, fb) and np.isinf(fa[3])
    assert a.failures == b.failures and b.evaluations == 5


def test_options_validated_on_construction(msd_record):
    """A bad option fails where it is written, naming the option and its value."""
    with pytest.raises(OptionError, match="optimizer = 'cmaes'"):
        FitOptions(optimizer="cmaes")
    with pytest.raises(OptionError, match="particles"):
        FitOptions(particles=1)
    with pytest.raises(OptionError, match="resume"):
        FitOptions(resume=True)
    with pytest.raises(OptionError, match="workers"):
        FitOptions(workers=0)
    m, t, u, y, _, _ = msd_record
    with pytest.raises(OptionError, match="FitOptions"):
        estimate(problem(m, (t, u, y), P0=P0), ["m"], fit=dict(iterations=1))
    with pytest.raises(OptionError, match="Problem"):
        estimate(m, ["m"])
    # the options land in the result's settings as plain dicts
    r = estimate(problem(m, (t, u, y), P0=P0), ["k"],
                 fit=FitOptions(particles=4, iterations=1, progress=False, polish=False,
                                hessian=False, check_discretisation=False))
    assert r.settings["ukf"] == dict(alpha=1.0, beta=2.0, kappa=0.0, method="rk4", substeps=2,
                                     jacobian="mean", hold="zoh", backend=DEFAULT_BACKEND,
                                     refine=())
    assert r.settings["particles"] == 4 and r.evaluations == 4 * 2
    json.loads(r.to_json())


def test_initial_state_from_the_record(msd_record):
    """Without x0, the filter starts at the record's initial state
    (Experiment.initial_state: state columns, else the sidecar's x0), not at
    the model's X0; checked against ukf_nll run with that state."""
    from bondgraph.data.records import Experiment
    from bondgraph.inference.ukf import ukf_nll

    m, t, u, y, _, _ = msd_record
    exp = Experiment.from_arrays(t, model=m, u=u, y=y, meta={"name": "msd", "x0": {"p_mass": 0.3}})
    fit = FitOptions(particles=4, iterations=0, progress=False, polish=False, hessian=False,
                     check_discretisation=False)
    r = estimate(problem(m, exp, P0=P0), ["k"], fit=fit)
    x0 = m.state(p_mass=0.3)
    assert r.settings["x0"] == x0.tolist() and x0[0] != m.x0[0]
    want = ukf_nll(m, t, u, y, r.theta, x0, P0, options=UKF).nll[0]
    assert r.nll == pytest.approx(want, rel=1e-12)
    assert r.nll != pytest.approx(ukf_nll(m, t, u, y, r.theta, m.x0, P0, options=UKF).nll[0])


def test_curvatures_of_different_sizes_are_not_an_unidentified_direction():
    """A Hessian whose curvatures differ by 1e10 (a noise level fitted to
    1e-5 of its signal beside the parameters) with a correlation of -0.1 is
    positive definite: its bounds are its inverse (numpy); a correlation of
    1 - 1e-9 is a direction the data do not identify, whatever the scales."""
    H = np.array([[1e10, 1e4], [1e4, 1.0]])
    cr = cramer_rao(H, ["a", "b"], scale=np.array([10.0, 18.0]))
    assert cr["positive_definite"] and cr["warning"] is None
    np.testing.assert_allclose(cr["cov"], np.linalg.inv(H), rtol=1e-10)
    c = 1e5 * (1.0 - 1e-9)
    bad = cramer_rao(np.array([[1e10, c], [c, 1.0]]), ["a", "b"], scale=np.array([10.0, 18.0]))
    assert not bad["positive_definite"] and "not identified" in bad["warning"]


def test_bounds_of_the_others_when_a_parameter_sits_on_its_box():
    """estimate._on_box: a Hessian that is not positive definite because the
    NLL still falls beyond the box of the parameter on it (negative
    curvature read across the bound): the others' Cramér-Rao std are the
    inverse of their own block (hand computed: [[4, 1], [1, 2]]⁻¹ =
    [[2, -1], [-1, 4]] / 7), conditional on it held; the warning says so."""
    from bondgraph.inference.estimate import _on_box

    H = np.array([[4.0, 1.0, 0.0], [1.0, 2.0, 3.0], [0.0, 3.0, -1.0]])
    names = ["a", "b", "tau"]
    cr = cramer_rao(H, names, np.ones(3), conditional=True)
    assert not cr["positive_definite"] and np.isnan(cr["std"]).all()
    _on_box(cr, H, np.ones(3), names, ["tau"])
    np.testing.assert_allclose(cr["std"][:2], np.sqrt([2 / 7, 4 / 7]), rtol=1e-12)
    assert np.isnan(cr["std"][2]) and cr["conditional_on"] == ["tau"]
    assert cr["corr"][0, 1] == pytest.approx(-1 / np.sqrt(8), rel=1e-12)
    assert cr["warning"].startswith("Hessian of the NLL is not positive definite, and positive "
                                    "definite without tau on its bound")
    assert cr["warning"].endswith("conditional on tau held on its bound")
    # nobody on a box: nothing filled
    cr = cramer_rao(H, names, np.ones(3), conditional=True)
    _on_box(cr, H, np.ones(3), names, [])
    assert np.isnan(cr["std"]).all()
