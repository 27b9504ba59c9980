"""Reference models against (a) hand-written equations, symbolically, (b) a
scipy simulation of the hand-written ODE, (c) the power balance at random
states (1e-10 relative)."""

import numpy as np
import pytest
import sympy as sp
from scipy.integrate import solve_ivp

from bondgraph.catalog import reference as models
from bondgraph.numerics.model import Model
from bondgraph.core.equations import derive


def _syms(ss):
    by = {}
    for s in list(ss.states) + list(ss.inputs) + list(ss.params):
        by[s.name] = s
    return by


def _assert_same(a, b):
    assert sp.simplify(sp.together(a - b)) == 0, f"\n{a}\n!=\n{b}"


# ---------------------------------------------------------------- hand-written
def hand_msd(S):
    p, q, F, m, k, c = (S[n] for n in ("p_mass", "q_spring", "F", "m", "k", "c"))
    return {"p_mass": F - k * q - c * p / m, "q_spring": p / m}


def hand_dc_compliant(S):
    lam, pm, phi, pL = (S[n] for n in ("p_L_a", "p_J_m", "q_k_s", "p_J_L"))
    V, TL = S["V"], S["T_L"]
    Ra, La, km, Jm, bm, ks, JL, bL = (S[n] for n in ("R_a", "L_a", "k_m", "J_m", "b_m", "k_s",
                                                     "J_L", "b_L"))
    return {
        "p_L_a": V - Ra * lam / La - km * pm / Jm,
        "p_J_m": km * lam / La - bm * pm / Jm - ks * phi,
        "q_k_s": pm / Jm - pL / JL,
        "p_J_L": ks * phi - bL * pL / JL - TL,
    }


def hand_dc_gear(S):
    lam, pL, V = S["p_L_a"], S["p_J_L"], S["V"]
    Ra, La, km, Jm, n, JL, bL = (S[k] for k in ("R_a", "L_a", "k_m", "J_m", "n", "J_L", "b_L"))
    i, wL = lam / La, pL / JL
    # J_eq = J_L + n^2 J_m at the load: J_eq dω_L/dt = n k_m i - b_L ω_L
    JEq = JL + n**2 * Jm
    return {"p_L_a": V - Ra * i - km * n * wL,
            "p_J_L": JL * (n * km * i - bL * wL) / JEq}


def hand_rr(S):
    lam, V, R1, R2, L = (S[k] for k in ("p_L", "V", "R1", "R2", "L"))
    return {"p_L": R2 * (V - R1 * lam / L) / (R1 + R2)}


def hand_toy_cvt(S):
    p, T, r, dr, Je, m, c = (S[k] for k in ("p_m", "T", "r", "der(r)", "J_e", "m", "c"))
    v = p / m
    # (m + J_e/r²) dv/dt = T/r + J_e v ṙ/r³ - c v
    vdot = (T / r + Je * v * dr / r**3 - c * v) / (m + Je / r**2)
    return {"p_m": m * vdot}


HAND = {
    "mass_spring_damper": hand_msd,
    "dc_motor_compliant": hand_dc_compliant,
    "dc_motor_gear": hand_dc_gear,
    "rr_loop": hand_rr,
    "toy_cvt": hand_toy_cvt,
}


@pytest.fixture(scope="module")
def derived():
    return {name: derive(getattr(models, name)()) for name in HAND}


@pytest.mark.parametrize("name", sorted(HAND))
def test_symbolic_equations_match_hand_derivation(derived, name):
    ss = derived[name]
    S = _syms(ss)
    hand = HAND[name](S)
    assert sorted(hand) == sorted(s.name for s in ss.states)
    for s, fi in zip(ss.states, ss.f):
        _assert_same(fi, hand[s.name])


def test_state_counts_and_names(derived):
    assert [s.name for s in derived["dc_motor_compliant"].states] == [
        "p_L_a", "p_J_m", "q_k_s", "p_J_L"]
    assert [s.state_kind for s in derived["dc_motor_compliant"].states] == [
        "momentum", "momentum", "displacement", "momentum"]
    gear = derived["dc_motor_gear"]
    assert len(gear.states) == 2 and gear.derivative_elements == ["J_m"]
    cvt = derived["toy_cvt"]
    assert [u.name for u in cvt.inputs] == ["T", "r", "der(r)"]
    assert cvt.derivative_elements == ["J_e"]
    assert len(derived["rr_loop"].algebraic_loops) == 1


def test_mass_chain_matches_hand_derivation():
    n = 6
    ss = derive(models.mass_chain(n))
    S = _syms(ss)
    assert len(ss.states) == 2 * n - 1
    v = [S[f"p_M{i}"] / S[f"m{i}"] for i in range(1, n + 1)]
    force = [S[f"k{j}"] * S[f"q_K{j}"] + S[f"c{j}"] * (v[j - 1] - v[j]) for j in range(1, n)]
    hand = {}
    for i in range(1, n + 1):
        rhs = S["F"] if i == 1 else 0
        if i > 1:
            rhs += force[i - 2]
        if i < n:
            rhs -= force[i - 1]
        hand[f"p_M{i}"] = rhs
    for j in range(1, n):
        hand[f"q_K{j}"] = v[j - 1] - v[j]
    for s, fi in zip(ss.states, ss.f):
        _assert_same(fi, hand[s.name])


