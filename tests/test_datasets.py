"""Loaders of the public benchmarks (bondgraph/data/datasets.py), checked against
the numbers in /work/shared/data/*/README.md and independent readers
(scipy.io.loadmat, numpy), plus checksum verification and the pooch fetch
path driven by a local downloader (no network here)."""

from __future__ import annotations

import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
from scipy.io import loadmat
from scipy.signal import lfilter

from bondgraph.data import datasets as D
from bondgraph.errors import DataError

DATA = D.default_data_dir()
pytestmark = [
    pytest.mark.data,
    pytest.mark.skipif(DATA is None or not (DATA / "emps").is_dir(),
                       reason="real data sets absent: set BONDGRAPH_DATA or provide "
                              "../shared/data beside the project (see bondgraph/data/datasets.py)"),
]


# ---------------------------------------------------------------------- EMPS
@pytest.fixture(scope="module")
def emps_est():
    return D.emps("estimation")


@pytest.fixture(scope="module")
def emps_val():
    return D.emps("validation")


def test_emps_size_sampling_constants(emps_est, emps_val):
    for exp in (emps_est, emps_val):
        assert len(exp) == 24841
        assert exp.t[0] == 0.0 and exp.t[-1] == pytest.approx(24.84, abs=1e-6)
        assert np.abs(np.diff(exp.t) - 1e-3).max() < 5e-8  # 1 ms, +-2e-8 s jitter
        assert exp.units == {**{"qm": "m", "qg": "m", "vir": "V", "tau": "N"},
                             **({"pulses_N": "1"} if "pulses_N" in exp else {})}
        c = exp.meta["constants"]
        assert c["gtau"] == pytest.approx(35.15065, rel=1e-6)
        assert c["kp"] == pytest.approx(160.18, rel=1e-12)
        assert c["kv"] == pytest.approx(243.45, rel=1e-12)
        np.testing.assert_allclose(exp["tau"], c["gtau"] * exp["vir"], rtol=1e-15)
        assert exp.roles["qm"] == "output" and exp.roles["vir"] == "input"
        assert np.abs(exp["vir"]).max() <= 10.0  # drive saturates at +-10 V
    # the reference trajectory is the same in both files (to rounding, 7e-16 m)
    np.testing.assert_allclose(emps_est["qg"], emps_val["qg"], rtol=1e-9, atol=1e-15)


def test_emps_pulses(emps_val):
    p = emps_val["pulses_N"]
    onsets = np.flatnonzero((p[1:] > 0) & (p[:-1] == 0)) + 1
    assert onsets.size == 25
    assert emps_val.t[onsets[0]] == pytest.approx(0.344, abs=1e-3)
    assert np.diff(emps_val.t[onsets]) == pytest.approx(np.ones(24), abs=2e-3)
    assert np.unique(p).tolist() == [0.0, 5.0]
    assert np.count_nonzero(p) == pytest.approx(25 * 500, abs=25)
    # vir steps up by about +5 V at each pulse onset
    jumps = emps_val["vir"][onsets] - emps_val["vir"][onsets - 1]
    assert np.median(jumps) == pytest.approx(5.0, abs=0.5)


def test_emps_matches_csv_conversion_and_mat(emps_est):
    # independent readers: numpy on the CSV conversion, scipy on the .mat
    arr = np.genfromtxt(DATA / "emps" / "emps_estimation.csv", delimiter=",", names=True)
    for c in ("qm", "qg", "vir"):
        np.testing.assert_allclose(emps_est[c], arr[c], rtol=1e-9, atol=1e-15)
    m = loadmat(DATA / "emps" / "DATA_EMPS.mat")
    np.testing.assert_array_equal(emps_est["qm"], m["qm"].ravel())


def test_emps_from_csv_only(tmp_path):
    shutil.copy(DATA / "emps" / "emps_validation_pulses.csv", tmp_path)
    exp = D.emps("validation", data_dir=tmp_path)
    assert Path(exp.meta["source"]["file"]).name == "emps_validation_pulses.csv"
    assert len(exp) == 24841 and "pulses_N" in exp
    assert exp.meta["constants"] == D.EMPS_CONSTANTS


# ----------------------------------------------------------------------- CED
# README table, as printed: run -> RMS(z), RMS error of H(z) u, of |H(z) u|
CED_README = {
    "prbs_1": ("1.503", "2.10", "0.166"),
    "prbs_2": ("3.329", "4.00", "1.14"),
    "prbs_3": ("0.553", "0.906", "0.246"),
    "unif_11": ("0.672", "1.36", "1.18"),
    "unif_12": ("1.119", "1.41", "1.37"),
}
# report eq. (9): H(z) = 0.0414 / (z^3 - 2.6011 z^2 + 2.4060 z - 0.7823)
EQ9_B = [0.0, 0.0, 0.0, 0.0414]
EQ9_A = [1.0, -2.6011, 2.4060, -0.7823]


def rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


