"""The numba counterpart of :mod:`bondgraph.core.codegen`: compiled point and
column kernels from the same sympy expressions, CSE and names as the numpy
module.

:func:`generate_numba_source` writes per-point kernels ``f``, ``h`` and
``f_dfdx`` (one state vector per call, results written into caller-owned
arrays) and the column kernels ``f_cols`` and ``h_cols`` (every sigma point
at once, in a loop LLVM vectorises), decorated with ``numba.njit`` with
explicit signatures and ``cache=True``, which the fused UKF kernel
(:mod:`bondgraph.inference.ukf_numba`) calls as first-class functions. The
numpy module stays the reference and the fallback.

The column kernels compute sin, cos, atan, exp and tanh by the branch-free
functions of :mod:`bondgraph.core.vmath`, which they call as compiled once
per installation by :mod:`bondgraph.numerics.vmath_jit` (:data:`VMATH_MODULE`;
LLVM inlines the calls, so the loop over the points still vectorises);
:func:`vmath_inline` writes the same functions out as straight code (what
the kernels ran up to ``NUMBA_CODEGEN_VERSION`` 7; the tests compare the
two). The point kernels' tanh is ``vmath._tanh``, emitted verbatim
(:data:`NUMBA_TANH`). This module only writes text: it imports neither
numba nor the generated code.
"""

from __future__ import annotations

import ast
import copy
import functools
import inspect
import itertools
import textwrap

import sympy as sp

from bondgraph.core import domains, vmath
from bondgraph.core.codegen import Shared, _free, _Gen, _Printer, live_definitions
from bondgraph.core.equations import StateSpace, paused_gc


class _ScalarPrinter(_Printer):
    """Scalar code for numba point kernels: non-integer powers through
    ``np.power`` (numpy's nan/inf semantics; numba's ``**`` raises on a
    zero base with a negative exponent), Piecewise as conditional
    expressions (``np.select`` needs arrays) and tanh as the module's
    ``_tanh`` (:data:`NUMBA_TANH`)."""

    def _print_Pow(self, expr, rational=False):
        b, e = expr.args
        if e.is_Integer or e == sp.Rational(1, 2) or e == -sp.Rational(1, 2):
            return super()._print_Pow(expr, rational=rational)
        return f"np.power({self._print(b)}, {self._print(e)})"

    def _print_tanh(self, expr):
        return f"_tanh({self._print(expr.args[0])})"

    def _print_dpow(self, expr):
        return domains.scalar_text(expr, self._print)

    def _print_Piecewise(self, expr):
        out = "np.nan"
        for value, cond in reversed(expr.args):
            if cond == sp.true:
                out = self._print(value)
            else:
                out = f"({self._print(value)} if {self._print(cond)} else {out})"
        return out


#: decorator of the numba modules' scalar tanh (the point kernels' tanh)
_TANH_DECORATOR = ('@njit(types.float64(types.float64), cache=True, nogil=True, '
                   'error_model="numpy", inline="always")')
#: tanh of the numba modules (:func:`bondgraph.core.vmath._tanh`: exp for
#: |x| >= 0.55, np.tanh below), emitted into each numba module that uses it:
#: the function's source text, verbatim, under :data:`_TANH_DECORATOR`
NUMBA_TANH = f"\n{_TANH_DECORATOR}\n{inspect.getsource(vmath._tanh)}"
#: the select of the :mod:`bondgraph.core.vmath` functions as the column
#: kernels run them (plain Python has ``vmath._sel``), emitted into each
#: numba module that uses them: ``a if c else b`` as one LLVM select
#: instruction (both a and b are computed; a Python conditional expression
#: would be branches, whose blocks make numba's SSA and liveness passes slow
#: on long kernels: the column kernels of vehicle_full compiled in 8.7 s with
#: them)
NUMBA_SELECT = '''
@intrinsic
def _sel(typingctx, c, a, b):
    """``a if c else b`` as one LLVM select (no branch; a and b of one type)."""
    def codegen(context, builder, sig, args):
        return builder.select(args[0], args[1], args[2])
    return a(types.boolean, a, b), codegen
'''
#: LLVM fast-math flags of the column kernels: a division by a value the
#: loop does not change becomes a product with its reciprocal (arcp; the
#: vector divider is the loop's bottleneck), multiply-adds fuse (contract);
#: never nnan/ninf (the filter's failure checks rely on NaN and inf)
COLS_FASTMATH = ("arcp", "contract")
#: the module of the compiled vector functions the column kernels call
#: (compiled once per installation, not in every model's kernels)
VMATH_MODULE = "bondgraph.numerics.vmath_jit"
#: vector functions whose argument must be below 1e8 in magnitude
VMATH_LIMITED = ("_vsin", "_vcos")
#: sigma point kernels of the numba module (called by bondgraph.inference.ukf_numba)
NUMBA_FUNCTIONS = ("f", "h", "f_dfdx", "f_cols", "h_cols")
#: version of the numba code generator: part of the key of compiled kernels
#: built in memory (bump it when the generated numba text changes, also by
#: an edit of bondgraph/core/vmath.py)
NUMBA_CODEGEN_VERSION = 8


