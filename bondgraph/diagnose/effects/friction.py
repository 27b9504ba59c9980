"""Forces that depend on a flow at a 1-junction: viscous, quadratic,
Coulomb, direction-dependent and Stribeck friction (R elements), a constant
actuator effort, an unmeasured random-walk disturbance, and Dahl's
hysteretic friction (a friction force with its own state).

Sign conventions: friction-like laws are R elements (power into the R), so
the force they exert on the junction opposes the motion for positive
coefficients.

References
----------
Olsson, Åström, Canudas de Wit, Gäfvert & Lischinsky (1998), Friction models
and friction compensation, Eur. J. Control 4(3), 176-195.
Armstrong-Hélouvry, Dupont & Canudas de Wit (1994), A survey of models,
analysis tools and compensation methods for the control of machines with
friction, Automatica 30(7), 1083-1138.
Dahl, P. R. (1976), Solid friction damping of mechanical vibrations, AIAA J.
14(12), 1675-1682.
"""

from __future__ import annotations

import sympy as sp

from bondgraph.core.elements import One
from bondgraph.diagnose.effects.base import (
    ADDED_BY,
    Effect,
    EffectParam,
    Scales,
    Target,
    _box,
    _new_param,
    _one_junctions,
    _Structural,
    _unit,
    flow_junctions,
    input_sources,
    junction_units,
    source_junction,
)

#: factors of a friction law's tanh width (2 % of the junction's RMS flow)
#: that a confirmation also tries (from x1 outwards on each side; the
#: likelihood ratio decides, :func:`bondgraph.diagnose.confirm.profiled_shape`): the width is
#: a smoothing of sign(v), not physics, and too wide a one leaves a Coulomb
#: level that the record's reversals contradict for other effects to absorb
#: (a user's geared DC motor, Coulomb friction at the load: with the width at
#: 2 % the loop added a spurious speed-sensor gain that moved the motor
#: constant 30 %; at 0.2 % Coulomb friction alone, held-out error 0.00698
#: against 0.00709 with four more effects); too narrow a one biases the
#: level and the damping beside it (a hydraulic piston's seal friction
#: reversing over 4 %: F_c 7 % low at 2 %, 3 % high at 6 %)
SIGN_WIDTHS = (3.0, 0.3, 0.1)


class _JunctionLaw(Effect):
    """An R element on a 1-junction with a law of the junction flow,
    attached at every mechanical 1-junction whose flow the states fix
    (:func:`flow_junctions`)."""

    target_kind = "junction"
    additive = True
    mechanical_only = True

    def targets(self, graph):
        return flow_junctions(graph, self.mechanical_only)

    def law(self, f, P: dict, S: dict):
        """The R's effort as a function of the junction flow ``f``."""
        raise NotImplementedError

    def basis_law(self, f, S: dict) -> list:
        """Basis functions of the law (one per estimated parameter)."""
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
                                     f"{spc.description} ({self.title} at {target.name})")
        el = graph.R(f"{self.name}.{target.tag}", effort=lambda f: self.law(f, P, P))
        graph.connect(j, el)
        return P

    def basis(self, graph, target, scales):
        j = graph.element(target.name)
        shapes = self.shape_values(graph, target, scales)
        S = {k: sp.Float(v) for k, v in shapes.items()}
        # probe = MSe on the junction: force on the junction = -R law
        return [-b for b in self.basis_law(j.f, S)]

    def box(self, graph, target, scales):
        F = scales.get("force_rms", target.name)
        v = scales.v(target.name)
        return {p.name: b for p, b in zip(self.params, self.force_box(F, v)) if p.estimated}

    def force_box(self, F: float, v: float) -> list[tuple[float, float]]:
        """Boxes of the estimated parameters from the RMS net force ``F`` on
        the junction's inertia and the RMS flow ``v``: the effect's force
        between 5 % and 50 % of ``F`` at the RMS flow."""
        return [(0.05 * F, 0.5 * F)]


class Viscous(_JunctionLaw):
    """Viscous friction F = b v."""

    name = "viscous"
    title = "viscous friction"
    params = (EffectParam("b", "{effort}/{flow}", "viscous friction coefficient", nonnegative=True),)

    def law(self, f, P, S):
        return P["b"] * f

    def basis_law(self, f, S):
        return [f]

    def force_box(self, F, v):
        return [(0.05 * F / v, 0.5 * F / v)]


class QuadraticDrag(_JunctionLaw):
    """Quadratic (aerodynamic, turbulent) drag F = c v |v| (|v| smoothed)."""

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

    def force_box(self, F, v):
        return [(0.05 * F / v**2, 0.5 * F / v**2)]


