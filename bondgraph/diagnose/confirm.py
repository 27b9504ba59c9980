"""Confirmation of a candidate effect: build the real augmented graph, find
start values of its new parameters by batched grid searches, and refit all
parameters warm-started (Fisher scoring) from each start; the best refit is
the candidate's fit, and 2 (NLL₀ − NLL₁) its likelihood-ratio statistic
(Wilks 1938)."""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from types import SimpleNamespace

import numpy as np
import sympy as sp

from bondgraph.core.deferred import chi2
from bondgraph.diagnose.effects import Effect, Scales, get_effect
from bondgraph.diagnose.fit import (
    at_step,
    Context,
    Fit,
    bounds_around,
    criterion_for,
    evaluate_fit,
    fit_model,
    model_of,
    noise_params,
    problem_for,
    recommended_substeps,
    start_theta,
)
from bondgraph.diagnose.inference_calls import make_criterion, predicted_step_gain, run_ukf
from bondgraph.diagnose.result import Candidate
from bondgraph.errors import BondGraphError, NumericalError
from bondgraph.inference.optimize import minimize_batched
from bondgraph.inference.options import most_substeps
from bondgraph.numerics.model import Model


@dataclass
class Confirmation:
    """The refit of a candidate: the fit, the effect's parameter values by
    local name, the full names of its new estimated parameters, and whether
    the refit converged (``comparable``: False when the scoring stopped at
    its iteration limit even after :func:`continued`; its likelihood ratio is
    then not one the model reaches, and it never wins over a converged
    refit)."""

    fit: Fit
    values: dict
    new_params: list[str]
    comparable: bool = True
    #: fixed shape constants set away from their data-driven value by
    #: :func:`profiled_shape`, full name -> value (each one more degree of
    #: freedom of the likelihood-ratio test)
    shape: dict = field(default_factory=dict)

    @property
    def dof(self) -> int:
        """Degrees of freedom of the refit against the current model: its
        new estimated parameters and its profiled shape constants."""
        return len(self.new_params) + len(self.shape)


def confirm(ctx: Context, fit: Fit, cand: Candidate, scales: Scales,
            name: str) -> Confirmation | None:
    """Build ``fit``'s graph plus the candidate effect (named ``name``) and
    refit every parameter.

    Parameters
    ----------
    ctx : Context
    fit : Fit
        The current model's fit (warm start of the old parameters).
    cand : Candidate
        Its ``values`` start the new parameters.
    scales : Scales
    name : str
        Name of the augmented graph.

    Returns
    -------
    Confirmation or None
        None (logged) when the effect cannot be applied or the refit fails.
    """
    eff = get_effect(cand.effect, ctx.settings.effects)
    try:
        built = augmented_model(ctx, fit, cand, scales, name)
    except BondGraphError as exc:
        ctx.log(f"  confirmation of {cand.label} failed: {str(exc).splitlines()[0]}")
        return None
    if built is None:
        return None
    g, P, new, model = built
    start = {**fit.estimates(), **cand.profile}
    for n in fit.model.params:
        start.setdefault(n, float(fit.theta[fit.model.param_index(n)]))
    try:
        start = grid_refine(ctx, model, new, start)
        starts = ([start] + nested_starts(ctx, model, fit, cand, eff, P, start)
                  + score_line_starts(ctx, model, fit, cand, eff, P, start)
                  + natural_starts(eff, cand, P, new, start))
        # all parameters re-adjust (the nuisance ones absorbed part of the
        # missing effect): the confirmed fit is the candidate's final fit
        sub, f1 = stable_refit(ctx, g, list(fit.params) + new, starts, cand.label, model, fit)
    except BondGraphError as exc:
        ctx.log(f"  confirmation of {cand.label} failed: {str(exc).splitlines()[0]}")
        return None
    return _confirmed(sub, fit, cand, eff, scales, name, P, new, f1)


def augmented_model(ctx: Context, fit: Fit, cand: Candidate, scales: Scales,
                    name: str) -> tuple | None:
    """``(graph, P, new, model)``: :func:`_augmented` at the candidate's
    values and the graph's generated model, built once per candidate and
    current fit in this process (kept in ``ctx.cache`` until
    :func:`bondgraph.diagnose.runner.confirm_best` has confirmed its
    batch); None (logged) when the effect cannot be applied.

    Raises
    ------
    BondGraphError
        If the augmented graph cannot be derived (not kept: raised again
        the next time)."""
    key = ("augmented", id(fit), fit.nll, cand.label, name)
    if key in ctx.cache:
        return ctx.cache[key]
    eff = get_effect(cand.effect, ctx.settings.effects)
    built = _augmented(ctx, fit, cand, eff, scales, name)
    if built is not None:
        built = (*built, model_of(built[0]))
    ctx.cache[key] = built
    return built


def same_model_key(model: Model, P: dict, new: list[str], new_boxes: bool = True) -> tuple:
    """What a candidate's augmented model is, whatever its new parameters
    are called: the state equations f, the outputs h, the process noise
    and the parameters' boxes, its new estimated parameters ``new`` (full
    names, in order) renamed ``_new0``, ``_new1``, ... and its other
    parameters ``P`` (local name -> Parameter: shape constants, held
    values) replaced by their values. Two candidates with equal keys are
    one model (Karnopp, Margolis & Rosenberg: the equations, not the
    drawing, are the model): a term added to either of two R elements on
    one 1-junction whose laws the junction sums (the same law with the
    same box). Their refits from the same current fit are one refit
    (:func:`confirm_same`). With ``new_boxes`` False the new parameters'
    boxes are left out: a quadratic drag (c >= 0) at a junction and a
    quadratic law of either sign at a resistor on it are one likelihood,
    searched over different boxes (:func:`confirm_same` then reuses a refit
    only where it lies inside the other's box)."""
    ss = model.module.__state_space__
    by_name = {str(p): p for p in ss.params}
    fixed = {p.name: float(p.default) for p in P.values() if p.name not in new}
    rename = {by_name[n]: sp.Symbol(f"_new{i}") for i, n in enumerate(new) if n in by_name}
    rename.update({by_name[n]: sp.Float(v, 12) for n, v in fixed.items() if n in by_name})

    def text(e) -> str:
        return str(sp.sympify(e).xreplace(rename))

    boxes = tuple((str(rename.get(p, p)), tuple(float(b) for b in (p.bounds or ())))
                  for p in ss.params if p not in rename or (new_boxes and str(p) in new))
    return (tuple(str(x) for x in ss.states), tuple(str(u) for u in ss.inputs),
            tuple(text(e) for e in ss.f),
            tuple((o.name, text(o.expr), text(o.noise_std or 0)) for o in ss.outputs),
            tuple(text(q or 0) for q in ss.process_noise), tuple(sorted(boxes)))