#: the column kernels' loops run over a multiple of POINTS_VECTOR points, at
#: least POINTS_MIN: LLVM vectorises no loop of a constant trip count below
#: 16 (its "tiny loop" rule), and the branch-free functions run scalar cost
#: more than libm's (vehicle_coastdown, 11 points: 0.67 against 0.50 µs)
POINTS_VECTOR, POINTS_MIN = 4, 16


def padded_points(n_x: int) -> int:
    """Columns of a column kernel's arrays: the 2 n_x + 1 sigma points, then
    copies of point 0 up to a multiple of :data:`POINTS_VECTOR` and at least
    :data:`POINTS_MIN` (the loop over points runs in whole AVX2 vectors).

    The one definition of the padding rule: the fused UKF kernel compiles
    this function with numba (``bondgraph.inference.ukf_numba._padded``), so
    it stays plain integer arithmetic on module constants.

    Parameters
    ----------
    n_x : int
        Number of states.

    Returns
    -------
    int
    """
    return max(POINTS_MIN, (2 * n_x + POINTS_VECTOR) // POINTS_VECTOR * POINTS_VECTOR)


#: sympy functions the column kernels compute inline by the
#: :mod:`bondgraph.core.vmath` functions
VMATH_CALLS = {sp.sin: "_vsin", sp.cos: "_vcos", sp.atan: "_vatan", sp.exp: "_vexp",
               sp.tanh: "_vtanh"}


@functools.cache
def _vmath_def(name: str) -> ast.FunctionDef:
    """The syntax tree of the :mod:`bondgraph.core.vmath` function ``name``
    (one of :data:`bondgraph.core.vmath.INLINE`), from its source (shared:
    callers copy what they change)."""
    if name not in vmath.INLINE:
        raise KeyError(f"no inline vector function {name!r} (bondgraph.core.vmath.INLINE)")
    fn = ast.parse(textwrap.dedent(inspect.getsource(getattr(vmath, name)))).body[0]
    assert isinstance(fn, ast.FunctionDef) and fn.name == name
    return fn


class _Rename(ast.NodeTransformer):
    def __init__(self, names: set, prefix: str):
        self.names, self.prefix = names, prefix

    def visit_Name(self, node):
        if node.id in self.names:
            return ast.copy_location(ast.Name(self.prefix + node.id, node.ctx), node)
        return node


class _Expand(ast.NodeTransformer):
    """Calls of :mod:`bondgraph.core.vmath` functions replaced by their result
    variables, their statements appended to ``lines``."""

    def __init__(self, lines: list, counter):
        self.lines, self.counter = lines, counter

    def visit_Call(self, node):
        self.generic_visit(node)
        if isinstance(node.func, ast.Name) and node.func.id in vmath.INLINE:
            body, res, _ = vmath_inline(node.func.id, [ast.unparse(a) for a in node.args],
                                        self.counter)
            self.lines += body
            return ast.Name(res, ast.Load())
        return node


def vmath_inline(name: str, args, counter) -> tuple[list[str], str, str]:
    """Statements that compute the :mod:`bondgraph.core.vmath` function ``name`` at
    the argument expressions ``args`` (source text), with the calls it makes
    expanded too: straight code, so that numba compiles a kernel with many
    calls quickly (numba's IR-level inlining copies the callee's IR at every
    call site: 4x the compile time of vehicle_full) and LLVM vectorises the
    loop around it. Local names become ``_v<k>_<name>``, k from ``counter``.

    Parameters
    ----------
    name : str
        One of :data:`bondgraph.core.vmath.INLINE`.
    args : sequence of str
        Source text of the arguments.
    counter : iterator of int
        Numbers of the inlined calls (``itertools.count()``), shared by the
        calls of one kernel.

    Returns
    -------
    (lines, result variable, prefix of the locals)
    """
    fn = _vmath_def(name)
    pre = f"_v{next(counter)}_"
    params = [a.arg for a in fn.args.args]
    local = set(params) | {n.id for n in ast.walk(fn)
                           if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)}
    lines = [f"{pre}{p} = {a}" for p, a in zip(params, args)]
    body = fn.body[1:] if isinstance(fn.body[0], ast.Expr) else fn.body
    for stmt in body:
        stmt = _Rename(local, pre).visit(copy.deepcopy(stmt))
        stmt = _Expand(lines, counter).visit(stmt)
        if isinstance(stmt, ast.Return):
            lines.append(f"{pre}ret = {ast.unparse(stmt.value)}")
        else:
            lines.append(ast.unparse(stmt))
    return lines, f"{pre}ret", pre


