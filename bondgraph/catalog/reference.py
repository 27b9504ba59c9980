"""Canonical reference graphs, reused by tests, docs and benchmarks.

Each function returns a fresh :class:`~bondgraph.core.graph.BondGraph`. Their
hand-derived equations (for the tests) are given in the docstrings.
"""

from __future__ import annotations

from bondgraph.core.graph import BondGraph
from bondgraph.data.experiments import ExperimentSpec, ramp, step

#: registered models (``bondgraph.models`` entry point; ``bondgraph generate``)
MODELS: dict[str, str] = {
    "mass_spring_damper": "bondgraph.catalog.reference:mass_spring_damper",
    "dc_motor_compliant": "bondgraph.catalog.reference:dc_motor_compliant",
    "dc_motor_gear": "bondgraph.catalog.reference:dc_motor_gear",
    "rr_loop": "bondgraph.catalog.reference:rr_loop",
    "toy_cvt": "bondgraph.catalog.reference:toy_cvt",
    "mass_chain_5": "bondgraph.catalog.reference:mass_chain_5",
    "rlc_circuit": "bondgraph.catalog.reference:rlc_circuit",
    "hydraulic_tanks": "bondgraph.catalog.reference:hydraulic_tanks",
    "thermal_two_node": "bondgraph.catalog.reference:thermal_two_node",
}


def mass_spring_damper() -> BondGraph:
    """Mass-spring-damper driven by a force F.

    Hand-derived (p = m v, q = spring extension)::

        dp/dt = F - k q - c p/m
        dq/dt = p/m
    """
    g = BondGraph("mass_spring_damper", "Mass-spring-damper driven by a force F.")
    m = g.param("m", 2.0, "kg", (0.5, 8.0), "mass")
    k = g.param("k", 50.0, "N/m", (5.0, 500.0), "spring stiffness")
    c = g.param("c", 1.5, "N*s/m", (0.1, 20.0), "damping coefficient")
    F = g.input("F", "N", 0.0, "applied force")
    v = g.one("v", domain="translation")
    g.connect(g.Se("force", F), v)
    mass = g.I("mass", m)
    g.connect(v, mass)
    spring = g.C("spring", stiffness=k)
    g.connect(v, spring)
    g.connect(v, g.R("damper", c))
    g.sensor("x", spring.q, unit="m", noise_std=0.002, description="position")
    g.sensor("v", v.f, unit="m/s", noise_std=0.01, description="velocity")
    return g


def dc_motor_compliant() -> BondGraph:
    """DC motor driving a load inertia through a compliant shaft (4 states).

    Hand-derived (λ = L i, p_m = J_m ω_m, φ = shaft twist, p_L = J_L ω_L)::

        dλ/dt   = V - R_a λ/L - k_m p_m/J_m
        dp_m/dt = k_m λ/L - b_m p_m/J_m - k_s φ
        dφ/dt   = p_m/J_m - p_L/J_L
        dp_L/dt = k_s φ - b_L p_L/J_L - T_L
    """
    g = BondGraph("dc_motor_compliant", "DC motor, compliant shaft, load inertia.")
    V = g.input("V", "V", 0.0, "armature voltage")
    TL = g.input("T_L", "N*m", 0.0, "load torque")
    Ra = g.param("R_a", 1.2, "ohm", (0.2, 5.0), "armature resistance")
    La = g.param("L_a", 0.005, "H", (0.001, 0.02), "armature inductance")
    km = g.param("k_m", 0.08, "N*m/A", (0.02, 0.3), "torque constant")
    Jm = g.param("J_m", 2e-4, "kg*m^2", (5e-5, 1e-3), "rotor inertia")
    bm = g.param("b_m", 1e-4, "N*m*s/rad", (1e-5, 1e-3), "rotor viscous friction")
    ks = g.param("k_s", 50.0, "N*m/rad", (5.0, 500.0), "shaft stiffness")
    JL = g.param("J_L", 5e-3, "kg*m^2", (1e-3, 2e-2), "load inertia")
    bL = g.param("b_L", 2e-3, "N*m*s/rad", (1e-4, 1e-2), "load viscous friction")
    ji = g.one("i", domain="electrical")
    g.connect(g.Se("V", V), ji)
    g.connect(ji, g.R("R_a", Ra))
    g.connect(ji, g.I("L_a", La))
    gy = g.GY("motor", km)
    g.connect(ji, gy.p1)
    jm = g.one("w_m", domain="rotation")
    g.connect(gy.p2, jm)
    g.connect(jm, g.I("J_m", Jm))
    g.connect(jm, g.R("b_m", bm))
    js = g.zero("shaft", domain="rotation")
    g.connect(jm, js)
    g.connect(js, g.C("k_s", stiffness=ks))
    jl = g.one("w_L", domain="rotation")
    g.connect(js, jl)
    g.connect(jl, g.I("J_L", JL))
    g.connect(jl, g.R("b_L", bL))
    load = g.Se("load", -TL)
    g.connect(load, jl)
    g.sensor("w_L", jl.f, unit="rad/s", noise_std=0.5, description="load speed")
    g.sensor("i", ji.f, unit="A", noise_std=0.05, description="armature current")
    return g


