"""The vehicle's bond graphs: structure, derivation, the generated equations
against an independent hand-written implementation of docs/vehicle.md, power
balance at random states, structural configuration."""

import math
import time

import numpy as np
import pytest

from bondgraph.errors import DerivativeCausalityError  # noqa: F401  (hierarchy import check)
from bondgraph.numerics.model import Model
from vehicle_graphs import MODELS, VehicleEffects, build_vehicle
from vehicle_graphs.params import DR_DX, PARAMS, RHO
from vehicle_graphs.subsystems import Numerics
from bondgraph.core.equations import derive

NUM = Numerics()


# ------------------------------------------------------------ hand-derived
def _ramp(z, d):
    return 0.5 * (z + np.sqrt(z * z + d * d))


def _mf(kappa, Fz, P):
    B = P["k_slip"] / (P["C_mf"] * P["mu"])
    Bk = B * kappa
    return P["mu"] * Fz * np.sin(P["C_mf"] * np.arctan(Bk - P["E_mf"] * (Bk - np.arctan(Bk))))


def hand_full(x, u, P):
    """dx/dt and y of the full 2WD model, written from the equations in
    docs/vehicle.md (numpy, independent of the graph and of sympy)."""
    (p_m, p_I, th_s, p_wr, p_wf, p_e, xp, p_s, phi, th_g) = x.T
    brake, throttle = u.T
    m, g, L = P["m"], P["g"], P["L_wb"]
    v = p_m / m
    dth = p_I / P["I_theta"]
    w_r, w_f = p_wr / (2 * P["J_w"]), p_wf / (2 * P["J_w"])
    w_e, w_s = p_e / P["J_e"], p_s / P["J_s"]
    # normal loads with load transfer from the pitch state (§3.8)
    dF = (P["k_theta"] * th_s + P["c_theta"] * dth) / L
    Fz_r = m * g * np.cos(th_g) * P["l_f"] / L + dF
    Fz_f = m * g * np.cos(th_g) * (L - P["l_f"]) / L - dF
    # tires: slip with low-speed regularisation
    d = NUM.v_delta
    a = np.sqrt(v * v + d * d)
    den = 0.5 * (a + NUM.v_eps + np.sqrt((a - NUM.v_eps) ** 2 + d * d))
    Fx_r = _mf((P["r_dyn"] * w_r - v) / den, Fz_r, P)
    Fx_f = _mf((P["r_dyn"] * w_f - v) / den, Fz_f, P)
    F_aero = 0.5 * RHO * P["C_dA"] * v * a
    dp_m = Fx_r + Fx_f - F_aero - m * g * np.sin(th_g)
    dp_I = -P["k_theta"] * th_s - P["c_theta"] * dth + P["h_cg"] * (Fx_r + Fx_f - F_aero)
    # drive line
    n_tot = P["i_g"] * P["i_fd"]
    dphi = w_s / n_tot - w_r
    T_ds = P["k_ds"] * phi + P["c_ds"] * dphi
    ew = NUM.w_eps_wheel
    dp_wr = (T_ds - P["r_dyn"] * Fx_r - 2 * P["T_bmax"] * brake * np.tanh(w_r / ew)
             - P["f_r"] * Fz_r * P["r_dyn"] * np.tanh(w_r / ew))
    dp_wf = (-P["r_dyn"] * Fx_f - 2 * P["T_bmax"] * brake * np.tanh(w_f / ew)
             - P["f_r"] * Fz_f * P["r_dyn"] * np.tanh(w_f / ew))
    # engine
    T_wot = (P["T_pk"] * (1 - ((w_e - P["w_pk"]) / P["dw_T"]) ** 2)
             - NUM.k_cut * _ramp(w_e - P["w_max"], 10.0))
    T_e = throttle * T_wot + P["K_idle"] * _ramp(P["w_idle"] - w_e, NUM.w_delta_idle)
    T_fr = P["T_f0"] * np.tanh(w_e / NUM.w_eps_engine) + P["b_e"] * w_e
    # clutch and CVT
    s = xp / P["x_max"]
    s_clip = _ramp(s, NUM.s_delta) - _ramp(s - 1, NUM.s_delta)
    i_cvt = P["i_max"] - (P["i_max"] - P["i_min"]) * s_clip
    F_cl = _ramp(P["k_fw"] * (w_e**2 - P["w_eng"] ** 2) - P["k_p"] * xp, NUM.F_delta)
    T_cap = P["mu_cl"] * (P["r_p0"] + DR_DX * xp) * F_cl
    T_cl = T_cap * np.tanh((w_e - i_cvt * w_s) / (NUM.w_eps_clutch + T_cap / P["c_cl"]))
    T_s = i_cvt * T_cl
    dp_e = T_e - T_fr - T_cl
    dp_s = T_s - P["b_s"] * w_s - T_ds / n_tot
    psi = (P["k_fw"] * P["w_eng"] ** 2 + P["F_s0"] + (P["k_p"] + P["k_s"]) * xp
           + NUM.k_stop * (_ramp(xp - P["x_max"], NUM.x_delta) - _ramp(-xp, NUM.x_delta)))
    dxp = (P["k_fw"] * w_e**2 - P["k_h"] * T_s - psi) / P["b_sh"]
    f = np.stack([dp_m, dp_I, dth, dp_wr, dp_wf, dp_e, dxp, dp_s, dphi, 0 * th_g], axis=-1)
    y = np.stack([w_e, w_s, w_f, w_r, v, th_g + th_s + P["theta_off"],
                  dp_m / m + g * np.sin(th_g + th_s)], axis=-1)
    return f, y


