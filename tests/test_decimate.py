"""A record sampled far faster than its model needs, fitted on every K-th
sample (``Experiment.decimated``, ``--decimate K``): inputs held zero-order
averaged over each coarse interval (the same impulse), the others
point-sampled (the likelihood is exactly the subsampled record's).

References: block means and point samples by hand on a non-uniform grid; a
mass with viscous friction driven by a force that changes at every 1 ms
sample, simulated exactly by scipy's zero-order-hold discretisation
(``scipy.signal.cont2discrete``), estimated within 3 Cramér-Rao std on the
record decimated x10, where the point-sampled force (the input's values
at the kept samples only) puts the mass and the friction hundreds of std off."""

import json

import numpy as np
import pytest
from scipy.signal import cont2discrete

from bondgraph.cli.main import main
from bondgraph.data.records import Experiment
from bondgraph.errors import DataError


def test_block_means_and_point_samples_by_hand():
    t = np.array([0.0, 0.1, 0.3, 0.4, 0.6, 0.7, 1.0, 1.1])     # non-uniform
    F = np.array([1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0])
    x = np.arange(8.0)
    rec = Experiment.from_arrays(t, {"F": F, "x": x}, roles={"F": "input", "x": "output"},
                                 name="r")
    rec.meta["dt"] = 0.1
    d = rec.decimated(3, means=["F"])
    # kept samples 0, 3, 6; the sample 7 (less than a whole interval) dropped
    np.testing.assert_array_equal(d.t, [0.0, 0.4, 1.0])
    np.testing.assert_array_equal(d["x"], [0.0, 3.0, 6.0])
    # the value held over [0, 0.4): (1 * 0.1 + 2 * 0.2 + 4 * 0.1) / 0.4; over
    # [0.4, 1.0): (8 * 0.2 + 16 * 0.1 + 32 * 0.3) / 0.6; the last sample's own
    np.testing.assert_allclose(d["F"], [0.9 / 0.4, 12.8 / 0.6, 64.0])
    assert d.meta["columns"]["F"]["hold"] == "zoh"
    assert d.meta["decimated"] == {"factor": 3, "means": ["F"], "samples": 8}
    assert d.name == "r" and d.meta["dt"] == pytest.approx(0.3)
    assert rec.decimated(1) is rec
    with pytest.raises(DataError, match="factor"):
        rec.decimated(0)
    with pytest.raises(DataError, match="2 samples"):
        rec.decimated(8)
    with pytest.raises(DataError, match="no column"):
        rec.decimated(2, means=["G"])


M, C, DT, STD = 2.0, 4.0, 1e-3, 0.005

MODEL = '''
from bondgraph import BondGraph


def build():
    g = BondGraph("cart", "a mass with viscous friction")
    F = g.input("F", "N", 0.0, "force")
    m = g.param("m", 1.0, "kg", (0.1, 20.0), "mass")
    c = g.param("c", 2.0, "N*s/m", (0.01, 50.0), "viscous friction")
    v = g.one("v")
    g.connect(g.Se("force", F), v)
    g.connect(v, g.I("mass", m))
    g.connect(v, g.R("friction", c))
    g.sensor("v", v.f, unit="m/s")
    return g
'''


@pytest.fixture(scope="module")
def fast_record(tmp_path_factory):
    """10 s at 1 kHz: the force a slow sine plus a new random value at every
    sample (held zero-order), the speed exact at the samples (zero-order
    hold discretisation of m v' = F - c v), noise 5 mm/s."""
    n = 10_001
    t = np.arange(n) * DT
    rng = np.random.default_rng(3)
    F = 5.0 * np.sin(2 * np.pi * 0.3 * t) + rng.normal(0.0, 10.0, n)
    Ad, Bd, *_ = cont2discrete((np.array([[-C / M]]), np.array([[1.0 / M]]),
                                np.eye(1), np.zeros((1, 1))), DT, method="zoh")
    v = np.zeros(n)
    for i in range(n - 1):
        v[i + 1] = Ad[0, 0] * v[i] + Bd[0, 0] * F[i]
    d = tmp_path_factory.mktemp("dec")
    Experiment.from_arrays(t, {"F": F, "v": v + rng.normal(0.0, STD, n)},
                           units={"F": "N", "v": "m/s"}, roles={"F": "input", "v": "output"},
                           noise_std={"v": STD}, name="cart").save(d / "cart.csv")
    (d / "cart.py").write_text(MODEL)
    return d


def _fit(d, monkeypatch, capsys, *extra):
    monkeypatch.chdir(d)
    out = "est" + "_".join(a.strip("-") for a in extra)
    assert main(["estimate", "--model", "cart.py:build", "--data", "cart.csv", "--params",
                 "m,c", "--hold", "zoh", "--out", out, "--overwrite", *extra]) == 0
    res = json.loads((d / out / "result.json").read_text())
    return ({p: (e, s) for p, e, s in zip(res["params"], res["estimates"], res["std"])},
            capsys.readouterr().err)


