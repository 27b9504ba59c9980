"""The assembled vehicle: builder with structural configuration, and the
registered filter and truth models.

:func:`build_vehicle` composes the fragments of :mod:`vehicle_graphs.subsystems`
(engine, clutch/CVT, drive line, axles, body, pitch) into one bond graph.
Gear (L/H/N), drive (2WD/AWD), wheel lumping, suspension approximation and the
optional physical effects are *structural* arguments: they add or remove
elements and bonds, never set a modulus to zero.

Registered models (see ``MODELS`` in :mod:`vehicle_graphs`):

=========================  ========================================================
``vehicle_full``           full filter model, High range, 2WD (rear), 10 states
``vehicle_full_low``       the same in Low range
``vehicle_coastdown``      reduced coast-down filter model: neutral, no power
                           train, one lumped wheel, dynamic pitch (5 states)
``vehicle_coastdown_rigid`` the same with the cruder rigid-body approximation
                           (no suspension pitch, 3 states)
``vehicle_coastdown_truth`` truth of the coast-down experiments: neutral, per
                           axle wheels and loads, pitch-state load transfer,
                           pitch offset (6 states)
=========================  ========================================================
"""

from __future__ import annotations

from dataclasses import dataclass

import sympy as sp

from bondgraph import BondGraph

from . import params as _params
from . import subsystems as sub
from .subsystems import Numerics, const

#: measurement-noise standard deviations of the 40 Hz sensors (model units);
#: documented in docs/vehicle.md (realistic values for the instrument class)
SENSOR_NOISE: dict[str, float] = {
    "w_e": 2.0,       # rad/s (~20 rpm): engine speed from ignition pulses
    "w_s": 1.0,       # rad/s: CVT secondary speed, Hall sensor
    "w_wf": 0.2,      # rad/s (0.06 m/s): front wheel speed (ABS tone ring)
    "w_wr": 0.2,      # rad/s: rear wheel speed
    "v_gnss": 0.05,   # m/s: GNSS Doppler speed
    "pitch": 0.0017,  # rad (0.1 deg): IMU attitude pitch
    "a_x": 0.1,       # m/s^2: MEMS accelerometer with vehicle vibration
}

SENSOR_UNITS: dict[str, str] = {"w_e": "rad/s", "w_s": "rad/s", "w_wf": "rad/s",
                                "w_wr": "rad/s", "v_gnss": "m/s", "pitch": "rad",
                                "a_x": "m/s^2"}

SENSOR_DESCRIPTIONS: dict[str, str] = {
    "w_e": "engine speed",
    "w_s": "CVT secondary speed",
    "w_wf": "front wheel speed",
    "w_wr": "rear wheel speed",
    "v_gnss": "GNSS speed over ground",
    "pitch": "reported pitch: grade + suspension pitch (+ mounting offset)",
    "a_x": "longitudinal accelerometer (specific force, body axis)",
}


#: continuous-time process-noise intensities of the mechanical speeds, in
#: flow units per sqrt(s) (the momentum states get inertia x intensity):
#: unmodelled disturbances (road roughness, torque ripple). They are small
#: (over one 25 ms sample the body speed gets 0.6 mm/s, the engine 0.06 rad/s
#: of standard deviation, well below the sensor noise) and keep the UKF's
#: predicted covariance positive definite where the dynamics contract
#: strongly (brake held at standstill); see docs/vehicle.md. The grade's
#: random walk (parameter q_grade) is the main process noise, as in the
#: original work.
PROCESS_NOISE: dict[str, float] = {
    "v": 0.004,        # m/s/sqrt(s), body speed
    "w_wheel": 0.033,  # rad/s/sqrt(s), wheel speeds
    "w_e": 0.4,        # rad/s/sqrt(s), engine speed
    "w_s": 0.2,        # rad/s/sqrt(s), secondary speed
}


class _LazyParams(dict):
    """Declares a parameter of the table in the graph on first use."""

    def __init__(self, g: BondGraph, overrides: dict[str, float]):
        super().__init__()
        self.g = g
        self.overrides = overrides

    def __missing__(self, name):
        row = _params.spec(name)
        default = self.overrides.get(name, row.default)
        p = self.g.param(name, default, row.unit, row.bounds, row.description, row.source)
        self[name] = p
        return p


GEARS = ("L", "H", "N")