def dc_motor_gear() -> BondGraph:
    """DC motor driving a load inertia through a rigid gear n (2 states).

    The rotor inertia J_m is in derivative causality and is eliminated; with
    ω_m = n ω_L (gear modulus 1/n: ω_L = ω_m / n)::

        dλ/dt   = V - R_a λ/L - k_m n p_L/J_L
        dp_L/dt = (n k_m λ/L - b_L p_L/J_L) / (1 + n² J_m/J_L)

    i.e. J_eq = J_L + n² J_m at the load.
    """
    g = BondGraph("dc_motor_gear", "DC motor with a rigid gear to the load.")
    V = g.input("V", "V", 0.0, "armature voltage")
    Ra = g.param("R_a", 1.2, "ohm", (0.2, 5.0), "armature resistance")
    La = g.param("L_a", 0.005, "H", (0.001, 0.02), "armature inductance")
    km = g.param("k_m", 0.08, "N*m/A", (0.02, 0.3), "torque constant")
    Jm = g.param("J_m", 2e-4, "kg*m^2", (5e-5, 1e-3), "rotor inertia")
    n = g.param("n", 10.0, "", (2.0, 50.0), "gear reduction")
    JL = g.param("J_L", 5e-2, "kg*m^2", (1e-2, 2e-1), "load inertia")
    bL = g.param("b_L", 2e-3, "N*m*s/rad", (1e-4, 1e-2), "load viscous friction")
    ji = g.one("i", domain="electrical")
    g.connect(g.Se("V", V), ji)
    g.connect(ji, g.R("R_a", Ra))
    g.connect(ji, g.I("L_a", La))
    gy = g.GY("motor", km)
    g.connect(ji, gy.p1)
    jm = g.one("w_m", domain="rotation")
    g.connect(gy.p2, jm)
    g.connect(jm, g.I("J_m", Jm, priority=1))
    tf = g.TF("gear", 1 / n)
    g.connect(jm, tf.p1)
    jl = g.one("w_L", domain="rotation")
    g.connect(tf.p2, jl)
    g.connect(jl, g.I("J_L", JL))
    g.connect(jl, g.R("b_L", bL))
    g.sensor("w_L", jl.f, unit="rad/s", noise_std=0.2, description="load speed")
    return g


def rr_loop() -> BondGraph:
    """Voltage source, series R1, node with R2 to ground and an inductor
    branch: the two R elements form an algebraic loop (1 state, flux λ).

    Hand-derived: node voltage e = R2 (V - R1 λ/L) / (R1 + R2), dλ/dt = e.
    """
    g = BondGraph("rr_loop", "R-R algebraic loop: V, series R1, node with R2 and L.")
    V = g.input("V", "V", 0.0, "source voltage")
    R1 = g.param("R1", 10.0, "ohm", (1.0, 100.0), "series resistance")
    R2 = g.param("R2", 40.0, "ohm", (4.0, 400.0), "shunt resistance")
    L = g.param("L", 0.1, "H", (0.01, 1.0), "inductance")
    j1 = g.one("i1", domain="electrical")
    g.connect(g.Se("V", V), j1)
    g.connect(j1, g.R("R1", R1))
    node = g.zero("node", domain="electrical")
    g.connect(j1, node)
    g.connect(node, g.R("R2", R2))
    jl = g.one("iL", domain="electrical")
    g.connect(node, jl)
    g.connect(jl, g.I("L", L))
    g.sensor("iL", jl.f, unit="A", noise_std=0.001, description="inductor current")
    g.sensor("e_node", node.e, unit="V", noise_std=0.01, description="node voltage")
    return g


