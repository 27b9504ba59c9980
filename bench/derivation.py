"""Derivation + code generation time of the n-mass chain (39 and 79 states).

Targets (issue 2): <= 0.5 s for 39 states and <= 2 s for 79 states. Peers measured
on this machine: the PyPI package `bondgraph` 0.2.0 took 23.8 s for 79 states;
BondGraphTools took 12 s for 39 states.

Each size is built in a fresh subprocess (cold sympy caches, after imports and a
warm-up on the mass-spring-damper), repeated ``--repeat`` times; the median is
reported. The last line printed is one JSON object.

Usage: python bench/derivation.py [--repeat 3]
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
from bondgraph.core.equations import derive
generate_source(derive(mass_spring_damper()))   # warm-up: imports, unit registry
n = int(sys.argv[1])
t0 = time.perf_counter()
g = mass_chain(n)
ss = derive(g)
t1 = time.perf_counter()
src = generate_source(ss)
t2 = time.perf_counter()
print(json.dumps({"states": len(ss.states), "derive_s": t1 - t0, "codegen_s": t2 - t1,
                  "total_s": t2 - t0, "lines": src.count("\n")}))
"""

RESULT = Path(__file__).with_name("results") / "derivation.json"   # the current result
PEERS = {39: ("BondGraphTools", 12.0), 79: ("bondgraph 0.2.0 (PyPI)", 23.8)}
TARGETS = {39: 0.5, 79: 2.0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--result", default=str(RESULT),
                    help="where the result goes ('' for nowhere)")
    args = ap.parse_args()
    out = {}
    for masses in (20, 40):
        runs = []
        for _ in range(args.repeat):
            r = subprocess.run([sys.executable, "-c", CHILD, str(masses)], capture_output=True,
                               text=True, check=True)
            runs.append(json.loads(r.stdout.strip().splitlines()[-1]))
        n = runs[0]["states"]
        total = statistics.median(r["total_s"] for r in runs)
        peer, peer_s = PEERS[n]
        out[f"states_{n}"] = {
            "total_s": round(total, 4),
            "derive_s": round(statistics.median(r["derive_s"] for r in runs), 4),
            "codegen_s": round(statistics.median(r["codegen_s"] for r in runs), 4),
            "generated_lines": runs[0]["lines"],
            "target_s": TARGETS[n],
            "meets_target": total <= TARGETS[n],
            "peer": peer, "peer_s": peer_s,
            "speedup_vs_peer": round(peer_s / total, 1),
        }
        print(f"{n} states: {total:.3f} s (target <= {TARGETS[n]} s; {peer}: {peer_s} s, "
              f"{peer_s / total:.0f}x)")
    text = json.dumps(out)
    if args.result:
        Path(args.result).write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
