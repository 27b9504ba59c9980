"""Experiment records: the documented CSV + JSON-sidecar format.

One format serves synthetic records (:func:`bondgraph.data.experiments.run_experiment`,
:meth:`bondgraph.numerics.simulate.SimResult.save_csv`) and user data alike; it is
specified in ``docs/data_format.md``. In short:

* **CSV**: the first line is the header; the first column is ``t`` (time, in
  s unless the header says otherwise, e.g. ``t [ms]``); headers may carry a
  unit in brackets, ``v_gnss [m/s]``; an empty cell in an output column is a
  missing sample. A trailing comma at the end of every line is accepted (the
  CED benchmark files have one).
* **JSON sidecar** (same stem, ``.json``; optional): ``format:
  "bondgraph-experiment/1"``, ``name, model, truth_model, description, dt,
  columns: {col: {unit, role, noise_std}}, true_parameters, x0, noise,
  seed``. Unknown keys are kept in :attr:`Experiment.meta`.

Every defect of a file raises :class:`~bondgraph.errors.DataError` naming the
file, the 1-based line (the header is line 1) and the column: non-numeric
cells, NaN/inf in time or inputs, NaN in outputs when ``allow_missing`` is
False, non-increasing or repeated time, gaps, unknown units, units of the
wrong dimension, columns a model needs but the file lacks.
"""

from __future__ import annotations

import copy
import csv
import difflib
import io
import json
import math
import numbers
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from bondgraph.core import atomic
from bondgraph.core import units as _units
from bondgraph.core.jsonsafe import from_jsonable, to_jsonable
from bondgraph.errors import ColumnWarning, DataError, UnitMismatchError, join_names
from bondgraph.numerics.model import Model

#: value of the sidecar's ``format`` key
FORMAT = "bondgraph-experiment/1"
#: column roles
ROLES = ("time", "input", "output", "state", "other")
#: prefix of state columns (``state.p_mass``), so states never collide with
#: input or output names
STATE_PREFIX = "state."
#: default gap criterion: a time step above this multiple of the median step
GAP_FACTOR = 1.5

_HEADER_RE = re.compile(r"^(?P<name>[^\[\]]*?)\s*(?:\[(?P<unit>[^\[\]]*)\])?\s*$")


def parse_header(cell: str) -> tuple[str, str | None]:
    """Split a header cell ``"v_gnss [m/s]"`` into ``("v_gnss", "m/s")``.

    A header without brackets gives unit ``None`` (unspecified: the column is
    taken to be in the model's units). ``[1]`` or ``[]`` means dimensionless.
    """
    m = _HEADER_RE.match(cell.strip())
    if m is None:
        return cell.strip(), None
    name = m.group("name").strip().strip('"').strip()
    unit = m.group("unit")
    return name, (unit.strip() if unit is not None else None)


def format_header(name: str, unit: str | None) -> str:
    """Inverse of :func:`parse_header`."""
    return name if unit is None else f"{name} [{unit}]"


