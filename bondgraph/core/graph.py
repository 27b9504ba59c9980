"""Declaring a bond graph in Python: elements, bonds, parameters, inputs,
sensors, signal states and reusable fragments.

Data flow of the toolkit::

    declare (this module) -> causality -> equations -> codegen -> model
        -> simulate / filter / estimate -> diagnose

Example
-------
>>> import bondgraph as bg
>>> g = bg.BondGraph("msd")
>>> m = g.param("m", 2.0, "kg")
>>> k = g.param("k", 50.0, "N/m")
>>> c = g.param("c", 1.5, "N*s/m")
>>> F = g.input("F", "N")
>>> v = g.one("v", domain="translation")
>>> _ = g.connect(g.Se("force", F), v)
>>> mass = g.I("mass", m); _ = g.connect(v, mass)
>>> spring = g.C("spring", stiffness=k); _ = g.connect(v, spring)
>>> _ = g.connect(v, g.R("damper", c))
>>> _ = g.sensor("x", spring.q, unit="m")
>>> g.validate()
"""

from __future__ import annotations

import copy as _copy
from dataclasses import dataclass, field
from typing import Any, Callable

import sympy as sp

from bondgraph.core import units as _units
from bondgraph.core.elements import (
    GY,
    MGY,
    MTF,
    TF,
    C,
    CField,
    Element,
    I,
    IField,
    Junction,
    One,
    OnePort,
    Port,
    R,
    RField,
    Se,
    Sf,
    Source,
    TwoPort,
    Zero,
)
from bondgraph.core.symbols import Input, Parameter, StateVar, Var
from bondgraph.errors import (
    ConnectionError,
    DanglingPortError,
    DuplicateNameError,
    GraphError,
    InvalidNameError,
    JunctionError,
    PortCountError,
    UndeclaredSymbolError,
    UnitMismatchError,
    join_names,
)


class Bond:
    """A power bond from ``tail`` to ``head`` (half-arrow at ``head``).

    Attributes
    ----------
    name : str
        ``"tail -> head"`` using port labels.
    tail, head : Port
    e, f : Var
        Effort and flow of the bond.
    """

    def __init__(self, tail: Port, head: Port, name: str):
        self.tail = tail
        self.head = head
        self.name = name
        self.e = Var(f"e[{name}]", "effort", name)
        self.f = Var(f"f[{name}]", "flow", name)

    def ends(self) -> tuple[Port, Port]:
        return self.tail, self.head

    def other(self, port: Port) -> Port:
        return self.head if port is self.tail else self.tail

    def sign_at(self, element: Element) -> int:
        """+1 if the half-arrow points into ``element``, -1 if out of it."""
        if self.head.element is element:
            return 1
        if self.tail.element is element:
            return -1
        raise ValueError(f"bond {self.name} does not touch {element.name}")

    def __repr__(self) -> str:
        return f"<Bond {self.name}>"


@dataclass
class Sensor:
    """A measured output y = expr (+ noise of standard deviation ``noise_std``)."""

    name: str
    expr: sp.Expr
    unit: str = ""
    noise_std: Any = None
    description: str = ""


@dataclass
class SignalState:
    """A state that is not a bond-graph storage: dz/dt = rhs (random walk,
    lag, shift dynamics, sensor integrator)."""

    state: StateVar
    rhs: sp.Expr
    process_noise: Any = None


@dataclass
class Handle:
    """What ``BondGraph.include`` returns: access to a namespaced fragment.

    ``h.port("shaft")`` gives the parent-graph target of an exposed port;
    ``h["J"]`` the element, ``h.param("J")``, ``h.input("u")``,
    ``h.state("z")`` the renamed symbols.
    """

    graph: "BondGraph"
    prefix: str
    ports: dict[str, Any] = field(default_factory=dict)

    def _full(self, local: str) -> str:
        return f"{self.prefix}.{local}"

    def port(self, name: str):
        try:
            return self.ports[name]
        except KeyError:
            raise GraphError(f"fragment '{self.prefix}' exposes no port '{name}' "
                             f"(it has: {', '.join(sorted(self.ports)) or 'none'})") from None

    def __getitem__(self, local: str) -> Element:
        return self.graph.element(self._full(local))

    def param(self, local: str) -> Parameter:
        return self.graph.params[self._full(local)]

    def input(self, local: str) -> Input:
        return self.graph.inputs[self._full(local)]

    def state(self, local: str) -> StateVar:
        return self.graph.signal_states[self._full(local)].state