def confirm_same(ctx: Context, fit: Fit, cand: Candidate, scales: Scales, name: str,
                 rep: Candidate, conf: Confirmation) -> Confirmation | None:
    """The confirmation of ``cand`` whose augmented model is ``rep``'s
    (:func:`same_model_key`) from ``rep``'s refit ``conf``: ``rep``'s
    estimates, std, initial states and noise levels under ``cand``'s names,
    evaluated once on ``cand``'s own graph (its filter run, free runs,
    residuals; what the accept rule then checks, its admissibility
    included, is ``cand``'s). Refitted in full (:func:`confirm`) when the
    refit profiled a shape constant, the names do not map, the refit is
    not one of ``cand``'s boxes (:func:`refit_inside`), or the evaluation
    does not reproduce ``rep``'s likelihood."""
    try:
        built = augmented_model(ctx, fit, cand, scales, name)
        rep_built = augmented_model(ctx, fit, rep, scales, name)
    except BondGraphError:
        return confirm(ctx, fit, cand, scales, name)
    if built is None or rep_built is None or conf.shape or len(built[2]) != len(rep_built[2]):
        return confirm(ctx, fit, cand, scales, name)
    g, P, new, model = built
    names = dict(zip(rep_built[2], new))          # rep's new name -> cand's
    back = {v: k for k, v in names.items()}
    f0 = conf.fit
    if not refit_inside(f0, model, names):
        ctx.log(f"  {cand.label}: {rep.label}'s refit lies on its box or outside "
                f"{cand.label}'s: refitted in full")
        return confirm(ctx, fit, cand, scales, name)
    theta = np.array(model.theta(), dtype=float)   # its shape constants: the key's values
    constants = {p.name for p in P.values()} - set(new)
    for i, n in enumerate(model.params):
        if back.get(n, n) in f0.model.params:
            theta[i] = f0.theta[f0.model.param_index(back.get(n, n))]
        elif n not in constants:
            return confirm(ctx, fit, cand, scales, name)
    pb = problem_for(ctx, model)
    params = [names.get(n, n) for n in f0.params]
    std = {names.get(k, k): v for k, v in f0.std.items()}
    try:
        fitted = pb.conditioned_on(x0={**pb.prior.estimated, **f0.x0_est},
                                   noise_levels=f0.noise_est)
        f1 = evaluate_fit(ctx, fitted, g, params, theta, f"confirming {cand.label}", std)
    except BondGraphError:
        return confirm(ctx, fit, cand, scales, name)
    if not abs(f1.nll - f0.nll) <= 1e-6 * max(1.0, abs(f0.nll)):
        ctx.log(f"  {cand.label}: its model evaluated at {rep.label}'s refit gives NLL "
                f"{f1.nll:.6g}, not {f0.nll:.6g}: refitted in full")
        return confirm(ctx, fit, cand, scales, name)
    f1.converged, f1.iterations = f0.converged, f0.iterations
    f1.flat = tuple(names.get(n, n) for n in f0.flat)
    f1.ridge = _renamed(f0.ridge, names)
    f1.x0_est, f1.noise_est = dict(f0.x0_est), dict(f0.noise_est)
    f1.at_bound = [names.get(n, n) for n in f0.at_bound]
    f1.warnings = list(f0.warnings)
    eff = get_effect(cand.effect, ctx.settings.effects)
    values = {p.name: float(f1.theta[model.param_index(P[p.name].name)])
              for p in eff.params if p.name in P}
    return Confirmation(f1, values, new, comparable=conf.comparable)


def refit_inside(f0: Fit, model: Model, names: dict) -> bool:
    """Whether the refit ``f0`` of one candidate is a refit of another
    whose augmented model (``model``) has the same likelihood
    (:func:`same_model_key` without the new parameters' boxes; ``names``:
    the first's new parameter names -> the other's): for each new
    parameter the two boxes are equal, or the refit converged with the
    value strictly inside its own box (not on a bound) and inside the
    other's, an interior optimum of the likelihood the other's search
    would stop at too. A quadratic drag c >= 0 at a junction refitted at
    c = 1.14 is the quadratic law of either sign at a resistor on it; a law
    of either sign refitted at β < 0 is not the drag's refit."""
    for n, m in names.items():
        lo0, hi0 = f0.model.bounds([n])
        lo1, hi1 = model.bounds([m])
        if lo0[0] == lo1[0] and hi0[0] == hi1[0]:
            continue
        v = float(f0.theta[f0.model.param_index(n)])
        if f0.converged is False or n in f0.at_bound or not lo1[0] < v < hi1[0]:
            return False
    return True


def _renamed(text: str, names: dict) -> str:
    """``text`` with each whole parameter name of ``names`` (old -> new)
    replaced (a same-model refit's ridge text in its own names)."""
    if not text or not names:
        return text or ""
    pat = "|".join(rf"(?<![\w.]){re.escape(n)}(?![\w.])"
                   for n in sorted(names, key=len, reverse=True))
    return re.sub(pat, lambda m: names[m.group(0)], text)


def _augmented(ctx: Context, fit: Fit, cand: Candidate, eff: Effect, scales: Scales, name: str,
               values: dict | None = None) -> tuple | None:
    """``(graph, P, new)``: ``fit``'s graph plus ``eff`` at the candidate's
    target (named ``name``) from ``values`` (default the candidate's;
    :func:`start_values`), its parameters by local name and the full names
    of the new estimated ones (the held ones not), boxes widened
    (:func:`widen_boxes`); None (logged) when the effect cannot be applied."""
    g = fit.graph.copy(name)
    try:
        P = eff.apply(g, cand.target, start_values(eff, cand, values), scales)
    except BondGraphError as exc:
        ctx.log(f"  cannot apply {cand.label}: {str(exc).splitlines()[0]}")
        return None
    new = [P[p.name].name for p in eff.params
           if p.estimated and p.name in P and p.name not in cand.held]
    widen_boxes(eff, P, eff.grid_span(fit.graph, cand.target, scales)
                if not eff.additive else {})
    return g, P, new


def _confirmed(ctx: Context, fit: Fit, cand: Candidate, eff: Effect, scales: Scales, name: str,
               P: dict, new: list[str], f1: Fit) -> Confirmation:
    """The :class:`Confirmation` of the refit ``f1`` (the effect's values
    by local name), its shape constants profiled (:func:`profiled_shape`)."""
    values = {p.name: float(f1.theta[f1.model.param_index(P[p.name].name)])
              for p in eff.params if p.name in P}
    conf = Confirmation(f1, values, new, comparable=f1.converged is not False)
    return profiled_shape(ctx, fit, cand, eff, scales, name, conf)


def confirm_held(ctx: Context, fit: Fit, cand: Candidate, conf: Confirmation, scales: Scales,
                 name: str) -> Confirmation | None:
    """Refit ``cand`` with its ``held`` parameters (local name -> value)
    fixed and its other new parameters and every estimated one free, from
    the estimates of ``conf`` (the candidate's refit with all its
    parameters, whose flat direction the held ones were), its profiled
    shape constants back at their data-driven values and profiled again
    (:func:`profiled_shape`).

    Parameters
    ----------
    ctx : Context
    fit : Fit
        The current model's fit.
    cand : Candidate
        A confirmed candidate with ``held`` set (:attr:`Candidate.held`).
    conf : Confirmation
        Its refit with every parameter estimated.
    scales : Scales
    name : str
        Name of the augmented graph.

    Returns
    -------
    Confirmation or None
        None (logged) when the effect cannot be applied or the refit fails.
    """
    eff = get_effect(cand.effect, ctx.settings.effects)
    base = eff.shape_values(fit.graph, cand.target, scales)
    vals = {**conf.values, **{p.name: base[p.name] for p in eff.params
                              if p.profile and p.name in base}}
    built = _augmented(ctx, fit, cand, eff, scales, name, vals)
    if built is None:
        return None
    g, P, new = built
    held = {P[k].name for k in cand.held if k in P}
    start = {k: v for k, v in conf.fit.estimates().items() if k not in held}
    try:
        sub, f1 = stable_refit(ctx, g, list(fit.params) + new, [start, *nested_start(fit, P, new)],
                               cand.label, model_of(g), fit)
    except BondGraphError as exc:
        ctx.log(f"  confirmation of {cand.label} failed: {str(exc).splitlines()[0]}")
        return None
    return _confirmed(sub, fit, cand, eff, scales, name, P, new, f1)


def nested_start(fit: Fit, P: dict, new: list[str]) -> list[dict]:
    """The held refit's second start (:func:`confirm_held`): the current
    model's estimates (``fit``) with the new parameters ``new`` (full
    names; ``P`` the effect's parameters by local name) at 0, where the
    additive effect vanishes, so that the refit can end no worse than the
    model without it; empty when a new parameter's box excludes 0.

    The full refit's estimates, the first start, lie on the ridge the held
    terms made with the current model's: on a user's EMPS graph after a
    force offset and Coulomb friction, the direction-dependent friction's
    Coulomb half-difference had run to −41 N along the offset, and the
    refit with it held at 0 started 41 N off in force; it climbed to a
    viscous half-difference of +645 N s/m, a law RK4(1) no longer steps
    stably, and was refused as not comparable (LR −1.2e5), where the
    published asymmetric model's is −37 N s/m."""
    box = {p.name: p.bounds for p in P.values()}
    if any(box.get(n) is not None and not box[n][0] <= 0.0 <= box[n][1] for n in new):
        return []
    return [{**fit.estimates(), **{n: 0.0 for n in new}}]


