"""Alternatives of an R element's constitutive law: linear ↔ square-root
(orifice) ↔ quadratic ↔ cubic, and a power law whose exponent is estimated.

An R has a causal input x and output y: the flow in and the effort out
(``e = φ(f)``) when the graph imposes its flow, the effort in and the flow
out (``f = φ(e)``) when it imposes its effort (a hydraulic orifice between
two tanks, a resistor across a capacitor). The effects add a term to the
law in that causal form,

    y = law(x) + β·b(x),  b(x) ∈ { sgn(x)√|x|,  x|x|,  x³ },

so that the law stays explicit (no algebraic loop). With β free and the
linear coefficient re-estimated, the law moves from linear to any of the
three; a pure square-root law is the limit R → ∞ of a conductance-form
orifice f = e/R + β sgn(e)√|e|. The square root and the absolute value are
smoothed over ε, 1 % of the RMS of x in the record (sgn(x)√|x| ≈
x/(x² + ε²)^{1/4}, x|x| ≈ x√(x² + ε²)), so that the laws are smooth where
sigma points cross zero. A linear R (``resistance=``) that receives effort
is rewritten in conductance form, f = e/R, first.

A law between those exponents (natural convection from a wall, heat flow ∝
ΔT^1.25 to ΔT^1.33; turbulent pipe friction, Δp ∝ Q^1.75 to Q^1.85) leaves the
nearest fixed term a misfit the loop then pays for with look-alike effects
elsewhere: :class:`RPower` estimates the exponent,

    y = law(x) + β·x·((x² + ε²)/x_ref²)^((n − 1)/2)   ≈ β·x_ref·sgn(x)|x/x_ref|^n,

with x_ref the RMS of x in the record, so that β keeps the unit of a linear
coefficient whatever n is.

Heat that a surface radiates to another, Q = εσA·(T₁⁴ − T₂⁴) (Stefan-Boltzmann),
is not a law of the R's effort ΔT = T₁ − T₂ alone: :class:`Radiation` adds it to a
thermal resistance between two absolute temperatures of a pseudo bond graph
(temperature and heat flow, domain ``heat``), written with their sum
s = T₁ + T₂ as β·ΔT·s·(s² + ΔT²)/2, which is T₁⁴ − T₂⁴ whichever way the bond
points.

Sign convention: power into the R, so β > 0 adds dissipation.

References
----------
Karnopp, Margolis & Rosenberg, *System Dynamics*, 5th ed., §4.1 (nonlinear
resistances, causality of R elements), §11 (orifice flow Q = C_d A
√(2Δp/ρ)) and ch. 12 (pseudo bond graphs of heat transfer); Incropera &
DeWitt, *Fundamentals of Heat and Mass Transfer*, §1.2.3 (radiation
exchange of a small surface with its surroundings, q = εσA(T⁴ − T_sur⁴)).
"""

from __future__ import annotations

import sympy as sp

from bondgraph.core import units as _units
from bondgraph.core.causality import assign_causality
from bondgraph.core.elements import One, R, Se, Zero
from bondgraph.core.graph import BondGraph
from bondgraph.diagnose.effects.base import (
    Effect,
    EffectParam,
    Scales,
    _new_param,
    _Structural,
    element_units,
    fill_unit,
    resistor_targets,
)
from bondgraph.errors import GraphError


def causal_input(graph: BondGraph, el: R) -> str:
    """``"flow"`` if SCAP gives the R its flow (it returns the effort),
    ``"effort"`` otherwise."""
    cz = assign_causality(graph, validate=False)
    return "effort" if cz.receives_effort(el.port.bond, el) else "flow"


def add_to_r_law(graph: BondGraph, el: R, term) -> None:
    """Add ``term`` (an expression of the R's port variables, or a callable
    of its causal input x) to the law of ``el`` in its causal form (x, see
    :func:`causal_input`); a linear R that receives effort is first
    rewritten as f = e/R.

    Raises
    ------
    ValueError
        If the law is nonlinear and written in the other causality.
    """
    inp = causal_input(graph, el)
    if inp == "effort" and el.form == "effort":
        if el.resistance is None:
            raise ValueError(f"R '{el.name}': nonlinear effort law in effort-in causality")
        el.form, el.law = "flow", el.e / el.resistance
    elif inp == "flow" and el.form == "flow":
        raise ValueError(f"R '{el.name}': flow law in flow-in causality")
    x = el.e if inp == "effort" else el.f
    el.law = el.law + (term(x) if callable(term) else term)


