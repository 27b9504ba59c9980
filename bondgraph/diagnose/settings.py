"""Options of the residual-tracing loop (:func:`bondgraph.diagnose.runner.run_loop`).

:class:`LoopSettings` is frozen and made of frozen groups, each validated
once when it is built (an :class:`~bondgraph.errors.OptionError` names the
group and the option):

* :class:`AcceptRule` -- what an accepted effect must show;
* :class:`SearchOptions` -- how far and how hard the loop searches;
* :class:`~bondgraph.inference.prior.PriorSpec` -- the prior of the initial state;
* :class:`~bondgraph.inference.options.UKFOptions` -- the filter;
* :class:`FreeRunOptions` -- the free-run simulations of the error measure;
* :class:`~bondgraph.inference.options.Evaluation` -- batches and workers.

A changed option is a new object: ``dataclasses.replace(settings,
accept=replace(settings.accept, significance=0.05))``.
"""

from __future__ import annotations

import numbers
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Callable, Sequence, Union

from bondgraph.data.records import Experiment
from bondgraph.diagnose.effects import DEFAULT_EFFECTS, Effect
from bondgraph.errors import OptionError
from bondgraph.inference.executor import scheduler_address
from bondgraph.inference.options import NOISE_MODES, Evaluation, UKFOptions
from bondgraph.inference.prior import PriorSpec
from bondgraph.numerics.integrators import hold_within
from bondgraph.numerics.simulate import METHODS

#: the built-in error measures (``LoopSettings.metric``; bondgraph.diagnose.metric)
METRICS = ("nrmse_sim", "rmse_sim", "rmse_pred")
#: information criteria of the accept decision
CRITERIA = ("aic", "bic")
#: how the free runs read the sampled inputs between samples (``FreeRunOptions.hold``)
FREE_RUN_HOLDS = ("linear", "zoh", "filter")
#: the free runs' solvers: scipy's and the fixed-step ones
#: (:data:`bondgraph.numerics.simulate.METHODS`), or ``"fine"``, the
#: filter's own method at 4 times its substeps
#: (:func:`bondgraph.diagnose.inference_calls.fine_free_run`)
FREE_RUN_METHODS = METHODS + ("fine",)

#: the fraction of a user's record (``bondgraph loop --model M --data D``,
#: no ``--validate``) held out at its end for the accept decision and the
#: report's error before/after (``--holdout 0`` fits the whole record)
DEFAULT_HOLDOUT = 0.25

#: the loop's batch size of parameter sets per UKF run (``Evaluation.chunk``)
LOOP_CHUNK = 48

#: a user's error measure: ``metric(fit, data) -> float`` with attribute ``name``
Metric = Union[str, Callable]


@dataclass(frozen=True)
class TrueEffect:
    """The effect a synthetic case's truth has (``LoopSettings.true_effect``): the declared graph plus
    effect ``kind`` (a name of :mod:`bondgraph.diagnose.effects`) at
    ``target`` (a target name) with parameter ``values`` (by the effect's
    local parameter names). Unpacks as ``(kind, target)``."""

    kind: str
    target: str
    values: dict = field(default_factory=dict)

    def __iter__(self):
        return iter((self.kind, self.target))

    @property
    def label(self) -> str:
        """``"kind @ target"``, as a candidate's label."""
        return f"{self.kind} @ {self.target}"

    def to_dict(self) -> dict:
        """JSON-ready: kind, target, values."""
        return {"kind": self.kind, "target": self.target, "values": dict(self.values)}


def _integer(obj, name: str, minimum: int) -> None:
    v = getattr(obj, name)
    if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < minimum:
        raise OptionError(f"{type(obj).__name__}.{name} must be an integer >= {minimum}, "
                          f"got {v!r}")


def _level(obj, name: str, *, optional: bool = False, closed: bool = False) -> None:
    """``obj.name`` a real number in (0, 1) ((0, 1] if ``closed``; None if ``optional``)."""
    v = getattr(obj, name)
    if v is None and optional:
        return
    inside = not isinstance(v, bool) and isinstance(v, numbers.Real) and (
        0 < v <= 1 if closed else 0 < v < 1)
    if not inside:
        span = "(0, 1]" if closed else "(0, 1)"
        raise OptionError(f"{type(obj).__name__}.{name} must lie in {span}"
                          f"{' or be None' if optional else ''}, got {v!r}")


def _choice(obj, name: str, choices: tuple) -> None:
    v = getattr(obj, name)
    if v not in choices:
        raise OptionError(f"{type(obj).__name__}.{name} must be one of "
                          f"{', '.join(repr(c) for c in choices)}, got {v!r}")


