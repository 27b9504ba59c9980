"""Hysteresis with memory: the Bouc-Wen element (Bouc 1967; Wen 1976) at a
mechanical (translation, rotation) or electrical 1-junction.

The junction's flow ẋ (a velocity, an angular velocity, a current) drives a
hysteretic restoring effort (a force, a torque, a voltage)

    F = α·k·x + (1 − α)·k·z,
    dz/dt = A·ẋ − β·|ẋ|·|z|^(n−1)·z − γ·ẋ·|z|^n,

with x the displacement (charge) since the record's start and z its
hysteretic part (same unit), n = 1 and A = 1 fixed (the model is
over-parametrised: z, A, β, γ and (1 − α)·k can be rescaled together
without changing F; Ma, Zhang & Xu 2004). With n = 1:
dz/dt = ẋ − β·|ẋ|·z − γ·ẋ·|z|.

In the bond graph the elastic part α·k·x is a C element
``bouc_wen.<port>.C`` (stiffness α·k, state x) on the junction, and the
hysteretic part a signal state ``bouc_wen.<port>.z`` acting through a
modulated effort source ``bouc_wen.<port>`` of effort −(1 − α)·k·z.

Parameters and their declared boxes: k > 0; α ∈ [0, 1] (the elastic part
alone must have a non-negative stiffness, checked again by the loop's
admissibility check on the C); β > 0 and γ = ρ·β with the ratio ρ ∈
[−1, 1], so that β + γ >= 0 and β − γ >= 0: the conditions under which z
stays bounded (|z| <= 1/(β + γ) from rest; class I of Ikhouane, Mañosa &
Rodellar 2007) and the model is thermodynamically admissible, the
hysteretic loop dissipating energy on every cycle (Erlicher & Point 2004;
reviewed in Ismail, Ikhouane & Rodellar 2009, §3). The effect estimates
k, α, β and ρ.

References
----------
Bouc, R. (1967). Forced vibration of mechanical systems with hysteresis.
Proc. 4th Conf. on Nonlinear Oscillations, Prague.
Wen, Y.-K. (1976). Method for random vibration of hysteretic systems.
J. Eng. Mech. Div. ASCE 102(2), 249-263.
Erlicher, S., Point, N. (2004). Thermodynamic admissibility of Bouc-Wen
type hysteresis models. C. R. Mécanique 332, 51-57.
Ikhouane, F., Mañosa, V., Rodellar, J. (2007). Dynamic properties of the
hysteretic Bouc-Wen model. Systems & Control Letters 56, 197-205.
Ismail, M., Ikhouane, F., Rodellar, J. (2009). The hysteresis Bouc-Wen
model, a survey. Arch. Comput. Methods Eng. 16, 161-188.
Ma, F., Zhang, H., Bockstedte, A., Foliente, G. C., Paevere, P. (2004).
Parameter analysis of the differential model of hysteresis. J. Appl.
Mech. 71, 342-349.
"""

from __future__ import annotations

from bondgraph.core import units as _units
from bondgraph.core.elements import C
from bondgraph.diagnose.effects.base import (
    EffectParam,
    Scales,
    _new_param,
    _Structural,
    _unit,
    flow_junctions,
    junction_units,
)

#: the declared ratio box ρ = γ/β: β ± γ >= 0 (Erlicher & Point 2004)
RATIO_BOX = (-1.0, 1.0)
#: the declared box of α, the elastic fraction
ALPHA_BOX = (0.0, 1.0)


def _domain_ok(graph, j) -> bool:
    """A translational, rotational or electrical junction (declared domain,
    else its flow unit)."""
    if j.domain is not None:
        return j.domain in ("translation", "rotation", "electrical")
    _, fu = junction_units(graph, j)
    if not fu:
        return False
    try:
        return any(_units.same_dimension(fu, u) for u in ("m/s", "rad/s", "A"))
    except Exception:
        return False


def bonded_stiffness(graph, j) -> float | None:
    """The default stiffness of a linear C bonded to junction ``j`` (None
    when there is none)."""
    for p in j.ports:
        el = p.bond.other(p).element if p.bond is not None else None
        if isinstance(el, C) and el.stiffness is not None:
            try:
                return abs(float(el.stiffness.subs({s: s.default for s in
                                                    el.stiffness.free_symbols})))
            except (TypeError, AttributeError):
                return None
    return None