def toy_cvt() -> BondGraph:
    """Engine inertia -> MTF with time-varying ratio r(t) -> vehicle inertia.

    Rigid coupling v = r ω_e: the engine inertia takes derivative causality
    (the vehicle keeps its state, priority -1). With the input r and its
    derivative der(r)::

        (m + J_e/r²) dv/dt = T/r + J_e v ṙ / r³ - c v,      p = m v

    The J_e v ṙ / r³ term is the power the ratio change moves between the two
    inertias.
    """
    g = BondGraph("toy_cvt", "Toy CVT: engine inertia, MTF r(t), vehicle inertia.")
    T = g.input("T", "N*m", 0.0, "engine torque")
    r = g.input("r", "m/rad", 0.05, "ratio v/ω_e (wheel radius over overall ratio)")
    Je = g.param("J_e", 0.1, "kg*m^2", (0.02, 0.5), "engine inertia")
    m = g.param("m", 1200.0, "kg", (600.0, 2400.0), "vehicle mass")
    c = g.param("c", 20.0, "N*s/m", (1.0, 100.0), "linear drag")
    je = g.one("w_e", domain="rotation")
    g.connect(g.Se("engine", T), je)
    g.connect(je, g.I("J_e", Je))
    cvt = g.MTF("cvt", r)
    g.connect(je, cvt.p1)
    jv = g.one("v", domain="translation")
    g.connect(cvt.p2, jv)
    g.connect(jv, g.I("m", m, priority=-1))
    g.connect(jv, g.R("drag", c))
    g.sensor("v", jv.f, unit="m/s", noise_std=0.05, description="vehicle speed")
    g.sensor("w_e", je.f, unit="rad/s", noise_std=1.0, description="engine speed")
    return g


def mass_chain(n: int = 5) -> BondGraph:
    """Chain of ``n`` masses joined by ``n - 1`` spring-damper pairs, force F
    on the first mass: 2n - 1 states (39 for n = 20, 79 for n = 40).

    Hand-derived, with v_i = p_i/m_i, spring j between masses j and j+1::

        dp_i/dt = F δ_i1 + Σ_j ±(k_j q_j + c_j (v_j - v_j+1))
        dq_j/dt = v_j - v_{j+1}
    """
    g = BondGraph(f"mass_chain_{n}", f"Chain of {n} masses with springs and dampers.")
    F = g.input("F", "N", 0.0, "force on the first mass")
    js = []
    for i in range(1, n + 1):
        mi = g.param(f"m{i}", 1.0 + 0.1 * i, "kg", None, f"mass {i}")
        j = g.one(f"v{i}", domain="translation")
        g.connect(j, g.I(f"M{i}", mi))
        js.append(j)
    g.connect(g.Se("force", F), js[0])
    for i in range(1, n):
        ki = g.param(f"k{i}", 100.0 + 5.0 * i, "N/m", None, f"stiffness {i}")
        ci = g.param(f"c{i}", 0.5 + 0.05 * i, "N*s/m", None, f"damping {i}")
        # 0-junction forms the relative velocity v_i - v_i+1; the spring and the
        # damper share it on a 1-junction (parallel, Kelvin-Voigt)
        z = g.zero(f"s{i}", domain="translation")
        g.connect(js[i - 1], z)
        g.connect(z, js[i])
        rel = g.one(f"dv{i}", domain="translation")
        g.connect(z, rel)
        g.connect(rel, g.C(f"K{i}", stiffness=ki))
        g.connect(rel, g.R(f"D{i}", ci))
    g.sensor("v_last", js[-1].f, unit="m/s", noise_std=0.01, description=f"speed of mass {n}")
    return g


def mass_chain_5() -> BondGraph:
    """:func:`mass_chain` with 5 masses (9 states), registered for generation."""
    return mass_chain(5)


