"""Sensitivity and identifiability (bondgraph.sensitivity, and the forward
sensitivity equations of bondgraph.numerics.forward_sensitivity): forward
sensitivities against finite differences of scipy simulations, the
output-error information against the UKF's, a product-only parameter pair
flagged and one of them kept, Yao's ranking against Gram-Schmidt, Sobol'
indices against closed forms (Ishigami, linear), the CLI feeding
``bondgraph estimate --params recommended:...``, and the vehicle's stage-2
recommendation on the 60 s acceleration record checked with the NLL Hessian."""

import json
import warnings

import numpy as np
import pytest

from bondgraph.errors import ModelError
from bondgraph.core.graph import BondGraph
from bondgraph.numerics.model import Model
from bondgraph.numerics.forward_sensitivity import SolverOptions, output_sensitivities
from bondgraph.sensitivity.analysis import LocalOptions, analyse, recommended_params
from bondgraph.sensitivity.identifiability import (identifiability, orthogonal_ranking, recommend,
                                                   ukf_fisher)
from bondgraph.sensitivity.sobol import SobolOptions, sobol_indices
from bondgraph.errors import SensitivityError
from bondgraph.inference.options import UKFOptions
from bondgraph.inference.prior import PriorSpec
from bondgraph.inference.problem import NoiseSpec, make_problem
from bondgraph.numerics.simulate import simulate


