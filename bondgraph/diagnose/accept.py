"""The loop's decisions, as data (no logging): which candidates are
significant (Bonferroni), whether a confirmed candidate is accepted and why
not, and the records of an accepted or rejected candidate.

A candidate is accepted when, after re-estimating all parameters,

0. the refit converged (a confirmation that has not is continued first,
   :func:`bondgraph.diagnose.confirm.confirm`; one that still has not is
   reported as not comparable: its likelihood ratio is one it has not
   reached), the refitted model is physically admissible (every R law
   dissipates and every C and I stores non-negative energy over the range
   the record visits plus a margin,
   :func:`bondgraph.numerics.admissible.check_admissible`), and it simulates:
   its free run is finite and stays in the plausible range on the record
   *and* on every validation record (:func:`bondgraph.diagnose.fit.free_run_trouble`;
   a model whose free run diverges on the record it was fitted on is refused
   even when its error on the held-out part falls); the record identifies
   the effect's own parameters apart from the parameters the current fit
   identified (:func:`unidentified_effect`: a candidate that only moves
   along a ridge with them, a sensor gain beside a motor constant and the
   inertias it scales, is a reparametrisation);
1. the refit is finite (NLL and error);
2. the information criterion (AIC, Akaike 1974, or BIC, Schwarz 1978)
   decreases;
3. the likelihood-ratio test passes: LR = 2 (NLL₀ − NLL₁) has p < the
   loop's ``accept.significance`` under χ²(k), k the effect's new parameters
   (Wilks 1938);
4. the free-run error (on the validation record if there is one, else on
   the record) does not grow by more than the factor ``accept.metric_tolerance``
   (1.0: it may not rise), nor does it on any further validation record
   (``more_validation``, ``--validate`` given again: a model the loop
   accepts is never worse on a record it was judged on); where a validation
   record judges, the free-run error on the estimation record may not grow
   significantly either (:func:`grown_on_estimation`: a one-sided
   Diebold-Mariano test of the increase at :data:`ESTIMATION_GROWTH_LEVEL`):
   a refit that buys its likelihood with the filter's one-step predictions
   while the model's own simulation of the record it was fitted on gets
   worse is not a better model (a user's battery cell: a cold-start excess
   of the charging current, 0.0513 -> 0.787 on the fitted record, accepted
   on 0.0642 -> 0.0589 held out);
5. the decrease of that free-run error exceeds its own sampling
   uncertainty (``accept.error_level``, default 0.05; None: no such test): a
   one-sided Diebold-Mariano test (Diebold & Mariano 1995) on the paired
   per-sample differences of the squared standardised free-run errors,
   d_t = Σ_i (e0_ti² − e1_ti²), with the Newey & West (1987) long-run
   variance (Bartlett weights, bandwidth by Andrews' 1991 AR(1) plug-in
   rule) of its random part 2 Σ_i Δ_ti e1_ti given the change of the output
   Δ = ŷ0 − ŷ1 (:func:`error_decrease_test`), so that the autocorrelation of
   free-run errors does not overstate its precision and a decrease confined
   to one episode is not counted as its own noise. With further validation
   records their errors are stacked below the first's (:func:`pooled_errors`).

Why test 5: the likelihood-ratio test is computed by the discretised UKF.
Where its integrator (ROS2 with few substeps) has a systematic error, the
declared parameters absorb most of it and a flexible candidate (a sensor
polynomial, a gain) the rest, with an LR that is significant although
nothing is missing (a record simulated from the declared graph: ROS2 x 2
puts the best of 21 candidates near or past the Bonferroni threshold on 3 of
4 noise seeds, RK4 x 10 on none). The free-run error is simulated by an
accurate solver (``free_run.method``), so an effect that only fits the filter's
discretisation error, or the noise, leaves it unchanged within its
uncertainty (0.02513 -> 0.02506 in that case: z 1.26, p 0.10), whereas a missing
effect lowers it by many standard errors (the saturating engine torque of
``vehicle_engine_saturation``: 0.3715 -> 0.1358, z 10.5). Before the
structural profile over the grid (:func:`~bondgraph.diagnose.scoring.grid_starts`)
the rule without test 5 accepted, on that record, ``input_delay @ brake``
(a delay of a brake input that is zero throughout: LR 23 000 from the
process noise of its Padé states) with a free-run error unchanged
(0.3715 -> 0.3715): the kind of step test 5 exists to refuse.

The residual whiteness (sum of the Ljung-Box statistics, Ljung & Box 1978)
is reported before and after but never vetoes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from bondgraph.core.deferred import chi2, norm
from bondgraph.diagnose.effects import BY_NAME, Effect
from bondgraph.diagnose.fit import Fit, noise_params
from bondgraph.diagnose.inference_calls import andrews_bandwidth, long_run_variance  # noqa: F401
from bondgraph.diagnose.result import (FITTED_PART_ONLY, AppliedEffect, Candidate, Rejection,
                                       Step)
from bondgraph.diagnose.settings import AcceptRule
from bondgraph.numerics.admissible import Admissibility


def significant(cands: list[Candidate], level: float) -> list[Candidate]:
    """Candidates significant at family-wise ``level`` (Bonferroni over all
    of ``cands``: p · n < level)."""
    n_c = max(len(cands), 1)
    return [c for c in cands if c.p_value * n_c < level]


def error_decrease_test(e0: np.ndarray, e1: np.ndarray) -> tuple[float, float]:
    """One-sided Diebold-Mariano (1995) test that the free-run errors ``e1``
    (N, n_y) are smaller than ``e0`` (N, n_y), both standardised per output
    (:func:`bondgraph.diagnose.metric.standardised_errors`), with the
    variance of the loss differential conditional on the change of the
    model's output.

    The loss differential d_t = Σ_i (e0_ti² − e1_ti²) over the samples where
    both are finite, z = d̄ / sqrt(LRV/n). Both errors are free runs of
    fitted models against the same measurement, so their difference
    Δ_t = e0_t − e1_t = ŷ0_t − ŷ1_t holds no measurement noise: given the
    inputs and the two fits it is fixed, and d_t = Σ_i (Δ_ti² + 2 Δ_ti e1_ti)
    varies from sample to sample only through the errors e1 that remain.
    LRV is therefore the Newey-West long-run variance
    (:func:`long_run_variance`) of w_t = 2 Σ_i Δ_ti e1_ti, not of d_t: the
    fixed pattern Δ_t² is the decrease itself, and counted as noise it
    bounds z near 1 for any decrease confined to one episode, however large
    (a cold start's first 20 s: z 1.19 from the HAC variance of d_t, 7.6 by
    the t-ratio of regressing e0 on Δ). For an effect that fits only the
    noise (Δ a least-squares fit of e0), Σ Δ e1 ≈ 0 and z ≈ |N(0, 1)|/2
    (West 1996, Giacomini & White 2006 for tests conditional on the
    forecasts; Harvey, Leybourne & Newbold 1998 for the encompassing
    regression e0 = λΔ + ε whose HAC variance this is).

    Returns
    -------
    (z, p)
        The statistic and its one-sided p-value 1 − Φ(z); (nan, nan) with
        fewer than 3 common samples; (+inf, 0) or (−inf, 1) for a
        differential of zero variance.

    Raises
    ------
    ValueError
        If the shapes differ.
    """
    e0, e1 = np.asarray(e0, dtype=float), np.asarray(e1, dtype=float)
    if e0.shape != e1.shape:
        raise ValueError(f"error_decrease_test: shapes {e0.shape} and {e1.shape} differ")
    # z is invariant to a common scale of the errors: divided by the largest
    # finite one, so that a diverging free run cannot overflow the sums
    big = np.abs(np.concatenate([e0.ravel(), e1.ravel()]))
    big = big[np.isfinite(big)]
    scale = float(big.max()) if big.size else 0.0
    if scale > 0:
        e0, e1 = e0 / scale, e1 / scale
    e0, e1 = e0.reshape(e0.shape[0], -1), e1.reshape(e1.shape[0], -1)
    rows = np.any(np.isfinite(e0**2 - e1**2), axis=1)
    delta = e0[rows] - e1[rows]
    d = np.nansum(delta**2 + 2 * delta * e1[rows], axis=1)
    if d.size < 3:
        return float("nan"), float("nan")
    lrv = long_run_variance(np.nansum(2 * delta * e1[rows], axis=1))
    mean = float(d.mean())
    if lrv <= 0:
        return (float("inf"), 0.0) if mean > 0 else (float("-inf"), 1.0)
    z = mean / np.sqrt(lrv / d.size)
    return float(z), float(norm.sf(z))


def vuong_test(l_a: np.ndarray, l_b: np.ndarray, k_a: int, k_b: int) -> tuple[float, float]:
    """Vuong's (1989) test of two non-nested models on the same record from
    their per-sample negative log-likelihood contributions ``l_a``, ``l_b``
    (N,) [nats] (the UKF's prediction-error terms, :attr:`UKFResult.nll_terms`)
    and their numbers of estimated parameters.

    d_t = l_b,t − l_a,t (positive where model a predicts better);
    z = (Σ d_t − (k_a − k_b)) / sqrt(N · LRV(d)) with Akaike's correction of
    the sum and the Newey-West long-run variance (:func:`long_run_variance`:
    the terms of a misspecified filter are serially correlated; Rivers &
    Vuong 2002). Under the null that both models are equally close to the
    truth, z ~ N(0, 1).

    Returns
    -------
    (z, p)
        z > 0 favours model a; p the two-sided p-value 2 Φ(−|z|). (0, 1)
        when the contributions are equal at every sample; (nan, nan) with
        fewer than 3 samples both models scored.

    Raises
    ------
    ValueError
        If the shapes differ.
    """
    l_a, l_b = np.asarray(l_a, dtype=float), np.asarray(l_b, dtype=float)
    if l_a.shape != l_b.shape:
        raise ValueError(f"vuong_test: shapes {l_a.shape} and {l_b.shape} differ")
    d = (l_b - l_a).ravel()
    d = d[np.isfinite(d)]
    if d.size < 3:
        return float("nan"), float("nan")
    lrv = long_run_variance(d)
    total = float(d.sum()) - (k_a - k_b)
    if lrv <= 0:
        return (0.0, 1.0) if total == 0 else (float(np.sign(total) * np.inf), 0.0)
    z = total / np.sqrt(d.size * lrv)
    return float(z), float(2 * norm.sf(abs(z)))


def mark_ties(confirmed: list, level: float) -> list[str]:
    """Mark the confirmed candidates indistinguishable from the lead.

    Parameters
    ----------
    confirmed : list of (Candidate, Fit, int)
        Best first (by confirmed LR − 2k): each candidate, its refit (with a
        stored UKF run) and its number of new parameters.
    level : float
        Two-sided level of :func:`vuong_test`; 0 marks none.

    Returns
    -------
    list of str
        Labels tied with the lead (also in the lead's ``tied``; each tied
        candidate's ``confirmed`` gets ``tie_z``, ``tie_p``).
    """
    if len(confirmed) < 2 or level <= 0:
        return []
    lead, fa, ka = confirmed[0]
    la = per_sample_nll(fa)
    out = []
    for c, fb, kb in confirmed[1:]:
        lb = per_sample_nll(fb)
        if la is None or lb is None or la.shape != lb.shape:
            continue
        z, p = vuong_test(la, lb, ka, kb)
        if np.isfinite(p) and p >= level:
            out.append(c.label)
            if c.label not in lead.tied:
                lead.tied.append(c.label)
            if c.confirmed is not None:
                c.confirmed.update(tie_z=z, tie_p=p)
    return out


def rank_confirmed(confirmed: list) -> list:
    """The confirmed candidates best first: those whose refit converged
    (``comparable``) before those whose refit did not, each group by
    decreasing score (LR − 2k).

    Parameters
    ----------
    confirmed : list of (float, Candidate, Confirmation)
        The score, the candidate and its confirmation (with ``comparable``).

    Returns
    -------
    list
        The same tuples, reordered. A refit that stopped at its iteration
        limit has a likelihood ratio the model does not reach; ranking it by
        that number would let it win over a converged refit (issue: a
        non-converged 178 s sensor low-pass over a converged saturation).
    """
    return sorted(confirmed, key=lambda z: (not getattr(z[2], "comparable", True), -z[0]))


def per_sample_nll(fit: Fit) -> np.ndarray | None:
    """Per-sample NLL terms (N,) of a fit's stored UKF run [nats], or None
    (the terms :func:`vuong_test` compares)."""
    t = getattr(fit.ukf, "nll_terms", None)
    return None if t is None else np.asarray(t, dtype=float)[:, 0]


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
    error_z: float = float("nan")
    error_p_value: float = float("nan")


def decide(current: Fit, after: Fit, rule: AcceptRule, dof: int = 1,
           admissible: Admissibility | None = None, comparable: bool = True,
           box_free: Sequence[str] = (), interior: Sequence[str] = (),
           searched: Mapping[str, float] | None = None,
           known: Sequence[str] = ()) -> Decision:
    """Compare the candidate's refit ``after`` (``dof`` new parameters) with
    the ``current`` fit (module docstring for the rule).

    Parameters
    ----------
    current, after : Fit
    rule : AcceptRule
        The loop's accept rule (``LoopSettings.accept``).
    dof : int
        The candidate's new parameters.
    admissible : Admissibility, optional
        The refit's admissibility (:func:`bondgraph.diagnose.fit.admissibility`);
        None: not checked.
    comparable : bool
        False when the refit did not converge (its likelihood ratio is not
        one it reached).
    box_free : sequence of str
        Parameters on a bound of their box that the box is known not to
        decide (the likelihood gains next to nothing beyond it,
        :func:`bondgraph.diagnose.runner.box_not_deciding`): not a reason
        to reject.
    interior : sequence of str
        The candidate's new parameters that its effect declares ``interior``:
        one on a bound of its box is a reason to reject
        (:func:`at_family_edge`).
    searched : dict, optional
        The candidate's new parameters on the edge of a search box (a box
        the effect library set around the score test's estimate,
        :meth:`~bondgraph.diagnose.effects.base.Effect.search_boxed`),
        each mapped to what the likelihood gains beyond that box [nats], at
        least :data:`~bondgraph.diagnose.runner.BOX_DECIDES`
        (:func:`bondgraph.diagnose.runner.search_box_deciding`): a reason
        to reject.
    known : sequence of str
        Parameters declared without a box (``LoopSettings.hold_unidentified``):
        one the refit moves along a ridge with the candidate's new parameters
        is a reason to reject (:func:`moved_known_value`).

    Returns
    -------
    Decision
        ``reason`` (first failed test): "the refit did not converge ...",
        "the refit is not physically admissible: ...", "the refitted model
        does not simulate: ...", "the refit is not finite", "the refit moves
        ... onto its box" (:func:`newly_boxed`), "the effect's ... ends on
        its box" (:func:`at_family_edge`), "the effect's ... ends on the
        edge of the search box" (``searched``), "information criterion did
        not improve", "likelihood-ratio test not passed (LR l, p p)", "the
        error grew (a -> b)" (with "on the validation record" when it is
        that error), or "the error decrease is within its uncertainty (a ->
        b, z z, p p)" (:func:`fitted_part_only`). ``error_z`` and
        ``error_p_value`` are the Diebold-Mariano statistic and p-value
        (:func:`error_decrease_test`; NaN without per-sample errors).
    """
    ic0, ic1 = current.information(rule.criterion), after.information(rule.criterion)
    w0, w1 = current.residuals.whiteness, after.residuals.whiteness
    e0, e1 = current.accept_metric, after.accept_metric
    lr = 2.0 * (current.nll - after.nll)
    p = float(chi2.sf(lr, max(int(dof), 1))) if np.isfinite(lr) else float("nan")
    where = " on the validation record" if after.validation_metric is not None else ""
    dz, dp = float("nan"), float("nan")
    a0, a1 = pooled_errors(current, after)
    if a0 is not None:
        dz, dp = error_decrease_test(a0, a1)
    before = getattr(current, "more_metrics", {})
    pooled = "".join(f", '{k}' {before.get(k, float('nan')):.4g} -> {v:.4g}"
                     for k, v in getattr(after, "more_metrics", {}).items())
    reason = (_objection(current, after, lr, comparable, admissible, box_free, interior,
                         searched or {})
              or (moved_known_value(current, after, known) if comparable else "")
              or _failed_test(rule, (ic0, ic1), p, lr, (e0, e1), (dz, dp), where,
                              _grown_elsewhere(rule, current, after)
                              or grown_on_estimation(rule, current, after), pooled))
    reason = fitted_part_only(current, after, reason, where)
    return Decision(reason is None, reason, ic0, ic1, w0, w1, e0, e1, lr, p, dz, dp)


def fitted_part_only(current: Fit, after: Fit, reason: str | None,
                     where: str) -> str | None:
    """:func:`decide`'s ``reason``, and where a validation record refused the
    refit ``after`` on its error (``where``: " on the validation record")
    "; on the estimation record its error fell (a -> b, z z)" after it when
    that fall is significant (the one-sided Diebold-Mariano test of
    :func:`error_decrease_test`, p < :data:`ESTIMATION_GROWTH_LEVEL`).

    The contrast has two readings that the record alone cannot tell apart:
    the effect fits the estimation record's peculiarities (what the
    validation record is there to refuse), or it acts only where the
    validation record does not reach: a transient at the start of a record
    (a cold engine's warm-up) is absent from the held-out end of the same
    record, which can then neither confirm nor refuse it. The loop's
    summary says so once (:meth:`~bondgraph.diagnose.result.LoopResult.none_accepted`)."""
    if not (reason and where and reason.startswith(("the error grew" + where,
                                                    "the error decrease" + where))):
        return reason
    e0, e1 = current.metric, after.metric
    a0, a1 = getattr(current, "sim_errors", None), getattr(after, "sim_errors", None)
    if (a0 is None or a1 is None or np.shape(a0) != np.shape(a1)
            or not (np.isfinite(e0) and np.isfinite(e1) and e1 < e0)):
        return reason
    z, p = error_decrease_test(a0, a1)
    if not (np.isfinite(p) and p < ESTIMATION_GROWTH_LEVEL):
        return reason
    return f"{reason}{FITTED_PART_ONLY} ({e0:.4g} -> {e1:.4g}, z {z:.2f})"


#: relative move of a known value (declared without a box) along a flat
#: direction with a candidate's new parameters beyond which the candidate
#: rescales the model instead of adding to it (:func:`moved_known_value`)
KNOWN_MOVE_REL = 0.05


def moved_known_value(current: Fit, after: Fit, known: Sequence[str]) -> str:
    """Why the refit ``after`` is refused for moving a known value ("" when
    it is not): a parameter of ``known`` (declared without a box: the user's
    known value, which the loop estimates only where the record disagrees
    with it) that lies, with one of the candidate's new parameters, along a
    combination the refit's Fisher information does not identify apart
    (``after.flat``), and that the refit moves by more than
    :data:`KNOWN_MOVE_REL` of its value. Along such a ridge the record
    cannot say which of them moves; the user said which does not. A
    pump-fed piston (area A declared without a box, 2e-3 m², flow and
    pressure and position measured) whose seal friction reverses more
    softly than the library's tanh: a position-sensor gain g = −0.29
    rescaled A to 1.41e-3 (−29 %) and the mass, spring and damper with it
    (50 -> 24.9 kg), a tanh width in disguise, on a held-out NRMSE
    0.01483 -> 0.01474."""
    flat = set(after.flat or ())
    new = [n for n in after.params if n not in current.params and n in flat]
    if not new:
        return ""
    moved = []
    for n in known:
        if n not in flat or n not in current.params or n not in after.params:
            continue
        a = float(current.theta[current.model.param_index(n)])
        b = float(after.theta[after.model.param_index(n)])
        if abs(b - a) > KNOWN_MOVE_REL * abs(a):
            moved.append(f"{n} {a:.4g} -> {b:.4g} ({(b - a) / abs(a):+.0%})")
    if not moved:
        return ""
    return (f"the refit moves {', '.join(moved)}, declared without a box (a known value), "
            f"along a combination with {', '.join(new)} the record does not identify apart: "
            f"the effect rescales the model instead of adding to it (to estimate the value "
            f"freely, give it a box or list the parameters in --params)")


#: a parameter whose Cramér-Rao std grows by more than this factor in a
#: candidate's refit is left undetermined by it (:func:`unidentified_effect`)
STD_INFLATION = 10.0
#: ... when that std is also more than this fraction of its value: known to
#: within a few per cent, a parameter is determined however much its std grew
#: (a misspecified fit's std is too small to compare with, :mod:`bondgraph.inference.robust`)
UNDETERMINED_REL = 0.1


def unidentified_effect(current: Fit, after: Fit) -> str:
    """Why a candidate's refit ``after`` is not a model the record
    determines ("" when it is): the record does not identify one of the
    candidate's own new parameters apart from parameters that ``current``
    identified (both among the quantities along whose combination the
    refit's Fisher information is flat, ``after.flat``: collinearity index
    above 100, Brun, Reichert & Künsch 2001, or a likelihood that stops
    gaining along them, :func:`bondgraph.diagnose.fit.unidentified`), and
    the refit leaves those parameters undetermined: their Cramér-Rao std
    grows more than :data:`STD_INFLATION`-fold to more than
    :data:`UNDETERMINED_REL` of their value (or has none).

    Such an effect is a reparametrisation, not a finding: its gain is what
    the declared parameters lose when they move along the ridge with it.
    A user's DC motor (current and rotor speed measured, voltage the input)
    took a speed-sensor gain g = −0.29 that the record cannot tell apart
    from the torque constant and the inertias (held-out NRMSE 0.03296 ->
    0.0329): k_t went from 0.060 to 0.042 and both inertias halved, the
    std of k_t 400 times its earlier value. A strong but not exact
    correlation is no such case: two tank overflows whose levels correlate
    with an orifice (collinearity index above 100) are each determined to
    0.3 %. Nor is a law whose own terms correlate: natural convection from
    an oven's case, β·ΔT^1.25 beside the conduction ΔT/R, with the exponent
    estimated (n 1.254 ± 0.024, truth 1.25), leaves R at 1.188 ± 0.045 (truth
    1.2): a std 290 times the linear fit's, whose misfit made its own std
    far too small, yet 4 % of the value. Parameters ``current`` already did not identify
    (``current.flat``) are the declared fit's affair (its warning), not the
    candidate's.

    "Of their value" is judged by the larger of the Cramér-Rao std and the
    robust (sandwich) std ``after.std_robust`` where the caller computed it
    (:func:`robust_std_needed` says when): along such a ridge the refit's
    misfit makes the Cramér-Rao std too small. A DC motor with two inertias
    on its shaft (the record knows their sum) and a Coulomb friction sharper
    than the library's tanh width took a speed-sensor gain g = −0.30 (truth
    0): k_t 0.0600 ± 0.00002 became 0.0423 ± 0.0026, 6 % by the Cramér-Rao
    std, which passed; its sandwich std, 0.028 (66 %), refuses the gain
    (``tests/test_robust_identification.py``). Not every such gain: on a
    user's geared motor (rotor and load inertias and frictions) the gain's
    refit read k_t 0.0517 ± 0.0031 with a sandwich std of 0.0009, and it is
    accepted; there the record does determine g, through the friction's
    width, which the gain rescales (since the confirmation profiles that
    width, :func:`bondgraph.diagnose.confirm.profiled_shape`, the loop
    keeps a tenth of it and adds no gain)."""
    new, partners = _ridge(current, after)
    if not new or not partners:
        return undetermined(current, after)
    honest = [n for n in partners if not _inflated(current, after, n, robust=False)]
    why = ""
    if honest:
        why = "; " + ", ".join(
            f"{n}'s robust std is {_relative(after, n, robust=True):.0%} of its value "
            f"(its Cramér-Rao std {_relative(after, n, robust=False):.1%}, which assumes the "
            f"model is right)" for n in honest)
    return (f"the record does not identify {', '.join(new)} apart from {', '.join(partners)} "
            f"(the likelihood is flat along a combination of them): the effect would leave "
            f"them undetermined{why}")


def unidentified_new(current: Fit, after: Fit) -> tuple[list[str], list[str]]:
    """``(new, partners)``: the candidate's new parameters that the refit
    ``after`` does not identify apart from parameters ``current``
    identified, and those parameters, when that is why
    :func:`unidentified_effect` refuses it (two empty lists otherwise)."""
    new, partners = _ridge(current, after)
    if not new or not partners or not unidentified_effect(current, after):
        return [], []
    return new, partners


def _ridge(current: Fit, after: Fit, robust: bool = True) -> tuple[list[str], list[str]]:
    """The candidate's new parameters along a flat direction of ``after``
    and the parameters ``current`` identified that it leaves undetermined
    (:func:`unidentified_effect`; ``robust``: with ``after.std_robust``)."""
    flat = set(after.flat or ())
    if not flat:
        return [], []
    new = [n for n in after.params if n not in current.params and n in flat]
    had = set(current.flat or ())
    partners = [n for n in after.params if n in current.params and n in flat and n not in had
                and _inflated(current, after, n, robust=robust)]
    return new, partners


def robust_std_needed(current: Fit, after: Fit) -> list[str]:
    """The parameters whose robust (sandwich) std in ``after`` would decide
    :func:`unidentified_effect` and is not there: ``current`` identified
    them, the refit is flat along them and the candidate's new parameters,
    and their Cramér-Rao std grew more than :data:`STD_INFLATION`-fold yet
    stays within :data:`UNDETERMINED_REL` of their value. The caller
    computes ``after.std_robust`` for these (one batched filter run,
    :func:`bondgraph.diagnose.fit.robust_std_of`) before :func:`decide`."""
    if undetermined(current, after):
        return []
    new, _ = _ridge(current, after, robust=False)
    if not new:
        return []
    flat, had = set(after.flat or ()), set(current.flat or ())
    rob = after.std_robust or {}
    return [n for n in after.params if n in current.params and n in flat and n not in had
            and n not in rob and _grown(current, after, n)
            and not _inflated(current, after, n, robust=False)]


def undetermined(current: Fit, after: Fit) -> str:
    """Why the refit ``after`` determines neither its own new parameters nor
    declared ones ("" otherwise): its Fisher information gives none of the
    new parameters a Cramér-Rao std, nor a parameter that ``current``
    determined (those on a bound of their box aside: they have none by
    design). The information was not finite there (the filter fails near
    the refit along the ridge it followed), so no flat direction could be
    named either: a user's DC motor took a speed-sensor gain with a
    Stribeck term, k_t at half its value, every std missing."""
    std0, std1 = current.std or {}, after.std or {}
    bound = set(after.at_bound or ())
    new = [n for n in after.params if n not in current.params and n not in bound]
    lost = [n for n in after.params if n in current.params and n not in bound
            and std0.get(n) is not None and np.isfinite(std0[n]) and std1.get(n) is None]
    if not new or not lost or any(std1.get(n) is not None for n in new):
        return ""
    return (f"the refit's Fisher information gives no Cramér-Rao std for {', '.join(new)}, "
            f"nor for {', '.join(lost)} (the record determined them before): the effect "
            f"would leave them undetermined")


def _inflated(current: Fit, after: Fit, name: str, robust: bool = True) -> bool:
    """Whether ``name``'s Cramér-Rao std in ``after`` is missing, or more
    than :data:`STD_INFLATION` times its std in ``current`` and (the larger
    of it and, with ``robust``, its sandwich std ``after.std_robust``) more
    than :data:`UNDETERMINED_REL` of its value there (False when ``current``
    has no std to compare with)."""
    s0, s1 = (current.std or {}).get(name), (after.std or {}).get(name)
    if s0 is None or not np.isfinite(s0) or s0 <= 0:
        return False
    if s1 is None or not np.isfinite(s1):
        return True
    return _grown(current, after, name) and _relative(after, name, robust) > UNDETERMINED_REL


def _grown(current: Fit, after: Fit, name: str) -> bool:
    """Whether ``name``'s Cramér-Rao std grew more than :data:`STD_INFLATION`-fold
    from ``current`` to ``after`` (both finite)."""
    s0, s1 = (current.std or {}).get(name), (after.std or {}).get(name)
    ok = s0 is not None and s1 is not None and np.isfinite(s0) and np.isfinite(s1) and s0 > 0
    return bool(ok and s1 > STD_INFLATION * s0)


def _relative(after: Fit, name: str, robust: bool) -> float:
    """``name``'s std in ``after`` over its value's magnitude: the Cramér-Rao
    std, or with ``robust`` the larger of it and the sandwich std (inf at
    zero)."""
    s = float((after.std or {}).get(name) or 0.0)
    if robust:
        r = (after.std_robust or {}).get(name)
        s = max(s, float(r)) if r is not None and np.isfinite(r) else s
    value = abs(float(after.theta[after.model.param_index(name)]))
    return s / value if value > 0 else np.inf


def _failed_test(rule: AcceptRule, ic: tuple, p: float, lr: float, err: tuple, dm: tuple,
                 where: str, grown_elsewhere: str | None = None,
                 pooled: str = "") -> str | None:
    """The first of :func:`decide`'s statistical tests that fails (None:
    all pass): the information criterion ``ic`` (before, after), the
    likelihood ratio ``lr`` (p-value ``p``), the error ``err`` (before,
    after), its growth on a further validation record (``grown_elsewhere``,
    :func:`_grown_elsewhere`) and its decrease test ``dm`` (z, p; ``pooled``:
    the further validation records' errors before and after, ", 'b' 0.8 ->
    0.799", when the test pooled them)."""
    (ic0, ic1), (e0, e1), (dz, dp) = ic, err, dm
    if not ic1 < ic0:
        return "information criterion did not improve"
    if not p < rule.significance:
        return f"likelihood-ratio test not passed (LR {lr:.3g}, p {p:.2g})"
    if np.isfinite(e0) and not e1 <= rule.metric_tolerance * e0:
        return f"the error grew{where} ({e0:.4g} -> {e1:.4g})"
    if grown_elsewhere:
        return grown_elsewhere
    if rule.error_level is not None and np.isfinite(dp) and not dp < rule.error_level:
        place = " over the validation records" if pooled else where
        return (f"the error decrease{place} is within its uncertainty ({e0:.4g} -> "
                f"{e1:.4g}{pooled}, z {dz:.2f}, p {dp:.2g})")
    return None


def pooled_errors(current: Fit, after: Fit) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The per-sample standardised free-run errors (M, n_y) of ``current``
    and ``after`` that the error-decrease test pairs: those behind
    :attr:`~bondgraph.diagnose.fit.Fit.accept_metric`, then, stacked below,
    those on each further validation record (``more_errors``) where both
    fits have them; (None, None) where the first pair is missing."""
    a0, a1 = getattr(current, "accept_errors", None), getattr(after, "accept_errors", None)
    if a0 is None or a1 is None or a0.shape != a1.shape:
        return None, None
    more0, more1 = getattr(current, "more_errors", {}), getattr(after, "more_errors", {})
    pairs = [(more0.get(k), more1.get(k)) for k in more1]
    pairs = [(b0, b1) for b0, b1 in pairs if b0 is not None and b1 is not None
             and b0.shape == b1.shape]
    if not pairs:
        return a0, a1
    return (np.vstack([a0, *(b0 for b0, _ in pairs)]),
            np.vstack([a1, *(b1 for _, b1 in pairs)]))


def _grown_elsewhere(rule: AcceptRule, current: Fit, after: Fit) -> str | None:
    """"the error grew on the validation record 'r' (a -> b)" for the first
    further validation record (``more_metrics``) whose free-run error grows
    by more than ``rule.metric_tolerance``; None where none does."""
    before = getattr(current, "more_metrics", {})
    for name, e1 in getattr(after, "more_metrics", {}).items():
        e0 = before.get(name, float("nan"))
        if np.isfinite(e0) and not e1 <= rule.metric_tolerance * e0:
            return f"the error grew on the validation record '{name}' ({e0:.4g} -> {e1:.4g})"
    return None


#: one-sided level of the test that a refit's free-run error on the
#: estimation record grew (:func:`grown_on_estimation`): only a clear
#: worsening refuses, not the noise of a free-run metric
ESTIMATION_GROWTH_LEVEL = 0.01


def grown_on_estimation(rule: AcceptRule, current: Fit, after: Fit) -> str | None:
    """"the error grew on the estimation record (a -> b, z, p)" when a
    validation record judges the decision and the refit's free-run error on
    the record it was fitted on grows by more than ``rule.metric_tolerance``
    and significantly so (:func:`error_decrease_test` of the reversed pair,
    p < :data:`ESTIMATION_GROWTH_LEVEL`); None otherwise (no validation
    record: that error is the one :func:`decide` tests already; either
    fit without per-sample errors)."""
    if after.validation_metric is None:
        return None
    e0, e1 = current.metric, after.metric
    if not (np.isfinite(e0) and np.isfinite(e1)) or e1 <= rule.metric_tolerance * e0:
        return None
    a0, a1 = getattr(current, "sim_errors", None), getattr(after, "sim_errors", None)
    if a0 is None or a1 is None or np.shape(a0) != np.shape(a1):
        return None
    z, p = error_decrease_test(a1, a0)
    if not (np.isfinite(p) and p < ESTIMATION_GROWTH_LEVEL):
        return None
    return (f"the error grew on the estimation record ({e0:.4g} -> {e1:.4g}, z {z:.2f}, "
            f"p {p:.2g}): the likelihood gained in the filter's one-step predictions while "
            f"the model's free run of the record it was fitted on got worse")


def _objection(current: Fit, after: Fit, lr: float, comparable: bool,
               admissible: Admissibility | None, box_free: Sequence[str],
               interior: Sequence[str], searched: Mapping[str, float]) -> str | None:
    """The first of :func:`decide`'s tests of the refit as a model (before
    the statistics): converged, admissible, simulating, finite, no declared
    parameter newly on its box, no ``interior`` one on its box, none on a
    search box that decides it (``searched``), identified (None: all pass)."""
    unstable = getattr(after, "unstable", None)
    finite = [v for v in (after.nll, after.accept_metric, after.metric, after.validation_metric,
                          *getattr(after, "more_metrics", {}).values())
              if v is not None]
    if not comparable:
        return (f"the refit did not converge ({after.iterations} iterations): its likelihood "
                f"ratio {lr:.3g} is not comparable")
    if admissible is not None and not admissible.ok:
        return f"the refit is not physically admissible: {admissible.reason()}"
    if unstable:
        return f"the refitted model does not simulate: {unstable}"
    if not all(np.isfinite(v) for v in finite):
        val = "" if after.validation_metric is None else \
            f", on the validation record {after.validation_metric:.4g}"
        val += "".join(f", on '{k}' {v:.4g}"
                       for k, v in getattr(after, "more_metrics", {}).items())
        return (f"the refit is not finite (NLL {after.nll:.4g}, error on the record "
                f"{after.metric:.4g}{val})")
    if pinned := newly_boxed(current, after, exempt=box_free):
        return f"the refit moves {pinned} onto its box: the box, not the record, decides it"
    if edge := at_family_edge(after, interior):
        return (f"the effect's {edge} ends on its box: the record asks for more than the "
                f"effect's family covers (its likelihood ratio there is not χ², Self & "
                f"Liang 1987)")
    if searched:
        text = _on_box_text(after, list(searched))
        gain = max(searched.values())
        return (f"the effect's {text} ends on the edge of the search box the loop set around "
                f"its start (the score test's estimate, within the reach of the effect's grid; "
                f"no physical limit), and beyond it the likelihood gains {gain:.3g} nats: the "
                f"box, not the record, decides it")
    return unidentified_effect(current, after) or None


def at_family_edge(after: Fit, interior: Sequence[str]) -> str:
    """The parameters of ``interior`` (new parameters an effect declares
    ``interior``, :class:`~bondgraph.diagnose.effects.base.EffectParam`)
    that the refit ``after`` leaves on a bound of their box, with value and
    box ("" when none)."""
    return _on_box_text(after, [n for n in interior if n in (after.at_bound or ())])


def newly_boxed(current: Fit, after: Fit, exempt: Sequence[str] = ()) -> str:
    """The declared physical parameters (estimated in ``current``, not noise
    intensities, not in ``exempt``) that ``current`` had inside their boxes
    and the refit ``after`` puts on a bound, with their boxes ("" when none).

    A candidate whose gain needs a declared parameter pushed onto the limit
    of what the user declared physical is compensating, not explaining (a
    sensor offset that pays for an idle fuel flow pinned on its box), and
    its likelihood ratio at a boundary is not χ²-distributed (Self & Liang
    1987): such a refit is not comparable. Parameters already on their box
    in ``current`` are reported by the declared fit's verdict instead, and
    noise intensities on a bound (a process noise driven to zero by an
    effect that explains the model error) are not a compensation.
    """
    return _on_box_text(after, [n for n in newly_boxed_names(current, after)
                                if n not in exempt])


def _on_box_text(after: Fit, names: Sequence[str]) -> str:
    """``name = value (box [lo, hi])`` of ``names`` in ``after``, comma
    separated ("" for none)."""
    if not names:
        return ""
    model = after.model
    lo, hi = model.bounds(names)
    return ", ".join(f"{n} = {after.theta[model.param_index(n)]:.4g} (box [{a:.4g}, {b:.4g}])"
                     for n, a, b in zip(names, lo, hi))


def newly_boxed_names(current: Fit, after: Fit) -> list[str]:
    """The names behind :func:`newly_boxed` (no exemption)."""
    names = [n for n in after.at_bound if n in current.params and n not in current.at_bound]
    if not names:
        return []
    noise = noise_params(current.model)
    return [n for n in names if n in after.model.params and n not in noise]


def pair_member_boxed(pair: Fit, new_params) -> str | None:
    """Why a pair is not a pair when a member's own parameters end on a bound
    of their boxes (None otherwise): such a member is switched off (a drag
    coefficient at 0) or pinned by its box, so the pair's gain is its
    partner's, which must then pass alone; the likelihood ratio at a
    boundary is not χ²-distributed either (Self & Liang 1987).

    Parameters
    ----------
    pair : Fit
        The pair's refit (``at_bound``: its estimates on a bound).
    new_params : sequence of str
        The members' new parameters.
    """
    boxed = [n for n in new_params if n in pair.at_bound]
    if not boxed:
        return None
    lo, hi = pair.model.bounds(boxed)
    return ("a member's parameter ends on its box (" + ", ".join(
        f"{n} = {pair.theta[pair.model.param_index(n)]:.4g}, box [{a:.4g}, {b:.4g}]"
        for n, a, b in zip(boxed, lo, hi)) + "): that member is switched off or pinned, "
        "the gain is its partner's alone")


def pair_needed(pair: Fit, singles: list, dofs: list[int], level: float) -> str | None:
    """Why a pair of effects is not needed as a pair, or None: the pair's
    refit must beat each member's own refit by a likelihood ratio
    2 (NLL_single − NLL_pair) significant at ``level`` under χ²(k_other),
    k_other the other member's new parameters (Wilks 1938); otherwise the
    pair's gain is the better member's alone.

    Parameters
    ----------
    pair : Fit
    singles : list of (Fit or None)
        Each member's own confirmation refit (None: unknown).
    dofs : list of int
        Each member's new parameters (in the order of ``singles``).
    level : float

    Returns
    -------
    str or None
        The reason (which member does as well alone, with the likelihood
        ratio and p-value), or None when both are needed.
    """
    for i, single in enumerate(singles):
        if single is None:
            return f"member {i + 1}'s own refit is not available"
        k_other = max(int(dofs[1 - i]), 1)
        lr = 2.0 * (single.nll - pair.nll)
        p = float(chi2.sf(lr, k_other)) if np.isfinite(lr) else float("nan")
        if not p < level:
            return (f"member {i + 1} alone does as well (LR of the pair over it {lr:.3g}, "
                    f"p {p:.2g})")
    return None


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
                d.lr, d.lr_p_value, cand.target.kind, [n for n in names if n not in current.params],
                list(cand.tied), held=dict(cand.held),
                more_errors={k: [current.more_metrics.get(k), v]
                             for k, v in after.more_metrics.items()})


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


def confirmed_record(current: Fit, after: Fit, dof: int, values: dict, rule: AcceptRule,
                     d: Decision | None = None) -> dict:
    """What report.json keeps of a candidate's confirmation refit
    (:attr:`bondgraph.diagnose.result.Candidate.confirmed`)."""
    lr = 2.0 * (current.nll - after.nll)
    rec = {"lr": lr, "dof": dof, "p_value": float(chi2.sf(lr, max(dof, 1))),
           "nll": after.nll, "criterion": after.information(rule.criterion),
           "error": after.metric, "validation_error": after.validation_metric,
           "whiteness": after.residuals.whiteness, "values": dict(values),
           "converged": after.converged, "iterations": after.iterations,
           "at_bound": list(after.at_bound)}
    if getattr(after, "more_metrics", None):
        rec["more_validation_errors"] = dict(after.more_metrics)
    if d is not None:
        rec.update(accepted=d.accepted, reason=d.reason,
                   error_z=None if not np.isfinite(d.error_z) else d.error_z,
                   error_p_value=None if not np.isfinite(d.error_p_value) else d.error_p_value)
    return rec
