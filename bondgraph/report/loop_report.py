"""Writing the loop's report: ``report.json``, ``report.md``, PNG plots, the
augmented declared model (``augmented_model.py``) and its generated code.

``report.json`` holds ``steps`` (one entry per accepted effect: ``effect``,
``attached_to``, ``metric``, ``error_before``, ``error_after``,
``nll_before``, ``nll_after``, ``parameters`` with estimates and standard
deviations, plus the criterion and whiteness before/after) and ``rejected``
candidates with their scores, the evidence ranking of every step, the
initial and final fits, and the residual analyses.
"""

from __future__ import annotations

import copy
import hashlib
import inspect
import json
import pickle
import shutil
import threading
from pathlib import Path

import numpy as np

from bondgraph.core.atomic import OutputFolder
from bondgraph.core.codegen import generate_source
from bondgraph.core.plugins import resolve
from bondgraph.core.equations import derive
from bondgraph.diagnose.accept import UNDETERMINED_REL
from bondgraph.diagnose.result import (
    LoopResult,
    moved_declared,
    moved_text,
    robust_of,
    understated,
)
from bondgraph.inference.robust import ROBUST_RATIO
from bondgraph.report.drawing import draw, layout
from bondgraph.report.evidence import SHOWN, plot_evidence
from bondgraph.report.html import graph_changes, page
from bondgraph.report.plots import pyplot


class LoopReporter:
    """Writes the loop's log and report into one folder while the loop runs.

    Pass :meth:`log` and :meth:`update` to
    :func:`bondgraph.diagnose.loop.run_loop` (``log=``, ``on_update=``).
    The report is published from the partial
    :class:`~bondgraph.diagnose.result.LoopResult` after the initial fit,
    after every step and at the end, each time as a complete folder swapped
    into place (:class:`bondgraph.core.atomic.OutputFolder`): the folder
    always holds one whole version of the report, an intermediate one
    (``report.json``: ``"finished": false``) while the loop runs and after an
    interruption, the final one (``"finished": true``) at the end, never a
    mix of two versions or two runs. Log lines go to ``loop.log`` in the
    working folder ``.<out>.work`` beside it (and to ``echo``); each version
    of the report carries a copy of the log up to that point.

    An intermediate version is written on a thread of its own from a copy
    of the result (its generated code derived first, on the caller's
    thread: sympy stays on one thread), while the loop goes on: its plots
    took 1.6 s and 2.1 s of the bundled default loop's 32 s on the loop's
    thread. The next :meth:`update` (and :meth:`wait`) waits for it and
    raises what it raised; the thread is not a daemon, so a run that stops
    on an error or Ctrl-C still finishes the version it was writing.

    Parameters
    ----------
    out_dir : path
        The report folder.
    echo : callable, optional
        Also print each log line with it (e.g. ``print``).
    overwrite : bool
        Replace a non-empty ``out_dir`` (otherwise refused).
    plots : bool
        Draw the PNG plots (default); False writes the report's text, tables
        and generated code only (``bondgraph loop --no-plots``).
    background : bool
        Write the intermediate versions on a thread of their own (default);
        False writes every version before :meth:`update` returns.

    Raises
    ------
    OutputError
        ``out_dir`` is not empty (without ``overwrite``) or not writable;
        raised here, before the loop runs.
    """

    def __init__(self, out_dir, echo=None, *, overwrite: bool = False, plots: bool = True,
                 background: bool = True):
        self.folder = OutputFolder(out_dir, overwrite=overwrite)
        self.plots = plots
        self.background = background
        self._writer: threading.Thread | None = None
        self._failed: BaseException | None = None
        self.out = Path(out_dir)
        self.echo = echo
        self.log_path = self.folder.work_dir() / "loop.log"
        self.log_path.write_text("")
        #: files of earlier versions by the hash of what they show (:func:`write`)
        self.cache: dict = {}

    def log(self, line: str) -> None:
        """Append one line to ``loop.log`` (and echo it)."""
        if self.echo is not None:
            self.echo(line)
        with open(self.log_path, "a") as fh:
            fh.write(line + "\n")

    def update(self, result: LoopResult) -> None:
        """Publish the report of the loop's (partial) result: an intermediate
        one on a thread of its own (see the class), the final one
        (``result.finished``) before returning; after the final one, later
        log lines are appended to the published ``loop.log``.

        Raises
        ------
        OutputError
            This version could not be published, or (for an intermediate
            one) the intermediate one written before it (a final version
            that is published supersedes it).
        """
        failed = self._join()
        if result.finished or not self.background:
            self._publish(result)
            return
        if failed is not None:
            raise failed
        if result.applied:      # derived here: sympy is not used from two threads
            _generated_text(result, self.out, self.cache)
        # the loop goes on changing ``result``; its graphs are never changed,
        # and kept (not copied), their pickles key the cached code and plots
        graphs = (result.declared_graph, result.final_graph)
        snapshot = copy.deepcopy(result, {id(g): g for g in graphs if g is not None})
        self._writer = threading.Thread(target=self._publish_caught, args=(snapshot,),
                                        name="loop-report")
        self._writer.start()

    def wait(self, *, raise_failure: bool = True) -> None:
        """Wait for an intermediate version being written (:meth:`update`);
        raise what its writing raised (unless not ``raise_failure``: a loop
        that stopped on an error of its own waits so, its report complete
        before that error is said)."""
        failed = self._join()
        if failed is not None and raise_failure:
            raise failed

    def _join(self) -> BaseException | None:
        """Wait for the writer thread; what it raised (then forgotten)."""
        if self._writer is not None:
            self._writer.join()
            self._writer = None
        failed, self._failed = self._failed, None
        return failed

    def _publish_caught(self, result: LoopResult) -> None:
        """:meth:`_publish` on the writer thread, its exception kept for
        :meth:`wait`."""
        try:
            self._publish(result)
        except BaseException as exc:      # noqa: BLE001 -- re-raised by wait()
            self._failed = exc

    def _publish(self, result: LoopResult) -> None:
        """Write and swap in one version of the report of ``result``."""
        def version(folder: Path) -> None:
            shutil.copyfile(self.log_path, folder / "loop.log")
            write(result, folder, final=self.out, cache=self.cache, plots=self.plots)
        self.folder.publish(version)
        if result.finished:
            self.log_path = self.out / "loop.log"
            self.folder.remove_work_dir()