def vmath_function(name: str) -> str:
    """Source of a plain function ``name(x)`` made of the inline statements
    of :func:`vmath_inline` (what the column kernels run; for tests)."""
    lines, res, _ = vmath_inline(name, ["x"], itertools.count())
    return "\n".join([f"def {name}(x):"] + ["    " + ln for ln in lines + [f"return {res}"]])


class _Inline:
    """Calls of :data:`VMATH_CALLS` in a column kernel's expressions
    replaced by calls of the compiled :mod:`bondgraph.core.vmath` functions
    (:data:`VMATH_MODULE`; a libm call would keep the loop scalar), each
    argument in a variable ``_v<k>_x`` and each result in ``_v<k>_ret``."""

    def __init__(self, gen: "_NumbaGen", sh: Shared):
        self.gen, self.sh = gen, sh
        self.counter = itertools.count()
        self.far: list[str] = []
        self.used: set[str] = set()

    def text(self, e, limit: int, plain: str | None, out: list) -> str:
        """Text of ``e`` (``repl[limit]`` of the kernel's :class:`Shared`,
        or an output when ``limit`` is its length), its calls computed by
        statements appended to ``out``; ``plain`` (its text without inline
        code, if known) when it makes no call."""
        ex = self.expanded(e, out, limit, top=True)
        if ex is e and plain is not None:
            return plain
        return self.gen.pr(ex, limit)

    def expanded(self, e, out: list, limit: int, top: bool = False):
        """``e`` with its calls replaced by the result variables of their
        inline code (appended to ``out``, innermost first); a shared node
        before ``limit`` is a variable already computed."""
        if e.is_Atom or (not top and self.sh.index.get(e, (limit,))[0] < limit):
            return e
        args = [self.expanded(a, out, limit) for a in e.args]
        if any(a is not b for a, b in zip(args, e.args)):
            e = e.func(*args)
        name = VMATH_CALLS.get(e.func)
        if name is None:
            return e
        pre = f"_v{next(self.counter)}_"
        res = f"{pre}ret"
        out += [f"{pre}x = {self.gen.pr(e.args[0], limit)}", f"{res} = {name}({pre}x)"]
        self.used.add(name)
        if name in VMATH_LIMITED:
            out.append(f"_far += abs({pre}x) >= 1e8")
            self.far.append(name)
        return sp.Symbol(res)