@dataclass(frozen=True)
class AcceptRule:
    """What a confirmed candidate must show to be accepted
    (:func:`bondgraph.diagnose.accept.decide`).

    Attributes
    ----------
    criterion : {"aic", "bic"}
        Information criterion of the accept decision (Akaike 1974; Schwarz 1978).
    significance : float
        Family-wise level for "a significant effect is left" (Bonferroni over
        the candidates evaluated).
    tie_level : float
        Level of Vuong's (1989) test between the confirmed lead and each
        other confirmed candidate: a candidate whose per-sample likelihood
        does not differ from the lead's at this two-sided level is reported
        as tied with it (``Candidate.tied``; the record cannot tell them
        apart, e.g. a source lag and a sensor low-pass on a linear graph).
    metric_tolerance : float
        Reject an effect whose error (on ``validation`` if given, else the
        free-run error on the record) grows by more than this factor
        (default 1.0: the error may not rise).
    error_level : float or None
        The decrease of that free-run error must be significant at this
        one-sided level (a Diebold-Mariano test on the paired per-sample
        squared errors with a Newey-West variance conditional on the change
        of the output,
        :func:`bondgraph.diagnose.accept.error_decrease_test`); default
        0.05; None: no such test (only ``metric_tolerance``). It keeps an
        effect that fits only the filter's discretisation error or the noise
        (an LR just past its threshold, an unchanged free-run error) out.
    pairs : bool
        When no confirmed candidate passes the accept rule alone, refit
        pairs of the best confirmed ones together and accept a pair that
        passes it and needs both members
        (:func:`bondgraph.diagnose.runner.accepted_pair`); and when one
        passes but two or more are each significant, accept instead a pair
        that beats it (:func:`bondgraph.diagnose.runner.pair_before_single`).
        Default True.
    replace : bool
        After each accepted step, refit each effect accepted at an earlier
        step with its place's rivals of that step in its stead (the other
        laws confirmed there) and take a rival that the record now prefers
        (:func:`bondgraph.diagnose.runner.replaced_earlier`). Default True.
    """

    criterion: str = "aic"
    significance: float = 0.01
    tie_level: float = 0.05
    metric_tolerance: float = 1.0
    error_level: float | None = 0.05
    pairs: bool = True
    replace: bool = True

    def __post_init__(self):
        _choice(self, "criterion", CRITERIA)
        _level(self, "significance")
        _level(self, "tie_level")
        _level(self, "error_level", optional=True)
        tol = self.metric_tolerance
        if isinstance(tol, bool) or not isinstance(tol, numbers.Real) or not tol > 0:
            raise OptionError(f"AcceptRule.metric_tolerance must be > 0, got {tol!r}")
        _choice(self, "pairs", (True, False))
        _choice(self, "replace", (True, False))


