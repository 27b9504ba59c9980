"""The loop's decisions, as data (no logging): which candidates are
significant (Bonferroni), whether a confirmed candidate is accepted and why
not, and the records of an accepted or rejected candidate.

A candidate is accepted when, after re-estimating all parameters, the
information criterion (AIC, Akaike 1974, or BIC, Schwarz 1978) decreases,
the residual whiteness (sum of the Ljung-Box statistics, Ljung & Box 1978)
decreases or is within noise of white already, and the reported error does
not grow by more than ``metric_tolerance``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bondgraph.diagnose.effects import Effect
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
    (information criterion, whiteness, reported error, before and after)."""

    accepted: bool
    reason: str | None
    criterion_before: float
    criterion_after: float
    whiteness_before: float
    whiteness_after: float
    error_before: float
    error_after: float


def decide(current: Fit, after: Fit, settings: LoopSettings) -> Decision:
    """Compare the candidate's refit ``after`` with the ``current`` fit.

    Returns
    -------
    Decision
        ``reason`` (first failed test): "information criterion did not
        improve", "whiteness did not improve", or "the error grew (a -> b)".
    """
    ic0, ic1 = current.information(settings.criterion), after.information(settings.criterion)
    w0, w1 = current.residuals.whiteness, after.residuals.whiteness
    better_ic = ic1 < ic0
    # "whiteness improves": the Ljung-Box total decreases, or the innovations
    # are white already (within noise of χ²(dof))
    whiter = w1 < w0 or after.residuals.is_white()
    # guard: a step may not wreck the reported error (e.g. a friction law
    # that makes the free-run simulation stick)
    metric_ok = not (np.isfinite(current.metric) and
                     after.metric > settings.metric_tolerance * current.metric)
    reason = None
    if not better_ic:
        reason = "information criterion did not improve"
    elif not whiter:
        reason = "whiteness did not improve"
    elif not metric_ok:
        reason = f"the error grew ({current.metric:.4g} -> {after.metric:.4g})"
    return Decision(reason is None, reason, ic0, ic1, w0, w1, current.metric, after.metric)


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
                cand.confirmed_statistic or cand.statistic, cand.p_value)


def applied_effect(eff: Effect, cand: Candidate, after: Fit) -> AppliedEffect:
    """The accepted effect with its fitted values by local name, as the
    augmented model file re-applies it."""
    names = {p.name: eff.pname(cand.target, p.name) for p in eff.params}
    return AppliedEffect(cand.effect, cand.target,
                         {p: float(after.theta[after.model.param_index(n)])
                          for p, n in names.items() if n in after.model.params})


def rejection(step: int, cand: Candidate, d: Decision) -> Rejection:
    """The record of a rejected candidate at loop step ``step``."""
    return Rejection(step, cand, d.reason, d.criterion_after, d.whiteness_after)
