"""Registration: what installed packages add to the toolkit, and how a
``module:function`` reference is imported.

Kinds of registered objects (each a dict ``name -> "module:function"``):

``models``
    functions returning a :class:`~bondgraph.core.graph.BondGraph`
    (``bondgraph generate`` writes their generated code);
``experiments``
    functions returning an :class:`~bondgraph.data.experiments.ExperimentSpec`;
``cases``
    functions returning a :class:`~bondgraph.diagnose.cases.LoopCase`
    (``bondgraph loop --case NAME``);
``generated``
    the package that holds the generated code of registered models
    (``name -> "package"``; the first one found is used).

A package registers through entry points in its ``pyproject.toml``, each
naming a dict::

    [project.entry-points."bondgraph.models"]
    mypkg = "mypkg.graphs:MODELS"

or at run time with :func:`register`. The toolkit itself registers its
reference graphs, benchmark graphs and bundled cases the same way; the
library code names no application package.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, Mapping

from bondgraph.errors import ModelError

KINDS = ("models", "experiments", "cases", "generated")

#: run-time registrations: kind -> {name: "module:function"}
_RUNTIME: dict[str, dict[str, str]] = {k: {} for k in KINDS}


def _check_kind(kind: str) -> None:
    if kind not in KINDS:
        raise ModelError(f"unknown registration kind '{kind}' (kinds: {', '.join(KINDS)})")


def register(kind: str, entries: Mapping[str, str]) -> None:
    """Register ``name -> "module:function"`` entries of one kind at run time.

    Raises
    ------
    ModelError
        Unknown kind, or a name already registered with another target.
    """
    _check_kind(kind)
    known = registered(kind)
    for name, spec in entries.items():
        if name in known and known[name] != spec:
            raise ModelError(f"{kind[:-1]} '{name}' registered twice ({known[name]} and {spec})")
        _RUNTIME[kind][name] = spec


def unregister(kind: str, name: str) -> None:
    """Remove a run-time registration (entry points stay)."""
    _check_kind(kind)
    _RUNTIME[kind].pop(name, None)


def registered(kind: str) -> dict[str, str]:
    """Everything registered of one kind: entry points of the group
    ``bondgraph.<kind>`` (each a dict), then run-time registrations.

    Returns
    -------
    dict
        ``name -> "module:function"``.

    Raises
    ------
    ModelError
        A name registered twice with different targets, or an entry point
        that is not a dict.
    """
    _check_kind(kind)
    out: dict[str, str] = {}
    for ep in sorted(entry_points(group=f"bondgraph.{kind}"), key=lambda e: e.name):
        table = ep.load()
        if kind == "generated" and isinstance(table, type(sys)):
            table = {ep.name: table.__name__}
        if not isinstance(table, Mapping):
            raise ModelError(f"entry point '{ep.name} = {ep.value}' of group 'bondgraph.{kind}' "
                             f"must name a dict of name -> 'module:function'")
        for k, v in table.items():
            if k in out and out[k] != v:
                raise ModelError(f"{kind[:-1]} '{k}' registered twice ({out[k]} and {v})")
            out[k] = v
    for k, v in _RUNTIME[kind].items():
        if k in out and out[k] != v:
            raise ModelError(f"{kind[:-1]} '{k}' registered twice ({out[k]} and {v})")
        out[k] = v
    return out


def _pin_generated() -> None:
    """Import the registered packages of generated code (group
    ``bondgraph.generated``) before a user's folder goes first on the import
    path. A folder of the same name there (a loop's output folder holds its
    augmented model's code in ``generated/``; a user's project may have one)
    would otherwise shadow the package: as a namespace package under an
    editable install, or as the user's own package."""
    try:
        registered("generated")
    except ModelError:
        pass  # said where the package is used (registry.generated_dir)


def _import_file(path: Path):
    """Import a Python file as a module named after its stem (its folder goes on
    the import path, so that it can import its neighbours)."""
    path = path.resolve()
    name = path.stem
    folder = str(path.parent)
    if folder not in sys.path:
        _pin_generated()
        sys.path.insert(0, folder)
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ModelError(f"cannot import '{path}': not a Python file")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    try:
        spec.loader.exec_module(mod)
    except Exception as exc:
        sys.modules.pop(name, None)
        raise ModelError(f"importing '{path}' failed: {type(exc).__name__}: {exc}") from exc
    return mod


def resolve(spec: str) -> Any:
    """Import the object named by ``module:attribute`` or
    ``path/to/file.py:attribute``.

    The current directory is on the import path, so a module ``mymod.py`` in
    it is found as ``mymod:fn``.

    Raises
    ------
    ModelError
        Malformed reference, a module that cannot be imported (named, with the
        cause), or a missing attribute.
    """
    modname, sep, attr = str(spec).rpartition(":")
    if not sep or not modname or not attr or not attr.isidentifier():
        raise ModelError(f"'{spec}' is not a reference of the form module:function or "
                         f"path/to/file.py:function")
    if modname.endswith(".py") or "/" in modname or "\\" in modname:
        path = Path(modname)
        if not path.is_file():
            raise ModelError(f"'{spec}': no file '{path}'")
        mod = _import_file(path)
    else:
        cwd = str(Path.cwd())
        if cwd not in sys.path and "" not in sys.path:
            _pin_generated()
            sys.path.insert(0, cwd)
        try:
            mod = importlib.import_module(modname)
        except ModuleNotFoundError as exc:
            raise ModelError(f"'{spec}': module '{modname}' is not importable ({exc}); modules "
                             f"are looked up on the Python path and in the current directory "
                             f"{cwd}") from exc
        except Exception as exc:
            raise ModelError(f"'{spec}': importing module '{modname}' failed: "
                             f"{type(exc).__name__}: {exc}") from exc
    try:
        return getattr(mod, attr)
    except AttributeError:
        raise ModelError(f"'{spec}': module '{mod.__name__}' has no attribute '{attr}'") from None
