"""Registered models: ``name -> "module:function"`` building a BondGraph.

``bondgraph generate`` writes ``<generated package>/<name>.py`` (numpy) and
``<generated package>/numba_kernels/<name>.py`` (numba point kernels, from the
same derivation) for every registered model; ``bondgraph generate --check``
fails, naming the stale model, when either file differs from what its graph
produces (a test runs it).

Models are registered through :mod:`bondgraph.core.plugins` (entry points of the
group ``bondgraph.models``, or :func:`bondgraph.core.plugins.register`): the
toolkit's reference and benchmark graphs (:mod:`bondgraph.catalog`) and any
installed application package (the vehicle's ``vehicle_graphs``).
"""

from __future__ import annotations

import difflib
import importlib
import inspect
import time
from pathlib import Path

from bondgraph.core import plugins
from bondgraph.core.causality import STATIC_STATE
from bondgraph.core.codegen import generate_source
from bondgraph.core.codegen_c import generate_c_source
from bondgraph.core.codegen_numba import generate_numba_source
from bondgraph.core.equations import derive
from bondgraph.core.graph import BondGraph
from bondgraph.errors import BondGraphError, ModelError, StaleGeneratedCodeError

COMMAND = "bondgraph generate"


def registered() -> dict[str, str]:
    """All registered models, ``name -> "module:function"``."""
    return plugins.registered("models")


def resolve(spec: str):
    """Import ``module:function`` or ``path/file.py:function``
    (:func:`bondgraph.core.plugins.resolve`)."""
    return plugins.resolve(spec)


def build(name: str):
    """Build the BondGraph of a registered model (``graph.source`` is set).

    Raises
    ------
    ModelError
        Unknown name (the registered ones are listed).
    """
    reg = registered()
    if name not in reg:
        raise ModelError(f"unknown model '{name}' (registered: {', '.join(sorted(reg))})")
    g = resolve(reg[name])()
    g.source = reg[name]
    if g.name != name:
        g.name = name
    return g


def graph_builder(spec: str):
    """A function building the graph named by ``spec``: a registered model
    name, ``module:function`` or ``path/to/file.py:function`` (the current
    directory is on the import path).

    The builder is checked before it is called (:func:`check_builder`), and
    what it returns must be a :class:`~bondgraph.core.graph.BondGraph`.

    Raises
    ------
    ModelError
        Unknown name, module not importable, attribute missing, not a
        function that can be called without arguments, a builder that fails
        (the cause named) or does not return a BondGraph.
    """
    if spec in registered():
        return lambda: build(spec)
    if ":" not in spec:
        close = difflib.get_close_matches(spec, list(registered()), n=3, cutoff=0.5)
        raise ModelError(f"unknown model '{spec}': give a registered name "
                         f"({', '.join(sorted(registered()))}), module:function or "
                         f"path/to/file.py:function",
                         hint=f"did you mean {' or '.join(repr(c) for c in close)}?"
                         if close else None)
    fn = check_builder(spec, resolve(spec))

    def make():
        try:
            g = fn()
        except BondGraphError:
            raise
        except Exception as exc:
            raise ModelError(f"building the graph with '{spec}' failed{_user_line(exc)}: "
                             f"{type(exc).__name__}: {exc}", hint=_symbolic_hint(exc)) from exc
        if not isinstance(g, BondGraph):
            raise ModelError(f"'{spec}' returned {_a(type(g).__name__)}, not a BondGraph")
        g.source = spec
        return with_a_state(g)
    return make


def with_a_state(graph: BondGraph) -> BondGraph:
    """``graph`` itself, given an inert signal state z (dz/dt = 0, z(0) = 0,
    read by no law; named :data:`STATIC_STATE`) where it has no state of
    its own: every storage in derivative causality, no signal state (a
    dyno that imposes the measured speed on the vehicle's inertia, the fuel
    flow an algebraic function of the wheel power). Its outputs are then
    algebraic functions of its inputs; the filter's sigma points, the
    smoother and the free runs need a state dimension (a user's static
    Camry graph: "sigma points need a state dimension >= 1" from estimate,
    compare, sensitivity and loop). z changes no output: the likelihood is
    the static model's (innovations y − h(u), covariance R), and an effect
    the loop adds (a thermal state) brings states of its own. The state's
    description says why it is there.

    Returns
    -------
    BondGraph
        ``graph`` (changed in place when it had no state).
    """
    from bondgraph.core.causality import assign_causality
    from bondgraph.core.elements import C, CField, I, IField

    if graph.signal_states:
        return graph
    storages = sum(len(e.ports) if isinstance(e, (CField, IField)) else 1
                   for e in graph.elements.values() if isinstance(e, (I, C, CField, IField)))
    if storages > len(assign_causality(graph).derivative):
        return graph
    graph.state(STATIC_STATE, rhs=0, unit="1", initial=0.0,
                description="inert state: the graph has no state of its own (its outputs are "
                            "algebraic functions of its inputs), and the filter and the free "
                            "runs need one; it changes no output")
    return graph


