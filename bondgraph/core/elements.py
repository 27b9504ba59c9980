"""Bond-graph elements (Karnopp, Margolis & Rosenberg, *System Dynamics*, ch. 3-4).

Power sign convention (one for the whole toolkit): the half-arrow of a bond
points in the direction of positive power e*f. The toolkit sets it from the
element, never from the order of arguments to ``connect``:

* sources (Se, Sf, MSe, MSf) deliver power: half-arrow away from the source;
* storages and resistors (I, C, R and their multiport fields) absorb power:
  half-arrow into the element;
* two-ports (TF, GY, MTF, MGY) pass power through: into port ``p1``, out of
  port ``p2``;
* between two junctions the bond points from the first argument of
  ``connect`` to the second. That direction is part of the model, not an
  accident of argument order: it sets the sign with which the bond enters
  both junction sums (1(v1) -> 0 -> 1(v2) makes the 0-junction's third bond
  carry v1 - v2), exactly as the half-arrow drawn between two junctions does
  in a hand-drawn graph.

Constitutive laws (all power-in conventions):

=========  ==================================================================
Se / MSe   e = E(x, u, θ)
Sf / MSf   f = F(x, u, θ)
I          f = p / I          or  f = Φ(p)  (``flow=`` law of the momentum)
C          e = q / C = k q    or  e = Ψ(q)  (``effort=`` law of the displacement)
R          e = R f            or  e = φ(f) (``effort=``), f = φ(e) (``flow=``)
TF / MTF   e1 = m e2,  f2 = m f1                (m may be modulated for MTF)
GY / MGY   e1 = r f2,  e2 = r f1                (r may be modulated for MGY)
0          e_i all equal,  Σ ± f_i = 0  (+ for bonds pointing in)
1          f_i all equal,  Σ ± e_i = 0
=========  ==================================================================

Laws given as callables receive the port variable (or state) as a sympy
symbol and return a sympy expression, which may also use parameters, inputs,
states and the variables of other elements or junctions (modulation).
"""

from __future__ import annotations

from typing import Callable, Sequence

import sympy as sp

from bondgraph.core.symbols import StateVar, Var
from bondgraph.errors import ElementError, InvalidNameError


def local_state_name(element_name: str, letter: str, index: int | None = None) -> str:
    """State name for an element: ``p_mass``, ``engine.p_J`` (namespace kept)."""
    suffix = "" if index is None else f"_{index}"
    if "." in element_name:
        prefix, local = element_name.rsplit(".", 1)
        return f"{prefix}.{letter}_{local}{suffix}"
    return f"{letter}_{element_name}{suffix}"


#: what users of other tools call an element's argument -> this toolkit's name
_SYNONYMS = {"capacitance": "compliance", "capacity": "compliance", "spring": "stiffness",
             "inductance": "inertance", "mass": "inertance", "inertia": "inertance",
             "damping": "resistance", "ratio": "modulus", "gain": "modulus"}

#: the names of other tools and of the domains for exactly an element's own
#: parameter, taken as it (``C(capacitance=...)`` is ``C(compliance=...)``)
ALIASES = {"C": {"capacitance": "compliance", "capacity": "compliance"},
           "I": {"inductance": "inertance", "mass": "inertance", "inertia": "inertance"},
           "R": {"damping": "resistance"}}


def _aliased(kind: str, name: str, value, kw: dict):
    """``value`` (the element's own parameter, or None) or the one given by
    an alias of it in ``kw`` (:data:`ALIASES`, popped from ``kw``).

    Raises
    ------
    ElementError
        The parameter given twice, under its name and an alias (or two
        aliases).
    """
    for alias, own in ALIASES[kind].items():
        if alias in kw:
            if value is not None:
                raise ElementError(f"{kind} '{name}': {own} given twice ({alias}= is {own}=)",
                                   elements=[name])
            value = kw.pop(alias)
    return value


def _unknown_arguments(cls: type, name: str, unknown: dict) -> tuple[str, str | None]:
    """The message for keyword arguments an element's class does not take
    (the element, the arguments, what the class takes) and the hint (the
    argument likely meant, or None)."""
    import inspect

    takes = []
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None:
            continue
        for p in inspect.signature(init).parameters.values():
            if p.name not in ("self", "name") and p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL) \
                    and p.name not in takes:
                takes.append(p.name)
    hints = [f"{_SYNONYMS[k]}= in place of {k}=" for k in sorted(unknown)
             if _SYNONYMS.get(k) in takes]
    return (f"{cls.__name__} '{name}': unknown argument(s) {', '.join(sorted(unknown))}; "
            f"{cls.__name__} takes {', '.join(takes)}", "; ".join(hints) or None)


