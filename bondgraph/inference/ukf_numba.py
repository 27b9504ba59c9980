"""The fused UKF likelihood kernel (numba): one particle per thread.

The same filter as :mod:`bondgraph.inference.ukf` (Wan & van der Merwe 2000;
the difference form of :mod:`bondgraph.inference.sigma`), written for one
parameter set at a time and run over the sets by a pool of threads, one set
per call of the compiled kernel, which releases the GIL (:func:`run`):
sigma points, the transition (RK4 or ROS2 with the Jacobian at the central
sigma point or at every point, :mod:`bondgraph.numerics.integrators`), the
measurement update over the measured outputs, and the NLL accumulation.
Each set's arithmetic depends on nothing but its own data, so results do
not depend on the batch, the thread count or the split over workers.

Failure handling is that of the numpy path: the same checks at the same
places, with the same reasons (:data:`FAIL_REASONS`, formatted by the
caller), +inf NLL from the failing sample on, and the same diagonal loading
of covariances that are indefinite at rounding level
(:func:`bondgraph.inference.sigma.cholesky_batch`). The only documented
difference: an exactly singular ROS2 matrix W, which numpy's ``inv`` raises
on, gives a non-finite state here (a measure-zero event).

The kernel is model independent: the model's point kernels
(:mod:`bondgraph.numerics.compiled`) are passed as first-class functions of
fixed signature, so it is compiled once per installation and cached on disk
(``cache=True``), and a new model costs only the compilation of its own
small point kernels.

Arguments are packed (no function takes more than 12): the kernel
:func:`_kernel_py` takes ``(fns, rec, sets, opts, out, st, bufs)``: the
point kernels as one plain tuple (f, h, f_dfdx, f_cols, h_cols)
(:func:`point_fns`; a heterogeneous ``types.Tuple`` of first-class function
types: numba converts a tuple of dispatchers to it, not a namedtuple), the
record :data:`Record` (t, u, y), the parameter sets :data:`Sets` (th, x0,
P0, q2, Rd, R, Q, act), the options (ip, fp), the outputs :data:`Outputs`
(nll, info), the storage arrays ``st`` and the work buffers (buf, ibuf).
``st`` is an argument of its own, not a field of the outputs: the function
numba makes of the parallel loop takes tuples of arrays, not tuples nested
in them. :func:`_filter_one` takes the same packs for one set; the inlined
steps unpack what they use (``_predict(fns, ..., opts, wk)``), and the
per-point integrator takes its few work vectors as small tuples
(:func:`_ros2_point` ``vw`` = (ub, xt, F0, F1, k1, k2), ``lw`` = (J, Winv,
A, cols)). numba passes a
tuple as its flattened members, so the packing costs nothing at run time
(A/B in the commit that introduced it: same ms per evaluation within noise,
bit-identical NLL).

Performance layout (measured with bench/kernel_profile.py and
bench/kernel_phases.py): the kernel allocates nothing and runs without
numba's reference counting (``_nrt=False``): each set's work arrays are
carved from rows of two zeroed buffers that :func:`run` allocates
(:func:`_work_size`, :func:`_work`); the per-step helpers are inlined at
numba-IR level, so the work tuple is never passed by value; shared rows
u[k], y[k] are copied, not viewed. With the shared Jacobian (the default)
ROS2 runs stage by stage over the points: f of all points in one call of
the model's ``f_cols`` (points state-major; inputs, parameters and what
depends on them alone computed once per call; a loop over the points that
LLVM vectorises, with branch-free sin, cos, atan, exp and tanh), h likewise
(``h_cols``), RK4 stage by stage likewise (:func:`_rk4_shared`), and W = I − γhJ applied
to all points by LU solves over rows of points (:func:`_lu_w`,
:func:`_solve_w`; the Gauss-Jordan inverse :func:`_inverse_w` is the path
for non-finite or singular W, whose NaN/inf pattern is the reference's).
Sums are dot products over contiguous rows (points innermost), compiled
with the LLVM fast-math flags reassociation, contraction and no signed
zeros (:data:`FASTMATH`; never nnan/ninf: the failure checks rely on NaN
and inf), so the NLL equals the numpy reference's to rounding, not to the
bit (the equality tests allow 1e-9 relative).

The input hold over a sample interval is one small function,
:func:`_held_input` (codes :data:`HOLD_CODES`); a hold that varies within
the interval gets a code from :data:`FIRST_VARYING_HOLD` on and is then
evaluated at every stage time of the integrators. A hold that differs
between inputs (``"zoh,linear"``) is code :data:`PER_INPUT_HOLD`: the record
then carries three blocks of columns (:func:`kernel_inputs`), the samples
(what the measurement function reads), each interval's start and its change
(:func:`bondgraph.numerics.integrators.hold_inputs`).

References
----------
Wan, E. A., van der Merwe, R. (2000). The unscented Kalman filter for
nonlinear estimation. Proc. IEEE AS-SPCC, 153-158.
Verwer, J. G., Spee, E. J., Blom, J. G., Hundsdorfer, W. (1999). A
second-order Rosenbrock method applied to photochemical dispersion problems.
SIAM J. Sci. Comput. 20(4), 1456-1480.
"""

from __future__ import annotations

import atexit
import contextlib
import hashlib
import os
import subprocess
import sys
import threading
import time
import warnings
from collections import namedtuple
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from bondgraph.core.codegen_numba import padded_points
from bondgraph.core.progress import announced
from bondgraph.inference.options import interval_substeps
from bondgraph.numerics.compiled import ahead_workers, cache_dir
from bondgraph.numerics.integrators import GAMMA, hold_inputs, is_per_input, split_hold

try:  # numba is a regular dependency; the numpy path is the fallback without it
    import numba
    from numba import types
except ImportError:  # pragma: no cover - exercised only without numba
    numba = None
    types = None

LOG_2PI = float(np.log(2.0 * np.pi))

#: failure codes of the kernel -> the numpy path's reasons
FAIL_REASONS = {
    1: "posterior covariance P not positive definite",
    2: "prior covariance P not positive definite",
    3: ("non-finite state in the prediction (a sigma point diverged, or a law is "
        "not defined where a sigma point went: a log of, or a division by, a state near 0)"),
    4: "non-finite predicted output h(sigma point)",
    5: "innovation covariance S not positive definite",
}
#: UKFOptions.method -> code
METHOD_CODES = {"rk4": 0, "ros2": 1}
#: UKFOptions.jacobian -> code: 0 at the central sigma point, shared by the
#: set's points ("mean"); 1 at every point, frozen over the sub-steps
#: ("sigma"); 2 at every point and sub-step (integrators' "each")
JACOBIAN_CODES = {"mean": 0, "sigma": 1, "each": 2}
#: UKFOptions.hold -> code (see _held_input)
HOLD_CODES = {"zoh": 0, "mean": 1, "linear": 2}
#: holds with codes from here on vary within the interval (evaluated per stage)
FIRST_VARYING_HOLD = 2
#: code of a hold that differs between inputs: the record's u is
#: (N, 3 n_u), [samples, interval start, interval change] (:func:`kernel_inputs`)
PER_INPUT_HOLD = 3
#: layout of the integer options array of the kernel
IOPT = ("method", "substeps", "jacobian", "hold", "use_R", "use_Q", "store")
#: LLVM fast-math flags of the kernel: reassociation (vectorised sums),
#: contraction (fused multiply-add) and no signed zeros; never nnan/ninf,
#: the failure checks rely on NaN and inf
FASTMATH = {"reassoc", "contract", "nsz"}


def _jit(fn):
    """``numba.njit`` with numpy's error model (inf/nan, no exceptions), or
    the plain function without numba."""
    if numba is None:  # pragma: no cover
        return fn
    return numba.njit(cache=True, nogil=True, error_model="numpy", _nrt=False,
                      fastmath=FASTMATH)(fn)


def _jit_inline(fn):
    """:func:`_jit` inlined into its caller at numba-IR level: only for the
    steps that take the per-particle work tuple (and :func:`_work`, which
    makes it), whose passing by value (~40 arrays) otherwise costs more than
    the arithmetic of a step. The helpers that take a few arrays are plain
    :func:`_jit` calls, which LLVM inlines where it pays: numba's IR-level
    inlining copies the callee's IR at every call site, and with every
    helper inlined so the kernel compiled in 42 s against 19 s, and ran
    8 % slower (``bench/estimation.py --quick``: 1.24 against 1.14 ms per
    evaluation)."""
    if numba is None:  # pragma: no cover
        return fn
    return numba.njit(cache=True, nogil=True, error_model="numpy", inline="always",
                      _nrt=False, fastmath=FASTMATH)(fn)


