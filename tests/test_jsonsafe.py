"""The one JSON policy (bondgraph/core/jsonsafe.py) and the files that use it:
NaN -> null, ±inf -> "inf"/"-inf", numpy types -> Python, strict JSON out,
infinities back on reading."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from bondgraph.core.jsonsafe import from_jsonable, to_jsonable
from bondgraph.data.records import Experiment
from bondgraph.diagnose.effects import Target
from bondgraph.inference.estimate import EstimationResult
from bondgraph.numerics.integrators import rk4_stable_step
from bondgraph.numerics.simulate import _sample_stiffness


def _strict(obj) -> str:
    return json.dumps(to_jsonable(obj), allow_nan=False)


def test_non_finite_numbers():
    assert to_jsonable(float("nan")) is None
    assert to_jsonable(np.nan) is None
    assert to_jsonable(float("inf")) == "inf"
    assert to_jsonable(-np.inf) == "-inf"
    assert to_jsonable(np.float32("-inf")) == "-inf"
    assert to_jsonable(np.float16("nan")) is None
    assert to_jsonable([1.5, np.nan, np.inf, -np.inf]) == [1.5, None, "inf", "-inf"]


def test_numpy_types_become_python_types():
    out = to_jsonable({"f64": np.float64(0.1), "f32": np.float32(0.1), "i": np.int16(-7),
                       "u": np.uint64(2**63 + 1), "b": np.bool_(True), "z": np.array(2.5),
                       "m": np.arange(6, dtype=np.int32).reshape(2, 3),
                       "v": np.array([0.25, np.nan, np.inf]), "mask": np.array([True, False])})
    assert out == {"f64": 0.1, "f32": float(np.float32(0.1)), "i": -7, "u": 2**63 + 1,
                   "b": True, "z": 2.5, "m": [[0, 1, 2], [3, 4, 5]],
                   "v": [0.25, None, "inf"], "mask": [True, False]}
    # exact Python types, not numpy subclasses (json would take np.float64, not np.float32)
    assert type(out["f64"]) is float and type(out["f32"]) is float
    assert type(out["i"]) is int and type(out["b"]) is bool
    assert type(out["m"][1][2]) is int


def test_containers_dataclasses_paths():
    @dataclass
    class Box:
        lo: float
        hi: np.ndarray
        where: Path

    out = to_jsonable({1: (np.int64(2), Box(-np.inf, np.array([1.0, np.inf]), Path("a/b.csv"))),
                       "s": "inf-like text", "none": None})
    assert out == {"1": [2, {"lo": "-inf", "hi": [1.0, "inf"], "where": "a/b.csv"}],
                   "s": "inf-like text", "none": None}
    # the loop's targets keep the form its old sanitiser gave them
    assert to_jsonable(Target("junction", "1_drive")) == {"kind": "junction", "name": "1_drive"}
    # a class is not an instance: left alone (json then refuses it)
    assert to_jsonable(Box) is Box
    with pytest.raises(TypeError):
        _strict({"x": {1, 2}})


def test_input_is_not_modified():
    arr = np.array([1.0, np.inf])
    d = {"a": arr, "b": [np.nan]}
    to_jsonable(d)
    assert d["a"] is arr and np.isinf(arr[1]) and math.isnan(d["b"][0])


def test_round_trip_is_bit_exact_and_restores_infinities():
    vals = [0.1 + 0.2, 1e-300, -2.5e308, 5e-324, float(np.float32(1 / 3)), -0.0, 3]
    src = {"v": np.array(vals[:-1]), "n": vals[-1], "inf": np.inf, "ninf": -np.inf,
           "nan": np.nan, "nested": [{"h": np.inf}], "name": "m"}
    back = from_jsonable(json.loads(_strict(src)))
    assert [x.hex() for x in back["v"]] == [float(x).hex() for x in vals[:-1]]
    assert math.copysign(1.0, back["v"][5]) == -1.0  # -0.0 survives
    assert back["n"] == 3 and type(back["n"]) is int
    assert back["inf"] == math.inf and back["ninf"] == -math.inf
    assert back["nan"] is None  # NaN is "no value"; numeric readers make it NaN again
    assert back["nested"] == [{"h": math.inf}] and back["name"] == "m"
    np.testing.assert_array_equal(np.array([back["nan"], back["inf"], 1.0], dtype=float),
                                  [np.nan, np.inf, 1.0])


def test_from_jsonable_touches_only_the_two_strings():
    assert from_jsonable(["inf", "-inf", "Infinity", "INF", "+inf", "nan", None, 1]) == \
        [math.inf, -math.inf, "Infinity", "INF", "+inf", "nan", None, 1]


def test_estimation_result_json_round_trip_with_non_finite_values():
    r = EstimationResult(
        model="m", experiment="e", params=["a", "b"], estimates=np.array([1.0, 2.0]),
        std=np.array([0.1, np.nan]), corr=np.array([[1.0, np.nan], [np.nan, 1.0]]),
        hessian=np.array([[4.0, 0.0], [0.0, 0.0]]), nll=np.float64(12.5),
        nll_optimizer=np.inf, evaluations=np.int64(80), evaluations_total=90, wall_s=1.25,
        optimizer="pso", theta=np.array([1.0, 2.0, 3.0]), lower=np.array([0.0, -np.inf]),
        upper=np.array([np.inf, 5.0]), optimizer_result={"fun": np.float32(np.inf)})
    text = r.to_json()
    d = json.loads(text)
    assert d["nll_optimizer"] == "inf" and d["lower"] == [0.0, "-inf"] and d["std"][1] is None
    assert d["optimizer_result"] == {"fun": "inf"} and d["evaluations"] == 80
    back = EstimationResult.from_json(text)
    assert back.nll_optimizer == math.inf and back.nll == 12.5
    np.testing.assert_array_equal(back.lower, [0.0, -np.inf])
    np.testing.assert_array_equal(back.upper, [np.inf, 5.0])
    np.testing.assert_array_equal(back.std, [0.1, np.nan])
    np.testing.assert_array_equal(back.corr, r.corr)
    assert back.optimizer_result == {"fun": math.inf}


def test_record_sidecar_round_trip(tmp_path):
    t = np.arange(5) * 0.1
    exp = Experiment.from_arrays(
        t, {"x": np.array([0.0, 1.0, np.nan, 3.0, 4.0])}, roles={"x": "output"},
        meta={"limits": {"lo": -np.inf, "hi": np.float32(np.inf)}, "gain": np.float64(0.1),
              "count": np.int64(3), "undefined": np.nan, "flags": np.array([True, False])})
    path = exp.save(tmp_path / "r.csv")
    side = json.loads(path.with_suffix(".json").read_text())
    assert side["limits"] == {"lo": "-inf", "hi": "inf"} and side["undefined"] is None
    assert side["count"] == 3 and side["flags"] == [True, False]
    back = Experiment.load(path)
    assert back.meta["limits"] == {"lo": -math.inf, "hi": math.inf}
    assert back.meta["gain"] == 0.1 and back.meta["undefined"] is None
    np.testing.assert_array_equal(back["x"], exp["x"])


def test_stiffness_report_unbounded_step_is_inf_in_python_and_json():
    # purely imaginary or zero eigenvalues: no decaying mode limits the RK4 step
    assert rk4_stable_step(np.array([0.0, 0.0])) == math.inf
    sample, growing = _sample_stiffness(0.5, np.array([0.0 + 0.0j]), 0.01)
    assert sample["rk4_stable_step"] == math.inf and sample["rk4_substeps"] == 1
    assert growing == 0 and sample["stiffness_ratio"] == 1.0
    assert json.loads(_strict(sample))["rk4_stable_step"] == "inf"
