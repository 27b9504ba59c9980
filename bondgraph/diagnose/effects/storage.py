"""Effects of a C element (a spring, a capacitor, a tank, a heat capacity):
storage limits and alternatives of its constitutive law.

* :class:`EndStop` — a stiff one-sided spring beyond ±q_max (end stops,
  saturation of a travel);
* :class:`CapacityLimit` — a capacity limit with overflow: above q_max the
  excess flow leaves the storage through an overflow law, lost (an R to
  the common effort) or routed to a named 0-junction (another tank);
* :class:`Backlash` — a dead zone in a compliance;
* :class:`CubicStiffness` — Duffing's cubic hardening (k3 > 0) or softening
  (k3 < 0) term of the law, e = k q + k3 q³, with its energy k3 q⁴/4
  (additive: probe-able at k3 = 0).

* :class:`CubicRestoring` — the same cubic effort k3·q³ on a C's
  displacement, acting beside the element (a nonlinear spring in parallel, a
  cubic feedback of an analogue circuit) where a sensor reads the C's
  effort: the sensor keeps reading the declared law (additive).

And of an I element of the electrical domain (an inductor):

* :class:`InductorSaturation` — the iron core's saturation, the cubic term
  of the flux-current law, i = λ/L + k3 λ³ (k3 > 0: the current rises
  faster than the flux once the core saturates), its co-energy k3 λ⁴/4
  (additive).

References
----------
Duffing, G. (1918), Erzwungene Schwingungen bei veränderlicher
Eigenfrequenz, Vieweg. Chua, L. O. & Stromsmoe, K. A. (1970), Lumped-circuit
models for nonlinear inductors exhibiting hysteresis loops, IEEE Trans.
Circuit Theory 17(4) (the polynomial flux-current law). Karnopp, Margolis &
Rosenberg, *System Dynamics*, 5th ed., §4.2 (nonlinear C elements) and §8
(hydraulic tanks and orifices).
"""

from __future__ import annotations

import sympy as sp

from bondgraph.core import units as _units
from bondgraph.core.causality import assign_causality
from bondgraph.core.elements import C, I, One, R, Zero
from bondgraph.core.graph import BondGraph
from bondgraph.core.smooth import sigmoid, softplus
from bondgraph.diagnose.effects.base import (
    Effect,
    EffectParam,
    Scales,
    Target,
    _electrical,
    _in_integral_causality,
    _new_param,
    _Structural,
    default_value,
    element_units,
    fill_unit,
    inductor_targets,
    junction_units,
    log_grid,
    mechanical,
    split_bond,
    state_storage_targets,
    storage_stiffness,
    storage_targets,
)
from bondgraph.errors import GraphError


def storage_unit(graph: BondGraph, el: C) -> str:
    """Unit of a C element's displacement (flow unit × s; "" if unknown)."""
    _, fu = element_units(graph, el)
    return f"({fu})*s" if fu else ""


def _force_on_storage(graph: BondGraph, el: C, tag: str):
    """A 1-junction spliced into the bond of C element ``el`` (same flow as
    the C), so that an extra effort can act on its displacement."""
    return split_bond(graph, el.port.bond, "1", tag)


def _k_default(el: C) -> float:
    """Default value of the C's stiffness (1.0 if unknown)."""
    v = default_value(storage_stiffness(el))
    return abs(v) if v else 1.0


#: the stop stiffness of :class:`EndStop`, in multiples of the storage's own
#: stiffness: the data-driven value, and the factors of it a confirmation
#: tries (a rubber bump stop is a few times its spring, not a wall)
STOP_STIFFNESS = 100.0
STOP_SOFTER = (0.3, 0.1, 0.03)


