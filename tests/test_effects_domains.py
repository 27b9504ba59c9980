"""The effects of every energy domain (issue 12): each fragment's equations
against hand-derived ones, and its power balance.

For every effect the augmented graph is derived and generated
(:meth:`Model.from_graph`); at random states, inputs and parameters its
dx/dt and outputs are compared with the equations written out by hand from
the reference graph's docstring plus the fragment. The power balance is
checked twice: for the whole model, dH/dt along the flow (a central finite
difference of the generated stored energy, independent of the generated
``energy_rate``) equals the source power minus the dissipation; and for the
fragment, the change of stored energy, source power or dissipation against
the declared model equals what the fragment's ports carry by hand.
"""

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.signal import freqs

from bondgraph.catalog import reference as models
from bondgraph.diagnose.effects import Target, apply_effect, get_effect
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate

N = 12


def augmented(builder, effect, target, values):
    """(declared model, augmented model, parameter vector of the augmented
    model with ``values`` set)."""
    base = Model.from_graph(builder())
    g = builder()
    apply_effect(g, effect, Target(*target), values)
    m = Model.from_graph(g)
    return base, m, m.theta0.copy()


def rand_x(m, rng, scale):
    """Random states, (N, n_x); ``scale`` maps state name -> spread."""
    return np.column_stack([rng.normal(size=N) * scale.get(s, 1.0) for s in m.states])


def rand_u(m, rng, scale):
    return np.column_stack([rng.normal(size=N) * scale.get(s, 1.0) for s in m.inputs]) \
        if m.n_u else np.zeros((N, 0))


def col(m, x, name):
    return x[:, m.state_index(name)]


def pcol(m, th, name):
    return th[m.param_index(name)]


def base_x(base, m, x):
    """The declared model's states taken from the augmented state."""
    return np.column_stack([x[:, m.state_index(s)] for s in base.states])


def assert_power_balance(m, x, u, th):
    """dH/dt (central difference of H along f) = P_sources − P_dissipated."""
    f = m.f(x, u, th)
    h = 1e-6 / max(np.max(np.abs(f)), 1e-300)
    dH = (m.energy(x + h * f, u, th) - m.energy(x - h * f, u, th)) / (2 * h)
    bal = m.power_sources(x, u, th) - m.power_dissipated(x, u, th)
    scale = np.abs(m.power_sources(x, u, th)) + np.abs(m.power_dissipated(x, u, th)) + np.abs(dH)
    np.testing.assert_allclose(dH, bal, atol=1e-6 * np.max(scale) + 1e-12)


def softplus(z):
    return np.logaddexp(0.0, z)


# ------------------------------------------------------------------ sources
def test_source_offset_of_a_pump():
    base, m, th = augmented(models.hydraulic_tanks, "source_offset", ("source", "pump"),
                            {"b": 2e-4})
    rng = np.random.default_rng(0)
    x = rand_x(m, rng, {"q_tank1_C": 0.05, "q_tank2_C": 0.05})
    u = rand_u(m, rng, {"Q": 1e-3})
    C1, C2, R12, R2 = (pcol(m, th, n) for n in ("Ch1", "Ch2", "Rh12", "Rh2"))
    p1, p2 = col(m, x, "q_tank1_C") / C1, col(m, x, "q_tank2_C") / C2
    Q = u[:, 0]
    dx = m.f(x, u, th)
    np.testing.assert_allclose(dx[:, 0], Q + 2e-4 - (p1 - p2) / R12, rtol=1e-12)
    np.testing.assert_allclose(dx[:, 1], (p1 - p2) / R12 - p2 / R2, rtol=1e-12)
    assert_power_balance(m, x, u, th)
    # fragment: the pump's extra power is the offset flow times its pressure
    dP = m.power_sources(x, u, th) - base.power_sources(x, u, base.theta0)
    np.testing.assert_allclose(dP, 2e-4 * p1, rtol=1e-12)


