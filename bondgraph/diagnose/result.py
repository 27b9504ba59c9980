"""Records of the residual-tracing loop: the evidence for a candidate effect,
an accepted step, a rejection, a fit summary, and :class:`LoopResult`, which
holds everything a report of the loop needs (the report writer,
:mod:`bondgraph.report.loop_report`, reads nothing else)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from bondgraph.core.graph import BondGraph
from bondgraph.core.jsonsafe import to_jsonable
from bondgraph.diagnose.effects import Target
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

    @property
    def label(self) -> str:
        """``"effect @ target"``."""
        return f"{self.effect} @ {self.target.name}"

    def to_dict(self) -> dict:
        """JSON-ready fields plus ``label``."""
        d = asdict(self)
        d["target"] = {"kind": self.target.kind, "name": self.target.name}
        d["label"] = self.label
        return to_jsonable(d)


@dataclass
class Step:
    """One accepted effect: the reported error, NLL, information criterion
    and whiteness before and after, the parameters after (estimate and
    Cramér-Rao std), and the candidate's statistic."""

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
    """An accepted effect as the augmented model file re-applies it."""

    effect: str
    target: Target
    values: dict


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

    def to_dict(self) -> dict:
        """JSON-ready summary (no arrays)."""
        return to_jsonable({"model": self.model, "nll": self.nll, "aic": self.aic,
                            "bic": self.bic, "metric": self.metric, "whiteness": self.whiteness,
                            "estimates": self.estimates, "std": self.std,
                            "residuals": self.residuals.to_dict()})


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
    outputs, output_units : list of str
    finished : bool
        False for the partial results handed to ``on_update`` during the run.
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
    outputs: list[str] = field(default_factory=list)
    output_units: list[str] = field(default_factory=list)
    finished: bool = False

    def table(self) -> str:
        """Markdown table of the accepted steps (error = :attr:`metric`)."""
        rows = ["| step | effect | attached to | error before | error after | NLL before | NLL after |",
                "|---|---|---|---|---|---|---|"]
        for i, s in enumerate(self.steps, 1):
            rows.append(f"| {i} | {s.effect} | {s.attached_to} | {s.error_before:.4g} | "
                        f"{s.error_after:.4g} | {s.nll_before:.1f} | {s.nll_after:.1f} |")
        return "\n".join(rows)

    def to_dict(self, ranked: int = 25) -> dict:
        """JSON-ready content of ``report.json``: model, source, record,
        metric, criterion, finished, error before/after, steps, rejected,
        the ``ranked`` best candidates of every step, initial and final
        fits, settings."""
        return to_jsonable({
            "model": self.model, "source": self.source, "record": self.record,
            "metric": self.metric, "criterion": self.criterion, "finished": bool(self.finished),
            "error_before": self.initial.metric, "error_after": self.final.metric,
            "steps": [dict(vars(s)) for s in self.steps],
            "rejected": [r.to_dict() for r in self.rejected],
            "rankings": [[c.to_dict() for c in r[:ranked]] for r in self.rankings],
            "initial_fit": self.initial.to_dict(), "final_fit": self.final.to_dict(),
            "settings": self.settings,
        })