class EndStop(_Structural):
    """End stops (saturation) of a storage: a one-sided spring beyond
    ±q_max on the displacement of a C element, ``kstop`` times the
    storage's own stiffness (:data:`STOP_STIFFNESS`, a stiff stop; its
    confirmation also tries softer stops, :data:`STOP_SOFTER`, and keeps
    the one the record prefers by a likelihood-ratio test,
    :func:`bondgraph.diagnose.confirm.profiled_shape`: a quarter-car's
    rubber bump stop, 5.6 times its spring, was fitted by a 100-times stop
    beginning 0.0395 m out for a 0.03 m gap, and a cubic stiffness was
    accepted next to make up the difference). The stop is smooth (softplus
    of width q_max/20), so it acts a little below its level: the grid
    reaches beyond the largest displacement seen in the record."""

    name = "end_stop"
    title = "end stops / saturation of a storage"
    target_kind = "storage"
    params = (EffectParam("qmax", "{q}", "free travel each side", nonnegative=True),
              EffectParam("kstop", "1", "stop stiffness / the storage's own stiffness",
                          estimated=False, profile=STOP_SOFTER))

    def shape_values(self, graph, target, scales):
        return {"kstop": STOP_STIFFNESS}

    def targets(self, graph):
        return storage_targets(graph)

    def grid(self, graph, target, scales):
        m = scales.get("storage_max", target.name)
        return [{"qmax": m * f} for f in (0.3, 0.5, 0.7, 0.85, 1.0, 1.1, 1.25)]

    def box(self, graph, target, scales):
        m = scales.get("storage_max", target.name)
        return {"qmax": (0.4 * m, 0.85 * m)}

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        el = graph.element(target.name)
        qmax = _new_param(graph, self.pname(target, "qmax"), values.get("qmax", 1.0),
                          fill_unit("{q}", q=storage_unit(graph, el)), (1e-12, 1e12),
                          f"free travel of {target.name}")
        kstop = _new_param(graph, self.pname(target, "kstop"),
                           values.get("kstop", STOP_STIFFNESS), "", (1e-12, 1e12),
                           f"stop stiffness of {target.name} / its own stiffness")
        ks = kstop * storage_stiffness(el)
        q = el.q
        w = qmax / 20
        j = _force_on_storage(graph, el, f"{self.name}.{target.tag}.j")
        stop = ks * w * (softplus((q - qmax) / w) - softplus((-q - qmax) / w))
        graph.connect(graph.MSe(f"{self.name}.{target.tag}", -stop), j)
        return {"qmax": qmax, "kstop": kstop}


#: the edge width of :class:`Backlash`'s dead zone, in multiples of its half
#: gap: the data-driven value, and the factors of it a confirmation tries
#: (:func:`bondgraph.diagnose.confirm.profiled_shape`)
BACKLASH_EDGE = 0.3
BACKLASH_EDGE_FACTORS = (3.0, 0.3, 0.1)


class Backlash(_Structural):
    """Backlash (dead zone) in a compliance of a mechanical domain: no
    effort while |q| < g, the compliance's own law beyond it,

        e = k w [softplus((q − g)/w) − softplus((−q − g)/w)],   w = s g,

    a dead zone whose edges are rounded over the width w (s = 0.3 of the
    half gap, and the confirmation tries 0.9, 0.09 and 0.03 of it: the
    record's reversals tell a worn gear's soft take-up from a sharp one).
    The law is odd and increasing in q, so the compliance's energy stays
    positive. A damper beside the compliance (an R on the 1-junction of
    its bond, a junction without inertia, the R given its flow) is gated
    by the dead zone's slope σ((q − g)/w) + σ((−q − g)/w): no torque
    through the open gap. A gear pair's dead-zone model without the impact dynamics
    (Nordin & Gutman, "Controlling mechanical systems with backlash — a
    survey", Automatica 38, 2002).

    Before 2026-12 the law was k (q − g tanh(q/g)), which is cubic near
    q = 0 and transmits a quarter of k·g at the edge: on a user's
    two-mass drive with a sharp 15 mrad gap, the loop found the gap
    (15.8 mrad) but needed Dahl and Coulomb friction beside it, and still
    left 6 times the sensor noise on the motor speed of another record; a
    sharp dead zone alone left 5 times less error on the estimation record.
    """

    name = "backlash"
    title = "backlash / dead zone of a compliance"
    target_kind = "storage"
    params = (EffectParam("gap", "{q}", "half gap", nonnegative=True),
              EffectParam("edge", "1", "edge width / half gap", estimated=False,
                          profile=BACKLASH_EDGE_FACTORS))

    def shape_values(self, graph, target, scales):
        return {"edge": BACKLASH_EDGE}

    def targets(self, graph):
        return [t for t in storage_targets(graph)
                if mechanical(element_units(graph, graph.element(t.name))[1]) is not False]

    def grid(self, graph, target, scales):
        m = scales.get("storage_max", target.name)
        return [{"gap": m * f} for f in (0.02, 0.05, 0.1, 0.2, 0.4)]

    def box(self, graph, target, scales):
        m = scales.get("storage_max", target.name)
        return {"gap": (0.05 * m, 0.3 * m)}

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        el = graph.element(target.name)
        g_ = _new_param(graph, self.pname(target, "gap"), values.get("gap", 1.0),
                        fill_unit("{q}", q=storage_unit(graph, el)), (1e-12, 1e12),
                        f"half gap of {target.name}")
        s_ = _new_param(graph, self.pname(target, "edge"), values.get("edge", BACKLASH_EDGE),
                        "", (1e-12, 1e12), f"edge width of {target.name}'s gap / its half gap")
        k = storage_stiffness(el)
        q = el.q
        w = s_ * g_
        dead = w * (softplus((q - g_) / w) - softplus((-q - g_) / w))
        _gate_contact_dampers(graph, el, sigmoid((q - g_) / w) + sigmoid((-q - g_) / w))
        j = _force_on_storage(graph, el, f"{self.name}.{target.tag}.j")
        graph.connect(graph.MSe(f"{self.name}.{target.tag}", k * (q - dead)), j)
        return {"gap": g_, "edge": s_}


