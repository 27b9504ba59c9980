"""The loop on the real records, warm (issue 27): seconds and figures.

Runs ``bondgraph loop --case NAME`` for the bundled real-record cases in a
child process each, one after the other (one heavy run at a time), with the
kernel caches of this installation (warm: run it twice, or after the test
suite, to leave compilation out; ``--cold DIR`` runs with empty caches in DIR
instead). For each case it reports the wall time, the accepted effects, the
error before and after on the estimation record and on the held-out one
(from the case's ``report.json``), so that a speed-up that changes a result
shows, and the discretisation warnings the loop left in its report (a
bundled case should have none) and the substeps it adopted
(``auto_substeps``; throughout, or on the intervals that need them).
Target (issue 27): <= 30 s per case, the same figures.

Cases: ``silverbox --max-steps 1`` (arrow region, mV), ``ced`` (held-out u3
free-run RMS), ``emps`` (force error in %, held-out pulse run). They read
``../shared/data`` (or ``BONDGRAPH_DATA``); a case whose data is absent is
reported as skipped with the reason.

Usage: python bench/real_loops.py [--cases silverbox,ced,emps] [--cold DIR]
Last line JSON; also written to bench/results/real_loops.json.
"""

from __future__ import annotations

import argparse
import json
import re
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RESULT = Path(__file__).with_name("results") / "real_loops.json"

#: case -> extra arguments of `bondgraph loop`
CASES = {"silverbox": ["--max-steps", "1"], "ced": [], "emps": []}


def run_case(name: str, extra: list[str], out: Path, env: dict) -> dict:
    """One `bondgraph loop --case name` in a child; its time and figures."""
    cmd = [sys.executable, "-m", "bondgraph.cli.main", "loop", "--case", name, "--out", str(out),
           "--overwrite", *extra]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        tail = (p.stdout + p.stderr).strip().splitlines()[-5:]
        return {"case": name, "wall_s": round(wall, 1), "exit": p.returncode,
                "skipped": "\n".join(tail)}
    rep = json.loads((out / "report.json").read_text())
    return {"case": name, "args": extra, "wall_s": round(wall, 1), "metric": rep["metric"],
            "accepted": [" + ".join([f"{s['effect']} @ {s['attached_to']}",
                                     *s.get("together_with", [])]) for s in rep["steps"]],
            "error_before": rep["error_before"], "error_after": rep["error_after"],
            "validation_before": rep["validation_error_before"],
            "validation_after": rep["validation_error_after"],
            "discretisation_warnings": [w for w in rep.get("warnings", [])
                                        if w.startswith("discretisation error")],
            "substeps_adopted": [_adopted(w) for w in rep.get("warnings", [])
                                 if w.startswith("auto_substeps:")]}


def _adopted(line: str) -> str:
    """What an ``auto_substeps:`` line of the report adopted: ``"3"`` (the
    substeps of the same method), ``"rk4(1)"`` (the other method and its
    substeps), with " on the intervals that need them" for a refined grid."""
    m = re.search(r"takes (?:(\w+) with )?(\d+) substeps? per sample", line)
    what = "?" if m is None else (f"{m.group(1)}({m.group(2)})" if m.group(1) else m.group(2))
    return what + (" on the intervals that need them" if "intervals that need them" in line else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES),
                    help=f"comma-separated subset of {', '.join(CASES)}")
    ap.add_argument("--cold", default=None,
                    help="folder for fresh numba and kernel caches (a cold run)")
    ap.add_argument("--result", default=str(RESULT), help="where the result goes ('' for nowhere)")
    args = ap.parse_args()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if args.cold:
        base = Path(args.cold)
        env.update(NUMBA_CACHE_DIR=str(base / "numba"), BONDGRAPH_CACHE_DIR=str(base / "kernels"))
    names = [c for c in args.cases.split(",") if c]
    unknown = sorted(set(names) - set(CASES))
    if unknown:
        raise SystemExit(f"unknown case(s) {', '.join(unknown)} (cases: {', '.join(CASES)})")
    rows = []
    with tempfile.TemporaryDirectory(prefix="bondgraph-real-loops-") as tmp:
        for name in names:
            row = run_case(name, CASES[name], Path(tmp) / name, env)
            rows.append(row)
            print(f"{name}: {row['wall_s']} s; " + (
                f"skipped: {row['skipped']}" if "skipped" in row else
                f"{row['accepted']}; {row['error_before']:.4g} -> {row['error_after']:.4g}; "
                f"held-out {row['validation_before']} -> {row['validation_after']}"), flush=True)
    text = json.dumps({"cold": bool(args.cold), "cases": rows,
                       "seconds": {r["case"]: r["wall_s"] for r in rows},
                       "load": os.getloadavg()[0]})
    if args.result:
        Path(args.result).write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
