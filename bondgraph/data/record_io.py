"""The record file format: CSV reading and writing, header parsing, the
JSON sidecar, the time checks.

One format serves synthetic records (:func:`bondgraph.data.experiments.run_experiment`,
:meth:`bondgraph.numerics.simulate.SimResult.save_csv`) and user data alike; it is
specified in ``docs/data_format.md``. In short:

* **CSV**: the first line is the header; the first column is ``t`` (time, in
  s unless the header says otherwise, e.g. ``t [ms]``); headers may carry a
  unit in brackets, ``v_gnss [m/s]``; an empty cell in an output column is a
  missing sample. A trailing comma at the end of every line is accepted (the
  CED benchmark files have one). What spreadsheets write is read too: a
  first column ``time``/``Time (s)``/``time_ms``, units in parentheses
  (``Force (N)``), ``;`` or tab separators with decimal commas.
* **JSON sidecar** (same stem, ``.json``; optional): ``format:
  "bondgraph-experiment/1"``, ``name, model, truth_model, description, dt,
  columns: {col: {unit, role, noise_std, hold}}, true_parameters, x0, noise,
  seed``. Unknown keys are kept in the record's ``meta``.

Every defect of a file raises :class:`~bondgraph.errors.DataError` naming the
file, the 1-based line (the header is line 1) and the column: non-numeric
cells, NaN/inf in time or inputs, NaN in outputs when ``allow_missing`` is
False, non-increasing or repeated time, gaps, unknown units, units of the
wrong dimension (and, once bound to a model, :mod:`bondgraph.data.binding`,
columns the model needs but the file lacks).

:class:`~bondgraph.data.records.Experiment` reads and writes its files here
(:func:`read_record`, :func:`write_record`); binding a record to a model is
:mod:`bondgraph.data.binding`.
"""

from __future__ import annotations

import copy
import csv
import io
import json
import math
import numbers
import re
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from bondgraph.core import atomic
from bondgraph.core import units as _units
from bondgraph.core.jsonsafe import from_jsonable, to_jsonable
from bondgraph.data.binding import convert
from bondgraph.errors import DataError, UnitMismatchError

#: value of the sidecar's ``format`` key
FORMAT = "bondgraph-experiment/1"
#: column roles
ROLES = ("time", "input", "output", "state", "other")
#: how an input column may declare it was held between samples (sidecar
#: ``columns.<name>.hold``): a digital command held constant (zero-order), or a
#: sampled continuous signal, interpolated linearly (first-order)
INPUT_HOLDS = ("zoh", "linear")
#: default gap criterion: a time step above this multiple of the median step
GAP_FACTOR = 1.5

_HEADER_RE = re.compile(r"^(?P<name>[^\[\]]*?)\s*(?:\[(?P<unit>[^\[\]]*)\])?\s*$")
#: a unit in parentheses after a space, as spreadsheets and logging tools write
#: it: ``Force (N)``, ``Time (s)`` (``y(1)``, without the space, stays a name)
_PAREN_RE = re.compile(r"^(?P<name>[^()\[\]]*?\S)\s+\((?P<unit>[^()\[\]]*)\)\s*$")
#: names read as the time column when first (case-insensitive), with an
#: optional unit suffix (``time_s``, ``t_ms``)
_TIME_RE = re.compile(r"^(?:t|time)(?:_(?P<unit>s|ms|us|min|h))?$", re.IGNORECASE)


def parse_header(cell: str) -> tuple[str, str | None]:
    """Split a header cell ``"v_gnss [m/s]"`` into ``("v_gnss", "m/s")``.

    A header without brackets gives unit ``None`` (unspecified: the column is
    taken to be in the model's units). ``[1]`` or ``[]`` means dimensionless.
    A unit in parentheses after a space, ``"Force (N)"``, is read the same way.
    """
    cell = cell.strip().strip('"').strip()
    m = _PAREN_RE.match(cell)
    if m is not None and _is_unit(m.group("unit")):
        return m.group("name").strip(), m.group("unit").strip()
    m = _HEADER_RE.match(cell)
    if m is None:
        return cell, None
    name = m.group("name").strip().strip('"').strip()
    unit = m.group("unit")
    return name, (unit.strip() if unit is not None else None)


def _is_unit(text: str) -> bool:
    """Whether pint reads ``text`` as a unit (``"N"``, ``"m/s"``; not ``"filtered"``)."""
    try:
        _units.parse(text.strip())
    except Exception:
        return False
    return bool(text.strip())


