"""Vuong's (1989) test of two non-nested models (the loop's tie rule after
confirmation, :func:`bondgraph.diagnose.accept.vuong_test`): its size under
the null, with white and with serially correlated per-sample terms (the
Newey-West variance), its power, and Akaike's correction; the ties it marks
on confirmed candidates (:func:`bondgraph.diagnose.accept.mark_ties`)."""

from types import SimpleNamespace

import numpy as np
import pytest

from bondgraph.diagnose.accept import mark_ties, vuong_test


def _terms(y, mu):
    """Per-sample NLL of N(mu, 1) at y."""
    return 0.5 * np.log(2 * np.pi) + 0.5 * (y - mu) ** 2


def _ar1(rng, n, rho):
    e = rng.normal(size=n)
    y = np.empty(n)
    y[0] = e[0] / np.sqrt(1 - rho**2)
    for k in range(1, n):
        y[k] = rho * y[k - 1] + e[k]
    return y * np.sqrt(1 - rho**2)     # unit variance


@pytest.mark.parametrize("rho", [0.0, 0.8])
def test_size_under_the_null(rho):
    """y ~ N(0, 1); N(+0.3, 1) and N(−0.3, 1) are equally far from the
    truth: the 5 % test rejects about 5 % of records (with AR(1) data at
    ρ = 0.8 a white-noise variance would reject ~ 30 %)."""
    rng = np.random.default_rng(7)
    rej = []
    for _ in range(300):
        y = _ar1(rng, 2000, rho)
        z, p = vuong_test(_terms(y, 0.3), _terms(y, -0.3), 1, 1)
        rej.append(p < 0.05)
    assert 0.02 <= np.mean(rej) <= 0.10, np.mean(rej)


def test_power_and_hand_formula():
    rng = np.random.default_rng(3)
    y = rng.normal(0.1, 1.0, size=4000)
    z, p = vuong_test(_terms(y, 0.1), _terms(y, -0.3), 1, 1)
    assert z > 5 and p < 1e-6
    # white terms: the statistic is Σd / sqrt(N var d) within the
    # Newey-West variance's small-lag corrections
    d = _terms(y, -0.3) - _terms(y, 0.1)
    ref = d.sum() / np.sqrt(d.size * d.var())
    assert abs(z / ref - 1) < 0.1
    # swapping the models flips the sign
    z2, p2 = vuong_test(_terms(y, -0.3), _terms(y, 0.1), 1, 1)
    assert z2 == pytest.approx(-z) and p2 == pytest.approx(p)


def test_akaike_correction_and_degenerate_cases():
    y = np.random.default_rng(1).normal(size=500)
    la, lb = _terms(y, 0.2), _terms(y, -0.2)
    z0, _ = vuong_test(la, lb, 1, 1)
    z1, _ = vuong_test(la, lb, 3, 1)     # two parameters more: Σd − 2
    # same variance, the sum less k_a − k_b = 2: z0 − z1 = 2 z0 / Σd
    assert z0 - z1 == pytest.approx(2 * z0 / (lb - la).sum(), rel=1e-12)
    assert vuong_test(la, la, 1, 1) == (0.0, 1.0)
    assert all(np.isnan(vuong_test(la[:2], lb[:2], 1, 1)))
    with pytest.raises(ValueError):
        vuong_test(la, lb[:-1], 1, 1)


def _cand(label):
    return SimpleNamespace(label=label, tied=[], confirmed={"lr": 1.0})


def _fit(terms):
    return SimpleNamespace(ukf=SimpleNamespace(nll_terms=np.asarray(terms)[:, None]))


def test_mark_ties_marks_only_indistinguishable_candidates():
    rng = np.random.default_rng(5)
    y = rng.normal(size=3000)
    lead, near, far = _cand("a @ x"), _cand("b @ x"), _cand("c @ y")
    conf = [(lead, _fit(_terms(y, 0.25)), 1), (near, _fit(_terms(y, -0.25)), 1),
            (far, _fit(_terms(y, 1.0)), 1)]
    assert mark_ties(conf, 0.05) == ["b @ x"]
    assert lead.tied == ["b @ x"] and far.tied == [] and "tie_p" in near.confirmed
    assert near.confirmed["tie_p"] >= 0.05 and "tie_p" not in far.confirmed
    assert mark_ties(conf, 0.0) == []


def test_report_names_the_tie_beside_the_accepted_effect():
    """report.md says which confirmed candidates the record could not tell
    from the accepted one (Step.tied)."""
    from bondgraph.diagnose.result import Step
    from bondgraph.report.loop_report import _md_accepted

    step = Step("source_lag", "force", "nrmse", 0.3, 0.1, 10.0, 5.0, 22.0, 14.0, 3.0, 1.0,
                {"source_lag.force.tau": {"estimate": 0.064, "std": 0.0001}}, 12.0, 1e-4,
                tied=["sensor_lowpass @ v_last"])
    final = SimpleNamespace(estimates={"source_lag.force.tau": 0.064},
                            std={"source_lag.force.tau": 0.0001})
    text = "\n".join(_md_accepted(SimpleNamespace(steps=[step], final=final)))
    assert "cannot tell source_lag @ force from sensor_lowpass @ v_last" in text
    step.tied = []
    text = "\n".join(_md_accepted(SimpleNamespace(steps=[step], final=final)))
    assert "cannot tell" not in text
