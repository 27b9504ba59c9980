"""Bond graphs of the public real-data benchmarks in ``../shared/data``.

* ``emps`` — Electro-Mechanical Positioning System (Janot, Gautier & Brunot
  2019): a DC motor and ball screw moving a load, in a closed PD loop. The
  drive force is τ = gtau·vir; the rigid inverse model of the benchmark is
  τ = M q̈ + Fv q̇ + Fc sign(q̇) + offset::

      MSe(gtau·vir) → 1(v) ← I: M, R: Fv, R: Fc·tanh(v/v_eps), Se: −offset
                       └→ ∫ → q (position sensor qm)

  Filter model for the UKF: force noise of intensity ``q_F`` on the
  momentum (unmodelled forces), encoder noise ``sigma_q`` on qm.
* ``emps_viscous`` — the starting graph of a residual-tracing loop: mass and
  viscous friction only (no Coulomb friction, no offset).
* ``ced_linear`` — Coupled Electric Drives (Wigren & Schoukens 2017), the
  linear part of the benchmark's reference model,
  y = k ω0² / ((s + a)(s² + 2ζω0 s + ω0²)) u, as a bond graph::

      Se(u) → 1(i) ← R: R_a, I: L_a
               └→ GY: k_m → 1(ω_m) ← R: b_m
                              └→ 0(belt) ← C: 1/k_b   (belt and tensioner spring)
                                   └→ 1(ω_p) ← I: J_p, R: b_p   (pulley)
      sensor: speed = k_y·ω_p

  Defaults reproduce the continuous-time poles and gain of the report's
  eq. (9) discrete model (a = 7.21 1/s, ω0 = 21.2 rad/s, ζ = 0.12, DC gain
  1.83): see :func:`ced_linear`. The sign-blind counter (|speed|) and the
  anti-alias filter are the benchmark's undeclared effects and are not in
  this graph.
* ``camry_fuel`` — the 2018 Toyota Camry on a chassis dyno (ANL D3, 1 Hz):
  imposed speed, road load, Willans-line engine with idle fuel and a
  lagged fuel flow, declared warm (no thermal state). :func:`camry_warm`
  (the same graph with the hot-cycle fit's powertrain parameters,
  :data:`CAMRY_HOT_FIT`; the ``camry_cold`` case's declared graph) is built
  in memory, not registered: its generated code would repeat camry_fuel's.

References
----------
Janot, A., Gautier, M., Brunot, M. (2019). Data set and reference models of
EMPS. Nonlinear System Identification Benchmarks workshop, Eindhoven.
Wigren, T., Schoukens, M. (2017). Coupled electric drives data set and
reference models. Technical Report 2017-024, Uppsala University.
Guzzella, L., Sciarretta, A. (2013). Vehicle Propulsion Systems, 3rd ed.,
Springer.
"""

from __future__ import annotations

import sympy as sp

from bondgraph.core.graph import BondGraph

#: registered models (``bondgraph.models`` entry point; ``bondgraph generate``)
MODELS: dict[str, str] = {
    "emps": "bondgraph.catalog.benchmarks:emps",
    "emps_viscous": "bondgraph.catalog.benchmarks:emps_viscous",
    "ced_linear": "bondgraph.catalog.benchmarks:ced_linear",
    "silverbox_linear": "bondgraph.catalog.benchmarks:silverbox_linear",
    "camry_fuel": "bondgraph.catalog.benchmarks:camry_fuel",
}

#: force constant of the EMPS drive [N/V] (stored in DATA_EMPS.mat)
EMPS_GTAU = 35.15065

#: published IDIM-LS estimates, symmetric friction (Janot et al. 2019)
EMPS_IDIM_LS = {"M": 95.1089, "Fv": 203.5034, "Fc": 20.3935, "offset": -3.1648}
#: published force relative error of that model on the estimation record [%]
EMPS_IDIM_RELERR = 4.08


