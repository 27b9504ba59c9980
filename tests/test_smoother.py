"""The unscented RTS smoother (bondgraph.inference.smoother) against a
Kalman filter and RTS smoother written out by hand for a linear model (the
unscented transform is exact for linear maps, so both must agree to
rounding), and the smoothed initial state of an unmeasured state."""

import numpy as np

from bondgraph.inference.options import UKFOptions
from bondgraph.inference.smoother import rts_smooth
from bondgraph.numerics.integrators import make_step
from bondgraph.numerics.model import Model


def _kf_rts(Phi, Gam, H, Qd, R, x0, P0, u, y):
    """Textbook linear Kalman filter + RTS smoother (Rauch, Tung & Striebel
    1965), measurement update at every sample, prediction between them."""
    N, n = y.shape[0], x0.size
    xf, Pf = np.zeros((N, n)), np.zeros((N, n, n))
    xp, Pp = np.zeros((N, n)), np.zeros((N, n, n))
    x, P = x0.copy(), P0.copy()
    for k in range(N):
        if k > 0:
            x = Phi @ x + Gam @ u[k - 1]
            P = Phi @ P @ Phi.T + Qd
        xp[k], Pp[k] = x, P
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        x = x + K @ (y[k] - H @ x)
        P = P - K @ S @ K.T
        xf[k], Pf[k] = x, P
    xs, Ps = xf.copy(), Pf.copy()
    for k in range(N - 2, -1, -1):
        G = Pf[k] @ Phi.T @ np.linalg.inv(Pp[k + 1])
        xs[k] = xf[k] + G @ (xs[k + 1] - xp[k + 1])
        Ps[k] = Pf[k] + G @ (Ps[k + 1] - Pp[k + 1]) @ G.T
    return xs, Ps


def test_unscented_rts_equals_the_linear_rts_smoother():
    m = Model.load("mass_spring_damper")
    th = m.theta(m=2.0, k=60.0, c=1.5)
    dt, N = 0.02, 150
    t = np.arange(N) * dt
    rng = np.random.default_rng(3)
    u = rng.normal(0, 5, (N, 1))
    y = rng.normal(0, 0.01, (N, 2)) + np.column_stack([np.sin(t), np.cos(t)]) * 0.1
    opts = UKFOptions(method="rk4", substeps=2)
    step = make_step(m, "rk4", 2)
    # the discrete linear map of the filter's own step (exactly linear in x and u)
    Z = np.zeros((1, m.n_x))
    Phi = np.column_stack([step(np.eye(m.n_x)[i][None], np.zeros((1, 1)), th[None], dt)[0]
                           for i in range(m.n_x)])
    Gam = step(Z, np.ones((1, 1)), th[None], dt)[0][:, None]
    H = m.dhdx(Z, np.zeros((1, 1)), th[None])[0]
    R = np.diag(m.meas_std(th[None])[0] ** 2)
    x0 = np.array([0.05, -0.02])
    P0 = np.diag([0.1, 0.01]) ** 2
    Qd = np.zeros((2, 2))                     # the model has no process noise
    xs_ref, Ps_ref = _kf_rts(Phi, Gam, H, Qd, R, x0, P0, u, y)
    sm = rts_smooth(m, t, u, y, th, x0, P0, options=opts)
    assert np.allclose(sm.x, xs_ref, rtol=1e-8, atol=1e-12)
    assert np.allclose(sm.P, Ps_ref, rtol=1e-6, atol=1e-16)
    assert np.allclose(sm.x0, xs_ref[0]) and sm.P0.shape == (2, 2)


def test_smoothed_initial_state_finds_an_unmeasured_state():
    """Only the position is measured; the initial momentum is far from the
    prior mean. The smoothed x̂_0|N recovers it within 3 of its smoothed std,
    the filtered x̂_0|0 (prior-dominated for the momentum) does not."""
    m = Model.load("mass_spring_damper")
    th = m.theta(m=2.0, k=60.0, c=1.5)
    dt, N = 0.01, 400
    t = np.arange(N) * dt
    rng = np.random.default_rng(5)
    u = np.zeros((N, 1))
    x_true = np.array([1.2, 0.0])            # p = 1.2 kg m/s: v0 = 0.6 m/s
    step = make_step(m, "rk4", 4)
    X = [x_true]
    for k in range(N - 1):
        X.append(step(X[-1][None], u[k][None], th[None], dt)[0])
    X = np.array(X)
    Y = m.h(X, u, th[None])
    sd = m.meas_std(th[None])[0]
    y = Y + rng.normal(size=Y.shape) * sd
    y[:, 1] = np.nan                           # velocity not measured
    P0 = np.diag([1.0, 0.01]) ** 2
    sm = rts_smooth(m, t, u, y, th, np.zeros(2), P0, options=UKFOptions(method="rk4", substeps=4))
    z = (sm.x0 - x_true) / np.sqrt(np.diag(sm.P0))
    assert abs(z[0]) < 3.0
    assert abs(sm.x_filt[0, 0] - x_true[0]) > 0.5
