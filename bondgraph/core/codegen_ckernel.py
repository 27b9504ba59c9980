"""The numba point kernels of a model translated to C: the same statements,
compiled by the system C compiler in a tenth of numba's time.

A model's numba module (:func:`bondgraph.core.codegen_numba.generate_numba_source`)
is a small subset of Python: straight-line assignments of float
expressions, ``for`` loops over ``range``, ``if``, subscripts of the
argument arrays and calls of numpy's elementwise functions and of the
branch-free functions of :mod:`bondgraph.core.vmath`. numba compiles each of
its five kernels in 0.1-1 s, most of it in numba's own typing and lowering
(issue 27: the loop's candidates of one bundled run took 50 x 1.5 s; with
``NUMBA_OPT=0`` still 1.1 s each). :func:`translate` reads that module's
syntax tree and writes the same statements as C99 functions (the vmath
functions from their Python source the same way); a C compiler builds
them in about 0.1 s (:mod:`bondgraph.numerics.compiled_c`).

The C functions take their arrays as numba passes an array to a
first-class function (the fields of its data model, in order: meminfo,
parent, nitems, itemsize, data, shape, strides), so the fused UKF kernel
and the simulation kernels (:mod:`bondgraph.inference.ukf_numba`,
:mod:`bondgraph.inference.sim_numba`) call them exactly as they call the
numba dispatchers, through the wrapper address protocol
(``numba.types.WrapperAddressProtocol``).

What the translation keeps: every expression in the order and grouping of
the numba text, Python's true division (``a / b`` of two integers is a
float division), numpy's NaN propagation of ``maximum``/``minimum`` and its
``sign``, ``logaddexp`` as numpy computes it. What differs: the last bits
of a result, where the C compiler contracts multiply-adds or computes a
libm function otherwise than numba's LLVM (the tests compare the two to
1e-12 relative). A statement or function the translator does not know
raises :class:`~bondgraph.errors.CodegenError`: the caller then compiles
the numba module as before.

This module only writes text; it calls no compiler.
"""

from __future__ import annotations

import ast
import functools
import inspect
import textwrap

from bondgraph.core import vmath
from bondgraph.errors import CodegenError

#: the kernels of a numba module, with the array arguments' ranks
KERNELS = {"f": (1, 1, 1, 1), "h": (1, 1, 1, 1), "f_dfdx": (1, 1, 1, 1, 2),
           "f_cols": (1, 1, 1, 1), "h_cols": (1, 1, 1, 1)}
#: the kernels that loop over the sigma points (vectorised by gcc)
COLUMN_KERNELS = ("f_cols", "h_cols")
#: the largest numerator m of an exponent ±m/4 taken by square roots
MAX_QUARTERS = 32
#: argument types of the vmath functions (as compiled by numba in
#: :mod:`bondgraph.numerics.vmath_jit`)
VMATH_ARGS = {"_pow2": ("int64_t",), "_vsincos": ("double", "int64_t"), "_vatan": ("double",),
              "_vsin": ("double",), "_vcos": ("double",), "_vexp": ("double",),
              "_vtanh": ("double",)}
#: result types of the vmath functions
VMATH_RESULT = {name: "double" for name in VMATH_ARGS}
#: vmath functions the prelude defines in C of its own (same values)
C_DEFINED = ("_pow2",)
#: numpy (and builtin) functions of one or two float arguments -> C
CALLS = {"np.sqrt": "sqrt", "np.sin": "sin", "np.cos": "cos", "np.tan": "tan",
         "np.arcsin": "asin", "np.arccos": "acos", "np.arctan": "atan", "np.arctan2": "atan2",
         "np.sinh": "sinh", "np.cosh": "cosh", "np.tanh": "tanh", "np.arcsinh": "asinh",
         "np.arccosh": "acosh", "np.arctanh": "atanh", "np.exp": "exp", "np.expm1": "expm1",
         "np.log": "log", "np.log1p": "log1p", "np.log2": "log2", "np.log10": "log10",
         "np.power": "pow", "np.floor": "floor", "np.ceil": "ceil", "np.abs": "fabs",
         "np.fabs": "fabs", "np.hypot": "hypot", "np.maximum": "bg_maximum",
         "np.minimum": "bg_minimum", "np.sign": "bg_sign", "np.logaddexp": "bg_logaddexp",
         "np.cbrt": "cbrt", "np.exp2": "exp2", "np.fmod": "fmod", "np.heaviside": "bg_heaviside"}
