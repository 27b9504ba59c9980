"""Synthetic experiments: what to simulate, with which inputs, truth and noise.

An :class:`ExperimentSpec` names a model (the filter model whose outputs are
recorded), optionally a different *truth* model to simulate (e.g. a graph
with an effect the filter model lacks), input signals as vectorised
functions of time, initial state, true parameter overrides, noise and seed.
Specs are registered like models (:mod:`bondgraph.core.plugins`, kind
``experiments``): the toolkit's reference experiments are in
:mod:`bondgraph.catalog.reference`, the vehicle's in ``vehicle_graphs``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from bondgraph.core import plugins
from bondgraph.core.augment import SCHEDULE_PREFIX, scheduled
from bondgraph.data.binding import STATE_PREFIX
from bondgraph.data.records import Experiment
from bondgraph.errors import ModelError
from bondgraph.numerics import registry
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import InputSignals, simulate


@dataclass
class ExperimentSpec:
    """A synthetic experiment.

    Parameters
    ----------
    name : str
    model : str
        Registered model whose inputs/outputs define the record's columns.
    duration : float
        Record length [s].
    dt : float
        Sample interval [s] (0.025 s = 40 Hz for the vehicle).
    inputs : dict of str -> callable
        Input name -> vectorised function of time ``t (N,) -> (N,)`` in the
        model's input units; inputs not given take the model default.
    x0 : dict of str -> float
        Initial state overrides (model units).
    params : dict of str -> float
        True parameter values (overrides of the truth model's defaults).
    noise_std : dict of str -> float, optional
        Measurement-noise standard deviation per output (default: the
        model's ``meas_std`` at the true parameters).
    seed : int
        Seed of the noise generator.
    description : str
    truth_model : str, optional
        Model to simulate instead of ``model`` (it must have the same
        output names).
    schedules : dict of str -> callable, optional
        Parameters of the truth model that change during the record:
        parameter name -> vectorised function of time ``t (N,) -> (N,)`` in
        the parameter's unit (e.g. :func:`step`, :func:`ramp`). The truth
        model is simulated with each such parameter as the input
        ``true.<p>`` (:func:`bondgraph.core.augment.scheduled`), and the
        record keeps it as the column ``true.<p>`` (role ``other``): the
        truth as a time series. A scheduled parameter may not also be given
        in ``params``.

    ``model`` and ``truth_model`` are registered model names, or graph
    builders ``module:function`` / ``path/to/file.py:function`` (derived
    and generated in memory).
    """

    name: str
    model: str
    duration: float
    dt: float = 0.025
    inputs: dict[str, Callable[[np.ndarray], np.ndarray]] = field(default_factory=dict)
    x0: dict[str, float] = field(default_factory=dict)
    params: dict[str, float] = field(default_factory=dict)
    noise_std: dict[str, float] | None = None
    seed: int = 0
    description: str = ""
    truth_model: str | None = None
    schedules: dict[str, Callable[[np.ndarray], np.ndarray]] = field(default_factory=dict)


# ---------------------------------------------------------------- registry
def registered_experiments() -> dict[str, str]:
    """All registered experiments, ``name -> "module:function"``.

    Raises
    ------
    ModelError
        If a name is registered twice with different targets.
    """
    return plugins.registered("experiments")


def get_experiment(name: str) -> ExperimentSpec:
    """The :class:`ExperimentSpec` of a registered experiment.

    Raises
    ------
    ModelError
        Unknown name (the message lists the registered ones), or a
        registered function that does not return a spec of that name.
    """
    reg = registered_experiments()
    if name not in reg:
        raise ModelError(f"unknown experiment '{name}' (registered: "
                         f"{', '.join(sorted(reg)) or 'none'})")
    spec = plugins.resolve(reg[name])()
    if not isinstance(spec, ExperimentSpec):
        raise ModelError(f"{reg[name]} returned {type(spec).__name__}, not an ExperimentSpec")
    if spec.name != name:
        raise ModelError(f"{reg[name]} is registered as '{name}' but its spec is named "
                         f"'{spec.name}'")
    return spec


# ------------------------------------------------------------------ running
def sample_times(spec: ExperimentSpec) -> np.ndarray:
    """The sample grid of a spec: ``k * dt`` for k = 0 .. round(duration/dt)."""
    if not (spec.dt > 0 and spec.duration > 0):
        raise ModelError(f"experiment '{spec.name}': dt ({spec.dt}) and duration "
                         f"({spec.duration}) must be positive")
    n = int(round(spec.duration / spec.dt)) + 1
    return np.arange(n) * spec.dt


def run_experiment(spec: ExperimentSpec | str, *, method: str = "BDF", rtol: float = 1e-8,
                   atol: float = 1e-10, max_step: float | None = None):
    """Simulate a synthetic experiment and return the noisy record.

    The truth model (``spec.truth_model`` or ``spec.model``) is simulated at
    the true parameters (its defaults overridden by ``spec.params``) from
    ``spec.x0`` with the input callables, by a stiff-safe adaptive solver
    (BDF with the generated Jacobian by default); callables are evaluated at
    the exact solver times. The record is sampled every ``dt``. Gaussian,
    independent, zero-mean noise from ``numpy.random.default_rng(seed)`` is
    added to the outputs of ``spec.model``; its standard deviation is
    ``spec.noise_std[name]`` or, for outputs not listed, the filter model's
    ``meas_std`` at the true parameters.

    Columns: every input of the filter and truth models (including the
    ``der(.)`` inputs, as used by the simulation), the noisy outputs of
    ``spec.model``, and the truth states as ``state.<name>``.

    Parameters
    ----------
    spec : ExperimentSpec or str
        A spec or a registered experiment name.
    method : str
        Solver of :func:`bondgraph.numerics.simulate.simulate` (``BDF``, ``Radau``,
        ``LSODA``, ...).
    rtol, atol, max_step
        Solver settings.

    Returns
    -------
    Experiment
        ``meta`` holds ``name, model, truth_model, description, dt,
        duration, true_parameters`` (all truth parameters by name), ``x0``
        (all truth states), ``noise`` (``{distribution, std}``), ``seed``,
        ``method``; the output columns carry ``noise_std``.

    Raises
    ------
    ModelError
        Unknown models, inputs, parameters, states or noise entries, or a
        truth model lacking an output of ``spec.model``.
    NumericalError
        If the simulation diverges.
    """
    if isinstance(spec, str):
        spec = get_experiment(spec)
    filt, truth = _spec_models(spec)
    ctx = f"experiment '{spec.name}'"
    try:
        theta = truth.theta(spec.params)
        x0 = truth.state(spec.x0)
    except ModelError as exc:
        raise ModelError(f"{ctx}: {exc}") from None
    t = sample_times(spec)
    u_truth = {k: fn for k, fn in spec.inputs.items() if k in truth.inputs}
    u_truth.update({SCHEDULE_PREFIX + k: fn for k, fn in spec.schedules.items()})
    sim = simulate(truth, t, u=u_truth, x0=x0, theta=theta, method=method, rtol=rtol,
                   atol=atol, max_step=max_step)
    std = _noise_std(spec, filt)
    y = _noisy_outputs(spec, filt, sim, std)
    columns, units, roles = _record_columns(spec, filt, truth, sim, y)
    noise = {name: float(std[j]) for j, name in enumerate(filt.outputs)}
    meta = {
        "name": spec.name,
        "model": filt.name,
        "truth_model": truth.name,
        "description": spec.description,
        "dt": float(spec.dt),
        "duration": float(t[-1]),
        "true_parameters": {p: float(v) for p, v in zip(truth.params, theta)},
        "schedules": {p: SCHEDULE_PREFIX + p for p in spec.schedules},
        "x0": {s: float(v) for s, v in zip(truth.states, x0)},
        "noise": {"distribution": "gaussian", "independent": True, "mean": 0.0, "std": noise},
        "seed": int(spec.seed),
        "method": method,
        "generator": "bondgraph.data.experiments.run_experiment",
    }
    return Experiment.from_arrays(t, columns, units=units, roles=roles, noise_std=noise,
                                  meta=meta)


def _spec_models(spec: ExperimentSpec) -> tuple[Model, Model]:
    """The filter model and the truth model of a spec, checked against each
    other: every given input belongs to one of them, the truth model has every
    output of the filter model."""
    ctx = f"experiment '{spec.name}'"
    filt = Model.from_spec(spec.model)
    truth = Model.from_spec(spec.truth_model) if spec.truth_model and not spec.schedules else filt
    if spec.schedules:       # the truth is derived once, with its parameters as inputs
        both = sorted(set(spec.schedules) & set(spec.params))
        if both:
            raise ModelError(f"{ctx}: {', '.join(both)} given both in params and in "
                             f"schedules (a scheduled parameter's values are its schedule)")
        graph = registry.graph_builder(spec.truth_model or spec.model)()
        try:
            truth = Model.from_graph(scheduled(graph, list(spec.schedules)))
        except ModelError as exc:
            raise ModelError(f"{ctx}: {exc}") from None
    unknown = [k for k in spec.inputs if k not in truth.inputs and k not in filt.inputs]
    if unknown:
        raise ModelError(f"{ctx}: inputs {', '.join(unknown)} are not inputs of "
                         f"'{truth.name}' ({', '.join(truth.inputs)})")
    lacking = [y for y in filt.outputs if y not in truth.outputs]
    if lacking:
        raise ModelError(f"{ctx}: truth model '{truth.name}' lacks outputs "
                         f"{', '.join(lacking)} of '{filt.name}'")
    return filt, truth


def _noise_std(spec: ExperimentSpec, filt: Model) -> np.ndarray:
    """Noise standard deviation per filter-model output (n_y,): ``spec.noise_std``,
    else the model's ``meas_std`` at the true parameters."""
    ctx = f"experiment '{spec.name}'"
    theta_f = filt.theta({k: v for k, v in spec.params.items() if k in filt.params})
    std = np.asarray(filt.meas_std(theta_f), dtype=float).reshape(-1) if filt.n_y else np.zeros(0)
    for k, v in (spec.noise_std or {}).items():
        if k not in filt.outputs:
            raise ModelError(f"{ctx}: noise_std given for '{k}', which is not an output of "
                             f"'{filt.name}' ({', '.join(filt.outputs)})")
        if not (np.isfinite(v) and v >= 0):
            raise ModelError(f"{ctx}: noise_std['{k}'] = {v!r} must be finite and >= 0")
        std[filt.output_index(k)] = float(v)
    return std


def _noisy_outputs(spec: ExperimentSpec, filt: Model, sim, std: np.ndarray) -> np.ndarray:
    """The filter model's outputs (N, n_y) from the truth simulation plus
    independent Gaussian noise of standard deviation ``std`` (n_y,), drawn from
    ``numpy.random.default_rng(spec.seed)``."""
    rng = np.random.default_rng(spec.seed)
    n = sim.t.size
    y_true = np.column_stack([sim.output(k) for k in filt.outputs]) if filt.n_y else \
        np.zeros((n, 0))
    return y_true + rng.standard_normal((n, filt.n_y)) * std


def _record_columns(spec: ExperimentSpec, filt: Model, truth: Model, sim,
                    y: np.ndarray) -> tuple[dict, dict, dict]:
    """Columns, units and roles of the record: the inputs of both models (as
    simulated; an input only the filter model has from its callable or
    default), the noisy outputs ``y (N, n_y)``, the truth states."""
    columns, units, roles = {}, {}, {}
    for mdl in (filt, truth):
        fsig = None
        for j, name in enumerate(mdl.inputs):
            if name in columns:
                continue
            if name in truth.inputs:
                vals = sim.input(name)
            else:  # an input only the filter model has
                if fsig is None:
                    fsig = InputSignals(filt, sim.t, {k: v for k, v in spec.inputs.items()
                                                      if k in filt.inputs})
                vals = fsig.samples[:, j]
            columns[name] = vals
            units[name] = mdl.input_units[j] or None
            roles[name] = "other" if name[len(SCHEDULE_PREFIX):] in spec.schedules \
                and name.startswith(SCHEDULE_PREFIX) else "input"
    for j, name in enumerate(filt.outputs):
        columns[name] = y[:, j]
        units[name] = filt.output_units[j] or None
        roles[name] = "output"
    for j, name in enumerate(truth.states):
        columns[STATE_PREFIX + name] = sim.x[:, j]
        units[STATE_PREFIX + name] = truth.state_units[j] or None
        roles[STATE_PREFIX + name] = "state"
    return columns, units, roles


# ------------------------------------------------- reference experiments
def step(t0: float, value: float, before: float = 0.0) -> Callable[[np.ndarray], np.ndarray]:
    """Vectorised step ``before`` for t < t0, ``value`` from t0 on."""
    return lambda t: np.where(np.asarray(t) >= t0, value, before)


def ramp(t0: float, t1: float, v0: float, v1: float) -> Callable[[np.ndarray], np.ndarray]:
    """Vectorised ramp: ``v0`` before ``t0``, linear to ``v1`` at ``t1``, then ``v1``."""
    return lambda t: np.interp(t, [t0, t1], [v0, v1])
