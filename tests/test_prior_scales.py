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
