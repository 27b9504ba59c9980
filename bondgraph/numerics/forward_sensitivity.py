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

import math
import numbers
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from scipy.integrate import OdeSolver, solve_ivp

from bondgraph.errors import DataError, NumericalError, OptionError, SensitivityError
from bondgraph.numerics.integrators import hold_within
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import (
    InputSignals,
    Runaway,
    _vector,
    crawl_hint,
    guard_rhs,
    lsoda_segment,
)

#: solve_ivp methods that get the Jacobian of the augmented system
IMPLICIT_METHODS = ("BDF", "Radau", "LSODA")
#: solve_ivp methods by name (a subclass of scipy's OdeSolver is taken too)
SOLVER_METHODS = ("RK45", "RK23", "DOP853") + IMPLICIT_METHODS
#: sampled inputs between samples: linearly interpolated, or held
#: (:class:`bondgraph.numerics.simulate.InputSignals`)
SOLVER_HOLDS = ("linear", "zoh")


def check_solver_fields(obj) -> None:
    """Check ``method``, ``rtol``, ``atol`` and ``hold`` of ``obj`` (one rule
    for :class:`SolverOptions` and the options that carry its fields); the
    tolerances become floats.

    Raises
    ------
    OptionError
        A value out of its domain, named with ``obj``'s class.
    """
    cls = type(obj).__name__
    m = obj.method
    if not (m in SOLVER_METHODS or (isinstance(m, type) and issubclass(m, OdeSolver))):
        raise OptionError(f"{cls}.method = {m!r} is not one of "
                          f"{', '.join(repr(c) for c in SOLVER_METHODS)} (or an OdeSolver class)")
    for name in ("rtol", "atol"):
        v = getattr(obj, name)
        if (isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v)
                or v <= 0):
            raise OptionError(f"{cls}.{name} must be a finite number > 0, got {v!r}")
        object.__setattr__(obj, name, float(v))
    if not hold_within(obj.hold, SOLVER_HOLDS):
        raise OptionError(f"{cls}.hold = {obj.hold!r} is not one of "
                          f"{', '.join(repr(h) for h in SOLVER_HOLDS)} (or one of them per "
                          f"input, joined by commas)")


