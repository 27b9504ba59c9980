"""Output-error (free-run simulation) fit: bounded nonlinear least squares on
the simulation error, with the forward sensitivities as the Jacobian.

The criterion is the weighted sum of squares of the free-run simulation
error, ½ Σ_k Σ_i ((ŷ_i(t_k; θ, x0) − y_i(t_k)) / σ_i)², over the measured
samples (NaN skipped), minimised by :func:`scipy.optimize.least_squares`
(trust-region reflective, within the parameter box). By default the
Jacobian ∂ŷ/∂θ and ∂ŷ/∂x0 comes from the forward sensitivity equations
(:func:`bondgraph.numerics.forward_sensitivity.output_sensitivities`;
Dickinson & Gelinas 1976), integrated by scipy's adaptive solvers, which
restart at every change of a zero-order-held input (one ``solve_ivp`` per
sample on a sampled record). With ``OutputErrorOptions(substeps=n)`` the
free runs are the model's compiled fixed-step RK4 (or, with
``fixed_method="ros2"``, the L-stable ROS2 for a stiff model) with ``n``
steps per sample interval (:func:`bondgraph.inference.sim_numba.trajectory`) and
the Jacobian comes from forward differences of such runs, one per column
(on the EMPS record of 4968 samples a few milliseconds per run instead of
seconds); a model without compiled kernels, or a run that is not finite,
takes the sensitivity path.

When to use it rather than the UKF likelihood (:mod:`bondgraph.inference.estimate`):
the output-error fit assumes a deterministic model (no process noise) and
white measurement noise; it is the classical simulation-error criterion of
system identification (Ljung 1999, §7.3) and what a free-run (validation)
error measures. It cannot absorb unmodelled dynamics into process noise, so a
wrong structure shows fully in its residuals; it needs a stable model and a
good start (it is a local method). The UKF likelihood handles process noise,
unmeasured disturbances and unstable or drifting states.

References
----------
Dickinson, R. P., Gelinas, R. J. (1976). Sensitivity analysis of ordinary
differential equation systems. J. Comput. Phys. 21, 123-143. Ljung, L.
(1999). System Identification: Theory for the User, 2nd ed. Prentice Hall.
Boender, C. G. E., Rinnooy Kan, A. H. G. (1987). Bayesian stopping rules for
multistart global optimization methods. Math. Programming 37, 59-80.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares

from bondgraph.errors import DataError, ModelError, NumericalError, OptionError
from bondgraph.inference import sim_numba
from bondgraph.inference.fisher import near_bound, typical_magnitude
from bondgraph.inference.optimize import pso
from bondgraph.inference.options import SwarmOptions
from bondgraph.inference.prior import fixed_step_outputs, free_run_kernels
from bondgraph.numerics.forward_sensitivity import (
    SolverOptions,
    check_solver_fields,
    output_sensitivities,
)
from bondgraph.numerics.integrators import simulate_batch
from bondgraph.numerics.model import Model


@dataclass(frozen=True)
class OutputErrorOptions:
    """How :func:`output_error_fit` simulates and how long it searches.

    Parameters
    ----------
    hold : {"zoh", "linear"}
        Sampled inputs between samples (``"zoh"``: held, as the UKF's
        default sees them).
    method : {"LSODA", "BDF", "Radau", "RK45", "RK23", "DOP853"}
        solve_ivp method of the free run and its forward sensitivities.
    rtol, atol : float
        Their tolerances (> 0).
    max_nfev : int
        Most simulations of the least-squares search (>= 1).
    substeps : int or None
        Fixed-step steps per sample interval of the compiled free runs, the
        Jacobian by forward differences (module docstring); None (the
        default): ``method`` with the forward sensitivities.
    fixed_method : {"rk4", "ros2"}
        The fixed-step method of those runs: RK4, or ROS2 (L-stable, for a
        stiff model; Verwer et al. 1999).

    Raises
    ------
    OptionError
        A value out of its domain (the message names the option and value).

    Examples
    --------
    >>> OutputErrorOptions(hold="linear").solver.hold
    'linear'
    """

    hold: str = "zoh"
    method: str = "LSODA"
    rtol: float = 1e-8
    atol: float = 1e-10
    max_nfev: int = 100
    substeps: int | None = None
    fixed_method: str = "rk4"

    def __post_init__(self):
        check_solver_fields(self)
        if self.fixed_method not in ("rk4", "ros2"):
            raise OptionError(f"OutputErrorOptions.fixed_method must be 'rk4' or 'ros2', got "
                              f"{self.fixed_method!r}")
        for name, allow_none in (("max_nfev", False), ("substeps", True)):
            v = getattr(self, name)
            if v is None and allow_none:
                continue
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 1:
                raise OptionError(f"OutputErrorOptions.{name} must be an integer >= 1"
                                  f"{' or None' if allow_none else ''}, got {v!r}")
            object.__setattr__(self, name, int(v))

    @property
    def solver(self) -> SolverOptions:
        """The :class:`~bondgraph.numerics.forward_sensitivity.SolverOptions`
        of the free runs (method, tolerances, hold)."""
        return SolverOptions(method=self.method, rtol=self.rtol, atol=self.atol, hold=self.hold)


@dataclass
class OutputErrorResult:
    """What :func:`output_error_fit` returns.

    Attributes
    ----------
    names : list of str
        Estimated quantities: parameters, then ``x0.<state>``.
    x : ndarray (k,)
        Their estimates.
    theta : ndarray (n_theta,)
        All parameters at the estimate.
    x0 : ndarray (n_x,)
        Initial state at the estimate.
    cost : float
        ½ Σ (weighted residual)² at the estimate.
    rmse : ndarray (n_y,)
        RMS free-run error of each output [output units].
    std : dict
        Name -> standard deviation from s² (JᵀJ)⁻¹, s² = 2 cost / (n − k)
        (None where singular, on a bound, or not seen by the outputs: a
        zero column of J, left out of the inverse).
    at_bound : list of str
        Estimates on a bound of their box.
    y_sim : ndarray (N, n_y)
        Free-run outputs at the estimate.
    nfev, njev : int
        Simulations and sensitivity runs.
    status : int
        :func:`scipy.optimize.least_squares` status (> 0: converged).
    message : str
    warnings : list of str
        What the caller found wrong with the fit's numerics (a step that
        fails its check at the estimate and was kept as given).
    """

    names: list
    x: np.ndarray
    theta: np.ndarray
    x0: np.ndarray
    cost: float
    rmse: np.ndarray
    std: dict
    at_bound: list
    y_sim: np.ndarray
    nfev: int
    njev: int
    status: int
    message: str
    extra: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)

    def estimates(self) -> dict:
        """Name -> estimate."""
        return dict(zip(self.names, self.x.tolist()))


class _Problem:
    """Residuals and Jacobian of the output-error criterion at z (k,), with
    the sensitivity run of the last z cached (least_squares calls fun then
    jac at the same point)."""

    def __init__(self, model, t, u, y, params, states, theta, x0, sigma, solver: SolverOptions):
        self.model, self.t, self.u, self.solver = model, t, u, solver
        self.params, self.states = list(params), list(states)
        self.pidx = model.param_indices(self.params)
        self.sidx = [model.state_index(s) for s in self.states]
        self.theta, self.x0 = theta.copy(), x0.copy()
        self.mask = np.isfinite(y)
        self.y, self.w = y, 1.0 / sigma
        self._z, self._s = None, None

    def point(self, z):
        th, x0 = self.theta.copy(), self.x0.copy()
        th[self.pidx] = z[:len(self.pidx)]
        x0[self.sidx] = z[len(self.pidx):]
        return th, x0

    def sens(self, z):
        if self._z is None or not np.array_equal(z, self._z):
            th, x0 = self.point(z)
            self._s = output_sensitivities(self.model, self.t, self.u, th, x0, self.params,
                                           x0_states=self.states, solver=self.solver)
            self._z = np.array(z, dtype=float)
        return self._s

    def residuals(self, z):
        s = self.sens(z)
        return ((s.y - self.y) * self.w)[self.mask]

    def jacobian(self, z):
        s = self.sens(z)
        cols = [s.dydtheta] + ([s.dydx0] if self.states else [])
        J = np.concatenate(cols, axis=2) * self.w[None, :, None]      # (N, n_y, k)
        return J[self.mask]


#: weighted residual of every sample at a trial point whose fixed-step free
#: run is not finite (after a finite start): the trust region rejects the
#: step and shrinks, as at any point of higher cost
UNSTABLE_RESIDUAL = 1e3


class _FixedStepProblem(_Problem):
    """:class:`_Problem` with compiled fixed-step free runs (``method`` RK4
    or ROS2, ``substeps`` per sample interval) and a forward-difference Jacobian:
    column j from one more run with z_j moved by √ε · max(|z_j|, 1e-3 ·
    its box width, or 1e-3 without a box), inwards at an upper bound; that
    width's share at most 1000 times the start's |z_j|
    (:func:`~bondgraph.inference.fisher.typical_magnitude`: an effect's
    nominal box [0, 1e15] moved a damping coefficient of 1e-5 to 1.5e4). A
    trial point whose run is not finite gets residuals
    :data:`UNSTABLE_RESIDUAL` (the search steps back); at the start it
    raises."""

    def __init__(self, model, t, u, y, params, states, theta, x0, sigma, solver: SolverOptions,
                 *, kernels, substeps: int, box, method: str = "rk4"):
        super().__init__(model, t, u, y, params, states, theta, x0, sigma, solver)
        self.kernels, self.substeps, self.method = kernels, int(substeps), method
        self.u_run = (np.asarray(u, float).reshape(self.t.size, -1) if model.n_u
                      else np.zeros((self.t.size, 1)))
        self._zy = None
        lo, hi = (np.asarray(b, float) for b in box)
        width = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
        z0 = np.concatenate([np.asarray(theta, float)[self.pidx], np.asarray(x0, float)[self.sidx]])
        self.lo, self.hi, self.typical = lo, hi, typical_magnitude(z0, width)

    def outputs(self, z) -> np.ndarray:
        """Free-run outputs (N, n_y) at z (the last one cached: least_squares
        asks for the Jacobian at the point it just evaluated); NumericalError
        if not finite."""
        if self._zy is not None and np.array_equal(z, self._zy[0]):
            return self._zy[1]
        th, x0 = self.point(z)
        X = sim_numba.trajectory(self.kernels, self.t, self.u_run, self.solver.hold, th, x0,
                                 self.method, self.substeps)
        with np.errstate(all="ignore"):
            Y = np.asarray(self.model.h(X, self.u_run[:, :self.model.n_u], th[None, :]), float)
        if not np.isfinite(Y).all():
            raise NumericalError(f"the fixed-step {self.method.upper()} free run ({self.substeps} "
                                 f"steps per sample) of model '{self.model.name}' is not finite")
        self._zy = (np.array(z, dtype=float), Y)
        return Y

    def residuals(self, z):
        try:
            return ((self.outputs(z) - self.y) * self.w)[self.mask]
        except NumericalError:
            if self._zy is None:        # the start itself: the caller's problem
                raise
            # a trial point whose run blows up: a rejected step, not the end
            return np.full(int(self.mask.sum()), UNSTABLE_RESIDUAL)

    def sens(self, z):
        if self._z is not None and np.array_equal(z, self._z):
            return self._s
        z = np.array(z, dtype=float)
        Y0 = self.outputs(z)
        J = np.empty(Y0.shape + (z.size,))
        for j in range(z.size):
            h = np.sqrt(np.finfo(float).eps) * max(abs(z[j]), self.typical[j])
            h = -h if z[j] + h > self.hi[j] else h
            J[:, :, j] = self._column(z, j, h, Y0)
        self._zy = (z, Y0)
        k = len(self.pidx)
        self._s = SimpleNamespace(y=Y0, dydtheta=J[:, :, :k], dydx0=J[:, :, k:])
        self._z = z
        return self._s

    def _column(self, z, j: int, h: float, Y0: np.ndarray) -> np.ndarray:
        """The forward difference of the outputs along z_j by ``h``, or by
        ``-h`` where the run at ``z_j + h`` is not finite and ``z_j - h`` is
        inside the box (a run at the edge of stability); NumericalError when
        neither is."""
        zj = z.copy()
        zj[j] += h
        try:
            return (self.outputs(zj) - Y0) / h
        except NumericalError:
            if not self.lo[j] <= z[j] - h <= self.hi[j]:
                raise
        zj[j] = z[j] - h
        return (self.outputs(zj) - Y0) / -h


def _problem_for(model, t, u, y, params, states, th, xi, sigma, opts, box) -> _Problem:
    """The fixed-step problem when ``opts.substeps`` is set, the model has
    compiled kernels for its hold and the run at the start is finite; else
    the forward-sensitivity one."""
    args = (model, t, u, y, params, states, th, xi, np.asarray(sigma, float), opts.solver)
    kernels = (free_run_kernels(model, "numba", opts.fixed_method, opts.hold)
               if opts.substeps is not None else None)
    if kernels is not None:
        prob = _FixedStepProblem(*args, kernels=kernels, substeps=opts.substeps, box=box,
                                 method=opts.fixed_method)
        try:
            prob.outputs(np.concatenate([th[prob.pidx], xi[prob.sidx]]))
            return prob
        except NumericalError:
            pass
    return _Problem(*args)


def _spread(y: np.ndarray) -> float:
    """The std of an output's measured samples, 1.0 where it has fewer than
    two or none spread (an output the record lacks: NaN throughout, whose
    ``nanstd`` is NaN and would scale its residuals to NaN)."""
    ok = y[np.isfinite(y)]
    s = float(np.std(ok)) if ok.size >= 2 else 0.0
    return s if s > 0 else 1.0


def output_error_fit(model, t, u, y, params: Sequence[str], *, theta=None, x0=None,
                     x0_states: Sequence[str] = (), bounds=None, sigma=None,
                     options: OutputErrorOptions | None = None) -> OutputErrorResult:
    """Least-squares fit of ``params`` (and the initial states ``x0_states``)
    to the free-run simulation error (module docstring).

    Parameters
    ----------
    model : Model or str
    t : array (N,)
        Sample times [s].
    u : array (N, n_u) or None
    y : array (N, n_y)
        Measured outputs (NaN: missing).
    params : sequence of str
        Estimated parameters (k_θ); may be empty with ``x0_states``.
    theta : array (n_theta,), optional
        Start and values of the others (default the model's).
    x0 : array (n_x,), optional
        Initial state; start of the estimated ones (default the model's).
    x0_states : sequence of str
        Initial states estimated with the parameters.
    bounds : (lower, upper) of arrays (k,), optional
        Box of the estimated quantities (default: the parameters' declared
        boxes, initial states unbounded).
    sigma : array (n_y,), optional
        Output weights σ_i (default: the std of each measured output).
    options : OutputErrorOptions, optional
        Input hold, solve_ivp method and tolerances of the free runs
        (:func:`~bondgraph.numerics.forward_sensitivity.output_sensitivities`)
        and the limit of simulations (:class:`OutputErrorOptions`; default:
        zero-order hold, LSODA, rtol 1e-8, atol 1e-10, 100 simulations).

    Returns
    -------
    OutputErrorResult

    Raises
    ------
    OptionError
        ``options`` is not an :class:`OutputErrorOptions`.
    ModelError
        Unknown names, nothing to estimate, a start outside its box.
    DataError
        ``y`` of the wrong shape, or no measured sample.
    NumericalError
        The simulation fails at the start.
    """
    opts = OutputErrorOptions() if options is None else options
    if not isinstance(opts, OutputErrorOptions):
        raise OptionError(f"options must be an OutputErrorOptions, got {type(opts).__name__} "
                          f"{opts!r} (use OutputErrorOptions(**d) for a dict)")
    model = Model.from_spec(model)
    t = np.asarray(t, float)
    y = np.asarray(y, float).reshape(t.size, -1)
    if y.shape[1] != model.n_y:
        raise DataError(f"y has {y.shape[1]} columns, model '{model.name}' has {model.n_y} "
                        f"outputs")
    if not np.isfinite(y).any():
        raise DataError("no measured sample in y")
    params, states = list(params), list(x0_states)
    if not params and not states:
        raise ModelError("output_error_fit: nothing to estimate (no params, no x0_states)")
    th = np.array(model.theta0 if theta is None else theta, dtype=float)
    xi = np.array(model.x0 if x0 is None else x0, dtype=float)
    if sigma is None:
        sigma = np.array([_spread(y[:, i]) for i in range(model.n_y)])
    lo, hi = _box(model, params, states, bounds)
    prob = _problem_for(model, t, u, y, params, states, th, xi, sigma, opts, (lo, hi))
    z0 = np.concatenate([th[prob.pidx], xi[prob.sidx]])
    bad = [n for n, v, a, b in zip(params + states, z0, lo, hi) if not a <= v <= b]
    if bad:
        raise ModelError(f"output_error_fit: start outside its box: {', '.join(bad)}")
    with np.errstate(over="ignore"):    # a far trial step's huge residuals: its cost is inf
        r = least_squares(prob.residuals, z0, jac=prob.jacobian, bounds=(lo, hi),
                          method="trf", x_scale="jac", max_nfev=opts.max_nfev)
    return _result(prob, r, lo, hi)


def output_error_nll(y: np.ndarray, rmse: np.ndarray) -> float:
    """The Gaussian negative log-likelihood of an output-error fit with each
    output's noise variance at its maximum-likelihood value, the mean square
    free-run error: Σⱼ nⱼ/2 (1 + log 2π rmseⱼ²), nⱼ the measured samples of
    output j; +inf when an output's error is not finite (the criterion with the
    noise variance concentrated out: Ljung 1999, §7.4).

    Parameters
    ----------
    y : array (N, n_y)
        The record's outputs, NaN where not measured.
    rmse : array (n_y,)
        The fit's RMS free-run error per output (output units,
        :attr:`OutputErrorResult.rmse`).

    Returns
    -------
    float
        In nat.
    """
    n = np.sum(np.isfinite(np.asarray(y, float)), axis=0)
    r = np.asarray(rmse, float)
    if not np.all(np.isfinite(r)):
        return float("inf")
    with np.errstate(divide="ignore"):
        return float(np.sum(0.5 * n * (1.0 + np.log(2 * np.pi * r ** 2))))


def seen_initial_states(model, t, u, theta, x0, names: Sequence[str], *, method: str = "rk4",
                        substeps: int = 1, hold: str = "zoh") -> list[str]:
    """The states of ``names`` whose initial value the outputs see: the
    noise-free fixed-step run (:func:`~bondgraph.inference.prior.fixed_step_outputs`)
    from ``x0`` (n_x,) with that state moved by 1e-4 · max(|x0|, 1) differs
    from the run from ``x0`` somewhere. An unmeasured integrator (a position
    beside a measured velocity) is not seen: its initial value cannot be
    estimated from the outputs, and a zero column would leave the fit's
    information singular.

    Parameters
    ----------
    model : Model
    t : array (N,)
    u : array (N, n_u)
    theta : array (n_theta,)
    x0 : array (n_x,)
    names : sequence of str
        States of ``model``.
    method, substeps, hold :
        The runs' fixed-step method, steps per sample and input hold.

    Returns
    -------
    list of str
        Those of ``names`` seen, in order (all of them when the base run is
        not finite: nothing is decided from it).
    """
    x0 = np.asarray(x0, float)
    base = fixed_step_outputs(model, t, u, theta, x0, method, substeps, hold)
    if not np.isfinite(base).any():
        return list(names)
    out = []
    for n in names:
        j = model.state_index(n)
        xj = x0.copy()
        xj[j] += 1e-4 * max(abs(xj[j]), 1.0)
        moved = fixed_step_outputs(model, t, u, theta, xj, method, substeps, hold)
        with np.errstate(invalid="ignore"):
            if np.any(moved != base) or not np.array_equal(np.isnan(moved), np.isnan(base)):
                out.append(n)
    return out


def _box(model, params, states, bounds):
    """Box (k,) of the estimated quantities."""
    if bounds is not None:
        return np.asarray(bounds[0], float), np.asarray(bounds[1], float)
    lo, hi = model.bounds(params) if params else (np.zeros(0), np.zeros(0))
    n = len(states)
    return (np.concatenate([lo, np.full(n, -np.inf)]),
            np.concatenate([hi, np.full(n, np.inf)]))


def _result(prob: _Problem, r, lo, hi) -> OutputErrorResult:
    """The :class:`OutputErrorResult` of a finished least_squares run."""
    names = prob.params + [f"x0.{s}" for s in prob.states]
    th, x0 = prob.point(r.x)
    s = prob.sens(r.x)
    err = s.y - prob.y
    seen = np.isfinite(err).sum(axis=0)
    rmse = np.full(err.shape[1], np.nan)      # an output without a sample: NaN, no warning
    rmse[seen > 0] = np.sqrt(np.nanmean(err[:, seen > 0] ** 2, axis=0))
    near_lo, near_hi = near_bound(r.x, lo, hi, rel=1e-8)
    at = [n for n, a, b in zip(names, near_lo, near_hi) if a or b]
    n_res, k = int(prob.mask.sum()), r.x.size
    s2 = 2 * r.cost / max(n_res - k, 1)
    J = np.asarray(r.jac, float)
    # a quantity the outputs do not see (a zero column: an unmeasured
    # integrator's initial value) has no std, and leaves the others theirs
    seen = np.flatnonzero(np.any(J != 0.0, axis=0))
    d = np.full(k, np.nan)
    try:
        d[seen] = np.diag(s2 * np.linalg.inv(J[:, seen].T @ J[:, seen]))
    except np.linalg.LinAlgError:
        pass
    std = {n: (float(np.sqrt(v)) if v > 0 and n not in at else None)
           for n, v in zip(names, d)}
    return OutputErrorResult(names, r.x.copy(), th, x0, float(r.cost), rmse, std, at, s.y,
                             int(r.nfev), int(r.njev or 0), int(r.status), str(r.message))


#: a parameter whose box is positive and spans at least this ratio is
#: searched by the swarm in log θ (a stiffness in [0.01, 100])
LOG_SPAN = 10.0

#: independent swarms at most in one global output-error fit (:func:`_agreeing_swarms`)
SWARM_RUNS = 4
#: two swarms agree when their best mean squared errors differ by less than this fraction
SWARM_AGREE = 0.05


def swarm_output_error_fit(model, t, u, y, params: Sequence[str], *, theta=None, x0=None,
                           bounds=None, sigma=None, options: OutputErrorOptions | None = None,
                           swarm=None) -> OutputErrorResult:
    """Global output-error fit: a particle swarm over the parameters' box,
    then the local least-squares fit (:func:`output_error_fit`) from the best
    particle or the start ``theta``, whichever is better.

    The local fit alone finds the basin of its start (a linear drive fitted
    to a sign-blind sensor's |ω|, then given the rectifying sensor). The
    swarm (:func:`bondgraph.inference.optimize.pso`; Kennedy & Eberhart 1995)
    minimises the mean squared weighted free-run error over the box, in log
    θ where the box is positive and spans :data:`LOG_SPAN` or more. The start
    is not one of its particles: seeded with a good local fit, the swarm
    gathered in that basin and stalled (a user's CED graph with |ω|: NRMSE
    1.05 seeded, 0.29 not). Swarms of seeds ``swarm.seed``, +1, ... run
    until two agree on the best value (:func:`_agreeing_swarms`). A free run
    is the compiled fixed-step RK4 (:func:`~bondgraph.inference.sim_numba.rk4_trajectory`)
    or the batched numpy RK4 (:func:`~bondgraph.numerics.integrators.simulate_batch`).

    Parameters
    ----------
    model : Model
    t : array (N,)
        Sample times [s].
    u : array (N, n_u) or None
    y : array (N, n_y)
        Measured outputs (NaN: missing).
    params : sequence of str
        Estimated parameters (k >= 1); their boxes must be finite.
    theta : array (n_theta,), optional
        A start (compared with the swarm's best) and the other parameters'
        values (default the model's).
    x0 : array (n_x,), optional
        Initial state (default the model's).
    bounds : (lower, upper) of arrays (k,), optional
        Box (default the parameters' declared boxes).
    sigma : array (n_y,), optional
        Output weights (default the std of each measured output).
    options : OutputErrorOptions, optional
        Hold and fixed-step ``substeps`` of the free runs (default 4) and
        the local fit's settings.
    swarm : SwarmOptions, optional
        Each swarm's. Default: min(10 k, 60) particles, 100 iterations, stop
        after 20 iterations without a relative gain of 1e-6, seed 0.

    Returns
    -------
    OutputErrorResult
        The local fit's result from the swarm's best point.

    Raises
    ------
    ModelError
        Nothing to estimate, unknown names, a box that is not finite.
    NumericalError
        Neither a particle's nor the start's free run is finite, or the
        local fit fails.
    """
    model = Model.from_spec(model)
    opts = options if options is not None else OutputErrorOptions(substeps=4)
    if opts.substeps is None:
        opts = OutputErrorOptions(hold=opts.hold, method=opts.method, rtol=opts.rtol,
                                  atol=opts.atol, max_nfev=opts.max_nfev, substeps=4)
    params = list(params)
    if not params:
        raise ModelError("swarm_output_error_fit: nothing to estimate (no params)")
    th = np.array(model.theta0 if theta is None else theta, dtype=float)
    xi = np.array(model.x0 if x0 is None else x0, dtype=float)
    lo, hi = _box(model, params, [], bounds)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise ModelError("swarm_output_error_fit: the box of "
                         + ", ".join(n for n, a, b in zip(params, lo, hi)
                                     if not np.isfinite(a - b)) + " is not finite")
    crit = _SwarmCriterion(model, t, u, y, params, th, xi, sigma, opts)
    sw = swarm if swarm is not None else SwarmOptions(
        particles=min(10 * len(params), 60), stall_iterations=20, ftol=1e-6)
    best = th.copy()
    best[crit.pidx] = _swarm_best(crit, lo, hi, np.clip(th[crit.pidx], lo, hi), sw)
    return output_error_fit(model, t, u, y, params, theta=best, x0=xi, bounds=(lo, hi),
                            sigma=crit.sigma, options=opts)


def _swarm_best(crit, lo: np.ndarray, hi: np.ndarray, z0: np.ndarray, sw) -> np.ndarray:
    """The better (k,) of the start ``z0`` and the best point of independent
    swarms of ``crit`` in the box (:func:`_agreeing_swarms`), searched in log
    θ where the box is positive and spans :data:`LOG_SPAN` or more;
    NumericalError when neither a particle's nor the start's run is finite."""
    logs = (lo > 0) & (hi >= LOG_SPAN * np.maximum(lo, 1e-300))
    zlo, zhi = np.where(logs, np.log(np.maximum(lo, 1e-300)), lo), np.where(logs, np.log(hi), hi)
    res = _agreeing_swarms(lambda Z: crit(np.where(logs, np.exp(Z), Z)), zlo, zhi, sw)
    f0 = float(crit(z0[None, :])[0])
    if not np.isfinite(res.fun):
        if np.isfinite(f0):
            return z0
        raise NumericalError(f"swarm_output_error_fit: no free run of model "
                             f"'{crit.model.name}' in the box is finite")
    zb = np.clip(np.where(logs, np.exp(res.x), res.x), lo, hi)
    return zb if float(crit(zb[None, :])[0]) <= f0 else z0


def _agreeing_swarms(fun, lo: np.ndarray, hi: np.ndarray, sw):
    """The best of independent swarms (:func:`bondgraph.inference.optimize.pso`
    with seeds ``sw.seed``, ``sw.seed + 1``, ...) of ``fun`` on the box
    [lo, hi]: swarms are run until two of them end within
    :data:`SWARM_AGREE` of the best value found, at most :data:`SWARM_RUNS`.

    One swarm misses a narrow basin now and then: on a user's CED graph
    (eight parameters, a sign-blind sensor, the real record u1) one seed in
    six of a 60-particle swarm ended at NRMSE 1.06 (the record's mean)
    where the others reached 0.29, and more particles did not change that
    rate (120: one in six; 200 for 200 iterations: one in six short of the
    best). Two independent runs that agree are the usual stopping rule of a
    multistart search (the best value seen twice, a simple form of the
    stopping rules of Boender & Rinnooy Kan 1987); both failing at one value
    is rare (about one in thirty at that rate), a disagreement costs a third
    run."""
    runs = []
    for r in range(SWARM_RUNS):
        seed = None if sw.seed is None else int(sw.seed) + r
        runs.append(pso(fun, lo, hi, swarm=replace(sw, seed=seed), progress=False))
        fs = np.sort([x.fun for x in runs if np.isfinite(x.fun)])
        if fs.size >= 2 and fs[1] <= fs[0] + SWARM_AGREE * abs(fs[0]):
            break
    return min(runs, key=lambda x: x.fun if np.isfinite(x.fun) else np.inf)


class _SwarmCriterion:
    """Mean squared weighted free-run error of parameter sets X (S, k):
    compiled RK4 per set, or batched numpy RK4; +inf where not finite."""

    def __init__(self, model, t, u, y, params, theta, x0, sigma, opts: OutputErrorOptions):
        self.model, self.theta, self.x0, self.opts = model, theta, x0, opts
        self.t = np.asarray(t, float)
        self.y = np.asarray(y, float).reshape(self.t.size, -1)
        if self.y.shape[1] != model.n_y:
            raise DataError(f"y has {self.y.shape[1]} columns, model '{model.name}' has "
                            f"{model.n_y} outputs")
        self.u = (np.asarray(u, float).reshape(self.t.size, -1) if model.n_u
                  else np.zeros((self.t.size, 1)))
        self.pidx = model.param_indices(params)
        self.sigma = (np.array([np.nanstd(self.y[:, i]) or 1.0 for i in range(model.n_y)])
                      if sigma is None else np.asarray(sigma, float))
        self.mask = np.isfinite(self.y)
        self.kernels = free_run_kernels(model, "numba", "rk4", opts.hold)

    def __call__(self, X: np.ndarray) -> np.ndarray:
        thetas = np.repeat(self.theta[None, :], len(X), axis=0)
        thetas[:, self.pidx] = X
        if self.kernels is None:
            Y = simulate_batch(self.model, self.t, self.u[:, :self.model.n_u], thetas, self.x0,
                               method="rk4", substeps=self.opts.substeps, hold=self.opts.hold)
        else:
            Y = np.stack([self._run(th) for th in thetas], axis=1)
        with np.errstate(all="ignore"):
            E = np.where(self.mask[:, None, :], (Y - self.y[:, None, :]) / self.sigma, 0.0)
            f = np.sum(E ** 2, axis=(0, 2)) / max(int(self.mask.sum()), 1)
        return np.where(np.isfinite(f), f, np.inf)

    def _run(self, th: np.ndarray) -> np.ndarray:
        X = sim_numba.rk4_trajectory(self.kernels, self.t, self.u, self.opts.hold, th, self.x0,
                                     self.opts.substeps)
        with np.errstate(all="ignore"):
            return np.asarray(self.model.h(X, self.u[:, :self.model.n_u], th[None, :]), float)
