"""Fisher scoring does not depend on the parameters' units: the predicted
decrease and the scoring step are solved with Jacobi scaling
(:func:`bondgraph.inference.fisher.jacobi_solve`). Reference: the same
quantities in well-scaled coordinates, where no cut of small singular
values can act."""

from types import SimpleNamespace

import numpy as np

from bondgraph.inference.fisher import (
    _predicted_decrease,
    _scoring_step,
    jacobi_pinv,
    jacobi_solve,
)

# information of a law coefficient of ~1e-9, a resistance of ~1e5 and an O(1)
# parameter: F = S A S with A well conditioned, so F spans ~36 decades
A = np.array([[2.0, 0.9, -0.3], [0.9, 1.5, 0.4], [-0.3, 0.4, 1.0]])
S = np.diag([1e9, 1e-5, 1.0])
b = np.array([1.3, -0.7, 0.2])


def _derivs():
    return SimpleNamespace(F=S @ A @ S, grad=S @ b)


def test_predicted_decrease_is_unit_free():
    ref = 0.5 * b @ np.linalg.solve(A, b)         # ½ gᵀF⁻¹g = ½ bᵀA⁻¹b
    got = _predicted_decrease(_derivs(), np.ones(3), np.zeros(3, bool))
    assert got == np.float64(got) and abs(got / ref - 1) < 1e-10
    # what an unscaled least-squares cut at 1e-12 gives: the small
    # directions dropped, the decrease underestimated
    F, g = S @ A @ S, S @ b
    cut = 0.5 * g @ np.linalg.lstsq(F, g, rcond=1e-12)[0]
    assert abs(cut / ref - 1) > 0.05


def test_scoring_step_is_unit_free():
    for lam in (0.0, 1e-3, 10.0):
        As = A + lam * np.diag(np.diag(A))
        ref = -np.linalg.solve(S, np.linalg.solve(As, b))   # -(S As S)⁻¹ S b
        got = _scoring_step(_derivs(), np.ones(3), np.zeros(3, bool), lam)
        assert np.allclose(got, ref, rtol=1e-10, atol=0)


def test_jacobi_solve_singular_falls_back_to_least_squares():
    F = S @ np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 2.0]]) @ S
    g = S @ np.array([1.0, 1.0, 4.0])
    x = jacobi_solve(F, g, lstsq=True)
    # minimum-norm solution in the scaled coordinates: (½, ½, 2) there
    assert np.allclose(S @ x, [0.5, 0.5, 2.0], rtol=1e-10)


def test_jacobi_pinv_is_the_inverse_across_36_decades():
    """(S A S)⁺ = S⁻¹ A⁻¹ S⁻¹; numpy's pinv of the unscaled matrix cuts
    the small directions at its default rcond and is far off."""
    ref = np.linalg.inv(S) @ np.linalg.inv(A) @ np.linalg.inv(S)
    got = jacobi_pinv(S @ A @ S)
    assert np.allclose(got, ref, rtol=1e-9, atol=0)
    assert not np.allclose(np.linalg.pinv(S @ A @ S), ref, rtol=1e-3, atol=0)


# a near-singular information: the first two quantities enter nearly only
# as their sum (their scaled sensitivities differ by 1e-9), the third alone
A_RIDGE = np.array([[1.0, 1.0 - 1e-9, 0.0], [1.0 - 1e-9, 1.0, 0.0], [0.0, 0.0, 2.0]])


def test_flat_directions_name_the_ridge_and_the_decrease_beside_it():
    """By hand, in the unit-diagonal coordinates (A_RIDGE with its third row
    and column divided by √2): eigenvectors (1, 1, 0)/√2 (λ = 2 - 1e-9),
    (0, 0, 1) (λ = 1) and (1, -1, 0)/√2 (λ = 1e-9). With the scaled gradient
    (1, 1.01, 4/√2) the decrease outside the ridge is
    ½ [(2.01/√2)² / 2 + (4/√2)²] = ½ (1.010025 + 8); along the ridge it is
    ½ (0.01/√2)² / 1e-9 = 2.5e4 nats, which the full prediction carries."""
    from bondgraph.inference.fisher import flat_directions

    g = S @ np.array([1.0, 1.01, 4.0])
    flat, identified = flat_directions(S @ A_RIDGE @ S, g)
    assert flat[:2] in ((0, 1), (1, 0)) and len(flat) == 2
    # the eigenvalue 2 - 1e-9 enters the first term: relative 5e-10
    assert abs(identified - 0.5 * (2.01 ** 2 / 4 + 8.0)) < 1e-8
    full = _predicted_decrease(SimpleNamespace(F=S @ A_RIDGE @ S, grad=g), np.ones(3),
                               np.zeros(3, bool))
    assert 2.0e4 < full < 3.0e4
    # a well-conditioned information has no flat direction
    assert flat_directions(S @ A @ S, S @ b)[0] == ()
    # the third quantity held: the ridge is still named, the rest is empty
    flat2, ident2 = flat_directions(S @ A_RIDGE @ S, g, free=np.array([True, True, False]))
    assert sorted(flat2) == [0, 1] and abs(ident2 - 0.5 * 2.01 ** 2 / 4) < 1e-8


