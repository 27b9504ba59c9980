"""Data-driven scales of the effects (smoothing widths, grids, boxes),
measured along the filtered states of a fit: flows of the 1-junctions, net
efforts on the inertias, source values, rates and powers, stored quantities, the
efforts and flows of the R elements, inputs and outputs."""

from __future__ import annotations

import numpy as np
import sympy as sp

from bondgraph.core.elements import C, I, One, R, Source, Zero
from bondgraph.core.equations import derive
from bondgraph.diagnose.effects import Scales
from bondgraph.diagnose.fit import Context, Fit, problem_for


def record_scales(t: np.ndarray) -> Scales:
    """The scales a record's sample times (N,) [s] give alone: its duration
    and median sample interval (1 where they cannot be measured); every
    per-element scale empty, where the effects fall back to 1."""
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    return Scales(duration=(float(t[-1] - t[0]) or 1.0) if t.size else 1.0, dt=dt)


def operating_scales(ctx: Context, fit: Fit) -> Scales:
    """Data-driven scales of the effects along the filtered states of ``fit``.

    Returns
    -------
    Scales
        RMS and maximum of every 1-junction's flow, RMS of the net effort on
        its inertia, least value and RMS of every 0-junction's effort, maximum,
        least value, largest rate and mean power of every source, maximum, RMS
        and peak of every stored quantity, RMS of every R's effort and flow,
        maximum of every input, RMS of every measured output, the record
        duration and median sample interval. A quantity that cannot be
        evaluated is left out (the effects fall back to 1).
    """
    ss = derive(fit.graph)
    model = fit.model
    t, u, y = problem_for(ctx, model).arrays
    X = fit.ukf.x_filt[:, 0, :]
    sc = record_scales(t)
    args = (list(ss.states), list(ss.inputs), list(ss.params))
    uT = u.T if u.size else np.zeros((0, t.size))

    def evaluate(expr):
        fn = sp.lambdify(args, expr, "numpy")
        with np.errstate(all="ignore"):   # a law outside its domain (sqrt of a level < 0): NaN
            vals = fn(X.T, uT, fit.theta)
        return np.broadcast_to(np.asarray(vals, dtype=float), t.shape)

    rates = _state_rates(model, X, u, fit.theta)
    for name, el in fit.graph.elements.items():
        try:
            _element_scales(sc, name, el, ss, evaluate, X, t, rates)
        except Exception:
            continue
    for i, o in enumerate(model.outputs):
        ok = np.isfinite(y[:, i])               # an output the record lacks: no scale
        sc.output_rms[o] = float(np.sqrt(np.mean(y[ok, i] ** 2))) if ok.any() else float("nan")
    for j, n in enumerate(model.inputs):
        sc.input_max[n] = float(np.nanmax(np.abs(u[:, j]))) if u.size else 0.0
    return sc


#: the least values of the scales (``effort_min``, ``source_min``) leave out
#: this share of the record's first samples (:func:`settled`)
SETTLE_SHARE = 0.01


def settled(n: int) -> int:
    """The first sample of ``n`` that the least values of the scales count:
    the filter's first samples carry its prior where the record does not
    observe a state directly, not the record (a user's oven with a
    thermocouple lag: the block's heat at sample 0 was the graph's default
    0, a block at 0 K, and the radiation law, which needs absolute
    temperatures above 100 K, was not scored at the step that needed it).
    :data:`SETTLE_SHARE` of the samples, at least 1 (none of fewer than
    100)."""
    return 0 if n < 100 else max(1, int(round(SETTLE_SHARE * n)))


def _state_rates(model, X: np.ndarray, u: np.ndarray, theta: np.ndarray) -> dict:
    """dx/dt (N,) of every state along the filtered states, by name (empty
    if f cannot be evaluated)."""
    try:
        F = model.f(X, u, theta)
    except Exception:
        return {}
    return {s: F[:, i] for i, s in enumerate(model.states)}


def _element_scales(sc: Scales, name: str, el, ss, evaluate, X, t, rates) -> None:
    """Fill the tables of ``sc`` that element ``el`` contributes to."""
    def rms(v):
        return float(np.sqrt(np.nanmean(np.asarray(v) ** 2)))

    if isinstance(el, One):
        v = evaluate(ss.variable(el.f))
        sc.flow_rms[name] = rms(v)
        sc.flow_max[name] = float(np.nanmax(np.abs(v)))
        forces = [rates[p.bond.other(p).element.state.name] for p in el.ports
                  if p.bond is not None and isinstance(p.bond.other(p).element, I)
                  and p.bond.other(p).element.state.name in rates]
        if forces:
            sc.force_rms[name] = max(rms(f) for f in forces)
    elif isinstance(el, Source):
        v = evaluate(ss.variable(el.value))
        sc.source_max[name] = float(np.nanmax(np.abs(v)))
        sc.source_min[name] = float(np.nanmin(v[settled(v.size):]))
        if t.size > 1:
            sc.source_rate[name] = float(np.nanmax(np.abs(np.diff(v) / np.diff(t))))
        sc.source_power[name] = float(np.nanmean(np.abs(evaluate(ss.variable(el.e * el.f)))))
    elif isinstance(el, C) and el.q in ss.states:
        q = X[:, ss.states.index(el.q)]
        sc.storage_max[name] = float(np.nanmax(np.abs(q)))
        sc.storage_rms[name] = rms(q)
        sc.storage_peak[name] = float(np.nanmax(q))
    elif isinstance(el, I) and el.p in ss.states:       # an inductor's flux linkage
        p = X[:, ss.states.index(el.p)]
        sc.storage_max[name] = float(np.nanmax(np.abs(p)))
        sc.storage_rms[name] = rms(p)
        sc.storage_peak[name] = float(np.nanmax(p))
    elif isinstance(el, Zero):
        v = evaluate(ss.variable(el.e))
        sc.effort_min[name] = float(np.nanmin(v[settled(v.size):]))
        sc.effort_rms[name] = rms(v)
    elif isinstance(el, R):
        sc.r_effort_rms[name] = rms(evaluate(ss.variable(el.e)))
        sc.r_flow_rms[name] = rms(evaluate(ss.variable(el.f)))