class _NumbaGen(_Gen):
    """Scalar per-point kernels for numba from the same expressions and names
    as the numpy module (:func:`generate_numba_source`)."""

    def __init__(self, ss: StateSpace, *, source: str | None, command: str):
        super().__init__(ss, source=source, command=command)
        self.printer = _ScalarPrinter(self.namer.names)
        self.vmath_used: set[str] = set()

    def point_body(self, outputs) -> list[str]:
        """Lines computing ``outputs`` ([(array name, [(index, expr)], dense)])
        for one point, with one shared CSE, written into the given arrays."""
        exprs = [e for _, entries, _ in outputs for _, e in entries]
        grp = self.group(exprs)
        sh = self.shared(grp)
        reduced = self.reduced(sh, grp, exprs)
        lines = self._unpack(_free(reduced, sh), point=True)
        out = []
        k = 0
        for name, entries, dense in outputs:
            if not dense:
                out.append(f"{name}[:, :] = 0.0")
            for idx, _ in entries:
                out.append(f"{name}[{', '.join(str(i) for i in idx)}] = {self.pr(reduced[k])}")
                k += 1
        lines += self.definitions(sh, "\n".join(out), reduced) + out
        return lines or ["return"]

    def cols_function(self, name: str, out: str, doc: str, entries) -> str:
        """A ``@njit(SIG_COLS, cache=True)`` column kernel: ``entries``
        ([((i,), expr)]) at every sigma point, the point's state a read from
        ``_X[a * N_PTS + j]`` and entry i written to ``out[i * N_PTS + j]``
        (state- or output-major flat arrays: every access of an array is at
        a constant distance from the others, so LLVM's loop vectoriser needs
        one alias check per array pair). The inputs, parameters and the
        subexpressions of them alone are computed once, before the loop;
        sin, cos, atan, exp and tanh are the branch-free functions of
        :mod:`bondgraph.core.vmath`, called compiled (:data:`VMATH_MODULE`)
        in a loop whose trip count LLVM does not know (it vectorises the
        loop after inlining them). An argument of sin or cos of
        magnitude 1e8 or more (or inf) is counted and the loop is run again
        with numpy's functions."""
        npt = padded_points(len(self.ss.states))
        exprs = [e for _, e in entries]
        grp = self.group(exprs)
        sh = self.shared(grp)
        reduced = self.reduced(sh, grp, exprs)
        xs = {s for s in self.sym_index if self.sym_index[s][0] == "x"}
        varying = sh.depends(xs)
        texts = self.def_texts(sh, reduced)
        outs = [f"{out}[{i * npt} + _j] = {self.pr(e)}" for ((i,), _), e in zip(entries, reduced)]
        live = {n for n, _ in live_definitions([(n, t) for _, n, t in texts], "\n".join(outs))}
        defs = {k: (n, t) for k, n, t in texts}
        free = _free(reduced, sh)
        head = self._unpack(free - xs, point=True)
        head += [f"{n} = {t}" for k, (n, t) in defs.items() if n in live and not varying[k]]
        loads = [f"{self.namer.names[s]} = _X[{self.sym_index[s][1] * npt} + _j]"
                 for s in sorted(free & xs, key=lambda s: self.sym_index[s][1])]
        inline = _Inline(self, sh)
        body = list(loads)
        for k, (n, t) in defs.items():
            if n in live and varying[k]:
                body.append(f"{n} = {inline.text(sh.repl[k][1], k, t, body)}")
        for ((i,), _), e, plain in zip(entries, reduced, outs):
            body.append(plain if e.is_Atom else
                        f"{out}[{i * npt} + _j] = {inline.text(e, len(sh.repl), None, body)}")
        self.vmath_used |= inline.used
        # with calls in it, a loop of constant trip count that looks short
        # before LLVM inlines them is unrolled, not vectorised (emps: 7x the
        # time); a trip count known only at run time is vectorised
        count = "min(N_PTS, _X.shape[0] // N_X)" if inline.used else str(npt)
        lines = head + ["_far = 0"] * bool(inline.far) + [f"for _j in range({count}):"]
        lines += ["    " + ln for ln in body]
        if inline.far:
            plain = list(loads) + [f"{n} = {t}" for k, (n, t) in defs.items()
                                   if n in live and varying[k]] + outs
            lines += ["if _far:", f"    for _j in range({npt}):"]
            lines += ["        " + ln for ln in plain]
        text = "\n".join("    " + ln for ln in lines)
        fm = ", ".join(repr(f) for f in COLS_FASTMATH)
        return (f"@njit(SIG_COLS, cache=True, nogil=True, error_model=\"numpy\", "
                f"fastmath={{{fm}}})\n"
                f"def {name}(_X, u, theta, {out}):\n    \"\"\"{doc}\"\"\"\n{text}\n")

    def point_function(self, name: str, sig: str, args: str, doc: str, outputs) -> str:
        """A ``@njit(sig, cache=True)`` point kernel."""
        body = "\n".join("    " + ln for ln in self.point_body(outputs))
        return (f"@njit({sig}, cache=True, nogil=True, error_model=\"numpy\")\n"
                f"def {name}({args}):\n    \"\"\"{doc}\"\"\"\n{body}\n")

    def numba_module(self) -> str:
        """Source text of the numba module: header, sizes, signatures, kernels."""
        ss = self.ss
        nx, ny = len(ss.states), len(ss.outputs)
        jac = list(self.ss.jacobian("dfdx").items())
        f_entries = self._f_entries()
        h_entries = [((i,), e) for i, e in enumerate(ss.h)]
        parts = [self._numba_header(),
                 self.point_function("f", "SIG_POINT", "x, u, theta, _dxdt",
                                     f"dx/dt = f(x, u, theta) at one point into _dxdt ({nx},).",
                                     [("_dxdt", f_entries, True)]),
                 self.point_function("h", "SIG_POINT", "x, u, theta, _y",
                                     f"Outputs y = h(x, u, theta) at one point into _y ({ny},).",
                                     [("_y", h_entries, True)]),
                 self.point_function("f_dfdx", "SIG_F_DFDX", "x, u, theta, _dxdt, _J",
                                     f"f into _dxdt ({nx},) and df/dx into _J ({nx}, {nx}) "
                                     f"(shared subexpressions).",
                                     [("_dxdt", f_entries, True),
                                      ("_J", jac, len(jac) == nx * nx)]),
                 self.cols_function("f_cols", "_dxdt",
                                    f"f at every sigma point: state a of point j at "
                                    f"_X[a * N_PTS + j], dx_a/dt into _dxdt[a * N_PTS + j] "
                                    f"(({nx} * N_PTS,) each).", f_entries),
                 self.cols_function("h_cols", "_y",
                                    f"h at every sigma point: state a of point j at "
                                    f"_X[a * N_PTS + j], output b into _y[b * N_PTS + j] "
                                    f"(({ny} * N_PTS,)).", h_entries)]
        if self.vmath_used:   # the compiled vector functions the column kernels call
            imports = "from numba.extending import intrinsic\n"
            parts[0] = parts[0].replace(imports, imports + f"\nfrom {VMATH_MODULE} import "
                                        f"{', '.join(sorted(self.vmath_used))}\n", 1)
        if any("_tanh(" in p for p in parts[1:]):
            parts.insert(1, NUMBA_TANH.lstrip("\n"))
        if any("_sel(" in p for p in parts[1:]):
            parts.insert(1, NUMBA_SELECT.lstrip("\n"))
        return "\n\n".join(p.rstrip("\n") + "\n" for p in parts)

    def _numba_header(self) -> str:
        ss = self.ss
        nx, nu, npar, ny = (len(ss.states), len(ss.inputs), len(ss.params), len(ss.outputs))
        return f'''"""Numba point kernels of '{ss.name}': f, h and f_dfdx for one state vector,
f_cols and h_cols for every sigma point at once.

Generated by bondgraph from {self.source}
(graph '{ss.name}'), from the same sympy expressions as the numpy module
{ss.name}.py one directory up.
DO NOT EDIT: regenerate with `{self.command}`; `bondgraph generate --check`
fails when this file differs from what the graph produces.

One point per call: x ({nx},), u ({nu},), theta ({npar},) are C-contiguous float64
vectors (the order of the numpy module's STATES, INPUTS, PARAMS); each kernel
writes its result into the arrays it is given. f_cols and h_cols take the
2 N_X + 1 sigma points of the unscented Kalman filter state-major (state a of
point j at _X[a * N_PTS + j]; N_PTS rounds 2 N_X + 1 up to a multiple of 4,
the filter pads with copies of point 0), compute what depends on u and theta
alone once per call, and loop over the points with branch-free sin, cos, atan,
exp and tanh (within 2 ulp of numpy's; the loop vectorises). Compiled on
import with explicit signatures and cached on disk (cache=True); the fused UKF
kernel (bondgraph.inference.ukf_numba) calls them as first-class functions.
"""

import numpy as np
from numba import njit, types
from numba.extending import intrinsic

NAME = {ss.name!r}
N_X, N_U, N_THETA, N_Y = {nx}, {nu}, {npar}, {ny}
N_PTS = {padded_points(nx)}

_V = types.float64[::1]
_M = types.float64[:, ::1]
#: f and h: (x, u, theta, out); f_dfdx: (x, u, theta, out, jacobian);
#: f_cols and h_cols: (points state-major, u, theta, out output-major)
SIG_POINT = types.void(_V, _V, _V, _V)
SIG_F_DFDX = types.void(_V, _V, _V, _V, _M)
SIG_COLS = types.void(_V, _V, _V, _V)
'''

def generate_numba_source(ss: StateSpace, *, source: str | None = None,
                          command: str = "bondgraph generate") -> str:
    """Source text of the numba module of ``ss``: per-point kernels ``f``,
    ``h`` and ``f_dfdx`` (:data:`NUMBA_FUNCTIONS`) from the same sympy
    expressions, CSE and names as :func:`generate_source`.

    Parameters
    ----------
    ss : StateSpace
    source : str, optional
        ``module:function`` that builds the graph (for the header).
    command : str
        Command that regenerates the file (for the header).

    Returns
    -------
    str
        A module that imports numpy and numba only; importing it compiles
        the kernels (or loads them from numba's on-disk cache).
    """
    with paused_gc():
        return _NumbaGen(ss, source=source, command=command).numba_module()