def rlc_circuit() -> BondGraph:
    """Series RLC circuit driven by a voltage source (2 states).

    Hand-derived (λ = L i, q = charge of the capacitor)::

        dλ/dt = V - R λ/L - q/C
        dq/dt = λ/L,        i = λ/L,  v_C = q/C

    Defaults: ω0 = 1/√(LC) = 100 rad/s, ζ = (R/2)√(C/L) = 0.5.
    """
    g = BondGraph("rlc_circuit", "Series RLC circuit driven by a voltage source.")
    V = g.input("V", "V", 0.0, "source voltage")
    R = g.param("R", 10.0, "ohm", (1.0, 100.0), "resistance")
    L = g.param("L", 0.1, "H", (0.01, 1.0), "inductance")
    Cp = g.param("C", 1e-3, "F", (1e-4, 1e-2), "capacitance")
    i = g.one("i", domain="electrical")
    g.connect(g.Se("source", V), i)
    g.connect(i, g.R("resistor", R))
    g.connect(i, g.I("inductor", L))
    cap = g.C("capacitor", Cp)
    g.connect(i, cap)
    g.sensor("i", i.f, unit="A", noise_std=0.005, description="loop current")
    g.sensor("v_C", cap.q / Cp, unit="V", noise_std=0.02, description="capacitor voltage")
    return g


def hydraulic_tanks() -> BondGraph:
    """Pump, two tanks, an orifice between them and an outlet (2 states).

    Hand-derived (V_i = stored volumes, p_i = V_i/Ch_i the bottom pressures,
    Ch_i = A_i/(ρ g)); the pump delivers the flow Q::

        dV1/dt = Q - (p1 - p2)/Rh12
        dV2/dt = (p1 - p2)/Rh12 - p2/Rh2

    A pseudo-steady laminar (linear) orifice and outlet; sensors read the two
    pressures.
    """
    g = BondGraph("hydraulic_tanks", "Pump, tank, orifice, tank, outlet (hydraulic).")
    Q = g.input("Q", "m^3/s", 0.0, "pump flow")
    C1 = g.param("Ch1", 1e-4, "m^3/Pa", (1e-5, 1e-3), "tank 1 capacitance A1/(rho g)")
    C2 = g.param("Ch2", 2e-4, "m^3/Pa", (2e-5, 2e-3), "tank 2 capacitance A2/(rho g)")
    R12 = g.param("Rh12", 1e5, "Pa*s/m^3", (1e4, 1e6), "orifice resistance between the tanks")
    R2 = g.param("Rh2", 1e5, "Pa*s/m^3", (1e4, 1e6), "outlet resistance")
    t1 = g.zero("tank1", domain="hydraulic")
    g.connect(g.Sf("pump", Q), t1)
    c1 = g.C("tank1_C", C1)
    g.connect(t1, c1)
    orifice = g.one("orifice", domain="hydraulic")
    g.connect(t1, orifice)
    g.connect(orifice, g.R("orifice_R", R12))
    t2 = g.zero("tank2", domain="hydraulic")
    g.connect(orifice, t2)
    c2 = g.C("tank2_C", C2)
    g.connect(t2, c2)
    g.connect(t2, g.R("outlet", R2))
    g.sensor("p1", t1.e, unit="Pa", noise_std=5.0, description="tank 1 bottom pressure")
    g.sensor("p2", t2.e, unit="Pa", noise_std=5.0, description="tank 2 bottom pressure")
    return g


