"""Experiment registry and run_experiment (bondgraph/data/experiments.py)."""

from __future__ import annotations


import numpy as np
import pytest

from bondgraph.data import experiments as E
from bondgraph.data.records import Experiment
from bondgraph.errors import ModelError
from bondgraph.data.experiments import (ExperimentSpec, get_experiment, registered_experiments,
                                   run_experiment)
from bondgraph.core import plugins
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate


def test_registry_lists_reference_experiments():
    reg = registered_experiments()
    for name in ("msd_force_step", "dc_motor_voltage_step", "toy_cvt_torque_ratio_ramp"):
        assert reg[name] == f"bondgraph.catalog.reference:{name}"
        spec = get_experiment(name)
        assert isinstance(spec, ExperimentSpec) and spec.name == name
        Model.load(spec.model)  # every spec names a generated model


def test_registry_rejects_duplicates_and_unknown():
    with pytest.raises(ModelError, match="'msd_force_step' registered twice"):
        plugins.register("experiments", {"msd_force_step": "_fake_experiments:other"})
    plugins.register("experiments", {"msd_other": "_fake_experiments:other"})
    try:
        assert registered_experiments()["msd_other"] == "_fake_experiments:other"
    finally:
        plugins.unregister("experiments", "msd_other")
    assert "msd_other" not in registered_experiments()
    with pytest.raises(ModelError, match="unknown experiment 'nope'.*msd_force_step"):
        get_experiment("nope")


def spec_msd(**kw) -> ExperimentSpec:
    base = dict(name="msd_test", model="mass_spring_damper", duration=40.0, dt=0.01,
                inputs={"F": lambda t: 10.0 * np.sin(0.7 * t)},
                params={"m": 2.4, "k": 60.0, "c": 1.2}, x0={"q_spring": 0.01}, seed=11)
    base.update(kw)
    return ExperimentSpec(**base)


def test_reproducible_from_seed():
    a = run_experiment(spec_msd(duration=5.0))
    b = run_experiment(spec_msd(duration=5.0))
    for c in a.columns:
        np.testing.assert_array_equal(a.columns[c], b.columns[c])
    c = run_experiment(spec_msd(duration=5.0, seed=12))
    assert not np.array_equal(a["x"], c["x"])
    np.testing.assert_array_equal(a["state.q_spring"], c["state.q_spring"])  # same truth


def test_noise_std_is_as_declared():
    spec = spec_msd()
    exp = run_experiment(spec)
    msd = Model.load("mass_spring_damper")
    # independent truth: a fresh simulation with another solver
    truth = simulate(msd, exp.t, u={"F": spec.inputs["F"]}, x0=spec.x0, theta=spec.params,
                     method="LSODA", rtol=1e-10, atol=1e-12)
    declared = exp.noise_std
    assert declared == {"x": 0.002, "v": 0.01}  # the model's meas_std
    n = len(exp)
    assert n == 4001
    res = {}
    for name in ("x", "v"):
        e = exp[name] - truth.output(name)
        res[name] = e
        assert np.std(e, ddof=1) == pytest.approx(declared[name], rel=0.05)
        assert abs(np.mean(e)) < 4 * declared[name] / np.sqrt(n)
    assert abs(np.corrcoef(res["x"], res["v"])[0, 1]) < 4 / np.sqrt(n)


def test_declared_noise_overrides_model_default():
    exp = run_experiment(spec_msd(duration=10.0, noise_std={"v": 0.05}))
    assert exp.noise_std == {"x": 0.002, "v": 0.05}
    assert exp.meta["noise"]["std"] == {"x": 0.002, "v": 0.05}
    noiseless = run_experiment(spec_msd(duration=2.0, noise_std={"x": 0.0, "v": 0.0}))
    np.testing.assert_allclose(noiseless["x"], noiseless["state.q_spring"], rtol=0, atol=0)


def test_meta_and_round_trip(tmp_path):
    exp = run_experiment("toy_cvt_torque_ratio_ramp")
    m = exp.meta
    cvt = Model.load("toy_cvt")
    assert m["model"] == m["truth_model"] == "toy_cvt" and m["seed"] == 3
    assert m["true_parameters"] == {"J_e": 0.15, "m": 1350.0, "c": 25.0}
    assert m["x0"] == {"p_m": 0.0} and m["dt"] == 0.025 and m["description"]
    assert exp.roles["T"] == "input" and exp.roles["v"] == "output"
    # der(r) recorded as the simulation used it: the ramp slope 0.05/10 per s
    inside = (exp.t > 5.1) & (exp.t < 14.9)
    np.testing.assert_allclose(exp["der(r)"][inside], 0.005, rtol=1e-6)
    back = Experiment.load(exp.save(tmp_path / "cvt.csv"))
    np.testing.assert_array_equal(back.inputs_for(cvt), exp.inputs_for(cvt))
    np.testing.assert_array_equal(back.outputs_for(cvt), exp.outputs_for(cvt))
    assert back.meta["true_parameters"] == m["true_parameters"]
    assert back.meta["noise"]["distribution"] == "gaussian"
    # the truth states explain the noisy outputs: v = p_m / m within the noise
    v = back["state.p_m"] / m["true_parameters"]["m"]
    assert np.std(back["v"] - v) == pytest.approx(0.05, rel=0.15)


def test_truth_model_differs_from_filter_model():
    spec = ExperimentSpec(name="gear_from_compliant", model="dc_motor_gear",
                          truth_model="dc_motor_compliant", duration=0.3, dt=0.001,
                          inputs={"V": E.step(0.01, 12.0)}, seed=4)
    exp = run_experiment(spec)
    assert exp.names("output") == ["w_L"]
    assert exp.names("input") == ["V", "T_L"]
    assert len(exp.names("state")) == 4  # the truth model's states
    assert exp.meta["model"] == "dc_motor_gear"
    assert exp.meta["truth_model"] == "dc_motor_compliant"
    assert set(exp.meta["true_parameters"]) == set(Model.load("dc_motor_compliant").params)
    bad = ExperimentSpec(name="bad", model="dc_motor_compliant", truth_model="dc_motor_gear",
                         duration=0.1, dt=0.001)
    with pytest.raises(ModelError, match="lacks outputs i"):
        run_experiment(bad)


def test_bad_specs_name_the_culprit():
    with pytest.raises(ModelError, match="inputs G are not inputs"):
        run_experiment(spec_msd(duration=1.0, inputs={"G": np.sin}))
    with pytest.raises(ModelError, match="has no parameter 'mass'"):
        run_experiment(spec_msd(duration=1.0, params={"mass": 3.0}))
    with pytest.raises(ModelError, match="noise_std given for 'y'"):
        run_experiment(spec_msd(duration=1.0, noise_std={"y": 0.1}))
    with pytest.raises(ModelError, match="must be finite and >= 0"):
        run_experiment(spec_msd(duration=1.0, noise_std={"x": -1.0}))
    with pytest.raises(ModelError, match="must be positive"):
        run_experiment(spec_msd(duration=0.0))


@pytest.mark.parametrize("name", ["msd_force_step", "dc_motor_voltage_step"])
def test_registered_experiments_run(name):
    spec = get_experiment(name)
    exp = run_experiment(spec)
    mdl = Model.load(spec.model)
    assert len(exp) == int(round(spec.duration / spec.dt)) + 1
    U = exp.inputs_for(mdl)
    for k, fn in spec.inputs.items():
        np.testing.assert_array_equal(U[:, mdl.input_index(k)], fn(exp.t))
    assert np.all(np.isfinite(exp.outputs_for(mdl)))
