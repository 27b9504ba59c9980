"""Source shaping and input delay: what happens between a commanded input and
the effort or flow a source (Se, MSe, Sf, MSf) delivers.

* gain error, offset (additive: probe-able at β = 0);
* saturation, dead zone, rate limit, first-order lag (structural);
* transport delay of an input, fractional-sample delays included, as a
  Padé approximant realised by graph states (:class:`InputDelay`);
* a cold-start excess that a thermal capacitance, warmed by the source's own
  power, takes away (:class:`ColdStart`).

A source that drives a 1-junction with an effort gets the static shaping as
an extra modulated effort source on that junction (``shaped − value``);
every other source (flow sources, effort sources on a 0-junction) has its
value rewritten, ``value → shaped(value)``. Either way the source's power
``e·f`` is the power it delivers, so the power balance holds.

References
----------
Padé approximants of e^{-sτ}: Baker & Graves-Morris (1996), *Padé
Approximants*, 2nd ed., §1.2; Golub & Van Loan's closed form of the [n/n]
coefficients; the controllable canonical realisation: Kailath (1980),
*Linear Systems*, §2.1.
"""

from __future__ import annotations

from math import factorial

import numpy as np
import sympy as sp

from bondgraph.core.elements import One, Source
from bondgraph.core.graph import BondGraph
from bondgraph.core.smooth import smooth_abs
from bondgraph.diagnose.effects.base import (
    Effect,
    EffectParam,
    Scales,
    _new_param,
    _Structural,
    element_units,
    input_sources,
    input_targets,
    power_sources,
    time_constant_box,
    time_constant_grid,
    source_junction,
)


def drives_one(graph: BondGraph, src: Source) -> One | None:
    """The 1-junction an effort source drives (None for flow sources and
    sources on 0-junctions)."""
    j = source_junction(graph, src)
    return j if src.variable == "effort" and isinstance(j, One) else None


def source_unit(graph: BondGraph, src: Source) -> str:
    """Unit of the source's value (its effort or flow unit; "" if unknown)."""
    eu, fu = element_units(graph, src)
    return eu if src.variable == "effort" else fu


def _rewrite_value(src: Source, value: sp.Expr) -> None:
    """Set a source's value (it becomes a modulated source)."""
    src.value = sp.sympify(value)
    src.modulated = True


class ActuatorGain(Effect):
    """A gain error of an input-driven source: value → (1 + g)·value."""

    name = "actuator_gain"
    title = "actuator gain error"
    target_kind = "source"
    additive = True
    params = (EffectParam("g", "", "relative gain error"),)

    def targets(self, graph):
        return input_sources(graph, None)

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        src = graph.element(target.name)
        g = _new_param(graph, self.pname(target, "g"), values.get("g", 0.0), "", (-0.9, 2.0),
                       f"gain error of {target.name}")
        j = drives_one(graph, src)
        if j is not None:
            graph.connect(graph.MSe(f"{self.name}.{target.tag}", g * src.value), j)
        else:
            _rewrite_value(src, (1 + g) * src.value)
        return {"g": g}

    def basis(self, graph, target, scales):
        return [graph.element(target.name).value]

    def probe_site(self, graph, target):
        j = drives_one(graph, graph.element(target.name))
        return ("junction", j.name) if j is not None else ("source", target.name)

    def probe_junction(self, graph, target):
        """The junction the source drives (kept for user effects)."""
        return source_junction(graph, graph.element(target.name))

    def box(self, graph, target, scales):
        return {"g": (0.03, 0.3)}


class SourceOffset(Effect):
    """A constant offset of a source's value, value → value + b, for the
    sources whose offset the junction effect ``offset`` does not cover:
    flow sources and effort sources on a 0-junction."""

    name = "source_offset"
    title = "source offset"
    target_kind = "source"
    additive = True
    params = (EffectParam("b", "{u}", "constant added to the source's value"),)

    def targets(self, graph):
        return [t for t in input_sources(graph, None)
                if drives_one(graph, graph.element(t.name)) is None]

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        src = graph.element(target.name)
        b = _new_param(graph, self.pname(target, "b"), values.get("b", 0.0),
                       source_unit(graph, src), (-1e12, 1e12), f"offset of {target.name}")
        _rewrite_value(src, src.value + b)
        return {"b": b}

    def basis(self, graph, target, scales):
        return [sp.Integer(1)]

    def probe_site(self, graph, target):
        return ("source", target.name)

    def box(self, graph, target, scales):
        m = scales.get("source_max", target.name)
        return {"b": (0.03 * m, 0.2 * m)}


