"""State equations from a causal bond graph, with sympy.

Every bond carries two unknowns, e and f. Causality gives each unknown one
defining equation (the element at the non-stroke end computes the effort, the
element at the stroke end the flow). The unknowns, plus the state derivatives
ẋ, form a directed dependency graph; its strongly connected components, in
topological order, are solved one by one (block lower triangular ordering, as
in Modelica compilers):

* a single explicit equation is substituted;
* a zero-order causal loop (algebraic loop, e.g. two R elements in a loop)
  is an SCC without storages: it is torn, and the tear equations are solved
  with sympy (linear solve, else ``sympy.solve``); if sympy fails the error
  lists the loop's elements and bonds;
* a storage element in derivative causality contributes ``e = d/dt p(f)``
  (I) or ``f = d/dt q(e)`` (C). Its time derivative is expanded by the chain
  rule as Σ ∂W/∂x_i ẋ_i + Σ ∂W/∂u_j u̇_j, which closes an SCC with the ẋ of
  the integral storages; that SCC is linear in the derivatives and solved
  exactly. A modulus that is an input u (e.g. a CVT ratio r(t)) makes the
  derivative input ``der(u)`` appear: the model gains that input.

References
----------
Karnopp, Margolis & Rosenberg, *System Dynamics*, 5th ed. (2012), ch. 5 and 7
(derivative causality, algebraic loops). Cellier & Kofman, *Continuous System
Simulation* (2006), ch. 7 (BLT sorting and tearing).
"""

from __future__ import annotations

import contextlib
import gc
from dataclasses import dataclass, field
from typing import Any

import networkx as nx
import numpy as np
import sympy as sp

from bondgraph.core import units as _units
from bondgraph.core.causality import Causality, assign_causality
from bondgraph.core.domains import JUMPS, extend_domains
from bondgraph.core.elements import (
    GY,
    C,
    CField,
    Field,
    I,
    IField,
    Junction,
    OnePort,
    R,
    RField,
    Se,
    Source,
    TwoPort,
    Zero,
)
from bondgraph.core.graph import BondGraph
from bondgraph.core.symbols import Input, Parameter, StateVar
from bondgraph.errors import (
    AlgebraicLoopError,
    CausalityError,
    DerivativeCausalityError,
    join_names,
)


def diff(expr: sp.Expr, sym: sp.Symbol) -> sp.Expr:
    """∂expr/∂sym by the sum, product, power and chain rules; 0 for a
    function with a jump (:data:`bondgraph.core.domains.JUMPS`), its
    derivative away from the jump.

    Equal to ``sympy.diff`` (tested), about 10x faster on the sums of
    products that bond graphs produce, because it skips the generic
    ``Derivative`` machinery; anything unusual falls back to ``sympy.diff``.
    """
    return _diff(expr, sym, {})


def _free(e, memo: dict):
    """Free symbols of ``e``, each node's set computed once (``memo``) from
    its children's: ``free_symbols`` walks the whole subtree at every call,
    which a derivative asks at every level."""
    out = memo.get(e)
    if out is None:
        if e.is_Symbol:
            out = frozenset((e,))
        elif e.is_Atom:
            out = frozenset()
        elif e.is_Add or e.is_Mul or e.is_Pow or isinstance(e, sp.Function):
            out = frozenset().union(*[_free(a, memo) for a in e.args])
        else:  # bound variables (Derivative, Integral, ...): sympy's rule
            out = frozenset(e.free_symbols)
        memo[e] = out
    return out


def _diff(expr: sp.Expr, sym: sp.Symbol, memo: dict) -> sp.Expr:
    """:func:`diff` with the free symbols kept in ``memo`` (shared by the
    derivatives of one expression)."""
    if sym not in _free(expr, memo):
        return sp.S.Zero
    if expr == sym:
        return sp.S.One
    if isinstance(expr, JUMPS):
        # a jump (Coulomb's sign(v), a switch's Heaviside): 0 away from it;
        # sympy's DiracDelta, or its unevaluated Derivative when it cannot
        # tell the argument real, has no code (bondgraph.core.domains notes it)
        return sp.S.Zero
    if expr.is_Add:
        return sp.Add(*[_diff(a, sym, memo) for a in expr.args])
    if expr.is_Mul:
        args = expr.args
        terms = []
        for i, a in enumerate(args):
            if sym in _free(a, memo):
                d = _diff(a, sym, memo)
                if d != 0:
                    terms.append(sp.Mul(*(args[:i] + (d,) + args[i + 1:])))
        return sp.Add(*terms)
    if expr.is_Pow:
        b, e = expr.args
        if sym not in _free(e, memo):
            return e * b ** (e - 1) * _diff(b, sym, memo)
    elif isinstance(expr, sp.Function) and len(expr.args) == 1 and hasattr(expr, "fdiff"):
        inner = _diff(expr.args[0], sym, memo)
        try:
            outer = expr.fdiff(1)
        except Exception:  # pragma: no cover - unusual function
            return sp.diff(expr, sym)
        if not isinstance(outer, sp.Derivative) and not outer.has(sp.Subs):
            return outer * inner
    return sp.diff(expr, sym)


@dataclass
class Output:
    """A model output (sensor) after derivation."""

    name: str
    expr: sp.Expr
    unit: str = ""
    description: str = ""
    noise_std: Any = None