class BondGraph:
    """A bond graph: the declaration from which everything is derived.

    Parameters
    ----------
    name : str
        Model name (the generated module is ``generated/<name>.py``).
    description : str, optional
        One paragraph; copied into the generated module's docstring.

    Notes
    -----
    The power sign convention is documented in :mod:`bondgraph.core.elements`.
    Elements are processed by SCAP in sorted-name order and the half-arrow of
    a bond to an element is fixed by the element, so the derived equations do
    not depend on the order of declaration or of ``connect`` arguments; only
    a bond between two junctions takes its direction from ``connect(a, b)``
    (a -> b), which is part of the model.
    """

    def __init__(self, name: str, description: str = ""):
        self.name = name
        self.description = description
        self.elements: dict[str, Element] = {}
        self.bonds: list[Bond] = []
        self.params: dict[str, Parameter] = {}
        self.inputs: dict[str, Input] = {}
        self.sensors: dict[str, Sensor] = {}
        self.signal_states: dict[str, SignalState] = {}
        self.process_noise: dict[str, Any] = {}
        self.exposed: dict[str, Any] = {}
        self.source: str | None = None  # "module:function", set by the registry
        self.metadata: dict[str, Any] = {}

    # ------------------------------------------------------------ symbols
    def param(self, name: str, default: float = 1.0, unit: str | None = None,
              bounds: tuple[float, float] | None = None, description: str = "",
              source: str = "") -> Parameter:
        """Declare a parameter; see :class:`bondgraph.core.symbols.Parameter`."""
        self._check_free_name(name, self.params, "parameter")
        p = Parameter(name, default, unit, bounds, description, source)
        self.params[name] = p
        return p

    def add_param(self, p: Parameter) -> Parameter:
        """Declare an existing :class:`Parameter` object (e.g. shared)."""
        if p.name in self.params:
            if self.params[p.name] is p:
                return p
            raise DuplicateNameError(f"graph '{self.name}': parameter '{p.name}' declared twice")
        self.params[p.name] = p
        return p

    def input(self, name: str, unit: str | None = None, default: float = 0.0,
              description: str = "") -> Input:
        """Declare an input signal u_j."""
        self._check_free_name(name, self.inputs, "input")
        u = Input(name, unit, default, description)
        self.inputs[name] = u
        return u

    def state(self, name: str, rhs: Any = 0, *, unit: str | None = None, initial: float = 0.0,
              process_noise: Any = None, description: str = "") -> StateVar:
        """Declare a signal state z with dz/dt = rhs.

        Parameters
        ----------
        name : str
        rhs : expr or callable
            Right-hand side; a callable receives the state symbol (for
            laws that read the state itself, e.g. a first-order lag).
        unit : str, optional
        initial : float
        process_noise : float or expr, optional
            Continuous-time noise intensity (state unit per sqrt(s)); a
            random walk is ``rhs=0`` with a process noise.
        """
        self._check_free_name(name, self.signal_states, "state")
        z = StateVar(name, "signal", None, unit, initial, description)
        expr = rhs(z) if callable(rhs) else sp.sympify(rhs)
        self.signal_states[name] = SignalState(z, expr, process_noise)
        if process_noise is not None:
            self.process_noise[name] = process_noise
        return z

    def set_rhs(self, state: StateVar | str, rhs: Any) -> None:
        """Replace the right-hand side of a signal state."""
        key = state if isinstance(state, str) else state.name
        self.signal_states[key].rhs = sp.sympify(rhs)

    def set_process_noise(self, state: StateVar | str, std: Any) -> None:
        """Set the continuous-time process-noise intensity of any state
        (unit of the state per sqrt(s))."""
        key = state if isinstance(state, str) else state.name
        self.process_noise[key] = std

    def sensor(self, name: str, expr: Any, *, unit: str | None = None, noise_std: Any = None,
               description: str = "") -> Sensor:
        """Declare a measured output y = expr.

        ``expr`` may use states, inputs, parameters and any element or
        junction variable (``spring.q``, ``mass.f``, ``j.f``, ``mass.e``...).
        For the displacement or momentum of a bond that has no storage use
        :meth:`displacement` / :meth:`momentum`.
        """
        self._check_free_name(name, self.sensors, "sensor")
        s = Sensor(name, sp.sympify(expr), unit or "", noise_std, description)
        self.sensors[name] = s
        return s

    def _target_var(self, target, kind: str):
        """Effort or flow variable of a junction, element, port or bond."""
        if isinstance(target, Bond):
            return target.e if kind == "effort" else target.f
        if isinstance(target, Port):
            return target.e if kind == "effort" else target.f
        if isinstance(target, Zero) and kind == "effort":
            return target.e
        if isinstance(target, One) and kind == "flow":
            return target.f
        if isinstance(target, OnePort):
            return target.e if kind == "effort" else target.f
        raise GraphError(f"cannot read the {kind} of {target!r}: use a one-port element, "
                         f"a port, a bond, a 1-junction (flow) or a 0-junction (effort)")

    def displacement(self, target, name: str | None = None, unit: str | None = None) -> StateVar:
        """Displacement q = ∫f dt of a junction, element, port or bond.

        For a C element this is its state; otherwise an integrator state is
        added (kind ``"integral"``), named ``q_<target>``.
        """
        if isinstance(target, C):
            return target.q
        f = self._target_var(target, "flow")
        nm = name or f"q_{getattr(target, 'name', str(target))}"
        return self._integrator(nm, f, unit)

    def momentum(self, target, name: str | None = None, unit: str | None = None) -> StateVar:
        """Momentum p = ∫e dt of a junction, element, port or bond (an I's
        state, or a new integrator state ``p_<target>``)."""
        if isinstance(target, I):
            return target.p
        e = self._target_var(target, "effort")
        nm = name or f"p_{getattr(target, 'name', str(target))}"
        return self._integrator(nm, e, unit)

    def _integrator(self, name, var, unit):
        if name in self.signal_states:
            return self.signal_states[name].state
        z = StateVar(name, "integral", None, unit, 0.0, f"integral of {var.name}")
        self.signal_states[name] = SignalState(z, var, None)
        return z

    def _check_free_name(self, name: str, table: dict, what: str) -> None:
        if not isinstance(name, str) or not name or any(c.isspace() for c in name):
            raise InvalidNameError(f"graph '{self.name}': invalid {what} name {name!r} (a "
                                   f"non-empty string without white space)")
        if name in table:
            raise DuplicateNameError(f"graph '{self.name}': {what} '{name}' declared twice")
        symbols = {"parameter": self.params, "input": self.inputs, "state": self.signal_states}
        if what in symbols:
            for kind, other in symbols.items():
                if kind != what and name in other:
                    raise DuplicateNameError(
                        f"graph '{self.name}': {what} '{name}' has the name of {kind} "
                        f"'{name}': parameters, inputs and states need names of their own "
                        f"(the command line, the records and the reports refer to them by "
                        f"name)", hint=f"rename the {what}")

    # ----------------------------------------------------------- elements
    def add(self, element: Element) -> Element:
        """Add an element created outside the graph."""
        if element.name in self.elements:
            raise DuplicateNameError(f"graph '{self.name}': element '{element.name}' declared twice",
                                     elements=[element.name])
        self.elements[element.name] = element
        return element

    def element(self, name: str) -> Element:
        try:
            return self.elements[name]
        except KeyError:
            raise GraphError(f"graph '{self.name}' has no element '{name}'") from None

    def Se(self, name, effort, **kw) -> Se:
        """Effort source (constant or parameter)."""
        return self.add(Se(name, effort, **kw))

    def Sf(self, name, flow, **kw) -> Sf:
        """Flow source (constant or parameter)."""
        return self.add(Sf(name, flow, **kw))

    def MSe(self, name, effort, **kw) -> Se:
        """Modulated effort source: effort an expression of inputs, states,
        parameters and variables."""
        return self.add(Se(name, effort, modulated=True, **kw))

    def MSf(self, name, flow, **kw) -> Sf:
        """Modulated flow source."""
        return self.add(Sf(name, flow, modulated=True, **kw))

    def I(self, name, inertance=None, **kw) -> I:  # noqa: E743
        """Inertia; see :class:`bondgraph.core.elements.I`."""
        return self.add(I(name, inertance, **kw))

    def C(self, name, compliance=None, **kw) -> C:
        """Capacitance; see :class:`bondgraph.core.elements.C`."""
        return self.add(C(name, compliance, **kw))

    def R(self, name, resistance=None, **kw) -> R:
        """Resistor; see :class:`bondgraph.core.elements.R`."""
        return self.add(R(name, resistance, **kw))

    def TF(self, name, modulus, **kw) -> TF:
        """Transformer e1 = m e2, f2 = m f1 (m constant)."""
        return self.add(TF(name, modulus, **kw))

    def MTF(self, name, modulus, **kw) -> MTF:
        """Modulated transformer (m an expression)."""
        return self.add(MTF(name, modulus, **kw))

    def GY(self, name, modulus, **kw) -> GY:
        """Gyrator e1 = r f2, e2 = r f1."""
        return self.add(GY(name, modulus, **kw))

    def MGY(self, name, modulus, **kw) -> MGY:
        """Modulated gyrator."""
        return self.add(MGY(name, modulus, **kw))

    def zero(self, name, **kw) -> Zero:
        """0-junction (common effort)."""
        return self.add(Zero(name, **kw))

    def one(self, name, **kw) -> One:
        """1-junction (common flow)."""
        return self.add(One(name, **kw))

    def CField(self, name, energy: Callable, n: int, **kw) -> CField:
        return self.add(CField(name, energy, n, **kw))

    def IField(self, name, energy: Callable, n: int, **kw) -> IField:
        return self.add(IField(name, energy, n, **kw))

    def RField(self, name, effort: Callable, n: int, **kw) -> RField:
        return self.add(RField(name, effort, n, **kw))

    # -------------------------------------------------------------- bonds
    def _resolve(self, x) -> Port:
        if isinstance(x, str):
            if x in self.exposed:
                x = self.exposed[x]
            else:
                x = self.element(x)
        if isinstance(x, Port):
            if x.element.name not in self.elements or self.elements[x.element.name] is not x.element:
                raise ConnectionError(f"port {x.label} belongs to an element not in graph '{self.name}'",
                                      elements=[x.element.name])
            if isinstance(x.element, Junction):
                return x.element.new_port()
            return x
        if isinstance(x, Element):
            if x.name not in self.elements or self.elements[x.name] is not x:
                raise ConnectionError(f"element '{x.name}' is not in graph '{self.name}' "
                                      f"(add it first)", elements=[x.name])
            if isinstance(x, Junction):
                return x.new_port()
            if isinstance(x, OnePort):
                return x.port
            if isinstance(x, TwoPort):
                raise ConnectionError(
                    f"two-port '{x.name}' needs an explicit port: use {x.name}.p1 (power in) "
                    f"or {x.name}.p2 (power out)", elements=[x.name])
            free = [p for p in x.ports if p.bond is None]
            if len(free) == 1 or (free and len(x.ports) == 1):
                return free[0]
            raise ConnectionError(f"field '{x.name}' needs an explicit port: use .port(i)",
                                  elements=[x.name])
        raise ConnectionError(f"cannot connect {x!r}: expected an element, a port or a name")

    def connect(self, a, b, name: str | None = None) -> Bond:
        """Make a power bond between ``a`` and ``b``.

        Parameters
        ----------
        a, b : Element, Port or str
            Elements, ports of two-ports/fields (``tf.p1``), or names
            (element names or exposed fragment ports).
        name : str, optional
            Bond name; default ``"<a> -> <b>"`` in power direction.

        Returns
        -------
        Bond

        Raises
        ------
        ConnectionError
            If a port is already bonded, a two-port is given without a
            port, both ends demand the same power direction (e.g. an I
            bonded directly to a C: connect them through a junction), or
            ``name`` is not a string (a third element: a bond has two ends).

        Notes
        -----
        The half-arrow follows the element convention (see
        :mod:`bondgraph.core.elements`), whatever the argument order. Between two
        junctions it points from ``a`` to ``b``: there the direction is a
        modelling choice (it sets the signs of the junction sums), so write
        ``connect(a, b)`` in the direction of positive power.
        """
        if name is not None and not isinstance(name, str):
            raise ConnectionError(
                f"connect({_label(a)}, {_label(b)}, {_label(name)}): the third argument is the "
                f"bond's name (a string), not a third end: a bond joins two. To chain "
                f"{_label(a)} -> {_label(b)} -> {_label(name)}, connect each pair (a two-port "
                f"by its ports: connect(a, tf.p1), connect(tf.p2, b))",
                elements=[_label(a), _label(b), _label(name)])
        pa = self._resolve(a)
        pb = self._resolve(b)
        for p in (pa, pb):
            if p.bond is not None:
                raise ConnectionError(
                    f"port {p.label} is already bonded ({p.bond.name}); a one-port or a "
                    f"two-port port takes one bond", elements=[p.element.name], bonds=[p.bond.name])
        if pa.element is pb.element:
            raise ConnectionError(f"bond from '{pa.element.name}' to itself",
                                  elements=[pa.element.name])
        ra, rb = pa.power_preference(), pb.power_preference()
        if ra is None and rb is None:
            tail, head = pa, pb
        elif ra is None:
            tail, head = (pb, pa) if rb == "out" else (pa, pb)
        elif rb is None:
            tail, head = (pa, pb) if ra == "out" else (pb, pa)
        elif ra == "out" and rb == "in":
            tail, head = pa, pb
        elif ra == "in" and rb == "out":
            tail, head = pb, pa
        else:
            for p in (pa, pb):
                if isinstance(p.element, Junction):
                    p.element.ports.remove(p)
            raise ConnectionError(
                f"cannot bond '{pa.label}' to '{pb.label}': both {'absorb' if ra == 'in' else 'deliver'} "
                f"power by convention; connect them through a 0- or 1-junction",
                elements=[pa.element.name, pb.element.name])
        bname = name or f"{tail.label} -> {head.label}"
        existing = {bd.name for bd in self.bonds}
        if bname in existing:
            k = 2
            while f"{bname} #{k}" in existing:
                k += 1
            bname = f"{bname} #{k}"
        bond = Bond(tail, head, bname)
        tail.bond = bond
        head.bond = bond
        self.bonds.append(bond)
        return bond

    def bond(self, name: str) -> Bond:
        for b in self.bonds:
            if b.name == name:
                return b
        raise GraphError(f"graph '{self.name}' has no bond '{name}'")

    def bonds_of(self, element: Element) -> list[Bond]:
        """Bonds attached to ``element``, sorted by bond name."""
        return sorted((p.bond for p in element.ports if p.bond is not None), key=lambda b: b.name)

    # ----------------------------------------------------------- fragments
    def expose(self, name: str, target) -> None:
        """Expose a junction, element or port as an external port of this
        graph used as a fragment."""
        if isinstance(target, Element) and not isinstance(target, (Junction, OnePort)):
            raise GraphError(f"fragment '{self.name}': expose a port of two-port "
                             f"'{target.name}' (.p1/.p2), not the element")
        self.exposed[name] = target

    def include(self, fragment: "BondGraph", prefix: str) -> Handle:
        """Copy a fragment into this graph under the namespace ``prefix``.

        Element, parameter, input, sensor and state names of the fragment
        become ``prefix.name``; symbols the fragment did not declare itself
        (e.g. parameters passed in from this graph) are kept as they are.

        Returns
        -------
        Handle
            ``handle.port(name)`` gives the targets of the exposed ports.
        """
        if not prefix or any(c.isspace() for c in prefix):
            raise InvalidNameError(f"invalid fragment prefix {prefix!r}")
        subs: dict = {}
        for p in fragment.params.values():
            new = p.with_name(f"{prefix}.{p.name}")
            subs[p] = new
            self.add_param(new)
        for u in fragment.inputs.values():
            new = u.with_name(f"{prefix}.{u.name}")
            subs[u] = new
            self._check_free_name(new.name, self.inputs, "input")
            self.inputs[new.name] = new
        new_elems: dict[str, Element] = {}
        for el in fragment.elements.values():
            nel = el.clone(f"{prefix}.{el.name}", {})
            for o, n in zip(el.owned_symbols(), nel.owned_symbols()):
                subs[o] = n
            if isinstance(el, Junction):
                subs[el.var] = nel.var
            new_elems[el.name] = nel
        for nm, ss in fragment.signal_states.items():
            z = ss.state
            nz = StateVar(f"{prefix}.{z.name}", z.state_kind, z.element, z.unit, z.initial, z.description)
            subs[z] = nz
        # bonds: recreate between the cloned ports (same direction)
        new_bonds = []
        for bd in fragment.bonds:
            t = self._map_port(bd.tail, new_elems)
            h = self._map_port(bd.head, new_elems)
            nb = Bond(t, h, f"{t.label} -> {h.label}")
            t.bond = nb
            h.bond = nb
            subs[bd.e] = nb.e
            subs[bd.f] = nb.f
            new_bonds.append(nb)
        for el in new_elems.values():
            el.substitute(subs)
            self.add(el)
        existing = {b.name for b in self.bonds}
        for nb in new_bonds:
            if nb.name in existing:
                raise DuplicateNameError(f"bond '{nb.name}' declared twice", bonds=[nb.name])
            self.bonds.append(nb)
        for nm, ss in fragment.signal_states.items():
            nz = subs[ss.state]
            self._check_free_name(nz.name, self.signal_states, "state")
            rhs = ss.rhs.xreplace(subs)
            self.signal_states[nz.name] = SignalState(nz, rhs, _xrep(ss.process_noise, subs))
        for nm, std in fragment.process_noise.items():
            self.process_noise[f"{prefix}.{nm}"] = _xrep(std, subs)
        for s in fragment.sensors.values():
            self.sensor(f"{prefix}.{s.name}", s.expr.xreplace(subs), unit=s.unit,
                        noise_std=_xrep(s.noise_std, subs), description=s.description)
        handle = Handle(self, prefix)
        for pname, target in fragment.exposed.items():
            handle.ports[pname] = self._map_target(target, new_elems)
        self.metadata.setdefault("fragments", []).append(prefix)
        return handle

    def _map_port(self, port: Port, new_elems: dict[str, Element]) -> Port:
        nel = new_elems[port.element.name]
        if isinstance(nel, Junction):
            while len(nel.ports) <= port.index:
                nel.new_port()
            return nel.ports[port.index]
        return nel.ports[port.index]

    def _map_target(self, target, new_elems):
        if isinstance(target, Port):
            nel = new_elems[target.element.name]
            if isinstance(nel, Junction):
                return nel
            return nel.ports[target.index]
        if isinstance(target, Element):
            return new_elems[target.name]
        raise GraphError(f"cannot expose {target!r}")

    def copy(self, name: str | None = None) -> "BondGraph":
        """Deep copy (for augmenting a user's graph without touching it)."""
        new = _copy.deepcopy(self)
        if name:
            new.name = name
        return new

    # ------------------------------------------------------------ queries
    def storage_elements(self) -> list[Element]:
        return [e for e in self.elements.values() if isinstance(e, (I, C, CField, IField))]

    def junctions(self) -> list[Junction]:
        return [e for e in self.elements.values() if isinstance(e, Junction)]

    def all_states(self) -> list[StateVar]:
        """Candidate states in declaration order: storages, then signal states
        (storages in derivative causality drop out during derivation)."""
        out: list[StateVar] = []
        for el in self.elements.values():
            out += el.states()
        out += [ss.state for ss in self.signal_states.values()]
        return out

    def declared_symbols(self) -> set:
        syms: set = set(self.params.values()) | set(self.inputs.values())
        for el in self.elements.values():
            syms |= set(el.owned_symbols())
            for p in el.ports:
                syms |= {p.e, p.f}
        for b in self.bonds:
            syms |= {b.e, b.f}
        syms |= {ss.state for ss in self.signal_states.values()}
        return syms

    # ----------------------------------------------------------- validate
    def validate(self) -> None:
        """Check the declaration; raise the first problem found.

        Raises
        ------
        DanglingPortError
            A one-port element or field port without a bond.
        PortCountError
            A two-port (TF, GY, MTF, MGY) without a bond on each of its ports,
            or a constant TF/GY whose modulus varies (use MTF/MGY).
        JunctionError
            A junction with fewer than two bonds.
        UndeclaredSymbolError
            An expression using a symbol the graph does not declare.
        UnitMismatchError
            Effort x flow is not power on a bond, ends of a bond disagree, or
            a linear element's parameter has the wrong unit.
        """
        if not self.elements:
            raise GraphError(f"graph '{self.name}' has no elements")
        for el in self._sorted_elements():
            if isinstance(el, Junction):
                n = sum(1 for p in el.ports if p.bond is not None)
                if n < 2:
                    raise JunctionError(
                        f"{el.kind}-junction '{el.name}' has {n} bond{'s' if n != 1 else ''}; "
                        f"a junction needs at least two", elements=[el.name],
                        bonds=[p.bond.name for p in el.ports if p.bond is not None],
                        hint="connect it or remove it")
            elif isinstance(el, TwoPort):
                missing = [f"p{p.index + 1}" for p in el.ports if p.bond is None]
                if missing:
                    raise PortCountError(
                        f"{el.kind} '{el.name}' needs one bond on each of its two ports; "
                        f"port {' and '.join(missing)} is unconnected", elements=[el.name])
            else:
                for p in el.ports:
                    if p.bond is None:
                        raise DanglingPortError(
                            f"{el.kind} '{el.name}': port {p.label} has no bond",
                            elements=[el.name], hint="connect it to a junction")
        self._check_symbols()
        self._check_constant_moduli()
        self._check_units()

    def _sorted_elements(self) -> list[Element]:
        return [self.elements[k] for k in sorted(self.elements)]

    def _check_constant_moduli(self) -> None:
        for el in self._sorted_elements():
            if isinstance(el, TwoPort) and not el.modulated:
                bad = sorted(s.name for s in el.modulus.free_symbols if not isinstance(s, Parameter))
                if bad:
                    raise PortCountError(
                        f"{el.kind} '{el.name}': modulus depends on {join_names(bad)}, which vary; "
                        f"a varying modulus needs M{el.kind}", elements=[el.name],
                        hint=f"declare it with g.M{el.kind}(...)")

    def _expression_owners(self) -> list[tuple[str, str, sp.Expr]]:
        out = []
        for el in self._sorted_elements():
            for ex in el.expressions():
                out.append((f"{el.kind} '{el.name}'", el.name, ex))
        for s in self.sensors.values():
            out.append((f"sensor '{s.name}'", s.name, s.expr))
            if isinstance(s.noise_std, sp.Basic):
                out.append((f"noise of sensor '{s.name}'", s.name, s.noise_std))
        for nm, ss in self.signal_states.items():
            out.append((f"state '{nm}'", nm, ss.rhs))
        for nm, std in self.process_noise.items():
            if isinstance(std, sp.Basic):
                out.append((f"process noise of '{nm}'", nm, std))
        return out

    def _check_symbols(self) -> None:
        declared = self.declared_symbols()
        for what, owner, ex in self._expression_owners():
            for s in sorted(ex.free_symbols, key=lambda s: s.name):
                if s not in declared:
                    kind = type(s).__name__
                    raise UndeclaredSymbolError(
                        f"{what} uses symbol '{s.name}' ({kind}) that graph '{self.name}' does not "
                        f"declare", elements=[owner],
                        hint="declare it with g.param()/g.input(), or pass the parent graph's "
                             "symbol into the fragment (h.param(...))")
        state_names = {s.name for s in self.all_states()}
        for nm in self.process_noise:
            if nm not in state_names:
                raise UndeclaredSymbolError(f"process noise given for unknown state '{nm}'",
                                            elements=[nm])

    # --- units
    def bond_units(self) -> dict[str, tuple[str | None, str | None]]:
        """Effort and flow units of every bond, propagated through junctions.

        Returns
        -------
        dict
            bond name -> (effort unit or None, flow unit or None).

        Raises
        ------
        UnitMismatchError
            If two declarations meet on one bond with different dimensions.
        """
        import networkx as nx

        # bonds sharing units: all bonds of a junction; a one-port with units
        G = nx.Graph()
        for b in self.bonds:
            G.add_node(b.name)
        for el in self._sorted_elements():
            if isinstance(el, Junction):
                bs = self.bonds_of(el)
                for x, y in zip(bs, bs[1:]):
                    G.add_edge(x.name, y.name)
        decl: dict[str, list[tuple[str, str, str]]] = {}  # bond -> [(kind, unit, who)]
        for el in self._sorted_elements():
            if el.effort_unit is None and el.flow_unit is None:
                continue
            for bd in self.bonds_of(el):
                if isinstance(el, TwoPort):
                    continue
                if el.effort_unit:
                    decl.setdefault(bd.name, []).append(("effort", el.effort_unit, el.name))
                if el.flow_unit:
                    decl.setdefault(bd.name, []).append(("flow", el.flow_unit, el.name))
        result: dict[str, tuple[str | None, str | None]] = {b.name: (None, None) for b in self.bonds}
        for comp in nx.connected_components(G):
            comp = sorted(comp)
            eu = fu = None
            ewho = fwho = None
            for bn in comp:
                for kind, unit, who in decl.get(bn, []):
                    if kind == "effort":
                        if eu is None:
                            eu, ewho = unit, who
                        elif not _units.same_dimension(eu, unit):
                            raise UnitMismatchError(
                                f"bond '{bn}': effort unit '{unit}' from '{who}' does not match "
                                f"'{eu}' from '{ewho}'", elements=[who, ewho], bonds=[bn])
                    else:
                        if fu is None:
                            fu, fwho = unit, who
                        elif not _units.same_dimension(fu, unit):
                            raise UnitMismatchError(
                                f"bond '{bn}': flow unit '{unit}' from '{who}' does not match "
                                f"'{fu}' from '{fwho}'", elements=[who, fwho], bonds=[bn])
            for bn in comp:
                result[bn] = (eu, fu)
        return result

    def _check_units(self) -> None:
        bu = self.bond_units()
        for b in self.bonds:
            eu, fu = bu[b.name]
            if eu is not None and fu is not None and not _units.is_power(eu, fu) \
                    and not _units.is_pseudo_power(eu, fu):
                raise UnitMismatchError(
                    f"bond '{b.name}': effort [{eu}] x flow [{fu}] is not a power [W]",
                    elements=[b.tail.element.name, b.head.element.name], bonds=[b.name],
                    hint="check the domain or units declared on the junctions at both ends")
        # linear elements: parameter units against bond units
        for el in self._sorted_elements():
            bonds = self.bonds_of(el)
            if not bonds or not isinstance(el, (I, C, R, Source)):
                continue
            eu, fu = bu[bonds[0].name]
            if eu is None or fu is None:
                continue
            if isinstance(el, I) and el.inertance is not None:
                want = _units.quotient(_units.product(eu, "s"), fu)
                self._check_expr_unit(el, el.inertance, want, "inertance")
            elif isinstance(el, C) and el.compliance is not None:
                want = _units.quotient(_units.product(fu, "s"), eu)
                self._check_expr_unit(el, el.compliance, want, "compliance")
            elif isinstance(el, C) and el.stiffness is not None:
                want = _units.quotient(eu, _units.product(fu, "s"))
                self._check_expr_unit(el, el.stiffness, want, "stiffness")
            elif isinstance(el, R) and el.resistance is not None:
                self._check_expr_unit(el, el.resistance, _units.quotient(eu, fu), "resistance")
            elif isinstance(el, Source):
                self._check_expr_unit(el, el.value, eu if el.variable == "effort" else fu,
                                      el.variable)
        for el in self._sorted_elements():
            if isinstance(el, TwoPort):
                self._check_modulus_unit(el, bu)
        for sn in sorted(self.sensors):
            self._check_sensor_unit(self.sensors[sn], bu)

    def _var_unit(self, var: Var, bu: dict) -> str | None:
        """The unit of a port or junction variable: its bond's effort or
        flow unit (a junction's common variable: any of its bonds'); None
        for a two-port's or where no unit is known."""
        owner = self.elements.get(var.owner)
        if owner is None or (not isinstance(owner, Junction) and len(owner.ports) != 1):
            return None
        for p in owner.ports:
            if p.bond is not None:
                eu, fu = bu.get(p.bond.name, (None, None))
                return eu if var.var_kind == "effort" else fu
        return None

    def _check_sensor_unit(self, sensor, bu: dict) -> None:
        """A sensor's declared unit against the dimension of its expression
        (port variables in their bonds' units): a velocity declared in N was
        accepted, and a record's column in N then bound to it."""
        if not sensor.unit:
            return
        # each symbol by name with this graph's own declaration of its unit:
        # sympy takes equal-named symbols for one, and an expression may hold
        # the object of another graph (its unit with it)
        units = {p.name: p.unit for p in self.params.values()}
        units.update({u.name: u.unit for u in self.inputs.values()})
        units.update({z.name: z.unit for z in self.all_states()})
        subs = {}
        for v in sensor.expr.free_symbols:
            u = self._var_unit(v, bu) if isinstance(v, Var) else units.get(v.name)
            if not u:
                return          # a unit unknown: not judged
            subs[v] = Input(f"{v.name}__unit", u)
        try:
            have = expr_unit(sensor.expr.xreplace(subs))
        except UnitMismatchError:
            return              # a sum of mixed dimensions: the expression checks say so
        if have is None or have == _units.dimensionality(sensor.unit):
            return
        raise UnitMismatchError(
            f"sensor '{sensor.name}': its expression {sensor.expr} has dimension {have}, but "
            f"it is declared in [{sensor.unit}] = {_units.dimensionality(sensor.unit)}",
            elements=[sensor.name],
            hint="declare the unit of what the expression reads (a flow on a translation "
                 "junction is in m/s), or scale the expression to the declared unit")

    def _check_modulus_unit(self, el: TwoPort, bu: dict) -> None:
        """The dimension of a two-port's modulus against the bonds at its
        ports: a TF's m = e1/e2 (= f2/f1), a GY's r = e1/f2 (= e2/f1)
        (Karnopp, Margolis & Rosenberg, ch. 2). A TF whose modulus is the
        inverse of what its bonds need (a piston area A declared with the
        hydraulic side on p1, where e1 = m e2 needs 1/A) is the common slip:
        the message says to invert the modulus, or to swap the ports (which
        reverses the positive direction of the flow through it). Skipped
        where a unit is unknown (a symbol without unit, a bond whose units
        no junction or element declares)."""
        if any(p.bond is None for p in el.ports):
            return
        (e1, f1), (e2, f2) = (bu[p.bond.name] for p in el.ports)
        is_tf = isinstance(el, TF)
        num, den = (e1, e2) if is_tf else (e1, f2)
        if num is None or den is None:
            return
        try:
            have = expr_unit(el.modulus)
        except UnitMismatchError:
            return              # a sum of mixed dimensions: said by the expression checks
        if have is None:
            return
        want = _units.quotient(num, den)
        if have == _units.dimensionality(want):
            return
        law = "e1 = m·e2, f2 = m·f1" if is_tf else "e1 = r·f2, e2 = r·f1"

        def side(p) -> str:
            e, f = bu[p.bond.name]
            return f"{p.label} on '{_other_end(p)}' ({e}, {f})"

        inverse = have == _units.dimensionality(_units.quotient(den, num))
        if inverse and is_tf:
            hint = (f"the modulus is the inverse of what these bonds need: declare it as "
                    f"1/({el.modulus}) (the power direction kept), or connect p1 to "
                    f"'{_other_end(el.p2)}' and p2 to '{_other_end(el.p1)}' (e1 = m·e2 then "
                    f"reads from that side, and the bonds' power direction, hence the sign "
                    f"of the flow through the two-port, is reversed)")
        elif inverse:
            hint = f"the modulus is the inverse of what these bonds need: 1/({el.modulus})"
        else:
            hint = "check the modulus' parameter units and the domains at both ports"
        raise UnitMismatchError(
            f"{el.kind} '{el.name}': modulus {el.modulus} has dimension {have}, but {law} "
            f"between {side(el.p1)} and {side(el.p2)} needs [{want}] = "
            f"{_units.dimensionality(want)}", elements=[el.name],
            bonds=[p.bond.name for p in el.ports], hint=hint)

    def _check_expr_unit(self, el: Element, expr: sp.Expr, want: str, what: str) -> None:
        have = expr_unit(expr)
        if have is None:
            return
        if have != _units.dimensionality(want):
            bonds = [b.name for b in self.bonds_of(el)]
            raise UnitMismatchError(
                f"{el.kind} '{el.name}': {what} has dimension {have}, the bond needs "
                f"[{want}] = {_units.dimensionality(want)}", elements=[el.name], bonds=bonds,
                hint=_thermal_hint(self, el, have))

    def __repr__(self) -> str:
        return (f"<BondGraph {self.name}: {len(self.elements)} elements, {len(self.bonds)} bonds, "
                f"{len(self.params)} parameters>")


