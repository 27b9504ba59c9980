"""Batched UKF and its negative log-likelihood (bondgraph.inference.ukf).

References: filterpy 2.0's UnscentedKalmanFilter + MerweScaledSigmaPoints
(same model, data and settings), a direct numpy evaluation of the NLL
formula, and per-set runs of the same batch.
"""

import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from bondgraph.errors import DataError, ModelError
from bondgraph.numerics.integrators import ros2
from bondgraph.numerics.model import Model
from bondgraph.inference.sigma import merwe_weights
from bondgraph.inference.ukf import discretisation_check, nll_from_innovations, ukf_nll
from bondgraph.errors import OptionError
from bondgraph.inference.options import Discretisation, UKFOptions


def _motor_record(N=150, dt=0.002, seed=1):
    """dc_motor_compliant driven by a square wave; RK4(8) truth, noisy outputs
    with full and partial missing samples."""
    m = Model.load("dc_motor_compliant")
    t = np.arange(N) * dt
    u = np.zeros((N, m.n_u))
    u[:, 0] = 6.0 * np.sign(np.sin(2 * np.pi * 3 * t) + 1e-9)
    u[:, 1] = 0.01 * np.sin(5 * t)
    th = m.theta0
    x = np.zeros((1, m.n_x))
    ys = []
    for k in range(N):
        ys.append(m.h(x, u[k], th)[0])
        x = m.module.fx(x, dt, u[k], th, 8)
    rng = np.random.default_rng(seed)
    y = np.array(ys) + rng.normal(size=(N, m.n_y)) * m.meas_std(th)
    y[5, :] = np.nan          # nothing measured: update skipped
    y[7, 0] = np.nan          # only the current measured
    y[20:23, 1] = np.nan      # only the speed measured
    return m, t, u, y


def _filterpy_run(m, t, u, y, theta, x0, P0, Qd, alpha, beta, kappa, fx):
    """filterpy's UKF over the record with the toolkit's convention (prior at
    t[0], update first; missing outputs: update with the measured subset)."""
    pts = MerweScaledSigmaPoints(m.n_x, alpha, beta, kappa)
    R = np.diag(m.meas_std(theta) ** 2)
    ukf = UnscentedKalmanFilter(m.n_x, m.n_y, t[1] - t[0], hx=None, fx=fx, points=pts)
    ukf.x, ukf.P, ukf.Q = x0.copy(), P0.copy(), Qd
    ukf.sigmas_f = pts.sigma_points(ukf.x, ukf.P)
    ll, xs = 0.0, []
    for k in range(len(t)):
        if k > 0:
            ukf.predict(dt=t[k] - t[k - 1], u=u[k - 1], theta=theta)
        idx = np.flatnonzero(np.isfinite(y[k]))
        if idx.size:
            ukf.update(y[k, idx], R=R[np.ix_(idx, idx)],
                       hx=lambda s, k=k, idx=idx: m.h(s[None], u[k], theta)[0, idx])
            ll += ukf.log_likelihood
        xs.append(ukf.x.copy())
    return ll, np.array(xs)


@pytest.mark.parametrize("alpha,kappa", [(1.0, 0.0), (0.3, 0.0), (0.5, -1.0)])
def test_agrees_with_filterpy_rk4(alpha, kappa):
    m, t, u, y = _motor_record()
    thetas = np.array([m.theta0, m.theta0 * 1.1, m.theta0 * 0.9])
    x0 = np.zeros(m.n_x)
    P0 = np.diag([1e-4, 1e-8, 1e-4, 1e-6])
    Qd = np.diag([1e-6, 1e-9, 1e-6, 1e-8])
    r = ukf_nll(m, t, u, y, thetas, x0, P0, Q=Qd, store=True,
                options=UKFOptions(alpha=alpha, kappa=kappa, method="rk4", substeps=4))
    assert not r.failed.any()
    for p in range(3):
        def fx(s, dt, u, theta):
            return m.module.fx(s[None], dt, u, theta, 4)[0]
        ll, xs = _filterpy_run(m, t, u, y, thetas[p], x0, P0, Qd, alpha, 2.0, kappa, fx)
        assert r.nll[p] == pytest.approx(-ll, rel=1e-9)
        scale = np.abs(xs).max(axis=0)
        np.testing.assert_allclose(r.x_filt[:, p], xs, rtol=1e-9, atol=1e-9 * scale.max())
    # samples: 150, of which one has no measurement
    assert (r.n_obs == 0).sum() == 1 and (r.n_obs == 1).sum() == 4


