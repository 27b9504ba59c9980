"""Output-error screen: candidates refitted with the declared physics by a
global search when the current model's free run is poor.

The score test and the line probe judge a candidate at the current
estimates. When the declared model cannot reproduce the record (its
free-run error is near the record's own spread), its fit has bent every
parameter towards a compromise in which the missing effect is invisible: a
linear drive fitted to a sign-blind counter's |ω| settles on a nearly
constant, always positive speed, where the rectifying sensor changes
nothing (the user CED graph: its score test 0.56, rank 22 of 39). The
effect shows only after the physical parameters move to another basin
together with it.

So when the filter predicts by the free run (the model has no process noise,
or the loop fits by the free-run likelihood with the process noise held at
its floor, :func:`~bondgraph.diagnose.fit.predicts_by_free_run`: the
output-error likelihood is then the model's own; a vehicle case with a
grade process noise ranked a rectifying sensor above its true offset by it)
and the free-run NRMSE of the current fit
(mean over the outputs of
RMS(error)/std(measured)) is at least :data:`SCREEN_LEVEL`, each additive
candidate with natural values (a full rectification, ...;
``Effect.natural_points``) is put at them in the step's probe model and the
physical parameters (the estimated ones that are not noise intensities) are
refitted by a global output-error search
(:func:`bondgraph.inference.output_error.swarm_output_error_fit`: a particle
swarm over their boxes, then least squares), and so is the current model
itself (every β = 0). With a Gaussian output error of unknown variance the
likelihood ratio of the two is n·log(SSE₀/SSE₁) (n measured samples; Ljung
1999, §7.4): where it exceeds the candidate's statistic it replaces it, and
the candidate's confirmation starts from the global fit's parameters
(``Candidate.profile``). The confirmation then decides by the loop's own
likelihood; the screen only finds the basin.

References
----------
Ljung, L. (1999). System Identification: Theory for the User, 2nd ed.
Prentice Hall. Kennedy, J., Eberhart, R. (1995). Particle swarm
optimization. Proc. ICNN'95, 1942-1948.
"""

from __future__ import annotations

import numpy as np

from bondgraph.core.deferred import chi2
from bondgraph.diagnose.effects import get_effect
from bondgraph.diagnose.fit import Context, Fit, noise_params, predicts_by_free_run, problem_for
from bondgraph.diagnose.metric import nrmse
from bondgraph.diagnose.result import Candidate
from bondgraph.errors import BondGraphError
from bondgraph.inference.options import most_substeps
from bondgraph.inference.output_error import OutputErrorOptions, swarm_output_error_fit

#: free-run NRMSE of the current fit from which the screen runs (0.8: the
#: model's free run explains less than about a third of the record's variance)
SCREEN_LEVEL = 0.8


def free_run_nrmse(fit: Fit, y: np.ndarray) -> float:
    """Mean over the outputs of RMS(free-run error)/std(measured) of ``fit``
    on its record's outputs ``y`` (N, n_y) (:func:`bondgraph.diagnose.metric.nrmse`);
    inf when the free run failed or is not finite where ``y`` is measured."""
    if fit.sim_y is None:
        return np.inf
    sim = np.asarray(fit.sim_y, float)
    if (np.isfinite(y) & ~np.isfinite(sim)).any():     # the free run failed on the way
        return np.inf
    with np.errstate(all="ignore"):
        return nrmse(y, sim)


