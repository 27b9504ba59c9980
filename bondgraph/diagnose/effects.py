"""A library of physical effects a model may lack, as bond-graph fragments.

Each :class:`Effect` knows

* where it can attach in a given graph (:meth:`Effect.targets`, found from
  the graph's structure: 1-junctions for forces that depend on a velocity,
  sources for actuator errors, sensors for measurement errors, C elements for
  storage limits, transmission bonds for slip and compliance);
* how to add itself (:meth:`Effect.apply`): a fragment of elements and named
  parameters spliced into a *copy* of the graph (the user's declaration is
  never touched);
* for *additive* effects, its basis functions: the effect is
  Σ β_k·b_k(v) with β = 0 meaning "absent". These are probed all at once by
  :func:`probe_graph` for the score (Lagrange-multiplier) test of
  :mod:`bondgraph.diagnose.loop`. Other (*structural*) effects have no such neutral
  point (a slip that vanishes is an infinitely stiff coupling) and are scored
  by a likelihood-ratio fit.

Sign conventions: friction-like laws are R elements (power into the R), so
the force they exert on the junction opposes the motion for positive
coefficients. Offsets and gains are modulated effort sources.

Users add effects the same way: subclass :class:`Effect`, implement
``targets`` and ``apply`` (and ``basis`` if additive), and pass instances to
:func:`bondgraph.diagnose.loop.run_loop` (``effects=DEFAULT_EFFECTS + [MyEffect()]``).

References
----------
Friction laws: Olsson, Åström, Canudas de Wit, Gäfvert & Lischinsky (1998),
Friction models and friction compensation, Eur. J. Control 4(3), 176-195.
Armstrong-Hélouvry, Dupont & Canudas de Wit (1994), A survey of models,
analysis tools and compensation methods for the control of machines with
friction, Automatica 30(7), 1083-1138.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping

import sympy as sp

from bondgraph.core import units as _units
from bondgraph.core.elements import (
    GY,
    C,
    I,
    Junction,
    One,
    OnePort,
    Port,
    Source,
    TwoPort,
)
from bondgraph.core.graph import Bond, BondGraph
from bondgraph.core.smooth import softplus
from bondgraph.core.symbols import Parameter
from bondgraph.errors import GraphError


# ------------------------------------------------------------------ targets
@dataclass(frozen=True)
class Target:
    """Where an effect attaches.

    kind : {"junction", "source", "sensor", "storage", "bond"}
    name : element, sensor or bond name
    """

    kind: str
    name: str

    @property
    def tag(self) -> str:
        """Identifier-safe form of the target name."""
        return "".join(c if (c.isalnum() or c in "_.") else "_" for c in
                       self.name.replace(" -> ", "__"))

    def __str__(self) -> str:
        return f"{self.kind} '{self.name}'"


@dataclass
class Scales:
    """Data-driven scales used for smoothing widths and search boxes.

    flow_rms : dict junction name -> RMS of its flow over the record
    flow_max : dict junction name -> max |flow|
    output_rms : dict sensor name -> RMS of the measured output
    source_max : dict source name -> max |source value|
    duration, dt : record length and sample interval [s]
    """

    flow_rms: dict = field(default_factory=dict)
    flow_max: dict = field(default_factory=dict)
    output_rms: dict = field(default_factory=dict)
    source_max: dict = field(default_factory=dict)
    storage_max: dict = field(default_factory=dict)
    duration: float = 1.0
    dt: float = 0.01

    def v(self, junction: str) -> float:
        return max(float(self.flow_rms.get(junction, 1.0)), 1e-9)


@dataclass
class EffectParam:
    """A parameter of an effect: local name, unit template, description,
    default (or None: set from the data), bounds (or None: from the data),
    and whether the loop estimates it (shape constants such as tanh widths
    are fixed)."""

    name: str
    unit: str = ""
    description: str = ""
    estimated: bool = True
    nonnegative: bool = False
    #: fixed box of a dimensionless fraction (e.g. (0, 1)); None: the loop
    #: sets the box around the start value
    bounds: tuple[float, float] | None = None


# ------------------------------------------------------------------ helpers
def junction_units(graph: BondGraph, junction: Junction) -> tuple[str, str]:
    bu = graph.bond_units()
    for b in graph.bonds_of(junction):
        e, f = bu[b.name]
        if e or f:
            return e or "", f or ""
    return junction.effort_unit or "", junction.flow_unit or ""


def _unit(template: str, effort: str, flow: str) -> str:
    if not template:
        return ""
    if not effort and "{effort}" in template:
        return ""
    if not flow and "{flow}" in template:
        return ""
    return template.replace("{effort}", f"({effort})" if effort else "").replace(
        "{flow}", f"({flow})" if flow else "")


def source_junction(graph: BondGraph, src: OnePort) -> Junction | None:
    b = src.port.bond
    if b is None:
        return None
    other = b.head if b.tail.element is src else b.tail
    return other.element if isinstance(other.element, Junction) else None


def mechanical(flow_unit: str) -> bool | None:
    """True for a translational or rotational flow unit, None if unknown."""
    if not flow_unit:
        return None
    try:
        return (_units.same_dimension(flow_unit, "m/s") or _units.same_dimension(flow_unit, "rad/s"))
    except Exception:
        return None


def split_bond(graph: BondGraph, bond: Bond, kind: str, name: str) -> Junction:
    """Insert a new junction into ``bond`` keeping its power direction:
    ``tail -> new -> head``. Returns the new junction (``kind`` "0" or "1")."""
    if bond not in graph.bonds:
        raise GraphError(f"bond '{bond.name}' is not in graph '{graph.name}'")
    tail, head = bond.tail, bond.head
    graph.bonds.remove(bond)
    for p in (tail, head):
        p.bond = None
        if isinstance(p.element, Junction):
            p.element.ports.remove(p)
    j = graph.zero(name) if kind == "0" else graph.one(name)
    j.effort_unit = j.effort_unit
    a = tail if not isinstance(tail.element, Junction) else tail.element
    b = head if not isinstance(head.element, Junction) else head.element
    # preserve direction: tail -> j -> head
    t_el = a if isinstance(a, Port) else a
    graph.connect(t_el, j)
    graph.connect(j, b)
    for bd in graph.bonds[-2:]:
        if bd.head.element is j or bd.tail.element is j:
            pass
    # connect() orients bonds by element convention; check the direction held
    b1, b2 = graph.bonds[-2], graph.bonds[-1]
    if b1.head.element is not j or b2.tail.element is not j:
        raise GraphError(f"cannot split bond '{bond.name}' without reversing power")
    return j


def _new_param(graph: BondGraph, name: str, default: float, unit: str, bounds, description: str,
               source: str) -> Parameter:
    if name in graph.params:
        raise GraphError(f"graph '{graph.name}' already has parameter '{name}': effect added twice?")
    return graph.param(name, default, unit, bounds, description, source)


# ------------------------------------------------------------------ effects
class Effect:
    """Base class of the effect library.

    Attributes
    ----------
    name : str
        Identifier, e.g. ``"coulomb"``.
    title : str
        Human-readable name for reports.
    target_kind : str
        Kind of :class:`Target` it attaches to.
    params : tuple of EffectParam
    additive : bool
        True if the effect is Σ β_k b_k with β = 0 neutral (probe-able).
    """

    name = "effect"
    title = "effect"
    target_kind = "junction"
    params: tuple[EffectParam, ...] = ()
    additive = False
    #: considered only when no physical effect is significant (a random-walk
    #: disturbance can absorb any model error)
    last_resort = False

    # --- discovery
    def targets(self, graph: BondGraph) -> list[Target]:
        raise NotImplementedError

    # --- construction
    def shape_values(self, graph: BondGraph, target: Target, scales: Scales) -> dict[str, float]:
        """Values of the fixed shape constants (tanh widths ...) from the data."""
        return {}

    def apply(self, graph: BondGraph, target: Target, values: Mapping[str, float] | None = None,
              scales: Scales | None = None) -> dict[str, Parameter]:
        """Add the effect to ``graph`` (in place; pass a copy) at ``target``.

        Parameters
        ----------
        graph : BondGraph
        target : Target
        values : dict, optional
            Values of the effect's parameters (local names); missing ones
            take data-driven or neutral defaults.
        scales : Scales, optional
            Data scales for shape constants and boxes.

        Returns
        -------
        dict local name -> Parameter
            The parameters added (named ``<effect>.<target>.<local>``).
        """
        raise NotImplementedError

    # --- probe (additive effects only)
    def basis(self, graph: BondGraph, target: Target, scales: Scales) -> list[sp.Expr]:
        """Basis functions b_k, one per estimated parameter, so that the
        effect equals Σ β_k b_k (sign convention of the probe element)."""
        raise NotImplementedError

    def natural_points(self, target: Target) -> list[dict[str, float]]:
        """Values of the estimated parameters worth trying in the line probe
        besides multiples of the one-step estimate (e.g. full rectification)."""
        return []

    def pname(self, target: Target, local: str) -> str:
        return f"{self.name}.{target.tag}.{local}"

    def present(self, graph: BondGraph, target: Target) -> bool:
        """True if this effect is already in ``graph`` at ``target``."""
        return any(self.pname(target, p.name) in graph.params for p in self.params)

    def describe(self, target: Target) -> str:
        return f"{self.title} at {target}"


def _one_junctions(graph: BondGraph, mechanical_only: bool = True) -> list[Target]:
    """1-junctions carrying an inertia (the velocity of a mass): where a
    velocity-dependent force can act. Massless junctions (a sheave whose
    speed a damper sets) are skipped: a second resistive law there closes an
    algebraic loop."""
    out = []
    for name in sorted(graph.elements):
        el = graph.elements[name]
        if not isinstance(el, One):
            continue
        if not any(isinstance(p.bond.other(p).element, I) for p in el.ports if p.bond is not None):
            continue
        # a junction whose flow is imposed by a flow source gets no force effects
        if any(isinstance(b.other(p).element, Source) and b.other(p).element.variable == "flow"
               for p in el.ports if (b := p.bond) is not None):
            continue
        if mechanical_only:
            _, fu = junction_units(graph, el)
            if mechanical(fu) is False:
                continue
        out.append(Target("junction", name))
    return out


class _JunctionLaw(Effect):
    """An R element on a 1-junction with a law of the junction flow."""

    target_kind = "junction"
    additive = True
    mechanical_only = True

    def targets(self, graph):
        return _one_junctions(graph, self.mechanical_only)

    def law(self, f, P: dict, S: dict):
        raise NotImplementedError

    def basis_law(self, f, S: dict) -> list:
        raise NotImplementedError

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        j = graph.element(target.name)
        eu, fu = junction_units(graph, j)
        shapes = self.shape_values(graph, target, scales or Scales())
        P = {}
        for spc in self.params:
            default = values.get(spc.name, shapes.get(spc.name, 0.0))
            unit = _unit(spc.unit, eu, fu)
            b = _box(default, spc)
            P[spc.name] = _new_param(graph, self.pname(target, spc.name), default, unit, b,
                                     f"{spc.description} ({self.title} at {target.name})",
                                     "added by the residual-tracing loop")
        el = graph.R(f"{self.name}.{target.tag}", effort=lambda f: self.law(f, P, P))
        graph.connect(j, el)
        return P

    def basis(self, graph, target, scales):
        j = graph.element(target.name)
        shapes = self.shape_values(graph, target, scales)
        S = {k: sp.Float(v) for k, v in shapes.items()}
        # probe = MSe on the junction: force on the junction = -R law
        return [-b for b in self.basis_law(j.f, S)]


def _box(default: float, spc: EffectParam) -> tuple[float, float]:
    scale = abs(default) if default else 1.0
    if spc.nonnegative:
        return (0.0, max(10.0 * scale, 1e-9))
    return (-10.0 * scale, 10.0 * scale)


class Viscous(_JunctionLaw):
    name = "viscous"
    title = "viscous friction"
    params = (EffectParam("b", "{effort}/{flow}", "viscous friction coefficient", nonnegative=True),)

    def law(self, f, P, S):
        return P["b"] * f

    def basis_law(self, f, S):
        return [f]


class QuadraticDrag(_JunctionLaw):
    name = "quadratic_drag"
    title = "quadratic (aerodynamic) drag"
    params = (EffectParam("c", "{effort}/{flow}^2", "quadratic drag coefficient, e.g. rho*CdA/2",
                          nonnegative=True),
              EffectParam("eps", "{flow}", "smoothing width of |v|", estimated=False))

    def shape_values(self, graph, target, scales):
        return {"eps": 0.01 * scales.v(target.name)}

    def law(self, f, P, S):
        return P["c"] * f * sp.sqrt(f**2 + S["eps"] ** 2)

    def basis_law(self, f, S):
        return [f * sp.sqrt(f**2 + S["eps"] ** 2)]


class Coulomb(_JunctionLaw):
    name = "coulomb"
    title = "Coulomb friction (symmetric)"
    params = (EffectParam("Fc", "{effort}", "Coulomb friction level", nonnegative=True),
              EffectParam("eps", "{flow}", "tanh width of the sign function", estimated=False))

    def shape_values(self, graph, target, scales):
        return {"eps": 0.02 * scales.v(target.name)}

    def law(self, f, P, S):
        return P["Fc"] * sp.tanh(f / S["eps"])

    def basis_law(self, f, S):
        return [sp.tanh(f / S["eps"])]


class AsymmetricFriction(_JunctionLaw):
    """Direction-dependent friction: the even part of a friction law whose
    Coulomb and viscous coefficients differ for positive and negative motion
    (added on top of a symmetric law: Fc± = Fc ± dc, Fv± = Fv ± dv)."""

    name = "asymmetric_friction"
    title = "direction-dependent (asymmetric) friction"
    params = (EffectParam("dc", "{effort}", "half-difference of the Coulomb levels (+ minus -)"),
              EffectParam("dv", "{effort}/{flow}", "half-difference of the viscous coefficients"),
              EffectParam("eps", "{flow}", "tanh width", estimated=False))

    def shape_values(self, graph, target, scales):
        return {"eps": 0.02 * scales.v(target.name)}

    def law(self, f, P, S):
        s = sp.tanh(f / S["eps"])
        return P["dc"] * s**2 + P["dv"] * f * s

    def basis_law(self, f, S):
        s = sp.tanh(f / S["eps"])
        return [s**2, f * s]


class Stribeck(_JunctionLaw):
    name = "stribeck"
    title = "Stribeck friction (static above Coulomb)"
    params = (EffectParam("ds", "{effort}", "static minus Coulomb friction", nonnegative=True),
              EffectParam("vs", "{flow}", "Stribeck velocity", estimated=False),
              EffectParam("eps", "{flow}", "tanh width", estimated=False))

    def shape_values(self, graph, target, scales):
        v = scales.v(target.name)
        return {"vs": 0.1 * v, "eps": 0.02 * v}

    def law(self, f, P, S):
        return P["ds"] * sp.exp(-(f / S["vs"]) ** 2) * sp.tanh(f / S["eps"])

    def basis_law(self, f, S):
        return [sp.exp(-(f / S["vs"]) ** 2) * sp.tanh(f / S["eps"])]


class ConstantEffort(_JunctionLaw):
    """A constant force or torque offset of an actuator: attaches to the
    1-junctions that an input-driven effort source drives. (On other
    junctions a constant force opposing a motion that keeps its direction is
    indistinguishable from Coulomb friction, which the library has.)"""

    name = "offset"
    title = "actuator offset (constant force/torque)"
    params = (EffectParam("F0", "{effort}", "constant effort on the junction (along the flow)"),)
    mechanical_only = False

    def targets(self, graph):
        out = []
        for t in ActuatorGain().targets(graph):
            j = source_junction(graph, graph.element(t.name))
            if isinstance(j, One) and Target("junction", j.name) not in out:
                out.append(Target("junction", j.name))
        return out

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        j = graph.element(target.name)
        eu, fu = junction_units(graph, j)
        F0 = _new_param(graph, self.pname(target, "F0"), values.get("F0", 0.0), eu,
                        (-1e9, 1e9), f"constant effort at {target.name}",
                        "added by the residual-tracing loop")
        graph.connect(graph.MSe(f"{self.name}.{target.tag}", F0), j)
        return {"F0": F0}

    def basis(self, graph, target, scales):
        return [sp.Integer(1)]


class ActuatorGain(Effect):
    """A gain error of an effort source: effort (1 + g)·value."""

    name = "actuator_gain"
    title = "actuator gain error"
    target_kind = "source"
    additive = True
    params = (EffectParam("g", "", "relative gain error"),)

    def targets(self, graph):
        out = []
        for name in sorted(graph.elements):
            el = graph.elements[name]
            # actuators: effort sources driven by an input (not gravity, which
            # reads a state, nor constant sources)
            from bondgraph.core.symbols import Input

            if isinstance(el, Source) and el.variable == "effort" and not name.startswith(
                    ("offset.", "probe.")) and any(isinstance(s, Input)
                                                    for s in el.value.free_symbols):
                if source_junction(graph, el) is not None:
                    out.append(Target("source", name))
        return out

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        src = graph.element(target.name)
        j = source_junction(graph, src)
        g = _new_param(graph, self.pname(target, "g"), values.get("g", 0.0), "", (-0.9, 2.0),
                       f"gain error of {target.name}", "added by the residual-tracing loop")
        graph.connect(graph.MSe(f"{self.name}.{target.tag}", g * src.value), j)
        return {"g": g}

    def basis(self, graph, target, scales):
        return [graph.element(target.name).value]

    def probe_junction(self, graph, target):
        return source_junction(graph, graph.element(target.name))


class _SensorEffect(Effect):
    target_kind = "sensor"
    additive = True

    def targets(self, graph):
        return [Target("sensor", n) for n in sorted(graph.sensors)]

    def transform(self, y, P: dict, S: dict):
        raise NotImplementedError

    def basis_y(self, y, S: dict) -> list:
        raise NotImplementedError

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        sen = graph.sensors[target.name]
        shapes = self.shape_values(graph, target, scales or Scales())
        P = {}
        for spc in self.params:
            default = values.get(spc.name, shapes.get(spc.name, 0.0))
            unit = sen.unit if spc.unit == "{y}" else spc.unit
            lo, hi = (0.0, 1.0) if spc.name == "lam" else _box(default or 1.0, spc)
            if spc.name == "b":
                lo, hi = -1e9, 1e9
            P[spc.name] = _new_param(graph, self.pname(target, spc.name), default, unit, (lo, hi),
                                     f"{spc.description} ({self.title} of {target.name})",
                                     "added by the residual-tracing loop")
        sen.expr = self.transform(sen.expr, P, P)
        return P

    def basis(self, graph, target, scales):
        shapes = self.shape_values(graph, target, scales)
        S = {k: sp.Float(v) for k, v in shapes.items()}
        return self.basis_y(graph.sensors[target.name].expr, S)


class SensorOffset(_SensorEffect):
    name = "sensor_offset"
    title = "sensor offset"
    params = (EffectParam("b", "{y}", "constant added to the measurement"),)

    def transform(self, y, P, S):
        return y + P["b"]

    def basis_y(self, y, S):
        return [sp.Integer(1)]


class SensorGain(_SensorEffect):
    name = "sensor_gain"
    title = "sensor gain error"
    params = (EffectParam("g", "", "relative gain error of the measurement"),)

    def transform(self, y, P, S):
        return (1 + P["g"]) * y

    def basis_y(self, y, S):
        return [y]


class SensorRectification(_SensorEffect):
    """A sign-blind sensor: y -> (1 - λ) y + λ |y| (λ = 1: pure rectification,
    as a pulse counter that cannot see the direction)."""

    name = "sensor_rectification"
    title = "sensor rectification |y| (sign-blind sensor)"
    params = (EffectParam("lam", "", "rectification fraction (1 = |y|)", bounds=(0.0, 1.0)),
              EffectParam("eps", "{y}", "smoothing width of |y|", estimated=False))

    def shape_values(self, graph, target, scales):
        return {"eps": 0.01 * max(float(scales.output_rms.get(target.name, 1.0)), 1e-9)}

    def natural_points(self, target):
        return [{"lam": 1.0}, {"lam": 0.5}]

    def transform(self, y, P, S):
        return y + P["lam"] * (sp.sqrt(y**2 + S["eps"] ** 2) - y)

    def basis_y(self, y, S):
        return [sp.sqrt(y**2 + S["eps"] ** 2) - y]


# ------------------------------------------------------------- structural
class _Structural(Effect):
    """Effects without a neutral value of their parameters; scored by a
    likelihood-ratio fit over ``grid(scales)`` (values of the first
    parameter)."""

    additive = False

    def grid(self, graph, target, scales) -> list[dict[str, float]]:
        raise NotImplementedError


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

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        bond = graph.bond(target.name)
        j_side = bond.head.element if isinstance(bond.head.element, One) else bond.tail.element
        eu, fu = junction_units(graph, j_side)
        cs = _new_param(graph, self.pname(target, "cs"), values.get("cs", 1.0),
                        _unit("{effort}/{flow}", eu, fu), (1e-9, 1e12),
                        f"slip coefficient at {target.name}", "added by the residual-tracing loop")
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

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        bond = graph.bond(target.name)
        J = _inertia_near(graph, bond)
        j_side = bond.head.element if isinstance(bond.head.element, One) else bond.tail.element
        eu, fu = junction_units(graph, j_side)
        k = _new_param(graph, self.pname(target, "k"), values.get("k", 1.0),
                       _unit("{effort}/({flow}*s)", eu, fu), (1e-9, 1e15),
                       f"added stiffness at {target.name}", "added by the residual-tracing loop")
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


class SensorLowPass(_Structural):
    """A first-order low-pass sensor (anti-aliasing filter): the measurement
    is z with dz/dt = (y - z)/tau."""

    name = "sensor_lowpass"
    title = "sensor low-pass (first-order lag)"
    target_kind = "sensor"
    params = (EffectParam("tau", "s", "time constant", nonnegative=True),)

    def targets(self, graph):
        return [Target("sensor", n) for n in sorted(graph.sensors)]

    def grid(self, graph, target, scales):
        lo, hi = 0.5 * scales.dt, 0.05 * scales.duration
        return [{"tau": lo * (hi / lo) ** (k / 7)} for k in range(8)]

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        sen = graph.sensors[target.name]
        tau = _new_param(graph, self.pname(target, "tau"), values.get("tau", 0.01), "s",
                         (1e-6, 1e6), f"sensor time constant of {target.name}",
                         "added by the residual-tracing loop")
        y = sen.expr
        z = graph.state(f"{self.name}.{target.tag}.z", rhs=lambda s: (y - s) / tau, unit=sen.unit,
                        description=f"low-passed {target.name}")
        sen.expr = z
        return {"tau": tau}


class Disturbance(_Structural):
    """An unmeasured disturbance effort on a 1-junction, modelled as a
    random-walk state d with process-noise intensity q."""

    name = "disturbance"
    title = "unmeasured disturbance (random-walk effort)"
    target_kind = "junction"
    last_resort = True
    params = (EffectParam("q", "{effort}/s^0.5", "random-walk intensity", nonnegative=True),)

    def targets(self, graph):
        return _one_junctions(graph, mechanical_only=False)

    def grid(self, graph, target, scales):
        return [{"q": 10.0 ** k} for k in range(-3, 5)]

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        j = graph.element(target.name)
        eu, _ = junction_units(graph, j)
        q = _new_param(graph, self.pname(target, "q"), values.get("q", 1.0), "", (1e-12, 1e12),
                       f"disturbance intensity at {target.name}", "added by the residual-tracing loop")
        d = graph.state(f"{self.name}.{target.tag}.d", 0, unit=eu, process_noise=q,
                        description=f"disturbance effort at {target.name}")
        graph.connect(graph.MSe(f"{self.name}.{target.tag}", d), j)
        return {"q": q}


class _SourceShaping(_Structural):
    """A static nonlinearity of an effort source: an MSe on the source's
    junction adds ``shaped(value) - value``; one parameter, its grid in
    fractions of the source's largest value in the record."""

    target_kind = "source"
    #: grid of the parameter, as fractions of the source's largest value
    fractions: tuple[float, ...] = ()
    what = ""

    def targets(self, graph):
        return ActuatorGain().targets(graph)

    def grid(self, graph, target, scales):
        m = max(float(scales.source_max.get(target.name, 1.0)), 1e-9)
        p = self.params[0].name
        return [{p: m * f} for f in self.fractions]

    def shaped_minus_value(self, v, p):
        raise NotImplementedError

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        src = graph.element(target.name)
        j = source_junction(graph, src)
        eu, _ = junction_units(graph, j)
        name = self.params[0].name
        p = _new_param(graph, self.pname(target, name), values.get(name, 1.0), eu, (1e-9, 1e12),
                       f"{self.what} of {target.name}", "added by the residual-tracing loop")
        graph.connect(graph.MSe(f"{self.name}.{target.tag}", self.shaped_minus_value(src.value, p)),
                      j)
        return {name: p}