def _gate_contact_dampers(graph: BondGraph, el: C, contact) -> list[str]:
    """Multiply the law of every R beside the C element ``el`` (on the
    1-junction of its bond: the same relative flow) that SCAP gives its
    flow, e = φ(f), by ``contact`` (between 0 and 1: the slope of the dead
    zone), so that a shaft's damping, like its spring, transmits no effort
    while the gap is open (Nordin & Gutman 2002, the dead-zone model). The
    power e·f = contact·f·φ(f) keeps φ's sign: the R still dissipates.
    An R that receives its effort is left alone (gating its flow law would
    lock the gap instead of opening it). Only a junction without an I
    element is the compliance's own (a shaft's twist, a coupling's
    deflection): on a mass's junction (a spring to the ground) an R is as
    likely the mass's friction, which no gap interrupts. Returns the gated
    R's names."""
    bond = el.port.bond
    j = bond.other(el.port).element if bond is not None else None
    if not isinstance(j, One):
        return []
    around = [b.other(next(p for p in j.ports if p.bond is b)).element
              for b in graph.bonds_of(j)]
    if any(isinstance(x, I) or getattr(x, "kind", None) == "I" for x in around):
        return []
    rs = [r for r in around if isinstance(r, R) and r.form == "effort"]
    cz = assign_causality(graph, validate=False) if rs else None
    gated = []
    for r in rs:
        if cz.receives_effort(r.port.bond, r):
            continue
        r.law, r.resistance = contact * r.law, None
        gated.append(r.name)
    return gated