#: numpy constants -> C
NAMES = {"np.nan": "NAN", "np.inf": "INFINITY", "np.pi": "3.141592653589793",
         "np.e": "2.718281828459045"}
#: the C helpers every translation unit defines (numpy's semantics)
PRELUDE = r"""#include <math.h>
#include <stdint.h>
#include <string.h>

#define BG_V(n) void *n##_mi, void *n##_pa, int64_t n##_ni, int64_t n##_is, double *n, \
    int64_t n##_sh0, int64_t n##_st0
#define BG_M(n) void *n##_mi, void *n##_pa, int64_t n##_ni, int64_t n##_is, double *n, \
    int64_t n##_sh0, int64_t n##_sh1, int64_t n##_st0, int64_t n##_st1
#define BG_INLINE static inline __attribute__((always_inline))

/* numpy's maximum/minimum: NaN if either argument is NaN */
BG_INLINE double bg_maximum(double a, double b)
{ return (a != a || b != b) ? a + b : (a > b ? a : b); }
BG_INLINE double bg_minimum(double a, double b)
{ return (a != a || b != b) ? a + b : (a < b ? a : b); }
/* numpy's sign: -1, 0, 1, NaN for NaN */
BG_INLINE double bg_sign(double a)
{ return a > 0.0 ? 1.0 : (a < 0.0 ? -1.0 : (a == 0.0 ? 0.0 : a)); }
/* numpy's heaviside(x, h0) */
BG_INLINE double bg_heaviside(double x, double h0)
{ return x > 0.0 ? 1.0 : (x < 0.0 ? 0.0 : (x == 0.0 ? h0 : x)); }
/* numpy's logaddexp(a, b) = log(exp(a) + exp(b)) without overflow */
BG_INLINE double bg_logaddexp(double a, double b)
{
    if (a == b) return a + 0.6931471805599453;
    double d = a - b;
    if (d > 0.0) return a + log1p(exp(-d));
    if (d <= 0.0) return b + log1p(exp(d));
    return d;
}
/* x ** (m / 4), or 1 / that with neg (m > 0 not a multiple of 4), by square
   roots for the column kernels: pow is a library call, which keeps gcc
   from vectorising the loop over the sigma points; sqrt is an instruction.
   Within 4 + m/4 ulp of pow (the point kernels keep pow, equal to numba's to
   the bit); pow's values at -0 (+0, or +inf with neg), -inf (+inf, or +0
   with neg), +inf, NaN and x < 0 (NaN) kept. */
BG_INLINE double bg_powq(double x, int64_t m, int64_t neg)
{
    double xp = x + 0.0, s = sqrt(xp), q = sqrt(s), r;
    int64_t b = m % 4, i;
    r = b == 1 ? q : (b == 2 ? s : s * q);
    if (neg) {              /* reciprocals first: x**-1.25 of 1e250 is 1e-312, x**1.25 inf */
        r = 1.0 / r;
        xp = 1.0 / xp;
    }
    for (i = 0; i < m / 4; ++i)
        r *= xp;
    return x == -INFINITY ? (neg ? 0.0 : INFINITY) : r;
}
/* 2**n for -1022 <= n <= 1023 from the exponent bits: the value of
   bondgraph.core.vmath._pow2 (exact there; selects over the bits of n keep
   gcc from vectorising the loop around it, a bit cast does not) */
BG_INLINE double _pow2(int64_t n)
{
    uint64_t b = (uint64_t)(n + 1023) << 52;
    double d;
    memcpy(&d, &b, sizeof d);
    return d;
}
BG_INLINE int64_t bg_imin(int64_t a, int64_t b) { return a < b ? a : b; }
BG_INLINE int64_t bg_imax(int64_t a, int64_t b) { return a > b ? a : b; }
"""


class _Func:
    """What the translator knows of one function: its arrays (name -> rank),
    the C types of its locals, and whether it is a column kernel (a loop
    over the sigma points that gcc should vectorise: :func:`_quarter`)."""

    def __init__(self, arrays: dict, scalars: dict, consts: dict, columns: bool = False):
        self.arrays = arrays
        self.types = dict(scalars)
        self.consts = consts
        self.columns = columns


