"""The vehicle's bundled loop cases (``bondgraph loop --case NAME``).

Each record is simulated from a *truth* graph, the declared vehicle graph plus
one physical effect (aerodynamic drag, residual brake drag, a pitch-sensor
offset, CVT belt slip, a saturating engine torque), with the documented sensor noise and a fixed seed.
``vehicle_aero`` is the default case of ``bondgraph loop``.
"""

from __future__ import annotations

import math

import numpy as np

from bondgraph.core.graph import BondGraph
from bondgraph.diagnose.cases import LoopCase, TrueEffect, declared_builder, synthesize
from bondgraph.diagnose.effects import apply_effect
from bondgraph.diagnose.settings import LoopSettings, SearchOptions
from bondgraph.inference.prior import PriorSpec
from bondgraph.numerics.model import Model

from .analysis import initial_state
from .experiments import TRUE_COASTDOWN, TRUE_DRIVING, steps
from .vehicle import VehicleEffects, build_vehicle

#: registered cases (``bondgraph.cases`` entry point)
CASES: dict[str, str] = {
    "vehicle_aero": "vehicle_graphs.cases:case_aero",
    "vehicle_brake_drag": "vehicle_graphs.cases:case_brake",
    "vehicle_pitch_offset": "vehicle_graphs.cases:case_pitch",
    "vehicle_belt_slip": "vehicle_graphs.cases:case_slip",
    "vehicle_engine_saturation": "vehicle_graphs.cases:case_engine_saturation",
}


def coastdown_vehicle(name: str, effects: VehicleEffects = VehicleEffects()) -> BondGraph:
    """The coast-down filter model of the vehicle (neutral, no powertrain,
    lumped wheels, dynamic pitch) named ``name``, with ``effects``
    (:func:`vehicle_graphs.vehicle.build_vehicle`)."""
    return build_vehicle(name, gear="N", powertrain=False, wheels="lumped",
                         suspension="dynamic", effects=effects)


def full_vehicle(name: str, effects: VehicleEffects = VehicleEffects()) -> BondGraph:
    """The full filter model of the vehicle in High range, 2WD, named
    ``name``, with ``effects``."""
    return build_vehicle(name, gear="H", drive="2WD", effects=effects)

#: prior standard deviation of the initial grade on a level test track [rad]
#: (0.1 deg). Without it a constant grade explains a constant force (brake
#: drag) or a pitch offset as well as the effect itself: the coast-down
#: protocol assumes a level track, as the original work proposed for the
#: pitch offset.
LEVEL_TRACK = math.radians(0.1)


def coastdown_record(truth: BondGraph, declared: BondGraph, name: str, seed: int,
                     duration: float = 40.0, v0: float = 22.0):
    """A synthetic coast-down record: ``truth`` (any coast-down graph, e.g.
    the declared one plus an effect by :func:`bondgraph.apply_effect`) rolls
    out in neutral from ``v0`` [m/s] for ``duration`` [s] at 40 Hz, with the
    parameters of ``TRUE_COASTDOWN``; the outputs of ``declared`` are recorded
    with its sensors' noise, drawn with ``seed``
    (:func:`bondgraph.diagnose.cases.synthesize`).

    Returns
    -------
    Experiment
        Inputs and noisy outputs (each declaring its noise std); the true
        initial state ``x0`` and parameters in the sidecar.
    """
    tm = Model.from_graph(truth)
    th = tm.theta({k: v for k, v in TRUE_COASTDOWN.items() if k in tm.params})
    x0 = initial_state(tm, th, v=v0)
    t = np.arange(0.0, duration + 1e-9, 0.025)
    inputs = {"brake": lambda tt: np.zeros_like(tt)}
    return synthesize(truth, declared, t, inputs, x0, dict(TRUE_COASTDOWN), seed, name,
                      f"coast-down from {v0} m/s, {duration} s at 40 Hz, simulated from "
                      f"'{truth.name}'", truth_model=tm)


