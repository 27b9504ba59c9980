"""Compiled simulation kernels (numba): the noise-free trajectory and the
free run of a model from its compiled point kernels.

:func:`rk4_trajectory` integrates a record by classical RK4 sample by sample
(the arithmetic of :func:`bondgraph.numerics.integrators.rk4`);
:func:`free_run_rms` sums the squares of the states along a free run by RK4
or ROS2 (the compiled counterpart of
:func:`bondgraph.inference.prior.simulated_rms`). Like the fused UKF kernel
they are model independent: the model's point kernels
(:class:`bondgraph.numerics.compiled.PointKernels`) are passed as
first-class functions, so each kernel is compiled once per installation and
cached on disk. They take their steps from :mod:`bondgraph.inference.ukf_numba`
(:func:`~bondgraph.inference.ukf_numba._rk4_point`,
:func:`~bondgraph.inference.ukf_numba._ros2_point`, the input hold
:func:`~bondgraph.inference.ukf_numba._held_input`), the filter's own steps,
so that filter and simulation integrate alike. numba's on-disk cache of a
function is invalidated by changes of its own source file only: after an
edit of those steps, clear the cache of this module (``__pycache__``) too.
"""

from __future__ import annotations

import numpy as np

from bondgraph.inference.ukf_numba import (
    FASTMATH,
    METHOD_CODES,
    kernel_inputs,
    _all_finite,
    _compiled_once,
    _held_input,
    _rk4_point,
    _ros2_point,
)

try:  # numba is a regular dependency; the callers take numpy without it
    from numba import types
except ImportError:  # pragma: no cover - exercised only without numba
    types = None


def _trajectory_py(f, t, u, hold, th, x0, nsub, xr, wk, ub):
    """RK4 (``nsub`` steps per interval) from ``x0`` over the record into
    ``xr`` (N, n_x), the inputs held as ``hold`` says (work rows ``wk``
    (6, n_x), input buffer ``ub`` (n_u,))."""
    n = x0.shape[0]
    x, xt, k1, k2, k3, k4 = wk[0], wk[1], wk[2], wk[3], wk[4], wk[5]
    for a in range(n):
        x[a] = x0[a]
        xr[0, a] = x0[a]
    for k in range(t.shape[0] - 1):
        _held_input(u, k, 0.0, hold, ub)
        _rk4_point(f, x, u, k, hold, th, (t[k + 1] - t[k]) / nsub, nsub, (ub, xt, k1, k2, k3, k4))
        for a in range(n):
            xr[k + 1, a] = x[a]


_TRAJECTORY: list = []


def trajectory_kernel():
    """The compiled RK4 trajectory kernel (:func:`rk4_trajectory`; compiled
    once per installation, cached on disk, model independent like the
    filter kernel).

    Raises
    ------
    ImportError
        numba is not installed.
    """
    def sig():
        V, M = types.float64[::1], types.float64[:, ::1]
        point = types.FunctionType(types.void(V, V, V, V))
        return types.void(point, V, M, types.int64, V, V, types.int64, M, M, V)
    return _compiled_once(_TRAJECTORY, _trajectory_py, sig)


def rk4_trajectory(kernels, t, u, hold: str, theta, x0, substeps: int) -> np.ndarray:
    """States (N, n_x) of the noise-free trajectory from ``x0`` by classical
    RK4 with ``substeps`` steps per sample interval, the inputs ``u`` (N, n_u)
    held as ``hold`` says (:func:`~bondgraph.inference.ukf_numba.kernel_inputs`), with a
    model's compiled point kernels (:class:`bondgraph.numerics.compiled.PointKernels`): the
    arithmetic of :func:`bondgraph.numerics.integrators.rk4`, sample by
    sample, without a Python call per stage."""
    c = np.ascontiguousarray
    x0 = c(x0, dtype=float)
    n = x0.size
    xr = np.empty((np.asarray(t).size, n))
    uk, code = kernel_inputs(u, hold)
    trajectory_kernel()(kernels.f, c(t, dtype=float), uk, code,
                        c(theta, dtype=float), x0, int(substeps), xr, np.zeros((6, n)),
                        np.zeros(max(uk.shape[1], 1)))
    return xr