Work = namedtuple("Work", ["L", "D", "mean", "cov", "xs", "xt", "k1", "k2",
                           "k3", "k4", "F0", "F1", "J", "Winv", "A", "ub", "Ym", "idx",
                           "Pyx", "Gt", "z", "eps", "Ls", "yf", "nreg", "yv", "uk", "yk", "cols",
                           "FT", "K1", "K2", "XS", "skip", "XT", "XTf", "XSf", "FTf", "YT",
                           "YTf"])


#: the record as the kernel takes it: t (N,), u (N, n_u), y (N, n_y), ns
#: (N,): the substeps of the interval from each sample to the next (the
#: last entry unused; :func:`interval_counts`)
Record = namedtuple("Record", ["t", "u", "y", "ns"])
#: the parameter sets of one kernel call, one row each (A sets): th
#: (A, n_theta), x0 (A, n_x), P0 (A, n_x, n_x), q2 (A, n_x); Rd (A, n_y) or
#: one shared row, R and Q (A, ., .) or one shared matrix (codes use_R,
#: use_Q of :data:`IOPT` say which); act (A,): the sets' rows of the storage
Sets = namedtuple("Sets", ["th", "x0", "P0", "q2", "Rd", "R", "Q", "act"])
#: what the kernel writes besides the storage: nll (A,); info (A, 3):
#: failing sample (-1: none), failure code, loaded factorisations
Outputs = namedtuple("Outputs", ["nll", "info"])


def point_fns(kernels) -> tuple:
    """The model's point kernels as the kernel takes them: the plain tuple
    (f, h, f_dfdx, f_cols, h_cols) (numba converts a tuple of dispatchers
    to first-class function types, not a namedtuple of them)."""
    return (kernels.f, kernels.h, kernels.f_dfdx, kernels.f_cols, kernels.h_cols)


@_jit_inline
def _carve(buf, o, r, c):
    """The (r, c) block of the flat buffer ``buf`` from offset o, and the next offset."""
    return buf[o:o + r * c].reshape((r, c)), o + r * c


@_jit
def _work_size(n, ny, nu, nth):
    """Lengths of the float and integer work buffers of one parameter set
    (:func:`_work`)."""
    npt, m, pc = 2 * n + 1, max(n, ny), _padded(n)
    return (6 * n * n + npt * m + m + m * m + 9 * n + 2 * nu + 2 * pc * ny + 2 * n * ny
            + ny * ny + 5 * ny + nth + 5 * n * pc, ny + 1 + 2 * n + m)


#: columns of the state-major point arrays: the 2n + 1 sigma points and
#: copies of point 0; the generator's one padding rule, compiled
#: (:func:`bondgraph.core.codegen_numba.padded_points`: the column kernels'
#: loops run in whole vectors)
_padded = _jit(padded_points)


@_jit_inline
def _work(buf, ibuf, n, ny, nu, nth):
    """Per-particle work arrays carved from its zeroed buffers (allocated by
    the caller: the kernel allocates nothing and runs without numba's
    reference counting), with the set's state x, covariance P and
    parameters."""
    npt, m, pc = 2 * n + 1, max(n, ny), _padded(n)
    L, o = _carve(buf, 0, n, n)
    D, o = _carve(buf, o, m, npt)
    cov, o = _carve(buf, o, m, m)
    vn, o = _carve(buf, o, 9, n)
    J, o = _carve(buf, o, n, n)
    Winv, o = _carve(buf, o, n, n)
    A, o = _carve(buf, o, n, 2 * n)
    Ym, o = _carve(buf, o, ny, pc)
    Pyx, o = _carve(buf, o, ny, n)
    Gt, o = _carve(buf, o, ny, n)
    Ls, o = _carve(buf, o, ny, ny)
    vy, o = _carve(buf, o, 5, ny)
    vu, o = _carve(buf, o, 2, nu)
    mean, o = _carve(buf, o, 1, m)
    P, o = _carve(buf, o, n, n)
    tha, o = _carve(buf, o, 1, nth)
    FTf, FT = buf[o:o + n * pc], _carve(buf, o, n, pc)[0]
    K1, o = _carve(buf, o + n * pc, n, pc)
    K2, o = _carve(buf, o, n, pc)
    XSf, XS = buf[o:o + n * pc], _carve(buf, o, n, pc)[0]
    XTf, XT = buf[o + n * pc:o + 2 * n * pc], _carve(buf, o + n * pc, n, pc)[0]
    YTf, YT = buf[o + 2 * n * pc:o + (2 * n + ny) * pc], _carve(buf, o + 2 * n * pc, ny, pc)[0]
    wk = Work(L, D, mean[0], cov, vn[0], vn[1], vn[2], vn[3], vn[4], vn[5], vn[6],
              vn[7], J, Winv, A, vu[0], Ym, ibuf[:ny], Pyx, Gt, vy[0], vy[1], Ls, vy[2],
              ibuf[ny:ny + 1], vy[3], vu[1], vy[4], ibuf[ny + 1:ny + 1 + 2 * n], FT, K1, K2, XS,
              ibuf[ny + 1 + 2 * n:], XT, XTf, XSf, FTf, YT, YTf)
    return wk, vn[8], P, tha[0]


# ------------------------------------------------------------ linear algebra
@_jit
def _all_finite(A, r, c):
    """Whether A[:r, :c] is finite: Σ A·0 is 0 for finite entries and NaN
    otherwise, one branch-free sum the compiler vectorises (valid without
    the nnan/ninf fast-math flags)."""
    acc = 0.0
    for i in range(r):
        for j in range(c):
            acc += A[i, j] * 0.0
    return acc == 0.0


@_jit
def _chol_plain(A, m, eps, L, skip):
    """Lower Cholesky factor of A[:m, :m] + eps diag(A) (lower triangle used)
    into L; False where LAPACK's potrf fails (a pivot not > 0, or NaN).
    Rows and columns j with ``skip[j]`` (exactly zero in A) are zero in L."""
    for j in range(m):
        if skip[j]:
            for i in range(m):
                L[i, j] = 0.0
            continue
        s = A[j, j] + eps * A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, m):
            v = A[i, j]
            for k in range(j):
                v -= L[i, k] * L[j, k]
            L[i, j] = v / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@_jit
def _chol(A, m, L, known, skip):
    """:func:`bondgraph.inference.sigma.cholesky_batch` for one matrix:
    0 failed (not finite, or not positive definite even with relative
    diagonal loading 1e-12, 1e-9, 1e-6), 1 factorised, 2 factorised with
    loading. With ``known`` (state covariances) rows and columns that are
    exactly zero are left out of the loaded factorisation (zero in L);
    ``skip`` (m,) is work space."""
    for i in range(m):
        skip[i] = False
    if not _all_finite(A, m, m):
        return 0
    if _chol_plain(A, m, 0.0, L, skip):
        return 1
    for i in range(m):
        if known:
            zero = True
            for j in range(m):
                if A[i, j] != 0.0:
                    zero = False
                    break
            if zero:
                skip[i] = True
                continue
        if not A[i, i] > 0.0:
            return 0
    for eps in (1e-12, 1e-9, 1e-6):
        if _chol_plain(A, m, eps, L, skip):
            return 2
    return 0


@_jit
def _w_matrix(J, h, A):
    """[I − γ h J | I] into the work array A (n, 2n)."""
    n = J.shape[0]
    g = GAMMA * h
    for i in range(n):
        for j in range(n):
            A[i, j] = (1.0 if i == j else 0.0) - g * J[i, j]
            A[i, n + j] = 1.0 if i == j else 0.0


@_jit
def _inverse_w_dense(J, h, A, Winv):
    """Winv = (I − γ h J)⁻¹ by Gauss-Jordan elimination with partial
    pivoting over every column of [W | I] (numpy: ``np.linalg.inv``): the
    reference for :func:`_inverse_w`, and its path for non-finite values."""
    n = J.shape[0]
    _w_matrix(J, h, A)
    for c in range(n):
        p = c
        for i in range(c + 1, n):
            if abs(A[i, c]) > abs(A[p, c]):
                p = i
        if p != c:
            for j in range(2 * n):
                A[c, j], A[p, j] = A[p, j], A[c, j]
        d = A[c, c]
        for j in range(2 * n):
            A[c, j] /= d
        for i in range(n):
            if i != c:
                q = A[i, c]
                for j in range(2 * n):
                    A[i, j] -= q * A[c, j]
    for i in range(n):
        for j in range(n):
            Winv[i, j] = A[i, n + j]


