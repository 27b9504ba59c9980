"""The on-disk cache of derivations and generated code of graphs built in
memory (bondgraph.numerics.derivation_cache): a hit gives the same model as
deriving again, any change of the graph misses, what has no canonical text
is not cached, and a damaged entry is derived again."""

import subprocess
import sys

import numpy as np
import sympy as sp

from bondgraph.catalog import reference
from bondgraph.core.equations import derive
from bondgraph.core.codegen import generate_source
from bondgraph.numerics import derivation_cache as dc
from bondgraph.numerics.model import Model


def _entries(tmp_path):
    return sorted((tmp_path / "models").glob("*.pkl"))


def test_a_hit_gives_the_source_and_numbers_of_a_fresh_derivation(tmp_path, monkeypatch):
    monkeypatch.setenv("BONDGRAPH_CACHE_DIR", str(tmp_path))
    g = reference.mass_spring_damper()
    first = Model.from_graph(g, name="m1")
    assert len(_entries(tmp_path)) == 1
    calls = []
    monkeypatch.setattr("bondgraph.numerics.model.derive",
                        lambda *a, **k: calls.append(1) or derive(*a, **k))
    g2 = reference.mass_spring_damper()
    second = Model.from_graph(g2, name="m2")
    assert calls == []                                   # read, not derived
    # what the derivation does to its graph is done on a hit too
    assert (g2.elements["mass"].state.unit, g2.elements["spring"].state.unit) == ("N*s", "m")
    assert second.state_units == first.state_units == ["N*s", "m"]
    reference_text = generate_source(derive(g), source=g.source or f"<graph {g.name}>")
    assert second.module.__source_text__ == reference_text
    rng = np.random.default_rng(0)
    x = rng.normal(size=(5, first.n_x))
    u = rng.normal(size=(5, first.n_u))
    th = first.theta0 * rng.uniform(0.5, 2, size=(5, first.n_theta))
    np.testing.assert_array_equal(second.f(x, u, th), first.f(x, u, th))
    np.testing.assert_array_equal(second.dfdx(x, u, th), first.dfdx(x, u, th))


def test_a_changed_default_box_or_law_misses():
    keys = set()
    for change in (None, "default", "box", "law"):
        g = reference.mass_spring_damper()
        if change == "default":
            g.params["k"].default = g.params["k"].default * 1.000001
        elif change == "box":
            g.params["k"].bounds = (1.0, 1e4)
        elif change == "law":
            r = next(e for e in g.elements.values() if type(e).__name__ == "R")
            r.resistance = r.resistance * 2
        keys.add(dc.graph_key(g, "f,h"))
    assert len(keys) == 4 and None not in keys
    g = reference.mass_spring_damper()
    assert dc.graph_key(g, "f,h") != dc.graph_key(g, "f")


def test_the_key_does_not_depend_on_the_process(tmp_path):
    code = ("from bondgraph.catalog import reference; "
            "from bondgraph.numerics import derivation_cache as dc; "
            "import sympy; sympy.symbols('k m c q_spring')\n"   # a warmer sympy cache
            "print(dc.graph_key(reference.mass_spring_damper(), 'f'))")
    keys = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           env={"PYTHONHASHSEED": seed, "PATH": "/usr/bin:/bin"},
                           check=True).stdout.strip() for seed in ("1", "2")}
    keys.add(dc.graph_key(reference.mass_spring_damper(), "f"))
    assert len(keys) == 1 and len(keys.pop()) == 32


def test_a_closure_or_a_users_function_class_is_not_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("BONDGRAPH_CACHE_DIR", str(tmp_path))
    g = reference.mass_spring_damper()
    g.metadata["hook"] = lambda x: x
    assert dc.graph_key(g) is None
    Model.from_graph(g, name="closure")                   # still builds, uncached
    assert _entries(tmp_path) == []
    mine = type("mine", (sp.Function,), {"__module__": "users_module"})
    assert dc.graph_key({"law": mine(sp.Symbol("x"))}) is None
    assert dc.graph_key({"law": sp.tanh(sp.Symbol("x"))}) is not None


def test_a_damaged_entry_is_derived_again(tmp_path, monkeypatch):
    monkeypatch.setenv("BONDGRAPH_CACHE_DIR", str(tmp_path))
    g = reference.mass_spring_damper()
    Model.from_graph(g, name="a")
    (entry,) = _entries(tmp_path)
    entry.write_bytes(b"not a pickle")
    m = Model.from_graph(reference.mass_spring_damper(), name="b")
    assert m.module.__source_text__ == generate_source(
        derive(g), source=g.source or f"<graph {g.name}>")
    assert entry.read_bytes() != b"not a pickle"          # written again
