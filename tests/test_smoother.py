"""The unscented RTS smoother (bondgraph.inference.smoother) against a
Kalman filter and RTS smoother written out by hand for a linear model (the
unscented transform is exact for linear maps, so both must agree to
rounding), and the smoothed initial state of an unmeasured state."""

import numpy as np
import pytest

from bondgraph.inference import smoother
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


def _linear_maps(m, th, dt):
    """(Φ, Γ, H): the discrete linear map of the filter's own RK4(2) step of
    a linear model (exactly linear in x and u) and its output matrix."""
    step = make_step(m, "rk4", 2)
    Z = np.zeros((1, m.n_x))
    Phi = np.column_stack([step(np.eye(m.n_x)[i][None], np.zeros((1, 1)), th[None], dt)[0]
                           for i in range(m.n_x)])
    Gam = step(Z, np.ones((1, 1)), th[None], dt)[0][:, None]
    return Phi, Gam, m.dhdx(Z, np.zeros((1, 1)), th[None])[0]


def _batch_reference(Phi, Gam, H, R, u, x_true, x0, P0, rng):
    """A record of the linear map (Φ, Γ, H) without process noise from
    ``x_true`` (measurement noise R drawn from ``rng``) and, computed
    without any filter, the batch generalised least-squares estimate of x0
    (with Q = 0 every x_k is Φᵏ x0 + the forced response: information
    Σ (HΦᵏ)ᵀR⁻¹HΦᵏ + P0⁻¹): ``(ys (N, n_y), x0_ref, its covariance,
    Φᵏ (N, n, n), forced responses (N, n))``."""
    n = x0.size
    Rinv = np.linalg.inv(R)
    forced, A = np.zeros(n), np.eye(n)
    ys, info, rhs, As, fs = [], np.zeros((n, n)), np.zeros(n), [], []
    for k in range(len(u)):
        As.append(A.copy())
        fs.append(forced.copy())
        HA = H @ A
        yk = H @ (A @ x_true + forced) + rng.normal(0, 1, H.shape[0]) * np.sqrt(np.diag(R))
        info += HA.T @ Rinv @ HA
        rhs += HA.T @ Rinv @ (yk - H @ forced)
        ys.append(yk)
        forced = Phi @ forced + Gam @ u[k]
        A = Phi @ A
    P0i = np.linalg.inv(P0)
    cov = np.linalg.inv(info + P0i)
    return np.array(ys), cov @ (rhs + P0i @ x0), cov, np.array(As), np.array(fs)


@pytest.mark.parametrize("chunk", [4096, 7])
def test_unscented_rts_equals_the_linear_rts_smoother(chunk, monkeypatch):
    """Also with the batched predictions split into chunks of 7 intervals
    (their boundaries inside the record)."""
    monkeypatch.setattr(smoother, "CHUNK", chunk)
    m = Model.load("mass_spring_damper")
    th = m.theta(m=2.0, k=60.0, c=1.5)
    dt, N = 0.02, 150
    t = np.arange(N) * dt
    rng = np.random.default_rng(3)
    u = rng.normal(0, 5, (N, 1))
    y = rng.normal(0, 0.01, (N, 2)) + np.column_stack([np.sin(t), np.cos(t)]) * 0.1
    opts = UKFOptions(method="rk4", substeps=2)
    Phi, Gam, H = _linear_maps(m, th, dt)
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


def test_long_record_without_process_noise_smooths_to_the_batch_least_squares_x0():
    """No process noise, a lightly damped resonance and states of very
    different scales (the Silverbox's: m 5.8e-6 s², k 1.11, c 2.45e-4 s, Ts
    1.6384 ms): the filtered covariance collapses to round-off and came out
    indefinite ("filtered covariance at sample 1009 is not positive
    definite"; the loop on a user's Silverbox graph stopped smoothing). The
    smoothed initial state must be the batch generalised least-squares
    estimate of x0 (with Q = 0 every x_k is Φᵏ x0 + the forced response:
    information Σ (HΦᵏ)ᵀR⁻¹HΦᵏ + P0⁻¹), computed here without any filter,
    on a record that starts at rest (whether the round-off breaks the old
    Cholesky depends on the values; this one did at sample 1009)."""
    m = Model.load("mass_spring_damper")
    th = m.theta(m=5.8e-6, k=1.11, c=2.45e-4)
    dt, N = 2**14 / 1e7, 5000
    t = np.arange(N) * dt
    rng = np.random.default_rng(7)
    u = 0.02 * rng.normal(0, 1, (N, 1))
    R = np.diag([0.003, 1.0]) ** 2
    opts = UKFOptions(method="rk4", substeps=2, backend="numpy")
    Phi, Gam, H = _linear_maps(m, th, dt)
    x_true = np.zeros(2)
    x0, P0 = np.zeros(2), np.diag([1e-6, 0.05]) ** 2
    ys, x0_ref, cov, _, _ = _batch_reference(Phi, Gam, H, R, u, x_true, x0, P0, rng)
    sd = np.sqrt(np.diag(cov))
    sm = rts_smooth(m, t, u, ys, th, x0, P0, options=opts, R=R)
    assert np.all(np.abs(sm.x0 - x0_ref) < 0.01 * sd)
    assert np.all(np.abs(x0_ref - x_true) < 4 * sd)


