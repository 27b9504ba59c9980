"""Compiled point kernels of a model: who compiles them, where their source
comes from, and the on-disk caches.

A model's point kernels (``f``, ``h``, ``f_dfdx`` for one point, the column
kernels ``f_cols``, ``h_cols`` for every sigma point,
:func:`bondgraph.core.codegen_numba.generate_numba_source`) are written as
a numba module; the fused UKF kernel and the simulation kernels call them
as first-class functions. Who compiles them (:func:`kernel_kind`,
:data:`KERNELS_ENV`):

* the system C compiler (the default when there is one): the numba module's
  statements translated to C (:mod:`bondgraph.core.codegen_ckernel`) and
  built into a shared library in ``<cache>/c/``
  (:mod:`bondgraph.numerics.compiled_c`): 0.1-0.6 s a model against numba's
  1-3 s, the same speed at run time;
* numba (no C compiler, ``BONDGRAPH_KERNELS=numba``, or a model the
  translator or the compiler refuses, with a :class:`BackendWarning`): the
  module is imported, which compiles it, and numba caches the machine code
  on disk (``cache=True``).

Either way a second run does not compile again. The numba source is found or
written once:

* a registered model's kernels are ``numba_kernels/<name>.py`` next to its
  numpy module in the generated package (written and checked by
  ``bondgraph generate``); numba caches them in ``__pycache__`` there;
* a model built in memory (``module:function``, the loop's candidates) has
  its kernels written once to the kernel cache directory
  (:func:`cache_dir`), under a name keyed by the hash of its generated numpy
  source (its code, not its default values and boxes:
  :func:`kernel_key_text`) and
  :data:`~bondgraph.core.codegen_numba.NUMBA_CODEGEN_VERSION`: the same model in
  a later run finds its kernels, and their compiled code, without any sympy
  work.

Which backend runs is the caller's choice, taken literally
(:attr:`bondgraph.inference.options.Discretisation.backend`): ``"numba"``
compiles a model's kernels the first time they are needed (a registered
model's once per installation, an in-memory model's once per code key),
``"numpy"`` never does. Nothing here decides a result: whether a kernel is
in the cache (:func:`is_compiled`) changes how long a run takes, never which
backend or compiler runs, so a result does not depend on the calls made
before it or on what earlier runs left in the cache. (Before, an in-memory
model ran numpy until its estimated numpy time reached its estimated compile
time, a ski-rental rule; in the loop every scored candidate reached that
point by its second filter run, and the last digits of a result depended on
the cache.) The C compiler and numba give the same kernels to rounding (the
last bits differ where one contracts a multiply-add the other does not).

Compiling ahead (:func:`compile_ahead`): the loop scores a few dozen
candidate models in a row, each compiled on first use while the machine's
other cores wait. Given the list, a background worker (a thread running the
C compiler, or with numba one ``python -m bondgraph.numerics.compiled``
process, :data:`AHEAD_ENV`) compiles their kernels into the disk cache from
the last backwards while this process works through them from the first; a
model the background has started is waited for, one it has not reached is
compiled here. The kernels are the same either way (the same source; the
cache holds the machine code compiled), only who compiled them differs.
"""

from __future__ import annotations

import atexit
import functools
import hashlib
import importlib.util
import os
import subprocess
import sys
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

from bondgraph.core import codegen_ckernel, vmath
from bondgraph.core.codegen_ckernel import translate
from bondgraph.core.codegen_numba import NUMBA_CODEGEN_VERSION, generate_numba_source
from bondgraph.core.progress import announced
from bondgraph.errors import BackendWarning, CodegenError
from bondgraph.numerics import compiled_c

try:  # numba is a regular dependency; the numpy path is the fallback without it
    import numba
except ImportError:  # pragma: no cover - exercised only without numba
    numba = None

