"""Sensor effects: what happens between the physical variable y and the
recorded measurement.

* additive (probe-able at β = 0): offset, gain error, 2nd- and 3rd-order
  polynomial calibration, rectification (a sign-blind sensor);
* structural: first-order low-pass, quantisation.

Sensor effects change only the output equation y = h(x, u, θ) (and, for
the low-pass, add a signal state): no bond, no power.

References
----------
Quantisation as a smoothed staircase: the sawtooth y − Δ·round(y/Δ) has the
Fourier series Σ (−1)^{k+1} sin(2πky/Δ)/(πk) (Widrow & Kollár 2008,
*Quantization Noise*, ch. 4); damping the k-th harmonic by r^k sums it in
closed form, (Δ/π)·atan(r sin θ/(1 + r cos θ)), θ = 2πy/Δ.
"""

from __future__ import annotations

import sympy as sp

from bondgraph.diagnose.effects.base import (
    Effect,
    EffectParam,
    Scales,
    Target,
    _box,
    _new_param,
    _Structural,
    fill_unit,
    log_grid,
    time_constant_box,
    time_constant_grid,
)


def sensor_targets(graph) -> list[Target]:
    """Every sensor of the graph."""
    return [Target("sensor", n) for n in sorted(graph.sensors)]


class _SensorEffect(Effect):
    target_kind = "sensor"
    additive = True

    def targets(self, graph):
        return sensor_targets(graph)

    def transform(self, y, P: dict, S: dict):
        """The measurement as a function of the sensed expression ``y``."""
        raise NotImplementedError

    def basis_y(self, y, S: dict) -> list:
        """Basis functions in ``y`` (one per estimated parameter)."""
        raise NotImplementedError

    @staticmethod
    def fixed_box(spc) -> tuple[float, float] | None:
        """The fixed box of the parameter ``spc``: [0, 1] for the fraction
        λ, ±1e9 for an offset or a calibration coefficient; None for one
        whose box is set around its start (:func:`_box`)."""
        if spc.name == "lam":
            return 0.0, 1.0
        if spc.name == "b" or spc.name.startswith("c"):
            return -1e9, 1e9
        return None

    def param_box(self, spc, default: float) -> tuple[float, float]:
        """The box :meth:`apply` gives the parameter ``spc`` started at
        ``default``: its :meth:`fixed_box`, else ±10 |default| (:func:`_box`)."""
        return self.fixed_box(spc) or _box(default or 1.0, spc)

    def search_boxed(self):
        return tuple(p.name for p in self.params if p.estimated and self.fixed_box(p) is None)

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        sen = graph.sensors[target.name]
        shapes = self.shape_values(graph, target, scales or Scales())
        P = {}
        for spc in self.params:
            default = values.get(spc.name, shapes.get(spc.name, 0.0))
            unit = fill_unit(spc.unit, y=sen.unit)
            lo, hi = self.param_box(spc, default)
            P[spc.name] = _new_param(graph, self.pname(target, spc.name), default, unit, (lo, hi),
                                     f"{spc.description} ({self.title} of {target.name})")
        sen.expr = self.transform(sen.expr, P, P)
        return P

    def basis(self, graph, target, scales):
        shapes = self.shape_values(graph, target, scales)
        S = {k: sp.Float(v) for k, v in shapes.items()}
        return self.basis_y(graph.sensors[target.name].expr, S)


class SensorOffset(_SensorEffect):
    """A constant added to the measurement, y → y + b."""

    name = "sensor_offset"
    title = "sensor offset"
    params = (EffectParam("b", "{y}", "constant added to the measurement"),)

    def transform(self, y, P, S):
        return y + P["b"]

    def basis_y(self, y, S):
        return [sp.Integer(1)]

    def box(self, graph, target, scales):
        m = scales.get("output_rms", target.name)
        return {"b": (0.03 * m, 0.2 * m)}


class SensorGain(_SensorEffect):
    """A relative gain error of the measurement, y → (1 + g) y."""

    name = "sensor_gain"
    title = "sensor gain error"
    params = (EffectParam("g", "", "relative gain error of the measurement"),)

    def transform(self, y, P, S):
        return (1 + P["g"]) * y

    def basis_y(self, y, S):
        return [y]

    def box(self, graph, target, scales):
        return {"g": (0.03, 0.3)}


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

    def box(self, graph, target, scales):
        return {"lam": (0.3, 1.0)}


