"""A fitted model judged on records it was not fitted to: free-run
(simulation) error and one-step-ahead likelihood, as the loop judges its
held-out record.

The comparison of prediction-error validation (Ljung 1999, §16.6; MATLAB's
``compare``): the model runs freely from an initial state with the record's
measured inputs, and its outputs are compared with the measured ones. The
start is the loop's rule for a record that judges
(:func:`bondgraph.diagnose.fit.free_run`: the record's own initial state
where it gives one, else the RTS-smoothed x̂_0|N given the whole record, or
one fitted to its outputs where the smoother fails), or with
``init_samples`` = n the smoothed state given the record's first n samples
only, the error over the rest (the benchmark protocol of
nonlinearbenchmark.org, :func:`bondgraph.diagnose.fit.window_start`). The
input hold and the free runs' method are those the loop chooses for a
user's graph (:func:`bondgraph.diagnose.runner.chosen_numerics`), the
filter's step is chosen again against the noise levels held here and
checked by the NLL guard; on the records tried a free-run figure here is
the one ``bondgraph loop`` reported for the same model on the same record,
to the digit (EMPS pulses run 0.06151, CED u2 0.5065).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Mapping, Sequence

import numpy as np

from bondgraph.core.graph import BondGraph
from bondgraph.diagnose.fit import (Context, free_run, free_run_trouble, init_samples,
                                    loop_problem, model_of, samples_after)
from bondgraph.diagnose.inference_calls import run_ukf
from bondgraph.diagnose.metric import nrmse
from bondgraph.diagnose.runner import MIN_HELD_OUT, chosen_numerics
from bondgraph.diagnose.settings import FreeRunOptions, LoopSettings
from bondgraph.errors import OptionError
from bondgraph.inference.discretise import choose_discretisation, likelier_hold_at
from bondgraph.inference.problem import NoiseSpec
from bondgraph.inference.ukf import GUARD_REL, GUARD_SUBSTEPS


@dataclass(eq=False)
class Comparison:
    """One record's comparison (:func:`compare`).

    Attributes
    ----------
    record : str
        The record's name.
    outputs, units : list of str
        The model's outputs (n_y) and their units.
    t : ndarray (N,)
        Times [s].
    y : ndarray (N, n_y)
        Measured outputs (model units; NaN where missing).
    sim_y : ndarray (N, n_y) or None
        The free run; None where it failed.
    judged_from : int
        First sample the errors run over (``init_samples``; 0: all; on a
        record filtered on a finer grid, the grid point after the window's
        last sample).
    rms : ndarray (n_y,)
        RMS free-run error per output (output units; inf where the run failed).
    nrmse : ndarray (n_y,)
        RMS error over the std of the measurement, per output.
    bias : ndarray (n_y,)
        Mean error y − ŷ per output over the judged samples (output units;
        a model that stays below the record reads positive: a cold
        engine's extra fuel); NaN where the run failed or the output is not
        measured.
    fit_percent : ndarray (n_y,)
        100 (1 − ‖y − ŷ‖ / ‖y − ȳ‖): MATLAB ``compare``'s NRMSE fit (100 %
        a perfect run, 0 % the measurement's mean, negative worse).
    metric : float
        The loop's error measure: the mean of ``nrmse`` over the outputs
        (:func:`bondgraph.diagnose.metric.nrmse`).
    nll : float
        Negative log-likelihood of the record under the model's UKF
        (one-step-ahead predictions; inf where the filter fails). The prior
        spread of an initial state is the state's scale along the record
        under ``scales_from`` (:func:`compare`), as a fit took it at its
        start values: on the fitted record it is the fit's own NLL (a
        user's door: -8192.861066596097 both; the CED user graph 551.99
        against 551.82, ROS2(1) against RK4(4)). With the scales at the
        fitted values instead, a fit whose states barely move read 1416.7
        there.
    n_obs : int
        Scalar measurements the NLL sums over.
    start : str
        How the free run's initial state was set (in words).
    noise : dict
        Output -> (measurement-noise std the filter used, where it came from).
    numerics : str
        The filter's and free run's discretisation (one line).
    trouble : str or None
        Why the free run does not show a model that simulates
        (:func:`bondgraph.diagnose.fit.free_run_trouble`), or None.
    filter_failure : str or None
        Why the filter failed, or None.
    window : int
        The record's first samples that set the start (``init_samples``;
        0: the loop's rule).
    """

    record: str
    outputs: list
    units: list
    t: np.ndarray
    y: np.ndarray
    sim_y: np.ndarray | None
    judged_from: int
    rms: np.ndarray
    nrmse: np.ndarray
    fit_percent: np.ndarray
    bias: np.ndarray
    metric: float
    nll: float
    n_obs: int
    start: str
    noise: dict = field(default_factory=dict)
    numerics: str = ""
    trouble: str | None = None
    filter_failure: str | None = None
    window: int = 0

    def to_json(self) -> dict:
        """The comparison as JSON-ready values (arrays left out but the
        per-output figures)."""
        return {"record": self.record, "metric": self.metric, "nll": self.nll,
                "n_obs": self.n_obs, "init_samples": self.window,
                "judged_from": self.judged_from, "start": self.start,
                "numerics": self.numerics, "trouble": self.trouble,
                "filter_failure": self.filter_failure,
                "outputs": {o: {"unit": u, "rms": float(r), "nrmse": float(n),
                                "fit_percent": float(f), "bias": float(b),
                                "noise_std": self.noise[o][0], "noise_from": self.noise[o][1]}
                            for o, u, r, n, f, b in zip(self.outputs, self.units, self.rms,
                                                        self.nrmse, self.fit_percent,
                                                        self.bias)}}


def output_errors(y: np.ndarray, sim_y: np.ndarray | None, first: int = 0
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RMS error (n_y,), NRMSE (n_y,) and NRMSE fit in % (n_y,) of the free
    run ``sim_y`` (N, n_y) against ``y`` (N, n_y; NaN where missing) over the
    samples from ``first`` on; inf (and −inf %) for an output whose run failed
    or is not finite where it is measured; NaN for an output the record
    measures at fewer than two of those samples (a sensor the record lacks).
    The std and mean of an output are those of its judged samples."""
    n_y = y.shape[1]
    rms, nr, fit = np.full(n_y, np.inf), np.full(n_y, np.inf), np.full(n_y, -np.inf)
    ys = np.asarray(y, float)[first:]
    unseen = np.isfinite(ys).sum(axis=0) < 2
    rms[unseen], nr[unseen], fit[unseen] = np.nan, np.nan, np.nan
    if sim_y is None:
        return rms, nr, fit
    ss = np.asarray(sim_y, float)[first:]
    for j in range(n_y):
        seen = np.isfinite(ys[:, j])
        if unseen[j] or not np.all(np.isfinite(ss[seen, j])):
            continue
        e = ys[seen, j] - ss[seen, j]
        rms[j] = float(np.sqrt(np.mean(e * e)))
        sd = float(np.std(ys[seen, j]))
        nr[j] = rms[j] / (sd if sd > 0 else 1.0)
        dev = float(np.linalg.norm(ys[seen, j] - ys[seen, j].mean()))
        fit[j] = 100.0 * (1.0 - float(np.linalg.norm(e)) / (dev if dev > 0 else 1.0))
    return rms, nr, fit


