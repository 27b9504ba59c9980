"""The ``camry_cold`` loop case (ANL D3 2018 Camry, 1 Hz): the warm
powertrain fuel-flow graph (catalog.benchmarks.camry_warm, started from the
hot-cycle fit) on the cold-start UDDS bag of test 61811011. Figures measured
on this code (bondgraph loop --case camry_cold, 26 s wall): the cold start
ranks first by far (LR 213.4, next 14.1) and lowers AIC by 211 and the
cold-bag error 0.3152 -> 0.2914 cm³/s, but the loop's error-decrease test
(Diebold-Mariano, z 1.19, p 0.12) rejects it: the Willans line's own errors
dominate the free-run error. On the held-out hot UDDS 61811012 the declared
parameters read 0.409 cm³/s before and 0.408 with the candidate's. Skipped
without ../shared/data."""

import numpy as np
import pytest

from bondgraph.data.datasets import find_local

pytestmark = [pytest.mark.data, pytest.mark.slow]


def _have_data() -> bool:
    try:
        return find_local("camry", "61811011.csv") is not None
    except Exception:
        return False


needs_data = pytest.mark.skipif(not _have_data(), reason="ANL D3 Camry data not in "
                                "../shared/data/anl_d3_camry2018 (BONDGRAPH_DATA)")


@needs_data
def test_hot_fit_and_held_out_error():
    from bondgraph.catalog.benchmarks import CAMRY_HOT_FIT, camry_warm
    from bondgraph.catalog.cases import camry_fuel_error, camry_hot_fit
    from bondgraph.numerics.model import Model

    fit = camry_hot_fit()
    assert fit["eta"] == pytest.approx(CAMRY_HOT_FIT["eta"], rel=1e-3)
    assert fit["Q_idle"] == pytest.approx(CAMRY_HOT_FIT["Q_idle"], rel=1e-2)
    m = Model.from_graph(camry_warm())
    # the hot-cycle model on the held-out hot UDDS and on the cold bag [cm³/s]
    assert camry_fuel_error(m, m.theta0) == pytest.approx(0.4145, abs=0.002)
    assert camry_fuel_error(m, m.theta0, "61811011", 1367) == pytest.approx(0.3401, abs=0.002)


@needs_data
def test_loop_ranks_the_cold_start_first(tmp_path):
    from bondgraph.diagnose.cases import get_case
    from bondgraph.diagnose.runner import run_loop

    case = get_case("camry_cold")
    res = run_loop(case.declared(), case.record(), case.loop_settings())
    assert res.initial.metric == pytest.approx(0.3152, abs=0.002)
    top = res.rankings[0][0]
    assert (top.effect, top.target.name) == ("cold_start", "injector")
    assert top.statistic > 150 and top.statistic > 5 * res.rankings[0][1].statistic
    rej = {r.candidate.label: r for r in res.rejected}
    cs = rej["cold_start @ injector"]
    # confirmed: a large LR; rejected only by the error-decrease test
    assert cs.candidate.confirmed_statistic == pytest.approx(213.4, abs=5.0)
    assert "uncertainty" in cs.reason
    assert not res.steps
    assert np.isfinite(res.final.metric)
    # held out, the hot UDDS 61811012 from a hot start (no excess): the
    # declared fit on the cold bag, and the cold-start candidate's declared
    # parameters (its profile; the confirmation converged in 1 iteration)
    from bondgraph.catalog.cases import camry_fuel_error
    from bondgraph.numerics.model import Model

    m = Model.from_graph(case.declared())
    before = camry_fuel_error(m, m.theta({k: v for k, v in res.initial.estimates.items()
                                          if k in m.params}))
    after = camry_fuel_error(m, m.theta({k: v for k, v in cs.candidate.profile.items()
                                         if k in m.params}))
    assert before == pytest.approx(0.409, abs=0.003)
    assert after == pytest.approx(0.408, abs=0.003)
