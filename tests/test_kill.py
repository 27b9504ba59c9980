"""Fault injection (issue 13): ``bondgraph estimate`` and ``bondgraph loop``
killed with SIGKILL at random points, then rerun (``--resume`` for the
estimation).

* After every kill the output folder holds one whole run: either the
  previous run's folder, untouched (same files, same bytes), or one complete
  version written by one attempt of the new run (every file's time within
  that attempt, the result file present and of the new record), never a mix.
* After the rerun the result equals that of an uninterrupted run: the same
  estimates, NLL and optimizer history; the same loop report.

A small problem (120 samples, a swarm of 6 for 8 iterations; the loop with
one step) keeps each run at a few seconds; the whole file takes about two
minutes. It is part of the default run (marked ``slow``, not skipped).
"""

from __future__ import annotations

import json
import random
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bondgraph.data.experiments import run_experiment

KILLS = 3
EST = ["estimate", "--model", "mass_spring_damper", "--params", "m,k,c", "--quiet",
       "--method", "rk4", "--particles", "6", "--iterations", "8", "--seed", "3"]
LOOP = ["loop", "--model", "mass_spring_damper", "--params", "m,k,c", "--quiet",
        "--max-steps", "1", "--no-structural"]


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    d = tmp_path_factory.mktemp("kill")
    rec = run_experiment("msd_force_step")
    rec.segment(0, 120, name="good").save(d / "good.csv")
    rec.segment(20, 140, name="other").save(d / "other.csv")
    return d


def _start(args, cwd) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "bondgraph.cli.main", *map(str, args)],
                            cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _run(args, cwd) -> float:
    """Run to the end; its wall time [s]."""
    t0 = time.monotonic()
    p = _start(args, cwd)
    err = p.communicate()[1].decode()
    assert p.returncode == 0, err
    return time.monotonic() - t0


def _reference(args, cwd) -> float:
    """The uninterrupted reference run, then its wall time [s] once the
    compiled kernels are cached (run again into the same folder): the kill
    times are drawn up to that time. With a fresh kernel cache the first run
    also compiles, and kill times drawn from its wall time mostly fell after
    the end of a cached run: a few hundred attempts to reach KILLS kills."""
    _run(args, cwd)
    return _run([*args, "--overwrite"], cwd)


def _attempt(args, cwd, kill_after: float):
    """Start a run and SIGKILL it after ``kill_after`` s; (start, end, killed)."""
    start = time.time()
    p = _start(args, cwd)
    try:
        p.wait(timeout=kill_after)
        killed = False
    except subprocess.TimeoutExpired:
        p.kill()                                   # SIGKILL
        p.wait()
        killed = True
    err = p.stderr.read().decode()
    p.stderr.close()
    assert killed or p.returncode == 0, err
    return start - 0.01, time.time() + 0.01, killed


def _snapshot(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _one_whole_run(out: Path, old: dict, attempts: list, result_file: str, check_new) -> str:
    """'old' if ``out`` is the previous run's folder untouched, 'new' if it is
    one complete version written by a single attempt; fails otherwise."""
    assert out.is_dir(), "the output folder disappeared"
    now = _snapshot(out)
    if now == old:
        return "old"
    assert result_file in now, f"a folder without {result_file}: {sorted(now)}"
    times = [p.stat().st_mtime for p in out.rglob("*") if p.is_file()]
    assert any(a <= min(times) and max(times) <= b for a, b, _ in attempts), \
        f"files of {out} written by different runs: {sorted(now)}"
    check_new(json.loads(now[result_file]), now)
    return "new"


def _kill_campaign(base, out, old_args, records, result_file, check_new, resume, total_s):
    """Kill attempts at random points until ``KILLS`` kills happened; return the
    states seen and the attempts."""
    rng = random.Random(13)
    _run([*base[:1], *old_args, "--out", out], records)
    old = _snapshot(out)
    assert old
    attempts, seen, kills = [], [], 0
    while kills < KILLS:
        args = [*base, "--out", out, "--overwrite"]
        if resume and (out.parent / f".{out.name}.work" / "checkpoint.npz").exists():
            args.append("--resume")
        a = _attempt(args, records, rng.uniform(0.0, 1.1 * total_s))
        attempts.append(a)
        kills += a[2]
        seen.append(_one_whole_run(out, old, attempts, result_file, check_new))
    print(f"{base[0]}: {len(attempts)} attempts, {kills} killed; the folder after each: "
          f"{', '.join(seen)}")
    return attempts, seen


def _same_estimate(a: dict, b: dict) -> None:
    for key in ("params", "estimates", "std", "nll"):
        assert a[key] == b[key], key
    for key in ("x", "fun", "history"):
        assert a["optimizer_result"][key] == b["optimizer_result"][key], key


@pytest.mark.slow
def test_estimate_killed_at_random_points_resumes_to_the_same_result(records):
    data = records / "good.csv"
    ref_dir = records / "est_ref"
    wall = _reference([*EST, "--data", data, "--out", ref_dir], records)
    ref = json.loads((ref_dir / "result.json").read_text())
    out = records / "est_out"

    def check_new(res, files):
        assert res["settings"]["data"] == str(data)
        assert set(files) == {"result.json", "checkpoint.npz", "fit_outputs.png",
                              "innovations.png"}
        _same_estimate(res, ref)

    old_args = [*EST[1:], "--seed", "99", "--data", records / "other.csv"]
    attempts, seen = _kill_campaign([*EST, "--data", data], out, old_args, records,
                                    "result.json", check_new, True, wall)
    assert sum(a[2] for a in attempts) >= KILLS
    # the rerun after the last kill
    args = [*EST, "--data", data, "--out", out, "--overwrite"]
    if (records / ".est_out.work" / "checkpoint.npz").exists():
        args.append("--resume")
    _run(args, records)
    _same_estimate(json.loads((out / "result.json").read_text()), ref)
    assert not list(records.glob(".est_out.*")), "staging or working folders left behind"


@pytest.mark.slow
def test_loop_killed_at_random_points_reruns_to_the_same_report(records):
    data = records / "good.csv"
    ref_dir = records / "loop_ref"
    wall = _reference([*LOOP, "--data", data, "--out", ref_dir], records)
    ref = _snapshot(ref_dir)
    out = records / "loop_out"

    def check_new(rep, files):
        assert rep["record"] == "good[0:90]"     # the last 25 % held out (no --validate)
        md = files["report.md"].decode()
        pngs = {name for name in files if name.endswith(".png")}
        assert pngs and all(f"({p})" in md for p in pngs)
        assert ("augmented_model.py" in files) == (rep["augmented_model"] is not None)
        if rep["finished"]:
            assert files["report.json"] == ref["report.json"]

    old_args = [*LOOP[1:], "--data", records / "other.csv"]
    attempts, seen = _kill_campaign([*LOOP, "--data", data], out, old_args, records,
                                    "report.json", check_new, False, wall)
    assert sum(a[2] for a in attempts) >= KILLS
    _run([*LOOP, "--data", data, "--out", out, "--overwrite"], records)
    now = _snapshot(out)
    assert sorted(now) == sorted(ref)
    for name in now:
        if name != "loop.log":                      # the log holds wall times
            assert now[name] == ref[name], name
    assert json.loads(now["report.json"])["finished"] is True
    assert not list(records.glob(".loop_out.*")), "staging or working folders left behind"
