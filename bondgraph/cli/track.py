"""``bondgraph track``: online parameter tracking and change detection over a
record (:mod:`bondgraph.inference.track`), writing ``track.csv``,
``changes.json`` and a plot per tracked parameter."""

from __future__ import annotations

import argparse
import csv
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from bondgraph.cli.common import (
    add_data,
    add_discretisation,
    add_fixed,
    add_initial_state,
    add_model,
    add_overwrite,
    default_out,
    discretisation_given,
    filtered_record,
    load_model,
    load_record,
    output_folder,
    parse_names,
    parse_pairs,
    problem_from_args,
    published,
)
from bondgraph.core import progress
from bondgraph.core.jsonsafe import from_jsonable, to_jsonable
from bondgraph.errors import DataError, ExportError
from bondgraph.inference.discretise import (
    alternative_hold,
    choose_discretisation,
    likelier_hold_at,
    record_input_holds,
    supported_hold,
)
from bondgraph.inference.estimand import start_levels
from bondgraph.inference.fisher import near_bound
from bondgraph.inference.options import NOISE_MODES, TrackOptions
from bondgraph.inference.track import (
    Tracker,
    TrackingModel,
    check_tracked,
    choose_substeps,
    track,
)
from bondgraph.inference.ukf_numba import compile_in_background
from bondgraph.numerics.registry import graph_builder
from bondgraph.report.tracking import plot_track


#: the example line of ``bondgraph track --help``
EXAMPLE = "bondgraph track --model mass_spring_damper --data msd_force_step.csv --track c --out track_out"


def configure(p: argparse.ArgumentParser) -> None:
    """Options of ``bondgraph track``."""
    add_model(p)
    add_data(p, remedy="it tracks along one record; fit the constant parameters on several "
                       "with `bondgraph estimate --data A --data B` and pass its result.json "
                       "as --from")
    p.add_argument("--track", required=True, help="comma-separated parameters to track")
    p.add_argument("--drift", action="append", default=None,
                   help="name=value,... drift intensity of a tracked parameter, in its unit "
                        "per sqrt(s) (default 0: a constant, re-estimated at changes)")
    p.add_argument("--from", dest="from_result", default=None,
                   help="result.json of `bondgraph estimate` or report.json of `bondgraph "
                        "loop` (its final fit): its estimates are the start values (tracked) "
                        "and fixed values (others), its std the prior std")
    p.add_argument("--false-alarm-hours", type=float, default=10.0,
                   help="mean time between false alarms of the change detector [h] "
                        "(default 10; 0: no detection)")
    p.add_argument("--window", type=float, default=None,
                   help="GLR window [s] (default 10 s, but at least 20 samples)")
    p.add_argument("--observable-s", type=float, default=None,
                   help="window over which the record's information about a parameter is "
                        "summed to call it observable [s] (default 2 s, but at least 10 "
                        "samples)")
    p.add_argument("--observable-ratio", type=float, default=0.5,
                   help="observable where the window's data alone would leave at most this "
                        "fraction of the prior variance (default 0.5)")
    p.add_argument("--prior-rel", type=float, default=0.1,
                   help="prior std of a tracked parameter relative to its start (default 0.1)")
    p.add_argument("--glr-clip", type=float, default=3.0,
                   help="the change detector's standardised parameter updates are clipped to "
                        "± this before its sums (default 3: one sample adds at most 4.5 nats, "
                        "a sensor's single spike raises no alarm, a change shows as a run of "
                        "samples; 0: the plain Gaussian GLR)")
    p.add_argument("--no-calibrate", dest="calibrate", action="store_false",
                   help="leave the change detector as the threshold assumes: by default, "
                        "where a parameter's standardised updates are serially correlated on "
                        "the record (their sums vary at least twice as much as white noise's, "
                        "or more and their lag-1 autocorrelation shows it: the model's error), "
                        "they are divided by the square root of that factor so that "
                        "--false-alarm-hours holds (one line says so)")
    p.add_argument("--online", action="store_true",
                   help="also replay the record through the streaming tracker, one sample at "
                        "a time as they would arrive (each change decided from the samples up "
                        "to that moment; the serial inflation this record's pass measured): "
                        "its changes, when each was raised and when attributed, into the "
                        "summary and changes_online.json")
    p.add_argument("--out", default=None,
                   help="output directory (default track_<model>_<data>, numbered -2, -3, "
                        "... when it holds an earlier result); an explicit --out is refused "
                        "when not empty, unless --overwrite")
    add_overwrite(p)
    add_fixed(p)
    add_initial_state(p)
    p.add_argument("--noise", choices=NOISE_MODES, default="auto",
                   help="measurement-noise levels (as for estimate; auto: the record's)")
    add_discretisation(p, chosen=False)
    for a in p._actions:
        if a.dest == "method":
            a.help = ("UKF discretisation of the state equations (default: the model's filter "
                      "method; when its substeps do not converge on the tracked record, rk4 "
                      "if its do; one line on stderr)")
        if a.dest == "substeps":
            a.help = ("integrator steps per sample (default: chosen from the record by tracking "
                      "it with 1, 2, 4, ... substeps: the first whose observability windows' "
                      "log-likelihood is within one sampling std of a finer one's, "
                      "choose_substeps; one line on stderr)")
        if a.dest == "hold":
            a.help = ("input over a sample interval: zoh, mean, linear, or one per input "
                      "comma-joined (zoh,linear). Default: the hold the record declares for "
                      "each input (sidecar columns.<input>.hold), else the one its samples "
                      "support (a staircase zoh, a sampled continuous signal linear; where "
                      "the shape is ambiguous, the hold whose filter is likelier at the "
                      "tracking start); one line on stderr")
    p.add_argument("--no-plots", action="store_true")


