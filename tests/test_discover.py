"""Reconstruction of a missing force at a port and discovery of its law
(bondgraph/diagnose/discover), against truths simulated by scipy's
solve_ivp from hand-written equations.

Truth: the mass-spring-damper of the catalog (m = 2 kg, k = 50 N/m,
c = 8 N·s/m) with one extra force the declared graph lacks, either a cubic
spring −k3·x³ (k3 = 400 N/m³) or a Coulomb-like friction −Fc·tanh(v/ε)
(Fc = 4 N, ε = 0.01 m/s); 20 s at 100 Hz, two slow sines of force, the
position measured with Gaussian noise of 2 mm std.
"""

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.data.records import Experiment
from bondgraph.diagnose.discover.law import DiscoverOptions, discover_law
from bondgraph.diagnose.discover.reconstruct import (
    ReconstructOptions,
    augment_port,
    reconstruct,
)
from bondgraph.errors import GraphError, OptionError
from bondgraph.inference.options import UKFOptions

M, K, C = 2.0, 50.0, 8.0
K3, FC, EPS = 400.0, 4.0, 0.01
NOISE = 0.002
T = np.arange(0.0, 20.0, 0.01)


def force(t):
    return 12.0 * np.sin(2 * np.pi * 0.15 * t) + 6.0 * np.sin(2 * np.pi * 0.37 * t + 1.0)


def extra(case, x, v):
    """The missing force on the mass (N), hand-written."""
    return -K3 * x ** 3 if case == "cubic" else -FC * np.tanh(v / EPS)


def truth(case, seed=0):
    """(record, x (N,), v (N,), missing force (N,)) from solve_ivp of
    m dv/dt = F − k x − c v + extra(x, v), dx/dt = v."""
    def rhs(t, s):
        x, v = s
        return [v, (force(t) - K * x - C * v + extra(case, x, v)) / M]

    sol = solve_ivp(rhs, (T[0], T[-1]), [0.0, 0.0], t_eval=T, method="LSODA",
                    rtol=1e-9, atol=1e-11, max_step=0.005)
    x, v = sol.y
    y = x + NOISE * np.random.default_rng(seed).standard_normal(T.size)
    rec = Experiment.from_arrays(T, {"F": force(T), "x": y}, units={"F": "N", "x": "m"},
                                 roles={"F": "input", "x": "output"}, noise_std={"x": NOISE})
    return rec, x, v, extra(case, x, v)


@pytest.fixture(scope="module", params=["cubic", "friction"])
def case(request):
    rec, x, v, d_true = truth(request.param)
    r = reconstruct(mass_spring_damper(), rec, "v", params={"c": C})
    return request.param, r, x, v, d_true


def rms(a):
    return float(np.sqrt(np.mean(np.asarray(a) ** 2)))


def test_reconstruction_matches_the_missing_force(case):
    name, r, x, v, d_true = case
    mid = slice(100, -100)                   # 1 s from each end
    rel = rms(r.d[mid] - d_true[mid]) / rms(d_true[mid])
    assert rel < 0.10, f"{name}: RMS error {rel:.3f} of the force's RMS"
    # the port's own variables are the smoothed truth (position within the noise)
    assert rms(r.variables["q_spring"][mid] - x[mid]) < NOISE
    assert rms(r.variables["v.f"][mid] - v[mid]) < 0.05 * rms(v)
    assert r.primary == ["v.f", "q_spring"]
    assert r.units["v.f"] == "m/s" and r.port.unit == "N"
    # the std is honest: the error is within 3 std at ≥ 90 % of the samples
    inside = np.abs(r.d[mid] - d_true[mid]) < 3 * r.d_std[mid]
    assert inside.mean() > 0.9
    # the chosen intensity is the grid's likelihood minimum
    assert r.q == pytest.approx(r.q_grid[np.argmin(r.nll_grid)])