def profiled_shape(ctx: Context, fit: Fit, cand: Candidate, eff: Effect, scales: Scales,
                   name: str, conf: Confirmation) -> Confirmation:
    """The confirmation with the effect's profiled shape constants
    (:attr:`EffectParam.profile`, e.g. the tanh width of a Coulomb law) at
    the value the record prefers: every parameter refitted (from ``conf``'s
    estimates, continued until converged) at each factor of the data-driven
    value, and the best width kept when its likelihood-ratio test against
    the data-driven one (1 degree of freedom) passes the loop's significance
    level; the kept width is then counted in :attr:`Confirmation.dof`.

    A smoothing width is no physics: it is the resolution at which the law
    reverses, and a record with many reversals can tell it. At 2 % of the
    RMS speed a geared motor's load friction reversed too softly; the refit
    left a misfit at every reversal that the loop's next steps absorbed
    with a spurious sensor gain (Coulomb friction in a record sampled at
    100 Hz: a 0.2 % width alone reached a lower held-out error than 2 % with
    four more effects). A law softer than the data-driven one is tried too:
    a piston's seal friction reversing over 4 % of the RMS speed, fitted at
    2 %, left the Coulomb level 7 % low and the damping 15 % high, and the
    tracker of the leakage on that model raised a false alarm and found
    the leak's change 1.9 s late (at x3: the level 3 % high, the change
    found 12 ms after it happened).

    Parameters
    ----------
    ctx : Context
    fit : Fit
        The current model's fit.
    cand : Candidate
    eff : Effect
        The candidate's effect.
    scales : Scales
    name : str
        Name of the augmented graph.
    conf : Confirmation
        The refit at the data-driven shape.

    Returns
    -------
    Confirmation
        ``conf``, or the refit at the kept shape (``shape`` says its value);
        ``conf`` when the effect has no profiled constant, its refit did not
        converge, or no other shape passes.
    """
    shaped = [p for p in eff.params if p.profile and p.name in conf.values]
    if not shaped or not conf.comparable or not np.isfinite(conf.fit.nll):
        return conf
    names = list(fit.params) + list(conf.new_params)
    built = _width_models(ctx, fit, cand, eff, scales, name, conf, shaped)
    if 1.0 not in built or len(built) < 2:
        return conf
    sub, n = _profile_context(ctx, built, names, conf, cand.label)
    fits, tried = _width_refits(ctx, sub, built, names, conf, cand.label)
    ok = {k: f for k, f in fits.items() if f.converged is not False and np.isfinite(f.nll)}
    step = "" if n is None else f" at {n} substeps"
    if 1.0 not in ok or len(ok) < 2:
        ctx.log(f"  {cand.label}: {', '.join(p.name for p in shaped)} profiled{step} "
                f"({'; '.join(tried)}): the data-driven value kept")
        return conf
    k_best = min(ok, key=lambda k: ok[k].nll)
    lr = 2.0 * (ok[1.0].nll - ok[k_best].nll)
    keep = k_best != 1.0 and chi2.sf(lr, 1) < ctx.settings.accept.significance
    ctx.log(f"  {cand.label}: {', '.join(p.name for p in shaped)} profiled{step} "
            f"({'; '.join(tried)}): "
            + (f"x{k_best:g} kept (LR {lr:.1f} on 1 degree of freedom)" if keep
               else "the data-driven value kept"))
    return _kept(ctx, sub, built[k_best], ok[k_best], names, conf, cand, eff, shaped,
                 k_best) if keep else conf


def _kept(ctx: Context, sub: Context, model_at: tuple, f: Fit, names: list,
          conf: Confirmation, cand: Candidate, eff: Effect, shaped: list,
          k_best: float) -> Confirmation:
    """The confirmation at the kept width ``k_best`` (``model_at`` its
    (graph, model, P), ``f`` its refit in ``sub``), refitted at the loop's
    own step when ``sub`` had a finer one (where the other candidates are
    judged) and the loop's step keeps an RK4 filter stable for the kept law
    there (:func:`stable_context`; else ``f`` stays, at ``sub``'s step: a
    narrower tanh is a stiffer law, and a user's mass whose friction
    reverses over a third of the data-driven width, sampled at 20 Hz, was
    refitted at RK4(1) with its mode at z = −7.8); ``conf`` when that refit
    fails."""
    g, model, P = model_at
    if sub is not ctx and _unstable_at(ctx, model, names, f, f"{cand.label} at x{k_best:g}"):
        ctx.log(f"  {cand.label}: the loop's step is unstable for the law at x{k_best:g} width: "
                f"its refit at {_step_name(sub.problem.disc)} kept")
    elif sub is not ctx:    # back at the loop's step, where the others are judged
        try:
            f = continued(ctx, g, fit_model(
                ctx, g, names, f.estimates(), f"confirming {cand.label} at x{k_best:g} width",
                model=model, iterations=ctx.settings.search.confirm_iterations,
                tolerance=ctx.settings.search.confirm_tolerance), cand.label)
        except BondGraphError as exc:
            ctx.log(f"  {cand.label}: the refit at x{k_best:g} width at the loop's step "
                    f"failed ({str(exc).splitlines()[0]}): the data-driven value kept")
            return conf
    values = {p.name: float(f.theta[f.model.param_index(P[p.name].name)])
              for p in eff.params if p.name in P}
    return Confirmation(f, values, list(conf.new_params), f.converged is not False,
                        {P[p.name].name: values[p.name] for p in shaped})


def _unstable_at(ctx: Context, model: Model, names: list, f: Fit, label: str) -> bool:
    """Whether an RK4 filter at the loop's step is unstable for ``model`` at
    ``f``'s estimates (:func:`stable_context`)."""
    try:
        sub, _ = stable_context(ctx, model, names, f.estimates(), label, "the refit",
                                most_substeps(ctx.problem.disc), states_of(f, model))
    except NumericalError:
        return True
    return sub is not ctx


def _width_models(ctx: Context, fit: Fit, cand: Candidate, eff: Effect, scales: Scales,
                  name: str, conf: Confirmation, shaped: list) -> dict:
    """The augmented graph, its model and its applied parameters at each
    width factor of ``shaped`` (factor -> (graph, model, P)): ``conf``'s own
    at 1, the others started from ``conf``'s values; a factor whose graph
    cannot be built is logged and left out."""
    base = eff.shape_values(fit.graph, cand.target, scales)
    factors = sorted({k for p in shaped for k in p.profile}, reverse=True)
    g1 = conf.fit.graph         # the data-driven width: the confirmation's own model
    built = {1.0: (g1, conf.fit.model, {p.name: g1.params[eff.pname(cand.target, p.name)]
                                        for p in eff.params
                                        if eff.pname(cand.target, p.name) in g1.params})}
    for k in factors:
        g = fit.graph.copy(name)
        try:
            vals = {**conf.values, **{p.name: base[p.name] * k for p in shaped}}
            P = eff.apply(g, cand.target, start_values(eff, cand, vals), scales)
            widen_boxes(eff, P, eff.grid_span(fit.graph, cand.target, scales)
                        if not eff.additive else {})
            built[k] = (g, model_of(g), P)
        except BondGraphError as exc:
            ctx.log(f"  {cand.label}: width x{k:g} cannot be built: {str(exc).splitlines()[0]}")
    return built


def _profile_context(ctx: Context, built: dict, names: list, conf: Confirmation,
                     label: str) -> tuple:
    """``(context, substeps)``: the loop's context with the substeps the
    stiffest law of the profile needs at ``conf``'s estimates (its
    discretisation check, :func:`~bondgraph.diagnose.fit.recommended_substeps`),
    or ``(ctx, None)`` when the loop's own suffice. The law's stiffness is
    monotone in the factor, so the stiffest is at an end of the ladder: the
    smallest factor of a tanh width (the narrowest law), the largest of an
    end stop's stiffness (``kstop`` x1, its softer stops below); both ends
    are checked. At the loop's step the stiffest law's likelihood is its
    discretisation's, and the shape the record asks for loses."""
    found = [n for k in sorted({min(built), max(built)})
             if (n := _substeps_at(ctx, built[k][1], names, conf, f"{label} at x{k:g}"))
             is not None]
    if not found:
        return ctx, None
    n = max(found)
    return at_step(ctx, replace(ctx.problem.disc, substeps=n)), n


