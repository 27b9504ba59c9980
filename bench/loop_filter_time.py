"""Where a loop's filter time goes (issue 27): every run of the compiled
filter (``bondgraph.inference.ukf_numba.run``) timed and counted by its
call site in ``bondgraph/diagnose`` (the last three frames), for one bundled
case run in this process with its own settings.

Usage: python bench/loop_filter_time.py [CASE]   (default: the bundled default case)

Prints one line per call site (seconds of filter time, runs, parameter
sets, million set-steps), then the totals; last line JSON with ``wall_s``,
``filter_s`` and ``sites`` (call site -> seconds). The filter time is summed
over threads and can exceed the wall time.
"""

from __future__ import annotations

import collections
import json
import sys
import threading
import time
import traceback

from bondgraph.cli.loop import DEFAULT_CASE
from bondgraph.diagnose.cases import get_case
from bondgraph.diagnose.runner import run_loop
from bondgraph.inference import ukf_numba

SKIP = ("task", "<lambda>", "local_map", "run_tasks")


def main(name: str) -> dict:
    stats = collections.defaultdict(lambda: [0, 0, 0.0, 0])
    orig = ukf_numba.run
    lock = threading.Lock()

    def run(kernels, t, u, y, batch, opts, wts, kept):
        t0 = time.perf_counter()
        r = orig(kernels, t, u, y, batch, opts, wts, kept)
        dt = time.perf_counter() - t0
        key = [fr.name for fr in traceback.extract_stack()
               if "/bondgraph/diagnose/" in fr.filename and fr.name not in SKIP]
        with lock:
            s = stats[" > ".join(key[-3:])]
            s[0] += 1
            s[1] += batch.size
            s[2] += dt
            s[3] += batch.size * len(t) * opts.substeps
        return r

    ukf_numba.run = run
    case = get_case(name)
    t0 = time.time()
    run_loop(case.declared(), case.record(), case.loop_settings(), progress=False,
             log=lambda s: None)
    wall = time.time() - t0
    ukf_numba.run = orig
    for k, v in sorted(stats.items(), key=lambda kv: -kv[1][2]):
        print(f"{v[2]:7.1f} s {v[0]:5d} runs {v[1]:7d} sets {v[3] / 1e6:8.1f}M set-steps  {k}")
    total = sum(v[2] for v in stats.values())
    print(f"wall {wall:.1f} s, filter {total:.1f} s")
    return {"case": name, "wall_s": round(wall, 1), "filter_s": round(total, 1),
            "sites": {k: round(v[2], 2) for k, v in stats.items()}}


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1] if len(sys.argv) > 1 else DEFAULT_CASE)))
