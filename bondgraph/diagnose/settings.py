"""Options of the residual-tracing loop (:func:`bondgraph.diagnose.runner.run_loop`)."""

from __future__ import annotations

import numbers
from dataclasses import dataclass, field, fields
from typing import Any, Sequence

from bondgraph.diagnose.effects import DEFAULT_EFFECTS, Effect
from bondgraph.errors import OptionError
from bondgraph.inference.executor import scheduler_address
from bondgraph.inference.options import NOISE_MODES, UKFOptions

#: the built-in error measures (``LoopSettings.metric``; bondgraph.diagnose.metric)
METRICS = ("nrmse_sim", "rmse_sim", "rmse_pred")
#: information criteria of the accept decision
CRITERIA = ("aic", "bic")


#: the fraction of a user's record (``bondgraph loop --model M --data D``,
#: no ``--validate``) held out at its end for the accept decision and the
#: report's error before/after (``--holdout 0`` fits the whole record)
DEFAULT_HOLDOUT = 0.25


@dataclass
class LoopSettings:
    """Options of :func:`bondgraph.diagnose.runner.run_loop`.

    Attributes
    ----------
    params : list of str
        Parameters of the declared model estimated at every step.
    metric : str or callable
        Error measure reported before/after: ``"nrmse_sim"`` (mean over
        outputs of RMS(free-run simulation error)/std(measurement)),
        ``"rmse_sim"`` (RMS over outputs, output units), ``"rmse_pred"``
        (RMS of the one-step innovations), or a callable
        ``metric(fit, data) -> float`` with attribute ``name``
        (``data``: a :class:`bondgraph.diagnose.fit.Record`).
    criterion : {"aic", "bic"}
        Information criterion of the accept decision (Akaike 1974; Schwarz 1978).
    max_steps : int
    significance : float
        Family-wise level for "a significant effect is left" (Bonferroni over
        the candidates evaluated).
    confirm_top : int
        Candidates confirmed by a real fit per round.
    confirm_rounds : int
        Rounds of confirmation per step: when none of a round's confirmed
        candidates passes the accept rule, the next ``confirm_top``
        significant ones are confirmed, up to this many rounds (default 3:
        the score tests of additive candidates, first order, and the grid
        likelihood ratios of structural ones do not compare exactly; a
        user's two tanks whose pump saturates ranked the saturation 7th
        behind six additive candidates that all raised the held-out error).
    tie_level : float
        Level of Vuong's (1989) test between the confirmed lead and each
        other confirmed candidate: a candidate whose per-sample likelihood
        does not differ from the lead's at this two-sided level is reported
        as tied with it (``Candidate.tied``; the record cannot tell them
        apart, e.g. a source lag and a sensor low-pass on a linear graph).
    structural : bool or "always"
        Evaluate structural effects (slower: one model each); ``"always"``
        scores them even when an additive effect explains most of the
        innovation energy.
    effects : sequence of Effect
    x0, P0 : arrays, optional
        UKF prior (default: the record's true x0 if it has one, else the
        model's X0; :func:`bondgraph.inference.ukf.default_P0`).
    estimate_x0 : list of str
        Initial states estimated jointly with θ at every fit (``["all"]``:
        every state); later filter runs condition on the current fit's
        estimates (their prior shrinks to a token spread).
    x0_overrides : dict
        Initial states by name (``--x0``) imposed on the prior mean of every
        model that has them (over ``x0`` and the record's initial state).
    p0_rel : float, optional
        Prior std of each initial state relative to its scale (``--p0-rel``;
        default 0.05).
    fit : {"nll", "sim"}
        How the declared model is fitted first: by the UKF likelihood alone
        (``"nll"``), or by the output-error fit of its non-noise parameters
        (free-run least squares with forward sensitivities,
        :func:`bondgraph.inference.output_error.output_error_fit`) whose
        estimates then start the likelihood fit (``"sim"``; for a
        deterministic model whose likelihood fit starts far off). Effects are
        always scored and confirmed by the likelihood.
    p0_scale : {"state", "magnitude"}
        The scale of each initial state's prior std: the state's own scale
        along the record (the default; :func:`bondgraph.inference.prior.record_prior`:
        free-run RMS, process-noise walk, sensors; a sidecar's ``x0_std``
        imposed; a state whose initial value nothing gives gets its whole
        scale, and the free run starts from the RTS-smoothed initial state),
        or ``max(|x0|, 1)`` (:func:`bondgraph.inference.ukf.default_P0`, the
        old rule).
    P0_std : dict
        Prior standard deviations of named initial states (e.g. the grade on
        a level track), overriding ``P0``'s diagonal.
    fixed : dict
        Known parameter values (name -> value) set before every fit.
    initial_params : list of str, optional
        Parameters of the initial fit (default ``params``; later steps
        re-estimate all of ``params``). CED fits only its noise intensity
        first, so that "before" is the published linear model.
    ukf : UKFOptions
        Options of :func:`bondgraph.inference.ukf.ukf_nll` (alpha, method, substeps ...),
        passed on only by :mod:`bondgraph.diagnose.inference_calls`.
    auto_substeps : bool
        Adopt the discretisation check's recommended substeps when the
        filter's one-step discretisation error at the declared fit, or at an
        accepted fit, exceeds 0.1 measurement-noise std (that model is then
        refitted); default False: only warn.
    sim_method : str
        Solver of the free-run simulations (:func:`bondgraph.numerics.simulate.simulate`).
    sim_hold : {"linear", "zoh", "filter"}
        How the free-run simulations read the sampled inputs between samples:
        linear interpolation (default), zero-order hold (inputs that are held
        by a DAC: steps, PRBS), or ``"filter"``, the filter's own hold
        (``ukf.hold``), so that the free-run error judges the model as the
        likelihood fitted it (:func:`bondgraph.diagnose.fit.sim_inputs`).
    fit_iterations : int
        Fisher-scoring iterations of each warm-started re-estimation
        (L-BFGS-B if scoring fails).
    confirm_iterations : int
        Maximum Fisher-scoring iterations of a candidate's confirmation fit;
        it stops earlier at convergence (``confirm_tolerance``).
    confirm_tolerance : float
        Convergence of a confirmation fit [nats]: the predicted NLL decrease
        of a full scoring step, or the last step's decrease relative to
        1 + |NLL| times 1e-3 of it, below this.
    metric_tolerance : float
        Reject an effect whose error (on ``validation`` if given, else the
        free-run error on the record) grows by more than this factor
        (default 1.0: the error may not rise).
    error_level : float or None
        The decrease of that free-run error must be significant at this
        one-sided level (a Diebold-Mariano test on the paired per-sample
        squared errors with a Newey-West variance,
        :func:`bondgraph.diagnose.accept.error_decrease_test`); default
        0.05; None: no such test (only ``metric_tolerance``). It keeps an
        effect that fits only the filter's discretisation error or the noise
        (an LR just past its threshold, an unchanged free-run error) out.
    validation : Experiment, optional
        A held-out record: the accept decision compares the free-run error on
        it (from its own initial state, :func:`bondgraph.diagnose.fit.free_run`).
    holdout : float
        Without ``validation``: the fraction of the record, at its end, held
        out as the validation record (0: none; the fits use the rest; its
        prior mean is the record's initial-state rule on the segment, state
        columns if the record has them). ``bondgraph loop --model --data``
        without ``--validate`` holds out :data:`DEFAULT_HOLDOUT` unless
        ``--holdout`` says otherwise.
    structural_refit : int
        Fisher-scoring iterations over the declared estimated parameters
        together with a structural candidate's own, from its best grid point,
        when it is scored (0: the declared parameters stay frozen).
    structural_starts : int
        The best grid values of a structural candidate (default 3) that each
        get one Fisher-scoring step over the declared estimated (non-noise)
        parameters, the effect's held, before the joint profile starts from
        the best of them (0: the joint profile starts from the frozen grid's
        best; :func:`bondgraph.diagnose.scoring.grid_starts`).
    structural_threshold : float or None
        Skip the (slower) structural candidates when an additive effect
        already explains more than this share of the innovation energy (then
        :func:`bondgraph.diagnose.runner.significant_after_lead_check` and
        :func:`~bondgraph.diagnose.runner.accepted_among_skipped_structurals` score
        them when the
        additive lead falls short). None (default): never skipped. The share
        does not tell a right additive lead from a wrong one (a quadratic drag
        that is the truth explained 75 % of the vehicle's innovations; a
        sensor gain standing in for a source lag on an RLC circuit 72 %, an
        asymmetric friction standing in for a force lag on a two-mass chain
        69 %), so skipping traded findings for time.
    structural_near_best : bool
        When the structural candidates are skipped (``structural_threshold``),
        still score those at the places of the three best additive
        candidates (their targets, and for a source the inputs it reads): a
        saturation or a dead zone of a source is first seen as a gain error
        of that source, and would otherwise never be compared with it
        (default False; it matters only when a ``structural_threshold`` is
        set, since by default nothing is skipped).
    chunk : int
        Parameter sets per batched UKF run.
    workers : int
        Processes of the embedded Dask cluster that score the structural
        candidates and run the confirmation refits, one task each
        (1: in process; :mod:`bondgraph.diagnose.parallel`). Results do not
        depend on it.
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://HOST:PORT``; default
        ``$BONDGRAPH_SCHEDULER``): the candidates' tasks run on its workers.
    metric_name : str, optional
        Name of the metric in logs and reports (default: derived from ``metric``).
    true_effect : TrueEffect or (kind, target), optional
        A synthetic record's true effect: the result records its rank at
        every step (:func:`bondgraph.diagnose.result.rank_of`).
    noise : {"auto", "model"}
        Measurement-noise levels (``--noise``;
        :func:`bondgraph.inference.estimand.noise_plan`): ``"auto"`` (default)
        holds an output's noise std at the record's declaration (sidecar
        ``noise_std``) and estimates the undeclared ones with θ in every fit
        of the declared model and in every confirmation (``noise.<output>``;
        noise-intensity parameters not in ``params`` or ``fixed`` join
        ``params``); the score tests condition on the current fit's levels.
        ``"model"``: the graph's own sensor noise and noise-intensity values.
    on_failed_fit : {"stop", "continue"}
        What the loop does when the declared fit did not happen (no physical
        parameter found an interior optimum: each never left its start value
        or sits on a bound of its box, after a second attempt from the
        output-error fit, :func:`bondgraph.diagnose.runner.stuck_parameters`): ``"stop"``
        (default) raises :class:`~bondgraph.errors.DeclaredFitError` (the
        command line exits with code 2 naming them), ``"continue"``
        (``--keep-going``) warns and scores effects against it anyway.
    pairs : bool
        When no confirmed candidate passes the accept rule alone, refit
        pairs of the best confirmed ones together and accept a pair that
        passes it and needs both members
        (:func:`bondgraph.diagnose.runner.accepted_pair`; default True).
    """

    params: list[str]
    metric: Any = "nrmse_sim"
    criterion: str = "aic"
    max_steps: int = 4
    significance: float = 0.01
    confirm_top: int = 3
    confirm_rounds: int = 3
    tie_level: float = 0.05
    structural: Any = True
    effects: Sequence[Effect] = DEFAULT_EFFECTS
    x0: Any = None
    P0: Any = None
    estimate_x0: list = field(default_factory=list)
    x0_overrides: dict = field(default_factory=dict)
    p0_rel: float | None = None
    p0_scale: str = "state"
    fit: str = "nll"
    P0_std: dict = field(default_factory=dict)
    fixed: dict = field(default_factory=dict)
    initial_params: list | None = None
    ukf: UKFOptions = field(default_factory=UKFOptions)
    sim_method: str = "BDF"
    sim_hold: str = "linear"
    auto_substeps: bool = False
    fit_iterations: int = 10
    confirm_iterations: int = 40
    confirm_tolerance: float = 1e-2
    metric_tolerance: float = 1.0
    error_level: float | None = 0.05
    validation: Any = None
    holdout: float = 0.0
    structural_threshold: float | None = None
    structural_near_best: bool = False
    structural_refit: int = 2
    structural_starts: int = 3
    chunk: int = 48
    workers: int = 1
    scheduler: str | None = None
    metric_name: str | None = None
    true_effect: Any = None
    noise: str = "auto"
    on_failed_fit: str = "stop"
    pairs: bool = True

    def __post_init__(self):
        check_settings(self)
        if self.noise not in NOISE_MODES:
            raise OptionError(f"LoopSettings.noise must be one of {', '.join(NOISE_MODES)}, "
                              f"got {self.noise!r}")
        if self.p0_scale not in ("magnitude", "state"):
            raise OptionError(f"LoopSettings.p0_scale must be 'magnitude' or 'state', got "
                              f"{self.p0_scale!r}")
        if self.sim_hold not in ("linear", "zoh", "filter"):
            raise OptionError(f"LoopSettings.sim_hold must be 'linear', 'zoh' or 'filter', got "
                              f"{self.sim_hold!r}")
        if self.on_failed_fit not in ("stop", "continue"):
            raise OptionError(f"LoopSettings.on_failed_fit must be 'stop' or 'continue', got "
                              f"{self.on_failed_fit!r}")
        if self.fit not in ("nll", "sim"):
            raise OptionError(f"LoopSettings.fit must be 'nll' or 'sim', got {self.fit!r}")
        if not 0.0 <= float(self.holdout) < 0.9:
            raise OptionError(f"LoopSettings.holdout must be in [0, 0.9), got {self.holdout!r}")
        if not self.metric_tolerance > 0:
            raise OptionError(f"LoopSettings.metric_tolerance must be > 0, got "
                              f"{self.metric_tolerance!r}")
        if int(self.confirm_iterations) < 1:
            raise OptionError("LoopSettings.confirm_iterations must be >= 1")

    def summary(self) -> dict:
        """Every option as a report records it (JSON-able): plain values as
        they are; the UKF options as a dict; the metric, the effects and
        the validation record by name; arrays as lists; the true effect as
        ``(kind, target)``."""
        out = {}
        for f in fields(self):
            out[f.name] = _summarised(f.name, getattr(self, f.name))
        return out


