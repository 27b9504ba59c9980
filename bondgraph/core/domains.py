"""Laws defined on half of the real line, extended so that they stay finite.

A user's law often has a restricted domain: Torricelli's orifice
``k*sqrt(level)``, a Hertzian contact ``k*x**1.5``, a power law
``a*p**0.7``. Real trajectories stay inside it, but the unscented Kalman
filter's sigma points and an integrator's trial steps do not: a sigma point
of an unknown initial level of 0 ± 5 V, or a Runge-Kutta stage of a tank that
drains in one step, asks for ``sqrt`` of a negative number, numpy returns
NaN and the filter or the solver fails with a message about divergence that
does not name the law.

:func:`extend_domains` rewrites every power ``b**e`` of a non-integer
exponent ``e > 0`` whose base depends on a state and is not non-negative by
its form (a sum of squares, an absolute value) as

- ``dpow(b, e, 0)``, ``b**e`` for b > 0 and 0 below, for an even root (``e
  = m/n``, n even, or a non-rational e): the law's value at the boundary,
  continued (an empty tank lets nothing out; a contact that has opened
  pushes no more);
- ``dpow(b, e, ±1)``, ``±(-b)**e`` below 0, for an odd root (``e = m/n``, n
  odd): the real root, which numpy's ``**`` does not give.

Values inside the domain are unchanged; the derivative is the derivative of
the continued law (``e*dpow(b, e - 1, ∓s)*b'``), finite everywhere (0 at the
boundary itself). Each rewrite returns one note that names the expression,
so the commands say what they evaluate.

References: the sigma points that leave a state's admissible set and their
projection, Kandepu, Foss & Imsland (2008), *Applying the unscented Kalman
filter for nonlinear state estimation*, J. Process Control 18, 753-768; the
continuous extension of a law at its domain's boundary, as Modelica's
``smooth``/``noEvent`` guards of square-root orifice laws (Modelica
Association, Modelica.Fluid.Utilities.regRoot).
"""

from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np
import sympy as sp


#: functions with a jump: :func:`bondgraph.core.equations.diff` takes their
#: derivative as 0, :func:`extend_domains` notes each state-dependent one
JUMPS = (sp.sign, sp.Heaviside)


#: what a domain note of a jump says after the law and where it stands (:func:`jump_laws`)
JUMP_MARK = " jumps where "


def jump_laws(notes) -> list[str]:
    """The laws with a jump that domain notes name (``["sign(p_mass/m)"]``),
    for the hints of a solver or an FMU that failed where a state sticks."""
    return [n.split(" (in ", 1)[0] for n in notes if JUMP_MARK in n]


def nonnegative_by_form(e: sp.Expr) -> bool:
    """Whether ``e`` is non-negative for every real value of its symbols by
    its form: a non-negative number, an even power or an absolute value of
    a real expression, ``sqrt`` of anything, sums and products of those, and
    anything sympy itself proves non-negative. ``1 + (v/L)**2`` is (sympy
    alone says "unknown": L might be 0)."""
    if e.is_nonnegative:
        return True
    if e.is_Number:
        return bool(e >= 0)
    if isinstance(e, sp.Abs):
        return True
    if e.is_Pow:
        b, x = e.args
        if x.is_Integer and x.is_even:
            return bool(b.is_real) or all(s.is_real for s in b.free_symbols)
        if x.is_Rational and not x.is_Integer and x.q % 2 == 0:
            return True       # sympy's principal root of a real base, or NaN
        return nonnegative_by_form(b) and bool(x.is_real)
    if e.is_Add or e.is_Mul:
        return all(nonnegative_by_form(a) for a in e.args)
    return False


class dpow(sp.Function):
    """``dpow(b, x, s)``: ``b**x`` continued past the domain of a
    non-integer power; ``b**x`` for b > 0, ``s*(-b)**x`` for b < 0 (s = 0:
    the value 0 at the boundary, continued; s = ±1: the real root of an odd
    root), 0 at b = 0. Derivative in b: ``x*dpow(b, x - 1, -s)`` (0 for b
    <= 0 when s = 0). Printed as code that never evaluates the power outside
    its domain (no NaN, no numpy warning); the shared subexpressions of the
    code generator never hoist the bare power out of it."""

    nargs = 3

    def fdiff(self, argindex=1):
        b, x, s = self.args
        if argindex != 1:
            raise sp.ArgumentIndexError(self, argindex)
        return x * dpow(b, x - 1, -s)

    @classmethod
    def eval(cls, b, x, s):
        if b.is_Number:
            if b > 0:
                return b**x
            if b < 0:
                return s * (-b)**x
            return sp.S.Zero
        if b.is_positive:
            return b**x
        return None

    def _eval_evalf(self, prec):
        b = self.args[0]._eval_evalf(prec)
        if b is None or not b.is_Number:
            return None
        v = dpow(b, *self.args[1:])       # a number: eval gives its value
        return None if isinstance(v, dpow) else v._eval_evalf(prec)

    def _eval_is_real(self):
        return self.args[0].is_real

    def _numpycode(self, printer):
        if hasattr(printer, "_print_dpow"):      # a point kernel's printer
            return printer._print_dpow(self)
        b, x, s = self.args
        where = printer._module_format("numpy.where")
        tb, tx = printer._print(b), printer._print(x)
        pos = f"{where}(({tb}) > 0, {tb}, 1.0)**({tx})"
        if s == 0:
            return f"{where}(({tb}) > 0, {pos}, 0.0)"
        neg = f"{printer._print(s)}*{where}(({tb}) < 0, -({tb}), 1.0)**({tx})"
        return (f"{where}(({tb}) > 0, {pos}, {where}(({tb}) < 0, {neg}, 0.0))")

    def _pythoncode(self, printer):
        return self._numpycode(printer)

    def _sympystr(self, printer):
        """Printed as the user's power (``sqrt(q)``, ``x**1.5``): where it is
        continued, the model's domain notes say."""
        b, x, _ = self.args
        return printer._print(sp.Pow(b, x, evaluate=False))