def _quarter(exp) -> tuple[int, bool] | None:
    """``(m, negative)`` when the exponent ``exp`` (an AST node) is the
    constant ±m/4 with m not a multiple of 4 and m <= :data:`MAX_QUARTERS`
    (the exponents of the loop's smooth laws: |v|^(1/2) regularised gives
    (v² + ε²)^(±1/4), (…)^(5/4)), else None."""
    neg = False
    if isinstance(exp, ast.UnaryOp) and isinstance(exp.op, ast.USub):
        exp, neg = exp.operand, True
    if not (isinstance(exp, ast.Constant) and isinstance(exp.value, (int, float))
            and not isinstance(exp.value, bool)):
        return None
    m = 4.0 * float(exp.value)
    if not (m.is_integer() and 0 < m <= MAX_QUARTERS and int(m) % 4):
        return None
    return int(m), neg


def _promote(a: str, b: str) -> str:
    return "double" if "double" in (a, b) else "int64_t"


class _Expr:
    """C text and type of Python expressions (the subset of the kernels)."""

    def __init__(self, fn: _Func):
        self.fn = fn

    def type_of(self, node) -> str:
        return self.c(node)[1]

    def c(self, node) -> tuple[str, str]:  # noqa: C901 - one case per node kind
        """``(text, type)`` of ``node``; type ``"double"`` or ``"int64_t"``."""
        fn = self.fn
        if isinstance(node, ast.Constant):
            v = node.value
            if isinstance(v, bool):
                return ("1" if v else "0"), "int64_t"
            if isinstance(v, int):
                return str(v), "int64_t"
            if isinstance(v, float):
                r = repr(v)
                if r in ("inf", "-inf", "nan"):
                    return {"inf": "INFINITY", "-inf": "(-INFINITY)", "nan": "NAN"}[r], "double"
                return (r if ("." in r or "e" in r) else r + ".0"), "double"
            raise CodegenError(f"constant {v!r} in a kernel")
        if isinstance(node, ast.Name):
            if node.id in fn.consts:
                return str(fn.consts[node.id]), "int64_t"
            if node.id in fn.types:
                return node.id, fn.types[node.id]
            raise CodegenError(f"name {node.id!r} used before it is assigned")
        if isinstance(node, ast.Attribute):
            text = ast.unparse(node)
            if text in NAMES:
                return NAMES[text], "double"
            raise CodegenError(f"attribute {text!r} in a kernel")
        if isinstance(node, ast.Subscript):
            return self.subscript(node), "double" if self._is_array(node.value) else "int64_t"
        if isinstance(node, ast.UnaryOp):
            a, t = self.c(node.operand)
            if isinstance(node.op, ast.USub):
                return f"(-{a})", t
            if isinstance(node.op, ast.UAdd):
                return a, t
            if isinstance(node.op, ast.Not):
                return f"(!{a})", "int64_t"
            if isinstance(node.op, ast.Invert):
                return f"(~{a})", "int64_t"
        if isinstance(node, ast.BinOp):
            return self.binop(node)
        if isinstance(node, ast.BoolOp):
            op = " && " if isinstance(node.op, ast.And) else " || "
            return "(" + op.join(self.c(v)[0] for v in node.values) + ")", "int64_t"
        if isinstance(node, ast.Compare):
            ops = {ast.Lt: "<", ast.LtE: "<=", ast.Gt: ">", ast.GtE: ">=", ast.Eq: "==",
                   ast.NotEq: "!="}
            parts, left = [], node.left
            for op, right in zip(node.ops, node.comparators):
                if type(op) not in ops:
                    raise CodegenError(f"comparison {type(op).__name__} in a kernel")
                parts.append(f"({self.c(left)[0]} {ops[type(op)]} {self.c(right)[0]})")
                left = right
            return ("(" + " && ".join(parts) + ")") if len(parts) > 1 else parts[0], "int64_t"
        if isinstance(node, ast.IfExp):
            (b, tb), (o, to) = self.c(node.body), self.c(node.orelse)
            return f"({self.c(node.test)[0]} ? {b} : {o})", _promote(tb, to)
        if isinstance(node, ast.Call):
            return self.call(node)
        raise CodegenError(f"expression {ast.unparse(node)!r} in a kernel")

    def _is_array(self, node) -> bool:
        return isinstance(node, ast.Name) and node.id in self.fn.arrays

    def subscript(self, node) -> str:
        base = node.value
        if isinstance(base, ast.Attribute) and base.attr == "shape" and self._is_array(base.value):
            k = node.slice
            if isinstance(k, ast.Constant) and isinstance(k.value, int):
                return f"{base.value.id}_sh{k.value}"
        if not self._is_array(base):
            raise CodegenError(f"subscript {ast.unparse(node)!r} in a kernel")
        name, rank = base.id, self.fn.arrays[base.id]
        idx = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
        if len(idx) != rank or any(isinstance(i, ast.Slice) for i in idx):
            raise CodegenError(f"subscript {ast.unparse(node)!r} in a kernel")
        texts = [self.c(i)[0] for i in idx]
        if rank == 1:
            return f"{name}[{texts[0]}]"
        return f"{name}[({texts[0]}) * {name}_sh1 + ({texts[1]})]"

    def binop(self, node) -> tuple[str, str]:
        (a, ta), (b, tb) = self.c(node.left), self.c(node.right)
        op = node.op
        if isinstance(op, ast.Pow):
            return self.power(node.left, node.right, a, ta)
        if isinstance(op, ast.Div):
            if ta == tb == "int64_t":
                return f"((double){a} / (double){b})", "double"
            return f"({a} / {b})", "double"
        if isinstance(op, ast.FloorDiv):
            if ta == tb == "int64_t":
                return f"({a} / {b})", "int64_t"
            return f"floor({a} / {b})", "double"
        sym = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.BitAnd: "&", ast.BitOr: "|",
               ast.BitXor: "^"}.get(type(op))
        if sym is None:
            raise CodegenError(f"operator {type(op).__name__} in a kernel")
        if sym in "&|^":
            return f"({a} {sym} {b})", "int64_t"
        return f"({a} {sym} {b})", _promote(ta, tb)

    def power(self, base, exp, a: str, ta: str) -> tuple[str, str]:
        """``base ** exp``: a constant integer exponent by products (numba
        multiplies too), in a column kernel a constant exponent of quarters
        by square roots (``bg_powq``, :func:`_quarter`), anything else by
        ``pow``."""
        q = _quarter(exp) if self.fn.columns else None
        if q is not None:
            return f"bg_powq({a}, {q[0]}, {int(q[1])})", "double"
        e = exp
        neg = False
        if isinstance(e, ast.UnaryOp) and isinstance(e.op, ast.USub):
            e, neg = e.operand, True
        if isinstance(e, ast.Constant) and isinstance(e.value, int) and not isinstance(
                e.value, bool) and 0 <= e.value <= 8:
            n = e.value
            if n == 0:
                return "1.0", "double"
            text = _square_product(a, n)
            return (f"(1.0 / {text})" if neg else text), "double"
        b, _ = self.c(exp)
        return f"pow({a}, {b})", "double"

    def call(self, node) -> tuple[str, str]:
        name = ast.unparse(node.func)
        args = [self.c(a) for a in node.args]
        if node.keywords:
            raise CodegenError(f"call {ast.unparse(node)!r} with keywords in a kernel")
        texts = ", ".join(t for t, _ in args)
        if name == "_sel" and len(args) == 3:
            return f"({args[0][0]} ? {args[1][0]} : {args[2][0]})", _promote(args[1][1],
                                                                             args[2][1])
        if name == "np.power" and len(node.args) == 2:
            return self.power(node.args[0], node.args[1], args[0][0], args[0][1])
        if name == "np.int64":
            return f"((int64_t)({texts}))", "int64_t"
        if name in ("np.float64", "float"):
            return f"((double)({texts}))", "double"
        if name == "abs" or name in ("np.abs", "np.fabs"):
            if args[0][1] == "int64_t":
                return f"llabs({texts})", "int64_t"
            return f"fabs({texts})", "double"
        if name in ("min", "max") and all(t == "int64_t" for _, t in args) and len(args) == 2:
            return f"bg_i{name}({texts})", "int64_t"
        if name in ("min", "max") and len(args) == 2:
            return f"bg_{name}imum({texts})", "double"
        if name in VMATH_ARGS:
            return f"{name}({texts})", VMATH_RESULT[name]
        if name == "_tanh":
            return f"bg_tanh({texts})", "double"
        if name in CALLS:
            return f"{CALLS[name]}({texts})", "double"
        raise CodegenError(f"function {name!r} has no C translation")


