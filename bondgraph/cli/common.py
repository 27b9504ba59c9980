"""Options shared by the commands, declared and parsed in one place.

Every command that takes a model accepts a registered name,
``module:function`` or ``path/to/file.py:function`` (the current directory is
on the import path); ``--fixed``, ``--x0``, ``--p0-rel``, ``--estimate-x0``,
``--noise`` (:func:`add_estimation_scope`), ``--method``, ``--substeps``,
``--hold`` and ``--backend`` mean the same in every command.
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Iterable

import numpy as np

from bondgraph.core.atomic import OutputFolder, is_empty_dir
from bondgraph.core.equations import derive
from bondgraph.core.graph import BondGraph
from bondgraph.data.records import Experiment, ordinal
from bondgraph.errors import DataError, OptionError
from bondgraph.inference.discretise import (
    DiscretisationChoice,
    choose_discretisation,
    declared_holds,
    finer_grid_record,
    likelier_hold_at,
    oversampling,
    record_input_holds,
)
from bondgraph.inference.options import (
    DEFAULT_BACKEND,
    NOISE_MODES,
    P0_REL,
    P0_SCALES,
    UKF_BACKENDS,
    UKF_METHODS,
    UKFOptions,
)
from bondgraph.inference.prior import PriorSpec
from bondgraph.inference.problem import NoiseSpec, Problem, make_problem
from bondgraph.numerics.integrators import split_hold

MODEL_HELP = ("model: a registered name (`bondgraph models`), module:function or "
              "path/to/file.py:function returning a BondGraph (modules are imported from "
              "the current directory too)")


def parse_pairs(items: str | Iterable[str] | None, option: str) -> dict[str, float]:
    """``name=value`` pairs of an option, comma-separated or repeated.

    Parameters
    ----------
    items : str or iterable of str or None
        ``"a=1,b=2"`` or ``["a=1", "b=2"]``.
    option : str
        The option's name for messages (``"--fixed"``).

    Returns
    -------
    dict
        ``name -> float``.

    Raises
    ------
    OptionError
        An item without ``=`` or a value that is not a finite number.
    """
    if not items:
        return {}
    if isinstance(items, str):
        items = [items]
    out: dict[str, float] = {}
    for chunk in items:
        for item in chunk.split(","):
            if not item.strip():
                continue
            name, sep, val = item.partition("=")
            if not sep:
                raise OptionError(f"{option} expects name=value pairs separated by commas, got "
                                  f"'{item}'")
            try:
                out[name.strip()] = float(val)
            except ValueError:
                raise OptionError(f"{option}: value of '{name.strip()}' is not a number: "
                                  f"'{val}'") from None
            if not math.isfinite(out[name.strip()]):
                raise OptionError(f"{option}: value of '{name.strip()}' is not a finite "
                                  f"number: '{val.strip()}'")
    return out


def parse_names(text: str | None, option: str) -> list[str]:
    """Comma-separated names (``a,b,c``).

    Raises
    ------
    OptionError
        The option was given but holds no name.
    """
    if text is None:
        return []
    names = [s.strip() for s in text.split(",") if s.strip()]
    if not names:
        raise OptionError(f"{option}: no names given")
    return names


def parse_renames(text: str | None, option: str = "--columns") -> dict[str, str]:
    """``file=model`` pairs, comma-separated (``Current=I,Voltage=V``).

    Raises
    ------
    OptionError
        An item without ``=``, an empty name, a column named twice.
    """
    out: dict[str, str] = {}
    for item in (text or "").split(","):
        if not item.strip():
            continue
        old, sep, new = (x.strip() for x in item.partition("="))
        if not sep or not old or not new:
            raise OptionError(f"{option} expects COLUMN=NAME pairs separated by commas (the "
                              f"record's column, the model's name), got '{item.strip()}'")
        if old in out:
            raise OptionError(f"{option}: column '{old}' renamed twice")
        out[old] = new
    return out


def add_columns(p: argparse.ArgumentParser) -> None:
    """``--columns``: the record's columns renamed to the model's names;
    ``--dt``: the sample interval of records without a time column."""
    p.add_argument("--columns", default=None, metavar="COLUMN=NAME,...",
                   help="rename the records' columns to the model's input, output or state "
                        "names as they are read (e.g. Current=I,Voltage=V: a logger's names); "
                        "a unit in brackets after the new name replaces the file's "
                        "(Fuel=fuel[cm^3/s]: a logger's abbreviation pint reads otherwise); "
                        "every record of the command")
    p.add_argument("--dt", type=float, default=None, metavar="SECONDS",
                   help="sample interval of the records: a file without a time column "
                        "(published benchmark files often have none) is read with t = k dt; "
                        "one with a time column must agree with it; every record of the "
                        "command (default: the time column, or the sidecar's dt)")


def reading_options(args) -> str:
    """The options that read the command's records (``--columns``,
    ``--dt``) as command-line text (" --columns A=a --dt 0.02"; "" when
    none was given): a line that tells the user how to run another command
    on another record passes them on, quoted for a POSIX shell where needed
    (a unit in brackets: ``--columns 'Fuel=fuel[cm^3/s]'``)."""
    return "".join(f" --{o} {shlex.quote(str(v))}"
                   for o, v in (("columns", getattr(args, "columns", None)),
                                ("dt", getattr(args, "dt", None)))
                   if v is not None)


def parse_params(text: str, model=None) -> list[str]:
    """Parameters of ``--params``: ``a,b,c`` or ``recommended:<sensitivity.json>``
    (the set recommended by :func:`bondgraph.sensitivity.analysis.recommended_params`).

    Raises
    ------
    OptionError
        Empty list.
    SensitivityError
        Missing or malformed sensitivity file.
    ModelError
        A recommended parameter the model does not have.
    """
    text = (text or "").strip()
    if text.startswith("recommended:"):
        from bondgraph.sensitivity.analysis import recommended_params

        return recommended_params(text[len("recommended:"):], model)
    return parse_names(text, "--params")


def default_params(spec: str, model, command: str, fixed=()) -> list[str]:
    """The parameters a command estimates without ``--params``: those the
    graph declares with a box (``Parameter.box_declared``; a parameter
    declared without one is a known value, held at it, as ``bondgraph loop``
    holds it where the record cannot tell it apart), or all of the model's
    when none has a box; never one of ``fixed`` (``--fixed``: without it,
    ``--fixed m=2.5`` and no ``--params`` was refused as "m both fixed and
    estimated"). One line on stderr says which, and which are held.

    Parameters
    ----------
    spec : str
        ``--model`` (a registered name or a graph builder).
    model : Model
        The model built from it (its parameters, in order).
    command : str
        The command's name, for the line.
    fixed : collection of str
        The parameters ``--fixed`` holds.
    """
    from bondgraph.numerics.registry import graph_builder

    declared = graph_builder(spec)().params
    boxed = [n for n in model.params
             if n in declared and getattr(declared[n], "box_declared", True)]
    names = [n for n in boxed or list(model.params) if n not in fixed]
    held = [n for n in model.params if n not in names and n not in fixed]
    verb = "analysing" if command == "sensitivity" else "estimating"
    what = (f"the {len(names)} parameters declared with a box" if boxed else
            f"all {len(names)} parameters") + f" ({', '.join(names)})"
    if fixed:
        what = what.replace("all ", "") + f"; held at --fixed: {', '.join(fixed)}"
    if held:
        what += (f"; held at their declared values (declared without a box: known): "
                 f"{', '.join(held)}")
    print(f"bondgraph {command}: no --params: {verb} {what}; --params to choose",
          file=sys.stderr)
    return names


# ------------------------------------------------------------ declarations
def add_model(p: argparse.ArgumentParser, *, positional: bool = False,
              required: bool = True) -> None:
    """``--model`` (or a positional ``model``, which also takes ``--model``
    as the commands that filter do; :func:`merged_model` joins the two)."""
    if positional:
        p.add_argument("model", nargs="?", default=None, help=MODEL_HELP)
        p.add_argument("--model", dest="model_option", default=None, metavar="MODEL",
                       help="the same as the positional model")
    else:
        p.add_argument("--model", required=required, help=MODEL_HELP)


def merged_model(args: argparse.Namespace) -> str | None:
    """The model of a command whose model is positional (``add_model(p,
    positional=True)``), given either way; an error (text) when both are
    given and differ, or neither is. None when the command has no such
    model."""
    if not hasattr(args, "model_option"):
        return None
    given = {m for m in (args.model, args.model_option) if m is not None}
    if len(given) > 1:
        return f"two models given: {args.model!r} and --model {args.model_option!r}"
    if not given:
        return "the model is required: bondgraph COMMAND MODEL (or --model MODEL)"
    args.model = given.pop()
    del args.model_option
    return None


class Once(argparse.Action):
    """An option given at most once: a second occurrence is refused with
    ``remedy`` (argparse's default keeps the last one silently, so
    ``--data a.csv --data b.csv`` would drop a record without a word)."""

    def __init__(self, option_strings, dest, remedy: str = "", **kwargs):
        self.remedy = remedy
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        seen = getattr(namespace, "_once_seen", set())
        if self.dest in seen:
            raise argparse.ArgumentError(
                self, f"given twice ({getattr(namespace, self.dest)!r} and {values!r}); this "
                      f"command takes one" + (f": {self.remedy}" if self.remedy else ""))
        namespace._once_seen = seen | {self.dest}
        setattr(namespace, self.dest, values)


#: what a command that takes one record says to a second ``--data``
ONE_RECORD = ("run it once per record (`bondgraph estimate --data A --data B` fits one "
              "parameter set to several records)")


def add_data(p: argparse.ArgumentParser, *, required: bool = True,
             several: bool = False, remedy: str = ONE_RECORD, help: str | None = None) -> None:
    """``--data``: the record (``several``: repeatable, a list of records;
    else a second ``--data`` is refused with ``remedy``, :class:`Once`);
    ``help`` replaces the fitting commands' help text."""
    add_columns(p)
    if several:
        p.add_argument("--data", required=required, action="append", metavar="DATA",
                       help=help or "record CSV with optional JSON sidecar "
                                    "(docs/data_format.md); repeat for several records of the "
                                    "same system: one parameter set fitted to all, each record "
                                    "its own initial state")
        return
    p.add_argument("--data", required=required, action=Once, remedy=remedy,
                   help="record CSV with optional JSON sidecar (docs/data_format.md)")


def add_fixed(p: argparse.ArgumentParser) -> None:
    """``--fixed name=value,...``."""
    p.add_argument("--fixed", default=None,
                   help="name=value,... parameters held at given values")


def add_initial_state(p: argparse.ArgumentParser) -> None:
    """``--x0``, ``--p0-rel`` and ``--p0``: the UKF prior of the initial state
    (:func:`prior_spec`)."""
    p.add_argument("--x0", default=None,
                   help="name=value,... initial states (default: the record's state columns or "
                        "sidecar x0 for states the model has, else the model's X0)")
    p.add_argument("--p0-rel", type=float, default=P0_REL,
                   help="prior std of each initial state the record gives, relative to its "
                        f"scale (--p0; default {P0_REL:g})")
    p.add_argument("--p0", choices=P0_SCALES, default="state",
                   help="scale of each initial state's prior std: the state's own scale along "
                        "the record (state, default: free-run RMS, process-noise walk, sensors; "
                        "a sidecar's x0_std imposed; a state the record does not give gets its "
                        "whole scale) or max(abs(x0), 1) (magnitude, the old rule)")


def add_estimation_scope(p: argparse.ArgumentParser) -> None:
    """What an estimation moves besides ``--params``, the same in estimate,
    loop and sensitivity: ``--fixed``, ``--x0``, ``--p0-rel`` (the UKF
    prior), ``--estimate-x0`` (initial states estimated jointly with θ) and
    ``--noise`` (the measurement-noise policy,
    :func:`bondgraph.inference.estimand.noise_plan`)."""
    add_fixed(p)
    add_initial_state(p)
    p.add_argument("--estimate-x0", default=None, metavar="STATES",
                   help="initial states estimated jointly with the parameters (comma-separated "
                        "state names, all, or none); their prior shrinks to a token spread, so "
                        "the likelihood is conditional on them (estimate: where the model "
                        "declares no process noise, by default the states the record gives no "
                        "initial value of and the outputs see; none keeps them at the prior)")
    p.add_argument("--noise", choices=NOISE_MODES, default="auto",
                   help="measurement-noise levels: auto (default) holds an output's noise std "
                        "at the record's declaration (sidecar noise_std) and estimates the "
                        "undeclared ones (noise.<output>, and noise-intensity parameters not "
                        "in --params or --fixed); model: the graph's own sensor noise and "
                        "noise-intensity values")


def estimated_states(model, args) -> list[str]:
    """The initial states of ``--estimate-x0`` (``all``: every state;
    ``none``: none).

    Raises
    ------
    OptionError
        A state the model does not have (named), or no names.
    """
    from bondgraph.inference.estimand import x0_state_names

    text = getattr(args, "estimate_x0", None)
    if not text or text.strip().lower() == "none":
        return []
    return x0_state_names(model, parse_names(text, "--estimate-x0"))


def add_discretisation(p: argparse.ArgumentParser, *, chosen: bool = True) -> None:
    """``--method``, ``--substeps``, ``--hold``: the UKF's transition. Their
    defaults are None ("not given"): a command that chooses its numerics
    (``chosen``, :func:`chosen_problem`) fills in what the user left out;
    the loop takes its case's own options, else
    :class:`~bondgraph.inference.options.UKFOptions`' defaults."""
    dflt = "chosen, see --hold" if chosen else \
        "a bundled case's own; with --model/--data chosen as by estimate"
    p.add_argument("--method", choices=UKF_METHODS, default=None,
                   help=f"UKF discretisation of the state equations (default: {dflt})")
    p.add_argument("--substeps", type=int, default=None,
                   help=f"integrator steps per sample (default: {dflt})")
    p.add_argument("--hold", type=hold_argument, default=None, metavar="HOLD",
                   help="input over a sample interval: u_k (zoh), (u_k + u_k+1)/2 (mean), or "
                        "the first-order hold u_k + s (u_k+1 - u_k) (linear; for inputs sampled "
                        "from a continuous signal); one per input, comma-joined in the "
                        "model's input order, holds each its own way (zoh,linear). Default: "
                        + (_CHOSEN_HELP if chosen else dflt))
    p.add_argument("--decimate", type=positive_int, default=1, metavar="K",
                   help="fit every K-th sample of each record, for a record sampled far faster "
                        "than its model needs (each filter pass steps every sample): inputs "
                        "held zero-order averaged over each interval, the others "
                        "point-sampled; estimates limited by the measurement noise come out "
                        "about sqrt(K) wider (default 1: every sample)")
    add_backend(p)


def positive_int(text: str) -> int:
    """An integer >= 1 (argparse's error names the option)."""
    try:
        k = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if k < 1:
        raise argparse.ArgumentTypeError(f"{k} is below 1")
    return k


def hold_argument(text: str) -> str:
    """``--hold``: one of :data:`~bondgraph.inference.options.UKF_HOLDS`, or
    one per input comma-joined (argparse's error names the option)."""
    try:
        split_hold(text)
    except OptionError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text.replace(" ", "")


def solver_hold_argument(text: str) -> str:
    """``simulate --hold``: ``linear`` or ``zoh``, or one of them per input
    comma-joined (the adaptive solvers have no ``mean`` hold)."""
    text = hold_argument(text)
    if "mean" in split_hold(text):
        raise argparse.ArgumentTypeError(f"{text!r}: the adaptive solvers hold an input "
                                         f"linear or zoh")
    return text


#: how a command that chooses its numerics fills in --method/--substeps/--hold
_CHOSEN_HELP = ("what is not given is chosen: the hold the record declares (sidecar "
                "columns.<input>.hold) or its inputs' shape supports (where the shape is "
                "ambiguous, the likelier of the two holds), and the cheapest of "
                "ros2/rk4 with 1, 2, 3, 4, 6, 8, 12, 16 substeps whose one-step error is "
                "within 0.1 measurement-noise std per sample (without process noise also: "
                "whose free run bounds every estimate's bias by 0.5 Cramér-Rao std); one line "
                "on stderr says what was chosen")


def add_backend(p: argparse.ArgumentParser) -> None:
    """``--backend``: the implementation of the UKF likelihood
    (:attr:`bondgraph.inference.options.UKFOptions.backend`)."""
    p.add_argument("--backend", choices=UKF_BACKENDS, default=DEFAULT_BACKEND,
                   help="UKF likelihood: the compiled numba kernel or the numpy reference "
                        f"(default {DEFAULT_BACKEND}: numba when it is installed)")


def add_scheduler(p: argparse.ArgumentParser) -> None:
    """``--scheduler``: an existing Dask cluster for the batched evaluations
    (:class:`bondgraph.inference.executor.Executor`)."""
    p.add_argument("--scheduler", default=None,
                   help="Dask scheduler address tcp://HOST:PORT (default: $BONDGRAPH_SCHEDULER, "
                        "else this machine; start one with `dask scheduler` and `dask worker`)")


def add_quiet(p: argparse.ArgumentParser) -> None:
    """``--quiet``."""
    p.add_argument("--quiet", action="store_true", help="no progress output")


def add_overwrite(p: argparse.ArgumentParser) -> None:
    """``--overwrite``: replace a non-empty output folder."""
    p.add_argument("--overwrite", action="store_true",
                   help="replace a non-empty output folder (as a whole; without it such a "
                        "folder is refused)")


def unused_folder(base) -> Path:
    """The default output folder of a command run without ``--out``: ``base``
    when it is absent or empty, else the first of ``base-2``, ``base-3``, ...
    that is (so running the main job again keeps the earlier report instead
    of refusing; an explicit ``--out`` is still refused when not empty).

    Parameters
    ----------
    base : path
        The default folder, e.g. ``bondgraph-report``.

    Returns
    -------
    Path
        A folder that does not exist or is empty.
    """
    return next(p for p in _numbered_names(Path(base)) if not p.exists() or is_empty_dir(p))


def _numbered_names(base: Path):
    """``base``, ``base-2``, ``base-3``, ... (endless)."""
    yield base
    k = 2
    while True:
        yield base.with_name(f"{base.name}-{k}")
        k += 1


def default_out(args, base, command: str) -> Path:
    """``--out`` when given, else the command's default folder ``base`` made
    :func:`unused_folder` (an earlier result there is kept, said in one line
    on stderr unless ``--quiet``). With ``--resume`` (``bondgraph
    estimate``) the default is the last of ``base``, ``base-2``, ... that
    holds a checkpoint (in its working folder or published), else ``base``:
    the run it resumes went there.

    Parameters
    ----------
    args : argparse.Namespace
        The command's arguments (``out``; ``resume`` and ``quiet`` if any).
    base : path
        The default folder, e.g. ``compare_door_test``.
    command : str
        The command's name for the line, e.g. ``"compare"``.

    Returns
    -------
    Path
    """
    if args.out:
        return Path(args.out)
    base = Path(base)
    if getattr(args, "resume", False):
        held = [p for p in _numbered(base)
                if (p.with_name(f".{p.name}.work") / "checkpoint.npz").exists()
                or (p / "checkpoint.npz").exists()]
        return held[-1] if held else base
    path = unused_folder(base)
    if path != base and not getattr(args, "quiet", False):
        print(f"bondgraph {command}: ./{base} holds an earlier result (kept); this one goes to "
              f"./{path} (--out DIR to choose)", file=sys.stderr)
    return path


def _numbered(base: Path) -> list[Path]:
    """:func:`_numbered_names` as long as the folder or its working folder
    exists (``base`` always)."""
    names = _numbered_names(base)
    out = [next(names)]
    for p in names:
        if not (p.exists() or p.with_name(f".{p.name}.work").exists()):
            return out
        out.append(p)


def output_folder(path, args, option: str = "--out", *,
                  overwrite: bool | None = None) -> OutputFolder:
    """The command's output folder (:class:`bondgraph.core.atomic.OutputFolder`),
    checked now, before any work; ``overwrite`` defaults to ``--overwrite``.

    Raises
    ------
    OutputError
        A non-empty folder without ``--overwrite``, a file, or not writable.
    """
    if overwrite is None:
        overwrite = getattr(args, "overwrite", False)
    return OutputFolder(path, overwrite=overwrite, option=option)


def load_record(path, model, say=None, columns: str | dict | None = None,
                dt: float | None = None) -> Experiment:
    """The record of ``--data`` (:meth:`Experiment.load`; ``columns``: the
    ``--columns`` text or its ``{file: model}`` renames; ``dt``: ``--dt``,
    the sample interval of a file without a time column), with a
    :class:`~bondgraph.errors.ColumnWarning` for columns that match none of
    the model's names while some of its outputs are absent, and one line on
    ``say`` (default stderr) per output with missing samples
    (:func:`missing_note`). ``model`` is a
    :class:`~bondgraph.numerics.model.Model` or a
    :class:`~bondgraph.core.graph.BondGraph` (its sensors are the outputs;
    derived for its state names only when an output is absent).

    Raises
    ------
    DataError
        A defect of the file or its sidecar (file, line and column named).
    """
    renames = columns if isinstance(columns, dict) else parse_renames(columns)
    exp = Experiment.load(path, columns=renames or None, dt=dt)
    outputs = model.sensors if isinstance(model, BondGraph) else model.outputs
    require_information(exp, outputs)
    for line in missing_note(exp, outputs, Path(path).name):
        (say or _stderr)(line)
    if isinstance(model, BondGraph):
        if all(o in exp.columns for o in model.sensors):
            return exp
        model = SimpleNamespace(name=model.name, inputs=list(model.inputs),
                                outputs=list(model.sensors),
                                states=[str(x) for x in derive(model).states])
    exp.check_columns(model)
    return exp


def require_information(exp: Experiment, outputs) -> None:
    """Refuse a record whose column for one of ``outputs`` holds no
    finite sample, or one value throughout with no noise level declared
    (sidecar ``noise_std``): nothing to fit or judge, and its noise level
    cannot be seen (the loop failed later with "no output has a positive
    measurement-noise level ... (got [inf])"). A constant column with a
    declared level stays: the record then says the output stayed within
    its noise.

    Raises
    ------
    DataError
        Naming the file, the column, and what it holds.
    """
    for o in outputs:
        col = exp.columns.get(o)
        if col is None:
            continue
        vals = np.asarray(col, float)
        ok = vals[np.isfinite(vals)]
        if ok.size == 0:
            raise DataError(f"output '{o}' has no sample: every cell of its column is empty or "
                            f"NaN", path=exp._where(), line=1, column=o,
                            hint="fill the column with the measurement, or drop it from the "
                                 "record and the sensor from the graph")
        if ok.size > 1 and np.all(ok == ok[0]) and o not in exp.noise_std:
            unit = exp.units.get(o)
            raise DataError(f"output '{o}' reads {ok[0]:.6g}{' ' + unit if unit else ''} at every "
                            f"sample: a constant measurement holds nothing to fit or to judge a "
                            f"model by, and no noise level", path=exp._where(), line=1, column=o,
                            hint="check the column (a disconnected sensor, a wrong channel); "
                                 "drop it from the record and the sensor from the graph")


def missing_note(exp: Experiment, outputs, name: str) -> list[str]:
    """One line per output of ``outputs`` whose column in ``exp`` has
    missing samples (an empty cell or NaN, docs/data_format.md): how many,
    of how many, and the times of the first and last. The filter skips its
    measurement update at a missing sample (its likelihood leaves the
    sample out) and the free-run errors leave it out; a user who did not
    mean the gap reads it here instead of finding it in the numbers."""
    lines = []
    for o in outputs:
        col = exp.columns.get(o)
        if col is None:
            continue
        miss = np.flatnonzero(np.isnan(np.asarray(col, float)))
        if miss.size == 0:
            continue
        where = (f"at t = {exp.t[miss[0]]:.6g} s" if miss.size == 1 else
                 f"from t = {exp.t[miss[0]]:.6g} s to {exp.t[miss[-1]]:.6g} s")
        lines.append(f"{name}: {miss.size} of {len(exp)} samples of output '{o}' missing "
                     f"(empty or NaN; {where}): the filter skips its measurement update "
                     f"there and the errors leave {'it' if miss.size == 1 else 'them'} out")
    return lines


#: a record this long gets a line on ``--decimate`` where it is oversampled
#: (each filter pass steps every sample)
LONG_RECORD = 10_000


def filtered_record(exp: Experiment, model, args, say=None) -> Experiment:
    """The record a command filters: ``exp`` on every ``--decimate``-th
    sample (:func:`decimated_record`), then on a grid twice as fine where an
    input is band-limited (:func:`band_limited_record`)."""
    return band_limited_record(decimated_record(exp, model, args, say), model, args, say)


def decimated_window(args, say=None) -> None:
    """``--init-samples N`` with ``--decimate K``: N counts the record's own
    samples (a benchmark protocol's window, EMPS: the first 20 at 1 kHz),
    so it becomes the decimated record's samples that span the same time,
    ceil((N − 1)/K) + 1, set on ``args`` and said in one line on ``say``
    (default stderr)."""
    k, n = getattr(args, "decimate", 1) or 1, getattr(args, "init_samples", None)
    if k == 1 or not n or getattr(args, "window_decimated", False):
        return
    m = -(-(n - 1) // k) + 1
    (say or _stderr)(f"--init-samples {n} counts the record's own samples: {m} samples of the "
                     f"record decimated x{k} span the same time")
    args.init_samples, args.window_decimated = m, True      # once, however often called


def decimated_record(exp: Experiment, model, args, say=None) -> Experiment:
    """``exp`` on every K-th sample, K = ``args.decimate``
    (:meth:`~bondgraph.data.records.Experiment.decimated`): the inputs held
    zero-order (``--hold``, else the record's declaration or the input's
    shape, :func:`~bondgraph.inference.discretise.record_input_holds`)
    averaged over each interval, the others point-sampled; one line on
    ``say`` (default stderr) says so. K = 1: ``exp``, with a line on
    ``--decimate`` when it has :data:`LONG_RECORD` samples or more and its
    inputs and outputs are oversampled (:func:`_oversampled_note`).

    Raises
    ------
    DataError
        Fewer than 2 samples kept.
    """
    k = getattr(args, "decimate", 1) or 1
    tell = say or _stderr
    if k == 1:
        if len(exp) >= LONG_RECORD and not getattr(args, "quiet", False):
            _oversampled_note(exp, model, tell)
        return exp
    names = [n for n in model.inputs if n in exp.columns]
    if getattr(args, "hold", None) is not None:
        given = dict(zip(model.inputs, split_hold(args.hold, len(model.inputs))))
        held = {n: given[n] for n in names}
    else:
        u = np.column_stack([np.asarray(exp.columns[n], float) for n in names]) if names \
            else np.zeros((len(exp), 0))
        held = ({h.name: h.hold for h in record_input_holds(exp, names, u)}
                if np.isfinite(u).all() else declared_holds(exp, names))
    means = [n for n in names if held.get(n) in (None, "zoh")]
    out = exp.decimated(k, means=means)
    points = [n for n in names if n not in means]
    said = ([f"{', '.join(means)} averaged over each interval (held zero-order)"] if means
            else []) + [f"{', '.join(points + ['the outputs'])} point-sampled"]
    tell(f"{exp.name}: decimated x{k} ({len(exp)} -> {len(out)} samples, {exp.dt:.3g} s -> "
         f"{out.dt:.3g} s): {'; '.join(said)}")
    for n in points:        # a point-sampled input with content the coarse grid cannot hold
        fits, share = oversampling(exp.t, [exp.columns[n]], factors=(k,))
        if fits < k and np.isfinite(share):
            tell(f"warning: {exp.name}: input '{n}' holds {share:.2g} of its power above the "
                 f"decimated record's Nyquist frequency; point-sampled, that content aliases "
                 f"into the fit (--hold zoh averages it over each interval; or a smaller K)")
    return out


def _oversampled_note(exp: Experiment, model, tell) -> None:
    """One line on ``--decimate`` when ``exp``'s inputs and outputs hold
    next to nothing above 1/K of the Nyquist frequency
    (:func:`~bondgraph.inference.discretise.oversampling`)."""
    outputs = model.sensors if isinstance(model, BondGraph) else model.outputs
    names = [n for n in [*model.inputs, *outputs] if n in exp.columns]
    k, share = oversampling(exp.t, [exp.columns[n] for n in names])
    if k > 1:
        tell(f"{exp.name}: {len(exp)} samples at {exp.dt:.3g} s, and its "
             f"{', '.join(names)} hold {share:.1g} of their power above 1/{k} of the Nyquist "
             f"frequency: each filter pass steps every sample; --decimate {k} fits every "
             f"{ordinal(k)} sample, each pass in about 1/{k} of the time (inputs averaged over each "
             f"interval; estimates limited by the measurement noise about sqrt({k}) wider)")


def band_limited_record(exp: Experiment, model, args, say=None) -> Experiment:
    """The record a command filters: ``exp``, or, when ``--hold`` is not
    given and an input is band-limited with content where the linear hold
    misses its values between samples, the record on a grid twice as fine
    (:func:`~bondgraph.inference.discretise.finer_grid_record`). One line
    on ``say`` (default stderr) says so.

    Parameters
    ----------
    exp : Experiment
    model : Model or BondGraph
        Its inputs name the record's input columns.
    args : argparse.Namespace
        ``hold``: a given hold keeps the sampled grid.
    """
    if getattr(args, "hold", None) is not None:
        return exp
    fine, why = finer_grid_record(exp, list(model.inputs))
    if why:
        (say or _stderr)(f"{exp.name}: filtered on a grid twice as fine ({why}): "
                         f"{', '.join(fine.meta['finer_grid']['interpolated'])} interpolated "
                         f"band-limited between the samples, the outputs missing there (--hold "
                         f"to keep the sampled grid)")
    return fine


def published(folder: OutputFolder, staged: Iterable) -> list[Path]:
    """The paths that files written into a staging folder have once the
    folder is published (for ``wrote ...`` lines)."""
    return [folder.path / Path(p).name for p in staged]


def load_model(spec: str):
    """The :class:`~bondgraph.numerics.model.Model` named by ``--model``
    (:meth:`~bondgraph.numerics.model.Model.from_spec`); each law it evaluates
    continued past its domain said in one line (``Model.domain_notes``)."""
    from bondgraph.numerics.model import Model

    model = Model.from_spec(spec)
    for note in model.domain_notes:
        _stderr(f"note: {note}")
    return model


def prior_spec(args) -> PriorSpec:
    """The prior's specification of ``--x0``, ``--p0-rel`` and ``--p0``
    (:class:`bondgraph.inference.prior.PriorSpec`).

    Raises
    ------
    OptionError
        Malformed ``--x0``, a relative spread that is not > 0 (named as the
        options the user typed).
    """
    try:
        return PriorSpec(rel=args.p0_rel, scale=getattr(args, "p0", None) or "state",
                         x0_set=parse_pairs(args.x0, "--x0"))
    except OptionError as exc:
        raise OptionError(str(exc).replace("PriorSpec.rel (--p0-rel)", "--p0-rel")
                          .replace("PriorSpec.scale (--p0)", "--p0")) from exc


def discretisation_given(args) -> dict:
    """The discretisation options the user typed: ``{"method": ..., "substeps":
    ..., "hold": ...}`` for those of ``--method``, ``--substeps``, ``--hold``
    that are not None (their parser default)."""
    return {k: getattr(args, k) for k in ("method", "substeps", "hold")
            if getattr(args, k, None) is not None}


def ukf_from_args(args) -> UKFOptions:
    """The filter options of ``--method``, ``--substeps``, ``--hold``,
    ``--backend`` (and ``--alpha``/``--beta``/``--kappa`` where the command
    has them), validated once, named as typed; an option not given takes
    :class:`~bondgraph.inference.options.UKFOptions`' default.

    Raises
    ------
    OptionError
        A value out of its domain (``--substeps 0``).
    """
    kw = {k: getattr(args, k) for k in ("alpha", "beta", "kappa") if hasattr(args, k)}
    kw.update(discretisation_given(args))
    try:
        return UKFOptions(backend=args.backend, **kw)
    except OptionError as exc:
        text = str(exc)
        for key in ("method", "substeps", "hold", "backend", "alpha", "beta", "kappa"):
            text = text.replace(f"UKFOptions.{key}", f"--{key}")
        raise OptionError(text) from exc


def problem_from_args(model, experiment, args, values=None) -> Problem:
    """The model bound to the record with the shared options: ``--x0``,
    ``--p0-rel``, ``--p0`` (:func:`prior_spec`), ``--noise``, ``--fixed``
    (over ``values``, e.g. a record's true parameters) and the filter's
    options (:func:`ukf_from_args`); :func:`bondgraph.inference.problem.make_problem`.

    Raises
    ------
    OptionError, ModelError
        Malformed options, states or parameters the model does not have.
    DataError
        A record that does not fit the model.
    """
    prior = prior_spec(args)
    prior.check(model)
    fixed = {**(values or {}), **parse_pairs(args.fixed, "--fixed")}
    return make_problem(model, experiment, prior=prior, noise=NoiseSpec(args.noise),
                        ukf=ukf_from_args(args), fixed=fixed)


def chosen_problem(problem: Problem, args, theta=None, *, where: str = "at the start θ",
                   sigma=None, say=None, hold: str | None = None, why: str | None = None,
                   likelihood: bool = False) -> tuple[Problem, DiscretisationChoice | None]:
    """``problem`` with the discretisation that its check accepts at
    ``theta`` (:func:`bondgraph.inference.discretise.choose_discretisation`):
    the options of ``--method``, ``--substeps``, ``--hold`` that the user
    gave are kept, the others chosen; nothing is chosen when all three are
    given. One line on ``say`` (default stderr) says what was chosen and why.

    Parameters
    ----------
    problem : Problem
    args : argparse.Namespace
    theta : array (n_theta,), optional
        Default ``problem.theta`` (the start of the fit).
    where : str
        For the line ("at the start θ", "at the estimate").
    sigma : array (n_y,), optional
        Measurement-noise standard deviations (default: the problem's).
    say : callable, optional
    hold, why : str, optional
        A hold chosen by other evidence and why (the likelihood of fits
        under both, :func:`bondgraph.inference.discretise.alternative_hold`),
        used unless ``--hold`` was given.
    likelihood : bool
        Where an input's shape is ambiguous and no ``--hold`` was given, the
        hold whose filter is likelier at ``theta``
        (:func:`bondgraph.inference.discretise.likelier_hold_at`; a second
        line says which): for a command that works at given parameters.

    Returns
    -------
    (Problem, DiscretisationChoice or None)

    Raises
    ------
    OptionError
        A bad value of a given option, named as typed.
    """
    given = discretisation_given(args)
    if len(given) == 3:
        return problem, None
    th = problem.theta if theta is None else theta
    choice = choose_discretisation(problem, th, given=given, sigma=sigma, hold=hold, why=why)
    if likelihood and hold is None:
        choice, line = likelier_hold_at(problem, th, choice, sigma=sigma, where=where)
        if line:
            (say or _stderr)(line)
    (say or _stderr)(choice.line(where))
    if choice.disc != problem.disc:
        problem = problem.conditioned_on(disc=choice.disc)
    return problem, choice


#: a noise level profiled at the start this many times above the one the
#: start's discretisation check used is checked against again
#: (:func:`chosen_at_levels`)
PROFILED_ABOVE = 3.0


def chosen_at_levels(args, problem, params, states, say, *, hold: str | None = None,
                     why: str | None = None, where: str = "at the start θ",
                     likelihood: bool = False, profile: bool = True):
    """``(problem, choice)``: the discretisation chosen at the problem's θ
    (:func:`chosen_problem`), and chosen again against the noise levels
    profiled there (:func:`~bondgraph.inference.estimate.start_levels_profiled`)
    where the work on ``params`` (and the initial states ``states``)
    estimates a level that the first check took :data:`PROFILED_ABOVE` or
    more times lower. A level nothing declares is checked against the
    record's second differences, a quantised sensor's resolution: the EMPS
    encoder's 1.5e-8 m asked for RK4 with 16 substeps where the model's
    one-step misfit at the start is 4e-3 m and one substep meets the check.
    One line on ``say`` says which was chosen (``where`` begins it;
    ``hold``, ``why``, ``likelihood``: :func:`chosen_problem`'s); with
    ``profile`` False, the first choice.

    Raises
    ------
    OptionError
        As :func:`chosen_problem`.
    """
    from bondgraph.errors import EstimationError, NumericalError
    from bondgraph.inference.estimate import start_levels_profiled

    lines: list[str] = []
    pb, choice = chosen_problem(problem, args, say=lines.append, hold=hold, why=why, where=where,
                                likelihood=likelihood)
    if choice is None or not profile:
        for ln in lines:
            say(ln)
        return pb, choice
    try:
        levels = start_levels_profiled(pb, params, x0_states=states)
    except (EstimationError, NumericalError, FloatingPointError, np.linalg.LinAlgError):
        levels = np.full(problem.model.n_y, np.nan)
    used = np.asarray(choice.sigma, float).reshape(-1)
    above = np.isfinite(levels) & (~np.isfinite(used) | (levels > PROFILED_ABOVE * used))
    if not above.any():
        for ln in lines:
            say(ln)
        return pb, choice
    sigma = np.where(above, levels, used)
    outs = problem.model.outputs
    where = (f"{where}, against the noise levels profiled there ("
             + ", ".join(f"{outs[j]} {levels[j]:.3g}, not {used[j]:.3g}"
                         for j in np.flatnonzero(above)) + ")")
    return chosen_problem(problem, args, sigma=sigma, where=where, say=say, hold=hold, why=why,
                          likelihood=likelihood)


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)
