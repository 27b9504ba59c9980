"""Ranking rules of the score test (bondgraph.diagnose.scoring): nested
candidates (the larger leads only if its extra columns pass the nested
likelihood-ratio test) and candidates absorbed by the estimated parameters.
The Gram matrices are built from explicit signature columns, so the
correlations are known by construction."""

import numpy as np
import pytest
from scipy.stats import chi2

from bondgraph.diagnose.effects import Target
from bondgraph.diagnose.result import Candidate
from bondgraph.diagnose.scoring import mark_equivalent, rank_nested


def _cand(effect, target, stat, k):
    return Candidate(effect, effect, Target("sensor", target), "score", stat, k,
                     float(chi2.sf(stat, k)), stat - 2 * k)


def _gram(cols):
    G = np.column_stack(cols)
    A = G.T @ G
    n = np.sqrt(np.diag(A))
    return A / np.outer(n, n)


def test_larger_candidate_needs_significant_extra_gain():
    t = np.linspace(0.0, 1.0, 200)
    # column 0: estimated parameter; 1: poly2's c2; 2, 3: poly3's c2 (same) and c3
    An = _gram([np.sin(7 * t), t**2, t**2, t**3 - 0.5 * t])
    col_of = {("sensor_poly2", Target("sensor", "y")): [1],
              ("sensor_poly3", Target("sensor", "y")): [2, 3]}
    crit = chi2.isf(0.01, 1)                       # 6.635
    p2, p3 = _cand("sensor_poly2", "y", 100.0, 1), _cand("sensor_poly3", "y", 104.0, 2)
    assert p3.score > p2.score                     # AIC alone: the larger one leads
    demoted = rank_nested([p2, p3], col_of, An, 0.01)
    assert demoted == [(p3, p2)]
    assert np.isclose(p3.score, p2.score - (crit - 4.0))
    assert p3.score < p2.score
    # a significant extra gain keeps the larger candidate first
    q2, q3 = _cand("sensor_poly2", "y", 100.0, 1), _cand("sensor_poly3", "y", 110.0, 2)
    assert rank_nested([q2, q3], col_of, An, 0.01) == [] and q3.score == 106.0
    # not nested (another target): untouched
    r2, r3 = _cand("sensor_poly2", "y", 100.0, 1), _cand("sensor_poly3", "z", 104.0, 2)
    col_z = {("sensor_poly2", Target("sensor", "y")): [1],
             ("sensor_poly3", Target("sensor", "z")): [2, 3]}
    assert rank_nested([r2, r3], col_z, An, 0.01) == [] and r3.score == 100.0


def test_absorbed_when_signature_in_the_estimated_span():
    t = np.linspace(0.0, 1.0, 300)
    base = np.sin(5 * t)
    An = _gram([base, 2.0 * base + 1e-4 * np.cos(40 * t), np.cos(3 * t) * t])
    col_of = {("viscous", Target("sensor", "v")): [1], ("coulomb", Target("sensor", "v")): [2]}
    a, b = _cand("viscous", "v", 0.1, 1), _cand("coulomb", "v", 50.0, 1)
    mark_equivalent([a, b], col_of, An, [0])
    assert a.absorbed and not b.absorbed


def test_the_one_sided_score_keeps_a_signed_estimate_nonnegative():
    """scoring._one_sided: the energy explained with the one-step estimates
    β = −coefficient of the signed columns kept >= 0 equals the bounded
    least squares of scipy (lsq_linear) on the same columns, where the
    unconstrained fit asks for a negative β; unchanged where it does not.
    Columns: 0 an estimated parameter (free), 1 and 2 an effect's, 1 signed."""
    from scipy.optimize import lsq_linear

    from bondgraph.diagnose.scoring import _one_sided

    rng = np.random.default_rng(4)
    G = rng.normal(size=(300, 3))
    for coef, signed in (((0.5, 1.0, 0.3), [0]), ((0.5, 1.0, -0.3), [0]),
                         ((0.5, 1.0, 1.0), [0, 1]), ((0.5, -1.0, 0.2), [0])):
        # the innovation e ≈ −G·(−β): a positive coefficient is a negative β
        e = G @ np.array(coef) + 0.3 * rng.normal(size=300)
        A, b = G.T @ G, G.T @ e
        energy, sol = _one_sided(A, b, np.ones(3), [0], [1, 2], signed)
        ub = np.full(3, np.inf)
        for i in signed:
            ub[1 + i] = 0.0                 # β = −coefficient >= 0
        ref = lsq_linear(G, e, bounds=(np.full(3, -np.inf), ub), tol=1e-12)
        assert energy == pytest.approx(e @ e - np.sum((G @ ref.x - e) ** 2), rel=1e-9)
        np.testing.assert_allclose(sol, ref.x, atol=1e-9)
        if all(coef[1 + i] <= 0 for i in signed):
            # nothing asks for a negative β: the two-sided fit itself
            free = np.linalg.lstsq(G, e, rcond=None)[0]
            np.testing.assert_allclose(sol, free, atol=1e-9)


def test_a_signature_whose_smaller_nudge_failed_is_the_larger_nudges_without_a_warning():
    """scoring.signatures: forward differences of the innovations (N=50,
    n_y=1); a column whose smaller nudge failed throughout (NaN) takes the
    larger nudge's difference quotient, one whose larger nudge failed takes
    the smaller's, one nonlinear (the two differ by more than 5 %) the
    smaller's; numpy's all-NaN warning does not reach the user."""
    import warnings

    from bondgraph.diagnose.scoring import LADDER, signatures

    rng = np.random.default_rng(1)
    eps0 = rng.standard_normal((50, 1))
    lin, curved = rng.standard_normal((50, 1)), rng.standard_normal((50, 1))
    deltas = np.array([0.1, 0.1, 0.1])
    D = np.empty((2, 3, 50, 1))
    for l_, f in enumerate(LADDER[:2]):
        d = deltas[0] * f
        D[l_, 0] = eps0 + d * lin
        D[l_, 1] = eps0 + d * lin
        D[l_, 2] = eps0 + d * curved + (d * curved) ** 2 * 10.0
    D[1, 0] = np.nan                      # the smaller nudge of column 0 failed
    D[0, 1] = np.nan                      # the larger nudge of column 1 failed
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        J = signatures(eps0, D, np.empty((0, 50, 1)), deltas, [])
    np.testing.assert_allclose(J[:, :, 0], lin, rtol=1e-9)
    np.testing.assert_allclose(J[:, :, 1], lin, rtol=1e-9)
    small = deltas[2] * LADDER[1]
    np.testing.assert_allclose(J[:, :, 2], curved + small * curved ** 2 * 10.0, rtol=1e-9)