def _substeps_at(ctx: Context, model: Model, names: list, conf: Confirmation,
                 what: str) -> int | None:
    """The substeps ``model`` needs at ``conf``'s estimates beyond the
    loop's own (:func:`~bondgraph.diagnose.fit.recommended_substeps`), or
    None when the loop's suffice or its filter fails there."""
    try:
        # the filter's run at conf's estimates is all the check reads (its
        # innovation std): no free runs, no validation record
        pb = problem_for(ctx, model)
        theta = start_theta(ctx, pb, [p for p in names if p in model.params],
                            conf.fit.estimates(), what)
        res = run_ukf(pb, theta[None, :], store=True)
        return (recommended_substeps(ctx, SimpleNamespace(model=model, theta=theta, ukf=res)).n
                if np.isfinite(res.nll[0]) else None)
    except BondGraphError:
        return None


def _width_refits(ctx: Context, sub: Context, built: dict, names: list, conf: Confirmation,
                  label: str) -> tuple[dict, list]:
    """Every parameter refitted in ``sub`` at each width of ``built``, from
    ``conf``'s estimates and continued until converged (``conf`` itself at
    the data-driven width when ``sub`` is the loop's context): factor ->
    Fit, and one text per width for the log. From the data-driven width
    outwards on each side, the wider ones (x3) and the narrower ones (x0.3,
    then x0.1); on a side, a width further out is not refitted once a
    converged refit did not lower the lowest NLL so far (x1's included), or
    lowered it by less than :data:`FLAT_PROFILE` of what the keep test
    needs (the profile is flat there): a
    width beyond the one the record prefers fits it worse still (a refit is
    the costliest part of a confirmation, the finer substeps of the
    narrowest law make it costlier; on a user's four-mass chain the
    profiles took 69 s of a 96 s loop step). Each side has its own stop:
    a refit on one side says nothing of the other (a mass-spring-damper
    whose Coulomb friction reverses at a fifth of the data-driven width,
    sampled at 100 Hz: x3 NLL 41346 below x1's 44329, x0.3 above both at
    49600, the filter's two substeps not resolving the sharper law)."""
    fits, tried = {}, []

    def refit(k: float, bar: float = np.inf) -> Fit | None:
        g, model, _ = built[k]
        reach = ""
        if k == 1.0 and sub is ctx:
            fits[k] = conf.fit
        else:
            try:
                f = fit_model(sub, g, names, conf.fit.estimates(),
                              f"confirming {label} at x{k:g} width", model=model,
                              iterations=ctx.settings.search.confirm_iterations,
                              tolerance=ctx.settings.search.confirm_tolerance)
                reach = _out_of_reach(sub, f, bar)
                fits[k] = f if reach else continued(sub, g, f, label)
            except BondGraphError as exc:
                tried.append(f"x{k:g} failed ({str(exc).splitlines()[0]})")
                return None
        f = fits[k]
        tried.append(f"x{k:g} NLL {f.nll:.2f}" + ("" if f.converged is not False
                                                  else f" (not converged{reach})"))
        return f if f.converged is not False and np.isfinite(f.nll) else None

    one = refit(1.0) if 1.0 in built else None
    start = one.nll if one is not None else np.inf
    flat = FLAT_PROFILE * float(chi2.isf(ctx.settings.accept.significance, 1)) / 2.0
    for side in (sorted(k for k in built if k > 1.0),
                 sorted((k for k in built if k < 1.0), reverse=True)):
        best = start
        for i, k in enumerate(side):
            f = refit(k, best)
            if f is None:
                continue
            if f.nll >= best - flat and i + 1 < len(side):
                why = ("did not lower the NLL" if f.nll >= best else
                       f"lowered the NLL by {best - f.nll:.2g} only: the profile is flat there")
                tried.append(", ".join(f"x{n:g}" for n in side[i + 1:])
                             + f" not refitted (x{k:g} {why})")
                break
            best = min(best, f.nll)
    return fits, tried


#: a width's refit that lowers the lowest NLL of its side by less than this
#: fraction of the half critical value of the width's likelihood-ratio test
#: (χ²(1) at ``settings.accept.significance``: 0.33 nats at 0.01) ends its
#: side: the profile is flat there, and the next width, a factor 3 further
#: out, would have to gain ten times as much for the keep test to notice (a
#: user's fan motor: Coulomb friction at x3, x0.3 and x0.1 within 0.1 nats
#: of x1, three candidates, each refit 3-5 s at RK4(8))
FLAT_PROFILE = 0.1


#: a width's refit that stopped at its iteration limit is continued only if
#: this many of the scoring steps it would take next, each gaining what one
#: full step predicts from where it stopped, could bring it below the best
#: width's NLL so far (:func:`_out_of_reach`)
WIDTH_REACH_STEPS = 20


def _out_of_reach(ctx: Context, fit: Fit, bar: float) -> str:
    """A clause when ``fit`` (a width's refit, not converged) sits above
    ``bar``, the best width's NLL so far on its side, by more than
    :data:`WIDTH_REACH_STEPS` times the NLL decrease one full scoring step
    from it predicts (:func:`~bondgraph.diagnose.inference_calls.predicted_step_gain`,
    one batched run): continuing it cannot make it the kept width, and its
    continuation is the costliest part of a profile (a user's CVT
    driveline: the Coulomb law at three times its width, 71 nats above x1, was
    continued through 120 scoring iterations and L-BFGS-B's 1020 sets).
    "" when it converged, ``bar`` is not finite, it is within reach or the
    prediction fails."""
    if fit.converged is not False or not np.isfinite(bar) or not np.isfinite(fit.nll) \
            or fit.nll <= bar:
        return ""
    model = fit.model
    idx = [model.param_index(n) for n in fit.params]
    try:
        gain = predicted_step_gain(problem_for(ctx, model), fit.theta, idx,
                                   model.bounds(list(fit.params)))
    except (BondGraphError, FloatingPointError, np.linalg.LinAlgError, ValueError):
        return ""
    if not np.isfinite(gain) or fit.nll - WIDTH_REACH_STEPS * max(gain, 0.0) <= bar:
        return ""
    return (f"; {fit.nll - bar:.3g} nats above the best width, its next scoring step "
            f"predicts {gain:.3g}: not continued")


