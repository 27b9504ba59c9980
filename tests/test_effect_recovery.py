"""The effect-recovery benchmark's quick subset (bench/effect_recovery.py
--quick): records synthesised with one library effect drawn inside its
declared box; the loop's ranking must put the true effect first (or in the
first candidate's equivalence group) in at least 70 % of the cases, and the
fitted effect must lower the validation error."""

import importlib.util
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parents[1] / "bench" / "effect_recovery.py"


def _bench():
    spec = importlib.util.spec_from_file_location("effect_recovery", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_quick_matrix_ranks_the_truth_first(capsys):
    er = _bench()
    total = er.main(["--quick"])
    out = capsys.readouterr().out.strip().splitlines()
    assert out[-1].startswith("{") and '"total"' in out[-1]
    assert total["cases"] == len(er.QUICK) and total["skipped"] == 0
    assert total["graphs"] >= 3 and total["domains"] >= 3
    assert total["first_rate"] >= 0.7, total
    assert np.isfinite(total["median_val_after"])
    assert total["median_val_after"] < total["median_val_before"]