@dataclass
class StateSpace:
    """Explicit state-space model dx/dt = f(x, u, θ), y = h(x, u, θ).

    Attributes
    ----------
    name, description, source : str
        Model name, description, and the graph's builder (``module:function``).
    states : list of StateVar
        In declaration order: storages in integral causality, then signal
        and integrator states.
    inputs : list of Input
        Declared inputs, then any ``der(u)`` inputs needed by derivative
        causality.
    params : list of Parameter
        All declared parameters (θ), in declaration order.
    f : list of sympy.Expr
        dx/dt, one per state.
    outputs : list of Output
        y = h(x, u, θ) with measurement-noise standard deviations.
    energy : sympy.Expr
        Stored energy H(x, u, θ) (co-energy for nonlinear inertias).
    power_sources, power_dissipated : sympy.Expr
        Σ e f over sources (power delivered) and over R elements (absorbed).
    energy_rate : sympy.Expr
        dH/dt by the chain rule, Σ ∂H/∂x f + Σ ∂H/∂u der(u); equals
        power_sources - power_dissipated for a correct derivation.
    process_noise : list
        Continuous-time process-noise intensity per state (0 if none).
    causality : Causality
    derivative_elements : list of str
        Storages eliminated by derivative causality.
    algebraic_loops : list of list of str
        Variables of each algebraic loop solved symbolically.
    domain_notes : list of str
        One line per power of a restricted domain that f or h evaluates
        continued past it (:func:`bondgraph.core.domains.extend_domains`:
        ``sqrt(q)`` taken as 0 where q < 0).
    """

    name: str
    description: str
    source: str | None
    states: list[StateVar]
    inputs: list[Input]
    params: list[Parameter]
    f: list[sp.Expr]
    outputs: list[Output]
    energy: sp.Expr
    power_sources: sp.Expr
    power_dissipated: sp.Expr
    energy_rate: sp.Expr
    process_noise: list[Any]
    causality: Causality
    derivative_elements: list[str] = field(default_factory=list)
    algebraic_loops: list[list[str]] = field(default_factory=list)
    solved: dict = field(default_factory=dict, repr=False)
    domain_notes: list[str] = field(default_factory=list)

    # ------------------------------------------------------------ access
    @property
    def h(self) -> list[sp.Expr]:
        return [o.expr for o in self.outputs]

    @property
    def n_states(self) -> int:
        return len(self.states)

    def state(self, name: str) -> StateVar:
        for s in self.states:
            if s.name == name:
                return s
        raise KeyError(f"model '{self.name}' has no state '{name}' "
                       f"(states: {', '.join(s.name for s in self.states)})")

    def rhs(self, name: str) -> sp.Expr:
        """dx/dt of the state called ``name``."""
        return self.f[[s.name for s in self.states].index(self.state(name).name)]

    def variable(self, var) -> sp.Expr:
        """Solved expression of any bond, element or junction variable."""
        return var.xreplace(self._alias).xreplace(self.solved) if hasattr(self, "_alias") else \
            var.xreplace(self.solved)

    # --------------------------------------------------------- jacobians
    #: the Jacobians :meth:`jacobian` knows: (function, variables)
    JACOBIANS = {"dfdx": ("f", "states"), "dfdtheta": ("f", "params"),
                 "dhdx": ("h", "states"), "dhdtheta": ("h", "params"),
                 "dfdu": ("f", "inputs"), "dhdu": ("h", "inputs")}

    def jacobian(self, name: str) -> dict[tuple[int, int], sp.Expr]:
        """The non-zero entries of a Jacobian, row by row: a sparse Jacobian
        (a chain's ∂f/∂x is banded: its entries grow linearly with the
        states, its dense matrix quadratically). Computed once per state
        space (by :func:`diff`, only with respect to the symbols each
        expression contains) and kept; the caller gets a copy.

        Parameters
        ----------
        name : str
            One of ``"dfdx"`` (n_x, n_x), ``"dfdtheta"`` (n_x, n_θ),
            ``"dhdx"`` (n_y, n_x), ``"dhdtheta"`` (n_y, n_θ), ``"dfdu"``
            (n_x, n_u), ``"dhdu"`` (n_y, n_u).

        Returns
        -------
        dict
            ``{(i, j): ∂g_i/∂v_j}``, non-zero entries only, in row-major order.

        Raises
        ------
        KeyError
            An unknown name.
        """
        of, wrt = self.JACOBIANS[name]
        return dict(self.derived(("jacobian", name), lambda: self._jac_entries(
            self.f if of == "f" else self.h, getattr(self, wrt))))

    def derived(self, key, build):
        """A value derived from this state space (a Jacobian, the common
        subexpressions of code generation), computed once by ``build()``
        and kept under the hashable ``key`` (not pickled). The caller must
        not change it."""
        cache = self.__dict__.setdefault("_derived", {})
        if key not in cache:
            cache[key] = build()
        return cache[key]

    def __getstate__(self):
        """Pickled without the values kept by :meth:`derived`."""
        state = dict(self.__dict__)
        state.pop("_derived", None)
        return state

    @staticmethod
    def _jac_entries(exprs, wrt) -> dict:
        index = {s: j for j, s in enumerate(wrt)}
        out = {}
        for i, e in enumerate(exprs):
            memo: dict = {}
            for j in sorted(index[s] for s in _free(e, memo) if s in index):
                d = _diff(e, wrt[j], memo)
                if d != 0:
                    out[(i, j)] = d
        return out

    def _matrix(self, name: str, rows: int, cols: int) -> sp.Matrix:
        M = sp.zeros(rows, cols)
        for (i, j), d in self.jacobian(name).items():
            M[i, j] = d
        return M

    def dfdx(self) -> sp.Matrix:
        """∂f/∂x, shape (n_x, n_x) (dense; :meth:`jacobian` gives the non-zero entries)."""
        return self._matrix("dfdx", len(self.f), len(self.states))

    def dfdtheta(self) -> sp.Matrix:
        """∂f/∂θ, shape (n_x, n_θ)."""
        return self._matrix("dfdtheta", len(self.f), len(self.params))

    def dhdx(self) -> sp.Matrix:
        """∂h/∂x, shape (n_y, n_x)."""
        return self._matrix("dhdx", len(self.outputs), len(self.states))

    def dhdtheta(self) -> sp.Matrix:
        """∂h/∂θ, shape (n_y, n_θ)."""
        return self._matrix("dhdtheta", len(self.outputs), len(self.params))

    def dfdu(self) -> sp.Matrix:
        """∂f/∂u, shape (n_x, n_u) (the B of a linearisation)."""
        return self._matrix("dfdu", len(self.f), len(self.inputs))

    def dhdu(self) -> sp.Matrix:
        """∂h/∂u, shape (n_y, n_u) (the D of a linearisation)."""
        return self._matrix("dhdu", len(self.outputs), len(self.inputs))

    def describe(self) -> str:
        """Readable listing of the equations."""
        lines = [f"model {self.name}: {len(self.states)} states, {len(self.inputs)} inputs, "
                 f"{len(self.params)} parameters, {len(self.outputs)} outputs"]
        for s, fi in zip(self.states, self.f):
            lines.append(f"  d{s.name}/dt = {fi}")
        for o in self.outputs:
            lines.append(f"  {o.name} = {o.expr}")
        lines += [f"  note: {n}" for n in self.domain_notes]
        lines += [f"  note: {n}" for n in self.causality.derivative_notes()]
        return "\n".join(lines)


