"""Simulation of a generated model: adaptive (scipy) or fixed-step (RK4, ROS2).

:func:`simulate` integrates ``dx/dt = f(x, u, θ)`` of a
:class:`~bondgraph.numerics.model.Model` on a sample grid ``t`` and evaluates the
outputs ``y = h(x, u, θ)`` at every sample.

Methods
-------
``BDF``, ``Radau``, ``LSODA``
    :func:`scipy.integrate.solve_ivp` with the generated Jacobian
    ``model.dfdx`` (stiff-safe; the default is ``BDF``). ``LSODA`` runs
    through :func:`scipy.integrate.odeint`, the same ODEPACK solver
    (Hindmarsh 1983; Petzold 1983) called once per segment instead of once
    per step, with its own interpolation at the samples: on CED's record
    (500 samples, 38 zero-order-hold segments) a free run took 37 ms
    against solve_ivp's 115 ms, the same steps (4371 calls of the
    right-hand side) and the outputs within 1.6e-8 of their std.
``RK45``, ``RK23``, ``DOP853``
    :func:`scipy.integrate.solve_ivp`, explicit, no Jacobian.
``rk4``, ``ros2``
    :func:`bondgraph.numerics.integrators.rk4` / :func:`~bondgraph.numerics.integrators.ros2`
    with ``substeps`` steps per sample interval, inputs held at the sample
    value over the interval (zero-order hold), exactly what the UKF sees.

Inputs
------
``u`` may be an array ``(N, n_u)`` (or ``(N, n_base)`` without the
``der(.)`` inputs), a dict ``name -> array (N,) | scalar | vectorised
callable t -> array``, or a callable ``t -> (n_u,)`` (or ``(n_base,)``).
Inputs not given take the model default. Derivative inputs ``der(r)``
(``model.derivative_inputs``) are computed from ``r`` unless given: by
``numpy.gradient`` of sampled arrays, by a central difference of callables.

Between samples the adaptive solvers see callables evaluated exactly at any
time, and sampled arrays interpolated linearly (``hold="linear"``, the
default) or held (``hold="zoh"``; the record is then integrated piecewise
between the samples where an input changes, so the solver never steps over a
discontinuity). One hold per input, comma-joined in the model's input order
(``hold="zoh,linear"``), holds each sampled-array input its own way. The
fixed-step methods always hold the sample value.

References
----------
Hairer, E., Wanner, G. (1996). *Solving Ordinary Differential Equations II:
Stiff and Differential-Algebraic Problems*, 2nd ed., Springer (stiffness,
stability regions, Rosenbrock methods). Hindmarsh, A. C. (1983). ODEPACK, a
systematized collection of ODE solvers. Petzold, L. (1983). Automatic
selection of methods for solving stiff and nonstiff systems of ordinary
differential equations. SIAM J. Sci. Stat. Comput. 4(1), 136-148. Verwer et
al. (1999) for ROS2, see :mod:`bondgraph.numerics.integrators`.
"""

from __future__ import annotations

import math
import time
import warnings
from bisect import bisect_right
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any, Callable, Mapping

import numpy as np
from scipy.integrate import ODEintWarning, odeint, solve_ivp

from bondgraph.core import progress as _progress
from bondgraph.core.domains import jump_laws
from bondgraph.errors import DataError, ModelError, NumericalError, OptionError
from bondgraph.numerics import integrators
from bondgraph.numerics.integrators import split_hold
from bondgraph.numerics.model import Model

# a failed LSODA segment raises a NumericalError that names its time and
# state (:func:`_solve_ivp`); odeint's own warning about it is not repeated
warnings.filterwarnings("ignore", category=ODEintWarning, module=__name__)

#: solve_ivp methods that receive the generated Jacobian
IMPLICIT_METHODS = ("BDF", "Radau", "LSODA")
#: solve_ivp methods without a Jacobian
EXPLICIT_METHODS = ("RK45", "RK23", "DOP853")
#: fixed-step methods of :mod:`bondgraph.numerics.integrators`
FIXED_METHODS = ("rk4", "ros2")
METHODS = IMPLICIT_METHODS + EXPLICIT_METHODS + FIXED_METHODS


# ------------------------------------------------------------------ result
@dataclass
class SimResult:
    """A simulated trajectory.

    Attributes
    ----------
    t : ndarray (N,)
        Sample times [s].
    x : ndarray (N, n_x)
        States (model units).
    u : ndarray (N, n_u)
        Inputs at the samples, including ``der(.)`` inputs.
    y : ndarray (N, n_y)
        Noise-free outputs ``h(x, u, θ)``.
    model : Model
    theta : ndarray (n_theta,)
    method : str
    stats : dict
        Solver statistics (``nfev``, ``njev``, ``nlu``, ``wall_time_s``,
        ``substeps``, ``hold``, ``segments``, ``message``).
    """

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    y: np.ndarray
    model: Any
    theta: np.ndarray
    method: str
    stats: dict = field(default_factory=dict)

    def state(self, name: str) -> np.ndarray:
        """Trajectory of one state, (N,)."""
        return self.x[:, self.model.state_index(name)]

    def output(self, name: str) -> np.ndarray:
        """Trajectory of one output, (N,)."""
        return self.y[:, self.model.output_index(name)]

    def input(self, name: str) -> np.ndarray:
        """One input signal at the samples, (N,)."""
        return self.u[:, self.model.input_index(name)]

    def __repr__(self) -> str:
        return (f"<SimResult {self.model.name} {self.method}: {self.t.size} samples, "
                f"t = {self.t[0]:.6g} .. {self.t[-1]:.6g} s>")


# ------------------------------------------------------------------ inputs
def _central_diff(fn: Callable, t: np.ndarray, scale: float) -> np.ndarray:
    h = 1e-6 * max(scale, 1e-3)
    return (np.asarray(fn(t + h), dtype=float) - np.asarray(fn(t - h), dtype=float)) / (2 * h)