def stable_refit(ctx: Context, graph, names: list, starts: list, label: str,
                 model: Model, current: Fit | None = None) -> tuple[Context, Fit]:
    """``(context, fit)``: the confirmation's refit of ``names`` from each of
    ``starts`` (:func:`chosen_refit`) in ``ctx``, or, where an RK4 filter at
    the loop's substeps is unstable for ``model`` at the first start or at
    the refit (:func:`stable_context`; a refit that has not converged is
    checked before it is continued, :func:`_unstable_unconverged`), in a
    context with the substeps that make it stable, the refit done (again)
    there from the same starts, once:
    a refit whose law is unstable again at its end (stiffer still), or
    needs more than :data:`STABLE_FACTOR` times the loop's substeps there,
    is returned not converged, so not comparable (on that record a Padé
    input delay shrinking towards none chased RK4(2), (3), (4) refit after
    refit, and was refused for its free run all the same). Once more where
    that refit ended with an estimated parameter on its box: the chase ends
    there (a user's closed-loop EMPS graph with process noise: the Dahl
    friction's rest stiffness ran to the top of its box at RK4(4), which
    needed RK4(6); refused as not comparable, its held-out error 0.052
    against the accepted Stribeck law's 0.088). The first start
    is judged along ``current``'s filtered states (the current model's fit:
    an additive effect keeps its states), the refit along its own
    (:func:`states_of`), else along the filter's by ROS2.

    The candidate brings the stiff law, so the step the loop chose for the
    model without it need not hold for it: at an unstable step the NLL is
    rough in the parameters and the scoring stops on it (a user's EMPS
    graph at 1 kHz: a Stribeck refit at RK4(1) ended 17 000 nats above the
    model without the effect, "converged", after 111 s). The refit is
    judged against the current model's NLL at the loop's step, as an
    accepted fit refitted at the substeps its check asks for is
    (:func:`bondgraph.diagnose.runner.fit_after_discretisation_check`,
    which then gives the loop that step).

    Raises
    ------
    NumericalError
        At the first start the law needs more than :data:`STABLE_FACTOR`
        times the loop's substeps (its fast mode is beyond what the
        record's sampling resolves: that Stribeck law's start needed
        RK4(16), and refitted at the stable steps its level rose until
        it needed RK4(64), 780 s, and its model failed the held-out
        record); the caller reports the confirmation as failed.
    """
    base = most_substeps(ctx.problem.disc)
    sub, why = stable_context(ctx, model, names, starts[0], label, "its start", base,
                              None if current is None else states_of(current, model))
    if why:
        ctx.log(f"  {label}: {why}: refitted with {_step_name(sub.problem.disc)}")
    f1 = None
    again, boxed = sub is ctx, True     # refitted at a stabler step once (twice: boxed)
    while True:
        fits = refits_from_starts(sub, graph, names, starts, label, model)
        early = _unstable_unconverged(sub, model, names, fits, label, base) if again else None
        if early is not None:   # not continued on the step's rough likelihood
            nxt, why = early
            if nxt is None:
                f1 = _beyond_the_limit(sub, model, names, fits, min(fits, key=_nll_key), label,
                                       why, base)
                break
            ctx.log(f"  {label}: {why} (not converged there): refitted with "
                    f"{_step_name(nxt.problem.disc)}")
            sub, again = nxt, False
            continue
        f1, nxt = _after_refit(sub, graph, model, names, fits, label, base, again, boxed)
        if nxt is None:
            break
        boxed = boxed and again     # after the refit with an estimate on its box, no more
        sub, again = nxt, False
    if sub is not ctx:
        f1.step = sub.problem.disc      # what is computed again at the fit is computed there
    return sub, f1


def _after_refit(sub: Context, graph, model: Model, names: list, fits: list, label: str,
                 base: int, again: bool, boxed: bool) -> tuple[Fit, Context | None]:
    """``(fit, context or None)``: :func:`stable_refit`'s chosen refit among
    ``fits`` (made in ``sub``) and, where its law is unstable at ``sub``'s
    step, the context with the stable step to refit in: when this was the
    first refit (``again``), or, once (``boxed``), when the refit ended with
    an estimated parameter on its box; else None, the refit not comparable
    (logged), as where no step within the limit is stable
    (:func:`_beyond_the_limit`)."""
    f1 = chosen_refit(sub, graph, fits, label)
    try:
        nxt, why = stable_context(sub, model, names, f1.estimates(), label, "its refit",
                                  base, states_of(f1, model))
    except NumericalError as exc:
        nxt, why = None, str(exc)
    if nxt is sub:
        return f1, None
    if nxt is None:
        return _beyond_the_limit(sub, model, names, fits, f1, label, why, base), None
    on_box = [n for n in f1.at_bound if n in names]
    if not again and not (boxed and on_box):    # the law stiffened again: not chased further
        sub.log(f"  {label}: {why}: not comparable")
        f1.converged = False
        return f1, None
    if not again:
        why += f", with {', '.join(on_box)} on its box, where the law stiffens no further"
    sub.log(f"  {label}: {why}: refitted with {_step_name(nxt.problem.disc)}")
    return f1, nxt


#: a later start's scoring is ended where its iterate lies within this many
#: Cramér-Rao std of an earlier start's converged optimum in every estimated
#: parameter (:func:`refits_from_starts`)
MERGE_STD = 1.0
#: ... and its NLL is not below that optimum's by more than this [nats]
MERGE_NATS = 0.1


def refits_from_starts(ctx: Context, graph, names: list, starts: list, label: str,
                       model: Model) -> list[Fit]:
    """The confirmation's refits of ``names`` from each of ``starts`` in
    turn (``settings.search.confirm_iterations``, ``confirm_tolerance``),
    less those that run into an earlier start's optimum: a later start's
    scoring is ended once its iterate lies within :data:`MERGE_STD`
    Cramér-Rao std of an earlier start's converged estimates in every
    estimated parameter, with an NLL not below theirs by more than
    :data:`MERGE_NATS` nats, and that refit is left out (logged): the
    scoring from there ends where the earlier one did, whose NLL, within
    about half a nat per parameter of the iterate's, is the lower. A
    confirmation refits from up to four starts, and on a user's fan motor
    the three starts of a Coulomb friction's refit all converged to within
    1e-4 of one another, 17 iterations of 0.7 s each."""
    fits: list[Fit] = []
    origin: list[int] = []          # the start of each refit kept
    for j, s0 in enumerate(starts):
        hit: list = []
        f = fit_model(ctx, graph, names, s0, f"confirming {label}", model=model,
                      iterations=ctx.settings.search.confirm_iterations,
                      tolerance=ctx.settings.search.confirm_tolerance,
                      stop=_merging(fits, names, model, hit) if fits else None)
        if hit:
            ctx.log(f"  {label}: the refit from start {j + 1} reached the optimum of start "
                    f"{origin[hit[0]] + 1} (within {MERGE_STD:g} Cramér-Rao std of each "
                    f"estimate, after {f.iterations} iterations): not continued")
            continue
        fits.append(f)
        origin.append(j)
    return fits


def _merging(fits: list[Fit], names: list, model: Model, hit: list):
    """``stop(estimand, nll)`` of :func:`refits_from_starts`: True (the
    index of the start reached appended to ``hit``) where the iterate is
    within :data:`MERGE_STD` std of a converged fit of ``fits`` with all
    its std known; None when there is no such fit."""
    idx = [model.param_index(n) for n in names]
    refs = []
    for k, f in enumerate(fits):
        sd = [(f.std or {}).get(n) for n in names]
        if f.converged is False or not np.isfinite(f.nll) or any(
                s is None or not np.isfinite(s) or s <= 0 for s in sd):
            continue
        refs.append((k, f.nll, np.asarray(f.theta, float)[idx], np.array(sd, float)))
    if not refs:
        return None

    def stop(est, nll: float) -> bool:
        th = np.asarray(est.theta, float)[idx]
        for k, nll_r, th_r, sd_r in refs:
            if nll >= nll_r - MERGE_NATS and np.all(np.abs(th - th_r) <= MERGE_STD * sd_r):
                hit.append(k)
                return True
        return False
    return stop


def _beyond_the_limit(ctx: Context, model: Model, names: list, fits: list, best: Fit,
                      label: str, why: str, base: int) -> Fit:
    """``best``, the chosen refit among ``fits``, ended where no RK4 step up
    to :data:`STABLE_FACTOR` times ``base`` is stable (``why``): another
    start's converged refit that the step of ``ctx`` keeps stable
    (:func:`_stable_alternative`), else ``best`` marked not converged, so
    not comparable (logged)."""
    alt = _stable_alternative(ctx, model, names, fits, best, label, why, base)
    if alt is not None:
        return alt
    ctx.log(f"  {label}: {why}: not comparable")
    best.converged = False
    return best


def _stable_alternative(ctx: Context, model: Model, names: list, fits: list, best: Fit,
                        label: str, why: str, base: int) -> Fit | None:
    """The converged refit of lowest NLL among ``fits`` (one per start) other
    than ``best``, whose end the step of ``ctx`` keeps stable
    (:func:`stable_context` along its own states), when ``best`` ended where
    no step up to :data:`STABLE_FACTOR` times ``base`` is (``why``: that
    verdict); None when there is none (logged when there is). The
    likelihood at an unstable step is the step's, not the model's: a refit
    that ran into such a law may show an NLL no sound refit can reach, and a
    refit from another start that stayed where the step is sound is the
    comparable one (a user's EMPS graph: the held direction-dependent
    friction from the full refit's estimates ran to a viscous half-difference
    of +645 N s/m, where RK4(1) needs 48 substeps; from where the effect
    vanishes it converged at −38)."""
    done = sorted((f for f in fits if f is not best and f.converged is not False
                   and np.isfinite(f.nll)), key=lambda f: f.nll)
    for f in done:
        try:
            nxt, _ = stable_context(ctx, model, names, f.estimates(), label, "its refit", base,
                                    states_of(f, model))
        except NumericalError:
            continue
        if nxt is ctx:
            ctx.log(f"  {label}: the refit from the best start is not comparable ({why}); the "
                    f"converged refit from another start, stable at "
                    f"{_step_name(ctx.problem.disc)} (NLL {f.nll:.2f} against {best.nll:.2f}), "
                    f"is judged instead")
            return f
    return None