def output_error_screen(ctx: Context, probe, fit: Fit, cands: list[Candidate]) -> None:
    """The screen of the module docstring, in place on ``cands`` (the score
    test's candidates of ``probe``, a :class:`bondgraph.diagnose.scoring.Probe`
    of ``fit``): nothing when the free run of ``fit`` is better than
    :data:`SCREEN_LEVEL` or no candidate has natural values. Logs one line
    per candidate it raises."""
    noise = noise_params(fit.model)
    if not predicts_by_free_run(ctx, problem_for(ctx, fit.model), fit.theta):
        return      # process noise: the output-error likelihood is not the model's
    y = probe.y
    level = free_run_nrmse(fit, y)
    todo = [c for c in cands if not c.failed and _natural(ctx, c)]
    if level < SCREEN_LEVEL or not todo:
        return
    phys = [n for n in fit.params if n not in noise]
    if not phys:
        return
    ctx.log(f"  the current model's free run is poor (NRMSE {level:.3g} >= {SCREEN_LEVEL}): "
            f"{len(todo)} candidate(s) with natural values refitted with "
            f"{', '.join(phys)} by a global output-error search")
    base = _global_fit(ctx, probe, phys, probe.base)
    if base is None:
        return
    n = int(np.isfinite(y).sum())
    for cand in todo:
        best = None
        for pt, theta in _natural_sets(ctx, probe, cand):
            r = _global_fit(ctx, probe, phys, theta)
            if r is not None and (best is None or r.cost < best[1].cost):
                best = (pt, r)
        if best is None or not best[1].cost < base.cost:
            continue
        lr = float(n * np.log(base.cost / max(best[1].cost, 1e-300)))
        if lr <= cand.statistic:
            continue
        cand.statistic, cand.p_value = lr, float(chi2.sf(lr, cand.dof))
        cand.screened = True
        cand.score = lr - 2 * cand.dof
        cand.values.update(best[0])
        cand.profile = {k: float(v) for k, v in best[1].estimates().items()}
        ctx.log(f"  {cand.label} at {best[0]}: free-run RMS "
                f"{_fmt(base.rmse)} -> {_fmt(best[1].rmse)} with the physical parameters "
                f"refitted (output-error LR {lr:.1f}); its confirmation starts there")


def _natural(ctx: Context, cand: Candidate) -> bool:
    return bool(get_effect(cand.effect, ctx.settings.effects).natural_points(cand.target))


def _natural_sets(ctx: Context, probe, cand: Candidate) -> list[tuple[dict, np.ndarray]]:
    """(natural point, θ of the probe model with the candidate there and
    every other β = 0) for each of the candidate's natural points."""
    eff = get_effect(cand.effect, ctx.settings.effects)
    est = [p.name for p in eff.params if p.estimated]
    js = [probe.model.param_index(col.param) for col in probe.cols
          if (col.effect, col.target) == (cand.effect, cand.target)]
    out = []
    for pt in eff.natural_points(cand.target):
        theta = probe.base.copy()
        theta[js] = [pt.get(n, 0.0) for n in est[:len(js)]]
        out.append(({k: float(v) for k, v in pt.items()}, theta))
    return out


def _global_fit(ctx: Context, probe, phys: list[str], theta: np.ndarray):
    """:func:`global_output_error` on the probe's model and problem."""
    return global_output_error(ctx, probe.model, probe.problem, phys, theta)


def global_output_error(ctx: Context, model, problem, phys: list[str], theta: np.ndarray):
    """:func:`swarm_output_error_fit` of ``phys`` of ``model`` on
    ``problem``'s record (its prior mean as the initial state) from
    ``theta`` (n_theta,): the filter's hold, RK4 with the filter's substeps
    (twice those for a ROS2 filter), the boxes of :func:`search_box`. An
    :class:`~bondgraph.inference.output_error.OutputErrorResult`, or None
    (logged) when the fit fails."""
    d = problem.disc
    sub = most_substeps(d) * (1 if d.method == "rk4" else 2)
    opts = OutputErrorOptions(hold=d.hold, substeps=max(sub, 1))
    t, u, y = problem.t, problem.u, problem.y
    try:
        return swarm_output_error_fit(model, t, u, y, phys, theta=theta, x0=problem.x0,
                                      options=opts, bounds=search_box(model, phys, theta))
    except (BondGraphError, ValueError) as exc:   # ValueError: least_squares at a bad start
        ctx.log(f"  global output-error fit failed: {str(exc).splitlines()[0]}")
        return None


def search_box(model, names: list[str], theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The declared boxes of ``names``; where a side is not finite, a factor
    100 either way of a positive value (within the declared side), else
    ±20 |value| (at least ±1e-6): a swarm needs a finite box."""
    lo, hi = (np.array(b, float) for b in model.bounds(names))
    v = np.asarray(theta, float)[model.param_indices(names)]
    pos = v > 0
    span = np.maximum(20 * np.abs(v), 1e-6)
    lo = np.where(np.isfinite(lo), lo, np.where(pos, v / 100, v - span))
    hi = np.where(np.isfinite(hi), hi, np.where(pos, v * 100, v + span))
    return lo, hi


def _fmt(v) -> str:
    return ", ".join(f"{float(x):.4g}" for x in np.atleast_1d(v))