def convert(values: np.ndarray, from_unit: str | None, to_unit: str | None, *,
            path: str | None = None, column: str | None = None,
            what: str = "column") -> np.ndarray:
    """Convert ``values`` from ``from_unit`` to ``to_unit`` with pint.

    Offset units (``degC``) are converted properly (pint quantities), not by
    a factor. ``from_unit=None`` (unspecified) returns the values unchanged.

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
            path=path, line=1, column=column)
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


def check_time(t: np.ndarray, *, path: str | None = None, lines: np.ndarray | None = None,
               gap_factor: float | None = GAP_FACTOR, column: str = "t") -> None:
    """Check a time vector: finite, strictly increasing, no gaps.

    Parameters
    ----------
    t : array (N,)
        Times [s].
    path : str, optional
        File named in errors.
    lines : int array (N,), optional
        File line of each sample (default: sample ``i`` is on line ``i + 2``).
    gap_factor : float or None
        A step larger than ``gap_factor`` x the median step is a gap
        (``None`` disables the check).

    Raises
    ------
    DataError
        Naming the line of the first bad sample.
    """
    t = np.asarray(t, dtype=float)
    if lines is None:
        lines = np.arange(t.size) + 2
    if t.ndim != 1 or t.size < 2:
        raise DataError(f"a record needs at least 2 samples, got {t.size}", path=path,
                        column=column)
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        i = int(bad[0])
        raise DataError(f"time is {float(t[i])!r}; time must be finite", path=path,
                        line=int(lines[i]), column=column)
    dt = np.diff(t)
    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        kind = "repeated" if dt[i - 1] == 0 else "decreasing"
        raise DataError(f"{kind} time: t = {float(t[i])!r} after t = {float(t[i - 1])!r} on line "
                        f"{int(lines[i - 1])}; time must increase strictly",
                        path=path, line=int(lines[i]), column=column)
    if gap_factor is not None:
        med = float(np.median(dt))
        bad = np.flatnonzero(dt > gap_factor * med)
        if bad.size:
            i = int(bad[0]) + 1
            raise DataError(
                f"gap in time: step {dt[i - 1]:.6g} s from t = {float(t[i - 1])!r} to "
                f"t = {float(t[i])!r} exceeds {gap_factor:g} x the median step {med:.6g} s",
                path=path, line=int(lines[i]), column=column,
                hint="split the record at the gap, or fill the missing samples with "
                     "empty output cells (inputs must still be given)")


# --------------------------------------------------------------- the class
@dataclass
class Experiment:
    """A measured or synthetic record: time, named columns, units, metadata.

    Build one with :meth:`load`, :meth:`from_arrays`,
    :func:`bondgraph.data.experiments.run_experiment` or a loader of
    :mod:`bondgraph.data.datasets`; give it to a model with :meth:`inputs_for` and
    :meth:`outputs_for`.

    Attributes
    ----------
    t : ndarray (N,)
        Sample times [s].
    columns : dict of str -> ndarray (N,)
        Every column except ``t``, in file units; NaN marks a missing sample.
    units : dict of str -> str or None
        Unit of each column (``None``: unspecified, i.e. the model's units).
    meta : dict
        Sidecar content (``name, model, description, dt, columns{unit, role,
        noise_std}, true_parameters, x0, noise, seed, ...``).
    path : Path or None
        CSV file the record was loaded from or last saved to.
    lines : int ndarray (N,) or None
        File line of each sample (for error messages; None if not loaded).
    """

    t: np.ndarray
    columns: dict[str, np.ndarray]
    units: dict[str, str | None] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None
    lines: np.ndarray | None = field(default=None, repr=False, compare=False)

    def _line(self, i: int) -> int | None:
        if self.lines is not None:
            return int(self.lines[i])
        return i + 2 if self.path is not None else None

    # ------------------------------------------------------------ basics
    def __len__(self) -> int:
        return int(self.t.size)

    def __contains__(self, name: str) -> bool:
        return name == "t" or name in self.columns

    def __getitem__(self, name: str) -> np.ndarray:
        if name == "t":
            return self.t
        try:
            return self.columns[name]
        except KeyError:
            raise DataError(f"no column '{name}' (columns: {', '.join(self.columns)})",
                            path=self._where()) from None

    def _where(self) -> str | None:
        return str(self.path) if self.path is not None else None

    @property
    def name(self) -> str:
        """Record name (sidecar ``name``, else the file stem, else ``"experiment"``)."""
        if self.meta.get("name"):
            return str(self.meta["name"])
        return self.path.stem if self.path is not None else "experiment"

    @property
    def model_name(self) -> str | None:
        """The model named in the sidecar (``meta["model"]``), if any."""
        return self.meta.get("model")

    @property
    def dt(self) -> float:
        """Sample interval [s]: sidecar ``dt`` or the median time step."""
        if self.meta.get("dt"):
            return float(self.meta["dt"])
        return float(np.median(np.diff(self.t)))

    @property
    def duration(self) -> float:
        """``t[-1] - t[0]`` [s]."""
        return float(self.t[-1] - self.t[0])

    @property
    def roles(self) -> dict[str, str | None]:
        """Column name -> role (``input|output|state|other``; ``None`` if unknown)."""
        info = self.meta.get("columns", {}) or {}
        out = {}
        for c in self.columns:
            role = (info.get(c) or {}).get("role")
            if role is None and c.startswith(STATE_PREFIX):
                role = "state"
            out[c] = role
        return out

    @property
    def noise_std(self) -> dict[str, float]:
        """Column name -> declared measurement-noise standard deviation (file units)."""
        info = self.meta.get("columns", {}) or {}
        return {c: float(v["noise_std"]) for c, v in info.items()
                if isinstance(v, Mapping) and v.get("noise_std") is not None and c in self.columns}

    def names(self, role: str | None = None) -> list[str]:
        """Column names (without ``t``), optionally only those of one role."""
        if role is None:
            return list(self.columns)
        return [c for c, r in self.roles.items() if r == role]

    def states(self) -> dict[str, np.ndarray]:
        """State columns by state name (prefix ``state.`` removed)."""
        return {c[len(STATE_PREFIX):]: v for c, v in self.columns.items()
                if c.startswith(STATE_PREFIX)}

    # ------------------------------------------------------- construction
    @classmethod
    def from_arrays(cls, t, columns: Mapping[str, Any] | None = None, *, model=None,
                    u=None, y=None, x=None, units: Mapping[str, str | None] | None = None,
                    roles: Mapping[str, str] | None = None,
                    noise_std: Mapping[str, float] | None = None,
                    meta: Mapping[str, Any] | None = None, name: str | None = None,
                    check_gaps: bool = False) -> "Experiment":
        """Build a record from arrays.

        Parameters
        ----------
        t : array (N,)
            Sample times [s], strictly increasing.
        columns : dict of str -> array (N,) or scalar, optional
            Named columns (scalars are broadcast).
        model : Model or str, optional
            With ``u``, ``y``, ``x``: columns are named after the model's
            inputs, outputs and states (``state.<name>``), with its units
            and roles.
        u : array (N, n_u), optional
        y : array (N, n_y), optional
        x : array (N, n_x), optional
        units, roles, noise_std : dict of str -> ..., optional
            Per-column unit strings, roles and noise standard deviations
            (override what the model gives).
        meta : dict, optional
            Sidecar metadata (``name, model, description, ...``).
        name : str, optional
            Shortcut for ``meta["name"]``.
        check_gaps : bool
            Also apply the gap check of :meth:`load` (default off: simulations
            may use any increasing time grid).

        Raises
        ------
        DataError
            Wrong lengths, duplicate names, non-increasing or non-finite time,
            unknown roles or units.
        """
        t = np.array(t, dtype=float).reshape(-1)
        check_time(t, gap_factor=GAP_FACTOR if check_gaps else None)
        cols = _Columns(t.size)
        if model is not None:
            mdl = Model.load(model) if isinstance(model, str) else model
            cols.add_model_arrays(mdl, u, y, x)
            meta = {"model": mdl.name, **(meta or {})}
        elif any(a is not None for a in (u, y, x)):
            raise DataError("u, y and x arrays need a model to name their columns")
        for cname, values in (columns or {}).items():
            cols.add(cname, values)
        cols.override(units or {}, cols.units, "unit")
        cols.override(roles or {}, cols.roles, "role")
        meta = copy.deepcopy(dict(meta or {}))
        if name is not None:
            meta["name"] = name
        cols.describe_in(meta, noise_std)
        exp = cls(t=t, columns=cols.values, units=cols.units, meta=meta)
        exp._validate_meta()
        for cname, unit in cols.units.items():
            if unit is not None:
                _check_unit(unit, None, cname)
        return exp

    def _validate_meta(self, path: str | None = None) -> None:
        check_sidecar_types(self.meta, path)
        for cname, entry in (self.meta.get("columns") or {}).items():
            role = (entry or {}).get("role")
            if role is not None and role not in ROLES:
                raise DataError(f"unknown role '{role}' (use one of {', '.join(ROLES)})",
                                path=path, column=cname)
            std = (entry or {}).get("noise_std")
            if std is not None and not (isinstance(std, (int, float)) and std >= 0
                                        and math.isfinite(std)):
                raise DataError(f"noise_std must be a finite number >= 0, got {std!r}",
                                path=path, column=cname)

    # -------------------------------------------------------------- load
    @classmethod
    def from_simulation(cls, sim, name: str | None = None,
                        meta: Mapping | None = None) -> "Experiment":
        """A simulated trajectory as a record: inputs, noise-free outputs and
        ``state.<name>`` columns, in model units.

        Parameters
        ----------
        sim : bondgraph.numerics.simulate.SimResult
            ``t (N,)``, ``u (N, n_u)``, ``y (N, n_y)``, ``x (N, n_x)``.
        name : str, optional
            Record name (default ``<model>_sim``).
        meta : mapping, optional
            Extra sidecar entries.

        Returns
        -------
        Experiment
            Save it with :meth:`save` (CSV + JSON sidecar); its sidecar holds
            the parameters, x0, method and solver statistics.
        """
        m = sim.model
        info = {
            "name": name or f"{m.name}_sim",
            "description": f"noise-free simulation of {m.name} ({sim.method})",
            "dt": float(np.median(np.diff(sim.t))),
            "parameters": {p: float(v) for p, v in zip(m.params, sim.theta)},
            "x0": {s: float(v) for s, v in zip(m.states, sim.x[0])},
            "method": sim.method,
            "solver_stats": {k: v for k, v in sim.stats.items()
                             if isinstance(v, (int, float, str, bool)) or v is None},
            **(meta or {}),
        }
        return cls.from_arrays(sim.t, model=m, u=sim.u, y=sim.y, x=sim.x, meta=info)

    @classmethod
    def load(cls, path: str | Path, *, allow_missing: bool = True,
             gap_factor: float | None = GAP_FACTOR) -> "Experiment":
        """Read a CSV record and its JSON sidecar (if present).

        Parameters
        ----------
        path : str or Path
            The ``.csv`` file (or its ``.json`` sidecar).
        allow_missing : bool
            If True (default), empty cells and ``NaN`` in non-input columns
            are missing samples (NaN in :attr:`columns`). If False, every cell
            must hold a finite number.
        gap_factor : float or None
            Time steps above ``gap_factor`` x the median step are gaps
            (``None`` disables the check).

        Returns
        -------
        Experiment

        Raises
        ------
        DataError
            Naming the file, line and column: no header, missing or misplaced
            ``t``, duplicate names, rows of the wrong length, non-numeric
            cells, NaN/inf in time or inputs, NaN in any column when
            ``allow_missing`` is False, inf anywhere, non-increasing or
            repeated time, gaps, unknown units, a time unit that is not a
            time, a sidecar of the wrong format or inconsistent with the CSV.
        """
        path = Path(path)
        if path.suffix.lower() == ".json":
            path = path.with_suffix(".csv")
        where = str(path)
        if not path.exists():
            raise DataError("no such file", path=where)
        side = str(path.with_suffix(".json"))
        meta = _read_sidecar(path)
        header, header_line, rows, lines = _read_csv_rows(path)
        parsed, trailing = _parse_header_row(header, where, header_line)
        names = [p[0] for p in parsed]
        _check_row_lengths(rows, lines, len(names), trailing, where)
        line_arr = np.asarray(lines)
        cells = np.array(rows, dtype=str)
        side_cols = (meta.get("columns") or {}) if meta else {}
        units = _column_units(parsed, side_cols, where, side, header_line)
        roles = {nm: (side_cols.get(nm) or {}).get("role") for nm in names}
        data: dict[str, np.ndarray] = {}
        for j, nm in enumerate(names):
            data[nm] = _column_values(np.char.strip(cells[:, j]), nm, roles.get(nm),
                                      allow_missing, where, line_arr)
        t = data.pop("t")
        t_unit = units.pop("t")
        if t_unit is not None:
            try:
                t = convert(t, t_unit, "s", path=where, column="t", what="time")
            except DataError:
                raise DataError(f"time unit '{t_unit}' is not a time", path=where,
                                line=header_line, column="t") from None
        check_time(t, path=where, lines=line_arr, gap_factor=gap_factor)
        meta = meta or {}
        info = meta.setdefault("columns", {})
        for nm in names:
            entry = dict(info.get(nm) or {})
            entry["unit"] = units.get(nm, "s") if nm != "t" else "s"
            if nm == "t":
                entry["role"] = "time"
            info[nm] = entry
        exp = cls(t=t, columns=data, units=units, meta=meta, path=path, lines=line_arr)
        exp._validate_meta(side)
        if meta.get("dt"):
            med = float(np.median(np.diff(t)))
            if abs(med - float(meta["dt"])) > 0.01 * float(meta["dt"]):
                raise DataError(f"sidecar dt = {meta['dt']} s but the median time step is "
                                f"{med:.6g} s", path=side)
        return exp

    # -------------------------------------------------------------- save
    def save(self, path: str | Path, *, precision: int | None = None,
             sidecar: bool = True) -> Path:
        """Write the CSV (and the JSON sidecar).

        Parameters
        ----------
        path : str or Path
            Target ``.csv`` (the suffix is added if missing).
        precision : int, optional
            Significant digits (``%.{precision}g``). Default: the shortest
            text that reads back to the identical float64 (Python ``repr``),
            so a save/load round trip is bit-exact. Missing samples (NaN)
            are written as empty cells.
        sidecar : bool
            Also write ``<stem>.json``.

        Returns
        -------
        Path
            The CSV path.
        """
        path = Path(path)
        if path.suffix.lower() != ".csv":
            path = path.with_name(path.name + ".csv")
        path.parent.mkdir(parents=True, exist_ok=True)
        names = ["t", *self.columns]
        header = [format_header("t", "s")] + [format_header(c, self.units.get(c))
                                              for c in self.columns]
        cols = []
        for arr in [self.t, *self.columns.values()]:
            arr = np.asarray(arr, dtype=float)
            if precision is None:
                txt = [repr(v) for v in arr.tolist()]
            else:
                txt = np.char.mod(f"%.{int(precision)}g", arr).tolist()
            for i in np.flatnonzero(np.isnan(arr)):
                txt[i] = ""
            cols.append(txt)
        buf = io.StringIO(newline="")
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(header)
        w.writerows(zip(*cols))
        side_text = self._sidecar_text(names) if sidecar else None
        # never a new CSV beside the old sidecar: the old one goes first
        path.with_suffix(".json").unlink(missing_ok=True)
        atomic.write_text(path, buf.getvalue())
        if side_text is not None:
            atomic.write_text(path.with_suffix(".json"), side_text)
        self.path = path
        self.lines = None
        return path

    def _sidecar_text(self, names: list[str]) -> str:
        """The JSON sidecar of :meth:`save` (``format`` first, the documented
        keys in their order, then the others)."""
        meta = copy.deepcopy(self.meta)
        meta = {"format": FORMAT, **{k: v for k, v in meta.items() if k != "format"}}
        meta.setdefault("name", self.name)
        info = meta.setdefault("columns", {})
        for c in names:
            entry = dict(info.get(c) or {})
            entry["unit"] = "s" if c == "t" else self.units.get(c)
            if c == "t":
                entry["role"] = "time"
            first = {k: entry[k] for k in ("unit", "role", "noise_std") if k in entry}
            info[c] = {**first, **entry}
        meta["columns"] = {c: info[c] for c in names}
        order = ("format", "name", "model", "truth_model", "description", "dt", "columns",
                 "true_parameters", "x0", "x0_std", "noise", "seed")
        meta = {**{k: meta[k] for k in order if k in meta},
                **{k: v for k, v in meta.items() if k not in order}}
        return json.dumps(to_jsonable(meta), indent=2, allow_nan=False) + "\n"

    # ---------------------------------------------------------- for models
    def _model(self, model):
        if isinstance(model, str):
            return Model.load(model)
        return model

    def initial_state(self, model) -> np.ndarray:
        """The initial state of this record for ``model``: the first finite value
        of each ``state.<name>`` column, else the sidecar's ``x0[name]``, for the
        states the model has; the model's X0 for the others.

        This is the one initial-state rule of the toolkit (estimation,
        sensitivity and the loop use it).

        Parameters
        ----------
        model : Model
            Anything with ``states`` (names) and ``x0`` (n_x,).

        Returns
        -------
        ndarray (n_x,)
        """
        x0 = np.array(model.x0, dtype=float)
        cols = self.states()
        meta_x0 = (self.meta or {}).get("x0") or {}
        for i, name in enumerate(model.states):
            if name in cols and np.isfinite(cols[name][0]):
                x0[i] = float(cols[name][0])
            elif isinstance(meta_x0, Mapping) and name in meta_x0:
                x0[i] = float(meta_x0[name])
        return x0

    def given_initial_states(self, model) -> list[str]:
        """The states of ``model`` whose initial value this record gives: a
        finite first value of its ``state.<name>`` column, the sidecar's
        ``x0[name]`` or ``x0_std[name]``. For the others
        :meth:`initial_state` falls back to the model's X0, a guess: the
        prior of such a state is wide (:mod:`bondgraph.inference.prior`).

        Parameters
        ----------
        model : Model
            Anything with ``states`` (names).

        Returns
        -------
        list of str
            In the model's state order.
        """
        cols = self.states()
        meta = self.meta or {}
        x0 = meta.get("x0") if isinstance(meta.get("x0"), Mapping) else {}
        std = meta.get("x0_std") if isinstance(meta.get("x0_std"), Mapping) else {}
        return [n for n in model.states
                if (n in cols and np.isfinite(cols[n][0])) or n in x0 or n in std]

    def initial_state_std(self, model) -> dict[str, float]:
        """The declared spread of the initial state: the sidecar's ``x0_std``
        (state name -> standard deviation of the prior whose mean is
        :meth:`initial_state`), for the states ``model`` has.

        Raises
        ------
        DataError
            ``x0_std`` not a mapping of finite numbers >= 0.
        """
        raw = (self.meta or {}).get("x0_std") or {}
        if not isinstance(raw, Mapping):
            raise DataError("sidecar 'x0_std' must be an object {state: std}",
                            path=str(self.path) if self.path else None)
        out = {}
        for name, v in raw.items():
            try:
                sd = float(v)
            except (TypeError, ValueError):
                sd = float("nan")
            if not np.isfinite(sd) or sd < 0:
                raise DataError(f"sidecar x0_std of '{name}' must be a finite number >= 0, "
                                f"got {v!r}", path=str(self.path) if self.path else None)
            if name in model.states:
                out[name] = sd
        return out

    def missing_inputs(self, model) -> list[str]:
        """Inputs of ``model`` (not ``der(.)`` ones) that the record lacks."""
        mdl = self._model(model)
        out = []
        for name in mdl.inputs:
            src = mdl.derivative_inputs.get(name)
            if src is not None:
                if name in self.columns:
                    continue
                name = src
            if name not in self.columns and name not in out:
                out.append(name)
        return out

    def inputs_for(self, model, defaults_ok: bool = False) -> np.ndarray:
        """Input array for a model, in the model's units.

        Columns are matched to ``model.inputs`` by name and converted from
        the file's units to the model's (pint). A derivative input
        ``der(r)`` (``model.derivative_inputs``) is taken from a ``der(r)``
        column if the record has one, else computed from ``r`` by
        ``numpy.gradient`` (second-order central differences inside, one-sided
        at the ends; non-uniform steps allowed).

        Parameters
        ----------
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
        mdl = self._model(model)
        where = self._where()
        missing = self.missing_inputs(mdl)
        if missing and not defaults_ok:
            raise DataError(
                f"missing column(s) {join_names(missing)} needed by model '{mdl.name}' "
                f"(its inputs: {', '.join(mdl.inputs)}; the record has: "
                f"{', '.join(self.columns) or 'no columns'})",
                path=where, line=1, column=missing[0],
                hint="add the column(s), or call inputs_for(model, defaults_ok=True) to hold "
                     "them at the model defaults")
        n = len(self)
        U = np.empty((n, mdl.n_u))
        base: dict[str, np.ndarray] = {}

        def base_value(name: str) -> np.ndarray:
            if name not in base:
                j = mdl.input_index(name)
                if name in self.columns:
                    vals = self._input_column(name, mdl.input_units[j], mdl)
                else:
                    vals = np.full(n, float(mdl.u0[j]))
                base[name] = vals
            return base[name]

        for j, name in enumerate(mdl.inputs):
            src = mdl.derivative_inputs.get(name)
            if src is None:
                U[:, j] = base_value(name)
            elif name in self.columns:
                U[:, j] = self._input_column(name, mdl.input_units[j], mdl)
            else:
                U[:, j] = np.gradient(base_value(src), self.t)
        return U

    def _input_column(self, name: str, unit: str, mdl) -> np.ndarray:
        vals = self.columns[name]
        bad = np.flatnonzero(~np.isfinite(vals))
        if bad.size:
            i = int(bad[0])
            raise DataError(f"input value is {float(vals[i])!r} (at t = {float(self.t[i])!r}); inputs must "
                            f"be finite at every sample", path=self._where(),
                            line=self._line(i), column=name)
        return convert(vals, self.units.get(name), unit, path=self._where(), column=name,
                       what=f"input '{name}' of model '{mdl.name}'")

    def outputs_for(self, model) -> np.ndarray:
        """Measurement array for a model, in the model's units.

        Parameters
        ----------
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
        mdl = self._model(model)
        n = len(self)
        Y = np.full((n, mdl.n_y), np.nan)
        found = 0
        for j, name in enumerate(mdl.outputs):
            if name in self.columns:
                Y[:, j] = convert(self.columns[name], self.units.get(name), mdl.output_units[j],
                                  path=self._where(), column=name,
                                  what=f"output '{name}' of model '{mdl.name}'")
                found += 1
        if mdl.n_y and not found:
            close = self._closest_names(mdl)
            raise DataError(f"the record has no column for any output of model '{mdl.name}' "
                            f"({', '.join(mdl.outputs)}); its columns: "
                            f"{', '.join(self.columns)}", path=self._where(), line=1,
                            hint=f"rename the column(s): {close}" if close else None)
        return Y

    def unmatched_columns(self, model) -> list[str]:
        """Columns that match no input (nor ``der(.)`` input), output or
        state (``state.<name>``) of ``model``, other than those the sidecar
        marks ``role: other``."""
        mdl = self._model(model)
        known = {*mdl.inputs, *mdl.outputs, *(STATE_PREFIX + x for x in mdl.states)}
        roles = self.roles
        return [c for c in self.columns if c not in known and roles.get(c) != "other"]

    def _closest_names(self, mdl) -> str:
        """``'xpos' -> 'x'; ...`` for the unmatched columns that resemble a
        name of the model (difflib ratio >= 0.3, or one name contains the
        other); empty if none does."""
        names = [*mdl.outputs, *mdl.inputs, *(STATE_PREFIX + x for x in mdl.states)]
        pairs = []
        for c in self.unmatched_columns(mdl):
            close = difflib.get_close_matches(c, names, n=3, cutoff=0.3)
            close += [n for n in names if n not in close and (n.lower() in c.lower()
                                                              or c.lower() in n.lower())]
            if close:
                pairs.append(f"'{c}' -> {' or '.join(repr(n) for n in close[:3])}")
        return "; ".join(pairs)

    def check_columns(self, model) -> list[str]:
        """Warn when outputs of ``model`` are absent from the record while
        some columns match none of its names (a misspelt column, ``xpos``
        for ``x``, would otherwise be ignored).

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
        mdl = self._model(model)
        absent = [o for o in mdl.outputs if o not in self.columns]
        extra = self.unmatched_columns(mdl)
        if not (absent and extra):
            return []
        close = self._closest_names(mdl)
        warnings.warn(
            f"{self._where() or self.name}: column(s) {join_names(extra)} match no input, "
            f"output or state of model '{mdl.name}' and are ignored, while its output(s) "
            f"{join_names(absent)} are not in the record"
            + (f"; closest model names: {close}" if close else ""), ColumnWarning, stacklevel=2)
        return extra

    def noise_std_for(self, model) -> np.ndarray:
        """Declared noise standard deviations of the model's outputs, in model
        units; NaN where the record declares none. Shape (n_y,)."""
        mdl = self._model(model)
        out = np.full(mdl.n_y, np.nan)
        std = self.noise_std
        for j, name in enumerate(mdl.outputs):
            if name in std:
                out[j] = float(convert(np.array([std[name]]), self.units.get(name),
                                       mdl.output_units[j], path=self._where(), column=name)[0])
        return out

    # ------------------------------------------------------------- other
    def segment(self, start: int, stop: int | None = None, *, name: str | None = None
                ) -> "Experiment":
        """Samples ``start:stop`` as a new record (meta copied, name suffixed;
        a segment that starts later drops the sidecar's ``x0`` and ``x0_std``,
        which describe the record's first sample, not its own: its state
        columns, if any, give its initial state)."""
        sl = slice(start, stop)
        t = self.t[sl]
        if t.size < 2:
            raise DataError(f"segment [{start}:{stop}] has {t.size} samples; need >= 2",
                            path=self._where())
        meta = copy.deepcopy(self.meta)
        if t[0] != self.t[0]:
            meta.pop("x0", None)
            meta.pop("x0_std", None)
        meta["name"] = name or f"{self.name}[{start}:{'' if stop is None else stop}]"
        meta["segment"] = [int(start), None if stop is None else int(stop)]
        return Experiment(t=t.copy(), columns={k: v[sl].copy() for k, v in self.columns.items()},
                          units=dict(self.units), meta=meta, path=None)

    def to_dataframe(self):
        """A pandas DataFrame with ``t`` and every column (headers with units)."""
        import pandas as pd

        data = {format_header("t", "s"): self.t}
        for c, v in self.columns.items():
            data[format_header(c, self.units.get(c))] = v
        return pd.DataFrame(data)

    def summary(self) -> str:
        """Text summary: name, model, size, sample time and a column table."""
        dts = np.diff(self.t)
        lines = [f"Experiment '{self.name}'" + (f" ({self.path})" if self.path else "")]
        for key in ("model", "truth_model", "description"):
            if self.meta.get(key):
                lines.append(f"  {key}: {self.meta[key]}")
        lines.append(f"  {len(self)} samples, t = {self.t[0]:.6g} .. {self.t[-1]:.6g} s, "
                     f"dt median {np.median(dts):.6g} s (min {dts.min():.6g}, max {dts.max():.6g})")
        if self.meta.get("seed") is not None:
            lines.append(f"  seed: {self.meta['seed']}")
        if self.meta.get("true_parameters"):
            tp = ", ".join(f"{k}={v:.6g}" for k, v in self.meta["true_parameters"].items()
                           if isinstance(v, (int, float)))
            lines.append(f"  true parameters: {tp}")
        roles, std = self.roles, self.noise_std
        w = max([len(c) for c in self.columns] + [6])
        lines.append(f"  {'column':<{w}}  {'unit':<10} {'role':<7} {'missing':>7} "
                     f"{'min':>11} {'mean':>11} {'max':>11} {'noise_std':>10}")
        for c, v in self.columns.items():
            miss = int(np.isnan(v).sum())
            ok = v[~np.isnan(v)]
            lo, mu, hi = ((ok.min(), ok.mean(), ok.max()) if ok.size else (np.nan,) * 3)
            s = f"{std[c]:.4g}" if c in std else "-"
            unit = self.units.get(c)
            lines.append(f"  {c:<{w}}  {(unit if unit is not None else '?'):<10} "
                         f"{(roles.get(c) or '?'):<7} {miss:>7d} {lo:>11.5g} {mu:>11.5g} "
                         f"{hi:>11.5g} {s:>10}")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"<Experiment '{self.name}': {len(self)} samples, {self.duration:.6g} s, "
                f"columns {', '.join(self.columns)}>")