def _conditional_text(expr: dpow, pr, sqrt: str, power: str, choose) -> str:
    """``expr`` as nested conditional expressions of one language: ``sqrt``
    and ``power`` its function names, ``choose(cond, a, b)`` its "a if cond
    else b", ``pr`` printing the arguments."""
    b, x, s = expr.args
    tb, tx = pr(b), pr(x)
    pos = f"{sqrt}({tb})" if x == sp.Rational(1, 2) else f"{power}({tb}, {tx})"
    below = "0.0" if s == 0 else choose(f"({tb}) < 0", f"({pr(s)})*{power}(-({tb}), {tx})",
                                        "0.0")
    return choose(f"({tb}) > 0", pos, below)


def scalar_text(expr: dpow, pr) -> str:
    """One point's code of ``expr`` as a conditional expression (numba point
    and column kernels; the C kernels translate it), ``pr`` printing its
    arguments."""
    return _conditional_text(expr, pr, "np.sqrt", "np.power",
                             lambda c, a, b: f"({a} if {c} else {b})")


def c_text(expr: dpow, pr) -> str:
    """C99 text of ``expr`` (conditional expressions), ``pr`` printing its
    arguments."""
    return _conditional_text(expr, pr, "sqrt", "pow", lambda c, a, b: f"({c} ? {a} : {b})")


def _continued(b: sp.Expr, x: sp.Expr) -> sp.Expr:
    """``b**x`` continued to b <= 0 (see the module docstring)."""
    if x.is_Rational and x.q % 2 == 1:
        return dpow(b, x, -1 if x.p % 2 else 1)
    return dpow(b, x, 0)


def _candidate(e: sp.Expr, states: frozenset) -> bool:
    if not e.is_Pow:
        return False
    b, x = e.args
    if x.is_Integer or not x.is_number or not x.is_positive:
        return False
    return bool(b.free_symbols & states) and not nonnegative_by_form(b)


def extend_domains(exprs: Iterable[sp.Expr], states: Iterable[sp.Symbol],
                   where: Iterable[str] | None = None) -> tuple[list, list[str]]:
    """Rewrite the powers of :func:`nonnegative_by_form`-unknown, state-dependent
    bases in ``exprs`` (module docstring).

    Parameters
    ----------
    exprs : iterable of sympy.Expr
        E.g. the state derivatives f, then the outputs h.
    states : iterable of sympy.Symbol
        The state symbols: only a base that depends on one is rewritten
        (parameters and inputs keep their NaN, which names a wrong box or
        datum).
    where : iterable of str, optional
        What each expression is (``"dq_tank1/dt"``), for the notes; a power
        found only in expressions named ``""`` is rewritten without a note.

    Returns
    -------
    exprs : list of sympy.Expr
        The same expressions (the same objects where nothing changed).
    notes : list of str
        One per distinct rewritten power named in ``where``: ``"sqrt(q_tank1)
        (in dq_tank1/dt, dq_tank2/dt) is taken as 0, its value at the
        boundary, where q_tank1 < 0: ..."``; then one per state-dependent
        jump (``sign(v)``, :data:`JUMPS`), whose derivative is taken as 0.
    """
    exprs = [sp.sympify(e) for e in exprs]
    where = list(where) if where is not None else [f"expression {i}" for i in range(len(exprs))]
    st = frozenset(states)
    found: dict = {}
    jumps: dict = {}
    for i, e in enumerate(exprs):
        if not isinstance(e, sp.Basic):
            continue
        if e.has(sp.Pow):
            for p in e.atoms(sp.Pow):
                if _candidate(p, st):
                    found.setdefault(p, []).append(where[i])
        if where[i] and e.has(*JUMPS):
            for j in e.atoms(*JUMPS):
                if j.args[0].free_symbols & st:
                    jumps.setdefault(j, []).append(where[i])
    jump_notes = [f"{sp.sstr(j)} (in {', '.join(dict.fromkeys(w))}){JUMP_MARK}"
                  f"{sp.sstr(j.args[0])} = 0: its derivative is taken as 0 there too (the "
                  f"Jacobian away from the jump); fixed-step filters may chatter across it, a "
                  f"smooth law (bondgraph.core.smooth.smooth_sign, tanh(x/eps)) does not"
                  for j, w in jumps.items()]
    if not found:
        return exprs, jump_notes
    # innermost first, so a rewritten inner power is inside its outer one's base
    order = sorted(found, key=sp.count_ops)
    rep: dict = {}
    for p in order:
        b, x = p.args
        b2 = b.xreplace(rep)
        rep[p] = _continued(b2, x)
    out = [e.xreplace(rep) if isinstance(e, sp.Basic) else e for e in exprs]
    notes = []
    for p in order:
        b, x = p.args
        odd = x.is_Rational and x.q % 2 == 1
        uses = ", ".join(w for w in dict.fromkeys(found[p]) if w)
        if not uses:
            continue
        what = "its real root" if odd else "0, its value at the boundary"
        notes.append(f"{sp.sstr(p)} (in {uses}) is taken as {what}, where {sp.sstr(b)} < 0: "
                     f"numpy gives NaN there, where sigma points and solver steps may go")
    return out, notes + jump_notes