@pytest.mark.parametrize("effect,vals", [("source_lag", {"tau": 0.3}),
                                         ("source_rate_limit", {"r": 4.0, "tau_f": 0.02})])
def test_source_lag_and_rate_limit_of_a_heater(effect, vals):
    """The heater (Sf P/T0) delivers the state z instead of P/T0."""
    base, m, th = augmented(models.thermal_two_node, effect, ("source", "heater"), vals)
    assert m.states[:2] == base.states and len(m.states) == 3
    z_name = f"{effect}.heater.z"
    rng = np.random.default_rng(1)
    x = rand_x(m, rng, {"q_mass1": 5.0, "q_mass2": 5.0, z_name: 3.0})
    u = rand_u(m, rng, {"P": 900.0, "T_a": 2.0})
    T0, C1, C2, R12, R2a = (pcol(m, th, n) for n in ("T0", "Cth1", "Cth2", "Rth12", "Rth2a"))
    S1, S2, z = col(m, x, "q_mass1"), col(m, x, "q_mass2"), col(m, x, z_name)
    T1, T2 = T0 * S1 / C1, T0 * S2 / C2
    P, Ta = u[:, m.input_index("P")], u[:, m.input_index("T_a")]
    dx = m.f(x, u, th)
    # entropy flows: heater z, R12 (T1-T2)/(T0 R12), R2a (T2-Ta)/(T0 R2a)
    np.testing.assert_allclose(dx[:, 0], z - (T1 - T2) / (T0 * R12), rtol=1e-10)
    np.testing.assert_allclose(dx[:, 1], (T1 - T2) / (T0 * R12) - (T2 - Ta) / (T0 * R2a),
                               rtol=1e-10)
    v = P / T0
    if effect == "source_lag":
        want = (v - z) / 0.3
    else:
        want = 4.0 * np.tanh((v - z) / (4.0 * 0.02))
    np.testing.assert_allclose(dx[:, 2], want, rtol=1e-10)
    assert_power_balance(m, x, u, th)
    # fragment: the heater's power is T1 · z (effort × delivered flow)
    Pb = base.power_sources(base_x(base, m, x), u, base.theta0)
    np.testing.assert_allclose(m.power_sources(x, u, th) - Pb, T1 * (z - v), rtol=1e-9,
                               atol=1e-9)


