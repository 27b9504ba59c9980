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

The compiled counterpart (numba point and column kernels from the same
sympy expressions, CSE and names) is written by
:func:`bondgraph.core.codegen_numba.generate_numba_source`, which builds on
this module's generator; the numpy module stays the reference and the
fallback.
"""

from __future__ import annotations

import importlib.util
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
#: functions generated only on request (not part of the committed numpy
#: modules): df/du and dh/du, the B and D of a linearisation
#: (:mod:`bondgraph.export.linearize`)
OPTIONAL_FUNCTIONS = ("dfdu", "dhdu")


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
        """``dfdx``, ``dfdtheta``, ``dhdx``, ``dhdtheta``, on request
        ``dfdu`` and ``dhdu`` (non-zero entries only) and ``f_dfdx``."""
        ss = self.ss
        nx, npar, ny, nu = len(ss.states), len(ss.params), len(ss.outputs), len(ss.inputs)
        parts = []
        jac_specs = [("dfdx", ss.dfdx, (nx, nx), "df/dx"), ("dfdtheta", ss.dfdtheta, (nx, npar), "df/dtheta"),
                     ("dhdx", ss.dhdx, (ny, nx), "dh/dx"), ("dhdtheta", ss.dhdtheta, (ny, npar), "dh/dtheta"),
                     ("dfdu", ss.dfdu, (nx, nu), "df/du"), ("dhdu", ss.dhdu, (ny, nu), "dh/du")]
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


def write_module(ss: StateSpace, path: str | Path, *, source: str | None = None,
                 command: str = "bondgraph generate", functions=ALL_FUNCTIONS) -> Path:
    """Generate (:func:`generate_source`, the same options) and write
    ``path``; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(generate_source(ss, source=source, command=command, functions=functions))
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
