"""The threshold (dead-zone) law of a port (issue 29: "a weir flow that
starts above a threshold level"): law.threshold_law, law.dead_zone and
effect.threshold_alternative, on the reconstruction of
tests/test_discover.py's cubic-spring record with d̂ replaced by a
closed-form dead-zone law of the reconstructed velocity."""

import numpy as np
import pytest
import sympy as sp

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.diagnose.discover.effect import (
    Discovery,
    effect_for,
    threshold_alternative,
)
from bondgraph.diagnose.discover.law import (
    THRESHOLD_QUANTILES,
    DiscoverOptions,
    dead_zone,
    threshold_law,
)
from bondgraph.diagnose.discover.passivity import make_passive
from bondgraph.diagnose.discover.reconstruct import ReconstructOptions, reconstruct
from test_discover import C, truth


@pytest.fixture(scope="module")
def rec():
    record, _, _, _ = truth("cubic")
    return reconstruct(mass_spring_damper(), record, "v", params={"c": C},
                       options=ReconstructOptions(q=10.0))


def with_d(r, d):
    """``r`` with d̂ = ``d`` (N,) known exactly (std 1e-9)."""
    return type(r)(**{**r.__dict__, "d": d, "d_std": np.full_like(d, 1e-9)})


@pytest.mark.parametrize("side", [1, -1])
def test_dead_zone_is_max_of_the_shifted_variable(side):
    z = sp.Symbol("z")
    vals = np.linspace(-2.0, 2.0, 41)
    for p in (1.0, 1.5, 2.0):
        fn = sp.lambdify([z], dead_zone(z, 0.3, side, p), "numpy")
        np.testing.assert_allclose(fn(vals), np.maximum(side * (vals - 0.3), 0.0) ** p,
                                   rtol=1e-12, atol=1e-15)


def test_threshold_law_recovers_an_exact_dead_zone_law(rec):
    """d̂ = −3·max(v − a, 0)^1.5, a the 0.7 quantile of v on the fitted
    samples (the grid holds it): found with its threshold, exponent and
    coefficient, residual ~0."""
    v = np.asarray(rec.variables["v.f"], float)
    a = float(np.quantile(v, THRESHOLD_QUANTILES[1]))
    law = threshold_law(with_d(rec, -3.0 * np.maximum(v - a, 0.0) ** 1.5),
                        options=DiscoverOptions(trim=0.0))
    (tm,) = law.terms
    assert tm.name == f"max(v.f-{a:.3g},0)^1.5"
    assert tm.coef == pytest.approx(-3.0, rel=1e-9)
    assert law.rms_residual < 1e-9 * law.rms_d
    fn = sp.lambdify([law.symbols["v.f"]], tm.basis, "numpy")
    np.testing.assert_allclose(fn(v), np.maximum(v - a, 0.0) ** 1.5, rtol=1e-12, atol=1e-15)


def test_a_dissipative_threshold_law_is_kept_and_a_generating_one_refused(rec):
    """At the mass's 1-junction the law's R part is judged with the damper
    (c = 8 N·s/m) in parallel: −3·max(v − a, 0)^1.5 (a > 0) takes power out
    and is kept as the alternative; +300·max(v − a, 0)^2, which outruns the
    damper above v ≈ a + 8·v/300, produces power and is refused (None)."""
    v = np.asarray(rec.variables["v.f"], float)
    a = float(np.quantile(v, THRESHOLD_QUANTILES[1]))
    assert a > 0
    g = mass_spring_damper()
    for d, kept in ((-3.0 * np.maximum(v - a, 0.0) ** 1.5, True),
                    (300.0 * np.maximum(v - a, 0.0) ** 2, False)):
        r = with_d(rec, d)
        law = threshold_law(r)
        rep = make_passive(law, g, r.variables, params={"c": C})
        disc = Discovery(r, law, rep, effect_for(rep.law) if rep.law.terms else None, 1.0)
        alt = threshold_alternative(g, disc, {"c": C})
        assert (alt is not None) == kept, rep.summary()
        if kept:
            assert [pl.part for pl in alt.placement] == ["R"]