# ------------------------------------------------------------- internals
class _Columns:
    """Columns being assembled by :meth:`Experiment.from_arrays`: values (N,),
    units and roles by column name, in insertion order."""

    def __init__(self, n: int):
        self.n = n
        self.values: dict[str, np.ndarray] = {}
        self.units: dict[str, str | None] = {}
        self.roles: dict[str, str] = {}

    def add(self, cname: str, values, unit: str | None = None, role: str | None = None) -> None:
        """Add a column (a scalar is broadcast to N samples).

        Raises
        ------
        DataError
            Duplicate name, or values not of shape (N,).
        """
        n = self.n
        if cname == "t" or cname in self.values:
            raise DataError(f"duplicate column name '{cname}'", column=cname)
        arr = np.array(values, dtype=float)
        if arr.ndim == 0:
            arr = np.full(n, float(arr))
        arr = arr.reshape(-1) if arr.ndim > 1 and arr.size == n else arr
        if arr.shape != (n,):
            raise DataError(f"column has shape {arr.shape}, expected ({n},) like t",
                            column=cname)
        self.values[cname] = arr
        self.units[cname] = unit
        if role is not None:
            self.roles[cname] = role

    def add_model_arrays(self, mdl, u, y, x) -> None:
        """Columns named after the model's inputs ``u (N, n_u)``, outputs
        ``y (N, n_y)`` and states ``x (N, n_x)`` (``state.<name>``), with its
        units and roles; ``None`` arrays are skipped."""
        for arr, names, munits, role, prefix in (
                (u, mdl.inputs, mdl.input_units, "input", ""),
                (y, mdl.outputs, mdl.output_units, "output", ""),
                (x, mdl.states, mdl.state_units, "state", STATE_PREFIX)):
            if arr is None:
                continue
            arr = np.asarray(arr, dtype=float)
            if arr.shape != (self.n, len(names)):
                raise DataError(f"{role} array has shape {arr.shape}, expected "
                                f"({self.n}, {len(names)}) for model '{mdl.name}'")
            for j, nm in enumerate(names):
                self.add(prefix + nm, arr[:, j], (munits[j] or None), role)

    def override(self, given: Mapping, target: dict, what: str) -> None:
        """Set units or roles given by the caller; each must name a column."""
        for cname, value in given.items():
            if cname not in self.values:
                raise DataError(f"{what} given for unknown column '{cname}'", column=cname)
            target[cname] = value

    def describe_in(self, meta: dict, noise_std: Mapping[str, float] | None) -> None:
        """Write ``meta["columns"]``: role, noise_std and unit of every column
        (over what ``meta`` already says), ``t`` in s, no entries for absent
        columns."""
        info = meta.setdefault("columns", {})
        for cname in self.values:
            entry = dict(info.get(cname) or {})
            if cname in self.roles:
                entry["role"] = self.roles[cname]
            if noise_std and cname in noise_std:
                entry["noise_std"] = float(noise_std[cname])
            entry["unit"] = self.units[cname]
            info[cname] = entry
        for cname in list(info):
            if cname not in self.values and cname != "t":
                del info[cname]
        info["t"] = {"unit": "s", "role": "time"}