def write(result: LoopResult, out, *, final=None, cache: dict | None = None,
          plots: bool = True) -> None:
    """Write ``report.md``, the PNGs (unless not ``plots``), (once an effect is accepted) the
    augmented model with its generated code, and ``report.json`` last, into
    ``out``; ``final`` is where the folder will be published (named in the
    generated code; default ``out``). ``cache`` (a dict kept between the
    versions of one report, :class:`LoopReporter`) gives back a plot or the
    generated code whose inputs have not changed since an earlier version,
    instead of drawing or deriving it again."""
    out = Path(out)
    cache = {} if cache is None else cache
    report = result.to_dict()
    settings = report.pop("settings")   # keep "settings" last, after the file name
    report["augmented_model"] = "augmented_model.py" if result.applied else None
    report["settings"] = settings
    if result.applied:
        (out / "augmented_model.py").write_text(augmented_source(result))
        if not (result.source and ":" in result.source) and result.declared_graph is not None:
            (out / DECLARED_PICKLE).write_bytes(pickle.dumps(result.declared_graph))
        if not_reapplied(result) and result.final_graph is not None:
            (out / AUGMENTED_PICKLE).write_bytes(pickle.dumps(result.final_graph))
        _write_generated(result, out, Path(final) if final is not None else out, cache)
    pngs = _plots(result, out, cache) + _graph_plots(result, out, cache) if plots else []
    (out / "report.md").write_text(markdown(result, pngs))
    (out / "report.html").write_text(page(result, out, pngs))
    (out / "report.json").write_text(json.dumps(report, indent=2, allow_nan=False))


#: pickle of the declared graph next to augmented_model.py, for a graph
#: passed in memory (no module:function source)
DECLARED_PICKLE = "declared_graph.pkl"


def declared_import(source: str | None) -> list[str]:
    """Lines of ``augmented_model.py`` that define ``_declared``: the
    builder named by ``source`` (``module:function``, or ``file.py:function``
    made absolute) through :func:`bondgraph.core.plugins.resolve`, else the
    pickled declared graph (:data:`DECLARED_PICKLE`) beside the file."""
    if source and ":" in source:
        mod, fn = source.rsplit(":", 1)
        if mod.endswith(".py") or "/" in mod:
            mod = str(Path(mod).resolve())
        return [f"_declared = resolve({f'{mod}:{fn}'!r})"]
    return ["# the declared graph was passed in memory: rebuilt from its pickle",
            "def _declared():",
            f"    with open(Path(__file__).with_name({DECLARED_PICKLE!r}), 'rb') as fh:",
            "        return pickle.load(fh)"]


#: pickle of the final augmented graph beside augmented_model.py, when an
#: accepted effect cannot be re-applied from its class alone
AUGMENTED_PICKLE = "augmented_graph.pkl"


