"""Synthetic experiments: what to simulate, with which inputs, truth and noise.

An :class:`ExperimentSpec` names a model (the filter model whose outputs are
recorded), optionally a different *truth* model to simulate (e.g. a graph
with an effect the filter model lacks), input signals as vectorised
functions of time, initial state, true parameter overrides, noise and seed.
Registered specs live in the ``EXPERIMENTS`` dicts (``name ->
"module:function"``) of the modules in :data:`EXPERIMENT_MODULES`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

#: modules whose ``EXPERIMENTS`` dict is registered (missing modules skipped)
EXPERIMENT_MODULES: tuple[str, ...] = ("bondgraph.experiments", "vehicle_graphs")


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
        Registered model to simulate instead of ``model`` (it must have the
        same output names).
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
