"""A catalogue of bad inputs and misuses of the command line (issue 13).

Every entry runs ``bondgraph`` in-process (:func:`bondgraph.cli.main.main`)
and must end in exit code 2 with a one-line ``bondgraph CMD: error: ...``
naming the culprit (no traceback: any exception other than the typed ones
propagates and fails the test), or in the stated warning. The entries are
grouped by kind (``KINDS`` counts them); the tests after the table cover the
faults that need a prepared state (a checkpoint of other data, a non-empty
folder, a record without an output).
"""

from __future__ import annotations

import json
import textwrap
from collections import Counter
from pathlib import Path

import pytest

from bondgraph.cli.main import main
from bondgraph.diagnose.settings import DEFAULT_HOLDOUT
from bondgraph.data.experiments import run_experiment

#: the small record every entry uses: 120 samples of msd_force_step
N_SAMPLES = 120

EST = ["estimate", "--model", "mass_spring_damper", "--params", "m,k,c", "--quiet",
       "--method", "rk4", "--particles", "4", "--iterations", "1", "--no-polish", "--no-plots"]
LOOP = ["loop", "--model", "mass_spring_damper", "--params", "m,k,c", "--quiet",
        "--no-plots"]
SENS = ["sensitivity", "--model", "mass_spring_damper", "--quiet", "--no-plots"]

MODULES = {
    "fault_syntax.py": "def build(:\n    pass\n",
    "fault_notfn.py": "VALUE = 3\n",
    "fault_needsarg.py": "def build(n):\n    return n\n",
    "fault_retint.py": "def build():\n    return 3\n",
    "fault_annotated.py": "def build() -> dict:\n    return {}\n",
    "fault_raises.py": "def build():\n    raise RuntimeError('boom in the builder')\n",
    "fault_class.py": "class Thing:\n    pass\n",
    "fault_importerr.py": "import no_such_package_xyz\n\ndef build():\n    pass\n",
    "fault_revbounds.py": textwrap.dedent("""\
        from bondgraph.core.graph import BondGraph

        def build():
            g = BondGraph("rev")
            g.param("m", 2.0, "kg", (8.0, 0.5), "mass with reversed bounds")
            return g
        """),
    "fault_defout.py": textwrap.dedent("""\
        from bondgraph.core.graph import BondGraph

        def build():
            g = BondGraph("defout")
            g.param("k", 900.0, "N/m", (5.0, 500.0), "stiffness outside its bounds")
            return g
        """),
    "fault_nan_default.py": textwrap.dedent("""\
        from bondgraph.core.graph import BondGraph

        def build():
            g = BondGraph("nandef")
            g.param("c", float("nan"), "N*s/m", (0.1, 20.0))
            return g
        """),
}


def _csv_variants(d: Path, good: Path) -> None:
    """Bad records derived from the good one (CSV text edited)."""
    lines = good.read_text().splitlines()
    head, body = lines[0], lines[1:]
    side = json.loads(good.with_suffix(".json").read_text())

    def write(name, header, rows, sidecar=None):
        (d / f"{name}.csv").write_text("\n".join([header, *rows]) + "\n")
        if sidecar is not None:
            (d / f"{name}.json").write_text(json.dumps(sidecar))

    cut = [",".join(r.split(",")[:3]) for r in body]
    write("x_only", ",".join(head.split(",")[:3]), cut)           # t, F, x (issue item 1)
    xpos = dict(side, columns={("xpos" if k == "x" else k): v for k, v in side["columns"].items()})
    write("xpos", head.replace("x [m]", "xpos [m]"), body, xpos)
    write("evil_unit", head.replace("x [m]", "x [2**2**2**2**2**2**2]"), body)
    write("big_power", head.replace("x [m]", "x [m**99]"), body)
    write("bad_unit", head.replace("x [m]", "x [furlong_per_bogon]"), body)
    write("wrong_dim", head.replace("x [m]", "x [s]"), body)
    write("text_cell", head, [body[0], body[1].replace(body[1].split(",")[2], "abc", 1),
                              *body[2:]])
    write("time_back", head, [body[1], body[0], *body[2:]])
    write("dup_col", head + ",x [m]", [r + ",0" for r in body])
    write("header_only", head, [])
    write("true_text", head, body, dict(side, true_parameters={"m": "heavy", "k": 60.0}))
    write("dt_text", head, body, dict(side, dt="0.01 s"))
    cols = head.split(",")
    ix, iF = cols.index("x [m]"), next(i for i, c in enumerate(cols) if c.startswith("F"))

    def with_x(value):
        return [",".join(value if i == ix else c for i, c in enumerate(r.split(","))) for r in body]
    write("no_input", ",".join(c for i, c in enumerate(cols) if i != iF),
          [",".join(c for i, c in enumerate(r.split(",")) if i != iF) for r in body])
    write("const_x", head, with_x("0.5"))                        # a disconnected sensor
    write("empty_x", head, with_x(""))                           # a column with no sample
    write("short", head, body[:10], side)                        # 10 samples: 2 held out
    (d / "broken_json.csv").write_text("\n".join(lines) + "\n")
    (d / "broken_json.json").write_text("{ not json")
    (d / "empty.csv").write_text("")