def test_estimate_on_every_tenth_sample(fast_record, monkeypatch, capsys):
    d = fast_record
    full, _ = _fit(d, monkeypatch, capsys)
    dec, err = _fit(d, monkeypatch, capsys, "--decimate", "10")
    assert "cart: decimated x10 (10001 -> 1001 samples" in err
    assert "F averaged over each interval" in err
    for res in (full, dec):
        for p, truth in (("m", M), ("c", C)):
            assert abs(res[p][0] - truth) < 3 * res[p][1], (p, res)
    # a tenth of the speed samples: the noise-limited stds about sqrt(10) wider
    for p in ("m", "c"):
        assert 2.0 < dec[p][1] / full[p][1] < 5.0, (p, dec, full)


def test_point_sampled_force_is_far_off(fast_record, monkeypatch, capsys):
    """The reason for the block mean: the force's value at the kept samples
    alone (held over the 10 ms) misses the impulse of the other nine."""
    d = fast_record
    Experiment.load(d / "cart.csv").decimated(10).save(d / "points.csv")
    monkeypatch.chdir(d)
    assert main(["estimate", "--model", "cart.py:build", "--data", "points.csv", "--params",
                 "m,c", "--hold", "zoh", "--out", "points", "--overwrite"]) == 0
    res = json.loads((d / "points" / "result.json").read_text())
    m, std = res["estimates"][res["params"].index("m")], res["std"][res["params"].index("m")]
    assert abs(m - M) > 10 * std, (m, std)


def test_bad_factors_are_refused(capsys):
    assert main(["estimate", "--model", "m.py:f", "--data", "r.csv", "--decimate", "0"]) == 2
    assert "--decimate: 0 is below 1" in capsys.readouterr().err
    assert main(["loop", "--decimate", "5"]) == 2
    assert "--decimate 5 applies to a --model/--data record" in capsys.readouterr().err


def test_oversampling_reads_the_spectra():
    """A slow multisine (to 1/40 of the sampling rate) is ten times
    oversampled; white noise and a staircase changing at every other
    sample are not; nor is a grid with gaps."""
    from bondgraph.inference.discretise import oversampling

    t = np.arange(20_000) * 1e-3
    slow = np.sin(2 * np.pi * 3.0 * t) + 0.5 * np.sin(2 * np.pi * 25.0 * t + 1.0)
    k, share = oversampling(t, [slow, 0.3 * np.sin(2 * np.pi * 3.0 * t) ** 3])
    assert k == 10 and share < 1e-3
    # content at 25 Hz of 1 kHz sits above 1/20 of the Nyquist frequency
    assert oversampling(t, [slow], factors=(20,))[0] == 1
    noise = np.random.default_rng(0).normal(size=t.size)
    assert oversampling(t, [slow, noise])[0] == 1
    assert oversampling(t, [np.repeat(np.sign(noise[::2]), 2)])[0] == 1
    gaps = t.copy()
    gaps[5000:] += 0.5
    k, share = oversampling(gaps, [slow])
    assert k == 1 and np.isnan(share)


def test_a_protocols_window_keeps_its_time_span():
    """``--init-samples 20`` (EMPS: 20 ms at 1 kHz) with ``--decimate 10``:
    the 3 coarse samples at 0, 10 and 20 ms span the same 19 intervals of
    the original record (ceil(19 / 10) + 1); said in one line."""
    from types import SimpleNamespace

    from bondgraph.cli.common import decimated_window

    said = []
    args = SimpleNamespace(decimate=10, init_samples=20)
    decimated_window(args, said.append)
    assert args.init_samples == 3
    decimated_window(args, said.append)         # once: a second call leaves it
    assert args.init_samples == 3 and len(said) == 1
    assert said == ["--init-samples 20 counts the record's own samples: 3 samples of the record "
                    "decimated x10 span the same time"]
    for k, n, m in ((5, 50, 11), (1, 20, 20), (10, 0, 0), (10, None, None)):
        args = SimpleNamespace(decimate=k, init_samples=n)
        decimated_window(args, said.append)
        assert args.init_samples == m


def test_the_emps_protocols_decimation():
    """On the real EMPS record the block means are the protocol's own
    (``catalog.benchmarks.emps_arrays``: vir averaged over each 5 ms, the
    position point-sampled), up to the record's clock jitter (4e-5 of a
    step) in the time weights."""
    from bondgraph.catalog.benchmarks import emps_arrays
    from bondgraph.data import datasets as D

    data = D.default_data_dir()
    if data is None or not (data / "emps").is_dir():
        pytest.skip("real data sets absent: set BONDGRAPH_DATA or provide ../shared/data")
    exp = D.emps("estimation")
    t, u, y = emps_arrays(exp, decimate=5)
    d = exp.decimated(5, means=["vir"])
    n = t.size
    assert len(d) == n + 1          # and the last sample, whose interval the record lacks
    np.testing.assert_array_equal(d.t[:n], t)
    np.testing.assert_array_equal(d["qm"][:n], y[:, 0])
    np.testing.assert_allclose(d["vir"][:n], u[:, 0], rtol=1e-4, atol=1e-6 * np.ptp(u))