@dataclass(frozen=True)
class SolverOptions:
    """How :func:`output_sensitivities` integrates the state and sensitivity
    equations (scipy's ``solve_ivp``).

    Parameters
    ----------
    method : {"LSODA", "BDF", "Radau", "RK45", "RK23", "DOP853"}
        Implicit methods get the Jacobian of the augmented system
        (block-diagonal: ∂f/∂x on every block; the second-derivative
        coupling of S to x is left out, which only slows Newton's
        convergence, not the accuracy). A subclass of
        :class:`scipy.integrate.OdeSolver` is passed on as it is.
    rtol, atol : float
        Tolerances (> 0) for x and for the scaled sensitivities
        s_j ∂x/∂θ_j (same units as x).
    hold : {"linear", "zoh"}
        Sampled inputs between samples (``"zoh"``: integrated segment by
        segment, as the UKF's default sees them).
    max_step : float, optional
        Largest solver step [s] (> 0; default: unlimited).

    Raises
    ------
    OptionError
        A value out of its domain (the message names the option and value).

    Examples
    --------
    >>> SolverOptions(method="BDF", hold="zoh").rtol
    1e-08
    """

    method: str = "LSODA"
    rtol: float = 1e-8
    atol: float = 1e-10
    hold: str = "linear"
    max_step: float | None = None

    def __post_init__(self):
        check_solver_fields(self)
        v = self.max_step
        if v is not None:
            if (isinstance(v, bool) or not isinstance(v, numbers.Real) or not v > 0
                    or math.isnan(v)):
                raise OptionError(f"SolverOptions.max_step must be a number > 0 or None, "
                                  f"got {v!r}")
            object.__setattr__(self, "max_step", float(v))


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
    x0_states : list of str
        Initial states differentiated (``x0_states`` of :func:`output_sensitivities`).
    dxdx0 : ndarray (N, n_x, m) or None
        ∂x/∂x0_i of those states (the state-transition columns).
    dydx0 : ndarray (N, n_y, m) or None
        ∂y/∂x0_i.
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
    x0_states: list = field(default_factory=list)
    dxdx0: np.ndarray | None = None
    dydx0: np.ndarray | None = None

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
                         params: Sequence[str] | None = None, *,
                         solver: SolverOptions | None = None, x0_states: Sequence[str] = (),
                         x0_scale=None) -> Sensitivities:
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
        Parameters differentiated (default :func:`free_parameters`; an empty
        list with ``x0_states`` differentiates the initial states only).
    solver : SolverOptions, optional
        Method, tolerances, input hold and largest step of the integration
        (:class:`SolverOptions`; default: LSODA, rtol 1e-8, atol 1e-10,
        linear hold).
    x0_states : sequence of str
        Initial states also differentiated: columns ∂x/∂x0_i with
        ∂x/∂x0_i (t0) = e_i and d/dt ∂x/∂x0_i = ∂f/∂x · ∂x/∂x0_i (the
        state-transition matrix), integrated with the parameters' columns.
    x0_scale : array (n_x,), optional
        Scales of the initial states for the integration tolerance of their
        columns (default max(|x0_i|, 1e-6 max|x0|, 1e-12)).

    Returns
    -------
    Sensitivities

    Raises
    ------
    OptionError
        ``solver`` is not a :class:`SolverOptions`.
    ModelError
        Unknown parameter names, wrong shapes.
    SensitivityError
        No parameters, or one listed twice.
    DataError
        ``t`` not strictly increasing or shorter than 2 samples.
    NumericalError
        If the solver fails (time and message given).
    """
    opts = _solver_options(solver)
    model = Model.from_spec(model)
    x0_states = list(x0_states)
    params, t, th, x_init, cols = _prepare(model, t, theta, x0, params, x0_states, x0_scale)
    idx, sidx, sc = cols.idx, cols.sidx, cols.sc
    method, rtol, atol, hold = opts.method, opts.rtol, opts.atol, opts.hold
    sig = InputSignals(model, t, u, hold=hold)
    kw: dict[str, Any] = dict(method=method, rtol=rtol, atol=atol)
    if opts.max_step is not None:
        kw["max_step"] = opts.max_step
    t_wall = time.perf_counter()
    Z, segments, totals = _integrate(model, t, sig, th, cols, x_init, hold, kw)
    X, dx, dy = _outputs(model, Z, sig.samples, th, cols)
    n, k, m = model.n_x, len(idx), len(sidx)
    stats = dict(method=method, rtol=rtol, atol=atol, hold=hold, segments=segments,
                 augmented_states=n + n * (k + m), wall_time_s=time.perf_counter() - t_wall,
                 **totals)
    with np.errstate(all="ignore"):
        Y = np.asarray(model.h(X, sig.samples, th[None, :]), dtype=float)
    return Sensitivities(t=t, x=X, y=Y, dxdtheta=dx[:, :, :k], dydtheta=dy[:, :, :k],
                         params=list(params), theta=th, scale=sc, outputs=list(model.outputs),
                         stats=stats, x0_states=x0_states,
                         dxdx0=dx[:, :, k:] if m else None, dydx0=dy[:, :, k:] if m else None)


def _solver_options(solver) -> SolverOptions:
    """``solver`` checked to be :class:`SolverOptions` (None: the defaults).

    Raises
    ------
    OptionError
        For anything else (a dict: use ``SolverOptions(**d)``).
    """
    if solver is None:
        return SolverOptions()
    if not isinstance(solver, SolverOptions):
        raise OptionError(f"solver must be a SolverOptions, got {type(solver).__name__} "
                          f"{solver!r} (use SolverOptions(**d) for a dict)")
    return solver


def _outputs(model, Z, U, th, cols: "_Columns"):
    """States X (N, n_x) and unscaled state and output sensitivity columns
    (N, n_x, c), (N, n_y, c) from the integrated augmented system Z
    (dy = ∂h/∂x · dx + ∂h/∂θ for the parameter columns)."""
    N, n, k = Z.shape[0], model.n_x, len(cols.idx)
    X = Z[:, :n]
    St = Z[:, n:].reshape(N, n, cols.count)              # scaled columns
    th1 = th[None, :]
    with np.errstate(all="ignore"):
        Hx = model.dhdx(X, U, th1)                     # (N, n_y, n_x)
        Ht = model.dhdtheta(X, U, th1)[:, :, cols.idx]  # (N, n_y, k)
    allsc = np.concatenate([cols.sc, cols.xs])
    dY_scaled = Hx @ St
    dY_scaled[:, :, :k] += Ht * cols.sc
    return X, St / allsc, dY_scaled / allsc


def _prepare(model, t, theta, x0, params, x0_states, x0_scale):
    """Checked parameters, times, θ, x0 and the sensitivity columns of
    :func:`output_sensitivities` (DataError, ModelError as documented there)."""
    params = list(params) if (params is not None and not params and x0_states) else \
        check_params(model, params)
    th = _vector(model, theta, "theta")
    x_init = _vector(model, x0, "x0")
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or t.size < 2 or np.any(np.diff(t) <= 0):
        raise DataError("t must be a strictly increasing 1-D array of at least 2 samples")
    sc = parameter_scale(model, params, th) if params else np.zeros(0)
    sidx = [model.state_index(s) for s in x0_states]
    xs = _x0_column_scale(x_init, x0_scale)[sidx]
    return params, t, th, x_init, _Columns(model.param_indices(params), sc, sidx, xs)


def _x0_column_scale(x_init: np.ndarray, x0_scale) -> np.ndarray:
    """Scale of each initial state's sensitivity column (n_x,)."""
    if x0_scale is not None:
        s = np.abs(np.asarray(x0_scale, dtype=float))
    else:
        s = np.maximum(np.abs(x_init), 1e-6 * np.max(np.abs(x_init), initial=0.0))
    return np.where(s > 0, s, 1e-12)


