"""Binding a record to a model: its columns as the model's input and output
arrays, its initial state and noise levels, in the model's units.

Columns are matched to a model's inputs, outputs and states by name (states
as ``state.<name>``, :data:`STATE_PREFIX`) and converted from the record's
units to the model's with pint (:func:`convert`). Every function takes the
record (an :class:`~bondgraph.data.records.Experiment`) first; the
Experiment methods of the same names call them.
"""

from __future__ import annotations

import difflib
import warnings
from typing import Mapping

import numpy as np

from bondgraph.core import units as _units
from bondgraph.errors import ColumnWarning, DataError, UnitMismatchError, join_names
from bondgraph.numerics.model import Model

#: prefix of state columns (``state.p_mass``), so states never collide with
#: input or output names
STATE_PREFIX = "state."


def convert(values: np.ndarray, from_unit: str | None, to_unit: str | None, *,
            path: str | None = None, column: str | None = None,
            what: str = "column") -> np.ndarray:
    """Convert ``values`` from ``from_unit`` to ``to_unit`` with pint.

    Offset units (``degC``) are converted properly (pint quantities), not by
    a factor. ``from_unit=None`` (unspecified) returns the values unchanged.

    Parameters
    ----------
    values : array
    from_unit, to_unit : str or None
        Unit strings pint understands (``None`` or ``""`` as ``to_unit``:
        dimensionless).
    path, column : str, optional
        File and column named in errors.
    what : str
        What is converted, for the error of a unit of another dimension.

    Returns
    -------
    ndarray
        Float values in ``to_unit`` (``values`` itself where nothing changes).

    Raises
    ------
    DataError
        Unknown unit or a unit of another dimension (line 1, the column).
    """
    values = np.asarray(values, dtype=float)
    if from_unit is None:
        return values
    to_unit = to_unit or ""
    try:
        q_from = _units.parse(from_unit)
    except UnitMismatchError as exc:
        raise DataError(str(exc), path=path, line=1, column=column) from None
    try:
        q_to = _units.parse(to_unit)
    except UnitMismatchError:
        raise DataError(f"unknown target unit '{to_unit}'", path=path, line=1,
                        column=column) from None
    if q_from.dimensionality != q_to.dimensionality:
        raise DataError(
            f"unit '{from_unit}' ({q_from.dimensionality}) cannot be converted to "
            f"'{to_unit or '1'}' ({q_to.dimensionality}) for {what}",
            path=path, line=1, column=column,
            hint="if the record's unit text means another unit (a logger's abbreviation "
                 "that pint reads otherwise), give the unit where the column is renamed: "
                 "--columns COLUMN=NAME[UNIT] (Python: columns={'COLUMN': 'NAME [UNIT]'})")
    ureg = _units.registry()
    try:
        if q_from._ok_for_muldiv() and q_to._ok_for_muldiv():
            fac = float(q_from.to(q_to.units).magnitude) / float(q_to.magnitude)
            return values if fac == 1.0 else values * fac
        out = ureg.Quantity(values * q_from.magnitude, q_from.units).to(q_to.units).magnitude
        return np.asarray(out, dtype=float) / float(q_to.magnitude)
    except Exception as exc:  # pint raises several types
        raise DataError(f"cannot convert '{from_unit}' to '{to_unit}': {exc}", path=path,
                        line=1, column=column) from None


def _as_model(model):
    """``model``, loaded by name if it is a string."""
    if isinstance(model, str):
        return Model.load(model)
    return model


def initial_state(exp, model) -> np.ndarray:
    """The initial state of the record ``exp`` for ``model``: the first finite value
    of each ``state.<name>`` column, else the sidecar's ``x0[name]``, for the
    states the model has; the model's X0 for the others.

    This is the one initial-state rule of the toolkit (estimation,
    sensitivity and the loop use it).

    Parameters
    ----------
    exp : Experiment
        The record.
    model : Model
        Anything with ``states`` (names) and ``x0`` (n_x,).

    Returns
    -------
    ndarray (n_x,)
    """
    x0 = np.array(model.x0, dtype=float)
    cols = exp.states()
    meta_x0 = (exp.meta or {}).get("x0") or {}
    for i, name in enumerate(model.states):
        if name in cols and np.isfinite(cols[name][0]):
            x0[i] = float(cols[name][0])
        elif isinstance(meta_x0, Mapping) and name in meta_x0:
            x0[i] = float(meta_x0[name])
    return x0


def given_initial_states(exp, model) -> list[str]:
    """The states of ``model`` whose initial value the record ``exp`` gives:
    a finite first value of its ``state.<name>`` column, the sidecar's
    ``x0[name]`` or ``x0_std[name]``. For the others
    :func:`initial_state` falls back to the model's X0, a guess: the
    prior of such a state is wide (:mod:`bondgraph.inference.prior`).

    Parameters
    ----------
    exp : Experiment
        The record.
    model : Model
        Anything with ``states`` (names).

    Returns
    -------
    list of str
        In the model's state order.
    """
    cols = exp.states()
    meta = exp.meta or {}
    x0 = meta.get("x0") if isinstance(meta.get("x0"), Mapping) else {}
    std = meta.get("x0_std") if isinstance(meta.get("x0_std"), Mapping) else {}
    return [n for n in model.states
            if (n in cols and np.isfinite(cols[n][0])) or n in x0 or n in std]