def test_agrees_with_filterpy_ros2():
    """With the Jacobian at every sigma point, the filter's transition is
    bondgraph.numerics.integrators.ros2 used as filterpy's fx."""
    m, t, u, y = _motor_record(N=80)
    th = m.theta0
    x0 = np.zeros(m.n_x)
    P0 = np.diag([1e-4, 1e-8, 1e-4, 1e-6])
    Qd = np.diag([1e-6, 1e-9, 1e-6, 1e-8])
    r = ukf_nll(m, t, u, y, th, x0, P0, Q=Qd, store=True,
                options=UKFOptions(alpha=0.8, method="ros2", substeps=2, jacobian="sigma"))

    def fx(s, dt, u, theta):
        return ros2(m.f_dfdx, s[None], u, theta, dt, 2, f=m.f)[0]
    ll, xs = _filterpy_run(m, t, u, y, th, x0, P0, Qd, 0.8, 2.0, 0.0, fx)
    assert r.nll[0] == pytest.approx(-ll, rel=1e-9)
    np.testing.assert_allclose(r.x_filt[:, 0], xs, rtol=1e-9, atol=1e-12)


def test_shared_jacobian_ros2_step_by_hand():
    """integrators.ros2(jacobian="shared"), the filter's default transition:
    per group of points, W = I − γhJ(first point) and the two stages solved
    point by point with numpy.linalg.solve (Verwer et al. 1999, eq. ROS2)."""
    m = Model.load("dc_motor_compliant")
    rng = np.random.default_rng(4)
    x = rng.normal(size=(3, 9, m.n_x)) * [1.0, 1e-3, 1.0, 1e-2]
    th = np.array([m.theta0, m.theta0 * 1.1, m.theta0 * 0.9])[:, None, :]
    u, dt, gamma = np.array([5.0, 0.01]), 2e-3, 1.0 + 1.0 / np.sqrt(2.0)
    got = ros2(m.f_dfdx, x, u, th, dt, 1, f=m.f, jacobian="shared")
    want = np.empty_like(x)
    for p in range(3):
        J = m.f_dfdx(x[p, :1], u, th[p])[1][0]
        W = np.eye(m.n_x) - gamma * dt * J
        for i in range(9):
            k1 = np.linalg.solve(W, m.f(x[p, i][None], u, th[p])[0])
            f1 = m.f((x[p, i] + dt * k1)[None], u, th[p])[0]
            k2 = np.linalg.solve(W, f1 - 2.0 * k1)
            want[p, i] = x[p, i] + 1.5 * dt * k1 + 0.5 * dt * k2
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
    # a group of one point: the shared Jacobian is the point's own
    one = ros2(m.f_dfdx, x[:, :1], u, th, dt, 3, f=m.f, jacobian="shared")
    np.testing.assert_allclose(one, ros2(m.f_dfdx, x[:, :1], u, th, dt, 3, f=m.f),
                               rtol=1e-13, atol=1e-15)


def test_nll_equals_formula_from_innovations():
    m, t, u, y = _motor_record(N=60)
    thetas = np.array([m.theta0, m.theta0 * 1.05])
    r = ukf_nll(m, t, u, y, thetas, np.zeros(m.n_x), np.diag([1e-4, 1e-8, 1e-4, 1e-6]),
                Q=np.diag([1e-6, 1e-9, 1e-6, 1e-8]), store=True,
                options=UKFOptions(method="rk4", substeps=4))
    direct = nll_from_innovations(r.innovations, r.S)
    np.testing.assert_allclose(r.nll, direct, rtol=1e-11)
    np.testing.assert_allclose(r.nll, r.nll_terms.sum(axis=0), rtol=1e-12)
    # NIS = ε S⁻¹ ε at a fully measured sample
    k = 10
    e, S = r.innovations[k, 0], r.S[k, 0]
    assert r.nis[k, 0] == pytest.approx(e @ np.linalg.solve(S, e), rel=1e-10)
    # the skipped sample has no innovation and contributes nothing
    assert np.isnan(r.innovations[5]).all() and (r.nll_terms[5] == 0).all()


