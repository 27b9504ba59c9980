"""The filter models against the full vehicle in the regime they claim to
cover, and the suspension-approximation bias of the coast-down estimates
(issue 3: "show the bias with and without it")."""

import numpy as np
import pytest

from bondgraph.data.experiments import get_experiment, run_experiment, sample_times
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate
from bondgraph.inference.options import UKFOptions
from bondgraph.inference.ukf import ukf_nll
from vehicle_graphs import build_vehicle
from vehicle_graphs.analysis import PitchModel, coastdown_road_load, initial_state


@pytest.fixture(scope="module")
def coast_spec():
    return get_experiment("vehicle_coastdown")


@pytest.fixture(scope="module")
def coast_record(coast_spec):
    return run_experiment(coast_spec)


def _sim(name_or_model, spec, v0=22.0):
    m = Model.load(name_or_model) if isinstance(name_or_model, str) else name_or_model
    th = m.theta({k: v for k, v in spec.params.items() if k in m.params})
    x0 = initial_state(m, th, v=v0)
    t = sample_times(spec)
    return m, simulate(m, t, x0=x0, theta=th, rtol=1e-9, atol=1e-10)


def test_coastdown_model_agrees_with_full_vehicle_in_neutral(coast_spec):
    """Coast-down in neutral from 22 m/s: the reduced model (lumped wheels,
    no power train, 5 states) and the full vehicle in neutral (engine
    idling, CVT, secondary, per-axle wheels and loads, 10 states) give the
    same outputs to a small fraction of the sensor noise."""
    full_n = Model.from_graph(build_vehicle("vehicle_full_neutral", gear="N"))
    m_cd, r_cd = _sim("vehicle_coastdown", coast_spec)
    _, r_full = _sim(full_n, coast_spec)
    std = m_cd.meas_std(m_cd.theta0)
    for j, name in enumerate(m_cd.outputs):
        err = np.abs(r_cd.output(name) - r_full.output(name)).max()
        assert err < 0.2 * std[j], (name, err, std[j])
    # the speed falls from 22 to below 5 m/s: the whole coast-down regime is covered
    v = r_cd.output("v_gnss")
    assert v[0] == pytest.approx(22.0) and v[-1] < 5.0
    # and the engine of the full model idles meanwhile (decoupled in neutral)
    we = r_full.output("w_e") * 60 / (2 * np.pi)
    assert np.all(np.abs(we - we[0]) < 5.0) and 1150 < we[0] < 1250


def test_coastdown_model_agrees_with_its_truth_model(coast_spec):
    _, r_cd = _sim("vehicle_coastdown", coast_spec)
    m_t, r_t = _sim("vehicle_coastdown_truth", coast_spec)
    std = m_t.meas_std(m_t.theta0)
    err = np.abs(r_cd.y - r_t.y).max(axis=0)
    assert np.all(err < 0.2 * std), dict(zip(m_t.outputs, err / std))


def test_rigid_model_misses_the_suspension_pitch(coast_spec):
    """What the rigid approximation neglects: the nose-down pitch under the
    coast-down deceleration, 0.1-0.25 deg, i.e. more than the pitch sensor's
    noise (0.1 deg) at the start of the run."""
    _, r_t = _sim("vehicle_coastdown_truth", coast_spec)
    _, r_r = _sim("vehicle_coastdown_rigid", coast_spec)
    d = r_t.output("pitch") - r_r.output("pitch")
    assert np.degrees(d[0]) == pytest.approx(-0.21, abs=0.03)
    assert np.degrees(d[-1]) == pytest.approx(-0.11, abs=0.03)
    # the speed itself is unaffected (the pitch only enters through the sensor)
    assert np.abs(r_t.output("v_gnss") - r_r.output("v_gnss")).max() < 0.01


