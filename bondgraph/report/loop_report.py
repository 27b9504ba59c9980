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

import json
from pathlib import Path

import numpy as np

from bondgraph.core.codegen import generate_source
from bondgraph.core.equations import derive
from bondgraph.report.plots import pyplot


def _fit_summary(fit) -> dict:
    from bondgraph.diagnose.loop import _jsonable

    return _jsonable({
        "model": fit.graph.name, "nll": fit.nll, "aic": fit.aic(), "bic": fit.bic(),
        "metric": fit.metric, "whiteness": fit.residuals.whiteness,
        "estimates": fit.estimates(), "std": fit.std,
        "residuals": fit.residuals.to_dict(),
    })


class LoopReporter:
    """Writes the loop's log and report into one folder while the loop runs.

    Pass :meth:`log` and :meth:`update` to
    :func:`bondgraph.diagnose.loop.run_loop`: every log line goes to
    ``loop.log`` (and to ``echo``), and the report is rewritten after the
    initial fit, after every step and at the end, so that an interrupted run
    keeps its work.

    Parameters
    ----------
    out_dir : path
        The report folder (created).
    echo : callable, optional
        Also print each log line with it (e.g. ``print``).
    """

    def __init__(self, out_dir, echo=None):
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.echo = echo
        self.log_path = self.out / "loop.log"
        self.log_path.write_text("")

    def log(self, line: str) -> None:
        """Append one line to ``loop.log`` (and echo it)."""
        if self.echo is not None:
            self.echo(line)
        with open(self.log_path, "a") as fh:
            fh.write(line + "\n")

    def update(self, loop, current, final: bool = False) -> None:
        """Rewrite the report from the loop's state."""
        write(loop, current, final, self.out)


def write(loop, current, final: bool, out: Path) -> None:
    """Write ``report.json``, ``report.md``, the PNGs and the augmented model
    into ``out``."""
    from bondgraph.diagnose.loop import _jsonable, _metric_name

    out = Path(out)
    mname = _metric_name(loop.s, current.model)
    report = {
        "model": loop.user_graph.name,
        "source": loop.user_graph.source,
        "record": getattr(loop.data.exp, "name", None),
        "metric": mname,
        "criterion": loop.s.criterion,
        "finished": bool(final),
        "error_before": loop.initial.metric,
        "error_after": current.metric,
        "steps": [dict(vars(s)) for s in loop.steps],
        "rejected": [r for r in loop.rejected],
        "rankings": [[c.to_dict() for c in r[:25]] for r in loop.rankings],
        "initial_fit": _fit_summary(loop.initial),
        "final_fit": _fit_summary(current),
        "augmented_model": "augmented_model.py" if loop.applied else None,
        "settings": {"params": loop.s.params, "max_steps": loop.s.max_steps,
                     "significance": loop.s.significance, "ukf": loop.s.ukf.to_dict(),
                     "effects": [e.name for e in loop.s.effects]},
    }
    (out / "report.json").write_text(json.dumps(_jsonable(report), indent=2))
    _write_augmented(loop, current, out)
    pngs = _plots(loop, current, out)
    _write_markdown(loop, current, report, pngs, out)


