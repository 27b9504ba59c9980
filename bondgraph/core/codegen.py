"""Code generation: a derived :class:`~bondgraph.core.equations.StateSpace` becomes
a plain, readable Python module that imports only numpy.

Every function is batched over leading axes: ``x`` has shape ``(..., n_x)``,
``u`` ``(..., n_u)``, ``theta`` ``(..., n_θ)``; they broadcast together, so one
call evaluates every sigma point of every candidate parameter set (e.g.
``x`` of shape (80, 25, 12) with ``theta`` of shape (80, 1, 40)).

Generated functions: ``f``, ``h``, ``dfdx``, ``dfdtheta``, ``dhdx``,
``dhdtheta``, ``f_dfdx`` (f and its Jacobian with shared subexpressions, for
Rosenbrock steps), ``energy``, ``power_sources``, ``power_dissipated``,
``energy_rate``, ``meas_std``, ``proc_std``, and the filterpy adapter
``fx(x, dt, **kw)`` / ``hx(x, **kw)``. Common subexpressions are eliminated
with ``sympy.cse``; state, input, parameter and output indices are named
module constants; metadata (names, units, defaults, bounds) are module
constants too.

:func:`generate_numba_source` writes the compiled counterpart from the same
sympy expressions: per-point kernels ``f``, ``h`` and ``f_dfdx`` (one state
vector per call, results written into caller-owned arrays) decorated with
``numba.njit`` with explicit signatures and ``cache=True``, which the fused
UKF kernel (:mod:`bondgraph.inference.ukf_numba`) calls as first-class
functions. The numpy module stays the reference and the fallback.
"""

from __future__ import annotations

import ast
import copy
import importlib.util
import itertools
import sys
import textwrap
import types
from pathlib import Path

import sympy as sp
from sympy.printing.numpy import NumPyPrinter

from bondgraph.core.equations import StateSpace
from bondgraph.core.symbols import identifier
from bondgraph.errors import CodegenError

# argument and module names used inside generated functions; generated locals
# start with "_" (user names never do), so only these can collide
RESERVED = {"x", "u", "theta", "np"}

ALL_FUNCTIONS = ("f", "h", "dfdx", "dfdtheta", "dhdx", "dhdtheta", "f_dfdx", "energy",
                 "power_sources", "power_dissipated", "energy_rate")


class _Printer(NumPyPrinter):
    """NumPy printer with symbol renaming, broadcasting-safe max/min and
    cheap powers."""

    def __init__(self, names: dict):
        super().__init__({"fully_qualified_modules": True, "allow_unknown_functions": False})
        self._names = names

    def _print_Symbol(self, expr):
        return self._names.get(expr, expr.name)

    _print_Dummy = _print_Symbol

    def _print_Max(self, expr):
        args = [self._print(a) for a in expr.args]
        out = args[0]
        for a in args[1:]:
            out = f"np.maximum({out}, {a})"
        return out

    def _print_Min(self, expr):
        args = [self._print(a) for a in expr.args]
        out = args[0]
        for a in args[1:]:
            out = f"np.minimum({out}, {a})"
        return out

    def _print_Abs(self, expr):
        return f"np.abs({self._print(expr.args[0])})"

    def _print_Rational(self, expr):
        v = float(expr)
        r = repr(v)
        if len(r) <= 8:
            return r
        return f"({expr.p}/{expr.q})"

    def _print_Half(self, expr):
        return "0.5"

    def _print_Pow(self, expr, rational=False):
        b, e = expr.args
        if e.is_Integer and e < 0:
            base = self.parenthesize(b, sp.printing.precedence.PRECEDENCE["Pow"])
            n = -int(e)
            return f"1/{base}" if n == 1 else f"1/{base}**{n}"
        if e == sp.Rational(1, 2):
            return f"np.sqrt({self._print(b)})"
        if e == -sp.Rational(1, 2):
            return f"1/np.sqrt({self._print(b)})"
        return super()._print_Pow(expr, rational=rational)


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

    def _print_Piecewise(self, expr):
        out = "np.nan"
        for value, cond in reversed(expr.args):
            if cond == sp.true:
                out = self._print(value)
            else:
                out = f"({self._print(value)} if {self._print(cond)} else {out})"
        return out


class _Namer:
    """Unique identifiers for model symbols."""

    def __init__(self):
        self.used: set[str] = set(RESERVED)
        self.names: dict = {}

    def add(self, sym, prefix: str = "") -> str:
        base = prefix + identifier(sym.name)
        name = base
        k = 2
        while name in self.used:
            name = f"{base}_{k}"
            k += 1
        self.used.add(name)
        self.names[sym] = name
        return name


def _fmt_list(items, indent=4) -> str:
    items = list(items)
    if not items:
        return "()"
    body = ",\n".join(" " * indent + repr(i) for i in items)
    return "(\n" + body + ",\n)"


def _fmt_floats(values) -> str:
    vals = [repr(float(v)) for v in values]
    if not vals:
        return "np.zeros(0)"
    return "np.array([" + ", ".join(vals) + "])"