#: whether the numba backend can be used at all
NUMBA_AVAILABLE = numba is not None
#: environment variable naming the kernel cache directory
CACHE_ENV = "BONDGRAPH_CACHE_DIR"
#: environment variable: background processes compiling ahead (default 1 on
#: a machine with two or more cores, else 0; 0 switches it off)
AHEAD_ENV = "BONDGRAPH_COMPILE_AHEAD"
#: environment variable: who compiles a model's point kernels: ``auto`` (the
#: default: the C compiler when there is one, else numba), ``c`` (the C
#: compiler or an error), ``numba``
KERNELS_ENV = "BONDGRAPH_KERNELS"
#: the values of :data:`KERNELS_ENV`
KERNEL_KINDS = ("auto", "c", "numba")
_LOCK = threading.Lock()
_LOADED: dict[str, "PointKernels"] = {}
#: the background compilers (:class:`_Ahead`, one per process, at first use)
_AHEAD: list = []
#: seconds :func:`point_kernels` waits at most for a background compile
AHEAD_WAIT = 600.0


@dataclass
class PointKernels:
    """A model's compiled point kernels.

    Attributes
    ----------
    f, h, f_dfdx : numba dispatchers or :class:`~bondgraph.numerics.compiled_c.CKernel`
        ``f(x, u, theta, out)``, ``h(x, u, theta, out)``,
        ``f_dfdx(x, u, theta, out, jac)`` on C-contiguous float64 vectors.
    f_cols, h_cols : numba dispatchers or CKernel
        ``f_cols(X, u, theta, F)``: f at the 2 n_x + 1 sigma points and the
        padding columns (P = ``codegen_numba.padded_points(n_x)`` columns in all),
        X and F flat (n_x * P,) state-major (state a of point j at
        ``X[a * P + j]``); ``h_cols(X, u, theta, Y)``: h into Y (n_y * P,)
        output-major.
    path : Path
        The numba source file of the kernels.
    compile_s : float
        Seconds spent getting them in this process (compiling, or loading
        the cache).
    from_cache : bool
        Whether every kernel came from the on-disk cache.
    kind : str
        Who compiled them: ``"c"`` (the C compiler) or ``"numba"``.
    """

    f: object
    h: object
    f_dfdx: object
    f_cols: object
    h_cols: object
    path: Path
    compile_s: float
    from_cache: bool
    kind: str = "numba"


def cache_dir() -> Path:
    """The kernel cache directory: ``$BONDGRAPH_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/bondgraph/numba``, else ``~/.cache/bondgraph/numba``."""
    env = os.environ.get(CACHE_ENV)
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "bondgraph" / "numba"


def kernel_source_path(model) -> Path | None:
    """Where the numba source of ``model`` is or will be: the generated
    package's ``numba_kernels/<name>.py`` for a module loaded from a file,
    the cache directory for a model built in memory; None if neither applies
    (a file-backed module without numba kernels)."""
    mod = model.module
    text = getattr(mod, "__source_text__", None)
    if text is not None:
        key = hashlib.sha256(f"{NUMBA_CODEGEN_VERSION}\n{kernel_key_text(text)}".encode())
        return cache_dir() / f"{_safe(model.name)}_{key.hexdigest()[:20]}.py"
    file = getattr(mod, "__file__", None)
    if not file:
        return None
    path = Path(file).parent / "numba_kernels" / Path(file).name
    return path if path.exists() else None


#: lines of a generated numpy module that carry values or provenance, not
#: code: the numba kernels do not depend on them (``SOURCE``: where the graph
#: came from, e.g. ``sbuser.py:fn`` or ``/abs/path/sbuser.py:fn`` for the
#: same graph; keyed on it, a user's candidates were compiled again whenever
#: the command named the file another way)
VALUE_LINES = ("X0 = ", "INPUT_DEFAULTS = ", "PARAM_DEFAULTS = ", "PARAM_LOWER = ",
               "PARAM_UPPER = ", "SOURCE = ")