@dataclass(frozen=True)
class SearchOptions:
    """How far and how hard the loop searches: steps, the declared fit,
    the structural candidates, the confirmation refits.

    Attributes
    ----------
    max_steps : int
        Accepted effects at most (steps of the loop).
    fit : {"nll", "sim"}
        How the declared model is fitted first: by the UKF likelihood alone
        (``"nll"``), or by the output-error fit of its non-noise parameters
        (free-run least squares with forward sensitivities,
        :func:`bondgraph.inference.output_error.output_error_fit`) whose
        estimates then start the likelihood fit (``"sim"``; for a
        deterministic model whose likelihood fit starts far off). Effects are
        scored and confirmed by the likelihood ``likelihood`` names.
    likelihood : {"auto", "one_step", "free_run"}
        The likelihood the loop fits and judges by. ``"one_step"``: the
        UKF's one-step predictions with the process noise the fit estimates;
        ``"free_run"``: the estimated process-noise intensities held at a
        floor (their random walk 0.1 % of each state's spread), so that the
        filter's prediction is the free run and the likelihood that of the
        free-run errors the loop reports (the record's declared sensor noise
        then estimated: it holds the model's error); ``"auto"`` (default):
        one-step, unless the declared fit's process noise absorbs the
        model's error (its random walk exceeds its state's spread,
        :func:`bondgraph.diagnose.fit.process_noise_absorbing`) and the
        free-run fit's error is not larger
        (:func:`bondgraph.diagnose.runner.free_run_likelihood`).
    on_failed_fit : {"stop", "continue"}
        What the loop does when the declared fit did not happen (no physical
        parameter found an interior optimum: each never left its start value
        or sits on a bound of its box, after a second attempt from the
        output-error fit, :func:`bondgraph.diagnose.runner.stuck_parameters`): ``"stop"``
        (default) raises :class:`~bondgraph.errors.DeclaredFitError` (the
        command line exits with code 2 naming them), ``"continue"``
        (``--keep-going``) warns and scores effects against it anyway. The
        same holds for a declared fit that is not physically admissible
        (:func:`bondgraph.diagnose.runner.declared_inadmissible`).
    fit_iterations : int
        Fisher-scoring iterations of each warm-started re-estimation
        (L-BFGS-B if scoring fails).
    auto_substeps : bool
        Adopt the discretisation check's recommended substeps when the
        filter's one-step discretisation error at the declared fit, or at an
        accepted fit, exceeds 0.1 measurement-noise std (that model is then
        refitted); default False: only warn.
    auto_method : bool
        With ``auto_substeps``, the other method (ROS2 or RK4) may be
        adopted in place of more substeps of the current one, where its
        fewest substeps that meet the check cost fewer f evaluations per
        sample (:func:`~bondgraph.diagnose.fit.adopted_discretisation`; a
        user's CED graph: ROS2 needed 16 substeps where RK4 met the check
        with 3). Set by :func:`~bondgraph.diagnose.runner.chosen_numerics`
        unless the method is given; default False: the method stays.
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
    confirm_iterations : int
        Maximum Fisher-scoring iterations of a candidate's confirmation fit;
        it stops earlier at convergence (``confirm_tolerance``).
    confirm_tolerance : float
        Convergence of a confirmation fit [nats]: the predicted NLL decrease
        of a full scoring step, or the last step's decrease relative to
        1 + abs(NLL) times 1e-3 of it, below this.
    structural : bool or "always"
        Evaluate structural effects (slower: one model each); ``"always"``
        scores them even when an additive effect explains most of the
        innovation energy.
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
    other_hold : str, optional
        An input hold to fit the declared model under too, the likelier fit
        (by more than :data:`~bondgraph.inference.discretise.HOLD_MARGIN`)
        kept for the whole loop: set by
        :func:`~bondgraph.diagnose.runner.chosen_numerics` when an input's
        shape is ambiguous (:func:`~bondgraph.inference.discretise.alternative_hold`).
        None (default): the filter's hold is kept.
    check_hold : bool
        At the end, refit the final model with each input whose hold its
        shape chose held the other way (zero-order <-> linear), and warn
        when the record is likelier so by more than
        :data:`~bondgraph.inference.discretise.HOLD_CHECK_MARGIN` nats
        (:func:`~bondgraph.diagnose.runner.hold_at_final`): the shape cannot
        tell a held command whose steps vary smoothly from a sampled
        continuous signal, and the declared fit's likelihood cannot settle it
        while the model lacks an effect. Set by
        :func:`~bondgraph.diagnose.runner.chosen_numerics` unless the hold is
        given; False (default): no check.
    """

    max_steps: int = 4
    fit: str = "nll"
    likelihood: str = "auto"
    on_failed_fit: str = "stop"
    fit_iterations: int = 10
    auto_substeps: bool = False
    auto_method: bool = False
    confirm_top: int = 3
    confirm_rounds: int = 3
    confirm_iterations: int = 40
    confirm_tolerance: float = 1e-2
    structural: bool | str = True
    structural_threshold: float | None = None
    structural_near_best: bool = False
    structural_refit: int = 2
    structural_starts: int = 3
    other_hold: str | None = None
    check_hold: bool = False

    def __post_init__(self):
        for name, minimum in (("max_steps", 0), ("fit_iterations", 0), ("confirm_top", 1),
                              ("confirm_rounds", 1), ("confirm_iterations", 1),
                              ("structural_refit", 0), ("structural_starts", 0)):
            _integer(self, name, minimum)
        _choice(self, "fit", ("nll", "sim"))
        _choice(self, "likelihood", ("auto", "one_step", "free_run"))
        _choice(self, "on_failed_fit", ("stop", "continue"))
        _choice(self, "structural", (True, False, "always"))
        if self.other_hold is not None and not hold_within(self.other_hold, ("zoh", "linear")):
            raise OptionError(f"SearchOptions.other_hold must be 'zoh', 'linear' or one of them "
                              f"per input, got {self.other_hold!r}")
        _level(self, "structural_threshold", optional=True, closed=True)
        tol = self.confirm_tolerance
        if isinstance(tol, bool) or not isinstance(tol, numbers.Real) or not tol > 0:
            raise OptionError(f"SearchOptions.confirm_tolerance must be > 0, got {tol!r}")