def test_the_report_says_the_record_was_decimated():
    """report.md's and report.html's record sentence (``LoopResult.records``)
    names the decimation the settings record (``runner.settings_summary``)."""
    from bondgraph.diagnose.result import LoopResult

    res = LoopResult("m", "", "emps[0:1864]", "NRMSE", "AIC",
                     {"decimated": {"factor": 10, "means": ["vir"], "samples": 24841}})
    assert res.records() == ("Record: `emps[0:1864]`. The records are every 10th sample of "
                             "their files (vir averaged over each interval, the rest "
                             "point-sampled; --decimate).")
    assert "every" not in LoopResult("m", "", "r", "NRMSE", "AIC", {}).records()


def test_the_loop_fits_the_decimated_record(fast_record, monkeypatch, capsys):
    """``bondgraph loop --model ... --decimate 10``: the declared fit on every
    tenth sample (m, c within 3 std of the truth), the report says so."""
    d = fast_record
    monkeypatch.chdir(d)
    assert main(["loop", "--model", "cart.py:build", "--data", "cart.csv", "--params", "m,c",
                 "--hold", "zoh", "--decimate", "10", "--max-steps", "0", "--out", "loop10",
                 "--overwrite", "--no-plots", "--quiet"]) == 0
    assert "bondgraph loop: cart: decimated x10 (10001 -> 1001 samples" in capsys.readouterr().out
    rep = json.loads((d / "loop10" / "report.json").read_text())
    assert rep["settings"]["decimated"] == {"factor": 10, "means": ["F"], "samples": 10001}
    report = (d / "loop10" / "report.md").read_text()
    assert "every 10th sample of their files (F averaged" in report
    fit = rep["final_fit"]       # the first 75 % of the decimated record
    for p, truth in (("m", M), ("c", C)):
        assert abs(fit["estimates"][p] - truth) < 3 * fit["std"][p], (p, fit["estimates"])


def test_compare_and_track_filter_the_decimated_record(fast_record, monkeypatch, capsys):
    """``bondgraph compare`` and ``bondgraph track`` with ``--decimate 10``:
    each says it and works on the 1001 kept samples (an estimate at the
    truth judged: its free-run error at the noise level)."""
    import csv

    d = fast_record
    monkeypatch.chdir(d)
    assert main(["compare", "cart.py:build", "--data", "cart.csv", "--param", f"m={M}",
                 "--param", f"c={C}", "--hold", "zoh", "--decimate", "10", "--out", "cmp10",
                 "--overwrite"]) == 0
    out = capsys.readouterr()
    assert "cart: decimated x10 (10001 -> 1001 samples" in out.out + out.err
    (rec,) = json.loads((d / "cmp10" / "compare.json").read_text())["records"]
    assert rec["n_obs"] == 1001
    v = Experiment.load(d / "cart.csv").decimated(10)["v"]
    assert rec["metric"] == pytest.approx(STD / np.std(v), rel=0.1)   # the noise, nothing else
    assert main(["track", "--model", "cart.py:build", "--data", "cart.csv", "--track", "c",
                 "--fixed", f"m={M},c={C}", "--hold", "zoh", "--decimate", "10", "--out",
                 "tr10", "--overwrite"]) == 0
    out = capsys.readouterr()
    assert "cart: decimated x10 (10001 -> 1001 samples" in out.out + out.err
    with open(d / "tr10" / "track.csv") as fh:
        assert sum(1 for _ in csv.reader(fh)) == 1001 + 1


def test_ordinals_in_the_lines():
    """``data.records.ordinal``, which the decimation lines use (every 2nd
    sample, not "2th")."""
    from bondgraph.data.records import ordinal

    assert [ordinal(k) for k in (1, 2, 3, 4, 10, 11, 12, 13, 21, 22, 112)] == [
        "1st", "2nd", "3rd", "4th", "10th", "11th", "12th", "13th", "21st", "22nd", "112th"]


def test_a_point_sampled_input_with_fast_content_is_warned_about():
    """``--decimate`` point-samples an input held linearly; where it has
    content above the decimated record's Nyquist frequency (a 40 Hz tone at
    1 kHz, decimated x20: Nyquist 25 Hz) one warning line says it aliases and
    what to do; a slow input gets none."""
    from types import SimpleNamespace

    from bondgraph.cli.common import decimated_record

    t = np.arange(4000) * 1e-3
    model = SimpleNamespace(inputs=["F", "G"], outputs=["x"])
    rec = Experiment.from_arrays(t, {"F": np.sin(2 * np.pi * 40 * t), "G": np.sin(t),
                                     "x": np.cos(t)},
                                 roles={"F": "input", "G": "input", "x": "output"}, name="r")
    said = []
    out = decimated_record(rec, model, SimpleNamespace(decimate=20, hold="linear"), said.append)
    assert len(out) == 200 and said[0].startswith("r: decimated x20 (4000 -> 200 samples")
    (warn,) = said[1:]
    assert warn.startswith("warning: r: input 'F' holds") and "aliases" in warn