def test_input_delay_is_the_pade_approximant():
    """The delay states of an RLC's voltage: the transfer function from V to
    the delayed voltage (read from dλ/dt + Rλ/L + q/C) equals the [2/2]
    Padé approximant (1 − sτ/2 + (sτ)²/12)/(1 + sτ/2 + (sτ)²/12)."""
    tau = 0.013
    base, m, th = augmented(models.rlc_circuit, "input_delay", ("input", "V"),
                            {"tau": tau, "qn": 0.5})
    # a small process noise on the last Padé state only (keeps P definite)
    q = m.proc_std(th)
    assert q[m.state_index("input_delay.V.x2")] == 0.5 and q[m.state_index("input_delay.V.x1")] == 0
    R, L, C = (pcol(m, th, n) for n in ("R", "L", "C"))
    d = [m.state_index(s) for s in m.states if s.startswith("input_delay.V.")]
    assert len(d) == 2
    n = m.n_x
    lam, q = m.state_index("p_inductor"), m.state_index("q_capacitor")

    def delayed(x, u):  # V_d = dλ/dt + R λ/L + q/C
        return m.f(x, u, th)[..., lam] + R * x[..., lam] / L + x[..., q] / C

    # the fragment is linear: read A, B, Cd, D column by column
    z = np.zeros(n)
    A = np.column_stack([m.f(np.eye(n)[k], np.zeros(1), th)[d] for k in d])
    B = m.f(z, np.ones(1), th)[d]
    Cd = np.array([delayed(np.eye(n)[k], np.zeros(1)) for k in d])
    D = delayed(z, np.ones(1))
    w = np.array([1.0, 20.0, 77.0, 150.0])
    G = np.array([Cd @ np.linalg.solve(1j * wk * np.eye(2) - A, B) + D for wk in w])
    _, pade = freqs([tau**2 / 12, -tau / 2, 1.0], [tau**2 / 12, tau / 2, 1.0], worN=w)
    np.testing.assert_allclose(G, pade, rtol=1e-10)
    # all-pass, and close to the true delay while ωτ ≤ 1 (phase error < 1°)
    np.testing.assert_allclose(np.abs(G), 1.0, rtol=1e-10)
    err = np.angle(G * np.exp(1j * w * tau), deg=True)
    assert np.all(np.abs(err[w * tau <= 1.0]) < 1.0)
    # DC: at rest the delay states give V_d = V
    x_rest = np.zeros(n)
    x_rest[d] = np.linalg.solve(A, -B * 3.0)
    assert delayed(x_rest, np.array([3.0])) == pytest.approx(3.0, rel=1e-12)
    # the delay carries no power: the balance holds with V_d as the source
    rng = np.random.default_rng(2)
    x = rand_x(m, rng, {"p_inductor": 0.01, "q_capacitor": 1e-3})
    u = rand_u(m, rng, {"V": 5.0})
    assert_power_balance(m, x, u, th)
    i = x[:, lam] / L
    np.testing.assert_allclose(m.power_sources(x, u, th), delayed(x, u) * i, rtol=1e-9)


def test_input_delay_simulates_a_delayed_step_response():
    """Free run of the RLC with the delay against the declared model's
    response shifted by τ (scipy's solve_ivp of the hand-derived equations,
    input stepping at 0.1 s and 0.1 s + τ): equal to within the Padé
    approximant's ringing, a few percent of the step."""
    tau = 0.004
    base, m, th = augmented(models.rlc_circuit, "input_delay", ("input", "V"), {"tau": tau})
    R, L, C = 10.0, 0.1, 1e-3
    t = np.linspace(0.0, 0.2, 401)
    sim = simulate(m, t, lambda tt: np.where(tt >= 0.1, 1.0, 0.0), theta=th, max_step=5e-4)

    def rhs(tt, s):
        V = 1.0 if tt >= 0.1 + tau else 0.0
        return [V - R * s[0] / L - s[1] / C, s[0] / L]
    ref = solve_ivp(rhs, (0, 0.2), [0.0, 0.0], t_eval=t, max_step=2e-4, rtol=1e-9, atol=1e-12)
    vC = sim.y[:, m.output_index("v_C")]
    assert np.max(np.abs(vC - ref.y[1] / C)) < 0.05
    assert np.max(np.abs(vC)) > 0.9


# ------------------------------------------------------------------ sensors
@pytest.mark.parametrize("effect,vals", [("sensor_poly2", {"c2": 0.3}),
                                         ("sensor_poly3", {"c2": 0.2, "c3": -0.05})])
def test_sensor_polynomial_calibration(effect, vals):
    base, m, th = augmented(models.rlc_circuit, effect, ("sensor", "v_C"), vals)
    rng = np.random.default_rng(3)
    x = rand_x(m, rng, {"p_inductor": 0.01, "q_capacitor": 3e-3})
    u = rand_u(m, rng, {"V": 5.0})
    y = x[:, m.state_index("q_capacitor")] / 1e-3
    want = y + vals["c2"] * y**2 + vals.get("c3", 0.0) * y**3
    np.testing.assert_allclose(m.h(x, u, th)[:, m.output_index("v_C")], want, rtol=1e-12)
    np.testing.assert_allclose(m.h(x, u, th)[:, m.output_index("i")],
                               base.h(x, u, base.theta0)[:, base.output_index("i")], rtol=1e-14)
    # a sensor carries no power: the dynamics are unchanged
    np.testing.assert_allclose(m.f(x, u, th), base.f(x, u, base.theta0), rtol=1e-14)
    assert_power_balance(m, x, u, th)