#: the most substeps a confirmation's refit takes to keep an RK4 filter
#: stable for the candidate's law, as a multiple of the loop's own
#: (:func:`stable_refit`)
STABLE_FACTOR = 8


def _step_name(disc) -> str:
    """``"rk4(4)"``: a discretisation's method and substeps, for log lines."""
    return disc.describe().split(",")[0]


def _nll_key(fit: Fit) -> float:
    """A fit's NLL for ``min``, a non-finite one last."""
    return fit.nll if np.isfinite(fit.nll) else np.inf


def _unstable_unconverged(ctx: Context, model: Model, names: list, fits: list, label: str,
                          base: int) -> tuple | None:
    """``(context, why)`` when the best of a confirmation's ``fits`` did not
    converge and the loop's RK4 step is unstable for the law at it
    (:func:`stable_context` along its own states): continuing it there
    (:func:`continued`, up to three more rounds and L-BFGS-B) would crawl on
    the step's rough likelihood, so the refit moves to the stable step
    first (a user's EMPS graph at 100 Hz: a square-root damper continued to
    80 iterations at RK4(1), then found unstable and refitted at RK4(8)).
    ``(None, why)`` where no step up to :data:`STABLE_FACTOR` times ``base``
    is stable there; None where it converged, is stable, or cannot be
    checked."""
    best = min(fits, key=_nll_key)
    if best.converged is not False or not np.isfinite(best.nll):
        return None
    try:
        nxt, why = stable_context(ctx, model, names, best.estimates(), label, "its refit",
                                  base, states_of(best, model))
    except NumericalError as exc:
        return None, str(exc)
    return None if nxt is ctx else (nxt, why)


def states_of(fit: Fit, model: Model) -> np.ndarray | None:
    """``fit``'s filtered state estimates (N, n_x) where they are finite and
    ``model`` has as many states (an additive effect's model has the
    current one's), else None."""
    x = getattr(getattr(fit, "ukf", None), "x_filt", None)
    if x is None or np.ndim(x) != 3 or x.shape[2] != len(model.states):
        return None
    x = np.asarray(x[:, 0, :], float)
    return x if np.isfinite(x).all() else None


def stable_context(ctx: Context, model: Model, names: list, values: dict, label: str,
                   where: str, base: int, states=None) -> tuple[Context, str]:
    """``(context, why)``: ``ctx`` with the fewest substeps at which its RK4
    filter keeps ``model``'s modes inside the stability region along the
    filter's state estimates at ``values`` (:meth:`Problem.rk4_stable_substeps`)
    and a clause saying why; ``(ctx, "")`` when its own are stable, its
    method is ROS2, or the check cannot be made there. ``states`` (N, n_x):
    where the filter's states go (a fit's own estimates, :func:`states_of`);
    default the filter's by ROS2 at ``values`` (one more filter pass).

    Raises
    ------
    NumericalError
        No substeps up to 64, or none up to :data:`STABLE_FACTOR` times
        ``base`` (the loop's), are stable there.
    """
    try:
        pb = problem_for(ctx, model)
        theta = start_theta(ctx, pb, [p for p in names if p in model.params], values, label)
        n = pb.rk4_stable_substeps(theta, states)
    except BondGraphError:
        return ctx, ""
    if n is None:
        return ctx, ""
    unstable = (f"the filter's {_step_name(pb.disc)} is unstable at {where} (a fast mode of "
                f"the law outside RK4's stability region")
    if n == 0 or n > STABLE_FACTOR * base:
        need = "no RK4 up to 64 substeps is stable" if n == 0 else f"it needs rk4({n})"
        raise NumericalError(
            f"{unstable}) and {need}, more than {STABLE_FACTOR} times the loop's substeps: the "
            f"law is stiffer than the record's sampling resolves (--method ros2 steps it stably)")
    return at_step(ctx, replace(ctx.problem.disc, substeps=n, refine=())), (
        f"{unstable}; stable from rk4({n}))")


def chosen_refit(ctx: Context, graph, fits: list[Fit], label: str) -> Fit:
    """The confirmation's refit among ``fits`` (one per start): the lowest
    NLL, continued until it converges (:func:`continued`); if it still has
    not, the converged refit with the lowest NLL from another start, when
    there is one (logged): a refit that crawls along a flat ridge of the
    likelihood is not comparable, another start's converged optimum is (on
    a user's CED graph the rectifying sensor's refit from the output-error
    screen's start crawled for 120 iterations, LR 922 and rising, and the
    effect was refused as not comparable)."""
    best = min(fits, key=_nll_key)
    f1 = continued(ctx, graph, best, label)
    if f1.converged is not False:
        return f1
    done = [f for f in fits if f is not best and f.converged is not False and np.isfinite(f.nll)]
    if not done:
        return f1
    alt = min(done, key=lambda f: f.nll)
    ctx.log(f"  {label}: the refit from the best start did not converge (NLL {f1.nll:.2f}); "
            f"the converged refit from another start (NLL {alt.nll:.2f}) is judged instead")
    return alt


#: continuations of a confirmation refit that stopped at its iteration limit
CONTINUATIONS = 2
#: a continuation that converges within this many nats above the NLL it
#: started from has converged there (:func:`continued`)
CONTINUE_SLACK = 0.01


def continued(ctx: Context, graph, fit: Fit, label: str) -> Fit:
    """``fit`` if its scoring converged (or it was not fitted by scoring);
    else the scoring continued from where it stopped, up to
    :data:`CONTINUATIONS` more times ``confirm_iterations`` iterations, until
    it converges; the better of the two fits is kept (a continuation never
    raises the NLL it started from), except that a continuation that
    converges within :data:`CONTINUE_SLACK` nats above it is taken: the fit
    had converged there, up to the scoring's rounding (a user's oven graph:
    the declared fit's continuation converged 4.6e-5 nats above its start,
    was dropped, and the loop warned that every likelihood ratio was an
    upper bound). A refit the scoring still has not converged is handed to
    another optimiser (:func:`quasi_newton`) and the scoring run once more
    from where it ends. A refit still not converged then is
    returned with ``converged`` False: the caller reports it as not
    comparable (a 178 s sensor low-pass on a 4 s record reached LR 713
    "NOT converged" on a user's two-tank record and was accepted over a
    converged saturation)."""
    total = fit.iterations or 0
    for n in range(CONTINUATIONS + 1):
        if fit.converged is not False:
            break
        ctx.log(f"  {label}: refit not converged after {total} iterations; continuing"
                + (" with L-BFGS-B" if n == CONTINUATIONS else ""))
        try:
            start = fit.estimates() if n < CONTINUATIONS else quasi_newton(ctx, fit, label)
            if start is None:
                break
            nxt = fit_model(ctx, graph, list(fit.params), start,
                            f"continuing {label}", model=fit.model,
                            iterations=ctx.settings.search.confirm_iterations,
                            tolerance=ctx.settings.search.confirm_tolerance)
        except BondGraphError as exc:
            ctx.log(f"  continuing {label} failed: {str(exc).splitlines()[0]}")
            break
        total += nxt.iterations or 0
        if not nxt.nll <= fit.nll + (CONTINUE_SLACK if nxt.converged else 0.0):
            break
        fit = nxt
    fit.iterations = total if fit.iterations is not None else fit.iterations
    return fit


#: L-BFGS-B iterations of :func:`quasi_newton`
QUASI_NEWTON_ITERATIONS = 60


