"""An RK4 step outside its stability region is never chosen (issue 26).

A user's mass on a Maxwell element (a spring k2 in series with a damper c2,
beside a damper b to ground), driven by a force, its velocity measured at
10 Hz. The Maxwell element's own mode is fast: with m 1 kg, b 1 N·s/m,
k2 100 N/m and c2 1 N·s/m the state matrix of (p, q) is
[[−b/m, −k2], [1/m, −k2/c2]], whose eigenvalues are about −2.0 and −99 1/s
(hand-derived; numpy's ``eigvals`` below). At dt = 0.1 s the fast one puts
RK4's z = λ·h at −9.9 per substep, far outside its stability region
(|R(z)| <= 1 on the real axis down to z ≈ −2.785). Along the record's own
trajectory the fast state sits on its slow manifold, so a step from the
reference state errs little and the one-step check passed RK4 with fewer
substeps than stability allows; the filter's sigma points, off that
manifold, then grew by |R| every substep. The check now refuses such a step.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph import BondGraph
from bondgraph.data.records import Experiment
from bondgraph.inference import ukf as ukf_mod
from bondgraph.inference.discretise import choose_discretisation
from bondgraph.inference.options import Discretisation
from bondgraph.inference.problem import make_problem
from bondgraph.numerics.model import Model

M, B, K2, C2 = 1.0, 1.0, 100.0, 1.0
DT = 0.1
NOISE = 0.01        # m/s


def maxwell_graph() -> BondGraph:
    """The user's graph, at the truth; process noise on the momentum."""
    g = BondGraph("user_maxwell_mass", "A mass on a damper and a Maxwell element, force-driven.")
    m = g.param("m", M, "kg", (0.1, 10.0), "mass")
    b = g.param("b", B, "N*s/m", (0.1, 10.0), "damper to ground")
    k2 = g.param("k2", K2, "N/m", (10.0, 1000.0), "Maxwell spring")
    c2 = g.param("c2", C2, "N*s/m", (0.1, 10.0), "Maxwell damper")
    v = g.one("v", domain="translation")
    g.connect(g.Se("push", g.input("F", "N", 0.0, "applied force")), v)
    mass = g.I("mass", m)
    g.connect(v, mass)
    g.connect(v, g.R("ground", b))
    node = g.zero("maxwell", domain="translation")
    g.connect(v, node)
    g.connect(node, g.C("spring2", stiffness=k2))
    g.connect(node, g.R("damper2", c2))
    g.set_process_noise(mass.p, 0.05)
    g.sensor("v", v.f, unit="m/s", noise_std=NOISE)
    return g


def force(t):
    t = np.asarray(t, float)
    return 0.5 * np.sin(2 * np.pi * 0.2 * t) + 0.3 * np.sin(2 * np.pi * 0.53 * t + 1.0)


@pytest.fixture(scope="module")
def problem():
    """The graph bound to a 60 s record simulated by scipy (Radau, rtol
    1e-10) from the hand-written equations, the force held linear."""
    t = np.arange(601) * DT

    def rhs(tt, z):
        p, q = z
        return [float(force(tt)) - B * p / M - K2 * q, p / M - K2 * q / C2]

    sol = solve_ivp(rhs, (0, t[-1]), [0.0, 0.0], t_eval=t, method="Radau", rtol=1e-10,
                    atol=1e-12)
    rng = np.random.default_rng(3)
    exp = Experiment.from_arrays(
        t, {"F": force(t), "v": sol.y[0] / M + NOISE * rng.standard_normal(t.size)},
        units={"F": "N", "v": "m/s"}, roles={"F": "input", "v": "output"},
        noise_std={"v": NOISE}, name="maxwell_rec")
    model = Model.from_graph(maxwell_graph())
    return make_problem(model, exp)


def rk4_growth(z):
    """|R(z)| of RK4's stability function (hand formula)."""
    return np.abs(1 + z + z ** 2 / 2 + z ** 3 / 6 + z ** 4 / 24)


