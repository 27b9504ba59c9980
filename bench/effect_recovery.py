"""Effect-recovery matrix: does the loop's ranking find the effect a record has?

For each reference graph (translation, rotation + electrical, electrical,
hydraulic, thermal, a two-mass chain) and each effect of the default library
that attaches to it (one target each, drawn with the case's seed), a *truth*
graph is the declared graph plus the effect with its parameters drawn
uniformly inside the effect's declared box (:meth:`Effect.box`, from the
operating scales of the declared model on the same excitation). A record is
synthesised from the truth (:func:`bondgraph.diagnose.cases.synthesize`,
declared sensor noise, seeded), the declared model is fitted, every
candidate of the library is scored (:func:`bondgraph.diagnose.runner.gather_evidence`,
the loop's own ranking), and the true candidate is confirmed by a refit
(:func:`bondgraph.diagnose.confirm.confirm`).

Reported per case and in total:

* ``rank``: position of the truth in the ranking (1 = first); ``first``:
  ranked first, or inside the equivalence group of the first candidate
  (signatures indistinguishable in this record);
* ``first_confirmed``: the truth leads after the loop's confirmation of its
  ``confirm_top`` best significant candidates
  (:func:`bondgraph.diagnose.runner.confirm_best`), the order the loop's
  accept step works through (the accept rule itself left aside), or is
  reported tied with the lead (Vuong's test, ``confirmed_tied``; the total
  ``first_confirmed_tied`` counts these);
* ``absorbed``: the truth's signature lies in the span of the estimated
  parameters' (:attr:`Candidate.absorbed`, e.g. a viscous friction next to an
  estimated damper); ``not_excited``: the noise-free difference the truth
  makes is below the χ²(k) 1 % critical value (:func:`oracle_chi2`, an upper
  bound of any fit's likelihood gain). Such cases have nothing to find: they
  are counted apart (``apart``) and left out of the rates;
* ``within_3crb``: every estimated effect parameter within 3 Cramér-Rao
  standard deviations of its truth;
* ``val_before``/``val_after``: free-run simulation error (mean over the
  outputs of RMS error / std of the output) of the fitted declared and of the
  fitted augmented model on a validation record (other excitation, other
  noise seed);
* ``seconds``: wall time of the case.

Usage::

    python bench/effect_recovery.py            # full matrix (every graph x effect)
    python bench/effect_recovery.py --quick    # 4 cases, one per domain (~1.2 min CPU)

A per-graph table is printed, then one JSON line (the last line).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path
from dataclasses import replace

import numpy as np
from scipy.stats import chi2

from bondgraph.catalog import reference as ref
from bondgraph.diagnose.cases import SimulationOptions, synthesize
from bondgraph.diagnose.confirm import Confirmation, confirm
from bondgraph.diagnose.effects import DEFAULT_EFFECTS, Scales, get_effect
from bondgraph.diagnose.fit import Context, MetricRecord, fit_model, model_of, parameter_std
from bondgraph.diagnose.runner import confirm_best, gather_evidence, recommended_substeps
from bondgraph.diagnose.scales import operating_scales
from bondgraph.diagnose.settings import LoopSettings
from bondgraph.diagnose.settings import SearchOptions
from bondgraph.errors import NumericalError
from bondgraph.inference.options import UKFOptions
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate

RESULT = Path(__file__).with_name("results") / "effect_recovery.json"   # the current result


def _chain2():
    return ref.mass_chain(2)


def _multisine(freqs, amps, phase):
    """u(t) = Σ a_k sin(2π f_k t + φ_k) with φ shifted by ``phase``."""
    def u(t):
        return sum(a * np.sin(2 * np.pi * f * t + phase * (k + 1))
                   for k, (f, a) in enumerate(zip(freqs, amps)))
    return u


def sampled(inputs, t):
    """The inputs sampled at ``t`` (arrays (N,)): the truth is simulated with
    them held over each interval (``hold="zoh"``), exactly what the UKF sees,
    so that the estimates carry no discretisation bias of the input."""
    return {k: np.broadcast_to(np.asarray(f(t), dtype=float), t.shape).copy()
            for k, f in inputs.items()}


def _steps(level, period, phase):
    """A square wave between 0.2·level and level (period [s]) plus a slow sine."""
    def u(t):
        sq = np.where(np.sin(2 * np.pi * (t / period) + phase) > 0, 1.0, 0.2)
        return level * (sq + 0.3 * np.sin(2 * np.pi * t / (2.7 * period) + phase))
    return u


#: graph name -> builder, estimated parameters, duration [s], dt [s],
#: excitation (inputs as callables of t, for a phase), domain
GRAPHS = {
    "mass_spring_damper": dict(
        build=ref.mass_spring_damper, params=["k", "c"], T=10.0, dt=0.01, domain="translation",
        inputs=lambda ph: {"F": _multisine([0.4, 1.1, 1.9], [8.0, 5.0, 3.0], ph)}),
    "dc_motor_compliant": dict(
        build=ref.dc_motor_compliant, params=["R_a", "b_m", "b_L"], T=4.0, dt=0.005,
        domain="electrical+rotation",
        inputs=lambda ph: {"V": _multisine([0.5, 1.3, 3.1], [6.0, 3.0, 2.0], ph),
                           "T_L": _multisine([0.7], [0.05], ph)}),
    "rlc_circuit": dict(
        build=ref.rlc_circuit, params=["R", "C"], T=1.0, dt=0.001, domain="electrical",
        inputs=lambda ph: {"V": _multisine([3.0, 11.0, 23.0], [6.0, 4.0, 2.0], ph)}),
    "hydraulic_tanks": dict(
        build=ref.hydraulic_tanks, params=["Rh12", "Rh2"], T=200.0, dt=0.2, domain="hydraulic",
        inputs=lambda ph: {"Q": _steps(1e-3, 40.0, ph)}),
    "thermal_two_node": dict(
        build=ref.thermal_two_node, params=["Rth12", "Rth2a"], T=2000.0, dt=2.0,
        domain="thermal",
        inputs=lambda ph: {"P": _steps(200.0, 300.0, ph), "T_a": _multisine([1 / 900], [1.0],
                                                                              ph)}),
    "mass_chain_2": dict(
        build=_chain2, params=["k1", "c1"], T=10.0, dt=0.01, domain="translation",
        inputs=lambda ph: {"F": _multisine([0.3, 0.9, 2.3], [6.0, 4.0, 2.0], ph)}),
}

#: the --quick subset: (graph, effect), one per domain
QUICK = [("mass_spring_damper", "cubic_stiffness"), ("rlc_circuit", "sensor_offset"),
         ("hydraulic_tanks", "sensor_gain"), ("thermal_two_node", "actuator_gain")]


#: ROS2 substeps of the bench's UKF (``--substeps``): with 2 the filter's
#: discretisation biased precise estimates by 0.5-1 % (a dead zone
#: 1.617 ± 0.0026 for 1.605 at 2 substeps, 1.608 at 8)
SUBSTEPS = {"full": 8, "quick": 2}
_substeps = [SUBSTEPS["full"]]
#: how the records are simulated from the truth: RK4 with 10 steps per
#: sample, inputs held (:class:`bondgraph.diagnose.cases.SimulationOptions`)
RK4_ZOH = SimulationOptions(method="rk4", substeps=10, hold="zoh")


def settings_for(params):
    """Loop settings of the benchmark: the default library, ROS2 UKF with
    ``_substeps[0]`` substeps, structural candidates scored at every step
    (the loop's default; ``structural_near_best`` only matters when a
    ``structural_threshold`` is set)."""
    return LoopSettings(params=list(params), effects=DEFAULT_EFFECTS, metric="nrmse_sim",
                        ukf=UKFOptions(method="ros2", substeps=_substeps[0], alpha=1.0),
                        search=SearchOptions(structural_near_best=True))


def quiet(_msg):
    """Discard the loop's log lines."""