class InputSignals:
    """The input vector of a model as a function of time.

    Built by :func:`simulate` from any of the accepted forms of ``u``;
    ``samples`` holds the inputs at the sample times, ``at(tq)`` evaluates
    them at any time for the adaptive solvers (callables exactly, arrays by
    linear interpolation or zero-order hold).

    Parameters
    ----------
    model : Model
    t : array (N,)
    u : None, array, dict or callable
    hold : {"linear", "zoh"} or str
        One for every input, or one per input comma-joined in input order
        (:func:`bondgraph.numerics.integrators.split_hold`).

    Raises
    ------
    ModelError
        Unknown input names, arrays of the wrong shape, an unknown hold.
    DataError
        Non-finite input values (the input and sample are named).
    """

    def __init__(self, model, t: np.ndarray, u=None, hold: str = "linear"):
        try:
            holds = split_hold(hold, model.n_u)
        except OptionError as e:
            raise ModelError(str(e)) from None
        if any(h not in ("linear", "zoh") for h in holds):
            raise ModelError(f"unknown hold '{hold}' (use 'linear' or 'zoh', or one of them per "
                             f"input joined by commas)")
        self.model = model
        self.t = t
        self.hold = hold
        #: each input's hold ("linear" or "zoh")
        self.holds = holds
        self._scale = float(np.median(np.diff(t)))
        self._fns: list[Callable[[np.ndarray], np.ndarray]] = []
        #: each input at one time, a float (:meth:`at`: the values of _fns)
        self._scalar: list[Callable[[float], float]] = []
        self.samples = np.empty((t.size, model.n_u))
        self.source: dict[str, str] = {}
        self._array_cols: list[int] = []
        self._const_cols: list[int] = []
        spec = self._parse(u)
        for j, nm in enumerate(model.inputs):
            kind, val = self._resolve(j, nm, spec)
            self._install(j, kind, val)
        bad = np.argwhere(~np.isfinite(self.samples))
        if bad.size:
            i, j = bad[0]
            raise DataError(f"input '{model.inputs[j]}' is {float(self.samples[i, j])!r} at sample {i} "
                            f"(t = {float(t[i])!r}); inputs must be finite")
        self._table = self._sample_table()

    def _base_names(self) -> list[str]:
        """Inputs that are not ``der(.)`` inputs."""
        der = self.model.derivative_inputs
        return [nm for nm in self.model.inputs if nm not in der]

    def _parse(self, u) -> dict[str, tuple[str, Any]]:
        """The given inputs by name: ``("const", value) | ("array", samples) |
        ("fn", callable) | ("fn_sampled", (callable, samples))``."""
        if u is None:
            return {}
        if callable(u) and not isinstance(u, Mapping):
            return self._parse_callable(u)
        if isinstance(u, Mapping):
            return self._parse_mapping(u)
        return self._parse_array(u)

    def _parse_callable(self, u: Callable) -> dict[str, tuple[str, Any]]:
        """``u(t) -> (n_u,)`` or ``(n_base,)``: sampled once, kept for :meth:`at`."""
        model, t = self.model, self.t
        nu, base_names = model.n_u, self._base_names()
        probe = np.asarray(u(float(t[0])), dtype=float).reshape(-1)
        if probe.size == nu:
            names = list(model.inputs)
        elif probe.size == len(base_names):
            names = base_names
        else:
            raise ModelError(f"the input callable returns {probe.size} values; model "
                             f"'{model.name}' expects {nu} ({', '.join(model.inputs)})"
                             + (f" or {len(base_names)} ({', '.join(base_names)})"
                                if model.derivative_inputs else ""))
        vec = np.array([np.asarray(u(float(tk)), dtype=float).reshape(-1) for tk in t])

        def vector_fn(tq, _u=u):
            tq = np.atleast_1d(np.asarray(tq, dtype=float))
            return np.array([np.asarray(_u(float(s)), dtype=float).reshape(-1)
                             for s in tq])

        return {nm: ("fn_sampled", (lambda tq, j=j: vector_fn(tq)[:, j], vec[:, j]))
                for j, nm in enumerate(names)}

    def _parse_mapping(self, u: Mapping) -> dict[str, tuple[str, Any]]:
        """``{name: callable | scalar | array (N,)}``."""
        n = self.t.size
        spec: dict[str, tuple[str, Any]] = {}
        for nm, val in u.items():
            self.model.input_index(nm)  # raises ModelError naming the input
            if callable(val):
                spec[nm] = ("fn", val)
                continue
            arr = np.asarray(val, dtype=float)
            if arr.ndim == 0:
                spec[nm] = ("const", float(arr))
            elif arr.shape == (n,):
                spec[nm] = ("array", arr)
            else:
                raise ModelError(f"input '{nm}' has shape {arr.shape}; expected a "
                                 f"scalar, ({n},) like t, or a callable")
        return spec

    def _parse_array(self, u) -> dict[str, tuple[str, Any]]:
        """An array ``(N, n_u)`` or ``(N, n_base)`` (or one row, broadcast)."""
        model, n = self.model, self.t.size
        nu, base_names, der = model.n_u, self._base_names(), model.derivative_inputs
        arr = np.asarray(u, dtype=float)
        if arr.ndim == 1 and arr.size in (nu, len(base_names)):
            arr = np.broadcast_to(arr, (n, arr.size))
        if arr.ndim == 2 and arr.shape == (n, nu):
            names = list(model.inputs)
        elif arr.ndim == 2 and der and arr.shape == (n, len(base_names)):
            names = base_names
        else:
            raise ModelError(
                f"input array has shape {arr.shape}; model '{model.name}' expects "
                f"({n}, {nu}) for inputs {', '.join(model.inputs)}"
                + (f" or ({n}, {len(base_names)}) without the derivative inputs"
                   if der else ""))
        return {nm: ("array", np.array(arr[:, j])) for j, nm in enumerate(names)}

    def _resolve(self, j: int, nm: str, spec: dict) -> tuple[str, Any]:
        """Kind and value of model input ``j``: given, the derivative of a
        given input (``der(.)``), or the model default; records the source."""
        src = self.model.derivative_inputs.get(nm)
        kind, val = spec.get(nm, (None, None))
        if kind is None and src is not None:
            scale = self._scale
            skind, sval = spec.get(src, ("const", None))
            if skind == "const":
                kind, val = "const", 0.0
                self.source[nm] = f"0 (d/dt of constant {src})"
            elif skind == "array":
                kind, val = "array", np.gradient(sval, self.t)
                self.source[nm] = f"numpy.gradient of {src}"
            elif skind == "fn":
                kind, val = "fn", (lambda tq, f=sval: _central_diff(f, tq, scale))
                self.source[nm] = f"central difference of {src}(t)"
            else:  # fn_sampled
                f = sval[0]
                kind, val = "fn", (lambda tq, f=f: _central_diff(f, tq, scale))
                self.source[nm] = f"central difference of {src}(t)"
        elif kind is None:
            kind, val = "const", float(self.model.u0[j])
            self.source[nm] = "model default"
        else:
            self.source.setdefault(nm, "given")
        return kind, val

    def _install(self, j: int, kind: str, val) -> None:
        """Fill column ``j`` of :attr:`samples` and its function of time."""
        if kind == "const":
            self.samples[:, j] = val
            self._const_cols.append(j)
            self._fns.append(lambda tq, v=val: np.full(np.shape(tq), v))
            self._scalar.append(lambda tq, v=float(val): v)
            return
        if kind == "array":
            self.samples[:, j] = val
            self._array_cols.append(j)
            self._fns.append(self._array_fn(val, self.holds[j]))
            self._scalar.append(self._array_scalar(val, self.holds[j]))
            return
        if kind == "fn":
            self.samples[:, j] = np.broadcast_to(np.asarray(val(self.t), dtype=float),
                                                 (self.t.size,))
            self._fns.append(lambda tq, f=val: np.asarray(f(tq), dtype=float))
        else:  # fn_sampled
            f, vals = val
            self.samples[:, j] = vals
            self._fns.append(f)
        fn = self._fns[-1]
        self._scalar.append(lambda tq: float(np.asarray(fn(np.array([tq]))).reshape(-1)[0]))

    def _array_fn(self, vals: np.ndarray, hold: str) -> Callable:
        t = self.t
        if hold == "linear":
            return lambda tq: np.interp(tq, t, vals)

        def zoh(tq):
            k = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, t.size - 1)
            return vals[k]
        return zoh

    def _array_scalar(self, vals: np.ndarray, hold: str) -> Callable[[float], float]:
        """:meth:`_array_fn` at one time, as a float (the same numpy
        routines on a scalar: the same values, without the array round
        trip that an adaptive solver paid at every right-hand side call)."""
        t = self.t
        if hold == "linear":
            return lambda tq: float(np.interp(tq, t, vals))
        last = t.size - 1
        return lambda tq: float(vals[min(max(int(np.searchsorted(t, tq, side="right")) - 1, 0),
                                         last)])

    def _sample_table(self) -> tuple | None:
        """``(t list, samples (N, n_u), slopes (N-1, n_u))`` when every input
        is a constant or a sampled array (no callable): :meth:`at` is then
        one search and one vector expression. A linearly held column's slope
        is numpy.interp's, (u[k+1] - u[k]) / (t[k+1] - t[k]); a column held
        zero-order or constant has slope 0, so that ``slopes[k] * (tq - t[k])
        + samples[k]`` is, column by column, the value of numpy.interp and of
        the zero-order hold's search (the same floating-point operations).
        None where some input is a callable."""
        n_u = self.samples.shape[1]
        if len(self._array_cols) + len(self._const_cols) != n_u or self.t.size < 2:
            return None
        slopes = np.zeros((self.t.size - 1, n_u))
        lin = [j for j in self._array_cols if self.holds[j] == "linear"]
        if lin:
            s = self.samples[:, lin]
            slopes[:, lin] = (s[1:] - s[:-1]) / np.diff(self.t)[:, None]
            if not np.all(np.isfinite(slopes)):   # overflow: numpy.interp's own path
                return None
        return self.t.tolist(), self.samples, slopes

    def at(self, tq: float) -> np.ndarray:
        """Input vector (n_u,) at time ``tq``."""
        table = self._table
        if table is None:
            return np.array([fn(tq) for fn in self._scalar])
        tl, samples, slopes = table
        k = bisect_right(tl, tq) - 1
        if k < 0:
            return samples[0].copy()
        if k >= len(tl) - 1:
            return samples[-1].copy()
        return slopes[k] * (tq - tl[k]) + samples[k]

    def segment_input(self, a: int, hold: str) -> Callable[[float], np.ndarray]:
        """Input function of the segment starting at sample ``a``: the
        sampled-array inputs that ``hold`` holds zero-order (all with
        ``"zoh"``, some with a per-input hold) are held at sample ``a``
        (callables and linearly held arrays still vary inside the segment);
        none: :meth:`at`."""
        cols = self._held_columns(hold)
        if not cols:
            return self.at
        ua = self.samples[a]
        if len(cols) + len(self._const_cols) == self.samples.shape[1]:
            held = ua.copy()            # no callable: the same vector all segment long

            def u_held(tq: float) -> np.ndarray:
                return held
            return u_held

        def u_at(tq: float) -> np.ndarray:
            v = self.at(tq)
            v[cols] = ua[cols]
            return v
        return u_at

    def _held_columns(self, hold: str) -> list[int]:
        """The sampled-array inputs that ``hold`` holds zero-order."""
        holds = self.holds if hold == self.hold else split_hold(hold, self.model.n_u)
        return [j for j in self._array_cols if holds[j] == "zoh"]

    def segment_table(self, a: int, hold: str) -> tuple | None:
        """The input of :meth:`segment_input` as data for a compiled
        right-hand side (:func:`compiled_rhs`): ``(t (N,), samples (N, n_u),
        slopes (N-1, n_u), ua (n_u,), held (n_u,) int8)``, the sample table
        of :meth:`at` and the columns held at ``ua`` (the segment's first
        sample); None where some input is a callable (no table)."""
        if self._table is None:
            return None
        _, samples, slopes = self._table
        n_u = samples.shape[1]
        cols = self._held_columns(hold)
        held = np.zeros(n_u, dtype=np.int8)
        if cols:
            # every column held when no input varies inside the segment
            # (constants read the same from the table and from sample a)
            all_held = len(cols) + len(self._const_cols) == n_u
            held[list(range(n_u)) if all_held else cols] = 1
        return self.t, samples, slopes, samples[a].copy(), held

    def zoh_columns(self) -> list[int]:
        """The sampled-array inputs held zero-order (:attr:`holds`)."""
        return [j for j in self._array_cols if self.holds[j] == "zoh"]

    def change_points(self) -> np.ndarray:
        """Sample indices k where a sampled-array input held zero-order
        differs from sample k-1 (plus 0): the segments integrated
        separately."""
        cols = self.zoh_columns()
        if not cols:
            return np.array([0])
        s = self.samples[:, cols]
        ch = np.flatnonzero(np.any(s[1:] != s[:-1], axis=1)) + 1
        return np.concatenate([[0], ch])


