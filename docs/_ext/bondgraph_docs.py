"""Generated pages of the documentation, written at every build (``conf.py``
calls :func:`generate` before Sphinx reads the sources).

- ``reference/generated/api.rst``: every public name of :mod:`bondgraph`
  (``bondgraph.__all__``, grouped by the module that defines it), as
  autosummary entries whose pages autodoc fills from the docstrings;
- ``reference/generated/effects.md``: the effect library from the effects'
  own declarations (name, title, docstring, where it attaches, parameters
  with units and fixed boxes, limits) and, for each, one application to the
  first reference graph that admits it: the target, the box the effect
  declares there and the derived equations the effect enters;
- ``background/generated/bench_tables.md``: the benchmark tables, read from
  ``bench/results/*.json`` (the effect-recovery matrix summarised by the
  bench's own ``summarise``).

Nothing here is copied by hand: a change of the package or of a bench
result changes the pages at the next build.
"""

from __future__ import annotations

import copy
import importlib.util
import json
from pathlib import Path

import sympy as sp

ROOT = Path(__file__).resolve().parents[2]

# ---------------------------------------------------------------- API
#: page sections: heading -> module prefixes of bondgraph._API
SECTIONS = [
    ("Declare a graph", ("bondgraph.core.symbols", "bondgraph.core.elements",
                         "bondgraph.core.graph")),
    ("Causality, equations, code generation", ("bondgraph.core.causality",
                                               "bondgraph.core.equations",
                                               "bondgraph.core.codegen",
                                               "bondgraph.core.jsonsafe")),
    ("Model and simulation", ("bondgraph.numerics",)),
    ("Records and experiments", ("bondgraph.data",)),
    ("Filter and estimation", ("bondgraph.inference",)),
    ("Sensitivity", ("bondgraph.sensitivity",)),
    ("The loop and its effects", ("bondgraph.diagnose",)),
]


def api_page() -> str:
    """reST of the API reference: one autosummary table per section."""
    import bondgraph
    api = bondgraph._API
    lines = ["API reference", "=============", "",
             "Every name ``bondgraph`` exports (``from bondgraph import NAME``), listed where it "
             "is defined; each page is generated from the docstring.", ""]
    done = set()
    for title, prefixes in SECTIONS:
        names = sorted((mod, n) for n, mod in api.items() if mod.startswith(prefixes))
        if not names:
            continue
        lines += [title, "-" * len(title), "", ".. autosummary::", "   :toctree: api", ""]
        lines += [f"   {mod}.{n}" for mod, n in names]
        lines.append("")
        done.update(n for _, n in names)
    left = sorted(set(api) - done)
    if left:
        raise RuntimeError(f"public names in no section of the API page: {left}")
    lines += ["Modules reachable as attributes", "-------------------------------", "",
              ".. autosummary::", "   :toctree: api", "",
              "   bondgraph.core.smooth", "   bondgraph.errors", ""]
    return "\n".join(lines)


# ---------------------------------------------------------------- effects
def _first_application(effect, graphs):
    """(graph name, graph, target) of the first reference graph where
    ``effect`` attaches, or None."""
    for name, build in graphs:
        g = build()
        targets = effect.targets(g)
        if targets:
            return name, g, targets[0]
    return None


def _entered_equations(graph, effect, target) -> list[str]:
    """Derived equations (dx/dt and y) of ``graph`` with ``effect`` at
    ``target`` that contain one of the effect's parameters or states."""
    from bondgraph.core.equations import derive
    from bondgraph.diagnose.effects.base import Scales
    g = copy.deepcopy(graph)
    added = effect.apply(g, target, None, Scales())
    syms = set(added.values())
    ss = derive(g)
    syms |= {x for x in ss.states if x.name.startswith(f"{effect.name}.")}
    out = []
    for x, fx in zip(ss.states, ss.f):
        if fx.free_symbols & syms or x in syms:
            out.append(f"d{x.name}/dt = {sp.sstr(fx)}")
    for o in ss.outputs:
        if o.expr.free_symbols & syms:
            out.append(f"{o.name} = {sp.sstr(o.expr)}")
    return out


def _fmt_box(box) -> str:
    return ", ".join(f"{k} ∈ [{lo:.3g}, {hi:.3g}]" for k, (lo, hi) in box.items()) or "-"


