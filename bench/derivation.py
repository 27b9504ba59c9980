"""Derivation + code generation time of the n-mass chain (39 to 499 states).

What a user waits for when a new graph becomes a model (``bondgraph generate``,
or ``Model.from_spec`` of a graph builder): the derivation (causality, sympy
state equations), the numpy module's source and the numba kernels' source
(not numba's compilation). Each is timed separately.

Targets: issue 2, <= 0.5 s for 39 states and <= 2 s for 79 states; issue 27,
<= 2 s for 499 states with the time per state flat from 79 to 499 states.
Peers measured on this machine: the PyPI package `bondgraph` 0.2.0 took 23.8 s
for 79 states; BondGraphTools took 12 s for 39 states.

Each size is built in a fresh subprocess (cold sympy caches, after imports and
a warm-up on the mass-spring-damper), repeated ``--repeat`` times; the median
is reported, with the process's CPU time of the whole (the machine is shared:
wall time includes waiting for a core). The last line printed is one JSON
object, also written to bench/results/derivation.json (``--out`` elsewhere).

Usage: python bench/derivation.py [--repeat 3] [--masses 20 40 100 250] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import json, sys, time
from bondgraph.catalog.reference import mass_chain, mass_spring_damper
from bondgraph.core.codegen import generate_source
from bondgraph.core.codegen_numba import generate_numba_source
from bondgraph.core.equations import derive
_ss = derive(mass_spring_damper())     # warm-up: imports, unit registry
generate_source(_ss); generate_numba_source(_ss)
n = int(sys.argv[1])
c0 = time.process_time()
t0 = time.perf_counter()
g = mass_chain(n)
ss = derive(g)
t1 = time.perf_counter()
src = generate_source(ss)
t2 = time.perf_counter()
nsrc = generate_numba_source(ss)
t3 = time.perf_counter()
c3 = time.process_time()
print(json.dumps({"states": len(ss.states), "cpu_s": c3 - c0, "derive_s": t1 - t0, "numpy_s": t2 - t1,
                  "numba_s": t3 - t2, "total_s": t3 - t0, "lines": src.count("\n"),
                  "numba_lines": nsrc.count("\n")}))
"""

RESULT = Path(__file__).with_name("results") / "derivation.json"   # the current result
PEERS = {39: ("BondGraphTools", 12.0), 79: ("bondgraph 0.2.0 (PyPI)", 23.8)}
#: targets of derivation + numpy codegen (issue 2) and of the whole (issue 27)
TARGETS = {39: 0.5, 79: 2.0, 499: 2.0}


def measure(masses: int, repeat: int) -> dict:
    """Median times of ``repeat`` fresh subprocesses for the chain of ``masses``."""
    runs = []
    for _ in range(repeat):
        r = subprocess.run([sys.executable, "-c", CHILD, str(masses)], capture_output=True,
                           text=True, check=True)
        runs.append(json.loads(r.stdout.strip().splitlines()[-1]))
    n = runs[0]["states"]
    med = {k: statistics.median(r[k] for r in runs)
           for k in ("derive_s", "numpy_s", "numba_s", "total_s", "cpu_s")}
    out = {k: round(v, 4) for k, v in med.items()}
    out.update(states=n, masses=masses, generated_lines=runs[0]["lines"],
               numba_lines=runs[0]["numba_lines"],
               ms_per_state=round(1e3 * med["total_s"] / n, 3),
               cpu_ms_per_state=round(1e3 * med["cpu_s"] / n, 3),
               runs_total_s=[round(r["total_s"], 4) for r in runs])
    if n in TARGETS:
        timed = med["total_s"] if n == 499 else med["derive_s"] + med["numpy_s"]
        out.update(target_s=TARGETS[n], target_of="derive+numpy+numba" if n == 499
                   else "derive+numpy", meets_target=timed <= TARGETS[n])
    if n in PEERS:
        peer, peer_s = PEERS[n]
        out.update(peer=peer, peer_s=peer_s,
                   speedup_vs_peer=round(peer_s / (med["derive_s"] + med["numpy_s"]), 1))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--masses", type=int, nargs="+", default=[20, 40, 100, 250])
    ap.add_argument("--result", default=str(RESULT),
                    help="where the result goes ('' for nowhere)")
    args = ap.parse_args()
    out = {}
    for masses in args.masses:
        r = measure(masses, args.repeat)
        out[f"states_{r['states']}"] = r
        print(f"{r['states']:4d} states: derive {r['derive_s']:.3f} s, numpy {r['numpy_s']:.3f} s, "
              f"numba {r['numba_s']:.3f} s, total {r['total_s']:.3f} s (CPU {r['cpu_s']:.3f} s) "
              f"({r['ms_per_state']:.2f} ms/state, CPU {r['cpu_ms_per_state']:.2f})", flush=True)
    # from 79 states up (the range; 39 states is dominated by fixed costs)
    big = [r for r in out.values() if r["states"] >= 79]
    for key in ("ms_per_state", "cpu_ms_per_state"):
        per = [r[key] for r in big] or [1.0]
        out[f"{key}_max_over_min_from_79"] = round(max(per) / min(per), 2)
    if args.result:
        Path(args.result).parent.mkdir(parents=True, exist_ok=True)
        Path(args.result).write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