class _SourceShaping(_Structural):
    """A static nonlinearity of an input-driven source with one parameter;
    its grid in fractions of the source's largest value in the record."""

    target_kind = "source"
    #: grid of the parameter, as fractions of the source's largest value
    fractions: tuple[float, ...] = ()
    #: declared box, as fractions of the source's largest value
    box_fractions: tuple[float, float] = (0.1, 1.0)
    what = ""

    def targets(self, graph):
        return input_sources(graph, None)

    def grid(self, graph, target, scales):
        m = scales.get("source_max", target.name)
        p = self.params[0].name
        return [{p: m * f} for f in self.fractions]

    def box(self, graph, target, scales):
        m = scales.get("source_max", target.name)
        return {self.params[0].name: (m * self.box_fractions[0], m * self.box_fractions[1])}

    def shaped_minus_value(self, v, p):
        """shaped(v) − v for the parameter ``p``."""
        raise NotImplementedError

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        src = graph.element(target.name)
        name = self.params[0].name
        p = _new_param(graph, self.pname(target, name), values.get(name, 1.0),
                       source_unit(graph, src), (1e-9, 1e12), f"{self.what} of {target.name}")
        j = drives_one(graph, src)
        if j is not None:
            graph.connect(graph.MSe(f"{self.name}.{target.tag}",
                                    self.shaped_minus_value(src.value, p)), j)
        else:
            _rewrite_value(src, src.value + self.shaped_minus_value(src.value, p))
        return {name: p}


class ActuatorSaturation(_SourceShaping):
    """Smooth saturation of a source: value -> value/sqrt(1 + (value/L)^2)."""

    name = "actuator_saturation"
    title = "actuator saturation"
    params = (EffectParam("L", "{u}", "saturation level", nonnegative=True),)
    fractions = (0.3, 0.5, 0.7, 0.85, 1.0, 1.3, 2.0)
    box_fractions = (0.3, 0.9)
    what = "saturation level"

    def shaped_minus_value(self, v, L):
        return v / sp.sqrt(1 + (v / L) ** 2) - v


class ActuatorDeadZone(_SourceShaping):
    """Smooth dead zone of a source: value -> value - d·tanh(value/d)."""

    name = "actuator_deadzone"
    title = "actuator dead zone"
    params = (EffectParam("d", "{u}", "dead-zone half width", nonnegative=True),)
    fractions = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3)
    box_fractions = (0.05, 0.3)
    what = "dead-zone half width"

    def shaped_minus_value(self, v, d):
        return -d * sp.tanh(v / d)


class SourceLag(_Structural):
    """A first-order lag between the command and the source: the source
    delivers z, dz/dt = (value − z)/τ (actuator bandwidth, a pump's or a
    heater's time constant)."""

    name = "source_lag"
    title = "source first-order lag"
    target_kind = "source"
    params = (EffectParam("tau", "s", "time constant", nonnegative=True),)

    def targets(self, graph):
        return input_sources(graph, None)

    def grid(self, graph, target, scales):
        return time_constant_grid(scales)

    def box(self, graph, target, scales):
        return time_constant_box(scales)

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        src = graph.element(target.name)
        tau = _new_param(graph, self.pname(target, "tau"), values.get("tau", 0.01), "s",
                         (1e-9, 1e9), f"lag time constant of {target.name}")
        v = src.value
        z = graph.state(f"{self.name}.{target.tag}.z", rhs=lambda s: (v - s) / tau,
                        unit=source_unit(graph, src) or None,
                        description=f"lagged value of {target.name}")
        _rewrite_value(src, z)
        return {"tau": tau}