def _write_augmented(loop, current, out: Path) -> None:
    if not loop.applied:
        return
    src = loop.user_graph.source
    name = f"{loop.user_graph.name}_augmented"
    lines = [f'"""Augmented declared model written by `bondgraph loop`.',
             "",
             f"It rebuilds the declared model '{loop.user_graph.name}' unchanged and adds the",
             "effects the loop accepted, in order, with their estimated values. The declared",
             'model\'s own source is not modified."""',
             "",
             "from bondgraph.diagnose.effects import Target, apply_effect"]
    if src and ":" in src:
        mod, fn = src.split(":", 1)
        lines.append(f"from {mod} import {fn} as _declared")
    else:
        lines.append("# the declared graph was passed in memory: set _declared to its builder")
        lines.append("_declared = None")
    lines += ["", "", "def build():",
              f'    """{loop.user_graph.name} + ' +
              " + ".join(f"{a['effect']} @ {a['target'].name}" for a in loop.applied) + '."""',
              "    g = _declared()",
              f"    g.name = {name!r}"]
    for a in loop.applied:
        vals = {k: float(v) for k, v in a["values"].items()}
        lines.append(f"    apply_effect(g, {a['effect']!r}, Target({a['target'].kind!r}, "
                     f"{a['target'].name!r}), {vals!r})")
    est = current.estimates()
    lines += ["    for name, value in ESTIMATES.items():",
              "        g.params[name].default = value",
              "    return g", "",
              "",
              "#: parameter estimates of the final fit (applied as defaults by build())",
              "ESTIMATES = {"]
    lines += [f"    {k!r}: {float(v)!r}," for k, v in est.items()]
    lines += ["}", ""]
    (out / "augmented_model.py").write_text("\n".join(lines))
    gen = out / "generated"
    gen.mkdir(exist_ok=True)
    g = current.graph.copy(name)
    for k, v in est.items():
        if k in g.params:
            g.params[k].default = float(v)
    ss = derive(g)
    (gen / f"{name}.py").write_text(generate_source(
        ss, source=f"{out / 'augmented_model.py'}:build",
        command="bondgraph loop (see report.md)"))


def _plots(loop, current, out: Path) -> list[str]:
    plt = pyplot()

    pngs = []
    init = loop.initial
    t, u, y = loop.data.arrays(current.model)
    ny = y.shape[1]
    # measured vs model (free-run simulation) before and after
    fig, axes = plt.subplots(ny, 1, figsize=(10, 2.4 * ny + 0.6), sharex=True, squeeze=False)
    for i in range(ny):
        ax = axes[i, 0]
        ax.plot(t, y[:, i], ".", ms=2, color="0.55", label="measured")
        if init.sim_y is not None:
            ax.plot(t, init.sim_y[:, i], lw=1.2, color="tab:red", label="declared model (fitted)")
        if current is not init and current.sim_y is not None:
            ax.plot(t, current.sim_y[:, i], lw=1.2, color="tab:blue", label="augmented model")
        unit = current.model.output_units[i]
        ax.set_ylabel(f"{current.model.outputs[i]}\n[{unit or '-'}]", fontsize=8)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8, loc="best")
    axes[-1, 0].set_xlabel("t [s]")
    fig.suptitle("Measured vs free-run simulation, before and after the loop", fontsize=10)
    fig.tight_layout()
    p = out / "fit_before_after.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    pngs.append(p.name)
    # residuals before and after (one-step innovations, standardised)
    fig, axes = plt.subplots(ny, 1, figsize=(10, 2.2 * ny + 0.6), sharex=True, squeeze=False)
    for i in range(ny):
        ax = axes[i, 0]
        for fit, col, lab in ((init, "tab:red", "declared"), (current, "tab:blue", "augmented")):
            if fit is current and current is init:
                continue
            e = fit.ukf.innovations[:, 0, i]
            sd = np.sqrt(fit.ukf.S[:, 0, i, i])
            ax.plot(t, e / sd, lw=0.6, color=col, alpha=0.8, label=lab)
        ax.set_ylabel(f"{current.model.outputs[i]}\nε/√S", fontsize=8)
        ax.grid(alpha=0.3)
    if axes[0, 0].get_legend_handles_labels()[0]:
        axes[0, 0].legend(fontsize=8)
    axes[-1, 0].set_xlabel("t [s]")
    fig.suptitle("Standardised UKF innovations before and after", fontsize=10)
    fig.tight_layout()
    p = out / "residuals_before_after.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    pngs.append(p.name)
    # evidence ranking of every step
    for k, ranking in enumerate(loop.rankings, 1):
        top = ranking[:15][::-1]
        if not top:
            continue
        fig, ax = plt.subplots(figsize=(9, 0.32 * len(top) + 1.2))
        vals = [max(c.score, -5) for c in top]
        cols = ["tab:green" if any(s.effect == c.effect and s.attached_to == c.target.name
                                   for s in loop.steps) else "tab:gray" for c in top]
        ax.barh([c.label for c in top], vals, color=cols)
        ax.set_xlabel("evidence: χ² statistic − 2k (predicted AIC decrease)")
        ax.set_xscale("symlog", linthresh=10)
        ax.tick_params(axis="y", labelsize=7)
        ax.set_title(f"Step {k}: candidate effects (green: accepted)", fontsize=10)
        fig.tight_layout()
        p = out / f"evidence_step{k}.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        pngs.append(p.name)
    return pngs


