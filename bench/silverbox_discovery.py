"""Issue 29's Silverbox item: the bundled ``silverbox`` case with the
library's cubic stiffness switched off and discovery on
(:func:`bondgraph.diagnose.discover.effect.loop_with_discovery`): does the
discovered restoring-force law bring the arrow test region to <= 1 mV
(with the library's cubic stiffness the case reaches 0.63 mV)?

Usage::

    python bench/silverbox_discovery.py              # loop_with_discovery (~12 min, 1 core)
    python bench/silverbox_discovery.py --compete    # the law beside the library from step 1

Prints the loop's log, the discovered law, the accepted effects with their
estimates and the arrow error before and after (the case's metric,
:class:`bondgraph.catalog.cases.SilverboxError`), then one JSON line (the
last line). Needs the Silverbox data (``../shared/data`` or
``$BONDGRAPH_DATA``).
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from dataclasses import replace

from types import SimpleNamespace

from bondgraph.diagnose.cases import get_case
from bondgraph.diagnose.discover.effect import (
    discovered_effect,
    loop_with_discovery,
    with_discovered,
)
from bondgraph.diagnose.runner import run_loop


def competing(graph, record, settings):
    """``--compete``: the laws discovered on the declared graph (whatever the
    loop alone would accept; the best port's and its alternatives) beside
    the library from the first step, one loop run. Returns (LoopResult,
    the Discovery accepted, else the best port's, or None)."""
    best = discovered_effect(graph, record, settings, SimpleNamespace(steps=[]), log=print)
    if best is None:
        return run_loop(graph, record, settings, log=print, progress=False), None
    res = run_loop(graph, record, with_discovered(settings, *best.effects()), log=print,
                   progress=False)
    return res, best.accepted_in(res)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-steps", type=int, default=1, help="loop steps (default 1)")
    ap.add_argument("--drop", default="cubic_stiffness",
                    help="comma-separated effects removed from the case's library")
    ap.add_argument("--compete", action="store_true",
                    help="the laws discovered on the declared graph beside the library from the "
                         "first step (loop_with_discovery discovers only when the loop accepts "
                         "no physical effect or leaves coloured innovations)")
    a = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    case = get_case("silverbox")
    s = case.loop_settings()
    drop = set(a.drop.split(",")) if a.drop else set()
    s = replace(s, effects=tuple(e for e in s.effects if e.name not in drop),
                search=replace(s.search, max_steps=a.max_steps))
    run = competing if a.compete else (
        lambda g, r, st: loop_with_discovery(g, r, st, log=print))
    res, disc = run(case.declared(), case.record(), s)
    print()
    if disc is not None:
        print(disc.summary())
    steps = []
    for st in res.steps:
        est = {n: p["estimate"] for n, p in st.parameters.items()}
        std = {n: p.get("std") for n, p in st.parameters.items()}
        text = (disc.effect.readable(est, std) if disc is not None and disc.effect is not None
                and st.effect == disc.effect.name else f"{st.effect} @ {st.attached_to}")
        steps.append(text)
        print(f"accepted: {text}")
    print(f"arrow error [mV]: before {res.initial.metric:.4g}, after {res.final.metric:.4g}")
    print(json.dumps({"dropped": sorted(drop), "compete": a.compete, "discovery_ran": disc is not None,
                      "discovered": disc.passivity.law.readable() if disc is not None else None,
                      "accepted": steps, "arrow_before_mV": res.initial.metric,
                      "arrow_after_mV": res.final.metric,
                      "seconds": time.perf_counter() - t0}, default=str))
    return res, disc


if __name__ == "__main__":
    main()