@dataclass
class _Eq:
    var: sp.Symbol
    rhs: sp.Expr | None = None        # explicit: var = rhs
    residual: sp.Expr | None = None   # implicit: 0 = residual, solved for var
    origin: str = ""
    bond: str | None = None

    def expr(self) -> sp.Expr:
        return self.rhs if self.rhs is not None else self.residual


def _name(v) -> str:
    """``str(v)`` of an unknown of the dependency graph: a symbol's name
    without the printer (the sort keys of :meth:`_Deriver.solve`)."""
    return v.name if isinstance(v, sp.Symbol) else str(v)


def _xdot(state: StateVar) -> sp.Symbol:
    return sp.Symbol(f"d({state.name})/dt", real=True)


class _Deriver:
    def __init__(self, g: BondGraph, causality: Causality):
        self.g = g
        self.cz = causality
        self.eqs: dict[sp.Symbol, _Eq] = {}
        self.dt_targets: dict[sp.Symbol, tuple[sp.Expr, str]] = {}
        self.der_inputs: dict[Input, Input] = {}
        self.loops: list[list[str]] = []
        self.alias: dict = {}

    # ------------------------------------------------------------ set-up
    def _add(self, eq: _Eq) -> None:
        if eq.var in self.eqs:
            raise CausalityError(f"internal: variable {eq.var} defined twice "
                                 f"({self.eqs[eq.var].origin} and {eq.origin})")
        self.eqs[eq.var] = eq

    def build(self) -> None:
        """One defining equation per bond variable and state derivative, from
        every element in name order (then the signal states)."""
        self._build_aliases()
        self._build_states()
        for name in sorted(self.g.elements):
            el = self.g.elements[name]
            if isinstance(el, Junction):
                self._junction(el)
            elif isinstance(el, Source):
                b = el.port.bond
                var = b.e if isinstance(el, Se) else b.f
                self._add(_Eq(var, rhs=self._bond_vars(el.value), origin=el.name, bond=b.name))
            elif isinstance(el, (I, C)):
                self._storage(el)
            elif isinstance(el, (CField, IField)):
                self._storage_field(el)
            elif isinstance(el, R):
                self._resistor(el)
            elif isinstance(el, RField):
                self._resistor_field(el)
            elif isinstance(el, TwoPort):
                self._twoport(el, self._bond_vars(el.modulus))
            else:  # pragma: no cover
                raise CausalityError(f"unknown element type {type(el).__name__}")
        for ss in self.g.signal_states.values():
            self._add(_Eq(self.xdot[ss.state], rhs=self._bond_vars(ss.rhs), origin=ss.state.name))

    def _build_aliases(self) -> None:
        """Element port variables (and junction variables) -> bond variables."""
        alias: dict = {}
        for el in self.g.elements.values():
            if isinstance(el, OnePort):
                b = el.port.bond
                alias[el.e] = b.e
                alias[el.f] = b.f
            elif isinstance(el, (TwoPort, Field)):
                for p in el.ports:
                    alias[p.e] = p.bond.e
                    alias[p.f] = p.bond.f
            elif isinstance(el, Junction):
                bonds = self.g.bonds_of(el)
                alias[el.var] = bonds[0].e if isinstance(el, Zero) else bonds[0].f
        self.alias = alias

    def _bond_vars(self, ex) -> sp.Expr:
        """``ex`` in bond variables (port variables replaced by :attr:`alias`)."""
        return sp.sympify(ex).xreplace(self.alias)

    def _build_states(self) -> None:
        """States: storages in integral causality, then the signal states."""
        self.states: list[StateVar] = []
        for el in self.g.elements.values():
            if isinstance(el, (I, C, CField, IField)) and el.name not in self.cz.derivative:
                self.states += el.states()
        for ss in self.g.signal_states.values():
            self.states.append(ss.state)
        self.xdot = {s: _xdot(s) for s in self.states}

    def _storage(self, el) -> None:
        """I or C. Integral causality: the law gives the flow (I) or effort
        (C), the conjugate variable is the state derivative. Derivative
        causality: the conjugate is ``Dt[name]``, the time derivative of the
        inverted law (expanded by the chain rule in :meth:`solve`)."""
        b = el.port.bond
        law_var, rate_var = (b.f, b.e) if isinstance(el, I) else (b.e, b.f)
        if el.name not in self.cz.derivative:
            self._add(_Eq(law_var, rhs=self._bond_vars(el.law), origin=el.name, bond=b.name))
            self._add(_Eq(self.xdot[el.state], rhs=rate_var, origin=el.name, bond=b.name))
        else:
            W = self._invert_law(el, self._bond_vars(el.law), el.state, law_var)
            dt = sp.Symbol(f"Dt[{el.name}]", real=True)
            self.dt_targets[dt] = (W, el.name)
            self._add(_Eq(rate_var, rhs=dt, origin=el.name, bond=b.name))

    def _storage_field(self, el) -> None:
        """C- or I-field: one law and one state per port, integral causality only."""
        if el.name in self.cz.derivative:
            raise DerivativeCausalityError(
                f"multiport field '{el.name}' is in derivative causality on some port; "
                f"fields must be in integral causality",
                elements=[el.name], bonds=[p.bond.name for p in el.ports],
                hint="add a compliance or inertia between the field and the rigid "
                     "constraint, or merge the storages")
        for st, law, p in zip(el.states(), el.laws, el.ports):
            b = p.bond
            if isinstance(el, CField):
                self._add(_Eq(b.e, rhs=self._bond_vars(law), origin=el.name, bond=b.name))
                self._add(_Eq(self.xdot[st], rhs=b.f, origin=el.name, bond=b.name))
            else:
                self._add(_Eq(b.f, rhs=self._bond_vars(law), origin=el.name, bond=b.name))
                self._add(_Eq(self.xdot[st], rhs=b.e, origin=el.name, bond=b.name))

    def _resistor(self, el: R) -> None:
        """R: explicit when causality matches the law's form, else a residual
        solved for the other variable."""
        b = el.port.bond
        law = self._bond_vars(el.law)
        recv = self.cz.receives_effort(b, el)
        if el.form == "effort":
            if not recv:
                self._add(_Eq(b.e, rhs=law, origin=el.name, bond=b.name))
            else:
                self._add(_Eq(b.f, residual=b.e - law, origin=el.name, bond=b.name))
        else:
            if recv:
                self._add(_Eq(b.f, rhs=law, origin=el.name, bond=b.name))
            else:
                self._add(_Eq(b.e, residual=b.f - law, origin=el.name, bond=b.name))

    def _resistor_field(self, el: RField) -> None:
        """R-field: effort laws per port, explicit or residual like :meth:`_resistor`."""
        for law, p in zip(el.laws, el.ports):
            b = p.bond
            if not self.cz.receives_effort(b, el):
                self._add(_Eq(b.e, rhs=self._bond_vars(law), origin=el.name, bond=b.name))
            else:
                self._add(_Eq(b.f, residual=b.e - self._bond_vars(law), origin=el.name, bond=b.name))

    def _invert_law(self, el, law, state, port_var) -> sp.Expr:
        """Solve ``port_var = law(state)`` for the state (derivative causality)."""
        if isinstance(el, I) and el.inertance is not None:
            return el.inertance * port_var
        if isinstance(el, C) and el.compliance is not None:
            return el.compliance * port_var
        if isinstance(el, C) and el.stiffness is not None:
            return port_var / el.stiffness
        sols = _solve_for(law - port_var, state)
        if sols is None or len(sols) != 1:
            raise DerivativeCausalityError(
                f"{el.kind} '{el.name}' is in derivative causality and its law cannot be inverted "
                f"uniquely by sympy ({'no' if not sols else len(sols)} solutions)",
                elements=[el.name], bonds=[el.port.bond.name],
                hint="give a linear law, or add a compliance/inertia so the element keeps "
                     "integral causality")
        return sols[0]

    def _junction(self, j: Junction) -> None:
        bonds = self.g.bonds_of(j)
        cz = self.cz

        def is_strong(b):
            at_j = cz.stroke[b.name] == j.name
            return at_j if isinstance(j, Zero) else (not at_j)

        strong = [b for b in bonds if is_strong(b)]
        s = strong[0]
        sign = {b.name: b.sign_at(j) for b in bonds}
        if isinstance(j, Zero):
            for b in bonds:
                if b is not s:
                    self._add(_Eq(b.e, rhs=s.e, origin=j.name, bond=b.name))
            # -Σ sign_b f_b / sign_s as one sum (signs are ±1)
            total = sp.Add(*[-sign[b.name] * sign[s.name] * b.f for b in bonds if b is not s])
            self._add(_Eq(s.f, rhs=total, origin=j.name, bond=s.name))
        else:
            for b in bonds:
                if b is not s:
                    self._add(_Eq(b.f, rhs=s.f, origin=j.name, bond=b.name))
            total = sp.Add(*[-sign[b.name] * sign[s.name] * b.e for b in bonds if b is not s])
            self._add(_Eq(s.e, rhs=total, origin=j.name, bond=s.name))

    def _twoport(self, tp: TwoPort, m) -> None:
        b1, b2 = tp.p1.bond, tp.p2.bond
        recv1 = self.cz.receives_effort(b1, tp)
        recv2 = self.cz.receives_effort(b2, tp)
        if isinstance(tp, GY):
            if not recv1 and not recv2:
                self._add(_Eq(b1.e, rhs=m * b2.f, origin=tp.name, bond=b1.name))
                self._add(_Eq(b2.e, rhs=m * b1.f, origin=tp.name, bond=b2.name))
            else:
                self._add(_Eq(b2.f, rhs=b1.e / m, origin=tp.name, bond=b2.name))
                self._add(_Eq(b1.f, rhs=b2.e / m, origin=tp.name, bond=b1.name))
        else:
            if recv2:
                self._add(_Eq(b1.e, rhs=m * b2.e, origin=tp.name, bond=b1.name))
                self._add(_Eq(b2.f, rhs=m * b1.f, origin=tp.name, bond=b2.name))
            else:
                self._add(_Eq(b2.e, rhs=b1.e / m, origin=tp.name, bond=b2.name))
                self._add(_Eq(b1.f, rhs=b2.f / m, origin=tp.name, bond=b1.name))

    # ------------------------------------------------------------ solve
    def dependency_graph(self) -> nx.DiGraph:
        G = nx.DiGraph()
        unknowns = set(self.eqs) | set(self.dt_targets)
        for v in unknowns:
            G.add_node(v)
        for v, eq in self.eqs.items():
            for s in eq.expr().free_symbols:
                if s in unknowns and s != v:
                    G.add_edge(s, v)
                elif s == v and eq.rhs is not None:
                    G.add_edge(s, v)
        # Dt nodes: depend on the unknowns of W and on ẋ of the states W reaches
        state_set = set(self.states)
        for dt, (W, _) in self.dt_targets.items():
            direct = {s for s in W.free_symbols if s in unknowns}
            reach = set(direct)
            for s in direct:
                reach |= nx.ancestors(G, s)
            known_states = {s for s in W.free_symbols if s in state_set}
            for v in reach:
                if v in self.eqs:
                    known_states |= {s for s in self.eqs[v].expr().free_symbols if s in state_set}
            for s in direct:
                G.add_edge(s, dt)
            for st in known_states:
                G.add_edge(self.xdot[st], dt)
        return G

    def _der_input(self, u: Input) -> Input:
        if u not in self.der_inputs:
            unit = f"({u.unit})/s" if u.unit else ""
            self.der_inputs[u] = Input(f"der({u.name})", unit, 0.0,
                                       f"time derivative of {u.name} (derivative causality)",
                                       derivative_of=u)
        return self.der_inputs[u]

    def _dt_expr(self, dt: sp.Symbol, solved: dict) -> sp.Expr:
        W, el = self.dt_targets[dt]
        Ws = W.xreplace(solved)
        bad = [s for s in Ws.free_symbols if s in self.eqs or s in self.dt_targets]
        bad += [s for s in Ws.free_symbols if str(s).startswith("d(")]
        if bad:
            raise DerivativeCausalityError(
                f"storage '{el}' in derivative causality depends on another eliminated variable "
                f"({', '.join(map(str, bad))}): higher-index system", elements=[el],
                hint="add a compliance or an inertia to keep integral causality")
        out = sp.Integer(0)
        for s in sorted(Ws.free_symbols, key=lambda s: s.name):
            if isinstance(s, StateVar) and s in self.xdot:
                out += diff(Ws, s) * self.xdot[s]
            elif isinstance(s, Input) and s.derivative_of is None:
                out += diff(Ws, s) * self._der_input(s)
        # the rates of the states W reaches are solved before this node (its
        # edges in :meth:`dependency_graph`): a state declared by its rate
        # (``BondGraph.state``, a lagged source value) is not left as d(z)/dt
        return out.xreplace(solved)

    def solve(self) -> dict:
        G = self.dependency_graph()
        C = nx.condensation(G)
        members = C.graph["mapping"]
        comps: dict[int, list] = {}
        for v, c in members.items():
            comps.setdefault(c, []).append(v)
        # deterministic topological order
        order = list(nx.lexicographical_topological_sort(
            C, key=lambda c: min(_name(v) for v in comps[c])))
        solved: dict = {}
        for c in order:
            vs = sorted(comps[c], key=_name)
            if len(vs) == 1 and not G.has_edge(vs[0], vs[0]):
                v = vs[0]
                if v in self.dt_targets:
                    solved[v] = self._dt_expr(v, solved)
                    continue
                eq = self.eqs[v]
                if eq.rhs is not None:
                    solved[v] = eq.rhs.xreplace(solved)
                else:
                    res = eq.residual.xreplace(solved)
                    sols = _solve_for(res, v)
                    if sols is None or len(sols) != 1:
                        raise AlgebraicLoopError(
                            f"the law of '{eq.origin}' must be inverted for {v} on bond "
                            f"'{eq.bond}' and sympy found {'no' if not sols else len(sols)} "
                            f"unique solution", elements=[eq.origin],
                            bonds=[eq.bond] if eq.bond else [],
                            hint="write the law in the causality the graph imposes (effort= or "
                                 "flow=), or add a storage element to change the causality")
                    solved[v] = sols[0]
            else:
                self._solve_block(vs, G, solved)
        return solved

    def _loop_names(self, vs) -> tuple[list[str], list[str]]:
        els: list[str] = []
        bds: list[str] = []
        for v in vs:
            if v in self.eqs:
                eq = self.eqs[v]
                if eq.origin and eq.origin not in els:
                    els.append(eq.origin)
                if eq.bond and eq.bond not in bds:
                    bds.append(eq.bond)
            elif v in self.dt_targets:
                el = self.dt_targets[v][1]
                if el not in els:
                    els.append(el)
        return els, bds

    def _solve_block(self, vs, G, solved) -> None:
        H = G.subgraph(vs).copy()
        implicit = [v for v in vs if v in self.eqs and self.eqs[v].rhs is None]
        tears: list = list(implicit)
        H.remove_nodes_from(tears)
        xdot_names = {_name(v) for v in self.xdot.values()}
        while not nx.is_directed_acyclic_graph(H):
            # tear the node on most cycles (approx.: largest in*out degree)
            cyc_nodes = set().union(*[c for c in nx.strongly_connected_components(H) if len(c) > 1])
            best = max(sorted(cyc_nodes, key=_name),
                       key=lambda n: (H.in_degree(n) * H.out_degree(n), _name(n) in xdot_names))
            tears.append(best)
            H.remove_node(best)
        partial = dict(solved)
        for v in nx.lexicographical_topological_sort(H, key=_name):
            if v in self.dt_targets:
                partial[v] = self._dt_expr(v, partial)
            else:
                partial[v] = self.eqs[v].rhs.xreplace(partial)
        residuals = []
        for t in tears:
            if t in self.dt_targets:
                residuals.append(t - self._dt_expr(t, partial))
            else:
                eq = self.eqs[t]
                if eq.rhs is not None:
                    residuals.append(t - eq.rhs.xreplace(partial))
                else:
                    residuals.append(eq.residual.xreplace(partial))
        has_dt = any(v in self.dt_targets for v in vs)
        els, bds = self._loop_names(vs)
        sol = _solve_system(residuals, tears)
        if sol is None:
            what = "derivative-causality coupling" if has_dt else "algebraic loop"
            raise AlgebraicLoopError(
                f"{what} through {join_names(els)} (bonds {', '.join(repr(b) for b in bds)}) "
                f"could not be solved by sympy for {', '.join(map(str, tears))}",
                elements=els, bonds=bds,
                hint="make one of the laws linear in its port variable, add a storage "
                     "element (small C or I) to break the loop, or use the model's state "
                     "instead of the looped variable")
        for t, val in zip(tears, sol):
            solved[t] = val
        tsub = dict(zip(tears, sol))
        for v in vs:
            if v not in tsub:
                solved[v] = partial[v].xreplace(tsub)
        if not has_dt:
            self.loops.append([str(v) for v in vs])


