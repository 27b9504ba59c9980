"""``bondgraph loop --validate A --validate B``: every record given to judge
by judges the accept decision (``LoopSettings.more_validation``).

The records are the ones of ``test_compare``: a mass on viscous friction
pushed by a multisine force, integrated by scipy's solve_ivp at tight
tolerances, the position measured with 1 mm Gaussian noise. The estimation
record and the first validation record carry a constant force offset of
0.5 N that the declared graph lacks. A further record with the offset is
judged at the noise floor after the loop adds it (the NRMSE of the known
noise draw); a further record without it (the truth without an offset)
vetoes the effect, which makes the model worse there.
"""

import json
import os
import sys

import numpy as np
import pytest
from scipy.integrate import solve_ivp

sys.path.insert(0, os.path.dirname(__file__))
from test_compare import DT, F0, FV, GRAPH_FILE, M, N, NOISE, _force, _write  # noqa: E402


def _run(offset, x0, seed):
    t = np.arange(N) * DT
    sol = solve_ivp(lambda tt, z: [z[1], (_force(tt) + offset - FV * z[1]) / M], (0.0, t[-1]),
                    list(x0), t_eval=t, rtol=1e-11, atol=1e-13)
    noise = NOISE * np.random.default_rng(seed).standard_normal(N)
    return t, sol.y[0], noise


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    d = tmp_path_factory.mktemp("validate_many")
    out = {"dir": d}
    for name, offset, x0, seed in (("est", F0, (0.1, 0.2), 7), ("val", F0, (-0.2, 0.0), 8),
                                   ("more", F0, (0.3, -0.4), 9), ("still", 0.0, (0.0, 0.3), 10)):
        t, q, noise = _run(offset, x0, seed)
        _write(d / f"{name}.csv", t, q + noise)
        out[name] = (q, noise)
    (d / "user_drive.py").write_text(GRAPH_FILE.format(tests=os.path.dirname(__file__)))
    return out


def _loop(records, tmp_path, *more):
    from bondgraph.cli.main import main
    d = records["dir"]
    out = tmp_path / "loop"
    args = ["loop", "--model", f"{d / 'user_drive.py'}:user", "--data", str(d / "est.csv"),
            "--validate", str(d / "val.csv")]
    for m in more:
        args += ["--validate", str(d / f"{m}.csv")]
    args += ["--params", "M,Fv", "--max-steps", "1", "--no-structural", "--out", str(out),
             "--quiet", "--no-plots"]
    assert main(args) == 0
    return json.loads((out / "report.json").read_text())


def test_a_further_record_is_judged_before_and_after(records, tmp_path, capsys):
    rep = _loop(records, tmp_path, "more")
    assert [s["effect"] for s in rep["steps"]] == ["offset"], rep["rejected"]
    q, noise = records["more"]
    y = q + noise
    floor = float(np.sqrt(np.mean(noise ** 2)) / np.std(y))     # the truth's own NRMSE
    errs = rep["more_validation_errors"]["more"]
    assert errs["after"] == pytest.approx(floor, rel=0.1)
    assert errs["before"] > 10 * floor
    step = rep["steps"][0]
    assert step["more_errors"]["more"] == pytest.approx([errs["before"], errs["after"]])
    assert rep["settings"]["more_validation"] == ["more"]
    said = capsys.readouterr().out
    assert f"on the validation record (more): before {errs['before']:.4g}" in said
    cell = f"{errs['before']:.4g} -> {errs['after']:.4g}"
    assert f"error on more |" in said and cell in said            # the step table
    md = (tmp_path / "loop" / "report.md").read_text()
    assert f"`more` {cell}" in md and "Further validation records, not fitted: `more`" in md
    html = (tmp_path / "loop" / "report.html").read_text()
    assert "error on more" in html and cell.replace("->", "&rarr;") in html