def test_diverging_set_gets_inf_and_reason_others_unaffected():
    m, t, u, y = _motor_record(N=100)
    good1, good2 = m.theta0, m.theta0 * 1.02
    stiff = m.theta(k_s=5e6, J_m=5e-5)          # RK4(1) at 2 ms is unstable for this mode
    nan_set = m.theta(b_L=np.nan)
    batch = np.array([good1, stiff, good2, nan_set])
    opts = dict(x0=np.zeros(m.n_x), P0=np.diag([1e-4, 1e-8, 1e-4, 1e-6]),
                Q=np.diag([1e-6, 1e-9, 1e-6, 1e-8]), options=UKFOptions(method="rk4"))
    r = ukf_nll(m, t, u, y, batch, **opts)
    assert np.isinf(r.nll[1]) and np.isinf(r.nll[3])
    assert r.n_failed == 2 and list(r.failed) == [False, True, False, True]
    assert "sample" in r.reasons[1] and ("non-finite" in r.reasons[1]
                                         or "not positive definite" in r.reasons[1])
    assert "b_L" in r.reasons[3]
    assert r.reasons[0] is None and r.fail_step[0] == -1
    single = ukf_nll(m, t, u, y, np.array([good1, good2]), **opts)
    np.testing.assert_allclose(r.nll[[0, 2]], single.nll, rtol=1e-13)
    assert sum(r.failure_summary().values()) == 2
    # the same stiff set survives with the L-stable Rosenbrock step
    r2 = ukf_nll(m, t, u, y, stiff, **{**opts, "options": UKFOptions(method="ros2")})
    assert np.isfinite(r2.nll[0])


def test_nll_smooth_over_stiff_box_grid_convergence():
    """NLL along the log-diagonal of dc_motor_compliant's whole parameter box
    (rotor/shaft mode up to 3200 rad/s: stiff) is finite with ROS2 and smooth:
    its third differences shrink as h³ when the grid is refined 4x (a kink or
    noise would not)."""
    m, t, u, y = _motor_record(N=100)
    lo, hi = np.log(m.lower), np.log(m.upper)
    d3max = []
    for npts in (41, 161):
        s = np.linspace(0.0, 1.0, npts)
        thetas = np.exp(lo + s[:, None] * (hi - lo))
        r = ukf_nll(m, t, u, y, thetas, np.zeros(m.n_x), np.diag([1e-2, 1e-6, 1e-2, 1e-4]),
                    Q=np.diag([1e-6, 1e-9, 1e-6, 1e-8]),
                    options=UKFOptions(method="ros2", substeps=2))
        assert np.isfinite(r.nll).all(), r.reasons
        d3max.append(np.abs(np.diff(r.nll, 3)).max())
    assert 40 < d3max[0] / d3max[1] < 100          # 4³ = 64


def _emps_record(N=300, dt=0.01):
    """Synthetic EMPS-like record (tanh Coulomb friction, width 1 mm/s)."""
    m = Model.load("emps")
    t = np.arange(N) * dt
    u = (1.5 * np.sin(2 * np.pi * 0.7 * t) + 0.5 * np.sin(2 * np.pi * 2.3 * t))[:, None]
    th = m.theta(M=95.0, Fv=200.0, Fc=20.0, offset=-3.0, q_F=1.0, sigma_q=1e-5)
    x = np.zeros((1, 2))
    xs = []
    for k in range(N):
        xs.append(x[0])
        x = m.module.fx(x, dt, u[k], th, 20)
    y = np.array(xs)[:, 1:2] + np.random.default_rng(0).normal(size=(N, 1)) * 1e-5
    return m, t, u, y, th