def _solve_for(residual: sp.Expr, var: sp.Symbol):
    """Solutions of residual(var) = 0: closed form when linear, else sympy.solve."""
    d = diff(residual, var)
    if var not in d.free_symbols:
        if d == 0:
            return None
        return [-(residual.xreplace({var: 0})) / d]
    # sympy.solve on transcendental loops (tanh, atan, sin ... of the unknown)
    # can run for minutes and practically never succeeds: only small equations
    # in which the unknown appears polynomially or inside exp/log are tried
    if sp.count_ops(residual) > 120 or not _solvable_shape(residual, [var]):
        return None
    try:
        sols = sp.solve(residual, var, dict=False)
    except (NotImplementedError, ValueError, TypeError):
        return None
    sols = [s for s in sols if not s.has(sp.I)] or sols
    return sols or None


def _solvable_shape(expr: sp.Expr, unknowns) -> bool:
    """True if the unknowns appear in ``expr`` only through +, *, powers
    with a numeric exponent, exp and log (where sympy finds closed forms,
    e.g. LambertW). A power of an unknown to a symbolic exponent (a power
    law whose exponent is a parameter, ``(e² + ε²)^((n − 1)/2)``) has none,
    and sympy's solve ran for over 40 minutes on one beside a quintic
    (a discovered law in series with the library's ``r_power``)."""
    unknowns = set(unknowns)
    for f in expr.atoms(sp.Function):
        if f.free_symbols & unknowns and not isinstance(f, (sp.exp, sp.log)):
            return False
    for p in expr.atoms(sp.Pow):
        if p.base.free_symbols & unknowns and not p.exp.is_number:
            return False
    return True