def test_sensor_quantisation_is_the_damped_sawtooth_series():
    """y − (Δ/π)·atan(r sin θ/(1 + r cos θ)) is y minus the sawtooth
    y − Δ·round(y/Δ) written as its Fourier series (Δ/π) Σ (−1)^{k+1}
    sin(kθ)/k with the k-th term damped by r^k; as r → 1 it tends to
    Δ·round(y/Δ) away from the steps."""
    delta, r = 0.25, 0.9
    base, m, th = augmented(models.mass_spring_damper, "sensor_quantisation", ("sensor", "v"),
                            {"delta": delta, "r": r})
    rng = np.random.default_rng(4)
    x = rand_x(m, rng, {"p_mass": 3.0, "q_spring": 0.1})
    u = rand_u(m, rng, {"F": 1.0})
    y = x[:, m.state_index("p_mass")] / 2.0
    th_ = 2 * np.pi * y / delta
    k = np.arange(1, 400)[:, None]
    series = (delta / np.pi) * np.sum((-1.0) ** (k + 1) * r**k * np.sin(k * th_) / k, axis=0)
    got = m.h(x, u, th)[:, m.output_index("v")]
    np.testing.assert_allclose(got, y - series, rtol=1e-9, atol=1e-12)
    # sharp staircase at r = 0.99, between the steps
    th[m.param_index("sensor_quantisation.v.r")] = 0.99
    yq = np.array([0.3, -0.55, 1.05, 0.74])
    xq = np.zeros((4, 2))
    xq[:, 0] = yq * 2.0
    got = m.h(xq, np.zeros((4, 1)), th)[:, m.output_index("v")]
    np.testing.assert_allclose(got, delta * np.round(yq / delta), atol=0.01 * delta)
    np.testing.assert_allclose(m.f(x, u, th), base.f(x, u, base.theta0), rtol=1e-14)


# ------------------------------------------------------------------ storage
def test_cubic_stiffness_of_a_spring():
    """dp/dt = F − k q − k3 q³ − c p/m; the stored energy gains k3 q⁴/4."""
    k3 = 800.0
    base, m, th = augmented(models.mass_spring_damper, "cubic_stiffness", ("storage", "spring"),
                            {"k3": k3})
    rng = np.random.default_rng(5)
    x = rand_x(m, rng, {"p_mass": 2.0, "q_spring": 0.2})
    u = rand_u(m, rng, {"F": 10.0})
    p, q, F = x[:, 0], x[:, 1], u[:, 0]
    mm, k, c = 2.0, 50.0, 1.5
    dx = m.f(x, u, th)
    np.testing.assert_allclose(dx[:, m.state_index("p_mass")], F - k * q - k3 * q**3 - c * p / mm,
                               rtol=1e-12)
    np.testing.assert_allclose(dx[:, m.state_index("q_spring")], p / mm, rtol=1e-12)
    assert_power_balance(m, x, u, th)
    np.testing.assert_allclose(m.energy(x, u, th) - base.energy(x, u, base.theta0),
                               k3 * q**4 / 4, rtol=1e-10)


def test_cubic_stiffness_of_a_capacitor():
    """A nonlinear capacitor: v_C = q/C + k3 q³ (the RLC's sensor reads q/C:
    the sensed voltage is the linear part of the declared model)."""
    k3 = 2e9
    base, m, th = augmented(models.rlc_circuit, "cubic_stiffness", ("storage", "capacitor"),
                            {"k3": k3})
    rng = np.random.default_rng(6)
    x = rand_x(m, rng, {"p_inductor": 0.01, "q_capacitor": 2e-3})
    u = rand_u(m, rng, {"V": 5.0})
    lam, q, V = x[:, 0], x[:, 1], u[:, 0]
    dx = m.f(x, u, th)
    np.testing.assert_allclose(dx[:, 0], V - 10.0 * lam / 0.1 - q / 1e-3 - k3 * q**3, rtol=1e-10)
    assert_power_balance(m, x, u, th)