def _from_result(path) -> tuple[dict, dict]:
    """``(values, std)`` by parameter name of an estimate's result.json or a
    loop's report.json (its final fit: estimates and Cramér-Rao std); a
    quantity without a std (on its box: null in the file) has none."""
    try:
        d = from_jsonable(json.loads(Path(path).read_text()))
        if isinstance(d, dict) and isinstance(d.get("final_fit"), dict):
            fit = d["final_fit"]
            return ({n: float(v) for n, v in fit["estimates"].items()},
                    {n: float(s) for n, s in (fit.get("std") or {}).items()
                     if s is not None and np.isfinite(float(s))})
        names = list(d["params"])
        return (dict(zip(names, map(float, d["estimates"]))),
                {n: float(s) for n, s in zip(names, d.get("std") or [])
                 if s is not None and np.isfinite(float(s))})
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise DataError(f"--from {path}: neither a `bondgraph estimate` result.json nor a "
                        f"`bondgraph loop` report.json ({type(exc).__name__}: {exc})") from None


def _from_levels(path) -> dict:
    """The measurement-noise levels (output -> std) of ``--from``'s fit,
    estimated or held (:func:`bondgraph.export.params.read_noise_levels`:
    an estimate's ``noise.<output>``, a loop report's
    ``final_fit.noise_estimates``); before, a loop's were not read and a
    user's closed-loop EMPS graph was tracked against the record's
    second-difference levels (drive command 0.040 V against the fit's
    0.066 V).

    Raises
    ------
    DataError
        The file is neither a result nor a report.
    """
    from bondgraph.export.params import read_noise_levels

    try:
        return {o: float(v) for o, v in read_noise_levels(path).items()
                if v is not None and np.isfinite(float(v))}
    except ExportError as exc:
        raise DataError(f"--from {path}: {exc}") from None


