"""A confirmation refit whose Fisher scoring does not converge is continued
by another optimiser (issue 26, converged comparisons:
:func:`bondgraph.diagnose.confirm.continued`,
:func:`bondgraph.diagnose.confirm.quasi_newton`).

Reference: the same fit by Fisher scoring run to convergence from the same
start (no iteration limit), and the truth of the simulated record."""

from dataclasses import replace

import numpy as np

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.diagnose import confirm
from bondgraph.diagnose.cases import synthesize
from bondgraph.diagnose.fit import Context, fit_model, model_of
from bondgraph.diagnose.runner import chosen_numerics
from bondgraph.diagnose.settings import LoopSettings

TRUTH = {"m": 2.0, "k": 50.0, "c": 1.5}
START = {"m": 4.0, "k": 20.0, "c": 6.0}


def _context(lines):
    g = mass_spring_damper()
    t = np.arange(1500) * 0.01
    force = 10 * np.sin(2.1 * t) + 8 * np.sin(5.3 * t + 1.0) + 6 * np.sin(11.7 * t + 2.0)
    exp = synthesize(g, g, t, {"F": force}, {}, TRUTH, 4, "msd", "")
    settings = chosen_numerics(g, exp, LoopSettings(params=list(TRUTH)), log=lambda s: None)
    ctx = Context.on(exp, settings, model_of(g), lines.append, False)
    return g, ctx


def test_a_refit_the_scoring_leaves_unconverged_is_finished_by_lbfgsb():
    """Scoring limited to one iteration per run (the fit and each of its two
    continuations) stops far from the optimum; L-BFGS-B over m, k, c from
    there, then one more scoring iteration, converges where the scoring
    without a limit does (NLL within 0.01 nats, every parameter within 0.1
    of its Cramér-Rao std) and within 3 std of the truth."""
    lines: list = []
    g, ctx = _context(lines)
    ref = fit_model(ctx, g, list(TRUTH), START, "reference", iterations=200)
    assert ref.converged
    ctx.settings = replace(ctx.settings, search=replace(ctx.settings.search,
                                                        confirm_iterations=1))
    short = fit_model(ctx, g, list(TRUTH), START, "short", iterations=1)
    assert short.converged is False and short.nll > ref.nll + 10.0
    got = confirm.continued(ctx, g, short, "msd")
    assert any("msd: refit not converged after 3 iterations; continuing with L-BFGS-B" in ln
               for ln in lines), lines
    assert got.converged
    assert abs(got.nll - ref.nll) < 0.01, (got.nll, ref.nll)
    est, want = got.estimates(), ref.estimates()
    for n, v in TRUTH.items():
        assert abs(est[n] - want[n]) < 0.1 * ref.std[n], (n, est[n], want[n], ref.std[n])
        assert abs(est[n] - v) < 3 * ref.std[n], (n, est[n], v, ref.std[n])


def test_lbfgsb_that_gains_nothing_leaves_the_refit_as_it_was():
    """At the converged reference L-BFGS-B gains less than CONTINUE_SLACK:
    quasi_newton returns None (the caller keeps the refit, not converged)."""
    lines: list = []
    g, ctx = _context(lines)
    ref = fit_model(ctx, g, list(TRUTH), START, "reference", iterations=200)
    assert confirm.quasi_newton(ctx, ref, "msd") is None
    assert any("msd: L-BFGS-B over 3 parameters" in ln for ln in lines)


def test_a_declared_fit_on_a_bound_short_of_an_interior_optimum_goes_on_from_it():
    """A declared fit that stopped with the damping on the bottom of its
    box, c = 0.1 in [0.1, 20] (the scoring evaluated there only: the kind
    of stop a projected step makes when the likelihood first falls along
    the bound), is no verdict on the box: the refit with the box opened
    ends inside it (c near 1.5), so the loop refits the declared model in
    the declared boxes from there and goes on from that fit
    (:func:`bondgraph.diagnose.runner._declared_fit_verdict`), logged, with
    no warning about a box. Reference: the fit by Fisher scoring run to
    convergence from START (NLL within 0.01 nats, each parameter within
    0.1 of its Cramér-Rao std) and the truth (3 std)."""
    from bondgraph.diagnose import runner

    lines: list = []
    g, ctx = _context(lines)
    ref = fit_model(ctx, g, list(TRUTH), START, "reference", iterations=200)
    assert ref.converged and not ref.at_bound
    on_box = fit_model(ctx, g, list(TRUTH), {**START, "c": 0.1}, "initial fit", iterations=0)
    assert on_box.at_bound == ["c"] and on_box.nll > ref.nll + 100.0
    got = runner._declared_fit_verdict(ctx, g, on_box, list(TRUTH), [], ["c"])
    assert got is not on_box and not got.at_bound
    assert any("the refit with the box opened ended inside the declared box (c = " in ln
               and "the declared fit goes on from there" in ln for ln in lines), lines
    assert not any("warning: declared fit" in ln for ln in lines), lines
    assert abs(got.nll - ref.nll) < 0.01, (got.nll, ref.nll)
    est, want = got.estimates(), ref.estimates()
    for n, v in TRUTH.items():
        assert abs(est[n] - want[n]) < 0.1 * ref.std[n], (n, est[n], want[n], ref.std[n])
        assert abs(est[n] - v) < 3 * ref.std[n], (n, est[n], v, ref.std[n])
