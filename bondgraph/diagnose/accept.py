"""The loop's decisions, as data (no logging): which candidates are
significant (Bonferroni), whether a confirmed candidate is accepted and why
not, and the records of an accepted or rejected candidate.

A candidate is accepted when, after re-estimating all parameters,

1. the refit is finite (NLL and error);
2. the information criterion (AIC, Akaike 1974, or BIC, Schwarz 1978)
   decreases;
3. the likelihood-ratio test passes: LR = 2 (NLL₀ − NLL₁) has p < the
   loop's ``significance`` under χ²(k), k the effect's new parameters
   (Wilks 1938);
4. the free-run error (on the validation record if there is one, else on
   the record) does not grow by more than the factor ``metric_tolerance``
   (1.0: it may not rise).

The residual whiteness (sum of the Ljung-Box statistics, Ljung & Box 1978)
is reported before and after but never vetoes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from bondgraph.diagnose.effects import BY_NAME, Effect
from bondgraph.diagnose.fit import Fit
from bondgraph.diagnose.result import AppliedEffect, Candidate, Rejection, Step
from bondgraph.diagnose.settings import LoopSettings


def significant(cands: list[Candidate], level: float) -> list[Candidate]:
    """Candidates significant at family-wise ``level`` (Bonferroni over all
    of ``cands``: p · n < level)."""
    n_c = max(len(cands), 1)
    return [c for c in cands if c.p_value * n_c < level]


@dataclass
class Decision:
    """Accept or not, the reason of a rejection, and the quantities compared
    (information criterion, likelihood ratio and its p-value, whiteness,
    the accept error (validation or record) before and after)."""

    accepted: bool
    reason: str | None
    criterion_before: float
    criterion_after: float
    whiteness_before: float
    whiteness_after: float
    error_before: float
    error_after: float
    lr: float = float("nan")
    lr_p_value: float = float("nan")


def decide(current: Fit, after: Fit, settings: LoopSettings, dof: int = 1) -> Decision:
    """Compare the candidate's refit ``after`` (``dof`` new parameters) with
    the ``current`` fit (module docstring for the rule).

    Returns
    -------
    Decision
        ``reason`` (first failed test): "the refit is not finite",
        "information criterion did not improve", "likelihood-ratio test not
        passed (LR l, p p)", or "the error grew (a -> b)" (with "on the
        validation record" when it is that error).
    """
    ic0, ic1 = current.information(settings.criterion), after.information(settings.criterion)
    w0, w1 = current.residuals.whiteness, after.residuals.whiteness
    e0, e1 = current.accept_metric, after.accept_metric
    lr = 2.0 * (current.nll - after.nll)
    p = float(chi2.sf(lr, max(int(dof), 1))) if np.isfinite(lr) else float("nan")
    where = " on the validation record" if after.validation_metric is not None else ""
    reason = None
    if not (np.isfinite(after.nll) and np.isfinite(e1)):
        reason = f"the refit is not finite (NLL {after.nll:.4g}, error {e1:.4g})"
    elif not ic1 < ic0:
        reason = "information criterion did not improve"
    elif not p < settings.significance:
        reason = f"likelihood-ratio test not passed (LR {lr:.3g}, p {p:.2g})"
    elif np.isfinite(e0) and not e1 <= settings.metric_tolerance * e0:
        reason = f"the error grew{where} ({e0:.4g} -> {e1:.4g})"
    return Decision(reason is None, reason, ic0, ic1, w0, w1, e0, e1, lr, p)


def accepted_step(cand: Candidate, d: Decision, current: Fit, after: Fit, names: list[str],
                  std: dict, metric: str) -> Step:
    """The :class:`Step` of an accepted candidate: ``names`` with their
    estimates in ``after`` and Cramér-Rao ``std``; the statistic is the
    confirmed likelihood ratio if any, else the screening statistic."""
    P = {n: {"estimate": float(after.theta[after.model.param_index(n)]), "std": std.get(n)}
         for n in names}
    return Step(cand.effect, cand.target.name, metric, d.error_before, d.error_after,
                current.nll, after.nll, d.criterion_before, d.criterion_after,
                d.whiteness_before, d.whiteness_after, P,
                cand.confirmed_statistic or cand.statistic, cand.p_value,
                current.metric, after.metric, after.validation_metric is not None,
                d.lr, d.lr_p_value, cand.target.kind, [n for n in names if n not in current.params])


def applied_effect(eff: Effect, cand: Candidate, after: Fit) -> AppliedEffect:
    """The accepted effect with its fitted values by local name, as the
    augmented model file re-applies it (with the ``module:Class`` of a
    user-supplied effect)."""
    names = {p.name: eff.pname(cand.target, p.name) for p in eff.params}
    own = BY_NAME.get(eff.name)
    spec = None if own is not None and type(own) is type(eff) else \
        f"{type(eff).__module__}:{type(eff).__qualname__}"
    return AppliedEffect(cand.effect, cand.target,
                         {p: float(after.theta[after.model.param_index(n)])
                          for p, n in names.items() if n in after.model.params}, spec)


def rejection(step: int, cand: Candidate, d: Decision) -> Rejection:
    """The record of a rejected candidate at loop step ``step``."""
    return Rejection(step, cand, d.reason, d.criterion_after, d.whiteness_after)


def confirmed_record(current: Fit, after: Fit, dof: int, values: dict, settings: LoopSettings,
                     d: Decision | None = None) -> dict:
    """What report.json keeps of a candidate's confirmation refit
    (:attr:`bondgraph.diagnose.result.Candidate.confirmed`)."""
    lr = 2.0 * (current.nll - after.nll)
    rec = {"lr": lr, "dof": dof, "p_value": float(chi2.sf(lr, max(dof, 1))),
           "nll": after.nll, "criterion": after.information(settings.criterion),
           "error": after.metric, "validation_error": after.validation_metric,
           "whiteness": after.residuals.whiteness, "values": dict(values),
           "converged": after.converged, "iterations": after.iterations,
           "at_bound": list(after.at_bound)}
    if d is not None:
        rec.update(accepted=d.accepted, reason=d.reason)
    return rec