def test_rk4_is_given_the_substeps_its_stability_needs(problem, monkeypatch):
    """RK4 gets the fewest substeps that keep the hand-derived fast mode
    inside its stability region; without the rule the one-step check takes
    fewer, and the filter's NLL at those is far from ROS2(32)'s."""
    lam = np.linalg.eigvals(np.array([[-B / M, -K2], [1 / M, -K2 / C2]]))
    fast = lam[np.argmax(np.abs(lam))].real
    assert fast == pytest.approx(-99.0, rel=0.01)
    need = next(n for n in range(1, 64) if rk4_growth(fast * DT / n) <= 1.0)
    assert need == 4                          # 9.9 / 4 = 2.47 <= 2.785 < 9.9 / 3
    th = problem.model.theta0
    chosen = choose_discretisation(problem, th, given={"method": "rk4", "hold": "linear"})
    assert chosen.ok and chosen.disc.substeps == need, chosen.line()
    # the failing steps are named as unstable, not as an error in σ
    assert "rk4(1): unstable" in chosen.line() or "rk4(3): unstable" in chosen.line(), \
        chosen.line()
    # without the stability rule the one-step check alone passed a coarser,
    # unstable RK4: the rule is what refuses it
    monkeypatch.setattr(ukf_mod, "rk4_unstable", lambda modes, h: np.zeros(np.size(h), bool))
    blind = choose_discretisation(problem, th, given={"method": "rk4", "hold": "linear"})
    assert blind.ok and blind.disc.substeps < need, blind.line()
    monkeypatch.undo()
    # ... and that step ruins the filter's likelihood, where the chosen one
    # agrees with a fine L-stable reference
    def nll(method, n):
        d = Discretisation(method=method, substeps=n, hold="linear",
                           backend=problem.disc.backend)
        return float(problem.conditioned_on(disc=d).nll(th).nll[0])
    ref = nll("ros2", 32)
    assert abs(nll("rk4", need) - ref) < 1.0
    bad = nll("rk4", blind.disc.substeps)
    assert not np.isfinite(bad) or bad - ref > 100.0, (bad, ref)


def test_the_default_choice_is_stable(problem):
    """Left to choose the method, the check takes an L-stable ROS2 or an RK4
    inside its stability region; its NLL agrees with the fine reference."""
    th = problem.model.theta0
    chosen = choose_discretisation(problem, th)
    d = chosen.disc
    if d.method == "rk4":
        assert rk4_growth(-99.0 * DT / d.substeps) <= 1.0
    ref = Discretisation(method="ros2", substeps=32, hold=d.hold, backend=d.backend)
    assert float(problem.conditioned_on(disc=d).nll(th).nll[0]) == pytest.approx(
        float(problem.conditioned_on(disc=ref).nll(th).nll[0]), abs=1.0)


# --- a friction law's stiff mode, only at velocity reversals -------------------

FC, EPS, MASS, DT_F = 2.0, 0.01, 1.0, 0.05
F_NOISE = 0.1         # m/s: a coarse tachometer


def friction_graph() -> BondGraph:
    """A user's mass with a smooth Coulomb friction F = F_c·tanh(v/ε) and a
    weak viscous damper, force-driven, its velocity measured at 20 Hz."""
    import sympy as sp

    g = BondGraph("user_tanh_friction", "A mass with smooth Coulomb friction, force-driven.")
    m = g.param("m", MASS, "kg", (0.1, 10.0), "mass")
    fc = g.param("Fc", FC, "N", (0.1, 20.0), "Coulomb friction force")
    b = g.param("b", 0.1, "N*s/m", (0.01, 10.0), "viscous damper")
    v = g.one("v", domain="translation")
    g.connect(g.Se("push", g.input("F", "N", 0.0, "applied force")), v)
    mass = g.I("mass", m)
    g.connect(v, mass)
    g.connect(v, g.R("viscous", b))
    g.connect(v, g.R("coulomb", effort=lambda f: fc * sp.tanh(f / EPS)))
    g.set_process_noise(mass.p, 0.02)
    g.sensor("v", v.f, unit="m/s", noise_std=F_NOISE)
    return g


