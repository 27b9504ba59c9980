"""Forward sensitivity equations: output sensitivities dy/dθ along a record.

With S = dx/dθ (e.g. Dickinson & Gelinas 1976)::

    dx/dt = f(x, u, θ),          x(t0) = x0
    dS/dt = ∂f/∂x · S + ∂f/∂θ,   S(t0) = 0
    dy/dθ = ∂h/∂x · S + ∂h/∂θ

integrated together by scipy's ``solve_ivp`` (LSODA by default) with the
generated Jacobians ``dfdx``, ``dfdtheta``, ``dhdx``, ``dhdtheta`` — no
finite differences. Columns are integrated scaled, S̃_j = s_j ∂x/∂θ_j
(``s_j`` = :func:`parameter_scale`), so every column has the units of x and
one absolute tolerance serves all of them.

They give the output-error Fisher information
(:meth:`Sensitivities.information`) used by the identifiability analysis
(:mod:`bondgraph.sensitivity`), and the Jacobian of an output-error fit.

References
----------
Dickinson, R. P., Gelinas, R. J. (1976). Sensitivity analysis of ordinary
differential equation systems — a direct method. J. Comput. Phys. 21(2),
123-143.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from scipy.integrate import solve_ivp

from bondgraph.errors import DataError, NumericalError, SensitivityError
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import InputSignals, _vector

#: solve_ivp methods that get the Jacobian of the augmented system
IMPLICIT_METHODS = ("BDF", "Radau", "LSODA")


def free_parameters(model) -> list[str]:
    """Parameters whose bounds are a proper interval (lower < upper).

    Returns
    -------
    list of str
    """
    return [p for i, p in enumerate(model.params) if model.upper[i] > model.lower[i]]


def check_params(model, params: Sequence[str] | None) -> list[str]:
    """Validated parameter names (default: :func:`free_parameters`).

    Raises
    ------
    SensitivityError
        Empty list or a name given twice.
    ModelError
        Unknown names (the message lists the model's parameters).
    """
    params = free_parameters(model) if params is None else list(params)
    if not params:
        raise SensitivityError(f"no parameters to analyse for model '{model.name}'")
    dup = sorted({p for p in params if params.count(p) > 1})
    if dup:
        raise SensitivityError(f"parameter(s) listed twice: {', '.join(dup)}")
    model.param_indices(params)
    return params


def parameter_scale(model, params: Sequence[str], theta) -> np.ndarray:
    """Scale s_j of each parameter for relative sensitivities and bounds.

    ``|θ_j|``, or the width of its box when θ_j is (nearly) zero (an offset
    such as a sensor bias has no natural relative scale).

    Returns
    -------
    ndarray (k,)
    """
    idx = model.param_indices(params)
    th = np.asarray(theta, dtype=float)[idx]
    width = model.upper[idx] - model.lower[idx]
    small = np.abs(th) <= 1e-9 * np.maximum(width, 1e-300)
    s = np.where(small, width, np.abs(th))
    return np.where(s > 0, s, 1.0)


@dataclass
class Sensitivities:
    """Output sensitivities along a record (:func:`output_sensitivities`).

    Attributes
    ----------
    t : ndarray (N,)
    x : ndarray (N, n_x)
        States of the nominal simulation.
    y : ndarray (N, n_y)
        Noise-free outputs.
    dxdtheta : ndarray (N, n_x, k)
        ∂x/∂θ_j [state unit / parameter unit].
    dydtheta : ndarray (N, n_y, k)
        ∂y/∂θ_j [output unit / parameter unit].
    params : list of str
    theta : ndarray (n_theta,)
        Parameter vector of the analysis.
    scale : ndarray (k,)
        Parameter scales s_j (:func:`parameter_scale`).
    outputs : list of str
    stats : dict
        Solver statistics (nfev, njev, nlu, wall time, ...).
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    dxdtheta: np.ndarray
    dydtheta: np.ndarray
    params: list
    theta: np.ndarray
    scale: np.ndarray
    outputs: list
    stats: dict = field(default_factory=dict)

    def scaled(self, sigma=None) -> np.ndarray:
        """Scaled (dimensionless) sensitivities s_j ∂y_i/∂θ_j / σ_i.

        Parameters
        ----------
        sigma : array (n_y,), optional
            Output scales, e.g. the measurement-noise standard deviations
            (default 1: relative sensitivities s_j ∂y/∂θ_j in output units).

        Returns
        -------
        ndarray (N, n_y, k)
        """
        sig = np.ones(len(self.outputs)) if sigma is None else np.asarray(sigma, float)
        return self.dydtheta * self.scale[None, None, :] / sig[None, :, None]

    def information(self, sigma, mask=None) -> np.ndarray:
        """Output-error Fisher information in relative coordinates,
        Σ_k Z_kᵀ Z_k with Z = :meth:`scaled` (σ = noise std).

        Parameters
        ----------
        sigma : array (n_y,)
            Measurement-noise standard deviations.
        mask : array of bool (N, n_y), optional
            Measured samples (default: all).

        Returns
        -------
        ndarray (k, k)
        """
        Z = self.scaled(sigma)
        if mask is not None:
            Z = np.where(np.asarray(mask, bool)[:, :, None], Z, 0.0)
        Zf = Z.reshape(-1, Z.shape[-1])
        return Zf.T @ Zf


def output_sensitivities(model, t, u=None, theta=None, x0=None,
                         params: Sequence[str] | None = None, *, method: str = "LSODA",
                         rtol: float = 1e-8, atol: float = 1e-10, hold: str = "linear",
                         max_step: float | None = None) -> Sensitivities:
    """Output sensitivities dy/dθ along a record by the forward sensitivity
    equations (not finite differences; Dickinson & Gelinas 1976).

    Parameters
    ----------
    model : Model or str
        (:meth:`~bondgraph.numerics.model.Model.from_spec`).
    t : array (N,)
        Sample times [s], strictly increasing.
    u : array (N, n_u), dict or callable, optional
        Inputs (any form accepted by :func:`bondgraph.numerics.simulate.simulate`).
    theta : array (n_theta,) or dict, optional
        Parameters (default: model defaults; a dict overrides named ones).
    x0 : array (n_x,) or dict, optional
        Initial state, taken as independent of θ (S(t0) = 0).
    params : sequence of str, optional
        Parameters differentiated (default :func:`free_parameters`).
    method : {"BDF", "Radau", "LSODA"} or an explicit solve_ivp method
        Implicit methods get the Jacobian of the augmented system
        (block-diagonal: ∂f/∂x on every block; the second-derivative
        coupling of S to x is left out, which only slows Newton's
        convergence, not the accuracy).
    rtol, atol : float
        Tolerances for x and for the scaled sensitivities s_j ∂x/∂θ_j
        (same units as x).
    hold : {"linear", "zoh"}
        Sampled inputs between samples (``"zoh"``: integrated segment by
        segment, as the UKF's default sees them).
    max_step : float, optional

    Returns
    -------
    Sensitivities

    Raises
    ------
    ModelError
        Unknown parameter names, wrong shapes.
    SensitivityError
        No parameters, or one listed twice.
    DataError
        ``t`` not strictly increasing or shorter than 2 samples.
    NumericalError
        If the solver fails (time and message given).
    """
    model = Model.from_spec(model)
    params = check_params(model, params)
    idx = model.param_indices(params)
    th = _vector(model, theta, "theta")
    x_init = _vector(model, x0, "x0")
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or t.size < 2 or np.any(np.diff(t) <= 0):
        raise DataError("t must be a strictly increasing 1-D array of at least 2 samples")
    sc = parameter_scale(model, params, th)
    sig = InputSignals(model, t, u, hold=hold)
    kw: dict[str, Any] = dict(method=method, rtol=rtol, atol=atol)
    if max_step is not None:
        kw["max_step"] = float(max_step)
    t_wall = time.perf_counter()
    Z, segments, totals = _integrate(model, t, sig, th, idx, sc, x_init, hold, kw)
    n, k, N = model.n_x, len(idx), t.size
    X = Z[:, :n]
    St = Z[:, n:].reshape(N, n, k)                      # scaled: s_j ∂x/∂θ_j
    U = sig.samples
    th1 = th[None, :]
    with np.errstate(all="ignore"):
        Y = np.asarray(model.h(X, U, th1), dtype=float)
        Hx = model.dhdx(X, U, th1)                     # (N, n_y, n_x)
        Ht = model.dhdtheta(X, U, th1)[:, :, idx]      # (N, n_y, k)
    dY_scaled = Hx @ St + Ht * sc
    stats = dict(method=method, rtol=rtol, atol=atol, hold=hold, segments=segments,
                 augmented_states=n + n * k, wall_time_s=time.perf_counter() - t_wall, **totals)
    return Sensitivities(t=t, x=X, y=Y, dxdtheta=St / sc, dydtheta=dY_scaled / sc,
                         params=list(params), theta=th, scale=sc, outputs=list(model.outputs),
                         stats=stats)


def _augmented_system(model, th, idx, sc, u_at):
    """Right-hand side and Jacobian of [x; S̃] for solve_ivp, inputs ``u_at(t)``."""
    n, k = model.n_x, len(idx)
    th1 = th[None, :]
    eye_k = np.eye(k)

    def rhs(tq, z):
        x = z[:n][None, :]
        uq = u_at(tq)[None, :]
        fx = model.f(x, uq, th1)[0]
        A = model.dfdx(x, uq, th1)[0]
        B = model.dfdtheta(x, uq, th1)[0][:, idx] * sc
        S = z[n:].reshape(n, k)
        return np.concatenate([fx, (A @ S + B).ravel()])

    def jac(tq, z):
        A = model.dfdx(z[:n][None, :], u_at(tq)[None, :], th1)[0]
        J = np.zeros((n + n * k, n + n * k))
        J[:n, :n] = A
        J[n:, n:] = np.kron(A, eye_k)
        return J
    return rhs, jac


def _integrate(model, t, sig, th, idx, sc, x_init, hold, kw):
    """Integrate the augmented system over the record, segment by segment
    for a zero-order hold (restarting at every input change).

    Returns
    -------
    (Z (N, n + n k), number of segments, solver counters)

    Raises
    ------
    NumericalError
        A segment that fails or turns non-finite.
    """
    N, n = t.size, model.n_x
    if hold == "zoh":
        bounds = list(sig.change_points()) + [N - 1]
        segments = [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    else:
        segments = [(0, N - 1)]
    Z = np.empty((N, n + n * len(idx)))
    z = np.concatenate([x_init, np.zeros(n * len(idx))])
    Z[0] = z
    totals = {"nfev": 0, "njev": 0, "nlu": 0}
    for a, b in segments:
        rhs, jac = _augmented_system(model, th, idx, sc, sig.segment_input(a, hold))
        if kw["method"] in IMPLICIT_METHODS:
            kw["jac"] = jac
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            sol = solve_ivp(rhs, (t[a], t[b]), z, t_eval=t[a:b + 1], **kw)
        for key in totals:
            totals[key] += int(getattr(sol, key, 0) or 0)
        if sol.status != 0 or sol.y.shape[1] != b - a + 1 or not np.isfinite(sol.y).all():
            t_fail = float(sol.t[-1]) if sol.t.size else float(t[a])
            raise NumericalError(
                f"forward sensitivity integration ({kw['method']}) of model '{model.name}' "
                f"failed near t = {t_fail:.6g} s: {sol.message}",
                hint="try method='LSODA' or 'Radau', looser tolerances, or fewer parameters")
        Z[a:b + 1] = sol.y.T
        z = Z[b]
    return Z, len(segments), totals