@dataclass(frozen=True)
class VehicleEffects:
    """The physical effects a vehicle graph has or lacks (truth models of
    synthetic tests have some that the filter models lack).

    Attributes
    ----------
    aero : bool
        Aerodynamic drag R on the body.
    brake_drag : bool
        Residual brake drag torque T_bd per wheel (truth effect).
    pitch_offset : bool
        The pitch sensor has a fixed mounting offset theta_off.
    belt_slip : bool
        Creep law between belt and secondary sheave (truth effect).
    manifold_lag : bool
        First-order manifold torque lag state.
    """

    aero: bool = True
    brake_drag: bool = False
    pitch_offset: bool = True
    belt_slip: bool = False
    manifold_lag: bool = False


def build_vehicle(name: str = "vehicle", *, gear: str = "H", drive: str = "2WD",
                  powertrain: bool = True, wheels: str = "axles",
                  suspension: str = "dynamic", shaft_compliance: bool = True,
                  effects: VehicleEffects = VehicleEffects(), grade: str = "state",
                  numerics: Numerics = Numerics(), description: str | None = None,
                  process_noise: dict[str, float] | None = None,
                  radius: str = "shared") -> BondGraph:
    """Build the vehicle's bond graph.

    Parameters
    ----------
    name : str
        Graph (model) name.
    gear : {"H", "L", "N"}
        Gearbox range; "N" removes the drive line (engine and CVT, if
        present, run decoupled from the wheels).
    drive : {"2WD", "AWD"}
        Rear-wheel drive, or both axles driven through the gearbox output.
    powertrain : bool
        Include engine, clutch and CVT (False: the coast-down models; needs
        gear "N").
    wheels : {"axles", "lumped"}
        One lumped wheel per axle with its own normal load (front/rear), or
        one wheel for the whole vehicle (coast-down filter model; needs
        gear "N" without power train).
    suspension : {"dynamic", "rigid"}
        "dynamic": pitch states theta_s, dtheta_s/dt driven by the
        longitudinal force at the centre-of-mass height; the load transfer
        between the axles comes from the pitch state (vehicle_physics.md
        §3.8), and the pitch sensor reads theta_g + theta_s (+ offset).
        "rigid": no suspension; no load transfer; the pitch sensor reads the
        grade (+ offset) only: the original work's cruder approximation as we
        read it.
    shaft_compliance : bool
        Half-shaft compliance (C with R) per driven axle; without it SCAP
        lumps secondary, gearbox and driven wheels into one inertia.
    effects : VehicleEffects
        Aerodynamic drag, brake drag, pitch-sensor offset, belt slip,
        manifold lag (default: drag and the offset).
    grade : {"state", "input"}
        Road grade as a random-walk state theta_g (filter models; intensity
        q_grade) or as an input ``grade`` [rad] (truth models with a grade
        profile).
    numerics : Numerics
        Regularisation widths.
    description : str, optional
    process_noise : dict, optional
        Intensities of the speed disturbances ``{"v", "w_wheel", "w_e",
        "w_s"}`` in flow units per sqrt(s) (default :data:`PROCESS_NOISE`;
        a missing key or 0 declares none). The grade's intensity is the
        parameter ``q_grade``.
    radius : {"shared", "per_axle"}
        One dynamic tire radius ``r_dyn`` for every wheel, or one per axle
        (``r_dyn_f``, ``r_dyn_r``; needs wheels "axles"): what a puncture
        changes, so that front and rear wheel speeds may disagree at the
        same body speed.

    Returns
    -------
    BondGraph

    Raises
    ------
    ValueError
        For an unknown or inconsistent configuration (the message names the
        argument).
    """
    config = dict(gear=gear, drive=drive, powertrain=powertrain, wheels=wheels,
                  suspension=suspension, shaft_compliance=shaft_compliance,
                  aero=effects.aero, brake_drag=effects.brake_drag,
                  pitch_offset=effects.pitch_offset, belt_slip=effects.belt_slip,
                  manifold_lag=effects.manifold_lag, grade=grade, radius=radius)
    _check_config(config)
    g = _new_graph(name, description, config, numerics)
    _assemble(g, config, numerics, process_noise)
    return g


def _new_graph(name: str, description: str | None, config: dict,
               numerics: Numerics) -> BondGraph:
    """The empty graph, its configuration and numerics in ``metadata``; the
    default description lists the configuration."""
    if description is None:
        description = "CVT utility vehicle (Polaris Ranger UGV), longitudinal dynamics: " + \
            ", ".join(f"{k}={v}" for k, v in config.items()) + "."
    g = BondGraph(name, description)
    g.metadata["config"] = config
    g.metadata["numerics"] = numerics
    return g


