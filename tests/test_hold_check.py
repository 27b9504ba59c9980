"""The input hold checked at the loop's final model
(:func:`bondgraph.diagnose.runner.hold_at_final`).

The shape of a record cannot tell a command held constant over each sample
whose steps vary smoothly from a sampled continuous signal. The reference
here is exact: a mass on viscous friction under a smooth multisine force
held over each 10 ms sample, discretised exactly by scipy's
``cont2discrete`` (zero-order hold), against the same mass under a force
that is continuous between samples (scipy's ``solve_ivp``, rtol 1e-11).
Both shapes read "linear". Under it the held record's fit puts M 42
Cramér-Rao std off the truth; the check refits under zero-order, finds the
record 749 nats likelier and says so with the estimates that move (M back
within 3 std of the truth). The continuous record is likelier under its
shape's hold: no warning. ``bondgraph estimate`` checks the same at its
estimate (M 65 std off under linear, 879 nats, the noise std estimated).
"""

import json
import os
import sys

import numpy as np
from scipy.signal import cont2discrete

from bondgraph import LoopSettings, run_loop
from bondgraph.data.records import Experiment
from bondgraph.diagnose.runner import chosen_numerics
from bondgraph.diagnose.settings import SearchOptions

sys.path.insert(0, os.path.dirname(__file__))
from test_compare import FV, M, _truth, _write, drive  # noqa: E402

DT, N, NOISE = 0.01, 1500, 1e-3


def _held_record(tmp_path) -> Experiment:
    """Position of the mass under a force held over each sample (exact)."""
    t = np.arange(N) * DT
    fr = np.array([0.07, 0.23, 0.61])
    f = 3.0 * np.sum(np.sin(2 * np.pi * fr * t[:, None] + np.arange(3)), axis=1)
    A = np.array([[0.0, 1.0], [0.0, -FV / M]])
    B = np.array([[0.0], [1.0 / M]])
    Ad, Bd, *_ = cont2discrete((A, B, np.eye(2), np.zeros((2, 1))), DT, method="zoh")
    x = np.zeros((N, 2))
    x[0] = [0.1, 0.0]
    for k in range(N - 1):
        x[k + 1] = Ad @ x[k] + Bd[:, 0] * f[k]
    y = x[:, 0] + NOISE * np.random.default_rng(5).standard_normal(N)
    path = tmp_path / "held.csv"
    with open(path, "w") as fh:
        fh.write("t [s],F [N],qm [m]\n")
        for row in zip(t.tolist(), f.tolist(), y.tolist()):
            fh.write("%r,%r,%r\n" % row)
    return Experiment.load(path)


def _loop(rec, given=None):
    said = []
    s = LoopSettings(params=["M", "Fv"], holdout=0.25, search=SearchOptions(max_steps=0))
    s = chosen_numerics(drive(), rec, s, given=given, log=said.append)
    logs = []
    return s, run_loop(drive(), rec, s, log=logs.append, progress=False), said, logs


def test_a_held_force_whose_shape_reads_continuous_is_named(tmp_path):
    s, res, said, logs = _loop(_held_record(tmp_path))
    assert s.ukf.hold == "linear" and s.search.check_hold
    assert "F: linear (a sampled continuous signal" in said[0]
    # the shape's hold leaves M far off the truth with a small std
    est, sd = res.final.estimates["M"], res.final.std["M"]
    assert abs(est - M) > 20 * sd
    line = next(m for m in logs if "input hold of 'F' at the final model" in m)
    zoh = float(line.split("zoh NLL ")[1].split(",")[0])
    lin = float(line.split("(its shape's) NLL ")[1].split(",")[0])
    assert lin - zoh > 500 and line.endswith("the record prefers zoh")
    warning = next(w for w in res.warnings if "likelier with input 'F' held zoh" in w)
    assert f"{lin - zoh:.0f} nats" in warning
    assert 'columns.F.hold = "zoh"' in warning and "--hold zoh" in warning
    # the estimate the warning quotes under zoh is within 3 std of the truth
    m_zoh = float(warning.split("under it M ")[1].split(" ")[0])
    assert abs(m_zoh - M) < 3 * 0.00026 + 1e-4, m_zoh       # zoh's Cramér-Rao std 0.00026
    assert f"(was {est:.5g}" in warning