@_jit
def _inverse_w(J, h, A, Winv, cols):
    """Winv = (I − γ h J)⁻¹: :func:`_inverse_w_dense` restricted to the
    columns it changes. After step c the columns <= c of W are never read
    again, and a column whose pivot-row entry is exactly 0 is left as it is
    (x − q·0 = x for finite q); so every entry of Winv is the same double
    (up to the sign of zeros, which no later sum can see). A non-finite or
    zero pivot or multiplier reruns the dense elimination, whose NaN/inf
    pattern is then the reference's. ``cols``: int work vector (2n,)."""
    n = J.shape[0]
    _w_matrix(J, h, A)
    for c in range(n):
        p = c
        for i in range(c + 1, n):
            if abs(A[i, c]) > abs(A[p, c]):
                p = i
        d = A[c, c] if p == c else A[p, c]
        if d == 0.0 or not np.isfinite(d):
            _inverse_w_dense(J, h, A, Winv)
            return
        if p != c:
            A[c, c], A[p, c] = A[p, c], A[c, c]
        m = 0
        for j in range(c + 1, 2 * n):
            if p != c:
                A[c, j], A[p, j] = A[p, j], A[c, j]
            if A[c, j] != 0.0:
                A[c, j] /= d
                cols[m] = j
                m += 1
        for i in range(n):
            if i != c:
                q = A[i, c]
                if not np.isfinite(q):
                    _inverse_w_dense(J, h, A, Winv)
                    return
                for r in range(m):
                    j = cols[r]
                    A[i, j] -= q * A[c, j]
    for i in range(n):
        for j in range(n):
            Winv[i, j] = A[i, n + j]


@_jit
def _lu_w(J, h, A, piv):
    """LU factors (partial pivoting, row swaps in ``piv``) of W = I − γ h J
    in A[:, :n]: unit lower L below the diagonal, U on and above it.
    False (factors unusable) for a non-finite entry or a zero or
    non-finite pivot: the caller then takes :func:`_inverse_w`, whose
    NaN/inf pattern is the reference's."""
    n = J.shape[0]
    g = GAMMA * h
    for i in range(n):
        for j in range(n):
            A[i, j] = (1.0 if i == j else 0.0) - g * J[i, j]
    if not _all_finite(A, n, n):
        return False
    for c in range(n):
        p = c
        for i in range(c + 1, n):
            if abs(A[i, c]) > abs(A[p, c]):
                p = i
        piv[c] = p
        d = A[p, c]
        if d == 0.0 or not np.isfinite(d):
            return False
        if p != c:
            for j in range(n):
                A[c, j], A[p, j] = A[p, j], A[c, j]
        for i in range(c + 1, n):
            q = A[i, c] / d
            A[i, c] = q
            if q != 0.0:
                for j in range(c + 1, n):
                    A[i, j] -= q * A[c, j]
    return True


@_jit
def _solve_w(A, piv, F, K):
    """K = W⁻¹ F for all points at once (F, K: (n, points), one column per
    point) from the LU factors of :func:`_lu_w`: row swaps, forward and
    back substitution, each a row operation over the points (contiguous,
    vectorised); zero factors (the Jacobian's sparsity) are skipped."""
    n, npt = F.shape
    for i in range(n):
        for p in range(npt):
            K[i, p] = F[i, p]
    for c in range(n):
        r = piv[c]
        if r != c:
            for p in range(npt):
                K[c, p], K[r, p] = K[r, p], K[c, p]
    for i in range(1, n):
        for j in range(i):
            q = A[i, j]
            if q != 0.0:
                for p in range(npt):
                    K[i, p] -= q * K[j, p]
    for i in range(n - 1, -1, -1):
        for j in range(i + 1, n):
            q = A[i, j]
            if q != 0.0:
                for p in range(npt):
                    K[i, p] -= q * K[j, p]
        d = 1.0 / A[i, i]
        for p in range(npt):
            K[i, p] = K[i, p] * d


@_jit_inline
def _apply_w(lu, wk, F, K):
    """K = W⁻¹ F: by the LU factors (lu) or the product with W⁻¹."""
    if lu:
        _solve_w(wk.A, wk.cols, F, K)
    else:
        _times_w(wk.Winv, F, K)


@_jit
def _matvec(M, v, out):
    n = v.shape[0]
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += M[i, j] * v[j]
        out[i] = s


# ------------------------------------------------------------ sigma points
@_jit
def _sigma(x, L, c, XT):
    """Scaled sigma points χ_0 = x, χ_i = x + c L_i, χ_n+i = x − c L_i
    state-major into XT (n, :func:`_padded`): XT[a, j] is state a of point
    j; the columns after 2n are copies of point 0 (padding)."""
    n = x.shape[0]
    for a in range(n):
        xa = x[a]
        XT[a, 0] = xa
        for i in range(n):
            v = c * L[a, i]
            XT[a, 1 + i] = xa + v
            XT[a, 1 + n + i] = xa - v
        for j in range(2 * n + 1, XT.shape[1]):
            XT[a, j] = xa


@_jit
def _moments(Z, m, w, cc, mean, cov, D):
    """Difference-form unscented mean and covariance of Z[:m] (m rows,
    one per component; the points along the rows: state- or output-major)
    (:func:`bondgraph.inference.sigma.unscented_moments`); D[a, i] =
    Z_a,i+1 − Z_a,0 (each sum is a contiguous dot product, vectorised with
    reassociation)."""
    npt = D.shape[1]
    for a in range(m):
        z0 = Z[a, 0]
        for i in range(1, npt):
            D[a, i - 1] = Z[a, i] - z0
    for a in range(m):
        s = 0.0
        for i in range(npt - 1):
            s += D[a, i]
        mean[a] = w * s
    for a in range(m):
        for b in range(a + 1):
            s = 0.0
            for i in range(npt - 1):
                s += D[a, i] * D[b, i]
            v = w * s + cc * (mean[a] * mean[b])
            cov[a, b] = v
            cov[b, a] = v
    for a in range(m):
        mean[a] = Z[a, 0] + mean[a]


# ------------------------------------------------------------ transition
@_jit
def _held_input(u, k, frac, hold, out):
    """The input over the interval [t_k, t_k+1] at the fraction ``frac`` of
    it (numpy: :func:`bondgraph.numerics.integrators.hold_inputs`): hold 0
    (zoh) u_k; 1 (mean) (u_k + u_k+1)/2; 2 (linear, first-order hold)
    u_k + frac·(u_k+1 − u_k); u_k on the last row. A new hold is one more
    branch here (and a code in HOLD_CODES). Hold 3 (:data:`PER_INPUT_HOLD`,
    u of three blocks, :func:`kernel_inputs`): start + frac·change."""
    if hold == 3:
        m = u.shape[1] // 3
        for j in range(m):
            out[j] = u[k, m + j] + frac * u[k, 2 * m + j]
        return
    last = k + 1 >= u.shape[0]
    for j in range(u.shape[1]):
        if hold == 1 and not last:
            out[j] = 0.5 * (u[k, j] + u[k + 1, j])
        elif hold == 2 and not last:
            out[j] = u[k, j] + frac * (u[k + 1, j] - u[k, j])
        else:
            out[j] = u[k, j]


@_jit
def _stage_input(u, k, s, cst, nsub, hold, out):
    """Re-evaluate a varying hold at stage ``s + cst`` of ``nsub`` sub-steps
    (constant holds need nothing)."""
    if hold >= FIRST_VARYING_HOLD:
        _held_input(u, k, (s + cst) / nsub, hold, out)