def _check_unit(unit: str, path: str | None, column: str) -> None:
    try:
        _units.parse(unit)
    except UnitMismatchError as exc:
        raise DataError(str(exc), path=path, line=1, column=column,
                        hint="use a unit pint understands, e.g. m/s, km/h, N*m, rad/s, rpm, 1"
                        ) from None


def _read_csv_rows(path: Path) -> tuple[list[str], int, list[list[str]], list[int]]:
    """The header row, its line, the data rows and their lines (blank lines
    skipped; a UTF-8 byte-order mark is dropped).

    Raises
    ------
    DataError
        An empty file.
    """
    with open(path, newline="", encoding="utf-8-sig") as fh:
        reader = csv.reader(fh)
        rows: list[list[str]] = []
        lines: list[int] = []
        header: list[str] | None = None
        header_line = 1
        for row in reader:
            if not row or all(not c.strip() for c in row):
                continue
            if header is None:
                header = row
                header_line = reader.line_num
                continue
            rows.append(row)
            lines.append(reader.line_num)
    if header is None:
        raise DataError("empty file: no header line", path=str(path))
    return header, header_line, rows, lines


def _parse_header_row(header: list[str], where: str,
                      header_line: int) -> tuple[list[tuple[str, str | None]], bool]:
    """``(name, unit)`` per header cell and whether the lines end in a
    trailing comma (an empty last header cell).

    Raises
    ------
    DataError
        Empty or duplicate names, ``t`` missing or not first.
    """
    trailing = len(header) > 1 and header[-1].strip() == ""
    if trailing:
        header = header[:-1]
    parsed = [parse_header(h) for h in header]
    names = [p[0] for p in parsed]
    for j, nm in enumerate(names):
        if not nm:
            raise DataError(f"empty column name in header position {j + 1}", path=where,
                            line=header_line)
        if nm in names[:j]:
            raise DataError("duplicate column name", path=where, line=header_line,
                            column=nm)
    if names[0] != "t":
        if "t" in names:
            raise DataError(f"'t' must be the first column (it is column {names.index('t') + 1})",
                            path=where, line=header_line, column="t")
        raise DataError(f"first column must be the time 't', found '{names[0]}'",
                        path=where, line=header_line, column=names[0],
                        hint="name the time column 't' (unit in brackets, e.g. 't [s]')")
    return parsed, trailing