class SourceRateLimit(_Structural):
    """A slew-rate limit: the source delivers z, dz/dt = r·tanh((value −
    z)/(r·τ_f)): it follows the command with the fast time constant τ_f
    (fixed, half a sample) while |dz/dt| < r, and slews at r beyond."""

    name = "source_rate_limit"
    title = "source rate limit"
    target_kind = "source"
    params = (EffectParam("r", "{u}/s", "largest rate of change", nonnegative=True),
              EffectParam("tau_f", "s", "tracking time constant below the limit", estimated=False))

    def targets(self, graph):
        return input_sources(graph, None)

    def shape_values(self, graph, target, scales):
        return {"tau_f": 0.5 * scales.dt}

    def _rate(self, target, scales) -> float:
        """The command's typical full-scale rate: largest value over 20 samples."""
        return scales.get("source_max", target.name) / (20 * scales.dt)

    def grid(self, graph, target, scales):
        r = self._rate(target, scales)
        tf = 0.5 * scales.dt
        return [{"r": r * f, "tau_f": tf} for f in (0.1, 0.2, 0.4, 0.7, 1.0, 1.5, 2.5, 4.0)]

    def box(self, graph, target, scales):
        """From 0.2 of the full-scale rate (largest value over 20 samples) to
        twice it, but at most 0.6 of the command's largest rate in the record
        (``source_rate``): above that the limit never acts, and the effect
        left is the tracking lag τ_f alone."""
        r = self._rate(target, scales)
        top = min(2.0 * r, 0.6 * scales.get("source_rate", target.name, np.inf))
        return {"r": (min(0.2 * r, 0.5 * top), top)}

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        src = graph.element(target.name)
        unit = source_unit(graph, src)
        shapes = self.shape_values(graph, target, scales or Scales())
        r = _new_param(graph, self.pname(target, "r"), values.get("r", 1.0),
                       f"({unit})/s" if unit else "", (1e-12, 1e15), f"rate limit of {target.name}")
        tf = _new_param(graph, self.pname(target, "tau_f"),
                        values.get("tau_f", shapes.get("tau_f", 1e-3)), "s", (1e-9, 1e9),
                        f"tracking time constant of the rate limit of {target.name}")
        v = src.value
        z = graph.state(f"{self.name}.{target.tag}.z",
                        rhs=lambda s: r * sp.tanh((v - s) / (r * tf)), unit=unit or None,
                        description=f"rate-limited value of {target.name}")
        _rewrite_value(src, z)
        return {"r": r, "tau_f": tf}