#: words of the errors numpy, math and Python's ``if`` raise on a sympy symbol
_NOT_SYMBOLIC = ("ufunc", "convert expression to float", "truth value of Relational",
                 "cannot determine truth value")


def _user_line(exc: BaseException) -> str:
    """`` at FILE:LINE (source)``: the innermost frame of the builder's
    traceback outside bondgraph, sympy and numpy (the user's line), or ''."""
    import traceback

    skip = (str(Path(__file__).resolve().parents[1]), "site-packages", "<frozen", "/lib/python")
    for fr in reversed(traceback.extract_tb(exc.__traceback__)):
        if not any(s in str(fr.filename) for s in skip):
            code = f" ({fr.line.strip()})" if fr.line else ""
            return f" at {Path(fr.filename).name}:{fr.lineno}{code}"
    return ""


def _symbolic_hint(exc: BaseException) -> str | None:
    """What to write instead when a law used numpy, math or a Python ``if``
    on the graph's sympy symbols (their errors name neither the law nor the
    cause)."""
    text = str(exc)
    if isinstance(exc, TypeError) and any(w in text for w in _NOT_SYMBOLIC):
        return ("laws are sympy expressions of the graph's symbols: write sp.sqrt, sp.exp, "
                "sp.tanh ... (not numpy's or math's), and a branch as sp.Piecewise or "
                "sp.Max/sp.Min (not a Python if)")
    return None


#: return annotations that cannot be a BondGraph
_NOT_GRAPHS = ("None", "int", "float", "str", "bool", "dict", "list", "tuple", "set", "bytes")


def _a(word: str) -> str:
    return f"{'an' if word[:1].lower() in 'aeiou' else 'a'} {word}"


