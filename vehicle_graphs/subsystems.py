"""The vehicle's subsystems as reusable bond-graph fragments.

Each function returns a :class:`bondgraph.BondGraph` used as a fragment
(``parent.include(fragment, prefix)``) with exposed ports. Parameters are not
declared by the fragments: they receive the parent's parameter symbols (a
mapping ``P[name]``), and signals read from other subsystems (engine speed,
body speed, normal load, brake command) as sympy expressions, so that one
parameter (e.g. ``r_dyn``) is shared by both axles.

Power bonds (effort x flow): torque x angular speed [N m, rad/s] in the drive
line and wheels, force x speed [N, m/s] at the contact patches, body and CVT
sheave, pitch moment x pitch rate [N m, rad/s] in the suspension.

The equations each element contributes are given in the docstrings and, with
the stiffness numbers, in ``docs/vehicle.md``. Sources: Karnopp, Margolis &
Rosenberg (2012) for the bond-graph forms; Pacejka (2012) for the tire;
Guzzella & Onder (2010) for the engine; Cammalleri (2005) for the
speed- and torque-controlled rubber-belt variator; vehicle_physics.md §3.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import sympy as sp

from bondgraph import BondGraph

from .params import DR_DX, RHO


# ------------------------------------------------------------------ numerics
@dataclass(frozen=True)
class Numerics:
    """Regularisation widths of the smooth laws (numerical choices, [N]).

    They set the stiffness of the model: the values below keep the largest
    Jacobian eigenvalue of the full model below ~2000 1/s (RK4 needs at most
    ~16 sub-steps per 25 ms sample, at standstill); see docs/vehicle.md.

    Attributes
    ----------
    v_eps : float
        Floor of the slip denominator, m/s: kappa = v_sx / smax(|v|, v_eps).
        Below v_eps the tire acts as a viscous damper C_kappa/v_eps.
    v_delta : float
        Smoothing width of |v| and of the smooth max, m/s.
    w_eps_wheel : float
        tanh width of brake and rolling-resistance torques, rad/s.
    w_eps_clutch : float
        Base tanh width of the clutch slip law, rad/s.
    w_eps_engine : float
        tanh width of the engine's constant friction, rad/s.
    F_delta : float
        Width of the smooth ramp of the belt clamp force, N.
    k_stop : float
        Stiffness of the CVT ratio end stops, N/m.
    x_delta : float
        Width of the end-stop ramps, m.
    w_delta_idle : float
        Width of the idle-governor ramp, rad/s.
    k_cut : float
        Rev-limiter torque slope above w_max, N m s/rad (engine data [D]).
    s_delta : float
        Width of the smooth clip of the relative sheave travel x_p/x_max
        to [0, 1] in the ratio map (dimensionless).
    """

    v_eps: float = 2.0
    v_delta: float = 0.5
    w_eps_wheel: float = 2.0
    w_eps_clutch: float = 2.0
    w_eps_engine: float = 10.0
    F_delta: float = 5.0
    k_stop: float = 5.0e6
    x_delta: float = 2.0e-4
    w_delta_idle: float = 5.0
    k_cut: float = 2.0
    s_delta: float = 0.01


def const(value: float) -> sp.Expr:
    """A numeric constant as an exact rational when it is a short decimal
    (prints compactly in the generated code)."""
    return sp.nsimplify(value, rational=True) if float(value) == round(float(value), 6) \
        else sp.Float(value)


def ramp(z, delta):
    """Algebraic smooth ramp max(0, z) ~ (z + sqrt(z^2 + delta^2))/2.

    Differentiable everywhere, exact to delta^2/(4|z|) away from 0; costs a
    square root (no exp/log). ``delta`` in the unit of ``z``.
    """
    d = const(delta) if isinstance(delta, (int, float)) else delta
    return (z + sp.sqrt(z**2 + d**2)) / 2


def smax(a, b, delta):
    """Smooth max(a, b) = (a + b + sqrt((a - b)^2 + delta^2))/2."""
    d = const(delta) if isinstance(delta, (int, float)) else delta
    return (a + b + sp.sqrt((a - b)**2 + d**2)) / 2


def smooth_abs(x, delta):
    """|x| ~ sqrt(x^2 + delta^2)."""
    d = const(delta) if isinstance(delta, (int, float)) else delta
    return sp.sqrt(x**2 + d**2)


Params = Mapping[str, sp.Symbol]


# -------------------------------------------------------------------- engine
def engine(P: Params, throttle, num: Numerics = Numerics(), *, manifold_lag: bool = False
           ) -> BondGraph:
    """Engine: 1(w_e) with I: J_e, R: friction/pumping, MSe: combustion torque.

    ::

        J_e dw_e/dt = T_e - T_fr - T_cl
        T_wot(w) = T_pk [1 - ((w - w_pk)/dw_T)^2] - k_cut ramp(w - w_max)
        T_e      = u_th T_wot(w_e) + K_idle ramp(w_idle - w_e)        (no lag)
        tau_m dT_m/dt = u_th T_wot(w_e) - T_m,  T_e = T_m + idle term (manifold_lag)
        T_fr     = T_f0 tanh(w_e / w_eps) + b_e w_e

    The full-throttle map is a parabola about the peak-torque speed (70 % of
    T_pk at idle, 84 % at 6000 rpm) with a smooth rev-limiter fade above
    w_max; part throttle scales it linearly (u_th in [0, 1]). The idle
    governor adds torque below w_idle (keeps the engine alive in coast-down
    records). Literature form: vehicle_physics.md §3.1, Guzzella & Onder
    (2010) ch. 2.

    Parameters
    ----------
    P : mapping
        Parameter symbols ``J_e, T_pk, w_pk, dw_T, w_max, T_f0, b_e, w_idle,
        K_idle`` (+ ``tau_m``).
    throttle : sympy expression
        Throttle command u_th [1].
    num : Numerics
    manifold_lag : bool
        Add the first-order manifold torque lag state ``T_m``.

    Returns
    -------
    BondGraph
        Fragment exposing ``shaft`` (the 1-junction of w_e).
    """
    g = BondGraph("engine", "Engine: torque map, inertia, friction, idle governor.")
    w = g.one("w", domain="rotation")
    g.connect(w, g.I("J", P["J_e"]))
    we = w.f
    eps = const(num.w_eps_engine)
    g.connect(w, g.R("friction", effort=lambda f: P["T_f0"] * sp.tanh(f / eps) + P["b_e"] * f))
    xw = (we - P["w_pk"]) / P["dw_T"]
    T_wot = P["T_pk"] * (1 - xw**2) - const(num.k_cut) * ramp(we - P["w_max"], 10.0)
    T_idle = P["K_idle"] * ramp(P["w_idle"] - we, num.w_delta_idle)
    if manifold_lag:
        Tm = g.state("T_m", lambda z: (throttle * T_wot - z) / P["tau_m"], unit="N*m",
                     description="manifold-lagged combustion torque")
        T = Tm + T_idle
    else:
        T = throttle * T_wot + T_idle
    g.connect(g.MSe("torque", T), w)
    g.expose("shaft", w)
    return g


# --------------------------------------------------------------- clutch, CVT
def clutch_cvt(P: Params, w_e, num: Numerics = Numerics(), *, belt_slip: bool = False
               ) -> BondGraph:
    """Centrifugal clutch, rubber-belt CVT with shift dynamics, secondary.

    Graph::

        (engine 1(w_e)) -> 0(T_cl) -> 1(w_p) -> MTF 1/i_cvt(x_p) -> 1(w_s): I J_s, R b_s
                             |
                         R: clutch (slip w_e - w_p, capacity from w_e and x_p)

        1(dx_p/dt): MSe flyweights k_fw w_e^2, MSe helix -k_h T_s,
                    C springs (preloads, rates, end stops), R b_sh

    Equations (massless sheave, thrust ratio lumped to 1)::

        F_clamp = ramp(k_fw (w_e^2 - w_eng^2) - k_p x_p)            belt clamp at the primary
        T_cap   = mu_cl (r_p0 + x_p / (2 tan beta)) F_clamp
        T_cl    = T_cap tanh((w_e - w_p) / (w_eps + T_cap / c_cl))
        i_cvt   = i_max - (i_max - i_min) clip(x_p / x_max, 0, 1),   w_p = i_cvt w_s,
        T_s     = i_cvt T_cl
        b_sh dx_p/dt = k_fw w_e^2 - k_h T_s - Psi(x_p)
        Psi(x)  = k_fw w_eng^2 + F_s0 + (k_p + k_s) x
                  + k_stop [ramp(x - x_max) - ramp(-x)]              (end stops)

    The reasons for these laws are given with the steps that build them:
    :func:`_cvt_clamp_and_ratio` (engagement, ratio map), :func:`_cvt_clutch_and_belt`
    (the slip law's width), :func:`_cvt_shift_forces` (the variator's force
    balance, neglected powers); vehicle_physics.md §3.3.

    Parameters
    ----------
    P : mapping
        ``w_eng, k_fw, mu_cl, r_p0, c_cl, k_p, F_s0, k_s, k_h, b_sh, x_max,
        i_max, i_min, J_s, b_s`` (+ ``J_b, c_bs`` with belt slip).
    w_e : sympy expression
        Engine speed (the engine junction's flow).
    num : Numerics
    belt_slip : bool
        Truth effect: a creep law T = c_bs (w_b - w_s) between the belt (with
        the secondary sheave inertia J_b) and the secondary shaft.

    Returns
    -------
    BondGraph
        Fragment exposing ``engine`` (the clutch 0-junction; bond the engine
        junction to it) and ``secondary`` (the 1-junction of w_s).
    """
    g = BondGraph("cvt", "Centrifugal clutch and rubber-belt CVT with shift dynamics.")
    sheave, x = _cvt_sheave(g, P, num)
    i_cvt, T_cap = _cvt_clamp_and_ratio(P, w_e, x, num)
    node, belt, sec = _cvt_clutch_and_belt(g, P, i_cvt, T_cap, num, belt_slip=belt_slip)
    # priority 1: without shaft compliance the driven wheels keep their state
    # and J_s is lumped into them (derivative causality)
    g.connect(sec, g.I("J_s", P["J_s"], priority=1))
    g.connect(sec, g.R("drag", P["b_s"]))
    _cvt_shift_forces(g, P, w_e, belt.p2.e, sheave)
    g.expose("engine", node)
    g.expose("secondary", sec)
    g.metadata["ratio"] = i_cvt
    g.metadata["T_cap"] = T_cap
    return g


def _cvt_sheave(g: BondGraph, P: Params, num: Numerics):
    """The primary sheave's 1-junction (dx_p/dt) with the springs C: force
    Psi(x) (preloads, rates, end-stop ramps) and its exact energy. Returns the
    junction and the sheave travel x_p (the C's state)."""
    xmax = P["x_max"]
    ks = const(num.k_stop)
    xd = num.x_delta
    F_pre = P["k_fw"] * P["w_eng"]**2 + P["F_s0"]
    K = P["k_p"] + P["k_s"]
    xdelta = const(xd)

    def psi(q):
        return F_pre + K * q + ks * (ramp(q - xmax, xd) - ramp(-q, xd))

    def _R(z):  # integral of ramp(z): z^2/4 + (z sqrt(z^2+d^2) + d^2 asinh(z/d))/4
        return z**2 / 4 + (z * sp.sqrt(z**2 + xdelta**2) + xdelta**2 * sp.asinh(z / xdelta)) / 4

    def energy(q):
        return F_pre * q + K * q**2 / 2 + ks * (_R(q - xmax) + _R(-q) - 2 * _R(sp.Integer(0)))

    sheave = g.one("sheave", domain="translation")
    springs = g.C("springs", effort=psi, energy=energy)
    g.connect(sheave, springs)
    return sheave, springs.q


def _cvt_clamp_and_ratio(P: Params, w_e, x, num: Numerics):
    """The ratio i_cvt and the clutch's torque capacity T_cap from the sheave
    travel ``x`` and the engine speed ``w_e``.

    The clamp (and so the torque capacity) is zero below the engagement speed
    w_eng (flyweight force = primary-spring preload) and grows with w_e^2
    above it. The ratio map is linear in the sheave travel (linearised belt
    geometry), smoothly clipped to the stops.
    """
    xmax = P["x_max"]
    s_rel = x / xmax
    # ratio from the sheave position, smoothly clipped at the stops (the stop
    # springs keep x_p near [0, x_max]; the clip keeps i_cvt in [i_min, i_max])
    s_clip = ramp(s_rel, num.s_delta) - ramp(s_rel - 1, num.s_delta)
    i_cvt = P["i_max"] - (P["i_max"] - P["i_min"]) * s_clip
    F_clamp = ramp(P["k_fw"] * (w_e**2 - P["w_eng"]**2) - P["k_p"] * x, num.F_delta)
    r_p = P["r_p0"] + const(DR_DX) * x  # pitch radius grows with x_p: 1/(2 tan beta)
    T_cap = P["mu_cl"] * r_p * F_clamp
    return i_cvt, T_cap


def _cvt_clutch_and_belt(g: BondGraph, P: Params, i_cvt, T_cap, num: Numerics, *,
                         belt_slip: bool):
    """Clutch node with the slip law R, primary 1-junction, the belt MTF
    1/i_cvt and the secondary 1-junction (through J_b and the creep law with
    ``belt_slip``). Returns the clutch node, the belt and the secondary.

    The slip law is a regularised Coulomb law whose width grows with the
    capacity, so its slope never exceeds c_cl (clutch + belt creep lumped):
    this caps the clutch mode at -c_cl (1/J_e + i^2/J_s) instead of the
    -T_cap/w_eps (1/J_e + i^2/J_s) of a fixed-width tanh (~3e4 1/s when
    locked).
    """
    weps = const(num.w_eps_clutch)
    node = g.zero("clutch_node", domain="rotation")
    clutch = g.R("clutch", effort=lambda f: T_cap * sp.tanh(f / (weps + T_cap / P["c_cl"])))
    g.connect(node, clutch)
    prim = g.one("w_p", domain="rotation")
    g.connect(node, prim)
    belt = g.MTF("belt", 1 / i_cvt)
    g.connect(prim, belt.p1)
    sec = g.one("w_s", domain="rotation")
    if belt_slip:
        wb = g.one("w_b", domain="rotation")
        g.connect(belt.p2, wb)
        g.connect(wb, g.I("J_b", P["J_b"]))
        bnode = g.zero("belt_node", domain="rotation")
        g.connect(wb, bnode)
        g.connect(bnode, g.R("belt_creep", P["c_bs"]))
        g.connect(bnode, sec)
    else:
        g.connect(belt.p2, sec)
    return node, belt, sec


def _cvt_shift_forces(g: BondGraph, P: Params, w_e, T_s, sheave) -> None:
    """The shift force balance on the sheave: flyweights k_fw w_e^2, helix
    feedback -k_h T_s (``T_s`` the belt's secondary torque), damping b_sh.

    It follows the speed- and torque-controlled variator of Cammalleri
    (2005): flyweights (~w_e^2) close the primary against its spring, the
    secondary spring and the helix torque feedback (~T_s); more load
    backshifts. The MTF modulus is a signal from x_p: the power of the belt's
    radial motion is neglected, and the flyweight and helix sources take no
    power from the shafts (vehicle_physics.md §3.3).
    """
    g.connect(g.MSe("flyweights", P["k_fw"] * w_e**2), sheave)
    g.connect(g.MSe("helix", -P["k_h"] * T_s), sheave)
    g.connect(sheave, g.R("damping", P["b_sh"]))


# ----------------------------------------------------------------- driveline
def driveline(P: Params, *, drive: str = "2WD", shaft_compliance: bool = True) -> BondGraph:
    """Gearbox (one range), final drives, half-shaft compliance.

    Graph::

        p1 -> TF 1/i_g -> 1(w_out) -> TF 1/i_fd -> 0(T_ds,r) -> (rear axle)
                                   |                 |
                                   |              1(twist): C k_ds, R c_ds
                                   +-> TF 1/i_fd -> 0(T_ds,f) -> (front axle, AWD)

        w_out = w_s / i_g,  w_ax = w_out / i_fd,  T_ds = k_ds phi + c_ds dphi/dt,
        dphi/dt = w_ax - w_w

    Neutral is not a modulus of zero: it is the absence of this fragment
    (a zero TF cannot be inverted by causality assignment). The front and
    rear propshafts turn with the gearbox output, so that junction is a
    1-junction (axle torques add); 2WD removes the front branch. Without
    shaft compliance the secondary, gearbox and wheels of the driven axle are
    rigidly coupled and SCAP lumps their inertias (derivative causality).

    Parameters
    ----------
    P : mapping
        ``i_g, i_fd`` (+ ``k_ds, c_ds``).
    drive : {"2WD", "AWD"}
    shaft_compliance : bool

    Returns
    -------
    BondGraph
        Fragment exposing ``input`` (gearbox TF p1), ``rear`` and, for AWD,
        ``front`` (the shaft 0-junction, or the final-drive TF p2 without
        compliance).
    """
    if drive not in ("2WD", "AWD"):
        raise ValueError(f"drive must be '2WD' or 'AWD', not {drive!r}")
    g = BondGraph("driveline", "Gearbox, final drives and half-shafts.")
    gb = g.TF("gearbox", 1 / P["i_g"])
    out = g.one("w_out", domain="rotation")
    g.connect(gb.p2, out)
    axles = ("rear", "front") if drive == "AWD" else ("rear",)
    for ax in axles:
        fd = g.TF(f"fd_{ax}", 1 / P["i_fd"])
        g.connect(out, fd.p1)
        if shaft_compliance:
            node = g.zero(f"shaft_{ax}", domain="rotation")
            g.connect(fd.p2, node)
            tw = g.one(f"twist_{ax}", domain="rotation")
            g.connect(node, tw)
            g.connect(tw, g.C(f"k_{ax}", stiffness=P["k_ds"]))
            g.connect(tw, g.R(f"c_{ax}", P["c_ds"]))
            g.expose(ax, node)
        else:
            g.expose(ax, fd.p2)
    g.expose("input", gb.p1)
    return g


# -------------------------------------------------------------- wheel + tire
def magic_formula(kappa, F_z, P: Params):
    """Pacejka Magic Formula, longitudinal, pure slip.

    F_x = D sin(C atan(B k - E (B k - atan(B k)))), D = mu F_z,
    B = k_slip / (C mu) so that the slip stiffness is BCD = k_slip F_z.
    Pacejka (2012) §4.3.
    """
    Bk = P["k_slip"] / (P["C_mf"] * P["mu"]) * kappa
    return P["mu"] * F_z * sp.sin(P["C_mf"] * sp.atan(Bk - P["E_mf"] * (Bk - sp.atan(Bk))))


def axle(P: Params, *, n_wheels: int, F_z, v, brake, num: Numerics = Numerics(),
         brake_drag: bool = False) -> BondGraph:
    """Wheels of one axle (or of the whole vehicle, lumped) with their tires.

    Graph::

        1(w_w): I n J_w, R brake, R rolling [, R brake_drag] -> TF r_dyn -> 0(F_x) -> (body 1(v))
                                                                            |
                                                                        R: tire (slip v_sx)

        n J_w dw/dt = T_ds - r_dyn F_x - T_b - T_rr
        T_b  = n T_bmax u_b tanh(w / w_eps),   T_rr = f_r F_z r_dyn tanh(w / w_eps)
        v_sx = r_dyn w - v,   kappa = v_sx / smax(|v|, v_eps),   F_x = MF(kappa; mu, F_z)

    In straight-line driving the left and right wheels of an axle have the
    same speed and load (an open differential splits torque equally), so
    one lumped wheel per axle (``n_wheels=2``) is exact for the longitudinal
    dynamics; the coast-down filter model lumps all four (``n_wheels=4``).
    Low-speed regularisation (vehicle_physics.md §3.7): the slip denominator
    is a smooth max of |v| and v_eps, so below v_eps the tire is a viscous
    damper of coefficient k_slip F_z / v_eps; the tanh brake cannot hold the
    vehicle still on a slope (it creeps at ~w_eps atanh(T_grade/T_b)).

    Parameters
    ----------
    P : mapping
        ``J_w, T_bmax, f_r, r_dyn, mu, k_slip, C_mf, E_mf`` (+ ``T_bd``).
    n_wheels : int
        Wheels lumped in this fragment (2 per axle, 4 for the whole vehicle).
    F_z : sympy expression
        Normal load on these wheels together [N].
    v : sympy expression
        Body speed [m/s] (the tire law reads it: modulated R).
    brake : sympy expression
        Brake command u_b in [0, 1].
    num : Numerics
    brake_drag : bool
        Truth effect: residual brake drag n T_bd tanh(w / w_eps).

    Returns
    -------
    BondGraph
        Fragment exposing ``hub`` (1-junction of the wheel speed) and
        ``ground`` (the contact-patch 0-junction; bond it to the body).
    """
    g = BondGraph("axle", "Wheels, brakes, rolling resistance and tires.")
    n = sp.Integer(n_wheels)
    w = g.one("w", domain="rotation")
    g.connect(w, g.I("J", n * P["J_w"]))
    eps = const(num.w_eps_wheel)
    g.connect(w, g.R("brake", effort=lambda f: n * P["T_bmax"] * brake * sp.tanh(f / eps)))
    g.connect(w, g.R("rolling", effort=lambda f: P["f_r"] * F_z * P["r_dyn"] * sp.tanh(f / eps)))
    if brake_drag:
        g.connect(w, g.R("brake_drag", effort=lambda f: n * P["T_bd"] * sp.tanh(f / eps)))
    tf = g.TF("radius", P["r_dyn"])
    g.connect(w, tf.p1)
    patch = g.zero("patch", domain="translation")
    g.connect(tf.p2, patch)
    den = smax(smooth_abs(v, num.v_delta), const(num.v_eps), num.v_delta)
    g.connect(patch, g.R("tire", effort=lambda vs: magic_formula(vs / den, F_z, P)))
    g.expose("hub", w)
    g.expose("ground", patch)
    return g


# ---------------------------------------------------------------------- body
def body(P: Params, grade, num: Numerics = Numerics(), *, aero: bool = True) -> BondGraph:
    """Body: 1(v) with I: m, MSe: gravity on the grade, R: aerodynamic drag.

    ::

        m dv/dt = sum F_x - 1/2 rho C_dA v |v| - m g sin(theta_g)

    |v| is smoothed as sqrt(v^2 + v_delta^2) (a vanishing linear drag below
    v_delta). Rolling resistance sits at the wheels. vehicle_physics.md §3.9.

    Parameters
    ----------
    P : mapping
        ``m, g`` (+ ``C_dA``).
    grade : sympy expression
        Road grade theta_g [rad] (state or input).
    num : Numerics
    aero : bool
        Include aerodynamic drag (a declared model may omit it).

    Returns
    -------
    BondGraph
        Fragment exposing ``v`` (the 1-junction of the body speed).
    """
    g = BondGraph("body", "Body mass, gravity on the grade, aerodynamic drag.")
    v = g.one("v", domain="translation")
    g.connect(v, g.I("m", P["m"]))
    g.connect(g.MSe("gravity", -P["m"] * P["g"] * sp.sin(grade)), v)
    if aero:
        half_rho = const(RHO / 2)
        g.connect(v, g.R("aero", effort=lambda f: half_rho * P["C_dA"] * f
                         * smooth_abs(f, num.v_delta)))
    g.expose("v", v)
    return g


# --------------------------------------------------------------------- pitch
def pitch(P: Params) -> BondGraph:
    """Pitch suspension: 1(dtheta_s/dt) with I: I_theta, C: k_theta, R: c_theta.

    ::

        I_theta d2theta_s/dt2 = -k_theta theta_s - c_theta dtheta_s/dt + M_drive

    The drive moment M_drive (a modulated source added by the vehicle, which
    knows the tire forces) is the longitudinal force at the centre-of-mass
    height. vehicle_physics.md §3.10.

    Returns
    -------
    BondGraph
        Fragment exposing ``rate`` (the 1-junction of the pitch rate).
    """
    g = BondGraph("pitch", "Pitch suspension.")
    j = g.one("rate", domain="rotation")
    g.connect(j, g.I("I", P["I_theta"]))
    g.connect(j, g.C("k", stiffness=P["k_theta"]))
    g.connect(j, g.R("c", P["c_theta"]))
    g.expose("rate", j)
    return g