def initial_state_std(exp, model) -> dict[str, float]:
    """The declared spread of the initial state: the sidecar's ``x0_std``
    (state name -> standard deviation of the prior whose mean is
    :func:`initial_state`), for the states ``model`` has.

    Parameters
    ----------
    exp : Experiment
        The record.
    model : Model
        Anything with ``states`` (names).

    Returns
    -------
    dict of str -> float

    Raises
    ------
    DataError
        ``x0_std`` not a mapping of finite numbers >= 0.
    """
    raw = (exp.meta or {}).get("x0_std") or {}
    if not isinstance(raw, Mapping):
        raise DataError("sidecar 'x0_std' must be an object {state: std}",
                        path=str(exp.path) if exp.path else None)
    out = {}
    for name, v in raw.items():
        try:
            sd = float(v)
        except (TypeError, ValueError):
            sd = float("nan")
        if not np.isfinite(sd) or sd < 0:
            raise DataError(f"sidecar x0_std of '{name}' must be a finite number >= 0, "
                            f"got {v!r}", path=str(exp.path) if exp.path else None)
        if name in model.states:
            out[name] = sd
    return out


def missing_inputs(exp, model) -> list[str]:
    """Inputs of ``model`` (not ``der(.)`` ones) that the record ``exp`` lacks.

    Parameters
    ----------
    exp : Experiment
        The record.
    model : Model or str

    Returns
    -------
    list of str
        A ``der(r)`` input the record lacks counts as ``r`` when ``r`` is
        missing too.
    """
    mdl = _as_model(model)
    out = []
    for name in mdl.inputs:
        src = mdl.derivative_inputs.get(name)
        if src is not None:
            if name in exp.columns:
                continue
            name = src
        if name not in exp.columns and name not in out:
            out.append(name)
    return out


def require_inputs(exp, model) -> None:
    """Raise when the record ``exp`` lacks an input of ``model`` (a Model,
    or anything with ``name``, ``inputs`` and ``derivative_inputs``):
    every missing column named, with the remedy.

    Raises
    ------
    DataError
        Line 1, the first missing column.
    """
    missing = missing_inputs(exp, model)
    if missing:
        raise DataError(
            f"missing column(s) {join_names(missing)} needed by model '{model.name}' "
            f"(its inputs: {', '.join(model.inputs)}; the record has: "
            f"{', '.join(exp.columns) or 'no columns'})",
            path=exp._where(), line=1, column=missing[0],
            hint="add the column(s) to the record (a constant input: a column of its value); "
                 "from Python, inputs_for(model, defaults_ok=True) holds them at the model's "
                 "defaults")


def inputs_for(exp, model, defaults_ok: bool = False) -> np.ndarray:
    """Input array for a model, in the model's units.

    Columns are matched to ``model.inputs`` by name and converted from
    the file's units to the model's (pint). A derivative input
    ``der(r)`` (``model.derivative_inputs``) is taken from a ``der(r)``
    column if the record has one, else computed from ``r`` by
    ``numpy.gradient`` (second-order central differences inside, one-sided
    at the ends; non-uniform steps allowed).

    Parameters
    ----------
    exp : Experiment
        The record.
    model : Model or str
    defaults_ok : bool
        If True, an input the record lacks is held at the model default
        (``model.u0``); if False (default) that is a :class:`DataError`.

    Returns
    -------
    ndarray (N, n_u)

    Raises
    ------
    DataError
        Missing columns (all named, unless ``defaults_ok``), NaN/inf in
        an input column (line and column named), unknown units or units
        of the wrong dimension.
    """
    mdl = _as_model(model)
    if not defaults_ok:
        require_inputs(exp, mdl)
    n = len(exp)
    U = np.empty((n, mdl.n_u))
    base: dict[str, np.ndarray] = {}

    def base_value(name: str) -> np.ndarray:
        if name not in base:
            j = mdl.input_index(name)
            if name in exp.columns:
                vals = _input_column(exp, name, mdl.input_units[j], mdl)
            else:
                vals = np.full(n, float(mdl.u0[j]))
            base[name] = vals
        return base[name]

    for j, name in enumerate(mdl.inputs):
        src = mdl.derivative_inputs.get(name)
        if src is None:
            U[:, j] = base_value(name)
        elif name in exp.columns:
            U[:, j] = _input_column(exp, name, mdl.input_units[j], mdl)
        else:
            U[:, j] = np.gradient(base_value(src), exp.t)
    return U


def _input_column(exp, name: str, unit: str, mdl) -> np.ndarray:
    """Input column ``name`` in ``unit``; every sample must be finite."""
    vals = exp.columns[name]
    bad = np.flatnonzero(~np.isfinite(vals))
    if bad.size:
        i = int(bad[0])
        raise DataError(f"input value is {float(vals[i])!r} (at t = {float(exp.t[i])!r}); inputs must "
                        f"be finite at every sample", path=exp._where(),
                        line=exp._line(i), column=name)
    return convert(vals, exp.units.get(name), unit, path=exp._where(), column=name,
                   what=f"input '{name}' of model '{mdl.name}'")