def bare_levels(problem, levels: dict) -> tuple[dict, str]:
    """Measurement-noise stds to hold for the outputs that nothing gives
    one (the sensor declares none, ``meas_std`` 0, and the record declares
    none; the tracker estimates no level, so the filter would weigh them by
    0 and fail at sample 0): the level of ``--from``'s fit
    (``noise.<output>``) when it has one, else the start an estimate would
    take (:func:`~bondgraph.inference.estimand.start_levels`: the record's
    second-difference level, at least the output's std / 1e4).
    Returns ``(output -> std, one line saying which)``; ``({}, "")`` when
    every measured output has a level."""
    model = problem.model
    held = problem.noise.sigma(model)
    with np.errstate(all="ignore"):
        meas = np.asarray(model.meas_std(problem.theta[None, :]), float).reshape(-1)
    seen = start_levels(problem.y)
    out, how = {}, []
    for j, o in enumerate(model.outputs):
        if np.isfinite(held[j]) or meas[j] > 0 or not np.isfinite(problem.y[:, j]).any():
            continue
        v = levels.get(o)
        if v is not None and np.isfinite(v) and v > 0:
            out[o] = float(v)
            how.append(f"{o} = {v:.4g} (the --from fit's)")
        elif np.isfinite(seen[j]):
            out[o] = float(seen[j])
            how.append(f"{o} = {seen[j]:.4g} (the record's second differences, an upper "
                       f"estimate)")
    return out, ("measurement-noise std held (neither the sensor nor the record declares one; "
                 "the tracker estimates none): " + ", ".join(how)) if how else ""


def tracking_hold(problem, args) -> tuple[str, str]:
    """The inputs' hold for tracking without ``--hold``, and why: the one the
    record declares or its inputs' shape supports
    (:func:`~bondgraph.inference.discretise.record_input_holds`,
    :func:`~bondgraph.inference.discretise.supported_hold`); where a shape is
    ambiguous, the one whose filter is likelier at the tracking start
    (:func:`~bondgraph.inference.discretise.likelier_hold_at`, each hold's
    step chosen at that θ as ``--method``/``--substeps`` allow; one line on
    stderr says which)."""
    inputs = record_input_holds(problem.record, problem.model.inputs, problem.u)
    hold, why = supported_hold(inputs)
    if alternative_hold(inputs, hold) is None:
        return hold, why
    given = discretisation_given(args)
    choice = choose_discretisation(problem, problem.theta, given=given, hold=hold, why=why)
    kept, line = likelier_hold_at(problem, problem.theta, choice, where="at the tracking start")
    print(line, file=sys.stderr)
    return kept.disc.hold, kept.hold_reason


def tracking_discretisation(problem, tm, std: dict, opts, method_free: bool):
    """``problem`` with the tracking filter's substeps chosen from the
    tracked record (:func:`~bondgraph.inference.track.choose_substeps`, one
    line on stderr each). When its method does not converge within
    :data:`~bondgraph.inference.track.MAX_SUBSTEPS` and the user gave no
    ``--method``, RK4 is tried the same way and taken if it converges: a
    user's two-mass drive needed more than 128 ROS2 substeps (error 27
    window std at 32) where its estimate's check passed RK4 with 2."""
    choice = choose_substeps(problem, tm, std=std, options=opts)
    print(choice.line(), file=sys.stderr)
    if not choice.ok and method_free and problem.ukf.method != "rk4":
        alt = problem.conditioned_on(disc=replace(problem.disc, method="rk4", substeps=1))
        other = choose_substeps(alt, tm, std=std, options=opts)
        print(other.line() + ("; taken" if other.ok else ""), file=sys.stderr)
        if other.ok:
            return alt.conditioned_on(disc=replace(alt.disc, substeps=other.substeps))
    return problem.conditioned_on(disc=replace(problem.disc, substeps=choice.substeps))