def kernel_key_text(text: str) -> str:
    """The part of a generated numpy module's source ``text`` that its numba
    kernels depend on: without the module docstring (it lists the default
    values) and the lines of :data:`VALUE_LINES` (initial states, input and
    parameter defaults, boxes).

    A structural candidate of the loop is built with its grid's first value
    as default and its grid span as box, both derived from the current fit:
    keyed on the whole text, the same kernels got a new cache entry, and were
    compiled again, in every run (and for every record)."""
    body = text
    if body.startswith('"""'):
        end = body.find('"""', 3)
        body = body[end + 3:] if end >= 0 else body
    return "\n".join(line for line in body.splitlines() if not line.startswith(VALUE_LINES))


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name)[:40] or "model"


def is_compiled(model) -> bool:
    """Whether ``model``'s kernels are loaded in this process or compiled on
    disk (so that using them costs no compilation). Information only (what a
    run will cost, what to announce): it never decides which backend runs."""
    path = kernel_source_path(model)
    if path is None:
        return False
    kind = kernel_kind()
    if f"{kind}:{path}" in _LOADED:
        return True
    if kind == "c":
        try:
            return path.exists() and _c_library(path).exists()
        except (CodegenError, OSError):
            return False
    return _in_cache(path, {})


def numba_cache_dir(path: Path) -> Path | None:
    """Where numba caches the functions of the source file ``path``: its
    first cache locator that applies (``NUMBA_CACHE_DIR`` when set, else
    ``__pycache__`` beside the file when writable, else the user-wide
    cache), as numba itself chooses; None without numba or when no locator
    applies (the file does not exist)."""
    if numba is None:
        return None
    try:
        from numba.core.caching import CacheImpl
        locators = CacheImpl._locator_classes
    except (ImportError, AttributeError):  # pragma: no cover - another numba layout
        return path.parent / "__pycache__"

    def probe():  # the locators read only the line number of a function
        pass

    for cls in locators:
        try:
            loc = cls.from_function(probe, str(path))
        except Exception:  # pragma: no cover - a locator that cannot apply here
            loc = None
        if loc is not None:
            return Path(loc.get_cache_path())
    return None


def kernel_kind() -> str:
    """Who compiles point kernels here (:data:`KERNELS_ENV`): ``"c"`` when
    it says ``c``, or ``auto`` (the default) and a C compiler answers
    (:func:`bondgraph.numerics.compiled_c.compiler`); else ``"numba"``.

    Raises
    ------
    ValueError
        The environment variable is not one of :data:`KERNEL_KINDS`.
    """
    env = (os.environ.get(KERNELS_ENV) or "auto").strip().lower()
    if env not in KERNEL_KINDS:
        raise ValueError(f"{KERNELS_ENV}={os.environ.get(KERNELS_ENV)!r}: give one of "
                         f"{', '.join(KERNEL_KINDS)}")
    if env == "numba":
        return "numba"
    return "c" if env == "c" or compiled_c.compiler() is not None else "numba"


