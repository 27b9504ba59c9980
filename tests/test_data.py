"""Experiment format (bondgraph/data/records.py): loading, every DataError kind with its
line and column, unit conversion, der(u) inputs, save/load round trips."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bondgraph.data.binding import convert
from bondgraph.data.record_io import FORMAT, parse_header, read_table
from bondgraph.data.records import Experiment
from bondgraph.errors import DataError
from bondgraph.numerics.model import Model


@pytest.fixture(scope="module")
def msd():
    return Model.load("mass_spring_damper")


@pytest.fixture(scope="module")
def cvt():
    return Model.load("toy_cvt")


def write(tmp_path: Path, text: str, name: str = "rec.csv", sidecar: dict | None = None) -> Path:
    p = tmp_path / name
    p.write_text(text)
    if sidecar is not None:
        p.with_suffix(".json").write_text(json.dumps({"format": FORMAT, **sidecar}))
    return p


GOOD = "t [s],F [N],x [m],v [m/s]\n0,1,0.0,0\n0.1,1,0.01,0.2\n0.2,2,0.03,0.3\n0.3,2,,0.35\n"


def raises(path, match, line=None, column=None, **kw):
    with pytest.raises(DataError, match=match) as ei:
        Experiment.load(path, **kw)
    err = ei.value
    assert err.path == str(path)
    assert err.line == line, (err.line, str(err))
    assert err.column == column, (err.column, str(err))
    return err


# --------------------------------------------------------------- loading
def test_load_good_file(tmp_path, msd):
    exp = Experiment.load(write(tmp_path, GOOD))
    np.testing.assert_array_equal(exp.t, [0, 0.1, 0.2, 0.3])
    assert list(exp.columns) == ["F", "x", "v"]
    assert exp.units == {"F": "N", "x": "m", "v": "m/s"}
    assert np.isnan(exp["x"][3])  # empty cell = missing sample
    U = exp.inputs_for(msd)
    np.testing.assert_array_equal(U[:, 0], [1, 1, 2, 2])
    Y = exp.outputs_for(msd)
    assert Y.shape == (4, 2)
    np.testing.assert_array_equal(Y[:3, 0], [0.0, 0.01, 0.03])
    assert np.isnan(Y[3, 0]) and Y[3, 1] == 0.35
    text = exp.summary()
    assert "4 samples" in text and "missing" in text and "m/s" in text


def test_header_parsing():
    assert parse_header("v_gnss [m/s]") == ("v_gnss", "m/s")
    assert parse_header(" der(r) [(m/rad)/s] ") == ("der(r)", "(m/rad)/s")
    assert parse_header("throttle [1]") == ("throttle", "1")
    assert parse_header("z") == ("z", None)
    # a unit in parentheses after a space (spreadsheets, loggers); not a name's own parentheses
    assert parse_header("Force (N)") == ("Force", "N")
    assert parse_header("v (km/h)") == ("v", "km/h")
    assert parse_header("speed (filtered)") == ("speed (filtered)", None)
    assert parse_header("y(1)") == ("y(1)", None)


def test_trailing_comma_and_quoted_header(tmp_path):
    # the CED files: quoted names and a comma at the end of every line
    p = write(tmp_path, '"t","u","z",\n0,1,0.5,\n0.02,1,0.6,\n0.04,-1,0.7,\n')
    exp = Experiment.load(p)
    assert list(exp.columns) == ["u", "z"]
    np.testing.assert_array_equal(exp["z"], [0.5, 0.6, 0.7])
    names, arr = read_table(p)
    assert names == ["t", "u", "z"] and arr.shape == (3, 3)


def test_time_in_ms_is_converted(tmp_path):
    exp = Experiment.load(write(tmp_path, "t [ms],F\n0,1\n10,1\n20,1\n"))
    np.testing.assert_allclose(exp.t, [0, 0.01, 0.02])


def test_time_column_names_and_separators(tmp_path):
    """What spreadsheets and data loggers write: ``time``/``Time (s)``/``time_ms`` as the
    first column, units in parentheses, ``;`` or tab separators with decimal commas."""
    exp = Experiment.load(write(tmp_path, "Time (s);Force (N);x (mm)\n0,0;1,5;2\n"
                                          "0,01;1,5;2,5\n0,02;-1,0;3\n"))
    np.testing.assert_array_equal(exp.t, [0.0, 0.01, 0.02])
    np.testing.assert_array_equal(exp["Force"], [1.5, 1.5, -1.0])
    assert exp.units["x"] == "mm"
    exp = Experiment.load(write(tmp_path, "time_ms\tF\n0\t1.5\n10\t2\n20\t3\n", name="b.csv"))
    np.testing.assert_allclose(exp.t, [0.0, 0.01, 0.02])
    # a sidecar naming the time column as the file does; its unit converts
    p = write(tmp_path, "time,F\n0,1\n1,2\n2,3\n", name="c.csv",
              sidecar={"columns": {"time": {"unit": "min"}, "F": {"role": "input"}}})
    exp = Experiment.load(p)
    np.testing.assert_allclose(exp.t, [0.0, 60.0, 120.0])
    # decimal commas only in a file that writes no point: elsewhere a comma is a
    # thousands separator, not a number the reader guesses at
    raises(write(tmp_path, "t;F\n0;1,000.5\n1;2\n", name="d.csv"), "non-numeric cell '1,000.5'",
           line=2, column="F")
    raises(write(tmp_path, "t\tF\n0.0\t1,234\n1.0\t2\n", name="f.csv"),
           "non-numeric cell '1,234'", line=2, column="F")


def test_columns_renamed_as_read_with_their_sidecar_entries(tmp_path):
    """``Experiment.load(path, columns={file: model})``: values, units and the
    sidecar's description (by the file's names) follow the new name; the
    column order is kept."""
    p = write(tmp_path, "t,Current [mA],Voltage\n0,1,3.7\n1,2,3.6\n", name="log.csv",
              sidecar={"columns": {"Voltage": {"unit": "V", "role": "output",
                                               "noise_std": 0.002},
                                   "Current": {"role": "input"}}})
    exp = Experiment.load(p, columns={"Current": "I", "Voltage": "V"})
    assert list(exp.columns) == ["I", "V"]
    np.testing.assert_array_equal(exp["V"], [3.7, 3.6])
    assert exp.units == {"I": "mA", "V": "V"}
    assert exp.roles["I"] == "input" and exp.noise_std == {"V": 0.002}
    raises(p, "no column 'Volt' to rename", line=1, column="Volt", columns={"Volt": "V"})
    raises(p, "time column is not renamed", line=1, column="t", columns={"t": "time"})


def test_a_unit_given_with_the_new_name_replaces_the_files(tmp_path):
    """ANL's D3 dyno files write cm³/s as ``[ccps]``, which pint reads as
    centi-counts per second (1/time): converted to the model's cm³/s the
    column is refused, with the remedy; a unit in brackets after the new
    name (``--columns Fuel=fuel[cm^3/s]``) replaces the file's, and the
    values convert by it (mph to m/s: 0.44704 exactly). A unit pint does not
    know is refused in either place, naming the column."""
    p = write(tmp_path, "Time[s],Fuel[ccps],Spd[mph],x [zzz]\n0,1.5,10,1\n1,2.0,20,2\n")
    raises(p, "unit 'zzz'", line=1, column="x")
    exp = Experiment.load(p, columns={"Fuel": "fuel [cm^3/s]", "Spd[mph]": "v",
                                      "x": "x[mm]"})
    assert exp.units == {"fuel": "cm^3/s", "v": "mph", "x": "mm"}
    np.testing.assert_array_equal(exp["fuel"], [1.5, 2.0])
    np.testing.assert_allclose(convert(exp["v"], exp.units["v"], "m/s"), [4.4704, 8.9408])
    np.testing.assert_allclose(convert(exp["fuel"], "cm^3/s", "l/h"), [5.4, 7.2])
    with pytest.raises(DataError, match=r"'ccps' \(1 / \[time\]\) cannot be converted") as ei:
        convert([1.5], "ccps", "cm^3/s")
    assert "--columns COLUMN=NAME[UNIT]" in str(ei.value)
    raises(p, "unit 'qqq'", line=1, column="Fuel", columns={"Fuel": "fuel [qqq]", "x": "x[m]"})


# ------------------------------------------------------ every error kind
def test_missing_t(tmp_path):
    raises(write(tmp_path, "clock,F\n0,1\n1,2\n"), "first column must be the time 't'",
           line=1, column="clock")
    # 'time' elsewhere than first is a signal, and the first column is not a time
    raises(write(tmp_path, "F,time\n0,1\n1,2\n", name="e.csv"),
           "first column must be the time 't'", line=1, column="F")
    raises(write(tmp_path, "F,t\n0,1\n1,2\n"), "must be the first column", line=1, column="t")


def test_a_file_without_time_column_is_read_at_a_given_interval(tmp_path):
    """Published files often have no time column (Silverbox, CED: "u1,z1,"
    with a trailing comma): with the interval given (``dt``, the command
    line's ``--dt``, or the sidecar's ``dt``) the samples are at k dt; a
    file with a time column must agree with it; without one the error
    names both ways."""
    p = write(tmp_path, '"z1","u1",\n0.5,1,\n0.25,-1,\n0.125,1,\n')
    err = raises(p, "first column must be the time 't'", line=1, column="z1")
    assert "--dt SECONDS" in str(err) and '"dt" in the record\'s JSON sidecar' in str(err)
    exp = Experiment.load(p, dt=0.02, columns={"u1": "F"})
    np.testing.assert_array_equal(exp.t, [0.0, 0.02, 0.04])
    assert list(exp.columns) == ["z1", "F"] and exp.meta["dt"] == 0.02
    np.testing.assert_array_equal(exp["z1"], [0.5, 0.25, 0.125])
    assert exp.meta["columns"]["t"] == {"unit": "s", "role": "time"}
    side = write(tmp_path, "u,y\n1,2\n3,4\n", name="side.csv", sidecar={"dt": 0.5})
    np.testing.assert_array_equal(Experiment.load(side).t, [0.0, 0.5])
    # with a time column, dt must agree with its median step (within 1 %)
    np.testing.assert_array_equal(Experiment.load(write(tmp_path, GOOD), dt=0.1).t,
                                  [0, 0.1, 0.2, 0.3])
    raises(write(tmp_path, GOOD), r"dt = 0.2 s, but the median time step is 0.1 s", dt=0.2)
    for bad in (0.0, -1.0, float("nan")):
        raises(p, "is not a positive number of seconds", dt=bad)


def test_non_numeric_cell(tmp_path):
    raises(write(tmp_path, "t,F,x\n0,1,2\n0.1,1,2\n0.2,abc,2\n"), "non-numeric cell 'abc'",
           line=4, column="F")


def test_nan_and_inf_in_time(tmp_path):
    raises(write(tmp_path, "t,F\n0,1\nnan,1\n0.2,1\n"), "time must be finite", line=3,
           column="t")
    raises(write(tmp_path, "t,F\n0,1\n0.1,1\ninf,1\n"), "time must be finite", line=4,
           column="t")
    raises(write(tmp_path, "t,F\n0,1\n,1\n0.2,1\n"), "empty time cell", line=3, column="t")


def test_nan_inf_in_inputs(tmp_path, msd):
    # role known from the sidecar: rejected at load time
    side = {"columns": {"F": {"unit": "N", "role": "input"}}}
    raises(write(tmp_path, "t,F\n0,1\n0.1,NaN\n0.2,1\n", sidecar=side),
           "inputs must be given at every sample", line=3, column="F")
    raises(write(tmp_path, "t,F\n0,1\n0.1,1\n0.2,\n", name="b.csv", sidecar=side),
           "empty cell", line=4, column="F")
    # inf is never data
    raises(write(tmp_path, "t,F,x\n0,1,0\n0.1,1,-inf\n0.2,1,0\n", name="c.csv"),
           "infinite value", line=3, column="x")
    # role unknown at load time: rejected when used as a model input
    exp = Experiment.load(write(tmp_path, "t,F,x\n0,1,0\n0.1,nan,0\n0.2,1,0\n", name="d.csv"))
    with pytest.raises(DataError, match="inputs must be finite") as ei:
        exp.inputs_for(msd)
    assert (ei.value.line, ei.value.column) == (3, "F")


def test_nan_in_outputs_only_when_missing_not_allowed(tmp_path):
    p = write(tmp_path, "t,F,x\n0,1,0\n0.1,1,NaN\n0.2,1,0\n")
    assert np.isnan(Experiment.load(p)["x"][1])
    raises(p, "missing samples are not allowed", line=3, column="x", allow_missing=False)
    p2 = write(tmp_path, "t,F,x\n0,1,0\n0.1,1,0\n0.2,1,\n", name="e.csv")
    raises(p2, "empty cell", line=4, column="x", allow_missing=False)



def test_the_commands_say_which_output_samples_are_missing(tmp_path, msd):
    """``load_record`` (every command's ``--data``) says, one line per
    output, how many samples are missing and where, instead of leaving the
    gap to be found in the numbers; a complete column says nothing."""
    from bondgraph.cli.common import load_record

    rows = "".join(f"{0.1 * i:.1f},1,{'' if i in (2, 3, 5) else i},{'NaN' if i == 7 else -i}\n"
                   for i in range(9))
    said = []
    exp = load_record(write(tmp_path, "t,F,x,v\n" + rows), msd, said.append)
    assert np.isnan(exp["x"][[2, 3, 5]]).all() and np.isnan(exp["v"][7])
    assert said == [
        "rec.csv: 3 of 9 samples of output 'x' missing (empty or NaN; from t = 0.2 s to 0.5 s): "
        "the filter skips its measurement update there and the errors leave them out",
        "rec.csv: 1 of 9 samples of output 'v' missing (empty or NaN; at t = 0.7 s): the filter "
        "skips its measurement update there and the errors leave it out"]
    said.clear()
    load_record(write(tmp_path, "t,F,x,v\n0,1,0,0\n0.1,1,1,1\n", name="full.csv"), msd,
                said.append)
    assert said == []



def test_the_commands_refuse_an_output_without_information(tmp_path, msd):
    """An output column with no finite sample, or one value throughout
    (a disconnected sensor) with no declared noise level, is refused where
    the record is read, naming the file and the column; a constant column
    whose noise level the sidecar declares stays (it says the output
    stayed within its noise)."""
    from bondgraph.cli.common import load_record

    rows = "".join(f"{0.1 * i:.1f},1,{0.5 if i else ''},{0.1 * i}\n" for i in range(5))
    with pytest.raises(DataError, match=r"output 'x' reads 0.5 m at every sample") as ei:
        load_record(write(tmp_path, "t,F,x [m],v\n" + rows), msd, lambda m: None)
    assert (ei.value.line, ei.value.column) == (1, "x")
    empty = "".join(f"{0.1 * i:.1f},1,,{0.1 * i}\n" for i in range(5))
    with pytest.raises(DataError, match=r"output 'x' has no sample"):
        load_record(write(tmp_path, "t,F,x,v\n" + empty, name="e.csv"), msd, lambda m: None)
    side = {"columns": {"x": {"noise_std": 0.01}}}
    exp = load_record(write(tmp_path, "t,F,x [m],v\n" + rows, name="d.csv", sidecar=side), msd,
                      lambda m: None)
    assert np.nanmax(exp["x"]) == 0.5


def test_non_monotonic_repeated_time_and_gaps(tmp_path):
    raises(write(tmp_path, "t,F\n0,1\n0.2,1\n0.1,1\n0.3,1\n"), "decreasing time", line=4,
           column="t")
    raises(write(tmp_path, "t,F\n0,1\n0.1,1\n0.1,1\n0.2,1\n", name="b.csv"), "repeated time",
           line=4, column="t")
    gap = write(tmp_path, "t,F\n0,1\n0.1,1\n0.2,1\n0.5,1\n0.6,1\n", name="c.csv")
    err = raises(gap, "gap in time", line=5, column="t")
    assert "1.5 x the median step" in str(err)
    assert len(Experiment.load(gap, gap_factor=None)) == 5


def test_unknown_units(tmp_path):
    raises(write(tmp_path, "t,F [furlongz],x\n0,1,0\n0.1,1,0\n"), "unknown unit 'furlongz'",
           line=1, column="F")
    raises(write(tmp_path, "t [parsec],F\n0,1\n0.1,1\n", name="b.csv"), "not a time", line=1,
           column="t")


def test_wrong_dimension(tmp_path, msd):
    # a speed column in N, an input in m/s
    exp = Experiment.load(write(tmp_path, "t,F [N],v [N]\n0,1,0\n0.1,1,0\n"))
    with pytest.raises(DataError, match=r"unit 'N' .* cannot be converted to 'm/s'") as ei:
        exp.outputs_for(msd)
    assert (ei.value.line, ei.value.column) == (1, "v")
    exp = Experiment.load(write(tmp_path, "t,F [m/s],v\n0,1,0\n0.1,1,0\n", name="b.csv"))
    with pytest.raises(DataError, match="cannot be converted to 'N'") as ei:
        exp.inputs_for(msd)
    assert ei.value.column == "F"


def test_missing_columns_the_model_needs(tmp_path, cvt):
    exp = Experiment.load(write(tmp_path, "t,T [N*m],v\n0,1,0\n0.1,1,0\n"))
    with pytest.raises(DataError, match=r"missing column\(s\) 'r' needed by model 'toy_cvt'") as ei:
        exp.inputs_for(cvt)
    assert ei.value.line == 1 and ei.value.column == "r"
    U = exp.inputs_for(cvt, defaults_ok=True)
    np.testing.assert_array_equal(U[:, 1], cvt.u0[1])  # r held at its default
    np.testing.assert_array_equal(U[:, 2], 0.0)  # der(r) of a constant
    assert exp.missing_inputs(cvt) == ["r"]
    # no output column at all
    exp = Experiment.load(write(tmp_path, "t,T\n0,1\n0.1,1\n", name="b.csv"))
    with pytest.raises(DataError, match="no column for any output"):
        exp.outputs_for(cvt)


def test_malformed_rows_and_header(tmp_path):
    raises(write(tmp_path, "t,F\n0,1\n0.1,1,3\n"), "row has 3 cells", line=3, column=None)
    raises(write(tmp_path, "t,F,F\n0,1,1\n0.1,1,1\n", name="b.csv"), "duplicate column",
           line=1, column="F")
    with pytest.raises(DataError, match="no such file"):
        Experiment.load(tmp_path / "absent.csv")
    raises(write(tmp_path, "t,F\n0,1\n", name="c.csv"), "at least 2 samples")


def test_bad_sidecars(tmp_path):
    p = write(tmp_path, GOOD)
    p.with_suffix(".json").write_text('{"format": "other/2"}')
    with pytest.raises(DataError, match="sidecar format is 'other/2'") as ei:
        Experiment.load(p)
    assert ei.value.path.endswith("rec.json")
    # no format at all (a user's {"noise_std": {...}}): how a sidecar begins,
    # and where the misplaced key goes
    p.with_suffix(".json").write_text('{"noise_std": {"x1": 0.0002}}')
    with pytest.raises(DataError, match='no "format": "bondgraph-experiment/1" entry') as ei:
        Experiment.load(p)
    assert "top-level 'noise_std' belong(s) to a column" in str(ei.value)
    p.with_suffix(".json").write_text('{"format": ')
    with pytest.raises(DataError, match="invalid JSON"):
        Experiment.load(p)
    write(tmp_path, GOOD, sidecar={"columns": {"a": {"unit": "m"}}})
    with pytest.raises(DataError, match="the CSV lacks") as ei:
        Experiment.load(p)
    assert ei.value.column == "a"
    write(tmp_path, GOOD, sidecar={"columns": {"x": {"unit": "mm"}}})
    raises(p, "differs from the sidecar", line=1, column="x")
    write(tmp_path, GOOD, sidecar={"columns": {"x": {"role": "measurement"}}})
    with pytest.raises(DataError, match="unknown role 'measurement'"):
        Experiment.load(p)
    write(tmp_path, GOOD, sidecar={"dt": 0.5})
    with pytest.raises(DataError, match="median time step"):
        Experiment.load(p)
    # a column key at the top level would be kept and never read (a user's
    # noise levels left estimated): an error naming where it belongs
    write(tmp_path, GOOD, sidecar={"noise_std": {"x": 0.01}})
    with pytest.raises(DataError, match="'noise_std' at the top level is not read: it belongs "
                                        "to a column") as ei:
        Experiment.load(p)
    assert ei.value.path.endswith("rec.json")


# ------------------------------------------------------- unit conversion
def test_unit_conversion_kmh_to_ms(tmp_path, msd):
    exp = Experiment.load(write(tmp_path, "t,F [kN],x [mm],v [km/h]\n0,1,5,36\n0.1,2,7,72\n"))
    Y = exp.outputs_for(msd)
    np.testing.assert_allclose(Y[:, msd.output_index("v")], [10.0, 20.0], rtol=1e-15)
    np.testing.assert_allclose(Y[:, msd.output_index("x")], [0.005, 0.007], rtol=1e-15)
    np.testing.assert_allclose(exp.inputs_for(msd)[:, 0], [1000.0, 2000.0], rtol=1e-15)


def test_convert_offset_and_revolutions():
    np.testing.assert_allclose(convert([0.0, 100.0], "degC", "K"), [273.15, 373.15])
    np.testing.assert_allclose(convert([60.0], "rpm", "rad/s"), [2 * np.pi])
    np.testing.assert_allclose(convert([50.0], "%", ""), [0.5])
    with pytest.raises(DataError, match="cannot be converted"):
        convert([1.0], "N", "m/s", column="v")


def test_sidecar_unit_used_when_header_has_none(tmp_path, msd):
    p = write(tmp_path, "t,F,v\n0,1,3.6\n0.1,1,7.2\n",
              sidecar={"columns": {"v": {"unit": "km/h", "role": "output", "noise_std": 0.36}}})
    exp = Experiment.load(p)
    assert exp.units["v"] == "km/h" and exp.roles["v"] == "output"
    np.testing.assert_allclose(exp.outputs_for(msd)[:, 1], [1.0, 2.0])
    np.testing.assert_allclose(exp.noise_std_for(msd), [np.nan, 0.1])


# ------------------------------------------------------------- der(u)
def test_derivative_input_from_column_gradient(tmp_path, cvt):
    t = np.arange(0, 2.0001, 0.05)
    r = 0.05 + 0.01 * t ** 2  # dr/dt = 0.02 t
    exp = Experiment.from_arrays(t, {"T": np.full(t.size, 10.0), "r": r})
    U = exp.inputs_for(cvt)
    d = U[:, cvt.input_index("der(r)")]
    # numpy.gradient is exact for a quadratic inside (central differences)
    np.testing.assert_allclose(d[1:-1], 0.02 * t[1:-1], rtol=1e-12, atol=1e-15)
    # an explicit der(r) column wins
    exp2 = Experiment.from_arrays(t, {"T": 10.0, "r": r, "der(r)": 0.02 * t})
    np.testing.assert_array_equal(exp2.inputs_for(cvt)[:, 2], 0.02 * t)


def test_derivative_input_unit_conversion(tmp_path, cvt):
    # r given in mm/rad: der(r) must be in (m/rad)/s, i.e. after conversion
    t = np.arange(0, 1.0001, 0.1)
    exp = Experiment.from_arrays(t, {"T": 1.0, "r": 50.0 + 10.0 * t}, units={"r": "mm/rad"})
    U = exp.inputs_for(cvt)
    np.testing.assert_allclose(U[:, 1], 0.05 + 0.01 * t, rtol=1e-14)
    np.testing.assert_allclose(U[:, 2], 0.01, rtol=1e-12)


# ------------------------------------------------------------ round trip
def test_round_trip_bit_exact(tmp_path, msd):
    rng = np.random.default_rng(7)
    n = 300
    t = np.cumsum(np.full(n, 0.01) + rng.uniform(-1e-9, 1e-9, n))
    y = rng.standard_normal((n, 2)) * np.array([1e-7, 3e5])
    y[rng.integers(0, n, 20), 0] = np.nan
    exp = Experiment.from_arrays(t, model=msd, u=rng.standard_normal((n, 1)), y=y,
                                 x=rng.standard_normal((n, 2)) * 1e-300,
                                 noise_std={"x": 0.002}, meta={"seed": 5, "x0": {"p_mass": 0.0}})
    p = exp.save(tmp_path / "r.csv")
    back = Experiment.load(p)
    np.testing.assert_array_equal(back.t, exp.t)
    assert list(back.columns) == list(exp.columns)
    for c in exp.columns:
        np.testing.assert_array_equal(back.columns[c], exp.columns[c])  # NaN == NaN here
    assert back.meta["seed"] == 5 and back.meta["model"] == "mass_spring_damper"
    assert back.roles["x"] == "output" and back.roles["state.p_mass"] == "state"
    assert back.noise_std == {"x": 0.002}
    np.testing.assert_array_equal(back.outputs_for(msd), exp.outputs_for(msd))


def test_round_trip_at_given_precision(tmp_path):
    t = np.linspace(0, 1, 11)
    v = np.pi * np.arange(11) / 7
    exp = Experiment.from_arrays(t, {"a": v})
    back = Experiment.load(exp.save(tmp_path / "p.csv", precision=6))
    expect = np.array([float(f"{x:.6g}") for x in v])
    np.testing.assert_array_equal(back["a"], expect)
    assert np.abs(back["a"] - v).max() > 0  # 6 digits really lost something


def test_from_arrays_validation(msd):
    with pytest.raises(DataError, match="repeated time"):
        Experiment.from_arrays([0, 1, 1], {"a": [1, 2, 3]})
    with pytest.raises(DataError, match="expected \\(3,\\)"):
        Experiment.from_arrays([0, 1, 2], {"a": [1, 2]})
    with pytest.raises(DataError, match="expected \\(3, 2\\)"):
        Experiment.from_arrays([0, 1, 2], model=msd, y=np.zeros((3, 3)))
    with pytest.raises(DataError, match="unknown unit"):
        Experiment.from_arrays([0, 1, 2], {"a": 1.0}, units={"a": "blorps"})


def test_segment_and_dataframe(tmp_path):
    exp = Experiment.load(write(tmp_path, GOOD))
    seg = exp.segment(1, 3)
    np.testing.assert_array_equal(seg.t, [0.1, 0.2])
    assert seg.meta["segment"] == [1, 3]
    # the sidecar's x0 describes the first sample: a later segment drops it
    exp.meta["x0"], exp.meta["x0_std"] = {"p_mass": 0.3}, {"p_mass": 0.1}
    assert "x0" not in exp.segment(1, 3).meta and "x0_std" not in exp.segment(1, 3).meta
    assert exp.segment(0, 3).meta["x0"] == {"p_mass": 0.3}
    df = exp.to_dataframe()
    assert list(df.columns) == ["t [s]", "F [N]", "x [m]", "v [m/s]"]