@pytest.mark.parametrize("routed", [False, True])
def test_capacity_limit_with_overflow(routed):
    """Above V1max the overflow Q_o = (w/τ)·[softplus((V1 − V1max)/w) −
    softplus(−V1max/w)] leaves tank 1: lost (dissipated at p1), or routed
    into tank 2 (dissipated across p1 − p2); zero at an empty tank."""
    qmax, w, tau = 0.02, 5e-4, 0.5
    vals = {"qmax": qmax, "w": w, "tau": tau}
    g = models.hydraulic_tanks()
    eff = get_effect("capacity_limit") if not routed else \
        type(get_effect("capacity_limit"))(routes={"tank1_C": "tank2"})
    base = Model.from_graph(models.hydraulic_tanks())
    eff.apply(g, Target("storage", "tank1_C"), vals)
    m = Model.from_graph(g)
    th = m.theta0
    rng = np.random.default_rng(7)
    x = np.column_stack([0.02 + 0.004 * rng.normal(size=N), 0.03 * rng.normal(size=N)])
    u = rand_u(m, rng, {"Q": 1e-3})
    V1, V2, Q = x[:, 0], x[:, 1], u[:, 0]
    p1, p2 = V1 / 1e-4, V2 / 2e-4
    Qo = w / tau * (softplus((V1 - qmax) / w) - softplus(-qmax / w))
    dx = m.f(x, u, th)
    np.testing.assert_allclose(dx[:, 0], Q - (p1 - p2) / 1e5 - Qo, rtol=1e-10)
    np.testing.assert_allclose(dx[:, 1], (p1 - p2) / 1e5 - p2 / 1e5 + (Qo if routed else 0.0),
                               rtol=1e-10, atol=1e-15)
    assert_power_balance(m, x, u, th)
    dP = m.power_dissipated(x, u, th) - base.power_dissipated(x, u, base.theta0)
    np.testing.assert_allclose(dP, Qo * ((p1 - p2) if routed else p1), rtol=1e-9)
    # 8 widths below the limit the overflow is < 0.1 % of its value at the limit
    assert softplus((0.8 * qmax - qmax) / w) < 1e-3 * softplus(0.0)


def test_capacity_limit_overflow_is_zero_at_an_empty_tank_and_dissipates_below():
    """A wide onset (w = 15 % of V1max, as a refit from a poor start may
    leave it): the softplus tail alone, (w/τ)·e^(−V1max/w) = 7.6e-6 m³/s
    at V1 = 0, would keep draining an empty tank and produce power p1·Q < 0
    below it. The law minus its value at V1 = 0 is zero there and of V1's
    sign below, so the lost overflow dissipates p1·Q_o > 0."""
    qmax, w, tau = 0.02, 0.003, 0.5
    g = models.hydraulic_tanks()
    base = Model.from_graph(models.hydraulic_tanks())
    get_effect("capacity_limit").apply(g, Target("storage", "tank1_C"),
                                       {"qmax": qmax, "w": w, "tau": tau})
    m = Model.from_graph(g)
    x = np.array([[0.0, 0.0], [-0.01, 0.0], [-0.02, 0.0], [0.02, 0.0]])
    u = np.zeros((4, 1))
    q_out = base.f(x, u, base.theta0)[:, 0] - m.f(x, u, m.theta0)[:, 0]
    tail = w / tau * softplus(-qmax / w)
    assert tail == pytest.approx(6e-3 * math.exp(-20 / 3), rel=1e-3)
    np.testing.assert_allclose(q_out, w / tau * softplus((x[:, 0] - qmax) / w) - tail,
                               rtol=1e-9, atol=1e-15)
    assert abs(q_out[0]) < 1e-15 and np.all(q_out[1:3] < 0) and q_out[3] > 0
    dP = m.power_dissipated(x, u, m.theta0) - base.power_dissipated(x, u, base.theta0)
    np.testing.assert_allclose(dP, q_out * x[:, 0] / 1e-4, rtol=1e-9, atol=1e-15)
    assert np.all(dP[1:] > 0)


