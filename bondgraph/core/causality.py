"""Causality assignment by the Sequential Causality Assignment Procedure (SCAP).

Karnopp, Margolis & Rosenberg, *System Dynamics* (5th ed., ch. 5): assign a
source, propagate through junctions and two-ports; repeat for every source;
then assign integral causality to one storage element at a time, each time
propagating; then give the remaining R elements the causality of their law
(propagating after each); finally pick any still-open junction bond. Storages
that propagation forces into derivative causality, and R assignments that
were arbitrary, are recorded: the equation step eliminates the former and
solves the algebraic loops the latter may close.

The result is a *causal stroke* per bond: the end at which effort enters
(the element at the stroke end receives effort and returns flow).

Processing is in sorted name order, so the result does not depend on the
order in which the graph was declared.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from bondgraph.core.elements import (
    GY,
    C,
    CField,
    Element,
    I,
    IField,
    Junction,
    R,
    RField,
    Se,
    Source,
    TwoPort,
    Zero,
)
from bondgraph.core.graph import Bond, BondGraph
from bondgraph.errors import CausalConflictError, join_names


#: the inert signal state a graph without a state of its own is given by
#: :func:`bondgraph.numerics.registry.with_a_state` (named in
#: :meth:`Causality.derivative_notes`)
STATIC_STATE = "static_hold"


@dataclass
class Causality:
    """Result of SCAP.

    Attributes
    ----------
    graph : BondGraph
    stroke : dict
        bond name -> name of the element at the stroke end (it receives effort).
    derivative : list of str
        Storage elements left in derivative causality (eliminated later).
    arbitrary : list of str
        R elements (or bonds, ``bond:<name>``) whose causality SCAP chose
        freely; algebraic loops, if any, pass through them.
    order : list of (str, str)
        (element, step) in the order SCAP assigned them; step is "source",
        "storage", "derivative", "resistor" or "free bond".
    imposed : dict
        Storage in derivative causality -> the elements on the causal path
        that imposed its conjugate variable, origin first (itself left out).
    """

    graph: BondGraph
    stroke: dict[str, str]
    derivative: list[str] = field(default_factory=list)
    arbitrary: list[str] = field(default_factory=list)
    order: list[tuple[str, str]] = field(default_factory=list)
    imposed: dict[str, list[str]] = field(default_factory=dict)

    def derivative_notes(self) -> list[str]:
        """One line per storage in derivative causality: what imposes its
        effort (C) or flow (I), and that it adds no state. A storage in
        derivative causality is a rigid tie, intended (a gear's two
        inertias) or a sign that something is missing between it and what
        imposes it (20-sim warns of it likewise): two DC
        motors declared without rotor inertia or damping drive a belt
        compliance with the torque k_m·i of the armature current, which
        fixes the belt's deflection, and a belt drive of three storages has
        two states (Karnopp, Margolis & Rosenberg, ch. 5: derivative
        causality and its physical meaning)."""
        out = []
        n_st = sum(len(e.ports) if isinstance(e, (CField, IField)) else 1
                   for e in self.graph.elements.values() if isinstance(e, (I, C, CField, IField)))
        n_int = n_st - len(self.derivative)
        for name in self.derivative:
            el = self.graph.elements[name]
            what = "flow" if isinstance(el, (I, IField)) else "effort"
            path = [self.graph.elements[e] for e in self.imposed.get(name, [])]
            src = [e for e in path if isinstance(e, (Source, I, C, CField, IField, R, RField))]
            via = [e for e in path if e not in src and isinstance(e, TwoPort)]
            by = " and ".join(f"{e.kind} '{e.name}'" for e in src) or "the graph"
            thru = (" through " + ", ".join(f"{e.kind} '{e.name}'" for e in via)) if via else ""
            out.append(f"{el.kind} '{name}' is in derivative causality: its {what} is imposed by "
                       f"{by}{thru}, so it adds no state ({n_int} of {n_st} storages are "
                       f"states); it is tied rigidly to them, and an inertia, compliance or "
                       f"resistance between them would give it a state of its own")
        if n_int == 0 and STATIC_STATE in self.graph.signal_states:
            out.append(f"no storage is a state: the outputs are algebraic functions of the "
                       f"inputs (a static model); '{STATIC_STATE}' is an inert state added for "
                       f"the filter and the free runs, which need one (it changes no output)")
        return out

    def receives_effort(self, bond: Bond, element: Element) -> bool:
        """True if ``element`` (an end of ``bond``) has the causal stroke,
        i.e. receives effort on this bond and returns flow."""
        return self.stroke[bond.name] == element.name

    def stroke_end(self, bond: Bond | str):
        """The Port at the stroke end of a bond."""
        if isinstance(bond, str):
            bond = self.graph.bond(bond)
        return bond.head if self.stroke[bond.name] == bond.head.element.name else bond.tail

    def is_integral(self, element: Element | str) -> bool:
        name = element if isinstance(element, str) else element.name
        return name not in self.derivative

    def table(self) -> str:
        """Human-readable table: bond, power direction, stroke end."""
        rows = [f"{'bond':<48} stroke at"]
        for b in sorted(self.graph.bonds, key=lambda b: b.name):
            rows.append(f"{b.name:<48} {self.stroke[b.name]}")
        if self.derivative:
            rows.append("derivative causality: " + ", ".join(self.derivative))
        if self.arbitrary:
            rows.append("arbitrary (possible algebraic loops): " + ", ".join(self.arbitrary))
        return "\n".join(rows)


class _Scap:
    """Propagation engine. ``recv[bond]`` is the element name at the stroke end."""

    def __init__(self, g: BondGraph):
        self.g = g
        self.recv: dict[str, str] = {}
        self.why: dict[str, tuple[str, list[str]]] = {}  # bond -> (element, [trigger bonds])
        self.bonds = {b.name: b for b in g.bonds}
        self.of: dict[str, list[Bond]] = {n: g.bonds_of(el) for n, el in g.elements.items()}
        self.order: list[tuple[str, str]] = []

    # ------------------------------------------------------------ helpers
    def _other(self, b: Bond, el: Element) -> Element:
        return b.head.element if b.tail.element is el else b.tail.element

    def _set(self, b: Bond, receiver: Element, cause: Element, triggers: list[str]) -> None:
        cur = self.recv.get(b.name)
        if cur is not None:
            if cur != receiver.name:
                self._conflict_on_bond(b, receiver, cause, triggers)
            return
        self.recv[b.name] = receiver.name
        self.why[b.name] = (cause.name, triggers)
        self._queue.extend([b.head.element, b.tail.element])

    def _path(self, bond_name: str, seen=None) -> tuple[list[str], list[str]]:
        """Elements and bonds on the causal path that fixed ``bond_name``,
        origin first."""
        seen = seen or set()
        if bond_name in seen or bond_name not in self.why:
            return [], []
        seen.add(bond_name)
        cause, triggers = self.why[bond_name]
        els: list[str] = []
        bds: list[str] = []
        for t in triggers:
            e2, b2 = self._path(t, seen)
            els += [e for e in e2 if e not in els]
            bds += [x for x in b2 if x not in bds]
        if cause not in els:
            els.append(cause)
        bds.append(bond_name)
        return els, bds

    def _origins(self, bond_name: str) -> list[str]:
        els, _ = self._path(bond_name)
        return [e for e in els if isinstance(self.g.elements[e], (Source, I, C, CField, IField, R,
                                                                    RField))]

    def _conflict_on_bond(self, b: Bond, receiver: Element, cause: Element, triggers: list[str]):
        els1, bds1 = self._path(b.name)
        els2: list[str] = []
        bds2: list[str] = []
        for t in triggers:
            e, bb = self._path(t)
            els2 += e
            bds2 += bb
        els = list(dict.fromkeys(els1 + els2 + [cause.name]))
        bds = list(dict.fromkeys(bds1 + bds2 + [b.name]))
        raise self._make_error(els, bds, f"bond '{b.name}' would need its causal stroke at both "
                                         f"ends")

    def _make_error(self, els: list[str], bds: list[str], what: str) -> CausalConflictError:
        kinds = {e: self.g.elements[e].kind for e in els}
        srcs = [e for e in els if kinds[e] in ("Se", "MSe", "Sf", "MSf")]
        es = [e for e in srcs if kinds[e] in ("Se", "MSe")]
        fs = [e for e in srcs if kinds[e] in ("Sf", "MSf")]
        if len(es) >= 2:
            hint = (f"two effort sources ({join_names(es)}) set one effort: add a compliance "
                    f"(C) or resistance (R) between them via a 1-junction, or merge them into one "
                    f"source")
        elif len(fs) >= 2:
            hint = (f"two flow sources ({join_names(fs)}) set one flow: add an inertia (I) or "
                    f"resistance (R) between them via a 0-junction, or merge them into one source")
        elif srcs:
            hint = (f"source {join_names(srcs)} is forced into the wrong causality: change it to "
                    f"the other source type, or add a compliance / inertia so the junction "
                    f"structure can accept it")
        else:
            hint = "add a compliance (C) or an inertia (I) to break the rigid constraint"
        path = " -> ".join(f"{kinds[e]}:{e}" for e in els)
        return CausalConflictError(
            f"causal conflict: {what}. Causal path: {path}; bonds: "
            f"{', '.join(repr(b) for b in bds)}", elements=els, bonds=bds, hint=hint)

    # --------------------------------------------------------- propagation
    def propagate(self) -> None:
        while self._queue:
            el = self._queue.pop()
            if isinstance(el, Junction):
                self._junction(el)
            elif isinstance(el, TwoPort):
                self._twoport(el)

    def _junction(self, j: Junction) -> None:
        bonds = self.of[j.name]
        # "strong" bond: for a 0-junction the one bringing effort in (stroke at the
        # junction), for a 1-junction the one bringing flow in (stroke away).
        def strong(b):
            r = self.recv.get(b.name)
            if r is None:
                return None
            at_j = (r == j.name)
            return at_j if isinstance(j, Zero) else (not at_j)

        states = [(b, strong(b)) for b in bonds]
        strongs = [b for b, s in states if s is True]
        unknown = [b for b, s in states if s is None]
        if len(strongs) > 1:
            els: list[str] = []
            bds: list[str] = []
            for b in strongs:
                e, bb = self._path(b.name)
                els += e
                bds += bb
            var = "effort" if isinstance(j, Zero) else "flow"
            raise self._make_error(list(dict.fromkeys(els + [j.name])), list(dict.fromkeys(bds)),
                                   f"{j.kind}-junction '{j.name}' gets its {var} from more than "
                                   f"one bond ({', '.join(repr(b.name) for b in strongs)})")
        if len(strongs) == 1:
            for b in unknown:
                other = self._other(b, j)
                # weak bond: 0-junction gives effort out (stroke at the other end);
                # 1-junction receives effort (stroke at the junction)
                recv = other if isinstance(j, Zero) else j
                self._set(b, recv, j, [strongs[0].name])
        elif len(unknown) == 1:
            b = unknown[0]
            other = self._other(b, j)
            recv = j if isinstance(j, Zero) else other
            self._set(b, recv, j, [x.name for x in bonds if x is not b])
        elif not unknown:
            els: list[str] = []
            bds: list[str] = []
            for b in bonds:
                e, bb = self._path(b.name)
                els += e
                bds += bb
            var = "effort" if isinstance(j, Zero) else "flow"
            raise self._make_error(list(dict.fromkeys(els + [j.name])), list(dict.fromkeys(bds)),
                                   f"no bond sets the {var} of {j.kind}-junction '{j.name}'")

    def _twoport(self, tp: TwoPort) -> None:
        b1, b2 = tp.p1.bond, tp.p2.bond
        r1, r2 = self.recv.get(b1.name), self.recv.get(b2.name)
        at1 = None if r1 is None else (r1 == tp.name)
        at2 = None if r2 is None else (r2 == tp.name)
        gy = isinstance(tp, GY)
        # TF: strokes "in line": exactly one of the two ports receives effort.
        # GY: both receive effort, or neither.
        if at1 is not None and at2 is None:
            want = at1 if gy else (not at1)
            self._set(b2, tp if want else self._other(b2, tp), tp, [b1.name])
        elif at2 is not None and at1 is None:
            want = at2 if gy else (not at2)
            self._set(b1, tp if want else self._other(b1, tp), tp, [b2.name])
        elif at1 is not None and at2 is not None:
            ok = (at1 == at2) if gy else (at1 != at2)
            if not ok:
                els, bds = self._path(b1.name)
                e2, bd2 = self._path(b2.name)
                raise self._make_error(list(dict.fromkeys(els + e2 + [tp.name])),
                                       list(dict.fromkeys(bds + bd2)),
                                       f"{tp.kind} '{tp.name}' receives inconsistent causality "
                                       f"on its two ports")

    # ---------------------------------------------------------- procedure
    def run(self) -> Causality:
        g = self.g
        self._queue: list[Element] = []
        names = sorted(g.elements)
        derivative: list[str] = []
        arbitrary: list[str] = []
        derivative_set: set[str] = set()   # membership tests in constant time
        arbitrary_set: set[str] = set()
        # 1. sources
        for n in names:
            el = g.elements[n]
            if isinstance(el, Source):
                b = el.port.bond
                cur = self.recv.get(b.name)
                want = self._other(b, el) if isinstance(el, Se) else el
                if cur is not None and cur != want.name:
                    e1, b1 = self._path(b.name)
                    raise self._make_error(list(dict.fromkeys(e1 + [el.name])), b1,
                                           f"source '{el.name}' is forced into "
                                           f"{'flow' if isinstance(el, Se) else 'effort'}-out "
                                           f"causality on bond '{b.name}'")
                self._set(b, want, el, [])
                self.order.append((n, "source"))
                self.propagate()
        # 2. storages, integral causality preferred, one at a time
        storages = [g.elements[n] for n in names
                    if isinstance(g.elements[n], (I, C, CField, IField))]
        storages.sort(key=lambda e: (getattr(e, "priority", 0), e.name))
        for el in storages:
            for p in el.ports:
                b = p.bond
                integral_recv = el if isinstance(el, (I, IField)) else self._other(b, el)
                if b.name not in self.recv:
                    self._set(b, integral_recv, el, [])
                    self.propagate()
                    self.order.append((el.name, "storage"))
                elif self.recv[b.name] != integral_recv.name:
                    if el.name not in derivative_set:
                        derivative.append(el.name)
                        derivative_set.add(el.name)
                        self.order.append((el.name, "derivative"))
        # 3. resistors: the causality of their law
        for n in names:
            el = g.elements[n]
            if isinstance(el, (R, RField)):
                for p in el.ports:
                    b = p.bond
                    if b.name in self.recv:
                        continue
                    if isinstance(el, R) and el.form == "flow":
                        recv = el  # conductance form: effort in, flow out
                    else:
                        recv = self._other(b, el)  # resistance form: flow in, effort out
                    self._set(b, recv, el, [])
                    self.propagate()
                    if el.name not in arbitrary_set:
                        arbitrary.append(el.name)
                        arbitrary_set.add(el.name)
                    self.order.append((el.name, "resistor"))
        # 4. bonds still open (loops of junctions / two-ports only)
        for b in sorted(g.bonds, key=lambda b: b.name):
            if b.name not in self.recv:
                self._set(b, b.head.element, b.head.element, [])
                self.propagate()
                arbitrary.append(f"bond:{b.name}")
                self.order.append((b.name, "free bond"))
        # derivative causality can also arise for storages after step 2 propagation
        for el in storages:
            for p in el.ports:
                b = p.bond
                integral_recv = el if isinstance(el, (I, IField)) else self._other(b, el)
                if self.recv[b.name] != integral_recv.name and el.name not in derivative_set:
                    derivative.append(el.name)
                    derivative_set.add(el.name)
        return Causality(g, dict(self.recv), derivative, arbitrary, self.order,
                         {n: self._imposing(n) for n in derivative})

    def _imposing(self, name: str) -> list[str]:
        """The elements on the causal paths that fixed the bonds of storage
        ``name`` (in derivative causality), origin first, itself left out."""
        els: list[str] = []
        for p in self.g.elements[name].ports:
            els += [e for e in self._path(p.bond.name)[0] if e != name and e not in els]
        return els


def assign_causality(graph: BondGraph, *, validate: bool = True) -> Causality:
    """Assign causality to every bond of ``graph`` by SCAP.

    Parameters
    ----------
    graph : BondGraph
    validate : bool
        Run ``graph.validate()`` first.

    Returns
    -------
    Causality
        Causal stroke per bond, storages in derivative causality, arbitrary
        R assignments.

    Raises
    ------
    CausalConflictError
        Two effort sources on one 0-junction, two flow sources on one
        1-junction, or a source forced into the wrong causality. The message
        names the elements and bonds of the causal path and suggests a remedy.

    References
    ----------
    Karnopp, Margolis & Rosenberg, *System Dynamics*, 5th ed., Wiley 2012, §5.2.
    """
    if validate:
        graph.validate()
    return _Scap(graph).run()