def _check_row_lengths(rows: list[list[str]], lines: list[int], ncol: int, trailing: bool,
                       where: str) -> None:
    """Every row has ``ncol`` cells (an empty trailing cell is dropped in
    place); at least 2 rows.

    Raises
    ------
    DataError
        A row of another length, a value in the unnamed trailing column, fewer
        than 2 samples.
    """
    for i, row in enumerate(rows):
        if trailing and len(row) == ncol + 1:
            if row[-1].strip():
                raise DataError(f"value '{row[-1]}' in the unnamed trailing column",
                                path=where, line=lines[i])
            row.pop()
        if len(row) != ncol:
            raise DataError(f"row has {len(row)} cells, the header has {ncol} columns",
                            path=where, line=lines[i])
    if len(rows) < 2:
        raise DataError(f"a record needs at least 2 samples, found {len(rows)}", path=where)


def _column_units(parsed: list[tuple[str, str | None]], side_cols: Mapping, where: str,
                  side: str, header_line: int) -> dict[str, str | None]:
    """Unit of each column: the header's, else the sidecar's.

    Raises
    ------
    DataError
        A sidecar column the CSV lacks, header and sidecar units that differ,
        an unknown unit.
    """
    names = [p[0] for p in parsed]
    for cname in side_cols:
        if cname not in names:
            raise DataError(f"the sidecar describes column '{cname}', which the CSV lacks",
                            path=side, column=cname)
    units: dict[str, str | None] = {}
    for (nm, unit) in parsed:
        side_unit = (side_cols.get(nm) or {}).get("unit")
        if unit is not None and side_unit is not None and unit != side_unit:
            try:
                same = _units.factor(unit, side_unit) == 1.0
            except Exception:
                same = False
            if not same:
                raise DataError(f"header unit '{unit}' differs from the sidecar's "
                                f"'{side_unit}'", path=where, line=header_line, column=nm)
        units[nm] = unit if unit is not None else side_unit
        if units[nm] is not None:
            _check_unit(units[nm], where, nm)
    return units