@_jit
def _rk4_point(f, x, u, k, hold, th, h, nsub, vw):
    """``nsub`` classical RK4 steps of one point x (in place)
    (:func:`bondgraph.numerics.integrators.rk4`; the free runs of
    :mod:`bondgraph.inference.sim_numba`, the filter's points take
    :func:`_rk4_shared`); ``vw``: the work vectors
    (ub, xt, k1, k2, k3, k4), a tuple of the few this step uses (not the
    whole work tuple, whose ~40 arrays would be passed by value per
    point)."""
    ub, xt, k1, k2, k3, k4 = vw
    n = x.shape[0]
    for s in range(nsub):
        _stage_input(u, k, s, 0.0, nsub, hold, ub)
        f(x, ub, th, k1)
        for a in range(n):
            xt[a] = x[a] + (0.5 * h) * k1[a]
        _stage_input(u, k, s, 0.5, nsub, hold, ub)
        f(xt, ub, th, k2)
        for a in range(n):
            xt[a] = x[a] + (0.5 * h) * k2[a]
        f(xt, ub, th, k3)
        for a in range(n):
            xt[a] = x[a] + h * k3[a]
        _stage_input(u, k, s, 1.0, nsub, hold, ub)
        f(xt, ub, th, k4)
        for a in range(n):
            x[a] = x[a] + (h / 6.0) * (k1[a] + 2.0 * k2[a] + 2.0 * k3[a] + k4[a])


@_jit
def _ros2_point(f, fj, x, u, k, hold, th, h, nsub, jac, vw, lw):
    """``nsub`` ROS2 steps of one point x (in place)
    (:func:`bondgraph.numerics.integrators.ros2`); jac 0: Winv is given
    (shared), 1: df/dx at x at the start, frozen, 2: at every sub-step.
    ``vw``: the work vectors (ub, xt, F0, F1, k1, k2); ``lw``: the linear
    algebra's work (J, Winv, A (n, 2n), cols (2n,) int)."""
    ub, xt, F0, F1, k1, k2 = vw
    J, Winv, A, cols = lw
    n = x.shape[0]
    for s in range(nsub):
        _stage_input(u, k, s, 0.0, nsub, hold, ub)
        if jac == 2 or (jac == 1 and s == 0):
            fj(x, ub, th, F0, J)
            _inverse_w(J, h, A, Winv, cols)
        else:
            f(x, ub, th, F0)
        _matvec(Winv, F0, k1)
        for a in range(n):
            xt[a] = x[a] + h * k1[a]
        _stage_input(u, k, s, 1.0, nsub, hold, ub)
        f(xt, ub, th, F1)
        for a in range(n):
            F1[a] = F1[a] - 2.0 * k1[a]
        _matvec(Winv, F1, k2)
        for a in range(n):
            x[a] = x[a] + (1.5 * h) * k1[a] + (0.5 * h) * k2[a]


@_jit
def _times_w(W, F, K):
    """K = W F for all points at once (F, K: (n, points), one column per
    point): every entry is summed in the order of :func:`_matvec` (from 0.0,
    j ascending). Blocks of 8 points are accumulated in scalars (registers:
    the work arrays share one buffer, so sums kept in K would be stored and
    reloaded at every j), which the compiler packs into vector FMAs."""
    n, npt = F.shape
    for i in range(n):
        p = 0
        while p + 8 <= npt:
            s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
            for j in range(n):
                w = W[i, j]
                s0 += w * F[j, p]
                s1 += w * F[j, p + 1]
                s2 += w * F[j, p + 2]
                s3 += w * F[j, p + 3]
                s4 += w * F[j, p + 4]
                s5 += w * F[j, p + 5]
                s6 += w * F[j, p + 6]
                s7 += w * F[j, p + 7]
            K[i, p], K[i, p + 1], K[i, p + 2], K[i, p + 3] = s0, s1, s2, s3
            K[i, p + 4], K[i, p + 5], K[i, p + 6], K[i, p + 7] = s4, s5, s6, s7
            p += 8
        while p + 4 <= npt:
            s0 = s1 = s2 = s3 = 0.0
            for j in range(n):
                w = W[i, j]
                s0 += w * F[j, p]
                s1 += w * F[j, p + 1]
                s2 += w * F[j, p + 2]
                s3 += w * F[j, p + 3]
            K[i, p], K[i, p + 1], K[i, p + 2], K[i, p + 3] = s0, s1, s2, s3
            p += 4
        for q in range(p, npt):
            s0 = 0.0
            for j in range(n):
                s0 += W[i, j] * F[j, q]
            K[i, q] = s0


@_jit_inline
def _ros2_shared(fcols, u, k, hold, th, h, nsub, wk, lu):
    """:func:`_ros2_point` for every sigma point with the shared W⁻¹
    (Jacobian at the central point, jac 0), stage by stage over the points,
    state-major (wk.XT: state a of point j at XT[a, j]): f of all points in
    one call of the model's ``f_cols``, W⁻¹ applied to all points at once
    (:func:`_apply_w`: LU solves, or the product with the inverse where the
    factors are unusable). Each point's arithmetic is that of
    :func:`_ros2_point` up to the rounding of the linear solves and of the
    column kernels' library functions (2 ulp)."""
    n, npt = wk.XT.shape
    XT, XS, ub, K1, K2, FT = wk.XT, wk.XS, wk.ub, wk.K1, wk.K2, wk.FT
    for s in range(nsub):
        _stage_input(u, k, s, 0.0, nsub, hold, ub)
        fcols(wk.XTf, ub, th, wk.FTf)
        _apply_w(lu, wk, FT, K1)
        _stage_input(u, k, s, 1.0, nsub, hold, ub)
        for a in range(n):
            for j in range(npt):
                XS[a, j] = XT[a, j] + h * K1[a, j]
        fcols(wk.XSf, ub, th, wk.FTf)
        for a in range(n):
            for j in range(npt):
                FT[a, j] = FT[a, j] - 2.0 * K1[a, j]
        _apply_w(lu, wk, FT, K2)
        for a in range(n):
            for j in range(npt):
                XT[a, j] = XT[a, j] + (1.5 * h) * K1[a, j] + (0.5 * h) * K2[a, j]


@_jit_inline
def _rk4_shared(fcols, u, k, hold, th, h, nsub, wk):
    """``nsub`` classical RK4 steps
    (:func:`bondgraph.numerics.integrators.rk4`) of every sigma point at
    once, stage by stage over the points (state-major, wk.XT): f of all
    points in one call of the model's ``f_cols`` (a per-point step called
    ``f`` 4·nsub·(2n + 1) times per sample: 1.56 µs per set and sample of
    the EMPS model at RK4(2), one thread). The increments are summed as
    k1 + 2 k2 + 2 k3 + k4 (kept in wk.K1), the numpy reference's order, up
    to the column kernels' library functions (2 ulp) and the kernel's
    reassociation."""
    n, npt = wk.XT.shape
    XT, XS, ub, K1, FT = wk.XT, wk.XS, wk.ub, wk.K1, wk.FT
    for s in range(nsub):
        _stage_input(u, k, s, 0.0, nsub, hold, ub)
        fcols(wk.XTf, ub, th, wk.FTf)
        for a in range(n):
            for j in range(npt):
                K1[a, j] = FT[a, j]
                XS[a, j] = XT[a, j] + (0.5 * h) * FT[a, j]
        _stage_input(u, k, s, 0.5, nsub, hold, ub)
        fcols(wk.XSf, ub, th, wk.FTf)
        for a in range(n):
            for j in range(npt):
                K1[a, j] = K1[a, j] + 2.0 * FT[a, j]
                XS[a, j] = XT[a, j] + (0.5 * h) * FT[a, j]
        fcols(wk.XSf, ub, th, wk.FTf)
        for a in range(n):
            for j in range(npt):
                K1[a, j] = K1[a, j] + 2.0 * FT[a, j]
                XS[a, j] = XT[a, j] + h * FT[a, j]
        _stage_input(u, k, s, 1.0, nsub, hold, ub)
        fcols(wk.XSf, ub, th, wk.FTf)
        for a in range(n):
            for j in range(npt):
                XT[a, j] = XT[a, j] + (h / 6.0) * (K1[a, j] + FT[a, j])