# ---------------------------------------------------------------- simulate
def _as_model(model):
    if isinstance(model, str):
        return Model.load(model)
    return model


def _vector(model, value, kind: str) -> np.ndarray:
    if kind == "theta":
        names, default, build = model.params, model.theta0, model.theta
    else:
        names, default, build = model.states, model.x0, model.state
    if value is None:
        return default.copy()
    if isinstance(value, Mapping):
        return build(dict(value))
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape != (len(names),):
        raise ModelError(f"{kind} has shape {np.shape(value)}; model '{model.name}' expects "
                         f"({len(names)},) for {', '.join(names)}")
    return arr.copy()


def _check_t(t) -> np.ndarray:
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or t.size < 2:
        raise DataError(f"t must be a 1-D array of at least 2 sample times, got shape {t.shape}")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise DataError(f"t[{bad[0]}] is {float(t[bad[0]])!r}; sample times must be finite")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise DataError(f"t[{i}] = {float(t[i])!r} does not follow t[{i - 1}] = {float(t[i - 1])!r}; "
                        f"sample times must increase strictly")
    return t


def _nonfinite_error(model, t, X, method, extra="") -> NumericalError:
    bad = np.argwhere(~np.isfinite(X))
    i, j = bad[0]
    return NumericalError(
        f"state '{model.states[j]}' of model '{model.name}' became {float(X[i, j])!r} at "
        f"t = {t[i]:.6g} s (sample {i}) with method {method}{extra}",
        hint="the step is too large for the stiffest mode (see stiffness_report): use more "
             "substeps, method='ros2' or an implicit solver (BDF, Radau, LSODA); or the "
             "parameters make the model unstable")