# ------------------------------------------------------------- simulation (b)
def _lambdify_hand(name, ss):
    S = _syms(ss)
    hand = HAND[name](S)
    xs = [s for s in ss.states]
    us = [u for u in ss.inputs]
    ps = [p for p in ss.params]
    return sp.lambdify((xs, us, ps), [hand[s.name] for s in xs], "numpy")


SIM_CASES = {
    "mass_spring_damper": (lambda t: np.array([3.0 * (t > 0.1)]), 3.0),
    "dc_motor_compliant": (lambda t: np.array([12.0, 0.05 * np.sin(3 * t)]), 0.5),
    "dc_motor_gear": (lambda t: np.array([12.0 * min(t / 0.05, 1.0)]), 0.5),
    "rr_loop": (lambda t: np.array([5.0 * np.cos(20 * t)]), 0.2),
    "toy_cvt": (lambda t: np.array([40.0, 0.03 + 0.02 * t, 0.02]), 2.0),
}


@pytest.mark.parametrize("name", sorted(SIM_CASES))
def test_generated_model_simulates_like_hand_ode(derived, name):
    model = Model.load(name)
    hand = _lambdify_hand(name, derived[name])
    ufun, T = SIM_CASES[name]
    th = model.theta0
    x0 = np.zeros(model.n_x)
    if name == "toy_cvt":
        x0[0] = 1200.0 * 2.0  # 2 m/s
    ref = solve_ivp(lambda t, x: np.array(hand(x, ufun(t), th), dtype=float), (0, T), x0,
                    method="Radau", rtol=1e-10, atol=1e-12, dense_output=True)
    gen = solve_ivp(lambda t, x: model.f(x, ufun(t), th), (0, T), x0, method="Radau",
                    jac=lambda t, x: model.dfdx(x, ufun(t), th), rtol=1e-10, atol=1e-12,
                    dense_output=True)
    assert ref.success and gen.success
    tt = np.linspace(0, T, 200)
    a, b = ref.sol(tt), gen.sol(tt)
    scale = np.abs(a).max(axis=1, keepdims=True) + 1e-12
    assert np.max(np.abs(a - b) / scale) < 1e-6


# --------------------------------------------------------- power balance (c)
@pytest.mark.parametrize("name", sorted(SIM_CASES) + ["mass_chain_5"])
def test_power_balance_at_random_states(name):
    model = Model.load(name)
    rng = np.random.default_rng(0)
    N = 500
    x = rng.normal(size=(N, model.n_x)) * 3.0
    u = rng.normal(size=(N, model.n_u)) * 5.0
    if name == "toy_cvt":
        u[:, 1] = rng.uniform(0.02, 0.08, N)  # ratio away from zero
    th = model.theta0 * rng.uniform(0.5, 2.0, size=(N, model.n_theta))
    rate = model.energy_rate(x, u, th)
    ps, pd = model.power_sources(x, u, th), model.power_dissipated(x, u, th)
    scale = np.abs(rate) + np.abs(ps) + np.abs(pd)
    assert np.all(np.abs(rate - (ps - pd)) <= 1e-10 * scale + 1e-300)
    # and the chain rule itself: dH/dt numerically along f
    h = 1e-6
    if not model.derivative_inputs:
        dH = (model.energy(x + h * model.f(x, u, th), u, th)
              - model.energy(x - h * model.f(x, u, th), u, th)) / (2 * h)
        assert np.allclose(dH, rate, rtol=1e-5, atol=1e-8 * scale.max())


def test_jacobians_match_finite_differences():
    model = Model.load("dc_motor_compliant")
    rng = np.random.default_rng(1)
    x = rng.normal(size=(4, model.n_x))
    u = rng.normal(size=(4, model.n_u))
    th = model.theta0 * rng.uniform(0.8, 1.2, size=(4, model.n_theta))
    J = model.dfdx(x, u, th)
    f2, J2 = model.f_dfdx(x, u, th)
    np.testing.assert_allclose(J, J2, rtol=1e-13)
    np.testing.assert_allclose(f2, model.f(x, u, th), rtol=1e-13)
    for k in range(model.n_x):
        e = np.zeros(model.n_x)
        e[k] = 1e-6 * (1 + np.abs(x[:, k]).max())
        fd = (model.f(x + e, u, th) - model.f(x - e, u, th)) / (2 * e[k])
        np.testing.assert_allclose(J[..., k], fd, rtol=1e-6, atol=1e-6)
    Jt = model.dfdtheta(x, u, th)
    for k in range(model.n_theta):
        e = np.zeros(model.n_theta)
        e[k] = 1e-7 * model.theta0[k]
        fd = (model.f(x, u, th + e) - model.f(x, u, th - e)) / (2 * e[k])
        np.testing.assert_allclose(Jt[..., k], fd, rtol=1e-5, atol=1e-5 * np.abs(fd).max())
    Hx = model.dhdx(x, u, th)
    for k in range(model.n_x):
        e = np.zeros(model.n_x)
        e[k] = 1e-6
        fd = (model.h(x + e, u, th) - model.h(x - e, u, th)) / 2e-6
        np.testing.assert_allclose(Hx[..., k], fd, rtol=1e-6, atol=1e-7)