def _emps_base(name: str, description: str):
    g = BondGraph(name, description)
    vir = g.input("vir", "V", 0.0, "drive command (controller output); force = gtau*vir")
    gtau = g.param("gtau", EMPS_GTAU, "N/V", (30.0, 40.0), "drive force constant (known)",
                   source="Janot et al. 2019, DATA_EMPS.mat")
    M = g.param("M", 95.0, "kg", (50.0, 150.0), "moving mass (motor, screw and load)")
    Fv = g.param("Fv", 200.0, "N*s/m", (50.0, 400.0), "viscous friction")
    qF = g.param("q_F", 5.0, "", (0.05, 100.0),
                 "process-noise intensity on the momentum [N*sqrt(s)]: unmodelled forces")
    sq = g.param("sigma_q", 2e-7, "m", (1e-8, 1e-4),
                 "position measurement noise (encoder step 5e-8 m)")
    v = g.one("v", domain="translation")
    g.connect(g.MSe("motor", gtau * vir), v)
    mass = g.I("M", M)
    g.connect(v, mass)
    g.connect(v, g.R("Fv", Fv))
    g.set_process_noise(mass.p, qF)
    return g, v, sq


def emps() -> BondGraph:
    """EMPS drive: mass, viscous and Coulomb friction, force offset (3 parameters
    of friction + mass, 2 of noise; 2 states: momentum of M and position).

    Hand-derived (p = M q̇)::

        dp/dt = gtau·vir − Fv p/M − Fc tanh(p/(M v_eps)) − offset
        dq/dt = p/M,            y = q (qm)

    ``v_eps`` (default 1 mm/s, fixed) regularises sign(q̇); the benchmark's
    velocities reach 0.13 m/s.
    """
    g, v, sq = _emps_base("emps", "EMPS drive: mass, viscous + Coulomb friction, force offset, "
                                  "position sensor (Janot et al. 2019).")
    Fc = g.param("Fc", 20.0, "N", (0.0, 50.0), "Coulomb friction")
    off = g.param("offset", -3.0, "N", (-15.0, 15.0), "force offset")
    eps = g.param("v_eps", 1e-3, "m/s", (1e-4, 1e-2), "tanh width of the Coulomb law (fixed)")
    g.connect(v, g.R("coulomb", effort=lambda f: Fc * sp.tanh(f / eps)))
    g.connect(g.Se("offset", -off), v)
    q = g.displacement(v, name="q", unit="m")
    g.sensor("qm", q, unit="m", noise_std=sq, description="motor position (load side)")
    return g


def emps_viscous() -> BondGraph:
    """EMPS starting graph: mass and viscous friction only (no Coulomb
    friction, no offset), for the residual-tracing loop::

        dp/dt = gtau·vir − Fv p/M,   dq/dt = p/M,   y = q
    """
    g, v, sq = _emps_base("emps_viscous", "EMPS drive, starting graph: mass and viscous "
                                          "friction only.")
    q = g.displacement(v, name="q", unit="m")
    g.sensor("qm", q, unit="m", noise_std=sq, description="motor position (load side)")
    return g