@_jit_inline
def _transition(fns, u, k, th, dt, nsub, ip, wk):
    """Every sigma point (the columns of wk.XT) through the transition over
    interval k (``nsub`` substeps), in place (:func:`bondgraph.numerics.integrators.make_step`);
    ``fns``: the model's point kernels (:func:`point_fns`)."""
    f, _, fj, fcols, _ = fns
    method, jac, hold = ip[0], ip[2], ip[3]
    h = dt / nsub
    n = wk.XT.shape[0]
    npt = 2 * n + 1
    _held_input(u, k, 0.0, hold, wk.ub)
    XT, xs = wk.XT, wk.xs
    if method == 0:
        _rk4_shared(fcols, u, k, hold, th, h, nsub, wk)
        return
    if method == 1 and jac == 0:
        for a in range(n):
            xs[a] = XT[a, 0]
        fj(xs, wk.ub, th, wk.F0, wk.J)
        lu = _lu_w(wk.J, h, wk.A, wk.cols)
        if not lu:
            _inverse_w(wk.J, h, wk.A, wk.Winv, wk.cols)
        _ros2_shared(fcols, u, k, hold, th, h, nsub, wk, lu)
        return
    ub, xt = wk.ub, wk.xt
    for j in range(npt):
        # each point is integrated in the contiguous work vector xs: a view
        # per call of a first-class function costs more than the copies
        for a in range(n):
            xs[a] = XT[a, j]
        if j > 0:
            _held_input(u, k, 0.0, hold, ub)
        _ros2_point(f, fj, xs, u, k, hold, th, h, nsub, jac,
                    (ub, xt, wk.F0, wk.F1, wk.k1, wk.k2), (wk.J, wk.Winv, wk.A, wk.cols))
        for a in range(n):
            XT[a, j] = xs[a]


# ------------------------------------------------------------ predict / update
@_jit_inline
def _predict(fns, x, P, u, k, th, dt, nsub, q2, Q, opts, wk):
    """Prediction over interval k (to sample k + 1, ``nsub`` substeps) in
    place; 0 or a failure code (``fns``: :func:`point_fns`; ``opts``: (ip,
    fp) of :func:`_kernel_py`)."""
    ip, fp = opts
    n = x.shape[0]
    r = _chol(P, n, wk.L, True, wk.skip)
    if r == 0:
        return 1
    wk.nreg[0] += r == 2
    _sigma(x, wk.L, fp[0], wk.XT)
    _transition(fns, u, k, th, dt, nsub, ip, wk)
    if not _all_finite(wk.XT, n, 2 * n + 1):
        return 3
    _moments(wk.XT, n, fp[1], fp[2], x, P, wk.D)
    for a in range(n):
        P[a, a] += q2[a] * dt
    if ip[5]:
        for a in range(n):
            for b in range(n):
                P[a, b] += Q[a, b]
    return 0


@_jit_inline
def _measured_outputs(hcols, x, P, th, uk, yk, fp, wk):
    """Sigma points of the prior through h into wk.YT (output-major: output
    b of point j at YT[b, j]), restricted to the measured outputs of yk
    (their indices in wk.idx) in the rows of wk.Ym where some are missing;
    returns (m, failure code)."""
    n = x.shape[0]
    r = _chol(P, n, wk.L, True, wk.skip)
    if r == 0:
        return 0, 2
    wk.nreg[0] += r == 2
    _sigma(x, wk.L, fp[0], wk.XT)
    hcols(wk.XTf, uk, th, wk.YTf)
    m = 0
    for b in range(yk.shape[0]):
        if np.isfinite(yk[b]):
            wk.idx[m] = b
            m += 1
    npt = 2 * n + 1
    if m < yk.shape[0]:
        for b in range(m):
            for j in range(npt):
                wk.Ym[b, j] = wk.YT[wk.idx[b], j]
    if not _all_finite(wk.Ym if m < yk.shape[0] else wk.YT, m, npt):
        return m, 4
    return m, 0


@_jit_inline
def _update(hcols, x, P, th, uk, yk, Rd, R, opts, wk):
    """Measurement update at one sample in place: (NLL term, maha, m, failure
    code) (``opts``: (ip, fp) of :func:`_kernel_py`)."""
    ip, fp = opts
    n = x.shape[0]
    m, code = _measured_outputs(hcols, x, P, th, uk, yk, fp, wk)
    if code:
        return 0.0, 0.0, m, code
    S, w = wk.cov, fp[1]
    _moments(wk.Ym if m < yk.shape[0] else wk.YT, m, w, fp[2], wk.yf, S, wk.D)
    for a in range(m):
        if ip[4]:
            for b in range(m):
                S[a, b] += R[wk.idx[a], wk.idx[b]]
        else:
            S[a, a] += Rd[wk.idx[a]]
    _cross_cov(n, m, w, fp[0], wk)
    r = _chol(S, m, wk.Ls, False, wk.skip)
    if r == 0:
        return 0.0, 0.0, m, 5
    wk.nreg[0] += r == 2
    for b in range(m):
        wk.eps[b] = yk[wk.idx[b]] - wk.yf[b]
    term, maha = _correct(x, P, m, wk)
    return term, maha, m, 0


@_jit_inline
def _cross_cov(n, m, w, c, wk):
    """Pxyᵀ into wk.Pyx (m, n): Pxy[a, b] = w Σ_i c L[a, i] (D_b,i − D_b,n+i)
    (difference form, the central point cancels; L lower triangular, so
    i <= a). Overwrites the first n columns of D with the differences."""
    D, L = wk.D, wk.L
    for b in range(m):
        for i in range(n):
            D[b, i] = D[b, i] - D[b, n + i]
    for b in range(m):
        for a in range(n):
            s = 0.0
            for i in range(a + 1):
                s += L[a, i] * D[b, i]
            wk.Pyx[b, a] = (w * c) * s


@_jit
def _forward(Ls, m, b, out):
    """Solve Ls out = b (lower triangular, m x m)."""
    for i in range(m):
        s = b[i]
        for j in range(i):
            s -= Ls[i, j] * out[j]
        out[i] = s / Ls[i, i]


@_jit_inline
def _correct(x, P, m, wk):
    """Kalman correction from the Cholesky factor of S: Gᵀ = Ls⁻¹ Pxyᵀ,
    z = Ls⁻¹ ε, x += G z, P −= G Gᵀ (symmetrised); (NLL term, ε S⁻¹ ε).
    In small helpers on the arrays they use (one inlined body ran 2.5x
    slower: bench/kernel_phases.py)."""
    _gain_t(wk.Pyx, wk.Ls, m, wk.Gt)
    _forward(wk.Ls, m, wk.eps, wk.z)
    term, maha = _nll_term(wk.Ls, wk.z, m)
    _low_rank(wk.Gt, wk.z, m, wk.xt, wk.A)
    _apply_correction(x, P, wk.xt, wk.A)
    return term, maha


@_jit
def _gain_t(Pyx, Ls, m, Gt):
    """Gᵀ = Ls⁻¹ Pxyᵀ: one forward substitution over all n columns (rows
    contiguous)."""
    n = Gt.shape[1]
    for b in range(m):
        for a in range(n):
            Gt[b, a] = Pyx[b, a]
        for j in range(b):
            q = Ls[b, j]
            for a in range(n):
                Gt[b, a] -= q * Gt[j, a]
        d = Ls[b, b]
        for a in range(n):
            Gt[b, a] = Gt[b, a] / d


@_jit
def _low_rank(Gt, z, m, xt, T):
    """xt = G z and the lower triangle of T = G Gᵀ, summed over the outputs."""
    n = Gt.shape[1]
    for a in range(n):
        xt[a] = 0.0
        for c in range(a + 1):
            T[a, c] = 0.0
    for b in range(m):
        zb = z[b]
        for a in range(n):
            g = Gt[b, a]
            xt[a] += g * zb
            for c in range(a + 1):
                T[a, c] += g * Gt[b, c]


@_jit
def _apply_correction(x, P, xt, T):
    """x += xt, P −= T (lower triangle of T; P symmetrised)."""
    n = x.shape[0]
    for a in range(n):
        x[a] = x[a] + xt[a]
        for c in range(a + 1):
            v = 0.5 * ((P[a, c] - T[a, c]) + (P[c, a] - T[a, c]))
            P[a, c] = v
            P[c, a] = v


@_jit
def _nll_term(Ls, z, m):
    """0.5 (log det S + zᵀz + m log 2π) and zᵀz from S = Ls Lsᵀ."""
    logdet, maha = 0.0, 0.0
    for b in range(m):
        logdet += np.log(Ls[b, b])
        maha += z[b] * z[b]
    return 0.5 * (2.0 * logdet + maha + m * LOG_2PI), maha