def draw_truth(spec, eff, seed):
    """(target, truth values) of ``eff`` on the graph of ``spec``: a target
    drawn among the effect's targets, the estimated parameters uniform in
    the box from the declared model's operating scales, shape constants
    from the same scales. None if the effect has no target or no box."""
    rng = np.random.default_rng(seed)
    g = spec["build"]()
    targets = eff.targets(g)
    if not targets:
        return None
    tgt = targets[int(rng.integers(len(targets)))]
    t = np.arange(0.0, spec["T"], spec["dt"])
    rec = synthesize(g, spec["build"](), t, sampled(spec["inputs"](0.0), t), {}, {}, seed,
                     "scales", "", simulation=RK4_ZOH)
    ctx = Context.on(rec, settings_for(spec["params"]), model_of(g), log=quiet, progress=False)
    fit0 = fit_model(ctx, g, [], None, "declared at truth", iterations=0)
    sc = operating_scales(ctx, fit0)
    box = eff.box(g, tgt, sc)
    est = [p.name for p in eff.params if p.estimated]
    if not box or any(n not in box for n in est):
        return None
    vals = {n: float(rng.uniform(*sorted(box[n]))) for n in est}
    sign = {"cubic_stiffness", "sensor_offset", "source_offset", "sensor_poly2",
            "sensor_poly3", "offset"}
    if eff.name in sign and rng.random() < 0.5:
        vals = {k: -v for k, v in vals.items()}
    vals.update(eff.shape_values(g, tgt, sc))
    vals.update(consistent_shapes(spec, eff, tgt, vals, seed))
    return tgt, vals