def _assemble(g: BondGraph, c: dict, numerics: Numerics,
              process_noise: dict[str, float] | None) -> None:
    """Inputs and grade, body, pitch, wheels, pitch drive, power train and
    drive line, process noise, sensors, in this order (the order of the
    states and bonds); then the parameters in table order (a stable theta
    layout)."""
    overrides = {"i_g": _params.I_LOW} if c["gear"] == "L" else {}
    P = _LazyParams(g, overrides)
    brake = g.input("brake", "", 0.0, "brake command u_b in [0, 1]")
    throttle = g.input("throttle", "", 0.0, "throttle command u_th in [0, 1]") \
        if c["powertrain"] else None
    if c["grade"] == "state":
        theta_g = g.state("theta_g", 0, unit="rad", process_noise=P["q_grade"],
                          description="road grade (random walk), positive uphill")
    else:
        theta_g = g.input("grade", "rad", 0.0, "road grade, positive uphill")
    hb = g.include(sub.body(P, theta_g, numerics, aero=c["aero"]), "body")
    v = hb.port("v").f
    hp, theta_s, dF = _pitch(g, P, c["suspension"])
    axles = _axles(g, P, hb, v, theta_g, dF, brake, wheels=c["wheels"], numerics=numerics,
                   brake_drag=c["brake_drag"], radius=c["radius"])
    if hp is not None:
        _pitch_drive(g, P, hb, hp)
    he = hc = None
    if c["powertrain"]:
        he, hc = _powertrain(g, P, throttle, axles, numerics, gear=c["gear"], drive=c["drive"],
                             shaft_compliance=c["shaft_compliance"], belt_slip=c["belt_slip"],
                             manifold_lag=c["manifold_lag"])
    _process_noise(g, process_noise, [(hb["m"], "v")]
                   + [(h["J"], "w_wheel") for h in axles.values()]
                   + ([(he["J"], "w_e"), (hc["J_s"], "w_s")] if he is not None else []))
    _sensors(g, P, hb, v, axles, he, hc, theta_g, theta_s, pitch_offset=c["pitch_offset"])
    order = {p.name: i for i, p in enumerate(_params.PARAMS)}
    g.params = dict(sorted(g.params.items(), key=lambda kv: order[kv[0]]))


def _check_config(c: dict) -> None:
    """Raise ValueError, naming the argument, for an unknown or inconsistent
    configuration of :func:`build_vehicle`."""
    gear = c["gear"]
    if gear not in GEARS:
        raise ValueError(f"gear must be one of {GEARS}, not {gear!r}")
    if c["wheels"] not in ("axles", "lumped"):
        raise ValueError(f"wheels must be 'axles' or 'lumped', not {c['wheels']!r}")
    if c["suspension"] not in ("dynamic", "rigid"):
        raise ValueError(f"suspension must be 'dynamic' or 'rigid', not {c['suspension']!r}")
    if c["grade"] not in ("state", "input"):
        raise ValueError(f"grade must be 'state' or 'input', not {c['grade']!r}")
    if c["drive"] not in ("2WD", "AWD"):
        raise ValueError(f"drive must be '2WD' or 'AWD', not {c['drive']!r}")
    if c["wheels"] == "lumped" and gear != "N":
        raise ValueError("wheels='lumped' (one wheel for the vehicle) needs gear='N': a driven "
                         "axle has its own wheel speed")
    if not c["powertrain"] and gear != "N":
        raise ValueError(f"powertrain=False needs gear='N' (got gear={gear!r})")
    if c["belt_slip"] and not c["powertrain"]:
        raise ValueError("belt_slip=True needs powertrain=True")
    if c["manifold_lag"] and not c["powertrain"]:
        raise ValueError("manifold_lag=True needs powertrain=True")
    if c["radius"] not in ("shared", "per_axle"):
        raise ValueError(f"radius must be 'shared' or 'per_axle', not {c['radius']!r}")
    if c["radius"] == "per_axle" and c["wheels"] != "axles":
        raise ValueError("radius='per_axle' needs wheels='axles' (one wheel per axle)")


def _pitch(g: BondGraph, P, suspension: str):
    """The suspension pitch fragment (``"dynamic"``) or none (``"rigid"``):
    its handle, the pitch angle theta_s and the load transfer dF between the
    axles it causes (§3.8); 0 and 0 without it."""
    if suspension != "dynamic":
        return None, sp.Integer(0), sp.Integer(0)
    hp = g.include(sub.pitch(P), "pitch")
    theta_s = hp["k"].q
    dF = (P["k_theta"] * theta_s + P["c_theta"] * hp.port("rate").f) / P["L_wb"]
    return hp, theta_s, dF


class _Renamed(dict):
    """A view of the parameter mapping ``P`` in which some names stand for
    others (``r_dyn`` -> ``r_dyn_r`` for the rear axle of a per-axle model)."""

    def __init__(self, P, names: dict[str, str]):
        super().__init__()
        self.P, self.names = P, names

    def __missing__(self, name):
        return self.P[self.names.get(name, name)]