def _column_values(col: np.ndarray, nm: str, role: str | None, allow_missing: bool,
                   where: str, line_arr: np.ndarray) -> np.ndarray:
    """Floats of one column's stripped cells ``col`` (N,); empty cells are NaN.

    Raises
    ------
    DataError
        Naming the line: a non-numeric cell, an empty time cell, inf, NaN in
        an input or (``allow_missing=False``) in any column.
    """
    empty = col == ""
    try:
        vals = np.where(empty, "nan", col).astype(float)
    except ValueError:
        for i, s in enumerate(col):
            if s:
                try:
                    float(s)
                except ValueError:
                    raise DataError(f"non-numeric cell '{s}'", path=where,
                                    line=int(line_arr[i]), column=nm) from None
        raise  # pragma: no cover - numpy and float() disagree
    if nm == "t":
        if empty.any():
            i = int(np.flatnonzero(empty)[0])
            raise DataError("empty time cell", path=where, line=int(line_arr[i]), column=nm)
        return vals
    inf = np.flatnonzero(np.isinf(vals))
    if inf.size:
        i = int(inf[0])
        raise DataError(f"infinite value '{col[i]}'", path=where, line=int(line_arr[i]),
                        column=nm)
    nan = np.flatnonzero(np.isnan(vals))
    if nan.size and (not allow_missing or role == "input"):
        i = int(nan[0])
        what = "empty cell" if empty[i] else f"'{col[i]}'"
        why = ("inputs must be given at every sample" if role == "input"
               else "missing samples are not allowed (allow_missing=False)")
        raise DataError(f"{what}: {why}", path=where, line=int(line_arr[i]), column=nm)
    return vals