class ColdStart(_Structural):
    """A cold-start excess of a source that the source's own power warms
    away: the source delivers value + x, where the excess x is proportional
    to the temperature deficit T_w − T of a lumped thermal capacitance
    (an engine block and its coolant, a cold gearbox's oil, a pump's
    fluid) heated by the power the source delivers::

        value -> value + x,      dx/dt = −x·|P|/E_w,      P = e·f of the source's bond

    (|P| smoothed over P_ε: sqrt(P² + P_ε²)). The excess decays by e per
    energy E_w delivered, so a loaded source warms faster than an idling
    one; E_w is the capacitance's heat capacity times its temperature rise
    over the share of the source's power that heats it. The excess at the
    start of a record, x(0), is the state's initial value, learned by the
    filter like any unknown initial state (0 on a warm start: the effect is
    then absent); its guess, 20 % of the source's largest value in the
    record, sets the scale of its prior. On an engine the excess is the cold-start enrichment and
    the cold friction's fuel, both about linear in the deficit over the
    warm-up (Heywood 1988, §13.6; Guzzella & Sciarretta 2013, §3.2 and
    appendix on thermal engine models).

    Passive: the excess is delivered by the source itself (no element
    produces power), and x keeps its initial sign and decays monotonically
    to 0, so the free run stays bounded.

    References
    ----------
    Heywood, J. B. (1988). *Internal Combustion Engine Fundamentals*,
    McGraw-Hill, ch. 13 (friction and its dependence on oil temperature).
    Guzzella, L., Sciarretta, A. (2013). *Vehicle Propulsion Systems*, 3rd
    ed., Springer.
    """

    name = "cold_start"
    title = "cold-start excess warmed away by the source's power"
    target_kind = "source"
    params = (EffectParam("E_w", "{effort}*{flow}*s", "warm-up energy: the excess falls by e "
                          "per E_w delivered", nonnegative=True),
              EffectParam("P_eps", "{effort}*{flow}", "smoothing width of |P|", estimated=False))

    def targets(self, graph):
        return power_sources(graph)

    def _energy(self, target, scales) -> float:
        """The energy the source delivers over the record (mean |P| × duration)."""
        return scales.get("source_power", target.name) * scales.duration

    def shape_values(self, graph, target, scales):
        return {"P_eps": 1e-3 * scales.get("source_power", target.name)}

    def grid(self, graph, target, scales):
        e = self._energy(target, scales)
        pe = self.shape_values(graph, target, scales)["P_eps"]
        return [{"E_w": e * f, "P_eps": pe} for f in (0.01, 0.02, 0.05, 0.1, 0.2, 0.4, 0.8)]

    def box(self, graph, target, scales):
        """From 2 % to 50 % of the energy the source delivers over the record:
        the warm-up is then seen within the record (a smaller E_w is a
        transient of the first samples, a larger one a constant offset)."""
        e = self._energy(target, scales)
        return {"E_w": (0.02 * e, 0.5 * e)}

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        src = graph.element(target.name)
        eu, fu = element_units(graph, src)
        pu = f"({eu})*({fu})" if eu and fu else ""
        shapes = self.shape_values(graph, target, scales) if scales is not None else {}
        ew = _new_param(graph, self.pname(target, "E_w"), values.get("E_w", 1.0),
                        f"{pu}*s" if pu else "", (1e-12, 1e18),
                        f"warm-up energy of the cold-start excess of {target.name}")
        pe = _new_param(graph, self.pname(target, "P_eps"),
                        values.get("P_eps", shapes.get("P_eps", 1.0)), pu, (1e-15, 1e15),
                        f"smoothing width of |P| of {target.name}")
        v = src.value
        power = src.e * src.f
        # the guess of the initial excess (the filter learns it: nothing
        # gives it, so its prior spans the state's scale, which this guess sets)
        x0 = 0.2 * scales.get("source_max", target.name) if scales is not None else 0.0
        x = graph.state(f"{self.name}.{target.tag}.x",
                        rhs=lambda s: -s * smooth_abs(power, pe) / ew,
                        unit=source_unit(graph, src) or None, initial=float(x0),
                        description=f"cold-start excess of {target.name}")
        _rewrite_value(src, v + x)
        return {"E_w": ew, "P_eps": pe}


# ------------------------------------------------------------- input delay
def pade_coefficients(n: int) -> list[sp.Rational]:
    """Coefficients c_0..c_n of the denominator D(s) = Σ c_k s^k of the
    [n/n] Padé approximant of e^{-s} (numerator D(-s)):
    c_k = (2n − k)! n! / ((2n)! k! (n − k)!)."""
    return [sp.Rational(factorial(2 * n - k) * factorial(n),
                        factorial(2 * n) * factorial(k) * factorial(n - k)) for k in range(n + 1)]


def pade_realisation(n: int):
    """A realisation of the [n/n] Padé approximant of e^{-sτ} in time
    scaled by τ, with states in the unit of the input (x_1 = u at rest).

    Returns
    -------
    A : list of list (n × n), B : list (n,), Cc : list (n,), D : int
        τ dx/dt = A x + B u, y = Cc·x + D u (controllable canonical form
        of D(s)/c_n, states scaled by the DC gain d_0 = c_0/c_n).
    """
    c = pade_coefficients(n)
    d = [ck / c[n] for ck in c]                         # monic denominator
    sgn = (-1) ** n
    # strictly proper remainder N(s) − (−1)^n D(s), over c_n
    r = [((-1) ** k - sgn) * c[k] / c[n] for k in range(n)]
    A = [[sp.Integer(1) if j == i + 1 else sp.Integer(0) for j in range(n)] for i in range(n - 1)]
    A.append([-d[k] for k in range(n)])
    B = [sp.Integer(0)] * (n - 1) + [d[0]]
    Cc = [r[k] / d[0] for k in range(n)]
    return A, B, Cc, sgn


