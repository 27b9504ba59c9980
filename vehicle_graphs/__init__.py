"""The CVT utility vehicle (Polaris Ranger based UGV) as bond graphs.

* :mod:`vehicle_graphs.params` — the parameter table (name, meaning, unit,
  default, bounds, source);
* :mod:`vehicle_graphs.subsystems` — engine, clutch/CVT, drive line, axle
  (wheels, brakes, tires), body, pitch as reusable fragments;
* :mod:`vehicle_graphs.vehicle` — :func:`build_vehicle` (structural
  configuration: gear L/H/N, 2WD/AWD, lumped wheels, suspension
  approximation, optional effects) and the registered models;
* :mod:`vehicle_graphs.experiments` — synthetic experiments (coast-down,
  throttle steps, full throttle, braking, hill climb) at 40 Hz;
* :mod:`vehicle_graphs.analysis` — initial states, quasi-static pitch,
  coast-down road-load least squares, stiffness at operating points;
* :mod:`vehicle_graphs.doc` — the parameter table of ``docs/vehicle.md``.

See ``docs/vehicle.md``.
"""

from .subsystems import Numerics  # noqa: F401
from .vehicle import VehicleEffects, build_vehicle  # noqa: F401

#: registered models (``bondgraph generate`` writes ``generated/<name>.py``)
MODELS: dict[str, str] = {
    "vehicle_full": "vehicle_graphs.vehicle:vehicle_full",
    "vehicle_full_low": "vehicle_graphs.vehicle:vehicle_full_low",
    "vehicle_coastdown": "vehicle_graphs.vehicle:vehicle_coastdown",
    "vehicle_coastdown_rigid": "vehicle_graphs.vehicle:vehicle_coastdown_rigid",
    "vehicle_coastdown_truth": "vehicle_graphs.vehicle:vehicle_coastdown_truth",
}

#: registered synthetic experiments (``name -> "module:function"`` returning an
#: :class:`bondgraph.data.experiments.ExperimentSpec`)
EXPERIMENTS: dict[str, str] = {
    "vehicle_coastdown": "vehicle_graphs.experiments:coastdown",
    "vehicle_full_throttle_high": "vehicle_graphs.experiments:full_throttle_high",
    "vehicle_full_throttle_low": "vehicle_graphs.experiments:full_throttle_low",
    "vehicle_throttle_steps_high": "vehicle_graphs.experiments:throttle_steps_high",
    "vehicle_throttle_steps_low": "vehicle_graphs.experiments:throttle_steps_low",
    "vehicle_braking": "vehicle_graphs.experiments:braking",
    "vehicle_hill_climb": "vehicle_graphs.experiments:hill_climb",
}