@dataclass(frozen=True)
class FreeRunOptions:
    """How the free-run simulations of the error measure run
    (:func:`bondgraph.diagnose.fit.free_run`).

    Attributes
    ----------
    method : str
        Solver (:func:`bondgraph.numerics.simulate.simulate`; one of
        :data:`bondgraph.numerics.simulate.METHODS`; default ``"LSODA"``,
        which switches between Adams and BDF by stiffness: on the EMPS
        record's 4968 samples one free run took 0.49 s against scipy's BDF's
        3.0 s, the outputs within 2e-4 of the measurement's std of each other,
        BDF and Radau as far apart), or ``"fine"``: the
        filter's own method at 4 times its substeps, fixed-step
        (:func:`bondgraph.diagnose.inference_calls.fine_free_run`; a user's
        graph and record get it with the chosen discretisation).
    hold : {"linear", "zoh", "filter"} or str
        How the free runs read the sampled inputs between samples: linear
        interpolation (default), zero-order hold (inputs that are held by a
        DAC: steps, PRBS), one of these per input comma-joined in the
        model's input order (``"zoh,linear"``), or ``"filter"``, the filter's own hold
        (``ukf.hold``), so that the free-run error judges the model as the
        likelihood fitted it (:func:`bondgraph.diagnose.fit.sim_inputs`).
    init_samples : int
        0 (default): the free run on the record that judges (the held-out
        part or ``--validate``) starts where the loop's rule puts it
        (:func:`bondgraph.diagnose.fit.free_run`: the smoothed start
        x̂_0|N given that whole record, or the state the fitted part's
        filter ends in). N > 0: the benchmark protocol of nonlinear system
        identification (nonlinearbenchmark.org, the ``n_init`` of its
        ``nonlinear_benchmarks`` package: EMPS gives 20): the start is the
        smoothed initial state given the record's first N samples only, so
        the judging record's later samples cannot move the start to cancel
        a model's misfit (:func:`bondgraph.diagnose.fit.window_start`), and
        the free-run error that judges runs over the samples after them.
    """

    method: str = "LSODA"
    hold: str = "linear"
    init_samples: int = 0

    def __post_init__(self):
        if isinstance(self.init_samples, bool) \
                or not isinstance(self.init_samples, numbers.Integral) \
                or self.init_samples < 0 or self.init_samples == 1:
            raise OptionError(f"FreeRunOptions.init_samples must be 0 (the loop's start rule) "
                              f"or an integer of at least 2 samples, got {self.init_samples!r}")
        _choice(self, "method", FREE_RUN_METHODS)
        if not (self.hold == "filter" or hold_within(self.hold, ("linear", "zoh"))):
            _choice(self, "hold", FREE_RUN_HOLDS)