def thermal_two_node() -> BondGraph:
    """Two thermal masses, a heater and the ambient (2 states), as a true
    thermal bond graph linearised about T0: effort = temperature rise above
    T0 [K], flow = entropy flow [W/K]; a heat capacity C_th is the C of
    compliance C_th/T0, a thermal resistance R_th the R of resistance
    T0·R_th, the heater power P the flow source P/T0.

    Hand-derived (S_i = stored entropy, T_i = T0 S_i/C_i the temperature
    rises; heat flows = T0 × entropy flows)::

        Cth1 dT1/dt = P - (T1 - T2)/Rth12
        Cth2 dT2/dt = (T1 - T2)/Rth12 - (T2 - T_a)/Rth2a
    """
    g = BondGraph("thermal_two_node", "Heater, two thermal masses, ambient (thermal).")
    P = g.input("P", "W", 0.0, "heater power")
    Ta = g.input("T_a", "K", 0.0, "ambient temperature rise above T0")
    T0 = g.param("T0", 300.0, "K", (250.0, 350.0), "reference temperature (known)")
    C1 = g.param("Cth1", 500.0, "J/K", (50.0, 5000.0), "heat capacity of node 1")
    C2 = g.param("Cth2", 2000.0, "J/K", (200.0, 20000.0), "heat capacity of node 2")
    R12 = g.param("Rth12", 0.05, "K/W", (0.005, 0.5), "thermal resistance node 1 - node 2")
    R2a = g.param("Rth2a", 0.1, "K/W", (0.01, 1.0), "thermal resistance node 2 - ambient")
    n1 = g.zero("node1", domain="thermal")
    g.connect(g.Sf("heater", P / T0), n1)
    g.connect(n1, g.C("mass1", C1 / T0))
    b12 = g.one("path12", domain="thermal")
    g.connect(n1, b12)
    g.connect(b12, g.R("R12", T0 * R12))
    n2 = g.zero("node2", domain="thermal")
    g.connect(b12, n2)
    g.connect(n2, g.C("mass2", C2 / T0))
    b2a = g.one("path2a", domain="thermal")
    g.connect(n2, b2a)
    g.connect(b2a, g.R("R2a", T0 * R2a))
    amb = g.zero("ambient_node", domain="thermal")
    g.connect(b2a, amb)
    g.connect(g.Se("ambient", Ta), amb)
    g.sensor("T1", n1.e, unit="K", noise_std=0.05, description="temperature rise of node 1")
    g.sensor("T2", n2.e, unit="K", noise_std=0.05, description="temperature rise of node 2")
    return g


# ------------------------------------------------- reference experiments
def msd_force_step() -> ExperimentSpec:
    """Mass-spring-damper: a 10 N force step at t = 0.5 s, 10 s at 100 Hz."""
    return ExperimentSpec(
        name="msd_force_step", model="mass_spring_damper", duration=10.0, dt=0.01,
        inputs={"F": step(0.5, 10.0)},
        params={"m": 2.4, "k": 60.0, "c": 1.2}, seed=1,
        description="Mass-spring-damper, 10 N force step at t = 0.5 s; true m, k, c "
                    "differ from the defaults.")


def dc_motor_voltage_step() -> ExperimentSpec:
    """DC motor with compliant shaft: 12 V step at 0.05 s, a 0.1 N·m load
    torque step at 0.6 s, 1 s at 1 kHz."""
    return ExperimentSpec(
        name="dc_motor_voltage_step", model="dc_motor_compliant", duration=1.0, dt=0.001,
        inputs={"V": step(0.05, 12.0), "T_L": step(0.6, 0.1)},
        params={"R_a": 1.4, "k_s": 40.0, "J_L": 6e-3}, seed=2,
        description="DC motor (compliant shaft): 12 V armature step at 0.05 s, 0.1 N*m load "
                    "torque step at 0.6 s.")


def toy_cvt_torque_ratio_ramp() -> ExperimentSpec:
    """Toy CVT: 50 N·m engine torque from 0.5 s, ratio ramp 0.05 -> 0.1 m/rad
    over 5-15 s, 20 s at 40 Hz. The ratio change moves power between the
    engine and vehicle inertias (the J_e v ṙ / r³ term)."""
    return ExperimentSpec(
        name="toy_cvt_torque_ratio_ramp", model="toy_cvt", duration=20.0, dt=0.025,
        inputs={"T": step(0.5, 50.0), "r": ramp(5.0, 15.0, 0.05, 0.1)},
        params={"J_e": 0.15, "m": 1350.0, "c": 25.0}, seed=3,
        description="Toy CVT: 50 N*m torque step at 0.5 s, ratio ramp 0.05 -> 0.1 m/rad over "
                    "5-15 s.")


#: registered reference experiments (``bondgraph.experiments`` entry point)
EXPERIMENTS: dict[str, str] = {
    "msd_force_step": "bondgraph.catalog.reference:msd_force_step",
    "dc_motor_voltage_step": "bondgraph.catalog.reference:dc_motor_voltage_step",
    "toy_cvt_torque_ratio_ramp": "bondgraph.catalog.reference:toy_cvt_torque_ratio_ramp",
}
