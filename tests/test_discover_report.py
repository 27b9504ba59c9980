"""The report shows the reconstruction (issue 29): the DiscoveryPlot on
the loop's result (bondgraph/diagnose/discover/effect.discovery_plot), its
plot and its section of report.md (bondgraph/report/loop_report.py)."""

import numpy as np

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.diagnose.discover.effect import discover_effect, discovery_plot
from bondgraph.report.loop_report import DISCOVERY_PNG, _md_discovery, plot_discovery
from test_discover import C, truth


def test_the_plot_shows_the_reconstruction_against_the_law_evaluated_independently(tmp_path):
    rec, x, v, d_true = truth("cubic")
    disc = discover_effect(mass_spring_damper(), rec, "v", params={"c": C})
    dp = discovery_plot(disc)
    r = disc.reconstruction
    np.testing.assert_array_equal(dp.d, r.d)
    np.testing.assert_array_equal(dp.d_std, r.d_std)
    # the law by hand: Σ c_k b_k with numpy on the reconstruction's variables
    q, vf = r.variables["q_spring"], r.variables["v.f"]
    basis = {"q_spring^3": q ** 3, "q_spring^5": q ** 5, "q_spring": q, "v.f": vf,
             "|v.f|·v.f": np.abs(vf) * vf, "v.f^3": vf ** 3, "1": np.ones_like(q)}
    # the saturation v/(1 + |v/s|), s the RMS of v over the regression's
    # samples (2 % trimmed at each end; law.dictionary): a term that lowers
    # the declared damping, kept since the R part is judged with the damper
    cut = int(round(0.02 * vf.size))
    s_v = float(np.sqrt(np.mean(vf[cut:vf.size - cut] ** 2)))
    basis[f"v.f/(1+|v.f/{s_v:.3g}|)"] = vf / (1 + np.abs(vf / s_v))
    terms = disc.passivity.law.terms
    assert terms and all(tm.name in basis for tm in terms), [tm.name for tm in terms]
    want = sum(tm.coef * basis[tm.name] for tm in terms)
    np.testing.assert_allclose(dp.law, want, rtol=1e-12, atol=1e-12)
    assert "q_spring^3" in dp.text and not dp.accepted
    assert "storage: spring" in dp.passivity
    assert plot_discovery(dp, tmp_path / DISCOVERY_PNG) == DISCOVERY_PNG
    assert (tmp_path / DISCOVERY_PNG).stat().st_size > 10_000

    class Result:
        discovery = dp

    md = "\n".join(_md_discovery(Result()))
    assert f"![{DISCOVERY_PNG}]({DISCOVERY_PNG})" in md and dp.text in md