class ActuatorSaturation(_SourceShaping):
    """Smooth saturation of an effort source: value -> value/sqrt(1 + (value/L)^2)."""

    name = "actuator_saturation"
    title = "actuator saturation"
    params = (EffectParam("L", "{effort}", "saturation level", nonnegative=True),)
    fractions = (0.3, 0.5, 0.7, 0.85, 1.0, 1.3, 2.0)
    what = "saturation level"

    def shaped_minus_value(self, v, L):
        return v / sp.sqrt(1 + (v / L) ** 2) - v


class ActuatorDeadZone(_SourceShaping):
    """Smooth dead zone of an effort source: value -> value - d·tanh(value/d)."""

    name = "actuator_deadzone"
    title = "actuator dead zone"
    params = (EffectParam("d", "{effort}", "dead-zone half width", nonnegative=True),)
    fractions = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3)
    what = "dead-zone half width"

    def shaped_minus_value(self, v, d):
        return -d * sp.tanh(v / d)


def _storage_targets(graph: BondGraph) -> list[Target]:
    return [Target("storage", n) for n in sorted(graph.elements)
            if isinstance(graph.elements[n], C)]


def _force_on_storage(graph: BondGraph, el: C, tag: str) -> One:
    """A 1-junction spliced into the bond of C element ``el`` (same flow as
    the C), so that an extra effort can act on its displacement."""
    return split_bond(graph, el.port.bond, "1", tag)