def _effect_section(effect, graphs, optional: bool) -> list[str]:
    from bondgraph.diagnose.effects.base import Scales
    kind = ("last resort" if effect.last_resort else
            "additive (score test)" if effect.additive else "structural (likelihood-ratio grid)")
    doc = " ".join((type(effect).__doc__ or "").split())
    lines = [f"## `{effect.name}`: {effect.title}", "",
             f"{doc}", "",
             f"- class: `{type(effect).__module__}.{type(effect).__name__}`"
             + (" (optional: `LoopSettings(effects=DEFAULT_EFFECTS + OPTIONAL_EFFECTS)`)"
                if optional else ""),
             f"- attaches to: a {effect.target_kind}",
             f"- scored as: {kind}"]
    if effect.limits:
        lines.append("- limits: " + "; ".join(f"at the {side} end of `{p}` it becomes `{e}`"
                                              for p, (side, e) in effect.limits.items()))
    lines += ["", "| parameter | unit | estimated | fixed box | meaning |", "|---|---|---|---|---|"]
    for p in effect.params:
        box = f"[{p.bounds[0]:g}, {p.bounds[1]:g}]" if p.bounds else "from the data"
        unit = (p.unit or "1").replace("{", "(").replace("}", ")").replace("|", "\\|")
        how = ("yes" if p.estimated else "no (shape)" if not p.profile else
               "profiled at " + ", ".join(f"x{k:g}" for k in sorted({1.0, *p.profile},
                                                                    reverse=True)))
        lines.append(f"| `{p.name}` | {unit} | {how} "
                     f"| {box} | {p.description} |")
    app = _first_application(effect, graphs)
    if app is None:
        lines += ["", "No reference graph admits it.", ""]
        return lines
    gname, g, target = app
    try:
        eqs = _entered_equations(g, effect, target)
        box = effect.box(g, target, Scales())
    except Exception as exc:  # shown, never hidden: the page says what failed
        lines += ["", f"Applied to `{gname}` at {target}: {type(exc).__name__}: {exc}", ""]
        return lines
    lines += ["", f"On the reference graph `{gname}` at {target} (unit data scales), the "
                  f"declared box: {_fmt_box(box)}; the equations it enters:", "", "```text"]
    lines += eqs or ["(none: the effect acts through a state of its own)"]
    lines += ["```", ""]
    return lines


def effects_page() -> str:
    """Markdown of the effect library."""
    from bondgraph.catalog.reference import MODELS
    from bondgraph.core.plugins import resolve
    from bondgraph.diagnose.effects.library import DEFAULT_EFFECTS, OPTIONAL_EFFECTS
    order = ["mass_spring_damper", "dc_motor_compliant", "rlc_circuit", "hydraulic_tanks",
             "thermal_two_node", "toy_cvt", "dc_motor_gear", "rr_loop", "mass_chain_5"]
    graphs = [(n, resolve(MODELS[n])) for n in order if n in MODELS]
    lines = ["# Effect library", "",
             "Generated at each build from the effects' own declarations "
             "(`bondgraph/diagnose/effects/`). The loop scores every effect of "
             "`DEFAULT_EFFECTS` at every place of your graph where it can attach; "
             "a parameter's box \"from the data\" is set by the effect's `box` from the graph "
             "and the record's scales (shown below at unit scales). Write your own effect as a "
             "subclass of `bondgraph.diagnose.effects.Effect` (see the tutorial "
             "{doc}`../../tutorials/own_model`).", ""]
    for eff in DEFAULT_EFFECTS:
        lines += _effect_section(eff, graphs, optional=False)
    for eff in OPTIONAL_EFFECTS:
        lines += _effect_section(eff, graphs, optional=True)
    return "\n".join(lines)


# ---------------------------------------------------------------- benchmarks
def _bench_module(name: str):
    spec = importlib.util.spec_from_file_location(f"_bench_{name}", ROOT / "bench" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _scalar_rows(d: dict, prefix: str = "") -> list[tuple[str, object]]:
    rows = []
    for k, v in d.items():
        if isinstance(v, dict):
            rows += _scalar_rows(v, f"{prefix}{k}.")
        elif not isinstance(v, list):
            rows.append((f"{prefix}{k}", v))
    return rows


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v).replace("|", "\\|").replace("\n", " ")


