"""Refined substeps: more integration steps on the sample intervals that need
them (``UKFOptions.refine``, ``Discretisation.refine``).

References: filterpy 2.0's UnscentedKalmanFilter whose ``fx`` takes each
interval's own substeps (the generated module's RK4, or the toolkit's ROS2
with the Jacobian at every sigma point), a Kalman filter and RTS smoother
written out for a linear model with one transition matrix per interval,
scipy's ``solve_ivp`` for the one-step errors at the sigma points, and
runs by hand for the runs a ladder of errors gives.
"""

import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter
from scipy.integrate import solve_ivp

from bondgraph.errors import OptionError
from bondgraph.inference.discretise import refined_runs
from bondgraph.inference.options import Discretisation, UKFOptions, interval_substeps
from bondgraph.inference.problem import make_problem
from bondgraph.inference.smoother import rts_smooth
from bondgraph.inference.ukf import sigma_point_errors, ukf_nll
from bondgraph.numerics.integrators import make_step, ros2
from bondgraph.numerics.model import Model

REFINE = ((10, 25, 8), (40, 41, 16))


def _motor_record(N=80, dt=0.002, seed=1):
    """dc_motor_compliant driven by a square wave (its steps make the
    intervals after them stiff); RK4(8) truth, noisy outputs, one sample
    without measurements."""
    m = Model.load("dc_motor_compliant")
    t = np.arange(N) * dt
    u = np.zeros((N, m.n_u))
    u[:, 0] = 6.0 * np.sign(np.sin(2 * np.pi * 3 * t) + 1e-9)
    u[:, 1] = 0.01 * np.sin(5 * t)
    x = np.zeros((1, m.n_x))
    ys = []
    for k in range(N):
        ys.append(m.h(x, u[k], m.theta0)[0])
        x = m.module.fx(x, dt, u[k], m.theta0, 8)
    rng = np.random.default_rng(seed)
    y = np.array(ys) + rng.normal(size=(N, m.n_y)) * m.meas_std(m.theta0)
    y[5, :] = np.nan
    return m, t, u, y


def _filterpy_nll(m, t, u, y, theta, x0, P0, Qd, alpha, fx, per):
    """filterpy's UKF over the record (prior at t[0], update first), the
    transition over interval k by ``fx(..., ns=per[k])``."""
    pts = MerweScaledSigmaPoints(m.n_x, alpha, 2.0, 0.0)
    R = np.diag(m.meas_std(theta) ** 2)
    ukf = UnscentedKalmanFilter(m.n_x, m.n_y, t[1] - t[0], hx=None, fx=fx, points=pts)
    ukf.x, ukf.P, ukf.Q = x0.copy(), P0.copy(), Qd
    ukf.sigmas_f = pts.sigma_points(ukf.x, ukf.P)      # the first update's points
    ll = 0.0
    for k in range(len(t)):
        if k > 0:
            ukf.predict(dt=t[k] - t[k - 1], u=u[k - 1], theta=theta, ns=int(per[k - 1]))
        if np.isfinite(y[k]).all():
            ukf.update(y[k], R=R, hx=lambda s, k=k: m.h(s[None], u[k], theta)[0])
            ll += ukf.log_likelihood
    return -ll


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_refined_rk4_filter_agrees_with_filterpy(backend):
    """RK4 with 2 substeps, 8 on intervals 10..24 and 16 on interval 40:
    the NLL of both backends is filterpy's with each interval's own step."""
    m, t, u, y = _motor_record()
    x0, P0 = np.zeros(m.n_x), np.diag([1e-4, 1e-8, 1e-4, 1e-6])
    Qd = np.diag([1e-6, 1e-9, 1e-6, 1e-8])
    opts = UKFOptions(alpha=0.8, method="rk4", substeps=2, refine=REFINE, backend=backend)
    r = ukf_nll(m, t, u, y, m.theta0, x0, P0, Q=Qd, options=opts)
    per = interval_substeps(opts, t.size - 1)
    assert per[9] == 2 and per[10] == per[24] == 8 and per[25] == 2 and per[40] == 16

    def fx(s, dt, u, theta, ns):
        return m.module.fx(s[None], dt, u, theta, ns)[0]
    ref = _filterpy_nll(m, t, u, y, m.theta0, x0, P0, Qd, 0.8, fx, per)
    assert r.nll[0] == pytest.approx(ref, rel=1e-9)
    # and it is neither the base step's nor the finer one's throughout
    for n in (2, 8):
        other = ukf_nll(m, t, u, y, m.theta0, x0, P0, Q=Qd,
                        options=UKFOptions(alpha=0.8, method="rk4", substeps=n, backend=backend))
        assert abs(other.nll[0] - r.nll[0]) > 1e-6 * abs(r.nll[0])