def not_reapplied(result: LoopResult) -> list[str]:
    """The accepted effects ``augmented_model.py`` cannot re-apply by name
    or by a class constructed without arguments (a law the loop discovered,
    :class:`bondgraph.diagnose.discover.effect.DiscoveredEffect`, is data,
    not a class): their labels. The file then rebuilds the augmented graph
    from its pickle (:data:`AUGMENTED_PICKLE`)."""
    out = []
    for a in result.applied:
        if a.spec is None:
            continue
        try:
            inspect.signature(resolve(a.spec)).bind()
        except Exception:           # not importable, or it needs arguments
            out.append(f"{a.effect} @ {a.target.name}")
    return out


def _pickled_build(result: LoopResult, which: list[str]) -> list[str]:
    """``build()`` of ``augmented_model.py`` from the pickled final graph."""
    return ["", "", "def build():",
            f'    """{result.model} + ' + " + ".join(
                f"{a.effect} @ {a.target.name}" for a in result.applied) + ".",
            "",
            f"    Rebuilt from its pickle ({AUGMENTED_PICKLE}): {', '.join(which)} cannot be",
            '    re-applied from a class alone (a discovered law is data)."""',
            f"    with open(Path(__file__).with_name({AUGMENTED_PICKLE!r}), 'rb') as fh:",
            "        g = pickle.load(fh)",
            f"    g.name = {_augmented_name(result)!r}"]


def augmented_source(result: LoopResult) -> str:
    """Source of ``augmented_model.py``: a declared model whose ``build()``
    rebuilds the user's graph (:func:`declared_import`) and applies the
    accepted effects in order with their values (a user-supplied effect by
    its recorded ``module:Class``), then the final estimates
    (``ESTIMATES``) and the values the loop held the other parameters at
    (``HELD``, :func:`held_values`) as defaults, every parameter not in
    ``ESTIMATES`` marked as declared without a box (a known value: ``bondgraph
    estimate`` and ``sensitivity`` without ``--params`` then estimate what the
    loop estimated, not an effect's shape width or a term it held at 0,
    :func:`bondgraph.cli.common.default_params`); when an effect cannot be re-applied from
    its class (:func:`not_reapplied`), ``build()`` loads the final graph
    from its pickle instead."""
    lines = [f'"""Augmented declared model written by `bondgraph loop`.',
             "",
             f"It rebuilds the declared model '{result.model}' unchanged and adds the",
             "effects the loop accepted, in order, with their estimated values. The declared",
             'model\'s own source is not modified."""',
             "",
             "import pickle",
             "from pathlib import Path",
             "",
             "from bondgraph.core.plugins import resolve",
             "from bondgraph.diagnose.effects import Target, apply_effect",
             "", ""]
    which = not_reapplied(result)
    if which:
        lines += _pickled_build(result, which)
    else:
        lines += declared_import(result.source)
        lines += ["", "", "def build():",
                  f'    """{result.model} + ' +
                  " + ".join(f"{a.effect} @ {a.target.name}" for a in result.applied) + '."""',
                  "    g = _declared()",
                  f"    g.name = {_augmented_name(result)!r}"]
    for a in result.applied if not which else []:
        vals = {k: float(v) for k, v in a.values.items()}
        eff = repr(a.effect) if a.spec is None else f"resolve({a.spec!r})()"
        lines.append(f"    apply_effect(g, {eff}, Target({a.target.kind!r}, "
                     f"{a.target.name!r}), {vals!r})")
    held = held_values(result)
    lines += ["    for name, value in {**HELD, **ESTIMATES}.items():",
              "        g.params[name].default = value",
              "    for name, box in BOUNDS.items():",
              "        g.params[name].bounds = box",
              "    for name, p in g.params.items():",
              "        # what the loop did not estimate is a known value here: bondgraph",
              "        # estimate and sensitivity estimate ESTIMATES' parameters by default",
              "        p.box_declared = p.box_declared and name in ESTIMATES",
              "    return g", "",
              "",
              "#: parameter estimates of the final fit (applied as defaults by build())",
              "ESTIMATES = {"]
    lines += [f"    {k!r}: {float(v)!r}," for k, v in result.final.estimates.items()]
    lines += ["}", "",
              "#: the values the loop held the declared graph's other parameters at (--fixed,",
              "#: a known value held, --from a fit, or the declared default); applied as",
              "#: defaults by build(), so that the model is the one the loop fitted",
              "HELD = {"]
    lines += [f"    {k!r}: {v!r}," for k, v in held.items()]
    lines += ["}", "",
              "#: the boxes the loop fitted the effects' parameters in (from the record's",
              "#: scales; the effect library's own are nominal, such as [0, 1e15]); applied",
              "#: by build()",
              "BOUNDS = {"]
    lines += [f"    {k!r}: {v!r}," for k, v in effect_boxes(result).items()]
    lines += ["}", ""]
    return "\n".join(lines)


