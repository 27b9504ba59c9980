"""A record as the estimation and the analyses see it: arrays in a model's
units, and the initial state by the toolkit's one rule
(:meth:`bondgraph.data.records.Experiment.initial_state`)."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from bondgraph.data.records import Experiment
from bondgraph.errors import ModelError
from bondgraph.inference.prior import RULE_GIVEN, RULE_MODEL, RULE_RECORD, PriorSpec

__all__ = ["RULE_GIVEN", "RULE_MODEL", "RULE_RECORD", "as_record", "initial_state",
           "record_arrays", "state_vector"]



def as_record(experiment):
    """An :class:`~bondgraph.data.records.Experiment` for a CSV path (loaded),
    float arrays for a tuple ``(t, u, y)``, anything else as it is.

    Raises
    ------
    DataError
        A CSV that cannot be read (:meth:`Experiment.load`).
    """
    if isinstance(experiment, tuple):
        t, u, y = experiment
        return np.asarray(t, float), np.asarray(u, float), np.asarray(y, float)
    if isinstance(experiment, (str, Path)):
        return Experiment.load(experiment)
    return experiment


def record_arrays(model, experiment) -> tuple[np.ndarray, np.ndarray, np.ndarray, str, dict]:
    """``(t, u, y, name, meta)`` of a record for a model.

    Parameters
    ----------
    model : Model
    experiment : Experiment, str/Path of a CSV, or tuple ``(t, u, y)``

    Raises
    ------
    DataError
        Via :meth:`bondgraph.data.records.Experiment.load` / ``inputs_for`` /
        ``outputs_for``.
    """
    rec = as_record(experiment)
    if isinstance(rec, tuple):
        return rec + ("arrays", {})
    t = np.asarray(rec.t, dtype=float)
    return t, rec.inputs_for(model), rec.outputs_for(model), rec.name, dict(rec.meta or {})


def state_vector(model, x0) -> np.ndarray:
    """A state vector (n_x,) from an array, or from a dict of named values
    overriding the model's X0.

    Raises
    ------
    ModelError
        Unknown state names or a wrong length.
    """
    if isinstance(x0, Mapping):
        return model.state(dict(x0))
    arr = np.asarray(x0, dtype=float).reshape(-1)
    if arr.shape != (model.n_x,):
        raise ModelError(f"x0 has shape {np.shape(x0)}; model '{model.name}' expects "
                         f"({model.n_x},) for {', '.join(model.states)}")
    return arr.copy()


def initial_state(model, experiment, x0=None) -> tuple[np.ndarray, str]:
    """The initial state of an estimation or analysis on a record: the one
    rule, :meth:`bondgraph.inference.prior.PriorSpec.mean`.

    ``x0`` if given (array or dict of named overrides of X0); else the
    record's rule, :meth:`bondgraph.data.records.Experiment.initial_state`
    (state columns, else the sidecar's x0, else the model's X0); for bare
    arrays ``(t, u, y)``, the model's X0.

    Returns
    -------
    (x0 (n_x,), rule)
        ``rule`` is :data:`RULE_GIVEN`, :data:`RULE_RECORD` or :data:`RULE_MODEL`.
    """
    spec = PriorSpec(x0=None if x0 is None else state_vector(model, x0))
    rec = as_record(experiment)
    return spec.mean(model, None if isinstance(rec, tuple) else rec)