def test_factor_of_collapsed_and_indefinite_covariances():
    """A filtered covariance that underflowed to zero (the state known
    exactly) factors to zero; one that round-off made indefinite (an
    eigenvalue of −1e-20 beside 1) to a factor whose product is within
    1e-12 of it; a non-finite one is an error naming the sample."""
    from bondgraph.errors import NumericalError
    np.testing.assert_array_equal(smoother._factor(np.zeros((2, 2)), 3), np.zeros((1, 2, 2)))
    V = np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]])
    P = V @ np.diag([1.0, -1e-20]) @ V.T
    L = smoother._factor(P, 4)[0]
    np.testing.assert_allclose(L @ L.T, P, atol=1e-12)
    with pytest.raises(NumericalError, match="sample 7"):
        smoother._factor(np.full((2, 2), np.nan), 7)


def test_batched_factors_equal_the_one_by_one_factors():
    """smoother._factors (one stacked eigendecomposition) gives each
    covariance the loaded Cholesky factorisation refuses the factor _factor
    gives it alone: indefinite (rotated), collapsed to zero; a batch holding
    non-finite ones
    raises naming the latest of them, as the one-by-one loop did."""
    from bondgraph.errors import NumericalError

    from bondgraph.inference.sigma import cholesky_batch

    mats = []
    for a, lo in ((0.3, -1e-4), (1.1, -3e-3), (2.0, -0.5)):
        V = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        mats.append(V @ np.diag([2.0 + a, lo]) @ V.T)
    mats.append(np.zeros((2, 2)))
    P, ks = np.array(mats), np.array([3, 8, 9, 12])
    assert not cholesky_batch(P)[1].any()       # what the smoother hands on
    L = smoother._factors(P, ks)
    for j, k in enumerate(ks):
        np.testing.assert_allclose(L[j], smoother._factor(P[j], int(k))[0], rtol=1e-13,
                                   atol=1e-15)
    np.testing.assert_array_equal(L[3], np.zeros((2, 2)))
    bad = P.copy()
    bad[[0, 2]] = np.nan
    with pytest.raises(NumericalError, match="sample 9"):
        smoother._factors(bad, ks)


def test_compiled_recursion_equals_the_matrix_products():
    """The backward recursion (compiled, sums in index order) equals numpy's
    matrix products of the same formulas, sample by sample from the end
    (Särkkä 2008, Algorithm 3.2, the covariance in the Joseph form of the
    module docstring), to round-off: 3 states, 2 000 samples, contracting
    gains; the last sample keeps its filtered values."""
    from bondgraph.inference.smoother import _recursion

    rng = np.random.default_rng(5)
    N, n = 2000, 3
    xf = rng.normal(size=(N, n))
    A = rng.normal(size=(N, n, n))
    Pf = A @ np.swapaxes(A, 1, 2) + np.eye(n)
    m = rng.normal(size=(N - 1, n))
    B = rng.normal(size=(N - 1, n, n))
    Qe = B @ np.swapaxes(B, 1, 2) + np.eye(n)
    M = rng.normal(size=(N - 1, n, n))
    G = 0.3 * rng.normal(size=(N - 1, n, n))
    xs, Ps = xf.copy(), Pf.copy()
    for k in range(N - 2, -1, -1):
        xs[k] = xf[k] + G[k] @ (xs[k + 1] - m[k])
        Pk = M[k] @ M[k].T + G[k] @ (Qe[k] + Ps[k + 1]) @ G[k].T
        Ps[k] = 0.5 * (Pk + Pk.T)
    xc, Pc = xf.copy(), Pf.copy()
    # (random gains and covariances: the divergence check off, floor inf)
    assert _recursion(xf, Pf, m, G, M, Qe, xc, Pc, np.full(n, np.inf)) == 0
    assert np.allclose(xc, xs, rtol=1e-11, atol=1e-12)
    assert np.allclose(Pc, Ps, rtol=1e-11, atol=1e-12)
    assert np.array_equal(Pc, np.swapaxes(Pc, 1, 2))
    assert np.array_equal(xc[-1], xf[-1]) and np.array_equal(Pc[-1], Pf[-1])


