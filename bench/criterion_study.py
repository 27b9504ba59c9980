"""Which fitting criterion gives the better held-out simulation error on the
real records (issue 26, "one criterion for fitting and judging").

For each real-data loop case the loop runs twice on the same record and the
same options:

* ``likelihood``: the case as bundled, its process-noise intensities estimated
  with the other parameters (the one-step-ahead UKF likelihood: a model error
  may be absorbed as process noise);
* ``output_error``: the same with every process-noise intensity of the
  declared graph held at zero; the UKF then predicts by the free run, so its
  likelihood is the output-error (simulation) criterion with the sensor noise
  estimated (Ljung 1999, §7.3), the criterion the loop judges by.

Printed per case and variant: the case's own metric (held-out where the case
has a validation record) of the declared fit and of the final model, the
accepted steps and the wall time. Last line JSON.

Usage: python bench/criterion_study.py [--cases emps,ced,silverbox] [--max-steps N]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

from bondgraph.diagnose.cases import get_case
from bondgraph.diagnose.runner import run_loop
from bondgraph.errors import DeclaredFitError

RESULT = Path(__file__).with_name("results") / "criterion_study.json"   # the current result


def process_noise_params(graph) -> list[str]:
    """Parameters in the process-noise expressions of ``graph``."""
    names = set()
    for std in graph.process_noise.values():
        names |= {s.name for s in getattr(std, "free_symbols", ())}
    return sorted(n for n in names if n in graph.params)


def variant(case, criterion: str, max_steps: int | None):
    s = case.settings
    if max_steps is not None:
        s = dataclasses.replace(s, search=dataclasses.replace(s.search, max_steps=max_steps))
    if criterion == "output_error":
        q = process_noise_params(case.declared())
        s = dataclasses.replace(s, params=[p for p in s.params if p not in q],
                                initial_params=[p for p in (s.initial_params or []) if p not in q]
                                or None,
                                fixed={**dict(s.fixed or {}), **{p: 0.0 for p in q}})
    return s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="emps,ced,silverbox")
    ap.add_argument("--max-steps", type=int, default=None)
    ap.add_argument("--criteria", default="likelihood,output_error")
    ap.add_argument("--result", default=str(RESULT),
                    help="where the result goes ('' for nowhere)")
    args = ap.parse_args()
    rows = []
    for name in args.cases.split(","):
        case = get_case(name)
        for criterion in args.criteria.split(","):
            settings = variant(case, criterion, args.max_steps)
            t0 = time.perf_counter()
            stopped = None
            try:
                res = run_loop(case.declared(), case.record(), settings, log=lambda m: None,
                               progress=False)
            except DeclaredFitError as exc:
                # the loop's own verdict (exit code 2): reported, then the
                # loop is run on anyway (--keep-going) to see where it goes
                stopped = str(exc).splitlines()[0]
                print(f"{name:10s} {criterion:13s} declared fit failed: {stopped}", flush=True)
                settings = dataclasses.replace(settings, search=dataclasses.replace(
                    settings.search, on_failed_fit="continue"))
                res = run_loop(case.declared(), case.record(), settings, log=lambda m: None,
                               progress=False)
            row = {"case": name, "criterion": criterion, "declared_fit_failed": stopped,
                   "metric": res.metric,
                   "declared": res.initial.metric, "final": res.final.metric,
                   "declared_held_out": res.initial.validation_metric,
                   "final_held_out": res.final.validation_metric,
                   "steps": [f"{s.effect} @ {s.attached_to}" for s in res.steps],
                   "seconds": round(time.perf_counter() - t0, 1)}
            rows.append(row)
            held = ("" if row["final_held_out"] is None else
                    f"; held out {row['declared_held_out']:.4g} -> {row['final_held_out']:.4g}")
            print(f"{name:10s} {criterion:13s} {row['declared']:.4g} -> {row['final']:.4g}{held} "
                  f"({len(row['steps'])} steps: {', '.join(row['steps']) or '-'}; "
                  f"{row['seconds']} s)", flush=True)
    text = json.dumps({"criterion_study": rows})
    if args.result:
        Path(args.result).write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
