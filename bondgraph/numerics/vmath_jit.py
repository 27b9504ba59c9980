"""The branch-free functions of :mod:`bondgraph.core.vmath` compiled by
numba once per installation, for the column kernels of every model.

The column kernels ``f_cols`` and ``h_cols`` of a generated numba module
(:mod:`bondgraph.core.codegen_numba`) compute sin, cos, atan, exp and tanh
at every sigma point. Up to ``NUMBA_CODEGEN_VERSION`` 7 the generator wrote
the statements of these functions out at each call site, and numba typed
and lowered every copy again in every model: a third to a half of a model's
compile time (issue 27: the loop's first run compiles 49 candidate models).
Here each function is compiled once, with the column kernels' options
(``error_model="numpy"``, the fast-math flags
:data:`~bondgraph.core.codegen_numba.COLS_FASTMATH`), cached on disk
(``cache=True``), and its LLVM function is marked ``alwaysinline`` in the
module that numba links into a caller: LLVM inlines every call into the
kernel's loop over the points, which it vectorises as before. The machine
code of a kernel is that of the expanded statements (the same results to
the bit, the same time per call; ``tests/test_vmath.py``).

The functions are the code objects of :mod:`bondgraph.core.vmath`, bound to
globals in which ``_sel`` is numba's select intrinsic and the functions
they call are the compiled ones (so ``_vsin`` calls the compiled
``_vsincos``).
"""

from __future__ import annotations

import types

import numpy as np

from bondgraph.core import vmath
from bondgraph.core.codegen_numba import COLS_FASTMATH

try:  # numba is a regular dependency; without it nothing here is compiled
    import numba
    from numba.core.sigutils import normalize_signature
    from numba.extending import intrinsic
except ImportError:  # pragma: no cover - exercised only without numba
    numba = None

#: the signature each function is compiled for (the column kernels call
#: them on float64; ``_pow2`` on int64, ``_vsincos`` with an int64 shift),
#: in an order in which a function comes after those it calls
SIGNATURES = {"_pow2": "float64(int64)", "_vsincos": "float64(float64, int64)",
              "_vatan": "float64(float64)", "_vsin": "float64(float64)",
              "_vcos": "float64(float64)", "_vexp": "float64(float64)",
              "_vtanh": "float64(float64)"}


def _select():
    """numba's select intrinsic ``_sel(c, a, b)``: ``a if c else b`` as one
    LLVM select instruction (both computed, no branch)."""
    @intrinsic
    def _sel(typingctx, c, a, b):
        def codegen(context, builder, sig, args):
            return builder.select(args[0], args[1], args[2])
        return a(numba.types.boolean, a, b), codegen
    return _sel


def _always_inline(disp, sig: str) -> None:
    """Compile (or load) ``disp`` for ``sig`` and mark its LLVM function
    ``alwaysinline`` in the module numba links into its callers."""
    disp.compile(sig)
    args, _ = normalize_signature(sig)
    cres = disp.overloads[tuple(args)]
    mod = cres.library._get_module_for_linking()
    for fn in mod.functions:
        if not fn.is_declaration and fn.name == cres.fndesc.mangled_name:
            fn.add_function_attribute("alwaysinline")


def compiled_functions() -> dict:
    """The functions of :data:`SIGNATURES` compiled (or loaded from numba's
    cache) and marked ``alwaysinline``, by name."""
    ns = {"__name__": __name__, "np": np, "_sel": _select()}
    for name, sig in SIGNATURES.items():
        fn = getattr(vmath, name)
        clone = types.FunctionType(fn.__code__, ns, name, fn.__defaults__)
        clone.__qualname__, clone.__doc__ = fn.__qualname__, fn.__doc__
        ns[name] = numba.njit(cache=True, nogil=True, error_model="numpy",
                              fastmath=set(COLS_FASTMATH))(clone)
        _always_inline(ns[name], sig)
    return {n: ns[n] for n in SIGNATURES}


if numba is not None:
    globals().update(compiled_functions())