def effect_boxes(result: LoopResult) -> dict[str, tuple[float, float]]:
    """The boxes of the accepted effects' parameters in the loop's final
    graph (``result.final_graph``: the parameters the declared graph
    ``result.declared_graph`` does not have), as ``(lower, upper)`` floats;
    empty when the result lacks either graph."""
    final = getattr(result, "final_graph", None)
    declared = getattr(result, "declared_graph", None)
    if final is None or declared is None:
        return {}
    return {n: (float(p.bounds[0]), float(p.bounds[1])) for n, p in final.params.items()
            if n not in declared.params}


def held_values(result: LoopResult) -> dict[str, float]:
    """The values of the declared graph's parameters the loop did not
    estimate, as it held them: ``settings["fixed"]`` (``--fixed``, a known
    value held where the record cannot tell it,
    :func:`bondgraph.diagnose.runner.held_unidentified`), else the default
    of the declared graph the loop ran on (``--from`` sets those). The
    augmented model's ``build()`` rebuilds the declared graph from its
    source, whose defaults need not be these: a drive run with ``--fixed
    m=2.5`` gave an ``augmented_model.py`` with the source's mass."""
    fixed = dict((getattr(result, "settings", None) or {}).get("fixed") or {})
    graph = getattr(result, "declared_graph", None)
    est = set(result.final.estimates)
    if graph is None:
        return {n: float(v) for n, v in fixed.items() if n not in est}
    return {n: float(fixed.get(n, p.default)) for n, p in graph.params.items() if n not in est}


def _augmented_name(result: LoopResult) -> str:
    return f"{result.model}_augmented"


def _write_generated(result: LoopResult, out: Path, final: Path, cache: dict) -> None:
    """Generated code of the final augmented graph (estimates as defaults)
    in ``out/generated``; its source is named as ``final/augmented_model.py``
    (the text from ``cache`` when the final graph, its estimates and
    ``final`` are those of an earlier version)."""
    gen = out / "generated"
    gen.mkdir(exist_ok=True)
    (gen / f"{_augmented_name(result)}.py").write_text(_generated_text(result, final, cache))


def _generated_text(result: LoopResult, final: Path, cache: dict) -> str:
    """The generated code of :func:`_write_generated` (derived, or from
    ``cache``, where it is kept)."""
    name = _augmented_name(result)
    key = ("generated", _digest(pickle.dumps(result.final_graph), name, str(final),
                                sorted(result.final.estimates.items())))
    if key not in cache:
        g = result.final_graph.copy(name)
        for k, v in result.final.estimates.items():
            if k in g.params:
                g.params[k].default = float(v)
        cache[key] = generate_source(derive(g), source=f"{final / 'augmented_model.py'}:build",
                                     command="bondgraph loop (see report.md)")
    return cache[key]


def _digest(*parts) -> str:
    """Hash of ``parts``: arrays by dtype, shape and bytes, other objects by
    ``repr`` (floats in full precision)."""
    h = hashlib.sha256()
    for p in parts:
        if isinstance(p, np.ndarray):
            h.update(f"{p.dtype}{p.shape}".encode())
            h.update(np.ascontiguousarray(p).tobytes())
        elif isinstance(p, bytes):
            h.update(p)
        else:
            h.update(repr(p).encode())
        h.update(b"\0")
    return h.hexdigest()


def _cached_png(cache: dict, key: str, path: Path, draw) -> str:
    """``path``'s name: the PNG of ``cache[key]`` written there, else
    ``draw()`` (which saves it) and its bytes kept under ``key``."""
    if key in cache:
        path.write_bytes(cache[key])
        return path.name
    name = draw()
    cache[key] = path.read_bytes()
    return name