def run(args) -> int:
    """Track, detect, write the folder, print the summary."""
    if getattr(args, "backend", "numba") == "numba":
        compile_in_background()     # the filter kernel, once per installation, beside the set-up
    with progress.phase("loading the model"):
        graph = graph_builder(args.model)()
        model = load_model(args.model)
    names = parse_names(args.track, "--track")
    check_tracked(names, model)
    drift = parse_pairs(args.drift, "--drift")
    values, std = _from_result(args.from_result) if args.from_result else ({}, {})
    # the fit's measurement-noise levels, estimated or held (a loop's report
    # keeps them apart from the estimates, ``final_fit.noise_estimates``):
    # held for the outputs nothing else gives one (:func:`bare_levels`)
    levels = _from_levels(args.from_result) if args.from_result else {}
    values = {k: v for k, v in values.items() if k in model.params}
    folder = output_folder(default_out(args, f"track_{model.name}_{Path(args.data).stem}",
                                       "track"), args)
    exp = filtered_record(load_record(args.data, model, columns=args.columns, dt=args.dt), model,
                          args)
    problem = problem_from_args(model, exp, args, values=values)
    held, line = bare_levels(problem, levels)
    if held:
        print(line, file=sys.stderr)
        problem = problem.conditioned_on(noise_levels=held)
    opts = TrackOptions(prior_rel=args.prior_rel, window_s=args.window,
                        false_alarm_hours=args.false_alarm_hours or None,
                        observable_s=args.observable_s, observable_ratio=args.observable_ratio,
                        glr_clip=args.glr_clip or None, calibrate=args.calibrate)
    start = {n: float(problem.theta[model.param_index(n)]) for n in names}
    tm = TrackingModel.from_graph(graph, names, drift, start=start)
    std = {n: std[n] for n in names if n in std}
    if args.hold is None:               # the hold the record declares or supports
        hold, why = tracking_hold(problem, args)
        print(f"input hold {hold} (chosen; --hold to give it): {why}", file=sys.stderr)
        problem = problem.conditioned_on(disc=replace(problem.disc, hold=hold))
    if args.substeps is None:           # the substeps the tracked record needs
        with progress.phase("choosing the tracking filter's substeps"):
            problem = tracking_discretisation(problem, tm, std, opts, args.method is None)
    with progress.phase(f"tracking {', '.join(names)} (the filter, the smoother, the change "
                        f"tests)"):
        res = track(problem, tm, std=std, options=opts)
    online = None
    if args.online and opts.false_alarm_hours is not None:
        with progress.phase("replaying the record on-line (the streaming tracker)"):
            online = online_changes(problem, tm, std, opts, res)
    truth = dict((exp.meta or {}).get("true_parameters") or {})
    for name, column in ((exp.meta or {}).get("schedules") or {}).items():
        truth[name] = exp[column]        # a parameter that changes: its time series

    def version(d: Path) -> list:
        _write_csv(d / "track.csv", res.columns())
        (d / "changes.json").write_text(json.dumps(to_jsonable(
            {"threshold": res.threshold, "settings": res.settings,
             "changes": [c.to_dict() for c in res.changes]}), indent=2, allow_nan=False) + "\n")
        extra = []
        if online is not None:
            (d / "changes_online.json").write_text(json.dumps(to_jsonable(
                {"threshold": res.threshold, "inflation": res.settings.get("inflation"),
                 "changes": [c.to_dict() for c in online]}), indent=2, allow_nan=False) + "\n")
            extra.append(d / "changes_online.json")
        with progress.phase("drawing the plots"):
            pngs = [] if args.no_plots else plot_track(res, d, truth=truth)
        return [d / "track.csv", d / "changes.json", *extra, *pngs]
    written = folder.publish(version)
    print(summary(res))
    if online is not None:
        print(online_summary(online, res))
    elif args.online:
        print("--online: no change detection (--false-alarm-hours 0): nothing to replay")
    for pth in published(folder, written):
        print(f"wrote {pth}")
    return 0


def online_changes(problem, tm, std: dict, opts: TrackOptions, res) -> list:
    """The changes the streaming tracker (:class:`~bondgraph.inference.track.Tracker`,
    on-line detection) raises on ``problem``'s record fed one sample at a
    time, with the batch run ``res``'s serial inflation of each parameter's
    updates (an on-line tracker has no second pass to measure it)."""
    trk = Tracker.from_problem(problem, tm, std=std, options=opts,
                               inflation=res.settings.get("inflation"))
    t, u, y = problem.t, problem.u, problem.y
    for k in range(t.size):
        trk.update(t[k], u[k], y[k])
    return trk.changes