def mean_errors(y: np.ndarray, sim_y: np.ndarray | None, first: int = 0) -> np.ndarray:
    """Mean error y − ŷ (n_y,) of the free run ``sim_y`` (N, n_y) against
    ``y`` (N, n_y; NaN where missing) over the samples from ``first`` on;
    NaN for an output measured at none of them, or where the run failed or
    is not finite where measured."""
    ys = np.asarray(y, float)[first:]
    out = np.full(ys.shape[1], np.nan)
    if sim_y is None:
        return out
    e = ys - np.asarray(sim_y, float)[first:]
    for j in range(ys.shape[1]):
        seen = np.isfinite(ys[:, j])
        if seen.any() and np.all(np.isfinite(e[seen, j])):
            out[j] = float(np.mean(e[seen, j]))
    return out


def compare(graph: BondGraph, records: Sequence, *, noise: Mapping[str, float] | None = None,
            init_samples: int = 0, given: Mapping[str, object] | None = None,
            scales_from: BondGraph | None = None, log: Callable[[str], None] = print,
            progress: bool = False,
            initial_states: Sequence[Mapping[str, float] | None] | None = None
            ) -> list[Comparison]:
    """Judge ``graph`` (its parameter defaults: set them from a fit with
    :func:`bondgraph.export.params.model_graph`) on each of ``records``.

    For each record: the numerics the loop chooses for a user's graph at
    these parameters (:func:`bondgraph.diagnose.runner.chosen_numerics`:
    the filter's method, substeps and input hold its discretisation check
    accepts; free runs by the same method 4 times finer); the measurement
    noise held at the record's declaration, else at ``noise`` (a fit's
    estimates), else profiled on the record at these parameters
    (:func:`bondgraph.inference.estimate.start_levels_profiled`); the UKF's
    NLL; the free run from the loop's start for a record that judges
    (:func:`bondgraph.diagnose.fit.free_run`, or the first ``init_samples``
    samples' smoothed state, :func:`bondgraph.diagnose.fit.window_start`)
    and its errors (:func:`output_errors`).

    Parameters
    ----------
    graph : BondGraph
    records : sequence of Experiment
    noise : mapping, optional
        Output -> measurement-noise std (output units), e.g. a fit's
        estimates (:func:`bondgraph.export.params.read_noise_levels`).
    init_samples : int
        0 (default): the loop's start rule; n > 0: the start given the first
        n samples, the errors over the rest.
    given : mapping, optional
        Discretisation fields the caller fixes (``method``, ``substeps``,
        ``hold``).
    scales_from : BondGraph, optional
        The graph whose state scales on each record set the prior spread of
        the initial states (:meth:`~bondgraph.inference.problem.Problem.with_model`:
        the states it shares with ``graph`` inherit them): the declared graph
        at its declared values, as the loop and ``estimate`` take them, so
        that the start and the NLL are the loop's and the fit's (a declared
        fit whose states barely move scales them to nothing, and its start
        is then pinned to the prior mean). Default: ``graph`` itself.
    log : callable
        Gets one line per choice (numerics, noise levels, fallbacks).
    progress : bool
        Progress bars of the long steps.
    initial_states : sequence, optional
        For each record, initial states a fit estimated on it (state ->
        value, ``--estimate-x0``) or None: the filter and the free run start
        there, held at a token spread, as the fit's NLL took them (from the
        prior instead, the NLL on the fitted record differed from the
        fit's).

    Returns
    -------
    list of Comparison
        One per record, in order.

    Raises
    ------
    OptionError
        ``init_samples`` negative, 1, not an integer, or leaving fewer than
        :data:`~bondgraph.diagnose.runner.MIN_HELD_OUT` samples of a record;
        a noise level that is not a finite number > 0; no record.
    DataError
        A record that does not fit the model (its inputs or outputs absent).
    """
    if not records:
        raise OptionError("compare needs at least one record")
    n_init = check_window(records, init_samples)
    levels = dict(NoiseSpec("auto", held=noise or {}).held)    # each > 0 and finite
    starts = list(initial_states or [None] * len(records))
    if len(starts) != len(records):
        raise OptionError(f"compare: {len(starts)} sets of initial states for "
                          f"{len(records)} records")
    return [_compare_one(graph, rec, levels, n_init, dict(given or {}), log, progress,
                         scales_from, x0) for rec, x0 in zip(records, starts)]