class Coulomb(_JunctionLaw):
    """Coulomb friction F = Fc sign(v) (tanh-smoothed)."""

    name = "coulomb"
    title = "Coulomb friction (symmetric)"
    params = (EffectParam("Fc", "{effort}", "Coulomb friction level", nonnegative=True),
              EffectParam("eps", "{flow}", "tanh width of the sign function", estimated=False,
                          profile=SIGN_WIDTHS))

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
              EffectParam("eps", "{flow}", "tanh width", estimated=False,
                          profile=SIGN_WIDTHS))

    def shape_values(self, graph, target, scales):
        return {"eps": 0.02 * scales.v(target.name)}

    def law(self, f, P, S):
        s = sp.tanh(f / S["eps"])
        return P["dc"] * s**2 + P["dv"] * f * s

    def basis_law(self, f, S):
        s = sp.tanh(f / S["eps"])
        return [s**2, f * s]

    def force_box(self, F, v):
        return [(-0.3 * F, 0.3 * F), (-0.3 * F / v, 0.3 * F / v)]


class Stribeck(_JunctionLaw):
    """Stribeck friction: a static level above the Coulomb one that decays
    with the speed, ds exp(-(v/vs)²) sign(v)."""

    name = "stribeck"
    title = "Stribeck friction (static above Coulomb)"
    params = (EffectParam("ds", "{effort}", "static minus Coulomb friction", nonnegative=True),
              EffectParam("vs", "{flow}", "Stribeck velocity", estimated=False),
              EffectParam("eps", "{flow}", "tanh width", estimated=False,
                          profile=SIGN_WIDTHS))

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
        for t in input_sources(graph, "effort"):
            j = source_junction(graph, graph.element(t.name))
            if isinstance(j, One) and Target("junction", j.name) not in out:
                out.append(Target("junction", j.name))
        return out

    def search_boxed(self):
        return ()

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        j = graph.element(target.name)
        eu, fu = junction_units(graph, j)
        F0 = _new_param(graph, self.pname(target, "F0"), values.get("F0", 0.0), eu,
                        (-1e9, 1e9), f"constant effort at {target.name}")
        graph.connect(graph.MSe(f"{self.name}.{target.tag}", F0), j)
        return {"F0": F0}

    def basis(self, graph, target, scales):
        return [sp.Integer(1)]

    def force_box(self, F, v):
        return [(-0.3 * F, 0.3 * F)]


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
                       f"disturbance intensity at {target.name}")
        d = graph.state(f"{self.name}.{target.tag}.d", 0, unit=eu, process_noise=q,
                        description=f"disturbance effort at {target.name}")
        graph.connect(graph.MSe(f"{self.name}.{target.tag}", d), j)
        return {"q": q}


class DahlFriction(_Structural):
    """Dahl's hysteretic friction at a mechanical 1-junction: a friction
    force F with its own state, dF/dt = σ v (1 − (F/Fc) sign(v)) (sign
    smoothed by tanh), acting as −F on the junction. In steady sliding F →
    Fc sign(v) (Coulomb); on a reversal it changes sign over the presliding
    displacement ~ Fc/σ, which gives the hysteresis loop of friction versus
    displacement (Dahl 1976; Olsson et al. 1998, §3.1).

    The dissipated power is not an R element's: F is a signal state, and its
    power F·v appears as source power of the MSe."""

    name = "dahl"
    title = "Dahl hysteretic friction"
    target_kind = "junction"
    params = (EffectParam("Fc", "{effort}", "Coulomb level of the Dahl friction", nonnegative=True),
              EffectParam("sigma", "{effort}/({flow}*s)", "rest stiffness dF/dx at F = 0",
                          nonnegative=True),
              EffectParam("eps", "{flow}", "tanh width of sign(v)", estimated=False))
    limits = {"sigma": ("upper", "coulomb")}

    def targets(self, graph):
        return flow_junctions(graph, mechanical_only=True)

    def shape_values(self, graph, target, scales):
        return {"eps": 0.02 * scales.v(target.name)}

    def grid(self, graph, target, scales):
        F = scales.get("force_rms", target.name)
        x = scales.v(target.name) * scales.dt
        eps = self.shape_values(graph, target, scales)["eps"]
        # presliding displacement Fc/σ = d samples' travel; d down to 0.3 so
        # that the grid's reach (× GRID_REACH) covers the box's stiffest σ
        return [{"Fc": fc * F, "sigma": fc * F / (d * x), "eps": eps}
                for fc in (0.05, 0.15, 0.4) for d in (0.3, 3.0, 30.0)]

    def box(self, graph, target, scales):
        F = scales.get("force_rms", target.name)
        x = scales.v(target.name) * scales.dt
        return {"Fc": (0.05 * F, 0.5 * F), "sigma": (F / (50 * x), 5 * F / x)}

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        j = graph.element(target.name)
        eu, fu = junction_units(graph, j)
        shapes = self.shape_values(graph, target, scales or Scales())
        P = {}
        for spc in self.params:
            v = values.get(spc.name, shapes.get(spc.name, 1.0))
            P[spc.name] = _new_param(graph, self.pname(target, spc.name), v,
                                     _unit(spc.unit, eu, fu), (1e-12, 1e12),
                                     f"{spc.description} at {target.name}", ADDED_BY)
        v = j.f
        s = sp.tanh(v / P["eps"])
        F = graph.state(f"{self.name}.{target.tag}.F",
                        rhs=lambda F: P["sigma"] * v * (1 - F / P["Fc"] * s), unit=eu,
                        description=f"Dahl friction force at {target.name}")
        graph.connect(graph.MSe(f"{self.name}.{target.tag}", -F), j)
        return P
