"""The toolkit's one JSON policy for results and sidecars.

Every JSON file the toolkit writes (``result.json`` of an estimation,
``sensitivity.json``, the loop's ``report.json``, a record's sidecar, the
stiffness report of ``bondgraph simulate --stiffness``) passes its content
through :func:`to_jsonable` and is dumped with ``allow_nan=False``, so the
files are strict JSON (RFC 8259 has no NaN or infinity) and the same value
is spelled the same way in every file. Readers that turn a file back into
objects pass the parsed content through :func:`from_jsonable`.

The policy
----------
========================================  =====================================
Python / numpy value                      JSON
========================================  =====================================
finite ``float``, ``numpy.floating``      number (``float``: shortest repr, so
                                          a write/read round trip is bit-exact)
NaN                                       ``null`` ("no value": a missing
                                          sample, an undefined statistic)
``+inf`` / ``-inf``                       the strings ``"inf"`` / ``"-inf"`` (an
                                          infinite value is a value: an
                                          unbounded step, a failed criterion)
``numpy.integer``                         number (``int``)
``bool``, ``numpy.bool_``                 ``true`` / ``false``
``numpy.ndarray`` (any shape, 0-d too)    nested lists, element by element
mapping                                   object; keys become ``str(key)``
``list``, ``tuple``                       array
dataclass instance                        object of its fields, in order
``pathlib.PurePath``                      string
anything else (``str``, ``int``, None)    unchanged (``json.dumps`` raises
                                          ``TypeError`` for what JSON cannot
                                          hold)
========================================  =====================================

:func:`from_jsonable` undoes the one lossy-looking step that it can: the
strings ``"inf"`` and ``"-inf"`` become float infinities again. ``null`` stays
``None``; a reader that knows a field is numeric turns it back into NaN
(``numpy.array(values, dtype=float)`` does so).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import PurePath
from typing import Any, Mapping

import numpy as np

#: JSON spelling of +inf and -inf
POS_INF = "inf"
NEG_INF = "-inf"


def to_jsonable(obj: Any) -> Any:
    """Convert ``obj`` (recursively) to values ``json.dumps(..., allow_nan=False)``
    accepts, by the policy of this module (NaN -> ``None``, ±inf ->
    ``"inf"``/``"-inf"``, numpy scalars and arrays -> Python numbers and lists,
    mappings -> dicts with string keys, tuples -> lists, dataclasses -> dicts
    of their fields, paths -> strings).

    Parameters
    ----------
    obj : any
        Nested mappings, sequences, numpy arrays and scalars, dataclass
        instances.

    Returns
    -------
    any
        A new structure; ``obj`` is not modified.

    Examples
    --------
    >>> to_jsonable({"a": np.array([1.0, np.nan, -np.inf]), 2: np.int64(3)})
    {'a': [1.0, None, '-inf'], '2': 3}
    """
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        if math.isfinite(v):
            return v
        if math.isnan(v):
            return None
        return POS_INF if v > 0 else NEG_INF
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, PurePath):
        return str(obj)
    return obj


def from_jsonable(obj: Any) -> Any:
    """Inverse of :func:`to_jsonable` on parsed JSON: the strings ``"inf"`` and
    ``"-inf"`` become ``float('inf')`` and ``float('-inf')``, recursively in
    dicts and lists; everything else is returned as is (``None`` stays
    ``None``).

    Parameters
    ----------
    obj : any
        The result of ``json.loads``.

    Returns
    -------
    any
        A new structure; ``obj`` is not modified.

    Examples
    --------
    >>> from_jsonable({"h": "inf", "x": [1.0, None, "-inf"], "name": "m"})
    {'h': inf, 'x': [1.0, None, -inf], 'name': 'm'}
    """
    if isinstance(obj, dict):
        return {k: from_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [from_jsonable(v) for v in obj]
    if isinstance(obj, str) and obj in (POS_INF, NEG_INF):
        return math.inf if obj == POS_INF else -math.inf
    return obj


__all__ = ["to_jsonable", "from_jsonable", "POS_INF", "NEG_INF"]