def _square_product(a: str, n: int) -> str:
    """``a ** n`` (n >= 1) as products by repeated squaring."""
    if n == 1:
        return a
    half = _square_product(a, n // 2)
    sq = f"({half} * {half})"
    return f"({sq} * {a})" if n % 2 else sq


class _Body:
    """C statements of a function body (two passes: the locals' types, then
    the text)."""

    def __init__(self, fn: _Func):
        self.fn = fn
        self.ex = _Expr(fn)

    def infer(self, stmts) -> None:
        """The C type of every name the statements assign (a name assigned
        both a float and an integer is a float)."""
        for st in stmts:
            if isinstance(st, ast.Assign) and len(st.targets) == 1 and isinstance(
                    st.targets[0], ast.Name):
                name = st.targets[0].id
                t = self.ex.type_of(st.value)
                self.fn.types[name] = _promote(self.fn.types.get(name, t), t)
            elif isinstance(st, ast.AugAssign) and isinstance(st.target, ast.Name):
                name = st.target.id
                self.fn.types.setdefault(name, "int64_t")
            elif isinstance(st, ast.For):
                if not isinstance(st.target, ast.Name):
                    raise CodegenError("a kernel loop over more than one name")
                self.fn.types[st.target.id] = "int64_t"
                self.infer(st.body)
            elif isinstance(st, ast.If):
                self.infer(st.body)
                self.infer(st.orelse)

    def lines(self, stmts, indent: str) -> list[str]:  # noqa: C901 - one case per statement
        out = []
        for st in stmts:
            if isinstance(st, ast.Expr) and isinstance(st.value, ast.Constant):
                continue                       # a docstring
            if isinstance(st, ast.Assign):
                if len(st.targets) != 1:
                    raise CodegenError("a chained assignment in a kernel")
                out.extend(self.assign(st.targets[0], st.value, indent))
            elif isinstance(st, ast.AugAssign):
                sym = {ast.Add: "+=", ast.Sub: "-=", ast.Mult: "*="}.get(type(st.op))
                if sym is None or not isinstance(st.target, ast.Name):
                    raise CodegenError(f"statement {ast.unparse(st)!r} in a kernel")
                out.append(f"{indent}{st.target.id} {sym} {self.ex.c(st.value)[0]};")
            elif isinstance(st, ast.For):
                out.extend(self.loop(st, indent))
            elif isinstance(st, ast.If):
                out.append(f"{indent}if ({self.ex.c(st.test)[0]}) {{")
                out.extend(self.lines(st.body, indent + "    "))
                if st.orelse:
                    out.append(f"{indent}}} else {{")
                    out.extend(self.lines(st.orelse, indent + "    "))
                out.append(f"{indent}}}")
            elif isinstance(st, ast.Return):
                out.append(f"{indent}return;" if st.value is None else
                           f"{indent}return {self.ex.c(st.value)[0]};")
            elif isinstance(st, ast.Pass):
                continue
            else:
                raise CodegenError(f"statement {ast.unparse(st)!r} in a kernel")
        return out

    def assign(self, target, value, indent: str) -> list[str]:
        if isinstance(target, ast.Name):
            return [f"{indent}{target.id} = {self.ex.c(value)[0]};"]
        if isinstance(target, ast.Subscript) and isinstance(target.value, ast.Name):
            name = target.value.id
            sl = target.slice
            elts = sl.elts if isinstance(sl, ast.Tuple) else [sl]
            if all(isinstance(e, ast.Slice) and e.lower is None and e.upper is None
                   and e.step is None for e in elts) and name in self.fn.arrays:
                v = self.ex.c(value)[0]
                return [f"{indent}for (int64_t _i = 0; _i < {name}_ni; ++_i) {name}[_i] = {v};"]
            return [f"{indent}{self.ex.subscript(target)} = {self.ex.c(value)[0]};"]
        raise CodegenError(f"assignment to {ast.unparse(target)!r} in a kernel")

    def loop(self, st: ast.For, indent: str) -> list[str]:
        it = st.iter
        if not (isinstance(it, ast.Call) and ast.unparse(it.func) == "range"
                and len(it.args) in (1, 2) and not st.orelse):
            raise CodegenError(f"loop {ast.unparse(it)!r} in a kernel")
        lo, hi = ("0", self.ex.c(it.args[0])[0]) if len(it.args) == 1 else (
            self.ex.c(it.args[0])[0], self.ex.c(it.args[1])[0])
        v = st.target.id
        out = [f"{indent}for ({v} = {lo}; {v} < {hi}; ++{v}) {{"]
        out.extend(self.lines(st.body, indent + "    "))
        out.append(f"{indent}}}")
        return out

    def declarations(self, skip: set, indent: str) -> list[str]:
        by: dict = {}
        for name, t in self.fn.types.items():
            if name not in skip:
                by.setdefault(t, []).append(name)
        return [f"{indent}{t} {', '.join(names)};" for t, names in sorted(by.items())]


def _function(fdef: ast.FunctionDef, arrays: dict, scalars: dict, consts: dict,
              ret: str, name: str, storage: str) -> str:
    """C text of one function."""
    fn = _Func(arrays, scalars, consts, columns=name in COLUMN_KERNELS)
    body = _Body(fn)
    stmts = fdef.body
    body.infer(stmts)
    params = []
    for a in fdef.args.args:
        if a.arg in arrays:
            params.append(("BG_V" if arrays[a.arg] == 1 else "BG_M") + f"({a.arg})")
        else:
            params.append(f"{scalars[a.arg]} {a.arg}")
    decl = body.declarations(set(scalars) | set(arrays), "    ")
    text = body.lines(stmts, "    ")
    return f"{storage}{ret} {name}({', '.join(params)})\n{{\n" + "\n".join(decl + text) + "\n}\n"


@functools.cache
def _vmath_c(name: str) -> str:
    """C text of the :mod:`bondgraph.core.vmath` function ``name``."""
    src = textwrap.dedent(inspect.getsource(getattr(vmath, name)))
    fdef = ast.parse(src).body[0]
    scalars = dict(zip((a.arg for a in fdef.args.args), VMATH_ARGS[name]))
    return _function(fdef, {}, scalars, {}, VMATH_RESULT[name], name, "BG_INLINE ")


@functools.cache
def _tanh_c() -> str:
    """C text of the point kernels' tanh (:func:`bondgraph.core.vmath._tanh`)."""
    fdef = ast.parse(textwrap.dedent(inspect.getsource(vmath._tanh))).body[0]
    return _function(fdef, {}, {"x": "double"}, {}, "double", "bg_tanh", "BG_INLINE ")


def functions_c() -> str:
    """The C text every translation starts with: :data:`PRELUDE`, the point
    kernels' tanh (``bg_tanh``) and the :mod:`bondgraph.core.vmath` functions
    of :data:`bondgraph.core.vmath.INLINE` translated from their Python
    source (callees first; ``static inline``: an unused one costs the
    compiler nothing)."""
    return "\n".join([PRELUDE, _tanh_c()] + [_vmath_c(name) for name in vmath.INLINE
                                             if name not in C_DEFINED])


def _module_consts(tree: ast.Module) -> dict:
    out = {}
    for st in tree.body:
        if isinstance(st, ast.Assign):
            tgts = st.targets[0]
            names = tgts.elts if isinstance(tgts, ast.Tuple) else [tgts]
            vals = st.value.elts if isinstance(st.value, ast.Tuple) else [st.value]
            for n, v in zip(names, vals):
                if isinstance(n, ast.Name) and isinstance(v, ast.Constant) and isinstance(
                        v.value, int) and n.id.isupper():
                    out[n.id] = v.value
    return out


def translate(numba_source: str) -> str:
    """C99 text of the kernels of a generated numba module.

    Parameters
    ----------
    numba_source : str
        The text :func:`bondgraph.core.codegen_numba.generate_numba_source`
        wrote (a registered model's ``generated/numba_kernels/<model>.py``
        or an in-memory model's kernel file).

    Returns
    -------
    str
        One translation unit that includes ``<math.h>`` and ``<stdint.h>``
        and defines the exported functions ``f``, ``h``, ``f_dfdx``,
        ``f_cols`` and ``h_cols`` (:data:`KERNELS`), each taking its arrays
        as numba's data model passes them (macros ``BG_V``, ``BG_M``).

    Raises
    ------
    CodegenError
        A statement, operator or function the translator does not know (the
        caller compiles the numba module instead).
    """
    tree = ast.parse(numba_source)
    consts = _module_consts(tree)
    defs = {st.name: st for st in tree.body if isinstance(st, ast.FunctionDef)}
    missing = [k for k in KERNELS if k not in defs]
    if missing:
        raise CodegenError(f"the numba module defines no {', '.join(missing)}")
    parts = [functions_c()]
    for name, ranks in KERNELS.items():
        fdef = defs[name]
        arrays = {a.arg: r for a, r in zip(fdef.args.args, ranks)}
        if len(arrays) != len(fdef.args.args):
            raise CodegenError(f"kernel {name} takes {len(fdef.args.args)} arguments")
        parts.append(_function(fdef, arrays, {}, consts, "void", name, ""))
    return "\n".join(parts)