@pytest.mark.parametrize("suspension, biased", [("rigid", True), ("quasi_static", False)])
def test_least_squares_suspension_bias(coast_record, suspension, biased):
    """Road-load least squares on the noisy coast-down record: reading the
    pitch as grade (rigid) inflates f_r and C_dA by ~7 % (the predicted
    m^2 g h_cg / (k_theta m_eff)); removing the quasi-static pitch recovers
    them to 1 %."""
    P = coast_record.meta["true_parameters"]
    c = coast_record.columns
    est = coastdown_road_load(coast_record.t, c["v_gnss"], c["pitch"], m=P["m"], J_w=P["J_w"],
                              r_dyn=P["r_dyn"], theta_off=P["theta_off"], g=P["g"],
                              pitch_model=PitchModel(suspension, h_cg=P["h_cg"],
                                                     k_theta=P["k_theta"]))
    e_fr = est["f_r"] / P["f_r"] - 1
    e_cd = est["C_dA"] / P["C_dA"] - 1
    if biased:
        m_eff = P["m"] + 4 * P["J_w"] / P["r_dyn"] ** 2
        predicted = P["m"] ** 2 * P["g"] * P["h_cg"] / (P["k_theta"] * m_eff)
        assert predicted == pytest.approx(0.069, abs=0.002)
        assert e_fr == pytest.approx(predicted, abs=0.015)
        assert e_cd == pytest.approx(predicted, abs=0.015)
    else:
        assert abs(e_fr) < 0.01 and abs(e_cd) < 0.01, (e_fr, e_cd)


def _ukf_road_load(model_name, spec, record):
    """Maximum-likelihood f_r, C_dA by the UKF: NLL on a 5 x 5 grid
    (+-15-20 %), minimum of the fitted quadratic. Returns relative errors and
    the Hessian of the NLL in relative units."""
    m = Model.load(model_name)
    th0 = m.theta({k: v for k, v in spec.params.items() if k in m.params})
    fr0, cd0 = th0[m.param_index("f_r")], th0[m.param_index("C_dA")]
    a, b = np.meshgrid(np.linspace(-0.15, 0.2, 5), np.linspace(-0.15, 0.2, 5))
    a, b = a.ravel(), b.ravel()
    TH = np.tile(th0, (a.size, 1))
    TH[:, m.param_index("f_r")] = fr0 * (1 + a)
    TH[:, m.param_index("C_dA")] = cd0 * (1 + b)
    x0 = np.array([initial_state(m, th0, v=22.0)[s] for s in m.states])
    P0 = np.diag(np.maximum((0.02 * np.abs(x0)) ** 2, 1e-6))
    res = ukf_nll(m, record.t, record.inputs_for(m), record.outputs_for(m), TH, x0, P0,
                  options=UKFOptions(method="ros2", substeps=1))
    assert np.all(np.isfinite(res.nll)), res
    A = np.column_stack([np.ones_like(a), a, b, a * a, a * b, b * b])
    c, *_ = np.linalg.lstsq(A, res.nll, rcond=None)
    H = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    opt = np.linalg.solve(H, -c[1:3])
    return opt, H


def test_ukf_maximum_likelihood_suspension_bias(coast_spec, coast_record):
    """The same with the filter models themselves (batched UKF, ROS2): the
    rigid coast-down model's maximum-likelihood f_r and C_dA are biased by
    5-9 %, beyond five Cramer-Rao standard deviations (< 1 % each); the model
    with the dynamic pitch is unbiased to 1 %."""
    ok, H_ok = _ukf_road_load("vehicle_coastdown", coast_spec, coast_record)
    rigid, H_r = _ukf_road_load("vehicle_coastdown_rigid", coast_spec, coast_record)
    crb = np.sqrt(np.diag(np.linalg.inv(H_ok)))
    assert np.all(np.linalg.eigvalsh(H_ok) > 0) and np.all(crb < 0.01)
    assert np.all(np.abs(ok) < 0.01), ok
    assert np.all((rigid > 0.05) & (rigid < 0.09)), rigid
    assert np.all(np.abs(rigid) > 5 * crb), (rigid, crb)


@pytest.mark.parametrize("name", ["vehicle_full_throttle_high", "vehicle_braking"])
def test_full_filter_model_is_consistent_in_the_ukf(name):
    """At the true parameters the batched UKF (ROS2, one step per sample)
    runs through the driving records with the full filter model: finite
    NLL, and a mean normalised innovation squared near n_y (7), i.e. the
    declared sensor noise and the model explain the record."""
    spec = get_experiment(name)
    exp = run_experiment(spec)
    m = Model.load(spec.model)
    th = m.theta(spec.params)
    x0 = m.state(spec.x0)
    P0 = np.diag(np.maximum((0.01 * np.abs(x0)) ** 2, 1e-8))
    r = ukf_nll(m, exp.t, exp.inputs_for(m), exp.outputs_for(m), th, x0, P0,
                options=UKFOptions(method="ros2", substeps=1), store=True)
    assert np.isfinite(r.nll).all(), r
    nis = float(np.nanmean(r.nis))
    assert 0.8 * m.n_y < nis < 1.2 * m.n_y, nis
