"""Reconstruction of what is missing at a port: an unknown effort (at a
1-junction) or flow (at a 0-junction) as an integrated random walk,
estimated by the UKF and the unscented RTS smoother over the whole record.

The declared graph is augmented at the port with a modulated source whose
value is a new state ``d`` and with its rate ``r``::

    dd/dt = r,   dr/dt = w(t),   E[w(t) w(s)] = q² δ(t − s)

(an integrated random walk, the smoothing prior of a cubic smoothing spline;
Wahba 1978; Särkkä 2013, §10). At a 1-junction ``d`` is an effort (a
force, a torque, a voltage) entering the junction's effort balance; at a
0-junction a flow entering its flow balance. The intensity ``q`` (effort
per s^1.5) sets how fast ``d`` may change: it is given, or chosen by maximum
likelihood (the UKF's negative log-likelihood, one batched pass) over a grid
``q_i = S / τ_i^1.5`` of time scales ``τ_i`` from a few samples to a
fraction of the record, ``S`` the port's effort (flow) scale along the
declared model's filtered states. The declared model's process-noise
intensities, which compete with ``d`` for the same innovations, are turned
down meanwhile (:data:`NOISE_FACTORS`, :func:`intensity_grid`).

The smoothed ``d̂(t) = E[d(t) | whole record]`` with its std is returned
beside the port's own variables along the smoothed states: the junction's
common flow (1-junction) or effort (0-junction), the states of the storage
elements bonded to it, and the inputs.

References
----------
Wahba, G. (1978). Improper priors, spline smoothing and the problem of
guarding against model errors in regression. JRSS B 40(3), 364-372.
Särkkä, S. (2008). Unscented Rauch-Tung-Striebel smoother. IEEE TAC 53(3).
Särkkä, S. (2013). Bayesian Filtering and Smoothing. Cambridge UP.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import sympy as sp

from bondgraph.core.elements import C, I, One, Zero
from bondgraph.core.equations import derive
from bondgraph.diagnose.effects.base import junction_units
from bondgraph.errors import GraphError, NumericalError, OptionError
from bondgraph.inference.estimand import moves_meas_std, noise_parameters
from bondgraph.inference.options import UKFOptions
from bondgraph.inference.prior import PriorSpec
from bondgraph.inference.problem import NoiseSpec, make_problem
from bondgraph.inference.smoother import rts_smooth
from bondgraph.numerics.model import Model

#: prefix of the states and parameter the augmentation adds
PREFIX = "missing"
#: factor of the declared process-noise intensities during the
#: reconstruction (:func:`intensity_grid`): the declared process noise is the
#: model's stand-in for the unmodelled forces (flows), which the random walk
#: now represents. Profiled by likelihood instead (factors 1 to 0.001) the
#: white noise wins on Silverbox (at 0.1 of its declared level, with the
#: walk's smallest intensity: d̂ a near-constant 0.3 mV, no law), since it
#: follows the missing force sample by sample; held at 0.001 the walk
#: carries it (d̂ 2.9 mV RMS, a law with −2.2·y³)
NOISE_FACTORS = (1e-3,)


@dataclass(frozen=True)
class ReconstructOptions:
    """How the missing effort or flow is reconstructed.

    Parameters
    ----------
    q : float, optional
        The random walk's intensity (port effort or flow unit per s^1.5),
        given; None (default): chosen by maximum likelihood over the grid.
    grid : int
        Number of time scales τ of the grid (default 9).
    tau_min : float
        Shortest time scale, in sample intervals (default 2).
    tau_max : float
        Longest time scale, as a fraction of the record's duration
        (default 0.1).
    scale : float, optional
        The port's effort (flow) scale ``S`` (its unit); None: the RMS of
        the net effort on the inertias bonded to a 1-junction (the net flow
        into the capacitances of a 0-junction) along the declared model's
        filtered states.
    ukf : UKFOptions, optional
        The filter's options (default ``UKFOptions()``).
    noise_factors : tuple of float
        Factors of the declared process-noise intensities; with several,
        each intensity's likelihood is profiled over them (default
        :data:`NOISE_FACTORS`; ``(1.0,)``: held at their declared values).
    noise : dict, optional
        Measurement-noise stds (output -> std, output units; the loop's
        estimates) held for the outputs whose level neither the graph nor
        the record gives (:func:`held_noise`).

    Raises
    ------
    OptionError
        A non-positive ``q`` or ``scale``, fewer than 2 grid points,
        ``tau_min <= 0`` or ``tau_max`` outside (0, 1].
    """

    q: float | None = None
    grid: int = 9
    tau_min: float = 2.0
    tau_max: float = 0.1
    scale: float | None = None
    ukf: UKFOptions | None = None
    noise_factors: tuple = NOISE_FACTORS
    noise: dict | None = None

    def __post_init__(self):
        if self.q is not None and not (np.isfinite(self.q) and self.q > 0):
            raise OptionError(f"ReconstructOptions.q must be positive, got {self.q}")
        if self.scale is not None and not (np.isfinite(self.scale) and self.scale > 0):
            raise OptionError(f"ReconstructOptions.scale must be positive, got {self.scale}")
        if int(self.grid) != self.grid or self.grid < 2:
            raise OptionError(f"ReconstructOptions.grid must be an integer >= 2, got {self.grid}")
        if not self.tau_min > 0:
            raise OptionError(f"ReconstructOptions.tau_min must be positive, got {self.tau_min}")
        if not 0 < self.tau_max <= 1:
            raise OptionError(f"ReconstructOptions.tau_max must be in (0, 1], got {self.tau_max}")


@dataclass
class PortAugmentation:
    """Where and how a graph was augmented (:func:`augment_port`).

    Attributes
    ----------
    port : str
        The junction's name.
    kind : {"effort", "flow"}
        What is missing (an effort at a 1-junction, a flow at a 0-junction).
    unit, rate_unit : str
        Units of ``d`` and of its rate ``r``.
    d, r, q : str
        Names of the two new states and of the intensity parameter.
    source : str
        Name of the modulated source.
    """

    port: str
    kind: str
    unit: str
    rate_unit: str
    d: str
    r: str
    q: str
    source: str


@dataclass
class Reconstruction:
    """What :func:`reconstruct` returns.

    Attributes
    ----------
    t : ndarray (N,)
        Sample times (s).
    d, d_std : ndarray (N,)
        The smoothed missing effort (flow) at the port and its std, in
        ``port.unit``.
    variables : dict str -> ndarray (N,)
        The port's own variables along the smoothed states: the junction's
        flow (``"<port>.f"``) or effort (``"<port>.e"``), the states of the
        bonded storage elements (by state name) and the inputs (by name).
    primary : list of str
        The variables a law at the port is a function of (the junction's
        flow or effort and the storage states that are not a multiple of it:
        the capacitances' at a 1-junction, the inertias' at a 0-junction).
    units : dict str -> str
    port : PortAugmentation
    q : float
        The intensity used.
    q_grid, nll_grid : ndarray (G,)
        The grid and its negative log-likelihoods (empty when ``q`` was given).
    x, P : ndarray (N, n_x), (N, n_x, n_x)
        Smoothed states and covariances of the augmented model.
    model : Model
        The augmented model.
    theta : ndarray (n_theta,)
        Its parameter vector (the intensity included).
    x0, P0 : ndarray (n_x,), (n_x, n_x)
        The prior of the augmented state at ``t[0]``.
    """

    t: np.ndarray
    d: np.ndarray
    d_std: np.ndarray
    variables: dict
    primary: list
    units: dict
    port: PortAugmentation
    q: float
    q_grid: np.ndarray
    nll_grid: np.ndarray
    x: np.ndarray = field(repr=False)
    P: np.ndarray = field(repr=False)
    model: object = field(repr=False)
    theta: np.ndarray = field(repr=False)
    x0: np.ndarray = field(repr=False, default=None)
    P0: np.ndarray = field(repr=False, default=None)


def augment_port(graph, port: str):
    """A copy of ``graph`` with an integrated random walk entering ``port``.

    Parameters
    ----------
    graph : BondGraph
    port : str
        A 1-junction (a missing effort) or a 0-junction (a missing flow).

    Returns
    -------
    (BondGraph, PortAugmentation)

    Raises
    ------
    GraphError
        ``port`` is not a junction of ``graph``.
    """
    if port not in graph.elements or not isinstance(graph.elements[port], (One, Zero)):
        raise GraphError(f"graph '{graph.name}': '{port}' is not a junction")
    g = graph.copy(f"{graph.name}__missing")
    j = g.element(port)
    eu, fu = junction_units(g, j)
    kind = "effort" if isinstance(j, One) else "flow"
    unit = eu if kind == "effort" else fu
    rate_unit = f"({unit})/s"
    tag = port.replace(".", "_")
    names = PortAugmentation(port, kind, unit, rate_unit, f"{PREFIX}.{tag}.d",
                             f"{PREFIX}.{tag}.r", f"{PREFIX}.{tag}.q", f"{PREFIX}.{tag}")
    q = g.param(names.q, 1.0, f"({unit})/s^1.5", (1e-12, 1e12),
                f"intensity of the missing {kind}'s rate at {port}")
    r = g.state(names.r, 0, unit=rate_unit, process_noise=q,
                description=f"rate of the missing {kind} at {port}")
    d = g.state(names.d, r, unit=unit, description=f"missing {kind} at {port}")
    src = g.MSe(names.source, d) if kind == "effort" else g.MSf(names.source, d)
    g.connect(src, j)
    return g, names


def port_expressions(graph, port: str, dependent=()) -> tuple[dict, list]:
    """The port's own variables as symbols of ``graph`` (before derivation).

    Parameters
    ----------
    graph : BondGraph
    port : str
        A junction of ``graph``.
    dependent : collection of str
        Storage elements in derivative causality
        (``StateSpace.derivative_elements``): their states are not states
        of the model (a rigidly geared inertia's momentum follows the
        other's) and are left out.

    Returns
    -------
    (dict name -> sympy expression, list of primary names)
        The junction's flow (1-junction) or effort (0-junction), the states
        of the storage elements bonded to it, the inputs; the primary names
        are the junction's variable and the storage states that are not a
        multiple of it (:attr:`Reconstruction.primary`).
    """
    j = graph.element(port)
    own = (f"{port}.f", j.f) if isinstance(j, One) else (f"{port}.e", j.e)
    out = {own[0]: own[1]}
    primary = [own[0]]
    independent = C if isinstance(j, One) else I
    for p in j.ports:
        if p.bond is None:
            continue
        el = p.bond.other(p).element
        if (isinstance(el, (C, I)) and getattr(el, "state", None) is not None
                and el.name not in dependent):
            out[el.state.name] = el.state
            if isinstance(el, independent):
                primary.append(el.state.name)
    for name, inp in graph.inputs.items():
        out[name] = inp
    return out, primary


def port_values(graph, ss, port: str, X, u, theta) -> dict:
    """The port's variables (:func:`port_expressions`) of ``graph``, whose
    derived state space is ``ss``, along the states ``X`` (N, n_x) with the
    inputs ``u`` (N, n_u) and parameters ``theta`` (n_theta,): name ->
    array (N,)."""
    exprs, _ = port_expressions(graph, port, set(ss.derivative_elements))
    X = np.asarray(X, float)
    return _evaluate(_lambdified(ss, exprs), X, np.asarray(u, float), np.asarray(theta, float),
                     X.shape[0])


def _lambdified(ss, exprs: dict):
    args = (list(ss.states), list(ss.inputs), list(ss.params))
    return {k: sp.lambdify(args, ss.variable(e), "numpy") for k, e in exprs.items()}


def _evaluate(fns: dict, X, u, theta, n: int) -> dict:
    uT = u.T if u.size else np.zeros((0, n))
    return {k: np.broadcast_to(np.asarray(fn(X.T, uT, theta), float), (n,)).copy()
            for k, fn in fns.items()}


def port_scale(graph, model, problem, theta, port: str) -> float:
    """The port's effort (flow) scale ``S``: the RMS of the net effort on the
    inertias bonded to a 1-junction (the net flow into the capacitances of a
    0-junction) along the declared model's filtered states (1 if none).
    Storage elements in derivative causality (no state of the model) are
    left out.

    Raises
    ------
    NumericalError
        The declared model's filter fails on the record.
    """
    res = problem.nll(theta, store="full")
    if not np.isfinite(res.nll[0]):
        raise NumericalError(f"the declared model's filter fails: {res.reasons[0]}")
    X = res.x_filt[:, 0, :]
    j = graph.element(port)
    store = I if isinstance(j, One) else C
    names = [p.bond.other(p).element.state.name for p in j.ports
             if p.bond is not None and isinstance(p.bond.other(p).element, store)]
    idx = [model.states.index(n) for n in names if n in model.states]
    if not idx:
        return 1.0
    rates = np.asarray(model.f(X, problem.u, theta[None, :]), float)[:, idx]
    s = float(np.sqrt(np.mean(rates ** 2)))
    return s if np.isfinite(s) and s > 0 else 1.0


def reconstruct(graph, record, port: str, *, params=None,
                options: ReconstructOptions | None = None) -> Reconstruction:
    """Reconstruct the effort (flow) missing at ``port`` over ``record``.

    Parameters
    ----------
    graph : BondGraph
        The declared graph.
    record : Experiment
        The record (its declared noise levels are held).
    port : str
        A 1-junction (a missing effort) or 0-junction (a missing flow).
    params : dict, optional
        Parameter values of ``graph`` by name (default: its defaults).
    options : ReconstructOptions, optional

    Returns
    -------
    Reconstruction
        ``d`` (N,) and ``d_std`` (N,) in the port's effort (flow) unit, the
        port's variables (N,) by name.

    Raises
    ------
    GraphError
        ``port`` is not a junction.
    NumericalError
        The filter fails at every intensity, or the smoother fails.

    Notes
    -----
    Method: state augmentation by an integrated random walk (module
    docstring), maximum-likelihood intensity over a grid, unscented RTS
    smoother (Särkkä 2008).
    """
    opts = options or ReconstructOptions()
    g, aug = augment_port(graph, port)
    model, problem, sm, theta, qinfo = _smoothed(
        graph, record, g, aug, opts, params,
        lambda base, pb: port_scale(graph, base, pb, pb.theta, port))
    return _assemble(g, model, aug, problem, sm, theta, qinfo)


def _smoothed(graph, record, g, aug, opts: ReconstructOptions, params, scale) -> tuple:
    """The augmented graph ``g`` (walk ``aug``) on ``record``: the intensity
    by maximum likelihood over its grid (:func:`intensity_grid`), then the
    RTS smoother there. ``scale(base, problem)`` gives the walk's scale S
    unless ``opts.scale`` does (the declared model ``base`` of ``graph``
    and its problem on the record).

    Returns
    -------
    (model, problem, sm, theta, (q, q_grid, nll_grid))
        The augmented model and its problem, the smoothed run, the
        parameters (n_theta,) and the intensity with its grid.
    """
    ukf = opts.ukf or UKFOptions()
    fixed = dict(params or {})
    model = Model.from_graph(g, lazy=("dfdtheta", "dhdtheta"))
    base = Model.from_graph(graph, lazy=("dfdtheta", "dhdtheta"))
    noise = held_noise(base, record, opts.noise)
    pb = make_problem(base, record, ukf=ukf, fixed=fixed, noise=noise)
    S = opts.scale or scale(base, pb)
    t = pb.t
    dt = float(np.median(np.diff(t)))
    taus = np.geomspace(opts.tau_min * dt, opts.tau_max * (t[-1] - t[0]), int(opts.grid))
    prior = PriorSpec(x0_std={aug.d: 3.0 * S, aug.r: 3.0 * S / taus[0]})
    problem = make_problem(model, record, ukf=ukf, fixed=fixed, prior=prior, noise=noise)
    iq = model.params.index(aug.q)
    q_grid = np.array([float(opts.q)]) if opts.q is not None else S / taus ** 1.5
    proc = [model.param_index(n) for n in process_noise(base, pb.theta, opts)]
    theta, nll_grid = intensity_grid(problem, iq, q_grid, proc, opts.noise_factors)
    if opts.q is not None:
        q_grid, nll_grid = np.zeros(0), np.zeros(0)
    R = problem.noise.covariance(model, theta[None, :])
    sm = rts_smooth(model, t, problem.u, problem.y, theta, problem.x0, problem.P0,
                    options=ukf, R=None if R is None else R[0])
    return model, problem, sm, theta, (float(theta[iq]), q_grid, nll_grid)


def held_noise(model: Model, record, levels: dict | None) -> NoiseSpec | None:
    """The measurement-noise levels a reconstruction holds for the outputs
    whose level the graph does not give (its sensor's noise std 0 at the
    model's defaults): the record's declared level (model units), else
    ``levels`` (output -> std, the loop's estimates); None when there are
    none. The graph's own levels stay where it gives them. Without this a
    graph whose sensors declare no noise had a zero measurement variance
    and every reconstruction of ``--discover`` failed at sample 0 (a
    user's RLC filter)."""
    with np.errstate(all="ignore"):
        own = np.asarray(model.meas_std(model.theta0[None, :]), float)[0]
    missing = [o for o, v in zip(model.outputs, own) if not (np.isfinite(v) and v > 0)]
    if not missing:
        return None
    dec = np.full(len(model.outputs), np.nan)
    if record is not None and not isinstance(record, tuple):
        try:
            dec = np.asarray(record.noise_std_for(model), float)
        except Exception:      # a record that cannot say: the levels given
            pass
    held = {}
    for o in missing:
        v = dec[model.outputs.index(o)]
        v = v if np.isfinite(v) and v > 0 else float((levels or {}).get(o, np.nan))
        if np.isfinite(v) and v > 0:
            held[o] = float(v)
    return NoiseSpec(held=held) if held else None


def process_noise(base: Model, theta: np.ndarray, opts: ReconstructOptions) -> list[str]:
    """Names of the declared model ``base``'s process-noise intensities (at
    its parameter vector ``theta`` (n_theta,)): the parameters that change
    ``proc_std`` but neither ``f``, ``h`` nor ``meas_std``
    (:func:`bondgraph.inference.estimand.noise_parameters`); none when
    ``opts.noise_factors`` is ``(1.0,)``."""
    if tuple(opts.noise_factors) == (1.0,):
        return []
    th = np.asarray(theta, float)
    return [n for n in noise_parameters(base, th) if not moves_meas_std(base, th, n)]


def intensity_grid(problem, iq: int, q_grid: np.ndarray, proc: list[int],
                   factors=None) -> tuple[np.ndarray, np.ndarray]:
    """The augmented model's θ of largest likelihood over the intensities
    ``q_grid`` (G,) of the random walk (θ index ``iq``), each profiled over
    the declared process-noise intensities (θ indices ``proc``) scaled
    together by ``factors`` (default :data:`NOISE_FACTORS`), in one batched
    UKF run.

    The declared process noise and the random walk compete for the same
    innovations: at its declared level a white noise on the port's momentum
    explains the missing force sample by sample, and the likelihood then
    prefers the walk's smallest intensity (Silverbox, the cubic stiffness
    missing: d̂ 0.17 mV RMS, no law).

    Returns
    -------
    (theta (n_theta,), nll (G,))
        The best θ (its intensity and process-noise levels), and each
        intensity's NLL profiled over the factors.

    Raises
    ------
    NumericalError
        The filter fails at every intensity.
    """
    factors = np.asarray(NOISE_FACTORS if factors is None else factors, float)
    if not proc:
        factors = factors[:1]
    lo, hi = problem.model.lower, problem.model.upper
    th = np.repeat(problem.theta[None, :], q_grid.size * factors.size, axis=0)
    th[:, iq] = np.repeat(q_grid, factors.size)
    for j in proc:
        th[:, j] = np.clip(problem.theta[j] * np.tile(factors, q_grid.size), lo[j], hi[j])
    nll = np.asarray(problem.nll(th).nll, float)
    nll = np.where(np.isfinite(nll), nll, np.inf)
    if not np.isfinite(nll).any():
        raise NumericalError(f"reconstruction: the filter fails at every intensity "
                             f"({q_grid.size} intensities, {factors.size} process-noise levels)")
    return th[int(np.argmin(nll))].copy(), nll.reshape(q_grid.size, factors.size).min(axis=1)


#: a smoothed std of the walk above this share of the most its prior and
#: intensity allow is no information: the record told it next to nothing
#: (an unobserved direction; its smoothed std is that bound, or its
#: rounding beyond it: 5.8e79 or inf was seen at the same port, by the last
#: bit of the kernels' arithmetic, before the smoother restarted where it
#: diverged). Observed ports of a thermal two-node record reach 0.07 of it,
#: the unobserved ambient 1.0-1.4.
UNOBSERVED_SHARE = 0.9


def _walk_std(sm, problem, aug, q: float) -> np.ndarray:
    """The smoothed std (N,) of the walk ``aug.d``, inf where it exceeds
    :data:`UNOBSERVED_SHARE` of its prior bound: the std an integrated
    random walk reaches with no measurement, sqrt((σ_d0 + σ_r0 T)² + q² T³/3)
    at T = t - t0 (plus q² T, a plain walk's), σ_d0 and σ_r0 the prior's
    stds of the walk and its rate. A smoother that stays at its prior has
    learnt nothing from the record there, and beyond it the number is an
    unobserved direction's rounding (finite on one build, inf on another);
    ``discover_law`` refuses the port either way."""
    i, ir = problem.model.states.index(aug.d), problem.model.states.index(aug.r)
    std = np.sqrt(np.maximum(sm.P[:, i, i], 0))
    T = problem.t - problem.t[0]
    P0 = np.asarray(problem.P0, float)
    bound = np.sqrt((np.sqrt(max(P0[i, i], 0.0)) + np.sqrt(max(P0[ir, ir], 0.0)) * T) ** 2
                    + q * q * (T + T ** 3 / 3.0))
    with np.errstate(invalid="ignore"):
        return np.where(std <= UNOBSERVED_SHARE * bound, std, np.inf)


def _assemble(g, model, aug, problem, sm, theta, qinfo) -> Reconstruction:
    """The :class:`Reconstruction` of a smoothed augmented model."""
    ss = derive(g)
    exprs, primary = port_expressions(g, aug.port, set(ss.derivative_elements))
    n = problem.t.size
    values = _evaluate(_lambdified(ss, exprs), sm.x, problem.u, theta, n)
    units = {aug.d: aug.unit}
    j = g.element(aug.port)
    eu, fu = junction_units(g, j)
    for k in values:
        if k in model.states:
            units[k] = next((s.unit for s in g.all_states() if s.name == k), "") or ""
        elif k in g.inputs:
            units[k] = g.inputs[k].unit or ""
        else:
            units[k] = fu if k.endswith(".f") else eu
    i = model.states.index(aug.d)
    q, q_grid, nll_grid = qinfo
    return Reconstruction(problem.t.copy(), sm.x[:, i].copy(), _walk_std(sm, problem, aug, q),
                          values, primary, units, aug, q, q_grid, nll_grid, sm.x, sm.P, model,
                          theta, problem.x0.copy(), problem.P0.copy())


# ------------------------------------------------------------ a sensor's output
def augment_sensor(graph, sensor: str):
    """A copy of ``graph`` with an integrated random walk ``d`` added to the
    output of ``sensor``: y = h(x, u, θ) + d (an additive output offset,
    the same prior as at a junction, :func:`augment_port`).

    Parameters
    ----------
    graph : BondGraph
    sensor : str
        A sensor of ``graph``.

    Returns
    -------
    (BondGraph, PortAugmentation)
        ``kind`` is ``"output"``, ``unit`` the sensor's unit (``"1"`` when
        it declares none), ``source`` the sensor's name.

    Raises
    ------
    GraphError
        ``sensor`` is not a sensor of ``graph``.
    """
    if sensor not in graph.sensors:
        raise GraphError(f"graph '{graph.name}' has no sensor '{sensor}'")
    g = graph.copy(f"{graph.name}__missing_output")
    sen = g.sensors[sensor]
    unit = sen.unit or "1"
    rate_unit = f"({unit})/s"
    tag = "out_" + sensor.replace(".", "_")
    names = PortAugmentation(sensor, "output", unit, rate_unit, f"{PREFIX}.{tag}.d",
                             f"{PREFIX}.{tag}.r", f"{PREFIX}.{tag}.q", sensor)
    q = g.param(names.q, 1.0, f"({unit})/s^1.5", (1e-12, 1e12),
                f"intensity of the rate of the offset missing at the output {sensor}")
    r = g.state(names.r, 0, unit=rate_unit, process_noise=q,
                description=f"rate of the offset missing at the output {sensor}")
    d = g.state(names.d, r, unit=unit, description=f"offset missing at the output {sensor}")
    sen.expr = sen.expr + d
    return g, names


def reconstruct_sensor(graph, record, sensor: str, *, params=None,
                       options: ReconstructOptions | None = None) -> Reconstruction:
    """Reconstruct the additive offset d(t) missing at the output of
    ``sensor`` over ``record``: y = h(x) + d, d an integrated random walk
    (:func:`augment_sensor`), its intensity by maximum likelihood over the
    grid of :func:`reconstruct`, the unscented RTS smoother.

    Parameters
    ----------
    graph : BondGraph
        The declared graph.
    record : Experiment
        The record; it must hold the sensor's output.
    sensor : str
        A sensor of ``graph``.
    params : dict, optional
        Parameter values of ``graph`` by name (default: its defaults).
    options : ReconstructOptions, optional
        ``scale`` None: the std of the measured output.

    Returns
    -------
    Reconstruction
        ``d`` (N,) and ``d_std`` (N,) in the sensor's unit; ``variables``:
        the sensed quantity h(x, u, θ) along the smoothed states
        (``"<sensor>.y"``, the one primary variable: a law y = h + g(h)) and
        the inputs.

    Raises
    ------
    GraphError
        ``sensor`` is not a sensor of ``graph``.
    DataError
        The record lacks the sensor's output.
    NumericalError
        The filter fails at every intensity, or the smoother fails.
    """
    opts = options or ReconstructOptions()
    g, aug = augment_sensor(graph, sensor)
    model, problem, sm, theta, qinfo = _smoothed(
        graph, record, g, aug, opts, params,
        lambda base, pb: float(np.nanstd(pb.y[:, base.outputs.index(sensor)])) or 1.0)
    return _assemble_sensor(g, graph.sensors[sensor].expr, model, aug, problem, sm, theta, qinfo)


def _assemble_sensor(g, sensed, model, aug, problem, sm, theta, qinfo) -> Reconstruction:
    """The :class:`Reconstruction` of a smoothed model augmented at a sensor;
    ``sensed`` is the declared sensor's expression h."""
    ss = derive(g)
    own = f"{aug.port}.y"
    exprs = {own: sensed, **{name: inp for name, inp in g.inputs.items()}}
    n = problem.t.size
    values = _evaluate(_lambdified(ss, exprs), sm.x, problem.u, theta, n)
    units = {aug.d: aug.unit, own: aug.unit}
    units.update({k: g.inputs[k].unit or "" for k in g.inputs})
    i = model.states.index(aug.d)
    q, q_grid, nll_grid = qinfo
    return Reconstruction(problem.t.copy(), sm.x[:, i].copy(),
                          _walk_std(sm, problem, aug, q), values, [own], units, aug, q,
                          q_grid, nll_grid, sm.x, sm.P, model, theta, problem.x0.copy(),
                          problem.P0.copy())
