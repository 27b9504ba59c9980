"""The first step's structural candidates compiled while a first run waits
for the filter kernel (bondgraph.diagnose.scoring.compile_first_step_ahead):
built with empty scales, before any fit, their C kernels are the ones the
step builds later from the declared fit's scales, because a candidate's
kernels depend on its laws, not on the default values and boxes the scales
set (bondgraph.numerics.compiled.kernel_key_text)."""

import threading
from dataclasses import fields

import numpy as np
import pytest

pytest.importorskip("numba")

from bondgraph.catalog.reference import mass_spring_damper  # noqa: E402
from bondgraph.diagnose import scoring  # noqa: E402
from bondgraph.diagnose.effects import Scales, get_effect  # noqa: E402
from bondgraph.diagnose.fit import Context  # noqa: E402
from bondgraph.diagnose.settings import LoopSettings  # noqa: E402
from bondgraph.numerics import compiled, compiled_c  # noqa: E402

#: three structural laws of different kinds: a sensor's dynamics, a
#: saturating store, a friction state (4 candidates on the graph)
EFFECTS = ("sensor_lowpass", "capacity_limit", "dahl")


def _filled(graph, value: float) -> Scales:
    """Scales with every per-name entry ``value`` (what a fit's scales give:
    none at the empty scales' fallback of 1)."""
    names = set(graph.elements) | {"x", "v", "F", "force"}
    sc = Scales(duration=12.0, dt=0.01)
    for f in fields(sc):
        if isinstance(getattr(sc, f.name), dict):
            setattr(sc, f.name, {n: value for n in names})
    return sc


@pytest.fixture
def cache(tmp_path, monkeypatch):
    if compiled_c.compiler() is None:
        pytest.skip("no C compiler: the candidates' kernels are numba's")
    monkeypatch.setenv("BONDGRAPH_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("BONDGRAPH_KERNELS", raising=False)
    return tmp_path


def test_kernels_built_ahead_are_the_ones_the_step_uses(cache):
    graph = mass_spring_damper()
    effects = [get_effect(e) for e in EFFECTS]
    ctx = Context(None, LoopSettings(params=["k"]), log=lambda msg: None, progress=False)
    scoring._ahead_of_need(ctx, graph, Scales(duration=12.0, dt=0.01), effects,
                           threading.Event())
    fit = type("F", (), {"graph": graph})()
    targets = scoring.structural_targets(fit, effects)
    assert len(targets) == 4
    differ = []
    for eff, tgt in targets:
        early = scoring.build_candidate(ctx, fit, Scales(duration=12.0, dt=0.01), eff, tgt)
        late = scoring.build_candidate(ctx, fit, _filled(graph, 0.37), eff, tgt)
        differ.append(not np.array_equal(early[-1].theta0, late[-1].theta0)
                      or not np.array_equal(early[-1].upper, late[-1].upper))
        # the step's candidate finds its kernels built
        path = compiled.kernel_source_path(late[-1])
        assert path == compiled.kernel_source_path(early[-1])
        assert compiled._c_library(path).exists(), (eff.name, tgt.name)
    # the scales moved the values of the saturation's and the friction's
    # candidates (a sensor low-pass's box comes from the sampling alone)
    assert differ == [False, False, True, True]


def test_building_ahead_stops_when_the_wait_ends(cache):
    done = threading.Event()
    done.set()
    ctx = Context(None, LoopSettings(params=["k"]), log=lambda msg: None, progress=False)
    scoring._ahead_of_need(ctx, mass_spring_damper(), Scales(duration=12.0, dt=0.01),
                           [get_effect(e) for e in EFFECTS], done)
    assert not list(cache.rglob("*.so"))


def test_work_ahead_of_a_step_stops_at_once_on_a_warm_cache(cache, monkeypatch):
    """compile_step_ahead's thread (warm_stop): on a cold cache it builds every
    candidate's kernels; once they are built, it stops after the first
    candidate (a warm run pays one candidate's derivation, not the step's)."""
    graph = mass_spring_damper()
    effects = [get_effect(e) for e in EFFECTS]
    ctx = Context(None, LoopSettings(params=["k"]), log=lambda msg: None, progress=False)
    built = []
    real = scoring.build_candidate

    def counted(*a, **k):
        built.append(a[-1].name)
        return real(*a, **k)

    monkeypatch.setattr(scoring, "build_candidate", counted)
    scales = Scales(duration=12.0, dt=0.01)
    scoring._ahead_of_need(ctx, graph, scales, effects, threading.Event(), warm_stop=True)
    assert len(built) == 4 and len(list(cache.rglob("*.so"))) == 4
    built.clear()
    scoring._ahead_of_need(ctx, graph, scales, effects, threading.Event(), warm_stop=True)
    assert len(built) == 1


def test_no_work_ahead_of_the_last_step():
    from bondgraph.diagnose.runner import next_step_ahead
    ctx = Context(None, LoopSettings(params=["k"]), log=lambda msg: None, progress=False)
    last = ctx.settings.search.max_steps
    assert next_step_ahead(ctx, None, [object()], None, "t", last) is None
    assert next_step_ahead(ctx, None, [], None, "t", 1) is None


def test_the_next_steps_candidates_compile_on_a_thread(cache):
    """compile_step_ahead: a thread builds every structural candidate's kernels of
    the graph it is given (the one the step most likely accepts) until told to
    stop; without the C compiler's conditions (a structural threshold) nothing."""
    from dataclasses import replace
    from types import SimpleNamespace

    effects = [get_effect(e) for e in EFFECTS]
    problem = SimpleNamespace(disc=SimpleNamespace(backend="numba"),
                              t=np.linspace(0.0, 12.0, 1201))
    s = LoopSettings(params=["k"], effects=effects)
    ctx = Context(problem, s, log=lambda msg: None, progress=False)
    done = scoring.compile_step_ahead(ctx, mass_spring_damper())
    assert done is not None
    for _ in range(600):                        # at most a minute
        if len(list(cache.rglob("*.so"))) == 4:
            break
        threading.Event().wait(0.1)
    done.set()
    assert len(list(cache.rglob("*.so"))) == 4
    off = Context(problem, replace(s, search=replace(s.search, structural_threshold=0.5)),
                  log=lambda msg: None, progress=False)
    assert scoring.compile_step_ahead(off, mass_spring_damper()) is None