def _solve_system(residuals: list, unknowns: list):
    """Solve residuals = 0 for unknowns; None if sympy cannot (or not uniquely)."""
    if len(unknowns) == 1:
        sols = _solve_for(residuals[0], unknowns[0])
        return None if sols is None or len(sols) != 1 else sols
    try:
        A, b = sp.linear_eq_to_matrix(residuals, unknowns)
        if A.det() == 0:
            return None
        x = A.LUsolve(b)
        return [x[i] for i in range(len(unknowns))]
    except (sp.polys.polyerrors.PolynomialError, ValueError, NotImplementedError,
            sp.matrices.exceptions.NonInvertibleMatrixError):
        pass
    except Exception as exc:  # nonlinear
        if type(exc).__name__ != "NonlinearError":
            raise
    if sum(sp.count_ops(r) for r in residuals) > 150 or not all(
            _solvable_shape(r, unknowns) for r in residuals):
        return None
    try:
        sols = sp.solve(residuals, unknowns, dict=True)
    except (NotImplementedError, ValueError, TypeError):
        return None
    if len(sols) != 1 or any(u not in sols[0] for u in unknowns):
        return None
    return [sols[0][u] for u in unknowns]


def _assign_state_units(graph: BondGraph, states) -> None:
    """Units of storage states from their bond units: momentum = effort x s,
    displacement = flow x s (kept if the user gave one)."""
    try:
        bu = graph.bond_units()
    except Exception:  # unit problems are reported by validate()
        return
    states = set(states)
    for el in graph.elements.values():
        if isinstance(el, (I, C)) and el.state in states and not el.state.unit:
            e, f = bu.get(el.port.bond.name, (None, None))
            if isinstance(el, I) and e:
                el.state.unit = _canonical_unit(_units.product(e, "s"))
            elif isinstance(el, C) and f:
                el.state.unit = _canonical_unit(_units.product(f, "s"))


