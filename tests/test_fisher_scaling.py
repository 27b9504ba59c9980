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
