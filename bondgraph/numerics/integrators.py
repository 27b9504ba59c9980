"""Batched fixed-step integrators over a sample interval (inputs held
constant or, with a first-order hold, varying linearly over the interval).

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
  or re-evaluated every sub-step (``jacobian="each"``), or evaluated at one
  point of a group and shared by the group (``jacobian="shared"``: the
  UKF's sigma points of one parameter set share the Jacobian at their
  mean). Stiff modes are damped, never amplified, whatever the step.

The UKF (:mod:`bondgraph.inference.ukf`), the fixed-step simulation
(:mod:`bondgraph.numerics.simulate`) and the batched simulation of the
Sobol' analysis all step with :func:`make_step`; :func:`hold_inputs` gives
the input over each interval (zero-order hold, the interval mean, or the
first-order (linear) hold).

References
----------
Verwer, J. G., Spee, E. J., Blom, J. G., Hundsdorfer, W. (1999). A
second-order Rosenbrock method applied to photochemical dispersion problems.
SIAM J. Sci. Comput. 20(4), 1456-1480.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from bondgraph.errors import OptionError

GAMMA = 1.0 + 1.0 / np.sqrt(2.0)


def _stage_input(u: np.ndarray, du: np.ndarray | None, s: float) -> np.ndarray:
    """The input at fraction ``s`` of the interval: ``u + s·du`` (``u`` when
    the input is held constant, ``du`` None)."""
    return u if du is None or s == 0.0 else u + s * du


def rk4(f: Callable, x: np.ndarray, u: np.ndarray, theta: np.ndarray, dt: float,
        substeps: int = 1, du: np.ndarray | None = None) -> np.ndarray:
    """Advance ``x`` by ``dt`` with ``substeps`` classical RK4 steps.

    Parameters
    ----------
    f : callable
        ``f(x, u, theta) -> dx/dt`` batched (a generated model's ``f``).
    x : array (..., n_x)
    u : array (..., n_u)
        Input at the start of the interval (held constant when ``du`` is None).
    theta : array (..., n_theta)
    dt : float
        Interval [s].
    substeps : int
    du : array (..., n_u), optional
        Change of the input over the interval (first-order hold: the input
        at fraction s of the interval is ``u + s·du``; each stage sees it at
        its own time, so the hold is integrated to the method's order).

    Returns
    -------
    array (..., n_x)
    """
    h = dt / substeps
    for j in range(substeps):
        s0, s1 = j / substeps, (j + 1) / substeps
        u0, um, u1 = (_stage_input(u, du, s0), _stage_input(u, du, 0.5 * (s0 + s1)),
                      _stage_input(u, du, s1))
        k1 = f(x, u0, theta)
        k2 = f(x + (0.5 * h) * k1, um, theta)
        k3 = f(x + (0.5 * h) * k2, um, theta)
        k4 = f(x + h * k3, u1, theta)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return x


def _w_inverse(J: np.ndarray, h: float) -> np.ndarray:
    n = J.shape[-1]
    W = np.eye(n) - (GAMMA * h) * J
    return np.linalg.inv(W)


def _first_point(a: np.ndarray, ndim: int) -> np.ndarray:
    """``a[..., 0, :]`` if ``a`` has the point axis of an ``ndim``-dimensional
    state array, else ``a`` (broadcast over the points)."""
    a = np.asarray(a)
    return a[..., 0, :] if a.ndim == ndim else a


#: where ROS2 evaluates df/dx (see :func:`ros2`)
JACOBIANS = ("once", "each", "shared")


def _ros2_solver(f_dfdx, fx, x, u, theta, h, jacobian):
    """``(F0 = f(x), solve)`` with ``solve(r) = W⁻¹ r`` for the Jacobian option."""
    if jacobian == "shared":
        # one Jacobian per group of points, at its first point, shared by the
        # group: a stack of rows times W⁻ᵀ
        _, J = f_dfdx(x[..., 0, :], _first_point(u, x.ndim), _first_point(theta, x.ndim))
        WinvT = np.swapaxes(_w_inverse(J, h), -1, -2)
        return fx(x, u, theta), lambda r: r @ WinvT
    F0, J = f_dfdx(x, u, theta)
    Winv = _w_inverse(J, h)
    return F0, lambda r: (Winv @ r[..., None])[..., 0]


def ros2(f_dfdx: Callable, x: np.ndarray, u: np.ndarray, theta: np.ndarray, dt: float,
         substeps: int = 1, *, f: Callable | None = None, jacobian: str = "once",
         du: np.ndarray | None = None) -> np.ndarray:
    """Advance ``x`` by ``dt`` with ``substeps`` ROS2 steps.

    Parameters
    ----------
    f_dfdx : callable
        ``f_dfdx(x, u, theta) -> (f, df/dx)`` batched (generated).
    x, u, theta : arrays (..., n)
        ``u`` is the input at the start of the interval.
    dt : float
    substeps : int
    f : callable, optional
        ``f(x, u, theta)``; used for the second stage (cheaper than f_dfdx).
    jacobian : {"once", "each", "shared"}
        ``"once"``: df/dx at every point at the start of the interval, frozen
        over the sub-steps (W-method, default); ``"each"``: re-evaluated at
        every sub-step; ``"shared"``: ``x`` has shape (..., m, n), df/dx is
        evaluated once per group of m points at its first point (``u`` and
        ``theta`` with a point axis are taken at their first point too) and
        shared by the group, frozen — the UKF evaluates it at the central
        sigma point of each parameter set. ROS2 keeps order 2 for any W.
    du : array (..., n_u), optional
        Change of the input over the interval (first-order hold): the first
        stage sees the input at the start of a sub-step, the second at its
        end. That is ROS2 on the autonomous system (x, t) with the time
        column of the Jacobian left out, which a W-method allows: order 2
        is kept without a ∂f/∂t term.

    Returns
    -------
    array (..., n_x)

    Raises
    ------
    OptionError
        For an unknown ``jacobian``.
    """
    if jacobian not in JACOBIANS:
        raise OptionError(f"unknown ROS2 Jacobian option '{jacobian}' (use "
                          f"{', '.join(repr(j) for j in JACOBIANS)})")
    h = dt / substeps
    fx = f if f is not None else (lambda x_, u_, t_: f_dfdx(x_, u_, t_)[0])
    F0, solve = _ros2_solver(f_dfdx, fx, x, u, theta, h, jacobian)
    for s in range(substeps):
        ua, ub = _stage_input(u, du, s / substeps), _stage_input(u, du, (s + 1) / substeps)
        if s > 0:
            if jacobian == "each":
                F0, solve = _ros2_solver(f_dfdx, fx, x, ua, theta, h, jacobian)
            else:
                F0 = fx(x, ua, theta)
        k1 = solve(F0)
        F1 = fx(x + h * k1, ub, theta)
        k2 = solve(F1 - 2.0 * k1)
        x = x + (1.5 * h) * k1 + (0.5 * h) * k2
    return x


def make_step(model, method: str = "ros2", substeps: int = 1, *,
              jacobian: str = "once") -> Callable:
    """A transition ``step(x, u, theta, dt, du=None) -> x_next`` for a
    generated model (``u`` the input at the start of the interval, ``du`` its
    change over the interval for a first-order hold, see :func:`hold_inputs`).

    Parameters
    ----------
    model : Model
    method : {"rk4", "ros2"}
    substeps : int
        Steps per interval (>= 1).
    jacobian : {"once", "each", "shared"}
        ROS2 only (:func:`ros2`).

    Raises
    ------
    OptionError
        For an unknown method or Jacobian option, or substeps < 1.
    """
    if isinstance(substeps, bool) or int(substeps) != substeps or substeps < 1:
        raise OptionError(f"substeps must be an integer >= 1, got {substeps!r}")
    substeps = int(substeps)
    if method == "rk4":
        return lambda x, u, th, dt, du=None: rk4(model.f, x, u, th, dt, substeps, du)
    if method == "ros2":
        if jacobian not in JACOBIANS:
            raise OptionError(f"unknown ROS2 Jacobian option '{jacobian}' (use "
                              f"{', '.join(repr(j) for j in JACOBIANS)})")
        return lambda x, u, th, dt, du=None: ros2(model.f_dfdx, x, u, th, dt, substeps,
                                                  f=model.f, jacobian=jacobian, du=du)
    raise OptionError(f"unknown integration method '{method}' (use 'rk4' or 'ros2')")


#: input holds over a sample interval (see :func:`hold_inputs`)
HOLDS = ("zoh", "mean", "linear")
#: separator of a per-input hold: ``"zoh,linear"`` holds the first input
#: zero-order and the second linearly (:func:`split_hold`)
HOLD_SEPARATOR = ","


def split_hold(hold: str, n_u: int | None = None) -> tuple[str, ...]:
    """The hold of each input that ``hold`` names.

    A hold is one of :data:`HOLDS` for every input alike, or one of them per
    input, in the model's input order, joined by commas (``"zoh,linear"``:
    a digital command held between samples beside a sampled continuous
    signal).

    Parameters
    ----------
    hold : str
    n_u : int, optional
        The number of inputs; a per-input hold must name exactly that many.

    Returns
    -------
    tuple of str
        ``n_u`` holds (one entry for a uniform hold when ``n_u`` is None).

    Raises
    ------
    OptionError
        Not a string, an unknown hold (named), or a per-input hold of the
        wrong length.
    """
    if not isinstance(hold, str):
        raise OptionError(f"an input hold is a string, got {hold!r}")
    parts = tuple(h.strip() for h in hold.split(HOLD_SEPARATOR))
    bad = [h for h in parts if h not in HOLDS]
    if bad:
        raise OptionError(f"unknown input hold {bad[0]!r} in {hold!r} (use "
                          f"{', '.join(repr(h) for h in HOLDS)}, or one per input joined by "
                          f"commas, e.g. 'zoh,linear')")
    if len(parts) == 1:
        return parts if n_u is None else parts * int(n_u)
    if n_u is not None and len(parts) != n_u:
        raise OptionError(f"the per-input hold {hold!r} names {len(parts)} holds for {n_u} "
                          f"input(s); give one per input, in the model's input order")
    return parts


def join_hold(holds) -> str:
    """The hold string of per-input ``holds``: the one name when they agree
    (or there is no input), else :data:`HOLD_SEPARATOR`-joined
    (:func:`split_hold` inverts it)."""
    holds = tuple(holds)
    if len(set(holds)) <= 1:
        return holds[0] if holds else "zoh"
    return HOLD_SEPARATOR.join(holds)


def hold_within(hold, allowed) -> bool:
    """Whether ``hold`` is one of ``allowed``, or one of them per input
    (:func:`split_hold`; False for anything else, never an error)."""
    try:
        return set(split_hold(hold)) <= set(allowed)
    except OptionError:
        return False


def is_per_input(hold: str) -> bool:
    """Whether ``hold`` differs between inputs (:func:`split_hold`)."""
    return isinstance(hold, str) and HOLD_SEPARATOR in hold


@dataclass(frozen=True)
class HeldInputs:
    """The input over every sample interval [t_k, t_k+1], as
    :func:`hold_inputs` gives it: at fraction s ∈ [0, 1] of interval k the
    input is ``start[k] + s·change[k]`` (``start[k]`` when ``change`` is None).

    Attributes
    ----------
    start : ndarray (N, n_u)
        Input at the start of each interval.
    change : ndarray (N, n_u) or None
        Change over each interval (first-order hold; 0 on the last row), or
        None when the input is held constant.
    hold : str
        The hold that made it.
    """

    start: np.ndarray
    change: np.ndarray | None
    hold: str

    def interval(self, k: int) -> tuple[np.ndarray, np.ndarray | None]:
        """``(u, du)`` of interval k, the arguments of a :func:`make_step` transition."""
        return self.start[k], (None if self.change is None else self.change[k])


def hold_inputs(u: np.ndarray, hold: str = "zoh") -> HeldInputs:
    """The input held over each sample interval [t_k, t_k+1].

    This is the one definition of the input holds: the UKF, the fixed-step
    batched simulations and the discretisation check use it (a compiled
    filter kernel must mirror it).

    Parameters
    ----------
    u : array (N, n_u)
        Sampled inputs.
    hold : {"zoh", "mean", "linear"} or str
        ``"zoh"``: u_k (zero-order hold, the sampled-data convention);
        ``"mean"``: (u_k + u_k+1)/2 held constant, the interval mean of a
        linearly interpolated input; ``"linear"``: the first-order hold
        u_k + s·(u_k+1 − u_k), s ∈ [0, 1], seen by every integrator stage at
        its own time (for inputs sampled from a continuous signal, e.g. an
        anti-alias-filtered voltage: the zero-order hold lags such an input
        by half a sample, the mean hold removes the lag but flattens its
        slope within the interval). The last row is held at u_N-1. One hold
        per input, comma-joined in input order (``"zoh,linear"``,
        :func:`split_hold`), holds each column its own way.

    Returns
    -------
    HeldInputs

    Raises
    ------
    OptionError
        For an unknown hold, or a per-input hold whose length is not n_u.
    """
    u = np.asarray(u, dtype=float)
    if is_per_input(hold):
        if u.ndim != 2:
            raise OptionError(f"a per-input hold {hold!r} needs inputs of shape (N, n_u), got "
                              f"{u.shape}")
        holds = split_hold(hold, u.shape[1])
        start = np.array(u, dtype=float)
        change = np.zeros_like(start)
        for j, h in enumerate(holds):
            if h == "mean":
                start[:-1, j] = 0.5 * (u[:-1, j] + u[1:, j])
            elif h == "linear":
                change[:-1, j] = u[1:, j] - u[:-1, j]
        varying = "linear" in holds
        return HeldInputs(start, change if varying else None, hold)
    hold = split_hold(hold)[0]
    if hold == "zoh":
        return HeldInputs(u, None, hold)
    if hold == "mean":
        out = np.array(u, dtype=float)
        out[:-1] = 0.5 * (u[:-1] + u[1:])
        return HeldInputs(out, None, hold)
    change = np.zeros_like(u)
    change[:-1] = u[1:] - u[:-1]
    return HeldInputs(u, change, hold)


def rk4_growth(z) -> np.ndarray:
    """|R(z)|, RK4's amplification of a mode per step, R(z) = 1 + z + z²/2
    + z³/6 + z⁴/24 with z = h·λ (Hairer & Wanner 1996, IV.2); complex
    array in, array of the same shape out. The step is stable on the mode
    where it is <= 1."""
    z = np.asarray(z, dtype=complex)
    return np.abs(1 + z + z ** 2 / 2 + z ** 3 / 6 + z ** 4 / 24)


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
        return np.all(rk4_growth(h * lam) <= 1.0 + 1e-12)

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


def simulate_batch(model, t, u, thetas, x0, *, method: str = "ros2", substeps: int = 2,
                   hold: str = "zoh") -> np.ndarray:
    """Noise-free outputs of many parameter sets at once (fixed-step,
    batched over the sets; :func:`bondgraph.numerics.integrators.make_step`).

    Parameters
    ----------
    model : Model
    t : array (N,)
    u : array (N, n_u)
    thetas : array (P, n_theta)
    x0 : array (n_x,) or (P, n_x)
    method : {"ros2", "rk4"}
    substeps : int
    hold : {"zoh", "mean", "linear"}
        Input over an interval: u_k, (u_k + u_k+1)/2 or the first-order hold
        (:func:`bondgraph.numerics.integrators.hold_inputs`).

    Returns
    -------
    ndarray (N, P, n_y)
        NaN from the sample where a set's state turned non-finite.
    """
    th = np.atleast_2d(np.asarray(thetas, float))
    P = th.shape[0]
    x = np.broadcast_to(np.asarray(x0, float), (P, model.n_x)).copy()
    u = np.asarray(u, float).reshape(t.size, -1)
    u_held = hold_inputs(u, hold)
    step = make_step(model, method, substeps)
    Y = np.full((t.size, P, model.n_y), np.nan)
    with np.errstate(all="ignore"):
        Y[0] = model.h(x, u[0][None], th)
        for k_ in range(t.size - 1):
            uk, duk = u_held.interval(k_)
            x = step(x, uk[None], th, t[k_ + 1] - t[k_], None if duk is None else duk[None])
            bad = ~np.isfinite(x).all(axis=1)
            if bad.any():
                x[bad] = np.nan
            Y[k_ + 1] = model.h(x, u[k_ + 1][None], th)
    return Y