class EndStop(_Structural):
    """End stops (saturation) of a storage: a stiff one-sided spring beyond
    ±q_max on the displacement of a C element."""

    name = "end_stop"
    title = "end stops / saturation of a storage"
    target_kind = "storage"
    params = (EffectParam("qmax", "", "free travel each side", nonnegative=True),
              EffectParam("kstop", "", "stop stiffness", estimated=False))

    def targets(self, graph):
        return _storage_targets(graph)

    def grid(self, graph, target, scales):
        m = max(float(scales.storage_max.get(target.name, 1.0)), 1e-12)
        return [{"qmax": m * f} for f in (0.3, 0.5, 0.7, 0.85, 1.0)]

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        el = graph.element(target.name)
        qmax = _new_param(graph, self.pname(target, "qmax"), values.get("qmax", 1.0), "",
                          (1e-12, 1e12), f"free travel of {target.name}",
                          "added by the residual-tracing loop")
        k = el.stiffness if el.stiffness is not None else (1 / el.compliance if el.compliance is not None
                                                           else sp.Integer(1))
        ks = 100 * k
        q = el.q
        w = qmax / 20
        j = _force_on_storage(graph, el, f"{self.name}.{target.tag}.j")
        stop = ks * w * (softplus((q - qmax) / w) - softplus((-q - qmax) / w))
        graph.connect(graph.MSe(f"{self.name}.{target.tag}", -stop), j)
        return {"qmax": qmax}