def recovery_table(results: list) -> list[str]:
    """The effect-recovery matrix of ``bench/effect_recovery.py`` results."""
    per, total = _bench_module("effect_recovery").summarise(results)
    lines = ["| graph | cases | first | first after confirmation | within 3 CRB | apart | s |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for g, d in per.items():
        lines.append(f"| {g} | {d['cases']} | {d['first']} | {d['first_confirmed']} "
                     f"| {d['within_3crb']} | {d['apart']} | {d['seconds']:.0f} |")
    lines.append(f"| **total** | {total['cases']} | {total['first']} | {total['first_confirmed']}"
                 f" | {total['within_3crb']} | {total['apart']} | {total['seconds']:.0f} |")
    lines += ["", f"Rates: first {total['first_rate']:.1%}, first after confirmation "
                  f"{total['first_confirmed_rate']:.1%} ({total['first_confirmed_tied']} tied "
                  f"with the lead), within 3 CRB {total['within_3crb_rate']:.1%}; median "
                  f"validation error {total['median_val_before']:.3g} -> "
                  f"{total['median_val_after']:.3g}; {total['skipped']} skipped.", ""]
    return lines


def _json_tables(data) -> list[str]:
    """Markdown tables of one result: its scalars, then its first list of rows."""
    lines = []
    tables = data if isinstance(data, list) else []
    if isinstance(data, dict):
        rows = _scalar_rows(data)
        if rows:
            lines += ["| quantity | value |", "|---|---|"]
            lines += [f"| {k} | {_fmt(v)} |" for k, v in rows]
            lines.append("")
        tables = next((v for v in data.values() if isinstance(v, list)
                       and v and isinstance(v[0], dict)), [])
    if tables:
        keys = [k for k in tables[0] if not isinstance(tables[0][k], (dict, list))]
        lines += ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
        lines += ["| " + " | ".join(_fmt(r.get(k)) for k in keys) + " |" for r in tables]
        lines.append("")
    return lines


def bench_tables() -> str:
    """Markdown: one section per bench script ``bench/<name>.py``, its current
    result ``bench/results/<name>.json`` (and ``<name>.png``) as tables; a bench
    without a result, and a result file without a bench, are named as such."""
    results = ROOT / "bench" / "results"
    benches = sorted(p.stem for p in (ROOT / "bench").glob("*.py") if not p.stem.startswith("_"))
    lines = ["# Benchmark results (generated)", "",
             "One section per bench script `bench/<name>.py`, with its current result "
             "`bench/results/<name>.json` read at every documentation build (the history of "
             "each result is in git: `git log -p bench/results/<name>.json`); what the benches "
             "measure and how to read the numbers: {doc}`../benchmarks`.", ""]
    missing = [b for b in benches if not (results / f"{b}.json").exists()]
    orphans = sorted(p.name for p in results.iterdir()
                     if p.stem not in benches or p.suffix not in (".json", ".png"))
    if missing:
        lines += ["Benches without a stored result (run them to write one): "
                  + ", ".join(f"`bench/{b}.py`" for b in missing) + ".", ""]
    if orphans:
        lines += ["Files of `bench/results/` that no bench writes: "
                  + ", ".join(f"`{o}`" for o in orphans) + ".", ""]
    for name in benches:
        path = results / f"{name}.json"
        if not path.exists():
            continue
        lines += [f"## `{path.name}`", "", f"Written by `python bench/{name}.py`.", ""]
        if (results / f"{name}.png").exists():
            lines += [f"(and `bench/results/{name}.png`)", ""]
        data = json.loads(path.read_text())
        lines += recovery_table(data) if name == "effect_recovery" else _json_tables(data)
    return "\n".join(lines)


# ---------------------------------------------------------------- entry
def _write(path: Path, text: str) -> None:
    """Write only on change (Sphinx then rereads only what changed)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.exists() or path.read_text() != text:
        path.write_text(text)


def generate(docs: Path) -> None:
    """Write the generated pages under ``docs``."""
    _write(docs / "reference" / "generated" / "api.rst", api_page())
    _write(docs / "reference" / "generated" / "effects.md", effects_page())
    _write(docs / "background" / "generated" / "bench_tables.md", bench_tables())