@pytest.fixture(scope="module")
def friction_problem():
    """60 s at 20 Hz, simulated by scipy (Radau, rtol 1e-10) from the
    hand-written equation m·v' = F − F_c·tanh(v/ε) − b·v; the force
    reverses the mass every 2.5 s."""
    t = np.arange(1201) * DT_F

    def push(tt):
        return 5.0 * np.sin(2 * np.pi * 0.2 * np.asarray(tt, float))

    def rhs(tt, z):
        vv = z[0] / MASS
        return [float(push(tt)) - FC * np.tanh(vv / EPS) - 0.1 * vv]

    sol = solve_ivp(rhs, (0, t[-1]), [0.0], t_eval=t, method="Radau", rtol=1e-10, atol=1e-12)
    rng = np.random.default_rng(5)
    exp = Experiment.from_arrays(
        t, {"F": push(t), "v": sol.y[0] / MASS + F_NOISE * rng.standard_normal(t.size)},
        units={"F": "N", "v": "m/s"}, roles={"F": "input", "v": "output"},
        noise_std={"v": F_NOISE}, name="friction_rec")
    return make_problem(Model.from_graph(friction_graph()), exp)


def test_a_friction_reversal_asks_for_the_substeps_of_its_stiff_mode(friction_problem,
                                                                     monkeypatch):
    """The Jacobian at v = 0 is −F_c/(ε·m) = −200 1/s (hand-derived), z = −10
    per sample at 20 Hz: RK4 needs 4 substeps there, and only within the few
    samples of each reversal (every sample's modes are taken: a sparse
    subset can miss them). Without the rule the one-step check takes 3 (a
    coarse tachometer's noise hides the reversal's one-step error)."""
    lam = -FC / (EPS * MASS)
    need = next(n for n in range(1, 64) if rk4_growth(lam * DT_F / n) <= 1.0)
    assert need == 4
    pb, th = friction_problem, friction_problem.model.theta0
    chosen = choose_discretisation(pb, th, given={"method": "rk4", "hold": "linear"})
    assert chosen.ok and chosen.disc.substeps >= need, chosen.line()
    assert "rk4(3): unstable" in chosen.line(), chosen.line()
    monkeypatch.setattr(ukf_mod, "rk4_unstable", lambda modes, h: np.zeros(np.size(h), bool))
    blind = choose_discretisation(pb, th, given={"method": "rk4", "hold": "linear"})
    assert blind.ok and blind.disc.substeps < need, blind.line()
    monkeypatch.undo()

    def nll(method, n):
        d = Discretisation(method=method, substeps=n, hold="linear", backend=pb.disc.backend)
        return float(pb.conditioned_on(disc=d).nll(th).nll[0])

    # the chosen step's likelihood agrees with RK4's at 4 times its substeps
    n = chosen.disc.substeps
    assert nll("rk4", n) == pytest.approx(nll("rk4", 4 * n), abs=0.5)


def test_the_stable_substeps_of_the_maxwell_mode(problem):
    """:meth:`Problem.rk4_stable_substeps` (what a loop's confirmation
    refits a stiff candidate with) gives the hand-derived 4 from one
    substep, None where the step is already stable and for ROS2 (L-stable):
    z = −99·0.1/n is −3.3 at n = 3, outside RK4's region, and −2.475 at 4."""
    th = problem.model.theta0

    def at(method, n):
        d = Discretisation(method=method, substeps=n, hold="linear",
                           backend=problem.disc.backend)
        return problem.conditioned_on(disc=d).rk4_stable_substeps(th)

    assert rk4_growth(-99.0 * DT / 3) > 1.0 >= rk4_growth(-99.0 * DT / 4)
    assert at("rk4", 1) == 4
    assert at("rk4", 3) == 4
    assert at("rk4", 4) is None
    assert at("ros2", 1) is None