def vehicle_aero_declared() -> BondGraph:
    """Coast-down filter model without aerodynamic drag."""
    return coastdown_vehicle("vehicle_coastdown_noaero", VehicleEffects(aero=False))


def vehicle_brake_declared() -> BondGraph:
    """Coast-down filter model (with aero) that lacks residual brake drag."""
    return coastdown_vehicle("vehicle_coastdown")


def vehicle_pitch_declared() -> BondGraph:
    """Coast-down filter model without the pitch-sensor offset."""
    return coastdown_vehicle("vehicle_coastdown_nooffset", VehicleEffects(pitch_offset=False))


#: the coast-down cases' search: at ROS2(1) the filter's discretisation error
#: at the declared fit is 0.3-0.43 measurement-noise std per sample (the
#: accelerometer a_x), so the loop takes the substeps the check recommends
#: (4; the error then 0.06) and says so in one line (issue 27)
COASTDOWN_SEARCH = SearchOptions(auto_substeps=True)


#: the held-out run of a coast-down case: the same car rolled out again from a
#: higher speed (a coast-down test is several runs), its own sensor noise
HELD_OUT_V0 = 25.0


def coastdown_held_out(truth: BondGraph, declared: BondGraph, name: str, seed: int):
    """The validation record of a coast-down case: a second run of ``truth``
    from :data:`HELD_OUT_V0` with its own noise (``seed``), named
    ``<name>_run2``; the loop judges its accept decisions and reports the
    error before and after on it, never having fitted it."""
    return coastdown_record(truth, declared, f"{name}_run2", seed=seed, v0=HELD_OUT_V0)


def case_aero() -> LoopCase:
    truth = coastdown_vehicle("truth_aero", VehicleEffects(aero=True))
    return LoopCase(
        "vehicle_aero",
        "Coast-down record of a vehicle with aerodynamic drag; the declared coast-down "
        "filter model has none (the suspect list of the original work: drag leaking into "
        "rolling resistance). Held out: a second run from 25 m/s.",
        declared_builder(vehicle_aero_declared),
        lambda: coastdown_record(truth, vehicle_aero_declared(), "coastdown_aero", seed=101),
        LoopSettings(["f_r", "r_dyn", "theta_off", "q_grade"], metric="nrmse_sim",
                     search=COASTDOWN_SEARCH,
                     validation=coastdown_held_out(truth, vehicle_aero_declared(),
                                                   "coastdown_aero", seed=201)),
        ("quadratic_drag", "body.v"))


def case_brake() -> LoopCase:
    # rolling resistance known (tire data), the residual brake drag is not
    truth = coastdown_vehicle("truth_brake", VehicleEffects(brake_drag=True))
    return LoopCase(
        "vehicle_brake_drag",
        "Coast-down record of a vehicle with a residual brake drag torque at the wheels; "
        "rolling resistance known from tire data, drag and dynamic radius estimated. Held "
        "out: a second run from 25 m/s.",
        declared_builder(vehicle_brake_declared),
        lambda: coastdown_record(truth, vehicle_brake_declared(), "coastdown_brake_drag",
                                 seed=102),
        LoopSettings(["C_dA", "r_dyn", "theta_off", "q_grade"], metric="nrmse_sim",
                     prior=PriorSpec(x0_std={"theta_g": LEVEL_TRACK}), search=COASTDOWN_SEARCH,
                     validation=coastdown_held_out(truth, vehicle_brake_declared(),
                                                   "coastdown_brake_drag", seed=202)),
        ("coulomb", "wheels.w"))