def _plots(result: LoopResult, out: Path, cache: dict | None = None) -> list[str]:
    """Draw the PNGs (a plot whose inputs are unchanged since an earlier
    version of the report from ``cache``); returns their file names."""
    cache = {} if cache is None else cache
    init, final, aug = result.initial, result.final, _augmented(result)
    shown = [result.time, result.measured, result.outputs, result.output_units, aug]
    fits = [init.sim_y is None, init.sim_y] + ([final.sim_y is None, final.sim_y] if aug else [])
    if result.validation_time is not None:
        shown += [result.validation_time, result.validation_measured]
        fits += [init.validation_sim_y is None, init.validation_sim_y,
                 init.validation_metric, init.metric]
        if aug:
            fits += [final.validation_sim_y is None, final.validation_sim_y,
                     final.validation_metric, final.metric]
    for name, (t, y) in getattr(result, "more_measured", {}).items():
        shown += [name, t, y]
        for fit in (init, final) if aug else (init,):
            sim = getattr(fit, "more_sim_y", {}).get(name)
            fits += [sim is None, sim, getattr(fit, "more_metrics", {}).get(name)]
    inns = [init.innovations, init.innovation_var] + (
        [final.innovations, final.innovation_var] if aug else [])
    pngs = [_cached_png(cache, _digest("fit", *shown, *fits), out / "fit_before_after.png",
                        lambda: _plot_fit(result, out)),
            _cached_png(cache, _digest("innovations", *shown, *inns),
                        out / "residuals_before_after.png",
                        lambda: _plot_innovations(result, out))]
    for k, ranking in enumerate(result.rankings, 1):
        if ranking:
            acc = result.steps[k - 1] if k <= len(result.steps) else None
            key = _digest("evidence", k, [(c.label, c.score, c.failed, c.equivalent, c.tied,
                                           c.confirmed) for c in ranking[:SHOWN]],
                          None if acc is None else (acc.effect, acc.attached_to))
            pngs.append(_cached_png(cache, key, out / f"evidence_step{k}.png",
                                    lambda k=k, r=ranking: _plot_evidence(result, k, r, out)))
    if result.discovery is not None:
        dp = result.discovery
        pngs.append(_cached_png(cache, _digest("discovery", dp.t, dp.d, dp.d_std, dp.law, dp.text),
                                out / DISCOVERY_PNG, lambda: plot_discovery(dp, out / DISCOVERY_PNG)))
    return pngs


#: the plot of the reconstruction against the discovered law
DISCOVERY_PNG = "discovery.png"