def check_builder(spec: str, fn):
    """``fn`` if it can be a graph builder: a function (or BondGraph class)
    callable without arguments whose return annotation, if any, is not a
    type other than BondGraph. Checked without calling it.

    Raises
    ------
    ModelError
        Naming ``spec`` and what ``fn`` is.
    """
    if isinstance(fn, type):
        if issubclass(fn, BondGraph):
            return fn
        raise ModelError(f"'{spec}' is the class {fn.__name__}, not a function returning a "
                         f"BondGraph")
    if not callable(fn):
        raise ModelError(f"'{spec}' is {_a(type(fn).__name__)}, not a function returning a "
                         f"BondGraph")
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return fn                       # a builtin without a signature: try it
    needed = [p.name for p in sig.parameters.values()
              if p.default is p.empty and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
    if needed:
        raise ModelError(f"'{spec}' needs the argument(s) {', '.join(needed)}; a graph builder "
                         f"is called without arguments",
                         hint="wrap it: def build(): return " + spec.rsplit(":", 1)[1] + "(...)")
    ret = sig.return_annotation
    name = ret if isinstance(ret, str) else getattr(ret, "__name__", None)
    if ret is not sig.empty and (name in _NOT_GRAPHS or ret is None or (
            isinstance(ret, type) and not issubclass(ret, BondGraph))):
        raise ModelError(f"'{spec}' is annotated to return {name or ret!r}, not a BondGraph")
    return fn


def generated_dir() -> Path:
    """The package directory that holds generated code of registered models
    (registered as kind ``generated``)."""
    pkgs = plugins.registered("generated")
    if not pkgs:
        raise ModelError("no package for generated code is registered (entry point group "
                         "'bondgraph.generated')")
    name = pkgs[sorted(pkgs)[0]]
    mod = importlib.import_module(name)
    if getattr(mod, "__file__", None) is None:
        where = ", ".join(str(p) for p in getattr(mod, "__path__", []))
        raise ModelError(f"the package '{name}' of generated code is shadowed by a folder of "
                         f"that name on the import path ({where}): run from another folder, "
                         f"or rename that folder")
    return Path(mod.__file__).parent


def render(name: str) -> str:
    """Source text that ``bondgraph generate`` writes for model ``name``."""
    return render_files(name)[f"{name}.py"]


#: sub-package of the generated package holding the numba point kernels
NUMBA_DIR = "numba_kernels"
#: folder of the generated package holding the C99 functions (FMU export)
C_DIR = "c"


def render_files(name: str) -> dict[str, str]:
    """Every file ``bondgraph generate`` writes for model ``name``, by path
    relative to the generated package: the numpy module ``<name>.py``, its
    numba point kernels ``numba_kernels/<name>.py`` and its C99 functions
    ``c/<name>.c`` (:mod:`bondgraph.core.codegen_c`), all from one
    derivation."""
    g = build(name)
    ss = derive(g)
    return {f"{name}.py": generate_source(ss, source=g.source, command=COMMAND),
            f"{NUMBA_DIR}/{name}.py": generate_numba_source(ss, source=g.source,
                                                           command=COMMAND),
            f"{C_DIR}/{name}.c": generate_c_source(ss, source=g.source, command=COMMAND)}


def numba_path(name: str, directory: Path | None = None) -> Path:
    """Path of the numba point kernels of a registered model."""
    return Path(directory or generated_dir()) / NUMBA_DIR / f"{name}.py"


def c_path(name: str, directory: Path | None = None) -> Path:
    """Path of the C99 functions of a registered model (``c/<name>.c``)."""
    return Path(directory or generated_dir()) / C_DIR / f"{name}.c"


def generate(names=None, *, check: bool = False, directory: Path | None = None,
             verbose: bool = True) -> list[str]:
    """(Re)generate registered models, or check them.

    Parameters
    ----------
    names : list of str, optional
        Models to process (default: all registered).
    check : bool
        Do not write; return the names of which a file (numpy module or numba
        kernels) is missing or differs.
    directory : Path, optional
        Target directory (default :func:`generated_dir`).

    Returns
    -------
    list of str
        Stale models (check) or written models.
    """
    directory = Path(directory) if directory else generated_dir()
    names = sorted(registered()) if not names else list(names)
    out = []
    init = directory / NUMBA_DIR / "__init__.py"
    if not check and not init.exists():
        init.parent.mkdir(parents=True, exist_ok=True)
        init.write_text("")
    for n in names:
        t0 = time.perf_counter()
        files = render_files(n)
        if check:
            stale = [rel for rel, text in files.items()
                     if not _same_file(directory / rel, text, verbose)]
            if not init.exists():
                stale.append(f"{NUMBA_DIR}/__init__.py")
                if verbose:
                    print(f"STALE {n}: {init} is missing")
            if stale:
                out.append(n)
            elif verbose:
                print(f"ok    {n}")
            continue
        written = [rel for rel, text in files.items() if _write_if_changed(directory / rel, text)]
        if written:
            out.append(n)
        if verbose:
            for rel in files:
                state = "wrote" if rel in written else "same "
                print(f"{state} {directory / rel}"
                      + (f" ({time.perf_counter() - t0:.2f} s)" if rel in written else ""))
    return out


def _same_file(path: Path, text: str, verbose: bool) -> bool:
    """Whether ``path`` holds ``text``; prints the start of the diff if not."""
    old = path.read_text() if path.exists() else None
    if old == text:
        return True
    if verbose:
        name = path.stem
        if old is None:
            print(f"STALE {name}: {path} is missing")
        else:
            diff = list(difflib.unified_diff(old.splitlines(), text.splitlines(),
                                             f"{path} (on disk)", f"{path} (from graph)",
                                             lineterm="", n=1))
            print(f"STALE {name}: {path} differs from its graph "
                  f"({sum(1 for d in diff if d[:1] in '+-')} changed lines):")
            print("\n".join(diff[:20]))
    return False


def _write_if_changed(path: Path, text: str) -> bool:
    """Write ``text`` to ``path`` unless it is already there; True if written."""
    if path.exists() and path.read_text() == text:
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return True


def check_or_raise(names=None) -> None:
    """Raise :class:`StaleGeneratedCodeError` naming stale models."""
    stale = generate(names, check=True, verbose=False)
    if stale:
        raise StaleGeneratedCodeError(f"generated code is stale for: {', '.join(stale)}; "
                                      f"run `{COMMAND}`")