def _as_expr(value) -> sp.Expr:
    if isinstance(value, sp.Basic):
        return value
    return sp.sympify(value)


class Port:
    """One port of an element; a bond attaches to it.

    Attributes
    ----------
    element : Element
    index : int
        0 for one-ports; 0 (``p1``) or 1 (``p2``) for two-ports; running
        index for junctions and fields.
    e, f : Var
        Effort and flow of the bond on this port, usable in laws.
    bond : Bond or None
    """

    def __init__(self, element: "Element", index: int):
        self.element = element
        self.index = index
        self.bond = None
        if isinstance(element, TwoPort):
            label = f"{element.name}.p{index + 1}"
        elif isinstance(element, Field):
            label = f"{element.name}.{index + 1}"
        else:
            label = element.name
        self.label = label
        self.e = Var(f"{label}.e", "effort", label) if not isinstance(element, OnePort) else element.e
        self.f = Var(f"{label}.f", "flow", label) if not isinstance(element, OnePort) else element.f

    @property
    def name(self) -> str:
        return self.label

    def power_preference(self) -> str | None:
        """'out' if positive power leaves the element here, 'in' if it enters,
        None for junction ports (direction set by the caller)."""
        return self.element.power_preference(self.index)

    def __repr__(self) -> str:
        return f"<Port {self.label}>"


class Element:
    """Base class of all elements. ``kind`` is the bond-graph letter code."""

    kind = "?"
    n_ports: int | None = 1

    def __init__(self, name: str, *, effort_unit: str | None = None,
                 flow_unit: str | None = None, description: str = "", **unknown):
        if not isinstance(name, str) or not name or any(c.isspace() for c in name) or "->" in name:
            raise InvalidNameError(f"invalid element name {name!r}: use a non-empty name without spaces")
        if unknown:
            text, hint = _unknown_arguments(type(self), name, unknown)
            raise ElementError(text, elements=[name], hint=hint)
        self.name = name
        self.description = description
        self.effort_unit = effort_unit
        self.flow_unit = flow_unit
        self.ports: list[Port] = []
        if self.n_ports:
            self.ports = [Port(self, i) for i in range(self.n_ports)]

    # --- metadata used by graph, causality and equations -----------------
    def power_preference(self, index: int) -> str | None:
        raise NotImplementedError

    def expressions(self) -> list[sp.Expr]:
        """User expressions of this element (laws, moduli, source values)."""
        return []

    def owned_symbols(self) -> list[sp.Symbol]:
        """Symbols created by this element (port variables, states)."""
        out: list[sp.Symbol] = []
        for p in self.ports:
            out += [p.e, p.f]
        return out

    def states(self) -> list[StateVar]:
        return []

    def clone(self, name: str, subs: dict) -> "Element":
        """Copy under a new name with symbols substituted (namespacing)."""
        raise NotImplementedError

    #: names of attributes holding user expressions (or lists of them)
    _expr_attrs: tuple[str, ...] = ()

    def substitute(self, subs: dict) -> None:
        """Apply ``xreplace(subs)`` to every expression of this element."""
        for attr in self._expr_attrs:
            v = getattr(self, attr, None)
            if v is None:
                continue
            if isinstance(v, list):
                setattr(self, attr, [x.xreplace(subs) for x in v])
            else:
                setattr(self, attr, v.xreplace(subs))

    def _copy_common(self, other: "Element") -> "Element":
        other.description = self.description
        other.effort_unit = self.effort_unit
        other.flow_unit = self.flow_unit
        return other

    def __repr__(self) -> str:
        return f"{self.kind}:{self.name}"


class OnePort(Element):
    """Element with one port; its bond variables are ``.e`` and ``.f``."""

    n_ports = 1

    def __init__(self, name: str, **kw):
        self.e = Var(f"{name}.e", "effort", name)
        self.f = Var(f"{name}.f", "flow", name)
        super().__init__(name, **kw)

    @property
    def port(self) -> Port:
        return self.ports[0]

    def owned_symbols(self):
        return [self.e, self.f]


