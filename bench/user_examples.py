"""Users' graphs on the real records (issue 26): the examples run as a new
user runs them, their figures against the last recorded run.

``bench/real_loops.py`` checks the bundled cases, whose options are tuned;
a change to the loop (a faster line search, another start) can move the
result of a user's graph with no options while every bundled figure stays
(the sixty-third session's staged line search moved the user's EMPS graph
from the direction-dependent friction, held out 0.01319, to a quadratic
encoder term, 0.01878, and no check saw it). This script runs each example
in a child process, one after the other (one heavy run at a time), takes
the JSON summary the example prints last, adds the wall time, and compares
the accepted effects and the figures with ``bench/results/user_examples.json``
(the previous run): a figure that moved by more than 1 % or an accepted
list that changed is reported as ``changed``.

Examples (about 30 min in all on a 2-core machine):

* ``emps`` -- ``examples/emps_user.py``: the user's EMPS graph, held-out
  position NRMSE; ``emps_x10`` the same on every tenth sample
  (``--decimate 10``); ``emps_screw`` another user's graph of it (rotor,
  ball screw, load) on every tenth sample;
* ``silverbox`` -- ``examples/silverbox_user.py``: a mass-spring-damper,
  arrow and multisine test sets [mV];
* ``silverbox_rlc`` -- the same with ``--graph rlc``, a series RLC circuit;
* ``ced`` -- ``examples/ced_user.py``: another user's belt drive, RMS on the
  three PRBS runs; ``ced_unif`` the same graph fitted on the first
  uniform-amplitude run (``--runs unif``), RMS on all five runs.

They read ``../shared/data`` (or ``BONDGRAPH_DATA``); an example whose data
is absent is reported as skipped with the reason.

Usage: python bench/user_examples.py [--examples emps,ced] [--no-save]
Last line JSON; also written to bench/results/user_examples.json (unless
``--no-save``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULT = Path(__file__).with_name("results") / "user_examples.json"

#: example -> (script, extra arguments)
EXAMPLES = {
    "emps": ("emps_user.py", []),
    "emps_x10": ("emps_user.py", ["--decimate", "10"]),
    "emps_screw": ("emps_user.py", ["--graph", "screw", "--decimate", "10"]),
    "emps_closed": ("emps_user.py", ["--graph", "closed", "--decimate", "10"]),
    "silverbox": ("silverbox_user.py", []),
    "silverbox_rlc": ("silverbox_user.py", ["--graph", "rlc"]),
    "ced": ("ced_user.py", []),
    "ced_unif": ("ced_user.py", ["--runs", "unif"]),
    "ced_abs": ("ced_user.py", ["--graph", "abs"]),
}
#: a figure that moved by more than this relative amount is a change
RTOL = 0.01


def data_dir() -> Path:
    """The folder of the real records: ``BONDGRAPH_DATA`` or ``../shared/data``."""
    return Path(os.environ.get("BONDGRAPH_DATA") or ROOT.parent / "shared" / "data")


def run_example(name: str, out: Path) -> dict:
    """Run one example in a child process: its JSON summary (the last line
    it prints) with ``wall_s``, or ``{"skipped": reason}`` /
    ``{"failed": ...}``."""
    script, extra = EXAMPLES[name]
    env = {**os.environ, "BONDGRAPH_DATA": str(data_dir())}
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / script), "--out",
                           str(out / name), *extra], capture_output=True, text=True, env=env,
                          cwd=ROOT)
    wall = round(time.perf_counter() - t0, 1)
    lines = [s for s in proc.stdout.splitlines() if s.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        if any("not in the data folder" in s or "DataError" in s for s in tail):
            return {"skipped": " ".join(tail), "wall_s": wall}
        return {"failed": f"exit {proc.returncode}: {' '.join(tail)}", "wall_s": wall}
    return {**json.loads(lines[-1]), "wall_s": wall}


def numbers(d, prefix: str = "") -> dict:
    """The numeric figures of a summary by dotted key (times left out)."""
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(numbers(v, key + "."))
        elif isinstance(v, (int, float)) and not isinstance(v, bool) \
                and not key.endswith("_s") and "seconds" not in key:
            out[key] = float(v)
    return out


def changes(now: dict, before: dict | None) -> list[str]:
    """What moved against the previous run of the same example: the
    accepted effects, and each figure beyond :data:`RTOL`."""
    if not before or "skipped" in before or "failed" in before:
        return []
    said = []
    if now.get("accepted") != before.get("accepted"):
        said.append(f"accepted {before.get('accepted')} -> {now.get('accepted')}")
    a, b = numbers(now), numbers(before)
    for k in sorted(set(a) & set(b)):
        if abs(a[k] - b[k]) > RTOL * max(abs(b[k]), 1e-12):
            said.append(f"{k} {b[k]:.6g} -> {a[k]:.6g}")
    return said


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--examples", default=",".join(EXAMPLES),
                    help=f"comma-separated, of {', '.join(EXAMPLES)}")
    ap.add_argument("--no-save", action="store_true", help="do not write the results file")
    a = ap.parse_args(argv)
    names = [s.strip() for s in a.examples.split(",") if s.strip()]
    unknown = [s for s in names if s not in EXAMPLES]
    if unknown:
        ap.error(f"unknown example(s) {', '.join(unknown)}; known: {', '.join(EXAMPLES)}")
    previous = json.loads(RESULT.read_text()).get("examples", {}) if RESULT.exists() else {}
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            print(f"{name}: running ...", flush=True)
            r = run_example(name, Path(tmp))
            r["changed"] = changes(r, previous.get(name))
            res[name] = r
            print(f"{name}: {json.dumps(r)}", flush=True)
    doc = {"examples": {**previous, **res}, "date": time.strftime("%Y-%m-%d"),
           "load": os.getloadavg()[0]}
    if not a.no_save:
        RESULT.parent.mkdir(exist_ok=True)
        RESULT.write_text(json.dumps(doc, indent=1) + "\n")
    print(json.dumps({"examples": res}))
    return doc


if __name__ == "__main__":
    main()