class SensorPolynomial2(_SensorEffect):
    """A second-order calibration error, y → y + c2·y² (with the offset and
    gain effects, the full quadratic calibration curve)."""

    name = "sensor_poly2"
    title = "sensor calibration, 2nd order"
    params = (EffectParam("c2", "1/{y}", "quadratic calibration coefficient"),)

    def transform(self, y, P, S):
        return y + P["c2"] * y**2

    def basis_y(self, y, S):
        return [y**2]

    def box(self, graph, target, scales):
        m = scales.get("output_rms", target.name)
        return {"c2": (0.03 / m, 0.2 / m)}


class SensorPolynomial3(_SensorEffect):
    """A third-order calibration error, y → y + c2·y² + c3·y³."""

    name = "sensor_poly3"
    title = "sensor calibration, 3rd order"
    params = (EffectParam("c2", "1/{y}", "quadratic calibration coefficient"),
              EffectParam("c3", "1/{y}^2", "cubic calibration coefficient"))

    def transform(self, y, P, S):
        return y + P["c2"] * y**2 + P["c3"] * y**3

    def basis_y(self, y, S):
        return [y**2, y**3]

    def box(self, graph, target, scales):
        m = scales.get("output_rms", target.name)
        return {"c2": (0.03 / m, 0.15 / m), "c3": (0.03 / m**2, 0.15 / m**2)}


class SensorLowPass(_Structural):
    """A first-order low-pass sensor (anti-aliasing filter): the measurement
    is z with dz/dt = (y - z)/tau."""

    name = "sensor_lowpass"
    title = "sensor low-pass (first-order lag)"
    target_kind = "sensor"
    params = (EffectParam("tau", "s", "time constant", nonnegative=True),)

    def targets(self, graph):
        return sensor_targets(graph)

    def grid(self, graph, target, scales):
        return time_constant_grid(scales)

    def box(self, graph, target, scales):
        return time_constant_box(scales)

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        sen = graph.sensors[target.name]
        tau = _new_param(graph, self.pname(target, "tau"), values.get("tau", 0.01), "s",
                         (1e-6, 1e6), f"sensor time constant of {target.name}")
        y = sen.expr
        z = graph.state(f"{self.name}.{target.tag}.z", rhs=lambda s: (y - s) / tau, unit=sen.unit,
                        description=f"low-passed {target.name}")
        sen.expr = z
        return {"tau": tau}


class SensorQuantisation(_Structural):
    """A quantising sensor (an A/D converter, an encoder): the measurement
    is y rounded to steps of Δ, as a smoothed staircase
    y − (Δ/π)·atan(r sin(2πy/Δ)/(1 + r cos(2πy/Δ))) (the sawtooth's Fourier
    series with the k-th harmonic damped by r^k; r = 0.9 fixed, so that the
    staircase has a finite slope the UKF's sigma points can cross)."""

    name = "sensor_quantisation"
    title = "sensor quantisation"
    target_kind = "sensor"
    params = (EffectParam("delta", "{y}", "quantisation step", nonnegative=True),
              EffectParam("r", "", "sharpness of the staircase (0 < r < 1)", estimated=False))

    def targets(self, graph):
        return sensor_targets(graph)

    def shape_values(self, graph, target, scales):
        return {"r": 0.9}

    def grid(self, graph, target, scales):
        m = scales.get("output_rms", target.name)
        return [{"delta": m * f, "r": 0.9} for f in log_grid(0.01, 0.3, 8)]

    def box(self, graph, target, scales):
        m = scales.get("output_rms", target.name)
        return {"delta": (0.05 * m, 0.2 * m)}

    def apply(self, graph, target, values=None, scales=None):
        values = dict(values or {})
        sen = graph.sensors[target.name]
        d = _new_param(graph, self.pname(target, "delta"), values.get("delta", 1.0),
                       fill_unit("{y}", y=sen.unit), (1e-15, 1e15),
                       f"quantisation step of {target.name}")
        r = _new_param(graph, self.pname(target, "r"), values.get("r", 0.9), "", (0.0, 0.99),
                       f"staircase sharpness of {target.name}")
        y = sen.expr
        th = 2 * sp.pi * y / d
        sen.expr = y - d / sp.pi * sp.atan(r * sp.sin(th) / (1 + r * sp.cos(th)))
        return {"delta": d, "r": r}