# --------------------------------------------------------------------- sources
class Source(OnePort):
    """Se / Sf / MSe / MSf. ``value`` is the effort (Se) or flow (Sf)."""

    variable = "effort"
    _expr_attrs = ("value",)

    def __init__(self, name: str, value, *, modulated: bool = False, **kw):
        super().__init__(name, **kw)
        if value is None:
            what = self.variable
            raise ElementError(f"{'Se' if what == 'effort' else 'Sf'} '{name}': no {what} given; "
                               f"give a number, a parameter, an input or an expression")
        self.value = _as_expr(value)
        self.modulated = modulated

    @property
    def kind(self) -> str:  # type: ignore[override]
        base = "Se" if self.variable == "effort" else "Sf"
        return ("M" + base) if self.modulated else base

    def power_preference(self, index):
        return "out"

    def expressions(self):
        return [self.value]

    def clone(self, name, subs):
        new = type(self)(name, self.value.xreplace(subs), modulated=self.modulated)
        return self._copy_common(new)


class Se(Source):
    """Effort source: e = value (power delivered)."""

    variable = "effort"


class Sf(Source):
    """Flow source: f = value (power delivered)."""

    variable = "flow"


# -------------------------------------------------------------------- storages
class I(OnePort):  # noqa: E742 - bond-graph name
    """Inertia: state momentum p, ṗ = e, f = p/I or f = Φ(p).

    Parameters
    ----------
    name : str
    inertance : expr, optional
        Linear inertance I (mass, inertia, inductance; ``inductance=``,
        ``mass=`` or ``inertia=`` may stand for ``inertance=``).
    flow : callable, optional
        Nonlinear law ``flow(p) -> f``.
    energy : callable, optional
        Kinetic co-energy ``energy(p) -> H`` for a nonlinear law; computed as
        ∫Φ(p)dp by sympy when omitted.
    initial : float
        Initial momentum.
    priority : int
        SCAP processes storages by (priority, name); lower first. The first of
        two rigidly coupled inertias keeps its state.
    """

    kind = "I"
    _expr_attrs = ("inertance", "law", "energy")

    def __init__(self, name: str, inertance=None, *, flow: Callable | None = None,
                 energy: Callable | None = None, initial: float = 0.0, priority: int = 0, **kw):
        inertance = _aliased("I", name, inertance, kw)
        super().__init__(name, **kw)
        self.state = StateVar(local_state_name(name, "p"), "momentum", name, initial=initial)
        self.priority = priority
        if (inertance is None) == (flow is None):
            raise ElementError(f"I '{name}': give exactly one of inertance= or flow=")
        self.inertance = _as_expr(inertance) if inertance is not None else None
        p = self.state
        self.law = (p / self.inertance) if flow is None else _as_expr(flow(p))
        if energy is not None:
            self.energy = _as_expr(energy(p))
        elif self.inertance is not None:
            self.energy = p**2 / (2 * self.inertance)
        else:
            self.energy = None  # integrated lazily

    @property
    def p(self) -> StateVar:
        return self.state

    def power_preference(self, index):
        return "in"

    def expressions(self):
        return [self.law]

    def owned_symbols(self):
        return super().owned_symbols() + [self.state]

    def states(self):
        return [self.state]

    def clone(self, name, subs):
        new = I.__new__(I)
        OnePort.__init__(new, name)
        new.state = self.state.with_name(local_state_name(name, "p"), name)
        subs = dict(subs)
        subs[self.state] = new.state
        new.priority = self.priority
        new.inertance = self.inertance.xreplace(subs) if self.inertance is not None else None
        new.law = self.law.xreplace(subs)
        new.energy = self.energy.xreplace(subs) if self.energy is not None else None
        return self._copy_common(new)