class Backlash(_Structural):
    """Backlash (dead zone) in a compliance: e = k (q - g tanh(q/g))."""

    name = "backlash"
    title = "backlash / dead zone of a compliance"
    target_kind = "storage"
    params = (EffectParam("gap", "", "half gap", nonnegative=True),)

    def targets(self, graph):
        return _storage_targets(graph)

    def grid(self, graph, target, scales):
        m = max(float(scales.storage_max.get(target.name, 1.0)), 1e-12)
        return [{"gap": m * f} for f in (0.02, 0.05, 0.1, 0.2, 0.4)]

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        el = graph.element(target.name)
        g_ = _new_param(graph, self.pname(target, "gap"), values.get("gap", 1.0), "", (1e-12, 1e12),
                        f"half gap of {target.name}", "added by the residual-tracing loop")
        k = el.stiffness if el.stiffness is not None else (1 / el.compliance if el.compliance is not None
                                                           else sp.Integer(1))
        j = _force_on_storage(graph, el, f"{self.name}.{target.tag}.j")
        graph.connect(graph.MSe(f"{self.name}.{target.tag}", k * g_ * sp.tanh(el.q / g_)), j)
        return {"gap": g_}


#: the library used by :func:`bondgraph.diagnose.loop.run_loop` unless told otherwise
DEFAULT_EFFECTS: tuple[Effect, ...] = (
    Coulomb(), AsymmetricFriction(), Stribeck(), Viscous(), QuadraticDrag(), ConstantEffort(),
    ActuatorGain(), SensorOffset(), SensorGain(), SensorRectification(),
    Slip(), Compliance(), SensorLowPass(), Disturbance(), ActuatorSaturation(),
    ActuatorDeadZone(), EndStop(), Backlash(),
)