def test_refined_ros2_filter_agrees_with_filterpy():
    """ROS2 with the Jacobian at every sigma point, refined runs, compiled."""
    m, t, u, y = _motor_record(N=60)
    x0, P0 = np.zeros(m.n_x), np.diag([1e-4, 1e-8, 1e-4, 1e-6])
    Qd = np.diag([1e-6, 1e-9, 1e-6, 1e-8])
    opts = UKFOptions(alpha=0.8, method="ros2", substeps=1, jacobian="sigma",
                      refine=((3, 9, 4), (30, 32, 3)))
    r = ukf_nll(m, t, u, y, m.theta0, x0, P0, Q=Qd, options=opts)
    assert r.settings["backend_used"] == "numba"

    def fx(s, dt, u, theta, ns):
        return ros2(m.f_dfdx, s[None], u, theta, dt, ns, f=m.f)[0]
    ref = _filterpy_nll(m, t, u, y, m.theta0, x0, P0, Qd, 0.8, fx,
                        interval_substeps(opts, t.size - 1))
    assert r.nll[0] == pytest.approx(ref, rel=1e-9)


@pytest.mark.parametrize("method,base", [("rk4", 2), ("ros2", 1)])
def test_a_run_over_every_interval_is_that_step_throughout(method, base):
    """Bit for bit, both backends, stored arrays too; a run at the base's
    substeps or fewer changes nothing."""
    m, t, u, y = _motor_record(N=50)
    th = np.array([m.theta0, 1.1 * m.theta0])
    for backend in ("numba", "numpy"):
        kw = dict(method=method, backend=backend)
        fine = ukf_nll(m, t, u, y, th, store=True, options=UKFOptions(substeps=3 * base, **kw))
        run = ukf_nll(m, t, u, y, th, store=True,
                      options=UKFOptions(substeps=base, refine=((0, 49, 3 * base),), **kw))
        np.testing.assert_array_equal(run.nll, fine.nll)
        np.testing.assert_array_equal(run.x_filt, fine.x_filt)
        plain = ukf_nll(m, t, u, y, th, options=UKFOptions(substeps=base, **kw))
        low = ukf_nll(m, t, u, y, th,
                      options=UKFOptions(substeps=base, refine=((4, 20, base),), **kw))
        np.testing.assert_array_equal(low.nll, plain.nll)


def _kf_rts(Phis, Gams, H, R, x0, P0, u, y):
    """Textbook Kalman filter + RTS smoother (Rauch, Tung & Striebel 1965)
    with the transition (Φ_k, Γ_k) of each interval k."""
    N, n = y.shape[0], x0.size
    xf, Pf = np.zeros((N, n)), np.zeros((N, n, n))
    xp, Pp = np.zeros((N, n)), np.zeros((N, n, n))
    x, P = x0.copy(), P0.copy()
    for k in range(N):
        if k > 0:
            x = Phis[k - 1] @ x + Gams[k - 1] @ u[k - 1]
            P = Phis[k - 1] @ P @ Phis[k - 1].T
        xp[k], Pp[k] = x, P
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        x = x + K @ (y[k] - H @ x)
        P = P - K @ S @ K.T
        xf[k], Pf[k] = x, P
    xs = xf.copy()
    for k in range(N - 2, -1, -1):
        G = Pf[k] @ Phis[k].T @ np.linalg.inv(Pp[k + 1])
        xs[k] = xf[k] + G @ (xs[k + 1] - xp[k + 1])
    return xs


