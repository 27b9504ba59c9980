"""Plausibility of the assembled vehicle (issue 3, "Checks"): clutch
engagement speed, CVT upshift, top speed, coast-down deceleration, energy
lost in a coast-down = work of the resistances, braking, hill climb and
stiffness. The documented ranges and their sources are in docs/vehicle.md
("Plausibility checks")."""

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph.data.experiments import get_experiment, sample_times
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate, stiffness_report
from vehicle_graphs.analysis import initial_state
from vehicle_graphs.params import DR_DX, RPM
from vehicle_graphs.subsystems import Numerics


def _run_experiment(name):
    """A registered vehicle experiment simulated with BDF at its true
    parameters: (model, theta, SimResult)."""
    spec = get_experiment(name)
    model = Model.load(spec.model)
    th = model.theta(spec.params)
    res = simulate(model, sample_times(spec), u=spec.inputs, x0=spec.x0, theta=th,
                   rtol=1e-7, atol=1e-9)
    return model, th, res


NUM = Numerics()

#: documented plausible ranges (docs/vehicle.md, "Plausibility checks")
TOP_SPEED_HIGH = (18.0, 27.0)   # m/s: Ranger-class claims 40-60 mph
TOP_SPEED_LOW = (10.0, 16.0)    # m/s
DECEL_20 = (0.33, 0.65)         # m/s^2 at 20 m/s: f_r 0.01-0.02, C_dA 1.2-2.5
DECEL_10 = (0.15, 0.32)         # m/s^2 at 10 m/s


def _ratio(model, x, theta):
    """CVT ratio from the sheave state (the documented map)."""
    P = dict(zip(model.params, theta))
    s = x[:, model.state_index("cvt.q_springs")] / P["x_max"]
    r = lambda z: 0.5 * (z + np.sqrt(z * z + NUM.s_delta**2))  # noqa: E731
    return P["i_max"] - (P["i_max"] - P["i_min"]) * (r(s) - r(s - 1))


# ------------------------------------------------------------------ clutch
def test_clutch_capacity_engages_between_1200_and_1400_rpm():
    """Clutch torque at full slip (vehicle at rest) versus engine speed:
    negligible at 1200 rpm, crosses 1 N m between 1200 and 1400 rpm, and
    grows with the square of the engine speed above."""
    model = Model.load("vehicle_full")
    th = model.theta0
    P = dict(zip(model.params, th))
    x0 = initial_state(model, th)            # sheave at its low-ratio stop
    rpm = np.linspace(1000, 2500, 301)
    X = np.tile(np.array([x0[s] for s in model.states]), (rpm.size, 1))
    X[:, model.state_index("engine.p_J")] = P["J_e"] * rpm * RPM
    F = model.f(X, np.zeros((rpm.size, 2)), th)
    # secondary at rest, shaft untwisted: dp_s/dt = i_cvt T_cl
    T_cl = F[:, model.state_index("cvt.p_J_s")] / _ratio(model, X, th)
    assert T_cl[rpm == 1200][0] < 0.05
    engage = rpm[np.argmax(T_cl > 1.0)]
    assert 1200 <= engage <= 1400, engage
    assert np.all(np.diff(T_cl) > 0)
    # capacity = mu_cl r_p(x_p) (k_fw (w_e^2 - w_eng^2) - k_p x_p) well above engagement
    w = 2200 * RPM
    xp = x0["cvt.q_springs"]
    assert -1e-3 < xp < 0  # resting on the low-ratio stop
    expected = (P["mu_cl"] * (P["r_p0"] + DR_DX * xp)
                * (P["k_fw"] * (w**2 - P["w_eng"] ** 2) - P["k_p"] * xp))
    got = T_cl[np.argmin(abs(rpm - 2200))]
    assert got == pytest.approx(expected * math.tanh(w / (2 + expected / P["c_cl"])),
                                rel=2e-3)


def test_vehicle_starts_to_roll_between_1200_and_1400_rpm():
    """A slow throttle ramp from idle in High range: the vehicle starts to
    roll (0.05 m/s) while the engine passes 1200-1400 rpm."""
    model = Model.load("vehicle_full")
    th = model.theta0
    t = np.arange(0, 12.0, 0.025)
    x0 = initial_state(model, th)
    res = simulate(model, t, u={"throttle": lambda tt: np.clip((tt - 1.0) / 40.0, 0, 1)},
                   x0=x0, theta=th, rtol=1e-7, atol=1e-9)
    v, we = res.output("v_gnss"), res.output("w_e") / RPM
    assert we[0] == pytest.approx(1207, abs=10)  # idle (governor set 1220 rpm, droop)
    k = np.argmax(v > 0.05)
    assert k > 0, "the vehicle never moved"
    assert 1200 <= we[k] <= 1400, we[k]


