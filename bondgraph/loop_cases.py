"""Bundled cases of the residual-tracing loop.

Each :class:`LoopCase` pairs a *declared* filter model (what the engineer
wrote) with a record that has an effect the declared model lacks:

* synthetic vehicle cases: the record is simulated from a *truth* graph, the
  declared graph plus one physical effect (aerodynamic drag, residual brake
  drag, a pitch-sensor offset, CVT belt slip), with the documented sensor
  noise and a fixed seed;
* real data: EMPS (Coulomb and direction-dependent friction) and CED (a
  sign-blind speed sensor), read from the local data folder.

``bondgraph loop`` with no arguments runs :data:`DEFAULT_CASE`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from .graph import BondGraph

DEFAULT_CASE = "vehicle_aero"


@dataclass
class LoopCase:
    """A declared model, a record, the parameters to estimate, loop settings,
    and (for synthetic cases) the effect the truth has."""

    name: str
    description: str
    declared: Callable[[], BondGraph]
    record: Callable[[], Any]
    params: list[str]
    settings: dict = field(default_factory=dict)
    true_effect: tuple[str, str] | None = None   # (effect name, target name)


def synthesize(truth: BondGraph, declared: BondGraph, t: np.ndarray,
               inputs: dict[str, Callable[[np.ndarray], np.ndarray]], x0: dict[str, float],
               params: dict[str, float], seed: int, name: str, description: str):
    """Simulate ``truth`` and record the outputs of ``declared`` with the
    declared sensors' noise (``numpy.random.default_rng(seed)``).

    Returns
    -------
    Experiment
        Inputs, noisy outputs, true states (``state.<name>``) and meta
        (true parameters, x0, seed, noise).
    """
    from .data import Experiment
    from .model import Model
    from .simulate import simulate

    tm = Model.from_graph(truth)
    dm = Model.from_graph(declared)
    th = tm.theta({k: v for k, v in params.items() if k in tm.params})
    u = {k: f for k, f in inputs.items() if k in tm.inputs}
    x = tm.state({k: v for k, v in x0.items() if k in tm.states})
    sim = simulate(tm, t, u or None, x0=x, theta=th, method="BDF", rtol=1e-8, atol=1e-10)
    rng = np.random.default_rng(seed)
    thd = dm.theta({k: v for k, v in params.items() if k in dm.params})
    sd = dm.meas_std(thd)
    y = np.empty((t.size, dm.n_y))
    for i, o in enumerate(dm.outputs):
        y[:, i] = sim.y[:, tm.output_index(o)] + rng.normal(size=t.size) * sd[i]
    ud = np.column_stack([sim.u[:, tm.input_index(n)] if n in tm.inputs else
                          np.full(t.size, dm.u0[j]) for j, n in enumerate(dm.inputs)]) \
        if dm.n_u else None
    meta = {"name": name, "description": description, "model": declared.name,
            "truth_model": truth.name, "seed": seed,
            "true_parameters": {p: float(v) for p, v in zip(tm.params, th)},
            "x0": {s: float(v) for s, v in zip(tm.states, x) if s in dm.states},
            "noise": {o: float(v) for o, v in zip(dm.outputs, sd)}}
    return Experiment.from_arrays(t, model=dm, u=ud, y=y, meta=meta, name=name)


# ------------------------------------------------------------ the vehicle
def _vehicle(name: str, **kw) -> BondGraph:
    from vehicle_graphs import build_vehicle

    return build_vehicle(name, **kw)


COAST = dict(gear="N", powertrain=False, wheels="lumped", suspension="dynamic")

#: prior standard deviation of the initial grade on a level test track [rad]
#: (0.1 deg). Without it a constant grade explains a constant force (brake
#: drag) or a pitch offset as well as the effect itself: the coast-down
#: protocol assumes a level track, as the original work proposed for the
#: pitch offset.
LEVEL_TRACK = math.radians(0.1)


def _coastdown_record(truth: BondGraph, declared: BondGraph, name: str, seed: int,
                      duration: float = 40.0, v0: float = 22.0):
    from vehicle_graphs.analysis import initial_state
    from vehicle_graphs.experiments import TRUE_COASTDOWN

    from .model import Model

    tm = Model.from_graph(truth)
    th = tm.theta({k: v for k, v in TRUE_COASTDOWN.items() if k in tm.params})
    x0 = initial_state(tm, th, v=v0)
    t = np.arange(0.0, duration + 1e-9, 0.025)
    inputs = {"brake": lambda tt: np.zeros_like(tt)}
    return synthesize(truth, declared, t, inputs, x0, dict(TRUE_COASTDOWN), seed, name,
                      f"coast-down from {v0} m/s, {duration} s at 40 Hz, simulated from "
                      f"'{truth.name}'")


def vehicle_aero_declared() -> BondGraph:
    """Coast-down filter model without aerodynamic drag."""
    return _vehicle("vehicle_coastdown_noaero", aero=False, **COAST)


def vehicle_brake_declared() -> BondGraph:
    """Coast-down filter model (with aero) that lacks residual brake drag."""
    return _vehicle("vehicle_coastdown", **COAST)


def vehicle_pitch_declared() -> BondGraph:
    """Coast-down filter model without the pitch-sensor offset."""
    return _vehicle("vehicle_coastdown_nooffset", pitch_offset=False, **COAST)


def _case_vehicle_aero() -> LoopCase:
    return LoopCase(
        "vehicle_aero",
        "Coast-down record of a vehicle with aerodynamic drag; the declared coast-down "
        "filter model has none (the suspect list of the original work: drag leaking into "
        "rolling resistance).",
        vehicle_aero_declared,
        lambda: _coastdown_record(_vehicle("truth_aero", aero=True, **COAST),
                                  vehicle_aero_declared(), "coastdown_aero", seed=101),
        ["f_r", "r_dyn", "theta_off", "q_grade"],
        {"metric": "nrmse_sim"},
        ("quadratic_drag", "body.v"))


def _case_vehicle_brake() -> LoopCase:
    # rolling resistance known (tire data), the residual brake drag is not
    return LoopCase(
        "vehicle_brake_drag",
        "Coast-down record of a vehicle with a residual brake drag torque at the wheels; "
        "rolling resistance known from tire data, drag and dynamic radius estimated.",
        vehicle_brake_declared,
        lambda: _coastdown_record(_vehicle("truth_brake", brake_drag=True, **COAST),
                                  vehicle_brake_declared(), "coastdown_brake_drag", seed=102),
        ["C_dA", "r_dyn", "theta_off", "q_grade"],
        {"metric": "nrmse_sim", "P0_std": {"theta_g": LEVEL_TRACK}},
        ("coulomb", "wheels.w"))


def _case_vehicle_pitch() -> LoopCase:
    return LoopCase(
        "vehicle_pitch_offset",
        "Coast-down record with a 0.5 deg pitch-sensor mounting offset; the declared model "
        "reads the pitch sensor as grade + suspension pitch.",
        vehicle_pitch_declared,
        lambda: _coastdown_record(_vehicle("truth_pitch", **COAST), vehicle_pitch_declared(),
                                  "coastdown_pitch_offset", seed=103),
        ["f_r", "C_dA", "r_dyn", "q_grade"],
        {"metric": "nrmse_sim", "P0_std": {"theta_g": LEVEL_TRACK}},
        ("sensor_offset", "pitch"))


CASES: dict[str, Callable[[], LoopCase]] = {
    "vehicle_aero": _case_vehicle_aero,
    "vehicle_brake_drag": _case_vehicle_brake,
    "vehicle_pitch_offset": _case_vehicle_pitch,
}


def get_case(name: str) -> LoopCase:
    from .errors import ModelError

    try:
        return CASES[name]()
    except KeyError:
        raise ModelError(f"unknown loop case '{name}' (cases: {', '.join(CASES)})") from None
