"""The loop's report as one self-contained HTML page (``report.html``).

Everything is in the file: the plots as inline base64 PNGs, a few lines of
inline JavaScript that sort the tables by a click on a column head, the
style sheet. No network, no CDN. Every text from the result (names, reasons,
warnings) is escaped (:func:`html.escape`).

Sections, top to bottom: the warnings, the error before and after with the
accepted effects, the graph before and after (the added fragment in green),
the parameters with their Cramér-Rao std, the fit and innovation plots, the
evidence of every step (plot and sortable ranking), the rejected candidates,
the final residuals. Reads only :class:`bondgraph.diagnose.result.LoopResult`.
"""

from __future__ import annotations

import base64
import math
from html import escape
from pathlib import Path

from bondgraph.diagnose.result import (
    LoopResult,
    moved_declared,
    moved_text,
    robust_of,
    understated,
)
from bondgraph.report.evidence import confirmed_value
from bondgraph.inference.robust import ROBUST_RATIO

#: candidates listed per step in the ranking tables
RANKED = 60

STYLE = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:1.5em auto;
max-width:1250px;padding:0 1em;color:#222;line-height:1.4}
h1{font-size:1.5em}h2{font-size:1.2em;border-bottom:1px solid #ccc;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0;font-size:.88em}
th,td{border:1px solid #ccc;padding:.2em .5em;text-align:left}
td.n{text-align:right;font-variant-numeric:tabular-nums}
table.sortable th{cursor:pointer;background:#f0f3f7;user-select:none}
table.sortable th:after{content:" \\2195";color:#999}
tr.accepted td{background:#e3f6e3}tr.rejected td{background:#fbe9e9}
.warnings{background:#fff4d6;border:1px solid #e0b84a;padding:.5em 1em;border-radius:4px}
.running{background:#e8f0fe;border:1px solid #8ab4f8;padding:.5em 1em}
.big{font-size:1.15em}img{max-width:100%;border:1px solid #eee}
.pair{display:flex;gap:1em;flex-wrap:wrap}.pair figure{flex:1 1 480px;margin:0}
figcaption{font-size:.85em;color:#555}.muted{color:#777}
"""

#: sort a table by the clicked column (numbers by data-v, else by text)
SCRIPT = """
document.querySelectorAll("table.sortable th").forEach(function (th) {
  th.addEventListener("click", function () {
    var body = th.closest("table").tBodies[0], i = th.cellIndex;
    var up = th.dataset.dir !== "up"; th.dataset.dir = up ? "up" : "down";
    function key(row) {
      var c = row.cells[i], v = c.dataset.v !== undefined ? c.dataset.v : c.textContent.trim();
      var n = Number(v);
      return v !== "" && !isNaN(n) ? [0, n] : [1, v.toLowerCase()];
    }
    Array.from(body.rows).sort(function (a, b) {
      var x = key(a), y = key(b);
      var d = x[0] - y[0] || (x[1] < y[1] ? -1 : x[1] > y[1] ? 1 : 0);
      return up ? d : -d;
    }).forEach(function (r) { body.appendChild(r); });
  });
});
"""


def page(result: LoopResult, out, pngs: list[str]) -> str:
    """The text of ``report.html``.

    Parameters
    ----------
    result : LoopResult
        The loop's (partial) result.
    out : str or Path
        The folder holding the PNGs named in ``pngs`` (inlined from there).
    pngs : list of str
        File names of the plots: ``graph_before.png``, ``graph_after.png``,
        ``fit_before_after.png``, ``residuals_before_after.png``,
        ``evidence_step<k>.png`` (those present are shown).

    Returns
    -------
    str
        The whole page.
    """
    out = Path(out)
    images = {p: _img(out / p) for p in pngs}
    body = [f"<h1>Residual-tracing report: {escape(result.model)}</h1>",
            f"<p>{_code(result.records())} Metric: "
            f"{escape(result.metric)}. Criterion: {escape(result.criterion.upper())}.</p>"]
    if result.numerics():
        body.append(f"<p>{escape(result.numerics())}</p>")
    if not result.finished:
        body.append('<p class="running">Intermediate version: the loop is still running (or '
                    'was interrupted); this page is rewritten after every step.</p>')
    body += _warnings(result)
    body += _summary(result)
    body += _graphs(result, images)
    body += _parameters(result)
    body += _section("Fit before and after", [images.get("fit_before_after.png", ""),
                                               images.get("residuals_before_after.png", "")])
    body += _evidence(result, images)
    if result.discovery is not None:
        dp = result.discovery
        body += _section("Discovery (an effect beyond the library)",
                         [f"<p>The {escape(dp.kind)} missing at <code>{escape(dp.port)}</code>, "
                          f"reconstructed (±2σ), against the discovered law "
                          f"({'accepted' if dp.accepted else 'not accepted'} by the loop):</p>",
                          f"<pre>{escape(dp.text)}\n{escape(dp.passivity)}</pre>",
                          images.get("discovery.png", "")], anchor="discovery")
    body += _rejected(result)
    body += _residuals(result)
    body.append('<p class="muted">Also in this folder: <a href="report.md">report.md</a>, '
                '<a href="report.json">report.json</a>, <a href="loop.log">loop.log</a>.</p>')
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>Loop report: {escape(result.model)}</title><style>{STYLE}</style></head>"
            "<body>\n" + "\n".join(body) + f"\n<script>{SCRIPT}</script>\n</body></html>\n")


def _code(text: str) -> str:
    """``text`` escaped, its markdown code spans (`...`) as <code>."""
    parts = escape(text).split("`")
    return "".join(f"<code>{t}</code>" if i % 2 else t for i, t in enumerate(parts))


def _img(path: Path) -> str:
    """``<img>`` of the PNG at ``path`` as a data URI ("" if absent)."""
    if not path.exists():
        return ""
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return f'<img src="data:image/png;base64,{data}" alt="{escape(path.stem)}">'


def _section(title: str, parts: list[str], anchor: str | None = None) -> list[str]:
    """``<h2>`` and the non-empty ``parts``."""
    a = f' id="{escape(anchor)}"' if anchor else ""
    return [f"<h2{a}>{escape(title)}</h2>"] + [p for p in parts if p]


def _num(v, fmt: str = ".4g") -> tuple[str, str] | str:
    """A numeric cell: (shown text, sort value), or "-" for None/NaN."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-" if v is None or math.isnan(v) else (f"{v}", "")
    return (format(v, fmt), repr(float(v)))


def _table(heads: list[str], rows: list, classes: list[str] | None = None) -> str:
    """A sortable table; a cell is text (escaped) or (text, sort value)."""
    h = "".join(f"<th>{escape(x)}</th>" for x in heads)
    lines = [f'<table class="sortable"><thead><tr>{h}</tr></thead><tbody>']
    for i, row in enumerate(rows):
        cls = classes[i] if classes and classes[i] else ""
        cells = []
        for c in row:
            if isinstance(c, tuple):
                cells.append(f'<td class="n" data-v="{escape(c[1])}">{escape(c[0])}</td>')
            else:
                cells.append(f"<td>{escape(str(c))}</td>")
        lines.append((f'<tr class="{cls}">' if cls else "<tr>") + "".join(cells) + "</tr>")
    lines.append("</tbody></table>")
    return "\n".join(lines)


def _warnings(result: LoopResult) -> list[str]:
    """The warnings first: the result's, the final estimates on a bound
    (a process-noise intensity on the floor of its box is none: the record
    asks for no random walk there) and those the record does not identify
    separately."""
    items = list(result.warnings)
    boxed = [] if result.final is None else [
        n for n in result.final.at_bound if n not in getattr(result.final, "noise_floor", ())]
    if boxed:
        items.append("estimates on a bound of their box (no Cramér-Rao std): " + ", ".join(boxed))
    if result.final is not None and getattr(result.final, "flat", None):
        ridge = getattr(result.final, "ridge", "") or ""
        items.append("not identified separately by the record (the likelihood is flat along "
                     "a combination of them): " + ", ".join(result.final.flat)
                     + (f"; the combination, as relative changes: "
                        f"{ridge.removeprefix('; as relative changes: ')}" if ridge else ""))
    if not items:
        return []
    li = "".join(f"<li>{escape(w)}</li>" for w in items)
    return [f'<div class="warnings" id="warnings"><strong>Warnings</strong><ul>{li}</ul></div>']


def _summary(result: LoopResult) -> list[str]:
    """The error before and after, then the accepted effects."""
    i, f = result.initial, result.final
    if i.validation_metric is not None:
        line = (f"Error on the validation record before: <b>{i.validation_metric:.4g}</b>, "
                f"after: <b>{f.validation_metric:.4g}</b> (estimation record: "
                f"{i.metric:.4g} &rarr; {f.metric:.4g}).")
        more = result.more_validation()
        if more:
            line += "<br>Further validation records: " + "; ".join(
                f"{escape(k)} {'-' if b is None else f'{b:.4g}'} &rarr; {a:.4g}" for k, b, a in more) + "."
    else:
        line = f"Error before: <b>{i.metric:.4g}</b>, after: <b>{f.metric:.4g}</b>."
    parts = [f'<p class="big">{line}</p>']
    if not result.steps:
        parts.append(f"<p>No effect accepted: {escape(result.none_accepted())}.</p>")
    else:
        more = list(dict.fromkeys(k for s in result.steps for k in getattr(s, "more_errors", {})))
        rows = [[str(k), s.shown(),
                 s.shown_target(), _num(s.error_before), _num(s.error_after),
                 *(_arrow(s.more_errors.get(m)) for m in more),
                 _num(s.nll_before, ".1f"), _num(s.nll_after, ".1f"),
                 _num(s.lr, ".1f"), _scaled(s), ", ".join(s.tied)]
                for k, s in enumerate(result.steps, 1)]
        parts.append(_table(["step", "effect", "attached to", "error before", "error after",
                             *(f"error on {m}" for m in more),
                             "NLL before", "NLL after", "LR", "LR / scale (correlated "
                             "innovations)", "tied with (Vuong)"], rows))
    return _section("Result", parts, "result")


def _arrow(pair) -> str:
    """"before → after" of a step's error on a further validation record
    ("-" for a value not at hand)."""
    b, a = pair if pair else (None, None)
    return " → ".join("-" if v is None else f"{v:.4g}" for v in (b, a))


def _scaled(step) -> tuple[str, str] | str:
    """A step's likelihood ratio divided by its scale for correlated
    innovations (at least 1), with the scale
    (:func:`bondgraph.diagnose.fit.robust_lr`); "-" where it was not computed."""
    c = getattr(step, "lr_scale", None)
    if c is None or step.lr is None or not math.isfinite(step.lr / c):
        return "-"
    x = step.lr / max(c, 1.0)           # a scale below 1 never strengthens the evidence
    return (f"{x:.1f} (÷ {c:.3g})" if c > 1 else f"{x:.1f} (scale {c:.3g})", repr(float(x)))


def graph_changes(before, after) -> set[str]:
    """Names of the elements and bonds of graph ``after`` that graph
    ``before`` lacks (what the accepted effects added).

    Parameters
    ----------
    before, after : BondGraph or None

    Returns
    -------
    set of str
        Empty when either graph is None.
    """
    if before is None or after is None:
        return set()
    bonds = {b.name for b in before.bonds}
    return ({n for n in after.elements if n not in before.elements}
            | {b.name for b in after.bonds if b.name not in bonds})


def _graphs(result: LoopResult, images: dict) -> list[str]:
    """The declared graph and the augmented one, the added part in green."""
    before, after = images.get("graph_before.png"), images.get("graph_after.png")
    if not (before or after):
        return []
    added = sorted(n for n in graph_changes(result.declared_graph, result.final_graph)
                   if result.final_graph is not None and n in result.final_graph.elements)
    figs = []
    if before:
        figs.append(f"<figure>{before}<figcaption>declared graph</figcaption></figure>")
    if after:
        what = (f"added elements in green: {escape(', '.join(added))}" if added else
                "the accepted effects add no element (they change laws or sensors)")
        figs.append(f"<figure>{after}<figcaption>after the loop; {what}</figcaption></figure>")
    return _section("The graph before and after", [f'<div class="pair">{"".join(figs)}</div>'],
                    "graph")


def _parameters(result: LoopResult) -> list[str]:
    """Final estimates, initial states and noise stds with their std."""
    f = result.final
    rows, classes = [], []
    groups = [("parameter", f.estimates, ""), ("initial state", f.x0_estimates, "x0."),
              ("noise std", f.noise_estimates, "noise.")]
    declared = result.declared_graph.params if result.declared_graph is not None else None
    added = set() if declared is None else {n for n in f.estimates if n not in declared}
    robust = robust_of(f)
    for kind, values, prefix in groups:
        for name, v in values.items():
            sd = f.std.get(prefix + name)
            rb = robust.get(prefix + name)
            rel = abs(sd / v) * 100 if sd is not None and v else None
            note = ("on the floor of its box (no random walk asked for)"
                    if prefix + name in getattr(f, "noise_floor", ()) else
                    "on a bound" if name in f.at_bound else "")
            rows.append([name, kind, _num(v, ".6g"), _num(sd, ".3g"), _num(rb, ".3g"),
                         _num(rel, ".3g"), note])
            classes.append("accepted" if name in added else "")
    table = _table(["name", "kind", "estimate", "Cramér-Rao std", "robust std",
                    "std / |estimate| [%]", "note"], rows, classes)
    loose = understated(f.std, robust, f.estimates)
    warn = (f'<p class="warnings">The robust (sandwich) std exceeds the Cramér-Rao std by more '
            f'than {ROBUST_RATIO:g} times for {escape(", ".join(loose))}: the innovations are still '
            f'serially correlated, so the Cramér-Rao std understates their uncertainty; quote '
            f'the robust std.</p>' if loose else "")
    moved = moved_text(moved_declared(result))
    if moved:
        warn += f'<p class="warnings">{escape(moved[0].upper() + moved[1:])}.</p>'
    return _section("Parameters of the final model",
                    [table, warn, '<p class="muted">Rows in green: parameters of the accepted '
                     'effects.</p>' if added else ""], "parameters")


def _ranking_rows(ranking, accepted) -> tuple[list, list]:
    """Rows (and row classes) of one step's ranking table."""
    rows, classes = [], []
    best = max((c.score for c in ranking if not c.failed and math.isfinite(c.score)),
               default=float("nan"))
    for c in ranking[:RANKED]:
        conf = c.confirmed or {}
        verdict = ("accepted" if conf.get("accepted") else
                   "rejected: " + str(conf.get("reason")) if conf.get("accepted") is False else
                   "refitted" if conf else "")
        if c.failed:
            verdict = f"failed: {c.failed}"
        tie = (f"p {conf['tie_p']:.2g} vs the lead" if "tie_p" in conf else
               ", ".join(c.tied))
        rows.append([c.label, c.test, _num(c.statistic, ".1f"), str(c.dof),
                     _num(c.p_value, ".2g"), _num(c.score, ".1f"), _num(c.score - best, ".4g"),
                     _num(None if c.explained is None or c.screened else 100 * c.explained,
                          ".1f"),
                     _num(confirmed_value(c), ".1f"), tie, ", ".join(c.equivalent), verdict])
        classes.append("accepted" if (c.effect, c.target.name) == accepted else
                       "rejected" if conf.get("accepted") is False else "")
    return rows, classes


def _evidence(result: LoopResult, images: dict) -> list[str]:
    """Every step: its evidence plot and its sortable ranking."""
    parts = ['<p class="muted">Each bar is how far a candidate is behind the best of its step '
             '(χ² − 2k, the predicted AIC decrease, and for the refitted ones the confirmed '
             'LR − 2k). Click a column head to sort.</p>']
    for k, ranking in enumerate(result.rankings, 1):
        acc = result.steps[k - 1] if k <= len(result.steps) else None
        rows, classes = _ranking_rows(ranking, None if acc is None else
                                      (acc.effect, acc.attached_to))
        more = (f' <span class="muted">({RANKED} best of {len(ranking)} shown; all in '
                f'report.json)</span>' if len(ranking) > RANKED else "")
        parts += [f"<h3>Step {k}{more}</h3>", images.get(f"evidence_step{k}.png", ""),
                  _table(["candidate", "test", "χ²", "k", "p-value", "χ² − 2k", "behind best",
                          "explained [%]", "refit LR − 2k", "tied (Vuong)",
                          "indistinguishable from", "decision"], rows, classes)]
    return _section("Evidence of every step", parts, "evidence")


def _rejected(result: LoopResult) -> list[str]:
    """The refitted candidates that were not accepted, with the reason."""
    if not result.rejected:
        return []
    rows = [[str(r.step), r.candidate.label, r.reason, _num(r.criterion_after, ".2f"),
             _num(r.whiteness_after, ".1f")] for r in result.rejected]
    return _section("Rejected candidates", [_table(
        ["step", "candidate", "reason", f"{result.criterion.upper()} after", "whiteness after"],
        rows)], "rejected")


def _residuals(result: LoopResult) -> list[str]:
    """Per-output residual statistics of the final model and where the
    remaining residual is largest."""
    res = result.final.residuals
    rows = [[o.name, _num(o.bias), _num(o.rms), _num(o.bias_sigma, ".1f"),
             _num(o.ljung_box_p, ".2g"), _num(o.nis_mean, ".2f"), _num(o.peak_hz, ".3g")]
            if o.n else [o.name, "not in the record", "", "", "", "", ""] for o in res.outputs]
    parts = [_table(["output", "bias", "RMS", "bias/σ", "Ljung-Box p", "NIS", "peak Hz"], rows)]
    regions = []
    for r in res.top_regions(5):
        lo, hi, m = r.worst_bin()
        regions.append(f"<li>{escape(r.output)}: {escape(r.variable)} in [{lo:.4g}, {hi:.4g}] "
                       f"(mean ε²/S = {m:.2f}, η² = {r.eta2:.2f})</li>")
    if regions:
        parts.append("<p>Where the remaining residual is largest (η²: share of the squared "
                     "standardised innovation explained by the operating variable):</p>"
                     f"<ul>{''.join(regions)}</ul>")
    return _section("Residuals of the final model", parts, "residuals")
