"""The free run behind the state scales of the prior
(:func:`bondgraph.inference.prior.simulated_rms`)."""
import numpy as np
import pytest

from bondgraph.inference import prior
from bondgraph.inference.options import Discretisation
from bondgraph.numerics.model import Model


def test_singular_ros2_matrix_ends_the_run_not_the_loop(monkeypatch):
    """A ROS2 step whose matrix I − γhJ is singular (numpy's inv raises) ends
    the free run there, like a diverging state (it stopped a loop's
    confirmation on a two-mass chain with an end stop, LinAlgError "Singular
    matrix"). A run that stops before its end gives no scale (zeros: the
    other rules of :func:`state_scales` take over); cut to the samples it
    reached, the same steps give the RMS of a hand-written run."""
    m = Model.load("mass_spring_damper")
    t = np.arange(50) * 0.01
    u = np.ones((50, m.n_u))
    x0 = np.array([0.3] * m.n_x)
    real = prior.make_step(m, "ros2", 2)
    calls = []

    def step(x, uk, th, dt, du):
        calls.append(1)
        if len(calls) == 10:
            raise np.linalg.LinAlgError("Singular matrix")
        return real(x, uk, th, dt, du)

    monkeypatch.setattr(prior, "make_step", lambda *a, **k: step)
    got = prior.simulated_rms(m, t, u, m.theta0, x0, Discretisation("ros2", 2, backend="numpy"))
    np.testing.assert_array_equal(got, np.zeros(m.n_x))
    calls.clear()
    got = prior.simulated_rms(m, t[:10], u[:10], m.theta0, x0,
                              Discretisation("ros2", 2, backend="numpy"))
    xs = [x0[None]]
    for k in range(9):
        xs.append(real(xs[-1], u[k][None], m.theta0[None], 0.01, None))
    ref = np.sqrt(np.mean(np.concatenate(xs) ** 2, axis=0))
    np.testing.assert_allclose(got, ref, rtol=1e-12)


def _damper(c: float):
    """A mass on a damper of coefficient ``c`` (negative: it feeds the motion,
    v grows as e^(−c t / m)), its velocity measured as 3·v."""
    from bondgraph import BondGraph

    g = BondGraph(f"damper_{'neg' if c < 0 else 'pos'}", "mass on a damper")
    F = g.input("F", "N", 0.0, "force")
    m = g.param("m", 1.0, "kg", (0.1, 10.0), "mass")
    cc = g.param("c", c, "N*s/m", (-10.0, 10.0), "damping")
    v = g.one("v")
    g.connect(g.Se("force", F), v)
    g.connect(v, g.I("mass", m))
    g.connect(v, g.R("damper", cc))
    g.sensor("y", 3 * v.f, unit="m/s")
    return Model.from_graph(g, functions=("f", "h", "dfdx", "f_dfdx"))


def test_a_diverging_free_run_gives_no_scale_and_the_sensors_give_one():
    """A free run that grows without bound (v ∝ e^(5t), non-finite after
    about 142 s) measured the blow-up, not the state: a user's DC motor with
    a Dahl friction candidate got a prior spread of 8e76 and every sigma
    point diverged at the first sample. It gives zeros, with numpy's steps
    and the compiled ones; the state's scale then comes from its sensor,
    std(y)/|∂h/∂x| = std(y)/3, with ∂h/∂x by central differences for a
    model generated without dhdx (the loop's candidates)."""
    t = np.arange(2000) * 0.1
    u = np.zeros((t.size, 1))
    neg, pos = _damper(-5.0), _damper(5.0)
    assert not hasattr(neg, "dhdx")
    for backend in ("numpy", "numba"):
        disc = Discretisation("rk4", 2, "zoh", backend=backend)
        np.testing.assert_array_equal(
            prior.simulated_rms(neg, t, u, neg.theta0, np.ones(1), disc), np.zeros(1))
        # the stable one decays from 1 at e^(−5t): RMS over 2000 samples ≈ sqrt(1/(2·5·0.1)/2000)
        got = prior.simulated_rms(pos, t, u, pos.theta0, np.ones(1), disc)
        assert got[0] == pytest.approx(np.sqrt(1 / (1 - np.exp(-1.0)) / 2000), rel=0.01)
    y = 3 * np.sin(t)[:, None]          # driven from rest by a constant force: diverges too
    scale, rules = prior.state_scales(neg, t, np.ones((t.size, 1)), y, neg.theta0, np.zeros(1),
                                      Discretisation("rk4", 2, "zoh", backend="numpy"))
    assert rules == ["sensors"]
    assert scale[0] == pytest.approx(np.std(y) / 3, rel=1e-6)


def test_a_record_longer_than_the_scale_window_uses_its_first_samples():
    """A record longer than ``samples`` (the loop's first call on a user's
    65 062-sample Silverbox record raised "cannot reshape array of size
    48796 into shape (20000, newaxis)"): the RMS is that of the first
    ``samples`` samples, the same as for the record cut there, against a
    hand-written RK4 run of the same steps."""
    m = Model.load("mass_spring_damper")
    n, keep = 400, 150
    t = np.arange(n) * 0.01
    u = np.sin(t)[:, None] * np.ones((1, m.n_u))
    x0 = np.array([0.1] * m.n_x)
    disc = Discretisation("rk4", 1, "zoh", backend="numpy")
    got = prior.simulated_rms(m, t, u, m.theta0, x0, disc, samples=keep)
    cut = prior.simulated_rms(m, t[:keep], u[:keep], m.theta0, x0, disc, samples=keep)
    np.testing.assert_array_equal(got, cut)
    f = lambda x, uk: m.f(x[None], uk[None], m.theta0[None])[0]
    xs, x = [], x0.copy()
    for k in range(keep):
        xs.append(x)
        k1 = f(x, u[k]); k2 = f(x + 0.005 * k1, u[k]); k3 = f(x + 0.005 * k2, u[k])
        k4 = f(x + 0.01 * k3, u[k])
        x = x + 0.01 / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    np.testing.assert_allclose(got, np.sqrt(np.mean(np.array(xs) ** 2, axis=0)), rtol=1e-12)


