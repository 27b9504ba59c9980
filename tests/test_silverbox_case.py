"""The Silverbox loop case (bondgraph/catalog/cases.py): registered through
the entry points, its declared linear graph against the hand-derived
equations, its record against an independent read of the .mat file
(scipy.io.loadmat), and its free-run error metric against a scipy
simulation of the same linear model."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.io import loadmat
from scipy.signal import lsim

from bondgraph.catalog import cases as C
from bondgraph.catalog.benchmarks import SILVERBOX_DEFAULTS, silverbox_linear
from bondgraph.data import datasets as D
from bondgraph.diagnose.cases import get_case, registered_cases
from bondgraph.numerics.model import Model

DATA = D.default_data_dir()
pytestmark = [
    pytest.mark.data,
    pytest.mark.skipif(DATA is None or not (DATA / "silverbox").is_dir(),
                       reason="Silverbox data absent (../shared/data/silverbox)"),
]


def test_case_is_registered_and_its_record_is_the_training_block():
    """The record against an independent read of the .mat file: V1 and V2 at
    the samples, V2 missing between them, and V1 between samples the
    band-limited interpolation (zero-padded real FFT of the whole record,
    numpy.fft) within 1 µV."""
    assert "silverbox" in registered_cases()
    case = get_case("silverbox")
    kind, target = case.true_effect
    assert (kind, target) == ("cubic_stiffness", "spring")
    # the noise intensities are estimated with the physical parameters
    assert case.params == ["m", "d", "k", "q_F", "sigma_y"]
    opts = case.settings.ukf
    assert (opts.method, opts.substeps, opts.hold) == ("rk4", 1, "linear")
    rec = case.record()
    raw = loadmat(str(DATA / "silverbox" / "SNLS80mV.mat"))
    V1, V2 = raw["V1"].ravel(), raw["V2"].ravel()
    tr = slice(40650, 105712)
    u_all = V1 - V1[tr].mean()
    n, r = C.SILVERBOX_WINDOW, C.SILVERBOX_UPSAMPLE
    assert r == 2 and len(rec.t) == r * (n - 1) + 1
    np.testing.assert_allclose(rec["V1"][::r], u_all[tr][:n], atol=1e-12)
    np.testing.assert_allclose(rec["V2"][::r], V2[tr][:n] - V2[tr].mean(), atol=1e-12)
    assert np.isnan(rec["V2"][1::r]).all()
    spec = np.fft.rfft(u_all)
    fine = np.fft.irfft(np.concatenate([spec, np.zeros(u_all.size // 2)]), 2 * u_all.size) * 2
    np.testing.assert_allclose(rec["V1"][1::r], fine[2 * 40650 + 1: 2 * (40650 + n - 1): 2],
                               atol=1e-6)
    assert rec.t[1] - rec.t[0] == pytest.approx(2**14 / 1e7 / r, rel=1e-9)


def test_declared_graph_is_the_linear_mass_spring_damper():
    m = Model.from_graph(silverbox_linear())
    rng = np.random.default_rng(0)
    x = rng.normal(size=(10, 2)) * [1e-4, 0.1]
    u = rng.normal(size=(10, 1)) * 0.05
    mm, d, k = SILVERBOX_DEFAULTS["m"], SILVERBOX_DEFAULTS["d"], SILVERBOX_DEFAULTS["k"]
    dx = m.f(x, u, m.theta0)
    np.testing.assert_allclose(dx[:, 0], u[:, 0] - k * x[:, 1] - d * x[:, 0] / mm, rtol=1e-12)
    np.testing.assert_allclose(dx[:, 1], x[:, 0] / mm, rtol=1e-12)
    np.testing.assert_allclose(m.h(x, u, m.theta0)[:, 0], x[:, 1], rtol=1e-14)


def test_arrow_error_of_the_declared_defaults_against_scipy():
    """The metric's free run (RK4 on the case's grid, V1 held linearly over
    each grid interval, x0 fitted on the first 50 samples) against scipy's
    exact lsim of 1/(m s² + d s + k) with the same input linearly
    interpolated (``interp=True``) from rest (the arrow starts after 100
    samples of zero excitation), RMS over the measured samples: the errors
    [mV] agree within 0.5 %."""
    m = Model.from_graph(silverbox_linear())
    ours = C.silverbox_sim_error(m, m.theta0, "test_arrow")
    t, u, y = C._silverbox_arrays("test_arrow")
    mm, d, k = SILVERBOX_DEFAULTS["m"], SILVERBOX_DEFAULTS["d"], SILVERBOX_DEFAULTS["k"]
    _, ys, _ = lsim(([1.0], [mm, d, k]), u, t - t[0], interp=True)
    e = (ys - y)[50 * C.SILVERBOX_UPSAMPLE:]
    ref = 1e3 * np.sqrt(np.nanmean(e**2))
    assert 10.0 < ours < 20.0
    assert ours == pytest.approx(ref, rel=0.005)