def plot_discovery(dp, path: Path) -> str:
    """The reconstructed d̂(t) with its ±2σ band against the discovered law
    on the port's variables (a :class:`~bondgraph.diagnose.result.DiscoveryPlot`),
    over time and as d̂ versus the law; saved at ``path``, returns its name."""
    plt = pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 3.8), gridspec_kw={"width_ratios": [2.2, 1]})
    a1.fill_between(dp.t, dp.d - 2 * dp.d_std, dp.d + 2 * dp.d_std, color="C0", alpha=0.25,
                    label="±2σ")
    a1.plot(dp.t, dp.d, "C0", lw=1.0, label="reconstructed d̂")
    a1.plot(dp.t, dp.law, "C3", lw=1.0, ls="--", label="discovered law")
    a1.set_xlabel("time [s]")
    a1.set_ylabel(f"{dp.port} {dp.kind} [{dp.unit}]")
    a1.legend(loc="upper right", fontsize=8)
    a2.plot(dp.law, dp.d, ".", ms=2, color="C0")
    lo, hi = float(np.nanmin(dp.law)), float(np.nanmax(dp.law))
    a2.plot([lo, hi], [lo, hi], "k-", lw=0.8)
    a2.set_xlabel("law [%s]" % dp.unit)
    a2.set_ylabel("d̂ [%s]" % dp.unit)
    fig.suptitle(dp.text, fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def _md_discovery(result: LoopResult) -> list[str]:
    """The discovery section of ``report.md`` (empty when none ran)."""
    dp = result.discovery
    if dp is None:
        return []
    verdict = "accepted by the loop" if dp.accepted else "not accepted by the loop"
    return ["## Discovery (an effect beyond the library)", "",
            f"No library effect was accepted; the effort missing at `{dp.port}` was "
            f"reconstructed ({dp.kind}, ±2σ band) and its law discovered ({verdict}):", "",
            f"    {dp.text}", "", "Passivity and placement:", "",
            *[f"- {line}" for line in dp.passivity.splitlines()], "",
            f"![{DISCOVERY_PNG}]({DISCOVERY_PNG})", ""]


def _graph_plots(result: LoopResult, out: Path, cache: dict) -> list[str]:
    """``graph_before.png`` (the declared graph) and, once an effect is
    accepted, ``graph_after.png`` (the augmented graph, what the effects
    added in green), both in the augmented graph's layout; their names."""
    before = result.declared_graph
    after = result.final_graph if _augmented(result) else None
    if before is None:
        return []
    key = _digest("graphs", pickle.dumps(before), None if after is None else pickle.dumps(after))
    cached = cache.get(key)
    if cached is None:
        plt = pyplot()
        pos = layout(after if after is not None else before)
        drawn = [(before, "graph_before.png", (), "declared")]
        if after is not None:
            drawn.append((after, "graph_after.png", graph_changes(before, after),
                          "augmented (added in green)"))
        cached = {}
        for graph, name, marked, what in drawn:
            fig = draw(graph, out / name, highlight=marked, positions=pos,
                       title=f"{graph.name}: {what}; red bar = causal stroke")
            plt.close(fig)
            cached[name] = (out / name).read_bytes()
        cache[key] = cached
    for name, data in cached.items():
        (out / name).write_bytes(data)
    return list(cached)


def _augmented(result: LoopResult) -> bool:
    """Whether the final model differs from the declared one."""
    return bool(result.steps)


def _save(fig, path: Path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    pyplot().close(fig)
    return path.name


def _plot_fit(result: LoopResult, out: Path) -> str:
    """Measured outputs vs the free-run simulations before and after, on
    the estimation record and, where the loop had one, beside it on the
    validation (held-out) record and each further validation record, each
    panel titled with the two models' errors there; a simulation that failed is said on the plot (not
    silently left out)."""
    plt = pyplot()
    init, final = result.initial, result.final
    aug = _augmented(result)
    panels = [(result.time, result.measured, init.sim_y, final.sim_y, init.metric,
               final.metric, "estimation record (fitted)")]
    if result.validation_time is not None and result.validation_measured is not None:
        panels.append((result.validation_time, result.validation_measured,
                       init.validation_sim_y, final.validation_sim_y, init.validation_metric,
                       final.validation_metric,
                       f"validation record {(result.settings or {}).get('validation') or ''} "
                       f"(held out, not fitted)".replace("  ", " ")))
    for name, (t, y) in getattr(result, "more_measured", {}).items():
        panels.append((t, y, init.more_sim_y.get(name), final.more_sim_y.get(name),
                       init.more_metrics.get(name), final.more_metrics.get(name),
                       f"validation record {name} (not fitted)"))
    ny = result.measured.shape[1]
    widths = [max(float(p[0][-1] - p[0][0]), 1e-9) if len(p[0]) > 1 else 1.0 for p in panels]
    widths = [max(w, 0.3 * max(widths)) for w in widths]
    fig, axes = plt.subplots(ny, len(panels), figsize=(10 + 2 * (len(panels) - 1),
                                                       2.4 * ny + 0.8),
                             sharey="row", squeeze=False, gridspec_kw={"width_ratios": widths})
    failed_any = []
    for j, (t, y, before, after, e0, e1, what) in enumerate(panels):
        failed = [lab for sim, lab, shown in ((before, "declared model", True),
                                              (after, "augmented model", aug))
                  if shown and sim is None]
        failed_any += [f for f in failed if f not in failed_any]
        for i in range(ny):
            ax = axes[i, j]
            ax.plot(t, y[:, i], ".", ms=2, color="0.55", label="measured")
            if before is not None:
                ax.plot(t, before[:, i], lw=1.2, color="tab:red",
                        label="declared model (fitted)")
            if aug and after is not None:
                ax.plot(t, after[:, i], lw=1.2, color="tab:blue", label="augmented model")
            if failed:
                ax.text(0.5, 0.5, f"free-run simulation of the {' and the '.join(failed)} "
                        f"failed: not drawn", transform=ax.transAxes, ha="center",
                        va="center", fontsize=9, color="tab:red",
                        bbox=dict(fc="white", ec="tab:red", alpha=0.9))
            if j == 0:
                unit = result.output_units[i]
                ax.set_ylabel(f"{result.outputs[i]}\n[{unit or '-'}]", fontsize=8)
            ax.grid(alpha=0.3)
        errors = f"error {_num(e0)}" + (f" -> {_num(e1)}" if aug else "")
        axes[0, j].set_title(f"{what}\n{errors}", fontsize=9)
        axes[-1, j].set_xlabel("t [s]")
    axes[0, 0].legend(fontsize=8, loc="best")
    fig.suptitle("Measured vs free-run simulation, before and after the loop"
                 + (f" ({' and '.join(failed_any)}: simulation failed)" if failed_any else ""),
                 fontsize=10)
    return _save(fig, out / "fit_before_after.png")


def _num(v) -> str:
    """A figure for a panel title: 4 significant digits, "n/a" for None."""
    return "n/a" if v is None else f"{v:.4g}"


def _plot_innovations(result: LoopResult, out: Path) -> str:
    """Standardised one-step innovations ε/√S before and after."""
    plt = pyplot()
    t, ny = result.time, result.measured.shape[1]
    fits = [(result.initial, "tab:red", "declared")]
    if _augmented(result):
        fits.append((result.final, "tab:blue", "augmented"))
    fig, axes = plt.subplots(ny, 1, figsize=(10, 2.2 * ny + 0.6), sharex=True, squeeze=False)
    for i in range(ny):
        ax = axes[i, 0]
        for fit, col, lab in fits:
            e = fit.innovations[:, i]
            sd = np.sqrt(fit.innovation_var[:, i])
            ax.plot(t, e / sd, lw=0.6, color=col, alpha=0.8, label=lab)
        ax.set_ylabel(f"{result.outputs[i]}\nε/√S [-]", fontsize=8)
        ax.grid(alpha=0.3)
    if axes[0, 0].get_legend_handles_labels()[0]:
        axes[0, 0].legend(fontsize=8)
    axes[-1, 0].set_xlabel("t [s]")
    fig.suptitle("Standardised UKF innovations before and after", fontsize=10)
    return _save(fig, out / "residuals_before_after.png")


def _plot_evidence(result: LoopResult, k: int, ranking, out: Path) -> str:
    """The evidence plot of step ``k`` (:func:`bondgraph.report.evidence.plot_evidence`)."""
    return plot_evidence(result, k, ranking, out / f"evidence_step{k}.png")


def markdown(result: LoopResult, pngs: list[str]) -> str:
    """``report.md``: error before/after, accepted effects and final
    parameters, every step's evidence, the final residuals, the plots and
    the rejected candidates."""
    L = [f"# Residual-tracing report: {result.model}", ""]
    L.append(f"{result.records()} Metric: {result.metric}. "
             f"Criterion: {result.criterion.upper()}.")
    L.append("")
    if result.numerics():
        L += [result.numerics(), ""]
    L += _md_errors(result)
    L += _md_accepted(result)
    L.append("")
    L += _md_discovery(result)
    L.append("## Evidence (ranking of every step)")
    L.append("")
    for k, ranking in enumerate(result.rankings, 1):
        L += _md_ranking(k, ranking)
    L.append("")
    L += _md_residuals(result)
    L.append("")
    for p in pngs:
        if p != DISCOVERY_PNG:
            L.append(f"![{p}]({p})")
    L.append("")
    if result.rejected:
        L.append("## Rejected candidates")
        L.append("")
        for r in result.rejected:
            L.append(f"- step {r.step}: {r.candidate.label} — {r.reason}" + _md_refit(r.candidate))
    return "\n".join(L) + "\n"


def _md_errors(result: LoopResult) -> list[str]:
    """The error before/after (the validation record's first when there is
    one, the estimation record's beside it) and the warnings."""
    i, f = result.initial, result.final
    if i.validation_metric is not None:
        L = [f"**Error on the validation record before: {i.validation_metric:.4g}; after: "
             f"{f.validation_metric:.4g}** (on the estimation record: {i.metric:.4g} -> "
             f"{f.metric:.4g}).", ""]
        more = result.more_validation()
        if more:
            L[-1:] = ["On the further validation records: " + "; ".join(
                f"`{k}` {_num(b)} -> {a:.4g}" for k, b, a in more) + ".", ""]
    else:
        L = [f"**Error before: {i.metric:.4g}; after: {f.metric:.4g}.**", ""]
    for w in result.warnings:
        L.append(f"- warning: {w}")
    if result.warnings:
        L.append("")
    return L


def _md_refit(c) -> str:
    """The confirmed refit's numbers of a rejected candidate (or '')."""
    r = c.confirmed
    if not r:
        return ""
    v = f", validation error {r['validation_error']:.4g}" if r.get("validation_error") else ""
    v += "".join(f", on {k} {e:.4g}" for k, e in (r.get("more_validation_errors") or {}).items())
    return (f" (refit: LR {r['lr']:.1f}, criterion {r['criterion']:.2f}, error "
            f"{r['error']:.4g}{v})")


def _md_accepted(result: LoopResult) -> list[str]:
    L = ["## Accepted effects", ""]
    if not result.steps:
        L.append(f"None: {result.none_accepted()}"
                 + (" (their reasons under Rejected candidates)." if result.rejected else "."))
        return L
    L.append("| step | effect | attached to | error before | error after | NLL before | "
             "NLL after | whiteness before | after |")
    L.append("|---|---|---|---|---|---|---|---|---|")
    for i, s in enumerate(result.steps, 1):
        L.append(f"| {i} | {s.shown()} | {s.shown_target()} | {s.error_before:.4g} | "
                 f"{s.error_after:.4g} | {s.nll_before:.1f} | {s.nll_after:.1f} | "
                 f"{s.whiteness_before:.1f} | {s.whiteness_after:.1f} |")
    inflated = [(i, s) for i, s in enumerate(result.steps, 1)
                if (getattr(s, "lr_scale", None) or 0.0) > ROBUST_RATIO]
    if inflated:
        L += ["", "The innovations are serially correlated, so each step's likelihood ratio "
              "overstates its evidence; divided by its scale (the mean weight of its limiting "
              "distribution; Kent 1982, Satorra & Bentler 1994) and referred to χ²: "
              + "; ".join(f"step {i} LR {s.lr:.1f} / {s.lr_scale:.3g} = "
                          f"{s.lr / s.lr_scale:.1f} (p {s.lr_robust_p_value:.2g})"
                          for i, s in inflated)
              + ". The accept rule judges by the held-out error's own test."]
    for i, s in enumerate(result.steps, 1):
        if getattr(s, "tied", None):
            L += ["", f"Step {i}: the record cannot tell {s.effect} @ {s.attached_to} from "
                  f"{', '.join(s.tied)} (Vuong's test on the confirmed refits); the choice "
                  f"among them is not the data's — another record may decide."]
    L += ["", "Parameters of the final model:", "",
          "| parameter | estimate | Cramér-Rao std | robust std |", "|---|---|---|---|"]
    robust = robust_of(result.final)
    for n, v in result.final.estimates.items():
        sd, rb = result.final.std.get(n), robust.get(n)
        L.append(f"| {n} | {v:.6g} | {_g3(sd)} | {_g3(rb)} |")
    loose = understated(result.final.std, robust, result.final.estimates)
    if loose:
        L += ["", f"The robust (sandwich) std exceeds the Cramér-Rao std by more than "
              f"{ROBUST_RATIO:g} times for {', '.join(loose)}: the final model's innovations are "
              "still serially correlated (an effect it lacks, or noise levels that do not "
              "describe the misfit), so the Cramér-Rao std understates their uncertainty; quote "
              "the robust std (White 1982; Newey & West 1987)."]
    moved = moved_text(moved_declared(result))
    if moved:
        L += ["", moved[0].upper() + moved[1:] + "."]
    flat = getattr(result.final, "flat", None)
    if flat:
        ridge = getattr(result.final, "ridge", "") or ""
        whole = (f" The combination, as relative changes at the estimates: "
                 f"{ridge.removeprefix('; as relative changes: ')}." if ridge else "")
        L += ["", f"The record does not identify {', '.join(flat)} separately: the likelihood "
              "is flat along a combination of them where the fit stopped (relative eigenvalue "
              "of the Fisher information below 1e-4), so their values above are one point of "
              "a ridge; fix one of them (`bondgraph sensitivity` ranks the parameters and "
              f"recommends a set to estimate), or add a record that excites them apart.{whole}"
              + _ridge_width(flat, robust, result.final.estimates)]
    return L


def _ridge_width(flat, robust: dict, estimates: dict) -> str:
    """How far along the ridge each of ``flat`` is known: its robust std as a
    share of its value, where it has one (the accept rule counts a parameter
    within :data:`~bondgraph.diagnose.accept.UNDETERMINED_REL` of its value
    as determined however flat the information is); "" when none has one."""
    shares = [f"{n} {100 * robust[n] / abs(estimates[n]):.3g} %" for n in flat
              if robust.get(n) is not None and estimates.get(n)]
    if not shares:
        return ""
    return (f" Their robust std as a share of their values: {', '.join(shares)} (the accept "
            f"rule counts a parameter known within {UNDETERMINED_REL:.0%} as determined).")


def _g3(v) -> str:
    """``v`` to 3 significant digits, "-" for None."""
    return "-" if v is None else f"{v:.3g}"


def _md_ranking(k: int, ranking) -> list[str]:
    L = [f"Step {k}:", "",
         "| candidate | test | χ² | k | p-value | explained | indistinguishable from |",
         "|---|---|---|---|---|---|---|"]
    for c in ranking[:10]:
        # a screened candidate's statistic is not the score test whose share this is
        ex = f"{100 * c.explained:.1f} %" if c.explained is not None and not c.screened else "-"
        eq = ", ".join(c.equivalent) if c.equivalent else ""
        if c.failed:
            L.append(f"| {c.label} | {c.test} | failed | {c.dof} | - | - | {c.failed} |")
            continue
        L.append(f"| {c.label} | {c.test} | {c.statistic:.1f} | {c.dof} | {c.p_value:.2g} "
                 f"| {ex} | {eq} |")
    L.append("")
    return L


def _md_residuals(result: LoopResult) -> list[str]:
    res = result.final.residuals
    L = ["## Residuals of the final model", "", res.table(), ""]
    reg = res.top_regions(5)
    if reg:
        L.append("Where the remaining residual is largest (η²: share of the squared standardised "
                 "innovation explained by the operating variable):")
        L.append("")
        for r in reg:
            lo, hi, m = r.worst_bin()
            L.append(f"- {r.output}: {r.variable} in [{lo:.4g}, {hi:.4g}] (mean ε²/S = {m:.2f}, "
                     f"η² = {r.eta2:.2f})")
    return L