def test_a_backward_pass_that_diverges_restarts_from_the_filter():
    """No process noise and a fast contracting mode (mass-spring-damper m 1,
    k 1, c 20: time constants 0.05 s and 20 s, sampled every 0.01 s): the
    smoother's gain is Φ⁻¹ there (a factor e^0.2 a sample), round-off grows
    backwards, and the recursion overflowed to inf at every early sample.
    Where a smoothed variance exceeds twice the filtered one the pass
    restarts from the filtered posterior: every mean and covariance is
    finite, the restarts are counted, the samples after the last restart
    are the exact smoothed trajectory (with Q = 0, Φᵏ x̂0 + the forced
    response, x̂0 the batch generalised least-squares estimate, computed
    without any filter), and the smoothed states are nearer the truth than
    the filtered ones (RMS and worst sample)."""
    m = Model.load("mass_spring_damper")
    th = m.theta(m=1.0, k=1.0, c=20.0)
    dt, N = 0.01, 6000
    t = np.arange(N) * dt
    rng = np.random.default_rng(3)
    u = rng.normal(0, 1, (N, 1))
    R = np.diag([0.01, 0.01]) ** 2
    opts = UKFOptions(method="rk4", substeps=2, backend="numpy")
    Phi, Gam, H = _linear_maps(m, th, dt)
    x_true = np.array([0.3, 0.1])
    x0, P0 = np.zeros(2), np.diag([1.0, 1.0])
    ys, x0_ref, cov_ref, As, fs = _batch_reference(Phi, Gam, H, R, u, x_true, x0, P0, rng)
    sm = rts_smooth(m, t, u, ys, th, x0, P0, options=opts, R=R)
    assert np.all(np.isfinite(sm.x)) and np.all(np.isfinite(sm.P))
    assert sm.restarts > 0
    x_ref = As @ x0_ref + fs
    truth = As @ x_true + fs
    # smoothing halves the filter's error (0.00013, 0.00019 against 0.00032,
    # 0.00039 RMS; the measurement noise is 0.01)
    rms_s = np.sqrt(np.mean((sm.x - truth) ** 2, axis=0))
    rms_f = np.sqrt(np.mean((sm.x_filt - truth) ** 2, axis=0))
    assert np.all(rms_s < 0.6 * rms_f), (rms_s, rms_f)
    assert np.all(np.abs(sm.x - truth).max(axis=0) < np.abs(sm.x_filt - truth).max(axis=0))
    # the tail the recursion reached without a restart: the exact smoother
    # (within 1e-4 of the measurement noise std: 1.7e-7 at most seen)
    tail = slice(N - 200, N)
    assert np.all(np.abs(sm.x[tail] - x_ref[tail]) < 1e-6), \
        np.abs(sm.x[tail] - x_ref[tail]).max(axis=0)
    # the smoothed std against the exact one (Φᵏ cov Φᵏᵀ): the Joseph form
    # does not cancel P_k|k against G P⁻ Gᵀ. Below half the exact std only
    # where the filtered covariance is itself singular to working precision
    # (cond 1e14-1e17; measured: 4 samples of 6 000, the lowest 0.18 of the
    # exact std; the subtracting form gave 15 samples, the lowest 0.015)
    sd_ref = np.sqrt(np.diagonal(As @ cov_ref @ np.swapaxes(As, 1, 2), axis1=1, axis2=2))
    ratio = np.sqrt(np.maximum(np.diagonal(sm.P, axis1=1, axis2=2), 0.0)) / sd_ref
    assert ratio.min() > 0.1 and (ratio < 0.5).any(axis=1).sum() <= 8, \
        (ratio.min(axis=0), (ratio < 0.5).any(axis=1).sum())