def _canonical_unit(text: str) -> str:
    """Readable unit of a product with s: '(N)*(s)' -> 'N*s', '(m/s)*(s)' -> 'm'."""
    inner = text
    if text.startswith("(") and text.endswith(")*(s)"):
        inner = text[1:-5]
        if inner.endswith("/s") and "/" not in inner[:-2]:
            return inner[:-2]
        return f"{inner}*s"
    return text


def derive(graph: BondGraph, *, causality: Causality | None = None,
           validate: bool = True) -> StateSpace:
    """Derive the explicit state equations of a bond graph.

    Parameters
    ----------
    graph : BondGraph
    causality : Causality, optional
        A precomputed SCAP result; computed when omitted.
    validate : bool
        Validate the graph first.

    Returns
    -------
    StateSpace
        dx/dt = f(x, u, θ) (states named after their elements: momenta of I,
        displacements of C), outputs y = h(x, u, θ), energy H, source and
        dissipated power. Jacobians via ``.dfdx()``, ``.dfdtheta()``,
        ``.dhdx()``.

    Raises
    ------
    CausalConflictError, AlgebraicLoopError, DerivativeCausalityError
        See :mod:`bondgraph.errors`; each names the elements and bonds.

    References
    ----------
    Karnopp, Margolis & Rosenberg, *System Dynamics*, 5th ed., ch. 5 and 7.
    """
    with paused_gc():
        return _derive(graph, causality, validate)


