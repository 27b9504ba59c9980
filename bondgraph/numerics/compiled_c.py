"""A model's point kernels compiled by the system C compiler.

:func:`bondgraph.core.codegen_ckernel.translate` writes the statements of a
model's numba kernels (``f``, ``h``, ``f_dfdx``, ``f_cols``, ``h_cols``) as
C; this module compiles that text into a shared library in the kernel
cache (``<cache>/c/``, under the SHA-256 of the text, the compiler and its
flags, and the machine's instruction set) and loads it with ctypes. Each
kernel is a :class:`CKernel`: numba's fused UKF kernel and the simulation
kernels take it as a first-class function through numba's wrapper address
protocol (the address of a C function that takes its arrays as numba's
data model lays them out), and Python calls it through ctypes with the same
arguments as a numba dispatcher.

Why: numba compiles a model's five kernels in 1-3 s, most of it its own
typing and lowering; the C compiler builds the same statements in 0.1-0.6 s
(the 68 models of a bundled loop run and of ``generated/``: 0.29 s on
average, 0.64 s at most, against numba's 1.5 s for a coast-down candidate
and 3.1 s for ``vehicle_full``), and the kernels run as fast (the fused
kernel with ``vehicle_full``'s C kernels: 5.40 against 5.22 ms per
likelihood evaluation, ``bench/estimation.py``). The loop compiles every
candidate model of a user's graph once: that was most of a first run.

The compiler is ``$CC``, else ``cc``, ``gcc`` or ``clang`` on the PATH;
its flags are :data:`FLAGS` (``-O3`` vectorises the column kernels' loop
over the sigma points; ``-march=native``: the instruction set of this
machine, part of the cache key). Without one, or when it fails, the caller
(:func:`bondgraph.numerics.compiled.point_kernels`) compiles the numba
kernels instead.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import threading
from pathlib import Path

import numpy as np

try:  # numba is a regular dependency; without it no kernel is compiled at all
    import numba
    from numba import types as nbtypes
    _WAP = numba.types.WrapperAddressProtocol
except ImportError:  # pragma: no cover - exercised only without numba
    numba = None
    _WAP = object

#: environment variable naming the C compiler (else cc, gcc, clang on the PATH)
CC_ENV = "CC"
#: the compiler's flags: optimised and vectorised for this machine
#: (-O3 vectorises the loops over the sigma points, -O2 of gcc 12 does not:
#: 4x the time of the column kernels), no errno from libm and no trapping
#: floating point (both let the compiler vectorise sqrt and selects; the
#: kernels read NaN and inf, never the flags), and no contraction of a
#: multiply and an add into one FMA: numba's point kernels contract none,
#: and with gcc's default (-ffp-contract=fast) f, h and df/dx differed from
#: them in the last bit, enough to move three of the suite's loops to
#: another optimum (a CED declared fit 1.182 -> 1.370); without it they are
#: numba's to the bit (tests/test_ckernels.py)
FLAGS = ("-O3", "-march=native", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math", "-fPIC", "-shared")
#: the kernels of a module, in the order of ``PointKernels``, and their
#: arrays' ranks (``f_dfdx`` writes a matrix)
KERNELS = ("f", "h", "f_dfdx", "f_cols", "h_cols")
#: seconds a compile may take before it counts as failed
COMPILE_TIMEOUT = 300.0
_LOCK = threading.Lock()


class CCompileError(RuntimeError):
    """The C compiler is missing or could not build a model's kernels."""


@functools.cache
def compiler() -> tuple[str, str] | None:
    """``(path, version line)`` of the C compiler, or None without one
    (``$CC``, else ``cc``, ``gcc``, ``clang`` on the PATH, whichever answers
    ``--version``)."""
    names = [os.environ[CC_ENV].split()[0]] if os.environ.get(CC_ENV, "").strip() else []
    for name in names + ["cc", "gcc", "clang"]:
        path = shutil.which(name)
        if path is None:
            continue
        try:
            r = subprocess.run([path, "--version"], capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.SubprocessError):
            continue
        if r.returncode == 0:
            return path, (r.stdout.splitlines() or [""])[0].strip()
    return None


@functools.cache
def machine_key() -> str:
    """What the compiled code depends on besides its text: the processor
    and its instruction-set extensions (``-march=native``), the compiler
    and its flags."""
    flags = ""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith(("flags", "Features")):
                    flags = line
                    break
    except OSError:
        pass
    cc = compiler()
    return "\n".join([platform.machine(), platform.processor(), flags,
                      cc[1] if cc else "", " ".join(FLAGS)])


def library_path(c_text: str, cache: Path, stem: str) -> Path:
    """Where the shared library of ``c_text`` is kept under ``cache``."""
    key = hashlib.sha256(f"{machine_key()}\n{c_text}".encode()).hexdigest()[:20]
    return cache / "c" / f"{stem[:60]}_{key}.so"


