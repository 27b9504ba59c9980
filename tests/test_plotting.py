"""PNG plots (bondgraph/report/plots.py): files exist and hold real drawings."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.image import imread

from bondgraph.data.records import Experiment
from bondgraph.errors import DataError
from bondgraph.data.experiments import get_experiment, run_experiment
from bondgraph.numerics.model import Model
from bondgraph.report.plots import plot_record
from bondgraph.numerics.simulate import simulate


@pytest.fixture(scope="module")
def record():
    spec = get_experiment("msd_force_step")
    spec.duration = 3.0
    return run_experiment(spec)


def ink(path) -> tuple[float, np.ndarray]:
    """Fraction of non-white pixels and the image (RGB floats)."""
    img = imread(path)[..., :3]
    return float(np.mean(np.any(img < 0.9, axis=-1))), img


def has_color(img, rgb, tol=0.08) -> bool:
    return bool(np.any(np.all(np.abs(img - np.array(rgb)) < tol, axis=-1)))


C0 = (0x1f / 255, 0x77 / 255, 0xb4 / 255)  # matplotlib blue (record)
C3 = (0xd6 / 255, 0x27 / 255, 0x28 / 255)  # matplotlib red (simulated)


def test_one_png_per_group(tmp_path, record):
    paths = plot_record(record, tmp_path)
    assert [p.name for p in paths] == ["msd_force_step_states.png", "msd_force_step_inputs.png",
                                       "msd_force_step_outputs.png"]
    for p in paths:
        assert p.stat().st_size > 10_000
        frac, img = ink(p)
        assert 0.01 < frac < 0.5, (p, frac)  # drawn, not blank, not a solid block
        assert has_color(img, C0)


def test_measured_vs_simulated(tmp_path, record):
    msd = Model.load("mass_spring_damper")
    sim = simulate(msd, record.t, u=record.inputs_for(msd), hold="zoh")  # default parameters
    paths = plot_record(record, tmp_path, simulated=sim)
    out = [p for p in paths if p.name.endswith("outputs.png")][0]
    _, img = ink(out)
    assert has_color(img, C0) and has_color(img, C3)  # both curves are drawn
    only = plot_record(record, tmp_path / "single")
    _, img1 = ink([p for p in only if p.name.endswith("outputs.png")][0])
    assert not has_color(img1, C3)


def test_from_csv_and_simresult(tmp_path):
    chain = Model.load("mass_chain_5")
    t = np.linspace(0, 2, 201)
    sim = simulate(chain, t, u={"F": 1.0}, method="LSODA")
    csv = Experiment.from_simulation(sim, name="chain").save(tmp_path / "chain.csv")
    a = plot_record(csv, tmp_path / "a", max_per_figure=4)
    # 9 states -> 3 figures, 1 input, 1 output
    assert sorted(p.name for p in a) == sorted(
        ["chain_states_1.png", "chain_states_2.png", "chain_states_3.png",
         "chain_inputs.png", "chain_outputs.png"])
    b = plot_record(sim, tmp_path / "b", prefix="sim")
    # default: at most 8 axes per figure
    assert {p.name for p in b} == {"sim_states_1.png", "sim_states_2.png", "sim_inputs.png",
                                   "sim_outputs.png"}
    assert all(ink(p)[0] > 0.01 for p in a + b)


def test_record_without_sidecar_and_with_gaps(tmp_path):
    t = np.arange(0, 5, 0.05)
    x = np.sin(t)
    x[20:30] = np.nan
    exp = Experiment.from_arrays(t, {"F": np.cos(t), "x": x}, units={"F": "N", "x": "m"})
    csv = exp.save(tmp_path / "plain.csv", sidecar=False)
    # roles come from the model named here
    paths = plot_record(csv, tmp_path / "p", model="mass_spring_damper")
    assert {p.name for p in paths} == {"plain_inputs.png", "plain_outputs.png"}
    # without a model every column is an 'other' signal
    paths = plot_record(csv, tmp_path / "q")
    assert [p.name for p in paths] == ["plain_other.png"]


def test_bad_input(tmp_path):
    with pytest.raises(DataError, match="cannot plot a dict"):
        plot_record({"t": [0, 1]}, tmp_path)
    with pytest.raises(DataError, match="no such file"):
        plot_record(tmp_path / "missing.csv", tmp_path)


def test_cli_plot(tmp_path, record, capsys):
    from bondgraph.cli.main import main

    csv = record.save(tmp_path / "rec.csv")
    assert main(["plot", str(csv), "-o", str(tmp_path / "figs")]) == 0
    out = capsys.readouterr().out
    assert out.count("wrote") == 3
    assert (tmp_path / "figs" / "msd_force_step_outputs.png").exists()
