"""Atomic outputs (bondgraph.core.atomic) and checkpoint fingerprints
(bondgraph.inference.checkpoint), issue 13 items 2 and 3."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bondgraph.core import atomic
from bondgraph.core.atomic import OutputFolder
from bondgraph.errors import CheckpointError, OutputError
from bondgraph.inference import checkpoint
from bondgraph.inference.optimize import pso
from bondgraph.inference.options import Checkpointing, SwarmOptions


def _files(folder):
    return {p.name: p.read_text() for p in folder.iterdir()}


def test_write_text_replaces_and_leaves_no_temporary(tmp_path):
    p = tmp_path / "a.txt"
    atomic.write_text(p, "one")
    atomic.write_text(p, "two")
    assert p.read_text() == "two" and [q.name for q in tmp_path.iterdir()] == ["a.txt"]
    with pytest.raises(OutputError, match="no_dir"):
        atomic.write_text(tmp_path / "no_dir" / "b.txt", "x")


def test_replace_file_keeps_the_old_file_when_the_writer_fails(tmp_path):
    p = tmp_path / "c.npz"
    atomic.replace_file(p, lambda tmp: np.savez(tmp, a=np.arange(3)))

    def broken(tmp):
        tmp.write_bytes(b"half")
        raise RuntimeError("writer died")
    with pytest.raises(RuntimeError, match="writer died"):
        atomic.replace_file(p, broken)
    assert list(np.load(p)["a"]) == [0, 1, 2]
    assert [q.name for q in tmp_path.iterdir()] == ["c.npz"]


def test_output_folder_refuses_a_non_empty_folder_or_a_file(tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "old.md").write_text("old")
    with pytest.raises(OutputError, match=r"--out .*full is not empty \(it holds old.md\)"):
        OutputFolder(tmp_path / "full")
    (tmp_path / "f").write_text("")
    with pytest.raises(OutputError, match="is a file"):
        OutputFolder(tmp_path / "f", overwrite=True)
    OutputFolder(tmp_path / "full", overwrite=True)           # allowed, nothing written yet
    assert _files(tmp_path / "full") == {"old.md": "old"}
    (tmp_path / "empty").mkdir()
    OutputFolder(tmp_path / "empty")                           # an empty folder is fine


@pytest.mark.parametrize("swap", ["exchange", "two renames"])
def test_publish_replaces_the_folder_as_a_whole(tmp_path, monkeypatch, swap):
    if swap == "two renames":
        monkeypatch.setattr(atomic, "exchange", lambda a, b: False)
    out = tmp_path / "out"
    out.mkdir()
    (out / "augmented_model.py").write_text("previous run")
    folder = OutputFolder(out, overwrite=True)
    assert folder.publish(lambda d: (d / "report.json").write_text("v1")) == 2
    assert _files(out) == {"report.json": "v1"}
    folder.publish(lambda d: [(d / "report.md").write_text("m2"),
                              (d / "report.json").write_text("v2")])
    assert _files(out) == {"report.json": "v2", "report.md": "m2"}

    def dies(d):
        (d / "report.json").write_text("v3, half")
        raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        folder.publish(dies)
    assert _files(out) == {"report.json": "v2", "report.md": "m2"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"], "staging left behind"


def test_stale_staging_of_a_dead_process_is_removed(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()
    stale = tmp_path / f".out.staging-{dead}-0"
    stale.mkdir()
    live = tmp_path / f".out.staging-{os.getpid()}-99"
    live.mkdir()
    OutputFolder(tmp_path / "out")
    assert not stale.exists() and live.exists()


def test_work_dir_is_beside_the_folder(tmp_path):
    folder = OutputFolder(tmp_path / "out")
    w = folder.work_dir(create=False)
    assert w == tmp_path / ".out.work" and not w.exists()
    assert folder.work_dir().is_dir()
    folder.remove_work_dir()
    assert not w.exists()


def test_fingerprint_check_names_what_differs(tmp_path):
    a = {"data (t, u, y arrays)": checkpoint.digest(np.arange(3.0)), "parameter list": "m, k"}
    same = dict(a)
    checkpoint.check(tmp_path / "ck.npz", checkpoint.encode(a), same)
    b = {"data (t, u, y arrays)": checkpoint.digest(np.arange(3.0) + 1e-12),
         "parameter list": "m, c"}
    with pytest.raises(CheckpointError) as e:
        checkpoint.check(tmp_path / "ck.npz", checkpoint.encode(a), b)
    assert set(e.value.differs) == {"data (t, u, y arrays)", "parameter list"}
    msg = str(e.value)
    assert "ck.npz" in msg and "parameter list (checkpoint: m, k, now: m, c)" in msg
    assert a["data (t, u, y arrays)"] not in msg                 # hashes are not shown
    with pytest.raises(CheckpointError, match="no fingerprint"):
        checkpoint.check(tmp_path / "ck.npz", None, b)


def test_pso_resume_refuses_another_problem_and_continues_the_same(tmp_path):
    ck = tmp_path / "ck.npz"

    def f(X):
        return np.sum((X - 0.3) ** 2, axis=1)
    six = SwarmOptions(particles=6, seed=2, iterations=6)
    three = SwarmOptions(particles=6, seed=2, iterations=3)
    write = Checkpointing(ck, fingerprint={"data": "A"})
    resume = Checkpointing(ck, resume=True, fingerprint={"data": "A"})
    full = pso(f, [-1.0] * 2, [1.0] * 2, swarm=six, checkpointing=write, progress=False)
    pso(f, [-1.0] * 2, [1.0] * 2, swarm=three, checkpointing=write, progress=False)
    with pytest.raises(CheckpointError, match="data"):
        pso(f, [-1.0] * 2, [1.0] * 2, swarm=six, progress=False,
            checkpointing=Checkpointing(ck, resume=True, fingerprint={"data": "B"}))
    with pytest.raises(CheckpointError):
        pso(f, [-1.0] * 2, [2.0] * 2, swarm=six, checkpointing=resume, progress=False)
    resumed = pso(f, [-1.0] * 2, [1.0] * 2, swarm=six, checkpointing=resume, progress=False)
    np.testing.assert_array_equal(resumed.x, full.x)
    assert resumed.fun == full.fun and resumed.resumed_from == 3


def test_default_folder_is_numbered_past_earlier_results(tmp_path):
    """Without --out a command takes its default folder when absent or empty,
    else the first free ``-2``, ``-3``, ...; nothing earlier is touched."""
    from bondgraph.cli.common import unused_folder

    base = tmp_path / "bondgraph-report"
    assert unused_folder(base) == base
    base.mkdir()
    assert unused_folder(base) == base                      # empty: used as is
    (base / "report.md").write_text("1")
    assert unused_folder(base) == tmp_path / "bondgraph-report-2"
    (tmp_path / "bondgraph-report-2").mkdir()
    (tmp_path / "bondgraph-report-2" / "report.md").write_text("2")
    (tmp_path / "bondgraph-report-3").write_text("a file, not a folder")
    assert unused_folder(base) == tmp_path / "bondgraph-report-4"
    assert (base / "report.md").read_text() == "1"


def test_compare_and_estimate_defaults_keep_an_earlier_result(tmp_path, capsys):
    """``bondgraph compare`` and ``estimate`` without --out: a second run
    goes to ``-2`` and says so on stderr (it was refused as "not empty":
    the same command run twice failed); ``--out`` is taken as given;
    ``--resume`` without --out finds the folder whose checkpoint it resumes
    (the working folder of an interrupted run, or a published one)."""
    from types import SimpleNamespace

    from bondgraph.cli.common import default_out

    base = tmp_path / "compare_door_test"
    run = SimpleNamespace(out=None, quiet=False)
    assert default_out(run, base, "compare") == base
    base.mkdir()
    (base / "compare.json").write_text("{}")
    assert default_out(run, base, "compare") == tmp_path / "compare_door_test-2"
    assert "bondgraph compare: ./" + str(base) + " holds an earlier result (kept); this one " \
           "goes to ./" + str(tmp_path / "compare_door_test-2") in capsys.readouterr().err
    assert default_out(SimpleNamespace(out="x", quiet=False), base, "compare") == Path("x")
    assert default_out(SimpleNamespace(out=None, quiet=True), base, "compare").name \
        == "compare_door_test-2" and capsys.readouterr().err == ""
    # estimate --resume: base finished (result, no checkpoint), base-2
    # interrupted (its checkpoint in .base-2.work), base-3 never started
    est = tmp_path / "estimate_msd_rec"
    est.mkdir()
    (est / "result.json").write_text("{}")
    work = tmp_path / ".estimate_msd_rec-2.work"
    work.mkdir()
    (work / "checkpoint.npz").write_bytes(b"")
    resume = SimpleNamespace(out=None, quiet=False, resume=True)
    assert default_out(resume, est, "estimate") == tmp_path / "estimate_msd_rec-2"
    (est / "checkpoint.npz").write_bytes(b"")
    assert default_out(resume, est, "estimate") == tmp_path / "estimate_msd_rec-2"
    (work / "checkpoint.npz").unlink()
    work.rmdir()
    assert default_out(resume, est, "estimate") == est      # the published checkpoint
    fresh = SimpleNamespace(out=None, quiet=True, resume=False)
    assert default_out(fresh, est, "estimate") == tmp_path / "estimate_msd_rec-2"
