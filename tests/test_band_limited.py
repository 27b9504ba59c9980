"""A band-limited input (content up to where the linear hold misses its values
between samples, as Silverbox's V1): detected from the record
(``discretise.band_limits``), and the record filtered on a grid twice as
fine with the input interpolated band-limited (``cli.common.band_limited_record``,
``Experiment.on_finer_grid``).

References: the exact values of sinusoids between their samples; a
mass-spring-damper driven by a multisine, simulated by scipy's solve_ivp from
the continuous input (the truth between samples), estimated within 3
Cramér-Rao std by default where the linear hold is tens of std off."""

import json

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph.cli.main import main
from bondgraph.data.records import Experiment
from bondgraph.inference.discretise import (
    BandLimit,
    band_limited_midpoints,
    band_limits,
    input_holds,
)

DT = 0.01
#: a multisine with content to 0.4 Nyquist: 12 lines between 1 and 20 Hz at 100 Hz
FREQS = np.linspace(1.0, 20.0, 12)
PHASES = np.random.default_rng(4).uniform(0.0, 2 * np.pi, FREQS.size)


def multisine(t):
    return sum(np.sin(2 * np.pi * f * t + p) for f, p in zip(FREQS, PHASES)) / 3.0


def test_midpoints_are_the_signal_between_samples():
    t = np.arange(2000) * DT
    u = multisine(t)
    mid = band_limited_midpoints(u)
    exact = multisine(t[:-1] + DT / 2)
    inner = slice(50, -50)
    # the default Kaiser-windowed sinc of resample_poly: 0.5 % of the std at
    # worst up to 0.4 Nyquist, 0.1 % RMS
    assert np.max(np.abs(mid - exact)[inner]) < 5e-3 * np.std(u)
    assert np.sqrt(np.mean((mid - exact)[inner] ** 2)) < 1e-3 * np.std(u)
    lin = 0.5 * (u[:-1] + u[1:])
    assert np.sqrt(np.mean((lin - exact)[inner] ** 2)) > 0.05 * np.std(u)   # the linear hold's


def test_band_limits_tell_a_band_limited_signal_from_noise_and_slow_signals():
    t = np.arange(4000) * DT
    rng = np.random.default_rng(0)
    cases = {"ms": multisine(t), "noisy": np.sin(0.5 * t) + 0.3 * np.sin(2.3 * t)
             + 0.05 * rng.normal(size=t.size), "slow": np.sin(0.5 * t)}
    u = np.column_stack(list(cases.values()))
    names = list(cases)
    lims = {b.name: b for b in band_limits(t, u, names, input_holds(u, names))}
    assert lims["ms"].band_limited and lims["ms"].midpoint > 0.08
    assert lims["ms"].near_nyquist < 1e-3
    # white noise jumps from sample to sample: held zero-order, not interpolated
    assert "noisy" not in lims
    assert not BandLimit("noisy", 0.2, 0.5).band_limited      # content up to Nyquist
    assert not lims["slow"].band_limited and lims["slow"].midpoint < 0.01
    # a staircase (zero-order hold) is not interpolated; nor a short record
    stairs = np.repeat(rng.normal(size=100), 40)[:, None]
    assert band_limits(t, stairs, ["s"], input_holds(stairs, ["s"])) == []
    assert band_limits(t[:50], u[:50], names, input_holds(u[:50], names)) == []
    assert "band-limited" in BandLimit("V1", 0.2, 1e-5).describe()


def test_the_finer_grid_keeps_the_samples_and_misses_the_outputs():
    t = np.arange(5) * 0.5
    rec = Experiment.from_arrays(t, {"F": np.arange(5.0), "x": np.ones(5)},
                                 roles={"F": "input", "x": "output"}, name="r")
    rec.meta["dt"] = 0.5
    fine = rec.on_finer_grid({"F": np.arange(4) + 0.25}, linear=["F"], note="why")
    np.testing.assert_array_equal(fine.t, np.arange(9) * 0.25)
    np.testing.assert_array_equal(fine["F"][::2], np.arange(5.0))
    np.testing.assert_array_equal(fine["F"][1::2], np.arange(4) + 0.25)
    assert np.isnan(fine["x"][1::2]).all() and (fine["x"][::2] == 1).all()
    assert fine.dt == 0.25 and fine.meta["columns"]["F"]["hold"] == "linear"
    assert fine.name == "r" and fine.meta["finer_grid"]["note"] == "why"


