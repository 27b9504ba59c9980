"""Records of the residual-tracing loop: the evidence for a candidate effect,
an accepted step, a rejection, a fit summary, and :class:`LoopResult`, which
holds everything a report of the loop needs (the report writer,
:mod:`bondgraph.report.loop_report`, reads nothing else)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from bondgraph.core.graph import BondGraph
from bondgraph.core.jsonsafe import to_jsonable
from bondgraph.data.records import ordinal
from bondgraph.diagnose.effects import Target
from bondgraph.diagnose.inference_calls import ROBUST_RATIO
from bondgraph.diagnose.residuals import ResidualReport


@dataclass
class Candidate:
    """Evidence for one effect at one place.

    Attributes
    ----------
    effect, title : str
        Name and title of the effect (:mod:`bondgraph.diagnose.effects`).
    target : Target
    kind : {"score", "likelihood ratio"}
        Score test (additive effects; Rao 1948) or likelihood ratio over a
        grid (structural effects).
    statistic : float
        χ² statistic; ``dof`` its degrees of freedom, ``p_value`` its
        upper tail probability.
    score : float
        Predicted AIC decrease, statistic − 2 dof (Akaike 1974).
    explained : float or None
        Share of the whitened innovation energy the candidate explains
        (score test only).
    values : dict
        Estimated effect parameters (one-step or grid values).
    confirmed_statistic : float or None
        Likelihood ratio of the confirmation refit.
    last_resort : bool
        An effect scored only when no physical effect is significant.
    equivalent : list of str
        Candidates whose innovation signatures are indistinguishable from this
        one in this record (|correlation| > 0.999 with the estimated
        parameters partialled out): the data cannot tell them apart.
    absorbed : bool
        The candidate's innovation signature lies in the span of the
        estimated parameters' signatures (multiple correlation > 0.999,
        score test only): the declared model with re-estimated parameters
        reproduces the effect (a viscous friction next to an estimated
        damper), so the record cannot show it as missing.
    profile : dict
        Declared parameters re-fitted together with a structural candidate
        when it was scored (name -> value; empty if they stayed frozen); its
        confirmation starts from them.
    profiled : bool
        Structural candidates: False when the grid's best was not profiled
        (:func:`bondgraph.diagnose.scoring.worth_profiling`: the grid and
        the predicted gain of a scoring step stay below the critical value);
        its statistic is then the grid's, a lower bound.
    failed : str or None
        Why the candidate could not be scored (the filter failed: its reason);
        its statistic, p-value and score are then NaN, never a χ² of 0.
    limit_of : list of str
        Candidates this structural one became when scored: a parameter ended
        on the end of its span where the effect is another one
        (``Effect.limits``); marked equivalent to them once all are scored.
    joint_step : dict
        Score test only: the one-step (Gauss-Newton) estimates of the
        candidate *with* the estimated parameters moving, from the same
        normal equations as the statistic: ``"effect"`` (local name -> β,
        the one-step ``values`` before the line probe) and ``"estimated"``
        (full name -> the accompanying change of each estimated parameter);
        empty for other candidates. Its confirmation searches along this
        line (:func:`bondgraph.diagnose.confirm.score_line_starts`).
    tied : list of str
        Confirmed candidates whose refits the record cannot tell from this
        one's, the confirmed lead's (Vuong's test at ``settings.accept.tie_level``,
        :func:`bondgraph.diagnose.accept.vuong_test`; each one's ``confirmed``
        holds ``tie_z`` and ``tie_p``).
    confirmed : dict or None
        The confirmation refit: ``lr``, ``dof``, ``nll``, ``criterion``
        (after), ``error`` (free-run, record), ``validation_error``,
        ``whiteness``, ``values``, ``converged``, ``iterations``,
        ``at_bound``, and once decided ``accepted`` and ``reason``.
    held : dict
        Parameters of the effect held at their neutral value in its refit
        (local name -> value): a candidate whose refit the record cannot
        tell apart from the current model along these is refitted with its
        other terms alone (:func:`bondgraph.diagnose.runner.held_retry`);
        empty for every scored candidate.
    reach : float or None
        Profiled structural candidates: the likelihood ratio their refit
        could reach, the statistic plus the predicted gain of the scoring
        steps the profile did not take
        (:func:`bondgraph.diagnose.scoring.profile_reach`); an unconfirmed
        candidate whose reach comes near the best refit of its step is
        confirmed too (:func:`bondgraph.diagnose.runner.within_reach`).
        None for other candidates (their statistic is their reach).
    same_as : str or None
        The better-ranked candidate whose augmented model this one's is
        (:func:`bondgraph.diagnose.confirm.same_model_key`: a law at either
        of two R elements on one 1-junction); its confirmation is that
        one's refit evaluated on its own graph, and it takes no place of
        its own among the pairs (a pair with it is the pair with that one).
    screened : bool
        Its statistic is the output-error likelihood ratio of the screen
        (the physical parameters refitted with it by a global output-error
        search, :func:`bondgraph.diagnose.screen.output_error_screen`), which
        raised it above its score test's; ``explained`` stays the score
        test's share.
    """

    effect: str
    title: str
    target: Target
    kind: str
    statistic: float
    dof: int
    p_value: float
    score: float
    explained: float | None = None
    values: dict = field(default_factory=dict)
    confirmed_statistic: float | None = None
    last_resort: bool = False
    equivalent: list = field(default_factory=list)
    absorbed: bool = False
    failed: str | None = None
    confirmed: dict | None = None
    profile: dict = field(default_factory=dict)
    limit_of: list = field(default_factory=list)
    tied: list = field(default_factory=list)
    joint_step: dict = field(default_factory=dict)
    profiled: bool = True
    held: dict = field(default_factory=dict)
    reach: float | None = None
    same_as: str | None = None
    screened: bool = False

    @property
    def test(self) -> str:
        """The test behind ``statistic``, as the report names it: ``kind``,
        or "output-error LR (screen)" for a :attr:`screened` candidate."""
        return "output-error LR (screen)" if self.screened else self.kind

    @property
    def rank_key(self) -> float:
        """Sort key, best first: −score, failed (NaN) candidates last."""
        return -self.score if np.isfinite(self.score) else float("inf")

    @property
    def label(self) -> str:
        """``"effect @ target"`` (with ``" (dc = 0)"`` for its held parameters)."""
        held = "".join(f" ({k} = {v:g})" for k, v in self.held.items())
        return f"{self.effect} @ {self.target.name}{held}"

    def to_dict(self) -> dict:
        """JSON-ready fields plus ``label``."""
        d = asdict(self)
        d["target"] = {"kind": self.target.kind, "name": self.target.name}
        d["label"] = self.label
        return to_jsonable(d)


@dataclass
class Step:
    """One accepted effect: the accept error (the validation record's
    free-run error if there is one, else the record's), NLL, information
    criterion and whiteness before and after, the parameters after (estimate
    and Cramér-Rao std), the candidate's statistic; the record's own
    free-run error before and after, whether the error is the validation
    record's, the confirmed likelihood ratio and its p-value, the target's
    kind and the effect's parameter names, and the confirmed candidates the
    record could not tell from it (``tied``, Vuong's test), and the effects
    accepted with it as a pair (``together_with``: the step's numbers are
    the pair's, :func:`bondgraph.diagnose.runner.accepted_pair`), and the
    effects accepted earlier that this step removed (``removed``: switched
    off by it and no longer wanted by the accept rule,
    :func:`bondgraph.diagnose.runner.pruned`; the step's numbers are those
    of the model without them), and the effect's parameters held at their
    neutral value (``held``, local name -> value,
    :func:`bondgraph.diagnose.runner.held_retry`)."""

    effect: str
    attached_to: str
    metric: str
    error_before: float
    error_after: float
    nll_before: float
    nll_after: float
    criterion_before: float
    criterion_after: float
    whiteness_before: float
    whiteness_after: float
    parameters: dict
    statistic: float
    p_value: float
    estimation_error_before: float | None = None
    estimation_error_after: float | None = None
    validated: bool = False
    lr: float | None = None
    lr_p_value: float | None = None
    target_kind: str | None = None
    effect_params: list = field(default_factory=list)
    tied: list = field(default_factory=list)
    together_with: list = field(default_factory=list)
    removed: list = field(default_factory=list)
    held: dict = field(default_factory=dict)
    #: effects accepted earlier that this step's refit replaced by a rival
    #: at their place ("r_cubic @ Rwall by radiation";
    #: :func:`bondgraph.diagnose.runner.replaced_earlier`): the step's numbers
    #: are those of the model with the rival
    replaced: list = field(default_factory=list)
    #: the likelihood ratio's scale for serially correlated innovations and
    #: the p-value of ``lr`` divided by it (information; None where not
    #: computed, :func:`bondgraph.diagnose.fit.robust_lr`)
    lr_scale: float | None = None
    lr_robust_p_value: float | None = None
    #: the error on each further validation record before and after
    #: (record name -> [before, after]; ``LoopSettings.more_validation``)
    more_errors: dict = field(default_factory=dict)

    def shown(self) -> str:
        """The effect as the step tables show it: with its parameters held
        at 0 (:attr:`Candidate.held`), its pair partners' effects (their
        places in :meth:`shown_target`), the effects it removed and those it
        replaced by a rival."""
        return (self.effect + "".join(f" ({k} = {v:g})" for k, v in self.held.items())
                + "".join(f" + {w.split(' @ ')[0]}" for w in self.together_with)
                + "".join(f" (removing {r})" for r in self.removed)
                + "".join(f" (replacing {r})" for r in getattr(self, "replaced", ())))

    def shown_target(self) -> str:
        """Where the step tables say the effect attached: with its pair
        partners' places, in the order of :meth:`shown`."""
        return self.attached_to + "".join(
            f" + {w.split(' @ ', 1)[1]}" if " @ " in w else "" for w in self.together_with)


#: the phrase :func:`bondgraph.diagnose.accept.fitted_part_only` adds to a
#: refusal by the validation record's error (:meth:`LoopResult.none_accepted`
#: finds it there)
FITTED_PART_ONLY = "; on the estimation record its error fell"


@dataclass
class Rejection:
    """A confirmed candidate that was not accepted, with the reason."""

    step: int
    candidate: Candidate
    reason: str
    criterion_after: float
    whiteness_after: float

    def to_dict(self) -> dict:
        """JSON-ready: ``step``, the candidate's fields, ``reason``,
        ``criterion_after``, ``whiteness_after``."""
        return to_jsonable({"step": self.step, **self.candidate.to_dict(), "reason": self.reason,
                            "criterion_after": self.criterion_after,
                            "whiteness_after": self.whiteness_after})


@dataclass
class AppliedEffect:
    """An accepted effect as the augmented model file re-applies it;
    ``spec`` is ``module:Class`` of a user-supplied effect (None for the
    library's own effects, found by name)."""

    effect: str
    target: Target
    values: dict
    spec: str | None = None


def robust_of(summary) -> dict:
    """A fit summary's robust std by name ({} when it has none: a summary
    from before they existed, or a stand-in)."""
    return getattr(summary, "std_robust", None) or {}


def understated(std: dict, robust: dict, names) -> list[str]:
    """The ``names`` whose robust std (``robust``, by name) exceeds their
    Cramér-Rao std (``std``) by more than
    :data:`~bondgraph.inference.robust.ROBUST_RATIO`, each with the ratio
    ("c (24x)"), largest first."""
    ratio = {n: robust[n] / std[n] for n in names
             if std.get(n) and robust.get(n) is not None}
    return [f"{n} ({r:.3g}x)" for n, r in sorted(ratio.items(), key=lambda kv: -kv[1])
            if r > ROBUST_RATIO]


#: a declared parameter the accepted effects moved by more than this fraction
#: of its declared-fit value ... (:func:`moved_declared`)
MOVED_REL = 0.25
#: ... and by more than this many of its std (the largest of the declared
#: fit's and the final fit's Cramér-Rao and robust std)
MOVED_STD = 10.0


def moved_declared(result) -> list[tuple[str, float, float]]:
    """``(name, declared fit's value, final value)`` of the declared
    physical parameters (not the noise levels of its sensors and process
    noise) that the accepted effects moved by more than :data:`MOVED_REL` of
    their value and :data:`MOVED_STD` std ([] when no effect was accepted).

    Where the declared fit compensated for the missing effect (a rolling
    resistance that stood in for the aerodynamic drag) that is the
    correction; where the library lacks the law, an effect that rescales the
    model can stand in for it and take the declared parameters with it: a
    user's heated block whose radiation the library did not have took a
    power law, a capacity limit and an actuator gain of -0.86 on its
    heater, and its heat capacity went from 800 to 112 J/K, each step
    lowering the held-out error. The report names such moves; the user
    knows the values."""
    initial, final = getattr(result, "initial", None), getattr(result, "final", None)
    if not getattr(result, "steps", None) or not all(
            hasattr(f, a) for f in (initial, final) for a in ("estimates", "std")):
        return []
    g = getattr(result, "declared_graph", None)
    noise: set = set()
    if g is not None:
        for ex in [*g.process_noise.values(), *(s.noise_std for s in g.sensors.values())]:
            noise |= {str(x) for x in getattr(ex, "free_symbols", ())}
    declared = set(g.params) if g is not None else set(initial.estimates)
    r0, r1 = robust_of(initial), robust_of(final)
    out = []
    for n, v0 in initial.estimates.items():
        v1 = final.estimates.get(n)
        if n not in declared or n in noise or v1 is None or not v0:
            continue
        if not (np.isfinite(v0) and np.isfinite(v1)):
            continue
        sds = [x for x in (initial.std.get(n), r0.get(n), final.std.get(n), r1.get(n))
               if x is not None and np.isfinite(x)]
        shift = abs(v1 - v0)
        if shift > MOVED_REL * abs(v0) and shift > MOVED_STD * max(sds, default=0.0):
            out.append((n, float(v0), float(v1)))
    return out


def moved_text(moves: list[tuple[str, float, float]]) -> str:
    """One sentence on :func:`moved_declared`'s moves ("" for none)."""
    if not moves:
        return ""
    items = ", ".join(f"{n} {a:.4g} -> {b:.4g} ({100 * (b - a) / abs(a):+.0f} %)"
                      for n, a, b in moves)
    return (f"the accepted effects moved declared parameters far from the declared fit "
            f"(by more than {100 * MOVED_REL:.0f} % and {MOVED_STD:g} std): {items}. Where the "
            f"declared fit compensated for the missing effect, that is the correction; where "
            f"you know a value, compare: an effect that rescales the model (a gain, a limit) "
            f"can stand in for a law the library lacks. Hold a known value (--fixed NAME=VALUE) "
            f"and run again to see")


@dataclass
class FitSummary:
    """One fitted model as the report sees it.

    Attributes
    ----------
    model : str
        Graph name.
    nll, aic, bic, metric, whiteness : float
        Negative log-likelihood, Akaike and Schwarz criteria, the reported
        error, the sum of the Ljung-Box statistics of the innovations.
    estimates, std : dict
        Estimated parameters and their Cramér-Rao standard deviations.
    residuals : ResidualReport
    sim_y : array (N, n_y) or None
        Free-run simulated outputs.
    innovations, innovation_var : arrays (N, n_y)
        One-step UKF innovations and their variances (diagonal of S).
    at_bound : list of str
        Estimates on a bound of their box (their std is None).
    noise_floor : list of str
        Those of ``at_bound`` that are process-noise intensities on the
        floor of their box (:func:`bondgraph.diagnose.fit.process_noise_at_floor`):
        a random walk the record does not ask for, no warning.
    validation_metric : float or None
        The metric on the validation record (None without one).
    x0_estimates : dict
        Initial states estimated with θ (state name -> value); their
        Cramér-Rao std in ``std`` as ``x0.<state>``.
    noise_estimates : dict
        Measurement-noise stds estimated with θ (output -> std, output
        units); their Cramér-Rao std in ``std`` as ``noise.<output>``.
    flat : list of str
        Quantities the record does not identify separately: the likelihood
        is flat along a combination of them where the fit stopped
        (:attr:`bondgraph.inference.fisher.Scoring.flat`).
    ridge : str
        That combination as relative changes when it is a scale symmetry
        (:func:`bondgraph.diagnose.fit.ridge_changes`; "; as relative
        changes: ..."), else "".
    std_robust : dict
        Robust (sandwich) standard deviations by name, where the fit gave
        them (:func:`bondgraph.inference.robust.robust_std`): larger than
        ``std`` when the model's misfit is serially correlated.
    validation_sim_y : array (N_v, n_y) or None
        Free-run simulated outputs on the validation record (None without
        one, or where the free run failed there).
    more_metrics : dict
        The metric on each further validation record (record name -> value;
        ``LoopSettings.more_validation``).
    more_sim_y : dict
        The free run's outputs (N_r, n_y) on each further validation record
        (record name -> array, None where it failed).
    """

    model: str
    nll: float
    aic: float
    bic: float
    metric: float
    whiteness: float
    estimates: dict
    std: dict
    residuals: ResidualReport
    sim_y: np.ndarray | None
    innovations: np.ndarray
    innovation_var: np.ndarray
    at_bound: list = field(default_factory=list)
    validation_metric: float | None = None
    x0_estimates: dict = field(default_factory=dict)
    noise_estimates: dict = field(default_factory=dict)
    flat: list = field(default_factory=list)
    std_robust: dict = field(default_factory=dict)
    ridge: str = ""
    validation_sim_y: np.ndarray | None = None
    noise_floor: list = field(default_factory=list)
    more_metrics: dict = field(default_factory=dict)
    more_sim_y: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-ready summary (no arrays)."""
        return to_jsonable({"model": self.model, "nll": self.nll, "aic": self.aic,
                            "bic": self.bic, "metric": self.metric, "whiteness": self.whiteness,
                            "validation_metric": self.validation_metric,
                            "more_validation_metrics": self.more_metrics,
                            "at_bound": self.at_bound, "noise_floor": self.noise_floor,
                            "x0_estimates": self.x0_estimates,
                            "noise_estimates": self.noise_estimates, "flat": self.flat,
                            "ridge": self.ridge,
                            "estimates": self.estimates, "std": self.std,
                            "std_robust": robust_of(self), "residuals": self.residuals.to_dict()})


@dataclass
class DiscoveryPlot:
    """What the report shows of a discovery (issue 29): the reconstructed
    missing effort (flow) at a port against the discovered law.

    Attributes
    ----------
    port, kind, unit : str
        The junction, ``"effort"`` or ``"flow"``, the law's unit.
    t : ndarray (N,)
        Sample times [s].
    d, d_std : ndarray (N,)
        The reconstructed signal d̂(t) and its smoother std [unit].
    law : ndarray (N,)
        The law evaluated on the port's variables along the record (its
        coefficients refitted by the loop when it accepted the law, else
        as discovered) [unit].
    text : str
        The law, readable, each coefficient with its Cramér-Rao std where
        known.
    passivity : str
        The passivity check's summary and the law's placement (R element,
        storage law, source).
    accepted : bool
        The loop accepted the law.
    """

    port: str
    kind: str
    unit: str
    t: np.ndarray
    d: np.ndarray
    d_std: np.ndarray
    law: np.ndarray
    text: str
    passivity: str
    accepted: bool = False

    def to_dict(self) -> dict:
        """JSON-ready: the text fields (no arrays)."""
        return {"port": self.port, "kind": self.kind, "unit": self.unit, "law": self.text,
                "passivity": self.passivity, "accepted": self.accepted}


@dataclass
class LoopResult:
    """What :func:`bondgraph.diagnose.runner.run_loop` returns (and hands to
    ``on_update`` while it runs, with ``finished`` False).

    Attributes
    ----------
    model, source : str
        Declared graph name and its builder (``module:function``, or None).
    record : str or None
        Record name.
    metric : str
        Name of the reported error measure.
    criterion : str
        ``"aic"`` or ``"bic"``.
    settings : dict
        :meth:`LoopSettings.summary`.
    initial, final : FitSummary
        The declared model's fit and the current (final) model's fit.
    final_graph : BondGraph
        The current (final) augmented graph.
    steps : list of Step
    rejected : list of Rejection
    rankings : list of list of Candidate
        Every step's candidates, best first (the evidence plots draw them).
    applied : list of AppliedEffect
    time : array (N,)
        Sample times [s].
    measured : array (N, n_y)
        Measured outputs of the final model (NaN where missing).
    validation_time : array (N_v,) or None
        Sample times of the validation record [s] (None without one).
    validation_measured : array (N_v, n_y) or None
        Its measured outputs of the final model (NaN where missing).
    more_measured : dict
        Each further validation record's sample times [s] (N_r,) and
        measured outputs (N_r, n_y), record name -> (t, y).
    outputs, output_units : list of str
    finished : bool
        False for the partial results handed to ``on_update`` during the run.
    warnings : list of str
        Warnings about the declared fit (discretisation error, estimates on
        a bound).
    true_effect : dict or None
        The synthetic truth's effect (kind, target, values), if known.
    truth_ranks : list of (int or None)
        Rank of the true effect in every step's ranking (:func:`rank_of`).
    declared_graph : BondGraph or None
        A copy of the declared graph (the augmented model file rebuilds it
        from a pickle when the graph has no ``module:function`` source).
    discovery : DiscoveryPlot or None
        When discovery ran (:func:`bondgraph.diagnose.discover.effect.loop_with_discovery`,
        ``bondgraph loop --discover``): the reconstruction against the law.
    final_checks : list of str
        The warnings of the checks at the final model (the input holds,
        :func:`bondgraph.diagnose.runner.hold_at_final`; a sensor's
        glitches, :func:`bondgraph.diagnose.runner.glitches`), also in
        ``warnings``: the command line repeats them under its summary; and
        the final estimates' refit within the free-run bias bound
        (:func:`bondgraph.diagnose.runner.unbiased_final`), a ``"note: "``
        where it was kept.
    """

    model: str
    source: str | None
    record: str | None
    metric: str
    criterion: str
    settings: dict
    initial: FitSummary | None = None
    final: FitSummary | None = None
    final_graph: BondGraph | None = None
    steps: list[Step] = field(default_factory=list)
    rejected: list[Rejection] = field(default_factory=list)
    rankings: list[list[Candidate]] = field(default_factory=list)
    applied: list[AppliedEffect] = field(default_factory=list)
    time: np.ndarray | None = None
    measured: np.ndarray | None = None
    validation_time: np.ndarray | None = None
    validation_measured: np.ndarray | None = None
    more_measured: dict = field(default_factory=dict)
    outputs: list[str] = field(default_factory=list)
    output_units: list[str] = field(default_factory=list)
    finished: bool = False
    warnings: list[str] = field(default_factory=list)
    true_effect: dict | None = None
    truth_ranks: list = field(default_factory=list)
    declared_graph: BondGraph | None = None
    discovery: DiscoveryPlot | None = None
    final_checks: list[str] = field(default_factory=list)

    def records(self) -> str:
        """Which records the loop fitted and judged on, one sentence: the
        estimation record's name and samples, the validation record's (held
        out or given), and each output's missing samples (NaN in
        :attr:`measured`, :attr:`validation_measured`). report.md and
        report.html say it alike."""
        def part(name, t, y) -> str:
            if t is None:
                return f"`{name}`"
            miss = [] if y is None else [
                f"{o}: {int(n)} missing" for o, n in
                zip(self.outputs or [], np.isnan(np.asarray(y, float)).sum(axis=0)) if n]
            return f"`{name}` ({len(t)} samples{'; ' + ', '.join(miss) if miss else ''})"
        line = f"Record: {part(self.record, self.time, self.measured)}."
        val = (self.settings or {}).get("validation")
        if val:
            held = part(val, self.validation_time, self.validation_measured)
            line += f" Validation record: {held}, not fitted."
            more = list((self.settings or {}).get("more_validation") or [])
            if more:
                line += (f" Further validation records, not fitted: "
                         f"{', '.join(f'`{m}`' for m in more)}; the accepted model's error "
                         f"grows on none of them.")
            n = int(((self.settings or {}).get("free_run") or {}).get("init_samples") or 0)
            if n:
                line += (f" Its free runs start from its first {n} samples only and are "
                         f"judged on the samples after them.")
        return line + self._grid_note()

    def _grid_note(self) -> str:
        """What was done to the file's samples before the loop
        (``settings["decimated"]``, ``settings["finer_grid"]``,
        :func:`bondgraph.diagnose.runner.settings_summary`), one sentence or
        ""."""
        settings = self.settings or {}
        dec, fine = settings.get("decimated"), settings.get("finer_grid")
        out = ""
        if dec:
            means = list(dec.get("means") or [])
            out += (f" The records are every {ordinal(dec['factor'])} sample of their files"
                    + (f" ({', '.join(means)} averaged over each interval, the rest "
                       f"point-sampled; --decimate)" if means else " (point-sampled; --decimate)")
                    + ".")
        if fine:
            out += (f" Filtered on a grid {fine.get('factor', 2)} times finer than the samples "
                    f"({', '.join(fine.get('interpolated') or [])} interpolated band-limited).")
        return out

    def more_validation(self) -> list[tuple[str, float | None, float]]:
        """``(record, before, after)``: the error on each further validation
        record (``LoopSettings.more_validation``) of the declared fit and of
        the final model, in the order given; empty without them."""
        before = getattr(self.initial, "more_metrics", None) or {}
        after = getattr(self.final, "more_metrics", None) or {}
        return [(k, before.get(k), v) for k, v in after.items()]

    def numerics(self) -> str | None:
        """How the models were stepped, one sentence: the filter's method,
        substeps and input hold at the start (each input's by name for a
        per-input hold), those at the end where an accepted fit's check
        changed them (``settings["ukf_final"]``), and the free runs' solver
        and hold; None without them. report.md and report.html say it alike."""
        u, fr = (self.settings or {}).get("ukf"), (self.settings or {}).get("free_run")
        if not u:
            return None
        hold = str(u.get("hold", "zoh"))
        names = list(getattr(self.declared_graph, "inputs", None) or [])
        parts = hold.split(",")
        each = (" (" + ", ".join(f"{n} {h}" for n, h in zip(names, parts)) + ")"
                if len(parts) > 1 and len(parts) == len(names) else "")
        runs = [r for r in u.get("refine") or () if r[2] > int(u.get("substeps") or 1)]
        more = (f"; up to {max(r[2] for r in runs)} on {sum(r[1] - r[0] for r in runs)} "
                f"intervals" if runs else "")
        line = (f"Numerics: UKF with {u.get('method')}({u.get('substeps')}{more}) per sample at "
                f"the start, input hold {hold}{each}")
        end = (self.settings or {}).get("ukf_final")
        if end:
            line += (f"; {end.get('method')}({end.get('substeps')}"
                     + (" on the intervals that need them" if end.get("refine") else "")
                     + ") at the end (the discretisation check at an accepted fit, or the "
                       "final estimates refitted within its free-run bias bound)")
        if fr:
            how = ("the filter's method at 4x its substeps" if fr.get("method") == "fine"
                   else f"solve_ivp {fr.get('method')}")
            line += f"; free runs {how}, input hold {fr.get('hold')}"
        return line + "."

    def none_accepted(self) -> str:
        """Why no effect was accepted (for a result without steps), one
        phrase: "no step ran"; "N confirmed candidate(s) refused by the
        accept rule (the first three named)", their reasons in
        :attr:`rejected`, and where the validation record refused some
        whose error fell significantly on the estimation record
        (:func:`~bondgraph.diagnose.accept.fitted_part_only`), what that
        means and what to do; or "nothing significant left". The command's
        summary, report.md and report.html say it alike."""
        if not self.rankings:
            return "no step ran"
        refused = list(dict.fromkeys(r.candidate.label for r in self.rejected))
        if not refused:
            return "nothing significant left"
        named = ", ".join(refused[:3]) + (", ..." if len(refused) > 3 else "")
        text = f"{len(refused)} confirmed candidate(s) refused by the accept rule ({named})"
        only = list(dict.fromkeys(r.candidate.label for r in self.rejected
                                  if FITTED_PART_ONLY in r.reason))
        if only:
            text += (f"; the validation record refused {', '.join(only[:3])}"
                     f"{', ...' if len(only) > 3 else ''} although the estimation record's "
                     f"error fell significantly: such an effect fits that record's "
                     f"peculiarities, or acts only where the validation record does not reach "
                     f"(a transient at the start of a record, such as a warm-up, is absent from "
                     f"its held-out end); judge it on a record where it acts (--validate FILE), "
                     f"or fit and judge the whole record (--holdout 0)")
        return text

    def table(self) -> str:
        """Markdown table of the accepted steps (error = :attr:`metric`; with
        a validation record, the validation error and the estimation
        record's error beside it; with further validation records, one
        column each, "before -> after")."""
        val = any(s.validated for s in self.steps)
        more = list(dict.fromkeys(k for s in self.steps for k in getattr(s, "more_errors", {})))
        head = ("| step | effect | attached to | validation error before | validation error after "
                "| estimation error before | estimation error after |" if val else
                "| step | effect | attached to | error before | error after |")
        head += "".join(f" error on {k} |" for k in more)
        rows = [head + " NLL before | NLL after |",
                "|---" * ((9 if val else 7) + len(more)) + "|"]
        for i, s in enumerate(self.steps, 1):
            est = (f" {_num(s.estimation_error_before)} | {_num(s.estimation_error_after)} |"
                   if val else "")
            est += "".join(" {} -> {} |".format(*(_num(v) for v in s.more_errors.get(k, (None,) * 2)))
                           for k in more)
            rows.append(f"| {i} | {s.shown()} | {s.shown_target()} | {s.error_before:.4g} | "
                        f"{s.error_after:.4g} |{est} {s.nll_before:.1f} | {s.nll_after:.1f} |")
        return "\n".join(rows)

    def to_dict(self, ranked: int | None = None) -> dict:
        """JSON-ready content of ``report.json``: model, source, record,
        metric, criterion, finished, error before/after (the record's
        free-run error) and the validation error before/after (None without
        a validation record), steps, rejected, every step's ranking (all
        candidates, or the ``ranked`` best), initial and final fits, settings."""
        return to_jsonable({
            "model": self.model, "source": self.source, "record": self.record,
            "metric": self.metric, "criterion": self.criterion, "finished": bool(self.finished),
            "error_before": self.initial.metric, "error_after": self.final.metric,
            "validation_error_before": self.initial.validation_metric,
            "validation_error_after": self.final.validation_metric,
            "more_validation_errors": {
                k: {"before": self.initial.more_metrics.get(k), "after": v}
                for k, v in self.final.more_metrics.items()},
            "steps": [dict(vars(s)) for s in self.steps],
            "rejected": [r.to_dict() for r in self.rejected],
            "rankings": [[c.to_dict() for c in r[:ranked]] for r in self.rankings],
            "initial_fit": self.initial.to_dict(), "final_fit": self.final.to_dict(),
            "settings": self.settings, "warnings": list(self.warnings),
            "true_effect": self.true_effect, "truth_ranks": list(self.truth_ranks),
            "discovery": None if self.discovery is None else self.discovery.to_dict(),
        })


def _num(v) -> str:
    """``v`` with 4 significant digits, or "—" for None."""
    return "—" if v is None else f"{v:.4g}"


def rank_of(ranking: list[Candidate], kind: str, target: str) -> int | None:
    """1-based rank of the candidate ``kind @ target`` in ``ranking`` (best
    first), a group of indistinguishable candidates (``equivalent``)
    counting as one place; None if it is not in the ranking."""
    place, seen, label = 0, set(), f"{kind} @ {target}"
    for c in ranking:
        if c.label in seen:
            continue
        place += 1
        group = {c.label, *c.equivalent}
        seen |= group
        if label in group:
            return place
    return None