# ------------------------------------------------------------ storage
@_jit_inline
def _store_update(st, k, p, m, term, maha, wk):
    """Innovations, predicted outputs, S (measured block), NLL term and NIS at k."""
    for a in range(m):
        ia = wk.idx[a]
        st[0][k, p, ia] = wk.eps[a]
        st[2][k, p, ia] = wk.yf[a]
        for b in range(m):
            st[1][k, p, ia, wk.idx[b]] = wk.cov[a, b]
    st[6][k, p] = term
    st[7][k, p] = maha


@_jit_inline
def _store_filtered(h, st, k, p, x, P, uk, th, full, wk):
    """Filtered state, its outputs h(x̂, u_k) and (full) covariance at k."""
    n = x.shape[0]
    for a in range(n):
        st[4][k, p, a] = x[a]
    h(x, uk, th, wk.yv)
    for b in range(wk.yv.shape[0]):
        st[3][k, p, b] = wk.yv[b]
    if full:
        for a in range(n):
            for b in range(n):
                st[5][k, p, a, b] = P[a, b]


# ------------------------------------------------------------ one set, all sets
@_jit
def _filter_one(a, fns, rec, sets, opts, out, st, buf, ibuf):
    """The whole record (:data:`Record`) for parameter set ``a`` of ``sets``
    (:data:`Sets`): NLL into out.nll[a]; failing sample (-1: none), failure
    code and loaded factorisations into out.info[a] (:data:`Outputs`), the
    storage into ``st`` (:func:`_store_arrays`). ``fns``: :func:`point_fns`;
    ``opts``: (ip, fp) (:func:`_kernel_py`); ``buf``, ``ibuf``: the set's
    rows of the work buffers."""
    t, u, y, ns = rec
    th, x0, P0, q2, Rd, R, Q, act = sets
    ip = opts[0]
    out_f, out_i = out
    _, h, _, _, hcols = fns
    n, ny, nu = x0.shape[1], y.shape[1], u.shape[1]
    wk, x, P, tha = _work(buf, ibuf, n, ny, nu, th.shape[1])
    for i in range(n):
        x[i] = x0[a, i]
        for j in range(n):
            P[i, j] = P0[a, i, j]
    for i in range(th.shape[1]):
        tha[i] = th[a, i]
    Qa, Ra, Rda = Q[a * ip[5]], R[a * ip[4]], Rd[a * (1 - ip[4])]
    p = act[a]
    nll = 0.0
    out_i[a, 0], out_i[a, 1] = -1, 0
    q2a, uk, yk = q2[a], wk.uk, wk.yk
    for k in range(t.shape[0]):
        # copies of the shared rows u[k], y[k]: views of arrays shared by the
        # threads would update one reference count from every thread
        for j in range(uk.shape[0]):
            uk[j] = u[k, j]
        for j in range(yk.shape[0]):
            yk[j] = y[k, j]
        code = 0
        if k > 0:
            code = _predict(fns, x, P, u, k - 1, tha, t[k] - t[k - 1], ns[k - 1], q2a, Qa,
                            opts, wk)
        if code == 0 and _any_finite(yk):
            term, maha, m, code = _update(hcols, x, P, tha, uk, yk, Rda, Ra, opts, wk)
            if code == 0:
                nll += term
                if ip[6]:
                    _store_update(st, k, p, m, term, maha, wk)
        if code:
            out_i[a, 0], out_i[a, 1] = k, code
            nll = np.inf
            break
        if ip[6]:
            _store_filtered(h, st, k, p, x, P, uk, tha, ip[6] == 2, wk)
    out_f[a] = nll
    out_i[a, 2] = wk.nreg[0]


@_jit
def _any_finite(v):
    for i in range(v.shape[0]):
        if np.isfinite(v[i]):
            return True
    return False


def _kernel_py(fns, rec, sets, opts, out, st, bufs):
    """Every parameter set of ``sets`` in turn: :func:`_filter_one` with its
    own rows of the work buffers ``bufs`` = (buf, ibuf). ``fns``:
    :func:`point_fns`; ``rec``: :data:`Record`; ``opts``: (ip, fp), the
    integer options (:data:`IOPT`) and the sigma weights (c, w, centre
    covariance weight); ``out``: :data:`Outputs`; ``st``: the storage
    arrays (:func:`_store_arrays`). :func:`run` calls it for one set at a
    time from a pool of threads (the kernel holds no GIL): compiled with
    ``parallel=True`` and ``prange`` over the sets, the kernel took 58 s to
    compile against 36 s without (numba's parfor passes), the largest part
    of a first run after install."""
    buf, ibuf = bufs
    for a in range(sets.th.shape[0]):
        _filter_one(np.int64(a), fns, rec, sets, opts, out, st, buf[a], ibuf[a])


def _signature():
    """The kernel's explicit signature (first-class function types for the
    model's point kernels: compiled once for every model)."""
    V, M, I = types.float64[::1], types.float64[:, ::1], types.int64[::1]
    A3, A4 = types.float64[:, :, ::1], types.float64[:, :, :, ::1]
    IM = types.int64[:, ::1]
    point = types.FunctionType(types.void(V, V, V, V))
    jac = types.FunctionType(types.void(V, V, V, V, M))
    # f_cols and h_cols take flat vectors, like the point kernels
    fns = types.Tuple((point, point, jac, point, point))
    store = types.Tuple((A3, A4, A3, A3, A3, A4, M, M))
    return types.void(fns, types.NamedTuple((V, M, M, I), Record),
                      types.NamedTuple((M, M, A3, M, M, A3, A3, I), Sets), types.Tuple((I, V)),
                      types.NamedTuple((V, IM), Outputs), store, types.Tuple((M, IM)))


_LOCK = threading.Lock()
_KERNEL: list = []
#: the child process compiling the kernel into numba's cache
#: (:func:`compile_in_background`), while it runs
_BACKGROUND: list = []
#: work to overlap with this process's wait for that child (:func:`while_compiling`)
_WAITERS: list = []


