"""What the report plots say (issue 13, item 8): readable evidence ticks, an
'accepted' legend only when something was accepted, units on the
innovation axes, and a failed augmented simulation stated on the plot."""

from __future__ import annotations

import copy
import re
from types import SimpleNamespace

import matplotlib.figure
import numpy as np
import pytest

from bondgraph.data.experiments import run_experiment
from bondgraph.diagnose.loop import LoopSettings, run_loop
from bondgraph.diagnose.settings import SearchOptions
from bondgraph.inference.estimate import estimate
from bondgraph.inference.options import FitOptions, UKFOptions
from bondgraph.inference.prior import PriorSpec
from bondgraph.inference.problem import NoiseSpec, make_problem
from bondgraph.numerics.model import Model
from bondgraph.numerics.registry import build
from bondgraph.report import loop_report
from bondgraph.report.estimation import plot_fit


@pytest.fixture
def figures(monkeypatch):
    """Every figure saved while the test runs."""
    saved = []
    original = matplotlib.figure.Figure.savefig

    def keep(self, *args, **kw):
        saved.append(self)
        return original(self, *args, **kw)
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)
    return saved


@pytest.fixture(scope="module")
def record():
    return run_experiment("msd_force_step").segment(0, 120, name="short")


@pytest.fixture(scope="module")
def loop_result(record):
    """The loop on a record the declared model explains (nothing accepted)."""
    return run_loop(build("mass_spring_damper"), record, LoopSettings(params=["m", "k", "c"], search=SearchOptions(max_steps=1, structural=False)), progress=False)


def _texts(fig) -> list[str]:
    return [t.get_text() for t in fig.findobj(matplotlib.text.Text)]


def _evidence(result, out, figures):
    figures.clear()
    loop_report._plot_evidence(result, 1, result.rankings[0], out)
    (fig,) = figures
    return fig, fig.axes[0]


def test_evidence_ticks_are_plain_numbers_and_nothing_accepted_is_said(loop_result, tmp_path,
                                                                       figures):
    assert not loop_result.steps and loop_result.rankings[0]
    fig, ax = _evidence(loop_result, tmp_path, figures)
    # report.md and report.html say why, in the loop result's words
    why = loop_result.none_accepted()
    assert why == "nothing significant left"          # nothing refused here either
    assert f"None: {why}" in "\n".join(loop_report._md_accepted(loop_result))
    from bondgraph.report.html import _summary
    assert f"No effect accepted: {why}." in "".join(_summary(loop_result))
    labels = [t.get_text() for t in ax.get_xticklabels() if t.get_text()]
    assert labels
    for lab in labels:
        assert "×" not in lab and "$" not in lab and "10^" not in lab, lab
        float(lab.replace("−", "-"))                  # a plain number
    title = fig._suptitle.get_text()
    assert "none accepted" in title and "green" not in title
    colours = {tuple(np.round(p.get_facecolor()[:3], 3)) for p in ax.patches}
    green = tuple(np.round(matplotlib.colors.to_rgb("tab:green"), 3))
    assert green not in colours


def test_evidence_title_names_the_accepted_effect(loop_result, tmp_path, figures):
    res = copy.copy(loop_result)
    top = res.rankings[0][0]
    res.steps = [SimpleNamespace(effect=top.effect, attached_to=top.target.name)]
    fig, ax = _evidence(res, tmp_path, figures)
    assert fig._suptitle.get_text().endswith(
        f"(green: accepted ({top.effect} @ {top.target.name}))")
    green = matplotlib.colors.to_rgba("tab:green")
    assert sum(np.allclose(p.get_facecolor(), green) for p in ax.patches) == 1


def test_evidence_draws_each_candidate_s_gap_to_the_best(loop_result, tmp_path, figures):
    """Issue 30: bars of χ² values nearly equal on a log axis told nothing;
    each bar is now the candidate's χ² − 2k behind the best's, written
    beside it (the best: a bar of length 0 named 'best')."""
    ranking = [c for c in loop_result.rankings[0][:15] if not c.failed]
    fig, ax = _evidence(loop_result, tmp_path, figures)
    widths = sorted(p.get_width() for p in ax.patches)
    best = ranking[0].score
    assert widths == pytest.approx(sorted(best - c.score for c in ranking))
    assert widths[0] == 0.0
    texts = [t.get_text() for t in ax.texts]
    assert texts[0].startswith("best (χ² − 2k = ")
    gap = best - ranking[1].score
    assert texts[1] == "−" + (f"{gap:,.0f}".replace(",", "\u2009") if gap >= 100
                               else f"{gap:.3g}")