@dataclass
class _Columns:
    """The sensitivity columns of the augmented system: parameter indices and
    scales, initial-state indices and scales."""

    idx: np.ndarray
    sc: np.ndarray
    sidx: list
    xs: np.ndarray

    @property
    def count(self) -> int:
        return len(self.idx) + len(self.sidx)


def _augmented_system(model, th, cols: _Columns, u_at):
    """Right-hand side and Jacobian of [x; S̃] for solve_ivp, inputs ``u_at(t)``
    (S̃: the parameter columns, then the initial-state columns)."""
    n, k, c = model.n_x, len(cols.idx), cols.count
    th1 = th[None, :]
    eye_c = np.eye(c)

    def rhs(tq, z):
        x = z[:n][None, :]
        uq = u_at(tq)[None, :]
        fx = model.f(x, uq, th1)[0]
        A = model.dfdx(x, uq, th1)[0]
        S = z[n:].reshape(n, c)
        dS = A @ S
        if k:
            dS[:, :k] += model.dfdtheta(x, uq, th1)[0][:, cols.idx] * cols.sc
        return np.concatenate([fx, dS.ravel()])

    def jac(tq, z):
        A = model.dfdx(z[:n][None, :], u_at(tq)[None, :], th1)[0]
        J = np.zeros((n + n * c, n + n * c))
        J[:n, :n] = A
        J[n:, n:] = np.kron(A, eye_c)
        return J
    return rhs, jac


def _integrate(model, t, sig, th, cols: _Columns, x_init, hold, kw):
    """Integrate the augmented system over the record, segment by segment
    for a zero-order hold (restarting at every input change).

    Returns
    -------
    (Z (N, n + n c), number of segments, solver counters)

    Raises
    ------
    NumericalError
        A segment that fails or turns non-finite.
    """
    N, n, c = t.size, model.n_x, cols.count
    if sig.zoh_columns():
        bounds = list(sig.change_points()) + [N - 1]
        segments = [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    else:
        segments = [(0, N - 1)]
    Z = np.empty((N, n + n * c))
    S0 = np.zeros((n, c))
    for j, (i, s) in enumerate(zip(cols.sidx, cols.xs)):
        S0[i, len(cols.idx) + j] = s
    z = np.concatenate([x_init, S0.ravel()])
    Z[0] = z
    totals = {"nfev": 0, "njev": 0, "nlu": 0}
    dt = float(np.median(np.diff(t))) if N > 1 else None
    for a, b in segments:
        rhs, jac = _augmented_system(model, th, cols, sig.segment_input(a, hold))
        if kw["method"] in IMPLICIT_METHODS:
            kw["jac"] = jac
        try:
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                if kw["method"] == "LSODA":
                    sol = lsoda_segment(guard_rhs(rhs, dt), jac, t[a:b + 1], z, kw["rtol"],
                                        kw["atol"], kw.get("max_step"))
                else:
                    sol = solve_ivp(guard_rhs(rhs, dt), (t[a], t[b]), z, t_eval=t[a:b + 1],
                                    **kw)
        except Runaway as r:
            raise NumericalError(
                f"forward sensitivity integration ({kw['method']}) of model '{model.name}' "
                f"{r.why} near t = {r.t:.6g} s",
                hint=crawl_hint(model, jac, r.t, r.x, dt) if r.why.startswith("crawled") else
                "the parameters make the model unstable on this input, or the solver "
                "cannot follow it: check them; try method='LSODA' or 'Radau'") from None
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