class C(OnePort):
    """Capacitance: state displacement q, q̇ = f, e = q/C = k q or e = Ψ(q).

    Parameters
    ----------
    name : str
    compliance : expr, optional
        Linear compliance C (e = q/C; ``capacitance=`` or ``capacity=`` may
        stand for ``compliance=``).
    stiffness : expr, optional
        Linear stiffness k (e = k q); alternative to ``compliance``.
    effort : callable, optional
        Nonlinear law ``effort(q) -> e``.
    energy : callable, optional
        Potential energy ``energy(q)`` for a nonlinear law (else ∫Ψ dq).
    initial : float
        Initial displacement.
    priority : int
        SCAP order among storages (lower first).
    """

    kind = "C"
    _expr_attrs = ("compliance", "stiffness", "law", "energy")

    def __init__(self, name: str, compliance=None, *, stiffness=None,
                 effort: Callable | None = None, energy: Callable | None = None,
                 initial: float = 0.0, priority: int = 0, **kw):
        compliance = _aliased("C", name, compliance, kw)
        super().__init__(name, **kw)
        self.state = StateVar(local_state_name(name, "q"), "displacement", name, initial=initial)
        self.priority = priority
        given = [v is not None for v in (compliance, stiffness, effort)]
        if sum(given) != 1:
            raise ElementError(f"C '{name}': give exactly one of compliance=, stiffness= or effort=")
        q = self.state
        self.compliance = _as_expr(compliance) if compliance is not None else None
        self.stiffness = _as_expr(stiffness) if stiffness is not None else None
        if self.compliance is not None:
            self.law = q / self.compliance
            self.energy = q**2 / (2 * self.compliance)
        elif self.stiffness is not None:
            self.law = self.stiffness * q
            self.energy = self.stiffness * q**2 / 2
        else:
            self.law = _as_expr(effort(q))
            self.energy = _as_expr(energy(q)) if energy is not None else None

    @property
    def q(self) -> StateVar:
        return self.state

    def power_preference(self, index):
        return "in"

    def expressions(self):
        return [self.law]

    def owned_symbols(self):
        return super().owned_symbols() + [self.state]

    def states(self):
        return [self.state]

    def clone(self, name, subs):
        new = C.__new__(C)
        OnePort.__init__(new, name)
        new.state = self.state.with_name(local_state_name(name, "q"), name)
        subs = dict(subs)
        subs[self.state] = new.state
        new.priority = self.priority
        new.compliance = self.compliance.xreplace(subs) if self.compliance is not None else None
        new.stiffness = self.stiffness.xreplace(subs) if self.stiffness is not None else None
        new.law = self.law.xreplace(subs)
        new.energy = self.energy.xreplace(subs) if self.energy is not None else None
        return self._copy_common(new)


class R(OnePort):
    """Resistor: e = R f, or a nonlinear (optionally modulated) law.

    Parameters
    ----------
    name : str
    resistance : expr, optional
        Linear resistance (``damping=`` may stand for ``resistance=``).
    effort : callable, optional
        ``effort(f) -> e`` (resistance form), e.g. ``lambda v: Fc*tanh(v/eps)``.
    flow : callable, optional
        ``flow(e) -> f`` (conductance form).

    Notes
    -----
    SCAP gives an R the causality its law is written in when the graph leaves
    the choice free; otherwise the law is inverted symbolically (or solved
    together with its algebraic loop).
    """

    kind = "R"
    _expr_attrs = ("resistance", "law")

    def __init__(self, name: str, resistance=None, *, effort: Callable | None = None,
                 flow: Callable | None = None, **kw):
        resistance = _aliased("R", name, resistance, kw)
        super().__init__(name, **kw)
        given = [v is not None for v in (resistance, effort, flow)]
        if sum(given) != 1:
            raise ElementError(f"R '{name}': give exactly one of resistance=, effort= or flow=")
        self.resistance = _as_expr(resistance) if resistance is not None else None
        if flow is not None:
            self.form = "flow"
            self.law = _as_expr(flow(self.e))
        else:
            self.form = "effort"
            self.law = (self.resistance * self.f) if effort is None else _as_expr(effort(self.f))

    def power_preference(self, index):
        return "in"

    def expressions(self):
        return [self.law]

    def clone(self, name, subs):
        new = R.__new__(R)
        OnePort.__init__(new, name)
        subs = dict(subs)
        subs[self.e] = new.e
        subs[self.f] = new.f
        new.resistance = self.resistance.xreplace(subs) if self.resistance is not None else None
        new.form = self.form
        new.law = self.law.xreplace(subs)
        return self._copy_common(new)

    def residual(self) -> sp.Expr:
        """Law as ``0 = residual`` in the port variables."""
        if self.form == "effort":
            return self.e - self.law
        return self.f - self.law