def as_printed(value: float, printed: str) -> str:
    return f"{value:.{len(printed.split('.')[1])}f}"


@pytest.mark.parametrize("run", list(CED_README))
def test_ced_runs_against_readme(run):
    exp = D.ced(run)
    assert len(exp) == 500 and exp.dt == 0.02
    np.testing.assert_allclose(np.diff(exp.t), 0.02, rtol=1e-12)
    y = lfilter(EQ9_B, EQ9_A, exp["u"])
    got = (rms(exp["z"]), rms(exp["z"] - y), rms(exp["z"] - np.abs(y)))
    assert [as_printed(g, p) for g, p in zip(got, CED_README[run])] == list(CED_README[run])


def test_ced_u1_numbers_exactly_as_quoted():
    exp = D.ced("u1")
    y = lfilter(EQ9_B, EQ9_A, exp["u"])
    assert round(rms(exp["z"]), 3) == 1.503
    assert round(rms(exp["z"] - y), 2) == 2.10
    assert round(rms(exp["z"] - np.abs(y)), 3) == 0.166
    assert round(rms(exp["z"][400:] - np.abs(y[400:])), 3) == 0.158
    # amplitude 1 PRBS with a clock of 5 samples
    assert np.unique(exp["u"]).tolist() == [-1.0, 1.0]
    runs = np.diff(np.flatnonzero(np.diff(exp["u"]) != 0))
    assert np.all(runs % 5 == 0)


def test_ced_csv_matches_mat():
    m = loadmat(DATA / "ced" / "DATAUNIF.MAT")
    exp = D.ced("unif_12")
    np.testing.assert_allclose(exp["u"], m["u12"].ravel(), atol=5e-5)
    np.testing.assert_allclose(exp["z"], m["z12"].ravel(), atol=5e-5)
    assert exp.meta["split"]["train"] == [0, 400]
    all_runs = D.ced_runs()
    assert list(all_runs) == list(D.CED_RUNS)


def test_ced_mat_fallback(tmp_path):
    shutil.copy(DATA / "ced" / "DATAPRBS.MAT", tmp_path)
    exp = D.ced("prbs_1", data_dir=tmp_path)
    assert Path(exp.meta["source"]["file"]).suffix == ".MAT"
    assert round(rms(exp["z"]), 3) == 1.503


# ------------------------------------------------------------ Camry, EPA
@pytest.mark.parametrize("test,rows,miles,fuel", [
    ("61811011", 3378, 14.93, 1546), ("61811012", 1404, 7.48, 733),
    ("61811013", 1575, 20.51, 1369), ("61811014", 1320, 16.04, 1804)])
def test_camry_against_readme(test, rows, miles, fuel):
    df = D.camry_dyno(test)
    assert len(df) == rows
    assert np.all(np.diff(df["Time[s]"]) == 1.0)  # 1 Hz
    assert df["Dyno_Spd[mph]"].sum() / 3600.0 == pytest.approx(miles, abs=0.006)
    assert df["Eng_FuelFlow_Direct_DI[ccps]"].sum() == pytest.approx(fuel, abs=0.6)
    np.testing.assert_allclose(df["v [m/s]"], df["Dyno_Spd[mph]"] * 0.44704)
    assert df.attrs["cycle"] == D.CAMRY_TESTS[test]


def test_camry_us06_peak_and_short_id():
    assert D.camry_dyno(14)["Dyno_Spd[mph]"].max() == pytest.approx(80.5, abs=0.05)


def test_epa_table_against_readme():
    df = D.epa_test_cars()
    assert df.shape == (4397, 67)
    assert df["Test Category"].value_counts().to_dict() == {
        "FTP": 1818, "HWY": 1576, "US06": 411, "CD": 319, "SC03": 273}
    tt = df["Tested Transmission Type"]
    assert (tt == "Continuously Variable").sum() == 499
    assert tt.str.startswith("Selectable Continuously Variable").sum() == 222
    si = D.road_load_si(df)
    row = si[si["Represented Test Veh Model"] == "CAMRY XLE/XSE"].iloc[0]
    assert row["A_target [N]"] == pytest.approx(4.44822 * row["Target Coef A (lbf)"], rel=1e-5)
    assert row["B_target [N/(m/s)]"] == pytest.approx(9.9503 * row["Target Coef B (lbf/mph)"],
                                                      rel=1e-4)
    assert row["C_target [N/(m/s)^2]"] == pytest.approx(
        22.258 * row["Target Coef C (lbf/mph**2)"], rel=1e-4)
    cam = df[(df["Represented Test Veh Model"] == "CAMRY XLE/XSE")]
    assert cam["Target Coef A (lbf)"].between(26.5, 32.53).all()
    assert cam["Equivalent Test Weight (lbs.)"].between(3625, 3750).all()


# --------------------------------------------------------------- checksums
def test_checksums_of_local_files_match_registry():
    for key, ds in D.DATASETS.items():
        for name, df in ds.files.items():
            p = D.find_local(key, name)
            if p is not None:
                assert D.sha256(p) == df.sha256, p