class _Gen:
    def __init__(self, ss: StateSpace, *, source: str | None, command: str):
        self.ss = ss
        self.source = source or ss.source or "<unknown>"
        self.command = command
        nm = _Namer()
        self.x_names = [nm.add(s) for s in ss.states]
        self.u_names = [nm.add(s) for s in ss.inputs]
        self.p_names = [nm.add(s) for s in ss.params]
        self.namer = nm
        self.printer = _Printer(nm.names)
        self.sym_index = {}
        for i, s in enumerate(ss.states):
            self.sym_index[s] = ("x", i)
        for i, s in enumerate(ss.inputs):
            self.sym_index[s] = ("u", i)
        for i, s in enumerate(ss.params):
            self.sym_index[s] = ("theta", i)

    # ------------------------------------------------------------------
    def pr(self, expr) -> str:
        text = self.printer.doprint(expr)
        return text.replace("numpy.", "np.")

    def assign(self, target: str, e: sp.Expr) -> str:
        """``target = e``; a top-level sum or product writes straight into the
        output row through the ufunc's ``out=`` (one memory pass less than a
        temporary followed by a copy)."""
        if e.is_Add and len(e.args) >= 2:
            first, rest = e.args[0], sp.Add(*e.args[1:])
            return f"np.add({self.pr(rest)}, {self.pr(first)}, out={target})"
        if e.is_Mul and len(e.args) >= 2 and not any(a.is_Number for a in e.args[1:]):
            first, rest = e.args[0], sp.Mul(*e.args[1:])
            return f"np.multiply({self.pr(first)}, {self.pr(rest)}, out={target})"
        return f"{target} = {self.pr(e)}"

    def _unpack(self, syms, allowed=("x", "u", "theta"), point: bool = False) -> list[str]:
        lines = []
        for kind in ("x", "u", "theta"):
            chosen = sorted((s for s in syms if s in self.sym_index and self.sym_index[s][0] == kind),
                            key=lambda s: self.sym_index[s][1])
            for s in chosen:
                if kind not in allowed:
                    raise CodegenError(f"model '{self.ss.name}': {s.name} may not appear here "
                                       f"(only {', '.join(allowed)})")
                arr, i = self.sym_index[s]
                lines.append(f"{self.namer.names[s]} = {arr}[{'' if point else '..., '}{i}]")
        unknown = [s for s in syms if s not in self.sym_index and not str(s).startswith("_t")]
        if unknown:
            raise CodegenError(f"model '{self.ss.name}': symbols {sorted(map(str, unknown))} are not "
                               f"states, inputs or parameters")
        return lines

    def body(self, outputs: list[tuple[str, list[tuple[tuple, sp.Expr]]]],
             allowed=("x", "u", "theta"), shape_of=("x", "u", "theta")) -> list[str]:
        """Lines computing several output arrays with one shared CSE.

        outputs: list of (array_name, [(index_tuple, expr)], full_shape_suffix)
        """
        flat = []
        for _, entries, _suffix in outputs:
            flat += [e for _, e in entries]
        repl, reduced = sp.cse(flat, symbols=sp.numbered_symbols("_t"), optimizations=None,
                               order="none")
        syms = set()
        for e in reduced:
            syms |= e.free_symbols
        for _, e in repl:
            syms |= e.free_symbols
        syms = {s for s in syms if not str(s).startswith("_t")}
        lines = self._unpack(syms, allowed)
        for s, e in repl:
            lines.append(f"{s} = {self.pr(e)}")
        sizes = {"x": len(self.ss.states), "u": len(self.ss.inputs), "theta": len(self.ss.params)}
        if all(sizes[a] > 0 for a in shape_of):
            # np.broadcast(...).shape is ~2 us cheaper per call than broadcast_shapes
            shape_args = ", ".join(f"{a}[..., 0]" for a in shape_of)
            lines.append(f"_shape = np.broadcast({shape_args}).shape")
        else:
            shape_args = ", ".join(f"{a}.shape[:-1]" for a in shape_of)
            lines.append(f"_shape = np.broadcast_shapes({shape_args})")
        # Outputs are filled "state-major" (component axes first, so each
        # assignment writes one contiguous row) and returned as a view with the
        # component axes last: shape (..., n) as documented, memory laid out so
        # that a caller feeding the result back reads contiguous columns.
        k = 0
        for name, entries, suffix in outputs:
            dense = len(entries) == _prod(suffix)
            alloc = "np.empty" if dense else "np.zeros"
            if len(suffix) == 0:
                lines.append(f"{name} = {alloc}(_shape)")
            else:
                lines.append(f"{name} = {alloc}({tuple(suffix)!r} + _shape)")
            for idx, _ in entries:
                e = reduced[k]
                k += 1
                index = ", ".join(str(i) for i in idx)
                if len(suffix) == 0:
                    lines.append(self.assign(f"{name}[...]", e))
                else:
                    lines.append(self.assign(f"{name}[{index}, ...]", e))
            if len(suffix) == 1:
                lines.append(f"{name} = {name}.transpose((*range(1, len(_shape) + 1), 0))")
            elif len(suffix) == 2:
                lines.append(f"{name} = {name}.transpose((*range(2, len(_shape) + 2), 0, 1))")
        return lines

    def function(self, name: str, args: str, doc: str, outputs, returns: str,
                 allowed=("x", "u", "theta"), shape_of=("x", "u", "theta")) -> str:
        conv = [f"{a} = np.asarray({a}, dtype=float)" for a in shape_of]
        lines = conv + self.body(outputs, allowed, shape_of) + [f"return {returns}"]
        doc = textwrap.indent(doc.strip("\n"), "    ")
        return (f"def {name}({args}):\n    \"\"\"{doc.strip()}\n    \"\"\"\n" +
                "\n".join("    " + ln for ln in lines) + "\n")

    # ------------------------------------------------------------------
    def module(self, functions=ALL_FUNCTIONS) -> str:
        """Source text of the whole module: header and constants, index
        constants, the requested functions, the noise functions and the
        filterpy adapter."""
        parts = [self._header(), self._index_constants()]
        parts += self._model_functions(functions)
        parts += self._jacobian_functions(functions)
        parts += self._energy_functions(functions)
        parts += self._noise_functions()
        parts.append(_FILTERPY_ADAPTER)
        text = "\n\n".join(p.rstrip("\n") + "\n" for p in parts)
        return text.rstrip("\n") + "\n"

    def _header(self) -> str:
        """Module docstring (states, inputs, parameters, outputs) and the
        metadata constants."""
        ss = self.ss
        nx, nu, npar = len(ss.states), len(ss.inputs), len(ss.params)
        desc = (ss.description or f"State-space model '{ss.name}'.").strip()
        state_doc = "\n".join(f"    {i:3d} {s.name} [{s.unit or '-'}] {s.state_kind}"
                              f"{' of ' + s.element if s.element else ''}"
                              for i, s in enumerate(ss.states))
        in_doc = "\n".join(f"    {i:3d} {u.name} [{u.unit or '-'}] {u.description}".rstrip()
                           for i, u in enumerate(ss.inputs)) or "    (none)"
        par_doc = "\n".join(f"    {i:3d} {p.name} = {p.default:g} [{p.unit or '-'}] {p.description}".rstrip()
                            for i, p in enumerate(ss.params)) or "    (none)"
        out_doc = "\n".join(f"    {i:3d} {o.name} [{o.unit or '-'}] {o.description}".rstrip()
                            for i, o in enumerate(ss.outputs)) or "    (none)"
        deriv = (f"\nStorages eliminated by derivative causality: {', '.join(ss.derivative_elements)}."
                 if ss.derivative_elements else "")
        loops = (f"\nAlgebraic loops solved symbolically: {len(ss.algebraic_loops)}."
                 if ss.algebraic_loops else "")
        return f'''"""{desc}

Generated by bondgraph from {self.source} (graph '{ss.name}').
DO NOT EDIT: regenerate with `{self.command}`; `bondgraph generate --check`
fails when this file differs from what the graph produces.

Arrays are batched over leading axes: x (..., {nx}), u (..., {nu}),
theta (..., {npar}) broadcast together.{deriv}{loops}

States x:
{state_doc}
Inputs u:
{in_doc}
Parameters theta:
{par_doc}
Outputs y:
{out_doc}
"""

import numpy as np

NAME = {ss.name!r}
SOURCE = {self.source!r}
DESCRIPTION = {(ss.description or '')!r}

STATES = {_fmt_list(s.name for s in ss.states)}
STATE_UNITS = {_fmt_list(s.unit for s in ss.states)}
STATE_KINDS = {_fmt_list(s.state_kind for s in ss.states)}
STATE_ELEMENTS = {_fmt_list(s.element or '' for s in ss.states)}
X0 = {_fmt_floats(s.initial for s in ss.states)}

INPUTS = {_fmt_list(u.name for u in ss.inputs)}
INPUT_UNITS = {_fmt_list(u.unit for u in ss.inputs)}
INPUT_DEFAULTS = {_fmt_floats(u.default for u in ss.inputs)}
DERIVATIVE_INPUTS = {{{", ".join(f"{u.name!r}: {u.derivative_of.name!r}" for u in ss.inputs if u.derivative_of is not None)}}}

PARAMS = {_fmt_list(p.name for p in ss.params)}
PARAM_UNITS = {_fmt_list(p.unit for p in ss.params)}
PARAM_DEFAULTS = {_fmt_floats(p.default for p in ss.params)}
PARAM_LOWER = {_fmt_floats(p.bounds[0] for p in ss.params)}
PARAM_UPPER = {_fmt_floats(p.bounds[1] for p in ss.params)}
PARAM_DESCRIPTIONS = {_fmt_list(p.description for p in ss.params)}

OUTPUTS = {_fmt_list(o.name for o in ss.outputs)}
OUTPUT_UNITS = {_fmt_list(o.unit for o in ss.outputs)}
'''

    def _index_constants(self) -> str:
        """``IX_<state> = i`` etc.: named indices into x, u, theta and y."""
        ss = self.ss
        idx = ["# index constants: x[..., IX_<state>], u[..., IU_<input>], "
               "theta[..., IP_<param>], y[..., IY_<output>]"]
        for i, n in enumerate(self.x_names):
            idx.append(f"IX_{n} = {i}")
        for i, n in enumerate(self.u_names):
            idx.append(f"IU_{n} = {i}")
        for i, n in enumerate(self.p_names):
            idx.append(f"IP_{n} = {i}")
        onamer = _Namer()
        for i, o in enumerate(ss.outputs):
            idx.append(f"IY_{onamer.add(sp.Symbol(o.name))} = {i}")
        return "\n".join(idx) + "\n"

    def _model_functions(self, functions) -> list[str]:
        """``f`` and ``h``."""
        ss = self.ss
        nx, ny = len(ss.states), len(ss.outputs)
        parts = []
        X = "x : array (..., n_x)\n    States.\nu : array (..., n_u)\n    Inputs.\n" \
            "theta : array (..., n_theta)\n    Parameters."
        if "f" in functions:
            parts.append(self.function(
                "f", "x, u, theta",
                f"State derivatives dx/dt = f(x, u, theta).\n\nParameters\n----------\n{X}\n\n"
                f"Returns\n-------\narray (..., {nx})",
                [("_dxdt", self._f_entries(), (nx,))], "_dxdt"))
        if "h" in functions:
            parts.append(self.function(
                "h", "x, u, theta",
                f"Outputs y = h(x, u, theta) (noise-free sensors).\n\nReturns\n-------\n"
                f"array (..., {ny})",
                [("_y", [((i,), e) for i, e in enumerate(ss.h)], (ny,))], "_y"))
        return parts

    def _f_entries(self) -> list:
        """``[((i,), f_i)]``: the state equations as output entries."""
        return [((i,), e) for i, e in enumerate(self.ss.f)]

    def _jacobian_functions(self, functions) -> list[str]:
        """``dfdx``, ``dfdtheta``, ``dhdx``, ``dhdtheta`` (non-zero entries
        only) and ``f_dfdx``."""
        ss = self.ss
        nx, npar, ny = len(ss.states), len(ss.params), len(ss.outputs)
        parts = []
        jac_specs = [("dfdx", ss.dfdx, (nx, nx), "df/dx"), ("dfdtheta", ss.dfdtheta, (nx, npar), "df/dtheta"),
                     ("dhdx", ss.dhdx, (ny, nx), "dh/dx"), ("dhdtheta", ss.dhdtheta, (ny, npar), "dh/dtheta")]
        cache = {}
        for name, fn, shape, label in jac_specs:
            if name not in functions and not (name == "dfdx" and "f_dfdx" in functions):
                continue
            M = fn()
            cache[name] = M
            entries = [((i, j), M[i, j]) for i in range(M.rows) for j in range(M.cols) if M[i, j] != 0]
            if name in functions:
                parts.append(self.function(
                    name, "x, u, theta",
                    f"Jacobian {label}, shape (..., {shape[0]}, {shape[1]}).",
                    [("_J", entries, shape)], "_J"))
        if "f_dfdx" in functions:
            M = cache["dfdx"]
            entries = [((i, j), M[i, j]) for i in range(M.rows) for j in range(M.cols) if M[i, j] != 0]
            parts.append(self.function(
                "f_dfdx", "x, u, theta",
                f"f and df/dx together (shared subexpressions), for Rosenbrock steps.\n\n"
                f"Returns\n-------\n(array (..., {nx}), array (..., {nx}, {nx}))",
                [("_dxdt", self._f_entries(), (nx,)), ("_J", entries, (nx, nx))], "_dxdt, _J"))
        return parts

    def _energy_functions(self, functions) -> list[str]:
        """``energy``, ``power_sources``, ``power_dissipated``, ``energy_rate``."""
        ss = self.ss
        energy_specs = [("energy", ss.energy, "Stored energy H(x, u, theta) [J], shape (...)."),
                        ("power_sources", ss.power_sources, "Power delivered by the sources [W], shape (...)."),
                        ("power_dissipated", ss.power_dissipated, "Power absorbed by the R elements [W], shape (...)."),
                        ("energy_rate", ss.energy_rate,
                         "dH/dt by the chain rule [W], shape (...); equals power_sources - "
                         "power_dissipated.")]
        return [self.function(name, "x, u, theta", doc, [("_out", [((), ex)], ())], "_out")
                for name, ex, doc in energy_specs if name in functions]

    def _noise_functions(self) -> list[str]:
        """``meas_std`` and ``proc_std`` (functions of the parameters only)."""
        ss = self.ss
        nx, ny = len(ss.states), len(ss.outputs)
        mstd = [o.noise_std if o.noise_std is not None else 0 for o in ss.outputs]
        pstd = [v if v is not None else 0 for v in ss.process_noise]
        meas = self.function(
            "meas_std", "theta",
            f"Measurement-noise standard deviations, shape (..., {ny}), in output units.",
            [("_out", [((i,), sp.sympify(v)) for i, v in enumerate(mstd)], (ny,))], "_out",
            allowed=("theta",), shape_of=("theta",))
        proc = self.function(
            "proc_std", "theta",
            f"Process-noise intensities, shape (..., {nx}), in state units per sqrt(s)\n"
            f"(the covariance added over a step dt is diag(proc_std**2) * dt).",
            [("_out", [((i,), sp.sympify(v)) for i, v in enumerate(pstd)], (nx,))], "_out",
            allowed=("theta",), shape_of=("theta",))
        return [meas, proc]