def format_header(name: str, unit: str | None) -> str:
    """Inverse of :func:`parse_header`."""
    return name if unit is None else f"{name} [{unit}]"


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


def check_unit(unit: str, path: str | None, column: str) -> None:
    """Check that pint knows ``unit``.

    Parameters
    ----------
    unit : str
    path, column : str or None
        File and column named in the error.

    Raises
    ------
    DataError
        An unknown unit (line 1, the column), with a hint.
    """
    try:
        _units.parse(unit)
    except UnitMismatchError as exc:
        raise DataError(str(exc), path=path, line=1, column=column,
                        hint="use a unit pint understands, e.g. m/s, km/h, N*m, rad/s, rpm, 1"
                        ) from None


def check_meta(meta: Mapping, path: str | None = None) -> None:
    """Check a record's metadata: the sidecar types
    (:func:`check_sidecar_types`), every column's role (one of
    :data:`ROLES`), ``noise_std`` (a finite number >= 0) and ``hold`` (one
    of :data:`INPUT_HOLDS`, on a column whose role, if given, is ``input``).

    Parameters
    ----------
    meta : mapping
        Sidecar content.
    path : str, optional
        Sidecar file named in errors.

    Raises
    ------
    DataError
        Naming the file and the column.
    """
    check_sidecar_types(meta, path)
    for cname, entry in (meta.get("columns") or {}).items():
        role = (entry or {}).get("role")
        if role is not None and role not in ROLES:
            raise DataError(f"unknown role '{role}' (use one of {', '.join(ROLES)})",
                            path=path, column=cname)
        std = (entry or {}).get("noise_std")
        if std is not None and not (isinstance(std, (int, float)) and std >= 0
                                    and math.isfinite(std)):
            raise DataError(f"noise_std must be a finite number >= 0, got {std!r}",
                            path=path, column=cname)
        hold = (entry or {}).get("hold")
        if hold is not None and hold not in INPUT_HOLDS:
            raise DataError(f"hold must be one of {', '.join(repr(h) for h in INPUT_HOLDS)} "
                            f"(a digital command held, or a sampled continuous signal), got "
                            f"{hold!r}", path=path, column=cname)
        if hold is not None and role not in (None, "input"):
            raise DataError(f"hold is declared for inputs only; this column's role is "
                            f"'{role}'", path=path, column=cname)


# --------------------------------------------------------------- reading
def read_record(path: str | Path, *, allow_missing: bool = True,
                gap_factor: float | None = GAP_FACTOR,
                columns: Mapping[str, str] | None = None,
                dt: float | None = None) -> dict[str, Any]:
    """Read a CSV record and its JSON sidecar (if present): the fields of an
    :class:`~bondgraph.data.records.Experiment` (what
    :meth:`~bondgraph.data.records.Experiment.load` builds it from).

    Parameters
    ----------
    path : str or Path
        The ``.csv`` file (or its ``.json`` sidecar).
    allow_missing : bool
        Empty cells and ``NaN`` in non-input columns are missing samples
        (NaN); if False, every cell must hold a finite number.
    gap_factor : float or None
        Time steps above ``gap_factor`` x the median step are gaps
        (``None`` disables the check).
    columns : dict, optional
        ``{name in the file: name in the model}``: columns renamed after
        reading (a logger's ``Current`` as the model's input ``I``); the
        sidecar describes them by their names in the file. A unit in
        brackets after the new name replaces the file's (:func:`_column_units`).
    dt : float, optional
        The sample interval [s] (the command line's ``--dt``; else the
        sidecar's ``dt``). A file without a time column (published
        benchmark files often have none: Silverbox, CED) is read with
        ``t = k dt`` from 0; a file with one must agree with it (its median
        step within 1 %).

    Returns
    -------
    dict
        ``t`` (N,) in s, ``columns`` {name: (N,)} in file units, ``units``,
        ``meta`` (the sidecar, with every column's unit and role), ``path``
        (the CSV) and ``lines`` (the file line of each sample).

    Raises
    ------
    DataError
        Naming the file, line and column (:meth:`Experiment.load
        <bondgraph.data.records.Experiment.load>` lists the defects); a
        ``dt`` that is not a positive finite number.
    """
    path = Path(path)
    if path.suffix.lower() == ".json":
        path = path.with_suffix(".csv")
    where = str(path)
    if not path.exists():
        raise DataError("no such file", path=where)
    side = str(path.with_suffix(".json"))
    meta = _read_sidecar(path)
    if dt is not None:
        meta = dict(meta or {}, dt=_given_dt(dt, where))
    given = {parse_header(old)[0]: parse_header(new) for old, new in (columns or {}).items()}
    columns = {old: nu[0] for old, nu in given.items()}
    names, data, units, line_arr, header_line = _read_columns(
        path, meta, allow_missing, {old: nu[1] for old, nu in given.items() if nu[1] is not None})
    if columns:
        names = _renamed(names, data, units, meta, columns, where, header_line)
    t = _time_column(data.pop("t"), units.pop("t"), where, header_line, line_arr, gap_factor)
    meta = meta or {}
    info = meta.setdefault("columns", {})
    for nm in names:
        entry = dict(info.get(nm) or {})
        entry["unit"] = units.get(nm, "s") if nm != "t" else "s"
        if nm == "t":
            entry["role"] = "time"
        info[nm] = entry
    check_meta(meta, side)
    if meta.get("dt") and t.size > 1:
        _check_dt(t, float(meta["dt"]), dt is not None, where if dt is not None else side)
    return {"t": t, "columns": data, "units": units, "meta": meta, "path": path,
            "lines": line_arr}