def simulate(model, t, u=None, x0=None, theta=None, method: str = "BDF", rtol: float = 1e-8,
             atol: float = 1e-10, substeps: int = 1, max_step: float | None = None, *,
             hold: str = "linear", progress: bool | None = None,
             backend: str = "numpy") -> SimResult:
    """Simulate a model on the sample grid ``t``.

    Parameters
    ----------
    model : Model or str
        A generated model (or its registered name).
    t : array (N,)
        Sample times [s], strictly increasing; the simulation starts at
        ``t[0]`` from ``x0``.
    u : None, array (N, n_u) or (N, n_base), dict, or callable
        Inputs, in model units (see the module docstring); default: the
        model's input defaults.
    x0 : array (n_x,) or dict, optional
        Initial state (default ``model.x0``; a dict overrides named states).
    theta : array (n_theta,) or dict, optional
        Parameters (default ``model.theta0``; a dict overrides named ones).
    method : str
        ``BDF`` (default), ``Radau``, ``LSODA`` (with the generated Jacobian),
        ``RK45``, ``RK23``, ``DOP853``, or fixed-step ``rk4``, ``ros2``.
    rtol, atol : float
        Tolerances of the adaptive solvers.
    substeps : int
        Fixed-step methods: steps per sample interval.
    max_step : float, optional
        Largest step of the adaptive solvers [s] (default: unlimited; set it
        below the shortest input pulse that a callable input contains).
    hold : {"linear", "zoh"} or str
        Sampled-array inputs between samples (adaptive solvers), or one per input ("zoh,linear").
    progress : bool, optional
        tqdm progress bar for fixed-step loops (default: only for long runs,
        more than 2e5 sub-steps, and only on a terminal).
    backend : {"numpy", "numba"}
        What the adaptive solvers' right-hand side and Jacobian call: the
        generated numpy functions (default) or the model's compiled point
        kernels ``f`` and ``f_dfdx`` (:func:`bondgraph.numerics.compiled.point_kernels`;
        compiled at the first use of an in-memory model; the same
        expressions, equal to rounding; 5-10x less time per call of the
        right-hand side). numpy runs when the kernels cannot be had;
        ``stats["backend"]`` says which ran.

    Returns
    -------
    SimResult
        ``x (N, n_x)``, ``u (N, n_u)``, ``y (N, n_y)`` at the samples.

    Raises
    ------
    ModelError
        Unknown method, input names, or arrays of the wrong shape.
    DataError
        Non-finite or non-increasing times, non-finite inputs.
    NumericalError
        A state became non-finite or (adaptive methods) passed 1e100 (the
        message names the time and the state), or the adaptive solver failed
        or stalled (:func:`guard_rhs`).
    """
    model = _as_model(model)
    if backend not in ("numpy", "numba"):
        raise ModelError(f"unknown backend '{backend}' (use 'numpy' or 'numba')")
    if method not in METHODS:
        raise ModelError(f"unknown simulation method '{method}' (use one of {', '.join(METHODS)})")
    t = _check_t(t)
    th = _vector(model, theta, "theta")
    x_init = _vector(model, x0, "x0")
    if not np.all(np.isfinite(x_init)):
        raise DataError(f"x0 is not finite: {x_init}")
    sig = InputSignals(model, t, u, hold=hold)
    U = sig.samples
    stats: dict[str, Any] = {"method": method}
    t_wall = time.perf_counter()
    X = _states(model, sig, th, x_init, method, substeps, progress, (rtol, atol, max_step),
                backend, stats)
    stats["wall_time_s"] = time.perf_counter() - t_wall
    with np.errstate(all="ignore"):
        Y = np.asarray(model.h(X, U, th), dtype=float)
    return SimResult(t=t, x=X, u=U, y=Y, model=model, theta=th, method=method, stats=stats)


