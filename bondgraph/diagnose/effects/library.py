"""The default effect library and lookup by name."""

from __future__ import annotations

from typing import Mapping

from bondgraph.core.graph import BondGraph
from bondgraph.core.symbols import Parameter
from bondgraph.diagnose.effects.base import Effect, Target
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
from bondgraph.diagnose.effects.hysteresis import BoucWen
from bondgraph.diagnose.effects.laws import Radiation, RCubic, RPower, RQuadratic, RSquareRoot
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
)
from bondgraph.diagnose.effects.storage import (
    Backlash,
    CapacityLimit,
    CubicRestoring,
    CubicStiffness,
    EndStop,
    InductorSaturation,
    SeriesRC,
)
from bondgraph.errors import GraphError

#: the library used by :func:`bondgraph.diagnose.loop.run_loop` unless told otherwise
DEFAULT_EFFECTS: tuple[Effect, ...] = (
    Coulomb(), AsymmetricFriction(), Stribeck(), Viscous(), QuadraticDrag(), ConstantEffort(),
    ActuatorGain(), SensorOffset(), SensorGain(), SensorRectification(),
    Slip(), Compliance(), SensorLowPass(), Disturbance(), ActuatorSaturation(),
    ActuatorDeadZone(), EndStop(), Backlash(),
    # issue 12: every energy domain
    SourceOffset(), SensorPolynomial2(), SensorPolynomial3(), CubicStiffness(), RSquareRoot(),
    RQuadratic(), RCubic(), SourceLag(), SourceRateLimit(), InputDelay(), SensorQuantisation(),
    CapacityLimit(), DahlFriction(),
    InductorSaturation(),
    # issue 26: a user's warm fuel-flow graph on a cold-start record found the
    # warm-up only when asked; a record that starts warm gives it LR ~0, and
    # where it fits only a start transient the held-out error refuses it
    ColdStart(),
    # a user's Silverbox declared as a series RLC circuit reads the output
    # as the capacitor's voltage: the cubic beside the C, not in its law
    CubicRestoring(),
    # a user's oven (convection from its case, ΔT^1.25): the quadratic term
    # left a misfit that a cold start of the room air then absorbed
    RPower(),
    # a user's heated block in the pseudo bond graph of heat transfer: its
    # radiation to the room, εσA(T⁴ − T_a⁴), which no law of ΔT alone gives,
    # left a power law whose misfit an actuator gain of -0.79 and a
    # capacity limit then absorbed (the heat capacity at a seventh of its value)
    Radiation(),
    # a user's battery cell declared with one RC pair, the cell having two:
    # a nonlinear OCV term, a cold start of the current and a dead zone
    # stood in for the slow relaxation
    SeriesRC(),
)

#: effects of the library that the loop scores only when asked
#: (``LoopSettings(effects=DEFAULT_EFFECTS + OPTIONAL_EFFECTS)``, or
#: ``bondgraph loop --add-effects bouc_wen``): Bouc-Wen hysteresis (issue 29) is
#: a structural candidate (its own state) at every mechanical and electrical
#: 1-junction, each compiled on its grid (~4-5 % more candidates on the
#: bundled cases, but among the costliest to score)
OPTIONAL_EFFECTS: tuple[Effect, ...] = (BoucWen(),)

BY_NAME: dict[str, Effect] = {e.name: e for e in DEFAULT_EFFECTS + OPTIONAL_EFFECTS}


def get_effect(name: str, library=None) -> Effect:
    """The effect called ``name`` in ``library`` (default :data:`DEFAULT_EFFECTS`
    and :data:`OPTIONAL_EFFECTS`).

    Raises
    ------
    GraphError
        Unknown name (the library's names are listed).
    """
    lib = {e.name: e for e in (library or DEFAULT_EFFECTS + OPTIONAL_EFFECTS)}
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