def case_pitch() -> LoopCase:
    truth = coastdown_vehicle("truth_pitch")
    return LoopCase(
        "vehicle_pitch_offset",
        "Coast-down record with a 0.5 deg pitch-sensor mounting offset; the declared model "
        "reads the pitch sensor as grade + suspension pitch. Held out: a second run from "
        "25 m/s.",
        declared_builder(vehicle_pitch_declared),
        lambda: coastdown_record(truth, vehicle_pitch_declared(), "coastdown_pitch_offset",
                                 seed=103),
        LoopSettings(["f_r", "C_dA", "r_dyn", "q_grade"], metric="nrmse_sim",
                     prior=PriorSpec(x0_std={"theta_g": LEVEL_TRACK}), search=COASTDOWN_SEARCH,
                     validation=coastdown_held_out(truth, vehicle_pitch_declared(),
                                                   "coastdown_pitch_offset", seed=203)),
        ("sensor_offset", "pitch"))


def vehicle_slip_declared() -> BondGraph:
    """Full filter model (High range, 2WD) with a rigid belt."""
    return full_vehicle("vehicle_full")


#: the throttle steps (time [s], throttle) of the driving cases' record, and
#: of their held-out run (other levels at other times)
DRIVING_STEPS = ((2.0, 0.35), (9.0, 0.7), (16.0, 0.2), (22.0, 0.9))
HELD_OUT_STEPS = ((2.0, 0.6), (8.0, 0.25), (14.0, 0.85), (21.0, 0.45))


def driving_record(truth: BondGraph, declared: BondGraph, name: str, seed: int,
                   duration: float = 30.0, throttle_steps=DRIVING_STEPS, **truth_params: float):
    """A synthetic driving record: ``truth`` (a full vehicle graph in High
    range, e.g. the declared one plus an effect by
    :func:`bondgraph.apply_effect`) driven by ``throttle_steps`` (default
    :data:`DRIVING_STEPS`: 0.35, 0.7, 0.2, 0.9 at 2, 9, 16 and 22 s) for
    ``duration`` [s] at 40 Hz from its equilibrium, parameters
    ``TRUE_DRIVING`` with ``truth_params`` over them; the outputs of
    ``declared`` are recorded with its sensors' noise, drawn with ``seed``
    (:func:`bondgraph.diagnose.cases.synthesize`).

    Returns
    -------
    Experiment
    """
    tm = Model.from_graph(truth)
    params = dict(TRUE_DRIVING, **truth_params)
    th = tm.theta({k: v for k, v in params.items() if k in tm.params})
    x0 = initial_state(tm, th)
    t = np.arange(0.0, duration + 1e-9, 0.025)
    throttle = steps(list(throttle_steps))
    inputs = {"throttle": throttle, "brake": lambda tt: np.zeros_like(tt)}
    return synthesize(truth, declared, t, inputs, x0, params, seed, name,
                      f"throttle steps in High range, {duration} s at 40 Hz, simulated from "
                      f"'{truth.name}'", truth_model=tm)


def driving_held_out(truth: BondGraph, declared: BondGraph, name: str, seed: int,
                     **truth_params: float):
    """The validation record of a driving case: the same vehicle driven by
    other throttle steps (:data:`HELD_OUT_STEPS`) with its own noise, named
    ``<name>_run2``; the loop judges and reports on it, never fitting it."""
    return driving_record(truth, declared, f"{name}_run2", seed,
                          throttle_steps=HELD_OUT_STEPS, **truth_params)


#: truth belt-creep coefficient of the belt-slip case [N m s/rad]: 8 gives a
#: creep of about 1 % at cruise and up to ~10 % at low speed under full load
BELT_CREEP = 8.0