@pytest.mark.parametrize("alpha", [1e-3, 1e-2, 0.1, 1.0])
def test_nll_finite_and_smooth_for_small_alpha(alpha):
    """On the nonlinear EMPS graph, along a line through the whole box of
    (M, Fv, Fc, offset): the NLL is finite for α from 1e-3 to 1, and its
    rounding noise (4th differences on a 1e-5 sub-grid at 7 places) stays
    below 1e-2 nats at α = 1e-3 (it scales as 1/α²: 1e-6 at α >= 0.1),
    negligible against the 0.5-nat scale of a confidence region."""
    m, t, u, y, th = _emps_record()
    idx = m.param_indices(["M", "Fv", "Fc", "offset"])
    lo, hi = m.lower[idx], m.upper[idx]
    kw = dict(x0=np.zeros(2), P0=np.diag([1.0, 1e-8]),
              options=UKFOptions(alpha=alpha, method="ros2", substeps=2))
    s = np.linspace(0.0, 1.0, 41)
    line = np.repeat(th[None], s.size, 0)
    line[:, idx] = lo + s[:, None] * (hi - lo)
    r = ukf_nll(m, t, u, y, line, **kw)
    assert np.isfinite(r.nll).all(), r.reasons
    centres = np.linspace(0.05, 0.95, 7)
    sub = (centres[:, None] + np.arange(-4, 5)[None, :] * 1e-5).ravel()
    fine = np.repeat(th[None], sub.size, 0)
    fine[:, idx] = lo + sub[:, None] * (hi - lo)
    f = ukf_nll(m, t, u, y, fine, **kw).nll.reshape(7, 9)
    noise = np.abs(np.diff(f, 4, axis=1)).max(axis=1) / np.sqrt(70.0)
    assert noise.max() < (1e-2 if alpha < 0.1 else 1e-5)
    # the smooth part dominates: the line's curvature is resolved by the
    # coarse grid (second differences >> noise)
    assert np.abs(np.diff(r.nll, 2)).max() > 1e4 * noise.max()


def test_small_alpha_converges():
    """As α -> 0 the criterion converges (α = 1e-3 and 1e-2 agree to 1e-5
    relative, 10x closer than α = 1e-2 and 1)."""
    m, t, u, y, th = _emps_record()
    kw = dict(x0=np.zeros(2), P0=np.diag([1.0, 1e-8]))
    a, b, c = (ukf_nll(m, t, u, y, th, **kw,
                       options=UKFOptions(alpha=al, method="ros2", substeps=2)).nll[0]
               for al in (1e-3, 1e-2, 1.0))
    assert np.isfinite(a) and abs(a - b) < 1e-5 * abs(a)
    assert abs(a - b) < 0.1 * abs(b - c)


def test_weights_match_filterpy():
    for n, a, b, k in [(4, 1.0, 2.0, 0.0), (7, 1e-3, 2.0, 0.0), (3, 0.5, 2.0, 3 - 3)]:
        w = merwe_weights(n, a, b, k)
        pts = MerweScaledSigmaPoints(n, a, b, k)
        Wm, Wc = w.arrays()
        np.testing.assert_allclose(Wm, pts.Wm, rtol=1e-14)
        np.testing.assert_allclose(Wc, pts.Wc, rtol=1e-14)


def test_bad_input_errors():
    m, t, u, y = _motor_record(N=20)
    with pytest.raises(OptionError, match="alpha"):
        UKFOptions(alpha=0.0)
    with pytest.raises(OptionError, match="method = 'euler'"):
        UKFOptions(method="euler")
    with pytest.raises(OptionError, match="substeps"):
        UKFOptions(substeps=0)
    with pytest.raises(OptionError, match="UKFOptions"):
        ukf_nll(m, t, u, y, m.theta0, options=dict(method="rk4"))
    with pytest.raises(OptionError, match="kappa"):
        ukf_nll(m, t, u, y, m.theta0, options=UKFOptions(kappa=-m.n_x))
    with pytest.raises(ModelError, match="theta"):
        ukf_nll(m, t, u, y, m.theta0[:3])
    t2 = t.copy()
    t2[5] = t2[4]
    with pytest.raises(DataError, match="increasing"):
        ukf_nll(m, t2, u, y, m.theta0)
    u2 = u.copy()
    u2[3, 1] = np.nan
    with pytest.raises(DataError, match="T_L"):
        ukf_nll(m, t, u2, y, m.theta0)
    with pytest.raises(OptionError, match="P0"):
        ukf_nll(m, t, u, y, m.theta0, P0=np.eye(3))