def ced_linear() -> BondGraph:
    """CED belt-and-pulley drive, linear part (3 states: flux linkage of L_a,
    belt deflection, pulley momentum).

    Hand-derived (λ = L_a i, φ belt deflection, p = J_p ω_p; the motor
    junction has no inertia, so ω_m = (k_m i − k_b φ)/b_m)::

        dλ/dt = u − R_a λ/L_a − k_m ω_m
        dφ/dt = ω_m − p/J_p
        dp/dt = k_b φ − b_p p/J_p,         y = k_y p/J_p

    Defaults (L_a, k_m, J_p, b_p chosen; R_a, b_m, k_b, k_y fitted) give
    poles −7.21 and −2.53 ± 21.04j 1/s and DC gain 1.83, the continuous
    equivalents of the report's eq. (9) H(z) at Ts = 20 ms.
    """
    g = BondGraph("ced_linear", "CED coupled electric drives: motor lag, belt compliance, "
                                "spring-held pulley (linear part; Wigren & Schoukens 2017).")
    u = g.input("u", "V", 0.0, "sum of the two motor voltages")
    Ra = g.param("R_a", CED_DEFAULTS["R_a"], "ohm", (0.05, 10.0), "armature resistance")
    La = g.param("L_a", CED_DEFAULTS["L_a"], "H", (0.01, 1.0), "armature inductance")
    km = g.param("k_m", CED_DEFAULTS["k_m"], "N*m/A", (0.005, 0.5), "motor torque constant")
    bm = g.param("b_m", CED_DEFAULTS["b_m"], "N*m*s/rad", (0.005, 1.0), "motor-side damping")
    kb = g.param("k_b", CED_DEFAULTS["k_b"], "N*m/rad", (0.05, 5.0),
                 "belt and tensioner-spring stiffness")
    Jp = g.param("J_p", CED_DEFAULTS["J_p"], "kg*m^2", (1e-4, 1e-2), "pulley inertia")
    bp = g.param("b_p", CED_DEFAULTS["b_p"], "N*m*s/rad", (0.0, 1e-2), "pulley damping")
    ky = g.param("k_y", CED_DEFAULTS["k_y"], "", (0.1, 10.0), "counter scale (speed units per rad/s)")
    ji = g.one("i", domain="electrical")
    g.connect(g.Se("drive", u), ji)
    g.connect(ji, g.R("R_a", Ra))
    g.connect(ji, g.I("L_a", La))
    gy = g.GY("motor", km)
    g.connect(ji, gy.p1)
    jm = g.one("w_m", domain="rotation")
    g.connect(gy.p2, jm)
    g.connect(jm, g.R("b_m", bm))
    belt = g.zero("belt", domain="rotation")
    g.connect(jm, belt)
    g.connect(belt, g.C("spring", stiffness=kb))
    jp = g.one("w_p", domain="rotation")
    g.connect(belt, jp)
    g.connect(jp, g.I("J_p", Jp))
    g.connect(jp, g.R("b_p", bp))
    g.sensor("speed", ky * jp.f, unit="", noise_std=0.02,
             description="pulley speed from the pulse counter (signed here)")
    return g


#: defaults of :func:`ced_linear` (R_a, b_m, k_b, k_y fitted to eq. (9) of the report)
CED_DEFAULTS = {"R_a": 0.690777, "L_a": 0.1, "k_m": 0.05, "b_m": 0.0887117, "k_b": 0.450329,
                "J_p": 1e-3, "b_p": 1e-5, "k_y": 2.337023}