HAND_STATES = ["body.p_m", "pitch.p_I", "pitch.q_k", "rear.p_J", "front.p_J", "engine.p_J",
               "cvt.q_springs", "cvt.p_J_s", "driveline.q_k_rear", "theta_g"]
HAND_OUTPUTS = ["w_e", "w_s", "w_wf", "w_wr", "v_gnss", "pitch", "a_x"]


def _random_points(model, n, rng, spread=0.3):
    """Plausible random states, inputs and parameters (parameters within
    +-spread of their defaults, clipped to the bounds)."""
    P0 = dict(zip(model.params, model.theta0))
    th = model.theta0 * rng.uniform(1 - spread, 1 + spread, size=(n, model.n_theta))
    th = np.clip(th, model.lower, model.upper)
    th[:, model.param_index("E_mf")] = rng.uniform(-0.8, 0.4, n)
    if "theta_off" in model.params:
        th[:, model.param_index("theta_off")] = rng.uniform(-0.03, 0.03, n)
    v = rng.uniform(-3, 28, n)
    w_w = v / P0["r_dyn"] * rng.uniform(0.8, 1.2, n) + rng.normal(0, 2, n)
    X = np.zeros((n, model.n_x))
    vals = {
        "body.p_m": P0["m"] * v, "pitch.p_I": rng.normal(0, 50, n),
        "pitch.q_k": rng.normal(0, 0.02, n), "rear.p_J": 2 * P0["J_w"] * w_w,
        "front.p_J": 2 * P0["J_w"] * w_w * rng.uniform(0.9, 1.1, n),
        "wheels.p_J": 4 * P0["J_w"] * w_w,
        "engine.p_J": P0.get("J_e", 0) * rng.uniform(100, 700, n),
        "cvt.q_springs": rng.uniform(-0.002, 0.022, n),
        "cvt.p_J_s": P0.get("J_s", 0) * rng.uniform(-10, 700, n),
        "driveline.q_k_rear": rng.normal(0, 0.02, n),
        "driveline.q_k_front": rng.normal(0, 0.02, n),
        "theta_g": rng.normal(0, 0.1, n), "engine.T_m": rng.uniform(0, 70, n),
        "cvt.p_J_b": P0.get("J_b", 0) * rng.uniform(-10, 700, n),
    }
    for j, s in enumerate(model.states):
        X[:, j] = vals[s]
    U = np.zeros((n, model.n_u))
    for j, nm in enumerate(model.inputs):
        U[:, j] = rng.uniform(0, 1, n) if nm in ("throttle", "brake") else rng.normal(0, 0.1, n)
    return X, U, th


def test_full_model_matches_hand_derived_equations():
    model = Model.load("vehicle_full")
    assert model.states == HAND_STATES
    assert model.outputs == HAND_OUTPUTS
    assert model.inputs == ["brake", "throttle"]
    rng = np.random.default_rng(3)
    X, U, th = _random_points(model, 400, rng)
    P = {n: th[:, j] for j, n in enumerate(model.params)}
    f_ref, y_ref = hand_full(X, U, P)
    f_gen = model.f(X, U, th)
    y_gen = model.h(X, U, th)
    scale = np.abs(f_ref) + 1e-9
    np.testing.assert_allclose(f_gen, f_ref, rtol=1e-10, atol=1e-9)
    assert np.max(np.abs(f_gen - f_ref) / scale) < 1e-8
    np.testing.assert_allclose(y_gen, y_ref, rtol=1e-11, atol=1e-12)


