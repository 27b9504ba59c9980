"""Joint estimation of initial states with parameters (inference/estimand.py,
fisher.estimand_scoring) and the initial-state columns of the forward
sensitivities, against finite differences of simulate and against the
output-error information Σ Jᵀ R⁻¹ J."""

import numpy as np
import pytest

from bondgraph.errors import ModelError
from bondgraph.inference.estimand import Estimand
from bondgraph.inference.fisher import estimand_scoring
from bondgraph.inference.options import ScoringOptions, UKFOptions
from bondgraph.numerics.forward_sensitivity import SolverOptions, output_sensitivities
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate


@pytest.fixture(scope="module")
def msd():
    m = Model.load("mass_spring_damper")
    dt, N = 0.02, 300
    t = np.arange(N) * dt
    rng = np.random.default_rng(0)
    u = np.repeat(rng.normal(0.0, 20.0, N // 20), 20)[:, None]
    th = m.theta(m=2.5, k=80.0, c=2.0)
    x0 = np.array([0.3, 0.01])
    return m, t, u, th, x0


def test_initial_state_sensitivities_match_finite_differences(msd):
    m, t, u, th, x0 = msd
    s = output_sensitivities(m, t, u, th, x0, [], x0_states=["p_mass", "q_spring"],
                             solver=SolverOptions(method="BDF", rtol=1e-11, atol=1e-13,
                                                  hold="zoh"))
    assert s.dydx0.shape == (t.size, 2, 2) and s.dydtheta.shape == (t.size, 2, 0)
    for j in range(2):
        h = 1e-4
        xp, xm = x0.copy(), x0.copy()
        xp[j] += h
        xm[j] -= h
        fd = (simulate(m, t, u, xp, th, rtol=1e-12, atol=1e-14, hold="zoh").y
              - simulate(m, t, u, xm, th, rtol=1e-12, atol=1e-14, hold="zoh").y) / (2 * h)
        rel = np.abs(s.dydx0[:, :, j] - fd).max(axis=0) / np.abs(fd).max(axis=0)
        assert (rel < 1e-6).all(), (j, rel)
    # at t0 the state columns are the identity
    np.testing.assert_allclose(s.dxdx0[0], np.eye(2), atol=1e-12)


def test_estimand_maps_values_to_ukf_arguments(msd):
    m, t, u, th, x0 = msd
    est = Estimand(m, ["k"], states=["p_mass"], noises=["v"], theta=th, x0=x0,
                   x0_scale=np.array([0.5, 0.1]))
    assert est.names == ["k", "x0.p_mass", "noise.v"]
    np.testing.assert_allclose(est.value(), [80.0, 0.3, 0.01])
    Th, X0, R = est.expand(np.array([[70.0, -0.2, 0.05]]))
    np.testing.assert_allclose(Th[0], [2.5, 70.0, 2.0])
    np.testing.assert_allclose(X0[0], [-0.2, 0.01])
    np.testing.assert_allclose(np.diag(R[0]), [0.002 ** 2, 0.05 ** 2])
    lo, hi = est.bounds([1.0], [1000.0])
    np.testing.assert_allclose(lo, [1.0, 0.3 - 50.0, 0.01 / 1e4])
    np.testing.assert_allclose(hi, [1000.0, 0.3 + 50.0, 0.01 * 1e4])
    P = est.prior_cov(np.diag([4.0, 9.0]))
    np.testing.assert_allclose(P, np.diag([(1e-6 * 0.5) ** 2, 9.0]))
    with pytest.raises(ModelError):
        est.expand(np.zeros((1, 2)))


def test_unmeasured_initial_momentum_recovered_within_3_crb(msd):
    """Only the position is measured; the initial momentum (unmeasured) and
    the stiffness are estimated jointly from a wrong start. Without process
    noise the UKF likelihood is the output-error likelihood, so its Fisher
    information equals Σ Jᵀ R⁻¹ J from the forward sensitivities."""
    m, t, u, th, x0 = msd
    rng = np.random.default_rng(3)
    clean = simulate(m, t, u, x0, th, rtol=1e-10, atol=1e-12, hold="zoh").y
    y = clean + rng.normal(size=clean.shape) * m.meas_std(th)
    y[:, 1] = np.nan
    start = th.copy()
    start[m.param_index("k")] = 60.0
    est = Estimand(m, ["k"], states=["p_mass"], theta=start, x0=np.array([0.0, 0.01]),
                   x0_scale=np.array([1.0, 0.01]))
    lo, hi = est.bounds([10.0], [500.0])
    r = estimand_scoring(m, t, u, y, est, lo, hi, np.diag([1.0, 1e-16]),
                         options=UKFOptions(method="rk4", substeps=4),
                         scoring=ScoringOptions(max_iter=30))
    assert r.converged
    z = r.estimand.value()
    crb = np.sqrt(np.diag(np.linalg.inv(r.F)))
    assert abs(z[0] - 80.0) < 3 * crb[0], (z, crb)
    assert abs(z[1] - 0.3) < 3 * crb[1], (z, crb)
    assert crb[1] < 0.05            # informative: the record pins the momentum
    s = output_sensitivities(m, t, u, r.estimand.theta, r.estimand.x0, ["k"],
                             solver=SolverOptions(hold="zoh"), x0_states=["p_mass"])
    J = np.concatenate([s.dydtheta[:, 0, :], s.dydx0[:, 0, :]], axis=1)
    F_oe = J.T @ J / m.meas_std(th)[0] ** 2
    np.testing.assert_allclose(r.F, F_oe, rtol=5e-3)


def test_scoring_options_validated_on_construction():
    from bondgraph.errors import OptionError

    with pytest.raises(OptionError, match=r"ScoringOptions\.max_iter .* got -1"):
        ScoringOptions(max_iter=-1)
    with pytest.raises(OptionError, match=r"ScoringOptions\.atol must be >= 0, got -1\.0"):
        ScoringOptions(atol=-1.0)
    with pytest.raises(OptionError, match=r"ScoringOptions\.information must be True or False"):
        ScoringOptions(information=1)
    with pytest.raises(OptionError, match=r"ScoringOptions\.log must be callable"):
        ScoringOptions(log="print")
    assert ScoringOptions(log_scale=np.array([1, 0], bool)).log_scale == (True, False)
    m = Model.load("mass_spring_damper")
    est = Estimand(m, ["k"], theta=m.theta0, x0=np.zeros(2))
    with pytest.raises(OptionError, match="must be a ScoringOptions, got dict"):
        estimand_scoring(m, np.arange(3.0), None, np.zeros((3, m.n_y)), est, [1.0], [2.0],
                         np.eye(2), scoring={"max_iter": 3})