class CapacityLimit(_Structural):
    """A storage that cannot hold more than q_max: above it the excess
    leaves through an overflow law
    Q = (w/τ)·[softplus((q − q_max)/w) − softplus(−q_max/w)], which drains
    the excess within the time constant τ (one sample, fixed) and is
    negligible a few widths w (2 % of the largest stored quantity) below the
    limit: a tank's overflow weir, a clamp diode across a capacitor. The
    second term makes the flow zero at an empty storage (q = 0) and of q's
    sign below it, so that the lost overflow dissipates (e·Q ≥ 0 for a
    storage whose effort has q's sign) wherever the fit takes the state:
    without it the softplus tail (w/τ)·e^(−q_max/w) keeps draining an empty
    tank below zero, a source of power the admissibility check refuses
    (a refit whose w was 15 % of q_max: 2e-6 m³/s out of a tank at −339 Pa).

    The overflow is an R element with that flow law on a 0-junction spliced
    into the C's bond (so it sees the C's effort): its power e·Q is lost.
    With ``routes={storage: junction}`` the overflow of that storage passes
    instead through a 1-junction into the named 0-junction (the next tank),
    the R then seeing the effort difference.

    Parameters
    ----------
    routes : dict, optional
        C element name -> name of the 0-junction its overflow goes to; only
        those storages are targets. Default: every C, overflow lost.
    name : str, optional
        Effect name (default ``capacity_limit``, or ``capacity_overflow``
        with routes).
    """

    title = "capacity limit with overflow"
    target_kind = "storage"
    params = (EffectParam("qmax", "{q}", "capacity (largest stored quantity)"),
              EffectParam("w", "{q}", "width of the overflow onset", estimated=False),
              EffectParam("tau", "s", "overflow time constant", estimated=False))

    def __init__(self, routes: dict | None = None, name: str | None = None):
        self.routes = dict(routes or {})
        self.name = name or ("capacity_overflow" if self.routes else "capacity_limit")

    def targets(self, graph):
        out = state_storage_targets(graph)       # the overflow is written in the state q
        if self.routes:
            out = [t for t in out if t.name in self.routes]
        return out

    def shape_values(self, graph, target, scales):
        return {"w": 0.02 * scales.get("storage_max", target.name), "tau": scales.dt}

    def grid(self, graph, target, scales):
        top = scales.get("storage_peak", target.name, scales.get("storage_max", target.name))
        sh = self.shape_values(graph, target, scales)
        return [{"qmax": top * f, **sh} for f in (0.5, 0.7, 0.85, 0.95, 1.0, 1.05, 1.15)]

    def box(self, graph, target, scales):
        top = scales.get("storage_peak", target.name, scales.get("storage_max", target.name))
        return {"qmax": (0.5 * top, 0.9 * top)}

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        el = graph.element(target.name)
        unit = fill_unit("{q}", q=storage_unit(graph, el))
        shapes = self.shape_values(graph, target, scales or Scales())
        P = {}
        for spc, u in zip(self.params, (unit, unit, "s")):
            P[spc.name] = _new_param(graph, self.pname(target, spc.name),
                                     values.get(spc.name, shapes.get(spc.name, 1.0)), u,
                                     (-1e15, 1e15) if spc.name == "qmax" else (1e-15, 1e15),
                                     f"{spc.description} of {target.name}")
        w, tau = P["w"], P["tau"]
        overflow = w / tau * (softplus((el.q - P["qmax"]) / w) - softplus(-P["qmax"] / w))
        z = split_bond(graph, el.port.bond, "0", f"{self.name}.{target.tag}.j")
        r = graph.R(f"{self.name}.{target.tag}", flow=lambda e: overflow)
        dest = self.routes.get(target.name)
        if dest is None:
            graph.connect(z, r)
        else:
            j2 = graph.element(dest)
            if not isinstance(j2, Zero):
                raise TypeError(f"capacity overflow of '{target.name}' must go to a 0-junction, "
                                f"'{dest}' is {j2.kind}")
            one = graph.one(f"{self.name}.{target.tag}.path")
            graph.connect(z, one)
            graph.connect(one, j2)
            graph.connect(one, r)
        return P


class CubicStiffness(Effect):
    """Duffing's cubic stiffness of a C element: its law gains k3·q³ (its
    energy k3·q⁴/4), hardening for k3 > 0, softening for k3 < 0: a
    progressive spring, a nonlinear capacitor, a tank whose cross-section
    changes with the level. Additive: probe-able at k3 = 0."""

    name = "cubic_stiffness"
    title = "cubic (Duffing) stiffness"
    target_kind = "storage"
    additive = True
    params = (EffectParam("k3", "{effort}/{q}^3", "cubic stiffness coefficient"),)

    def targets(self, graph):
        return storage_targets(graph)

    def apply(self, graph, target, values=None, scales=None):
        el = graph.element(target.name)
        eu, _ = element_units(graph, el)
        return _add_cubic_term(graph, self, target, values,
                               fill_unit("{effort}/{q}^3", effort=eu, q=storage_unit(graph, el)),
                               "cubic stiffness")

    def basis(self, graph, target, scales):
        return [storage_variable(graph.element(target.name)) ** 3]

    def box(self, graph, target, scales):
        m = scales.get("storage_max", target.name)
        k = _k_default(graph.element(target.name))
        return {"k3": (0.05 * k / m**2, 0.3 * k / m**2)}


