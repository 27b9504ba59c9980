"""The C99 counterpart of :mod:`bondgraph.core.codegen`: the model's f, h and
Jacobians as plain C functions, from the same sympy expressions and CSE.

:func:`generate_c_source` writes one self-contained translation unit
(``generated/c/<model>.c`` for the registered models, written and compared
by ``bondgraph generate`` / ``bondgraph generate --check``) that includes
only ``<math.h>``:

* sizes ``BG_N_X``, ``BG_N_U``, ``BG_N_THETA``, ``BG_N_Y`` and the defaults
  ``BG_X0``, ``BG_U0``, ``BG_THETA0`` (in the order of the numpy module's
  ``STATES``, ``INPUTS``, ``PARAMS``);
* ``bg_f(x, u, theta, dxdt)``, ``bg_h(x, u, theta, y)`` and the Jacobians
  ``bg_dfdx``, ``bg_dfdu``, ``bg_dhdx``, ``bg_dhdu`` (dense, row-major:
  entry (i, j) of an (m, n) Jacobian at ``J[i * n + j]``), all ``static``:
  the file is meant to be included by the code that uses it (the FMU's
  fmi2 functions, :mod:`bondgraph.export.fmu`).

The functions the expressions can contain are C99's (``exp``, ``log``,
``sqrt``, ``pow``, ``sin``, ``cos``, ``atan``, ``tanh``, ``fabs``, ``fmax``,
``fmin``, Piecewise as conditional expressions) and the two smooth
functions of :mod:`bondgraph.core.smooth`, printed as ``bg_softplus``
(``fmax(z, 0) + log1p(exp(-|z|))``, numpy's ``logaddexp(0, z)``) and
``bg_sigmoid`` (``0.5 + 0.5 tanh(z/2)``). The branch-free functions of
:mod:`bondgraph.core.vmath` are a numba speed device only: C calls libm.
This module only writes text; it calls no compiler.
"""

from __future__ import annotations

import sympy as sp
from sympy.printing.c import C99CodePrinter

from bondgraph.core import domains
from bondgraph.core.codegen import RESERVED, _Gen, _Namer
from bondgraph.core.equations import StateSpace

#: C keywords and <math.h> names a model symbol must not shadow (a symbol
#: named like one gets a suffix, as the numpy module's reserved names do)
C_RESERVED = frozenset("""
auto break case char const continue default do double else enum extern float for goto if
inline int long register restrict return short signed sizeof static struct switch typedef
union unsigned void volatile while acos asin atan atan2 cos sin tan cosh sinh tanh exp log
log10 log1p expm1 pow sqrt fabs fmax fmin floor ceil fmod erf erfc tgamma lgamma j0 j1 jn
y0 y1 yn hypot cbrt round trunc isnan isinf NAN INFINITY HUGE_VAL M_PI J dxdt y main
""".split())

#: the functions of the C file, with their output array and Jacobian method
#: of :class:`~bondgraph.core.equations.StateSpace` (None: f or h itself)
C_FUNCTIONS = ("f", "h", "dfdx", "dfdu", "dhdx", "dhdu")


class _CPrinter(C99CodePrinter):
    """C99 printer with symbol renaming, inline Piecewise and the smooth
    functions of :mod:`bondgraph.core.smooth`."""

    def __init__(self, names: dict):
        super().__init__({"allow_unknown_functions": False})
        self._names = names

    def _print_Symbol(self, expr):
        return self._names.get(expr, expr.name)

    _print_Dummy = _print_Symbol

    def _print_softplus(self, expr):
        return f"bg_softplus({self._print(expr.args[0])})"

    def _print_sigmoid(self, expr):
        return f"bg_sigmoid({self._print(expr.args[0])})"

    def _print_dpow(self, expr):
        return domains.c_text(expr, self._print)

    def _print_Piecewise(self, expr):
        out = "NAN"
        for value, cond in reversed(expr.args):
            if cond == sp.true:
                out = f"({self._print(value)})"
            else:
                out = f"(({self._print(cond)}) ? ({self._print(value)}) : {out})"
        return out