# ------------------------------------------------------------------ EMPS helpers
def emps_arrays(experiment=None, decimate: int = 5):
    """EMPS record as filter arrays, decimated.

    Parameters
    ----------
    experiment : Experiment, optional
        From :func:`bondgraph.data.datasets.emps` (default: loaded from the local
        data folder, no download).
    decimate : int
        Keep every ``decimate``-th position sample; the input over each
        interval is the mean of ``vir`` over its ``decimate`` 1-kHz samples,
        which is what a zero-order hold over the interval should carry (the
        force impulse is preserved).

    Returns
    -------
    (t (N,), u (N, 1) [V], y (N, 1) [m])
    """

    if experiment is None:
        from bondgraph.data.datasets import emps as _load

        experiment = _load("estimation", download=False)
    t, q, vir = experiment.t, experiment["qm"], experiment["vir"]
    n = (t.size // decimate) * decimate
    return (t[:n:decimate].copy(), vir[:n].reshape(-1, decimate).mean(axis=1)[:, None],
            q[:n:decimate][:, None].copy())


def emps_filtered_signals(experiment=None, cutoff: float = 100.0, edge: int = 50, step: int = 10):
    """q, q̇, q̈ and τ = gtau·vir as in the benchmark's inverse-model protocol,
    at the full sample rate.

    4th-order Butterworth low-pass at ``cutoff`` Hz applied forward and
    backward (filtfilt) to qm, central differences for q̇ and q̈, ``edge``
    samples dropped at both ends (README of ``../shared/data/emps``). The
    protocol's decimation by ``step`` is *parallel*: the force and every
    column of the regressor (sign(q̇) included) are low-passed and then
    downsampled alike (:func:`emps_decimate`; Gautier 1997, Janot et al.
    2019), so a model's force τ̂ is computed at the full rate and decimated
    with τ. Slicing without the anti-alias filter left the drive's
    quantisation noise in τ: the published symmetric IDIM-LS then read
    4.20 % (published 4.08 %) and M 95.31 kg (95.11); with it 4.04 % and
    M 95.11 kg.

    Returns
    -------
    dict with arrays ``q, qd, qdd, tau`` (M,) in SI units and ``step`` (int).
    """
    import numpy as np
    from scipy.signal import butter, filtfilt

    if experiment is None:
        from bondgraph.data.datasets import emps as _load

        experiment = _load("estimation", download=False)
    t, q, vir = experiment.t, experiment["qm"], experiment["vir"]
    dt = float(np.median(np.diff(t)))
    b, a = butter(4, cutoff / (0.5 / dt))
    qf = filtfilt(b, a, q)
    qd = np.gradient(qf, dt)
    qdd = np.gradient(qd, dt)
    sl = slice(edge, t.size - edge)
    return dict(q=qf[sl], qd=qd[sl], qdd=qdd[sl], tau=EMPS_GTAU * vir[sl], step=int(step))


def emps_decimate(x, step: int):
    """The protocol's parallel decimation of a full-rate signal (N,) or
    columns (N, k): scipy's order-8 Chebyshev type I anti-alias filter,
    applied forward and backward, then every ``step``-th sample."""
    from scipy.signal import decimate

    return decimate(x, int(step), ftype="iir", axis=0, zero_phase=True) if step > 1 else x


def emps_force_relerr(M: float, Fv: float, Fc: float, offset: float, signals: dict) -> float:
    """Force relative error of the inverse model, ||τ − τ̂|| / ||τ|| [%], with
    τ̂ = M q̈ + Fv q̇ + Fc sign(q̇) + offset on :func:`emps_filtered_signals`,
    τ and τ̂ decimated in parallel (:func:`emps_decimate`)."""
    import numpy as np

    s = signals
    tau_hat = M * s["qdd"] + Fv * s["qd"] + Fc * np.sign(s["qd"]) + offset
    tau, tau_hat = emps_decimate(s["tau"], s["step"]), emps_decimate(tau_hat, s["step"])
    return float(100.0 * np.linalg.norm(tau - tau_hat) / np.linalg.norm(tau))


def emps_idim_ls(signals: dict) -> dict[str, float]:
    """Inverse-dynamic-model least squares (IDIM-LS): τ = [q̈, q̇, sign(q̇), 1]·θ,
    the force and the columns decimated in parallel (:func:`emps_decimate`)."""
    import numpy as np

    s = signals
    A = np.column_stack([s["qdd"], s["qd"], np.sign(s["qd"]), np.ones_like(s["qd"])])
    th, *_ = np.linalg.lstsq(emps_decimate(A, s["step"]), emps_decimate(s["tau"], s["step"]),
                             rcond=None)
    return dict(zip(("M", "Fv", "Fc", "offset"), map(float, th)))


#: defaults of :func:`silverbox_linear`: the continuous equivalent of a
#: least-squares ARX(2, 2) fit to the Silverbox training block (ω0 = 436 rad/s,
#: ζ = 0.048, DC gain 0.90)
SILVERBOX_DEFAULTS = {"m": 5.8e-6, "d": 2.45e-4, "k": 1.11}


def silverbox_linear() -> BondGraph:
    """Silverbox (Wigren & Schoukens 2013), declared as a *linear*
    mass-spring-damper driven by the input voltage V1 (ECC paper eq. 13 with
    k(y) = a): the "force" is V1 [V], the "displacement" is the output V2
    [V], so m is in s², d in s and k is dimensionless (1/k the DC gain).

    Hand-derived (p = m ẏ, y the spring's displacement)::

        dp/dt = V1 − k y − d p/m + w(t)
        dy/dt = p/m,            output V2 = y

    ``q_F`` is the intensity of the process noise w on the momentum (the
    unmodelled forces; the cubic stiffness the loop must find), ``sigma_y``
    the output noise (its default 0.1 mV: the published black-box models
    reach 0.26 mV simulation error, so the noise is below that; the bundled
    case estimates it).
    """
    g = BondGraph("silverbox_linear", "Silverbox electronic Duffing oscillator, declared linear: "
                                      "mass-spring-damper driven by the input voltage.")
    V1 = g.input("V1", "V", 0.0, "input voltage (the force)")
    m = g.param("m", SILVERBOX_DEFAULTS["m"], "s^2", (1e-7, 1e-4), "mass (V1 per d²y/dt²)")
    d = g.param("d", SILVERBOX_DEFAULTS["d"], "s", (1e-6, 1e-2), "damping (V1 per dy/dt)")
    k = g.param("k", SILVERBOX_DEFAULTS["k"], "", (0.1, 10.0), "linear stiffness (V1 per y)")
    qF = g.param("q_F", 1e-3, "V*s^0.5", (1e-7, 1.0),
                 "process-noise intensity on the momentum: unmodelled forces")
    sy = g.param("sigma_y", 1e-4, "V", (1e-6, 1e-2), "output noise (fixed)")
    v = g.one("v")
    g.connect(g.Se("drive", V1), v)
    mass = g.I("mass", m)
    g.connect(v, mass)
    spring = g.C("spring", stiffness=k)
    g.connect(v, spring)
    g.connect(v, g.R("damper", d))
    g.set_process_noise(mass.p, qF)
    g.sensor("V2", spring.q, unit="V", noise_std=sy, description="output voltage (displacement)")
    return g


# ------------------------------------------------------------------ Camry
#: 1 lbf in N and 1 mph in m/s (the EPA table's units)
LBF, MPH = 4.44822, 0.44704
#: road load and test weight of the 2018 Camry XLE 2.5 L 8AT, from the EPA
#: MY2022 Test Car List (the same XV70 generation; ``../shared/data/
#: epa_test_car_list_2022``): target coefficients A 26.5-32.5 lbf, B
#: 0.199-0.225 lbf/mph, C 0.0165-0.0171 lbf/mph², equivalent test weight
#: 3625-3750 lb; the middles of those ranges in SI. Proxies: the dyno
#: settings of this exact car are not published.
CAMRY_ROAD_LOAD = {"m": 3687.5 * 0.45359237, "A": 29.5 * LBF, "B": 0.212 * LBF / MPH,
                   "C": 0.0168 * LBF / MPH**2}
#: lower heating value of the fuel per volume [J/cm³]: E10 gasoline, about
#: 41.9 MJ/kg at 0.745 kg/L (typical values; fixed, so η absorbs its error)
CAMRY_FUEL_H = 31.2e3


def camry_fuel(name: str = "camry_fuel") -> BondGraph:
    """Warm (isothermal) powertrain fuel-flow model of the 2018 Camry on the
    chassis dyno (1 state: the fuel flow).

    The dyno imposes the measured speed v on the vehicle (a flow source on
    the vehicle's 1-junction); the vehicle's inertia takes derivative
    causality (the input ``der(v)``), so the graph computes the wheel force
    F_w = m dv/dt + A tanh(v/v_ε) + B v + C v² and the wheel power
    P_w = F_w v. The engine is a Willans line (Guzzella & Sciarretta 2013,
    §3.2): the fuel power needed is P_w/η plus the idle (friction and
    pumping) fuel, fuelled only for positive wheel power (a smooth positive
    part, width P_ε: the engine gets no fuel back on braking); the injected
    flow follows that demand with a first-order lag τ_f. The fuel flows
    through the injector (a flow source) into the combustion, an R of
    constant effort H (the fuel's heating value per volume), so the fuel
    power H·Q is dissipated::

        MSf(v) -> 1(v) <- I: m (derivative causality), R: A tanh(v/v_ε) + B v + C v²
        MSf(Q) -> 1(fuel) <- R: H tanh(Q/Q_ε)          (combustion)

        Q* = Q_idle + P_ε softplus(F_w v / P_ε) / (η H)
        dQ/dt = (Q* − Q)/τ_f + w(t),       fuel = Q (+ noise σ_Q)

    Declared warm: no thermal state (the engine at its running temperature).
    A, B, C and m are the EPA table's proxies (:data:`CAMRY_ROAD_LOAD`,
    fixed in the bundled case); η, Q_idle, τ_f are the powertrain's.

    References
    ----------
    Guzzella, L., Sciarretta, A. (2013). *Vehicle Propulsion Systems*, 3rd
    ed., Springer: §2.1 (road load), §3.2 (Willans-line engine model).
    """
    g = BondGraph(name, "2018 Camry on a chassis dyno, warm: imposed speed, road load, "
                        "Willans-line engine with idle fuel, lagged fuel flow.")
    v = g.input("v", "m/s", 0.0, "dyno roll speed (vehicle speed), measured")
    rl = CAMRY_ROAD_LOAD
    m = g.param("m", rl["m"], "kg", (1500.0, 1900.0), "equivalent test weight (dyno inertia)",
                source="EPA Test Car List MY2022, Camry 2.5 L 8AT")
    A = g.param("A", rl["A"], "N", (50.0, 250.0), "road load, constant term",
                source="EPA Test Car List MY2022, target coefficient A")
    B = g.param("B", rl["B"], "N*s/m", (0.0, 10.0), "road load, linear term",
                source="EPA Test Car List MY2022, target coefficient B")
    C = g.param("C", rl["C"], "N*s^2/m^2", (0.2, 0.6), "road load, quadratic term",
                source="EPA Test Car List MY2022, target coefficient C")
    veps = g.param("v_eps", 0.1, "m/s", (0.01, 1.0), "tanh width of the rolling law (fixed)")
    eta = g.param("eta", 0.33, "", (0.15, 0.5), "fuel-to-wheel efficiency (Willans slope)")
    qi = g.param("Q_idle", 0.2, "cm^3/s", (0.02, 1.0), "idle fuel flow (warm engine)")
    tau = g.param("tau_f", 1.0, "s", (0.5, 10.0), "fuel-flow lag time constant (at least half "
                                                   "a sample of the 1 Hz records)")
    H = g.param("H", CAMRY_FUEL_H, "J/cm^3", (25e3, 40e3),
                "heating value of the fuel per volume (fixed)")
    peps = g.param("P_eps", 500.0, "W", (10.0, 5000.0),
                   "width of the smooth positive part of the wheel power (fixed)")
    qeps = g.param("Q_eps", 0.01, "cm^3/s", (1e-4, 0.1), "tanh width of the combustion law (fixed)")
    sq = g.param("sigma_Q", 0.1, "cm^3/s", (1e-3, 1.0), "fuel-flow sensor noise")
    qq = g.param("q_Q", 0.1, "cm^3/s^1.5", (1e-4, 10.0),
                 "process-noise intensity on the fuel flow (unmodelled fuelling)")
    jv = g.one("vehicle", domain="translation")
    dyno = g.MSf("dyno", v)
    g.connect(dyno, jv)
    g.connect(jv, g.I("mass", m))
    g.connect(jv, g.R("road", effort=lambda f: A * sp.tanh(f / veps) + B * f + C * f * sp.Abs(f)))
    from bondgraph.core.smooth import smooth_pos

    demand = qi + smooth_pos(dyno.e * v, peps) / (eta * H)
    Q = g.state("Q", rhs=lambda s: (demand - s) / tau, unit="cm^3/s", initial=0.2,
                process_noise=qq, description="injected fuel flow")
    jf = g.one("fuel")
    g.connect(g.MSf("injector", Q), jf)
    g.connect(jf, g.R("combustion", effort=lambda f: H * sp.tanh(f / qeps)))
    g.sensor("fuel", jf.f, unit="cm^3/s", noise_std=sq, description="measured fuel flow")
    return g


#: output-error fit of :func:`camry_fuel`'s η and Q_idle (τ_f on the lower end
#: of its box: the 1 Hz records do not resolve the lag) on the hot cycles
#: 61811013 (2 x HWFET) and 61811014 (2 x US06), free runs from the measured
#: first fuel flow (:func:`bondgraph.catalog.cases.camry_hot_fit`, 6 s): RMS
#: 0.303 and 0.755 cm³/s. The hot UDDS 61811012 is held out (0.414 cm³/s).
CAMRY_HOT_FIT = {"eta": 0.333257, "Q_idle": 0.0633904, "tau_f": 0.5}


def camry_warm() -> BondGraph:
    """:func:`camry_fuel` with the powertrain parameters of the hot-cycle fit
    (:data:`CAMRY_HOT_FIT`) as defaults: the declared model of the
    ``camry_cold`` loop case."""
    g = camry_fuel("camry_warm")
    for k, v in CAMRY_HOT_FIT.items():
        g.params[k].default = float(v)
    return g