def _summarised(name: str, v):
    """One option of :meth:`LoopSettings.summary` as JSON-able data."""
    if name == "effects":
        return [e.name for e in v]
    if name == "validation":
        return None if v is None else getattr(v, "name", None)
    if name == "metric" and callable(v):
        return getattr(v, "name", getattr(v, "__name__", "custom metric"))
    if name == "true_effect" and v is not None:
        return v.to_dict() if hasattr(v, "to_dict") else {"kind": v[0], "target": v[1]}
    if hasattr(v, "to_dict"):
        return v.to_dict()
    if hasattr(v, "tolist"):
        return v.tolist()
    if isinstance(v, (list, tuple)):
        return list(v)
    if isinstance(v, dict):
        return dict(v)
    return v


def _integer(name: str, v, minimum: int) -> None:
    if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < minimum:
        raise OptionError(f"LoopSettings.{name} must be an integer >= {minimum}, got {v!r}")


def check_settings(s: LoopSettings) -> None:
    """Validate the loop's options where they are given (``--metric bogus``,
    ``--max-steps -1`` ...), not after a long fit.

    Raises
    ------
    OptionError
        Naming the option, the value and what is allowed.
    """
    if not callable(s.metric) and s.metric not in METRICS:
        raise OptionError(f"LoopSettings.metric = {s.metric!r} is not one of "
                          f"{', '.join(METRICS)} (or a callable metric(fit, record))")
    scheduler_address(s.scheduler)      # a malformed address fails here, not after a fit
    if s.criterion not in CRITERIA:
        raise OptionError(f"LoopSettings.criterion = {s.criterion!r} is not one of "
                          f"{', '.join(CRITERIA)}")
    for name, minimum in (("max_steps", 0), ("confirm_top", 1), ("confirm_rounds", 1),
                          ("workers", 1),
                          ("fit_iterations", 0), ("structural_starts", 0),
                          ("confirm_iterations", 0), ("chunk", 1)):
        _integer(name, getattr(s, name), minimum)
    sig = s.significance
    if isinstance(sig, bool) or not isinstance(sig, numbers.Real) or not 0 < sig < 1:
        raise OptionError(f"LoopSettings.significance must lie in (0, 1), got {sig!r}")
    lev = s.error_level
    if lev is not None and (isinstance(lev, bool) or not isinstance(lev, numbers.Real)
                            or not 0 < lev < 1):
        raise OptionError(f"LoopSettings.error_level must lie in (0, 1) or be None, got "
                          f"{lev!r}")
    thr = s.structural_threshold
    if thr is not None and (isinstance(thr, bool) or not isinstance(thr, numbers.Real)
                            or not 0 < thr <= 1):
        raise OptionError(f"LoopSettings.structural_threshold must lie in (0, 1] or be None, "
                          f"got {thr!r}")
    if s.structural not in (True, False, "always"):
        raise OptionError(f"LoopSettings.structural must be True, False or 'always', got "
                          f"{s.structural!r}")
    if not isinstance(s.ukf, UKFOptions):
        raise OptionError(f"LoopSettings.ukf must be a UKFOptions, got {type(s.ukf).__name__}")