def build(c_text: str, lib: Path) -> None:
    """Compile ``c_text`` into the shared library ``lib`` (atomically: a
    half-written library is never found).

    Raises
    ------
    CCompileError
        No compiler, or it failed (its message included).
    """
    cc = compiler()
    if cc is None:
        raise CCompileError("no C compiler found (set CC, or install cc, gcc or clang)")
    lib.parent.mkdir(parents=True, exist_ok=True)
    tag = f"{os.getpid()}.{threading.get_ident()}"
    src = lib.with_suffix(f".{tag}.c")
    tmp = lib.with_suffix(f".{tag}.tmp")
    src.write_text(c_text)
    try:
        r = subprocess.run([cc[0], *FLAGS, "-o", str(tmp), str(src), "-lm"],
                           capture_output=True, text=True, timeout=COMPILE_TIMEOUT)
        if r.returncode != 0 or not tmp.exists():
            raise CCompileError(f"{Path(cc[0]).name} failed on {lib.stem}: "
                                f"{(r.stderr or r.stdout).strip()[-2000:]}")
        os.replace(tmp, lib)
    except subprocess.TimeoutExpired as exc:
        raise CCompileError(f"{Path(cc[0]).name} took more than {COMPILE_TIMEOUT:.0f} s "
                            f"on {lib.stem}") from exc
    finally:
        for p in (src, tmp):
            try:
                p.unlink()
            except OSError:
                pass


def _array_args(a, rank: int) -> list:
    """numba's data model of the C-contiguous float64 array ``a`` as the C
    kernels take it: meminfo, parent, nitems, itemsize, data, shape,
    strides."""
    import numpy as np
    if not (isinstance(a, np.ndarray) and a.dtype == np.float64 and a.ndim == rank
            and a.flags.c_contiguous):
        raise TypeError(f"a C kernel takes C-contiguous float64 arrays of rank {rank}, "
                        f"got {type(a).__name__} {getattr(a, 'dtype', '')} "
                        f"{getattr(a, 'shape', '')}")
    return [None, None, a.size, 8, a.ctypes.data, *a.shape, *a.strides]


class CKernel(_WAP):
    """One compiled C kernel: a first-class function for numba (the wrapper
    address protocol: :meth:`__wrapper_address__`, :meth:`signature`) and a
    callable for Python (``kernel(x, u, theta, out)``; ``f_dfdx`` also takes
    the Jacobian (n_x, n_x)), on C-contiguous float64 arrays like the numba
    dispatcher it replaces.

    Parameters
    ----------
    lib : Path
        The shared library.
    name : str
        One of :data:`KERNELS`.
    """

    def __init__(self, lib: Path, name: str):
        self.lib, self.name = Path(lib), name
        self.ranks = (1, 1, 1, 1, 2) if name == "f_dfdx" else (1, 1, 1, 1)
        fn = getattr(_dll(str(self.lib)), name)
        per = {1: [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64,
                   ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64],
               2: [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64,
                   ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64,
                   ctypes.c_int64]}
        fn.argtypes = [t for r in self.ranks for t in per[r]]
        fn.restype = None
        self._fn = fn
        self._addr = ctypes.cast(fn, ctypes.c_void_p).value

    def __wrapper_address__(self) -> int:
        return self._addr

    def signature(self):
        """The kernel's numba signature (``void`` of C-contiguous float64
        arrays, as the numba kernels')."""
        V, M = nbtypes.float64[::1], nbtypes.float64[:, ::1]
        return nbtypes.void(*[V if r == 1 else M for r in self.ranks])

    def __call__(self, *arrays) -> None:
        if len(arrays) != len(self.ranks):
            raise TypeError(f"C kernel {self.name} takes {len(self.ranks)} arrays, "
                            f"got {len(arrays)}")
        try:
            _caller(self.ranks)(self._addr, *arrays)
        except (TypeError, numba.core.errors.TypingError):
            for a, r in zip(arrays, self.ranks):   # name what is wrong
                _array_args(a, r)
            raise

    def call_ctypes(self, *arrays) -> None:
        """The same call through ctypes (no numba involved; 40 times the
        time of :meth:`__call__`, which a compiled caller makes)."""
        args = []
        for a, r in zip(arrays, self.ranks):
            args += _array_args(a, r)
        self._fn(*args)

    def __reduce__(self):
        return CKernel, (str(self.lib), self.name)

    def __repr__(self) -> str:
        return f"CKernel({self.name!r} of {self.lib.name})"