def _ros2_trajectory_py(f, fj, t, u, hold, th, x0, nsub, xr, work):
    """ROS2 (``nsub`` steps per interval, the Jacobian at the start of each
    interval, frozen over its sub-steps, as
    :func:`bondgraph.numerics.integrators.make_step`) from ``x0`` over the
    record into ``xr`` (N, n_x), the inputs held as ``hold`` says;
    ``work`` as :func:`_free_run_py`'s. A non-finite state stays in ``xr``
    (the caller marks the run from there)."""
    wk, ub, J, Winv, A, cols = work
    n = x0.shape[0]
    x, xt, k1, k2, F0, F1 = wk[0], wk[1], wk[2], wk[3], wk[6], wk[7]
    for a in range(n):
        x[a] = x0[a]
        xr[0, a] = x0[a]
    for k in range(t.shape[0] - 1):
        h = (t[k + 1] - t[k]) / nsub
        _held_input(u, k, 0.0, hold, ub)
        _ros2_point(f, fj, x, u, k, hold, th, h, nsub, 1, (ub, xt, F0, F1, k1, k2),
                    (J, Winv, A, cols))
        for a in range(n):
            xr[k + 1, a] = x[a]


_ROS2_TRAJECTORY: list = []


def _point_types():
    """numba types (vector, matrix, point kernel f, f with its Jacobian) of
    the simulation kernels' signatures."""
    V, M = types.float64[::1], types.float64[:, ::1]
    return (V, M, types.FunctionType(types.void(V, V, V, V)),
            types.FunctionType(types.void(V, V, V, V, M)))


def _work_signature():
    """numba types of the free-run kernels' work tuple (wk, ub, J, Winv, A, cols)."""
    V, M = types.float64[::1], types.float64[:, ::1]
    return types.Tuple((M, V, M, M, M, types.int64[::1]))


def _work(n: int, n_u: int) -> tuple:
    """The work tuple of :func:`_free_run_py` and :func:`_ros2_trajectory_py`
    for ``n`` states and ``n_u`` input columns."""
    return (np.zeros((8, n)), np.zeros(max(n_u, 1)), np.zeros((n, n)), np.zeros((n, n)),
            np.zeros((n, 2 * n)), np.zeros(2 * n, dtype=np.int64))


def ros2_trajectory_kernel():
    """The compiled ROS2 trajectory kernel (:func:`ros2_trajectory`; compiled
    once per installation, cached on disk, model independent).

    Raises
    ------
    ImportError
        numba is not installed.
    """
    def sig():
        V, M, point, jac = _point_types()
        return types.void(point, jac, V, M, types.int64, V, V, types.int64, M,
                          _work_signature())
    return _compiled_once(_ROS2_TRAJECTORY, _ros2_trajectory_py, sig, fastmath=FASTMATH)


def ros2_trajectory(kernels, t, u, hold: str, theta, x0, substeps: int) -> np.ndarray:
    """States (N, n_x) of the noise-free trajectory from ``x0`` by ROS2 with
    ``substeps`` steps per sample interval (the Jacobian at the start of each
    interval, frozen), the inputs ``u`` (N, n_u) held as ``hold`` says, with
    a model's compiled point kernels: the compiled counterpart of
    :func:`bondgraph.numerics.integrators.simulate_batch` with
    ``method="ros2"`` (the linear algebra of W is the filter kernel's, so
    states agree to rounding, not to the bit). Verwer et al. (1999)."""
    c = np.ascontiguousarray
    x0 = c(x0, dtype=float)
    n = x0.size
    xr = np.empty((np.asarray(t).size, n))
    uk, code = kernel_inputs(u, hold)
    ros2_trajectory_kernel()(kernels.f, kernels.f_dfdx, c(t, dtype=float), uk, code,
                             c(theta, dtype=float), x0, int(substeps), xr,
                             _work(n, uk.shape[1]))
    return xr


def trajectory(kernels, t, u, hold: str, theta, x0, method: str, substeps: int) -> np.ndarray:
    """States (N, n_x) of the noise-free trajectory by ``method``: "rk4"
    (:func:`rk4_trajectory`) or "ros2" (:func:`ros2_trajectory`)."""
    run = rk4_trajectory if method == "rk4" else ros2_trajectory
    return run(kernels, t, u, hold, theta, x0, substeps)