def _fixed_step(model, t, U, th, x, method, substeps, progress):
    n = t.size
    X = np.empty((n, model.n_x))
    X[0] = x
    step = integrators.make_step(model, method, substeps)
    steps = range(n - 1)
    if progress is None:
        progress = (n - 1) * substeps > 200_000
    if progress:
        steps = _progress.bar(steps, desc=f"simulate {model.name} ({method})", unit="sample",
                              leave=False)
    # a batch axis of 1: the generated functions are used in their batched form
    x = np.asarray(x, dtype=float)[None, :]
    th1 = th[None, :]
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for k in steps:
            x = step(x, U[k:k + 1], th1, t[k + 1] - t[k])
            X[k + 1] = x[0]
            if not np.all(np.isfinite(x)):
                d = np.asarray(model.f(X[k][None, :], U[k:k + 1], th1), dtype=float)[0]
                if not np.all(np.isfinite(d)):      # not the step: a law undefined there
                    raise _undefined_error(model, method, Runaway(
                        t[k], X[k], "", component=int(np.argmin(np.isfinite(d)))))
                raise _nonfinite_error(model, t, X[:k + 2], method,
                                       f" ({substeps} substeps per sample)")
    return X


def _states(model, sig: InputSignals, th, x_init, method, substeps, progress, tols, backend,
            stats) -> np.ndarray:
    """The states (N, n_x) of :func:`simulate` by its fixed-step or adaptive
    method (``tols`` = (rtol, atol, max_step)); ``stats`` filled."""
    t, U = sig.t, sig.samples
    if method in FIXED_METHODS:
        substeps = int(substeps)
        if substeps < 1:
            raise ModelError(f"substeps must be >= 1, got {substeps}")
        X = _fixed_step(model, t, U, th, x_init, method, substeps, progress)
        stats.update(substeps=substeps, hold="zoh",
                     nfev=(4 if method == "rk4" else 2) * substeps * (t.size - 1),
                     njev=(t.size - 1) if method == "ros2" else 0)
        return X
    kernels = _rhs_kernels(model) if backend == "numba" else None
    X = _solve_ivp(model, t, sig, th, x_init, method, tols, stats, kernels)
    stats.update(rtol=tols[0], atol=tols[1], hold=sig.hold,
                 backend="numpy" if kernels is None else "numba")
    return X


def _rhs_kernels(model):
    """The compiled point kernels of ``model`` for an adaptive solver, or
    None (numpy) when they cannot be had (numba missing, no kernels)."""
    try:
        from bondgraph.numerics.compiled import point_kernels
        return point_kernels(model)
    except Exception:  # numba missing or unable to compile: the numpy functions run
        return None


def _point_rhs(model, kernels, th, u_at):
    """``(rhs, jac)`` of one segment: the generated numpy functions on a
    batch of one, or the compiled point kernels (``kernels``)."""
    th1 = th[None, :]
    if kernels is None:
        def rhs(tq, xq):
            return model.f(xq[None, :], u_at(tq)[None, :], th1)[0]

        def jac(tq, xq):
            return model.dfdx(xq[None, :], u_at(tq)[None, :], th1)[0]
        return rhs, jac
    thc, n = np.ascontiguousarray(th, dtype=float), model.n_x
    f, f_dfdx = kernels.f, kernels.f_dfdx

    def rhs_c(tq, xq):
        out = np.empty(n)
        f(np.ascontiguousarray(xq, dtype=float), np.ascontiguousarray(u_at(tq), dtype=float),
          thc, out)
        return out

    def jac_c(tq, xq):
        out, J = np.empty(n), np.empty((n, n))
        f_dfdx(np.ascontiguousarray(xq, dtype=float),
               np.ascontiguousarray(u_at(tq), dtype=float), thc, out, J)
        return J
    return rhs_c, jac_c


#: A state whose squared norm passes this has run away (|x| > 1e100): no
#: physical state does, and an adaptive solver can cycle on it for hours
#: (LSODA was seen at 8 million calls at one t) instead of failing.
RUNAWAY_NORM2 = 1e200
#: Right-hand-side calls without the solver reaching a later time than
#: before; a step that needs this many has stalled.
STALL_CALLS = 50_000
#: Right-hand-side calls in which an adaptive solver must advance at least
#: one sample interval; one that does not crawls: it resolves a fast, lightly
#: damped mode far above the sampling (a user's piston with its area
#: inverted: a 1e8 rad/s oil-column mode sampled at 1 kHz, LSODA at 25 s for
#: 30 samples, an output-error fit silent for minutes). Stick-slip friction
#: with a narrow tanh takes some hundreds per interval at its reversals.
CRAWL_CALLS = 20_000


class Runaway(Exception):
    """Raised inside the right-hand side to stop an adaptive solver
    (``component``: the derivative that was not finite at a finite state,
    when that was the cause)."""

    def __init__(self, tq: float, xq: np.ndarray, why: str, component: int | None = None):
        super().__init__(why)
        self.t, self.x, self.why = float(tq), np.array(xq, dtype=float), why
        self.component = component


def _ran_away(tq, xq) -> Runaway:
    """The state ``xq`` passed :data:`RUNAWAY_NORM2` or is not finite."""
    return Runaway(tq, xq, "ran away" if np.all(np.isfinite(xq)) else "became non-finite")


def _stalled(tq, xq) -> Runaway:
    """:data:`STALL_CALLS` calls without the solver advancing."""
    return Runaway(tq, xq, f"stalled ({STALL_CALLS} calls without advancing)")


def _crawling(tq, xq, dt: float) -> Runaway:
    """:data:`CRAWL_CALLS` calls advancing less than one sample interval."""
    return Runaway(tq, xq, f"crawled ({CRAWL_CALLS} calls advancing less than one sample "
                           f"interval of {dt:.4g} s)")


def crawl_hint(model, jac, tq: float, xq, dt: float) -> str:
    """What makes an adaptive solver crawl at ``(tq, xq)``: the fastest mode
    of the Jacobian ``jac(t, x)`` there against the sampling interval
    ``dt``, and what to check."""
    try:
        ev = np.linalg.eigvals(np.asarray(jac(tq, xq), dtype=float)[:model.n_x, :model.n_x])
        lam = ev[int(np.argmax(np.abs(ev)))]
        kind = (f"oscillating, damping ratio {-lam.real / abs(lam):.2g}" if lam.imag != 0
                else "real")
        fast = (f"its fastest mode there is {abs(lam):.3g} rad/s ({kind}), "
                f"{abs(lam) * dt:.3g} times the sampling rate 1/dt; ")
    except Exception:       # no Jacobian here: the advice stands without the figure
        fast = ""
    return (f"the model is far too fast for its sampling at these parameters: {fast}check "
            f"the parameters' values and units (a compliance, mass or a transformer's modulus "
            f"off by orders of magnitude), or simulate with a fixed step (method='rk4' or "
            f"'ros2' with substeps)")