def online_summary(online: list, res) -> str:
    """What the replay found, beside the batch tracker's changes: each
    change with its alarm and attribution times, and whether the batch run
    has it (the same change sample and parameter)."""
    batch = {(c.index, c.parameter) for c in res.changes}
    first = sum(1 for c in online if c.at_start)
    lines = [f"on-line (the streaming tracker, each sample as it arrives): {len(online) - first}"
             f" change(s)" + (f" and {first} at the start" if first else "")]
    for c in online:
        same = "as the batch run" if (c.index, c.parameter) in batch else "not in the batch run"
        same += "; at the start: within the first window after it became observable" \
            if c.at_start else ""
        lines.append(f"  t = {c.time:.6g} s: {c.parameter} raised at {c.alarm_time:.6g} s "
                     f"(by {c.detected}'s updates), attributed at {c.attributed_time:.6g} s: "
                     f"{c.before:.6g} -> {c.after:.6g} ± {c.after_std:.3g} ({same})")
    missed = [c for c in res.changes if (c.index, c.parameter) not in
              {(o.index, o.parameter) for o in online}]
    for c in missed:
        lines.append(f"  the batch run's change of {c.parameter} at {c.time:.6g} s is not "
                     f"found on-line (the batch attributes with a whole window after the alarm "
                     f"and restarts centred on the segment's end; the stream decides as soon "
                     f"as one restart explains the samples by more than the threshold, "
                     f"centred there)")
    return "\n".join(lines)


def _write_csv(path: Path, cols: dict) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(list(cols))
        for row in zip(*cols.values()):
            w.writerow([repr(float(v)) for v in row])


def _observability_line(res, name: str, i: int, most: int = 4) -> str:
    """``observable 93 % of the record; not observable 20.1-50.3 s, ...``
    (the ``most`` longest stretches, in time order)."""
    frac = float(np.mean(res.observable[:, i]))
    st = res.unobservable(name)
    if not st:
        return f"  {'':>16s}  observable over the whole record"
    shown = sorted(sorted(st, key=lambda ab: ab[0] - ab[1])[:most])
    more = f" and {len(st) - most} shorter" if len(st) > most else ""
    return (f"  {'':>16s}  observable {100 * frac:.3g} % of the record; not observable "
            + ", ".join(f"{a:.6g}-{b:.6g} s" for a, b in shown) + more
            + " (no change detected there)" + (needed_window(res, name, i) if frac < 0.5 else ""))


def needed_window(res, name: str, i: int) -> str:
    """For a parameter observable in less than half the record: the window
    over which the record's typical information per sample Ī (the median
    over the samples) would make it observable, σ₀² Ī W >= 1/ρ − 1
    (:func:`~bondgraph.inference.changes.observable_mask`), W in seconds,
    with the options that set it; or that the whole record holds less than
    that. "" when the result does not say σ₀. The median, not the mean: a
    few samples of extreme information (a parameter pinned on its box, its
    std 0) made the mean's window 3.4e-38 s on a user's closed-loop EMPS
    graph whose Fv was observable over 25 % of the record."""
    s0 = (res.settings.get("sigma0") or {}).get(name)
    rho = (res.settings.get("track") or {}).get("observable_ratio")
    dt = res.settings.get("dt")
    if not s0 or not rho or not dt or res.information is None:
        return ""
    info = res.information[:, i]
    info = info[np.isfinite(info)]
    mean = float(np.median(info)) if info.size else 0.0
    need = 1.0 / rho - 1.0
    if mean <= 0 or s0 ** 2 * mean * res.t.size < need:
        return (f"; at its typical (median) information per sample the whole record would "
                f"hold too little to see a change of {s0:.3g} {res.units[i]} (--prior-rel of its "
                f"start): not trackable from this record")
    w = need / (s0 ** 2 * mean) * dt
    # the option a quarter above the mean's window, rounded up to 2 digits:
    # at the mean's own window, half the windows of an even record fall short
    top = 10.0 ** (np.floor(np.log10(1.25 * w)) - 1)
    give = float(np.ceil(1.25 * w / top) * top)
    return (f"; at this record's typical information it would be observable over windows of "
            f"about {w:.2g} s (--observable-s {give:g}; changes then need --window of at least "
            f"that)")