def _write_markdown(loop, current, report, pngs, out: Path) -> None:
    init = loop.initial
    L = [f"# Residual-tracing report: {loop.user_graph.name}", ""]
    L.append(f"Record: `{report['record']}`. Metric: {report['metric']}. "
             f"Criterion: {loop.s.criterion.upper()}.")
    L.append("")
    L.append(f"**Error before: {init.metric:.4g}; after: {current.metric:.4g}.**")
    L.append("")
    L.append("## Accepted effects")
    L.append("")
    if loop.steps:
        L.append("| step | effect | attached to | error before | error after | NLL before | "
                 "NLL after | whiteness before | after |")
        L.append("|---|---|---|---|---|---|---|---|---|")
        for i, s in enumerate(loop.steps, 1):
            L.append(f"| {i} | {s.effect} | {s.attached_to} | {s.error_before:.4g} | "
                     f"{s.error_after:.4g} | {s.nll_before:.1f} | {s.nll_after:.1f} | "
                     f"{s.whiteness_before:.1f} | {s.whiteness_after:.1f} |")
        L.append("")
        L.append("Parameters of the final model:")
        L.append("")
        L.append("| parameter | estimate | Cramér-Rao std |")
        L.append("|---|---|---|")
        for n, v in current.estimates().items():
            sd = current.std.get(n)
            L.append(f"| {n} | {v:.6g} | {sd:.3g} |" if sd is not None else f"| {n} | {v:.6g} | - |")
    else:
        L.append("None: no candidate was significant and improved both the criterion and the "
                 "whiteness.")
    L.append("")
    L.append("## Evidence (ranking of every step)")
    L.append("")
    if loop.rankings:
        for k, ranking in enumerate(loop.rankings, 1):
            L.append(f"Step {k}:")
            L.append("")
            L.append("| candidate | test | χ² | k | p-value | explained | indistinguishable from |")
            L.append("|---|---|---|---|---|---|---|")
            for c in ranking[:10]:
                ex = f"{100 * c.explained:.1f} %" if c.explained is not None else "-"
                eq = ", ".join(c.equivalent) if c.equivalent else ""
                L.append(f"| {c.label} | {c.kind} | {c.statistic:.1f} | {c.dof} | {c.p_value:.2g} "
                         f"| {ex} | {eq} |")
            L.append("")
    L.append("")
    L.append("## Residuals of the final model")
    L.append("")
    L.append(current.residuals.table())
    L.append("")
    reg = current.residuals.top_regions(5)
    if reg:
        L.append("Where the remaining residual is largest (η²: share of the squared standardised "
                 "innovation explained by the operating variable):")
        L.append("")
        for r in reg:
            lo, hi, m = r.worst_bin()
            L.append(f"- {r.output}: {r.variable} in [{lo:.4g}, {hi:.4g}] (mean ε²/S = {m:.2f}, "
                     f"η² = {r.eta2:.2f})")
    L.append("")
    for p in pngs:
        L.append(f"![{p}]({p})")
    L.append("")
    if loop.rejected:
        L.append("## Rejected candidates")
        L.append("")
        for r in loop.rejected:
            L.append(f"- step {r['step']}: {r['label']} — {r['reason']}")
    (out / "report.md").write_text("\n".join(L) + "\n")