@contextlib.contextmanager
def _first_class_quiet():
    """Keep numba's "first-class function type feature is experimental"
    warning from the user: numba raises it whenever it types the kernel's
    tuple of point kernels (at compile, cache load and call); the feature
    is typed and tested here."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", numba.NumbaExperimentalFeatureWarning)
        yield


def _cached_marker() -> Path:
    """The file that says numba's cache holds this kernel: named by numba's
    and Python's versions, this module's text and numba's cache folder, in
    the kernel cache folder (:func:`bondgraph.numerics.compiled.cache_dir`)."""
    key = hashlib.sha256("\n".join([
        numba.__version__, sys.version, os.environ.get("NUMBA_CACHE_DIR", ""),
        hashlib.sha256(Path(__file__).read_bytes()).hexdigest()]).encode()).hexdigest()[:20]
    return cache_dir() / f"fused_ukf_kernel_{key}.cached"


def compile_in_background() -> bool:
    """Start compiling the kernel into numba's on-disk cache in a child
    process, unless it is there (:func:`_cached_marker`), loaded, the
    kernel cache folder cannot be written (the marker could not say it is
    there, and every run would compile twice), or background compiles are
    off (``BONDGRAPH_COMPILE_AHEAD=0``,
    :func:`bondgraph.numerics.compiled.ahead_workers`). A command calls it
    first thing: the kernel takes about 15 s to compile once per
    installation, and meanwhile this process imports, builds the problem
    and compiles the other kernels; :func:`kernel` waits for the child and
    loads its result (or compiles itself if the child failed). numba
    compiles one function at a time per process (its compiler lock), so a
    thread would not overlap. Returns whether a child was started."""
    if numba is None or _KERNEL or _BACKGROUND or not ahead_workers():
        return False
    try:
        marker = _cached_marker()
        if marker.exists():
            return False
        # a cache folder this process cannot write: each run would spawn a
        # child and then compile again itself (numba's cache likely fails too)
        marker.parent.mkdir(parents=True, exist_ok=True)
        if not os.access(marker.parent, os.W_OK):
            return False
        child = subprocess.Popen(
            [sys.executable, "-c", "from bondgraph.inference.ukf_numba import kernel; kernel()"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:
        return False
    _BACKGROUND.append(child)
    atexit.register(_stop_background, child)
    return True


def while_compiling(task) -> bool:
    """Run ``task(done)`` on a daemon thread while this process waits for
    the kernel's background compile (:func:`compile_in_background`), from
    the moment :func:`kernel` starts waiting; ``done`` is a
    :class:`threading.Event` set when the wait ends, after which the task
    should stop soon (the process needs its cores again). On a first run
    the process waits there for about 10-20 s with one core idle (the
    loop's first fit needs the kernel); the loop compiles its first step's
    candidate kernels in that time
    (:func:`bondgraph.diagnose.scoring.compile_first_step_ahead`).

    Parameters
    ----------
    task : callable
        ``task(done)``; its exceptions are its own (not raised here).

    Returns
    -------
    bool
        Whether the task was queued: False when no background compile is
        pending (the kernel is loaded, in numba's cache, or compiled in
        this process): then there is no wait to fill.
    """
    with _LOCK:
        if not _BACKGROUND or _KERNEL:
            return False
        _WAITERS.append(task)
        return True


def _start_waiters() -> threading.Event:
    """Start the tasks of :func:`while_compiling` (each once) on daemon
    threads; the event to set when the wait ends."""
    done = threading.Event()
    for task in _WAITERS:
        threading.Thread(target=_quiet_task, args=(task, done), daemon=True,
                         name="bondgraph-while-compiling").start()
    _WAITERS.clear()
    return done


def _quiet_task(task, done) -> None:
    """``task(done)`` at the lowest CPU priority (on Linux the thread's
    nice value, which the processes it starts inherit), so that it takes
    only the core the wait leaves idle and never slows the compile waited
    for; a failure only loses the time it would have saved."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
    try:
        task(done)
    except Exception:  # noqa: BLE001 - work ahead of need; the need itself reports
        pass


def _stop_background(child) -> None:
    """At exit: a background compile this process no longer waits for stops
    (numba writes its cache files whole, by rename)."""
    if child.poll() is None:
        child.terminate()


def kernel() -> tuple[object, float]:
    """The compiled kernel and the seconds this call spent compiling it (or
    loading it from numba's cache, or waiting for :func:`compile_in_background`;
    0 once loaded in this process).

    Raises
    ------
    ImportError
        numba is not installed.
    """
    if numba is None:
        raise ImportError("numba is not installed (pip install numba)")
    with _LOCK:
        if _KERNEL:
            return _KERNEL[0], 0.0
        t0 = time.perf_counter()
        if _BACKGROUND:
            child = _BACKGROUND.pop()
            if child.poll() is None:
                done = _start_waiters()
                with announced("compiling the fused UKF kernel (in the background since the "
                               "command started)", note="once per installation: numba caches it"):
                    child.wait()
                done.set()
            _WAITERS.clear()
        with _first_class_quiet(), announced("compiling the fused UKF kernel",
                                             note="once per installation: numba caches it"):
            k = numba.njit(_signature(), cache=True, nogil=True,
                           error_model="numpy", _nrt=False, fastmath=FASTMATH)(_kernel_py)
        _KERNEL.append(k)
        with contextlib.suppress(OSError):
            marker = _cached_marker()
            marker.parent.mkdir(parents=True, exist_ok=True)
            marker.touch()
        return k, time.perf_counter() - t0


def threads() -> int:
    """Threads :func:`run` spreads the parameter sets over: numba's thread
    count (``NUMBA_NUM_THREADS``, default the machine's cores;
    ``numba.set_num_threads`` lowers it)."""
    return max(1, int(numba.get_num_threads())) if numba is not None else 1


_POOLS: dict = {}
# a forked child has none of its parent's threads: it makes pools of its own
# (a pool copied from the parent would queue the sets to threads that do not
# run there, and wait for ever)
if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_POOLS.clear)
    # nor its parent's background compile, which it cannot wait for
    os.register_at_fork(after_in_child=_BACKGROUND.clear)


def _pool(n: int):
    """A pool of ``n`` threads, made once per size and kept."""
    with _LOCK:
        if n not in _POOLS:
            _POOLS[n] = ThreadPoolExecutor(max_workers=n, thread_name_prefix="bondgraph-ukf")
        return _POOLS[n]


def _entry(kern):
    """The compiled entry point of the kernel's one signature: calling it
    skips the dispatcher's typing of the arguments (the tuple of
    first-class functions costs about 1 ms to type on every call)."""
    return next(iter(kern.overloads.values())).entry_point


def _compiled_once(store: list, py, signature, fastmath=False):
    """``py`` compiled (allocation-free, cached on disk, with numba's
    ``fastmath``: False or a set of LLVM flags such as :data:`FASTMATH`)
    with the signature ``signature()`` builds, once per process (kept in
    ``store``; under the kernel's lock): the simulation kernels of
    :mod:`bondgraph.inference.sim_numba`.

    Raises
    ------
    ImportError
        numba is not installed.
    """
    if numba is None:
        raise ImportError("numba is not installed (pip install numba)")
    with _LOCK:
        if not store:
            with announced(f"compiling the simulation kernel {py.__name__}",
                           note="once per installation: numba caches it"):
                store.append(numba.njit(signature(), cache=True, nogil=True,
                                        error_model="numpy", _nrt=False, fastmath=fastmath)(py))
        return store[0]


def unsupported(opts) -> str | None:
    """Why the kernel cannot run with UKFOptions ``opts`` (None if it can)."""
    for name, codes in (("method", METHOD_CODES), ("jacobian", JACOBIAN_CODES),
                        ("hold", HOLD_CODES)):
        if name == "hold" and is_per_input(opts.hold):
            continue
        if getattr(opts, name) not in codes:
            return f"the numba kernel has no {name} {getattr(opts, name)!r}; numpy ran instead"
    return None


def kernel_inputs(u, hold: str) -> tuple[np.ndarray, int]:
    """The inputs as the kernels take them, and the hold's code.

    Parameters
    ----------
    u : array (N, n_u)
    hold : str
        One of :data:`HOLD_CODES`, or a per-input hold (``"zoh,linear"``,
        :func:`bondgraph.numerics.integrators.split_hold`).

    Returns
    -------
    u_kernel : ndarray (N, n_u), or (N, 3 n_u) for a per-input hold
        C-contiguous floats; a per-input hold's three blocks are the
        samples, each interval's start and its change
        (:func:`bondgraph.numerics.integrators.hold_inputs`).
    code : int

    Raises
    ------
    OptionError
        An unknown hold, or a per-input hold of the wrong length.
    """
    u = np.asarray(u, dtype=float)
    if not is_per_input(hold):
        return np.ascontiguousarray(u), HOLD_CODES[split_hold(hold)[0]]
    held = hold_inputs(u, hold)
    change = held.change if held.change is not None else np.zeros_like(u)
    return np.ascontiguousarray(np.hstack([u, held.start, change])), PER_INPUT_HOLD


def _empty_store() -> tuple:
    z3, z4, z2 = np.zeros((0, 0, 0)), np.zeros((0, 0, 0, 0)), np.zeros((0, 0))
    return (z3, z4, z3, z3, z3, z4, z2, z2)


def _store_arrays(kept) -> tuple:
    """The storage arrays of a FilterStorage (writable, C-contiguous)."""
    if kept is None:
        return _empty_store()
    P_filt = kept.P_filt if kept.P_filt is not None else np.zeros((0, 0, 0, 0))
    return (kept.innovations, kept.S, kept.y_pred, kept.y_filt, kept.x_filt, P_filt,
            kept.nll_terms, kept.nis)


def interval_counts(opts, samples: int) -> np.ndarray:
    """The kernel's ``ns`` (samples,) int64: the substeps of the interval
    from each sample to the next (:func:`bondgraph.inference.options.interval_substeps`
    of ``opts``; the last entry, no interval, ``opts.substeps``)."""
    ns = np.full(max(int(samples), 1), opts.substeps, dtype=np.int64)
    if opts.refine and samples > 1:
        ns[:-1] = interval_substeps(opts, samples - 1)
    return ns


