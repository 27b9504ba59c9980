"""Input holds of the fixed-step integrators (bondgraph.numerics.integrators):
the first-order (linear) hold against the exact solution of a linear system
driven by a piecewise-linear input, its convergence order with RK4 and ROS2,
and the UKF with hold="linear" against filterpy-free hand propagation."""

import numpy as np
import pytest
from scipy.linalg import expm

from bondgraph.errors import OptionError
from bondgraph.inference.options import Discretisation, UKFOptions
from bondgraph.inference.ukf import discretisation_check, ukf_nll
from bondgraph.numerics.integrators import hold_inputs, make_step
from bondgraph.numerics.model import Model


def _exact_ramp_step(A, B, x, u0, u1, dt):
    """x(dt) of dx/dt = A x + B u(t), u linear from u0 to u1 over [0, dt]:
    the augmented-matrix exponential of [A B 0; 0 0 I/dt; 0 0 0] (Van Loan 1978)."""
    n, m = A.shape[0], B.shape[1]
    M = np.zeros((n + 2 * m, n + 2 * m))
    M[:n, :n] = A
    M[:n, n:n + m] = B
    M[n:n + m, n + m:] = np.eye(m) / dt
    E = expm(M * dt)
    return E[:n, :n] @ x + E[:n, n:n + m] @ u0 + E[:n, n + m:] @ (u1 - u0)


@pytest.fixture(scope="module")
def msd():
    return Model.load("mass_spring_damper")


def _matrices(model, th):
    """A, B of the (linear) mass-spring-damper from the generated Jacobian."""
    x = np.zeros((1, model.n_x))
    A = model.dfdx(x, np.zeros((1, 1)), th[None])[0]
    B = (model.f(x, np.ones((1, 1)), th[None]) - model.f(x, np.zeros((1, 1)), th[None]))[0][:, None]
    return A, B


def test_hold_inputs_definitions():
    u = np.array([[0.0, 1.0], [2.0, 1.0], [6.0, 3.0]])
    z = hold_inputs(u, "zoh")
    assert z.change is None and np.array_equal(z.start, u)
    m = hold_inputs(u, "mean")
    assert m.change is None and np.array_equal(m.start, [[1.0, 1.0], [4.0, 2.0], [6.0, 3.0]])
    lin = hold_inputs(u, "linear")
    assert np.array_equal(lin.start, u)
    assert np.array_equal(lin.change, [[2.0, 0.0], [4.0, 2.0], [0.0, 0.0]])
    uk, duk = lin.interval(1)
    assert np.array_equal(uk, [2.0, 1.0]) and np.array_equal(duk, [4.0, 2.0])
    with pytest.raises(OptionError, match="hold"):
        hold_inputs(u, "foh")
    assert UKFOptions(hold="linear").hold == "linear"


@pytest.mark.parametrize("method,order", [("rk4", 4), ("ros2", 2)])
def test_linear_hold_converges_to_the_exact_ramp_response(msd, method, order):
    """One interval of a ramp input: the error against the exact solution
    falls as h^(order+1) per step with the first-order hold; with the
    zero-order hold it stalls at the hold's own error."""
    th = msd.theta(m=2.0, k=80.0, c=1.0)
    A, B = _matrices(msd, th)
    x0 = np.array([0.3, -0.01])
    u0, u1 = np.array([1.0]), np.array([25.0])
    dt = 0.2
    exact = _exact_ramp_step(A, B, x0, u0, u1, dt)
    errs, errs_zoh = [], []
    for sub in (4, 8, 16):
        step = make_step(msd, method, sub)
        errs.append(np.abs(step(x0[None], u0[None], th[None], dt, (u1 - u0)[None])[0] - exact).max())
        errs_zoh.append(np.abs(step(x0[None], u0[None], th[None], dt)[0] - exact).max())
    rates = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(rates > order - 0.3), rates
    assert errs_zoh[-1] > 100 * errs[-1]


def test_ukf_linear_hold_propagates_the_exact_ramp(msd):
    """With tiny P0 and noise, the UKF's predicted output under hold="linear"
    (RK4, 8 substeps) is the exact response to the piecewise-linear input."""
    th = msd.theta(m=2.0, k=80.0, c=1.0)
    A, B = _matrices(msd, th)
    N, dt = 40, 0.05
    t = np.arange(N) * dt
    u = (10 * np.sin(3 * t) + 5 * t)[:, None]
    x = np.array([0.0, 0.0])
    X = [x]
    for k in range(N - 1):
        x = _exact_ramp_step(A, B, x, u[k], u[k + 1], dt)
        X.append(x)
    X = np.array(X)
    Y = msd.h(X, u, th[None])
    y = np.full((N, msd.n_y), np.nan)
    r = ukf_nll(msd, t, u, y, th, x0=np.zeros(2), P0=np.diag([1e-12, 1e-12]),
                options=UKFOptions(method="rk4", substeps=8, hold="linear"), store=True)
    # no measurement: the filtered states are the predictions
    Yf = r.y_filt[:, 0, :]
    assert np.abs(Yf - Y).max() < 1e-6 * np.abs(Y).max()
    rz = ukf_nll(msd, t, u, y, th, x0=np.zeros(2), P0=np.diag([1e-12, 1e-12]),
                 options=UKFOptions(method="rk4", substeps=8, hold="zoh"), store=True)
    assert np.abs(rz.y_filt[:, 0, :] - Y).max() > 1e-3 * np.abs(Y).max()


def test_discretisation_check_sees_the_hold(msd):
    """The check's reference uses the same hold as the step under test, so a
    fine step has (nearly) no error under any hold."""
    t = np.arange(100) * 0.02
    u = np.sin(4 * t)[:, None] * 20
    th = msd.theta0
    for hold in ("zoh", "mean", "linear"):
        d = discretisation_check(msd, t, u, th, disc=Discretisation("rk4", 16, hold))
        assert d["one_step"].max() < 1e-5
