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