def test_refined_smoother_equals_the_linear_rts_smoother():
    """A linear mass-spring-damper (the unscented transform is exact): the
    forward and backward passes take each interval's own RK4 step."""
    m = Model.load("mass_spring_damper")
    th = m.theta(m=2.0, k=60.0, c=1.5)
    dt, N = 0.05, 80
    t = np.arange(N) * dt
    rng = np.random.default_rng(3)
    u = rng.normal(0, 5, (N, 1))
    y = rng.normal(0, 0.01, (N, 2)) + np.column_stack([np.sin(t), np.cos(t)]) * 0.1
    opts = UKFOptions(method="rk4", substeps=1, refine=((20, 35, 4), (60, 61, 8)))
    Z = np.zeros((1, m.n_x))

    def maps(s):
        step = make_step(m, "rk4", s)
        Phi = np.column_stack([step(np.eye(m.n_x)[i][None], np.zeros((1, 1)), th[None], dt)[0]
                               for i in range(m.n_x)])
        return Phi, step(Z, np.ones((1, 1)), th[None], dt)[0][:, None]
    per = interval_substeps(opts, N - 1)
    pairs = {s: maps(int(s)) for s in np.unique(per)}
    H = m.dhdx(Z, np.zeros((1, 1)), th[None])[0]
    R = np.diag(m.meas_std(th[None])[0] ** 2)
    x0, P0 = np.array([0.05, -0.02]), np.diag([0.1, 0.01]) ** 2
    xs_ref = _kf_rts([pairs[s][0] for s in per], [pairs[s][1] for s in per], H, R, x0, P0, u, y)
    sm = rts_smooth(m, t, u, y, th, x0, P0, options=opts)
    assert np.allclose(sm.x, xs_ref, rtol=1e-8, atol=1e-12)
    plain = rts_smooth(m, t, u, y, th, x0, P0, options=UKFOptions(method="rk4", substeps=1))
    assert not np.allclose(plain.x, xs_ref, rtol=1e-8, atol=1e-12)


def test_refine_is_checked_and_read():
    d = Discretisation(method="rk4", substeps=2, refine=[(30, 31, 16), [3, 5, 8]])
    assert d.refine == ((3, 5, 8), (30, 31, 16))          # canonical: sorted int triples
    assert d.interval_substeps(32).tolist() == [2] * 3 + [8] * 2 + [2] * 25 + [16, 2]
    assert d.uniform() == Discretisation(method="rk4", substeps=16)
    assert d.for_free_run().substeps == 16 and not d.for_free_run().refine
    assert "8/16 on 3 intervals (2 runs)" in d.describe()
    for bad in ([(3, 5, 8), (4, 6, 8)], [(5, 5, 2)], [(1, 2, 0)], [(1, 2)], [(0, 2.5, 2)], 3):
        with pytest.raises(OptionError, match="refine"):
            UKFOptions(refine=bad)
    with pytest.raises(OptionError, match="another record"):
        d.interval_substeps(20)


def test_a_problem_refuses_runs_beyond_its_record_and_another_record_takes_them_throughout():
    m, t, u, y = _motor_record(N=50)
    opts = UKFOptions(method="rk4", substeps=2, refine=((10, 20, 8),))
    pb = make_problem(m, (t, u, y), ukf=opts)
    other = pb.on_record((t[:30], u[:30], y[:30]))
    assert other.ukf.substeps == 8 and other.ukf.refine == ()
    with pytest.raises(OptionError, match="beyond the record's 19 intervals"):
        make_problem(m, (t[:20], u[:20], y[:20]), ukf=opts)
    # the problem's likelihood is the refined filter's
    direct = ukf_nll(m, t, u, y, pb.theta, pb.x0, pb.P0, options=opts).nll[0]
    assert pb.nll(pb.theta).nll[0] == direct


def test_refined_runs_by_hand():
    """Per interval the fewest substeps within the limit, held over the
    margin either side; the runs above the base."""
    lim = 0.1
    E = np.array([[0.01, 0.5, 0.3, 0.02, 0.02, 0.02, 0.02, 0.9, 0.01, 0.01],   # 1 substep
                  [0.01, 0.2, 0.05, 0.01, 0.01, 0.01, 0.01, 0.3, 0.01, 0.01],  # 2
                  [0.01, 0.05, 0.01, 0.01, 0.01, 0.01, 0.01, 0.05, 0.01, 0.01]])  # 4
    assert refined_runs(E, [1, 2, 4], lim, margin=0) == ((1, 2, 4), (2, 3, 2), (7, 8, 4))
    assert refined_runs(E, [1, 2, 4], lim, margin=1) == ((0, 3, 4), (3, 4, 2), (6, 9, 4))
    assert refined_runs(E, [1, 2, 4], lim, margin=0,
                        base=[1, 1, 1, 1, 8, 1, 1, 1, 1, 1]) == ((1, 2, 4), (2, 3, 2),
                                                                  (4, 5, 8), (7, 8, 4))
    assert refined_runs(E[:, [0, 3, 4]], [1, 2, 4], lim) == ()
    E2 = E.copy()
    E2[2, 7] = 0.2                       # no rung meets the limit at interval 7
    assert refined_runs(E2, [1, 2, 4], lim) is None
    # errors that do not fall with every substep: interval 3 meets the limit
    # at 1 and 4 substeps, not at 2, which its neighbour 2 needs: it takes 4
    E3 = E.copy()
    E3[1, 3] = 0.2
    assert refined_runs(E3, [1, 2, 4], lim, margin=1) == ((0, 4, 4), (6, 9, 4))


