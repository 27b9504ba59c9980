"""Isolated outliers (a sensor's single-sample glitches) named at the
loop's final model and at an estimate
(:func:`bondgraph.diagnose.residuals.isolated_outliers`).

The reference for the rule: standard normal draws (numpy, seeded), in
which no sample lies 8 robust std out (one in 8e14), with glitches added
at known samples. The reference for the commands: the user's cart of
``tests/test_prune_insignificant.py`` (scipy's ``solve_ivp``), its 100 Hz
speed sensor (noise 0.01 m/s) given six 2 m/s glitches at known times.
"""

import json
import os
import sys
from pathlib import Path

import numpy as np

from bondgraph.cli.main import main
from bondgraph.diagnose.residuals import OUTLIER_Z, isolated_outliers

sys.path.insert(0, os.path.dirname(__file__))
from test_prune_insignificant import N, _record  # noqa: E402

GLITCHES = [348, 619, 625, 786, 2423, 2449]


def test_isolated_glitches_are_found_largest_first():
    z = np.random.default_rng(0).standard_normal(3000)
    assert isolated_outliers(z)[0].size == 0                  # Gaussian: none
    z[[100, 1500, 2900]] += [60.0, -90.0, 30.0]
    z[[7, 8]] = np.nan                                          # missing samples are skipped
    idx, largest = isolated_outliers(z)
    assert idx.tolist() == [1500, 100, 2900]
    assert largest > 80.0


def test_what_is_not_a_glitch():
    rng = np.random.default_rng(1)
    z = rng.standard_normal(3000)
    one = z.copy()
    one[10] = OUTLIER_Z + 1.0        # one sample barely out: 1/3000 of the squares' sum is not 5 %
    assert isolated_outliers(one)[0].size == 0
    run = z.copy()
    run[500:505] = 40.0              # a run of large innovations: the model's error, no glitch
    assert isolated_outliers(run)[0].size == 0
    many = z.copy()
    many[::50] += 40.0               # 2 % of the samples: heavy tails, no glitches
    assert isolated_outliers(many)[0].size == 0
    sparse = z.copy()
    sparse[[5, 6]] = [np.nan, 50.0]  # a glitch next to a missing sample: its neighbours are measured ones
    assert isolated_outliers(sparse)[0].tolist() == [6]


def _glitched(tmp_path) -> Path:
    _record(tmp_path / "run.csv")
    lines = (tmp_path / "run.csv").read_text().splitlines()
    for k in GLITCHES:
        c = lines[k + 1].split(",")
        c[3] = repr(float(c[3]) + (2.0 if k % 2 else -2.0))
        lines[k + 1] = ",".join(c)
    (tmp_path / "glitch.csv").write_text("\n".join(lines) + "\n")
    return tmp_path / "glitch.csv"


def _times(text: str) -> list[float]:
    return [float(v) for v in text.split("(t = ")[1].split(" s;")[0].split(", ")]


def test_the_loop_names_the_glitches_on_both_parts_of_the_record(tmp_path, capsys):
    rc = main(["loop", "--model", f"{os.path.dirname(__file__)}/test_prune_insignificant.py:cart",
               "--data", str(_glitched(tmp_path)), "--out", str(tmp_path / "loop"),
               "--no-plots", "--max-steps", "0"])
    assert rc == 0
    rep = json.loads((tmp_path / "loop" / "report.json").read_text())
    warn = [w for w in rep["warnings"] if "isolated sample" in w]
    assert len(warn) == 2 and all(w.startswith("v_wheel on glitch[") for w in warn)
    cut = int(0.75 * N)               # the held-out last quarter: its free run
    assert _times(warn[0]) == [round(k * 0.01, 6) for k in GLITCHES if k < cut]
    assert "from the filter's prediction" in warn[0]
    assert _times(warn[1]) == [round(k * 0.01, 6) for k in GLITCHES if k >= cut]
    assert "from the free run" in warn[1]
    # repeated under the summary, where a user reads the result
    tail = capsys.readouterr().out.split("no effect accepted")[1]
    assert [line[len("warning: "):] for line in tail.splitlines()
            if line.startswith("warning: ")] == warn


def test_estimate_names_the_glitches_and_a_clean_record_has_none(tmp_path):
    model = f"{os.path.dirname(__file__)}/test_prune_insignificant.py:cart"
    for data, out in ((_glitched(tmp_path), "g"), (tmp_path / "run.csv", "c")):
        assert main(["estimate", "--model", model, "--data", str(data), "--params", "M,c",
                     "--out", str(tmp_path / out), "--no-plots", "--quiet"]) == 0
    glitched = json.loads((tmp_path / "g" / "result.json").read_text())["warnings"]
    warn = [w for w in glitched if "isolated sample" in w]
    assert len(warn) == 1 and warn[0].startswith("v_wheel: 6 isolated samples")
    assert "leave those cells empty" in warn[0]
    clean = json.loads((tmp_path / "c" / "result.json").read_text())["warnings"]
    assert not any("isolated sample" in w for w in clean)