def test_scoring_stops_on_a_flat_ridge_only_when_it_gains_little():
    """The convergence test of Fisher scoring: converged in the identified
    directions (decrease 1.25e-7 nats there) while the full prediction along a
    ridge is 2.5e2 nats: stopped, the ridge named, only when the last
    accepted step gained less than FLAT_GAIN and a tolerance is set."""
    from bondgraph.inference.fisher import FLAT_GAIN, _converged

    d = SimpleNamespace(F=S @ A_RIDGE @ S, grad=S @ np.array([1e-3, 0.0, 0.0]))
    x, L = np.ones(3), np.zeros(3, bool)
    free = np.ones(3, bool)
    assert _predicted_decrease(d, x, L) > 1e2
    done, flat = _converged(d, x, L, free, 1e-2, 0.5 * FLAT_GAIN)
    assert done and sorted(flat) == [0, 1]
    assert _converged(d, x, L, free, 1e-2, 2.0 * FLAT_GAIN) == (False, ())
    assert _converged(d, x, L, free, 0.0, 0.0) == (False, ())      # atol 0: rtol alone stops
    # the identified part itself not converged: no stop
    d2 = SimpleNamespace(F=d.F, grad=S @ np.array([1.0, 1.0, 1.0]))
    assert _converged(d2, x, L, free, 1e-2, 0.0) == (False, ())


def test_the_line_search_runs_its_other_points_only_when_the_full_steps_disappoint():
    """:func:`bondgraph.inference.fisher._line_search` on the quadratic
    NLL(θ) = NLL₀ + gᵀΔ + ½ ΔᵀFΔ (the model its ratio test compares with):
    the scoring step is exact there, so the first batch (α 1 and 2) gains
    all the model predicts and the six damped points and the decade moves
    are not run (one batch); on an NLL that rises along the step, or falls
    five times faster than the model says (the model wrong), the rest is
    run too (two batches). The decrease of the quadratic model is checked
    by hand."""
    from bondgraph.inference.fisher import (FIRST_ALPHAS, _candidates, _line_search,
                                            _model_decrease, _scoring_step)

    F = np.array([[2.0, 0.5], [0.5, 1.0]])
    g = np.array([1.0, -2.0])
    z = np.array([1.0, 3.0])
    L = np.array([False, True])                      # the second in log θ: decade moves
    d = SimpleNamespace(F=F, grad=g, nll=10.0)
    step = _scoring_step(d, z, L, 0.0)
    alphas, cand = _candidates(z, step, L, np.full(2, 1e-3), np.full(2, 1e3))
    assert len(cand) == 6 + 4 and set(FIRST_ALPHAS) <= set(alphas)

    def quad(c):
        dl = np.array([c[0] - z[0], np.log(c[1] / z[1])])
        gz, Fz = g * np.array([1.0, z[1]]), F * np.outer([1.0, z[1]], [1.0, z[1]])
        return 10.0 + gz @ dl + 0.5 * dl @ Fz @ dl

    full = cand[list(alphas).index(1.0)]
    assert abs(_model_decrease(d, z, full, L) - (10.0 - quad(full))) < 1e-12
    assert 10.0 - quad(full) > 0.5                   # a real decrease to compare with
    calls = []

    def line(rows, f=quad):
        calls.append(len(rows))
        return np.array([f(r) for r in rows])

    nll, runs = _line_search(line, d, z, L, alphas, cand, 1e-6)
    assert runs == 1 and calls == [2]
    assert np.isfinite(nll).sum() == 2 and np.nanmin(nll) == quad(full)
    calls.clear()
    nll, runs = _line_search(lambda rows: line(rows, lambda c: 20.0 - quad(c)), d, z, L,
                             alphas, cand, 1e-6)
    assert runs == 2 and calls == [2, 8] and np.isfinite(nll).all()
    # a gain far above the model's (the step far too short): the rest too
    calls.clear()
    nll, runs = _line_search(lambda rows: line(rows, lambda c: 10.0 - 5.0 * (10.0 - quad(c))),
                             d, z, L, alphas, cand, 1e-6)
    assert runs == 2 and calls == [2, 8]
    # a gain that would end the scoring (3.12 nats below the relative stop,
    # here rtol 0.5 of 1 + |NLL| = 7.9) is taken only from every point
    calls.clear()
    nll, runs = _line_search(line, d, z, L, alphas, cand, 0.5)
    assert runs == 2 and calls == [2, 8]