def test_sigma_point_errors_against_solve_ivp():
    """At a few intervals of a stored run, each sigma point of the posterior
    (filterpy's MerweScaledSigmaPoints) over the interval by the generated
    module's RK4(1) and by solve_ivp (LSODA, rtol 1e-12): the largest output
    error in noise stds is the function's."""
    m, t, u, y = _motor_record(N=40)
    th = m.theta0
    x0, P0 = np.zeros(m.n_x), np.diag([1e-4, 1e-8, 1e-4, 1e-6])
    opts = UKFOptions(method="rk4", substeps=1, alpha=0.8)
    r = ukf_nll(m, t, u, y, th, x0, P0, Q=np.diag([1e-6, 1e-9, 1e-6, 1e-8]), options=opts,
                store="full")
    sig = np.asarray(m.meas_std(th[None])[0], float)
    got = sigma_point_errors(m, t, u, th, r.x_filt[:, 0], r.P_filt[:, 0], opts, [1, 4], sig)
    assert got.shape == (2, 39) and np.all(got[1] < got[0])
    pts = MerweScaledSigmaPoints(m.n_x, 0.8, 2.0, 0.0)
    for k in (0, 12, 30):
        P = r.P_filt[k, 0]
        sigmas = pts.sigma_points(r.x_filt[k, 0], 0.5 * (P + P.T))
        dt = t[k + 1] - t[k]
        worst = 0.0
        for s in sigmas:
            sol = solve_ivp(lambda _, x: m.f(x[None], u[k], th[None])[0], (0, dt), s,
                            method="LSODA", rtol=1e-12, atol=1e-14)
            y_ref = m.h(sol.y[:, -1][None], u[k + 1], th[None])[0]
            y_rk4 = m.h(m.module.fx(s[None], dt, u[k], th, 1), u[k + 1], th[None])[0]
            worst = max(worst, float(np.max(np.abs(y_rk4 - y_ref) / sig)))
        assert got[0, k] == pytest.approx(worst, rel=1e-4)


def test_the_tracking_filter_takes_refined_runs_throughout():
    """The tracker filters parts of a record and streams samples: a
    refinement made for a record's intervals is taken at its largest
    substeps throughout."""
    from bondgraph.catalog.reference import mass_spring_damper
    from bondgraph.inference.options import TrackOptions
    from bondgraph.inference.track import TrackingModel, filter_options

    tm = TrackingModel.from_graph(mass_spring_damper(), ["c"])
    opts = UKFOptions(method="rk4", substeps=2, refine=((3, 9, 8),))
    for match in (False, True):
        got = filter_options(opts, tm, TrackOptions(match_spread=match))
        assert (got.substeps, got.refine, got.kappa) == (8, (), -1.0 if match else 0.0)


def test_refined_runs_with_uneven_intervals_and_a_linear_hold():
    """Sample intervals of three lengths, the first-order hold (each stage
    sees the input at its own time): the compiled kernel and the numpy
    filter agree, stored filtered states too; the smoother runs over it."""
    m, t, u, y = _motor_record(N=70)
    t = np.cumsum(np.r_[0.0, np.tile([0.002, 0.003, 0.0015], 23)])
    th = np.array([m.theta0, 0.9 * m.theta0])
    x0, P0 = np.zeros(m.n_x), np.diag([1e-4, 1e-8, 1e-4, 1e-6])
    kw = dict(method="rk4", substeps=2, hold="linear", refine=((5, 17, 6), (40, 44, 12)))
    a = ukf_nll(m, t, u, y, th, x0, P0, store=True, options=UKFOptions(backend="numpy", **kw))
    b = ukf_nll(m, t, u, y, th, x0, P0, store=True, options=UKFOptions(backend="numba", **kw))
    assert b.settings["backend_used"] == "numba" and np.isfinite(a.nll).all()
    np.testing.assert_allclose(b.nll, a.nll, rtol=1e-9)
    np.testing.assert_allclose(b.x_filt, a.x_filt, rtol=1e-8, atol=1e-12)
    plain = ukf_nll(m, t, u, y, th, x0, P0, options=UKFOptions(method="rk4", substeps=2,
                                                               hold="linear"))
    assert np.all(np.abs(plain.nll - b.nll) > 1e-9 * np.abs(b.nll))
    sm = rts_smooth(m, t, u, y, m.theta0, x0, P0, options=UKFOptions(**kw))
    assert np.isfinite(sm.x).all() and sm.x.shape == (70, m.n_x)
