"""Derivations and generated code of graphs built in memory, kept on disk.

The residual-tracing loop builds dozens of candidate graphs (the declared
graph plus one effect at one place) and derives and generates each in memory
(:meth:`bondgraph.numerics.model.Model.from_graph`): 0.1-0.3 s of sympy per
candidate, about 9 s of a 40-80 s warm ``bondgraph loop`` on the bundled case,
the same candidates on every run and in every test that runs a loop.

This module keeps ``(state space, generated source)`` under a fingerprint of
the graph: the SHA-256 of its canonical text (:func:`canonical_text`: the
graph's contents in declaration order, sympy expressions by ``srepr``, not a
pickle, whose bytes depend on which equal objects happen to be one object),
the functions asked for, and the version of the code that derives and
generates (the sources of :mod:`bondgraph.core`, the versions of sympy, pint
and Python).
Any change of the graph, a parameter's default or box, or the deriving code
gives another key, so a stale entry is never read. A graph that holds a
Python closure or a sympy function class of the user's is simply not cached.

The folder is ``<kernel cache>/models`` (:func:`bondgraph.numerics.compiled.cache_dir`:
``$BONDGRAPH_CACHE_DIR``, else ``~/.cache/bondgraph/numba``); entries are
written atomically, an unreadable entry is ignored and rewritten, and a
folder that cannot be written only costs the time saved.
"""

from __future__ import annotations

import enum
import functools
import hashlib
import pickle
import sys
import types
from importlib import metadata   # pint's version without importing pint (~0.4 s)
from pathlib import Path

import numpy as np
import sympy as sp

from bondgraph.core import atomic
from bondgraph.numerics.compiled import cache_dir

#: bump to drop every entry written before (a change of the entry format)
FORMAT = 1


@functools.cache
def code_version() -> str:
    """Digest of what derives and generates: the sources of
    :mod:`bondgraph.core` (read once per process), the versions of sympy,
    pint (units of derived states) and Python, and :data:`FORMAT`."""
    versions = f"{FORMAT}|{sp.__version__}|{metadata.version('pint')}|{sys.version_info[:3]}"
    h = hashlib.sha256(versions.encode())
    core = Path(atomic.__file__).parent
    for path in sorted(core.glob("*.py")):
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()


class Uncacheable(Exception):
    """Part of a graph that has no canonical text (a closure, a lambda, an
    object of a type the fingerprint does not know)."""


def graph_key(graph, *parts: str) -> str | None:
    """The fingerprint of ``graph`` with ``parts`` (what is generated from
    it) under this code version (:func:`code_version`): the SHA-256 of the
    graph's canonical text (:func:`canonical_text`); None when the graph
    holds something without one."""
    try:
        text = canonical_text(graph)
    except (Uncacheable, RecursionError):
        return None
    h = hashlib.sha256(code_version().encode())
    h.update(text.encode())
    for p in parts:
        h.update(b"\0" + p.encode())
    return h.hexdigest()[:32]


def canonical_text(obj) -> str:
    """A text that two equal graphs share whatever the identity of their
    parts: sympy expressions by ``srepr`` (whether two equal expressions
    are one object depends on sympy's cache, that is on what the process
    did before), numbers and strings by ``repr``, arrays by dtype, shape
    and bytes, sets sorted, objects by their class and attributes in order,
    an object met again by the index of its first visit (the graph's own
    cycles: an element and its bonds).

    Raises
    ------
    Uncacheable
        A lambda or closure, a sympy function class defined outside sympy
        and bondgraph, or an object of another kind.
    """
    out: list[str] = []
    _canon(obj, out, {})
    return "".join(out)


_ATOMS = (type(None), bool, int, float, complex, str, bytes)