def _read_sidecar(csv_path: Path) -> dict[str, Any]:
    side = csv_path.with_suffix(".json")
    if not side.exists():
        return {}
    try:
        meta = from_jsonable(json.loads(side.read_text(encoding="utf-8")))
    except json.JSONDecodeError as exc:
        raise DataError(f"invalid JSON: {exc.msg}", path=str(side), line=exc.lineno) from None
    if not isinstance(meta, dict):
        raise DataError("the sidecar must hold a JSON object", path=str(side))
    fmt = meta.get("format")
    if fmt != FORMAT:
        raise DataError(f"sidecar format is {fmt!r}, expected '{FORMAT}'", path=str(side))
    check_sidecar_types(meta, str(side))
    return meta


#: sidecar keys holding text
_TEXT_KEYS = ("name", "model", "truth_model", "description")
#: sidecar keys holding {name: finite number}
_NUMBER_MAPS = ("true_parameters", "parameters", "x0")


def _is_number(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)


def check_sidecar_types(meta: Mapping, path: str | None = None) -> None:
    """Check the types of the documented sidecar keys (before any work uses
    them): text for ``name, model, truth_model, description``; a positive
    number for ``dt``; ``{name: finite number}`` for ``true_parameters``,
    ``parameters`` and ``x0``; an integer ``seed``; objects for ``columns``
    (one object per column, a text ``unit``) and ``noise``. Other keys are free.

    Raises
    ------
    DataError
        Naming the sidecar file and the key (and entry) of the wrong type.
    """
    def bad(msg: str, column: str | None = None):
        return DataError(f"sidecar {msg}", path=path, column=column)

    for key in _TEXT_KEYS:
        if meta.get(key) is not None and not isinstance(meta[key], str):
            raise bad(f"'{key}' must be text, got {meta[key]!r}")
    dt = meta.get("dt")
    if dt is not None and not (_is_number(dt) and dt > 0):
        raise bad(f"'dt' must be a positive number of seconds, got {dt!r}")
    for key in _NUMBER_MAPS:
        val = meta.get(key)
        if val is None:
            continue
        if not isinstance(val, Mapping):
            raise bad(f"'{key}' must be an object {{name: number}}, got {val!r}")
        for name, v in val.items():
            if not _is_number(v):
                raise bad(f"'{key}': the value of '{name}' must be a finite number, got {v!r}")
    seed = meta.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, numbers.Integral)):
        raise bad(f"'seed' must be an integer, got {seed!r}")
    if meta.get("noise") is not None and not isinstance(meta["noise"], Mapping):
        raise bad(f"'noise' must be an object, got {meta['noise']!r}")
    cols = meta.get("columns")
    if cols is None:
        return
    if not isinstance(cols, Mapping):
        raise bad("'columns' must be an object {column: {unit, role, noise_std}}")
    for cname, entry in cols.items():
        if entry is not None and not isinstance(entry, Mapping):
            raise bad(f"'columns': the entry of '{cname}' must be an object "
                      f"{{unit, role, noise_std}}, got {entry!r}", column=cname)
        unit = (entry or {}).get("unit")
        if unit is not None and not isinstance(unit, str):
            raise bad(f"'columns': the unit of '{cname}' must be text, got {unit!r}",
                      column=cname)