# --------------------------------------------------------------- R laws
@pytest.mark.parametrize("effect,beta,eps", [("r_sqrt", 3e-6, 50.0),
                                             ("r_quadratic", 2e-11, 50.0),
                                             ("r_cubic", 1e-13, None)])
def test_r_law_of_an_orifice_in_effort_in_causality(effect, beta, eps):
    """The orifice between the tanks receives Δp = p1 − p2 and returns its
    flow: Q12 = Δp/R12 + β·b(Δp)."""
    vals = {"beta": beta} | ({"eps": eps} if eps else {})
    base, m, th = augmented(models.hydraulic_tanks, effect, ("resistor", "orifice_R"), vals)
    rng = np.random.default_rng(8)
    x = rand_x(m, rng, {"q_tank1_C": 0.05, "q_tank2_C": 0.05})
    u = rand_u(m, rng, {"Q": 1e-3})
    p1, p2 = x[:, 0] / 1e-4, x[:, 1] / 2e-4
    dp = p1 - p2
    b = {"r_sqrt": lambda e: e / (e**2 + eps**2) ** 0.25,
         "r_quadratic": lambda e: e * np.sqrt(e**2 + eps**2),
         "r_cubic": lambda e: e**3}[effect](dp)
    Q12 = dp / 1e5 + beta * b
    dx = m.f(x, u, th)
    np.testing.assert_allclose(dx[:, 0], u[:, 0] - Q12, rtol=1e-10)
    np.testing.assert_allclose(dx[:, 1], Q12 - p2 / 1e5, rtol=1e-10)
    assert_power_balance(m, x, u, th)
    dP = m.power_dissipated(x, u, th) - base.power_dissipated(x, u, base.theta0)
    np.testing.assert_allclose(dP, beta * b * dp, rtol=1e-9)


@pytest.mark.parametrize("effect,beta", [("r_cubic", 3.0), ("r_quadratic", 0.7)])
def test_r_law_of_a_damper_in_flow_in_causality(effect, beta):
    """The damper receives v and returns its force: F_d = c v + β·b(v)."""
    eps = 0.05
    base, m, th = augmented(models.mass_spring_damper, effect, ("resistor", "damper"),
                            {"beta": beta, "eps": eps})
    rng = np.random.default_rng(9)
    x = rand_x(m, rng, {"p_mass": 3.0, "q_spring": 0.1})
    u = rand_u(m, rng, {"F": 5.0})
    v = x[:, 0] / 2.0
    b = v**3 if effect == "r_cubic" else v * np.sqrt(v**2 + eps**2)
    dx = m.f(x, u, th)
    np.testing.assert_allclose(dx[:, 0], u[:, 0] - 50.0 * x[:, 1] - 1.5 * v - beta * b,
                               rtol=1e-10)
    assert_power_balance(m, x, u, th)
    dP = m.power_dissipated(x, u, th) - base.power_dissipated(x, u, base.theta0)
    np.testing.assert_allclose(dP, beta * b * v, rtol=1e-9)