#: a record shorter than two GLR windows is cut into this many windows for
#: the inconsistency warning (more than 5 % of them, and more than one, must
#: be inconsistent: with one window it could never fire)
SHORT_RECORD_WINDOWS = 20


def summary(res) -> str:
    """The one-screen summary: final estimates and the detected changes."""
    lines = [f"tracked {', '.join(res.names)} over {res.t[-1] - res.t[0]:.6g} s "
             f"({res.t.size} samples), NLL {res.nll:.6g}",
             "threshold: " + ("none (no detection)" if res.threshold is None
                              else f"{res.threshold:.4g}")]
    for n, lam in (res.settings.get("inflation") or {}).items():
        if lam > 1.0:
            lines.append(f"  {n}: its updates are serially correlated on this record (their sums "
                         f"vary {lam:.3g} times as much as white noise's: the model's error, "
                         f"which the test would read as changes); the test takes them divided "
                         f"by {np.sqrt(lam):.3g}, a change must be that much larger to be seen "
                         f"(--no-calibrate: as they are); `bondgraph loop` finds what the model "
                         f"lacks")
    for i, n in enumerate(res.names):
        lines.append(f"  {n:>16s}: start {res.estimate[0, i]:.6g} ± {res.std[0, i]:.3g}, "
                     f"end {res.estimate[-1, i]:.6g} ± {res.std[-1, i]:.3g} {res.units[i]}")
        if res.observable is not None:
            lines.append(_observability_line(res, n, i))
    w_s, span = res.settings["window"] * res.settings["dt"], res.t[-1] - res.t[0]
    if span < 2 * w_s:          # one GLR window: the test below could never fire
        w_s = max(span / SHORT_RECORD_WINDOWS, res.settings["dt"])
    bad = res.inconsistent(window_s=w_s)
    n_win = max(1, int(np.ceil((span + 1e-9) / w_s)))
    if len(bad) > max(1, 0.05 * n_win):
        lines.append(f"warning: the innovations are larger than the model allows in {len(bad)} "
                     f"of {n_win} windows of {w_s:.4g} s (first at {bad[0][0]:.6g} s): the "
                     f"model lacks "
                     f"an effect there (or the filter's step is too coarse: --substeps), and "
                     f"the tracker may read it as parameter changes; find it with `bondgraph "
                     f"loop` before trusting the changes")
    for i, n in enumerate(res.names):
        lo, hi = res.settings.get("boxes", {}).get(n, (None, None))
        if lo is None:
            continue
        near_lo, near_hi = near_bound(res.estimate[:, i], lo, hi, rel=1e-3)
        on = np.mean(near_lo | near_hi)
        if on > 0.05:
            lines.append(f"warning: {n} sits on its box [{lo:g}, {hi:g}] for {100 * on:.0f} % "
                         f"of the record: the box, or the model, is wrong there")
    start = [c for c in res.changes if c.at_start]
    for c in start:
        lines.append(f"at the start: {c.parameter} {c.before:.6g} ± {c.before_std:.3g} -> "
                     f"{c.after:.6g} ± {c.after_std:.3g} from {c.time:.6g} s (alarm "
                     f"{c.alarm_time:.6g} s, GLR {c.statistic:.4g}), within the detector's first "
                     f"window after it became observable: the record's first informative "
                     f"samples disagree with the start value (a prior that does not hold on "
                     f"this record, or a change early in it); not counted as a change")
    lines.append(f"{len(res.changes) - len(start)} change(s)")
    for c in res.changes:
        if not c.at_start:
            lines.append(f"  t = {c.time:.6g} s (alarm {c.alarm_time:.6g} s): {c.parameter} "
                         f"{c.before:.6g} ± {c.before_std:.3g} -> {c.after:.6g} ± "
                         f"{c.after_std:.3g} (GLR {c.statistic:.4g})")
    return "\n".join(lines)