#: a continued law is named when the states put its base below 0 on more
#: than this share of a record's samples (:func:`continued_share`)
CONTINUED_SHARE = 0.01


def continued_share(exprs: Iterable[sp.Expr], symbols: Sequence[sp.Symbol],
                    values: Sequence) -> list[tuple[str, str, float]]:
    """Where a record's trajectory sits outside the domain of the laws
    that :func:`extend_domains` continued with 0 (even roots; an odd root's
    real root is the law itself).

    Parameters
    ----------
    exprs : iterable of sympy.Expr
        Expressions holding ``dpow`` (the state derivatives and outputs).
    symbols : sequence of sympy.Symbol
        The symbols the bases may use (states, inputs, parameters).
    values : sequence
        One array (N,) or scalar per symbol: a trajectory (filtered states,
        measured inputs) and the parameters.

    Returns
    -------
    list of (law, base, share)
        Each continued power whose base is below 0 at more than
        :data:`CONTINUED_SHARE` of the samples where it is finite, as
        printed (``"sqrt(p1 - p2)"``, ``"p1 - p2"``) with that share.
    """
    atoms: dict = {}
    for e in exprs:
        if isinstance(e, sp.Basic) and e.has(dpow):
            for a in e.atoms(dpow):
                if a.args[2] == 0:
                    atoms.setdefault(a.args[0], a)
    out = []
    for b, a in atoms.items():
        fn = sp.lambdify(list(symbols), b, "numpy")
        with np.errstate(all="ignore"):
            v = np.asarray(fn(*values), float).reshape(-1)
        ok = np.isfinite(v)
        if not ok.any():
            continue
        share = float(np.mean(v[ok] < 0))
        if share > CONTINUED_SHARE:
            out.append((sp.sstr(a), sp.sstr(b), share))
    return out


def laws_at_their_boundary(exprs: Iterable[sp.Expr], symbols: Sequence[sp.Symbol],
                           values: Sequence[float], tol: float) -> list[tuple[str, str]]:
    """The continued powers of exponent below 1 whose base is at 0 at a
    point: there the law's slope is infinite (a square-root orifice at an
    empty tank, a Hertzian contact just touching, ``x**0.5``), and the
    continued law's derivative (:class:`dpow`, 0 at the boundary) is not
    the limit of the law's from inside its domain, so a Jacobian taken there
    describes no small motion about the point (a linearisation's poles at 0).

    Parameters
    ----------
    exprs : iterable of sympy.Expr
        Expressions holding ``dpow`` (the state derivatives and outputs).
    symbols : sequence of sympy.Symbol
        The symbols the bases may use.
    values : sequence of float
        One value per symbol: the point.
    tol : float
        |base| <= tol counts as at the boundary (>= 0; the caller's scale).

    Returns
    -------
    list of (law, base)
        As printed (``"sqrt(q_tank)"``, ``"q_tank"``), each law once.
    """
    atoms: dict = {}
    for e in exprs:
        if isinstance(e, sp.Basic) and e.has(dpow):
            for a in e.atoms(dpow):
                x = a.args[1]
                if x.is_number and float(x) < 1.0:
                    atoms.setdefault(a.args[0], a)
    out = []
    for b, a in atoms.items():
        with np.errstate(all="ignore"):
            v = float(sp.lambdify(list(symbols), b, "numpy")(*values))
        if np.isfinite(v) and abs(v) <= tol:
            out.append((sp.sstr(a), sp.sstr(b)))
    return out