def test_discretisation_check_orders():
    """RK4's one-step output error is far below ROS2's at the same step on a
    smooth oscillator (orders 4 and 2)."""
    m = Model.load("mass_spring_damper")
    dt, N = 0.02, 200
    t = np.arange(N) * dt
    u = np.repeat(np.random.default_rng(0).normal(0, 20, N // 25), 25)[:, None]
    th = m.theta(m=2.5, k=80.0, c=2.0)
    a = discretisation_check(m, t, u, th, disc=Discretisation("ros2", 1))
    b = discretisation_check(m, t, u, th, disc=Discretisation("ros2", 4))
    c = discretisation_check(m, t, u, th, disc=Discretisation("rk4", 1))
    assert a["reference"] == "rk4"
    # ROS2 is second order: local error O(h³), so 4 sub-steps of h/4 give
    # 4 (1/4)³ = 1/16 of the one-step error
    assert 10 < a["one_step"].max() / b["one_step"].max() < 25
    assert c["one_step"].max() < 1e-2 * a["one_step"].max()


def test_discretisation_reference_is_ros2_where_rk4_is_at_its_stability_edge():
    """The check's default reference is RK4 only when RK4 at half its
    substeps agrees: a damper so stiff that the fast mode's λ·h = −2.7 per
    RK4 substep at the reference's substeps (inside RK4's stability
    interval [−2.785, 0]: R(−2.7) = 0.88 per substep against e^−2.7 = 0.067,
    finite but wrong) and −5.4 at half of them (R = 19.4: overflow) takes
    ROS2 (L-stable), whose runs at 16 and 32 substeps agree; a soft model
    keeps RK4."""
    m = Model.load("mass_spring_damper")
    dt, N, sub = 0.01, 400, 32
    t = np.arange(N) * dt
    u = np.zeros((N, 1))
    c = 2.7 / (dt / sub)                 # m = 1: the fast mode λ ≈ −c, the slow one −k/c
    stiff = m.theta(m=1.0, k=50.0, c=c)
    x0 = np.array([0.1, 1e-3])
    from bondgraph.inference.ukf import _agree, _trajectory
    from bondgraph.numerics.integrators import hold_inputs

    held = hold_inputs(u, "zoh")
    half = _trajectory(m, t, u, "zoh", held, stiff[None], x0[None], "rk4", sub // 2, "numpy")
    assert not np.isfinite(half).all()                # RK4 at λ·h = −5.4 overflows
    a = discretisation_check(m, t, u, stiff, x0, disc=Discretisation("ros2", 64, hold="zoh"),
                             reference_substeps=sub, sigma=np.array([1e-6, 1e-6]),
                             free_run=False)
    assert a["reference"] == "ros2"
    ros2 = [_trajectory(m, t, u, "zoh", held, stiff[None], x0[None], "ros2", n, "numpy")
            for n in (sub // 2, sub)]
    assert _agree(ros2[1], ros2[0])
    soft = discretisation_check(m, t, u, m.theta(m=1.0, k=50.0, c=1.0), x0,
                                disc=Discretisation("ros2", 1, hold="zoh"), free_run=False)
    assert soft["reference"] == "rk4"


def test_input_hold_mean():
    """hold="mean" predicts with (u_k + u_k+1)/2 over [t_k, t_k+1] (h of this
    model does not read u, so it equals ZOH on the averaged input)."""
    m = Model.load("mass_spring_damper")
    t = np.arange(60) * 0.02
    u = np.linspace(0.0, 30.0, 60)[:, None]
    y = np.zeros((60, 2))
    kw = dict(x0=np.zeros(2), P0=np.diag([1e-4, 1e-6]))
    umid = u.copy()
    umid[:-1] = 0.5 * (u[:-1] + u[1:])
    a = ukf_nll(m, t, u, y, m.theta0, options=UKFOptions(method="rk4", hold="mean"), **kw).nll
    b = ukf_nll(m, t, umid, y, m.theta0, options=UKFOptions(method="rk4"), **kw).nll
    c = ukf_nll(m, t, u, y, m.theta0, options=UKFOptions(method="rk4"), **kw).nll
    assert a[0] == b[0] and a[0] != c[0]
    with pytest.raises(OptionError, match="hold"):
        UKFOptions(hold="foh")
