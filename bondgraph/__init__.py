"""bondgraph: declare a bond graph, assign causality, derive and generate its
state equations, simulate, filter and estimate, trace residuals to missing
effects.

The package is layered along the data flow (``docs/ARCHITECTURE.md``); each
layer imports only the layers below it:

``core`` (declare, causality, equations, codegen) <- ``numerics`` (model,
registry, integrators, simulate) <- ``data`` (records, benchmark data,
synthetic experiments) <- ``inference`` (UKF, optimisers, estimation, Fisher)
<- ``sensitivity`` <- ``diagnose`` (residuals, effects, the loop) <- ``report``
(plots, drawings, loop report) <- ``cli``.

This module re-exports the public API of every stage. Names are imported on
first use, so ``import bondgraph`` stays cheap.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from typing import Any

try:
    #: the installed distribution's version (pyproject.toml ``version``)
    __version__ = importlib.metadata.version("bondgraph-toolkit")
except importlib.metadata.PackageNotFoundError:  # a source tree on sys.path, not installed
    __version__ = "0+unknown"

#: public name -> module that defines it
_API: dict[str, str] = {}


def _export(module: str, *names: str) -> None:
    for n in names:
        _API[n] = module


# declare
_export("bondgraph.core.symbols", "Input", "Parameter", "StateVar", "Var")
_export("bondgraph.core.elements", "C", "CField", "GY", "I", "IField", "MGY", "MTF", "One", "R",
        "RField", "Se", "Sf", "TF", "Zero")
_export("bondgraph.core.graph", "Bond", "BondGraph", "Fragment", "Handle", "Sensor")
# causality, equations, code generation
_export("bondgraph.core.causality", "Causality", "assign_causality")
_export("bondgraph.core.equations", "StateSpace", "derive")
_export("bondgraph.core.codegen", "generate_source", "load_module", "write_module")
_export("bondgraph.core.jsonsafe", "from_jsonable", "to_jsonable")
# model, simulation
_export("bondgraph.numerics.model", "Model")
_export("bondgraph.numerics.simulate", "SimResult", "simulate", "stiffness_report")
# records
_export("bondgraph.data.records", "Experiment")
_export("bondgraph.data.experiments", "ExperimentSpec", "get_experiment", "run_experiment")
# filter, estimation
_export("bondgraph.inference.options", "Checkpointing", "Discretisation", "Evaluation",
        "EvolutionOptions", "FitOptions", "SwarmOptions", "UKFOptions")
_export("bondgraph.inference.prior", "PriorSpec")
_export("bondgraph.inference.problem", "NoiseSpec", "Problem", "make_problem")
_export("bondgraph.inference.ukf", "UKFResult", "ukf_nll")
_export("bondgraph.inference.optimize", "de", "pso")
_export("bondgraph.inference.estimate", "EstimationResult", "Stage", "estimate", "two_stage")
_export("bondgraph.inference.options", "TrackOptions")
_export("bondgraph.inference.track", "Change", "TrackResult", "Tracker", "TrackingModel", "track")
# sensitivity, diagnosis
_export("bondgraph.sensitivity.analysis", "LocalOptions", "analyse")
_export("bondgraph.sensitivity.sobol", "SobolOptions")
_export("bondgraph.diagnose.effects", "Effect", "apply_effect")
_export("bondgraph.diagnose.loop", "AcceptRule", "FreeRunOptions", "LoopResult", "LoopSettings",
        "SearchOptions", "chosen_numerics", "run_loop")
_export("bondgraph.diagnose.compare", "Comparison", "compare")
_export("bondgraph.diagnose.cases", "LoopCase", "SimulationOptions", "TrueEffect",
        "synthesize")

#: sub-modules reachable as attributes (``bondgraph.smooth.smooth_sign``)
_MODULES = {"smooth": "bondgraph.core.smooth", "errors": "bondgraph.errors"}

__all__ = sorted(_API) + sorted(_MODULES) + ["__version__"]


def __getattr__(name: str) -> Any:
    if name in _API:
        value = getattr(importlib.import_module(_API[name]), name)
    elif name in _MODULES:
        value = importlib.import_module(_MODULES[name])
    else:
        raise AttributeError(f"module 'bondgraph' has no attribute '{name}'")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__