def check_window(records: Sequence, init_samples: int) -> int:
    """``init_samples`` (``--init-samples``) when it leaves each of
    ``records`` at least :data:`~bondgraph.diagnose.runner.MIN_HELD_OUT`
    samples to judge by (a finer grid's points not counted).

    Raises
    ------
    OptionError
        A negative or non-integer window, or one that leaves a record too
        few samples (the record and its size named).
    """
    try:
        n_init = FreeRunOptions(init_samples=init_samples).init_samples
    except OptionError as exc:
        raise OptionError(str(exc).replace("FreeRunOptions.init_samples", "--init-samples")) \
            from None
    for rec in records:
        left = samples_after(rec, n_init)
        if n_init and left < MIN_HELD_OUT:
            raise OptionError(f"--init-samples {n_init} leaves {left} samples of record "
                              f"'{rec.name}' ({samples_after(rec, 0)} samples) to judge by: "
                              f"at least {MIN_HELD_OUT}")
    return n_init


def _compare_one(graph, rec, levels: dict, n_samples: int, given: dict, log, progress,
                 scales_from=None, x0: Mapping[str, float] | None = None) -> Comparison:
    """:func:`compare` on one record; its first ``n_samples`` set the start
    (``x0``: initial states a fit estimated on it, held there)."""
    say = (lambda m: log(f"{rec.name}: {m.strip()}"))
    settings = chosen_numerics(graph, rec, LoopSettings(params=[]), given=given,
                               log=lambda _m: None)
    settings = replace(settings, free_run=replace(settings.free_run, init_samples=n_samples))
    model = model_of(graph)
    if scales_from is None:
        problem = loop_problem(model, rec, settings)
    else:                                       # the declared graph's scales, inherited
        problem = loop_problem(model_of(scales_from), rec, settings).with_model(model)
    if x0:
        problem = problem.conditioned_on(x0={n: v for n, v in x0.items()
                                             if n in model.states})
        say("initial states as the fit estimated them on this record: "
            + ", ".join(f"{n} = {v:.6g}" for n, v in x0.items()))
    held, said = _noise_levels(problem, rec, levels)
    problem = replace(problem, noise=NoiseSpec("auto").holding(
        {o: v for o, (v, _) in held.items()}))
    say("measurement-noise std " + ", ".join(f"{o} {v:.4g} ({why})"
                                             for o, (v, why) in held.items()))
    for ln in said:
        say(ln)
    theta = problem.theta
    problem, numerics = _numerics(problem, theta, given, [held[o][0] for o in model.outputs])
    for ln in numerics:
        say(ln)
    res = run_ukf(problem, theta[None, :])
    nll = float(res.nll[0])
    failure = None if np.isfinite(nll) else str(res.reasons[0])
    ctx = Context(problem, settings, log=say, progress=progress)
    sim_y = free_run(ctx, problem, theta, own=False)
    n_init = init_samples(ctx, rec)             # the grid points of those samples
    t, _, y = problem.arrays
    rms, nr, fit = output_errors(y, sim_y, n_init)
    judged = y.copy()
    judged[:n_init] = np.nan
    metric = nrmse(judged, sim_y) if sim_y is not None else float("inf")
    return Comparison(
        record=rec.name, outputs=list(model.outputs), units=list(model.output_units),
        t=np.asarray(t, float), y=np.asarray(y, float), sim_y=sim_y, judged_from=n_init,
        rms=rms, nrmse=nr, fit_percent=fit, bias=mean_errors(y, sim_y, n_init), metric=float(metric),
        nll=nll,
        n_obs=int(np.isfinite(y).sum()), start=_start_text(problem, n_samples),
        noise=held, numerics=" ".join(numerics),
        trouble=free_run_trouble(sim_y, y, model.outputs), filter_failure=failure,
        window=n_samples)


