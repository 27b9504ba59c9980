"""The evidence plot of one loop step: what separates the candidates.

The screening statistics of a step are often huge and close (χ² 96 366 and
93 767): bars of their values look equal. This plot draws instead how far
each candidate is *behind the best*, on a symmetric-log axis (linear below
10, logarithmic above), with the gap written beside each bar:

* left panel, the screening of every candidate (score test or likelihood
  ratio over a grid): best χ² − 2k minus the candidate's χ² − 2k (the
  predicted AIC decrease); ``≡`` marks candidates whose innovation
  signatures the record cannot tell apart (``Candidate.equivalent``), and
  a failed candidate is named as failed;
* right panel (when candidates were refitted), the confirmation refits:
  the confirmed lead's LR − 2k minus each refit's; the accepted candidate
  in green, those Vuong's test cannot tell from the lead hatched
  (``tied``, with the test's p-value), rejected ones in red with the reason.

Reads only :class:`bondgraph.diagnose.result.Candidate` and
:class:`bondgraph.diagnose.result.LoopResult`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bondgraph.report.plots import pyplot

#: candidates drawn per step
SHOWN = 15
#: linear range of the symmetric-log gap axis (χ² units)
LINEAR = 10.0
ACCEPTED, TIED, REJECTED, PLAIN = "tab:green", "tab:orange", "tab:red", "0.55"


def accepted_at(result, k: int):
    """The step accepted at step ``k`` (1-based) or None (the loop stopped)."""
    return result.steps[k - 1] if k <= len(result.steps) else None


def is_accepted(c, acc) -> bool:
    """Whether candidate ``c`` is the accepted step ``acc``."""
    return acc is not None and (acc.effect, acc.attached_to) == (c.effect, c.target.name)


def confirmed_value(c) -> float | None:
    """LR − 2k of ``c``'s confirmation refit, or None (not refitted)."""
    conf = c.confirmed or {}
    lr, dof = conf.get("lr"), conf.get("dof", c.dof)
    if lr is None or not np.isfinite(lr):
        return None
    return float(lr) - 2 * float(dof)


def number(v: float) -> str:
    """``v`` for a reader: whole numbers with thin spaces from 100 on
    (``96 362``), three significant digits below."""
    return f"{v:,.0f}".replace(",", "\u2009") if abs(v) >= 100 else f"{v:.3g}"


def short_reason(reason: str | None, width: int = 42) -> str:
    """The reason of a rejection cut to ``width`` characters."""
    text = str(reason or "rejected")
    return text if len(text) <= width else text[: width - 1] + "…"


def plot_evidence(result, k: int, ranking, path) -> str:
    """Draw the evidence plot of step ``k`` into ``path`` (PNG).

    Parameters
    ----------
    result : LoopResult
        The loop's (partial) result: its ``steps`` say what was accepted.
    k : int
        The step (1-based).
    ranking : list of Candidate
        The step's candidates, best first.
    path : str or Path
        Where the PNG is written.

    Returns
    -------
    str
        The file name of ``path``.
    """
    plt = pyplot()
    top = ranking[:SHOWN]
    acc = accepted_at(result, k)
    refitted = [c for c in top if confirmed_value(c) is not None]
    ncol = 2 if refitted else 1
    fig, axes = plt.subplots(1, ncol, figsize=(7.5 + 4.5 * (ncol - 1), 0.36 * len(top) + 1.9),
                             sharey=True, squeeze=False,
                             gridspec_kw={"width_ratios": [3, 2][:ncol]})
    rows = np.arange(len(top))[::-1]          # the best on top
    _screening(axes[0, 0], top, rows, acc)
    axes[0, 0].set_yticks(rows, [c.label + ("  ≡" if c.equivalent else "") for c in top],
                          fontsize=8)
    if refitted:
        _confirmations(axes[0, 1], top, rows, acc)
    note = (f"green: accepted ({acc.effect} @ {acc.attached_to})"
            if any(is_accepted(c, acc) for c in top) else
            f"accepted: {acc.effect} @ {acc.attached_to}, not among these" if acc is not None
            else "none accepted")
    fig.suptitle(f"Step {k}: how far each candidate is behind the best ({note})", fontsize=10)
    fig.legend(handles=_legend(top, refitted), loc="lower center", ncol=4, fontsize=7,
               frameon=False)
    fig.tight_layout(rect=(0, 0.07 if len(top) > 3 else 0.12, 1, 1))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path).name