@contextlib.contextmanager
def paused_gc():
    """Python's cyclic garbage collector paused inside the block (if it ran
    before; nested blocks and threads only keep it paused longer).

    Derivation and code generation allocate millions of small sympy objects
    and free them by reference counting; every full collection meanwhile
    walks all live objects, a cost that grows with the graph at each
    collection (0.2-0.6 s of 2 s for a 499-state chain, none at 79 states).
    The objects left are collected after the block as usual.
    """
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def _derive(graph: BondGraph, causality: Causality | None, validate: bool) -> StateSpace:
    """:func:`derive`."""
    if causality is None:
        causality = assign_causality(graph, validate=validate)
    d = _Deriver(graph, causality)
    d.build()
    _assign_state_units(graph, d.states)
    solved = d.solve()
    states = d.states
    f = _state_derivatives(d, solved)
    A = lambda ex: sp.sympify(ex).xreplace(d.alias).xreplace(solved)  # noqa: E731
    outputs = [Output(s.name, A(s.expr), s.unit, s.description,
                      A(s.noise_std) if isinstance(s.noise_std, sp.Basic) else s.noise_std)
               for s in graph.sensors.values()]
    for o in outputs:
        leftover = _unsolved(d, o.expr)
        if leftover:  # pragma: no cover - guarded by the solver
            raise CausalityError(f"internal: sensor '{o.name}' still depends on {leftover}")
    H_terms = _energy_terms(graph, causality, d, solved)
    P_src, P_diss = _powers(graph, solved)
    f, outputs, H_terms, (P_src, P_diss), solved, notes = _extended(
        states, f, outputs, H_terms, (P_src, P_diss), solved)
    rate = _energy_rate(H_terms, d, f)
    inputs = list(graph.inputs.values()) + list(d.der_inputs.values())
    noise = []
    for s in states:
        v = graph.process_noise.get(s.name, 0)
        noise.append(A(v) if isinstance(v, sp.Basic) else v)
    ss = StateSpace(
        name=graph.name, description=graph.description, source=graph.source,
        states=states, inputs=inputs, params=list(graph.params.values()), f=f,
        outputs=outputs, energy=sp.Add(*H_terms), power_sources=P_src, power_dissipated=P_diss,
        energy_rate=rate, process_noise=noise, causality=causality,
        derivative_elements=list(causality.derivative), algebraic_loops=d.loops, solved=solved,
        domain_notes=notes)
    ss._alias = d.alias
    return ss


def _extended(states, f, outputs, H_terms, powers, solved):
    """f, the outputs, the energy terms, the powers and the solved variables
    with every state-dependent power of a restricted domain continued past
    it (:func:`bondgraph.core.domains.extend_domains`), and its notes (for
    f and the outputs)."""
    keys = list(solved)
    exprs = (list(f) + [o.expr for o in outputs] + list(H_terms) + list(powers)
             + [solved[k] for k in keys])
    where = ([f"d{s.name}/dt" for s in states] + [o.name for o in outputs]
             + [""] * (len(exprs) - len(f) - len(outputs)))
    out, notes = extend_domains(exprs, states, where)
    if not notes and out == exprs:
        return f, outputs, H_terms, powers, solved, notes
    it = iter(out)
    f2 = [next(it) for _ in f]
    for o in outputs:
        o.expr = next(it)
    H2 = [next(it) for _ in H_terms]
    P2 = tuple(next(it) for _ in powers)
    solved2 = {k: next(it) for k in keys}
    return f2, outputs, H2, P2, solved2, notes


def _unsolved(d: _Deriver, ex: sp.Expr) -> list:
    """The unknowns of ``d`` (port variables, derivative-causality targets)
    still in ``ex``: none once solved."""
    return [x for x in ex.free_symbols if x in d.eqs or x in d.dt_targets]


def _state_derivatives(d: _Deriver, solved: dict) -> list[sp.Expr]:
    """f: the solved ẋ of every state, in states and inputs only."""
    f = []
    for s in d.states:
        ex = solved[d.xdot[s]]
        leftover = _unsolved(d, ex)
        if leftover:  # pragma: no cover - guarded by the solver
            raise CausalityError(f"internal: d{s.name}/dt still depends on {leftover}")
        f.append(ex)
    return f