# -------------------------------------------------------------------- two-ports
class TwoPort(Element):
    """Two-port with ports ``p1`` (power in) and ``p2`` (power out)."""

    n_ports = 2
    modulated = False
    _expr_attrs = ("modulus",)

    def __init__(self, name: str, modulus, **kw):
        super().__init__(name, **kw)
        self.modulus = _as_expr(modulus)

    @property
    def p1(self) -> Port:
        return self.ports[0]

    @property
    def p2(self) -> Port:
        return self.ports[1]

    def power_preference(self, index):
        return "in" if index == 0 else "out"

    def expressions(self):
        return [self.modulus]

    def clone(self, name, subs):
        new = type(self)(name, 1)
        subs = dict(subs)
        for old_p, new_p in zip(self.ports, new.ports):
            subs[old_p.e] = new_p.e
            subs[old_p.f] = new_p.f
        new.modulus = self.modulus.xreplace(subs)
        return self._copy_common(new)


class TF(TwoPort):
    """Transformer: e1 = m e2, f2 = m f1 (m constant: parameters only)."""

    kind = "TF"


class MTF(TF):
    """Modulated transformer: as TF with m an expression of states, inputs,
    parameters and other variables (e.g. a CVT ratio)."""

    kind = "MTF"
    modulated = True


class GY(TwoPort):
    """Gyrator: e1 = r f2, e2 = r f1 (r constant)."""

    kind = "GY"


class MGY(GY):
    """Modulated gyrator: r an expression."""

    kind = "MGY"
    modulated = True


# -------------------------------------------------------------------- junctions
#: the names other tools give the domains (20-sim's and Modelica's libraries,
#: textbooks): what a user writes first
DOMAIN_ALIASES = {"translational": "translation", "linear": "translation",
                  "rotational": "rotation", "rotary": "rotation", "electric": "electrical",
                  "fluid": "hydraulic", "hydraulics": "hydraulic", "heat_flow": "heat",
                  "magnetics": "magnetic"}


def domain_suggestion(domain: str, known) -> str | None:
    """The remedy for a misspelt ``domain``: the known domain it most likely
    means, an alias of :data:`DOMAIN_ALIASES` (case ignored) or the closest
    name (:func:`difflib.get_close_matches`); both mechanical ones for
    'mechanical'; None when nothing is near."""
    import difflib

    key = str(domain).strip().lower()
    if key in ("mechanical", "mechanics"):
        return "domain='translation' (a linear motion) or domain='rotation' (a shaft)"
    near = key if key in known else DOMAIN_ALIASES.get(key)
    if near not in known:
        close = difflib.get_close_matches(key, list(known), n=1, cutoff=0.6)
        near = close[0] if close else None
    return f"domain='{near}'" if near else None


class Junction(Element):
    """0- or 1-junction; any number of bonds (at least two)."""

    n_ports = None

    def __init__(self, name: str, *, domain: str | None = None, **kw):
        super().__init__(name, **kw)
        if domain is not None:
            from bondgraph.core.units import DOMAINS

            if domain not in DOMAINS:
                near = domain_suggestion(domain, DOMAINS)
                raise ElementError(f"junction '{name}': unknown domain '{domain}' "
                                   f"(known: {', '.join(DOMAINS)})", elements=[name],
                                   hint=near)
            e_u, f_u = DOMAINS[domain]
            self.effort_unit = self.effort_unit or e_u
            self.flow_unit = self.flow_unit or f_u
        self.domain = domain

    def new_port(self) -> Port:
        p = Port(self, len(self.ports))
        self.ports.append(p)
        return p

    def power_preference(self, index):
        return None

    def owned_symbols(self):
        return [self.var]

    def clone(self, name, subs):
        new = type(self)(name)
        new.domain = self.domain
        return self._copy_common(new)


class Zero(Junction):
    """0-junction: common effort ``.e`` (alias ``.effort``); flows sum to zero."""

    kind = "0"

    def __init__(self, name: str, **kw):
        self.e = Var(f"{name}.e", "effort", name)
        super().__init__(name, **kw)

    @property
    def var(self):
        return self.e

    @property
    def effort(self):
        return self.e


class One(Junction):
    """1-junction: common flow ``.f`` (alias ``.flow``); efforts sum to zero."""

    kind = "1"

    def __init__(self, name: str, **kw):
        self.f = Var(f"{name}.f", "flow", name)
        super().__init__(name, **kw)

    @property
    def var(self):
        return self.f

    @property
    def flow(self):
        return self.f