def outputs_for(exp, model) -> np.ndarray:
    """Measurement array for a model, in the model's units.

    Parameters
    ----------
    exp : Experiment
        The record.
    model : Model or str

    Returns
    -------
    ndarray (N, n_y)
        NaN where the record lacks an output column or a sample is
        missing.

    Raises
    ------
    DataError
        If the record has no column for any model output, or a column's
        unit is unknown or of the wrong dimension.
    """
    mdl = _as_model(model)
    n = len(exp)
    Y = np.full((n, mdl.n_y), np.nan)
    found = 0
    for j, name in enumerate(mdl.outputs):
        if name in exp.columns:
            Y[:, j] = convert(exp.columns[name], exp.units.get(name), mdl.output_units[j],
                              path=exp._where(), column=name,
                              what=f"output '{name}' of model '{mdl.name}'")
            found += 1
    if mdl.n_y and not found:
        close = _closest_names(exp, mdl)
        raise DataError(f"the record has no column for any output of model '{mdl.name}' "
                        f"({', '.join(mdl.outputs)}); its columns: "
                        f"{', '.join(exp.columns)}", path=exp._where(), line=1,
                        hint=f"rename the column(s): {close}" if close else None)
    return Y


def unmatched_columns(exp, model) -> list[str]:
    """Columns that match no input (nor ``der(.)`` input), output or
    state (``state.<name>``) of ``model``, other than those the sidecar
    marks ``role: other``.

    Parameters
    ----------
    exp : Experiment
        The record.
    model : Model or str

    Returns
    -------
    list of str
        In the record's column order.
    """
    mdl = _as_model(model)
    known = {*mdl.inputs, *mdl.outputs, *(STATE_PREFIX + x for x in mdl.states)}
    roles = exp.roles
    return [c for c in exp.columns if c not in known and roles.get(c) != "other"]


def _closest_names(exp, mdl) -> str:
    """``'xpos' -> 'x'; ...`` for the unmatched columns that resemble a
    name of the model (difflib ratio >= 0.3, or one name contains the
    other); empty if none does."""
    names = [*mdl.outputs, *mdl.inputs, *(STATE_PREFIX + x for x in mdl.states)]
    pairs = []
    for c in unmatched_columns(exp, mdl):
        close = difflib.get_close_matches(c, names, n=3, cutoff=0.3)
        close += [n for n in names if n not in close and (n.lower() in c.lower()
                                                          or c.lower() in n.lower())]
        if close:
            pairs.append(f"'{c}' -> {' or '.join(repr(n) for n in close[:3])}")
    return "; ".join(pairs)


def check_columns(exp, model, *, stacklevel: int = 2) -> list[str]:
    """Warn when outputs of ``model`` are absent from the record while
    some columns match none of its names (a misspelt column, ``xpos``
    for ``x``, would otherwise be ignored).

    Parameters
    ----------
    exp : Experiment
        The record.
    model : Model or str
    stacklevel : int
        Of the warning, as in :func:`warnings.warn` (2: the caller of this
        function).

    Returns
    -------
    list of str
        The unmatched columns warned about (empty: no warning).

    Warns
    -----
    ColumnWarning
        Naming the unmatched columns, the closest model names and the
        absent outputs.
    """
    mdl = _as_model(model)
    absent = [o for o in mdl.outputs if o not in exp.columns]
    extra = unmatched_columns(exp, mdl)
    if not (absent and extra):
        return []
    close = _closest_names(exp, mdl)
    warnings.warn(
        f"{exp._where() or exp.name}: column(s) {join_names(extra)} match no input, "
        f"output or state of model '{mdl.name}' and are ignored, while its output(s) "
        f"{join_names(absent)} are not in the record"
        + (f"; closest model names: {close}" if close else "")
        + "; rename columns as they are read with --columns COLUMN=NAME,... (from Python, "
          "Experiment.load(path, columns={COLUMN: NAME}))", ColumnWarning,
        stacklevel=stacklevel)
    return extra


def noise_std_for(exp, model) -> np.ndarray:
    """Declared noise standard deviations of the model's outputs, in model
    units; NaN where the record declares none.

    Parameters
    ----------
    exp : Experiment
        The record.
    model : Model or str

    Returns
    -------
    ndarray (n_y,)
    """
    mdl = _as_model(model)
    out = np.full(mdl.n_y, np.nan)
    std = exp.noise_std
    for j, name in enumerate(mdl.outputs):
        if name in std:
            out[j] = float(convert(np.array([std[name]]), exp.units.get(name),
                                   mdl.output_units[j], path=exp._where(), column=name)[0])
    return out


__all__ = ["STATE_PREFIX", "convert", "initial_state", "given_initial_states",
           "initial_state_std", "missing_inputs", "inputs_for", "outputs_for",
           "unmatched_columns", "check_columns", "noise_std_for"]