def case_slip() -> LoopCase:
    # the clutch creep slope c_cl and the helix gain k_h are known here: with
    # only the engine and secondary speeds measured, clutch creep, a torque-
    # dependent CVT ratio (helix feedback through a quasi-static sheave) and
    # belt creep all show as a torque-proportional drop of w_s/w_e, and cannot
    # be told apart from this record
    params = ["T_pk", "q_grade"]
    # the other parameters are known (stage 1 of the protocol: rolling
    # resistance, drag, dynamic radius, pitch offset; the rest from the table)
    fixed = {k: v for k, v in TRUE_DRIVING.items() if k not in params}
    truth = full_vehicle("truth_belt_slip", VehicleEffects(belt_slip=True))
    return LoopCase(
        "vehicle_belt_slip",
        "Driving record (throttle steps, High range) of a vehicle whose CVT belt creeps on "
        "the secondary sheave; the declared full filter model has a rigid belt. Held out: a "
        "run with other throttle steps.",
        declared_builder(vehicle_slip_declared),
        lambda: driving_record(truth, vehicle_slip_declared(), "throttle_steps_belt_slip",
                               seed=104, c_bs=BELT_CREEP),
        # the driving record too: ros2(1) is 0.21 noise std per sample at the
        # declared fit and at the fit with the slip, ros2(4) 0.06
        LoopSettings(params, metric="nrmse_sim", fixed=fixed,
                     prior=PriorSpec(x0_std={"theta_g": LEVEL_TRACK}), search=COASTDOWN_SEARCH,
                     validation=driving_held_out(truth, vehicle_slip_declared(),
                                                 "throttle_steps_belt_slip", seed=204,
                                                 c_bs=BELT_CREEP)),
        ("slip", "cvt.belt.p2 -> cvt.w_s"))




#: truth saturation level of the engine-torque case, as a fraction of the
#: peak torque T_pk (the issue asks for 60-90 %)
ENGINE_SATURATION = 0.7

#: the engine-torque source of the full vehicle graph (a loop target)
ENGINE_TORQUE = ("source", "engine.torque")


def engine_saturation_truth() -> BondGraph:
    """The declared full filter model plus ``actuator_saturation`` at the
    engine torque, level ``ENGINE_SATURATION`` x T_pk (public effect API)."""
    g = full_vehicle("truth_engine_saturation")
    apply_effect(g, "actuator_saturation", ENGINE_TORQUE,
                 {"L": ENGINE_SATURATION * TRUE_DRIVING["T_pk"]})
    return g


def case_engine_saturation() -> LoopCase:
    # as in the belt-slip case the parameters of stage 1 and the drive line
    # are known; the declared fit can only lower the peak torque T_pk to
    # compensate the saturation (issue 11: the effect must still rank first).
    # It lowers it onto its box (45 N m, the likelihood gaining 516 nats
    # beyond): with T_pk the only physical parameter the loop would call the
    # declared fit failed and stop (runner._declared_fit_verdict); here the
    # box is right and the missing saturation is what pushes T_pk onto it,
    # which is what the case shows, so it goes on as --keep-going does
    params = ["T_pk", "q_grade"]
    fixed = {k: v for k, v in TRUE_DRIVING.items() if k not in params}
    level = ENGINE_SATURATION * TRUE_DRIVING["T_pk"]
    return LoopCase(
        "vehicle_engine_saturation",
        "Driving record (throttle steps, High range) of a vehicle whose engine torque "
        f"saturates smoothly at {level:.1f} N m ({ENGINE_SATURATION:.0%} of the peak "
        "torque); the declared full filter model has the unsaturated torque map. Held out: "
        "a run with other throttle steps.",
        declared_builder(vehicle_slip_declared),
        lambda: driving_record(engine_saturation_truth(), vehicle_slip_declared(),
                                "throttle_steps_engine_saturation", seed=105),
        LoopSettings(params, metric="nrmse_sim", fixed=fixed,
                     prior=PriorSpec(x0_std={"theta_g": LEVEL_TRACK}),
                     search=SearchOptions(on_failed_fit="continue", auto_substeps=True),
                     validation=driving_held_out(engine_saturation_truth(),
                                                 vehicle_slip_declared(),
                                                 "throttle_steps_engine_saturation", seed=205)),
        TrueEffect("actuator_saturation", ENGINE_TORQUE[1], {"L": level}))