# ---------------------------------------------------------------------- fields
class Field(Element):
    """Multiport storage or resistive field with ``n`` ports (``.port(i)``)."""

    def __init__(self, name: str, n: int, **kw):
        if n < 1:
            raise ElementError(f"field '{name}' needs at least one port")
        self.n_ports = n
        super().__init__(name, **kw)

    def port(self, i: int) -> Port:
        return self.ports[i]

    def power_preference(self, index):
        return "in"


class CField(Field):
    """Multiport C field from a potential energy H(q_1..q_n): e_i = ∂H/∂q_i.

    Parameters
    ----------
    name : str
    energy : callable
        ``energy(q1, ..., qn) -> H``.
    n : int
        Number of ports.
    """

    kind = "C"
    _expr_attrs = ("energy", "laws")

    def __init__(self, name: str, energy: Callable, n: int, *, priority: int = 0, **kw):
        super().__init__(name, n, **kw)
        self._states = [StateVar(local_state_name(name, "q", i + 1), "displacement", name)
                        for i in range(n)]
        self.energy = _as_expr(energy(*self._states))
        self.laws = [sp.diff(self.energy, q) for q in self._states]
        self.priority = priority

    def states(self):
        return list(self._states)

    def expressions(self):
        return [self.energy]

    def owned_symbols(self):
        return super().owned_symbols() + list(self._states)

    def clone(self, name, subs):
        new = CField.__new__(CField)
        Field.__init__(new, name, self.n_ports)
        new._states = [s.with_name(local_state_name(name, "q", i + 1), name)
                       for i, s in enumerate(self._states)]
        subs = dict(subs)
        subs.update(dict(zip(self._states, new._states)))
        new.energy = self.energy.xreplace(subs)
        new.laws = [law.xreplace(subs) for law in self.laws]
        new.priority = self.priority
        return self._copy_common(new)


class IField(Field):
    """Multiport I field from a kinetic co-energy H(p_1..p_n): f_i = ∂H/∂p_i."""

    kind = "I"
    _expr_attrs = ("energy", "laws")

    def __init__(self, name: str, energy: Callable, n: int, *, priority: int = 0, **kw):
        super().__init__(name, n, **kw)
        self._states = [StateVar(local_state_name(name, "p", i + 1), "momentum", name)
                        for i in range(n)]
        self.energy = _as_expr(energy(*self._states))
        self.laws = [sp.diff(self.energy, p) for p in self._states]
        self.priority = priority

    states = CField.states
    expressions = CField.expressions
    owned_symbols = CField.owned_symbols

    def clone(self, name, subs):
        new = IField.__new__(IField)
        Field.__init__(new, name, self.n_ports)
        new._states = [s.with_name(local_state_name(name, "p", i + 1), name)
                       for i, s in enumerate(self._states)]
        subs = dict(subs)
        subs.update(dict(zip(self._states, new._states)))
        new.energy = self.energy.xreplace(subs)
        new.laws = [law.xreplace(subs) for law in self.laws]
        new.priority = self.priority
        return self._copy_common(new)


class RField(Field):
    """Multiport resistive field e_i = φ_i(f_1..f_n).

    Parameters
    ----------
    name : str
    effort : callable
        ``effort(f1, ..., fn) -> [e1, ..., en]``.
    n : int
    """

    kind = "R"
    _expr_attrs = ("laws",)

    def __init__(self, name: str, effort: Callable, n: int, **kw):
        super().__init__(name, n, **kw)
        laws = effort(*[p.f for p in self.ports])
        if len(laws) != n:
            raise ElementError(f"R field '{name}': effort() must return {n} expressions")
        self.laws = [_as_expr(v) for v in laws]

    def expressions(self):
        return list(self.laws)

    def clone(self, name, subs):
        new = RField.__new__(RField)
        Field.__init__(new, name, self.n_ports)
        subs = dict(subs)
        for o, n_ in zip(self.ports, new.ports):
            subs[o.e] = n_.e
            subs[o.f] = n_.f
        new.laws = [law.xreplace(subs) for law in self.laws]
        return self._copy_common(new)


STORAGE_TYPES = (I, C, CField, IField)
RESISTIVE_TYPES = (R, RField)
SOURCE_TYPES = (Source,)


def state_vars(elements: Sequence[Element]) -> list[StateVar]:
    out: list[StateVar] = []
    for el in elements:
        out += el.states()
    return out