def test_corrupted_copy_raises_naming_the_file(tmp_path):
    (tmp_path / "emps").mkdir()
    bad = tmp_path / "emps" / "DATA_EMPS.mat"
    data = bytearray((DATA / "emps" / "DATA_EMPS.mat").read_bytes())
    data[5000] ^= 0xFF
    bad.write_bytes(bytes(data))
    with pytest.raises(DataError, match="SHA-256 mismatch") as ei:
        D.emps(data_dir=tmp_path)
    assert ei.value.path == str(bad)
    # a knowingly modified CSV is accepted with verify=False
    (tmp_path / "ced").mkdir()
    src = (DATA / "ced" / "DATAPRBS.csv").read_text()
    mod = tmp_path / "ced" / "DATAPRBS.csv"
    mod.write_text(src.replace("0.031746,1,", "0.031747,1,", 1))
    with pytest.raises(DataError, match="SHA-256 mismatch") as ei:
        D.ced("prbs_1", data_dir=tmp_path)
    assert ei.value.path == str(mod)
    assert D.ced("prbs_1", data_dir=tmp_path, verify=False)["z"][0] == 0.031747


def test_explicit_folder_without_files(tmp_path, monkeypatch):
    with pytest.raises(DataError, match="none of DATA_EMPS.mat, emps_estimation.csv"):
        D.emps(data_dir=tmp_path)
    with pytest.raises(DataError, match="does not exist"):
        D.emps(data_dir=tmp_path / "nowhere")
    # BONDGRAPH_DATA is a local folder too
    (tmp_path / "ced").mkdir()
    shutil.copy(DATA / "ced" / "DATAUNIF.csv", tmp_path / "ced")
    monkeypatch.setenv(D.ENV_DATA, str(tmp_path))
    assert D.ced("unif_11").meta["source"]["file"].startswith(str(tmp_path))
    with pytest.raises(DataError, match="none of DATAPRBS.csv"):
        D.ced("prbs_1")


# ------------------------------------------- the pooch fetch path, offline
def _zip_downloader(zpath, calls):
    def download(url, output_file, pooch_obj):
        calls.append(url)
        shutil.copy(zpath, output_file)
    return download


def test_fetch_archive_verifies_members(tmp_path, monkeypatch):
    z = tmp_path / "EMPS.zip"
    with zipfile.ZipFile(z, "w") as zf:  # publisher layout: a folder in the zip
        for n in ("DATA_EMPS.mat", "DATA_EMPS_PULSES.mat"):
            zf.write(DATA / "emps" / n, f"EMPS/{n}")
    calls = []
    monkeypatch.delenv(D.ENV_DATA, raising=False)
    monkeypatch.setattr(D, "default_data_dir", lambda: None)  # nothing local
    exp = D.emps("validation", cache=tmp_path / "cache", downloader=_zip_downloader(z, calls))
    assert calls == [D.DATASETS["emps"].files["DATA_EMPS_PULSES.mat"].url]
    assert "nonlinearbenchmark.org" in calls[0] and calls[0].endswith("EMPS.zip")
    assert len(exp) == 24841 and ".unzip" in exp.meta["source"]["file"]
    # a corrupted member is named
    z2 = tmp_path / "bad.zip"
    raw = bytearray((DATA / "emps" / "DATA_EMPS.mat").read_bytes())
    raw[-10] ^= 0x01
    with zipfile.ZipFile(z2, "w") as zf:
        zf.writestr("EMPS/DATA_EMPS.mat", bytes(raw))
    with pytest.raises(DataError, match="SHA-256 mismatch") as ei:
        D.emps("estimation", cache=tmp_path / "cache2", downloader=_zip_downloader(z2, []))
    assert ei.value.path.endswith("DATA_EMPS.mat") and "cache2" in ei.value.path


def test_fetch_single_file_checked_by_pooch(tmp_path):
    good = DATA / "epa_test_car_list_2022" / "22-tstcar.csv"
    p = D.fetch("epa", "22-tstcar.csv", cache=tmp_path / "a",
                downloader=_zip_downloader(good, []))
    assert D.sha256(p) == D.DATASETS["epa"].files["22-tstcar.csv"].sha256
    junk = tmp_path / "junk.csv"
    junk.write_text("not the EPA file\n")
    with pytest.raises(DataError, match="failed its checksum") as ei:
        D.fetch("epa", "22-tstcar.csv", cache=tmp_path / "b",
                downloader=_zip_downloader(junk, []))
    assert ei.value.path.endswith("22-tstcar.csv")
    with pytest.raises(DataError, match="local conversion, not published"):
        D.fetch("emps", "emps_estimation.csv", cache=tmp_path / "c")


def test_every_published_file_has_a_url_and_checksum():
    for ds in D.DATASETS.values():
        assert ds.landing.startswith("https://") and ds.citation
        for df in ds.files.values():
            assert len(df.sha256) == 64
            assert df.url is None or df.url.startswith("https://")