def test_a_further_record_the_effect_makes_worse_vetoes_it(records, tmp_path):
    rep = _loop(records, tmp_path, "still")
    assert not rep["steps"]
    reasons = [r["reason"] for r in rep["rejected"]]
    assert any(r.startswith("the error grew on the validation record 'still'") for r in reasons), \
        reasons
    errs = rep["more_validation_errors"]["still"]
    assert errs["before"] == errs["after"]            # nothing accepted
    refused = next(r for r in rep["rejected"] if "'still'" in r["reason"])
    assert refused["confirmed"]["more_validation_errors"]["still"] > errs["before"]
    grew = next(r for r in reasons if "'still'" in r)
    before, after = (float(v) for v in grew.split("(")[1].split(")")[0].split(" -> "))
    assert before == pytest.approx(errs["before"], rel=1e-3) and after > before


def test_decide_pools_the_further_records_and_vetoes_a_growth_on_any():
    """The error-decrease test pairs the stacked per-sample errors of every
    validation record (:func:`pooled_errors`); a growth on a further record
    is named before it."""
    from bondgraph.diagnose.accept import decide, pooled_errors
    from bondgraph.diagnose.settings import AcceptRule
    from test_loop_accept import _fit

    rng = np.random.default_rng(3)
    e_noise = rng.standard_normal((400, 1))
    cur = _fit(-1000.0, 2, 20.0, 1.0, validation=0.50)
    after = _fit(-1100.0, 3, 20.0, 0.9, validation=0.499)
    # on the first record the change is within the noise ...
    cur.validation_errors, after.validation_errors = e_noise + 0.01, e_noise
    d = decide(cur, after, AcceptRule())
    assert not d.accepted and "within its uncertainty" in d.reason
    # ... a further record where it is large carries the pooled test
    cur.more_metrics, after.more_metrics = {"b": 0.8}, {"b": 0.1}
    cur.more_errors = {"b": e_noise + 2.0}
    after.more_errors = {"b": e_noise}
    a0, a1 = pooled_errors(cur, after)
    assert a0.shape == (800, 1)
    np.testing.assert_array_equal(a1[400:], e_noise)
    d = decide(cur, after, AcceptRule())
    assert d.accepted, d.reason
    # a growth on a further record vetoes, named with the record
    after.more_metrics = {"b": 0.81}
    d = decide(cur, after, AcceptRule())
    assert d.reason == "the error grew on the validation record 'b' (0.8 -> 0.81)"
    # a further record the after model cannot be judged on is not paired
    after.more_metrics, after.more_errors = {"b": 0.1}, {"b": None}
    assert pooled_errors(cur, after)[0].shape == (400, 1)
    # a pooled decrease within the noise names every record's errors
    after.more_metrics, after.more_errors = {"b": 0.799}, {"b": e_noise}
    cur.more_errors = {"b": e_noise + 0.001}
    d = decide(cur, after, AcceptRule())
    assert d.reason.startswith("the error decrease over the validation records is within its "
                               "uncertainty (0.5 -> 0.499, 'b' 0.8 -> 0.799, z ")


def test_further_validation_records_are_checked_as_settings(records):
    from bondgraph.data.records import Experiment
    from bondgraph.diagnose.settings import LoopSettings
    from bondgraph.errors import OptionError

    d = records["dir"]
    val, more = Experiment.load(d / "val.csv"), Experiment.load(d / "more.csv")
    s = LoopSettings(params=["M"], validation=val, more_validation=[more])
    assert s.more_validation == (more,) and s.summary()["more_validation"] == ["more"]
    with pytest.raises(OptionError, match="needs a first record that judges"):
        LoopSettings(params=["M"], more_validation=[more])
    assert LoopSettings(params=["M"], holdout=0.25, more_validation=[more]).more_validation
    with pytest.raises(OptionError, match="'val' given more than once"):
        LoopSettings(params=["M"], validation=val, more_validation=[val])
    with pytest.raises(OptionError, match="sequence of Experiments"):
        LoopSettings(params=["M"], validation=val, more_validation=more)