def point_kernels(model, kind: str | None = None) -> PointKernels:
    """The compiled point kernels of ``model`` (compiled or loaded once per
    process).

    Parameters
    ----------
    model : Model
    kind : {"c", "numba"}, optional
        Who compiles them (default :func:`kernel_kind`). With the default a
        model the C translator or compiler refuses is compiled by numba
        (a :class:`~bondgraph.errors.BackendWarning` says why); ``"c"``
        given, or ``BONDGRAPH_KERNELS=c``, raises instead.

    Raises
    ------
    ImportError
        numba is not installed.
    FileNotFoundError
        A model loaded from a file whose numba kernels were not generated
        (run ``bondgraph generate``).
    bondgraph.numerics.compiled_c.CCompileError, CodegenError
        ``kind="c"`` and the kernels cannot be translated or compiled.
    Exception
        Whatever numba raises for code it cannot compile (the caller falls
        back to numpy).
    """
    if numba is None:
        raise ImportError("numba is not installed (pip install numba)")
    strict = kind == "c" or (kind is None and
                             (os.environ.get(KERNELS_ENV) or "").strip().lower() == "c")
    kind = kind or kernel_kind()
    path = kernel_source_path(model)
    if path is None:
        raise FileNotFoundError(f"model '{model.name}' has no numba kernels (run "
                                f"`bondgraph generate`)")
    key = f"{kind}:{path}"
    with _LOCK:
        got = _LOADED.get(key)
        if got is not None:
            return got
        if not path.exists():
            _write_source(model, path)
        if kind == "c":
            try:
                got = _LOADED[key] = _c_kernels(model, path)
                return got
            except (CodegenError, compiled_c.CCompileError, OSError) as exc:
                if strict:
                    raise
                warnings.warn(f"model '{model.name}': the C kernels could not be built "
                              f"({str(exc).splitlines()[0][:300]}); numba compiles them",
                              BackendWarning, stacklevel=2)
        nkey = f"numba:{path}"
        got = _LOADED.get(nkey)
        if got is None:
            with announced(f"compiling the numba kernels of model '{model.name}'",
                           note="once: numba caches them on disk"):
                _await_ahead(path)
                got = _LOADED[nkey] = _import(path)
        _LOADED[key] = got
    return got


def _c_kernels(model, path: Path) -> PointKernels:
    """The C kernels of the numba source ``path``: its translation's shared
    library from the cache, built when missing (waiting for the background
    compiler when it has started it)."""
    t0 = time.perf_counter()
    lib = _c_library(path)
    cached = lib.exists()
    if not cached:
        _await_ahead(path)
        if not lib.exists():
            with announced(f"compiling the C kernels of model '{model.name}'",
                           note="once: kept on disk"):
                compiled_c.build(_c_text(path), lib)
    fns = compiled_c.load(lib)
    return PointKernels(*fns, path, time.perf_counter() - t0, cached, "c")


def _c_text(path: Path) -> str:
    """The C translation of the numba source ``path``."""
    return translate(path.read_text())


#: the library of each numba source translated in this process, by
#: :func:`_c_source_key` and cache folder
_C_LIBRARIES: dict[tuple[str, str], Path] = {}


@functools.lru_cache(maxsize=1)
def _translator_key() -> str:
    """What a C translation depends on besides the numba source: the
    translator's code and the vector-math functions it inlines, and the
    machine the library is built for (:func:`compiled_c.machine_key`)."""
    h = hashlib.sha256(compiled_c.machine_key().encode())
    for mod in (codegen_ckernel, vmath):
        h.update(Path(mod.__file__).read_bytes())
    return h.hexdigest()


def _c_source_key(path: Path) -> str:
    """The key of the numba source ``path`` in the translation index."""
    return hashlib.sha256(_translator_key().encode() + path.read_bytes()).hexdigest()[:32]


def _c_library(path: Path) -> Path:
    """Where the shared library of the numba source ``path`` is kept.

    The library's name hashes the source's C translation; the translation
    (40 ms for a coast-down candidate: on the default loop 117 of them,
    4.7 s of one core, before any filter ran) is made once per source and
    translator: remembered in this process and in an index on disk
    (``c/index/`` of the cache directory) that maps the source's hash to
    the library's name."""
    key = _c_source_key(path)
    base = cache_dir() / "c"
    got = _C_LIBRARIES.get((key, str(base)))
    if got is not None:
        return got
    index = base / "index" / f"{key}.txt"
    try:
        name = index.read_text().strip()
    except OSError:
        name = ""
    if name and "/" not in name and name.endswith(".so"):
        lib = base / name
    else:
        lib = compiled_c.library_path(_c_text(path), cache_dir(), path.stem)
        try:
            index.parent.mkdir(parents=True, exist_ok=True)
            tmp = index.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
            tmp.write_text(lib.name)
            os.replace(tmp, index)
        except OSError:     # a read-only cache: translate again next time
            pass
    _C_LIBRARIES[(key, str(base))] = lib
    return lib