def _canon(obj, out: list, seen: dict) -> None:
    """:func:`canonical_text` of ``obj`` appended to ``out``."""
    if isinstance(obj, (sp.Basic, sp.MatrixBase)):
        out.append(f"S{_sympy_text(obj)};")
    elif isinstance(obj, _ATOMS) or isinstance(obj, (enum.Enum, np.generic)):
        out.append(f"{type(obj).__name__}:{obj!r};")
    elif isinstance(obj, np.ndarray):
        data = hashlib.sha256(np.ascontiguousarray(obj).tobytes()).hexdigest()
        out.append(f"A{obj.dtype}{obj.shape}{data};")
    elif id(obj) in seen:
        out.append(f"@{seen[id(obj)][0]};")
    else:
        # the object is kept with its index: a temporary (an attribute dict)
        # freed during the walk would hand its id to another object
        seen[id(obj)] = (len(seen), obj)
        _canon_container(obj, out, seen)


def _canon_container(obj, out: list, seen: dict) -> None:
    """:func:`_canon` of a container, a function or an object with attributes."""
    if isinstance(obj, (list, tuple)):
        out.append(f"{type(obj).__name__}[")
        for v in obj:
            _canon(v, out, seen)
        out.append("]")
    elif isinstance(obj, dict):
        out.append(f"{type(obj).__name__}{{")
        for k, v in obj.items():
            _canon(k, out, seen)
            _canon(v, out, seen)
        out.append("}")
    elif isinstance(obj, (set, frozenset)):
        out.append("set{" + "".join(sorted(canonical_text(v) for v in obj)) + "}")
    elif isinstance(obj, (types.FunctionType, types.BuiltinFunctionType, type)):
        name = f"{obj.__module__}.{obj.__qualname__}"
        if "<" in name:
            raise Uncacheable(name)
        out.append(f"F{name};")
    elif hasattr(obj, "__dict__") or hasattr(type(obj), "__slots__"):
        out.append(f"O{type(obj).__module__}.{type(obj).__qualname__}(")
        _canon(_attributes(obj), out, seen)
        out.append(")")
    else:
        raise Uncacheable(type(obj).__qualname__)


def _attributes(obj) -> dict:
    """The instance attributes of ``obj`` (``__dict__`` and ``__slots__``)."""
    attrs = dict(getattr(obj, "__dict__", {}))
    for cls in type(obj).__mro__:
        for name in getattr(cls, "__slots__", ()):
            if name not in attrs and hasattr(obj, name):
                attrs[name] = getattr(obj, name)
    return attrs


def _sympy_text(expr) -> str:
    """``srepr`` of ``expr``; a bondgraph symbol met on its own (a graph's
    parameter, input or state) with its metadata, which ``srepr`` does not
    print (a parameter's default, unit and box). Inside an expression a
    symbol counts by its name only: sympy's cache may hand a new graph an
    expression built from an earlier graph's equal symbols, whose metadata
    the earlier derivation changed (a state's unit). A function class of its
    own (not sympy's, not bondgraph's) makes it uncacheable, since its code
    is not in the text."""
    if isinstance(expr, sp.Symbol) and hasattr(expr, "meta"):
        return f"{sp.srepr(expr)}{canonical_text(expr.meta())}"
    for f in expr.atoms(sp.Function):
        mod = type(f).__module__ or ""
        if not mod.startswith(("sympy", "bondgraph")):
            raise Uncacheable(f"{mod}.{type(f).__name__}")
    return sp.srepr(expr)


def _path(key: str) -> Path:
    return cache_dir() / "models" / f"{key}.pkl"


def load(key: str | None):
    """The value stored under ``key``, or None (no key, no entry, or an
    entry that cannot be read)."""
    if key is None:
        return None
    try:
        return pickle.loads(_path(key).read_bytes())
    except Exception:  # noqa: BLE001 - missing, truncated or foreign entry: derive again
        return None


def store(key: str | None, value) -> None:
    """Keep ``value`` under ``key`` (nothing when ``key`` is None or the
    folder cannot be written: the cache only saves time)."""
    if key is None:
        return
    path = _path(key)
    try:
        data = pickle.dumps(value, protocol=4)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic.write_bytes(path, data)
    except Exception:  # noqa: BLE001 - a read-only or full disk only costs time
        return