def _undefined(tq, xq, k: int) -> Runaway:
    """Derivative ``k`` is not finite at the finite state ``xq``."""
    return Runaway(tq, xq, "met a derivative that is not finite at a finite state", component=k)


def _crawl_guard(dt: float | None) -> Callable[[float, np.ndarray], None]:
    """A check called with every right-hand-side evaluation that raises
    :func:`_crawling` when :data:`CRAWL_CALLS` calls in a row advanced the
    furthest time reached by less than ``dt`` (no check for ``dt`` None)."""
    mark = [0, -np.inf, -np.inf]        # calls, furthest t, furthest t at the last check

    def check(tq, xq):
        mark[0] += 1
        mark[1] = max(mark[1], tq)
        if mark[0] >= CRAWL_CALLS:
            if mark[1] - mark[2] < dt:
                raise _crawling(tq, xq, dt)
            mark[0], mark[2] = 0, mark[1]
    return (lambda tq, xq: None) if not dt or not np.isfinite(dt) else check


def guard_rhs(rhs, dt: float | None = None):
    """``rhs(t, x)`` for ``scipy.integrate.solve_ivp`` that stops the
    solver by raising ``Runaway`` (its ``t``, ``x`` and ``why``) when the
    state is non-finite or its squared norm passes ``RUNAWAY_NORM2``, when
    the solver has made ``STALL_CALLS`` calls without reaching a later
    time than before, or (with the sampling interval ``dt``) when
    ``CRAWL_CALLS`` calls advanced it less than ``dt``. The first derivative
    that is not finite at a finite state (a law outside its domain: log of
    a state at 0) is kept as ``g.undefined`` (a ``Runaway`` whose
    ``component`` names it), not raised: the solver may reject that trial
    step and go on; if it fails, the caller names the law instead of the
    failure."""
    seen = [-np.inf, 0]
    crawl = _crawl_guard(dt)

    def g(tq, xq):
        s = float(np.dot(xq, xq))
        if not s < RUNAWAY_NORM2:
            raise _ran_away(tq, xq)
        if tq > seen[0]:
            seen[0], seen[1] = tq, 0
        else:
            seen[1] += 1
            if seen[1] > STALL_CALLS:
                raise _stalled(tq, xq)
        crawl(tq, xq)
        d = rhs(tq, xq)
        if g.undefined is None and not np.all(ok := np.isfinite(d)):
            # kept, not raised: a solver may reject the trial step and go on
            g.undefined = _undefined(tq, xq, int(np.argmin(ok)))
        return d
    g.undefined = None
    return g


def compiled_rhs(kernels, th, table, n_x: int, dt: float | None = None) -> Callable | None:
    """The guarded right-hand side of :func:`guard_rhs` over the point
    kernels ``kernels`` at ``th`` and the segment's input ``table``
    (:meth:`InputSignals.segment_table`) as one compiled call per
    evaluation (:func:`bondgraph.numerics.compiled_c.table_rhs`): the same
    derivative to the bit, the same ``Runaway`` raised or kept in
    ``g.undefined``, at a tenth of the Python path's cost per call (an
    adaptive free run calls it some 10⁴-10⁵ times). None where it does not
    apply (numba kernels, an input given as a callable)."""
    f = getattr(kernels, "f", None)
    if table is None or not hasattr(f, "__wrapper_address__"):
        return None
    from bondgraph.numerics import compiled_c as cc

    ts, samples, slopes, ua, held = table
    try:
        call, addr = cc.table_rhs(), f.__wrapper_address__()
    except Exception:  # numba cannot compile it here: the Python path, the same values
        return None
    thc = np.ascontiguousarray(th, dtype=float)
    u, out = np.empty(samples.shape[1]), np.empty(n_x)
    state, limits = np.array([-np.inf, 0.0]), np.array([RUNAWAY_NORM2, float(STALL_CALLS)])
    ts = np.ascontiguousarray(ts, dtype=float)
    crawl = _crawl_guard(dt)

    def g(tq, xq):
        xq = np.ascontiguousarray(xq, dtype=float)
        crawl(tq, xq)
        code = call(addr, float(tq), xq, ts, samples, slopes, ua, held, thc, u, out, state,
                    limits)
        if code:
            if code == cc.RHS_RUNAWAY:
                raise _ran_away(tq, xq)
            if code == cc.RHS_STALLED:
                raise _stalled(tq, xq)
            if g.undefined is None:
                g.undefined = _undefined(tq, xq, int(code - cc.RHS_UNDEFINED))
        return out.copy()
    g.undefined = None
    return g


#: LSODA's step limit per segment (:func:`lsoda_segment`): none in effect, as with
#: solve_ivp; :func:`guard_rhs` stops a solver that stalls or runs away
LSODA_MXSTEP = 2**31 - 1


def lsoda_segment(rhs, jac, ts, x, rtol, atol, max_step=None) -> SimpleNamespace:
    """Integrate one segment by ODEPACK's LSODA (:func:`scipy.integrate.odeint`
    with the Jacobian ``jac``, never stepping past ``ts[-1]``; Petzold 1983):
    one call for the whole segment where ``solve_ivp(method="LSODA")`` makes
    one Python round trip per step.

    Parameters
    ----------
    rhs, jac : callable
        ``rhs(t, x) -> (n,)`` and ``jac(t, x) -> (n, n)`` (∂f_i/∂x_j).
    ts : array (k,)
        Increasing sample times; ``x`` is the state at ``ts[0]``.
    x : array (n,)
    rtol, atol : float
    max_step : float, optional
        Largest step [s] (default unlimited).

    Returns
    -------
    SimpleNamespace
        The fields of solve_ivp's result that its callers read: ``y``
        (n, k') at the first k' samples reached (k' = k unless it failed),
        ``t`` (k',), ``status`` (0 or -1), ``message``, ``nfev``, ``njev``,
        ``nlu`` (= ``njev``: LSODA factors each Jacobian it forms).

    Raises
    ------
    Exception
        Whatever ``rhs`` or ``jac`` raise (e.g. :class:`Runaway` of
        :func:`guard_rhs`).
    """
    Y, info = odeint(rhs, x, ts, Dfun=jac, tfirst=True, rtol=rtol, atol=atol,
                     tcrit=np.array([ts[-1]]), hmax=0.0 if max_step is None else float(max_step),
                     mxstep=LSODA_MXSTEP, full_output=True)
    ok = info["message"] == "Integration successful."
    got = ts.size
    if not ok:
        # the samples reached before the failure (odeint leaves the rest unset)
        reached = np.asarray(info["tcur"][:ts.size - 1]) >= ts[1:]
        got = 1 + (int(np.argmin(reached)) if not reached.all() else ts.size - 1)
    nje = int(info["nje"][got - 2]) if got > 1 else 0
    return SimpleNamespace(y=np.asarray(Y[:got]).T, t=ts[:got], status=0 if ok else -1,
                           message=info["message"], nfev=int(info["nfe"][got - 2]) if got > 1
                           else 0, njev=nje, nlu=nje)