def _time_column(t: np.ndarray, t_unit: str | None, where: str, header_line: int,
                 lines: np.ndarray, gap_factor: float | None) -> np.ndarray:
    """The time column ``t`` (N,) in seconds, checked (:func:`check_time`);
    a logger's "-0.0" is 0 (not "-0 s" in every line that names a time).

    Raises
    ------
    DataError
        A time unit that is not a time; the checks of :func:`check_time`.
    """
    if t_unit is not None:
        try:
            t = convert(t, t_unit, "s", path=where, column="t", what="time")
        except DataError:
            raise DataError(f"time unit '{t_unit}' is not a time", path=where,
                            line=header_line, column="t") from None
    check_time(t, path=where, lines=lines, gap_factor=gap_factor)
    return t + 0.0


def _given_dt(dt, where: str) -> float:
    """``dt`` (a sample interval given to :func:`read_record`) as a float.

    Raises
    ------
    DataError
        ``dt`` is not a positive finite number.
    """
    if not (isinstance(dt, (int, float)) and np.isfinite(dt) and dt > 0):
        raise DataError(f"the sample interval dt = {dt!r} is not a positive number of seconds",
                        path=where)
    return float(dt)


def _check_dt(t: np.ndarray, dt: float, given: bool, where: str) -> None:
    """Refuse a time column whose median step differs from ``dt`` by more
    than 1 % (``given``: ``dt`` came from the caller, else the sidecar).

    Raises
    ------
    DataError
        Naming ``where`` (the CSV for a given ``dt``, else the sidecar).
    """
    med = float(np.median(np.diff(t)))
    if abs(med - dt) > 0.01 * dt:
        what = f"the sample interval given, dt = {dt:g} s," if given else f"sidecar dt = {dt:g} s"
        raise DataError(f"{what} but the median time step is {med:.6g} s", path=where)


def _renamed(names: list[str], data: dict, units: dict, meta: Mapping,
             columns: Mapping[str, str], where: str, header_line: int) -> list[str]:
    """``names`` with each ``columns`` key replaced by its value, and the
    same done in place to ``data``, ``units`` and the sidecar's column
    entries (``meta``).

    Raises
    ------
    DataError
        A column to rename that the file lacks, the time column, a new name
        that is empty or that another column already has.
    """
    for old, new in columns.items():
        if old not in names:
            raise DataError(f"no column '{old}' to rename to '{new}' (the record has: "
                            f"{', '.join(n for n in names if n != 't')})", path=where,
                            line=header_line, column=old)
        if old == "t" or new == "t":
            raise DataError("the time column is not renamed", path=where, line=header_line,
                            column=old)
    out = [columns.get(n, n) for n in names]
    for new in set(columns.values()):
        if not new or out.count(new) > 1:
            raise DataError(f"renaming gives two columns named '{new}'" if new
                            else "a column renamed to an empty name", path=where,
                            line=header_line, column=new or None)
    side = (meta.get("columns") or {}) if meta else {}
    for table in (data, units, side):
        # rebuilt in place under the new names, in the file's order
        items = [(columns.get(k, k), v) for k, v in table.items()]
        table.clear()
        table.update(items)
    return out