def test_discovered_law_has_the_right_term(case):
    name, r, x, v, d_true = case
    law = discover_law(r)
    if name == "cubic":
        right = [tm for tm in law.terms if tm.name == "q_spring^3"]
        assert len(right) == 1 and law.terms[0] is right[0]
        assert right[0].coef == pytest.approx(-K3, rel=0.10)
    else:
        # the smooth signs of v at the dictionary's widths (0.02 and 0.1 of
        # v's RMS; the truth's ε lies between them): their coefficients sum
        # to the Coulomb level, the law's limit for |v| >> ε
        right = [tm for tm in law.terms if tm.name.startswith("tanh(v.f/")]
        assert right and law.terms[0] in right
        assert sum(tm.coef for tm in right) == pytest.approx(-FC, rel=0.10)
    # no spurious term carries more than 5 % of the missing force's RMS
    for tm in law.terms:
        if tm not in right:
            assert tm.rms < 0.05 * rms(d_true), f"{name}: spurious {tm.name} ({tm.rms:.3g} N)"
    # the law at the true states reproduces the true force: within 10 % of
    # its RMS for the cubic, 15 % for the friction (whose ε is not in the
    # dictionary: near v = 0 the found law's slope differs)
    vals = {"q_spring": x, "v.f": v, "F": force(T)}
    tol = 0.10 if name == "cubic" else 0.15
    assert rms(law.evaluate(vals) - d_true) < tol * rms(d_true)
    assert law.readable().startswith("v effort [N] = -")


def test_sparse_regression_recovers_a_law_from_a_noise_free_signal():
    """d̂ given exactly (a closed-form law of known variables, tiny std):
    OMP with the block cross-validation finds exactly its two terms."""
    rec, x, v, _ = truth("cubic")
    r = reconstruct(mass_spring_damper(), rec, "v", params={"c": C},
                    options=ReconstructOptions(q=10.0))
    xs, vs = r.variables["q_spring"], r.variables["v.f"]
    s = np.sqrt(np.mean(vs ** 2))
    r.d = 3.0 * vs * np.abs(vs) - 2.5 * np.tanh(vs / (0.1 * s))
    r.d_std = np.full_like(r.d, 1e-6)
    law = discover_law(r, options=DiscoverOptions(trim=0.0))
    got = {tm.name: tm.coef for tm in law.terms}
    assert set(got) == {"|v.f|·v.f", f"tanh(v.f/{0.1 * s:.3g})"}
    assert got["|v.f|·v.f"] == pytest.approx(3.0, rel=1e-3)
    assert law.rms_residual < 1e-2 * law.rms_d
    del xs


def test_augment_port_adds_an_integrated_random_walk():
    g, aug = augment_port(mass_spring_damper(), "v")
    assert aug.kind == "effort" and aug.unit == "N"
    assert aug.d in g.signal_states and aug.r in g.signal_states
    assert g.signal_states[aug.d].rhs == g.signal_states[aug.r].state
    assert aug.r in g.process_noise and aug.d not in g.process_noise
    with pytest.raises(GraphError):
        augment_port(mass_spring_damper(), "mass")


@pytest.mark.parametrize("kw", [dict(q=-1.0), dict(grid=1), dict(tau_max=2.0), dict(scale=0.0)])
def test_reconstruct_options_are_validated(kw):
    with pytest.raises(OptionError):
        ReconstructOptions(**kw)


@pytest.mark.parametrize("kw", [dict(max_terms=0), dict(folds=1), dict(trim=0.5)])
def test_discover_options_are_validated(kw):
    with pytest.raises(OptionError):
        DiscoverOptions(**kw)