def ahead_workers() -> int:
    """Background compile processes (:data:`AHEAD_ENV`; default 1 with two
    or more cores, else 0).

    Raises
    ------
    ValueError
        The environment variable is not a whole number >= 0.
    """
    env = os.environ.get(AHEAD_ENV)
    if env is None or not env.strip():
        return 1 if (os.cpu_count() or 1) >= 2 else 0
    try:
        n = int(env)
    except ValueError:
        n = -1
    if n < 0:
        raise ValueError(f"{AHEAD_ENV}={env!r}: give a whole number of processes >= 0 "
                         f"(0 switches compiling ahead off)")
    return n


def compile_ahead(models) -> int:
    """Compile the point kernels of ``models`` (to be used in this order) in
    the background (:data:`AHEAD_ENV` workers), the last first, into the
    disk cache; :func:`point_kernels` waits for a model a background worker
    has started and compiles one none has reached itself (no model is
    compiled twice). Models already loaded or compiled, or without a state
    space to generate kernels from, are left out. Call :func:`cancel_ahead`
    when done with the list.

    With the C compiler (:func:`kernel_kind`) the workers are threads that
    run it; with numba they are plain ``python -m
    bondgraph.numerics.compiled`` children fed kernel paths one at a time
    (not ``multiprocessing``, which re-imports the caller's main script:
    a user's script without a ``__main__`` guard would run twice).

    Parameters
    ----------
    models : sequence of Model

    Returns
    -------
    int
        How many models were queued (0 without numba or with
        :data:`AHEAD_ENV` = 0).
    """
    if numba is None or not ahead_workers():
        return 0
    kind = kernel_kind()
    todo, listed = [], {}
    with _LOCK:
        for model in models:
            path = kernel_source_path(model)
            if path is None or f"{kind}:{path}" in _LOADED:
                continue
            try:
                if not path.exists():
                    _write_source(model, path)
                done = (_c_library(path).exists() if kind == "c" else _in_cache(path, listed))
            except (FileNotFoundError, CodegenError):   # point_kernels says so
                continue
            if not done:
                todo.append(str(path))
    if todo:
        _ahead(kind).add(todo)
    return len(todo)


def build_ahead(model) -> bool:
    """Build the C library of ``model``'s point kernels into the disk cache
    in the calling thread, without loading it and without this module's
    lock (work ahead of need, on a thread of its own:
    :func:`point_kernels` later finds the library built;
    :func:`compile_ahead` is for kernels needed soon, in use order).

    Parameters
    ----------
    model : Model

    Returns
    -------
    bool
        Whether a library was built: False when the kernels are not the C
        compiler's (:func:`kernel_kind`), are built or loaded already, or
        fail (:func:`point_kernels` builds them again when they are needed
        and reports why).
    """
    if numba is None or kernel_kind() != "c":
        return False
    path = kernel_source_path(model)
    if path is None or f"c:{path}" in _LOADED:
        return False
    try:
        if not path.exists():
            _write_source(model, path)
    except Exception:  # noqa: BLE001 - point_kernels reports it when the kernels are needed
        return False
    return _build_c(path)


def _build_c(path: Path) -> bool:
    """Build the C library of the numba source ``path`` into the cache unless
    it is there; whether it was built (a failure is left to
    :func:`point_kernels`, which builds it again when it is needed and
    reports why)."""
    try:
        lib = _c_library(path)
        if lib.exists():
            return False
        compiled_c.build(_c_text(path), lib)
    except Exception:  # noqa: BLE001 - the caller's own compile reports it
        return False
    return True