def consistent_shapes(spec, eff, tgt, vals, seed) -> dict:
    """The effect's fixed shape constants (tanh widths, Stribeck velocity,
    overflow width...) as the loop computes them on the *truth's* record
    (scales along the fitted declared model's filtered states there), not on
    the declared model's own record: a friction changes the flows, so the
    constants would otherwise differ between the truth and every candidate
    (a model mismatch no estimate can remove, which biased the Coulomb and
    Stribeck estimates by 5-8 Cramér-Rao std). Empty if the effect has none."""
    if not eff.shape_values(spec["build"](), tgt, Scales()):
        return {}
    truth = spec["build"]()
    eff.apply(truth, tgt, vals)
    g = spec["build"]()
    t = np.arange(0.0, spec["T"], spec["dt"])
    rec = synthesize(truth, spec["build"](), t, sampled(spec["inputs"](0.0), t), {}, {}, seed,
                     "shapes", "", simulation=RK4_ZOH)
    ctx = Context.on(rec, settings_for(spec["params"]), model_of(g), log=quiet, progress=False)
    fit = fit_model(ctx, g, spec["params"], None, "declared")
    return eff.shape_values(g, tgt, operating_scales(ctx, fit))


def validation_error(model, theta, exp):
    """Mean over outputs of RMS(free-run error)/std(output) on ``exp``."""
    t, u, y = MetricRecord(exp).arrays(model)
    x0 = model.x0
    try:
        sim = simulate(model, t, u if model.n_u else None, x0=x0, theta=theta, method="rk4",
                       substeps=10)
    except Exception:
        return float("nan")
    e = sim.y - y
    return float(np.mean(np.sqrt(np.nanmean(e**2, axis=0)) / np.nanstd(y, axis=0)))


def run_case(gname, ename, seed, choice=True):
    """One case of the matrix (a dict of results; ``skipped`` with a reason
    if the effect does not apply). ``choice``: also confirm the loop's
    ``confirm_top`` candidates (``first_confirmed``; None without)."""
    t0 = time.perf_counter()
    spec = GRAPHS[gname]
    eff = get_effect(ename)
    drawn = draw_truth(spec, eff, seed)
    if drawn is None:
        return {"graph": gname, "effect": ename, "skipped": "no target or no box"}
    tgt, vals = drawn
    truth = spec["build"]()
    eff.apply(truth, tgt, vals)
    declared = spec["build"]()
    t = np.arange(0.0, spec["T"], spec["dt"])
    try:
        rec = synthesize(truth, declared, t, sampled(spec["inputs"](0.0), t), {}, {}, seed,
                         "train", "", simulation=RK4_ZOH)
        val = synthesize(truth, declared, t, sampled(spec["inputs"](1.3), t), {}, {},
                         seed + 7919, "val", "", simulation=RK4_ZOH)
    except NumericalError as exc:      # a softening spring drawn strong enough to escape
        return {"graph": gname, "effect": ename, "target": tgt.name,
                "skipped": f"the drawn truth has no record: {str(exc).splitlines()[0]}"}
    oracle = oracle_chi2(spec, declared, rec, t, seed)
    ctx = Context.on(rec, settings_for(spec["params"]), model_of(declared), log=quiet,
                     progress=False)
    fit = fit_model(ctx, declared, spec["params"], None, "declared")
    sc = operating_scales(ctx, fit)
    ranking, signif = gather_evidence(ctx, fit, sc)
    labels = [(c.effect, c.target.name) for c in ranking]
    key = (ename, tgt.name)
    rank = labels.index(key) + 1 if key in labels else None
    first = rank == 1 or (bool(ranking) and f"{ename} @ {tgt.name}" in
                          (ranking[0].equivalent or []))
    mine = ranking[rank - 1] if rank else None
    shapes = eff.shape_values(declared, tgt, sc)
    out = {"graph": gname, "domain": spec["domain"], "effect": ename, "target": tgt.name,
           "seed": seed, "truth": {k: vals[k] for k in vals
                                   if k in [p.name for p in eff.params if p.estimated]},
           "rank": rank, "first": bool(first), "n_candidates": len(ranking),
           "absorbed": bool(mine is not None and mine.absorbed),
           "oracle_chi2": oracle,
           "not_excited": bool(oracle < chi2.isf(0.01, sum(p.estimated for p in eff.params))),
           "shape_mismatch": max([abs(v / vals[k] - 1) for k, v in shapes.items()
                                  if vals.get(k)] + [0.0]),
           "top": f"{ranking[0].effect} @ {ranking[0].target.name}" if ranking else None,
           "top5": [[c.label, round(float(c.score), 2), c.equivalent] for c in ranking[:5]]}
    confirmed = confirm_best(ctx, fit, signif, sc, "augmented") if choice else []
    out.update(loop_choice(confirmed, ename, tgt.name) if choice else
               {"first_confirmed": None, "confirmed": []})
    out.update(confirm_truth(ctx, fit, ranking, key, sc, eff, vals, val, confirmed))
    out["val_before"] = validation_error(fit.model, fit.theta, val)
    out["seconds"] = time.perf_counter() - t0
    return out