class InputDelay(_Structural):
    """A transport delay τ of an input, u(t) → u(t − τ), fractional-sample
    delays included.

    The delay is an [n/n] Padé approximant of e^{-sτ} realised by n graph
    states (:func:`pade_realisation`; ``order`` n = 2 by default), and the
    delayed expression replaces the input in every element, sensor and
    signal state of the graph. The states are ordinary states of the
    generated model: the UKF propagates them with the sigma points and the
    free-run simulation integrates them, so no layer below the graph needs
    to know about the delay, and τ is a smooth parameter (the likelihood is
    differentiable in τ, also between samples). The approximant is all-pass
    (exact gain) with a phase error below 1° up to ωτ = 1.8 for n = 2 and
    ωτ = 3.5 for n = 3; on a step it rings once (a non-minimum-phase
    undershoot), which the plant downstream of the input filters. Its poles
    scale with 1/τ, so very short delays are stiff: the UKF's ROS2
    discretisation handles them, RK4 needs substeps.
    """

    name = "input_delay"
    title = "input (transport) delay"
    target_kind = "input"
    params = (EffectParam("tau", "s", "delay", nonnegative=True),
              EffectParam("qn", "{u}/s^0.5", "process-noise intensity of the last Padé state",
                          estimated=False))

    def __init__(self, order: int = 2):
        if order < 1:
            raise ValueError("InputDelay order must be >= 1")
        self.order = int(order)

    def targets(self, graph):
        return input_targets(graph)

    def shape_values(self, graph, target, scales):
        """A small process noise on the Padé chain, std 10⁻³ of the largest
        input in stationarity at τ = one sample (q = 10⁻³ u_max √(2/Ts)):
        without it the input-driven states become exactly known and the
        filter's covariance loses positive definiteness."""
        return {"qn": 1e-3 * scales.get("input_max", target.name) * (2.0 / scales.dt) ** 0.5}

    def grid(self, graph, target, scales):
        qn = self.shape_values(graph, target, scales)["qn"]
        return [{"tau": f * scales.dt, "qn": qn} for f in (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0,
                                                          5.0)]

    def box(self, graph, target, scales):
        return {"tau": (0.3 * scales.dt, 3.0 * scales.dt)}

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        u = graph.inputs[target.name]
        shapes = self.shape_values(graph, target, scales) if scales is not None else {}
        tau = _new_param(graph, self.pname(target, "tau"), values.get("tau", 0.01), "s",
                         (1e-9, 1e9), f"transport delay of input {target.name}")
        qn = _new_param(graph, self.pname(target, "qn"), values.get("qn", shapes.get("qn", 0.0)),
                        f"({u.unit})/s^0.5" if u.unit else "", (0.0, 1e15),
                        f"process noise of the Padé chain of input {target.name}")
        A, B, Cc, D = pade_realisation(self.order)
        names = [f"{self.name}.{target.tag}.x{k + 1}" for k in range(self.order)]
        xs = [sp.Symbol(n) for n in names]           # placeholders for the states
        delayed = D * u + sum(c * x for c, x in zip(Cc, xs))
        substitute(graph, {u: delayed})
        states = []
        for k, n in enumerate(names):
            rhs = (sum(a * x for a, x in zip(A[k], xs)) + B[k] * u) / tau
            states.append(graph.state(n, rhs=rhs, unit=u.unit or None,
                                      process_noise=qn if k == self.order - 1 else None,
                                      description=f"Padé state {k + 1} of the delay of {u.name}"))
        substitute(graph, dict(zip(xs, states)))
        return {"tau": tau}


def substitute(graph: BondGraph, subs: dict) -> None:
    """Apply ``xreplace(subs)`` to every element, sensor and signal-state
    expression of ``graph`` (in place)."""
    for el in graph.elements.values():
        el.substitute(subs)
    for s in graph.sensors.values():
        s.expr = s.expr.xreplace(subs)
    for ss in graph.signal_states.values():
        ss.rhs = ss.rhs.xreplace(subs)