class CubicRestoring(Effect):
    """A cubic restoring effort k3·q³ on the displacement q of a C element
    whose effort a sensor reads, acting *beside* the element: on a
    1-junction spliced into the C's bond (the C's flow, so the same
    displacement), as a modulated effort source −k3·q³, so the effort
    balance sees k q + k3 q³ while the sensor still reads the C's own law.

    Why beside: :class:`CubicStiffness` writes the term into the C's law,
    and a sensor that reads the C's effort (a capacitor's voltage, a tank's
    pressure, a load cell on the spring) then reads it too. Which is right
    is physics the record has to decide: a nonlinear capacitor or a tank
    whose cross-section changes with the level changes the reading; a
    nonlinear spring in parallel with a measured one, or the cubic feedback
    of an electronic Duffing oscillator whose output voltage is the
    capacitor's (the Silverbox declared as a series RLC circuit), does not.
    Where no sensor reads the C's effort the two are the same model, so this
    effect attaches only where one does (:func:`measured_storage_targets`).

    Hardening only (k3 >= 0): the term's energy k3 q⁴/4 is then convex and
    the model passive whatever the C's law; the loop's admissibility check
    does not see a modulated source. Additive: probe-able at k3 = 0 on the
    spliced junction (probe site ``beside``).

    References
    ----------
    Duffing (1918); Karnopp, Margolis & Rosenberg, *System Dynamics*, 5th ed.,
    §4.2 (C elements in parallel on a 1-junction share the displacement).
    """

    name = "cubic_restoring"
    title = "cubic restoring effort beside a measured C"
    target_kind = "storage"
    additive = True
    params = (EffectParam("k3", "{effort}/{q}^3", "cubic restoring coefficient",
                          nonnegative=True),)

    def targets(self, graph):
        return measured_storage_targets(graph)

    def probe_site(self, graph, target):
        return ("beside", target.name)

    def apply(self, graph, target, values=None, scales=None):
        el = graph.element(target.name)
        eu, _ = element_units(graph, el)
        k3 = _new_param(graph, self.pname(target, "k3"), dict(values or {}).get("k3", 0.0),
                        fill_unit("{effort}/{q}^3", effort=eu, q=storage_unit(graph, el)),
                        (0.0, 1e15), f"cubic restoring effort beside {target.name}")
        install_beside(graph, el, f"{self.name}.{target.tag}", -k3 * el.q**3)
        return {"k3": k3}

    def basis(self, graph, target, scales):
        return [-graph.element(target.name).q ** 3]

    def box(self, graph, target, scales):
        return CubicStiffness().box(graph, target, scales)


def measured_storage_targets(graph: BondGraph) -> list:
    """The C elements in integral causality (:func:`state_storage_targets`)
    whose own effort ``.e`` a sensor expression holds, in a mechanical or electrical domain or one
    whose units the graph does not say. A sensor on the common effort of a
    0-junction the C sits on is not one: the effort beside the C is in
    series with it, so that sensor reads the sum, as it reads
    :class:`CubicStiffness`. Not in a thermal or hydraulic graph: a
    temperature or pressure in series with a heat capacity or a tank that
    depends on its stored heat or volume is no element of those domains (a
    heat capacity that changes with temperature, a tank whose section
    changes with the level, is the law's cubic, which the sensor reads)."""
    read = set()
    for s in graph.sensors.values():
        read |= set(getattr(s.expr, "free_symbols", ()))
    out = []
    for t in storage_targets(graph):
        el = graph.element(t.name)
        fu = element_units(graph, el)[1]
        if el.e in read and (not fu or mechanical(fu) or _electrical(graph, el)):
            out.append(t)
    # the term is written in the state q: integral causality only (SCAP is
    # run only for a graph that has such a C)
    return _in_integral_causality(graph, out) if out else []