def loop_choice(confirmed, ename, tname):
    """What the loop would pick (:func:`bondgraph.diagnose.runner.confirm_best`:
    the ``confirm_top`` best significant candidates refitted, ordered by
    confirmed LR − 2k; the accept rule left aside): ``first_confirmed`` if the
    truth leads that order, lies in its leader's equivalence group, or is
    reported tied with the leader (``tied``: Vuong's test cannot tell their
    refits apart on the record, :func:`bondgraph.diagnose.accept.mark_ties`)."""
    lead = confirmed[0][0] if confirmed else None
    label = f"{ename} @ {tname}"
    return {"first_confirmed": bool(lead is not None and (
                lead.label == label or label in (lead.equivalent or [])
                or label in (lead.tied or []))),
            "confirmed_tied": bool(lead is not None and lead.label != label
                                   and label not in (lead.equivalent or [])
                                   and label in (lead.tied or [])),
            "tied": list(lead.tied) if lead is not None else [],
            "confirmed": [[c.label, round(float(c.confirmed_statistic), 2)]
                          for c, _ in confirmed]}


def oracle_chi2(spec, declared, rec, t, seed) -> float:
    """Σ ((y_truth − y_declared)/σ)² over the record: the noise-free
    difference the effect makes, the declared model at the truth's own
    parameters (same seed, so the noise cancels), in units of the sensor
    noise. An upper bound of the likelihood gain any fit can show (a refit
    of the declared parameters can only shrink the difference): below the
    χ²(k) 1 % critical value the effect is not excited by this record
    (``not_excited``; a rectification of an output that never changes sign)."""
    same = synthesize(spec["build"](), declared, t, sampled(spec["inputs"](0.0), t), {}, {},
                      seed, "declared", "", simulation=RK4_ZOH)
    model = Model.from_graph(declared)
    _, _, y1 = MetricRecord(rec).arrays(model)
    _, _, y0 = MetricRecord(same).arrays(model)
    sd = model.meas_std(model.theta0)
    return float(np.nansum(((y1 - y0) / sd) ** 2))