def run(kernels, t, u, y, batch, opts, wts, kept) -> float:
    """Filter the active sets of ``batch`` (a
    :class:`bondgraph.inference.ukf.FilterBatch` after its start checks) with
    the compiled kernel, filling its NLL, failures and reasons, and ``kept``
    (a FilterStorage or None) as the numpy path does.

    Parameters
    ----------
    kernels : bondgraph.numerics.compiled.PointKernels
    t, u, y : arrays (N,), (N, n_u), (N, n_y)
    opts : UKFOptions
    wts : SigmaWeights

    Returns
    -------
    float
        Seconds spent compiling (or loading) the kernel in this call.
    """
    kern, compile_s = kernel()
    A = batch.size
    if A == 0:
        return compile_s
    c = np.ascontiguousarray
    n, ny = batch.x.shape[1], y.shape[1]
    u, hold_code = kernel_inputs(u, opts.hold)
    ip = np.array([METHOD_CODES[opts.method], opts.substeps, JACOBIAN_CODES[opts.jacobian],
                   hold_code, batch.R is not None, batch.Q is not None,
                   0 if kept is None else (2 if kept.P_filt is not None else 1)], dtype=np.int64)
    fp = np.array([wts.c, wts.w, wts.center_cov])
    R = c(batch.R, dtype=float) if batch.R is not None else np.zeros((1, ny, ny))
    Rd = c(batch.Rd, dtype=float) if batch.Rd is not None else np.zeros((1, ny))
    Q = c(batch.Q, dtype=float) if batch.Q is not None else np.zeros((1, n, n))
    out_f, out_i = np.empty(A), np.empty((A, 3), dtype=np.int64)
    per_set = [c(batch.th, dtype=float), c(batch.x, dtype=float), c(batch.P, dtype=float),
               c(batch.q2, dtype=float)]
    fns = point_fns(kernels)
    rec = Record(c(t, dtype=float), c(u, dtype=float), c(y, dtype=float),
                 interval_counts(opts, t.size))
    nf, ni = _work_size(n, ny, u.shape[1], batch.th.shape[1])
    act, st = c(batch.act, dtype=np.int64), _store_arrays(kept)
    T = min(threads(), A)
    buf, ibuf = np.zeros((T, nf)), np.zeros((T, ni), dtype=np.int64)
    call, todo = _entry(kern), iter(range(A))
    lock = threading.Lock()

    def worker(j: int) -> None:
        # sets are taken one at a time (a dynamic schedule): their costs
        # differ (failures stop early, loaded factorisations retry), and a
        # static split left a thread idle (full bench: 1.82 of 2 cores busy)
        b, ib = buf[j:j + 1], ibuf[j:j + 1]
        first = True
        while True:
            with lock:
                a = next(todo, None)
            if a is None:
                return
            if not first:           # each set starts from zeroed work rows
                b[:], ib[:] = 0.0, 0
            first, s = False, slice(a, a + 1)
            sets = Sets(*[v[s] for v in per_set], Rd if ip[4] else Rd[s],
                        R[s] if ip[4] else R, Q[s] if ip[5] else Q, act[s])
            call(fns, rec, sets, (ip, fp), Outputs(out_f[s], out_i[s]), st, (b, ib))

    with _first_class_quiet():
        if T == 1:
            worker(0)
        else:
            list(_pool(T).map(worker, range(T)))
    for a, p in enumerate(batch.act):
        k, code = int(out_i[a, 0]), int(out_i[a, 1])
        if k >= 0:
            batch.failed[p], batch.fail_step[p] = True, k
            batch.reasons[p] = f"sample {k} (t = {t[k]:.6g} s): {FAIL_REASONS[code]}"
            batch.nll[p] = np.inf
        else:
            batch.nll[p] = out_f[a]
    batch.n_reg += int(out_i[:, 2].sum())
    return compile_s


class StepKernel:
    """One sample of the fused kernel for one parameter set: predict from
    the previous sample and update with the new one, every array allocated
    once (a streaming filter's per-sample step, no per-sample allocation).

    The record handed to the kernel is two samples long, the first without
    measurements, so :func:`_filter_one` runs exactly one predict (over the
    interval, with the kernel's input hold) and one update; the first
    sample of a stream is a one-sample record (update only).

    Parameters
    ----------
    kernels : bondgraph.numerics.compiled.PointKernels
    batch : bondgraph.inference.ukf.FilterBatch
        One active set after its start checks: its θ, process-noise
        intensities and measurement noise are used.
    n_u : int
    opts : UKFOptions
        Supported by the kernel (:func:`unsupported` is None).
    wts : SigmaWeights

    Notes
    -----
    The filter is that of :func:`bondgraph.inference.ukf.ukf_nll` (Wan &
    van der Merwe 2000); this class only moves its state between calls.
    """

    def __init__(self, kernels, batch, n_u: int, opts, wts):
        self.kern, self.compile_s = kernel()
        n, ny = batch.x.shape[1], (batch.Rd.shape[1] if batch.Rd is not None
                                    else batch.R.shape[1])
        c = np.ascontiguousarray
        u0, hold_code = kernel_inputs(np.zeros((2, n_u)), opts.hold)
        holds = split_hold(opts.hold, n_u)
        #: a per-input hold's mean and linear columns (:meth:`step` fills the blocks)
        self._mean = np.array([h == "mean" for h in holds], dtype=bool)
        self._lin = np.array([h == "linear" for h in holds], dtype=bool)
        self.t, self.u, self.y = np.zeros(2), u0, np.full((2, ny), np.nan)
        ns = np.full(2, opts.substeps, dtype=np.int64)
        self.recs = (Record(self.t[1:], self.u[1:], self.y[1:], ns[1:]),
                     Record(self.t, self.u, self.y, ns))
        R = c(batch.R, dtype=float) if batch.R is not None else np.zeros((1, ny, ny))
        Rd = c(batch.Rd, dtype=float) if batch.Rd is not None else np.zeros((1, ny))
        Q = c(batch.Q, dtype=float) if batch.Q is not None else np.zeros((1, n, n))
        self.sets = Sets(c(batch.th, dtype=float), np.zeros((1, n)), np.zeros((1, n, n)),
                         c(batch.q2, dtype=float), Rd, R, Q, np.zeros(1, dtype=np.int64))
        self.opts = (np.array([METHOD_CODES[opts.method], opts.substeps,
                               JACOBIAN_CODES[opts.jacobian], hold_code,
                               batch.R is not None, batch.Q is not None, 2], dtype=np.int64),
                     np.array([wts.c, wts.w, wts.center_cov]))
        self.out = Outputs(np.zeros(1), np.zeros((1, 3), dtype=np.int64))
        self.st = (np.full((2, 1, ny), np.nan), np.full((2, 1, ny, ny), np.nan),
                   np.full((2, 1, ny), np.nan), np.full((2, 1, ny), np.nan),
                   np.full((2, 1, n), np.nan), np.full((2, 1, n, n), np.nan),
                   np.zeros((2, 1)), np.full((2, 1), np.nan))
        nf, ni = _work_size(n, ny, u0.shape[1], batch.th.shape[1])
        self.bufs = (np.zeros((1, nf)), np.zeros((1, ni), dtype=np.int64))
        self.fns = point_fns(kernels)
        self.call = _entry(self.kern)

    def step(self, x, P, t_prev, t_now, u_prev, u_now, y) -> tuple[float, str | None]:
        """Advance ``x (n,)``, ``P (n, n)`` in place to the sample
        ``(t_now, u_now, y (n_y,))``, predicting from ``t_prev`` with the
        inputs ``u_prev``, ``u_now`` held as the options say; ``t_prev``
        None: the first sample (update only).

        Returns
        -------
        (nll term [nats], failure reason or None)
        """
        first = t_prev is None
        m = np.size(u_now)
        if self.u.shape[1] != m:        # a per-input hold's blocks, as hold_inputs makes them
            up = np.asarray(u_now if first else u_prev, dtype=float)
            un = np.asarray(u_now, dtype=float)
            self.u[0, :m] = up
            self.u[0, m:2 * m] = np.where(self._mean, 0.5 * (up + un), up)
            self.u[0, 2 * m:] = np.where(self._lin, un - up, 0.0)
            self.u[1, m:2 * m] = un         # the last row: held, no change
            self.u[1, 2 * m:] = 0.0
        elif not first:
            self.u[0] = u_prev
        if not first:
            self.t[0] = t_prev
        self.t[1], self.u[1, :np.size(u_now)], self.y[1] = t_now, u_now, y
        self.sets.x0[0] = x
        self.sets.P0[0] = P
        with _first_class_quiet():
            self.call(self.fns, self.recs[0 if first else 1], self.sets, self.opts, self.out,
                      self.st, self.bufs)
        k, code = int(self.out.info[0, 0]), int(self.out.info[0, 1])
        if k >= 0:
            return np.inf, FAIL_REASONS[code]
        i = 0 if first else 1
        x[:] = self.st[4][i, 0]
        P[:] = self.st[5][i, 0]
        return float(self.out.nll[0]), None
