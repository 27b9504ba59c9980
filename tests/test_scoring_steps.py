"""Batched Fisher-scoring steps from several starts
(:func:`bondgraph.inference.fisher.scoring_steps`, used by the structural
candidates' profile starts): each start gets exactly what one iteration of
the unbatched scoring (:func:`bondgraph.diagnose.inference_calls.fisher_fit`
with one iteration) gives it. Reference: that unbatched scoring, start by
start, on the user's mass-spring-damper record simulated by scipy."""

from __future__ import annotations

import numpy as np

from bondgraph.diagnose.inference_calls import fisher_fit, fisher_steps
from bondgraph.inference.options import UKFOptions
from bondgraph.inference.problem import make_problem
from bondgraph.numerics.model import Model
from test_default_numerics import TRUTH, msd_graph
from test_robust_std import _record

PARAMS = ["m", "k", "c"]


def test_batched_steps_equal_one_scoring_iteration_per_start():
    model = Model.from_graph(msd_graph())
    pb = make_problem(model, _record(0, 0.0, n=801),
                      ukf=UKFOptions(method="rk4", substeps=1, hold="linear"))
    idx = [model.param_index(p) for p in PARAMS]
    box = model.bounds(PARAMS)
    starts = []
    for f in ([1.2, 0.9, 1.5], [0.8, 1.1, 0.7], [1.0, 1.0, 1.0], [1.05, 0.97, 3.0]):
        th = model.theta0.copy()
        th[idx] = [TRUTH[p] * x for p, x in zip(PARAMS, f)]
        starts.append(th)
    # the last start also leaves the box along c (the scoring clips it)
    starts[-1][idx[2]] = box[1][2] * 1.5
    got = fisher_steps(pb, starts, idx, box)
    assert len(got) == len(starts)
    moved = 0
    for th, g in zip(starts, got):
        ref = fisher_fit(pb, th, idx, box, 1, log_scale=np.zeros(3, bool), information=False)
        assert g is not None
        np.testing.assert_allclose(g[0], ref[0], rtol=1e-12, atol=0)
        assert abs(g[1] - ref[7]) <= 1e-9 * (1 + abs(ref[7]))
        moved += not np.allclose(g[0][idx], np.clip(th[idx], *box))
    assert moved >= 3          # the steps are taken, not only the starts returned
    # a start where the filter fails is None, the others unchanged
    bad = starts[0].copy()
    bad[idx[0]] = np.nan
    again = fisher_steps(pb, [bad, starts[1]], idx, box)
    assert again[0] is None
    np.testing.assert_allclose(again[1][0], got[1][0], rtol=1e-12, atol=0)