def _undefined_error(model, method: str, r: Runaway) -> NumericalError:
    """The error of a solver that met a derivative that is not finite at a
    finite state (:func:`guard_rhs`): the state derivative, its value and
    the state, and what usually causes it."""
    k = r.component
    name = model.states[k] if k < len(model.states) else f"component {k}"
    at = ", ".join(f"{n} = {v:.6g}" for n, v in zip(model.states, r.x))
    return NumericalError(
        f"{method}: d{name}/dt of model '{model.name}' is not finite at t = {r.t:.6g} s, "
        f"where the state is finite ({at}): a law is not defined there",
        hint="a log or a division by a state at or below 0, or a power of a negative base "
             "of a parameter or input; start inside the laws' domain (x0, --x0), check the "
             "parameters' signs and the inputs, or write the law for the whole range")


def _jump_hint(model) -> str:
    """The hint for an adaptive solver that failed on a model whose laws
    jump (``sign(v)``: its domain notes say which): at a jump where the
    state sticks (Coulomb friction holding a mass at rest) the right-hand
    side switches sign at every step and no step is small enough
    (a Filippov solution, which adaptive solvers without event handling
    cannot follow). Empty for a model without jumps."""
    jumps = jump_laws(getattr(model, "domain_notes", ()))
    if not jumps:
        return ""
    return (f"the model's {', '.join(jumps)} jumps at 0, and a state that sticks there makes "
            f"the right-hand side switch at every step, which adaptive solvers cannot follow: "
            f"use a fixed-step method (method='rk4' or 'ros2' with substeps), or a smooth law "
            f"(bondgraph.core.smooth.smooth_sign(x, eps) = tanh(x/eps))")