def _in_cache(path: Path, listed: dict) -> bool:
    """Whether the kernel source ``path`` has a numba index in its cache
    folder, from one listing of that folder per ``listed`` (source folder ->
    the stems with an index in its cache; :func:`compile_ahead` shares one
    over its models: a listing per model read the whole folder each time,
    37 ms per model with 49 000 cached files, about a second per loop step
    of a warm run)."""
    if path.parent not in listed:      # one locator probe and one listing per folder
        cache = numba_cache_dir(path)
        try:
            names = os.listdir(cache) if cache is not None else []
        except OSError:
            names = []
        listed[path.parent] = {n.split(".", 1)[0] for n in names if n.endswith(".nbi")}
    return path.stem in listed[path.parent]


def cancel_ahead() -> None:
    """Drop the background compilations not started yet (those running
    finish into the disk cache)."""
    if _AHEAD:
        _AHEAD[0].clear()


def _ahead(kind: str = "numba") -> "_Ahead":
    """The process's background compilers (started at the first use; new
    ones when the compiler changed)."""
    with _LOCK:
        if _AHEAD and _AHEAD[0].kind != kind:
            _AHEAD.pop().close()
        if not _AHEAD:
            _AHEAD.append(_Ahead(ahead_workers(), kind))
            atexit.register(_AHEAD[0].close)
        return _AHEAD[0]


def _await_ahead(path: Path) -> None:
    """Wait for the background compilation of ``path`` if one has started;
    take it off the queue if not (this process compiles it)."""
    if _AHEAD:
        _AHEAD[0].claim(str(path))


class _Ahead:
    """Background compilers fed from one queue of kernel paths in use
    order: each worker, when ready, gets the last path nobody has taken
    (:meth:`_next`); this process takes its paths from the front
    (:meth:`claim`). With ``kind`` "c" a worker is a thread that runs the C
    compiler; with "numba" a child process that imports the kernels. A
    worker that dies is dropped (its path counts as not compiled: the caller
    compiles it)."""

    def __init__(self, n: int, kind: str = "numba"):
        self.cond = threading.Condition()
        self.kind = kind
        self.queue: list[str] = []          # not started, in use order
        self.running: dict[int, str] = {}   # worker index -> path it compiles
        self.idle: list[int] = []           # workers waiting for a path
        self.procs = []
        self.closed = False
        if kind == "c":
            for i in range(n):
                threading.Thread(target=self._serve_c, args=(i,), daemon=True,
                                 name=f"bondgraph-cc_{i}").start()
            return
        # numba read its cache folder when this process imported it: the
        # workers must write where this process will look, whatever the
        # environment says now
        env = dict(os.environ, NUMBA_NUM_THREADS="1")
        env.pop("NUMBA_CACHE_DIR", None)
        if numba.config.CACHE_DIR:
            env["NUMBA_CACHE_DIR"] = str(numba.config.CACHE_DIR)
        for i in range(n):
            try:
                proc = subprocess.Popen([sys.executable, "-m", "bondgraph.numerics.compiled"],
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        stderr=subprocess.DEVNULL, text=True, bufsize=1,
                                        env=env)
            except OSError:                 # no process to start: compile here
                continue
            self.procs.append(proc)
            threading.Thread(target=self._serve, args=(len(self.procs) - 1,),
                             daemon=True).start()

    def add(self, paths: list[str]) -> None:
        with self.cond:
            self.queue.extend(p for p in paths
                              if p not in self.queue and p not in self.running.values())
            while self.idle and self.queue:
                self._next(self.idle.pop())
            self.cond.notify_all()          # threads of the C compiler take their own

    def clear(self) -> None:
        with self.cond:
            self.queue.clear()

    def claim(self, path: str) -> None:
        """This process compiles ``path`` unless a worker already is: then
        wait for it."""
        with self.cond:
            if path in self.queue:
                self.queue.remove(path)
                return
            # a worker that hangs is not waited for forever: then this
            # process compiles it too
            self.cond.wait_for(lambda: path not in self.running.values(), AHEAD_WAIT)

    def wait_idle(self, timeout: float) -> bool:
        """Wait until no path is queued or compiling (or ``timeout`` [s]);
        whether that happened."""
        with self.cond:
            return self.cond.wait_for(lambda: not self.queue and not self.running, timeout)

    def _next(self, i: int) -> None:
        """Give worker ``i`` the last queued path (under the condition's lock)."""
        if self.kind == "c":                # the threads take their paths
            self.cond.notify_all()
            return
        if not self.queue:
            self.idle.append(i)
            return
        path = self.queue.pop()
        self.running[i] = path
        try:
            self.procs[i].stdin.write(path + "\n")
            self.procs[i].stdin.flush()
        except (OSError, ValueError):        # the worker is gone
            self.running.pop(i, None)
            self.cond.notify_all()

    def _serve(self, i: int) -> None:
        """Read worker ``i``'s "ready" lines (one at the start, one after
        each path) and hand it the next path."""
        for line in self.procs[i].stdout:
            if line.strip() != "ready":
                continue
            with self.cond:
                self.running.pop(i, None)
                self.cond.notify_all()
                self._next(i)
        with self.cond:                     # EOF: the worker exited
            self.running.pop(i, None)
            if i in self.idle:
                self.idle.remove(i)
            self.cond.notify_all()

    def _serve_c(self, i: int) -> None:
        """Thread ``i``: build the C library of the last queued path, until
        closed (a failure is left to the caller, which builds it again and
        reports it)."""
        while True:
            with self.cond:
                self.cond.wait_for(lambda: self.queue or self.closed)
                if self.closed:
                    return
                path = self.queue.pop()
                self.running[i] = path
            _build_c(Path(path))
            with self.cond:
                self.running.pop(i, None)
                self.cond.notify_all()

    def close(self) -> None:
        """Stop the workers (at exit): a compile under way is abandoned."""
        self.clear()
        with self.cond:
            self.closed = True
            self.cond.notify_all()
        for proc in self.procs:
            try:
                proc.stdin.close()
            except OSError:
                pass
            if proc.poll() is None:
                proc.terminate()