def load(path: str | Path, **kw) -> Experiment:
    """Shortcut for :meth:`Experiment.load`."""
    return Experiment.load(path, **kw)


def read_table(path: str | Path, *, encoding: str = "utf-8-sig") -> tuple[list[str], np.ndarray]:
    """Read a plain numeric CSV (no ``t`` required): header names and an
    (N, n) float array. Accepts a trailing comma on every line (the CED
    benchmark files) and quoted header cells; empty cells become NaN.

    Raises
    ------
    DataError
        Naming the line and column of a non-numeric cell or a row of the
        wrong length.
    """
    path = Path(path)
    where = str(path)
    with open(path, newline="", encoding=encoding) as fh:
        reader = csv.reader(fh)
        header = None
        rows, lines = [], []
        for row in reader:
            if not row or all(not c.strip() for c in row):
                continue
            if header is None:
                header = [c.strip() for c in row]
                continue
            rows.append(row)
            lines.append(reader.line_num)
    if header is None:
        raise DataError("empty file: no header line", path=where)
    trailing = len(header) > 1 and header[-1] == ""
    if trailing:
        header = header[:-1]
    n = len(header)
    out = np.empty((len(rows), n))
    for i, row in enumerate(rows):
        if trailing and len(row) == n + 1 and not row[-1].strip():
            row = row[:-1]
        if len(row) != n:
            raise DataError(f"row has {len(row)} cells, the header has {n} columns", path=where,
                            line=lines[i])
        for j, cell in enumerate(row):
            s = cell.strip()
            if not s:
                out[i, j] = np.nan
                continue
            try:
                out[i, j] = float(s)
            except ValueError:
                raise DataError(f"non-numeric cell '{s}'", path=where, line=lines[i],
                                column=header[j]) from None
    return header, out


__all__ = ["Experiment", "FORMAT", "ROLES", "STATE_PREFIX", "GAP_FACTOR", "load", "convert",
           "check_time", "parse_header", "format_header", "read_table"]
