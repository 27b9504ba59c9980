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
import re
import sys
import textwrap
import types
from pathlib import Path

import sympy as sp
from sympy.printing.numpy import NumPyPrinter

from bondgraph.core.equations import StateSpace, expand_stored_energy, paused_gc
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


class Shared:
    """Common subexpressions of a list of expressions, by one of two methods.

    ``Shared(exprs)`` (the tree method) finds them in one pass, linear in the
    size of the expression trees: every distinct node is visited once, by
    hash; a node that is not an atom and occurs at two places or more (a
    node met again is not walked again, as in :func:`sympy.cse`'s tree pass)
    gets a variable ``_t<k>``, numbered children first. Nothing is rebuilt:
    the printer (:meth:`_Printer.code`) prints a shared node as its
    variable's name where it meets it, so the expressions keep their form.
    It does not look for common sub-sums or sub-products, nor extract
    minus signs (which sorts a sum's terms, quadratic in a long sum).

    :meth:`by_sympy` runs :func:`sympy.cse` (``optimizations=None``,
    ``order="none"``), which also shares common sub-products and sub-sums
    and extracts minus signs: fewer operations in the kernels of the
    filter, at a cost per expression that is linear for the state
    equations and their Jacobians but quadratic in the length of one sum.

    Parameters
    ----------
    exprs : sequence of sympy.Basic
        The expressions computed together (one function's outputs).

    Attributes
    ----------
    repl : list of (str, sympy.Basic)
        ``(name, expression)`` of every shared subexpression, children
        first (the tree method: the original node; sympy: the rebuilt
        expression in the variables before it).
    reduced : list of sympy.Basic
        ``exprs``, an expression that is itself shared replaced by the
        symbol of its variable (sympy: rebuilt in the variables).
    index : dict
        The tree method: shared node -> (position in ``repl``, name);
        empty for sympy.
    free : set of sympy.Symbol
        Free symbols of ``exprs``.

    References
    ----------
    Aho, Sethi & Ullman, *Compilers: Principles, Techniques, and Tools*
    (1986), sec. 5.2 (the DAG of an expression: one node per distinct
    subexpression, found by hashing).
    """

    def __init__(self, exprs):
        exprs = [sp.sympify(e) for e in exprs]
        seen, repeated, free = set(), set(), set()
        stack = list(reversed(exprs))
        while stack:  # count: an extractable node met twice is repeated
            e = stack.pop()
            if e.is_Atom:
                if e.is_Symbol:
                    free.add(e)
                continue
            if isinstance(e, _EXTRACTABLE):
                if e in seen:
                    repeated.add(e)
                    continue
                seen.add(e)
            stack.extend(reversed(e.args))
        self.free = free
        self.repl: list = []
        self.index: dict = {}
        done: set = set()
        for e in exprs:
            self._define(e, repeated, done)
        self.reduced = [sp.Symbol(self.index[e][1]) if e in self.index else e for e in exprs]
        self.position = {name: k for k, (name, _) in enumerate(self.repl)}
        self._refs = None

    @classmethod
    def by_sympy(cls, exprs) -> "Shared":
        """The subexpressions :func:`sympy.cse` finds, in the same form."""
        repl, reduced = sp.cse(list(exprs), symbols=sp.numbered_symbols("_t"),
                               optimizations=None, order="none")
        self = cls.__new__(cls)
        self.repl = [(s.name, e) for s, e in repl]
        self.reduced = list(reduced)
        self.index = {}
        self.position = {name: k for k, (name, _) in enumerate(self.repl)}
        free = set()
        for e in self.reduced + [e for _, e in repl]:
            free |= e.free_symbols
        self.free = {s for s in free if s.name not in self.position}
        self._refs = None
        return self

    def needed(self, exprs) -> list[int]:
        """Positions in :attr:`repl` of the variables that ``exprs`` (some
        of :attr:`reduced`) use, directly or through other variables, in
        order (each expression walked down to the variables only)."""
        if self._refs is None:
            self._refs = [self._uses(e) for _, e in self.repl]
        need: set = set()
        stack = [k for e in exprs for k in self._uses(e)]
        while stack:
            k = stack.pop()
            if k not in need:
                need.add(k)
                stack.extend(self._refs[k])
        return sorted(need)

    def _uses(self, root) -> set:
        """Positions of the variables ``root``'s own nodes use."""
        out, stack = set(), [root]
        while stack:
            e = stack.pop()
            if e.is_Atom:
                k = self.position.get(e.name) if e.is_Symbol else None
                if k is not None:
                    out.add(k)
                continue
            hit = self.index.get(e) if e is not root else None
            if hit is not None:
                out.add(hit[0])
            else:
                stack.extend(e.args)
        return out

    def depends(self, symbols: set) -> list[bool]:
        """For each variable of :attr:`repl`, whether its expression contains
        one of ``symbols`` (directly or through the variables it uses; each
        expression walked down to the variables only)."""
        flags: list[bool] = []
        for _, root in self.repl:
            dep, stack = False, list(root.args)
            while stack and not dep:
                e = stack.pop()
                hit = self.index.get(e)
                if hit is not None:
                    dep = flags[hit[0]]
                elif e.is_Atom:
                    k = self.position.get(e.name) if e.is_Symbol else None
                    dep = flags[k] if k is not None else e in symbols
                else:
                    stack.extend(e.args)
            flags.append(dep)
        return flags

    def _define(self, root, repeated: set, done: set) -> None:
        """Number the shared nodes under ``root`` in post-order (iterative:
        expression trees may be deeper than Python's recursion limit)."""
        stack = [(root, False)]
        while stack:
            e, children_done = stack.pop()
            if children_done:
                if e in repeated:
                    name = f"_t{len(self.repl)}"
                    self.index[e] = (len(self.repl), name)
                    self.repl.append((name, e))
                continue
            if e.is_Atom or e in done:
                continue
            done.add(e)
            stack.append((e, True))
            stack.extend((a, False) for a in reversed(e.args))


