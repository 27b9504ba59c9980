"""The prior of the initial state: its mean and a covariance that follows
each state's own scale.

The spread of a state's prior is relative to that state's scale along the
record, not to ``max(|x0|, 1)``: a small momentum (0.002 kg m/s) next to a
large one (26 000 kg m/s) gets its own spread. The scale of state i is, in
this order (:func:`state_scales`):

1. its deterministic scale, the RMS of the state along a free-run
   simulation of the model with the record's inputs from the prior mean
   (fixed-step, the filter's discretisation), or ``|x0_i|`` if larger;
2. where that is 0 (a state nothing drives, e.g. a road grade that only
   process noise moves): the spread a random walk of the state's process
   noise reaches over the record, ``proc_std_i · sqrt(duration)``;
3. where that is 0 too: the scale the sensors give, std(y_j) / |∂h_j/∂x_i|
   at the prior mean, over the outputs that see the state;
4. else a tiny absolute floor (the state is neither driven nor seen).

The prior covariance (:func:`prior_covariance`) is diagonal with
``(rel · scale_i)²``, except where the record declares a spread: a
sidecar's ``x0_std`` (by state name) is the standard deviation of that
state's prior, its ``x0`` the mean (:meth:`bondgraph.data.records.Experiment.initial_state`).
A state whose initial value nothing gives (no state column, no sidecar
``x0``/``x0_std``, no user value: its mean is the model's X0, a guess) gets
the spread of its whole scale, ``UNKNOWN_REL · scale_i``: the filter then
learns it from the data instead of trusting the guess, and the RTS-smoothed
initial state (:mod:`bondgraph.inference.smoother`) estimates it.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from bondgraph.errors import ModelError, OptionError
from bondgraph.inference import sim_numba, ukf_numba
from bondgraph.inference.options import DEFAULT_BACKEND
from bondgraph.numerics import compiled
from bondgraph.numerics.integrators import hold_inputs, make_step

#: at most this many samples of the record are simulated for the scales
SCALE_SAMPLES = 20000
#: floor of a scale no rule could set (a state neither driven nor seen)
SCALE_FLOOR = 1e-9
#: prior std of an initial state nothing gives, relative to its scale
UNKNOWN_REL = 1.0
#: estimated seconds of one numpy step (one sub-step of one sample) of the
#: free run (batch of one point: Python overhead; for the break-even rule
#: of :func:`bondgraph.numerics.compiled.compile_pays`)
NUMPY_S_PER_STEP = 2e-4


def simulated_rms(model, t, u, theta, x0, *, method: str = "ros2", substeps: int = 2,
                  hold: str = "zoh", samples: int = SCALE_SAMPLES,
                  backend: str = DEFAULT_BACKEND) -> np.ndarray:
    """RMS of every state along a fixed-step free run from ``x0`` with the
    record's inputs (the first ``samples`` samples; up to the first
    non-finite state if the run diverges, or up to a singular ROS2 matrix
    I − γhJ).

    Parameters
    ----------
    model : Model
    t : array (N,)
    u : array (N, n_u)
    theta : array (n_theta,)
    x0 : array (n_x,)
    method, substeps, hold :
        The discretisation (:func:`bondgraph.numerics.integrators.make_step`,
        :func:`~bondgraph.numerics.integrators.hold_inputs`).
    backend : {"numba", "numpy"}
        numba: the compiled free run (:func:`bondgraph.inference.sim_numba.free_run_rms`,
        the same steps, values equal to rounding) where the model's kernels
        are compiled or compiling pays (:func:`bondgraph.numerics.compiled.compile_pays`);
        else the numpy steps, sample by sample.

    Returns
    -------
    ndarray (n_x,)
        0 where nothing finite was simulated.
    """
    n = min(int(np.size(t)), int(samples))
    t = np.asarray(t, float)[:n]
    u = np.asarray(u, float).reshape(np.size(t), -1) if model.n_u else np.zeros((n, 0))
    u = u[:n]
    numpy_s = n * substeps * NUMPY_S_PER_STEP
    kernels = _free_run_kernels(model, backend, method, hold, numpy_s)
    if kernels is not None:
        return sim_numba.free_run_rms(kernels, t, u, hold, theta, x0, method, substeps)
    held = hold_inputs(u, hold)
    step = make_step(model, method, substeps)
    th = np.asarray(theta, float)[None, :]
    x = np.asarray(x0, float)[None, :].copy()
    acc, count = np.zeros(model.n_x), 0
    with np.errstate(all="ignore"):
        for k in range(n):
            if not np.isfinite(x).all():
                break
            acc += x[0] ** 2
            count += 1
            if k < n - 1:
                uk, duk = held.interval(k)
                try:
                    x = step(x, uk, th, t[k + 1] - t[k], duk)
                except np.linalg.LinAlgError:    # a singular ROS2 matrix: the run ends here
                    break
    if hasattr(model, "numpy_seconds"):      # the estimate, not the clock (numpy_estimate)
        model.numpy_seconds += numpy_s
    return np.sqrt(acc / count) if count else np.zeros(model.n_x)


def _free_run_kernels(model, backend: str, method: str, hold: str, numpy_s: float):
    """The model's compiled point kernels for the free run, or None (numpy):
    backend numpy, numba missing, a method or hold the kernel lacks, an
    in-memory model whose compilation does not pay yet (``numpy_s``: the
    estimated numpy time of this run), or kernels that do not load."""
    if (backend != "numba" or not compiled.NUMBA_AVAILABLE
            or method not in ukf_numba.METHOD_CODES or hold not in ukf_numba.HOLD_CODES
            or not hasattr(model, "module") or not compiled.compile_pays(model, numpy_s)):
        return None
    try:
        return compiled.point_kernels(model)
    except Exception:  # no kernels for this model, or numba cannot compile them
        return None


def sensor_scales(model, u, y, theta, x0) -> np.ndarray:
    """Scale of each state as the sensors see it: min over the outputs j
    with ∂h_j/∂x_i ≠ 0 at the prior mean of std(y_j) / |∂h_j/∂x_i|; 0 for
    states no sensor sees.

    Parameters
    ----------
    u : array (N, n_u)
    y : array (N, n_y)
        Measured outputs (NaN where missing).
    """
    if not hasattr(model, "dhdx"):
        return np.zeros(model.n_x)
    th = np.asarray(theta, float)[None, :]
    u0 = np.asarray(u, float)[:1] if model.n_u else np.zeros((1, 0))
    with np.errstate(all="ignore"):
        H = np.asarray(model.dhdx(np.asarray(x0, float)[None, :], u0, th))[0]   # (n_y, n_x)
        sd = np.nanstd(np.asarray(y, float), axis=0)
    out = np.zeros(model.n_x)
    for i in range(model.n_x):
        g = np.abs(H[:, i])
        ok = np.isfinite(g) & (g > 0) & np.isfinite(sd) & (sd > 0)
        if ok.any():
            out[i] = float(np.min(sd[ok] / g[ok]))
    return out


def state_scales(model, t, u, y, theta, x0, *, method: str = "ros2", substeps: int = 2,
                 hold: str = "zoh", backend: str = DEFAULT_BACKEND) -> tuple[np.ndarray, list[str]]:
    """The scale of every state along the record (module docstring, rules 1-4).

    Parameters
    ----------
    model : Model
    t, u, y : arrays (N,), (N, n_u), (N, n_y)
        The record (y: NaN where missing).
    theta : array (n_theta,)
    x0 : array (n_x,)
        Prior mean.
    method, substeps, hold :
        Discretisation of the free run.
    backend : {"numba", "numpy"}
        Of the free run (:func:`simulated_rms`).

    Returns
    -------
    (scales (n_x,), rules)
        ``rules[i]`` names the rule that set state i: "simulation",
        "process noise", "sensors" or "floor".
    """
    x0 = np.asarray(x0, float)
    theta = np.asarray(theta, float)
    scale = np.maximum(simulated_rms(model, t, u, theta, x0, method=method, substeps=substeps,
                                     hold=hold, backend=backend), np.abs(x0))
    rules = ["simulation" if s > 0 and np.isfinite(s) else "" for s in scale]
    scale = np.where(np.isfinite(scale), scale, 0.0)
    duration = float(np.asarray(t, float)[-1] - np.asarray(t, float)[0]) if np.size(t) > 1 else 1.0
    with np.errstate(all="ignore"):
        q = np.asarray(model.proc_std(theta[None, :]), float)[0]
    walk = np.where(np.isfinite(q), np.abs(q), 0.0) * np.sqrt(max(duration, 0.0))
    sens = None
    for i in range(model.n_x):
        if rules[i]:
            continue
        if walk[i] > 0:
            scale[i], rules[i] = walk[i], "process noise"
            continue
        if sens is None:
            sens = sensor_scales(model, u, y, theta, x0)
        if sens[i] > 0:
            scale[i], rules[i] = sens[i], "sensors"
        else:
            scale[i], rules[i] = SCALE_FLOOR, "floor"
    return scale, rules


def declared_std(model, x0_std: Mapping[str, float] | None) -> np.ndarray:
    """The declared prior standard deviations (n_x,), NaN where none is declared.

    Raises
    ------
    ModelError
        A state the model does not have.
    OptionError
        A negative or non-finite spread.
    """
    out = np.full(model.n_x, np.nan)
    for name, sd in (x0_std or {}).items():
        i = model.state_index(name)
        sd = float(sd)
        if not np.isfinite(sd) or sd < 0:
            raise OptionError(f"x0_std of state '{name}' must be a finite number >= 0, got {sd!r}")
        out[i] = sd
    return out


def prior_covariance(model, scales: np.ndarray, *, rel: float = 0.05,
                     x0_std: Mapping[str, float] | None = None,
                     unknown: Sequence[str] = ()) -> np.ndarray:
    """The prior covariance (n_x, n_x) of the initial state: diagonal,
    ``(rel · scale_i)²``, ``(UNKNOWN_REL · scale_i)²`` for the states in
    ``unknown``, with the declared spreads ``x0_std`` (name -> std) imposed.

    Parameters
    ----------
    model : Model
    scales : array (n_x,)
        :func:`state_scales`.
    rel : float
        Relative spread (> 0).
    x0_std : dict, optional
        Declared prior standard deviations by state name (a sidecar's
        ``x0_std``, a user's option).
    unknown : sequence of str
        States whose initial value nothing gives (their mean is a guess).

    Raises
    ------
    OptionError
        ``rel`` not positive, or wrong shape of ``scales``.
    ModelError
        Unknown state names in ``x0_std``.
    """
    if not (np.isfinite(rel) and rel > 0):
        raise OptionError(f"the relative prior spread must be > 0, got {rel!r}")
    scales = np.asarray(scales, float)
    if scales.shape != (model.n_x,):
        raise OptionError(f"state scales have shape {scales.shape}, expected ({model.n_x},)")
    sd = rel * scales
    for name in unknown:
        i = model.state_index(name)
        sd[i] = UNKNOWN_REL * scales[i]
    dec = declared_std(model, x0_std)
    sd = np.where(np.isfinite(dec), dec, sd)
    return np.diag(sd ** 2)


def record_prior(model, t, u, y, theta, x0, *, rel: float = 0.05,
                 x0_std: Mapping[str, float] | None = None, method: str = "ros2",
                 substeps: int = 2, hold: str = "zoh",
                 unknown: Sequence[str] = (),
                 backend: str = DEFAULT_BACKEND) -> tuple[np.ndarray, dict]:
    """:func:`prior_covariance` with the scales of :func:`state_scales`
    (``unknown``: the states whose initial value nothing gives; ``backend``:
    of the free run, :func:`simulated_rms`).

    Returns
    -------
    (P0 (n_x, n_x), info)
        ``info``: ``scales`` and ``rules`` by state name, ``rel``, ``unknown``.
    """
    if np.shape(x0) != (model.n_x,):
        raise ModelError(f"x0 has shape {np.shape(x0)}, expected ({model.n_x},)")
    scales, rules = state_scales(model, t, u, y, theta, x0, method=method, substeps=substeps,
                                 hold=hold, backend=backend)
    P0 = prior_covariance(model, scales, rel=rel, x0_std=x0_std, unknown=unknown)
    info = {"rel": float(rel), "scales": dict(zip(model.states, scales.tolist())),
            "unknown": list(unknown),
            "rules": dict(zip(model.states, rules)),
            "declared_std": {k: float(v) for k, v in (x0_std or {}).items()}}
    return P0, info