def test_joseph_form_equals_the_subtracting_form_on_a_nonlinear_model():
    """A stiffening spring (the mass-spring-damper with the library's cubic
    stiffness: the transition's second differences, Q̃'s nonlinear part, are
    not zero) and a short well-conditioned record: the smoothed covariances
    equal the textbook form P_k|k + G (P_k+1|N − P⁻) Gᵀ computed here with
    filterpy's sigma points and unscented transform (Särkkä 2008, Algorithm
    3.2) over the filter's own step, to rounding."""
    from filterpy.kalman import MerweScaledSigmaPoints, unscented_transform

    from bondgraph.catalog.reference import mass_spring_damper
    from bondgraph.diagnose.effects import apply_effect, get_effect
    from bondgraph.inference.ukf import ukf_nll

    g = mass_spring_damper()
    eff = get_effect("cubic_stiffness")
    apply_effect(g, eff, eff.targets(g)[0], {"k3": 2.0e5})
    m = Model.from_graph(g)
    th = m.theta(**{"m": 2.0, "k": 60.0, "c": 1.5})
    dt, N = 0.01, 300
    t = np.arange(N) * dt
    rng = np.random.default_rng(11)
    u = rng.normal(0, 20, (N, 1))
    y = rng.normal(0, 0.01, (N, 2)) + np.column_stack([np.sin(3 * t), 3 * np.cos(3 * t)]) * 0.2
    opts = UKFOptions(method="rk4", substeps=2, backend="numpy")
    x0, P0 = np.zeros(2), np.diag([0.1, 0.3]) ** 2
    sm = rts_smooth(m, t, u, y, th, x0, P0, options=opts)
    assert sm.restarts == 0
    res = ukf_nll(m, t, u, y, th[None], x0, P0, options=opts, store="full")
    xf, Pf = res.x_filt[:, 0], res.P_filt[:, 0]
    pts = MerweScaledSigmaPoints(2, alpha=opts.alpha, beta=opts.beta, kappa=opts.kappa)
    step = make_step(m, "rk4", 2)
    xs, Ps = xf.copy(), Pf.copy()
    nonlinear = 0.0
    for k in range(N - 2, -1, -1):
        chi = pts.sigma_points(xf[k], Pf[k])
        X = step(chi, np.repeat(u[k][None], len(chi), axis=0), th[None], dt)
        mp, Pp = unscented_transform(X, pts.Wm, pts.Wc)
        C = ((chi - xf[k]).T * pts.Wc) @ (X - mp)
        G = C @ np.linalg.inv(Pp)
        Phi = C.T @ np.linalg.inv(Pf[k])
        nonlinear = max(nonlinear, np.abs(Pp - Phi @ Pf[k] @ Phi.T).max() / np.abs(Pp).max())
        xs[k] = xf[k] + G @ (xs[k + 1] - mp)
        Ps[k] = Pf[k] + G @ (Ps[k + 1] - Pp) @ G.T
    # Q̃ has a nonlinear part to get right: up to 5.2e-4 of P⁻ (measured)
    assert nonlinear > 1e-4, nonlinear
    # to rounding: a state crossing zero (3.8e-4 of states of order 1) differs by
    # 3.5e-12 on one 2-core machine (its BLAS), 9e-9 of itself: the atol is of the states' scale
    np.testing.assert_allclose(sm.x, xs, rtol=1e-9, atol=1e-10 * np.abs(xs).max())
    np.testing.assert_allclose(sm.P, Ps, rtol=1e-7, atol=1e-14)


def test_a_restarted_backward_pass_gives_no_initial_state_and_says_why():
    """The same fast contracting mode through a Problem: x̂_0|N would hold
    the record's first samples only, so ``Problem.smoothed_initial_state``
    raises SmootherRestartError (a NumericalError) with the restarts
    counted, worded as the expected condition it is without process noise
    (the loop's log printed it as "smoothed initial state unavailable" on
    every such run, which read like a failure)."""
    from bondgraph.errors import NumericalError, SmootherRestartError
    from bondgraph.inference.problem import PriorSpec, make_problem

    m = Model.load("mass_spring_damper")
    th = m.theta(m=1.0, k=1.0, c=20.0)
    dt, N = 0.01, 6000
    t = np.arange(N) * dt
    rng = np.random.default_rng(3)
    u = rng.normal(0, 1, (N, 1))
    Phi, Gam, H = _linear_maps(m, th, dt)
    R = np.diag([0.01, 0.01]) ** 2
    ys = _batch_reference(Phi, Gam, H, R, u, np.array([0.3, 0.1]), np.zeros(2),
                          np.eye(2), rng)[0]
    pb = make_problem(m, (t, u, ys), prior=PriorSpec(x0=np.zeros(2), P0=np.eye(2)),
                      ukf=UKFOptions(method="rk4", substeps=2, backend="numpy"))
    with pytest.raises(SmootherRestartError) as info:
        pb.smoothed_initial_state(th)
    assert isinstance(info.value, NumericalError) and info.value.restarts > 0
    said = str(info.value)
    assert said.startswith("without process noise the smoother gives no initial state")
    assert f"restarted from the filter at {info.value.restarts} sample" in said
    assert "unavailable" not in said and "diverged" not in said