def _worker_main() -> int:
    """A background compiler (``python -m bondgraph.numerics.compiled``):
    says "ready", then for each kernel path read from stdin imports
    (compiles) it into numba's disk cache and says "ready" again."""
    print("ready", flush=True)
    for line in sys.stdin:
        path = line.strip()
        if path:
            try:
                _import(Path(path))
            except Exception as exc:  # noqa: BLE001 - the caller's own compile reports it
                print(f"{path}: {exc!r}", file=sys.stderr, flush=True)
        print("ready", flush=True)
    return 0


def _write_source(model, path: Path) -> None:
    """Generate an in-memory model's numba source and write it atomically."""
    ss = getattr(model.module, "__state_space__", None)
    if ss is None:
        raise FileNotFoundError(f"model '{model.name}' was built without its state space; "
                                f"no numba kernels can be generated")
    text = generate_numba_source(ss, source=getattr(model, "source", None),
                                 command="bondgraph (in memory)")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _import(path: Path) -> PointKernels:
    """Import a kernel module by path (compiling or loading numba's cache)."""
    name = f"_bondgraph_numba_{_safe(path.parent.name)}_{path.stem}"
    t0 = time.perf_counter()
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    try:
        spec.loader.exec_module(mod)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    dt = time.perf_counter() - t0
    fns = (mod.f, mod.h, mod.f_dfdx, mod.f_cols, mod.h_cols)
    hits = all(sum(fn.stats.cache_hits.values()) > 0 for fn in fns)
    return PointKernels(*fns, path, dt, hits)


if __name__ == "__main__":      # the canonical module's function, not this __main__ copy's
    from bondgraph.numerics.compiled import _worker_main as _main
    raise SystemExit(_main())