def test_r_law_of_a_thermal_resistance():
    """Square-root term on the thermal resistance to the ambient (effort in:
    the temperature difference)."""
    beta, eps = 1e-3, 0.02
    base, m, th = augmented(models.thermal_two_node, "r_sqrt", ("resistor", "R2a"),
                            {"beta": beta, "eps": eps})
    rng = np.random.default_rng(10)
    x = rand_x(m, rng, {"q_mass1": 5.0, "q_mass2": 5.0})
    u = rand_u(m, rng, {"P": 900.0, "T_a": 2.0})
    T1, T2 = 300.0 * x[:, 0] / 500.0, 300.0 * x[:, 1] / 2000.0
    dT = T2 - u[:, m.input_index("T_a")]
    S2a = dT / (300.0 * 0.1) + beta * dT / (dT**2 + eps**2) ** 0.25
    dx = m.f(x, u, th)
    np.testing.assert_allclose(dx[:, 1], (T1 - T2) / (300.0 * 0.05) - S2a, rtol=1e-10)
    assert_power_balance(m, x, u, th)


# ------------------------------------------------------------- friction
def test_dahl_friction():
    """dF/dt = σ v (1 − (F/Fc) tanh(v/ε)); dp/dt = F_in − k q − c v − F;
    the friction's power −F·v is the power its modulated source delivers."""
    Fc, sigma, eps = 2.0, 400.0, 0.01
    base, m, th = augmented(models.mass_spring_damper, "dahl", ("junction", "v"),
                            {"Fc": Fc, "sigma": sigma, "eps": eps})
    rng = np.random.default_rng(11)
    x = rand_x(m, rng, {"p_mass": 0.1, "q_spring": 0.1, "dahl.v.F": 2.0})
    u = rand_u(m, rng, {"F": 5.0})
    v, q, Fd = x[:, 0] / 2.0, x[:, 1], x[:, m.state_index("dahl.v.F")]
    dx = m.f(x, u, th)
    np.testing.assert_allclose(dx[:, 0], u[:, 0] - 50.0 * q - 1.5 * v - Fd, rtol=1e-10)
    np.testing.assert_allclose(dx[:, m.state_index("dahl.v.F")],
                               sigma * v * (1 - Fd / Fc * np.tanh(v / eps)), rtol=1e-10)
    assert_power_balance(m, x, u, th)
    Pb = base.power_sources(base_x(base, m, x), u, base.theta0)
    np.testing.assert_allclose(m.power_sources(x, u, th) - Pb, -Fd * v, rtol=1e-9)


def test_friction_attaches_at_a_massless_flow_junction():
    """Two masses coupled by a spring-damper (mass_chain(2)): the
    relative-velocity junction dv1 carries no inertia but the states fix its
    flow, so friction attaches there too; a Coulomb force at dv1 acts equal
    and opposite on the two masses: dp1/dt gains −Fc tanh((v1 − v2)/ε) and
    dp2/dt gains +Fc tanh((v1 − v2)/ε)."""
    g = models.mass_chain(2)
    assert [t.name for t in get_effect("coulomb").targets(g)] == ["dv1", "v1", "v2"]
    Fc, eps = 0.8, 0.05
    base, m, th = augmented(lambda: models.mass_chain(2), "coulomb", ("junction", "dv1"),
                            {"Fc": Fc, "eps": eps})
    rng = np.random.default_rng(12)
    x = rand_x(m, rng, {})
    u = rand_u(m, rng, {"F": 3.0})
    v1, v2 = col(m, x, "p_M1") / 1.1, col(m, x, "p_M2") / 1.2
    fr = Fc * np.tanh((v1 - v2) / eps)
    d = m.f(x, u, th) - base.f(x, u, base.theta0)
    np.testing.assert_allclose(d[:, m.state_index("p_M1")], -fr, rtol=1e-9)
    np.testing.assert_allclose(d[:, m.state_index("p_M2")], fr, rtol=1e-9)
    np.testing.assert_allclose(d[:, m.state_index("q_K1")], 0.0, atol=1e-12)
    assert_power_balance(m, x, u, th)
    dP = m.power_dissipated(x, u, th) - base.power_dissipated(x, u, base.theta0)
    np.testing.assert_allclose(dP, fr * (v1 - v2), rtol=1e-9)