def _read_columns(path: Path, meta: Mapping, allow_missing: bool,
                  given: Mapping[str, str] | None = None) -> tuple:
    """The CSV's column names, values by name (``t`` included, file units),
    units by name (``given`` by the file's names, else the header's, else
    the sidecar ``meta``'s), the file line of each sample and the header's
    line."""
    where, side = str(path), str(path.with_suffix(".json"))
    header, header_line, rows, lines, delimiter = _read_csv_rows(path)
    dt = float(meta["dt"]) if meta and meta.get("dt") else None
    parsed, trailing, time_name = _parse_header_row(header, where, header_line,
                                                    timeless=dt is not None)
    names = [p[0] for p in parsed]
    _check_row_lengths(rows, lines, len(names), trailing, where)
    line_arr = np.asarray(lines)
    cells = np.array(rows, dtype=str)
    if delimiter != "," and not np.any(np.char.find(cells, ".") >= 0):
        # ``1,5;2,25``: decimal commas (the lists of spreadsheets set to a
        # European locale), only where no cell of the file has a point: in a
        # file that writes points, ``1,234`` is a thousands separator and
        # stays non-numeric, as does ``1.234,5``
        cells = np.char.replace(cells, ",", ".")
    side_cols = (meta.get("columns") or {}) if meta else {}
    if time_name != "t" and time_name in side_cols and "t" not in side_cols:
        side_cols["t"] = side_cols.pop(time_name)
    units = _column_units(parsed, side_cols, where, side, header_line, given or {})
    roles = {nm: (side_cols.get(nm) or {}).get("role") for nm in names}
    data: dict[str, np.ndarray] = {}
    for j, nm in enumerate(names):
        data[nm] = _column_values(np.char.strip(cells[:, j]), nm, roles.get(nm),
                                  allow_missing, where, line_arr)
    if not time_name:
        # no time column: the samples at k dt (the given sample interval)
        names = ["t", *names]
        data = {"t": np.arange(line_arr.size) * dt, **data}
        units = {"t": "s", **units}
    return names, data, units, line_arr, header_line


# --------------------------------------------------------------- writing
def write_record(path: str | Path, t, columns: Mapping[str, Any], units: Mapping,
                 meta: Mapping, name: str, *, precision: int | None = None,
                 sidecar: bool = True) -> Path:
    """Write a record's CSV (and its JSON sidecar): what
    :meth:`~bondgraph.data.records.Experiment.save` does.

    Parameters
    ----------
    path : str or Path
        Target ``.csv`` (the suffix is added if missing).
    t : array (N,)
        Times [s].
    columns : dict of str -> array (N,)
        Every column except ``t``, in the order of the file.
    units : dict of str -> str or None
        Unit of each column (the header's brackets).
    meta : mapping
        Sidecar content (:func:`sidecar_text`).
    name : str
        The record's name, for a sidecar without one.
    precision : int, optional
        Significant digits (``%.{precision}g``). Default: the shortest
        text that reads back to the identical float64 (Python ``repr``).
        NaN is written as an empty cell.
    sidecar : bool
        Also write ``<stem>.json`` (an old sidecar is removed either way).

    Returns
    -------
    Path
        The CSV path.
    """
    path = Path(path)
    if path.suffix.lower() != ".csv":
        path = path.with_name(path.name + ".csv")
    path.parent.mkdir(parents=True, exist_ok=True)
    names = ["t", *columns]
    header = [format_header("t", "s")] + [format_header(c, units.get(c))
                                          for c in columns]
    cols = []
    for arr in [t, *columns.values()]:
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
    side_text = sidecar_text(meta, name, units, names) if sidecar else None
    # never a new CSV beside the old sidecar: the old one goes first
    path.with_suffix(".json").unlink(missing_ok=True)
    atomic.write_text(path, buf.getvalue())
    if side_text is not None:
        atomic.write_text(path.with_suffix(".json"), side_text)
    return path


def sidecar_text(meta: Mapping, name: str, units: Mapping, names: list[str]) -> str:
    """The JSON sidecar of a record (``format`` first, the documented keys
    in their order, then the others).

    Parameters
    ----------
    meta : mapping
        Sidecar content (copied, not changed).
    name : str
        ``name`` where ``meta`` has none.
    units : dict of str -> str or None
        Unit of each column (``t`` is in s).
    names : list of str
        The columns, ``t`` first, in the order of the CSV.

    Returns
    -------
    str
    """
    meta = copy.deepcopy(meta)
    meta = {"format": FORMAT, **{k: v for k, v in meta.items() if k != "format"}}
    meta.setdefault("name", name)
    info = meta.setdefault("columns", {})
    for c in names:
        entry = dict(info.get(c) or {})
        entry["unit"] = "s" if c == "t" else units.get(c)
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