@pytest.fixture(scope="module")
def msd_multisine(tmp_path_factory):
    """m 0.5 kg, k 400 N/m, c 2 N s/m (resonance 4.5 Hz) driven by the
    multisine (to 20 Hz at 100 Hz: ω·dt up to 1.26), x measured (noise
    0.025 mm), 5 s; solve_ivp from the continuous force."""
    m, k, c = 0.5, 400.0, 2.0
    t = np.arange(501) * DT
    sol = solve_ivp(lambda s, z: [z[1], (multisine(s) - k * z[0] - c * z[1]) / m],
                    (0, t[-1]), [0.0, 0.0], t_eval=t, rtol=1e-10, atol=1e-12)
    x = sol.y[0] + np.random.default_rng(1).normal(0.0, 2.5e-5, t.size)
    d = tmp_path_factory.mktemp("bl")
    rec = Experiment.from_arrays(t, {"F": multisine(t), "x": x}, units={"F": "N", "x": "m"},
                                 roles={"F": "input", "x": "output"},
                                 noise_std={"x": 2.5e-5}, name="ms")
    rec.save(d / "ms.csv")
    (d / "msd.py").write_text(MODEL)
    return d, {"m": m, "k": k, "c": c}


MODEL = '''
from bondgraph import BondGraph


def build():
    g = BondGraph("msd_ms", "mass-spring-damper")
    F = g.input("F", "N", 0.0, "force")
    m = g.param("m", 0.4, "kg", (0.05, 5.0), "mass")
    k = g.param("k", 300.0, "N/m", (10.0, 4000.0), "stiffness")
    c = g.param("c", 1.0, "N*s/m", (0.01, 20.0), "damping")
    v = g.one("v")
    g.connect(g.Se("force", F), v)
    g.connect(v, g.I("mass", m))
    spring = g.C("spring", stiffness=k)
    g.connect(v, spring)
    g.connect(v, g.R("damper", c))
    g.sensor("x", spring.q, unit="m")
    return g
'''


def _fit(d, monkeypatch, capsys, *extra):
    monkeypatch.chdir(d)
    out = "est_" + "_".join(a.strip("-") for a in extra)
    assert main(["estimate", "--model", "msd.py:build", "--data", "ms.csv", "--fit", "sim",
                 "--out", out, "--overwrite", *extra]) == 0
    res = json.loads((d / out / "result.json").read_text())
    return res, capsys.readouterr().err


def test_estimate_interpolates_a_band_limited_input_by_default(msd_multisine, monkeypatch,
                                                               capsys):
    d, truth = msd_multisine
    res, err = _fit(d, monkeypatch, capsys)
    assert "ms: filtered on a grid twice as fine (F: band-limited" in err
    for p in ("m", "k", "c"):
        assert abs(res["estimates"][p] - truth[p]) < 3 * res["std"][p], (p, res["estimates"][p])
    # the sampled grid's linear hold: the damping 17 std off (the refined
    # grid's within 3)
    lin, err = _fit(d, monkeypatch, capsys, "--hold", "linear")
    assert "twice as fine" not in err
    assert abs(lin["estimates"]["c"] - truth["c"]) > 8 * lin["std"]["c"]


def test_the_loop_report_says_the_record_was_filtered_on_a_finer_grid():
    """diagnose.runner.settings_summary (report.json's settings): the finer
    grid's note, when the record has one."""
    from types import SimpleNamespace

    from bondgraph.diagnose.runner import settings_summary
    from bondgraph.diagnose.settings import LoopSettings
    from bondgraph.inference.options import UKFOptions
    from bondgraph.inference.problem import NoiseSpec

    t = np.arange(5) * 0.5
    rec = Experiment.from_arrays(t, {"F": np.arange(5.0), "x": np.ones(5)},
                                 roles={"F": "input", "x": "output"}, name="r")
    fine = rec.on_finer_grid({"F": np.arange(4) + 0.5}, linear=["F"], note="F: band-limited")

    def ctx(record):
        return SimpleNamespace(settings=LoopSettings(params=["k"]), problem=SimpleNamespace(
            noise=NoiseSpec("auto"), ukf=UKFOptions(), record=record))
    assert settings_summary(ctx(fine))["finer_grid"] == {"factor": 2, "interpolated": ["F"],
                                                         "note": "F: band-limited"}
    assert "finer_grid" not in settings_summary(ctx(rec))