class BoucWen(_Structural):
    """The Bouc-Wen hysteretic element at a 1-junction (module docstring):
    F = α·k·x + (1 − α)·k·z, dz/dt = ẋ − β·|ẋ|·z − ρ·β·ẋ·|z| (n = 1,
    A = 1), acting as −F on the junction. Scales: the stiffness from a
    linear C bonded to the junction (else the junction's force RMS over its
    flow RMS × 1 s), the displacement from the force RMS over it."""

    name = "bouc_wen"
    title = "Bouc-Wen hysteresis"
    target_kind = "junction"
    params = (EffectParam("k", "{effort}/({flow}*s)", "Bouc-Wen stiffness", nonnegative=True),
              EffectParam("alpha", "", "elastic fraction of the stiffness", bounds=ALPHA_BOX),
              EffectParam("beta", "1/({flow}*s)", "Bouc-Wen β (inverse yield displacement)",
                          nonnegative=True),
              EffectParam("rho", "", "ratio γ/β", bounds=RATIO_BOX))

    def targets(self, graph):
        return [t for t in flow_junctions(graph, mechanical_only=False)
                if _domain_ok(graph, graph.element(t.name))]

    def scales_of(self, graph, target, scales: Scales) -> tuple[float, float]:
        """(k_ref, x_ref): the stiffness and displacement scales."""
        j = graph.element(target.name)
        F = scales.get("force_rms", target.name)
        k = bonded_stiffness(graph, j) or F / scales.v(target.name)
        return k, F / k

    def grid(self, graph, target, scales):
        k, x = self.scales_of(graph, target, scales)
        return [{"k": kf * k, "alpha": 0.5, "beta": 1.0 / (d * x), "rho": 0.0}
                for kf in (0.2, 0.6, 2.0) for d in (0.1, 0.3, 1.0)]

    def grid_span(self, graph, target, scales):
        """The grid's reach for k and β; α its declared box (its grid is
        the single value 0.5); ρ, whose grid holds 0, keeps its declared
        box (:data:`RATIO_BOX`, set in :meth:`apply`)."""
        out = super().grid_span(graph, target, scales)
        out["alpha"] = ALPHA_BOX
        return out

    def box(self, graph, target, scales):
        k, x = self.scales_of(graph, target, scales)
        return {"k": (0.05 * k, 5.0 * k), "alpha": ALPHA_BOX, "beta": (0.3 / x, 30.0 / x),
                "rho": RATIO_BOX}

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        j = graph.element(target.name)
        eu, fu = junction_units(graph, j)
        start = {"k": 1.0, "alpha": 0.5, "beta": 1.0, "rho": 0.0}
        P = {}
        for spc in self.params:
            box = spc.bounds if spc.bounds is not None else (1e-12, 1e12)
            P[spc.name] = _new_param(graph, self.pname(target, spc.name),
                                     float(values.get(spc.name, start[spc.name])),
                                     _unit(spc.unit, eu, fu), box,
                                     f"{spc.description} at {target.name}")
        k, alpha, beta, rho = P["k"], P["alpha"], P["beta"], P["rho"]
        spring = graph.C(f"{self.name}.{target.tag}.C", stiffness=alpha * k)
        graph.connect(j, spring)
        v = j.f
        z = graph.state(f"{self.name}.{target.tag}.z",
                        rhs=lambda z: bouc_wen_rate(v, z, beta, rho),
                        unit=f"({fu})*s" if fu else None,
                        description=f"Bouc-Wen hysteretic displacement at {target.name}")
        graph.connect(graph.MSe(f"{self.name}.{target.tag}", -(1 - alpha) * k * z), j)
        return P


def bouc_wen_rate(v, z, beta, rho, A=1, n: int = 1):
    """dz/dt = A·v − β·|v|·|z|^(n−1)·z − γ·v·|z|^n with γ = ρ·β (sympy
    or numpy operands; ``n`` a positive integer, 1 in the library)."""
    if n == 1:
        return A * v - beta * abs(v) * z - rho * beta * v * abs(z)
    return A * v - beta * abs(v) * abs(z) ** (n - 1) * z - rho * beta * v * abs(z) ** n