def _gap_axis(ax, gaps, xlabel: str) -> None:
    """Symmetric-log gap axis from 0 with plain-number ticks."""
    ax.set_xscale("symlog", linthresh=LINEAR)
    finite = [g for g in gaps if g is not None and np.isfinite(g)]
    right = max(finite + [LINEAR]) * 4
    ax.set_xlim(-0.3, right)
    from matplotlib.ticker import FuncFormatter

    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}" if v >= 0 else ""))
    ax.set_xlabel(xlabel, fontsize=8)
    ax.tick_params(axis="x", labelsize=8)
    ax.grid(axis="x", alpha=0.3)


def _bar(ax, y: float, gap: float, colour: str, text: str, hatch: str | None = None) -> None:
    """One bar from 0 to ``gap`` with a dot at its end (visible at 0) and
    ``text`` beside it."""
    ax.barh(y, gap, height=0.6, color=colour, hatch=hatch, edgecolor="white" if hatch else None)
    ax.plot([gap], [y], "o", ms=5, color=colour, mec="k", mew=0.4)
    ax.text(max(gap, 0) * 1.15 + 0.6, y, text, va="center", fontsize=7)


def _screening(ax, top, rows, acc) -> None:
    """Left panel: each candidate's screening χ² − 2k behind the best's."""
    scores = [c.score for c in top if not c.failed and np.isfinite(c.score)]
    best = max(scores) if scores else 0.0
    gaps = []
    for c, y in zip(top, rows):
        if c.failed or not np.isfinite(c.score):
            ax.text(0.5, y, f"failed: {short_reason(c.failed, 50)}", va="center", fontsize=7,
                    color=REJECTED)
            gaps.append(None)
            continue
        gap = best - c.score
        gaps.append(gap)
        text = f"best (χ² − 2k = {number(c.score)})" if gap == 0 else f"−{number(gap)}"
        _bar(ax, y, gap, ACCEPTED if is_accepted(c, acc) else PLAIN, text)
    _gap_axis(ax, gaps, "screening: behind the best χ² − 2k (predicted AIC decrease) by")
    ax.set_title("all candidates (score test / likelihood-ratio grid)", fontsize=9)


def _confirmations(ax, top, rows, acc) -> None:
    """Right panel: each refit's LR − 2k behind the confirmed lead's, the
    accepted one green, the tied ones hatched, the rejected ones red."""
    vals = [confirmed_value(c) for c in top]
    lead = max(v for v in vals if v is not None)
    gaps = []
    for c, y, v in zip(top, rows, vals):
        if v is None:
            ax.text(0.5, y, "not refitted", va="center", fontsize=7, color="0.6")
            gaps.append(None)
            continue
        gap = lead - v
        gaps.append(gap)
        conf = c.confirmed
        tied = "tie_p" in conf and np.isfinite(conf["tie_p"]) or bool(c.tied)
        colour = (ACCEPTED if is_accepted(c, acc) else
                  REJECTED if conf.get("accepted") is False else PLAIN)
        text = "lead" if gap == 0 else f"−{number(gap)}"
        if "tie_p" in conf:
            text += f", tied with the lead (Vuong p {conf['tie_p']:.2g})"
        elif c.tied:
            text += f", tied with {', '.join(c.tied[:2])}" + (", …" if len(c.tied) > 2 else "")
        if conf.get("accepted") is False:
            text += f"; rejected: {short_reason(conf.get('reason'), 32)}"
        _bar(ax, y, gap, colour, text, hatch="///" if tied else None)
    _gap_axis(ax, gaps, "refit: behind the confirmed lead's LR − 2k by")
    ax.set_title("confirmation refits (what the decision used)", fontsize=9)


def _legend(top, refitted) -> list:
    """Legend handles of what the plot shows."""
    from matplotlib.patches import Patch

    h = [Patch(color=ACCEPTED, label="accepted"), Patch(color=PLAIN, label="not accepted")]
    if refitted:
        h += [Patch(color=REJECTED, label="refit rejected"),
              Patch(facecolor=PLAIN, hatch="///", edgecolor="white",
                    label="tied: Vuong's test cannot tell it from the lead")]
    if any(c.equivalent for c in top):
        h.append(Patch(color="white", label="≡ same innovation signature as another"))
    return h
