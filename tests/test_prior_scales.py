"""The free run behind the state scales of the prior
(:func:`bondgraph.inference.prior.simulated_rms`)."""
import numpy as np

from bondgraph.inference import prior
from bondgraph.inference.options import Discretisation
from bondgraph.numerics.model import Model


def test_singular_ros2_matrix_ends_the_run_not_the_loop(monkeypatch):
    """A ROS2 step whose matrix I − γhJ is singular (numpy's inv raises) ends
    the free run there, like a diverging state, and the RMS is that of the
    samples before it (it stopped a loop's confirmation on a two-mass chain
    with an end stop, LinAlgError "Singular matrix")."""
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
    xs = [x0[None]]
    for k in range(9):
        xs.append(real(xs[-1], u[k][None], m.theta0[None], 0.01, None))
    ref = np.sqrt(np.mean(np.concatenate(xs) ** 2, axis=0))
    np.testing.assert_allclose(got, ref, rtol=1e-12)


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