def test_a_stiff_model_rk4_cannot_run_takes_the_scale_of_its_ros2_run():
    """A mass of 1 kg on a damper of 5000 N s/m (rate 5000 /s), pushed by
    1 N from rest, at 0.05 s per RK4 step: |λh| = 250, far outside RK4's
    stability region, the run diverges. The scale is that of the L-stable
    ROS2 run with the same steps: the velocity sits at F/c = 2e-4 m/s
    after the first step, its RMS over 2000 samples within 1 % of it."""
    t = np.arange(2000) * 0.1
    u = np.ones((t.size, 1))
    stiff = _damper(5.0)
    th = stiff.theta0.copy()
    th[stiff.param_index("c")] = 5000.0
    for backend in ("numpy", "numba"):
        got = prior.simulated_rms(stiff, t, u, th, np.zeros(1),
                                  Discretisation("rk4", 2, "zoh", backend=backend))
        assert got[0] == pytest.approx(2e-4, rel=0.01)
        bare = prior._free_run_rms(stiff, t, u, th, np.zeros(1),
                                   Discretisation("rk4", 2, "zoh", backend=backend))
        assert bare is None                                     # RK4 alone diverged


def test_a_candidate_inherits_the_scales_of_the_states_it_shares():
    """A loop candidate's problem (:meth:`Problem.with_model`) takes the
    scales of the states it shares with the loop's model, not those of its
    own free run: the default loop's Dahl friction at the body's pitch had
    a finite but wild free run at its first grid value (RMS 3.6e16 of the
    pitch momentum, declared scale 0.06) and every grid point failed at the
    first sample. Here the loop's model is a mass on a damper of +5 N s/m
    and the candidate the same mass with the damper at −5 (v ∝ e^(5t), a
    free run that reaches 1e86 within the record but stays finite): the
    candidate's prior is the loop model's, to the bit, and the candidate's
    own run would have given a scale beyond 1e80. A new state whose run
    leaves an inherited scale by more than WILD_RUN takes the other rules
    (here the sensor's scale)."""
    from bondgraph.inference.options import UKFOptions
    from bondgraph.inference.problem import make_problem

    t = np.arange(400) * 0.1              # e^(5·40) = 7e86: finite, wild
    u = np.ones((t.size, 1))
    y = 3 * np.sin(t)[:, None]
    pos, neg = _damper(5.0), _damper(-5.0)
    base = make_problem(pos, (t, u, y), ukf=UKFOptions(method="rk4", substeps=2))
    cand = base.with_model(neg)
    assert base.scales["p_mass"] > 0
    np.testing.assert_array_equal(cand.P0, base.P0)
    assert cand.scales == base.scales
    own = prior.simulated_rms(neg, t, u, neg.theta0, base.x0, Discretisation("rk4", 2))
    assert np.isfinite(own[0]) and own[0] > 1e80
    # a new state beside the wild one (a second mass on a +5 damper, its
    # velocity measured as 3·v): its own run is tame, but the run is judged
    # as a whole, so it takes its sensor's scale, std(y2)/3
    from bondgraph import BondGraph

    g = BondGraph("two", "a wild mass and a new one")
    F = g.input("F", "N", 0.0, "force")
    for name, c in (("a", -5.0), ("b", 5.0)):
        v = g.one(f"v_{name}")
        g.connect(g.Se(f"force_{name}", F), v)
        g.connect(v, g.I(f"mass_{name}", g.param(f"m_{name}", 1.0, "kg", (0.1, 10), "mass")))
        g.connect(v, g.R(f"damper_{name}", g.param(f"c_{name}", c, "N*s/m", (-10, 10), "d")))
        g.sensor(f"y_{name}", 3 * v.f, unit="m/s")
    two = Model.from_graph(g, functions=("f", "h", "dfdx", "f_dfdx"))
    y2 = np.column_stack([y[:, 0], 2 * np.cos(t)])
    wild = two.states[0]
    scale, rules = prior.state_scales(two, t, u, y2, two.theta0, np.zeros(2),
                                      Discretisation("rk4", 2), {wild: 0.2})
    assert rules == ["inherited", "sensors"] and scale[0] == 0.2
    assert scale[1] == pytest.approx(np.std(y2[:, 1]) / 3, rel=1e-6)
    tame = prior.simulated_rms(two, t, u, two.theta0, np.zeros(2), Discretisation("rk4", 2))
    assert tame[1] == pytest.approx(0.2, rel=0.05)     # F/c = 0.2 m/s: its own run's scale
    scale, rules = prior.state_scales(two, t, u, y2, two.theta0, np.zeros(2),
                                      Discretisation("rk4", 2), {wild: 1e90})
    assert rules == ["inherited", "simulation"] and scale[1] == tame[1]
