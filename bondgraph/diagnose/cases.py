"""Bundled cases of the residual-tracing loop.

Each :class:`LoopCase` pairs a *declared* filter model (what the engineer
wrote) with a record that has an effect the declared model lacks:

* synthetic cases: the record is simulated (:func:`synthesize`) from a
  *truth* graph, the declared graph plus one physical effect, with the
  declared sensor noise and a fixed seed;
* real data: a record with a known missing effect.

Cases register like models (:mod:`bondgraph.core.plugins`, kind ``cases``):
the toolkit's real-data cases are in :mod:`bondgraph.catalog.cases`, the
vehicle's in ``vehicle_graphs.cases``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Callable

import numpy as np

from bondgraph.core import plugins
from bondgraph.core.graph import BondGraph
from bondgraph.data.records import Experiment
from bondgraph.diagnose.settings import LoopSettings
from bondgraph.errors import ModelError, OptionError
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate


def declared_builder(fn: Callable[[], BondGraph]) -> Callable[[], BondGraph]:
    """Builder that records its ``module:function`` as the graph's source (the
    augmented model file the loop writes imports it)."""

    def make() -> BondGraph:
        g = fn()
        g.source = f"{fn.__module__}:{fn.__name__}"
        return g
    make.__name__ = fn.__name__
    return make


@dataclass(frozen=True)
class TrueEffect:
    """The effect a synthetic case's truth has: the declared graph plus
    effect ``kind`` (a name of :mod:`bondgraph.diagnose.effects`) at
    ``target`` (a target name) with parameter ``values`` (by the effect's
    local parameter names). Unpacks as ``(kind, target)``."""

    kind: str
    target: str
    values: dict = field(default_factory=dict)

    def __iter__(self):
        return iter((self.kind, self.target))

    @property
    def label(self) -> str:
        """``"kind @ target"``, as a candidate's label."""
        return f"{self.kind} @ {self.target}"

    def to_dict(self) -> dict:
        """JSON-ready: kind, target, values."""
        return {"kind": self.kind, "target": self.target, "values": dict(self.values)}


@dataclass
class LoopCase:
    """A declared model, a record, the parameters to estimate, loop settings,
    and (for synthetic cases) the effect the truth has (a :class:`TrueEffect`;
    a ``(kind, target)`` tuple is converted)."""

    name: str
    description: str
    declared: Callable[[], BondGraph]
    record: Callable[[], Any]
    params: list[str]
    settings: dict = field(default_factory=dict)
    true_effect: TrueEffect | None = None

    def __post_init__(self):
        if self.true_effect is not None and not isinstance(self.true_effect, TrueEffect):
            self.true_effect = TrueEffect(*self.true_effect)

    def loop_settings(self, params: list[str] | None = None) -> LoopSettings:
        """The case's loop options (:class:`~bondgraph.diagnose.settings.LoopSettings`):
        its declared settings, its parameters (or ``params``) and its true
        effect (synthetic cases: the result records its rank).

        Raises
        ------
        OptionError
            A setting the loop does not have, or a bad value.
        """
        extra = {} if self.true_effect is None else {"true_effect": self.true_effect}
        unknown = sorted(set(self.settings) - {f.name for f in fields(LoopSettings)})
        if unknown:
            raise OptionError(f"case '{self.name}' declares unknown loop setting(s) "
                              f"{', '.join(unknown)}")
        return LoopSettings(params=list(self.params if params is None else params),
                            **{**self.settings, **extra})


def synthesize(truth: BondGraph, declared: BondGraph, t: np.ndarray,
               inputs: dict[str, Callable[[np.ndarray], np.ndarray]], x0: dict[str, float],
               params: dict[str, float], seed: int, name: str, description: str, *,
               hold: str = "linear", method: str = "BDF", substeps: int = 1,
               truth_model: Model | None = None):
    """Simulate ``truth`` and record the outputs of ``declared`` with the
    declared sensors' noise (``numpy.random.default_rng(seed)``).

    ``inputs`` maps input names to callables of t or to arrays (N,) sampled
    at ``t``; ``hold`` is how :func:`bondgraph.numerics.simulate.simulate`
    reads sampled arrays between samples (``"zoh"``: held, exactly what the
    UKF's zero-order hold sees). ``method`` and ``substeps`` choose the
    solver (default BDF, rtol 1e-8; ``"rk4"`` with ``substeps`` steps per
    sample always holds the samples and is much faster on long records).
    ``truth_model``: ``truth``'s model if the caller has built it already
    (``Model.from_graph(truth)``; it is not derived again).

    Returns
    -------
    Experiment
        Inputs, noisy outputs, true states (``state.<name>``) and meta
        (true parameters, x0, seed, noise); every output declares the noise
        std it was drawn with (``noise_std``), so that ``noise="auto"`` holds
        the filter's noise at it.
    """
    tm = Model.from_graph(truth) if truth_model is None else truth_model
    dm = Model.from_graph(declared)
    th = tm.theta({k: v for k, v in params.items() if k in tm.params})
    u = {k: f for k, f in inputs.items() if k in tm.inputs}
    x = tm.state({k: v for k, v in x0.items() if k in tm.states})
    sim = simulate(tm, t, u or None, x0=x, theta=th, method=method, rtol=1e-8, atol=1e-10,
                   hold=hold, substeps=substeps)
    rng = np.random.default_rng(seed)
    thd = dm.theta({k: v for k, v in params.items() if k in dm.params})
    sd = dm.meas_std(thd)
    y = np.empty((t.size, dm.n_y))
    for i, o in enumerate(dm.outputs):
        y[:, i] = sim.y[:, tm.output_index(o)] + rng.normal(size=t.size) * sd[i]
    ud = np.column_stack([sim.u[:, tm.input_index(n)] if n in tm.inputs else
                          np.full(t.size, dm.u0[j]) for j, n in enumerate(dm.inputs)]) \
        if dm.n_u else None
    meta = {"name": name, "description": description, "model": declared.name,
            "truth_model": truth.name, "seed": seed,
            "true_parameters": {p: float(v) for p, v in zip(tm.params, th)},
            "x0": {s: float(v) for s, v in zip(tm.states, x) if s in dm.states},
            "noise": {o: float(v) for o, v in zip(dm.outputs, sd)}}
    return Experiment.from_arrays(t, model=dm, u=ud, y=y, meta=meta, name=name,
                                  noise_std={o: float(v) for o, v in zip(dm.outputs, sd)})


def registered_cases() -> dict[str, str]:
    """All registered loop cases, ``name -> "module:function"``."""
    return plugins.registered("cases")


def get_case(name: str) -> LoopCase:
    """Build the registered case ``name``.

    Raises
    ------
    ModelError
        Unknown case (the registered ones are listed).
    """
    reg = registered_cases()
    if name not in reg:
        raise ModelError(f"unknown loop case '{name}' (cases: {', '.join(sorted(reg))})")
    return plugins.resolve(reg[name])()
