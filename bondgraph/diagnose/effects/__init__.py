"""A library of physical effects a model may lack, as bond-graph fragments.

Each :class:`Effect` knows

* where it can attach in a given graph (:meth:`Effect.targets`, found from
  the graph's structure: flow junctions of the mechanical domains for forces
  that depend on a velocity, sources and inputs for actuator errors and
  delays, sensors for measurement errors, C elements for storage limits and
  stiffness laws, R elements for alternative laws, transmission bonds for
  slip and compliance), in translation, rotation, electrical, hydraulic and
  thermal graphs alike;
* how to add itself (:meth:`Effect.apply`): a fragment of elements and named
  parameters with units spliced into a *copy* of the graph (the user's
  declaration is never touched);
* its declared parameter box (:meth:`Effect.box`), from the graph and the
  data scales;
* for *additive* effects, its basis functions: the effect is
  Σ β_k·b_k(v) with β = 0 meaning "absent". These are probed all at once by
  :func:`probe_graph` for the score (Lagrange-multiplier) test of
  :mod:`bondgraph.diagnose.scoring`. Other (*structural*) effects have no such
  neutral point (a slip that vanishes is an infinitely stiff coupling) and
  are scored by a likelihood-ratio fit over a grid.

The families live in submodules: :mod:`~.friction` (friction laws, offset,
disturbance, Dahl hysteresis), :mod:`~.hysteresis` (the Bouc-Wen element),
:mod:`~.sources` (gain, offset, saturation,
dead zone, rate limit, lag, input delay, cold start), :mod:`~.sensors`, :mod:`~.storage`
(end stops, capacity limit, backlash, cubic stiffness in the law or beside it),
:mod:`~.laws`
(R-law alternatives), :mod:`~.coupling` (slip, compliance), :mod:`~.probe`
and :mod:`~.library` (the default list, and the optional effects scored only
when asked: the cold start).

Users add effects the same way: subclass :class:`Effect`, implement
``targets``, ``apply`` and ``box`` (and ``basis``/``probe_site`` if additive,
``grid`` if structural), and pass instances to
:func:`bondgraph.diagnose.runner.run_loop` (``effects=DEFAULT_EFFECTS + (MyEffect(),)``).
"""

from bondgraph.diagnose.effects.base import (
    ADDED_BY,
    Effect,
    EffectParam,
    Scales,
    Target,
    element_units,
    fill_unit,
    flow_junctions,
    input_sources,
    input_targets,
    junction_units,
    mechanical,
    power_sources,
    resistor_targets,
    source_junction,
    split_bond,
    storage_targets,
)
from bondgraph.diagnose.effects.coupling import Compliance, Slip
from bondgraph.diagnose.effects.friction import (
    AsymmetricFriction,
    ConstantEffort,
    Coulomb,
    DahlFriction,
    Disturbance,
    QuadraticDrag,
    Stribeck,
    Viscous,
)
from bondgraph.diagnose.effects.hysteresis import BoucWen, bouc_wen_rate
from bondgraph.diagnose.effects.laws import Radiation, RCubic, RQuadratic, RSquareRoot, add_to_r_law
from bondgraph.diagnose.effects.library import (
    BY_NAME,
    DEFAULT_EFFECTS,
    OPTIONAL_EFFECTS,
    apply_effect,
    get_effect,
)
from bondgraph.diagnose.effects.probe import ProbeColumn, probe_graph
from bondgraph.diagnose.effects.sensors import (
    SensorGain,
    SensorLowPass,
    SensorOffset,
    SensorPolynomial2,
    SensorPolynomial3,
    SensorQuantisation,
    SensorRectification,
)
from bondgraph.diagnose.effects.sources import (
    ActuatorDeadZone,
    ActuatorGain,
    ActuatorSaturation,
    ColdStart,
    InputDelay,
    SourceLag,
    SourceOffset,
    SourceRateLimit,
    pade_realisation,
)
from bondgraph.diagnose.effects.storage import (
    Backlash,
    CapacityLimit,
    CubicRestoring,
    CubicStiffness,
    EndStop,
    InductorSaturation,
    SeriesRC,
    add_to_storage_law,
)

__all__ = [
    "ADDED_BY", "ActuatorDeadZone", "ActuatorGain", "ActuatorSaturation", "AsymmetricFriction",
    "BY_NAME", "Backlash", "BoucWen", "CapacityLimit", "ColdStart", "Compliance", "ConstantEffort", "Coulomb",
    "CubicRestoring", "CubicStiffness", "DEFAULT_EFFECTS", "DahlFriction", "Disturbance", "Effect",
    "EffectParam",
    "InductorSaturation",
    "EndStop", "InputDelay", "OPTIONAL_EFFECTS", "ProbeColumn", "QuadraticDrag", "RCubic", "RQuadratic",
    "Radiation",
    "RSquareRoot", "Scales", "SensorGain", "SensorLowPass", "SensorOffset", "SensorPolynomial2",
    "SensorPolynomial3", "SensorQuantisation", "SensorRectification", "SeriesRC", "Slip",
    "SourceLag",
    "SourceOffset", "SourceRateLimit", "Stribeck", "Target", "Viscous", "add_to_r_law",
    "add_to_storage_law", "apply_effect", "element_units", "fill_unit", "flow_junctions",
    "get_effect", "input_sources", "input_targets", "junction_units", "mechanical",
    "pade_realisation", "power_sources", "probe_graph", "resistor_targets", "source_junction", "split_bond",
    "storage_targets",
]