def _thermal_hint(graph: BondGraph, el: Element, have) -> str | None:
    """The hint of a unit mismatch on a true thermal bond (temperature and
    entropy flow) whose element is written for the pseudo bond graph
    (temperature and heat flow: a heat capacity in J/K, a thermal
    resistance in K/W), else None."""
    bu = graph.bond_units()
    units = [bu.get(b.name, (None, None)) for b in graph.bonds_of(el)]
    if not any(e and f and _units.same_dimension(e, "K") and _units.same_dimension(f, "W/K")
               for e, f in units):
        return None
    pseudo = {"J/K", "K/W", "W/K", "K*s/W", "W*s/K", "W"}    # "W": a heat flow (a heater)
    if not any(have == _units.dimensionality(u) for u in pseudo):
        return None
    return ("the junctions' domain 'thermal' is the true bond graph (temperature and entropy "
            "flow in W/K); for temperature and heat flow in W (a heat capacity in J/K, a "
            "thermal resistance in K/W) declare domain='heat', the pseudo bond graph")


def _other_end(port: Port) -> str:
    """Name of the element at the other end of ``port``'s bond."""
    b = port.bond
    return b.other(port).element.name


#: A fragment is a bond graph with exposed ports, included by a parent graph.
Fragment = BondGraph


def _label(x) -> str:
    """How an argument of :meth:`BondGraph.connect` reads in a message: a
    port's label, an element's name, a string as given, else its repr."""
    for attr in ("label", "name"):
        v = getattr(x, attr, None)
        if isinstance(v, str):
            return v
    return x if isinstance(x, str) else repr(x)