BY_NAME: dict[str, Effect] = {e.name: e for e in DEFAULT_EFFECTS}


def get_effect(name: str, library=None) -> Effect:
    lib = {e.name: e for e in (library or DEFAULT_EFFECTS)}
    try:
        return lib[name]
    except KeyError:
        raise GraphError(f"unknown effect '{name}' (library: {', '.join(sorted(lib))})") from None


def apply_effect(graph: BondGraph, effect: str | Effect, target: Target | tuple[str, str],
                 values: Mapping[str, float] | None = None) -> dict[str, Parameter]:
    """Add a library effect to ``graph`` in place (used by the augmented model
    files the loop writes). ``target`` is a :class:`Target` or ``(kind, name)``."""
    eff = get_effect(effect) if isinstance(effect, str) else effect
    tgt = target if isinstance(target, Target) else Target(*target)
    return eff.apply(graph, tgt, values)


# --------------------------------------------------------------------- probe
@dataclass
class ProbeColumn:
    """One probe parameter: effect, target, index of its basis function."""

    param: str
    effect: str
    target: Target
    k: int
    basis: sp.Expr


def probe_graph(graph: BondGraph, effects, scales: Scales,
                exclude: set | None = None) -> tuple[BondGraph, list[ProbeColumn]]:
    """A copy of ``graph`` with every additive effect at every target added
    as Σ β_k b_k with β = 0 (neutral), one parameter per basis function.

    Forces on a junction go through one modulated effort source per junction
    (effort = Σ β b); sensor effects are added to the sensor expressions.

    Returns
    -------
    (BondGraph, list of ProbeColumn)
    """
    g = graph.copy(f"{graph.name}__probe")
    cols: list[ProbeColumn] = []
    per_junction: dict[str, list] = {}
    per_sensor: dict[str, list] = {}
    for eff in effects:
        if not eff.additive:
            continue
        for tgt in eff.targets(graph):
            if eff.present(graph, tgt) or tgt.name in (exclude or ()):
                continue
            bases = eff.basis(g, tgt, scales)
            for k, b in enumerate(bases):
                pname = f"probe.{eff.name}.{tgt.tag}.{k}"
                p = g.param(pname, 0.0, "", (-1e12, 1e12), f"probe of {eff.title} at {tgt}")
                cols.append(ProbeColumn(pname, eff.name, tgt, k, b))
                if eff.target_kind == "sensor":
                    per_sensor.setdefault(tgt.name, []).append(p * b)
                else:
                    jname = tgt.name if eff.target_kind == "junction" else \
                        eff.probe_junction(g, tgt).name
                    per_junction.setdefault(jname, []).append(p * b)
    for jname, terms in per_junction.items():
        j = g.element(jname)
        g.connect(g.MSe(f"probe.{j.name}", sp.Add(*terms)), j)
    for sname, terms in per_sensor.items():
        g.sensors[sname].expr = g.sensors[sname].expr + sp.Add(*terms)
    return g, cols
