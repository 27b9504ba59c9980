"""Effects of a rigid coupling between two inertias (a transmission bond
between a two-port and a 1-junction): belt or clutch slip, an added
compliance. Each frees the coupling, so that both inertias keep their
state."""

from __future__ import annotations

import math

import sympy as sp

from bondgraph.core.elements import GY, I, Junction, One, TwoPort
from bondgraph.core.graph import Bond, BondGraph
from bondgraph.core.symbols import Parameter
from bondgraph.diagnose.effects.base import (
    EffectParam,
    Target,
    _new_param,
    _Structural,
    _unit,
    junction_units,
    mechanical,
    split_bond,
)


def _transmission_bonds(graph: BondGraph) -> list[Target]:
    """Bonds between a two-port port and a 1-junction, or between two
    1-junctions: where a rigid coupling can slip or twist."""
    out = []
    for b in sorted(graph.bonds, key=lambda b: b.name):
        a, c = b.tail.element, b.head.element
        if isinstance(a, TwoPort) and isinstance(c, One) or isinstance(c, TwoPort) and isinstance(a, One):
            tp = a if isinstance(a, TwoPort) else c
            if isinstance(tp, GY):
                continue
            j = c if isinstance(c, One) else a
            _, fu = junction_units(graph, j)
            if mechanical(fu) is False:
                continue
            # only where the junction carries an inertia: a coupling to a
            # massless junction (a sheave set by a damper) has nothing to twist
            # against, and a slip there closes an algebraic loop of two laws
            if _inertance_near(graph, b) is None:
                continue
            out.append(Target("bond", b.name))
    return out


def _inertance_near(graph: BondGraph, bond: Bond):
    """Inertance expression of an inertia on a junction at either end of the
    bond (the largest by default value), or None."""
    best, best_val = None, -1.0
    for p in (bond.tail, bond.head):
        el = p.element
        if not isinstance(el, Junction):
            continue
        for q in el.ports:
            if q.bond is None:
                continue
            o = q.bond.other(q).element
            if isinstance(o, I) and o.inertance is not None:
                try:
                    v = float(o.inertance.subs({s: s.default for s in o.inertance.free_symbols
                                                if isinstance(s, Parameter)}))
                except (TypeError, ValueError):
                    continue
                if v > best_val:
                    best, best_val = o.inertance, v
    return best


def _inertia_near(graph: BondGraph, bond: Bond) -> float:
    """Default value of :func:`_inertance_near` (1.0 if none), for scaling boxes."""
    J = _inertance_near(graph, bond)
    if J is None:
        return 1.0
    return float(J.subs({s: s.default for s in J.free_symbols if isinstance(s, Parameter)}))


def _side_inertia(graph: BondGraph, z: Junction, J, fraction: float, tag: str) -> None:
    """Give the two-port side of a coupling cut at 0-junction ``z`` a small
    inertia (``fraction`` x J): the sheave, belt or hub that the cut separates.
    Without it two resistive laws in series form an algebraic loop."""
    if J is None:
        return
    for b in graph.bonds_of(z):
        other = b.head if b.tail.element is z else b.tail
        if isinstance(other.element, TwoPort):
            tp = other.element
            # the two-port's far side: if an inertia sits there, it moves with
            # this side through the transformer and no extra inertia is needed
            far = tp.p1 if other is tp.p2 else tp.p2
            fj = far.bond.other(far).element if far.bond is not None else None
            if isinstance(fj, Junction) and any(
                    isinstance(q.bond.other(q).element, I) for q in fj.ports if q.bond is not None):
                return
            side = split_bond(graph, b, "1", f"{tag}.side")
            graph.connect(side, graph.I(f"{tag}.J", fraction * J, priority=-1))
            return