def quasi_newton(ctx: Context, fit: Fit, label: str) -> dict | None:
    """Where bounded L-BFGS-B (batched central-difference gradients,
    :func:`bondgraph.inference.optimize.minimize_batched`; Byrd, Lu,
    Nocedal & Zhu 1995) takes the physical and effect parameters of a refit
    whose Fisher scoring did not converge, the noise intensities, initial
    states and noise stds held at the refit's estimates. The scoring's
    Levenberg-damped step uses the expected information, which on a
    misspecified model's curved ridge points poorly: a user's belt drive
    with a rectifying sensor (nine parameters) took 3 % of it per iteration
    for 120 iterations, 0.05-0.2 nats each. A quasi-Newton method builds its
    curvature from the gradients it meets instead.

    Parameters
    ----------
    ctx : Context
    fit : Fit
        The refit (``fit.theta`` (n_theta,), its ``x0_est``, ``noise_est``).
    label : str
        Name of the refit in the log line.

    Returns
    -------
    dict or None
        Every estimate of ``fit`` by name, the moved parameters at
        L-BFGS-B's result, for the scoring to start from again; None when
        it gains less than :data:`CONTINUE_SLACK` nats over its start (or
        every parameter is a noise intensity).

    Raises
    ------
    BondGraphError
        If the filter cannot be set up at the refit (its failures inside
        the search count as an infinite NLL).

    References
    ----------
    Byrd, R. H., Lu, P., Nocedal, J., Zhu, C. (1995). A limited memory
    algorithm for bound constrained optimization. SIAM J. Sci. Comput.
    16(5), 1190-1208.
    """
    model = fit.model
    noise = noise_params(model)
    names = [n for n in fit.params if n not in noise]
    if not names:
        return None
    base = problem_for(ctx, model)
    pb = base.conditioned_on(x0={**base.prior.estimated, **(fit.x0_est or {})},
                             noise_levels=dict(fit.noise_est or {}))
    crit = make_criterion(pb, names, fit.theta, ctx.settings.evaluation.chunk)
    lo, hi = bounds_around(model, names, fit.theta)
    x0 = np.array([fit.theta[model.param_index(n)] for n in names])
    f0 = float(np.asarray(crit(x0[None, :]))[0])
    x, f, nfev, _ = minimize_batched(crit, x0, lo, hi, maxiter=QUASI_NEWTON_ITERATIONS)
    ctx.log(f"  {label}: L-BFGS-B over {len(names)} parameters (noise levels held): NLL "
            f"{f0:.3f} -> {f:.3f} ({nfev} parameter sets)")
    if not f < f0 - CONTINUE_SLACK:
        return None
    return {**fit.estimates(), **dict(zip(names, (float(v) for v in x)))}


def confirm_pair(ctx: Context, fit: Fit, pair: tuple, scales: Scales,
                 name: str, base: Fit | None = None,
                 off: Candidate | None = None) -> Confirmation | None:
    """Refit ``fit``'s graph with both candidates of ``pair`` (two confirmed
    :class:`Candidate`, at different places) applied, every parameter
    re-estimated from the current estimates and each effect's confirmed
    values (continued until converged, :func:`continued`); with ``base``
    (a member's own refit) and ``off`` (the other member, an additive
    effect), from ``base``'s estimates with ``off``'s coefficients at 0
    (clipped into their boxes), the pair's point that is the member's refit:
    the pair nests it, so this refit ends no worse than the member alone.

    Returns
    -------
    Confirmation or None
        ``values`` keyed ``"<label>.<local name>"``; None (logged) when an
        effect cannot be applied or the refit fails.
    """
    g = fit.graph.copy(name)
    new, values_of, start, mine_of, shape = [], {}, dict(fit.estimates()), {}, {}
    for cand in pair:
        eff = get_effect(cand.effect, ctx.settings.effects)
        vals = start_values(eff, cand, {**cand.values,
                                        **(cand.confirmed or {}).get("values", {})})
        try:
            P = eff.apply(g, cand.target, vals, scales)
        except BondGraphError as exc:
            ctx.log(f"  cannot apply {cand.label} beside the other: {str(exc).splitlines()[0]}")
            return None
        widen_boxes(eff, P, eff.grid_span(fit.graph, cand.target, scales)
                    if not eff.additive else {})
        shape.update(shape_kept(eff, fit.graph, cand.target, scales, P, vals))
        mine_of[cand.label] = [P[p.name] for p in eff.params
                               if p.estimated and p.name in P and p.name not in cand.held]
        new += [par.name for par in mine_of[cand.label]]
        values_of[cand.label] = {p.name: P[p.name].name for p in eff.params if p.name in P}
        start.update({P[k].name: float(v) for k, v in vals.items() if k in P})
        start.update(cand.profile)
    if base is not None and off is not None:
        start.update(base.estimates())
        for par in mine_of[off.label]:
            lo, hi = par.bounds if par.bounds is not None else (-np.inf, np.inf)
            start[par.name] = float(np.clip(0.0, lo, hi))
    label = " + ".join(c.label for c in pair)
    try:
        _, f1 = stable_refit(ctx, g, list(fit.params) + new, [start], label, model_of(g), fit)
    except BondGraphError as exc:
        ctx.log(f"  confirmation of {label} failed: {str(exc).splitlines()[0]}")
        return None
    values = {f"{lab}.{k}": float(f1.theta[f1.model.param_index(n)])
              for lab, names in values_of.items() for k, n in names.items()}
    return Confirmation(f1, values, new, f1.converged is not False, shape)


def shape_kept(eff: Effect, graph, target, scales: Scales, P: dict, values: dict) -> dict:
    """The profiled shape constants of ``eff`` applied (``P``, local name ->
    parameter) at a value other than their data-driven one (a member's
    confirmation kept another width, :func:`profiled_shape`): full name ->
    value."""
    shaped = [p.name for p in eff.params if p.profile and p.name in P and p.name in values]
    if not shaped:
        return {}
    base = eff.shape_values(graph, target, scales)
    return {P[n].name: float(values[n]) for n in shaped
            if n in base and not abs(values[n] - base[n]) <= 1e-9 * abs(base[n])}


def start_values(eff: Effect, cand: Candidate, values: dict | None = None) -> dict:
    """The candidate's values (or ``values``, local name -> value: a pair's
    start from the member's confirmation), with the physical sign imposed on
    an additive effect's nonnegative parameters (friction coefficients of R
    laws; 1e-9 instead of 0), clipped into the effect's declared boxes (a
    score-test value of λ = 1159 for λ ∈ [0, 1] starts at 1: boxes are never
    widened). A pair's start took a member's confirmed values unchecked: on a
    user's two-mass drive a viscous friction confirmed at b = −0.0207 could
    not be applied beside the load's Coulomb friction ("default lies outside
    its bounds (0, 0.207)") and the pair was never refitted."""
    values = dict(cand.values if values is None else values)
    for p in eff.params:
        if p.name in cand.held:
            values[p.name] = cand.held[p.name]
            continue
        if p.name not in values:
            continue
        if eff.additive and p.nonnegative:
            values[p.name] = abs(values[p.name]) or 1e-9
        if p.bounds is not None:
            values[p.name] = float(np.clip(values[p.name], *p.bounds))
    return values


def widen_boxes(eff: Effect, P: dict, spans: dict | None = None) -> None:
    """Set the search box of each new estimated parameter around its start
    value: the effect's declared box if any, a factor 100 either way for a
    positive structural parameter (within its grid's reach ``spans``, local
    name -> (lo, hi), :meth:`Effect.grid_span`, when given), else
    ±20 |value| (from 0 if nonnegative)."""
    for p in eff.params:
        if p.name in P and p.estimated:
            par = P[p.name]
            v = float(par.default)
            span = max(abs(v) * 20.0, 1e-6)
            if p.bounds is not None:
                par.bounds = tuple(p.bounds)
            elif not eff.additive and v > 0:
                lo, hi = (spans or {}).get(p.name, (0.0, np.inf))
                v = float(np.clip(v, lo, hi))
                par.default = v
                par.bounds = (max(v / 100.0, lo), min(v * 100.0, hi))
            else:
                par.bounds = (0.0 if p.nonnegative else -span, span)