def _solve_ivp(model, t, sig: InputSignals, th, x0, method, tols, stats, kernels=None):
    n = t.size
    X = np.empty((n, model.n_x))
    rtol, atol, max_step = tols
    kw = dict(method=method, rtol=rtol, atol=atol)
    if max_step is not None:
        kw["max_step"] = float(max_step)
    if sig.zoh_columns():
        bounds = list(sig.change_points()) + [n - 1]
        segments = [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    else:
        segments = [(0, n - 1)]
    totals = {"nfev": 0, "njev": 0, "nlu": 0}
    dt = float(np.median(np.diff(t))) if n > 1 else None
    x = np.array(x0, dtype=float)
    X[0] = x
    for a, b in segments:
        rhs, jac = _point_rhs(model, kernels, th, sig.segment_input(a, sig.hold))
        if method in IMPLICIT_METHODS:
            kw["jac"] = jac
        guarded = None if kernels is None else compiled_rhs(
            kernels, th, sig.segment_table(a, sig.hold), model.n_x, dt)
        guarded = guarded or guard_rhs(rhs, dt)
        try:
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                if method == "LSODA":
                    sol = lsoda_segment(guarded, jac, t[a:b + 1], x, rtol, atol, max_step)
                else:
                    sol = solve_ivp(guarded, (t[a], t[b]), x, t_eval=t[a:b + 1], **kw)
        except Runaway as r:
            if guarded.undefined is not None:
                raise _undefined_error(model, method, guarded.undefined) from None
            j = int(np.argmax(np.where(np.isfinite(r.x), np.abs(r.x), np.inf)))
            raise NumericalError(
                f"{method} {r.why} for model '{model.name}' near t = {r.t:.6g} s "
                f"(largest state there: '{model.states[j]}' = {r.x[j]:.6g})",
                hint=(crawl_hint(model, jac, r.t, r.x, dt) if r.why.startswith("crawled") else
                      _jump_hint(model) or "the solver cannot follow the model here: try "
                      "another method (BDF, Radau, LSODA) or a max_step"
                      if r.why.startswith("stalled") else
                      "the parameters make the model unstable on this input (a state passed "
                      "1e100): check their values and signs")) from None
        for k in totals:
            totals[k] += int(getattr(sol, k, 0) or 0)
        if guarded.undefined is not None and (sol.status != 0 or sol.y.shape[1] != b - a + 1
                                              or not np.all(np.isfinite(sol.y))):
            raise _undefined_error(model, method, guarded.undefined)
        if sol.status != 0 or sol.y.shape[1] != b - a + 1:
            got = sol.y.shape[1]
            t_fail = float(sol.t[-1]) if got else float(t[a])
            Xs = sol.y.T
            if Xs.size and not np.all(np.isfinite(Xs)):
                X[a:a + got] = Xs
                raise _nonfinite_error(model, t, X[:a + got], method)
            last = Xs[-1] if got else x
            j = int(np.argmax(np.abs(last))) if last.size else 0
            raise NumericalError(
                f"{method} failed for model '{model.name}' near t = {t_fail:.6g} s: "
                f"{sol.message} (largest state there: '{model.states[j]}' = {last[j]:.6g})",
                hint=_jump_hint(model) or "check the inputs and parameters; try "
                     "method='Radau' or 'LSODA', looser tolerances, or max_step")
        X[a:b + 1] = sol.y.T
        X[a] = x        # the segment's start exactly (BDF's dense output gives it to rounding)
        if not np.all(np.isfinite(X[a:b + 1])):
            raise _nonfinite_error(model, t, X[:b + 1], method)
        x = X[b]
    stats.update(totals, segments=len(segments), message="ok")
    return X


# ------------------------------------------------------------- stiffness
def stiffness_report(model, result: SimResult, theta=None, *, every: int | None = None,
                     max_samples: int = 200) -> tuple[dict, str]:
    """Eigenvalues of ``df/dx`` along a trajectory and what they mean for RK4.

    At every ``every``-th sample of ``result`` the generated Jacobian is
    evaluated and its eigenvalues λ computed. Reported per sample and
    overall: max abs(Re λ) (the fastest mode), the stiffness ratio
    max abs(Re λ) / min abs(Re λ) over the decaying modes (Re λ < 0), the largest
    step for which RK4 is stable on every mode (h·λ inside RK4's stability
    region, :func:`bondgraph.numerics.integrators.rk4_stable_step`) and the RK4
    sub-steps per sample interval that stability needs,
    ``ceil(Δt / h_stable)``. Growing modes (Re λ > 0) are physics, not a
    step limit; they are counted separately.

    Parameters
    ----------
    model : Model or str
    result : SimResult
    theta : array (n_theta,) or dict, optional
        Default ``result.theta``.
    every : int, optional
        Sample stride (default: at most ``max_samples`` samples).
    max_samples : int

    Returns
    -------
    report : dict
        ``model, every, n_checked, dt, max_abs_re, t_max_abs_re,
        stiffness_ratio, rk4_stable_step, rk4_substeps_needed,
        n_growing_modes, samples: [{t, eigenvalues: [[re, im], ...],
        max_abs_re, stiffness_ratio, rk4_stable_step, rk4_substeps}]``,
        plain Python numbers; ``rk4_stable_step`` is ``inf`` where no
        decaying mode limits the step. Write it with
        :func:`bondgraph.core.jsonsafe.to_jsonable` (``inf`` -> ``"inf"``).
    table : str
        The same as a text table.

    References
    ----------
    Hairer & Wanner (1996), ch. IV.2 (stability function of explicit RK
    methods) and IV.1 (stiffness ratio).
    """
    model = _as_model(model)
    th = result.theta if theta is None else _vector(model, theta, "theta")
    n = result.t.size
    every = int(every) if every else max(1, int(math.ceil(n / max_samples)))
    idx = np.arange(0, n, every)
    J = np.asarray(model.dfdx(result.x[idx], result.u[idx], th), dtype=float)
    lam = np.linalg.eigvals(J) if model.n_x else np.zeros((idx.size, 0), complex)
    dts = np.diff(result.t)
    samples, growing = [], 0
    for k, i in enumerate(idx):
        sample, n_grow = _sample_stiffness(float(result.t[i]), lam[k],
                                           float(dts[min(i, dts.size - 1)]))
        samples.append(sample)
        growing = max(growing, n_grow)
    worst = max(samples, key=lambda r: r["max_abs_re"])  # the first of equal maxima
    report = {
        "model": model.name,
        "method": result.method,
        "every": every,
        "n_checked": int(idx.size),
        "dt": float(np.median(dts)),
        "max_abs_re": worst["max_abs_re"],
        "t_max_abs_re": worst["t"],
        "stiffness_ratio": max([0.0] + [r["stiffness_ratio"] for r in samples]),
        "rk4_stable_step": min([math.inf] + [r["rk4_stable_step"] for r in samples]),
        "rk4_substeps_needed": max([1] + [r["rk4_substeps"] for r in samples]),
        "n_growing_modes": growing,
        "samples": samples,
    }
    return report, _stiffness_table(report)


def _sample_stiffness(t: float, ev: np.ndarray, dt: float) -> tuple[dict, int]:
    """Stiffness figures at one sample from the eigenvalues ``ev`` (n_x,) of
    ``df/dx`` and the sample interval ``dt`` [s]: the sample's report entry and
    its number of growing modes (Re λ > 0)."""
    re = ev.real
    scale = np.abs(ev).max() if ev.size else 0.0
    decaying = re[re < -1e-12 * max(scale, 1e-300)]
    max_abs = float(np.abs(re).max()) if ev.size else 0.0
    ratio = float(np.abs(decaying).max() / np.abs(decaying).min()) if decaying.size else 1.0
    h = integrators.rk4_stable_step(ev)
    sub = int(math.ceil(dt / h - 1e-12)) if np.isfinite(h) and h > 0 else 1
    sample = {
        "t": t,
        "eigenvalues": [[float(z.real), float(z.imag)] for z in sorted(ev, key=lambda z: z.real)],
        "max_abs_re": max_abs,
        "stiffness_ratio": ratio,
        "rk4_stable_step": float(h),
        "rk4_substeps": max(sub, 1),
    }
    return sample, int(np.sum(re > 1e-12 * max(scale, 1e-300)))


def _stiffness_table(rep: dict, rows: int = 12) -> str:
    s = rep["samples"]
    h = rep["rk4_stable_step"]
    lines = [
        f"Stiffness of {rep['model']} along the trajectory ({rep['n_checked']} samples, "
        f"every {rep['every']}; dt = {rep['dt']:.6g} s)",
        f"  max |Re λ| = {rep['max_abs_re']:.6g} 1/s at t = {rep['t_max_abs_re']:.6g} s; "
        f"stiffness ratio up to {rep['stiffness_ratio']:.4g}",
        f"  largest stable RK4 step {h:.6g} s -> "
        f"RK4 needs >= {rep['rk4_substeps_needed']} substeps per sample",
    ]
    if rep["n_growing_modes"]:
        lines.append(f"  note: up to {rep['n_growing_modes']} growing mode(s) (Re λ > 0)")
    lines.append(f"  {'t [s]':>10} {'max|Re λ| [1/s]':>16} {'ratio':>10} {'h_RK4 [s]':>11} "
                 f"{'substeps':>8}  eigenvalues")
    pick = np.unique(np.concatenate([np.linspace(0, len(s) - 1, min(rows, len(s))).astype(int),
                                     [int(np.argmax([r['max_abs_re'] for r in s]))]]))
    for i in pick:
        r = s[i]
        ev = ", ".join(f"{re:.4g}{im:+.4g}j" if im else f"{re:.4g}" for re, im in r["eigenvalues"])
        lines.append(f"  {r['t']:>10.4g} {r['max_abs_re']:>16.6g} "
                     f"{r['stiffness_ratio']:>10.4g} "
                     f"{r['rk4_stable_step']:>11.4g} {r['rk4_substeps']:>8d}"
                     f"  {ev}")
    return "\n".join(lines)