def _call_intrinsic(n: int):
    """A numba intrinsic ``_call(address, a0, ..., a<n-1>)`` that calls the C
    function at ``address`` with the arrays as numba passes them to a
    first-class function (the LLVM values of their data model, as the fused
    kernel calls a kernel through the wrapper address protocol)."""
    from llvmlite import ir
    from numba.extending import intrinsic

    def typer(typingctx, addr, *arrays):
        def codegen(context, builder, sig, llargs):
            fnty = ir.FunctionType(ir.VoidType(),
                                   [context.get_value_type(t) for t in sig.args[1:]])
            builder.call(builder.inttoptr(llargs[0], fnty.as_pointer()), llargs[1:])
            return context.get_dummy_value()
        return nbtypes.void(addr, *arrays), codegen

    names = ", ".join(f"a{i}" for i in range(n))
    ns = {"typer": typer}
    exec(f"def _call(typingctx, addr, {names}):\n    return typer(typingctx, addr, {names})\n",
         ns)
    return intrinsic(ns["_call"])


if numba is not None:
    _CALL4, _CALL5 = _call_intrinsic(4), _call_intrinsic(5)

    def _call_point(address, a0, a1, a2, a3):
        """Call the C kernel at ``address`` (f, h, f_cols, h_cols)."""
        _CALL4(address, a0, a1, a2, a3)

    def _call_jacobian(address, a0, a1, a2, a3, a4):
        """Call the C kernel at ``address`` (f_dfdx)."""
        _CALL5(address, a0, a1, a2, a3, a4)


@functools.cache
def _caller(ranks: tuple):
    """The numba function that calls a C kernel of array ranks ``ranks`` by
    its address, compiled for C-contiguous float64 arrays alone (another
    array is a TypeError, not a wrong read): a Python call of a C kernel
    costs what a numba dispatcher's does (0.3 µs), not ctypes' conversion of
    28 arguments (11.5 µs; an adaptive solver calls f a hundred thousand
    times). Compiled once per installation (cached on disk)."""
    V, M = nbtypes.float64[::1], nbtypes.float64[:, ::1]
    py = _call_jacobian if len(ranks) == 5 else _call_point
    disp = numba.njit(cache=True, nogil=True)(py)
    disp.compile(nbtypes.void(nbtypes.int64, *[V if r == 1 else M for r in ranks]))
    disp.disable_compile()
    return disp


#: what :func:`table_rhs` returns besides 0 (the derivative written): the
#: state ran away or is not finite, the solver stalled; a derivative that is
#: not finite at a finite state returns ``RHS_UNDEFINED + i`` (i: the first
#: such component; the derivative is written all the same)
RHS_RUNAWAY, RHS_STALLED, RHS_UNDEFINED = 1, 2, 3


def _table_rhs(address, tq, x, ts, samples, slopes, ua, held, th, u, out, state, limits):
    """The guarded right-hand side of an adaptive solver in one compiled
    call (:func:`table_rhs`): the checks of
    :func:`bondgraph.numerics.simulate.guard_rhs`, the inputs of
    :meth:`bondgraph.numerics.simulate.InputSignals.at` over its sample
    table (then the held columns, ``held[j]`` nonzero, set to ``ua[j]``), and
    the C kernel ``f`` at ``address``, written into ``out``."""
    n = x.shape[0]
    s = 0.0
    for i in range(n):
        s += x[i] * x[i]
    if not s < limits[0]:
        return RHS_RUNAWAY
    if tq > state[0]:
        state[0] = tq
        state[1] = 0.0
    else:
        state[1] += 1.0
        if state[1] > limits[1]:
            return RHS_STALLED
    m = ts.shape[0]
    lo, hi = 0, m
    while lo < hi:                  # bisect_right
        mid = (lo + hi) // 2
        if tq < ts[mid]:
            hi = mid
        else:
            lo = mid + 1
    k = lo - 1
    for j in range(u.shape[0]):
        if held[j]:
            u[j] = ua[j]
        elif k < 0:
            u[j] = samples[0, j]
        elif k >= m - 1:
            u[j] = samples[m - 1, j]
        else:
            u[j] = slopes[k, j] * (tq - ts[k]) + samples[k, j]
    _CALL4(address, x, u, th, out)
    for i in range(n):
        if not np.isfinite(out[i]):
            return RHS_UNDEFINED + i
    return 0


@functools.cache
def table_rhs():
    """The numba function :func:`_table_rhs` (compiled once per
    installation, cached on disk): an adaptive solver's call of a model's
    C kernel costs one dispatch (4 µs in all) instead of the Python checks,
    input interpolation and call of
    :func:`bondgraph.numerics.simulate.guard_rhs` (about 20 µs), with the
    same values to the bit (``tests/test_simulate.py``)."""
    return numba.njit(cache=True, nogil=True)(_table_rhs)


@functools.cache
def _dll(path: str):
    """The loaded shared library (once per process)."""
    return ctypes.CDLL(path)


def load(lib: Path) -> tuple:
    """The :data:`KERNELS` of the shared library ``lib`` as :class:`CKernel`."""
    return tuple(CKernel(lib, name) for name in KERNELS)
