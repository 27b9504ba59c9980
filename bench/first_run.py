"""The first `bondgraph loop` after install, and the next one (issue 27).

Runs the README's main job (``bondgraph loop``, the bundled default case, no
arguments) in a child process twice: first with fresh, empty numba and
bondgraph kernel caches (``NUMBA_CACHE_DIR``, ``BONDGRAPH_CACHE_DIR`` in a
temporary folder: what a user waits for after ``pip install``), then again
with the caches the first run filled (warm). For each run it reports the
wall time, the CPU time of the child (user + system, its own children
included: ``cpu_s``, the steadier figure on a shared machine), the time at
which each of the loop's stages was printed, and the longest silence (no
byte on stdout or stderr: the pipes are read as the bytes arrive, so the dot
an announced compile appends counts), and the loop's figures (free-run NRMSE before and
after, on the held-out run where the case has one: a speed-up must not change them). Targets: first run <= 60 s,
warm <= 10 s, nothing silent for more than 2 s. Last line JSON.

Usage: python bench/first_run.py [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

RESULT = Path(__file__).with_name("results") / "first_run.json"   # the current result

STAGES = {"initial fit": r"initial fit:", "step 1 scored": r"step 1: .* candidates scored",
          "step 1 decided": r"ACCEPT|nothing significant|no candidate", "done": r"\] done in"}


def _pump(stream, chunks: list, lines: list, t0: float) -> None:
    """Read ``stream`` (binary) as its bytes arrive: each chunk's arrival
    time into ``chunks`` (the silences are measured between any output, a
    dot appended to an announced line too), each completed line with the
    time of the chunk that ended it into ``lines``."""
    buf = b""
    fd = stream.fileno()
    while True:
        data = os.read(fd, 65536)
        now = time.perf_counter() - t0
        if not data:
            break
        chunks.append(now)
        buf += data
        *done, buf = buf.split(b"\n")
        lines.extend((now, raw.decode("utf-8", "replace")) for raw in done)
    if buf:
        lines.append((time.perf_counter() - t0, buf.decode("utf-8", "replace")))


def run_once(env: dict, out: Path) -> dict:
    """One `bondgraph loop --out out` in a child; its timings."""
    cmd = [sys.executable, "-m", "bondgraph.cli.main", "loop", "--out", str(out), "--overwrite"]
    t0 = time.perf_counter()
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, bufsize=0)
    lines: list = []
    chunks: list = []
    threads = [threading.Thread(target=_pump, args=(s, chunks, lines, t0))
               for s in (p.stdout, p.stderr)]
    for th in threads:
        th.start()
    code = p.wait()
    for th in threads:
        th.join()
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    if code != 0:
        tail = "\n".join(text for _, text in lines[-20:])
        raise SystemExit(f"bondgraph loop exited with {code}:\n{tail}")
    lines.sort(key=lambda x: x[0])
    times = [0.0] + sorted(chunks) + [wall]
    gaps = [(b - a, a) for a, b in zip(times[:-1], times[1:])]
    silence, at = max(gaps)
    stages = {}
    for name, pat in STAGES.items():
        hit = next((t for t, text in lines if re.search(pat, text)), None)
        stages[name] = None if hit is None else round(hit, 1)
    before = next((text[-100:] for t, text in reversed(lines) if t <= at), "(start)")
    fig = next((m.groups() for _, text in lines
                if (m := re.search(r"before:? ([0-9.]+)\s+after:? ([0-9.]+)", text))), None)
    return {"wall_s": round(wall, 1), "cpu_s": round(cpu, 1), "stages_s": stages,
            "longest_silence_s": round(silence, 1), "silent_after": before,
            "nrmse_before_after": None if fig is None else [float(v) for v in fig]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", default=None, help="folder for the caches and reports (kept)")
    ap.add_argument("--result", default=str(RESULT),
                    help="where the result goes ('' for nowhere)")
    args = ap.parse_args()
    base = Path(args.keep or tempfile.mkdtemp(prefix="bondgraph-first-run-"))
    # no PYTHONUNBUFFERED: the pipes get what a user's pipe or log file gets
    env = dict(os.environ, NUMBA_CACHE_DIR=str(base / "numba"),
               BONDGRAPH_CACHE_DIR=str(base / "kernels"))
    env.pop("PYTHONUNBUFFERED", None)
    load0 = os.getloadavg()[0]
    first = run_once(env, base / "report1")
    print(f"first run: {first['wall_s']} s (CPU {first['cpu_s']} s), NRMSE "
          f"{first['nrmse_before_after']}; stages {first['stages_s']}; longest silence "
          f"{first['longest_silence_s']} s after: {first['silent_after']}", flush=True)
    warm = run_once(env, base / "report2")
    print(f"warm run:  {warm['wall_s']} s (CPU {warm['cpu_s']} s), NRMSE "
          f"{warm['nrmse_before_after']}; stages {warm['stages_s']}; longest silence "
          f"{warm['longest_silence_s']} s after: {warm['silent_after']}", flush=True)
    text = json.dumps({"first_run_s": first["wall_s"], "warm_s": warm["wall_s"],
                       "first_cpu_s": first["cpu_s"], "warm_cpu_s": warm["cpu_s"],
                       "first": first, "warm": warm, "load_start": load0,
                       "load": os.getloadavg()[0]})
    if args.result:
        Path(args.result).write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
