"""The vehicle's synthetic experiments: registered specs, the 40 Hz noisy
records in the documented experiment format, and the simulate/plot commands
of docs/vehicle.md."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from bondgraph.data.records import Experiment
from bondgraph.errors import DataError
from bondgraph.data.experiments import get_experiment, registered_experiments, run_experiment
from bondgraph.numerics.model import Model
from vehicle_graphs import EXPERIMENTS, MODELS
from vehicle_graphs.vehicle import SENSOR_NOISE, SENSOR_UNITS


@pytest.mark.parametrize("name", sorted(EXPERIMENTS))
def test_registered_spec_is_consistent(name):
    spec = get_experiment(name)
    assert registered_experiments()[name] == EXPERIMENTS[name]
    assert spec.dt == 0.025  # 40 Hz
    assert spec.model in MODELS
    truth = Model.load(spec.truth_model or spec.model)
    filt = Model.load(spec.model)
    assert set(filt.outputs) <= set(truth.outputs)
    assert set(spec.inputs) <= set(truth.inputs)
    assert set(spec.x0) == set(truth.states)
    assert set(spec.params) <= set(truth.params)
    t = np.arange(0, spec.duration, spec.dt)
    for nm, fn in spec.inputs.items():
        vals = np.asarray(fn(t))
        assert vals.shape == t.shape and np.all((vals >= 0) & (vals <= 1)), nm
    # the initial state is an equilibrium of its fast states (no start transient)
    th = truth.theta(spec.params)
    x0 = truth.state(spec.x0)
    u0 = np.array([spec.inputs[n](np.array([0.0]))[0] if n in spec.inputs else truth.u0[j]
                   for j, n in enumerate(truth.inputs)])
    F = truth.f(x0, u0, th)
    for s in ("pitch.p_I", "engine.p_J", "cvt.q_springs"):
        if s in truth.states:
            assert abs(F[truth.state_index(s)]) < 1e-6, (s, F[truth.state_index(s)])
    assert spec.description and spec.seed >= 0


def test_true_parameters_differ_from_defaults():
    spec = get_experiment("vehicle_throttle_steps_high")
    m = Model.load(spec.model)
    diff = [p for p, v in spec.params.items() if not math.isclose(v, m.theta0[m.param_index(p)])]
    assert len(diff) >= 8


@pytest.fixture(scope="module")
def coast_record():
    return run_experiment("vehicle_coastdown")


def test_record_noise_and_metadata(coast_record):
    exp = coast_record
    assert exp.dt == pytest.approx(0.025)
    assert exp.t[-1] == pytest.approx(60.0) and len(exp) == 2401
    meta = exp.meta
    assert meta["model"] == "vehicle_coastdown"
    assert meta["truth_model"] == "vehicle_coastdown_truth"
    assert meta["seed"] == 11
    assert meta["true_parameters"]["theta_off"] == pytest.approx(math.radians(0.5))
    assert meta["true_parameters"]["f_r"] == pytest.approx(0.022)
    truth = Model.load("vehicle_coastdown_truth")
    X = np.column_stack([exp.columns["state." + s] for s in truth.states])
    th = truth.theta(meta["true_parameters"])
    y_true = truth.h(X, exp.inputs_for(truth), th)
    for j, name in enumerate(truth.outputs):
        assert exp.units[name] == SENSOR_UNITS[name]
        assert meta["noise"]["std"][name] == SENSOR_NOISE[name]
        e = exp.columns[name] - y_true[:, j]
        assert abs(e.mean()) < 4 * SENSOR_NOISE[name] / math.sqrt(e.size)
        assert np.std(e) == pytest.approx(SENSOR_NOISE[name], rel=0.06), name


def test_record_round_trip_and_bad_files(coast_record, tmp_path):
    path = coast_record.save(tmp_path / "coast.csv")
    side = json.loads(path.with_suffix(".json").read_text())
    assert side["format"] == "bondgraph-experiment/1"
    assert side["columns"]["v_gnss"]["unit"] == "m/s"
    back = Experiment.load(path)
    np.testing.assert_array_equal(back.columns["v_gnss"], coast_record.columns["v_gnss"])
    m = Model.load("vehicle_coastdown")
    np.testing.assert_array_equal(back.outputs_for(m), coast_record.outputs_for(m))
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    jb = header.index("brake")
    # NaN in an input: named by line and column
    bad = list(lines)
    cells = bad[101].split(",")
    cells[jb] = "nan"
    bad[101] = ",".join(cells)
    p2 = tmp_path / "bad_input.csv"
    p2.write_text("\n".join(bad) + "\n")
    p2.with_suffix(".json").write_text(path.with_suffix(".json").read_text())  # roles
    with pytest.raises(DataError) as err:
        Experiment.load(p2)
    assert err.value.line == 102 and err.value.column == "brake"
    # non-monotonic time
    bad = list(lines)
    bad[50], bad[51] = bad[51], bad[50]
    p3 = tmp_path / "bad_time.csv"
    p3.write_text("\n".join(bad) + "\n")
    with pytest.raises(DataError, match="line"):
        Experiment.load(p3)


def test_write_records(tmp_path, coast_record):
    from vehicle_graphs.experiments import write_records

    paths = write_records(tmp_path, ["vehicle_coastdown"])
    assert [p.name for p in paths] == ["vehicle_coastdown.csv"]
    assert (tmp_path / "vehicle_coastdown.json").exists()
    back = Experiment.load(paths[0])
    np.testing.assert_array_equal(back.columns["pitch"], coast_record.columns["pitch"])
    assert back.meta["true_parameters"]["f_r"] == pytest.approx(0.022)


def test_seed_makes_records_reproducible(coast_record):
    again = run_experiment("vehicle_coastdown")
    np.testing.assert_array_equal(again.columns["pitch"], coast_record.columns["pitch"])


def test_simulate_and_plot_commands_of_the_docs(tmp_path):
    """The two commands docs/vehicle.md gives for one experiment."""
    out = tmp_path / "full_throttle.csv"
    r = subprocess.run([sys.executable, "-m", "bondgraph.cli.main", "simulate", "vehicle_full",
                        "--experiment", "vehicle_full_throttle_high", "-o", str(out),
                        "--rtol", "1e-6", "--atol", "1e-8"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    sim = Experiment.load(out)
    v = sim.columns["v_gnss"]
    assert 15.0 < v.max() < 22.0  # 25 s of full throttle in High
    r = subprocess.run([sys.executable, "-m", "bondgraph.cli.main", "plot", str(out), "-o",
                        str(tmp_path / "plots")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    pngs = sorted(p.name for p in (tmp_path / "plots").glob("*.png"))
    assert any("outputs" in p for p in pngs) and any("inputs" in p for p in pngs), pngs
