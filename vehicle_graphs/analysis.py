"""Numerical helpers for the vehicle models: consistent initial states,
the coast-down road-load least squares (suspension-approximation bias), and
stiffness at operating points.

All functions work on a loaded :class:`bondgraph.numerics.model.Model` of one of the
vehicle graphs (state names follow :func:`vehicle_graphs.build_vehicle`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from bondgraph.errors import ModelError, NumericalError
from bondgraph.numerics.integrators import rk4_stable_step

from .params import RHO

#: wheels lumped in each wheel fragment of the vehicle graphs
_WHEEL_STATES = {"rear.p_J": 2, "front.p_J": 2, "wheels.p_J": 4}


def _theta(model, theta) -> np.ndarray:
    if theta is None:
        return model.theta0.copy()
    if isinstance(theta, Mapping):
        return model.theta(theta)
    th = np.asarray(theta, dtype=float)
    if th.shape != (model.n_theta,):
        raise ModelError(f"theta has shape {th.shape}; model '{model.name}' has "
                         f"{model.n_theta} parameters")
    return th


def initial_state(model, theta=None, *, v: float = 0.0, grade: float = 0.0,
                  u: Mapping[str, float] | None = None,
                  settle: Sequence[str] | None = None) -> dict[str, float]:
    """A consistent initial state of a vehicle model.

    Body speed ``v`` and wheel speeds ``v / r_dyn`` (zero slip; per axle
    ``v / r_dyn_r``, ``v / r_dyn_f`` in a model with per-axle radii), the grade
    state (if any), shaft twists and secondary at rest or rolling with the
    wheels; then the fast states in ``settle`` are put in equilibrium
    (``f_i(x) = 0`` solved for them with the others fixed, by Newton on the
    generated Jacobian): by default the pitch (quasi-static pitch under the
    current deceleration), the engine speed (idle equilibrium with the clutch
    open at zero throttle), and the CVT sheave (at its stop).

    Parameters
    ----------
    model : Model
    theta : array (n_theta,) or dict, optional
        Parameters (default: the model's defaults).
    v : float
        Body speed [m/s].
    grade : float
        Road grade [rad] (the ``theta_g`` state, when the model has one).
    u : dict, optional
        Input values during settling (default: model defaults, i.e. zero
        throttle and brake).
    settle : sequence of str or "all", optional
        States to put in equilibrium (default: those of pitch, engine and
        sheave present in the model). ``"all"``: every state but the grade,
        i.e. a steady state (e.g. held by the brake on a slope: the tanh
        brake's steady creep).

    Returns
    -------
    dict
        State name -> value (model units: momenta, displacements).

    Raises
    ------
    NumericalError
        If the Newton iteration does not converge (the message names the
        states).
    """
    th = _theta(model, theta)
    P = dict(zip(model.params, th))
    x = model.x0.copy()
    names = model.states
    idx = {n: i for i, n in enumerate(names)}
    if "body.p_m" in idx:
        x[idx["body.p_m"]] = P["m"] * v
    radius = {n: P.get(f"r_dyn_{n[0]}", P.get("r_dyn")) for n in _WHEEL_STATES}
    for n, k in _WHEEL_STATES.items():
        if n in idx:
            x[idx[n]] = k * P["J_w"] * v / radius[n]
    if "theta_g" in idx:
        x[idx["theta_g"]] = grade
    if "cvt.p_J_s" in idx and "driveline.q_k_rear" in idx:
        x[idx["cvt.p_J_s"]] = P["J_s"] * v / radius["rear.p_J"] * P["i_g"] * P["i_fd"]
    if "engine.p_J" in idx:
        x[idx["engine.p_J"]] = P["J_e"] * P["w_idle"]
    uu = model.input(dict(u or {}))
    if settle is None:
        settle = [n for n in ("pitch.p_I", "pitch.q_k", "engine.p_J", "cvt.q_springs")
                  if n in idx]
    elif settle == "all":
        settle = [n for n in names if n != "theta_g"]
    sel = np.array([idx[n] for n in settle], dtype=int)
    if sel.size:
        for _ in range(60):
            F, J = model.f_dfdx(x, uu, th)
            r = F[sel]
            A = J[np.ix_(sel, sel)]
            dx = np.linalg.solve(A, -r)
            x[sel] += dx
            if np.all(np.abs(dx) <= 1e-12 * (1.0 + np.abs(x[sel]))):
                break
        else:
            raise NumericalError(f"initial_state of '{model.name}': equilibrium of "
                                 f"{', '.join(settle)} did not converge")
    return {n: float(x[i]) for n, i in idx.items()}


# --------------------------------------------------------------- coast-down
@dataclass(frozen=True)
class PitchModel:
    """How :func:`coastdown_road_load` reads the grade from the pitch sensor.

    Attributes
    ----------
    suspension : {"quasi_static", "rigid"}
        The suspension approximation (see :func:`coastdown_road_load`).
    h_cg : float
        Height of the centre of mass [m].
    k_theta : float
        Pitch stiffness of the suspension [N m/rad].

    Raises
    ------
    ValueError
        An unknown ``suspension``.
    """

    suspension: str = "quasi_static"
    h_cg: float = 0.6
    k_theta: float = 1.0e5

    def __post_init__(self):
        if self.suspension not in ("quasi_static", "rigid"):
            raise ValueError(f"suspension must be 'quasi_static' or 'rigid', not "
                             f"{self.suspension!r}")


def coastdown_road_load(t: np.ndarray, v: np.ndarray, pitch: np.ndarray, *, m: float,
                        J_w: float, r_dyn: float, theta_off: float = 0.0, g: float = 9.81,
                        pitch_model: PitchModel = PitchModel(), window: float = 2.0,
                        v_min: float = 3.0) -> dict[str, float]:
    """Rolling resistance and drag area from a coast-down record, by linear
    least squares on the road-load equation (SAE J2263 form).

    In neutral, with the grade read from the pitch sensor::

        m_eff dv/dt + m g sin(theta_g) = -f_r m g cos(theta_g) - 1/2 rho C_dA v^2
        m_eff = m + 4 J_w / r_dyn^2                     (wheel inertia, §3.9)

    The grade estimate depends on the suspension approximation:

    * ``"rigid"`` (the original work's reading): theta_g = pitch - theta_off.
      The body pitch under the coast-down deceleration, theta_s =
      h_cg m (dv/dt + g theta_g) / k_theta (0.1-0.25 deg nose-down), is
      taken for grade: a force error m g theta_s proportional to the
      deceleration inflates both f_r and C_dA by about m^2 g h_cg / (k_theta
      m_eff) (~7 % with the table's values).
    * ``"quasi_static"`` (the better approximation): the quasi-static pitch
      is removed, theta_g = (pitch - theta_off - h_cg m dv/dt / k_theta) /
      (1 + h_cg m g / k_theta) (small-angle form).

    dv/dt and the pitch are smoothed by a Savitzky-Golay filter (cubic,
    ``window`` seconds).

    Parameters
    ----------
    t, v, pitch : arrays (N,)
        Time [s], GNSS speed [m/s], reported pitch [rad] at a uniform rate.
    m, J_w, r_dyn, theta_off, g : float
        Known parameters (SI units).
    pitch_model : PitchModel
        The suspension approximation, ``h_cg`` and ``k_theta`` (default
        ``"quasi_static"``, 0.6 m, 1e5 N m/rad).
    window : float
        Smoothing window [s].
    v_min : float
        Samples below this speed are left out [m/s].

    Returns
    -------
    dict
        ``f_r``, ``C_dA``, ``n`` (samples used), ``rms`` (residual force
        RMS, N).

    Raises
    ------
    ValueError
        Arrays of different lengths, or too few
        samples above ``v_min``.

    References
    ----------
    SAE J2263 (coast-down road load); vehicle_physics.md §3.9-3.10.
    """
    suspension, h_cg, k_theta = pitch_model.suspension, pitch_model.h_cg, pitch_model.k_theta
    t, v, pitch = (np.asarray(a, dtype=float) for a in (t, v, pitch))
    if not (t.shape == v.shape == pitch.shape):
        raise ValueError(f"t, v and pitch must have one shape (got {t.shape}, {v.shape}, "
                         f"{pitch.shape})")
    vs, dv, ps, n_win = _smoothed(t, v, pitch, window)
    if suspension == "rigid":
        th_g = ps - theta_off
    else:
        th_g = (ps - theta_off - h_cg * m * dv / k_theta) / (1.0 + h_cg * m * g / k_theta)
    keep = np.ones(t.size, bool)
    keep[: n_win // 2] = False
    keep[-(n_win // 2):] = False
    keep &= vs > v_min
    if keep.sum() < 10:
        raise ValueError(f"only {int(keep.sum())} samples above v_min = {v_min} m/s")
    return _road_load_fit(vs[keep], dv[keep], th_g[keep], m=m, m_eff=m + 4.0 * J_w / r_dyn**2,
                          g=g)


def _smoothed(t: np.ndarray, v: np.ndarray, pitch: np.ndarray, window: float):
    """Savitzky-Golay smoothing (cubic, ``window`` seconds, an odd number >= 5
    of samples): speed, its derivative [m/s^2] and pitch, each (N,), and the
    window length in samples."""
    dt = float(np.median(np.diff(t)))
    n_win = max(5, int(round(window / dt)) | 1)
    from scipy.signal import savgol_filter   # deferred: not needed at import

    vs = savgol_filter(v, n_win, 3)
    dv = savgol_filter(v, n_win, 3, deriv=1, delta=dt)
    ps = savgol_filter(pitch, n_win, 3)
    return vs, dv, ps, n_win


def _road_load_fit(vs: np.ndarray, dv: np.ndarray, th_g: np.ndarray, *, m: float,
                   m_eff: float, g: float) -> dict[str, float]:
    """Least squares of m_eff dv/dt + m g sin(theta_g) = -f_r m g cos(theta_g)
    - 1/2 rho C_dA v^2 over the given samples: ``f_r, C_dA, n, rms``."""
    y = m_eff * dv + m * g * np.sin(th_g)
    A = np.column_stack([-m * g * np.cos(th_g), -0.5 * RHO * vs**2])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    res = y - A @ coef
    return {"f_r": float(coef[0]), "C_dA": float(coef[1]), "n": int(vs.size),
            "rms": float(np.sqrt(np.mean(res**2)))}


# ----------------------------------------------------------------- stiffness
def stiffness_at(model, x: np.ndarray, u: np.ndarray, theta=None, dt: float = 0.025
                 ) -> dict[str, float]:
    """Fastest mode at one operating point and what it means for RK4.

    Parameters
    ----------
    model : Model
    x : array (n_x,)
    u : array (n_u,)
    theta : array or dict, optional
    dt : float
        Sample interval [s].

    Returns
    -------
    dict
        ``max_abs_lambda`` (largest |lambda| of df/dx, 1/s), ``lambda``
        (that eigenvalue, complex), ``h_rk4`` (largest stable RK4 step, s),
        ``substeps`` (RK4 sub-steps per ``dt`` for stability).
    """
    th = _theta(model, theta)
    lam = np.linalg.eigvals(np.asarray(model.dfdx(x, u, th), dtype=float))
    k = int(np.argmax(np.abs(lam)))
    h = rk4_stable_step(lam)
    return {"max_abs_lambda": float(np.abs(lam[k])), "lambda": complex(lam[k]),
            "h_rk4": float(h), "substeps": int(np.ceil(dt / h - 1e-12))}