class Slip(_Structural):
    """Belt or clutch slip: the rigid coupling of a transmission bond becomes
    a slip law T = c_s·Δω (creep: torque proportional to the slip speed);
    the two sides get their own speeds. The side cut off from the two-port
    gets a small inertia (belt, sheave) of ``inertia_fraction`` times the
    inertia beyond the coupling, so that no algebraic loop of two resistors
    appears."""

    inertia_fraction = 0.05

    name = "slip"
    title = "belt or clutch slip"
    target_kind = "bond"
    params = (EffectParam("cs", "{effort}/{flow}", "slip (creep) coefficient: torque per slip speed",
                          nonnegative=True),)

    def targets(self, graph):
        return _transmission_bonds(graph)

    def grid(self, graph, target, scales):
        J = _inertia_near(graph, graph.bond(target.name))
        # slip time constants J/cs from a tenth of a sample (creep of a stiff
        # belt: quasi-static within a sample) to half the record length
        lo, hi = 0.1 * scales.dt, 0.5 * scales.duration
        taus = [lo * (hi / lo) ** (k / 8) for k in range(9)]
        return [{"cs": J / tau} for tau in taus]

    def box(self, graph, target, scales):
        J = _inertia_near(graph, graph.bond(target.name))
        return {"cs": (J / (0.05 * scales.duration), J / (2 * scales.dt))}

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        bond = graph.bond(target.name)
        j_side = bond.head.element if isinstance(bond.head.element, One) else bond.tail.element
        eu, fu = junction_units(graph, j_side)
        cs = _new_param(graph, self.pname(target, "cs"), values.get("cs", 1.0),
                        _unit("{effort}/{flow}", eu, fu), (1e-9, 1e12),
                        f"slip coefficient at {target.name}")
        J = _inertance_near(graph, bond)
        z = split_bond(graph, bond, "0", f"{self.name}.{target.tag}.j")
        graph.connect(z, graph.R(f"{self.name}.{target.tag}", effort=lambda f: cs * f))
        _side_inertia(graph, z, J, self.inertia_fraction, f"{self.name}.{target.tag}")
        return {"cs": cs}


class Compliance(_Structural):
    """An added compliance (spring + damper) between two inertias coupled
    rigidly through a transmission bond."""

    name = "compliance"
    title = "added compliance between two inertias"
    target_kind = "bond"
    params = (EffectParam("k", "{effort}/({flow}*s)", "stiffness", nonnegative=True),
              EffectParam("zeta", "", "damping ratio of the added mode", estimated=False))

    def targets(self, graph):
        return _transmission_bonds(graph)

    def grid(self, graph, target, scales):
        J = _inertia_near(graph, graph.bond(target.name))
        wmin, wmax = 2 * math.pi / scales.duration, math.pi / scales.dt
        ws = [wmin * (wmax / wmin) ** (k / 7) for k in range(8)]
        return [{"k": J * w**2, "zeta": 0.2} for w in ws]

    def box(self, graph, target, scales):
        J = _inertia_near(graph, graph.bond(target.name))
        w_lo, w_hi = 2 * math.pi * 10 / scales.duration, math.pi / (5 * scales.dt)
        return {"k": (J * w_lo**2, J * w_hi**2)}

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        bond = graph.bond(target.name)
        J = _inertia_near(graph, bond)
        j_side = bond.head.element if isinstance(bond.head.element, One) else bond.tail.element
        eu, fu = junction_units(graph, j_side)
        k = _new_param(graph, self.pname(target, "k"), values.get("k", 1.0),
                       _unit("{effort}/({flow}*s)", eu, fu), (1e-9, 1e15),
                       f"added stiffness at {target.name}")
        zeta = values.get("zeta", 0.2)
        Jx = _inertance_near(graph, bond)
        z = split_bond(graph, bond, "0", f"{self.name}.{target.tag}.j")
        _side_inertia(graph, z, Jx, Slip.inertia_fraction, f"{self.name}.{target.tag}")
        rel = graph.one(f"{self.name}.{target.tag}.rel")
        graph.connect(z, rel)
        graph.connect(rel, graph.C(f"{self.name}.{target.tag}.C", stiffness=k))
        # damping ratio zeta of the added mode with the nearby inertia
        graph.connect(rel, graph.R(f"{self.name}.{target.tag}.R",
                                   2 * zeta * sp.sqrt(k * (Jx if Jx is not None else J))))
        return {"k": k}