def test_a_continuous_force_keeps_its_hold_without_a_warning(tmp_path):
    t, q = _truth(0.0)
    rec = _write(tmp_path / "cont.csv", t,
                 q + NOISE * np.random.default_rng(6).standard_normal(len(t)))
    s, res, _, logs = _loop(rec)
    assert s.ukf.hold == "linear"
    line = next(m for m in logs if "input hold of 'F' at the final model" in m)
    zoh = float(line.split("zoh NLL ")[1].split(",")[0])
    lin = float(line.split("(its shape's) NLL ")[1].split(",")[0])
    assert zoh > lin + 10 and not line.endswith("prefers zoh")
    assert not any("likelier with input" in w for w in res.warnings)


def test_a_given_hold_is_not_checked(tmp_path):
    s, res, _, logs = _loop(_held_record(tmp_path), given={"hold": "linear"})
    assert not s.search.check_hold
    assert not any("input hold of" in m for m in logs)
    assert not any("likelier with input" in w for w in res.warnings)


def _estimate(tmp_path, rec_path, *more):
    from bondgraph.cli.main import main
    out = tmp_path / "est"
    rc = main(["estimate", "--model", f"{os.path.dirname(__file__)}/test_compare.py:drive",
               "--data", str(rec_path), "--params", "M,Fv", "--out", str(out), "--no-plots",
               "--quiet", *more])
    assert rc == 0
    return json.loads((out / "result.json").read_text())


def test_estimate_names_a_held_force_whose_shape_reads_continuous(tmp_path, capsys):
    """The estimate under the shape's linear hold puts M 65 std off (with
    the noise std estimated); refitted from it under zero-order the record
    is 879 nats likelier and M within 3 std of the truth. The result keeps
    the shape's estimate and says so."""
    _held_record(tmp_path)
    res = _estimate(tmp_path, tmp_path / "held.csv")
    err = capsys.readouterr().err
    line = next(m for m in err.splitlines() if m.startswith("input hold of 'F' at the estimate"))
    zoh = float(line.split("zoh NLL ")[1].split(",")[0])
    lin = float(line.split("(its shape's) NLL ")[1].split(",")[0])
    assert lin - zoh > 500 and line.endswith("the record prefers zoh")
    assert res["settings"]["ukf"]["hold"] == "linear"        # the result is the shape's
    m_lin = res["estimates"][res["params"].index("M")]
    assert abs(m_lin - M) > 20 * res["std"][res["params"].index("M")]
    warning = next(w for w in res["warnings"] if "likelier with input 'F' held zoh" in w)
    m_zoh = float(warning.split("under it M ")[1].split(" ")[0])
    assert abs(m_zoh - M) < 3 * 0.0003, m_zoh
    assert "--hold zoh" in warning and "bondgraph loop" in warning


def test_estimate_keeps_quiet_on_a_continuous_force(tmp_path, capsys):
    t, q = _truth(0.0)
    _write(tmp_path / "cont.csv", t, q + NOISE * np.random.default_rng(6).standard_normal(len(t)))
    res = _estimate(tmp_path, tmp_path / "cont.csv")
    err = capsys.readouterr().err
    line = next(m for m in err.splitlines() if m.startswith("input hold of 'F' at the estimate"))
    assert not line.endswith("prefers zoh")
    assert not any("likelier with input" in w for w in res["warnings"])
    # a given hold: nothing checked
    _estimate(tmp_path, tmp_path / "cont.csv", "--hold", "linear", "--overwrite")
    assert "input hold of" not in capsys.readouterr().err


def test_a_hold_warning_of_a_model_far_from_white_says_the_misfit_weighs_in():
    """:func:`runner._misfit_clause`: the final model's Ljung-Box sum above
    10 times its degrees of freedom (a user's swing arm without its gravity
    law: 7.4e4 against about 20) adds that the misfit weighs in both holds'
    likelihoods; near white (38.6 against 20, a CVT driveline's final model)
    or without residuals it adds nothing."""
    from types import SimpleNamespace as NS

    from bondgraph.diagnose.runner import FAR_FROM_WHITE, _misfit_clause

    def fit(w, dof=20.0):
        return NS(residuals=NS(whiteness=w, whiteness_dof=dof))

    clause = _misfit_clause(fit(7.408e4))
    assert clause.startswith("; but the final model's innovations are far from white "
                             "(whiteness 7.41e+04, about 20 if white)")
    assert _misfit_clause(fit(38.6)) == "" and _misfit_clause(NS(residuals=None)) == ""
    assert _misfit_clause(fit(FAR_FROM_WHITE * 20.0)) == ""
    assert _misfit_clause(fit(FAR_FROM_WHITE * 20.0 + 1.0)) != ""