def io_units(graph: BondGraph, el: R) -> tuple[str, str]:
    """Units of the R's causal input x and output y (:func:`causal_input`)."""
    eu, fu = element_units(graph, el)
    return (eu, fu) if causal_input(graph, el) == "effort" else (fu, eu)


def io_rms(graph: BondGraph, target, scales) -> tuple[float, float]:
    """RMS of the R's causal input x and output y in the record (``scales``)."""
    inp = causal_input(graph, graph.element(target.name))
    x = scales.get("r_effort_rms" if inp == "effort" else "r_flow_rms", target.name)
    y = scales.get("r_flow_rms" if inp == "effort" else "r_effort_rms", target.name)
    return float(x), float(y)


def law_params(eff, graph: BondGraph, target, values: dict, shapes: dict, fallback: float,
               bounds_of) -> dict:
    """The parameters of ``eff``'s term at the R ``target`` added to
    ``graph``, by local name: units from the R's causal input x and output y
    (:func:`io_units`), start values from ``values``, else ``shapes``, else
    ``fallback``, boxes ``bounds_of(spec)``."""
    xu, yu = io_units(graph, graph.element(target.name))
    return {spc.name: _new_param(graph, eff.pname(target, spc.name),
                                 values.get(spc.name, shapes.get(spc.name, fallback)),
                                 fill_unit(spc.unit, x=xu, y=yu), bounds_of(spc),
                                 f"{spc.description} ({eff.title} of {target.name})")
            for spc in eff.params}


class _RLawTerm(Effect):
    """A term β·b(x) added to an R's law in its causal form."""

    target_kind = "resistor"
    additive = True

    def targets(self, graph):
        return resistor_targets(graph)

    def shape_values(self, graph, target, scales):
        return {"eps": 0.01 * io_rms(graph, target, scales)[0]}

    def term(self, x, S: dict):
        """The basis function b(x)."""
        raise NotImplementedError

    def apply(self, graph, target, values=None, scales=None):
        shapes = self.shape_values(graph, target, scales or Scales())
        P = law_params(self, graph, target, dict(values or {}), shapes, 0.0,
                       lambda spc: (-1e15, 1e15) if spc.estimated else (1e-15, 1e15))
        add_to_r_law(graph, graph.element(target.name),
                     lambda x: P[self.params[0].name] * self.term(x, P))
        return P

    def basis(self, graph, target, scales):
        el = graph.element(target.name)
        S = {k: sp.Float(v) for k, v in self.shape_values(graph, target, scales).items()}
        x = el.e if causal_input(graph, el) == "effort" else el.f
        return [self.term(x, S)]

    def box(self, graph, target, scales):
        """The term's output at the RMS input between 10 % and 50 % of the
        R's RMS output."""
        x, y = io_rms(graph, target, scales)
        b = abs(float(self.term(sp.Float(x), {"eps": 0.01 * x})))
        return {self.params[0].name: (0.1 * y / b, 0.5 * y / b)}


class RSquareRoot(_RLawTerm):
    """Square-root (orifice) law: y += β·sgn(x)√|x| (a turbulent orifice
    written in conductance form, Q = K √Δp)."""

    name = "r_sqrt"
    title = "square-root (orifice) law of a resistor"
    params = (EffectParam("beta", "{y}/{x}^0.5", "square-root law coefficient"),
              EffectParam("eps", "{x}", "smoothing width of sgn(x)√|x|", estimated=False))

    def term(self, x, S):
        return x / (x**2 + S["eps"] ** 2) ** sp.Rational(1, 4)


class RQuadratic(_RLawTerm):
    """Quadratic law: y += β·x|x| (turbulent flow, drag)."""

    name = "r_quadratic"
    title = "quadratic law of a resistor"
    params = (EffectParam("beta", "{y}/{x}^2", "quadratic law coefficient"),
              EffectParam("eps", "{x}", "smoothing width of |x|", estimated=False))

    def term(self, x, S):
        return x * sp.sqrt(x**2 + S["eps"] ** 2)