def test_reconstruction_on_a_linear_case_equals_the_closed_form_rts_smoother():
    """Declared graph = truth (no missing force): the augmented model is
    linear, the unscented filter and smoother are exact, and d̂, its std
    must equal a hand-written Kalman filter and RTS smoother (Rauch, Tung &
    Striebel 1965) on the same discretisation: RK4, one step per sample,
    input held over the sample, process noise diag(0, 0, 0, q²)·dt."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 5.0, 0.01)
    x_true = 0.1 * np.sin(3.0 * t)
    y = x_true + NOISE * rng.standard_normal(t.size)
    rec = Experiment.from_arrays(t, {"F": force(t), "x": y}, units={"F": "N", "x": "m"},
                                 roles={"F": "input", "x": "output"}, noise_std={"x": NOISE})
    q = 30.0
    ukf = UKFOptions(method="rk4", substeps=1, hold="zoh")
    r = reconstruct(mass_spring_damper(), rec, "v", params={"c": C},
                    options=ReconstructOptions(q=q, ukf=ukf))
    names = r.model.states
    ip, iq = names.index("p_mass"), names.index("q_spring")
    i_d, i_r = names.index(r.port.d), names.index(r.port.r)
    A = np.zeros((4, 4))
    A[ip, ip], A[ip, iq], A[ip, i_d] = -C / M, -K, 1.0      # dp/dt = F − k q − c p/m + d
    A[iq, ip] = 1.0 / M                                       # dq/dt = p/m
    A[i_d, i_r] = 1.0                                         # dd/dt = r
    B = np.zeros(4)
    B[ip] = 1.0
    h = 0.01
    Ah = A * h
    powers = [np.linalg.matrix_power(Ah, j) for j in range(5)]
    Phi = sum(powers[j] / math.factorial(j) for j in range(5))          # one RK4 step
    Gam = h * sum(powers[j] / math.factorial(j + 1) for j in range(4)) @ B
    Q = np.zeros((4, 4))
    Q[i_r, i_r] = q ** 2 * h
    Hrow = np.zeros(4)
    Hrow[iq] = 1.0
    u = force(t)
    n = t.size
    xf, Pf, xp, Pp = np.zeros((n, 4)), np.zeros((n, 4, 4)), np.zeros((n, 4)), np.zeros((n, 4, 4))
    x, P = r.x0.copy(), r.P0.copy()
    for k in range(n):
        if k:
            x, P = Phi @ x + Gam * u[k - 1], Phi @ P @ Phi.T + Q
        xp[k], Pp[k] = x, P
        S = Hrow @ P @ Hrow + NOISE ** 2
        Kg = P @ Hrow / S
        x, P = x + Kg * (y[k] - Hrow @ x), P - np.outer(Kg, Hrow @ P)
        xf[k], Pf[k] = x, P
    xs, Ps = xf.copy(), Pf.copy()
    for k in range(n - 2, -1, -1):
        G = Pf[k] @ Phi.T @ np.linalg.inv(Pp[k + 1])
        xs[k] = xf[k] + G @ (xs[k + 1] - xp[k + 1])
        Ps[k] = Pf[k] + G @ (Ps[k + 1] - Pp[k + 1]) @ G.T
    scale = np.max(np.abs(xs[:, i_d]))
    assert np.max(np.abs(r.d - xs[:, i_d])) < 1e-6 * scale
    assert np.allclose(r.d_std, np.sqrt(Ps[:, i_d, i_d]), rtol=1e-5)
    assert np.allclose(r.variables["v.f"], xs[:, ip] / M, rtol=1e-6, atol=1e-9)


def _thermal_record():
    """thermal_two_node's own equations (hand-written, temperatures), heater
    power and ambient as multisines, by solve_ivp; both temperatures
    measured (noise 0.05 K declared)."""
    c1, c2, r12, r2a = 500.0, 2000.0, 0.05, 0.1
    t = np.arange(0.0, 6000.0, 2.0)

    def P(t):
        return 200.0 + 100.0 * np.sin(2 * np.pi * t / 600) + 60.0 * np.sin(2 * np.pi * t / 211)

    def Ta(t):
        return np.sin(2 * np.pi * t / 900)

    def rhs(t, s):
        q12 = (s[0] - s[1]) / r12
        return [(P(t) - q12) / c1, (q12 - (s[1] - Ta(t)) / r2a) / c2]

    sol = solve_ivp(rhs, (t[0], t[-1]), [0.0, 0.0], t_eval=t, method="LSODA", rtol=1e-9,
                    atol=1e-12, max_step=1.0)
    rng = np.random.default_rng(3)
    cols = {"P": P(t), "T_a": Ta(t), "T1": sol.y[0] + 0.05 * rng.standard_normal(t.size),
            "T2": sol.y[1] + 0.05 * rng.standard_normal(t.size)}
    return Experiment.from_arrays(t, cols, units={"P": "W", "T_a": "K", "T1": "K", "T2": "K"},
                                  roles={"P": "input", "T_a": "input", "T1": "output",
                                         "T2": "output"},
                                  noise_std={"T1": 0.05, "T2": 0.05})


def test_a_port_the_record_does_not_observe_is_refused_and_skipped():
    """The flow missing at the ambient's 0-junction (its effort imposed by
    the ambient source) is not observed: the smoother's std is not finite
    there. discover_law refuses it with a NumericalError naming the port
    (before: scikit-learn's InvalidParameterError from orthogonal_mp with
    no usable column, which stopped loop_with_discovery), and the loop's
    discovery skips that port and goes on with the others."""
    from types import SimpleNamespace

    from bondgraph.catalog.reference import thermal_two_node
    from bondgraph.diagnose.discover.effect import discovered_effect
    from bondgraph.diagnose.settings import LoopSettings
    from bondgraph.errors import NumericalError

    rec = _thermal_record()
    r = reconstruct(thermal_two_node(), rec, "ambient_node")
    assert not np.all(np.isfinite(r.d_std))
    with pytest.raises(NumericalError, match="ambient_node"):
        discover_law(r)
    logs = []
    discovered_effect(thermal_two_node(), rec, LoopSettings(params=["Rth12", "Rth2a"]),
                      SimpleNamespace(steps=[]), ports=["ambient_node", "node1"],
                      log=logs.append)
    assert any(line.startswith("discovery at 'ambient_node' skipped") for line in logs), logs


def test_a_port_beside_a_geared_inertia_is_reconstructed():
    """The DC motor with a rigid gear (``dc_motor_gear``): the motor's
    inertia J_m is in derivative causality (its momentum follows the
    load's), so ``p_J_m`` is no state of the model; reconstructing at the
    motor shaft's junction ``w_m`` raised ``ValueError: 'p_J_m' is not in
    list`` (the port's scale and variables read every bonded inertia),
    which stopped ``loop_with_discovery`` on both DC-motor cases of the
    discovery bench. Now the dependent inertia is left out, and the torque
    reconstructed at either shaft is the missing load torque
    −0.02·ω/(1 + |ω|/3) of the hand-written truth (solve_ivp), at the motor
    shaft divided by the gear ratio n = 10: within 30 % of its RMS
    (measured 20 % at both)."""
    from bondgraph.catalog.reference import dc_motor_gear

    ra, la, km, jm, n, jl, bl = 1.2, 0.005, 0.08, 2e-4, 10.0, 5e-2, 2e-3
    t = np.arange(0.0, 10.0, 0.01)

    def volt(s):
        return 5 * np.sin(2 * np.pi * 0.15 * s) + 3 * np.sin(2 * np.pi * 0.6 * s + 1)

    def tau(w):
        return 0.02 * w / (1 + np.abs(w) / 3.0)

    def rhs(s, z):
        i, w = z
        return [(volt(s) - ra * i - km * n * w) / la,
                (n * km * i - bl * w - tau(w)) / (jl + n ** 2 * jm)]

    sol = solve_ivp(rhs, (0.0, t[-1]), [0.0, 0.0], t_eval=t, method="LSODA", rtol=1e-9,
                    atol=1e-12, max_step=0.005)
    w = sol.y[1]
    y = w + 0.01 * np.random.default_rng(0).standard_normal(t.size)
    rec = Experiment.from_arrays(t, {"V": volt(t), "w_L": y}, units={"V": "V", "w_L": "rad/s"},
                                 roles={"V": "input", "w_L": "output"}, noise_std={"w_L": 0.01})
    opts = ReconstructOptions(ukf=UKFOptions(hold="linear"))
    mid = slice(50, -50)
    d_true = -tau(w)[mid]
    for port, gain in (("w_m", n), ("w_L", 1.0)):
        r = reconstruct(dc_motor_gear(), rec, port, options=opts)
        assert "p_J_m" not in r.variables and r.primary == [f"{port}.f"]
        assert rms(gain * r.d[mid] - d_true) < 0.3 * rms(d_true), port


def test_a_walk_std_near_its_prior_bound_is_not_observed():
    """A smoother is never less certain than its prior: the walk's std with
    no measurement is sqrt((σ_d0 + σ_r0 T)² + q² (T + T³/3)); a smoothed std
    above 0.9 of that is a direction the record told next to nothing (or
    the rounding of one: 5.8e79 was seen on one build where another gave
    inf) and becomes inf, so that discover_law refuses the port the same
    way on every build. By hand: σ_d0 = 2, σ_r0 = 0.5, q = 0.1, T = 0, 1,
    2 s: bounds sqrt(4), sqrt(6.25 + 0.0133), sqrt(9 + 0.0467) = 2, 2.50267,
    3.00777."""
    from types import SimpleNamespace

    from bondgraph.diagnose.discover.reconstruct import UNOBSERVED_SHARE, _walk_std

    assert UNOBSERVED_SHARE == 0.9
    t = np.array([0.0, 1.0, 2.0])
    bound = np.sqrt((2.0 + 0.5 * t) ** 2 + 0.01 * (t + t ** 3 / 3))
    np.testing.assert_allclose(bound, [2.0, 2.502665, 3.007768], rtol=1e-6)
    P = np.zeros((3, 3, 3))
    P[:, 0, 0] = [1.0, (0.9 * bound[1]) ** 2 * 0.99, (0.9 * bound[2]) ** 2 * 1.01]
    P[:, 1, 1] = 1.0
    problem = SimpleNamespace(model=SimpleNamespace(states=["d", "r", "x"]), t=t,
                              P0=np.diag([4.0, 0.25, 1.0]))
    std = _walk_std(SimpleNamespace(P=P), problem, SimpleNamespace(d="d", r="r"), 0.1)
    np.testing.assert_allclose(std[:2], [1.0, 0.9 * bound[1] * np.sqrt(0.99)])
    assert std[2] == np.inf
