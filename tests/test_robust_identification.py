"""The accept rule's identification test judged by the robust (sandwich) std
where the Cramér-Rao std of a misspecified refit is too small
(diagnose.accept.robust_std_needed, unidentified_effect; runner.decided).

A user's DC motor: voltage in, armature current and shaft speed measured
(noise 0.02 A and 0.5 rad/s), two inertias on the one shaft (rotor and load:
the record identifies only their sum) and the library's Coulomb friction
already accepted, whose tanh width (2 % of the speed scale) is far wider than
the truth's. The record is simulated by scipy from the equations written by
hand. A speed-sensor gain g then rescales the speed the friction sees and
gains hundreds of nats by moving along a ridge with the torque constant and
the inertias (w_meas = (1 + g) w: k_t/(1 + g), J/(1 + g)² give the same
record but for the friction's width): g ≈ −0.3 where the truth has none, and
k_t 30 % off. Its Cramér-Rao std stays within 10 % of k_t, so the rule read
k_t as determined and the loop accepted the gain on a user's geared motor
(k_t 0.060 -> 0.041); the sandwich std, which allows for the misfit, is
several times larger, and the rule now refuses the gain.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

from bondgraph import BondGraph, apply_effect
from bondgraph.data.records import Experiment
from bondgraph.diagnose.accept import robust_std_needed, unidentified_effect
from bondgraph.diagnose.confirm import confirm
from bondgraph.diagnose.effects import Target
from bondgraph.diagnose.fit import Context, fit_model, model_of
from bondgraph.diagnose.result import Candidate
from bondgraph.diagnose.runner import chosen_numerics, decided
from bondgraph.diagnose.scales import operating_scales
from bondgraph.diagnose.settings import LoopSettings

RA, LA, KM, J, B, FC, EPS = 1.0, 0.005, 0.06, 1.6e-3, 2e-4, 0.02, 0.01
NOISE = (0.02, 0.5)
PARAMS = ["Ra", "La", "km", "J_rotor", "J_load", "b", "coulomb.shaft.Fc"]


def motor() -> BondGraph:
    """The user's graph: rotor and load inertia on one shaft, a viscous
    damper, and the Coulomb friction the loop accepted (width 3 rad/s, 2 %
    of the speed scale, as the library sets it)."""
    g = BondGraph("dc_motor_two_inertias", "DC motor and its load on one shaft.")
    Ra = g.param("Ra", 1.2, "ohm", (0.1, 10.0), "armature resistance")
    La = g.param("La", 0.005, "H", (0.0005, 0.05), "armature inductance")
    km = g.param("km", 0.05, "N*m/A", (0.01, 0.5), "torque constant")
    J1 = g.param("J_rotor", 1e-3, "kg*m**2", (1e-5, 1e-1), "rotor inertia")
    J2 = g.param("J_load", 1e-3, "kg*m**2", (1e-5, 1e-1), "load inertia")
    b = g.param("b", 1e-4, "N*m*s/rad", (1e-6, 1e-2), "viscous friction")
    el = g.one("armature", domain="electrical")
    g.connect(g.Se("supply", g.input("V", "V", 0.0, "armature voltage")), el)
    g.connect(el, g.R("R_a", Ra))
    g.connect(el, g.I("L_a", La))
    shaft = g.one("shaft", domain="rotation")
    gy = g.GY("emf", km)
    g.connect(el, gy.p1)
    g.connect(gy.p2, shaft)
    g.connect(shaft, g.I("rotor", J1))
    g.connect(shaft, g.I("load", J2))
    g.connect(shaft, g.R("damper", b))
    apply_effect(g, "coulomb", ("junction", "shaft"), {"Fc": 0.01, "eps": 3.0})
    g.sensor("i", el.f, unit="A", noise_std=NOISE[0])
    g.sensor("w", shaft.f, unit="rad/s", noise_std=NOISE[1])
    return g


def record(seed: int, name: str, seconds: float = 10.0) -> Experiment:
    """Voltage steps held 0.5 s (±12 V), 100 Hz; the truth
    L di/dt = V − R i − k_t w, J dw/dt = k_t i − b w − Fc tanh(w/0.01) (J the
    two inertias' sum) by scipy's LSODA between steps (rtol 1e-9)."""
    rng = np.random.default_rng(seed)
    n = int(round(seconds / 0.01)) + 1
    t = np.arange(n) * 0.01
    v = np.repeat(rng.uniform(-12.0, 12.0, n // 50 + 1), 50)[:n]

    def rhs(_, x, u):
        i, w = x
        return [(u - RA * i - KM * w) / LA, (KM * i - B * w - FC * np.tanh(w / EPS)) / J]

    X = np.zeros((n, 2))
    for a in range(0, n - 1, 50):
        e = min(a + 50, n - 1)
        sol = solve_ivp(rhs, (t[a], t[e]), X[a], method="LSODA", t_eval=t[a:e + 1],
                        rtol=1e-9, atol=1e-9, args=(v[a],))
        X[a:e + 1] = sol.y.T
    y = X + rng.normal(0.0, NOISE, X.shape)
    return Experiment.from_arrays(
        t, {"V": v, "i": y[:, 0], "w": y[:, 1]}, units={"V": "V", "i": "A", "w": "rad/s"},
        roles={"V": "input", "i": "output", "w": "output"},
        noise_std={"i": NOISE[0], "w": NOISE[1]}, name=name)


def test_a_sensor_gain_along_a_ridge_is_refused_by_the_sandwich_std():
    """The fit with the Coulomb friction recovers k_t (within 3 std of 0.06);
    the sensor gain's refit is far from the truth's g = 0 with k_t moved
    along the ridge, its Cramér-Rao std grown more than 10-fold but within
    10 % of its value (the rule alone would read it as determined); the
    runner computes the sandwich std for k_t alone of what the rule needs,
    and the rule then names the gain and k_t, the sandwich std above 10 %."""
    g = motor()
    exp = record(1, "rec")
    settings = chosen_numerics(g, exp, LoopSettings(params=PARAMS, validation=record(
        2, "held_out")), log=lambda s: None)
    ctx = Context.on(exp, settings, model_of(g), lambda s: None, False)
    current = fit_model(ctx, g, PARAMS, None, "declared")
    km0 = current.estimates()["km"]
    assert abs(km0 - KM) < 3 * current.std["km"]
    assert {"J_rotor", "J_load"} <= set(current.flat)        # only their sum is known
    scales = operating_scales(ctx, current)
    cand = Candidate("sensor_gain", "", Target("sensor", "w"), "score", 400.0, 1, 0.0, 398.0,
                     values={"g": -0.03})
    conf = confirm(ctx, current, cand, scales, "gain")
    assert conf is not None
    after = conf.fit
    est = after.estimates()
    assert est["sensor_gain.w.g"] < -0.15                     # truth: no gain at all
    assert est["km"] < 0.85 * KM                              # k_t moved along the ridge
    assert after.nll < current.nll - 50                       # hundreds of nats here
    assert {"km", "sensor_gain.w.g"} <= set(after.flat)
    s0, s1 = current.std["km"], after.std["km"]
    assert s1 > 10 * s0 and s1 < 0.1 * est["km"]              # inflated, yet "determined"
    assert unidentified_effect(current, after) == ""          # by the Cramér-Rao std alone
    assert robust_std_needed(current, after) == ["km"]
    decided(ctx, current, after, 1, True, "sensor_gain @ w", added=[cand])
    assert after.std_robust["km"] > 0.1 * est["km"]           # the sandwich std says otherwise
    assert robust_std_needed(current, after) == []
    reason = unidentified_effect(current, after)
    assert reason.startswith("the record does not identify sensor_gain.w.g apart from km ")
    assert "km's robust std is" in reason


def test_cramer_rao_std_of_a_singular_information_is_the_reparametrised_models():
    """Two parallel dampers c, c2 (identical information columns: the record
    sees c + c2): cr_std gives m and k the std of the model written with the
    sum s = c + c2 alone (its 3 x 3 information inverted by hand's rule,
    numpy's inv), and c, c2 none; the plain inverse read rounding noise.
    A regular information is inverted as before."""
    from bondgraph.diagnose.fit import cr_std

    a = np.array([[5.3647e7, -1.9125e6, 5.6485e5], [-1.9125e6, 7.4306e4, 1.3889e4],
                  [5.6485e5, 1.3889e4, 1.9311e6]])           # (m, k, s)
    F = np.zeros((4, 4))
    F[:3, :3] = a
    F[3, :3] = F[:3, 3] = a[2]                              # c2's column is c's
    F[3, 3] = a[2, 2]
    ref = np.sqrt(np.diag(np.linalg.inv(a)))
    got = cr_std(F, ["m", "k", "c", "c2"])
    assert got["c"] is None and got["c2"] is None
    assert np.allclose([got["m"], got["k"]], ref[:2], rtol=1e-9)
    reg = np.array([[4.0, 1.0], [1.0, 2.0]])
    assert np.allclose(list(cr_std(reg, ["a", "b"]).values()),
                       np.sqrt(np.diag(np.linalg.inv(reg))), rtol=1e-12)