#: Gauss-Legendre nodes of :class:`StoredEnergy`'s quadrature
ENERGY_NODES = 32


class StoredEnergy(sp.Function):
    """H(q) = ∫₀^q Ψ(s) ds of a storage law Ψ that sympy cannot integrate
    in closed form (a softplus dead zone, a user's tabulated-looking law):
    ``StoredEnergy(q, Lambda(s, Ψ(s)))``.

    Its derivative is the law itself (∂H/∂q = Ψ(q)), so the energy rate
    by the chain rule stays exactly the sources' power minus the
    dissipation; its value is printed as a Gauss-Legendre quadrature of
    :data:`ENERGY_NODES` nodes (:meth:`quadrature`; exact for a
    polynomial law of degree < 64, Davis & Rabinowitz, *Methods of
    Numerical Integration*, 1984, ch. 2.7).
    """

    nargs = 2

    def fdiff(self, argindex=1):
        if argindex != 1:  # the law's body is not a function of q
            raise sp.ArgumentIndexError(self, argindex)
        q, law = self.args
        return law(q)

    def quadrature(self) -> sp.Expr:
        """The energy as Σ wᵢ q/2 Ψ(q (1 + xᵢ)/2) over the Gauss-Legendre
        nodes xᵢ and weights wᵢ on [−1, 1]."""
        q, law = self.args
        x, w = np.polynomial.legendre.leggauss(ENERGY_NODES)
        return sp.Add(*(sp.Float(wi / 2) * q * law(sp.Float((xi + 1) / 2) * q)
                        for xi, wi in zip(x, w)))


def stored_energy(law: sp.Expr, state: sp.Symbol) -> sp.Expr:
    """∫₀^state law d(state) in closed form, else a :class:`StoredEnergy`.

    Parameters
    ----------
    law : sympy.Expr
        A storage's constitutive law in its state (effort of a C's
        displacement, flow of an I's momentum).
    state : sympy.Symbol

    Returns
    -------
    sympy.Expr
        The potential (co-)energy, zero at state 0.
    """
    s = sp.Dummy("s", real=True)
    body = law.xreplace({state: s})
    energy = sp.integrate(body, (s, 0, state))
    if energy.has(sp.Integral):
        return StoredEnergy(state, sp.Lambda(s, body))
    return energy


def expand_stored_energy(expr: sp.Expr) -> sp.Expr:
    """``expr`` with every :class:`StoredEnergy` replaced by its quadrature
    (for printing as code)."""
    if not expr.has(StoredEnergy):
        return expr
    return expr.replace(lambda e: isinstance(e, StoredEnergy), lambda e: e.quadrature())


def _energy_terms(graph: BondGraph, causality: Causality, d: _Deriver,
                  solved: dict) -> list[sp.Expr]:
    """Stored energy, one term per storage (differentiated term by term in
    :func:`_energy_rate`). A storage without a given energy gets
    ∫ law d(state); one in derivative causality is expressed through the
    inverted law."""
    H_terms: list[sp.Expr] = []
    for el in graph.elements.values():
        if isinstance(el, (I, C)):
            energy = el.energy
            if energy is None:
                energy = stored_energy(el.law, el.state)
            if el.name in causality.derivative:
                W = [v[0] for v in d.dt_targets.values() if v[1] == el.name][0]
                energy = energy.xreplace({el.state: W.xreplace(solved)})
            H_terms.append(energy.xreplace(d.alias).xreplace(solved))
        elif isinstance(el, (CField, IField)):
            H_terms.append(el.energy.xreplace(d.alias).xreplace(solved))
    return H_terms


def _powers(graph: BondGraph, solved: dict) -> tuple[sp.Expr, sp.Expr]:
    """Power delivered by the sources and absorbed by the R elements (e·f),
    each product left unevaluated (:func:`_product`)."""
    src_terms, diss_terms = [], []
    for name in sorted(graph.elements):
        el = graph.elements[name]
        if isinstance(el, Source):
            b = el.port.bond
            src_terms.append(_product(solved[b.e], solved[b.f]))
        elif isinstance(el, (R, RField)):
            for p in el.ports:
                diss_terms.append(_product(solved[p.bond.e], solved[p.bond.f]))
    return sp.Add(*src_terms), sp.Add(*diss_terms)


def _product(e: sp.Expr, f: sp.Expr) -> sp.Expr:
    """e·f as an unevaluated product when both are sums: sympy's product of
    a sum with itself (a damper's e = c·Δv times f = Δv) makes a power of a
    sum, whose creation asks the assumptions of every term (the slowest
    step of the derivation of a long chain); the value is the same."""
    if e.is_Add or f.is_Add or (e.is_Mul and f.is_Mul):
        return sp.Mul(e, f, evaluate=False)
    return e * f


def _energy_rate(H_terms: list[sp.Expr], d: _Deriver, f: list[sp.Expr]) -> sp.Expr:
    """dH/dt by the chain rule: Σ ∂H/∂x_i ẋ_i + Σ ∂H/∂u_j u̇_j (``der(u)`` inputs)."""
    f_of = {s: fi for s, fi in zip(d.states, f)}
    for u, du in d.der_inputs.items():
        f_of[u] = du
    rate_terms = []
    known = set(f_of)
    for term in H_terms:
        for s in sorted(term.free_symbols & known, key=lambda s: s.name):
            rate_terms.append(diff(term, s) * f_of[s])
    return sp.Add(*rate_terms)