def hand_coastdown(x, u, P, rigid=False):
    """Coast-down filter model (one lumped wheel of 4 J_w, dynamic or no pitch)."""
    if rigid:
        p_m, p_w, th_g = x.T
        p_I = th_s = 0 * p_m
    else:
        p_m, p_I, th_s, p_w, th_g = x.T
    brake = u[:, 0]
    m, g = P["m"], P["g"]
    v, w = p_m / m, p_w / (4 * P["J_w"])
    d = NUM.v_delta
    a = np.sqrt(v * v + d * d)
    den = 0.5 * (a + NUM.v_eps + np.sqrt((a - NUM.v_eps) ** 2 + d * d))
    Fz = m * g * np.cos(th_g)
    Fx = _mf((P["r_dyn"] * w - v) / den, Fz, P)
    F_aero = 0.5 * RHO * P["C_dA"] * v * a
    dp_m = Fx - F_aero - m * g * np.sin(th_g)
    tw = np.tanh(w / NUM.w_eps_wheel)
    dp_w = -P["r_dyn"] * Fx - 4 * P["T_bmax"] * brake * tw - P["f_r"] * Fz * P["r_dyn"] * tw
    pitch = th_g + th_s + P["theta_off"]
    a_x = dp_m / m + g * np.sin(th_g + th_s)
    y = np.stack([w, w, v, pitch, a_x], axis=-1)
    if rigid:
        return np.stack([dp_m, dp_w, 0 * th_g], axis=-1), y
    dth = p_I / P["I_theta"]
    dp_I = -P["k_theta"] * th_s - P["c_theta"] * dth + P["h_cg"] * (Fx - F_aero)
    return np.stack([dp_m, dp_I, dth, dp_w, 0 * th_g], axis=-1), y