def _axles(g: BondGraph, P, hb, v, theta_g, dF, brake, *, wheels: str, numerics: Numerics,
           brake_drag: bool, radius: str = "shared") -> dict:
    """Wheels and tires connected to the body (speed ``v``): one lumped wheel
    (all four), or rear and front axles with their static loads plus/minus
    the load transfer ``dF`` (with ``radius="per_axle"`` each with its own
    dynamic radius ``r_dyn_r``, ``r_dyn_f``). Returns the handles by name
    (``wheels`` or ``rear``, ``front``)."""
    mg_cos = P["m"] * P["g"] * sp.cos(theta_g)
    axles = {}
    if wheels == "lumped":
        axles["wheels"] = g.include(sub.axle(P, n_wheels=4, F_z=mg_cos, v=v, brake=brake,
                                             num=numerics, brake_drag=brake_drag), "wheels")
    else:
        Fz_r = mg_cos * P["l_f"] / P["L_wb"] + dF
        Fz_f = mg_cos * (P["L_wb"] - P["l_f"]) / P["L_wb"] - dF
        Pr, Pf = (P, P) if radius == "shared" else \
            (_Renamed(P, {"r_dyn": "r_dyn_r"}), _Renamed(P, {"r_dyn": "r_dyn_f"}))
        axles["rear"] = g.include(sub.axle(Pr, n_wheels=2, F_z=Fz_r, v=v, brake=brake,
                                           num=numerics, brake_drag=brake_drag), "rear")
        axles["front"] = g.include(sub.axle(Pf, n_wheels=2, F_z=Fz_f, v=v, brake=brake,
                                            num=numerics, brake_drag=brake_drag), "front")
    for h in axles.values():
        g.connect(h.port("ground"), hb.port("v"))
    return axles


def _pitch_drive(g: BondGraph, P, hb, hp) -> None:
    """Pitch drive: the longitudinal ground force at the centre-of-mass height.

    Ground forces (tires) pitch the body about its centre of mass; forces
    acting on the body itself (gravity along the grade, aerodynamic drag, any
    force added later at the body junction) do not. The ground force is the
    body's net force minus the gravity component: h_cg (m dv/dt - F_grav) =
    h_cg (F_tires - F_aero) for this graph, but written from the junction so
    it stays right when forces are added to the body.
    """
    drive_src = g.MSe("pitch_drive", P["h_cg"] * (hb["m"].e - hb["gravity"].e))
    g.connect(drive_src, hp.port("rate"))


def _powertrain(g: BondGraph, P, throttle, axles: dict, numerics: Numerics, *, gear: str,
                drive: str, shaft_compliance: bool, belt_slip: bool, manifold_lag: bool):
    """Engine and clutch/CVT, and (gear L or H) the drive line to the rear (and,
    AWD, front) hubs. Returns the engine and CVT handles."""
    he = g.include(sub.engine(P, throttle, numerics, manifold_lag=manifold_lag), "engine")
    w_e = he.port("shaft").f
    hc = g.include(sub.clutch_cvt(P, w_e, numerics, belt_slip=belt_slip), "cvt")
    g.connect(he.port("shaft"), hc.port("engine"))
    if gear != "N":
        hd = g.include(sub.driveline(P, drive=drive, shaft_compliance=shaft_compliance),
                       "driveline")
        g.connect(hc.port("secondary"), hd.port("input"))
        g.connect(hd.port("rear"), axles["rear"].port("hub"))
        if drive == "AWD":
            g.connect(hd.port("front"), axles["front"].port("hub"))
    return he, hc


def _process_noise(g: BondGraph, process_noise: dict[str, float] | None, inertias) -> None:
    """Speed disturbances on the momenta: inertia x intensity, for each
    ``(inertia element, key)`` whose intensity (default :data:`PROCESS_NOISE`)
    is given and non-zero.

    Raises
    ------
    ValueError
        Unknown keys.
    """
    qn = PROCESS_NOISE if process_noise is None else process_noise
    unknown = set(qn) - set(PROCESS_NOISE)
    if unknown:
        raise ValueError(f"process_noise has unknown keys {sorted(unknown)} "
                         f"(known: {', '.join(PROCESS_NOISE)})")
    for element, key in inertias:
        if qn.get(key):
            g.set_process_noise(element.state, element.inertance * const(qn[key]))