@pytest.fixture(scope="module")
def msd():
    m = Model.load("mass_spring_damper")
    dt, N = 0.02, 300
    t = np.arange(N) * dt
    rng = np.random.default_rng(0)
    u = np.repeat(rng.normal(0.0, 20.0, N // 20), 20)[:, None]
    th = m.theta(m=2.5, k=80.0, c=2.0)
    x0 = np.array([0.3, 0.01])
    return m, t, u, th, x0


@pytest.mark.parametrize("hold", ["zoh", "linear"])
def test_forward_sensitivities_match_finite_differences(msd, hold):
    m, t, u, th, x0 = msd
    names = ["m", "k", "c"]
    s = output_sensitivities(m, t, u, th, x0, names,
                             solver=SolverOptions(method="BDF", rtol=1e-11, atol=1e-13,
                                                  hold=hold))
    assert s.dydtheta.shape == (t.size, 2, 3) and s.dxdtheta.shape == (t.size, 2, 3)
    ref = simulate(m, t, u, x0, th, rtol=1e-12, atol=1e-14, hold=hold).y
    np.testing.assert_allclose(s.y, ref, rtol=1e-7, atol=1e-9)
    for j, p in enumerate(names):
        i = m.param_index(p)
        h = 1e-4 * th[i]
        tp, tm = th.copy(), th.copy()
        tp[i] += h
        tm[i] -= h
        fd = (simulate(m, t, u, x0, tp, rtol=1e-12, atol=1e-14, hold=hold).y
              - simulate(m, t, u, x0, tm, rtol=1e-12, atol=1e-14, hold=hold).y) / (2 * h)
        rel = np.abs(s.dydtheta[:, :, j] - fd).max(axis=0) / np.abs(fd).max(axis=0)
        assert (rel < 1e-6).all(), (p, rel)


def test_output_error_information_matches_ukf_fisher(msd):
    """Without process noise and with a known initial state the UKF
    likelihood is the output-error likelihood: its Fisher information is
    Σ Jᵀ R⁻¹ J with J from the forward sensitivities."""
    m, t, u, th, x0 = msd
    names = ["m", "k", "c"]
    s = output_sensitivities(m, t, u, th, x0, names, solver=SolverOptions(hold="zoh"))
    y = s.y + np.random.default_rng(1).normal(size=s.y.shape) * m.meas_std(th)
    D = ukf_fisher(m, t, u, y, th, names, x0, np.diag([1e-12, 1e-14]),
                   UKFOptions(method="rk4", substeps=4))
    F_oe = s.information(m.meas_std(th)) / np.outer(s.scale, s.scale)
    np.testing.assert_allclose(D.F, F_oe, rtol=2e-3)


def _gain_product_model():
    """Mass with damper driven by a·b·F: a and b enter only as their product."""
    g = BondGraph("gain_product", "force a*b*F on a damped mass")
    F = g.input("F", "N")
    m_ = g.param("m", 1.0, "kg", (0.5, 2.0))
    c = g.param("c", 0.8, "N*s/m", (0.1, 3.0))
    a = g.param("a", 2.0, "", (0.5, 4.0))
    b = g.param("b", 1.5, "", (0.5, 4.0))
    v = g.one("v", domain="translation")
    g.connect(g.Se("F", a * b * F), v)
    g.connect(v, g.I("m", m_))
    g.connect(v, g.R("d", c))
    g.sensor("v", v.f, unit="m/s", noise_std=0.01)
    return Model.from_graph(g)


def test_product_parameters_flagged_and_one_kept():
    model = _gain_product_model()
    t = np.arange(400) * 0.02
    u = np.sign(np.sin(1.3 * t))[:, None]
    y = simulate(model, t, u, np.zeros(1), model.theta0, hold="zoh").y
    y = y + np.random.default_rng(0).normal(size=y.shape) * 0.01
    pb = make_problem(model, (t, u, y), prior=PriorSpec(x0=np.zeros(1), P0=np.diag([1e-8])),
                      ukf=UKFOptions(method="rk4"))
    rep = analyse(pb, ["a", "b", "c"])
    ident = rep.local["identifiability"]
    kinds = {(f["type"], tuple(sorted(f["params"]))) for f in ident["flags"]}
    assert ("product", ("a", "b")) in kinds
    assert not ident["full_rank"] and {"a", "b"} <= set(ident["unidentifiable"])
    # the forward sensitivities see the same structure
    assert any(f["type"] == "product" for f in rep.local["output_error"]["flags"])
    rec = rep.recommendation
    assert "c" in rec["estimate"]
    assert len({"a", "b"} & set(rec["estimate"])) == 1
    dropped = ({"a", "b"} - set(rec["estimate"])).pop()
    dec = {d["param"]: d for d in rec["decisions"]}[dropped]
    assert dec["decision"] == "fix" and "product" in dec["reason"]
    assert rec["check"]["full_rank"] and rec["check"]["max_rel_crb"] < 0.1
    # a ratio is flagged as a ratio
    F = np.array([[1.0, -1.0], [-1.0, 1.0]])
    assert identifiability(F, ["p", "q"])["flags"][0]["type"] == "ratio"


def test_orthogonal_ranking_is_yao_gram_schmidt():
    rng = np.random.default_rng(3)
    Z = rng.normal(size=(50, 5)) * [3.0, 1.0, 2.0, 0.5, 1.5]
    Z[:, 3] = Z[:, 0] + 0.01 * rng.normal(size=50)     # nearly collinear with column 0
    names = list("abcde")
    got = orthogonal_ranking(Z.T @ Z, names)
    # Yao et al. (2003): largest column, project out, repeat
    R, order, norms = Z.copy(), [], []
    left = list(range(5))
    while left:
        nrm = np.linalg.norm(R[:, left], axis=0)
        j = left[int(np.argmax(nrm))]
        order.append(names[j])
        norms.append(nrm.max())
        q = R[:, j] / np.linalg.norm(R[:, j])
        R = R - np.outer(q, q @ R)
        left.remove(j)
    assert [g[0] for g in got] == order
    np.testing.assert_allclose([g[1] for g in got], norms, rtol=1e-6)
    assert order[-1] in ("a", "d")
    rec = recommend(Z.T @ Z, names)
    assert len({"a", "d"} & set(rec["estimate"])) == 1


def test_sobol_ishigami_within_confidence():
    def ishigami(X, a=7.0, b=0.1):
        return np.sin(X[:, 0]) + a * np.sin(X[:, 1]) ** 2 + b * X[:, 2] ** 4 * np.sin(X[:, 0])

    r = sobol_indices(ishigami, ["x1", "x2", "x3"], [-np.pi] * 3, [np.pi] * 3,
                      SobolOptions(N=4096, seed=0, chunk=10000))
    assert r["evaluations"] == 4096 * 8
    d = r["indices"]["y"]
    S1 = np.array([0.3139, 0.4424, 0.0])
    ST = np.array([0.5576, 0.4424, 0.2437])
    assert (np.abs(d["S1"] - S1) <= d["S1_conf"]).all(), (d["S1"], d["S1_conf"])
    assert (np.abs(d["ST"] - ST) <= d["ST_conf"]).all(), (d["ST"], d["ST_conf"])
    assert abs(d["S2"][0, 2] - 0.2437) <= d["S2_conf"][0, 2]
    assert abs(d["S2"][0, 1]) <= d["S2_conf"][0, 1] and abs(d["S2"][1, 2]) <= d["S2_conf"][1, 2]


def test_sobol_linear_model_closed_form():
    a = np.array([1.0, 2.0, 0.5, 3.0])
    lo, hi = np.array([0.0, -1.0, 2.0, 0.0]), np.array([1.0, 1.0, 6.0, 0.5])
    var = a ** 2 * (hi - lo) ** 2 / 12.0
    exact = var / var.sum()
    r = sobol_indices(lambda X: np.column_stack([X @ a, 2 * X @ a + 1]), list("pqrs"), lo, hi,
                      SobolOptions(N=2048, seed=1), output_names=["y", "z"])
    for on in ("y", "z"):
        d = r["indices"][on]
        assert (np.abs(d["S1"] - exact) <= d["S1_conf"]).all(), (on, d["S1"], exact)
        assert (np.abs(d["ST"] - exact) <= d["ST_conf"]).all(), (on, d["ST"], exact)
        iu = np.triu_indices(4, 1)
        assert (np.abs(d["S2"][iu]) <= d["S2_conf"][iu] + 1e-12).all()


def test_errors(msd):
    m, t, u, th, x0 = msd
    with pytest.raises(ModelError, match="no parameter 'mass'"):
        output_sensitivities(m, t, u, th, x0, ["mass"])
    with pytest.raises(SensitivityError, match="twice"):
        output_sensitivities(m, t, u, th, x0, ["m", "m"])
    with pytest.raises(SensitivityError, match="no sensitivity file"):
        recommended_params("/nonexistent/sensitivity.json")
    with pytest.raises(SensitivityError, match="lower < upper"):
        sobol_indices(lambda X: X[:, 0], ["a", "b"], [0, 1], [1, 1], SobolOptions(N=8))
    with pytest.raises(SensitivityError, match="NLL transform"):
        SobolOptions(nll_transform="sqrt")


# ----------------------------------------------------------------------- CLI
@pytest.fixture()
def msd_csv(tmp_path, msd):
    from bondgraph.data.records import Experiment

    m, t, u, th, x0 = msd
    s = output_sensitivities(m, t, u, th, x0, ["m"], solver=SolverOptions(hold="zoh"))
    y = s.y + np.random.default_rng(2).normal(size=s.y.shape) * m.meas_std(th)
    exp = Experiment.from_arrays(t, model=m, u=u, y=y,
                                 meta={"name": "msd_synth", "x0": {"p_mass": 0.3, "q_spring": 0.01},
                                       "true_parameters": {"m": 2.5, "k": 80.0, "c": 2.0}})
    path = tmp_path / "msd.csv"
    exp.save(path)
    return path


def test_cli_writes_json_plots_and_feeds_estimate(tmp_path, msd_csv, capsys):
    from bondgraph.cli.main import main

    out = tmp_path / "sens"
    rc = main(["sensitivity", "--model", "mass_spring_damper", "--data", str(msd_csv),
               "--global", "16", "--at-truth", "--out", str(out), "--quiet", "--method", "rk4",
               "--p0-rel", "0.001"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "recommended" in text and "Sobol' indices of ln(1 + NLL - min)" in text
    d = json.loads((out / "sensitivity.json").read_text())
    assert d["params"] == ["m", "k", "c"]
    assert set(d["recommendation"]["estimate"]) == {"m", "k", "c"}
    assert d["recommendation"]["check"]["full_rank"]
    g = d["global"]
    assert g["evaluations"] == 16 * (2 * 3 + 2)
    assert g["nll_transform"].startswith("ln") and g["nll_max"] > g["nll_min"]
    assert set(g["indices"]["NLL"]) >= {"S1", "S1_conf", "ST", "ST_conf", "S2", "S2_conf"}
    for png in ("tornado.png", "heatmap_s2.png", "correlation.png", "sensitivities.png"):
        assert (out / png).stat().st_size > 1000, png
    assert recommended_params(out, "mass_spring_damper") == d["recommendation"]["estimate"]
    est = tmp_path / "est"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = main(["estimate", "--model", "mass_spring_damper", "--data", str(msd_csv),
                   "--params", f"recommended:{out / 'sensitivity.json'}", "--particles", "6",
                   "--iterations", "2", "--no-polish", "--no-plots", "--quiet", "--out", str(est),
                   "--method", "rk4"])
    assert rc == 0
    r = json.loads((est / "result.json").read_text())
    # the recommended parameters, and (--noise auto, the record declares no
    # noise_std) the two sensors' noise stds
    assert r["params"] == d["recommendation"]["estimate"] + ["noise.x", "noise.v"]


def test_cli_unknown_parameter(msd_csv, capsys):
    from bondgraph.cli.main import main

    rc = main(["sensitivity", "--model", "mass_spring_damper", "--data", str(msd_csv),
               "--params", "m,spring", "--quiet", "--no-plots"])
    assert rc == 2
    assert "no parameter 'spring'" in capsys.readouterr().err


# ------------------------------------------------------------------- vehicle
#: stage-2 candidates of the vehicle (bench/estimation.py PARAMS)
STAGE2 = ["T_pk", "k_fw", "k_h", "w_eng", "mu_cl", "c_cl", "k_slip", "J_e"]


@pytest.mark.slow
def test_vehicle_acceleration_stage2_recommendation_identifiable():
    """60 s acceleration record (throttle steps 0.3 ... 1.0, High range, 40 Hz):
    the recommended stage-2 set has a full-rank information and every relative
    Cramér-Rao bound under 10 %; checked independently with the central-
    difference Hessian of the NLL (observed information) at the truth."""
    from bondgraph.inference.estimate import Criterion, cramer_rao, hessian_batched
    from bondgraph.data.experiments import run_experiment
    from bondgraph.inference.ukf import default_P0

    model = Model.load("vehicle_full")
    exp = run_experiment("vehicle_throttle_steps_high")
    assert exp.t[-1] - exp.t[0] >= 59.9
    truth = {k: v for k, v in exp.meta["true_parameters"].items() if k in model.params}
    # the vehicle's consistent initial state at the first measured speed
    # (engine at idle equilibrium, wheels rolling): the application's choice
    from vehicle_graphs.analysis import initial_state as vehicle_initial_state

    v = exp["v_gnss"]
    x0v = model.state(vehicle_initial_state(model, model.theta(truth),
                                            v=float(v[np.isfinite(v)][0])))
    pb = make_problem(model, exp, prior=PriorSpec(rel=0.01, scale="magnitude", x0=x0v),
                      noise=NoiseSpec("model"), fixed=truth)
    rep = analyse(pb, STAGE2, local=LocalOptions(sensitivities=False))
    rec = rep.recommendation
    est = rec["estimate"]
    assert len(est) >= 5
    assert rec["check"]["full_rank"]
    assert rec["check"]["max_rel_crb"] < 0.10
    assert rec["check"]["max_abs_corr"] <= 0.95
    for d in rec["decisions"]:
        assert d["reason"]
    # independent: Hessian of the NLL over the recommended set
    th = model.theta(truth)
    x0 = np.asarray(rep.settings["x0"])
    crit = Criterion(make_problem(model, exp, prior=PriorSpec(x0=x0, P0=default_P0(model, x0,
                                                                                0.01))),
                     est, th)
    xv = th[model.param_indices(est)]
    std = np.array([rec["check"]["rel_crb"][i] * abs(xv[i]) for i in range(len(est))])
    H, _, _ = hessian_batched(crit, xv, 0.2 * std)
    cr = cramer_rao(H, est, np.abs(xv))       # positive definiteness in relative coordinates
    assert cr["positive_definite"], cr["warning"]
    rel = cr["std"] / np.abs(xv)
    assert (rel < 0.10).all(), dict(zip(est, rel))


@pytest.mark.slow
def test_vehicle_coastdown_stage1():
    from bondgraph.data.experiments import run_experiment

    model = Model.load("vehicle_coastdown")
    exp = run_experiment("vehicle_coastdown")
    pb = make_problem(model, exp, prior=PriorSpec(rel=0.01, scale="magnitude"),
                      noise=NoiseSpec("model"))
    rep = analyse(pb, ["f_r", "C_dA", "r_dyn", "theta_off"])
    assert rep.settings["x0_rule"] == "record state columns / sidecar x0"
    assert set(rep.recommendation["estimate"]) == {"f_r", "C_dA", "r_dyn", "theta_off"}
    assert rep.recommendation["check"]["max_rel_crb"] < 0.10
    oe = rep.local["output_error"]
    assert oe["full_rank"] and np.asarray(oe["rms_scaled"]).shape == (4, model.n_y)


def test_solver_options_validated_on_construction(msd):
    from bondgraph.errors import OptionError

    with pytest.raises(OptionError, match=r"SolverOptions\.method = 'Euler' is not one of"):
        SolverOptions(method="Euler")
    with pytest.raises(OptionError, match=r"SolverOptions\.rtol must be a finite number > 0"):
        SolverOptions(rtol=0.0)
    with pytest.raises(OptionError, match=r"SolverOptions\.hold = 'mean' is not one of"):
        SolverOptions(hold="mean")
    with pytest.raises(OptionError, match=r"SolverOptions\.max_step must be a number > 0"):
        SolverOptions(max_step=-1.0)
    m, t, u, th, x0 = msd
    with pytest.raises(OptionError, match="solver must be a SolverOptions, got dict"):
        output_sensitivities(m, t, u, th, x0, ["m"], solver={"hold": "zoh"})


def test_a_ridge_is_named_with_its_relative_changes_and_the_fixed_parameter():
    """Relative sensitivities s1, s2 and s3 = -(s1 + s2) + 1e-4 noise: the
    relative changes (+1, +1, +1) leave the outputs unchanged to 1e-4, so
    the relative information's weakest eigenvector is (1, 1, 1) (exactly,
    up to the noise) and the collinearity index is far above 20. The
    recommendation fixes one of the three (or two: its subset test), which
    then sets the others' scale; two independent sensitivities give
    no ridge."""
    from bondgraph.sensitivity.identifiability import RIDGE_GAMMA, ridge_line

    rng = np.random.default_rng(5)
    S = rng.normal(size=(200, 3))
    S[:, 2] = -(S[:, 0] + S[:, 1]) + 1e-4 * rng.normal(size=200)
    scale = np.array([2.0, 50.0, 1.5])
    F = (S / scale).T @ (S / scale)             # model units: dθ_j = s_j dθ̃_j
    rec = recommend(F, ["m", "k", "c"], scale)
    r = rec["ridge"]
    assert r is not None and r["collinearity_index"] > RIDGE_GAMMA
    assert r["params"] == ["m", "k", "c"]
    for n in ("m", "k", "c"):
        assert r["direction"][n] == pytest.approx(1.0, abs=1e-3)
    assert rec["fix"] and r["fixed"] == [n for n in r["params"] if n in rec["fix"]]
    line = ridge_line(r)
    assert "m +1.00, k +1.00, c +1.00" in line and f"fixing {', '.join(r['fixed'])}" in line
    assert recommend(F[:2, :2], ["m", "k"], scale[:2])["ridge"] is None


def test_the_correlations_of_a_ridge_are_one_flag_line():
    """The pairwise |corr| > 0.95 of the ridge's members in one line after
    it (a k-way scale symmetry gives k(k-1)/2 pairs); a correlation of a
    parameter off the ridge keeps its own line."""
    from bondgraph.sensitivity.analysis import flag_lines

    fl = [{"type": "correlated", "params": ["k1", "k2"], "value": -1.0,
           "message": "corr(k1, k2) = -1.000 (|corr| > 0.95)"},
          {"type": "correlated", "params": ["k1", "k4"], "value": 0.994,
           "message": "corr(k1, k4) = +0.994 (|corr| > 0.95)"},
          {"type": "correlated", "params": ["k2", "k4"], "value": -0.996,
           "message": "corr(k2, k4) = -0.996 (|corr| > 0.95)"},
          {"type": "correlated", "params": ["k3", "w"], "value": 0.97,
           "message": "corr(k3, w) = +0.970 (|corr| > 0.95)"},
          {"type": "crb", "params": ["k4"], "value": 1.0, "message": "k4: relative CRB 100%"}]
    ridge = {"params": ["k4", "k1", "k2"]}
    assert flag_lines(fl, ridge) == [
        "flag: corr(k3, w) = +0.970 (|corr| > 0.95)",
        "flag: 3 pairwise correlations among k4, k1, k2 with |corr| 0.994 to 1.000 (the ridge "
        "above)"]
    assert flag_lines(fl) == [f"flag: {f['message']}" for f in fl[:4]]


def _quarter_car() -> BondGraph:
    """Road velocity into the tyre spring, unsprung and sprung masses, the
    suspension spring and damper; body acceleration and deflection
    measured: no force or mass reference."""
    g = BondGraph("qcar_ridge", "quarter-car")
    ms = g.param("ms", 280.0, "kg", (100.0, 600.0), "sprung mass")
    mu = g.param("mu", 35.0, "kg", (10.0, 100.0), "unsprung mass")
    ks = g.param("ks", 1.8e4, "N/m", (3e3, 6e4), "suspension stiffness")
    kt = g.param("kt", 1.6e5, "N/m", (5e4, 5e5), "tyre stiffness")
    cs = g.param("cs", 1200.0, "N*s/m", (100.0, 5000.0), "suspension damping")
    vr = g.input("vr", "m/s", 0.0, "road velocity")
    tyre, wheel = g.zero("tyre", domain="translation"), g.one("wheel", domain="translation")
    susp, rel = g.zero("susp", domain="translation"), g.one("rel", domain="translation")
    body = g.one("body", domain="translation")
    g.connect(g.Sf("road", vr), tyre)
    g.connect(tyre, g.C("tyre_k", 1 / kt))
    g.connect(tyre, wheel)
    g.connect(wheel, g.I("mu_m", mu))
    g.connect(wheel, susp)
    g.connect(susp, body)
    g.connect(body, g.I("ms_m", ms))
    g.connect(susp, rel)
    g.connect(rel, g.C("spring", 1 / ks))
    g.connect(rel, g.R("damper", cs))
    g.sensor("a_body", g.element("ms_m").e / ms, unit="m/s^2", noise_std=0.05)
    g.sensor("defl", g.element("spring").q, unit="m", noise_std=0.0005)
    return g


def test_the_quarter_cars_scale_symmetry_is_named_whole():
    """Scaling both masses, both stiffnesses and the damping by one factor
    leaves the body acceleration F/ms and the deflection unchanged (the
    road drives a velocity): the sensitivity analysis names all five on
    one ridge, each with a relative change of +1 (within 0.02; the
    initial-state prior in momenta breaks the symmetry slightly), and the
    parameter the recommendation fixes is on it."""
    m = Model.from_graph(_quarter_car())
    t = np.arange(800) * 0.005
    rng = np.random.default_rng(2)
    f = np.arange(0.5, 12.0, 0.5)
    ph = rng.uniform(0, 2 * np.pi, f.size)
    vr = (0.08 / np.sqrt(1 + (f / 2) ** 2) * np.sin(2 * np.pi * f * t[:, None] + ph)).sum(1)
    sim = simulate(m, t, vr[:, None], np.zeros(m.n_x), m.theta0, method="LSODA",
                   rtol=1e-9, atol=1e-12)
    y = sim.y + rng.normal(size=sim.y.shape) * [0.05, 0.0005]
    pb = make_problem(m, (t, vr[:, None], y), prior=PriorSpec(x0=np.zeros(m.n_x)),
                      ukf=UKFOptions(method="rk4", substeps=2, hold="linear"))
    rep = analyse(pb, ["ms", "mu", "ks", "kt", "cs"])
    r = rep.recommendation["ridge"]
    assert r is not None and sorted(r["params"]) == ["cs", "ks", "kt", "ms", "mu"]
    for n in r["params"]:
        assert r["direction"][n] == pytest.approx(1.0, abs=0.02)
    assert r["fixed"] and set(r["fixed"]) == set(rep.recommendation["fix"])
    assert "ridge: the record does not identify" in rep.table()


def test_an_unbounded_box_is_no_scale_of_a_nonzero_value():
    """analysis_scale: a force offset of 0.76 in the effect library's box
    (-1e9, 1e9) is scaled by 0.76, not by the box's width 2e9 (its
    sensitivity then 1e9 times its own outranked every physical parameter
    on the EMPS pulses run); at exactly 0 the width stays the scale, and a
    value nearly 0 beside a box that states a scale takes the box's width
    (parameter_scale)."""
    from bondgraph.core.graph import BondGraph
    from bondgraph.numerics.model import Model
    from bondgraph.sensitivity.analysis import analysis_scale

    g = BondGraph("scales", "mass on friction with an offset and a bias")
    u = g.input("u", "N", 0.0, "force")
    M = g.param("M", 2.0, "kg", (0.1, 10.0), "mass")
    F0 = g.param("F0", 0.76, "N", (-1e9, 1e9), "force offset")
    b = g.param("b", 1e-12, "m/s", (-1.0, 1.0), "sensor bias")
    v = g.one("v")
    g.connect(g.Se("drive", u), v)
    g.connect(g.Se("offset", F0), v)
    g.connect(v, g.I("mass", M))
    g.connect(v, g.R("friction", 3.0))
    g.sensor("vm", v.f + b, unit="m/s", noise_std=0.01)
    m = Model.from_graph(g)
    th = m.theta({})
    np.testing.assert_allclose(analysis_scale(m, ["M", "F0", "b"], th), [2.0, 0.76, 2.0])
    th0 = m.theta({"F0": 0.0})
    np.testing.assert_allclose(analysis_scale(m, ["F0"], th0), [2e9])


def test_table_columns_fit_long_parameter_names():
    """An effect's parameter (``cubic_stiffness.spring.k3``, 25 characters)
    does not run into the decision column: every row's decision starts where
    the header's does."""
    from bondgraph.sensitivity.analysis import SensitivityReport

    names = ["m", "cubic_stiffness.spring.k3", "sensor_poly3.V2.c2"]
    decisions = [dict(rank=i + 1, param=n, decision="estimate", rel_crb=0.01 * (i + 1),
                      reason="by hand") for i, n in enumerate(names)]
    rep = SensitivityReport(model="g", experiment="rec", params=names, theta={}, scale=[],
                            local={}, recommendation=dict(estimate=names, decisions=decisions))
    lines = rep.table().splitlines()
    col = lines[1].index("decision")
    rows = [ln for ln in lines if ln.strip().startswith(("1 ", "2 ", "3 "))]
    assert len(rows) == 3
    for ln, n in zip(rows, names):
        assert ln[col:col + 8] == "estimate" and ln[:col].split()[1] == n