@dataclass(frozen=True)
class LoopSettings:
    """Options of :func:`bondgraph.diagnose.runner.run_loop` (frozen; the
    groups are validated when they are built, the rest here).

    Attributes
    ----------
    params : list of str
        Parameters of the declared model estimated at every step.
    initial_params : list of str, optional
        Parameters of the initial fit (default ``params``; later steps
        re-estimate all of ``params``). CED fits only its noise intensity
        first, so that "before" is the published linear model.
    fixed : dict
        Known parameter values (name -> value) set before every fit.
    hold_unidentified : sequence of str
        Parameters of ``params`` the loop holds at their current (declared
        or fixed) value when the declared fit does not identify them apart
        from others (they load on a flat direction of its Fisher
        information, :func:`bondgraph.diagnose.fit.unidentified`) or leaves
        them on a bound of their box: one at a time, the largest loading
        first, the declared model refitted after each, until none of them is
        flat or on its box; the log and the report say which.
        ``bondgraph loop --model`` without ``--params`` passes the
        parameters declared without a box (known values: a motor constant
        beside the mass and friction it scales). Default: none.
    estimate_x0 : list of str
        Initial states estimated jointly with θ at every fit (``["all"]``:
        every state); later filter runs condition on the current fit's
        estimates (their prior shrinks to a token spread).
    effects : sequence of Effect
        The effect library the loop scores (default
        :data:`bondgraph.diagnose.effects.DEFAULT_EFFECTS`).
    metric : str or callable
        Error measure reported before/after: ``"nrmse_sim"`` (mean over
        outputs of RMS(free-run simulation error)/std(measurement)),
        ``"rmse_sim"`` (RMS over outputs, output units), ``"rmse_pred"``
        (RMS of the one-step innovations), or a callable
        ``metric(fit, data) -> float`` with attribute ``name``
        (``data``: a :class:`bondgraph.diagnose.fit.MetricRecord`).
    metric_name : str, optional
        Name of the metric in logs and reports (default: derived from ``metric``).
    validation : Experiment, optional
        A held-out record: the accept decision compares the free-run error on
        it (from its own initial state, :func:`bondgraph.diagnose.fit.free_run`).
    more_validation : sequence of Experiment
        Further held-out records (``--validate`` given more than once; beside
        ``validation`` or the held-out part): an accepted model simulates on each, its free-run
        error grows on none of them, and their per-sample errors join the
        validation record's in the error-decrease test
        (:func:`bondgraph.diagnose.accept.decide`). Names differ from each
        other and from ``validation``'s.
    holdout : float
        Without ``validation``: the fraction of the record, at its end, held
        out as the validation record (0: none; the fits use the rest; its
        prior mean is the record's initial-state rule on the segment, state
        columns if the record has them). ``bondgraph loop --model --data``
        without ``--validate`` holds out :data:`DEFAULT_HOLDOUT` unless
        ``--holdout`` says otherwise.
    noise : {"auto", "model"}
        Measurement-noise levels (``--noise``;
        :func:`bondgraph.inference.estimand.noise_plan`): ``"auto"`` (default)
        holds an output's noise std at the record's declaration (sidecar
        ``noise_std``) and estimates the undeclared ones with θ in every fit
        of the declared model and in every confirmation (``noise.<output>``;
        noise-intensity parameters not in ``params`` or ``fixed`` join
        ``params``); the score tests condition on the current fit's levels.
        ``"model"``: the graph's own sensor noise and noise-intensity values.
    true_effect : TrueEffect or (kind, target), optional
        A synthetic record's true effect: the result records its rank at
        every step (:func:`bondgraph.diagnose.result.rank_of`).
    accept : AcceptRule
        The accept decision's criterion and levels.
    search : SearchOptions
        Steps, the declared fit, structural candidates, confirmation refits.
    prior : PriorSpec
        The prior of the initial state (:class:`bondgraph.inference.prior.PriorSpec`:
        ``x0`` a whole prior mean, ``x0_set`` states by name (``--x0``),
        ``P0`` a whole covariance, ``x0_std`` declared stds by name (e.g. the
        grade on a level track), ``rel`` (``--p0-rel``) and ``scale``
        (``--p0``: ``"state"``, each state's own scale along the record, or
        ``"magnitude"``, max(abs(x0), 1))); every problem of the loop is built
        with it (:func:`bondgraph.diagnose.fit.loop_problem`).
    ukf : UKFOptions
        Options of :func:`bondgraph.inference.ukf.ukf_nll` (alpha, method, substeps ...),
        passed on only by :mod:`bondgraph.diagnose.inference_calls`.
    free_run : FreeRunOptions
        Solver and input hold of the free-run simulations.
    evaluation : Evaluation
        Parameter sets per batched UKF run (``chunk``; None, the default:
        :data:`LOOP_CHUNK`); ``workers``: processes of the embedded Dask
        cluster that score the structural candidates and run the
        confirmation refits, one task each (1: in process;
        :mod:`bondgraph.diagnose.parallel`); ``scheduler``: address of an
        existing Dask scheduler (``tcp://HOST:PORT``; default
        ``$BONDGRAPH_SCHEDULER``). Results do not depend on it.
    """

    params: list[str]
    initial_params: list[str] | None = None
    fixed: dict[str, float] = field(default_factory=dict)
    hold_unidentified: Sequence[str] = ()
    estimate_x0: list[str] = field(default_factory=list)
    effects: Sequence[Effect] = DEFAULT_EFFECTS
    metric: Metric = "nrmse_sim"
    metric_name: str | None = None
    validation: Experiment | None = None
    more_validation: Sequence[Experiment] = ()
    holdout: float = 0.0
    noise: str = "auto"
    true_effect: TrueEffect | tuple[str, str] | None = None
    accept: AcceptRule = field(default_factory=AcceptRule)
    search: SearchOptions = field(default_factory=SearchOptions)
    prior: PriorSpec = field(default_factory=PriorSpec)
    ukf: UKFOptions = field(default_factory=UKFOptions)
    free_run: FreeRunOptions = field(default_factory=FreeRunOptions)
    evaluation: Evaluation = field(default_factory=Evaluation)

    def __post_init__(self):
        if not callable(self.metric) and self.metric not in METRICS:
            raise OptionError(f"LoopSettings.metric = {self.metric!r} is not one of "
                              f"{', '.join(METRICS)} (or a callable metric(fit, record))")
        _choice(self, "noise", NOISE_MODES)
        stray = [n for n in self.hold_unidentified if n not in self.params]
        if isinstance(self.hold_unidentified, str) or stray:
            raise OptionError(f"LoopSettings.hold_unidentified must name parameters of params, "
                              f"got {self.hold_unidentified!r}")
        holdout = self.holdout
        if isinstance(holdout, bool) or not isinstance(holdout, numbers.Real) \
                or not 0.0 <= holdout < 0.9:
            raise OptionError(f"LoopSettings.holdout must be in [0, 0.9), got {holdout!r}")
        if self.validation is not None and not isinstance(self.validation, Experiment):
            raise OptionError(f"LoopSettings.validation must be an Experiment or None, got "
                              f"{type(self.validation).__name__}")
        self._check_more_validation()
        for name, cls in (("accept", AcceptRule), ("search", SearchOptions),
                          ("prior", PriorSpec), ("ukf", UKFOptions),
                          ("free_run", FreeRunOptions), ("evaluation", Evaluation)):
            if not isinstance(getattr(self, name), cls):
                raise OptionError(f"LoopSettings.{name} must be a {cls.__name__}, got "
                                  f"{type(getattr(self, name)).__name__}")
        if self.evaluation.chunk is None:      # the loop's filters always run in batches
            object.__setattr__(self, "evaluation", replace(self.evaluation, chunk=LOOP_CHUNK))
        scheduler_address(self.evaluation.scheduler)   # a malformed address fails here

    def _check_more_validation(self) -> None:
        """``more_validation`` as a tuple of Experiments with names of their
        own, and only beside ``validation``."""
        more = self.more_validation
        if isinstance(more, Experiment) or not isinstance(more, (list, tuple)) \
                or not all(isinstance(r, Experiment) for r in more):
            raise OptionError(f"LoopSettings.more_validation must be a sequence of Experiments, "
                              f"got {more!r:.80}")
        object.__setattr__(self, "more_validation", tuple(more))
        if more and self.validation is None and not self.holdout:
            raise OptionError("LoopSettings.more_validation needs a first record that judges: "
                              "a validation record (LoopSettings.validation) or a held-out "
                              "part (LoopSettings.holdout)")
        first = [self.validation] if more and self.validation is not None else []
        names = [r.name for r in first + list(more)]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise OptionError(f"the validation records must have names of their own: "
                              f"{', '.join(repr(n) for n in twice)} given more than once",
                              hint="rename the records (Experiment.name) or give each file once")

    def summary(self) -> dict:
        """Every option as a report records it (JSON-able): plain values as
        they are, the groups as nested dicts (the prior's arrays as lists);
        the metric, the effects and the validation record by name; the true
        effect as ``{"kind", "target"(, "values")}``."""
        return {f.name: _summarised(f.name, getattr(self, f.name)) for f in fields(self)}