@pytest.fixture(scope="module")
def d(tmp_path_factory):
    """A folder with the good record, its bad variants and faulty modules."""
    d = tmp_path_factory.mktemp("faults")
    rec = run_experiment("msd_force_step")
    rec.segment(0, N_SAMPLES, name="good").save(d / "good.csv")
    rec.segment(20, 20 + N_SAMPLES, name="other").save(d / "other.csv")
    _csv_variants(d, d / "good.csv")
    for name, text in MODULES.items():
        (d / name).write_text(text)
    (d / "a_file").write_text("not a folder")
    (d / "fault_good.py").write_text(
        "from bondgraph.catalog.reference import mass_spring_damper\n\n"
        "def build():\n    g = mass_spring_damper()\n    g.name = 'my_msd'\n    return g\n")
    (d / "full").mkdir()
    (d / "full" / "old_report.md").write_text("a previous run")
    return d


#: (kind, argv, substrings the message must contain); {d} is the fixture folder
CATALOGUE = [
    # -- command line usage (issue 4)
    ("usage", ["no_such_command"], ["unknown command 'no_such_command'"]),
    ("usage", ["estimat"], ["did you mean 'estimate'"]),
    ("usage", [*EST[:5]], ["--data"]),
    ("usage", [*EST, "--data", "{d}/good.csv", "--bogus-flag"], ["--bogus-flag"]),
    ("usage", [*EST, "--data", "{d}/good.csv", "--seed", "one"], ["--seed", "one"]),
    ("usage", [*EST, "--data", "{d}/good.csv", "--optimizer", "cmaes"], ["--optimizer", "cmaes"]),
    ("usage", [*EST, "--data", "{d}/good.csv", "--method", "euler"], ["--method", "euler"]),
    ("usage", ["loop", "--data", "{d}/good.csv", "--out", "{d}/r_nomodel"],
     ["--data", "needs --model"]),
    ("usage", ["loop", "--model", "mass_spring_damper", "--out", "{d}/r_nodata"], ["--data"]),
    ("usage", [*LOOP, "--data", "{d}/good.csv", "--criterion", "aicc"], ["--criterion", "aicc"]),
    ("usage", ["simulate", "mass_spring_damper", "--noise-std", "x=0.1", "-o", "{d}/n.csv"],
     ["--noise-std needs --noise"]),
    ("usage", ["simulate", "mass_spring_damper", "--noise", "--noise-std", "x=-1", "-o",
               "{d}/n.csv"], ["--noise-std", "x=-1.0", ">= 0"]),
    # -- option values (issue 4)
    ("options", [*LOOP, "--data", "{d}/good.csv", "--metric", "bogus", "--out", "{d}/r1"],
     ["--metric = 'bogus'", "nrmse_sim"]),
    ("options", [*LOOP, "--data", "{d}/good.csv", "--max-steps", "-1", "--out", "{d}/r2"],
     ["--max-steps must be an integer >= 0, got -1"]),
    ("options", [*LOOP, "--data", "{d}/good.csv", "--significance", "2", "--out", "{d}/r3"],
     ["--significance must lie in (0, 1), got 2"]),
    ("options", [*EST[:-8], "--particles", "0", "--data", "{d}/good.csv", "--out", "{d}/e1"],
     ["particles", "0"]),
    ("options", [*EST[:-8], "--particles", "-5", "--data", "{d}/good.csv", "--out", "{d}/e2"],
     ["particles", "-5"]),
    ("options", [*EST, "--iterations", "-1", "--data", "{d}/good.csv", "--out", "{d}/e3"],
     ["iterations", "-1"]),
    ("options", [*EST, "--stall", "0", "--data", "{d}/good.csv", "--out", "{d}/e4"],
     ["stall_iterations", "0"]),
    ("options", [*EST, "--workers", "0", "--data", "{d}/good.csv", "--out", "{d}/e5"],
     ["workers", "0"]),
    ("options", [*EST, "--substeps", "0", "--data", "{d}/good.csv", "--out", "{d}/e6"],
     ["substeps", "0"]),
    ("options", [*EST, "--alpha", "-1", "--data", "{d}/good.csv", "--out", "{d}/e7"],
     ["alpha", "-1"]),
    ("options", [*EST, "--fixed", "m:3", "--data", "{d}/good.csv", "--out", "{d}/e8"],
     ["--fixed", "m:3"]),
    ("options", [*EST, "--fixed", "m=three", "--data", "{d}/good.csv", "--out", "{d}/e9"],
     ["--fixed", "'m'"]),
    ("options", [*EST, "--fixed", "m=nan", "--params", "k,c", "--data", "{d}/good.csv",
                 "--out", "{d}/e11"], ["--fixed", "'m'", "not a finite number", "nan"]),
    ("options", [*EST, "--x0", "p_mass=inf", "--data", "{d}/good.csv", "--out", "{d}/e12"],
     ["--x0", "'p_mass'", "inf"]),
    ("options", ["simulate", "mass_spring_damper", "--input", "F=-inf", "-o", "{d}/sim2.csv"],
     ["--input", "'F'", "-inf"]),
    ("options", [*EST, "--resume", "--checkpoint", "{d}/no_ck.npz", "--data", "{d}/good.csv",
                 "--out", "{d}/e10"], ["checkpoint", "no_ck.npz", "does not exist"]),
    ("options", [*SENS, "--data", "{d}/good.csv", "--seconds", "0", "--out", "{d}/s1"],
     ["--seconds 0"]),
    # -- parameters and states named wrongly
    ("parameter", [*EST[:3], "--params", "m,stiffness", "--data", "{d}/good.csv",
                   "--out", "{d}/p1"], ["stiffness"]),
    ("parameter", [*EST, "--fixed", "m=3", "--data", "{d}/good.csv", "--params", "m",
                   "--out", "{d}/p2"], ["m both fixed and estimated"]),
    ("parameter", [*EST, "--x0", "velocity=1", "--data", "{d}/good.csv", "--out", "{d}/p3"],
     ["velocity"]),
    ("parameter", [*SENS, "--data", "{d}/good.csv", "--params", "m,spring", "--out", "{d}/p4"],
     ["'spring'"]),
    ("parameter", ["simulate", "mass_spring_damper", "--param", "mass=2", "-o",
                   "{d}/sim1.csv"], ["mass"]),
    ("parameter", [*LOOP, "--data", "{d}/good.csv", "--params", "m,q", "--out", "{d}/p5"],
     ["'q'"]),
    # -- models: names, modules, builders (issue 5)
    ("model", ["equations", "mass_spring_dampr"], ["mass_spring_dampr", "mass_spring_damper"]),
    ("model", ["simulate", "mass_spring_damper", "-e", "no_such_experiment"],
     ["no_such_experiment"]),
    ("model", [*LOOP, "--model", "no_such_module_abc:build", "--data", "{d}/good.csv",
               "--out", "{d}/m1"], ["no_such_module_abc", "current directory"]),
    ("model", [*LOOP, "--model", "fault_syntax:build", "--data", "{d}/good.csv",
               "--out", "{d}/m2"], ["fault_syntax", "SyntaxError"]),
    ("model", [*LOOP, "--model", "fault_importerr:build", "--data", "{d}/good.csv",
               "--out", "{d}/m3"], ["fault_importerr", "no_such_package_xyz"]),
    ("model", [*LOOP, "--model", "fault_notfn:VALUE", "--data", "{d}/good.csv",
               "--out", "{d}/m4"], ["fault_notfn:VALUE", "not a function"]),
    ("model", [*LOOP, "--model", "fault_notfn:build", "--data", "{d}/good.csv",
               "--out", "{d}/m5"], ["fault_notfn", "no attribute 'build'"]),
    ("model", [*LOOP, "--model", "fault_needsarg:build", "--data", "{d}/good.csv",
               "--out", "{d}/m6"], ["fault_needsarg:build", "argument(s) n"]),
    ("model", [*LOOP, "--model", "fault_retint:build", "--data", "{d}/good.csv",
               "--out", "{d}/m7"], ["fault_retint:build", "returned an int", "not a BondGraph"]),
    ("model", [*LOOP, "--model", "fault_annotated:build", "--data", "{d}/good.csv",
               "--out", "{d}/m8"], ["fault_annotated:build", "dict", "not a BondGraph"]),
    ("model", [*LOOP, "--model", "fault_raises:build", "--data", "{d}/good.csv",
               "--out", "{d}/m9"], ["fault_raises:build", "boom in the builder"]),
    ("model", [*LOOP, "--model", "fault_class:Thing", "--data", "{d}/good.csv",
               "--out", "{d}/m10"], ["fault_class:Thing", "class Thing"]),
    ("model", [*EST[:2], "{d}/missing_file.py:build", *EST[3:], "--data", "{d}/good.csv",
               "--out", "{d}/m11"], ["missing_file.py"]),
    ("model", [*LOOP, "--model", "fault_revbounds:build", "--data", "{d}/good.csv",
               "--out", "{d}/m12"], ["'m'", "bounds"]),
    ("model", [*LOOP, "--model", "fault_defout:build", "--data", "{d}/good.csv",
               "--out", "{d}/m13"], ["'k'", "900"]),
    ("model", [*LOOP, "--model", "fault_nan_default:build", "--data", "{d}/good.csv",
               "--out", "{d}/m14"], ["'c'", "nan"]),
    # -- records and sidecars (issues 5, 6)
    ("data", [*EST, "--data", "{d}/no_such.csv", "--out", "{d}/d1"], ["no_such.csv"]),
    ("data", [*EST, "--data", "{d}/empty.csv", "--out", "{d}/d2"], ["empty.csv"]),
    ("data", [*EST, "--data", "{d}/header_only.csv", "--out", "{d}/d3"], ["header_only.csv"]),
    ("data", [*EST, "--data", "{d}/text_cell.csv", "--out", "{d}/d4"],
     ["text_cell.csv", "line 3", "abc"]),
    ("data", [*EST, "--data", "{d}/time_back.csv", "--out", "{d}/d5"], ["time_back.csv", "line"]),
    ("data", [*EST, "--data", "{d}/dup_col.csv", "--out", "{d}/d6"], ["dup_col.csv", "'x'"]),
    ("data", [*EST, "--data", "{d}/evil_unit.csv", "--out", "{d}/d7"],
     ["evil_unit.csv", "column 'x'", "power of a power"]),
    ("data", [*EST, "--data", "{d}/big_power.csv", "--out", "{d}/d7b"],
     ["big_power.csv", "column 'x'", "m**99", "beyond"]),
    ("data", [*EST, "--data", "{d}/bad_unit.csv", "--out", "{d}/d8"],
     ["bad_unit.csv", "furlong_per_bogon"]),
    ("data", [*EST, "--data", "{d}/wrong_dim.csv", "--out", "{d}/d9"], ["wrong_dim.csv", "'x'"]),
    ("data", [*EST, "--data", "{d}/true_text.csv", "--out", "{d}/d10"],
     ["true_text.json", "true_parameters", "heavy"]),
    ("data", [*EST, "--data", "{d}/dt_text.csv", "--out", "{d}/d11"],
     ["dt_text.json", "dt", "0.01 s"]),
    ("data", [*EST, "--data", "{d}/broken_json.csv", "--out", "{d}/d12"], ["broken_json.json"]),
    ("data", ["plot", "{d}/no_such_record.csv", "-o", "{d}/pl"], ["no_such_record.csv"]),
    ("data", [*LOOP, "--data", "{d}/good.csv", "--validate", "{d}/no_input.csv",
              "--out", "{d}/d13"], ["no_input.csv", "column 'F'", "missing column(s) 'F'"]),
    ("data", [*LOOP, "--data", "{d}/no_input.csv", "--out", "{d}/d14"],
     ["no_input.csv", "column 'F'", "missing column(s) 'F'"]),
    ("data", [*EST, "--data", "{d}/const_x.csv", "--out", "{d}/d15"],
     ["const_x.csv", "column 'x'", "reads 0.5 m at every sample"]),
    ("data", [*LOOP, "--data", "{d}/empty_x.csv", "--out", "{d}/d16"],
     ["empty_x.csv", "column 'x'", "has no sample"]),
    ("data", [*LOOP, "--data", "{d}/short.csv", "--out", "{d}/d17"],
     ["10-sample record", "leaves 2 samples to judge by", "--holdout 0"]),
    # -- output folders (issue 3, 5)
    ("output", [*EST, "--data", "{d}/good.csv", "--out", "{d}/full"],
     ["--out", "full", "not empty", "--overwrite"]),
    ("output", [*LOOP, "--data", "{d}/good.csv", "--out", "{d}/full"],
     ["--out", "full", "not empty", "--overwrite"]),
    ("output", [*SENS, "--data", "{d}/good.csv", "--out", "{d}/full"], ["full", "not empty"]),
    ("output", [*EST, "--data", "{d}/good.csv", "--out", "{d}/a_file"], ["a_file", "is a file"]),
    ("output", [*LOOP, "--data", "{d}/good.csv", "--out", "{d}/a_file/sub"],
     ["a_file", "cannot create"]),
    ("output", [*EST, "--data", "{d}/good.csv", "--out", "/proc/bondgraph_out"],
     ["--out", "/proc/bondgraph_out"]),
    # -- estimation that cannot succeed (issue 4)
    ("estimation", [*EST[:3], "--params", "k,c", *EST[5:], "--fixed", "m=0",
                    "--data", "{d}/good.csv", "--out", "{d}/n1"],
     ["no finite NLL", "k, c", "mass_spring_damper"]),
]