class RCubic(_RLawTerm):
    """Cubic law: y += β·x³ (a progressive damper, a varistor-like resistor)."""

    name = "r_cubic"
    title = "cubic law of a resistor"
    params = (EffectParam("beta", "{y}/{x}^3", "cubic law coefficient"),)

    def shape_values(self, graph, target, scales):
        return {}

    def term(self, x, S):
        return x**3


class RPower(_Structural):
    """Power law with an estimated exponent: y += β·x·((x² + ε²)/x_ref²)^((n−1)/2),
    about β·x_ref·sgn(x)|x/x_ref|^n (module docstring): natural convection
    (n 1.25-1.33), turbulent pipe friction (n 1.75-1.85), an orifice (0.5),
    drag (2). β is the term's output at x = x_ref over x_ref (the unit of a
    linear coefficient); x_ref, the RMS of x in the record, and ε, 1 % of
    it, are fixed.

    Scored over a grid of exponents (0.5, 1.5, 2, 3) and two sizes of β
    (the term at x_ref 10 % and 30 % of the R's RMS output), then profiled;
    the exponent stays in [0.25, 4], and a refit that ends on either end
    is refused (``interior``: the record then asks for a law no power law
    in that range gives; a Camry's fuel flow took n = 4 with β on its box
    too). At n = 1 the term is the linear law itself: a refit that drifts
    there leaves β and the R's own coefficient on a ridge, which the accept
    rule refuses.
    """

    name = "r_power"
    title = "power law of a resistor (estimated exponent)"
    target_kind = "resistor"
    params = (EffectParam("beta", "{y}/{x}", "power law coefficient at x_ref", nonnegative=True),
              EffectParam("n", "", "exponent of the power law", bounds=(0.25, 4.0),
                          interior=True),
              EffectParam("x_ref", "{x}", "reference input (RMS of x)", estimated=False),
              EffectParam("eps", "{x}", "smoothing width of |x|", estimated=False))
    exponents = (0.5, 1.5, 2.0, 3.0)
    fractions = (0.1, 0.3)

    def targets(self, graph):
        return resistor_targets(graph)

    def shape_values(self, graph, target, scales):
        x, _ = io_rms(graph, target, scales)
        return {"x_ref": x, "eps": 0.01 * x}

    def grid(self, graph, target, scales):
        x, y = io_rms(graph, target, scales)
        g = y / x if x > 0 else 1.0
        return [{"beta": f * g, "n": n} for n in self.exponents for f in self.fractions]

    def grid_span(self, graph, target, scales):
        span = super().grid_span(graph, target, scales)
        span["n"] = self.params[1].bounds
        return span

    def box(self, graph, target, scales):
        return self.grid_span(graph, target, scales)

    def apply(self, graph, target, values=None, scales=None):
        shapes = self.shape_values(graph, target, scales) if scales is not None else {}
        P = law_params(self, graph, target, dict(values or {}), shapes, 1.0,
                       lambda spc: spc.bounds or ((0.0, 1e15) if spc.nonnegative
                                                  else (1e-15, 1e15)))
        b, n, xr, ep = (P[k] for k in ("beta", "n", "x_ref", "eps"))
        add_to_r_law(graph, graph.element(target.name),
                     lambda x: b * x * ((x**2 + ep**2) / xr**2) ** ((n - 1) / 2))
        return P


#: the least temperature [K] both sides of a radiating resistance keep over
#: the record for :class:`Radiation` to attach: the efforts are absolute
#: temperatures (a graph in temperature rises above a reference, or in °C,
#: reaches 0 or stays far below this)
ABSOLUTE_TEMPERATURE = 100.0