def prior_summary(prior: PriorSpec) -> dict:
    """A :class:`PriorSpec` as JSON-able data (every field; arrays as lists)."""
    return {"rel": prior.rel, "scale": prior.scale,
            "x0": None if prior.x0 is None else list(prior.x0),
            "x0_set": dict(prior.x0_set),
            "P0": None if prior.P0 is None else prior.P0.tolist(),
            "x0_std": dict(prior.x0_std), "estimated": dict(prior.estimated)}


def _summarised(name: str, v):
    """One option of :meth:`LoopSettings.summary` as JSON-able data."""
    if name == "effects":
        return [e.name for e in v]
    if name == "validation":
        return None if v is None else v.name
    if name == "more_validation":
        return [r.name for r in v]
    if name == "metric" and callable(v):
        return getattr(v, "name", getattr(v, "__name__", "custom metric"))
    if name == "true_effect" and v is not None:
        return v.to_dict() if hasattr(v, "to_dict") else {"kind": v[0], "target": v[1]}
    if name == "prior":
        return prior_summary(v)
    if name == "ukf":
        return v.to_dict()
    if name in ("accept", "search", "free_run", "evaluation"):
        return asdict(v)
    if isinstance(v, (list, tuple)):
        return list(v)
    if isinstance(v, dict):
        return dict(v)
    return v
