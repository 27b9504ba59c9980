"""Experiment records: the :class:`Experiment` class, a record in memory.

An Experiment holds time, named columns, their units and the sidecar
metadata of a record in the documented CSV + JSON-sidecar format
(``docs/data_format.md``), built by :meth:`Experiment.load`,
:meth:`Experiment.from_arrays`, :meth:`Experiment.from_simulation`,
:func:`bondgraph.data.experiments.run_experiment` or a loader of
:mod:`bondgraph.data.datasets`. The file format (reading, writing, checks)
is :mod:`bondgraph.data.record_io`; binding a record to a model (its input
and output arrays, initial state and noise levels in the model's units) is
:mod:`bondgraph.data.binding`, whose functions the methods of the same names
call.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from bondgraph.data import binding, record_io
from bondgraph.data.binding import STATE_PREFIX
from bondgraph.data.record_io import GAP_FACTOR, check_time, format_header
from bondgraph.errors import DataError
from bondgraph.numerics.model import Model
from bondgraph.numerics.integrators import split_hold


# --------------------------------------------------------------- the class
def ordinal(k: int) -> str:
    """``k`` as an English ordinal: 1st, 2nd, 3rd, 4th, 10th, 11th, 22nd."""
    k = int(k)
    suffix = "th" if 10 <= k % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(k % 10, "th")
    return f"{k}{suffix}"


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
        record_io.check_meta(exp.meta)
        for cname, unit in cols.units.items():
            if unit is not None:
                record_io.check_unit(unit, None, cname)
        return exp

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
            the parameters, x0, method and solver statistics, and how the
            simulation held each input between samples (``columns.<input>.hold``,
            ``"zoh"`` or ``"linear"``, from the solver statistics; the
            filter's default hold reads it, :mod:`bondgraph.inference.discretise`).
        """
        m = sim.model
        hold = sim.stats.get("hold")
        holds = split_hold(hold, m.n_u) if isinstance(hold, str) else ()
        held = ({"columns": {n: {"hold": h} for n, h in zip(m.inputs, holds)
                             if not n.startswith("der(")}}
                if holds and set(holds) <= {"zoh", "linear"} else {})
        info = {
            "name": name or f"{m.name}_sim",
            "description": f"noise-free simulation of {m.name} ({sim.method})",
            "dt": float(np.median(np.diff(sim.t))),
            "parameters": {p: float(v) for p, v in zip(m.params, sim.theta)},
            "x0": {s: float(v) for s, v in zip(m.states, sim.x[0])},
            "method": sim.method,
            "solver_stats": {k: v for k, v in sim.stats.items()
                             if isinstance(v, (int, float, str, bool)) or v is None},
            **held,
            **(meta or {}),
        }
        return cls.from_arrays(sim.t, model=m, u=sim.u, y=sim.y, x=sim.x, meta=info)

    @classmethod
    def load(cls, path: str | Path, *, allow_missing: bool = True,
             gap_factor: float | None = GAP_FACTOR,
             columns: Mapping[str, str] | None = None,
             dt: float | None = None) -> "Experiment":
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
        columns : dict, optional
            ``{name in the file: name in the model}``: columns renamed as
            they are read (``{"Current": "I"}``; the command line's
            ``--columns Current=I``).
        dt : float, optional
            Sample interval [s] (the command line's ``--dt``; else the
            sidecar's ``dt``): a file without a time column is read with
            ``t = k dt``; one with a time column must agree with it.

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
            time, a sidecar of the wrong format or inconsistent with the CSV,
            a ``dt`` the time column contradicts.
        """
        return cls(**record_io.read_record(path, allow_missing=allow_missing,
                                           gap_factor=gap_factor, columns=columns, dt=dt))

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
        path = record_io.write_record(path, self.t, self.columns, self.units, self.meta,
                                      self.name, precision=precision, sidecar=sidecar)
        self.path = path
        self.lines = None
        return path

    # ---------------------------------------------------------- for models
    def initial_state(self, model) -> np.ndarray:
        """The initial state of this record for ``model``, the toolkit's one
        initial-state rule (:func:`bondgraph.data.binding.initial_state`)."""
        return binding.initial_state(self, model)

    def given_initial_states(self, model) -> list[str]:
        """The states of ``model`` whose initial value this record gives
        (:func:`bondgraph.data.binding.given_initial_states`)."""
        return binding.given_initial_states(self, model)

    def initial_state_std(self, model) -> dict[str, float]:
        """The sidecar's ``x0_std`` for the states of ``model``
        (:func:`bondgraph.data.binding.initial_state_std`)."""
        return binding.initial_state_std(self, model)

    def missing_inputs(self, model) -> list[str]:
        """Inputs of ``model`` that the record lacks
        (:func:`bondgraph.data.binding.missing_inputs`)."""
        return binding.missing_inputs(self, model)

    def inputs_for(self, model, defaults_ok: bool = False) -> np.ndarray:
        """Input array (N, n_u) for ``model``, in the model's units
        (:func:`bondgraph.data.binding.inputs_for`)."""
        return binding.inputs_for(self, model, defaults_ok)

    def outputs_for(self, model) -> np.ndarray:
        """Measurement array (N, n_y) for ``model``, in the model's units,
        NaN where not measured (:func:`bondgraph.data.binding.outputs_for`)."""
        return binding.outputs_for(self, model)

    def unmatched_columns(self, model) -> list[str]:
        """Columns that match no name of ``model``
        (:func:`bondgraph.data.binding.unmatched_columns`)."""
        return binding.unmatched_columns(self, model)

    def check_columns(self, model) -> list[str]:
        """Warn (ColumnWarning) when outputs of ``model`` are absent while
        some columns match none of its names; the columns warned about
        (:func:`bondgraph.data.binding.check_columns`)."""
        return binding.check_columns(self, model, stacklevel=3)

    def noise_std_for(self, model) -> np.ndarray:
        """Declared noise standard deviations (n_y,) of the outputs of
        ``model``, in model units (:func:`bondgraph.data.binding.noise_std_for`)."""
        return binding.noise_std_for(self, model)

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

    def on_finer_grid(self, midpoints: Mapping[str, Any], *, linear: Sequence[str] = (),
                      note: str = "") -> "Experiment":
        """The record on a grid twice as fine: a point midway between each
        pair of samples (2N − 1 points). The columns of ``midpoints`` (input
        values between samples, N − 1 each, file units) take them there;
        every other column is NaN there (an output, a state or a truth is
        not known between samples). The inputs in ``linear`` are declared
        held linearly over the finer intervals (sidecar ``columns.<name>.hold``);
        ``meta["finer_grid"]`` says why (``note``).

        Raises
        ------
        DataError
            A midpoint column of the wrong length, not finite, or not a
            column of the record.
        """
        n = self.t.size
        t = np.empty(2 * n - 1)
        t[::2], t[1::2] = self.t, 0.5 * (self.t[:-1] + self.t[1:])
        cols = {}
        for c, v in self.columns.items():
            out = np.full(2 * n - 1, np.nan)
            out[::2] = v
            if c in midpoints:
                m = np.asarray(midpoints[c], float).reshape(-1)
                if m.size != n - 1 or not np.isfinite(m).all():
                    raise DataError(f"on_finer_grid: column '{c}' needs {n - 1} finite "
                                    f"midpoints, got {m.size}", path=self._where())
                out[1::2] = m
            cols[c] = out
        unknown = sorted(set(midpoints) - set(self.columns))
        if unknown:
            raise DataError(f"on_finer_grid: no column(s) {', '.join(unknown)}",
                            path=self._where())
        meta = copy.deepcopy(self.meta)
        if meta.get("dt"):
            meta["dt"] = float(meta["dt"]) / 2
        info = meta.setdefault("columns", {})
        for c in linear:
            info.setdefault(c, {})["hold"] = "linear"
        meta["finer_grid"] = {"factor": 2, "interpolated": list(linear), "note": note}
        meta["name"] = self.name
        return Experiment(t=t, columns=cols, units=dict(self.units), meta=meta, path=None)

    def decimated(self, factor: int, *, means: Sequence[str] = ()) -> "Experiment":
        """Every ``factor``-th sample as a new record, for a record sampled
        far faster than its model needs (each filter pass steps every sample).

        The samples kept are 0, K, 2K, ... (K = ``factor``); a tail shorter
        than K intervals is dropped. A column of ``means`` (an input held
        zero-order) takes over each coarse interval the time-weighted mean of
        the values it held over the K fine intervals in it: the held value
        with the same impulse (∫u dt), which a zero-order hold at the coarse
        step then holds (the rule of the EMPS protocol's decimation, Janot et
        al. 2019); its hold is declared ``"zoh"`` (sidecar
        ``columns.<name>.hold``). Every other column (outputs, states, inputs
        held linearly) is point-sampled: a model's likelihood of the kept
        samples is exactly that of the subsampled record, and the
        measurement noise of a sample is unchanged (so estimates limited by
        that noise come out about √K wider). ``meta["decimated"]`` records
        the factor, the averaged columns and the original length.

        Parameters
        ----------
        factor : int
            K >= 1 (1: this record itself).
        means : sequence of str
            Columns held zero-order, averaged over each interval.

        Returns
        -------
        Experiment
            (N − 1) // K + 1 samples, ``dt`` K times the original.

        Raises
        ------
        DataError
            K not a positive integer, fewer than 2 samples kept, or a name of
            ``means`` that is not a column.
        """
        if isinstance(factor, bool) or int(factor) != factor or factor < 1:
            raise DataError(f"decimated: the factor is a positive integer, got {factor!r}",
                            path=self._where())
        k = int(factor)
        if k == 1:
            return self
        m = (self.t.size - 1) // k + 1
        if m < 2:
            raise DataError(f"decimated x{k}: {self.t.size} samples keep {m}; need >= 2 samples",
                            path=self._where())
        unknown = sorted(set(means) - set(self.columns))
        if unknown:
            raise DataError(f"decimated: no column(s) {', '.join(unknown)}", path=self._where())
        idx = np.arange(m) * k
        w = np.diff(self.t)[: (m - 1) * k].reshape(m - 1, k)
        cols = {}
        for c, v in self.columns.items():
            v = np.asarray(v)
            out = v[idx].copy()
            if c in means:
                blocks = np.asarray(v[: (m - 1) * k], float).reshape(m - 1, k)
                out[:-1] = (blocks * w).sum(axis=1) / w.sum(axis=1)
            cols[c] = out
        meta = copy.deepcopy(self.meta)
        if meta.get("dt"):
            meta["dt"] = float(meta["dt"]) * k
        info = meta.setdefault("columns", {})
        for c in means:
            info.setdefault(c, {})["hold"] = "zoh"
        meta["decimated"] = {"factor": k, "means": list(means), "samples": int(self.t.size)}
        meta["name"] = self.name
        return Experiment(t=self.t[idx].copy(), columns=cols, units=dict(self.units), meta=meta,
                          path=None, lines=None if self.lines is None else self.lines[idx])

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


def load(path: str | Path, *, allow_missing: bool = True,
         gap_factor: float | None = GAP_FACTOR) -> Experiment:
    """Shortcut for :meth:`Experiment.load` (the same options)."""
    return Experiment.load(path, allow_missing=allow_missing, gap_factor=gap_factor)


__all__ = ["Experiment", "load"]
