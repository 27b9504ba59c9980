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

import numbers
from dataclasses import dataclass, replace
from typing import Any, Callable

import numpy as np

from bondgraph.core import plugins
from bondgraph.core.graph import BondGraph
from bondgraph.data.records import Experiment
from bondgraph.diagnose.settings import LoopSettings, TrueEffect
from bondgraph.errors import ModelError, OptionError
from bondgraph.numerics.integrators import hold_within
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import METHODS, simulate

#: how :func:`bondgraph.numerics.simulate.simulate` reads sampled inputs
#: between samples
SIMULATION_HOLDS = ("linear", "zoh")


def declared_builder(fn: Callable[[], BondGraph]) -> Callable[[], BondGraph]:
    """Builder that records its ``module:function`` as the graph's source (the
    augmented model file the loop writes imports it)."""

    def make() -> BondGraph:
        g = fn()
        g.source = f"{fn.__module__}:{fn.__name__}"
        return g
    make.__name__ = fn.__name__
    return make


@dataclass
class LoopCase:
    """A declared model, a record, the loop's options (a
    :class:`~bondgraph.diagnose.settings.LoopSettings`, its ``params`` the
    parameters to estimate), and (for synthetic cases) the effect the truth
    has (a :class:`TrueEffect`; a ``(kind, target)`` tuple is converted).
    ``held_out``, optional: ``held_out(result) -> str``, one line the
    command prints after the loop (a :class:`~bondgraph.diagnose.result.LoopResult`):
    the declared and the final model on a record the case holds out where
    the loop cannot judge by it (a real case whose effect only one record
    shows: the Camry's cold start, judged on the cold bag, checked on a
    hot test where it must change nothing).

    Raises
    ------
    OptionError
        ``settings`` is not a :class:`LoopSettings`.
    """

    name: str
    description: str
    declared: Callable[[], BondGraph]
    record: Callable[[], Any]
    settings: LoopSettings
    true_effect: TrueEffect | None = None
    held_out: Callable[[Any], str] | None = None

    def __post_init__(self):
        if not isinstance(self.settings, LoopSettings):
            raise OptionError(f"case '{self.name}': settings must be a LoopSettings, got "
                              f"{type(self.settings).__name__}")
        if self.true_effect is not None and not isinstance(self.true_effect, TrueEffect):
            self.true_effect = TrueEffect(*self.true_effect)

    @property
    def params(self) -> list[str]:
        """The parameters the case estimates (``settings.params``)."""
        return list(self.settings.params)

    def loop_settings(self, params: list[str] | None = None) -> LoopSettings:
        """The case's loop options (:class:`~bondgraph.diagnose.settings.LoopSettings`):
        its declared settings, its parameters (or ``params``) and its true
        effect (synthetic cases: the result records its rank)."""
        return replace(self.settings,
                       params=list(self.settings.params if params is None else params),
                       true_effect=(self.settings.true_effect if self.true_effect is None
                                    else self.true_effect))


@dataclass(frozen=True)
class SimulationOptions:
    """How :func:`synthesize` simulates the truth
    (:func:`bondgraph.numerics.simulate.simulate`, rtol 1e-8, atol 1e-10).

    Parameters
    ----------
    method : str
        One of :data:`bondgraph.numerics.simulate.METHODS`: an adaptive
        solver (default BDF), or fixed-step ``"rk4"`` / ``"ros2"``, which
        always hold the samples and are much faster on long records.
    substeps : int
        Fixed-step methods: steps per sample interval (>= 1).
    hold : {"linear", "zoh"}
        How adaptive solvers read sampled input arrays between samples
        (``"zoh"``: held, exactly what the UKF's zero-order hold sees).

    Raises
    ------
    OptionError
        A value out of its domain (the message names the option and value).

    Examples
    --------
    >>> SimulationOptions(method="rk4", substeps=10, hold="zoh").substeps
    10
    """

    method: str = "BDF"
    substeps: int = 1
    hold: str = "linear"

    def __post_init__(self):
        if self.method not in METHODS:
            raise OptionError(f"SimulationOptions.method = {self.method!r} is not one of "
                              f"{', '.join(repr(m) for m in METHODS)}")
        v = self.substeps
        if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 1:
            raise OptionError(f"SimulationOptions.substeps must be an integer >= 1, got {v!r}")
        object.__setattr__(self, "substeps", int(v))
        if not hold_within(self.hold, SIMULATION_HOLDS):
            raise OptionError(f"SimulationOptions.hold = {self.hold!r} is not one of "
                              f"{', '.join(repr(h) for h in SIMULATION_HOLDS)}")


def synthesize(truth: BondGraph, declared: BondGraph, t: np.ndarray,
               inputs: dict[str, Callable[[np.ndarray], np.ndarray]], x0: dict[str, float],
               params: dict[str, float], seed: int, name: str, description: str, *,
               simulation: SimulationOptions | None = None,
               truth_model: Model | None = None):
    """Simulate ``truth`` and record the outputs of ``declared`` with the
    declared sensors' noise (``numpy.random.default_rng(seed)``).

    ``inputs`` maps input names to callables of t or to arrays (N,) sampled
    at ``t``; ``simulation`` (a :class:`SimulationOptions`, default BDF with
    linearly interpolated samples) chooses the solver, its substeps and how
    it reads sampled arrays between samples. ``truth_model``: ``truth``'s
    model if the caller has built it already (``Model.from_graph(truth)``;
    it is not derived again).

    Returns
    -------
    Experiment
        Inputs, noisy outputs, true states (``state.<name>``) and meta
        (true parameters, x0, seed, noise); every output declares the noise
        std it was drawn with (``noise_std``), so that ``noise="auto"`` holds
        the filter's noise at it.

    Raises
    ------
    OptionError
        ``simulation`` is not a :class:`SimulationOptions`.
    """
    sim_opts = SimulationOptions() if simulation is None else simulation
    if not isinstance(sim_opts, SimulationOptions):
        raise OptionError(f"simulation must be a SimulationOptions, got "
                          f"{type(sim_opts).__name__} {sim_opts!r}")
    tm = Model.from_graph(truth) if truth_model is None else truth_model
    dm = Model.from_graph(declared)
    th = tm.theta({k: v for k, v in params.items() if k in tm.params})
    u = {k: f for k, f in inputs.items() if k in tm.inputs}
    x = tm.state({k: v for k, v in x0.items() if k in tm.states})
    sim = simulate(tm, t, u or None, x0=x, theta=th, method=sim_opts.method, rtol=1e-8,
                   atol=1e-10, hold=sim_opts.hold, substeps=sim_opts.substeps)
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