def _sensors(g: BondGraph, P, hb, v, axles: dict, he, hc, theta_g, theta_s, *,
             pitch_offset: bool) -> None:
    """The 40 Hz sensors: engine and secondary speeds (with a power train),
    front and rear wheel speeds, GNSS speed, pitch (grade + suspension pitch
    + offset) and the longitudinal accelerometer (specific force)."""
    def sensor(nm, expr):
        g.sensor(nm, expr, unit=SENSOR_UNITS[nm], noise_std=SENSOR_NOISE[nm],
                 description=SENSOR_DESCRIPTIONS[nm])

    if he is not None:
        sensor("w_e", he.port("shaft").f)
        sensor("w_s", hc.port("secondary").f)
    front, rear = (axles["wheels"], axles["wheels"]) if "wheels" in axles else \
        (axles["front"], axles["rear"])
    sensor("w_wf", front.port("hub").f)
    sensor("w_wr", rear.port("hub").f)
    sensor("v_gnss", v)
    pitch_meas = theta_g + theta_s
    if pitch_offset:
        pitch_meas = pitch_meas + P["theta_off"]
    sensor("pitch", pitch_meas)
    sensor("a_x", hb["m"].e / P["m"] + P["g"] * sp.sin(theta_g + theta_s))


# ------------------------------------------------------------ registered
def vehicle_full() -> BondGraph:
    """Full filter model: High range, rear-wheel drive (the Ranger's normal
    mode; its on-demand AWD engages the front axle only when the rear
    slips), half-shaft compliance, dynamic pitch, grade random walk,
    pitch-sensor offset. 10 states."""
    return build_vehicle("vehicle_full", gear="H", drive="2WD",
                         description="Full filter model of the CVT utility vehicle, High range, "
                                     "2WD: engine, centrifugal clutch, CVT shift state, "
                                     "secondary, half-shaft, front and rear wheels, body, "
                                     "pitch, grade random walk.")


def vehicle_track() -> BondGraph:
    """The full filter model with one dynamic tire radius per axle
    (``r_dyn_f``, ``r_dyn_r``): the model for tracking what changes while
    driving (a punctured tire's radius, rolling resistance, peak friction),
    where front and rear wheel speeds may disagree. High range, 2WD.
    10 states. Not registered (``vehicle_graphs.vehicle:vehicle_track``)."""
    return build_vehicle("vehicle_track", gear="H", drive="2WD", radius="per_axle",
                         description="Full filter model with per-axle dynamic tire radii "
                                     "(tracking a puncture), High range, 2WD.")


def vehicle_track_low() -> BondGraph:
    """:func:`vehicle_track` in Low range (i_g = 2.25 x High): hard launches
    that reach the tires' friction limit. Not registered
    (``vehicle_graphs.vehicle:vehicle_track_low``)."""
    return build_vehicle("vehicle_track_low", gear="L", drive="2WD", radius="per_axle",
                         description="Full filter model with per-axle dynamic tire radii, "
                                     "Low range, 2WD.")


def vehicle_full_low() -> BondGraph:
    """Full filter model in Low range (i_g = 2.25 x High), 2WD. 10 states."""
    return build_vehicle("vehicle_full_low", gear="L", drive="2WD",
                         description="Full filter model of the CVT utility vehicle, Low range, "
                                     "2WD.")


def vehicle_coastdown() -> BondGraph:
    """Reduced coast-down filter model: neutral, no engine or CVT, one lumped
    wheel (all four), dynamic pitch driven by the tire and drag forces at
    the centre-of-mass height, grade random walk, pitch offset. 5 states."""
    return build_vehicle("vehicle_coastdown", gear="N", powertrain=False, wheels="lumped",
                         suspension="dynamic",
                         description="Reduced coast-down filter model: neutral, lumped wheels, "
                                     "body with drag, dynamic pitch, grade random walk.")


def vehicle_coastdown_rigid() -> BondGraph:
    """Coast-down filter model with the cruder rigid approximation: no
    suspension pitch (the pitch sensor is read as grade + offset). 3 states."""
    return build_vehicle("vehicle_coastdown_rigid", gear="N", powertrain=False,
                         wheels="lumped", suspension="rigid",
                         description="Coast-down filter model with a rigid body (suspension "
                                     "pitch neglected): the original work's approximation.")


def vehicle_coastdown_truth() -> BondGraph:
    """Truth model of the coast-down experiments: the full vehicle in neutral
    without the (decoupled) power train: front and rear wheels with their
    own loads, load transfer from the pitch state. 6 states."""
    return build_vehicle("vehicle_coastdown_truth", gear="N", powertrain=False,
                         wheels="axles", suspension="dynamic",
                         description="Truth model of coast-down records: vehicle in neutral "
                                     "with per-axle wheels and pitch-state load transfer.")
