"""Parameter table of the CVT utility vehicle (Polaris Ranger based UGV).

One row per parameter: name, meaning, unit, default, bounds, source. The
builders in :mod:`vehicle_graphs.vehicle` declare from this table only the
parameters the chosen structure uses (e.g. ``i_g`` takes the Low or High
default, ``theta_off`` only exists when the pitch sensor has an offset), and
``docs/vehicle.md`` prints it with :func:`vehicle_graphs.doc.param_table`.

Source tags (as in ``/work/shared/reference/vehicle_physics.md``):

* ``[O]`` from the original work (Auby 2016, master's thesis): measured or
  specified on the vehicle;
* ``[L]`` typical / literature value (vehicle_physics.md §2.2 ranges and the
  references given there), a default to be estimated or measured;
* ``[D]`` design value of this project: chosen inside the [L] range so that
  the assembled model behaves plausibly (shift curve, launch, top speed);
  documented in docs/vehicle.md; not measured;
* ``[N]`` numerical choice (regularisation widths), not physics.

All angles in rad, speeds in rad/s (engine speeds are given in rpm in the
descriptions for reading only).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

RPM = 2.0 * math.pi / 60.0  # rad/s per rpm

#: physical constants (not estimated; fixed in the expressions)
G = 9.81      # m/s^2 [L]
RHO = 1.2     # kg/m^3 [L] air density
TAN_BETA = math.tan(math.radians(13.0))  # sheave half-angle 13 deg [L]
#: primary pitch-radius growth per sheave travel, 1/(2 tan beta), rounded (m/m)
DR_DX = 2.1657


@dataclass(frozen=True)
class ParamSpec:
    """One row of the vehicle's parameter table.

    Attributes
    ----------
    name : str
        Parameter name in every vehicle model (flat, no namespace).
    default : float
    unit : str
        pint unit string.
    bounds : (float, float)
        Estimation box.
    description : str
        Meaning.
    source : str
        ``[O]``, ``[L]``, ``[D]`` or ``[N]`` tag and where the value comes from.
    group : str
        Subsystem (engine, clutch/CVT, driveline, wheel/tire, body, pitch, noise).
    """

    name: str
    default: float
    unit: str
    bounds: tuple[float, float]
    description: str
    source: str
    group: str


def _p(group, name, default, unit, bounds, description, source):
    return ParamSpec(name, float(default), unit, (float(bounds[0]), float(bounds[1])),
                     description, source, group)


#: Gearbox range ratios [L]: High reduction and Low = 2.25 x High (issue: "ratio of
#: the two ranges about 2.25"; vehicle_physics.md §1: Low ~ 2-2.5 x High).
I_HIGH = 2.5
I_LOW = 2.25 * I_HIGH

PARAMS: tuple[ParamSpec, ...] = (
    # ----------------------------------------------------------------- engine
    _p("engine", "J_e", 0.12, "kg*m^2", (0.05, 0.2),
       "engine + primary-clutch inertia", "[L] §2.2 range 0.05-0.2"),
    _p("engine", "T_pk", 65.0, "N*m", (45.0, 90.0),
       "peak full-throttle torque of the map T_wot", "[L] §2.2 range 45-90 (0.5-1.0 L engines)"),
    _p("engine", "w_pk", 4000 * RPM, "rad/s", (3000 * RPM, 5000 * RPM),
       "engine speed of peak torque (4000 rpm)", "[D] inside the usual 3000-5000 rpm"),
    _p("engine", "dw_T", 5000 * RPM, "rad/s", (3500 * RPM, 7000 * RPM),
       "width of the torque parabola: T_wot = T_pk (1 - ((w - w_pk)/dw_T)^2) (70 % at idle)",
       "[D] typical small-engine curve shape"),
    _p("engine", "w_max", 6500 * RPM, "rad/s", (6000 * RPM, 7000 * RPM),
       "rev-limiter speed (6500 rpm): torque fades above it",
       "[L] §2.2 rev limit 6000-7000 rpm"),
    _p("engine", "T_f0", 5.0, "N*m", (0.0, 15.0),
       "constant part of friction + pumping torque", "[L] closed-throttle drag 10-20 % of T_pk"),
    _p("engine", "b_e", 0.012, "N*m*s/rad", (0.0, 0.05),
       "speed-proportional friction + pumping coefficient",
       "[L] with T_f0: 9 N m at 3000 rpm (14 % of T_pk)"),
    _p("engine", "w_idle", 1220 * RPM, "rad/s", (1100 * RPM, 1300 * RPM),
       "idle-governor set speed (1220 rpm; with the droop the engine idles at ~1210 rpm)",
       "[L] §2.2 idle 1100-1300 rpm"),
    _p("engine", "K_idle", 2.0, "N*m*s/rad", (0.5, 10.0),
       "idle-governor gain (torque per rad/s below the set speed)", "[D] droop ~5 rad/s at idle"),
    _p("engine", "tau_m", 0.1, "s", (0.05, 0.2),
       "manifold torque lag (only with manifold_lag=True)", "[L] §2.2 0.05-0.2 s (Guzzella & Onder)"),
    # ------------------------------------------------------------ clutch / CVT
    _p("cvt", "w_eng", 1300 * RPM, "rad/s", (1200 * RPM, 1600 * RPM),
       "clutch engagement speed (1300 rpm): flyweight force = primary-spring preload",
       "[L] §2.2 1200-1600 rpm; issue: 1200-1400 rpm"),
    _p("cvt", "k_fw", 0.044, "N*s^2", (0.02, 0.08),
       "flyweight force per engine speed squared, F_fw = k_fw w_e^2",
       "[D] full-throttle shift at ~3600-3900 rpm, light throttle ~2600 rpm"),
    _p("cvt", "mu_cl", 0.9, "", (0.5, 1.2),
       "effective belt-sheave friction 2 mu_b/cos(beta) of the clamp-to-torque law",
       "[L] mu_b 0.25-0.5, beta 13-14 deg"),
    _p("cvt", "r_p0", 0.04, "m", (0.03, 0.06),
       "primary pitch radius at the low-ratio stop", "[L] §2.2 radii 0.03-0.12 m"),
    _p("cvt", "c_cl", 5.0, "N*m*s/rad", (2.0, 10.0),
       "clutch/belt creep slope: largest dT_cl/d(slip) (caps the clutch stiffness)",
       "[D] creep ~3 % at full load ([L] 1-5 %)"),
    _p("cvt", "k_p", 50000.0, "N/m", (20000.0, 150000.0),
       "primary spring rate over sheave travel", "[D]"),
    _p("cvt", "F_s0", 1320.0, "N", (500.0, 3000.0),
       "secondary spring preload, reflected to the primary sheave (thrust ratio 1)",
       "[D] sets the light-throttle shift speed"),
    _p("cvt", "k_s", 160000.0, "N/m", (50000.0, 400000.0),
       "secondary spring rate, reflected to the primary sheave travel", "[D] flat shift curve"),
    _p("cvt", "k_h", 25.0, "1/m", (10.0, 50.0),
       "helix gain: secondary clamp per secondary torque, 1/(r_h tan phi_h)",
       "[L] §2.2 20-50 1/m"),
    _p("cvt", "b_sh", 20000.0, "N*s/m", (5000.0, 100000.0),
       "sheave damping (massless shift: ratio time constant b_sh/(k_p + k_s) ~ 0.1 s)",
       "[L] tau_cvt 0.1-0.5 s"),
    _p("cvt", "x_max", 0.02, "m", (0.015, 0.025),
       "primary sheave travel between the ratio stops", "[D]"),
    _p("cvt", "i_max", 3.0, "", (2.6, 3.4), "CVT low ratio (launch), r_s/r_p at x_p = 0",
       "[L] §1 about 3:1"),
    _p("cvt", "i_min", 0.7, "", (0.6, 0.8), "CVT overdrive ratio at x_p = x_max",
       "[L] §1 about 0.7:1"),
    _p("cvt", "J_s", 0.05, "kg*m^2", (0.02, 0.08),
       "secondary clutch + gearbox input inertia", "[L] §2.2 0.02-0.08"),
    _p("cvt", "b_s", 0.01, "N*m*s/rad", (0.001, 0.05),
       "secondary / gearbox viscous drag", "[D] small"),
    _p("cvt", "J_b", 0.01, "kg*m^2", (0.002, 0.03),
       "secondary sheave + belt inertia (only with belt_slip=True)", "[D]"),
    _p("cvt", "c_bs", 30.0, "N*m*s/rad", (5.0, 100.0),
       "belt-secondary creep coefficient, T = c_bs (w_b - w_s) (only with belt_slip=True)",
       "[L] creep 1-5 % at full load"),
    # --------------------------------------------------------------- driveline
    _p("driveline", "i_g", I_HIGH, "", (0.9 * I_HIGH, 1.1 * I_LOW),
       f"gearbox reduction of the chosen range (High {I_HIGH:g}, Low {I_LOW:g})",
       "[L] overall High 10-15 with i_fd; Low = 2.25 x High (issue)"),
    _p("driveline", "i_fd", 4.0, "", (3.5, 4.5),
       "final-drive reduction (rear and front)", "[L] overall i_g i_fd = 10 in High"),
    _p("driveline", "k_ds", 15000.0, "N*m/rad", (5000.0, 30000.0),
       "half-shaft torsional stiffness per axle", "[L] §2.2 5e3-3e4"),
    _p("driveline", "c_ds", 40.0, "N*m*s/rad", (10.0, 150.0),
       "half-shaft torsional damping per axle (zeta ~ 0.1)", "[L] zeta 0.05-0.2"),
    # -------------------------------------------------------------- wheel/tire
    _p("wheel", "r_dyn", 0.31, "m", (0.28, 0.35),
       "dynamic tire radius", "[L] §2.2 0.30-0.34 (25-27 in tires)"),
    _p("wheel", "r_dyn_f", 0.31, "m", (0.28, 0.35),
       "dynamic tire radius of the front axle (models with per-axle radii)",
       "[L] §2.2 0.30-0.34; a puncture lowers one axle's radius"),
    _p("wheel", "r_dyn_r", 0.31, "m", (0.28, 0.35),
       "dynamic tire radius of the rear axle (models with per-axle radii)",
       "[L] §2.2 0.30-0.34; a puncture lowers one axle's radius"),
    _p("wheel", "J_w", 1.5, "kg*m^2", (1.0, 2.0),
       "inertia of one wheel + tire + hub + disc (+ its share of drive-line parts)",
       "[L] §2.2 1-2"),
    _p("wheel", "f_r", 0.02, "", (0.005, 0.15),
       "rolling-resistance coefficient", "[L] §2.2 paved 0.01-0.02, gravel 0.02-0.05"),
    _p("wheel", "mu", 0.9, "", (0.2, 1.1), "peak tire-road friction (Magic Formula D/F_z)",
       "[L] §2.2 dry asphalt 0.8-1.0"),
    _p("wheel", "k_slip", 15.0, "", (5.0, 20.0),
       "longitudinal slip stiffness per normal load, C_kappa/F_z = BCD/F_z",
       "[L] §2.2 5-20"),
    _p("wheel", "C_mf", 1.65, "", (1.3, 1.9), "Magic Formula shape factor C",
       "[L] §2.2 1.6-1.7 (Pacejka 2012)"),
    _p("wheel", "E_mf", 0.0, "", (-1.0, 0.5), "Magic Formula curvature factor E",
       "[L] §2.2 -1 < E < 0.5"),
    _p("wheel", "T_bmax", 1000.0, "N*m", (500.0, 1500.0),
       "brake torque per wheel at full command", "[L] §2.2 0.5-1.5 kN m"),
    _p("wheel", "T_bd", 8.0, "N*m", (0.0, 30.0),
       "residual brake drag torque per wheel (only with brake_drag=True)", "[D] truth effect"),
    # -------------------------------------------------------------------- body
    _p("body", "m", 1200.0, "kg", (1100.0, 1300.0),
       "vehicle mass (1040 kg empty + 160 kg occupants)", "[O] vehicle scale, +-20 kg"),
    _p("body", "g", G, "m/s^2", (9.78, 9.83),
       "gravitational acceleration (a constant; a symbol so units check)", "[L] standard"),
    _p("body", "C_dA", 1.8, "m^2", (1.0, 2.8),
       "aerodynamic drag area (air density 1.2 kg/m^3 fixed)", "[L] §2.2 open, boxy 1.2-2.5"),
    _p("body", "L_wb", 2.05, "m", (2.0, 2.1), "wheelbase", "[O] vehicle specification"),
    _p("body", "l_f", 1.26, "m", (1.2, 1.32), "front axle to centre of mass",
       "[O] from axle loads (rear: L_wb - l_f = 0.79 m)"),
    _p("body", "h_cg", 0.60, "m", (0.4, 0.8), "centre-of-mass height",
       "[O] educated guess, not measured"),
    _p("body", "q_grade", 0.01, "rad/s^0.5", (1e-5, 0.05),
       "grade random-walk intensity (filter models)", "[L] §2.2 0.005-0.05 by terrain"),
    # ------------------------------------------------------------------- pitch
    _p("pitch", "I_theta", 1093.0, "kg*m^2", (800.0, 1400.0), "pitch moment of inertia",
       "[O] formula m_ve (L/2)^2"),
    _p("pitch", "k_theta", 1.0e5, "N*m/rad", (4.0e4, 1.7e5), "pitch (suspension) stiffness",
       "[L] §2.2 4e4-1.7e5 (1-2 Hz)"),
    _p("pitch", "c_theta", 6000.0, "N*m*s/rad", (2600.0, 11000.0), "pitch damping (zeta ~ 0.29)",
       "[L] §2.2 2.6e3-1.1e4"),
    _p("pitch", "theta_off", 0.0, "rad", (-0.035, 0.035),
       "pitch-sensor / suspension mounting offset", "[O] exists, value unknown; [L] +-2 deg"),
)

BY_NAME: dict[str, ParamSpec] = {p.name: p for p in PARAMS}


def spec(name: str) -> ParamSpec:
    """Row of the table by name.

    Raises
    ------
    KeyError
        Naming the unknown parameter and listing the known ones.
    """
    try:
        return BY_NAME[name]
    except KeyError:
        raise KeyError(f"vehicle parameter table has no '{name}' "
                       f"(known: {', '.join(BY_NAME)})") from None