def install_beside(graph: BondGraph, el: C, name: str, effort: sp.Expr) -> None:
    """A modulated effort source of value ``effort`` on a 1-junction
    spliced into C element ``el``'s bond (``name``.j; the MSe ``name``),
    its sign taken with the bond's power direction so that ``-effort``
    adds to the effort the C's side of the junction presents."""
    j = split_bond(graph, el.port.bond, "1", f"{name}.j")
    graph.connect(graph.MSe(name, el.port.bond.sign_at(el) * effort), j)


def add_to_storage_law(el: C | I, term: sp.Expr, energy: sp.Expr) -> None:
    """Add ``term`` to a storage element's law (a C's effort, a function of
    its displacement; an I's flow, of its momentum) and ``energy`` (its
    integral) to its stored energy (co-energy)."""
    el.law = el.law + term
    if el.energy is not None:
        el.energy = el.energy + energy


def storage_variable(el: C | I) -> sp.Symbol:
    """The energy variable of a storage element: an I's momentum, a C's
    displacement."""
    return el.p if isinstance(el, I) else el.q


def _add_cubic_term(graph: BondGraph, eff: Effect, target, values, unit: str,
                    what: str) -> dict:
    """``eff``'s cubic term k3·x³ (energy k3·x⁴/4) in the law of the storage
    element at ``target`` (x: :func:`storage_variable`), k3 a new parameter
    in ``unit`` (start ``values["k3"]``, default 0)."""
    el = graph.element(target.name)
    x = storage_variable(el)
    k3 = _new_param(graph, eff.pname(target, "k3"), dict(values or {}).get("k3", 0.0), unit,
                    (-1e15, 1e15), f"{what} of {target.name}")
    add_to_storage_law(el, k3 * x**3, k3 * x**4 / 4)
    return {"k3": k3}


class InductorSaturation(Effect):
    """Saturation of an inductor's iron core: its flux-current law gains
    the cubic term k3·λ³, i = λ/L + k3·λ³ (λ: the I element's momentum, the
    flux linkage; co-energy k3·λ⁴/4), so that the current rises faster than
    the flux once the core saturates (k3 > 0): the dual of a hardening
    spring on an I element. Only at I elements of the electrical domain (a
    mass or a fluid inertance does not saturate). Additive: probe-able at
    k3 = 0 (Chua & Stromsmoe 1970, the polynomial law)."""

    name = "inductor_saturation"
    title = "saturating inductor (cubic flux-current law)"
    target_kind = "storage"
    additive = True
    params = (EffectParam("k3", "{flow}/({effort}*s)^3", "cubic flux-current coefficient"),)

    def targets(self, graph):
        return inductor_targets(graph)

    def apply(self, graph, target, values=None, scales=None):
        eu, fu = element_units(graph, graph.element(target.name))
        return _add_cubic_term(graph, self, target, values,
                               fill_unit("{flow}/({effort}*s)^3", flow=fu, effort=eu),
                               "cubic flux-current coefficient")

    def basis(self, graph, target, scales):
        return [storage_variable(graph.element(target.name)) ** 3]

    def box(self, graph, target, scales):
        m = scales.get("storage_max", target.name)
        el = graph.element(target.name)
        a = abs(default_value(el.inertance)) if el.inertance is not None else 0.0
        g = 1.0 / a if a else 1.0
        return {"k3": (0.05 * g / m**2, 1.0 * g / m**2)}


#: domains whose 1-junctions sum potentials along a path, where an RC pair in
#: series is a relaxation the model may lack (a cell's diffusion, a Foster
#: network's stage); in mechanics the same pair (a Maxwell element) is what
#: :class:`~bondgraph.diagnose.effects.coupling.Compliance` and Dahl's
#: friction cover
RELAXATION_DOMAINS = ("electrical", "heat")


def _relaxation_domain(graph: BondGraph, j) -> str | None:
    """``"electrical"`` or ``"heat"`` for a junction of those domains (its
    declared domain, else its bonds' units: a current as flow, or a
    temperature x heat-flow bond), None otherwise."""
    if j.domain is not None:
        return j.domain if j.domain in RELAXATION_DOMAINS else None
    eu, fu = junction_units(graph, j)
    if not (eu and fu):
        return None
    try:
        if _units.same_dimension(fu, "A") and _units.same_dimension(eu, "V"):
            return "electrical"
        if _units.is_pseudo_power(eu, fu):
            return "heat"
    except Exception:
        return None
    return None


