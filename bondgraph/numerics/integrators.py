"""Batched fixed-step integrators over a sample interval (zero-order-hold inputs).

Both work on any leading batch shape, so a UKF propagates every sigma point of
every parameter set in one call.

* :func:`rk4` — classical Runge-Kutta, ``substeps`` steps per interval. Stable
  for h|λ| <= 2.785 on the negative real axis: stiff tire/clutch modes need
  many sub-steps.
* :func:`ros2` — the two-stage, second-order, L-stable Rosenbrock method ROS2
  of Verwer, Spee, Blom & Hundsdorfer (1999), γ = 1 + 1/√2::

      W = I - γ h J
      W k1 = f(x_n)
      W k2 = f(x_n + h k1) - 2 k1
      x_n+1 = x_n + 3/2 h k1 + 1/2 h k2

  It keeps order 2 for any matrix J (a W-method), so the generated Jacobian
  is evaluated once per interval and reused over the sub-steps ("frozen"),
  or re-evaluated every sub-step (``jacobian="each"``). Stiff modes are
  damped, never amplified, whatever the step.

References
----------
Verwer, J. G., Spee, E. J., Blom, J. G., Hundsdorfer, W. (1999). A
second-order Rosenbrock method applied to photochemical dispersion problems.
SIAM J. Sci. Comput. 20(4), 1456-1480.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

GAMMA = 1.0 + 1.0 / np.sqrt(2.0)


def rk4(f: Callable, x: np.ndarray, u: np.ndarray, theta: np.ndarray, dt: float,
        substeps: int = 1) -> np.ndarray:
    """Advance ``x`` by ``dt`` with ``substeps`` classical RK4 steps.

    Parameters
    ----------
    f : callable
        ``f(x, u, theta) -> dx/dt`` batched (a generated model's ``f``).
    x : array (..., n_x)
    u : array (..., n_u)
        Held constant over the interval.
    theta : array (..., n_theta)
    dt : float
        Interval [s].
    substeps : int

    Returns
    -------
    array (..., n_x)
    """
    h = dt / substeps
    for _ in range(substeps):
        k1 = f(x, u, theta)
        k2 = f(x + (0.5 * h) * k1, u, theta)
        k3 = f(x + (0.5 * h) * k2, u, theta)
        k4 = f(x + h * k3, u, theta)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return x


def _w_inverse(J: np.ndarray, h: float) -> np.ndarray:
    n = J.shape[-1]
    W = np.eye(n) - (GAMMA * h) * J
    return np.linalg.inv(W)


def ros2(f_dfdx: Callable, x: np.ndarray, u: np.ndarray, theta: np.ndarray, dt: float,
         substeps: int = 1, *, f: Callable | None = None, jacobian: str = "once") -> np.ndarray:
    """Advance ``x`` by ``dt`` with ``substeps`` ROS2 steps.

    Parameters
    ----------
    f_dfdx : callable
        ``f_dfdx(x, u, theta) -> (f, df/dx)`` batched (generated).
    x, u, theta : arrays (..., n)
    dt : float
    substeps : int
    f : callable, optional
        ``f(x, u, theta)``; used for the second stage (cheaper than f_dfdx).
    jacobian : {"once", "each"}
        Evaluate df/dx once per interval (frozen W-method, default) or at
        every sub-step.

    Returns
    -------
    array (..., n_x)
    """
    h = dt / substeps
    fx = f if f is not None else (lambda x_, u_, t_: f_dfdx(x_, u_, t_)[0])
    F0, J = f_dfdx(x, u, theta)
    Winv = _w_inverse(J, h)
    for s in range(substeps):
        if s > 0:
            if jacobian == "each":
                F0, J = f_dfdx(x, u, theta)
                Winv = _w_inverse(J, h)
            else:
                F0 = fx(x, u, theta)
        k1 = np.einsum("...ij,...j->...i", Winv, F0)
        F1 = fx(x + h * k1, u, theta)
        k2 = np.einsum("...ij,...j->...i", Winv, F1 - 2.0 * k1)
        x = x + (1.5 * h) * k1 + (0.5 * h) * k2
    return x


def make_step(model, method: str = "ros2", substeps: int = 1, **kw) -> Callable:
    """A transition ``step(x, u, theta, dt) -> x_next`` for a generated model.

    Parameters
    ----------
    model : Model
    method : {"rk4", "ros2"}
    substeps : int

    Raises
    ------
    ValueError
        For an unknown method.
    """
    if method == "rk4":
        return lambda x, u, th, dt: rk4(model.f, x, u, th, dt, substeps)
    if method == "ros2":
        return lambda x, u, th, dt: ros2(model.f_dfdx, x, u, th, dt, substeps, f=model.f, **kw)
    raise ValueError(f"unknown integration method '{method}' (use 'rk4' or 'ros2')")


def rk4_stable_step(eigenvalues: np.ndarray) -> float:
    """Largest RK4 step that keeps h·λ inside RK4's stability region, for
    the given Jacobian eigenvalues (bisection on |R(hλ)| <= 1).

    Parameters
    ----------
    eigenvalues : array of complex

    Returns
    -------
    float
        Step in seconds (inf if every eigenvalue is zero).
    """
    lam = np.asarray(eigenvalues, dtype=complex).ravel()
    # growing modes (Re > 0) are physics, not a step-size limit
    lam = lam[(np.abs(lam) > 0) & (lam.real <= 1e-12 * np.abs(lam))]
    if lam.size == 0:
        return float("inf")

    def ok(h):
        z = h * lam
        R = 1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24
        return np.all(np.abs(R) <= 1.0 + 1e-12)

    hi = 4.0 / np.abs(lam).max()
    lo = 0.0
    if ok(hi):
        return hi
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if ok(mid):
            lo = mid
        else:
            hi = mid
    return lo
