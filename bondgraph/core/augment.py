"""Augmented-state graphs: chosen parameters become random-walk states.

:func:`augment` returns a copy of a bond graph in which each tracked
parameter ``p`` is replaced, in every law, modulus, source, sensor and noise
expression, by a function of a new signal state ``tracked.<p>`` whose
dynamics are a random walk::

    d z/dt = 0  (+ white process noise)

The result is an ordinary graph: it is derived, generated (numpy and numba)
and filtered like any model (``Model.from_graph``), so the UKF estimates the
parameter jointly with the states ("augmenting the state with the
parameters"; Jazwinski 1970, ch. 8; Ljung 1979).

Box of the parameter (``transform``)
-----------------------------------
``"logit"`` (default): the parameter stays inside its declared box
``(lower, upper)`` for every sigma point::

    p = lower + (upper − lower) / (1 + exp(−z)),   z = ln((p − lower)/(upper − p))

``lower`` and ``upper`` become the fixed parameters ``tracked.<p>.lower`` and
``tracked.<p>.upper`` (in the parameter's unit, so the graph's unit checks
still hold). ``"none"``: ``p = z`` (the state in the parameter's unit, no box).

A prior std of ``z`` is at most :data:`LOGIT_UNIFORM_STD` = π/√3, the std of
``z`` when ``p`` is uniform over its box (:meth:`TrackedParameter.std_of`): a
wider Gaussian in ``z`` is less informative than the box itself only in
name, its mass lies on the box's edges, where the slope of the transform
vanishes; one update of the filter can then carry the state there, and the
parameter stays on its bound with a std near zero (a restarted tracker on a
measured record did so for 50-150 s at each change).

Drift intensity
---------------
The intensity ``q`` of each tracked parameter is a parameter
``drift.<p>`` in the parameter's unit per sqrt(s): over a time ``dt`` the
parameter's variance grows by ``q² dt``. With the logit transform the state
``z`` gets the process noise ``q / g'(z_0)``, with ``g'(z) = dp/dz =
(p − lower)(upper − p)/(upper − lower)`` at the parameter's start value
``p_0``: the intensity is exact (to first order) at ``p_0`` and follows the
slope of the transform elsewhere (a random walk of ``z``). ``q = 0`` makes
the parameter a constant the filter estimates (its variance only shrinks).

References
----------
Jazwinski, A. H. (1970). Stochastic Processes and Filtering Theory.
Academic Press, ch. 8 (parameter estimation by state augmentation).
Ljung, L. (1979). Asymptotic behavior of the extended Kalman filter as a
parameter estimator for linear systems. IEEE TAC 24(1), 36-50.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import sympy as sp

from bondgraph.core.elements import Source, TwoPort
from bondgraph.core.symbols import Parameter
from bondgraph.errors import ModelError, OptionError, ParameterError

#: how the box of a tracked parameter is kept (module docstring)
TRANSFORMS = ("logit", "none")
#: the std of z = logit((p − lower)/(upper − lower)) when p is uniform over its
#: box (the standard logistic distribution's, π/√3): the widest prior std of
#: a logit state (:meth:`TrackedParameter.std_of`)
LOGIT_UNIFORM_STD = math.pi / math.sqrt(3.0)

#: prefix of the new states (``tracked.<p>``) and drift parameters (``drift.<p>``)
STATE_PREFIX = "tracked."
DRIFT_PREFIX = "drift."


@dataclass(frozen=True)
class TrackedParameter:
    """How one parameter is tracked in an augmented graph.

    Attributes
    ----------
    name : str
        The parameter of the original graph.
    state : str
        Its state in the augmented graph (``tracked.<name>``).
    transform : {"logit", "none"}
    lower, upper : float
        The parameter's box (its declared bounds), in its unit.
    unit : str
    start : float
        The value ``z`` starts from (the state's ``initial``), in the
        parameter's unit.
    drift_param : str
        The drift-intensity parameter (``drift.<name>``), unit per sqrt(s).
    drift : float
        Its default value.
    slope0 : float
        ``dp/dz`` at ``start`` (1 for ``"none"``).
    """

    name: str
    state: str
    transform: str
    lower: float
    upper: float
    unit: str
    start: float
    drift_param: str
    drift: float
    slope0: float

    # ------------------------------------------------------------ the transform
    def value(self, z):
        """The parameter p(z) (numpy, any shape)."""
        z = np.asarray(z, float)
        if self.transform == "none":
            return z.copy()
        with np.errstate(over="ignore"):        # exp(-z) = inf: p = lower, as it should
            return self.lower + (self.upper - self.lower) / (1.0 + np.exp(-z))

    def slope(self, z):
        """dp/dz at z (numpy, any shape)."""
        z = np.asarray(z, float)
        if self.transform == "none":
            return np.ones_like(z)
        with np.errstate(over="ignore"):
            s = 1.0 / (1.0 + np.exp(-z))
        return (self.upper - self.lower) * s * (1.0 - s)

    def state_of(self, p):
        """z(p), the inverse of :meth:`value` (numpy).

        Raises
        ------
        ParameterError
            A value on or outside the box (logit).
        """
        p = np.asarray(p, float)
        if self.transform == "none":
            return p.copy()
        if np.any(p <= self.lower) or np.any(p >= self.upper):
            raise ParameterError(f"tracked parameter '{self.name}': {p} is not strictly inside "
                                 f"its box ({self.lower:g}, {self.upper:g})")
        return np.log((p - self.lower) / (self.upper - p))

    def std_of(self, p, std_p):
        """The std of z for a std ``std_p`` of p at p: first order
        (``std_p / g'(z)``), for the logit transform at most
        :data:`LOGIT_UNIFORM_STD` (the spread of z when p is uniform over
        its box; wider puts the prior's mass on the box's edges, where the
        filter's updates can leave the state with a vanishing slope).

        Raises
        ------
        ParameterError
            A value on or outside the box (logit).
        """
        sz = np.asarray(std_p, float) / self.slope(self.state_of(p))
        return sz if self.transform == "none" else np.minimum(sz, LOGIT_UNIFORM_STD)


def _transform_expr(z, lo_sym, hi_sym, transform: str):
    if transform == "none":
        return z
    return lo_sym + (hi_sym - lo_sym) / (1 + sp.exp(-z))


def augment(graph, track: Sequence[str], drift: Mapping[str, float] | None = None, *,
            transform: str = "logit", start: Mapping[str, float] | None = None):
    """A copy of ``graph`` in which the parameters ``track`` are random-walk states.

    Parameters
    ----------
    graph : BondGraph
        The original graph (not changed).
    track : sequence of str
        Parameters of ``graph`` to track (at least one, no repeats).
    drift : dict, optional
        Parameter -> drift intensity q >= 0 in the parameter's unit per
        sqrt(s) (default 0: constant, estimated). It is the default of the
        parameter ``drift.<p>`` of the new graph, which an estimation may fit.
    transform : {"logit", "none"}
        How the box is kept (module docstring).
    start : dict, optional
        Parameter -> the value its state starts from (default the declared
        default; strictly inside the box for "logit").

    Returns
    -------
    BondGraph
        Named ``<name>_track``; ``metadata["tracked"]`` is a tuple of
        :class:`TrackedParameter` in the order of ``track``.

    Raises
    ------
    ModelError
        An unknown parameter (the known ones listed), a repeat, a drift for a
        parameter not tracked, or a drift that is negative or not finite.
    OptionError
        An unknown transform.
    ParameterError
        A start value outside or on the box (logit).
    """
    track = list(track)
    drift = dict(drift or {})
    start = dict(start or {})
    _check_request(graph, track, drift, start, transform)
    g = graph.copy(f"{graph.name}_track")
    subs, tracked = {}, []
    for name in track:
        p = g.params.pop(name)
        tp, expr = _tracked_state(g, p, transform, float(drift.get(name, 0.0)),
                                  float(start.get(name, p.default)))
        subs[p] = expr
        tracked.append(tp)
    _substitute(g, subs)
    g.metadata["tracked"] = tuple(tracked)
    return g


def _check_request(graph, track, drift, start, transform) -> None:
    if transform not in TRANSFORMS:
        raise OptionError(f"augment: transform {transform!r} is not one of "
                          f"{', '.join(map(repr, TRANSFORMS))}")
    if not track:
        raise ModelError("augment: no parameter to track (give at least one)")
    for name in track:
        if name not in graph.params:
            raise ModelError(f"augment: graph '{graph.name}' has no parameter '{name}' "
                             f"(parameters: {', '.join(graph.params)})")
    if len(set(track)) != len(track):
        raise ModelError(f"augment: a parameter is named twice in {track}")
    for name, q in drift.items():
        if name not in track:
            raise ModelError(f"augment: drift given for '{name}', which is not tracked "
                             f"(tracked: {', '.join(track)})")
        if not (isinstance(q, (int, float)) and math.isfinite(q) and q >= 0):
            raise ModelError(f"augment: the drift intensity of '{name}' must be a finite "
                             f"number >= 0, got {q!r}")
    for name in start:
        if name not in track:
            raise ModelError(f"augment: start given for '{name}', which is not tracked")


def _tracked_state(g, p: Parameter, transform: str, q: float, p0: float):
    """Declare the state of ``p`` (and its box and drift parameters) in
    ``g``; returns ``(TrackedParameter, expression of p in the state)``."""
    lo, hi = (float(b) for b in p.bounds)
    unit = p.unit or ""
    qunit = f"({unit})/s**0.5" if unit else "1/s**0.5"
    spec = TrackedParameter(p.name, STATE_PREFIX + p.name, transform, lo, hi, unit, p0,
                            DRIFT_PREFIX + p.name, q, 1.0)
    z0 = float(spec.state_of(p0))
    slope0 = float(spec.slope(z0))
    spec = TrackedParameter(**{**spec.__dict__, "slope0": slope0})
    qmax = max(10.0 * q, hi - lo) if hi > lo else max(10.0 * q, 1.0)
    qsym = g.param(spec.drift_param, q, qunit, (0.0, qmax),
                   f"drift intensity of tracked parameter {p.name}")
    if transform == "none":
        expr_of = None
        zunit = unit
    else:
        los = g.param(f"{spec.state}.lower", lo, unit, (lo, lo), f"lower bound of {p.name}")
        his = g.param(f"{spec.state}.upper", hi, unit, (hi, hi), f"upper bound of {p.name}")
        expr_of = (los, his)
        zunit = ""
    z = g.state(spec.state, 0, unit=zunit, initial=z0, process_noise=qsym / slope0,
                description=f"tracked parameter {p.name} ({transform} coordinate)")
    expr = z if expr_of is None else _transform_expr(z, *expr_of, transform)
    return spec, expr


def _substitute(g, subs: dict) -> None:
    """Replace the tracked parameters in every expression of ``g``."""
    for el in g.elements.values():
        uses = any(s in subs for ex in el.expressions() for s in ex.free_symbols)
        el.substitute(subs)
        if uses and isinstance(el, (TwoPort, Source)):
            el.modulated = True     # its modulus or value now varies with a state
    for s in g.sensors.values():
        s.expr = s.expr.xreplace(subs)
        if isinstance(s.noise_std, sp.Basic):
            s.noise_std = s.noise_std.xreplace(subs)
    for ss in g.signal_states.values():
        ss.rhs = ss.rhs.xreplace(subs)
        if isinstance(ss.process_noise, sp.Basic):
            ss.process_noise = ss.process_noise.xreplace(subs)
    for nm, std in list(g.process_noise.items()):
        if isinstance(std, sp.Basic):
            g.process_noise[nm] = std.xreplace(subs)


def tracked_parameters(graph) -> tuple[TrackedParameter, ...]:
    """The :class:`TrackedParameter` of an augmented graph (empty for another)."""
    return tuple(graph.metadata.get("tracked", ()))


#: prefix of the inputs that replace scheduled parameters (``true.<p>``)
SCHEDULE_PREFIX = "true."


def scheduled(graph, names: Sequence[str]):
    """A copy of ``graph`` in which the parameters ``names`` are input signals.

    Each parameter ``p`` is replaced, in every law, modulus, source, sensor
    and noise expression, by the input ``true.<p>`` (same unit, its default
    the parameter's): a truth model in which a parameter changes during a
    record (a puncture at t = 30 s, a slow ramp of rolling resistance) is
    simulated by giving that input as a function of time. The elements that
    use it become modulated (MTF, MGY, modulated R/C/I laws; Karnopp,
    Margolis & Rosenberg 2012, ch. 4).

    Parameters
    ----------
    graph : BondGraph
        The original graph (not changed).
    names : sequence of str
        Parameters of ``graph`` (at least one, no repeats).

    Returns
    -------
    BondGraph
        Named ``<name>_scheduled``; ``metadata["scheduled"]`` is the tuple
        of the parameter names, in order.

    Raises
    ------
    ModelError
        No parameter, an unknown parameter (the known ones listed), a repeat.
    """
    names = list(names)
    if not names:
        raise ModelError("scheduled: no parameter to schedule (give at least one)")
    unknown = [n for n in names if n not in graph.params]
    if unknown:
        raise ModelError(f"scheduled: graph '{graph.name}' has no parameter "
                         f"{', '.join(map(repr, unknown))} (parameters: {', '.join(graph.params)})")
    if len(set(names)) != len(names):
        raise ModelError(f"scheduled: a parameter is named twice in {names}")
    g = graph.copy(f"{graph.name}_scheduled")
    subs = {}
    for name in names:
        p = g.params.pop(name)
        subs[p] = g.input(SCHEDULE_PREFIX + name, p.unit, p.default,
                          f"{p.name} as a function of time (scheduled truth)")
    _substitute(g, subs)
    g.metadata["scheduled"] = tuple(names)
    return g