def natural_starts(eff: Effect, cand: Candidate, P: dict, new: list[str],
                   start: dict) -> list[dict]:
    """Extra starts at the effect's natural values (full rectification, ...)
    where they differ from ``start`` by more than 5 %: the likelihood may
    have two basins (a half-rectified sensor is a compromise the nuisance
    parameters can settle in)."""
    starts = []
    for pt in eff.natural_points(cand.target):
        alt, moved = dict(start), False
        for k, v in pt.items():
            if k in P and P[k].name in new:
                old_v = float(start.get(P[k].name, np.nan))
                moved |= not abs(old_v - v) <= 0.05 * max(abs(v), 1e-12)
                alt[P[k].name] = float(v)
        if moved:
            starts.append(alt)
    return starts


#: the factors of :func:`grid_refine`'s two passes (coarse, then fine around
#: the best value)
GRID_FACTORS = (np.geomspace(0.05, 20.0, 13), np.geomspace(0.6, 1.66, 9))


def grid_refine(ctx: Context, model: Model, names: list[str], start: dict) -> dict:
    """Improve the start values of ``names`` (the new parameters) by two
    batched coordinate grid searches (13 factors in [0.05, 20], then 9 in
    [0.6, 1.66], both signs where the box allows, all clipped into the
    declared boxes) with everything else fixed: two UKF calls per parameter
    instead of an optimizer's dozens. The mirrored trials flip the sign of
    the searched parameter only.

    Returns
    -------
    dict
        ``start`` (completed with the defaults of ``names``) with the best
        grid values of ``names``.
    """
    theta = model.theta0.copy()
    for k, v in start.items():
        if k in model.params:
            theta[model.param_index(k)] = v
    for n in names:
        if n not in start:
            start[n] = float(theta[model.param_index(n)])
    if not names:
        return start
    crit = criterion_for(ctx, model, names, theta)
    lo, hi = bounds_around(model, names, theta)
    x = np.clip(np.array([start[n] for n in names], dtype=float), lo, hi)
    for factors in GRID_FACTORS:
        for i in range(len(names)):
            xs = np.repeat(x[None, :], factors.size + 1, axis=0)
            base = x[i] if x[i] != 0 else (hi[i] - lo[i]) * 1e-3
            xs[1:, i] = np.clip(base * factors, lo[i], hi[i])
            if lo[i] < 0 < hi[i]:
                mirror = xs[1:].copy()
                mirror[:, i] = np.clip(-mirror[:, i], lo[i], hi[i])
                xs = np.concatenate([xs, mirror])
            f = crit(xs)
            if np.any(np.isfinite(f)):
                x = xs[int(np.nanargmin(np.where(np.isfinite(f), f, np.nan)))]
    out = dict(start)
    out.update({n: float(v) for n, v in zip(names, x)})
    return out


def nested_starts(ctx: Context, model: Model, fit: Fit, cand: Candidate, eff: Effect,
                  P: dict, start: dict) -> list[dict]:
    """A second start for an additive candidate's refit: the point where it
    vanishes (the parameters its score test moves, ``cand.joint_step``, at
    0, clipped into their boxes; the rest at the current fit), kept only
    when its NLL is below that of ``start`` (``[]`` otherwise): the current
    model's own fit, from which the refit can only gain. The grid
    searches multiples of the score test's one-step values, which can all
    lie far beyond the optimum: on a user's two-tank record a square-root
    orifice term's grid start had NLL 1.0e8 against the current fit's
    −1603, its refit stopped at an NLL 3751 nats above the model it nests,
    reported as "LR 0.0"."""
    step = cand.joint_step or {}
    zero = [P[k].name for k in step.get("effect", {}) if k in P and P[k].name in model.params
            and any(p.name == k and p.estimated for p in eff.params)]
    if not eff.additive or not zero:
        return []
    names = list(dict.fromkeys(list(fit.params) + zero))
    theta = model.theta0.copy()
    for k, v in start.items():
        if k in model.params:
            theta[model.param_index(k)] = v
    lo, hi = model.bounds(names)
    est = fit.estimates()
    here = np.clip(np.array([start.get(n, theta[model.param_index(n)]) for n in names]), lo, hi)
    null = np.clip(np.array([0.0 if n in zero else est.get(n, here[i])
                             for i, n in enumerate(names)]), lo, hi)
    f = criterion_for(ctx, model, names, theta)(np.stack([here, null]))
    if not (np.isfinite(f[1]) and (f[1] < f[0] or not np.isfinite(f[0]))):
        return []
    ctx.log(f"  {cand.label}: the point where the effect vanishes starts a second refit "
            f"(NLL {f[1]:.1f}, {f[0]:.1f} at the grid's start)")
    return [{**start, **{n: float(v) for n, v in zip(names, null)}}]


#: multiples of the score test's joint step searched by
#: :func:`score_line_starts`: a coarse pass over both signs, then a fine one
#: around the best multiple (the factors of :func:`grid_refine`)
LINE_FACTORS = GRID_FACTORS


def score_line_starts(ctx: Context, model: Model, fit: Fit, cand: Candidate, eff: Effect,
                      P: dict, start: dict) -> list[dict]:
    """A second start for an additive candidate's refit: the best point of
    the line the score test's joint step points along (the effect's one-step
    β and the change of the estimated parameters that goes with it,
    ``cand.joint_step``), kept only when its NLL is below that of ``start``.

    :func:`grid_refine` searches the new parameters with the estimated ones
    fixed at the current fit, which has absorbed part of the missing effect:
    when the two are strongly correlated the conditional optimum can sit in
    another basin (a cubic spring k3 = 500 N/m³ that the linear stiffness
    absorbed as k 120 N/m for the truth's 50: with k held the grid found
    k3 = −2630, and the refit stopped at −3366, softening; along the joint
    step, k3 505 with k 49). The line is
    θ(s) = (θ̂, 0) + s·(Δθ, β), s in ±:data:`LINE_FACTORS` (coarse, then
    fine around the best), clipped into the declared boxes: two batched UKF
    calls.

    Parameters
    ----------
    ctx : Context
    model : Model
        The augmented model.
    fit : Fit
        The current fit (its estimated parameters are the ones the step moves).
    cand : Candidate
        An additive candidate scored by :func:`bondgraph.diagnose.scoring.score_additive`.
    eff : Effect
    P : dict
        Local name -> the applied effect's parameter.
    start : dict
        The start found by :func:`grid_refine` (full name -> value).

    Returns
    -------
    list of dict
        ``[start with the line's best point]``, or ``[]`` (no joint step,
        or the line does no better than ``start``).
    """
    step = cand.joint_step or {}
    moved = {P[k].name: v for k, v in step.get("effect", {}).items()
             if k in P and any(p.name == k and p.estimated for p in eff.params)}
    if not moved or not any(moved.values()):
        return []
    names = list(fit.params) + list(moved)
    est = fit.estimates()
    x0 = np.array([est[n] for n in fit.params] + [0.0] * len(moved))
    d = np.array([step.get("estimated", {}).get(n, 0.0) for n in fit.params] + list(moved.values()))
    if not np.all(np.isfinite(d)):
        return []
    theta = model.theta0.copy()
    for k, v in start.items():
        if k in model.params:
            theta[model.param_index(k)] = v
    crit = criterion_for(ctx, model, names, theta)
    lo, hi = model.bounds(names)
    here = np.clip(np.array([start.get(n, theta[model.param_index(n)]) for n in names]), lo, hi)
    f_here = float(crit(here[None, :])[0])
    best, f_best, s0 = None, np.inf, 1.0
    for k, factors in enumerate(LINE_FACTORS):
        ss = np.concatenate([factors, -factors]) if k == 0 else s0 * factors
        X = np.clip(x0[None, :] + ss[:, None] * d[None, :], lo, hi)
        f = np.where(np.isfinite(f := crit(X)), f, np.inf)
        i = int(np.argmin(f))
        if f[i] < f_best:
            best, f_best, s0 = X[i], float(f[i]), float(ss[i])
    if best is None or not f_best < f_here:
        return []
    ctx.log(f"  {cand.label}: the score test's joint step (x{s0:.3g}) starts a second refit "
            f"(NLL {f_best:.1f}, {f_here:.1f} at the grid's start)")
    return [{**start, **{n: float(v) for n, v in zip(names, best)}}]