# --------------------------------------------------------------------- CVT
@pytest.fixture(scope="module")
def full_throttle():
    return _run_experiment("vehicle_full_throttle_high")


def test_cvt_upshifts_as_speed_rises(full_throttle):
    model, th, res = full_throttle
    v = res.output("v_gnss")
    i_cvt = _ratio(model, res.x, th)
    acc = (res.t > 2.5) & (res.t < 25.0)          # full throttle, clutch locked
    assert i_cvt[res.t < 2.0].min() > 2.95           # launch at the low-ratio stop
    vv, ii = v[acc], i_cvt[acc]
    assert np.all(np.diff(vv) > 0)
    # (at the low-ratio stop the ratio may breathe by 1e-4 with the stop's compliance)
    assert np.all(np.diff(ii) <= 1e-4), "ratio rose while the vehicle accelerated"
    assert np.interp(5.0, vv, ii) > np.interp(10.0, vv, ii) > np.interp(15.0, vv, ii)
    assert ii[-1] == pytest.approx(0.7, abs=0.03)  # overdrive stop reached
    # the measured speed ratio w_e / w_s follows (plus clutch/belt creep of a few %)
    ws = res.output("w_s")
    locked = acc & (v > 5.0)
    creep = res.output("w_e")[locked] / (i_cvt[locked] * ws[locked]) - 1
    assert np.all((creep > 0) & (creep < 0.06)), creep
    # engine speed during the full-throttle shift: 3200-4000 rpm (flyweight design)
    shifting = acc & (i_cvt < 2.8) & (i_cvt > 0.75)
    we = res.output("w_e")[shifting] / RPM
    assert 3200 < we.min() and we.max() < 4000, (we.min(), we.max())


def test_full_throttle_stiffness_allows_rk4_at_20_substeps(full_throttle):
    model, th, res = full_throttle
    rep, table = stiffness_report(model, res, every=2)
    assert rep["rk4_substeps_needed"] <= 20, table
    assert rep["max_abs_re"] < 2200


def test_top_speed_in_documented_range():
    for name, rng_ in (("vehicle_full", TOP_SPEED_HIGH), ("vehicle_full_low", TOP_SPEED_LOW)):
        model = Model.load(name)
        th = model.theta0
        t = np.arange(0, 150.0, 0.5)
        res = simulate(model, t, u={"throttle": 1.0}, x0=initial_state(model, th), theta=th,
                       rtol=1e-6, atol=1e-8)
        v = res.output("v_gnss")
        assert rng_[0] <= v[-1] <= rng_[1], (name, v[-1])
        assert abs(v[-1] - v[-11]) < 0.02, "not yet at top speed"


# -------------------------------------------------------------- coast-down
@pytest.fixture(scope="module")
def coast():
    model = Model.load("vehicle_coastdown_truth")
    th = model.theta0
    x0 = np.array([initial_state(model, th, v=22.0)[s] for s in model.states])
    return model, th, x0


def test_coastdown_deceleration_in_documented_range(coast):
    model, th, x0 = coast
    t = np.arange(0, 50.0, 0.025)
    res = simulate(model, t, x0=x0, theta=th, rtol=1e-8, atol=1e-10)
    v = res.output("v_gnss")
    a = -np.gradient(v, t)
    for v_at, (lo, hi) in ((20.0, DECEL_20), (10.0, DECEL_10)):
        k = np.argmin(abs(v - v_at))
        assert lo <= a[k] <= hi, (v_at, a[k])
    # and it is the road-load law: (f_r m g + 1/2 rho C_dA v^2) / m_eff
    P = dict(zip(model.params, th))
    m_eff = P["m"] + 4 * P["J_w"] / P["r_dyn"] ** 2
    k = np.argmin(abs(v - 15.0))
    expect = (P["f_r"] * P["m"] * P["g"] + 0.6 * P["C_dA"] * v[k] ** 2) / m_eff
    assert a[k] == pytest.approx(expect, rel=0.01)