@pytest.mark.parametrize("name", ["vehicle_coastdown", "vehicle_coastdown_rigid"])
def test_coastdown_models_match_hand_derived_equations(name):
    model = Model.load(name)
    rigid = name.endswith("rigid")
    assert model.states == (["body.p_m", "wheels.p_J", "theta_g"] if rigid else
                            ["body.p_m", "pitch.p_I", "pitch.q_k", "wheels.p_J", "theta_g"])
    rng = np.random.default_rng(9)
    X, U, th = _random_points(model, 300, rng)
    P = {n: th[:, j] for j, n in enumerate(model.params)}
    f_ref, y_ref = hand_coastdown(X, U, P, rigid=rigid)
    np.testing.assert_allclose(model.f(X, U, th), f_ref, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(model.h(X, U, th), y_ref, rtol=1e-11, atol=1e-12)


def test_low_range_differs_only_by_the_gear_ratio():
    hi, lo = Model.load("vehicle_full"), Model.load("vehicle_full_low")
    assert hi.params == lo.params and hi.states == lo.states
    j = hi.param_index("i_g")
    assert lo.theta0[j] == pytest.approx(2.25 * hi.theta0[j])
    rng = np.random.default_rng(4)
    X, U, th = _random_points(hi, 50, rng)
    np.testing.assert_allclose(hi.f(X, U, th), lo.f(X, U, th), rtol=1e-13, atol=1e-12)


def test_jacobian_matches_finite_differences():
    model = Model.load("vehicle_full")
    rng = np.random.default_rng(5)
    X, U, th = _random_points(model, 20, rng)
    J = model.dfdx(X, U, th)
    for k in range(model.n_x):
        h = 1e-6 * (1.0 + np.abs(X[:, k]))
        Xp, Xm = X.copy(), X.copy()
        Xp[:, k] += h
        Xm[:, k] -= h
        fd = (model.f(Xp, U, th) - model.f(Xm, U, th)) / (2 * h[:, None])
        np.testing.assert_allclose(J[:, :, k], fd, rtol=2e-5, atol=1e-6 * np.abs(fd).max())


# ------------------------------------------------------------ power balance
POWER_CASES = {
    "vehicle_full": None,
    "vehicle_full_low": None,
    "vehicle_coastdown": None,
    "vehicle_coastdown_rigid": None,
    "vehicle_coastdown_truth": None,
    "awd_beltslip_lag_drag": dict(drive="AWD", effects=VehicleEffects(
        belt_slip=True, manifold_lag=True, brake_drag=True)),
}


@pytest.mark.parametrize("case", sorted(POWER_CASES))
def test_power_balance_at_random_states(case):
    """dH/dt (chain rule, generated) = power of the sources - power absorbed by
    the R elements, to 1e-9 relative, and dH/dt agrees with a numerical
    derivative of H along f."""
    cfg = POWER_CASES[case]
    model = Model.load(case) if cfg is None else Model.from_graph(build_vehicle(case, **cfg))
    rng = np.random.default_rng(7)
    X, U, th = _random_points(model, 400, rng)
    rate = model.energy_rate(X, U, th)
    ps, pd = model.power_sources(X, U, th), model.power_dissipated(X, U, th)
    scale = np.abs(rate) + np.abs(ps) + np.abs(pd)
    assert np.all(scale > 0)
    assert np.max(np.abs(rate - (ps - pd)) / scale) < 1e-9
    # the energy rate is the real derivative of the stored energy
    F = model.f(X, U, th)
    h = 1e-7
    dH = (model.energy(X + h * F, U, th) - model.energy(X - h * F, U, th)) / (2 * h)
    np.testing.assert_allclose(dH, rate, rtol=1e-5, atol=1e-7 * np.abs(rate).max())
    # dissipation is non-negative at physically consistent points (R laws passive)
    assert np.all(pd >= -1e-9 * scale)


# -------------------------------------------------------------- structure
EXPECTED_STATES = {
    "vehicle_full": 10, "vehicle_full_low": 10, "vehicle_coastdown": 5,
    "vehicle_coastdown_rigid": 3, "vehicle_coastdown_truth": 6,
}


def test_registered_models_and_sizes():
    assert set(MODELS) == set(EXPECTED_STATES)
    for name, n in EXPECTED_STATES.items():
        m = Model.load(name)
        assert m.n_x == n, (name, m.states)
        # every parameter comes from the documented table, with its bounds
        table = {p.name: p for p in PARAMS}
        for j, p in enumerate(m.params):
            assert p in table, p
            assert (m.lower[j], m.upper[j]) == table[p].bounds
            assert m.lower[j] <= m.theta0[j] <= m.upper[j], p


def test_full_model_is_an_explicit_ode_and_derives_fast():
    """No algebraic loop, no storage in derivative causality; derivation +
    code generation of the full model well under 10 s."""
    from bondgraph.core.codegen import generate_source
    from bondgraph.numerics.registry import build

    t0 = time.perf_counter()
    g = build("vehicle_full")
    ss = derive(g)
    text = generate_source(ss, source=g.source)
    elapsed = time.perf_counter() - t0
    assert ss.algebraic_loops == []
    assert ss.derivative_elements == []
    assert len(ss.states) == 10
    assert "def f(" in text
    assert elapsed < 10.0, f"derive + codegen took {elapsed:.1f} s"
    # transcendental calls in f stay few (compact code for the UKF)
    import re

    body = text.split("def f(")[1].split("\ndef ")[0]
    n_trans = len(re.findall(r"np\.(tanh|sin|cos|arctan|exp|log|logaddexp)\(", body))
    assert n_trans <= 14, n_trans


def test_structural_configuration():
    def states(**kw):
        return [s.name for s in derive(build_vehicle("v", **kw)).states]

    fx = VehicleEffects

    base = set(states())
    assert set(states(drive="AWD")) - base == {"driveline.q_k_front"}
    assert set(states(effects=fx(belt_slip=True))) - base == {"cvt.p_J_b"}
    assert set(states(effects=fx(manifold_lag=True))) - base == {"engine.T_m"}
    neutral = set(states(gear="N"))
    assert base - neutral == {"driveline.q_k_rear"}
    # without shaft compliance the driven wheels and the secondary are lumped
    ss = derive(build_vehicle("v", shaft_compliance=False))
    assert ss.derivative_elements == ["cvt.J_s"]
    assert "driveline.q_k_rear" not in [s.name for s in ss.states]
    # optional effects appear as parameters only when declared
    g = build_vehicle("v", effects=fx(aero=False, pitch_offset=False))
    assert "C_dA" not in g.params and "theta_off" not in g.params
    assert "T_bd" in build_vehicle("v", effects=fx(brake_drag=True)).params
    assert "q_grade" not in build_vehicle("v", grade="input").params
    assert "grade" in build_vehicle("v", grade="input").inputs


@pytest.mark.parametrize("kw, culprit", [
    (dict(gear="R"), "gear"), (dict(drive="4WD"), "drive"), (dict(wheels="one"), "wheels"),
    (dict(suspension="soft"), "suspension"), (dict(grade="table"), "grade"),
    (dict(wheels="lumped"), "wheels='lumped'"), (dict(powertrain=False), "powertrain=False"),
    (dict(gear="N", powertrain=False, effects=VehicleEffects(belt_slip=True)), "belt_slip"),
])
def test_bad_configuration_is_named(kw, culprit):
    with pytest.raises(ValueError, match=culprit):
        build_vehicle("v", **kw)


def test_gear_neutral_decouples_the_power_train():
    """In neutral the engine, clutch and CVT do not act on the wheels: the
    vehicle states of the full model evolve exactly as those of the truth
    model without power train, whatever the engine does."""
    full_n = Model.from_graph(build_vehicle("full_n", gear="N"))
    truth = Model.load("vehicle_coastdown_truth")
    rng = np.random.default_rng(8)
    X, U, th = _random_points(full_n, 100, rng)
    shared = truth.states
    idx = [full_n.state_index(s) for s in shared]
    th_t = np.stack([th[:, full_n.param_index(p)] for p in truth.params], axis=-1)
    Ut = U[:, [full_n.input_index("brake")]]
    np.testing.assert_allclose(full_n.f(X, U, th)[:, idx], truth.f(X[:, idx], Ut, th_t),
                               rtol=1e-12, atol=1e-10)
    ys = [full_n.output_index(o) for o in truth.outputs]
    np.testing.assert_allclose(full_n.h(X, U, th)[:, ys], truth.h(X[:, idx], Ut, th_t),
                               rtol=1e-12, atol=1e-12)


def test_sensor_noise_is_declared_and_documented():
    from vehicle_graphs.vehicle import SENSOR_NOISE

    m = Model.load("vehicle_full")
    std = m.meas_std(m.theta0)
    for j, o in enumerate(m.outputs):
        assert std[j] == SENSOR_NOISE[o] > 0
    from vehicle_graphs.vehicle import PROCESS_NOISE

    q = m.proc_std(m.theta0)
    P = dict(zip(m.params, m.theta0))
    expected = {"theta_g": P["q_grade"], "body.p_m": P["m"] * PROCESS_NOISE["v"],
                "rear.p_J": 2 * P["J_w"] * PROCESS_NOISE["w_wheel"],
                "front.p_J": 2 * P["J_w"] * PROCESS_NOISE["w_wheel"],
                "engine.p_J": P["J_e"] * PROCESS_NOISE["w_e"],
                "cvt.p_J_s": P["J_s"] * PROCESS_NOISE["w_s"]}
    for j, s in enumerate(m.states):
        assert q[j] == pytest.approx(expected.get(s, 0.0), rel=1e-12), s
    # switched off on request
    m0 = Model.from_graph(build_vehicle("v", gear="N", powertrain=False, wheels="lumped",
                                        process_noise={}))
    assert np.count_nonzero(m0.proc_std(m0.theta0)) == 1
    with pytest.raises(ValueError, match="w_x"):
        build_vehicle("v", process_noise={"w_x": 1.0})


def test_static_normal_loads_match_the_measured_axle_loads():
    """At rest on level ground the rear/front normal loads (from the wheel
    equations: rolling-resistance torque / (f_r r_dyn) when the wheel spins
    forward) split 1200 kg as l_f / L = 0.615 rear (measured 640/1040)."""
    model = Model.load("vehicle_coastdown_truth")
    P = dict(zip(model.params, model.theta0))
    x = np.zeros(model.n_x)
    w = 1000.0  # fast wheel: tanh = 1, so T_rr = f_r F_z r_dyn exactly
    x[model.state_index("rear.p_J")] = 2 * P["J_w"] * w
    F = model.f(x, np.zeros(1), model.theta0)
    # the tire force at zero body speed is saturated (kappa large); subtract it
    # through the body equation: dp_m/dt = Fx_r (front at rest: Fx_f = 0)
    Fx_r = F[model.state_index("body.p_m")]
    T_rr = -(F[model.state_index("rear.p_J")] + P["r_dyn"] * Fx_r)
    Fz_r = T_rr / (P["f_r"] * P["r_dyn"])
    assert Fz_r == pytest.approx(P["m"] * P["g"] * P["l_f"] / P["L_wb"], rel=1e-9)
    assert Fz_r / (P["m"] * P["g"]) == pytest.approx(640 / 1040, abs=0.002)
    assert math.isclose(P["m"], 1200.0) and math.isclose(P["I_theta"], 1093.0)