def _numerics(problem, theta: np.ndarray, given: dict, sigma: list) -> tuple:
    """``(problem, lines)``: ``problem`` with the discretisation its check
    accepts at ``theta`` against the noise levels ``sigma`` (n_y,)
    (:func:`bondgraph.inference.discretise.choose_discretisation`; the
    fields the user ``given`` kept; where an input's shape leaves its hold
    ambiguous, the hold under which the filter is likelier at ``theta``,
    :func:`~bondgraph.inference.discretise.likelier_hold_at`, as
    sensitivity and track take it), then with the substeps whose NLL agrees
    with RK4's (else ROS2's, where RK4's is not finite) at
    :data:`~bondgraph.inference.ukf.GUARD_SUBSTEPS` substeps to
    :data:`~bondgraph.inference.ukf.GUARD_REL` (the NLL guard of
    :func:`bondgraph.inference.ukf.nll_guard`: the filter's covariance
    propagation can feel a step that the check, which follows the free
    run, passes: a user's CED graph's stiff armature mode), unless
    ``--substeps`` is given; the reference itself where no doubling agrees.
    The lines say what was chosen."""
    lines = []
    if len(given) < 3:
        where = "at these parameters and noise levels"
        choice = choose_discretisation(problem, theta, given=given, sigma=sigma)
        if "hold" not in given:     # an ambiguous input's shape: the likelier hold here
            choice, line = likelier_hold_at(problem, theta, choice, sigma=sigma, where=where)
            lines += [line] if line else []
        lines.append(choice.line(where))
        if choice.disc != problem.disc:
            problem = problem.conditioned_on(disc=choice.disc)
    if "substeps" in given:
        return problem, lines

    def nll_of(p) -> float:
        return float(run_ukf(p, theta[None, :]).nll[0])

    def apart(a: float, b: float) -> float:
        if not (np.isfinite(a) and np.isfinite(b)):
            return 0.0 if a == b else np.inf
        return abs(a - b) / max(abs(b), 1e-300)

    disc = replace(problem.disc, refine=())
    ref_p = problem.conditioned_on(disc=replace(disc, method="rk4", substeps=GUARD_SUBSTEPS))
    now, ref = nll_of(problem), nll_of(ref_p)
    if not np.isfinite(ref):        # a mode too fast for RK4 even so: the L-stable ROS2
        ref_p = problem.conditioned_on(disc=replace(disc, method="ros2",
                                                    substeps=GUARD_SUBSTEPS))
        ref = nll_of(ref_p)
    name = f"{ref_p.disc.method}({GUARD_SUBSTEPS})"
    if apart(now, ref) <= GUARD_REL or not np.isfinite(ref):
        return problem, lines
    s = disc.substeps
    while s < GUARD_SUBSTEPS:
        s = min(2 * s, GUARD_SUBSTEPS)
        p = problem.conditioned_on(disc=replace(disc, substeps=s))
        if apart(nll_of(p), ref) <= GUARD_REL:
            lines.append(f"{disc.method}({disc.substeps})'s NLL {now:.6g} is {apart(now, ref):.2g} "
                         f"relative from {name}'s {ref:.6g}: the filter takes "
                         f"{disc.method}({s}), whose NLL agrees")
            return p, lines
    lines.append(f"{disc.method}({disc.substeps})'s NLL {now:.6g} is {apart(now, ref):.2g} "
                 f"relative from {name}'s {ref:.6g}, and no finer step of it "
                 f"agrees: the filter takes {name}")
    return ref_p, lines