def confirm_truth(ctx, fit, ranking, key, sc, eff, vals, val, confirmed=()):
    """Refit with the true effect (reusing the loop's confirmation of it in
    ``confirmed`` if there is one); its estimates, CRB std, whether each is
    within 3 std of the truth, and the validation error after."""
    cand = next((c for c in ranking if (c.effect, c.target.name) == key), None)
    if cand is None:
        return {"within_3crb": False, "val_after": float("nan"), "estimate": {}}
    r = next((r for c, r in confirmed if c is cand), None) or \
        confirm(ctx, fit, cand, sc, "augmented")
    if r is None:
        return {"within_3crb": False, "val_after": float("nan"), "estimate": {}}
    r, substeps = finer_if_needed(ctx, r)
    std = parameter_std(ctx, r.fit)
    est, ok = {}, True
    for p in eff.params:
        if not p.estimated:
            continue
        full = eff.pname(cand.target, p.name)
        s = std.get(full)
        est[p.name] = {"value": r.values[p.name], "std": s}
        ok = ok and s is not None and abs(r.values[p.name] - vals[p.name]) <= 3 * s
    return {"within_3crb": bool(ok), "estimate": est, "substeps": substeps,
            "val_after": validation_error(r.fit.model, r.fit.theta, val)}


def finer_if_needed(ctx, r):
    """The confirmation refitted with the substeps the loop's discretisation
    check recommends at it (:func:`bondgraph.diagnose.runner.fit_after_discretisation_check`,
    what ``auto_substeps`` does with an accepted effect), if the filter's
    one-step discretisation error there exceeds 0.1 noise std; else as it
    is. Returns (confirmation, substeps used)."""
    n = recommended_substeps(ctx, r.fit).n
    if n is None:
        return r, ctx.problem.disc.substeps
    finer = replace(ctx, problem=ctx.problem.conditioned_on(
        disc=replace(ctx.problem.disc, substeps=n)), cache={})
    f = fit_model(finer, r.fit.graph, list(r.fit.params), r.fit.estimates(), "finer",
                  model=r.fit.model)
    values = dict(r.values)
    for k in r.values:
        full = [p for p in r.new_params if p.endswith("." + k)]
        if full:
            values[k] = float(f.theta[f.model.param_index(full[0])])
    return Confirmation(f, values, r.new_params), n


def cases(quick: bool, graphs=None):
    """The (graph, effect, seed) list of the matrix."""
    if quick:
        return [(g, e, 1000 + i) for i, (g, e) in enumerate(QUICK)]
    out = []
    for gi, g in enumerate(graphs or GRAPHS):
        graph = GRAPHS[g]["build"]()
        for ei, e in enumerate(DEFAULT_EFFECTS):
            if e.targets(graph):
                out.append((g, e.name, 1000 + 100 * gi + ei))
    return out


def apart(r) -> bool:
    """A case with nothing to find: the truth is absorbed by the declared
    model's estimated parameters, or not excited by the record."""
    return bool(r.get("absorbed") or r.get("not_excited"))


def summarise(results):
    """Per-graph and total counts. A case with nothing to find
    (:func:`apart`: absorbed or not excited) is counted apart (``apart``)
    and left out of the rates."""
    done = [r for r in results if "skipped" not in r]
    scored = [r for r in done if not apart(r)]
    per = {}
    for r in done:
        d = per.setdefault(r["graph"], {"cases": 0, "apart": 0, "first": 0,
                                        "first_confirmed": 0, "within_3crb": 0,
                                        "seconds": 0.0})
        d["seconds"] += r["seconds"]
        if apart(r):
            d["apart"] += 1
            continue
        d["cases"] += 1
        d["first"] += int(r["first"])
        d["first_confirmed"] += int(bool(r.get("first_confirmed")))
        d["within_3crb"] += int(r["within_3crb"])
    n = max(len(scored), 1)
    total = {"cases": len(scored), "apart": len(done) - len(scored),
             "absorbed": sum(bool(r.get("absorbed")) for r in done),
             "not_excited": sum(bool(r.get("not_excited")) for r in done),
             "skipped": len(results) - len(done),
             "first": sum(int(r["first"]) for r in scored),
             "first_confirmed": sum(int(bool(r.get("first_confirmed"))) for r in scored),
             "first_confirmed_tied": sum(int(bool(r.get("confirmed_tied"))) for r in scored),
             "within_3crb": sum(int(r["within_3crb"]) for r in scored),
             "first_rate": sum(int(r["first"]) for r in scored) / n,
             "first_confirmed_rate": sum(int(bool(r.get("first_confirmed")))
                                         for r in scored) / n,
             "within_3crb_rate": sum(int(r["within_3crb"]) for r in scored) / n,
             "median_val_before": float(np.nanmedian([r["val_before"] for r in scored]))
             if scored else None,
             "median_val_after": float(np.nanmedian([r["val_after"] for r in scored]))
             if scored else None,
             "seconds": sum(r["seconds"] for r in done),
             "graphs": len(per), "domains": len({r["domain"] for r in done})}
    return per, total