def _xrep(v, subs):
    if isinstance(v, sp.Basic):
        return v.xreplace(subs)
    return v


def expr_unit(expr: sp.Expr, _factor: bool = False):
    """Dimension (pint dimensionality) of ``expr`` from its symbols' units, or
    None when unknown (a symbol without unit, or a bare number: numbers are
    dimensionless only as factors). Raises UnitMismatchError when a sum adds
    different dimensions."""
    if expr.is_Number or expr in (sp.pi, sp.E):
        return _units.dimensionality("1") if _factor else None
    if isinstance(expr, sp.Symbol):
        u = getattr(expr, "unit", None)
        if not u:
            return None  # no unit declared: unknown, not dimensionless
        return _units.dimensionality(u)
    if expr.is_Add:
        dims = [expr_unit(a) for a in expr.args if not a.is_Number]
        known = [d for d in dims if d is not None]
        if len(known) < len(dims):
            return None
        for d in known[1:]:
            if d != known[0]:
                raise UnitMismatchError(f"sum of different dimensions in '{expr}': {known[0]} and {d}")
        return known[0]
    if expr.is_Mul:
        out = _units.parse("1")
        for a in expr.args:
            d = expr_unit(a, _factor=True)
            if d is None:
                return None
            out = out * _dim_quantity(d)
        return out.dimensionality
    if expr.is_Pow:
        base, ex = expr.args
        d = expr_unit(base, _factor=True)
        if d is None:
            return None
        if ex.is_Number:
            return (_dim_quantity(d) ** float(ex)).dimensionality
        return _units.dimensionality("1")
    # functions: arguments must be dimensionless where known
    return _units.dimensionality("1")


def _dim_quantity(dim):
    ureg = _units.registry()
    q = ureg.Quantity(1.0, "dimensionless")
    base = {"[mass]": "kg", "[length]": "m", "[time]": "s", "[current]": "A",
            "[temperature]": "K", "[substance]": "mol", "[luminosity]": "cd"}
    for k, v in dim.items():
        q = q * ureg.Quantity(1.0, base.get(k, "dimensionless")) ** v
    return q