def _start_text(problem, n_init: int) -> str:
    """How :func:`bondgraph.diagnose.fit.free_run` sets the free run's
    initial state on ``problem``'s record (in words)."""
    unknown = problem.prior.unknown(problem.model, problem.record)
    if not unknown:
        return "the record's own initial state (state columns or sidecar x0)"
    given = [s for s in problem.model.states if s not in unknown]
    what = (f"the smoothed state given its first {n_init} samples (errors over the rest)"
            if n_init else "the smoothed state given the whole record (the loop's rule; a "
                           "start fitted to the outputs where the smoother fails, logged)")
    return what + (f"; {', '.join(given)} from the record" if given else "")


def _noise_levels(problem, rec, levels: dict) -> tuple[dict, list[str]]:
    """Output -> (std, source) for every output of ``problem``'s model: the
    record's declaration, else ``levels``, else profiled at the problem's θ
    (:func:`bondgraph.inference.estimate.start_levels_profiled`), else the
    graph's own sensor noise, else the level the record's second
    differences show (:func:`bondgraph.inference.estimand.record_noise_level`);
    and the lines to log."""
    from bondgraph.errors import EstimationError, NumericalError
    from bondgraph.inference.estimand import record_noise_level
    from bondgraph.inference.estimate import start_levels_profiled

    model = problem.model
    declared = np.asarray(rec.noise_std_for(model), float)
    own = np.asarray(model.meas_std(problem.theta[None, :]), float)[0]
    held, todo = {}, []
    for j, o in enumerate(model.outputs):
        if np.isfinite(declared[j]) and declared[j] > 0:
            held[o] = (float(declared[j]), "the record's declaration")
        elif o in levels:
            held[o] = (levels[o], "the fit's estimate")
        else:
            todo.append(j)
    said = []
    if todo:
        free = [p for p in model.params if p not in problem.fixed][:1]
        prof = np.full(model.n_y, np.nan)
        if free:
            try:
                prof = start_levels_profiled(
                    replace(problem, noise=NoiseSpec("auto").holding(
                        {o: v for o, (v, _) in held.items()})), free)
            except (EstimationError, NumericalError, FloatingPointError,
                    np.linalg.LinAlgError) as exc:
                said.append(f"profiling the noise levels failed ({str(exc).splitlines()[0]}): "
                            f"the graph's own levels are used")
        for j in todo:
            o = model.outputs[j]
            if np.isfinite(prof[j]) and prof[j] > 0:
                held[o] = (float(prof[j]), "profiled on this record at these parameters")
            elif np.isfinite(own[j]) and own[j] > 0:
                held[o] = (float(own[j]), "the graph's sensor noise")
            else:
                seen = float(record_noise_level(problem.arrays[2][:, j:j + 1])[0])
                held[o] = ((seen, "seen in the record's second differences")
                           if np.isfinite(seen) and seen > 0 else
                           (1.0, "1 output unit: nothing gives one"))
    return {o: held[o] for o in model.outputs}, said