def print_table(results, per, total):
    """The per-case lines and the per-graph table."""
    for r in results:
        if "skipped" in r:
            print(f"  {r['graph']:20s} {r['effect']:22s} skipped: {r['skipped']}")
            continue
        print(f"  {r['graph']:20s} {r['effect']:22s} @ {r['target']:10s} rank {r['rank']!s:>4s}"
              f"{' (absorbed)' if r.get('absorbed') else ''}"
              f"{' (not excited)' if r.get('not_excited') else ''}"
              f" first {'yes' if r['first'] else 'no ':3s}"
              f" conf {'yes' if r.get('first_confirmed') else 'no ':3s}"
              f" 3CRB {'yes' if r['within_3crb'] else 'no '}"
              f" val {r['val_before']:.3g} -> {r['val_after']:.3g}  {r['seconds']:.1f} s"
              f"  (top: {r['top']})")
    print(f"\n{'graph':22s} {'cases':>5s} {'first':>6s} {'1st conf':>8s} {'3 CRB':>6s} "
          f"{'apart':>6s} {'time [s]':>9s}")
    for g, d in list(per.items()) + [("total", total)]:
        print(f"{g:22s} {d['cases']:5d} {d['first']:6d} {d['first_confirmed']:8d} "
              f"{d['within_3crb']:6d} {d['apart']:6d} {d['seconds']:9.1f}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="the fixed subset (< 3 min; without the loop-choice confirmations)")
    ap.add_argument("--graphs", default=None, help="comma-separated graph names (full run)")
    ap.add_argument("--json-out", default=None,
                    help="also write the per-case results here (default: bench/results/"
                         "effect_recovery.json for the full matrix, none for a subset)")
    ap.add_argument("--substeps", type=int, default=None,
                    help="ROS2 substeps of the UKF (default 8; 2 with --quick)")
    ap.add_argument("--cases", default=None,
                    help="comma-separated graph:effect cases of the full matrix (their seeds)")
    ap.add_argument("--merge", nargs="+", default=None, metavar="JSON",
                    help="summarise the per-case results of earlier runs (--json-out files; "
                         "with --cases, those cases are run again and replace theirs)")
    a = ap.parse_args(argv)
    _substeps[0] = a.substeps or SUBSTEPS["quick" if a.quick else "full"]
    warnings.simplefilter("ignore")
    results = []
    todo = cases(a.quick, a.graphs.split(",") if a.graphs else None)
    if a.cases:
        want = {tuple(c.split(":")) for c in a.cases.split(",")}
        todo = [c for c in cases(False) if (c[0], c[1]) in want]
    if a.merge:
        for path in a.merge:
            with open(path) as fh:
                results += json.load(fh)
        again = {(g, e) for g, e, _ in todo} if a.cases else set()
        results = [r for r in results if (r["graph"], r["effect"]) not in again]
        todo = todo if a.cases else []
    for k, (g, e, seed) in enumerate(todo):
        try:
            r = run_case(g, e, seed, choice=not a.quick)
        except Exception as exc:  # a case that fails counts as not recovered
            r = {"graph": g, "domain": GRAPHS[g]["domain"], "effect": e, "target": "?",
                 "seed": seed, "rank": None, "first": False, "within_3crb": False,
                 "val_before": float("nan"), "val_after": float("nan"), "seconds": 0.0,
                 "top": None, "error": f"{type(exc).__name__}: {str(exc).splitlines()[0]}"}
        results.append(r)
        print(f"[{k + 1}/{len(todo)}] {g} {e}: rank {r.get('rank')} first {r.get('first')} "
              f"first confirmed {r.get('first_confirmed')} 3CRB {r.get('within_3crb')} "
              f"{r.get('error', '')}", file=sys.stderr, flush=True)
    per, total = summarise(results)
    print_table(results, per, total)
    full = not (a.quick or a.graphs or a.cases or a.merge)
    json_out = a.json_out or (str(RESULT) if full else None)
    if json_out:
        with open(json_out, "w") as fh:
            json.dump(results, fh, indent=1, default=str)
    print(json.dumps({"quick": a.quick, "substeps": _substeps[0], "total": total,
                      "per_graph": per}, default=str))
    return total


if __name__ == "__main__":
    main()