class _CGen(_Gen):
    """C functions from the same expressions as the numpy module."""

    def __init__(self, ss: StateSpace, *, source: str | None, command: str):
        self.ss = ss
        self.source = source or ss.source or "<unknown>"
        self.command = command
        nm = _Namer()
        nm.used |= set(C_RESERVED) | RESERVED
        self.x_names = [nm.add(s) for s in ss.states]
        self.u_names = [nm.add(s) for s in ss.inputs]
        self.p_names = [nm.add(s) for s in ss.params]
        self.namer = nm
        self.printer = _CPrinter(nm.names)
        self.sym_index = {}
        for kind, syms in (("x", ss.states), ("u", ss.inputs), ("theta", ss.params)):
            for i, s in enumerate(syms):
                self.sym_index[s] = (kind, i)

    def pr(self, expr) -> str:
        return self.printer.doprint(expr)

    def c_function(self, name: str, out: str, doc: str, entries, size: int) -> str:
        """``static void bg_<name>(x, u, theta, out)``: ``entries`` ([(flat
        index, expr)]) with one shared CSE; a sparse output is zeroed first."""
        repl, reduced = sp.cse([e for _, e in entries], symbols=sp.numbered_symbols("_t"),
                               optimizations=None, order="none")
        syms = set()
        for e in list(reduced) + [e for _, e in repl]:
            syms |= e.free_symbols
        lines = ["(void)x; (void)u; (void)theta;"]
        lines += ["const double " + ln + ";" for ln in
                  self._unpack({s for s in syms if not str(s).startswith("_t")}, point=True)]
        lines += [f"const double {s} = {self.pr(e)};" for s, e in repl]
        if len(entries) < size:
            lines.append(f"for (int _i = 0; _i < {size}; ++_i) {out}[_i] = 0.0;")
        lines += [f"{out}[{k}] = {self.pr(e)};" for (k, _), e in zip(entries, reduced)]
        body = "\n".join("    " + ln for ln in lines)
        return (f"/* {doc} */\nBG_UNUSED static void bg_{name}(const double *x, const double *u, "
                f"const double *theta, double *{out})\n{{\n{body}\n}}\n")

    def c_module(self) -> str:
        """Source text of the C file: header, sizes, defaults, functions."""
        ss = self.ss
        nx, nu, ny = len(ss.states), len(ss.inputs), len(ss.outputs)
        parts = [self._c_header()]
        parts.append(self.c_function("f", "dxdt", f"dx/dt = f(x, u, theta) into dxdt[{nx}]",
                                     list(enumerate(ss.f)), nx))
        parts.append(self.c_function("h", "y", f"outputs y = h(x, u, theta) into y[{ny}]",
                                     list(enumerate(ss.h)), ny))
        for name, M, label in (("dfdx", ss.dfdx(), "df/dx"), ("dfdu", ss.dfdu(), "df/du"),
                               ("dhdx", ss.dhdx(), "dh/dx"), ("dhdu", ss.dhdu(), "dh/du")):
            entries = [(i * M.cols + j, M[i, j]) for i in range(M.rows) for j in range(M.cols)
                       if M[i, j] != 0]
            parts.append(self.c_function(name, "J", f"{label} ({M.rows}, {M.cols}) row-major "
                                         f"into J", entries, M.rows * M.cols))
        del nu
        return "\n".join(p.rstrip("\n") + "\n" for p in parts)

    def _c_header(self) -> str:
        ss = self.ss

        def arr(name, values):
            vals = [repr(float(v)) for v in values] or ["0.0"]
            return f"BG_UNUSED static const double {name}[{len(vals)}] = {{{', '.join(vals)}}};"

        def listing(items):
            return "\n".join(f" * {i:3d} {text}" for i, text in enumerate(items)) or " *   (none)"

        states = listing(f"{s.name} [{s.unit or '-'}]" for s in ss.states)
        inputs = listing(f"{u.name} [{u.unit or '-'}]" for u in ss.inputs)
        params = listing(f"{p.name} = {p.default:g} [{p.unit or '-'}]" for p in ss.params)
        outputs = listing(f"{o.name} [{o.unit or '-'}]" for o in ss.outputs)
        return f"""/* C99 functions of the model '{ss.name}'.
 *
 * Generated by bondgraph from {self.source} (graph '{ss.name}'), from the same
 * sympy expressions as the numpy module {ss.name}.py one directory up.
 * DO NOT EDIT: regenerate with `{self.command}`; `bondgraph generate --check`
 * fails when this file differs from what the graph produces.
 *
 * One point per call: x[BG_N_X], u[BG_N_U], theta[BG_N_THETA]; Jacobians are
 * dense and row-major. Every function is static: include this file.
 *
 * States x:
{states}
 * Inputs u:
{inputs}
 * Parameters theta:
{params}
 * Outputs y:
{outputs}
 */

#include <math.h>

#if defined(__GNUC__) || defined(__clang__)
#define BG_UNUSED __attribute__((unused))
#else
#define BG_UNUSED
#endif

#define BG_N_X {len(ss.states)}
#define BG_N_U {len(ss.inputs)}
#define BG_N_THETA {len(ss.params)}
#define BG_N_Y {len(ss.outputs)}

{arr("BG_X0", [s.initial for s in ss.states])}
{arr("BG_U0", [u.default for u in ss.inputs])}
{arr("BG_THETA0", [p.default for p in ss.params])}

/* softplus(z) = log(1 + exp(z)) without overflow (numpy's logaddexp(0, z)) */
BG_UNUSED static double bg_softplus(double z)
{{
    return fmax(z, 0.0) + log1p(exp(-fabs(z)));
}}

/* sigmoid(z) = 1/(1 + exp(-z)) = 0.5 + 0.5 tanh(z/2) */
BG_UNUSED static double bg_sigmoid(double z)
{{
    return 0.5 + 0.5 * tanh(0.5 * z);
}}
"""


def generate_c_source(ss: StateSpace, *, source: str | None = None,
                      command: str = "bondgraph generate") -> str:
    """C99 source of the model ``ss``: f, h, df/dx, df/du, dh/dx, dh/du
    (:data:`C_FUNCTIONS`) from the same sympy expressions and CSE as
    :func:`bondgraph.core.codegen.generate_source`.

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
        A C99 translation unit that includes only ``<math.h>``; its
        functions are ``static`` (include the file where they are used).
        Method: sympy's C99 code printer and common-subexpression
        elimination (Meurer et al. 2017, *SymPy: symbolic computing in
        Python*, PeerJ Comput. Sci. 3:e103).
    """
    return _CGen(ss, source=source, command=command).c_module()