KINDS = Counter(kind for kind, _, _ in CATALOGUE)


def _ids():
    seen: Counter = Counter()
    out = []
    for kind, argv, _ in CATALOGUE:
        key = f"{kind}-{argv[0]}"
        seen[key] += 1
        out.append(f"{key}-{seen[key]}")
    return out


@pytest.mark.parametrize("kind, argv, needles", CATALOGUE, ids=_ids())
def test_fault_is_a_named_error_with_exit_code_2(kind, argv, needles, d, capsys, monkeypatch):
    monkeypatch.chdir(d)                      # --model modules come from the current folder
    rc = main([a.replace("{d}", str(d)) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    errors = [ln for ln in lines if ln.startswith("bondgraph") and ": error: " in ln]
    assert len(errors) == 1, err                   # one line names the fault ...
    rest = lines[lines.index(errors[0]) + 1:]
    assert all(ln.startswith("  Remedy: ") for ln in rest), err      # ... then at most a remedy
    assert len(rest) <= 1, err
    for needle in needles:
        assert needle in err, f"{needle!r} not in {err!r}"


def test_catalogue_size_and_kinds():
    """At least 40 faults; every kind of the issue present."""
    assert len(CATALOGUE) >= 40
    assert set(KINDS) == {"usage", "options", "parameter", "model", "data", "output",
                          "estimation"}


def _run(argv, d):
    return main([a.replace("{d}", str(d)) for a in argv])


def test_misspelt_column_is_a_warning_naming_the_closest_name(d, capsys):
    """`xpos` for `x` (issue 4): the run goes on, with a ColumnWarning that
    names the unmatched column, the absent output and the closest name."""
    assert _run([*EST, "--data", "{d}/xpos.csv", "--out", "{d}/w1"], d) == 0
    err = capsys.readouterr().err
    assert "bondgraph estimate: warning:" in err
    assert "'xpos'" in err and "output(s) 'x'" in err and "'xpos' -> 'x'" in err
    assert _run([*EST, "--data", "{d}/good.csv", "--out", "{d}/w2"], d) == 0
    assert "warning" not in capsys.readouterr().err


def test_columns_renamed_as_they_are_read(d, capsys):
    """`--columns xpos=x` reads a logger's name as the model's output: the
    estimate equals that of the record whose column is named x; the warning
    about the unmatched column names the option; a rename of a column the
    file lacks, or onto another column's name, is refused naming it."""
    assert _run([*EST, "--data", "{d}/xpos.csv", "--out", "{d}/r0"], d) == 0
    assert "--columns COLUMN=NAME" in capsys.readouterr().err
    assert _run([*EST, "--data", "{d}/xpos.csv", "--columns", "xpos=x", "--out", "{d}/r1"],
                d) == 0
    assert "warning" not in capsys.readouterr().err
    assert _run([*EST, "--data", "{d}/good.csv", "--out", "{d}/r2"], d) == 0
    a, b = (json.loads((d / r / "result.json").read_text()) for r in ("r1", "r2"))
    assert a["estimates"] == b["estimates"]
    assert _run([*EST, "--data", "{d}/xpos.csv", "--columns", "pos=x", "--out", "{d}/r3"],
                d) == 2
    assert "no column 'pos' to rename to 'x'" in capsys.readouterr().err
    assert _run([*EST, "--data", "{d}/good.csv", "--columns", "v=x", "--out", "{d}/r4"], d) == 2
    assert "two columns named 'x'" in capsys.readouterr().err
    assert _run([*EST, "--data", "{d}/good.csv", "--columns", "v", "--out", "{d}/r5"], d) == 2
    assert "COLUMN=NAME" in capsys.readouterr().err


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_loop_on_a_record_without_one_output_runs(d, capsys):
    """Issue item 1: `cut -d, -f1-3` of the record (t, F, x; no v, no
    sidecar) no longer crashes the loop, nor warns about NaN statistics; the
    report says v was not measured."""
    assert _run([*LOOP, "--data", "{d}/x_only.csv", "--out", "{d}/xo", "--max-steps", "1",
                 "--no-structural"], d) == 0
    rep = json.loads((d / "xo" / "report.json").read_text())
    assert rep["finished"] is True
    by_name = {o["name"]: o for o in rep["initial_fit"]["residuals"]["outputs"]}
    # the fits use the record less its held-out end (DEFAULT_HOLDOUT without --validate)
    fitted = int(round(N_SAMPLES * (1 - DEFAULT_HOLDOUT)))
    assert by_name["x"]["n"] == fitted and by_name["x"]["rms"] > 0
    assert rep["settings"]["holdout"] == DEFAULT_HOLDOUT
    assert rep["validation_error_before"] is not None
    assert by_name["v"]["n"] == 0 and by_name["v"]["rms"] is None
    assert "| v | not in the record |" in (d / "xo" / "report.md").read_text()


def test_resume_from_a_checkpoint_of_other_data_is_refused(d, capsys):
    """Issue item 2: the checkpoint carries a fingerprint of the data; resuming
    with another record names what differs."""
    ck = str(d / "ck_good.npz")
    assert _run([*EST, "--data", "{d}/good.csv", "--out", "{d}/c1", "--checkpoint", ck], d) == 0
    capsys.readouterr()
    rc = _run([*EST, "--data", "{d}/other.csv", "--out", "{d}/c2", "--checkpoint", ck,
               "--resume"], d)
    err = capsys.readouterr().err
    assert rc == 2 and "ck_good.npz" in err and "data" in err
    rc = _run([*EST[:3], "--params", "m,k", *EST[5:], "--data", "{d}/good.csv",
               "--out", "{d}/c3", "--checkpoint", ck, "--resume"], d)
    err = capsys.readouterr().err
    assert rc == 2 and "param" in err
    # the same problem resumes
    assert _run([*EST, "--data", "{d}/good.csv", "--out", "{d}/c4", "--checkpoint", ck,
                 "--resume"], d) == 0


def test_overwrite_replaces_the_folder_as_a_whole(d, tmp_path):
    """Issue item 3: with --overwrite the old folder's files are gone (not
    mixed with the new ones); the result is written last."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "augmented_model.py").write_text("# a previous run")
    (out / "generated").mkdir()
    assert _run([*EST, "--data", "{d}/good.csv", "--out", str(out)], d) == 2
    assert (out / "augmented_model.py").exists()           # refused: untouched
    assert _run([*EST, "--data", "{d}/good.csv", "--out", str(out), "--overwrite"], d) == 0
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.npz", "result.json"]
    assert not list(tmp_path.glob(".out.*")), "staging or working folders left behind"


def test_model_module_is_imported_from_the_current_folder(d, monkeypatch, capsys):
    """`--model fault_good:build` finds fault_good.py in the current folder."""
    monkeypatch.chdir(d)
    assert _run([*EST[:2], "fault_good:build", *EST[3:], "--data", "{d}/good.csv",
                 "--out", "{d}/g1"], d) == 0
    res = json.loads((d / "g1" / "result.json").read_text())
    assert res["model"] == "my_msd"


def test_loop_warns_about_a_misspelt_column_of_its_graph(d, capsys):
    """The loop reads the record against the declared graph (its sensors and
    derived states): the same ColumnWarning, before any fit (here the run
    then stops at a bad --metric)."""
    rc = _run([*LOOP, "--data", "{d}/xpos.csv", "--metric", "bogus", "--out", "{d}/lw"], d)
    err = capsys.readouterr().err
    assert rc == 2 and "bondgraph loop: warning:" in err and "'xpos' -> 'x'" in err
    assert "state.p_mass" not in err            # state columns are known (derived states)