def test_coastdown_energy_lost_equals_work_of_resistances(coast):
    """Integrate dx/dt together with W_R = int P_dissipated dt and
    W_S = int P_sources dt (scipy Radau, tight tolerances): the stored energy
    lost, H(0) - H(T), equals W_R - W_S; and the body and wheel kinetic energy
    lost equals the work of rolling resistance and drag to 1 %."""
    model, th, x0 = coast
    u = np.zeros(model.n_u)
    n = model.n_x

    def rhs(t, z):
        x = z[:n]
        return np.concatenate([model.f(x, u, th), [model.power_dissipated(x, u, th),
                                                   model.power_sources(x, u, th)]])

    T = 40.0
    sol = solve_ivp(rhs, (0, T), np.concatenate([x0, [0.0, 0.0]]), method="Radau",
                    rtol=1e-11, atol=1e-9, dense_output=True)
    assert sol.success
    xT, W_R, W_S = sol.y[:n, -1], sol.y[n, -1], sol.y[n + 1, -1]
    lost = model.energy(x0, u, th) - model.energy(xT, u, th)
    assert lost > 1e5  # ~ 1/2 m_eff (22^2 - 10^2) J
    assert lost == pytest.approx(W_R - W_S, rel=1e-8)
    # physical reading: rolling resistance and aerodynamic drag do that work
    P = dict(zip(model.params, th))
    tt = np.linspace(0, T, 8001)
    Z = sol.sol(tt)
    v = Z[model.state_index("body.p_m")] / P["m"]
    W_phys = np.trapezoid(P["f_r"] * P["m"] * P["g"] * v + 0.6 * P["C_dA"] * v**3, tt)
    assert W_R == pytest.approx(W_phys, rel=0.01)


# ---------------------------------------------------------- braking, hill
def test_braking_deceleration_and_stop():
    model, th, res = _run_experiment("vehicle_braking")
    v, t = res.output("v_gnss"), res.t
    assert v.max() > 10.0
    P = dict(zip(model.params, th))
    # brake torque 4 x 0.4 T_bmax at the wheels, plus road load
    sel = (t > 13.6) & (v > 3.0)
    a = -np.gradient(v, t)[sel]
    m_eff = P["m"] + 4 * P["J_w"] / P["r_dyn"] ** 2
    a_brake = 4 * 0.4 * P["T_bmax"] / P["r_dyn"] / m_eff
    assert np.median(a) == pytest.approx(a_brake, rel=0.15)
    assert abs(v[(t > 20) & (t < 24)]).max() < 0.05  # stopped (tanh brake creeps < 5 cm/s)
    rep, table = stiffness_report(model, res, every=2)
    assert rep["rk4_substeps_needed"] <= 20, table


def test_hill_climb_low_range():
    model, th, res = _run_experiment("vehicle_hill_climb")
    v = res.output("v_gnss")
    # held by the brake: the smooth (tanh) brake lets it creep back at ~0.1 m/s
    assert v[res.t < 1.9].min() > -0.15
    assert v[-1] > 5.0
    # the pitch sensor reads the grade (8.5 deg) plus squat and the offset
    P = dict(zip(model.params, th))
    pitch0 = res.output("pitch")[0]
    squat = P["h_cg"] * P["m"] * P["g"] * math.sin(math.atan(0.15)) / P["k_theta"]
    assert pitch0 == pytest.approx(math.atan(0.15) + squat + P["theta_off"], abs=2e-4)


def test_rk4_with_16_substeps_tracks_bdf_within_sensor_noise():
    """Fixed-step RK4 (what the UKF uses) at 16 sub-steps of 25 ms reproduces
    the BDF solution of a full-throttle launch in Low range to a fraction of
    the sensor noise."""
    spec = get_experiment("vehicle_full_throttle_low")
    model = Model.load(spec.model)
    th = model.theta(spec.params)
    t = sample_times(spec)[:481]  # 12 s
    u = np.column_stack([spec.inputs[n](t) for n in model.inputs])
    ref = simulate(model, t, u=u, x0=spec.x0, theta=th, hold="zoh", rtol=1e-9, atol=1e-10)
    rk = simulate(model, t, u=u, x0=spec.x0, theta=th, method="rk4", substeps=16)
    assert np.all(np.isfinite(rk.y))
    std = model.meas_std(th)
    err = np.abs(rk.y - ref.y).max(axis=0)
    assert np.all(err < 0.2 * std), dict(zip(model.outputs, err / std))