def _free_run_py(f, fj, t, u, hold, th, x0, method, nsub, acc, work):
    """Free run from ``x0`` over the record (``method`` 0: RK4, 1: ROS2 with
    the Jacobian at the start of each interval, frozen over its ``nsub``
    sub-steps, as :func:`bondgraph.numerics.integrators.make_step`), the
    inputs held as ``hold`` says: the sum of x² over the samples into
    ``acc`` (n_x,) up to the first non-finite state; returns the number of
    samples summed. ``work``: the tuple (wk, ub, J, Winv, A, cols) of work
    rows ``wk`` (8, n_x), input buffer ``ub``, J, Winv (n_x, n_x), A
    (n_x, 2 n_x), cols (2 n_x,))."""
    wk, ub, J, Winv, A, cols = work
    n = x0.shape[0]
    x, xt, k1, k2, k3, k4, F0, F1 = wk[0], wk[1], wk[2], wk[3], wk[4], wk[5], wk[6], wk[7]
    for a in range(n):
        x[a] = x0[a]
    count = 0
    for k in range(t.shape[0]):
        if not _all_finite(wk, 1, n):
            break
        for a in range(n):
            acc[a] += x[a] * x[a]
        count += 1
        if k < t.shape[0] - 1:
            h = (t[k + 1] - t[k]) / nsub
            _held_input(u, k, 0.0, hold, ub)
            if method == 0:
                _rk4_point(f, x, u, k, hold, th, h, nsub, (ub, xt, k1, k2, k3, k4))
            else:
                _ros2_point(f, fj, x, u, k, hold, th, h, nsub, 1, (ub, xt, F0, F1, k1, k2),
                            (J, Winv, A, cols))
    return count


_FREE_RUN: list = []


def free_run_kernel():
    """The compiled free-run kernel (:func:`free_run_rms`; compiled once per
    installation, cached on disk, model independent).

    Raises
    ------
    ImportError
        numba is not installed.
    """
    def sig():
        V, M, point, jac = _point_types()
        return types.int64(point, jac, V, M, types.int64, V, V, types.int64, types.int64, V,
                           _work_signature())
    return _compiled_once(_FREE_RUN, _free_run_py, sig, fastmath=FASTMATH)


def free_run_rms(kernels, t, u, hold: str, theta, x0, method: str,
                 substeps: int) -> np.ndarray | None:
    """RMS of every state along the free run from ``x0`` (:func:`_free_run_py`)
    with a model's compiled point kernels: the compiled counterpart of
    :func:`bondgraph.inference.prior.simulated_rms` (the same steps; the
    linear algebra of ROS2 is the kernel's, so values agree to rounding).

    Parameters
    ----------
    kernels : bondgraph.numerics.compiled.PointKernels
    t, u : arrays (N,), (N, n_u)
    hold : str
        A key of :data:`~bondgraph.inference.ukf_numba.HOLD_CODES`, or a per-input hold
        (:func:`~bondgraph.inference.ukf_numba.kernel_inputs`).
    theta, x0 : arrays (n_theta,), (n_x,)
    method : {"rk4", "ros2"}
    substeps : int

    Returns
    -------
    ndarray (n_x,) or None
        None when the run stops before its last sample (it diverged; see
        :func:`bondgraph.inference.prior.simulated_rms`).
    """
    c = np.ascontiguousarray
    x0 = c(x0, dtype=float)
    n = x0.size
    u = c(u, dtype=float).reshape(np.size(t), -1) if np.size(u) else np.zeros((np.size(t), 0))
    acc = np.zeros(n)
    u, code = kernel_inputs(u, hold)
    count = free_run_kernel()(kernels.f, kernels.f_dfdx, c(t, dtype=float), u, code,
                              c(theta, dtype=float), x0, METHOD_CODES[method], int(substeps),
                              acc, _work(n, u.shape[1]))
    if count < np.size(t):
        return None
    return np.sqrt(acc / count) if count else np.zeros(n)