#: the filterpy adapter at the end of every generated module
_FILTERPY_ADAPTER = textwrap.dedent('''
    def fx(x, dt, u=None, theta=None, substeps=1):
        """filterpy-style transition x(t + dt) by classical RK4 with ``substeps``
        steps, inputs held constant (zero-order hold). ``u`` and ``theta`` default
        to INPUT_DEFAULTS and PARAM_DEFAULTS.
        """
        u = INPUT_DEFAULTS if u is None else u
        theta = PARAM_DEFAULTS if theta is None else theta
        _h = dt / substeps
        for _ in range(substeps):
            _k1 = f(x, u, theta)
            _k2 = f(x + 0.5 * _h * _k1, u, theta)
            _k3 = f(x + 0.5 * _h * _k2, u, theta)
            _k4 = f(x + _h * _k3, u, theta)
            x = x + (_h / 6.0) * (_k1 + 2.0 * _k2 + 2.0 * _k3 + _k4)
        return x


    def hx(x, u=None, theta=None):
        """filterpy-style measurement function: y = h(x, u, theta)."""
        u = INPUT_DEFAULTS if u is None else u
        theta = PARAM_DEFAULTS if theta is None else theta
        return h(x, u, theta)
    ''')


#: tanh of the numba modules: for |x| >= 0.55, 1 - 2/(exp(2|x|) + 1) with the sign
#: of x (glibc's tanh takes expm1 there, 2.5x the time of exp: tanh was a
#: sixth of the fused UKF kernel's time on vehicle_full, perf); np.tanh below.
#: Within 4.3e-16 relative of np.tanh (1e6 points on [-30, 30]); ±1 at ±inf
#: and for large |x|, NaN for NaN (the comparison is false, exp(NaN) is NaN).
NUMBA_TANH = '''
@njit(types.float64(types.float64), cache=True, nogil=True, error_model="numpy", inline="always")
def _tanh(x):
    """tanh(x) by exp for |x| >= 0.55 (bondgraph.core.codegen.NUMBA_TANH)."""
    a = abs(x)
    if a < 0.55:
        return np.tanh(x)
    r = 1.0 - 2.0 / (np.exp(2.0 * a) + 1.0)
    return r if x > 0 else -r
'''
#: Branch-free sin, cos, atan, exp and tanh of the column kernels, emitted
#: into each numba module that uses them: range reduction and rational or
#: polynomial approximations after S. L. Moshier, *Methods and Programs for
#: Mathematical Functions* (1989; the Cephes library), with conditional
#: expressions for selects, so that LLVM vectorises a loop that calls them
#: (numba's pip LLVM has no vector libm; a libm call keeps a loop scalar).
#: Within 2 ulp of numpy (tests/test_vmath.py: 1e6 points per range, the
#: non-finite values); sin and cos for |x| < 1e8 (the column kernels count
#: larger arguments and recompute with numpy's functions). The sources are
#: templates: :func:`vmath_inline` expands them, and the calls between
#: them, into straight code at each call site of a column kernel.
NUMBA_VMATH = {
    "_vatan": '''
def _vatan(x):
    """atan(x): 3 ranges by selects, a 4/5 rational in x² (Moshier 1989)."""
    a = abs(x)
    big = a > 2.41421356237309504880
    mid = a > 0.66
    z0 = _sel(big, -1.0, _sel(mid, a - 1.0, a)) / _sel(big, a, _sel(mid, a + 1.0, 1.0))
    y0 = _sel(big, 1.5707963267948966, _sel(mid, 0.7853981633974483, 0.0))
    mb = _sel(big, 6.123233995736765886130e-17, _sel(mid, 3.061616997868382943065e-17, 0.0))
    z = z0 * z0
    p = ((((-8.750608600031904122785e-1 * z - 1.615753718733365076637e1) * z
           - 7.500855792314704667340e1) * z - 1.228866684490136173410e2) * z
         - 6.485021904942025371773e1)
    q = (((((z + 2.485846490142306297962e1) * z + 1.650270098316988542046e2) * z
           + 4.328810604912902668951e2) * z + 4.853903996359136964868e2) * z
         + 1.945506571482613964425e2)
    r = y0 + ((z0 * (z * p / q) + z0) + mb)
    return _sel(x < 0, -r, r)
''',
    "_vsincos": '''
def _vsincos(a, shift):
    """sin (shift 0) or cos (shift 2) of a >= 0 below 1e8: reduction by π/4 in
    three parts, degree-6 polynomials in z² (Moshier 1989)."""
    y0 = np.floor(a * 1.2732395447351628)
    j0 = _sel(a < 1e15, np.int64(y0), np.int64(0))
    odd = (j0 & 1) == 1
    j1 = _sel(odd, j0 + 1, j0)
    y = _sel(odd, y0 + 1.0, y0)
    j2 = (j1 + shift) & 7
    neg = j2 > 3
    j = _sel(neg, j2 - 4, j2)
    z = (((a - y * 7.85398125648498535156e-1) - y * 3.77489470793079817668e-8)
         - y * 2.69515142907905952645e-15)
    zz = z * z
    c = 1.0 - 0.5 * zz + zz * zz * ((((((-1.13585365213876817300e-11 * zz
                                         + 2.08757008419747316778e-9) * zz
                                        - 2.75573141792967388112e-7) * zz
                                       + 2.48015872888517045348e-5) * zz
                                      - 1.38888888888730564116e-3) * zz
                                     + 4.16666666666665929218e-2))
    s = z + z * zz * ((((((1.58962301576546568060e-10 * zz - 2.50507477628578072866e-8) * zz
                          + 2.75573136213857245213e-6) * zz - 1.98412698295895385996e-4) * zz
                        + 8.33333333332211858878e-3) * zz - 1.66666666666666307295e-1))
    r = _sel((j == 1) | (j == 2), c, s)
    return _sel(neg, -r, r)
''',
    "_vsin": '''
def _vsin(x):
    """sin(x) for |x| < 1e8 (_vsincos)."""
    r = _vsincos(abs(x), 0)
    return _sel(x < 0, -r, r)
''',
    "_vcos": '''
def _vcos(x):
    """cos(x) for |x| < 1e8 (_vsincos)."""
    return _vsincos(abs(x), 2)
''',
    "_pow2": '''
def _pow2(n):
    """2**n for |n| <= 1022 from the bits of |n| (selects and exact products)."""
    neg = n < 0
    a = _sel(neg, -n, n)
    p0 = _sel((a & 1) != 0, _sel(neg, 0.5, 2.0), 1.0)
    p1 = p0 * _sel((a & 2) != 0, _sel(neg, 0.25, 4.0), 1.0)
    p2 = p1 * _sel((a & 4) != 0, _sel(neg, 0.0625, 16.0), 1.0)
    p3 = p2 * _sel((a & 8) != 0, _sel(neg, 0.00390625, 256.0), 1.0)
    p4 = p3 * _sel((a & 16) != 0, _sel(neg, 1.52587890625e-05, 65536.0), 1.0)
    p5 = p4 * _sel((a & 32) != 0, _sel(neg, 2.3283064365386963e-10, 4294967296.0), 1.0)
    p6 = p5 * _sel((a & 64) != 0, _sel(neg, 5.421010862427522e-20, 1.8446744073709552e19), 1.0)
    p7 = p6 * _sel((a & 128) != 0, _sel(neg, 2.938735877055719e-39, 3.402823669209385e38), 1.0)
    p8 = p7 * _sel((a & 256) != 0, _sel(neg, 8.636168555094445e-78, 1.157920892373162e77), 1.0)
    return p8 * _sel((a & 512) != 0, _sel(neg, 7.458340731200207e-155, 1.3407807929942597e154),
                     1.0)
''',
    "_vexp": '''
def _vexp(x):
    """exp(x) = 2**n exp(r), |r| <= ln2/2, a 2/3 rational in r² (Moshier 1989);
    inf above 709.78, 0 below -708.40 (numpy: a subnormal there), NaN for NaN."""
    xc = _sel(x > 709.79, 709.79, _sel(x < -708.4, -708.4, x))
    fl = np.floor(1.4426950408889634 * xc + 0.5)
    r = (xc - fl * 6.93145751953125e-1) - fl * 1.42860682030941723212e-6
    n = np.int64(fl)
    xx = r * r
    px = r * ((1.26177193074810590878e-4 * xx + 3.02994407707441961300e-2) * xx
              + 9.99999999999999999910e-1)
    e0 = 1.0 + 2.0 * (px / ((((3.00198505138664455042e-6 * xx + 2.52448340349684104192e-3) * xx
                              + 2.27265548208155028766e-1) * xx + 2.00000000000000000009e0)
                            - px))
    big = n > 1000
    e1 = _sel(big, e0 * 2.0, e0) * _pow2(_sel(big, n - 1, n))
    e = _sel(x > 7.09782712893383996843e2, np.inf, _sel(x < -7.08396418532264106224e2, 0.0, e1))
    return _sel(x != x, x, e)
''',
    "_vtanh": '''
def _vtanh(x):
    """tanh(x): x + x³ P(x²)/Q(x²) below |x| = 0.625 (Moshier 1989), else
    1 − 2/(exp(2|x|) + 1) with the sign of x, exp(2|x|) = 2**n (q + p)/(q − p)
    as in _vexp; one division for both branches (a select of numerator and
    denominator); NaN for NaN."""
    a = abs(x)
    z = x * x
    aa = 2.0 * _sel(a > 40.0, 40.0, a)
    fl = np.floor(1.4426950408889634 * aa + 0.5)
    r = (aa - fl * 6.93145751953125e-1) - fl * 1.42860682030941723212e-6
    rr = r * r
    p = r * ((1.26177193074810590878e-4 * rr + 3.02994407707441961300e-2) * rr
             + 9.99999999999999999910e-1)
    q = (((3.00198505138664455042e-6 * rr + 2.52448340349684104192e-3) * rr
          + 2.27265548208155028766e-1) * rr + 2.00000000000000000009e0)
    d = q - p
    small = a < 0.625
    num = _sel(small, x * z * ((-9.64399179425052238628e-1 * z - 9.92877231001918586564e1) * z
                               - 1.61468768441708447952e3), 2.0 * d)
    den = _sel(small, ((z + 1.12811678491632931402e2) * z + 2.23548839060100448583e3) * z
               + 4.84406305325125486048e3, _pow2(np.int64(fl)) * (q + p) + d)
    t = num / den
    big = 1.0 - t
    return _sel(small, x + t, _sel(x < 0, -big, big))
''',
}
#: the select of the NUMBA_VMATH templates, emitted into each numba module
#: that uses them: ``a if c else b`` as one LLVM select instruction (both a and
#: b are computed; a Python conditional expression would be branches, whose
#: blocks make numba's SSA and liveness passes slow on long kernels: the
#: column kernels of vehicle_full compiled in 8.7 s with them)
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
#: vector functions whose argument must be below 1e8 in magnitude
VMATH_LIMITED = ("_vsin", "_vcos")
#: sigma point kernels of the numba module (called by bondgraph.inference.ukf_numba)
NUMBA_FUNCTIONS = ("f", "h", "f_dfdx", "f_cols", "h_cols")
#: version of the numba code generator: part of the key of compiled kernels
#: built in memory (bump it when the generated numba text changes)
NUMBA_CODEGEN_VERSION = 6