# ------------------------------------------------------------- internals
def _delimiter(path: Path) -> str:
    """The cell separator: ``,``, or ``;`` or a tab where the header line
    has no comma (the first non-blank line decides)."""
    with open(path, newline="", encoding="utf-8-sig") as fh:
        for line in fh:
            if line.strip():
                if "," in line:
                    return ","
                if ";" in line:
                    return ";"
                if "\t" in line:
                    return "\t"
                return ","
    return ","


def _read_csv_rows(path: Path) -> tuple[list[str], int, list[list[str]], list[int], str]:
    """The header row, its line, the data rows, their lines and the cell
    separator (blank lines skipped; a UTF-8 byte-order mark is dropped).

    Raises
    ------
    DataError
        An empty file.
    """
    delimiter = _delimiter(path)
    with open(path, newline="", encoding="utf-8-sig") as fh:
        reader = csv.reader(fh, delimiter=delimiter)
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
    return header, header_line, rows, lines, delimiter


def _parse_header_row(header: list[str], where: str, header_line: int,
                      timeless: bool = False) -> tuple[list[tuple[str, str | None]], bool, str]:
    """``(name, unit)`` per header cell, whether the lines end in a trailing
    comma (an empty last header cell) and the time column's name in the file
    ("" when ``timeless`` (a sample interval is given) and the file has
    none). A first column named ``time`` (any case) or
    ``t_<unit>``/``time_<unit>`` (``s, ms, us, min, h``) is the time ``t``.

    Raises
    ------
    DataError
        Empty or duplicate names, ``t`` not first, or missing without
        ``timeless``.
    """
    trailing = len(header) > 1 and header[-1].strip() == ""
    if trailing:
        header = header[:-1]
    parsed = [parse_header(h) for h in header]
    time_name = parsed[0][0]
    tm = _TIME_RE.match(time_name)
    if tm is not None and time_name != "t" and "t" not in [p[0] for p in parsed[1:]]:
        # ``time``, ``Time (s)``, ``time_ms``: the time column under another name
        unit = parsed[0][1] if parsed[0][1] is not None else tm.group("unit")
        parsed[0] = ("t", unit)
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
        if timeless:
            return parsed, trailing, ""
        raise DataError(f"first column must be the time 't', found '{names[0]}'",
                        path=where, line=header_line, column=names[0],
                        hint="name the time column 't' or 'time' (unit in brackets, "
                             "e.g. 't [s]'); for a file without one (sampled at a fixed "
                             "interval) give the interval: --dt SECONDS on the command line, "
                             "or \"dt\" in the record's JSON sidecar")
    return parsed, trailing, time_name


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
                  side: str, header_line: int,
                  given: Mapping[str, str]) -> dict[str, str | None]:
    """Unit of each column: the one ``given`` with its new name (by the
    file's name), else the header's, else the sidecar's. A unit given
    replaces the file's: a logger's abbreviation that pint reads as another
    unit (``ccps``, cm³/s in ANL's D3 files, is centi-counts per second to
    pint) or does not know.

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
        if nm in given:
            check_unit(given[nm], where, nm)
            units[nm] = given[nm]
            continue
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
            check_unit(units[nm], where, nm)
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
    if fmt is None:
        misplaced = [k for k in ("noise_std", "hold", "unit", "role") if k in meta]
        raise DataError(
            f"the sidecar has no \"format\": \"{FORMAT}\" entry; a record's sidecar begins "
            f"{{\"format\": \"{FORMAT}\", \"columns\": {{\"<column>\": {{\"unit\": ..., "
            f"\"role\": ..., \"noise_std\": ...}}}}}} (docs/data_format.md)"
            + (f"; its top-level {', '.join(repr(k) for k in misplaced)} belong(s) to a column"
               if misplaced else ""), path=str(side))
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
    (one object per column, a text ``unit``) and ``noise``. Other keys are
    free, except the column keys ``noise_std``, ``hold``, ``unit`` and
    ``role`` at the top level: there they would be kept and never read (a
    user's top-level ``"noise_std": {"current": 0.01}`` left the noise
    estimated), so they are an error naming where they belong.

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
    for key in ("noise_std", "hold", "unit", "role"):
        if key in meta:
            raise bad(f"'{key}' at the top level is not read: it belongs to a column, e.g. "
                      f"\"columns\": {{\"<column>\": {{\"{key}\": ...}}}} (see the record "
                      f"format: docs/data_format.md)")
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


__all__ = ["FORMAT", "ROLES", "GAP_FACTOR", "parse_header", "format_header", "check_time",
           "check_unit", "check_meta", "check_sidecar_types", "read_record", "write_record",
           "sidecar_text", "read_table"]
