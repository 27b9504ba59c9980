"""The graph to export or linearise, with estimated parameters as defaults.

A model reference resolves as in every command (a registered name,
``module:function`` or ``path/to/file.py:function``, e.g. the loop's
``augmented_model.py:build``); estimated values come from the JSON that
``bondgraph estimate`` writes (``result.json``: ``params``, ``estimates``,
``fixed``) or from the loop's ``report.json`` (``final_fit.estimates``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Mapping

from bondgraph.core.graph import BondGraph
from bondgraph.core.jsonsafe import from_jsonable
from bondgraph.errors import ExportError
from bondgraph.numerics import registry


def read_params(path: str | Path, *, estimated: bool = False,
                initial: bool = False) -> dict[str, float]:
    """Parameter values from an estimation result or a loop report.

    Parameters
    ----------
    path : str or Path
        ``result.json`` of ``bondgraph estimate`` (the estimates by name and
        the fixed values; of ``--fit sim`` too) or ``report.json`` of
        ``bondgraph loop`` (the final fit's estimates).
    estimated : bool
        Only the quantities the fit estimated (a result's fixed values left
        out).
    initial : bool
        From a loop's report, its initial fit (the declared graph's,
        ``initial_fit.estimates``) instead of the final one.

    Returns
    -------
    dict
        ``name -> value`` in model units; the estimated noise levels
        (``noise.<output>``) and initial states (``x0.<state>``) are not
        parameters of the graph and are left out.

    Raises
    ------
    ExportError
        The file is missing, not JSON, of neither format, or holds a value
        that is not a finite number (the parameter is named); ``initial``
        with a file that is not a loop's report.
    """
    path = Path(path)
    try:
        doc = from_jsonable(json.loads(path.read_text()))
    except FileNotFoundError:
        raise ExportError(f"parameter file {path} does not exist") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ExportError(f"parameter file {path} is not JSON: {exc}") from None
    which = "initial_fit" if initial else "final_fit"
    if isinstance(doc, dict) and isinstance(doc.get(which), dict) \
            and isinstance(doc[which].get("estimates"), dict):
        values = dict(doc[which]["estimates"])
    elif initial:
        raise ExportError(f"{path} is not a `bondgraph loop` report.json: it holds no initial "
                          f"fit (initial_fit.estimates)")
    elif isinstance(doc, dict) and doc.get("fit") == "sim" \
            and isinstance(doc.get("estimates"), dict):       # estimate --fit sim
        values = {**({} if estimated else dict(doc.get("fixed") or {})),
                  **dict(doc["estimates"])}
    elif isinstance(doc, dict) and isinstance(doc.get("params"), list) \
            and isinstance(doc.get("estimates"), list):
        if len(doc["params"]) != len(doc["estimates"]):
            raise ExportError(f"{path}: {len(doc['params'])} params but "
                              f"{len(doc['estimates'])} estimates")
        values = {**({} if estimated else dict(doc.get("fixed") or {})),
                  **dict(zip(doc["params"], doc["estimates"]))}
    else:
        raise ExportError(f"{path} is neither a `bondgraph estimate` result.json (params, "
                          f"estimates) nor a `bondgraph loop` report.json (final_fit.estimates)")
    out = {}
    for name, value in values.items():
        if str(name).startswith(("noise.", "x0.")):
            continue
        try:
            v = float(value)
        except (TypeError, ValueError):
            v = math.nan
        if not math.isfinite(v):
            raise ExportError(f"{path}: parameter '{name}' is {value!r}, not a finite number")
        out[str(name)] = v
    return out


def read_noise_levels(path: str | Path, *, initial: bool = False) -> dict[str, float]:
    """Measurement-noise levels of a fit: what :func:`read_params` leaves out.

    Parameters
    ----------
    path : str or Path
        ``result.json`` of ``bondgraph estimate`` (its ``noise.<output>``
        estimates, and the levels it held, ``settings.noise_levels``; with
        ``--fit sim``, ``noise_levels``: the declared levels or the RMS
        free-run errors) or
        ``report.json`` of ``bondgraph loop`` (the final fit's estimated
        levels, ``final_fit.noise_estimates``, and the held ones,
        ``settings.noise_levels``).
    initial : bool
        From a loop's report, its initial fit's levels instead of the final
        fit's.

    Returns
    -------
    dict
        ``output -> std`` (output units); the estimates over the held
        levels; {} when the file has none.

    Raises
    ------
    ExportError
        As :func:`read_params` (the file is read by it first).
    """
    read_params(path, initial=initial)      # the same errors for a bad file
    doc = from_jsonable(json.loads(Path(path).read_text()))
    held = (doc.get("settings") or {}).get("noise_levels") or doc.get("noise_levels") or {}
    out = {}
    for o, v in held.items():               # estimate: {"std": .., "how": ..}; loop: a number
        v = v.get("std") if isinstance(v, dict) else v
        out[str(o)] = v
    which = "initial_fit" if initial else "final_fit"
    if isinstance(doc.get(which), dict):
        out.update((doc[which].get("noise_estimates") or {}))
    elif isinstance(doc.get("params"), list):
        out.update({n[len("noise."):]: v for n, v in zip(doc["params"], doc["estimates"])
                    if str(n).startswith("noise.")})
    levels = {}
    for o, v in out.items():
        try:
            f = float(v)
        except (TypeError, ValueError):
            continue
        if math.isfinite(f) and f > 0:
            levels[str(o)] = f
    return levels


def read_initial_states(path: str | Path) -> tuple[Path | None, dict[str, float]]:
    """The initial states a fit estimated with θ (``--estimate-x0``) and the
    record they belong to: what :func:`read_params` leaves out besides the
    noise levels.

    Parameters
    ----------
    path : str or Path
        ``result.json`` of ``bondgraph estimate``.

    Returns
    -------
    (Path or None, dict)
        The record the fit was made on, by its absolute path
        (``settings.data_path``; None when it was fitted on several, or the
        file does not say) and ``state -> value`` (state units) of
        its estimated initial states ({} when there are none, or the file
        is a loop's report).

    Raises
    ------
    ExportError
        As :func:`read_params` (the file is read by it first).
    """
    read_params(path)                       # the same errors for a bad file
    doc = from_jsonable(json.loads(Path(path).read_text()))
    # the record's absolute path: a relative one ("rec.csv") would match another
    # folder's record of that name where compare runs elsewhere
    data = (doc.get("settings") or {}).get("data_path")
    if not isinstance(doc.get("params"), list) or not isinstance(data, str):
        return None, {}
    x0 = {n[len("x0."):]: float(v) for n, v in zip(doc["params"], doc["estimates"])
          if str(n).startswith("x0.") and math.isfinite(float(v))}
    return (Path(data) if x0 else None), x0


def model_graph(spec: str | BondGraph, params: Mapping[str, float] | None = None) -> BondGraph:
    """The graph named by ``spec`` with ``params`` as its parameter defaults.

    Parameters
    ----------
    spec : str or BondGraph
        Registered name, ``module:function`` or ``path/to/file.py:function``
        (:func:`bondgraph.numerics.registry.graph_builder`), or a graph (copied).
    params : mapping, optional
        ``name -> value`` (model units), e.g. from :func:`read_params`.

    Returns
    -------
    BondGraph

    Raises
    ------
    ModelError
        Unknown model reference.
    ExportError
        A parameter the model does not have (the unknown and the known names).
    """
    g = spec.copy(spec.name) if isinstance(spec, BondGraph) else registry.graph_builder(spec)()
    params = dict(params or {})
    unknown = sorted(set(params) - set(g.params))
    if unknown:
        raise ExportError(f"model '{g.name}' has no parameter(s) {', '.join(unknown)} "
                          f"(its parameters: {', '.join(g.params)})",
                          hint="give the parameters of this model; a loop's report.json "
                               "goes with its augmented_model.py:build")
    for name, value in params.items():
        g.params[name].default = float(value)
    return g