#: the column kernels' loops run over a multiple of POINTS_VECTOR points, at
#: least POINTS_MIN: LLVM vectorises no loop of a constant trip count below
#: 16 (its "tiny loop" rule), and the branch-free functions run scalar cost
#: more than libm's (vehicle_coastdown, 11 points: 0.67 against 0.50 µs)
POINTS_VECTOR, POINTS_MIN = 4, 16


def padded_points(n_x: int) -> int:
    """Columns of a column kernel's arrays: the 2 n_x + 1 sigma points, then
    copies of point 0 up to a multiple of :data:`POINTS_VECTOR` and at least
    :data:`POINTS_MIN` (the loop over points runs in whole AVX2 vectors)."""
    return max(POINTS_MIN, (2 * n_x + POINTS_VECTOR) // POINTS_VECTOR * POINTS_VECTOR)


#: sympy functions the column kernels compute inline by :data:`NUMBA_VMATH`
VMATH_CALLS = {sp.sin: "_vsin", sp.cos: "_vcos", sp.atan: "_vatan", sp.exp: "_vexp",
               sp.tanh: "_vtanh"}


def _vmath_def(name: str) -> ast.FunctionDef:
    """The parsed :data:`NUMBA_VMATH` function ``name`` (decorator dropped)."""
    fn = ast.parse(textwrap.dedent(NUMBA_VMATH[name])).body[0]
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
    """Calls of :data:`NUMBA_VMATH` functions replaced by their result
    variables, their statements appended to ``lines``."""

    def __init__(self, lines: list, counter):
        self.lines, self.counter = lines, counter

    def visit_Call(self, node):
        self.generic_visit(node)
        if isinstance(node.func, ast.Name) and node.func.id in NUMBA_VMATH:
            body, res, _ = vmath_inline(node.func.id, [ast.unparse(a) for a in node.args],
                                        self.counter)
            self.lines += body
            return ast.Name(res, ast.Load())
        return node


def vmath_inline(name: str, args, counter) -> tuple[list[str], str, str]:
    """Statements that compute the :data:`NUMBA_VMATH` function ``name`` at
    the argument expressions ``args`` (source text), with the calls it makes
    expanded too: straight code, so that numba compiles a kernel with many
    calls quickly (numba's IR-level inlining copies the callee's IR at every
    call site: 4x the compile time of vehicle_full) and LLVM vectorises the
    loop around it. Local names become ``_v<k>_<name>``, k from ``counter``.

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


class _NumbaGen(_Gen):
    """Scalar per-point kernels for numba from the same expressions and names
    as the numpy module (:func:`generate_numba_source`)."""

    def __init__(self, ss: StateSpace, *, source: str | None, command: str):
        super().__init__(ss, source=source, command=command)
        self.printer = _ScalarPrinter(self.namer.names)

    def point_body(self, outputs) -> list[str]:
        """Lines computing ``outputs`` ([(array name, [(index, expr)], dense)])
        for one point, with one shared CSE, written into the given arrays."""
        flat = [e for _, entries, _ in outputs for _, e in entries]
        repl, reduced = sp.cse(flat, symbols=sp.numbered_symbols("_t"), optimizations=None,
                               order="none")
        syms = set()
        for e in list(reduced) + [e for _, e in repl]:
            syms |= e.free_symbols
        lines = self._unpack({s for s in syms if not str(s).startswith("_t")}, point=True)
        lines += [f"{s} = {self.pr(e)}" for s, e in repl]
        k = 0
        for name, entries, dense in outputs:
            if not dense:
                lines.append(f"{name}[:, :] = 0.0")
            for idx, _ in entries:
                lines.append(f"{name}[{', '.join(str(i) for i in idx)}] = {self.pr(reduced[k])}")
                k += 1
        return lines or ["return"]

    def cols_function(self, name: str, out: str, doc: str, entries) -> str:
        """A ``@njit(SIG_COLS, cache=True)`` column kernel: ``entries``
        ([((i,), expr)]) at every sigma point, the point's state a read from
        ``_X[a * N_PTS + j]`` and entry i written to ``out[i * N_PTS + j]``
        (state- or output-major flat arrays: every access of an array is at
        a constant distance from the others, so LLVM's loop vectoriser needs
        one alias check per array pair). The inputs, parameters and the
        subexpressions of them alone are computed once, before the loop;
        sin, cos, atan, exp and tanh are the branch-free :data:`NUMBA_VMATH`
        (the loop over points vectorises). An argument of sin or cos of
        magnitude 1e8 or more (or inf) is counted and the loop is run again
        with numpy's functions."""
        npt = padded_points(len(self.ss.states))
        repl, reduced = sp.cse([e for _, e in entries], symbols=sp.numbered_symbols("_t"),
                               optimizations=None, order="none")
        xs = {s for s in self.sym_index if self.sym_index[s][0] == "x"}
        varying = set(xs)
        for sym, e in repl:
            if e.free_symbols & varying:
                varying.add(sym)
        syms = set()
        for e in list(reduced) + [e for _, e in repl]:
            syms |= e.free_symbols
        used = {s for s in syms if not str(s).startswith("_t")}
        head = self._unpack(used - xs, point=True)
        head += [f"{s} = {self.pr(e)}" for s, e in repl if s not in varying]
        loads = [f"{self.namer.names[s]} = _X[{self.sym_index[s][1] * npt} + _j]"
                 for s in sorted(used & xs, key=lambda s: self.sym_index[s][1])]
        counter, far = itertools.count(), []

        def expanded(e, out: list):
            """``e`` with its calls of :data:`VMATH_CALLS` replaced by the
            result variables of their inline code (appended to ``out``,
            innermost first; a libm call would keep the loop scalar)."""
            if e.is_Atom:
                return e
            args = [expanded(a, out) for a in e.args]
            if any(a is not b for a, b in zip(args, e.args)):
                e = e.func(*args)
            name = VMATH_CALLS.get(e.func)
            if name is None:
                return e
            code, res, pre = vmath_inline(name, [self.pr(e.args[0])], counter)
            out += code
            if name in VMATH_LIMITED:
                out.append(f"_far += abs({pre}x) >= 1e8")
                far.append(name)
            return sp.Symbol(res)

        body = list(loads)
        for s, e in repl:
            if s in varying:
                body.append(f"{s} = {self.pr(expanded(e, body))}")
        for ((i,), _), e in zip(entries, reduced):
            body.append(f"{out}[{i * npt} + _j] = {self.pr(expanded(e, body))}")
        lines = head + ["_far = 0"] * bool(far) + [f"for _j in range({npt}):"]
        lines += ["    " + ln for ln in body]
        if far:
            plain = list(loads) + [f"{s} = {self.pr(e)}" for s, e in repl if s in varying]
            plain += [f"{out}[{i * npt} + _j] = {self.pr(e)}"
                      for ((i,), _), e in zip(entries, reduced)]
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
        J = self.ss.dfdx()
        jac = [((i, j), J[i, j]) for i in range(nx) for j in range(nx) if J[i, j] != 0]
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


def _prod(t) -> int:
    out = 1
    for v in t:
        out *= v
    return out


def generate_source(ss: StateSpace, *, source: str | None = None,
                    command: str = "bondgraph generate", functions=ALL_FUNCTIONS) -> str:
    """Source text of the generated module for ``ss``.

    Parameters
    ----------
    ss : StateSpace
    source : str, optional
        ``module:function`` that builds the graph (for the header).
    command : str
        Command that regenerates the file (for the header).
    functions : sequence of str
        Subset of :data:`ALL_FUNCTIONS` to generate (``meas_std``,
        ``proc_std``, ``fx``, ``hx`` are always there).

    Returns
    -------
    str
    """
    return _Gen(ss, source=source, command=command).module(functions)


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
    return _NumbaGen(ss, source=source, command=command).numba_module()


def write_module(ss: StateSpace, path: str | Path, **kw) -> Path:
    """Generate and write ``path``; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(generate_source(ss, **kw))
    return path


def load_module(path: str | Path, name: str | None = None) -> types.ModuleType:
    """Import a generated module from a file path (not necessarily on sys.path)."""
    path = Path(path)
    modname = name or f"_bondgraph_generated_{path.stem}_{abs(hash(str(path.resolve())))}"
    spec = importlib.util.spec_from_file_location(modname, path)
    if spec is None or spec.loader is None:
        raise CodegenError(f"cannot import generated module {path}")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[modname] = mod
    spec.loader.exec_module(mod)
    return mod


def module_from_source(text: str, name: str) -> types.ModuleType:
    """Execute generated source in memory (for temporary candidate models)."""
    mod = types.ModuleType(name)
    mod.__file__ = f"<generated {name}>"
    exec(compile(text, mod.__file__, "exec"), mod.__dict__)
    return mod