class Radiation(_RLawTerm):
    """Thermal radiation beside a thermal resistance: the heat flow gains
    β·(T₁⁴ − T₂⁴) (Stefan-Boltzmann; β = εσA for a small surface in large
    surroundings, σ = 5.670e-8 W/(m² K⁴)), written as β·x·s·(s² + x²)/2 with
    x = T₁ − T₂ the R's effort and s = T₁ + T₂ (module docstring).

    Attaches to an R of a pseudo bond graph of heat transfer (effort a
    temperature, flow a heat flow in W; domain ``heat``) that receives its
    effort (f = law(ΔT)), on a 1-junction with just two other bonds, to
    0-junctions or effort sources, one pointing into the junction and one
    out of it (a path for the heat: the R's effort is then ±(T₁ − T₂)):
    T₁ and T₂ are their efforts. Scored only
    where both stay above :data:`ABSOLUTE_TEMPERATURE` over the record (the
    law needs absolute temperatures). β >= 0: radiation carries heat from
    hot to cold (s > 0), so the term is passive.
    """

    name = "radiation"
    title = "thermal radiation (T⁴ law) beside a thermal resistance"
    params = (EffectParam("beta", "{y}/{x}^4", "radiative coefficient εσA", nonnegative=True),)

    def targets(self, graph):
        # one pass over the bonds' units first: a graph with no heat bond (every
        # graph but a pseudo bond graph of heat transfer) is done without
        # looking at each R (its units, its causality)
        if not any(e and f and _units.is_pseudo_power(e, f)
                   for e, f in graph.bond_units().values()):
            return []
        return [t for t in resistor_targets(graph) if self.sides(graph, t) is not None]

    def sides(self, graph: BondGraph, target) -> tuple | None:
        """``((T₁, where₁), (T₂, where₂))``: the efforts on either side of
        the R ``target`` (expressions) and where they are read (``("junction",
        name)`` or ``("source", name)``), or None where the effect does not
        attach (class docstring)."""
        el = graph.element(target.name)
        if not isinstance(el, R) or el.port.bond is None:
            return None
        eu, fu = element_units(graph, el)
        if not (eu and fu and _units.is_pseudo_power(eu, fu)):
            return None
        if causal_input(graph, el) != "effort":
            return None
        j = el.port.bond.other(el.port).element
        if not isinstance(j, One) or len(j.ports) != 3:
            return None
        out, into = [], []
        for p in j.ports:
            other = p.bond.other(p).element if p.bond is not None else None
            if other is el:
                continue
            if isinstance(other, Zero):
                out.append((other.e, ("junction", other.name)))
            elif isinstance(other, Se):
                out.append((other.value, ("source", other.name)))
            else:
                return None
            into.append(p.bond.head is p)
        # a path through the junction (one bond in, one out): the R's effort
        # is then ±(T₁ − T₂); two bonds in would make it T₁ + T₂
        if len(out) != 2 or into[0] == into[1]:
            return None
        return tuple(out)

    def _sum(self, graph, target):
        sides = self.sides(graph, target)
        if sides is None:
            raise GraphError(
                f"radiation cannot attach at R '{target.name}': it needs an R of a pseudo bond "
                f"graph of heat transfer (effort a temperature, flow a heat flow in W) that "
                f"receives its effort, on a 1-junction with one bond in from a 0-junction or "
                f"effort source and one out to another")
        (a, _), (b, _) = sides
        return a + b

    def absolute(self, graph, target, scales) -> bool:
        """Both sides stay above :data:`ABSOLUTE_TEMPERATURE` over the record."""
        lows = []
        for _, (kind, name) in self.sides(graph, target):
            table = scales.effort_min if kind == "junction" else scales.source_min
            lows.append(table.get(name, float("nan")))
        return all(v > ABSOLUTE_TEMPERATURE for v in lows)

    def shape_values(self, graph, target, scales):
        return {}

    def term(self, x, S):
        s = S["s"]
        return x * s * (s**2 + x**2) / 2

    def basis(self, graph, target, scales):
        if not self.absolute(graph, target, scales):
            return []
        el = graph.element(target.name)
        return [self.term(el.e, {"s": self._sum(graph, target)})]

    def apply(self, graph, target, values=None, scales=None):
        s = self._sum(graph, target)
        P = law_params(self, graph, target, dict(values or {}), {}, 0.0,
                       lambda spc: (0.0, 1e15))
        add_to_r_law(graph, graph.element(target.name),
                     lambda x: P["beta"] * self.term(x, {"s": s}))
        return P

    def box(self, graph, target, scales):
        """The term at the R's RMS temperature difference and the sides'
        RMS temperatures between 10 % and 50 % of the R's RMS heat flow."""
        x, y = io_rms(graph, target, scales)
        s = 0.0
        for _, (kind, name) in self.sides(graph, target):
            s += (scales.get("effort_rms", name) if kind == "junction"
                  else scales.get("source_max", name))
        b = abs(float(self.term(sp.Float(x), {"s": sp.Float(s)})))
        return {"beta": (0.1 * y / b, 0.5 * y / b)}