def test_holdout_and_validate_together_judge_on_both(records):
    """``--holdout 0.25 --validate more.csv``: the held-out quarter is the
    first record that judges, the file beside it (``held_out`` cuts it)."""
    from bondgraph.cli.loop import loop_settings
    from bondgraph.cli.main import command_parser
    from bondgraph.data.records import Experiment
    from bondgraph.diagnose.runner import held_out
    from bondgraph.diagnose.settings import LoopSettings
    from test_compare import drive

    d = records["dir"]
    args = command_parser("loop").parse_args(
        ["--model", "m", "--data", str(d / "est.csv"), "--holdout", "0.25",
         "--validate", str(d / "more.csv")])
    s = loop_settings(args, LoopSettings(params=["M", "Fv"]), drive())
    assert s.validation is None and [r.name for r in s.more_validation] == ["more"]
    est, s2 = held_out(Experiment.load(d / "est.csv"), s)
    assert len(est.t) == 750 and s2.validation.name == "est[750:]"
    assert [r.name for r in s2.more_validation] == ["more"]
    # without --holdout the first file judges first, as before
    args = command_parser("loop").parse_args(
        ["--model", "m", "--data", str(d / "est.csv"), "--validate", str(d / "val.csv"),
         "--validate", str(d / "more.csv")])
    s = loop_settings(args, LoopSettings(params=["M", "Fv"]), drive())
    assert s.validation.name == "val" and [r.name for r in s.more_validation] == ["more"]


def test_estimate_judges_its_fit_on_the_records_of_validate(records, tmp_path, capsys):
    """``bondgraph estimate --validate more.csv``: the true graph (with the
    offset) fitted on est.csv reads the noise draw of a record it was not
    fitted to (another start, another draw), as ``bondgraph compare`` does."""
    from bondgraph.cli.main import main

    d = records["dir"]
    (tmp_path / "user_drive.py").write_text(
        GRAPH_FILE.format(tests=os.path.dirname(__file__)).replace("drive()", "drive(offset=True)"))
    spec = f"{tmp_path / 'user_drive.py'}:user"
    est = tmp_path / "est"
    base = ["estimate", "--model", spec, "--data", str(d / "est.csv"), "--params", "M,Fv,F0",
            "--iterations", "20", "--no-plots", "--quiet"]
    # refused before the fit: a window without a record to judge, one the record cannot hold
    assert main(base + ["--init-samples", "20", "--out", str(est)]) == 2
    assert "give --validate FILE" in capsys.readouterr().err
    assert main(base + ["--validate", str(d / "more.csv"), "--init-samples", "995",
                        "--out", str(est)]) == 2
    assert "leaves 5 samples of record 'more'" in capsys.readouterr().err
    assert not est.exists()
    assert main(base + ["--validate", str(d / "more.csv"), "--out", str(est)]) == 0
    said = capsys.readouterr().out
    assert "the estimate on the records it was not fitted to (--validate):" in said
    doc = json.loads((est / "validation" / "compare.json").read_text())
    rec = doc["records"][0]
    q, noise = records["more"]
    assert rec["record"] == "more"
    assert rec["outputs"]["qm"]["rms"] == pytest.approx(float(np.sqrt(np.mean(noise ** 2))),
                                                        rel=0.05)
    assert (est / "validation" / "more_compare.csv").is_file()
    assert f"| more | qm | {rec['outputs']['qm']['rms']:.4g}" in said
    # the same figure as the command that judges a fit on its own
    out = tmp_path / "cmp"
    assert main(["compare", spec, "--data", str(d / "more.csv"), "--params",
                 str(est / "result.json"), "--out", str(out), "--quiet", "--no-plots"]) == 0
    again = json.loads((out / "compare.json").read_text())["records"][0]
    assert again["outputs"]["qm"]["rms"] == pytest.approx(rec["outputs"]["qm"]["rms"], rel=1e-9)
