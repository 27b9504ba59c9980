"""The effect base class, attachment targets, data scales and the helpers the
effect families share (units of a junction, splicing a junction into a bond,
declaring an effect's parameters, finding attachment points).

An effect is a bond-graph fragment with units and a declared parameter box
(:meth:`Effect.box`); :meth:`Effect.targets` finds where the physics admits
it in a graph, :meth:`Effect.apply` splices it into a copy of the graph.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
import sympy as sp

from bondgraph.core import units as _units
from bondgraph.core.causality import assign_causality
from bondgraph.core.elements import C, I, Junction, One, OnePort, Port, R, Source, Zero
from bondgraph.core.graph import Bond, BondGraph
from bondgraph.core.symbols import Input, Parameter
from bondgraph.errors import BondGraphError, GraphError

#: the source of every parameter an effect adds
ADDED_BY = "added by the residual-tracing loop"


# ------------------------------------------------------------------ targets
@dataclass(frozen=True)
class Target:
    """Where an effect attaches.

    kind : {"junction", "source", "sensor", "storage", "bond", "resistor", "input"}
    name : element, sensor, bond or input name
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

    flow_rms, flow_max : dict
        1-junction name -> RMS and max |flow| over the record.
    output_rms : dict
        Sensor name -> RMS of the measured output.
    source_max : dict
        Source name -> max |source value|.
    storage_max, storage_rms : dict
        C element name -> max |q| and RMS of q along the filtered states.
    r_effort_rms, r_flow_rms : dict
        R element name -> RMS of its effort and of its flow.
    input_max : dict
        Input name -> max |u|.
    force_rms : dict
        1-junction name -> RMS of the net effort on its inertia (the rate
        of its momentum state).
    storage_peak : dict
        C element name -> max q (signed) along the filtered states.
    source_rate : dict
        Source name -> max |d value/dt| over the record (finite differences).
    source_power : dict
        Source name -> mean |e·f| of its bond over the record (the power it
        delivers, in W when the graph has units).
    effort_min, effort_rms : dict
        0-junction name -> least value and RMS of its effort over the record
        (an absolute temperature stays far above 0; the least value after
        the filter's start, :func:`bondgraph.diagnose.scales.settled`).
    source_min : dict
        Source name -> least value over the record (after the filter's
        start).
    duration, dt : float
        Record length and median sample interval [s].
    """

    flow_rms: dict = field(default_factory=dict)
    flow_max: dict = field(default_factory=dict)
    output_rms: dict = field(default_factory=dict)
    source_max: dict = field(default_factory=dict)
    storage_max: dict = field(default_factory=dict)
    storage_rms: dict = field(default_factory=dict)
    r_effort_rms: dict = field(default_factory=dict)
    r_flow_rms: dict = field(default_factory=dict)
    input_max: dict = field(default_factory=dict)
    force_rms: dict = field(default_factory=dict)
    storage_peak: dict = field(default_factory=dict)
    source_rate: dict = field(default_factory=dict)
    source_power: dict = field(default_factory=dict)
    effort_min: dict = field(default_factory=dict)
    effort_rms: dict = field(default_factory=dict)
    source_min: dict = field(default_factory=dict)
    duration: float = 1.0
    dt: float = 0.01

    def v(self, junction: str) -> float:
        """RMS flow of a 1-junction (1.0 if unknown; at least 1e-9)."""
        return max(float(self.flow_rms.get(junction, 1.0)), 1e-9)

    def get(self, table: str, name: str, default: float = 1.0) -> float:
        """``getattr(self, table)[name]`` as a positive float (``default``
        if missing, at least 1e-12)."""
        return max(float(getattr(self, table).get(name, default)), 1e-12)


@dataclass
class EffectParam:
    """A parameter of an effect: local name, unit template, description,
    default (or None: set from the data), bounds (or None: from the data),
    and whether the loop estimates it (shape constants such as tanh widths
    are fixed).

    ``unit`` may use ``{effort}``, ``{flow}`` (of the target's bond),
    ``{y}`` (of a sensor), ``{u}`` (of an input or source), ``{q}`` (of a
    storage's displacement)."""

    name: str
    unit: str = ""
    description: str = ""
    estimated: bool = True
    nonnegative: bool = False
    #: fixed box of a dimensionless fraction (e.g. (0, 1)); None: the loop
    #: sets the box around the start value
    bounds: tuple[float, float] | None = None
    #: an estimate on a bound of this parameter's box is no finding of the
    #: effect (a power law's exponent at the end of the exponents it covers:
    #: the record asks for something beyond the effect's family), and the
    #: accept rule refuses it (:func:`bondgraph.diagnose.accept.decide`)
    interior: bool = False
    #: factors of the data-driven shape value (``shape_values``) that a
    #: confirmation refit tries beside it, for a fixed shape constant whose
    #: value the record can tell (a tanh width of a sign function); the
    #: width kept is counted as one more parameter of the effect
    #: (:func:`bondgraph.diagnose.confirm.profiled_shape`)
    profile: tuple[float, ...] = ()


# ------------------------------------------------------------------ helpers
def junction_units(graph: BondGraph, junction: Junction) -> tuple[str, str]:
    """Effort and flow unit of the bonds of ``junction`` ("" if unknown)."""
    bu = graph.bond_units()
    for b in graph.bonds_of(junction):
        e, f = bu[b.name]
        if e or f:
            return e or "", f or ""
    return junction.effort_unit or "", junction.flow_unit or ""


def element_units(graph: BondGraph, el: OnePort) -> tuple[str, str]:
    """Effort and flow unit of a one-port's bond ("" if unknown)."""
    b = el.port.bond
    if b is None:
        return "", ""
    e, f = graph.bond_units().get(b.name, (None, None))
    return e or "", f or ""


def fill_unit(template: str, **units: str) -> str:
    """Unit of an effect parameter from its template: ``{effort}``,
    ``{flow}``, ``{y}``, ``{u}``, ``{q}`` replaced by the given units; ""
    (unknown) if the template needs a unit that is unknown."""
    if not template:
        return ""
    out = template
    for key, unit in units.items():
        token = "{" + key + "}"
        if token in out:
            if not unit:
                return ""
            out = out.replace(token, f"({unit})")
    return "" if "{" in out else out


def _unit(template: str, effort: str, flow: str) -> str:
    """:func:`fill_unit` with the effort and flow unit of a bond."""
    return fill_unit(template, effort=effort, flow=flow)


def source_junction(graph: BondGraph, src: OnePort) -> Junction | None:
    """The junction a source is bonded to (None if it is bonded elsewhere)."""
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


def is_mechanical_junction(graph: BondGraph, j: Junction) -> bool | None:
    """True if ``j`` belongs to a mechanical domain (translation, rotation),
    by its declared domain or by its flow unit; None if unknown."""
    if j.domain in ("translation", "rotation"):
        return True
    if j.domain is not None:
        return False
    _, fu = junction_units(graph, j)
    return mechanical(fu)


def split_bond(graph: BondGraph, bond: Bond, kind: str, name: str) -> Junction:
    """Insert a new junction into ``bond`` keeping its power direction:
    ``tail -> new -> head``. Returns the new junction (``kind`` "0" or "1").

    Raises
    ------
    GraphError
        If the bond is not in the graph, or the split would reverse power.
    """
    if bond not in graph.bonds:
        raise GraphError(f"bond '{bond.name}' is not in graph '{graph.name}'")
    tail, head = bond.tail, bond.head
    graph.bonds.remove(bond)
    for p in (tail, head):
        p.bond = None
        if isinstance(p.element, Junction):
            p.element.ports.remove(p)
    j = graph.zero(name) if kind == "0" else graph.one(name)
    a = tail if not isinstance(tail.element, Junction) else tail.element
    b = head if not isinstance(head.element, Junction) else head.element
    graph.connect(a if isinstance(a, Port) else a, j)
    graph.connect(j, b)
    # connect() orients bonds by element convention; check the direction held
    b1, b2 = graph.bonds[-2], graph.bonds[-1]
    if b1.head.element is not j or b2.tail.element is not j:
        raise GraphError(f"cannot split bond '{bond.name}' without reversing power")
    return j


def _new_param(graph: BondGraph, name: str, default: float, unit: str, bounds, description: str,
               source: str = ADDED_BY) -> Parameter:
    """Declare an effect parameter (``GraphError`` if the graph has it: the
    effect was added twice). A ``default`` outside the effect's fixed box
    ``bounds`` starts on the box's nearer edge: the default is the score
    test's guess, the box the effect's physics (a user's CED graph: the
    actuator gain's score step gave g = −8.02 for g ∈ [−0.9, 2], and the
    candidate, third of 37, was dropped as "cannot apply")."""
    if name in graph.params:
        raise GraphError(f"graph '{graph.name}' already has parameter '{name}': effect added twice?")
    if bounds is not None and isinstance(default, (int, float)) and np.isfinite(default):
        bounds = reach_guards(bounds, float(default))
        lo, hi = (-np.inf if bounds[0] is None else bounds[0],
                  np.inf if bounds[1] is None else bounds[1])
        if lo <= hi:
            default = float(np.clip(default, lo, hi))
    return graph.param(name, default, unit, bounds, description, source)


#: a fixed box edge at least this large in magnitude (or, for a positive
#: lower edge, at most its inverse) is a numeric guard, not physics
GUARD = 1e9


def reach_guards(bounds, default: float) -> tuple:
    """An effect's fixed box ``bounds`` with its numeric guards moved to
    reach ``default``: an edge of magnitude >= :data:`GUARD` (1e12, 1e15:
    "finite") or a positive lower edge <= 1/:data:`GUARD` (1e-12:
    "positive") says nothing about the physics, which lies in the sign and
    in the declared edges, and it depends on the units. A start beyond one
    moves it to 1e3 times beyond the start. A user's hydraulic hose: the
    score test put a cubic stiffness at 4e20 Pa/m⁹ (its volume ~1e-5 m³),
    the guard ±1e15 clipped the start, and the refit's box (±20 times the
    start) ended at 2e16, where the refit stopped on the box edge.

    Parameters
    ----------
    bounds : (lower, upper)
        The effect's fixed box, in the parameter's unit; an edge may be
        None (unbounded).
    default : float
        The start value, in the same unit.

    Returns
    -------
    tuple
        ``(lower, upper)``: ``bounds`` with a guard the start lies beyond
        moved past it (the other edges as given).
    """
    lo, hi = bounds
    if hi is not None and abs(hi) >= GUARD and default > hi:
        hi = 1e3 * default
    if lo is not None and lo <= -GUARD and default < lo:
        lo = 1e3 * default
    elif lo is not None and 0.0 < lo <= 1.0 / GUARD and 0.0 < default < lo:
        lo = default / 1e3
    return (lo, hi)


def _box(default: float, spc: EffectParam) -> tuple[float, float]:
    """Default search box of an effect parameter: ±10 |default| (from 0 if
    nonnegative)."""
    scale = abs(default) if default else 1.0
    if spc.nonnegative:
        return (0.0, max(10.0 * scale, 1e-9))
    return (-10.0 * scale, 10.0 * scale)


def default_value(expr: sp.Expr) -> float | None:
    """Value of an expression of parameters at their defaults (None if it
    has other symbols)."""
    try:
        return float(expr.subs({s: s.default for s in expr.free_symbols
                                if isinstance(s, Parameter)}))
    except (TypeError, ValueError):
        return None


def storage_stiffness(el: C) -> sp.Expr:
    """The (linear) stiffness of a C element: k, 1/C, or ∂e/∂q at q = 0 of
    a nonlinear law (1 if that is zero or unknown)."""
    if el.stiffness is not None:
        return el.stiffness
    if el.compliance is not None:
        return 1 / el.compliance
    k = sp.diff(el.law, el.q).subs(el.q, 0)
    return k if k != 0 else sp.Integer(1)


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
    last_resort : bool
        Considered only when no physical effect is significant (a
        random-walk disturbance can absorb any model error).
    limits : dict
        ``{parameter: (side, effect)}``: at that end (``"upper"`` or
        ``"lower"``) of the parameter's span the effect becomes the other
        effect at the same place (Dahl friction at an infinite rest stiffness
        is Coulomb friction); a candidate scored there is reported
        equivalent to it (:func:`bondgraph.diagnose.scoring.mark_limits`).
    """

    name = "effect"
    title = "effect"
    target_kind = "junction"
    params: tuple[EffectParam, ...] = ()
    additive = False
    last_resort = False
    limits: dict = {}

    # --- discovery
    def targets(self, graph: BondGraph) -> list[Target]:
        """Where the effect can attach in ``graph``."""
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

    def search_boxed(self) -> tuple[str, ...]:
        """Local names of the estimated parameters whose box :meth:`apply`
        sets around the start value it is given (the score test's estimate,
        ±10 times it, :func:`_box`) rather than from the effect's physics.

        Such a box is a search range, not a physical limit: an estimate on
        its edge (the upper edge only for a ``nonnegative`` parameter, whose
        0 is the effect switched off) is decided by the box, not by the
        record, and the loop refuses the candidate when opening the box
        gains the likelihood (:func:`bondgraph.diagnose.runner.search_box_deciding`).

        The base class names, for an additive effect, every estimated
        parameter without declared ``bounds``: its confirmation refits set
        that box to ±20 times the start, whatever :meth:`apply` set
        (:func:`bondgraph.diagnose.confirm.widen_boxes`). A quadratic
        armature law on a user's belt drive (CED) was accepted with β on
        that edge (5.25, 20 times its start; opened, it ran to the new edge)
        while a pair refit ending on a box was refused. A structural effect
        names them too (:meth:`_Structural.search_boxed`)."""
        if not self.additive:
            return ()
        return tuple(p.name for p in self.params if p.estimated and p.bounds is None)

    def box(self, graph: BondGraph, target: Target, scales: Scales) -> dict[str, tuple[float, float]]:
        """The declared box of each estimated parameter, in its unit, from
        the graph (stiffness, inertia ...) and the data scales: the range of
        physically plausible values of the effect at this target (the
        effect-recovery benchmark draws its truths inside it)."""
        return {}

    # --- probe (additive effects only)
    def basis(self, graph: BondGraph, target: Target, scales: Scales) -> list[sp.Expr]:
        """Basis functions b_k, one per estimated parameter, so that the
        effect equals Σ β_k b_k (sign convention of the probe site)."""
        raise NotImplementedError

    def probe_site(self, graph: BondGraph, target: Target) -> tuple[str, str]:
        """Where the probe adds Σ β_k b_k: ``("junction", name)`` (an effort
        on a 1-junction), ``("sensor", name)`` (added to the measurement),
        ``("source", name)`` (added to a source's value), ``("resistor",
        name)`` (added to an R's law in its causal form), ``("storage",
        name)`` (added to a C's effort law) or ``("beside", name)`` (an
        effort on a 1-junction spliced into the C's bond)."""
        if self.target_kind in ("junction", "sensor", "resistor", "storage"):
            return (self.target_kind, target.name)
        if hasattr(self, "probe_junction"):  # effects written before probe sites
            return ("junction", self.probe_junction(graph, target).name)
        raise NotImplementedError(f"effect '{self.name}' names no probe site")

    def natural_points(self, target: Target) -> list[dict[str, float]]:
        """Values of the estimated parameters worth trying in the line probe
        besides multiples of the one-step estimate (e.g. full rectification)."""
        return []

    def pname(self, target: Target, local: str) -> str:
        """Full name of a parameter of this effect at ``target``."""
        return f"{self.name}.{target.tag}.{local}"

    def present(self, graph: BondGraph, target: Target) -> bool:
        """True if this effect is already in ``graph`` at ``target``, or
        ``target`` is part of what this effect added (its elements are named
        ``<effect>.<place>...``): the same effect on its own fragment is a
        reparametrisation of the one there (a gain error of the gain error's
        source, (1 + g₁ + g₁g₂)·u, flat along g₁, g₂; a diode-clamped RC
        network's loop scored it at χ² 382 and 775 in two steps)."""
        if str(target.name).startswith(f"{self.name}."):
            return True
        return any(self.pname(target, p.name) in graph.params for p in self.params)

    def describe(self, target: Target) -> str:
        """``"<title> at <target>"``."""
        return f"{self.title} at {target}"

    def refit_violations(self, graph: BondGraph, target: Target, fit, inputs, t) -> list:
        """What this effect's laws break at a refit beyond what the loop's
        admissibility check of its R, C and I laws sees
        (:func:`bondgraph.numerics.admissible.check_admissible`): a list of
        :class:`~bondgraph.numerics.admissible.Violation` (empty: nothing).
        ``graph`` is the graph the effect was added to, ``fit`` the refit
        (its graph, model, θ and filtered states), ``inputs`` (N, n_u) and
        ``t`` (N,) [s] the record's. The library's effects are R, C, I laws
        or sources with boxes that keep them passive: nothing to add."""
        return []


class _Structural(Effect):
    """Effects without a neutral value of their parameters; scored by a
    likelihood-ratio fit over ``grid(scales)`` (values of the first
    parameter)."""

    additive = False
    #: how far beyond its grid a positive parameter may move when refitted
    GRID_REACH = 4.0

    def search_boxed(self) -> tuple[str, ...]:
        """Every estimated parameter without declared ``bounds``: its
        confirmation refits set its box to the start ×/÷ 100 within the
        grid's reach (:func:`bondgraph.diagnose.confirm.widen_boxes`,
        :meth:`grid_span`), no physical limit. An edge where the effect
        fades out (a lag of no length, a limit never reached) is no reason
        to refuse: there the likelihood gains nothing beyond it
        (:func:`bondgraph.diagnose.runner.search_box_deciding`). On a user's
        belt drive (CED) a power-law armature term was accepted with β on
        the top of its grid's reach; opened, it gained 15.6 nats."""
        return tuple(p.name for p in self.params if p.estimated and p.bounds is None)

    def grid(self, graph, target, scales) -> list[dict[str, float]]:
        """Values of the estimated parameters to evaluate (a list of dicts)."""
        raise NotImplementedError

    def grid_span(self, graph, target, scales) -> dict[str, tuple[float, float]]:
        """Box of each estimated parameter whose grid values are all
        positive: from the smallest grid value / :attr:`GRID_REACH` to the
        largest × :attr:`GRID_REACH`. The refits of a structural candidate
        (profile, confirmation) stay inside it: the grid spans the values
        the effect means, and beyond it a parameter can turn the effect
        into another one (an input delay of 4.7 s on a 1 s record, whose
        Padé states with their small process noise then act as an
        unmeasured disturbance)."""
        grid = self.grid(graph, target, scales)
        out = {}
        for p in self.params:
            vals = [float(g[p.name]) for g in grid if p.name in g]
            if p.estimated and vals and min(vals) > 0:
                out[p.name] = (min(vals) / self.GRID_REACH, max(vals) * self.GRID_REACH)
        return out


def log_grid(lo: float, hi: float, n: int) -> list[float]:
    """``n`` log-spaced values from ``lo`` to ``hi`` (both > 0)."""
    if n == 1:
        return [lo]
    return [lo * (hi / lo) ** (k / (n - 1)) for k in range(n)]


def time_constant_grid(scales: "Scales") -> list[dict[str, float]]:
    """Grid of a first-order time constant ``tau`` (a lag or low-pass):
    8 log-spaced values from half a sample to 5 % of the record."""
    return [{"tau": t} for t in log_grid(0.5 * scales.dt, 0.05 * scales.duration, 8)]


def time_constant_box(scales: "Scales") -> dict[str, tuple[float, float]]:
    """Box of a first-order time constant ``tau``: one sample to
    min(20 samples, 2 % of the record)."""
    return {"tau": (scales.dt, min(20 * scales.dt, 0.02 * scales.duration))}


# ------------------------------------------------------------ target finders
def _flow_imposed(el: One) -> bool:
    """True if a flow source is bonded to the 1-junction ``el``."""
    return any(isinstance(b.other(p).element, Source) and b.other(p).element.variable == "flow"
               for p in el.ports if (b := p.bond) is not None)


def _has_inertia(el: Junction) -> bool:
    return any(isinstance(p.bond.other(p).element, I) for p in el.ports if p.bond is not None)


def _one_junctions(graph: BondGraph, mechanical_only: bool = True) -> list[Target]:
    """1-junctions carrying an inertia (the velocity of a mass): where a
    velocity-dependent force can act. Massless junctions (a sheave whose
    speed a damper sets) are skipped: a second resistive law there closes an
    algebraic loop."""
    out = []
    for name in sorted(graph.elements):
        el = graph.elements[name]
        if not isinstance(el, One) or not _has_inertia(el) or _flow_imposed(el):
            continue
        if mechanical_only and is_mechanical_junction(graph, el) is False:
            continue
        out.append(Target("junction", name))
    return out


def flow_junctions(graph: BondGraph, mechanical_only: bool = True) -> list[Target]:
    """Every 1-junction whose flow the states fix (an inertia on it, or a
    relative velocity of inertias, e.g. the junction of a spring-damper
    between two masses), so that a resistive law added there receives the
    flow and returns an effort: :func:`_one_junctions` plus the massless
    junctions where a test R with a linear law gets flow-in causality and
    closes no algebraic loop (checked by SCAP on a copy)."""
    base = _one_junctions(graph, mechanical_only)
    names = {t.name for t in base}
    out = list(base)
    for name in sorted(graph.elements):
        el = graph.elements[name]
        if name in names or not isinstance(el, One) or _flow_imposed(el):
            continue
        if mechanical_only and is_mechanical_junction(graph, el) is not True:
            continue
        if _r_gets_flow(graph, name):
            out.append(Target("junction", name))
    return sorted(out, key=lambda t: t.name)


def _r_gets_flow(graph: BondGraph, junction: str) -> bool:
    """SCAP on a copy with a linear R bonded to ``junction``: True if the R
    receives the flow, none of the graph's R elements is left with an
    arbitrary causality, and the storages keep their causality."""
    try:
        base = assign_causality(graph, validate=False)
        g = graph.copy(f"{graph.name}__rtest")
        r = g.R("__rtest", 1)
        g.connect(g.element(junction), r)
        cz = assign_causality(g, validate=False)
    except BondGraphError:
        return False
    if cz.receives_effort(r.port.bond, r) or cz.arbitrary:
        return False
    return sorted(cz.derivative) == sorted(base.derivative)


def input_sources(graph: BondGraph, variable: str | None = "effort") -> list[Target]:
    """Sources (Se, MSe, Sf, MSf; only effort or flow ones if ``variable``
    says so) whose value reads an input and that are bonded to a junction:
    the actuators (not gravity, which reads a state, nor constants); the
    loop's own offset and probe sources are skipped."""
    out = []
    for name in sorted(graph.elements):
        el = graph.elements[name]
        if not isinstance(el, Source) or (variable is not None and el.variable != variable):
            continue
        if name.startswith(("offset.", "probe.")):
            continue
        if any(isinstance(s, Input) for s in el.value.free_symbols) and \
                source_junction(graph, el) is not None:
            out.append(Target("source", name))
    return out


def storage_targets(graph: BondGraph) -> list[Target]:
    """Every C element (one-port capacitance)."""
    return [Target("storage", n) for n in sorted(graph.elements)
            if isinstance(graph.elements[n], C)]


def _electrical(graph: BondGraph, el: OnePort) -> bool:
    """True when ``el``'s flow unit is a current."""
    fu = element_units(graph, el)[1]
    try:
        return bool(fu) and _units.same_dimension(fu, "A")
    except Exception:
        return False


def _in_integral_causality(graph: BondGraph, targets: list[Target]) -> list[Target]:
    """``targets`` whose element SCAP leaves in integral causality (its
    energy variable a state); none when the causality cannot be assigned."""
    try:
        cz = assign_causality(graph, validate=False)
    except BondGraphError:
        return []
    return [t for t in targets if t.name not in cz.derivative]


def inductor_targets(graph: BondGraph) -> list[Target]:
    """The I elements of the electrical domain (flow unit a current) in
    integral causality (their momentum, the flux linkage, a state)."""
    return _in_integral_causality(graph, [
        Target("storage", n) for n in sorted(graph.elements)
        if isinstance(graph.elements[n], I) and _electrical(graph, graph.elements[n])])


def state_storage_targets(graph: BondGraph) -> list[Target]:
    """The C elements in integral causality (SCAP, Karnopp, Margolis &
    Rosenberg): those whose displacement q is a state. A C that SCAP leaves
    in derivative causality (a compliance between two flow sources, e.g. a
    belt between a massless motor and a pulley) has no state of its own, so
    an effect written in its q (a capacity limit) cannot attach there."""
    return _in_integral_causality(graph, storage_targets(graph))


def resistor_targets(graph: BondGraph) -> list[Target]:
    """R elements (not the loop's own) whose law is linear (a resistance)
    or already written in the causality SCAP gives them, so that a term in
    the causal input can be added to the law."""
    try:
        cz = assign_causality(graph, validate=False)
    except BondGraphError:
        return []
    out = []
    for name in sorted(graph.elements):
        el = graph.elements[name]
        if not isinstance(el, R) or _added_by_loop(el):
            continue
        recv = cz.receives_effort(el.port.bond, el)
        if el.resistance is not None or (el.form == "flow") == recv:
            out.append(Target("resistor", name))
    return out


def _added_by_loop(el) -> bool:
    """True if an element's laws read a parameter an effect added."""
    return any(getattr(s, "source", "") == ADDED_BY or s.name.startswith("probe.")
               for ex in el.expressions() for s in ex.free_symbols)


def power_sources(graph: BondGraph) -> list[Target]:
    """Every source (Se, Sf, MSe, MSf) bonded to a junction, whatever its
    value reads (an input, a state, a constant), except the loop's own
    sources (offsets, probes, and any source whose value reads a parameter
    an effect added) and the flow sources that impose the flow of an inertia
    (which then takes derivative causality: a change of their value would
    need its own time derivative)."""
    out = []
    for name in sorted(graph.elements):
        el = graph.elements[name]
        if not isinstance(el, Source) or name.startswith(("offset.", "probe.")):
            continue
        j = source_junction(graph, el)
        if _added_by_loop(el) or j is None:
            continue
        if el.variable == "flow" and isinstance(j, One) and _has_inertia(j):
            continue
        out.append(Target("source", name))
    return out


def input_targets(graph: BondGraph) -> list[Target]:
    """Inputs that an element, sensor or signal state of ``graph`` reads."""
    used: set = set()
    for _, _, ex in graph._expression_owners():
        used |= {s.name for s in ex.free_symbols if isinstance(s, Input)}
    return [Target("input", n) for n in sorted(graph.inputs) if n in used]


def zero_junction_of(graph: BondGraph, el: OnePort) -> Zero | None:
    """The 0-junction a one-port is bonded to, or None."""
    j = source_junction(graph, el)
    return j if isinstance(j, Zero) else None