def test_evidence_marks_the_tied_and_rejected_refits(loop_result, tmp_path, figures):
    """The confirmation panel: the lead's refit at 0, a tied refit hatched
    with Vuong's p-value, a rejected one red with its reason."""
    res = copy.copy(loop_result)
    ranking = [copy.copy(c) for c in loop_result.rankings[0][:3]]
    lead, tied, other = ranking
    lead.confirmed = {"lr": 500.0, "dof": lead.dof, "accepted": False,
                      "reason": "the refitted model does not simulate"}
    lead.tied = [tied.label]
    tied.confirmed = {"lr": 480.0, "dof": tied.dof, "accepted": True, "tie_z": 0.5,
                      "tie_p": 0.62}
    res.steps = [SimpleNamespace(effect=tied.effect, attached_to=tied.target.name)]
    figures.clear()
    loop_report._plot_evidence(res, 1, ranking, tmp_path)
    (fig,) = figures
    right = fig.axes[1]
    bars = right.patches
    assert [b.get_width() for b in bars] == pytest.approx(
        [0.0, 20.0 + 2 * (tied.dof - lead.dof)])
    assert matplotlib.colors.same_color(bars[0].get_facecolor(), "tab:red")
    assert matplotlib.colors.same_color(bars[1].get_facecolor(), "tab:green")
    assert bars[1].get_hatch() == "///"
    texts = [t.get_text() for t in right.texts]
    assert "tied with the lead (Vuong p 0.62)" in texts[1]
    assert f"lead, tied with {tied.label}; rejected: the refitted model does not sim" in texts[0]
    assert texts[2] == "not refitted"


def test_failed_augmented_simulation_is_stated_on_the_fit_plot(loop_result, tmp_path, figures):
    res = copy.copy(loop_result)
    top = res.rankings[0][0]
    res.steps = [SimpleNamespace(effect=top.effect, attached_to=top.target.name)]
    res.final = copy.copy(res.final)
    res.final.sim_y = None                         # the augmented model's simulation failed
    figures.clear()
    loop_report._plot_fit(res, tmp_path)
    (fig,) = figures
    texts = " ".join(_texts(fig))
    assert "free-run simulation of the augmented model failed" in texts
    assert "augmented model: simulation failed" in fig._suptitle.get_text()
    # the declared model's simulation is drawn, and no failure is claimed without one
    figures.clear()
    loop_report._plot_fit(loop_result, tmp_path)
    assert not any("failed" in t for t in _texts(figures[0]))


def test_the_fit_plot_shows_the_held_out_record_beside_the_fitted_one(loop_result, tmp_path,
                                                                     figures):
    """With a validation record the fit plot has a second column: the
    held-out record's measured outputs and both models' free runs there
    (the arrays drawn are the summaries' own), each column titled with the
    two models' errors on its record."""
    res = copy.copy(loop_result)
    top = res.rankings[0][0]
    res.steps = [SimpleNamespace(effect=top.effect, attached_to=top.target.name)]
    ny = res.measured.shape[1]
    tv = res.time[-1] + 0.01 * np.arange(1, 41)
    yv = np.linspace(0.0, 1.0, 40)[:, None] * np.ones(ny)
    res.validation_time, res.validation_measured = tv, yv
    res.initial, res.final = copy.copy(res.initial), copy.copy(res.final)
    res.initial.validation_sim_y, res.initial.validation_metric = 2.0 * yv, 0.8123
    res.final.validation_sim_y, res.final.validation_metric = 1.5 * yv, 0.2345
    figures.clear()
    loop_report._plot_fit(res, tmp_path)
    (fig,) = figures
    assert len(fig.axes) == 2 * ny
    held = fig.axes[1]                         # row 0, column 1
    lines = {ln.get_label(): ln for ln in held.get_lines()}
    np.testing.assert_array_equal(lines["measured"].get_xdata(), tv)
    np.testing.assert_array_equal(lines["declared model (fitted)"].get_ydata(), 2.0 * yv[:, 0])
    np.testing.assert_array_equal(lines["augmented model"].get_ydata(), 1.5 * yv[:, 0])
    assert held.get_title() == ("validation record (held out, not fitted)\n"
                                "error 0.8123 -> 0.2345")
    assert fig.axes[0].get_title() == ("estimation record (fitted)\nerror "
                                       f"{res.initial.metric:.4g} -> {res.final.metric:.4g}")
    # without a validation record: one column, as before
    figures.clear()
    loop_report._plot_fit(loop_result, tmp_path)
    assert len(figures[0].axes) == ny


def test_innovation_axes_carry_units(record, tmp_path, figures):
    model = Model.load("mass_spring_damper")
    pb = make_problem(model, record, prior=PriorSpec(scale="magnitude"), noise=NoiseSpec("model"),
                      ukf=UKFOptions(method="rk4"))
    res = estimate(pb, ["k"],
                   fit=FitOptions(particles=4, iterations=1, polish=False, progress=False,
                                  hessian=False, check_discretisation=False))
    figures.clear()
    paths = plot_fit(model, record, res, tmp_path)
    assert [p.name for p in paths] == ["fit_outputs.png", "innovations.png"]
    innovations = figures[1]
    ylabels = [ax.get_ylabel() for ax in innovations.axes]
    assert ylabels == ["ε x [m]", "ε v [m/s]"]
    assert all(ax.get_xlabel() in ("", "t [s]") for ax in innovations.axes)
    assert innovations.axes[-1].get_xlabel() == "t [s]"
    assert re.fullmatch(r"x: \d+\.\d% within ±2σ", innovations.axes[0].get_title())