class SeriesRC(_Structural):
    """An RC pair in series with a path's resistance: a 0-junction with a
    resistance R and a capacitance C = τ/R spliced onto the 1-junction
    (a Voigt stage), whose effort e = q·R/τ, dq/dt = f − q/τ, adds to the
    path's efforts: R·f in a steady flow, nothing at a sudden change.

    What it stands for: the second (third ...) RC pair of a battery cell's
    Thevenin model (solid-phase diffusion beside the charge transfer;
    Plett 2015, §2.10; Hu, Li & Peng 2012 compare one to three pairs), a
    capacitor's dielectric absorption, a stage of a Foster network of a
    thermal impedance (a heat path's slow layer; JEDEC JESD51-14). It
    attaches to a 1-junction of the electrical or heat domain
    (:data:`RELAXATION_DOMAINS`) that carries an R (a series path with
    a loss), once per junction. R >= 0 (at 0 the pair vanishes) and
    τ > 0 keep it passive: its R dissipates, its C stores q²/(2C) >= 0.
    Structural (a new state): scored over a grid of τ (half a sample to
    a tenth of the record) and of R (0.3 to 3 times the junction's own
    resistance, its R's RMS effort over RMS flow).
    """

    name = "series_rc"
    title = "added RC pair in series (a relaxation)"
    target_kind = "junction"
    params = (EffectParam("R", "{effort}/{flow}", "resistance of the pair", nonnegative=True),
              EffectParam("tau", "s", "time constant R·C of the pair", nonnegative=True))

    def targets(self, graph):
        out = []
        for name in sorted(graph.elements):
            el = graph.elements[name]
            if not isinstance(el, One) or name.startswith(f"{self.name}."):
                continue
            if _relaxation_domain(graph, el) is None:
                continue
            if any(isinstance(p.bond.other(p).element, R) for p in el.ports
                   if p.bond is not None):
                out.append(Target("junction", name))
        return out

    def _resistance(self, graph, target, scales) -> float:
        """The junction's own resistance scale: the largest RMS effort over
        RMS flow of its R elements (1.0 when the record gives none)."""
        j = graph.element(target.name)
        vals = []
        for p in j.ports:
            other = p.bond.other(p).element if p.bond is not None else None
            if isinstance(other, R):
                e = scales.r_effort_rms.get(other.name)
                f = scales.r_flow_rms.get(other.name)
                if e and f and e > 0 and f > 0:
                    vals.append(float(e) / float(f))
        return max(vals) if vals else 1.0

    def grid(self, graph, target, scales):
        r = self._resistance(graph, target, scales)
        taus = log_grid(0.5 * scales.dt, 0.1 * scales.duration, 8)
        return [{"R": r * k, "tau": t} for t in taus for k in (0.3, 1.0, 3.0)]

    def box(self, graph, target, scales):
        r = self._resistance(graph, target, scales)
        return {"R": (0.1 * r, 3.0 * r), "tau": (2 * scales.dt, 0.05 * scales.duration)}

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        j = graph.element(target.name)
        if not isinstance(j, One):
            raise GraphError(f"series_rc attaches to a 1-junction, not '{target.name}'")
        eu, fu = junction_units(graph, j)
        tag = f"{self.name}.{target.tag}"
        Rp = _new_param(graph, self.pname(target, "R"), values.get("R", 1.0),
                        fill_unit("{effort}/{flow}", effort=eu, flow=fu), (0.0, 1e15),
                        f"resistance of the RC pair added in series at {target.name}")
        tau = _new_param(graph, self.pname(target, "tau"), values.get("tau", 1.0), "s",
                         (1e-9, 1e12), f"time constant of the RC pair at {target.name}")
        z = graph.zero(f"{tag}.j", domain=j.domain)
        graph.connect(j, z)
        graph.connect(z, graph.C(f"{tag}.C", tau / Rp))
        graph.connect(z, graph.R(f"{tag}.R", Rp))
        return {"R": Rp, "tau": tau}