#: nodes :class:`Shared` may give a variable (not, e.g., the (expr, cond)
#: pairs of a Piecewise, which no printer prints alone)
_EXTRACTABLE = (sp.Expr, sp.logic.boolalg.Boolean)
#: a variable of :class:`Shared` in generated text
_SHARED_NAME = re.compile(r"\b_t\d+\b")


def live_definitions(defs: list, used: str) -> list:
    """The definitions ``[(name, text)]`` (in order) that the text ``used``
    needs, directly or through other definitions (one backward pass)."""
    need = set(_SHARED_NAME.findall(used))
    keep = []
    for name, text in reversed(defs):
        if name in need:
            keep.append((name, text))
            need.update(_SHARED_NAME.findall(text))
    return keep[::-1]


class _Printer(NumPyPrinter):
    """NumPy printer with symbol renaming, broadcasting-safe max/min,
    cheap powers and shared subexpressions (:class:`Shared`) printed as
    their variables. Sums and products print in sympy's argument order
    (``order="none"``: sorting the terms of a sum for printing grows faster
    than linearly with its size)."""

    def __init__(self, names: dict):
        super().__init__({"fully_qualified_modules": True, "allow_unknown_functions": False,
                          "order": "none"})
        self._names = names
        self.shared: dict = {}
        self._limit = 0

    def code(self, expr, shared: Shared | None = None, limit: int | None = None) -> str:
        """Text of ``expr``; a node of ``shared`` among the first ``limit``
        of ``shared.repl`` (all when None) prints as its variable."""
        self.shared = shared.index if shared is not None else {}
        self._limit = len(self.shared) if limit is None else limit
        self._not_supported = set()
        self._number_symbols = set()
        text = self._print(sp.sympify(expr))
        if self._not_supported:
            raise CodegenError("cannot print " + ", ".join(sorted(
                type(e).__name__ for e in self._not_supported)) + " as numpy code")
        return text.replace("numpy.", "np.")

    def _shared_name(self, expr):
        if self.shared and isinstance(expr, sp.Basic):
            hit = self.shared.get(expr)
            if hit is not None and hit[0] < self._limit:
                return hit[1]
        return None

    def _print(self, expr, **kwargs):
        name = self._shared_name(expr)
        return name if name is not None else super()._print(expr, **kwargs)

    def parenthesize(self, item, level, strict=False):
        name = self._shared_name(item)
        return name if name is not None else super().parenthesize(item, level, strict)

    def _as_ordered_terms(self, expr, order=None):
        """A sum's terms in sympy's order, the first one without a negative
        coefficient moved to the front (``x - y``, not ``-y + x``)."""
        terms = list(expr.args)
        for k, t in enumerate(terms):
            c = t.args[0] if t.is_Mul else t
            if not (c.is_Number and c.is_negative):
                if k:
                    terms.insert(0, terms.pop(k))
                break
        return terms

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
        self.current: Shared | None = None
        self._groups: list | None = None
        self._texts: dict = {}
        self.sym_index = {}
        for i, s in enumerate(ss.states):
            self.sym_index[s] = ("x", i)
        for i, s in enumerate(ss.inputs):
            self.sym_index[s] = ("u", i)
        for i, s in enumerate(ss.params):
            self.sym_index[s] = ("theta", i)

    # ------------------------------------------------------------------
    def pr(self, expr, limit: int | None = None) -> str:
        """Text of ``expr``, the nodes of :attr:`current` (the function's
        :class:`Shared`; the first ``limit`` of them) as their variables."""
        return self.printer.code(expr, self.current, limit)

    def shared(self, exprs, tree: bool = False) -> Shared:
        """:class:`Shared` of ``exprs`` (by :meth:`Shared.by_sympy`, or the
        tree method), made :attr:`current`; kept for the other functions
        of the same expressions."""
        key = ("shared", tuple(exprs), tree)
        self.current = self.ss.derived(key, lambda: Shared(key[1]) if tree else
                                       Shared.by_sympy(key[1]))
        return self.current

    def group(self, exprs) -> tuple:
        """The expressions whose common subexpressions are found together
        with ``exprs``: f and df/dx (f, dfdx, f_dfdx and the numba f, f_dfdx,
        f_cols share one :func:`sympy.cse`), h and dh/dx, else ``exprs``
        (df/dθ joined to f and df/dx would save a tenth of the time of a
        long chain but splits f's products for the Jacobian's sake: more
        operations in the filter's kernels)."""
        if self._groups is None:
            fj = tuple(self.ss.f) + tuple(self.ss.jacobian("dfdx").values())
            hj = tuple(self.ss.h) + tuple(self.ss.jacobian("dhdx").values())
            self._groups = [(set(fj), fj), (set(hj), hj)]
        exprs = tuple(exprs)
        for members, grp in self._groups:
            if all(e in members for e in exprs):
                return grp
        return exprs

    def reduced(self, sh: Shared, group, exprs) -> list:
        """The reduced forms (:attr:`Shared.reduced`) of ``exprs``, members
        of ``group``, the expressions of ``sh``."""
        if len(exprs) == len(group) and all(a is b for a, b in zip(exprs, group)):
            return sh.reduced
        of = dict(zip(group, sh.reduced))
        return [of[e] for e in exprs]

    def def_texts(self, sh: Shared, reduced) -> list[tuple[int, str, str]]:
        """``(position, name, text)`` of the variables of ``sh`` (the
        :attr:`current`) that the expressions ``reduced`` use, directly or
        through others, in order; each printed once per generator (the
        functions of one group share them)."""
        texts = self._texts.setdefault(sh, {})
        out = []
        for k in sh.needed(reduced):
            if k not in texts:
                texts[k] = self.pr(sh.repl[k][1], k)
            out.append((k, sh.repl[k][0], texts[k]))
        return out

    def definitions(self, sh: Shared, used: str, reduced) -> list[str]:
        """``name = expression`` lines of the variables of ``sh`` that the
        expressions ``reduced``, printed as the text ``used``, need."""
        defs = [(name, text) for _, name, text in self.def_texts(sh, reduced)]
        return [f"{name} = {text}" for name, text in live_definitions(defs, used)]

    def assign(self, target: str, e: sp.Expr) -> str:
        """``target = e``; a top-level sum or product writes straight into the
        output row through the ufunc's ``out=`` (one memory pass less than a
        temporary followed by a copy)."""
        # the rest of the terms (factors) as they are, not a new sum (product)
        # evaluated and sorted by sympy
        if e.is_Add and len(e.args) >= 2:
            first, rest = e.args[0], _unevaluated(sp.Add, e.args[1:])
            return f"np.add({self.pr(rest)}, {self.pr(first)}, out={target})"
        if e.is_Mul and len(e.args) >= 2 and not any(a.is_Number for a in e.args[1:]):
            first, rest = e.args[0], _unevaluated(sp.Mul, e.args[1:])
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
             allowed=("x", "u", "theta"), shape_of=("x", "u", "theta"),
             tree: bool = False) -> list[str]:
        """Lines computing several output arrays with one shared CSE (of
        their :meth:`group`; the tree method when ``tree``), the
        subexpressions they do not need left out.

        outputs: list of (array_name, [(index_tuple, expr)], full_shape_suffix)
        """
        exprs = [e for _, entries, _suffix in outputs for _, e in entries]
        grp = exprs if tree else self.group(exprs)
        sh = self.shared(grp, tree)
        out_lines = self._output_lines(outputs, self.reduced(sh, grp, exprs))
        lines = self._unpack(_free(self.reduced(sh, grp, exprs), sh) if grp is not exprs
                             else sh.free, allowed)
        lines += self.definitions(sh, "\n".join(out_lines), self.reduced(sh, grp, exprs))
        sizes = {"x": len(self.ss.states), "u": len(self.ss.inputs), "theta": len(self.ss.params)}
        if all(sizes[a] > 0 for a in shape_of):
            # np.broadcast(...).shape is ~2 us cheaper per call than broadcast_shapes
            shape_args = ", ".join(f"{a}[..., 0]" for a in shape_of)
            lines.append(f"_shape = np.broadcast({shape_args}).shape")
        else:
            shape_args = ", ".join(f"{a}.shape[:-1]" for a in shape_of)
            lines.append(f"_shape = np.broadcast_shapes({shape_args})")
        return lines + out_lines

    def _output_lines(self, outputs, reduced) -> list[str]:
        """Allocation and assignment lines of the output arrays."""
        # Outputs are filled "state-major" (component axes first, so each
        # assignment writes one contiguous row) and returned as a view with the
        # component axes last: shape (..., n) as documented, memory laid out so
        # that a caller feeding the result back reads contiguous columns.
        lines = []
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
                 allowed=("x", "u", "theta"), shape_of=("x", "u", "theta"),
                 tree: bool = False) -> str:
        conv = [f"{a} = np.asarray({a}, dtype=float)" for a in shape_of]
        lines = conv + self.body(outputs, allowed, shape_of, tree) + [f"return {returns}"]
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
        # laws continued past their domain (bondgraph.core.domains): only
        # when there are some, so other modules' text is unchanged
        domain = (f"DOMAIN_NOTES = {_fmt_list(ss.domain_notes)}\n"
                  if getattr(ss, "domain_notes", None) else "")
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
{domain}'''

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
        jac_specs = [("dfdx", (nx, nx), "df/dx"), ("dfdtheta", (nx, npar), "df/dtheta"),
                     ("dhdx", (ny, nx), "dh/dx"), ("dhdtheta", (ny, npar), "dh/dtheta"),
                     ("dfdu", (nx, nu), "df/du"), ("dhdu", (ny, nu), "dh/du")]
        for name, shape, label in jac_specs:
            if name in functions:
                parts.append(self.function(
                    name, "x, u, theta",
                    f"Jacobian {label}, shape (..., {shape[0]}, {shape[1]}).",
                    [("_J", list(ss.jacobian(name).items()), shape)], "_J"))
        if "f_dfdx" in functions:
            parts.append(self.function(
                "f_dfdx", "x, u, theta",
                f"f and df/dx together (shared subexpressions), for Rosenbrock steps.\n\n"
                f"Returns\n-------\n(array (..., {nx}), array (..., {nx}, {nx}))",
                [("_dxdt", self._f_entries(), (nx,)),
                 ("_J", list(ss.jacobian("dfdx").items()), (nx, nx))], "_dxdt, _J"))
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
        # the tree method: these sums grow with the graph (one term per
        # storage or resistor), and sympy's minus-sign test sorts them
        return [self.function(name, "x, u, theta", doc,
                              [("_out", [((), expand_stored_energy(ex))], ())], "_out", tree=True)
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


def _unevaluated(op, args):
    """``op(*args)`` as given (one argument: itself)."""
    return args[0] if len(args) == 1 else op(*args, evaluate=False)


def _free(reduced, sh: Shared) -> set:
    """Free symbols of the model that ``reduced`` needs, through the
    definitions of ``sh`` too (each definition walked once)."""
    need, out, seen = list(reduced), set(), set()
    while need:
        e = need.pop()
        if e.is_Atom:
            k = sh.position.get(e.name) if e.is_Symbol else None
            if k is not None and k not in seen:
                seen.add(k)
                need.append(sh.repl[k][1])
            elif k is None and e.is_Symbol:
                out.add(e)
            continue
        hit = sh.index.get(e)
        if hit is not None:
            if hit[0] in seen:
                continue
            seen.add(hit[0])
        need.extend(e.args)
    return out


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
    with paused_gc():
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
