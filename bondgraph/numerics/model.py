"""A generated model, loaded for numerical work.

:class:`Model` wraps a generated module (``generated/<name>.py`` or one built
in memory) and gives names, defaults, bounds and parameter-vector helpers.
Everything downstream (simulation, UKF, estimation, diagnosis) works on a
:class:`Model`, never on sympy.
"""

from __future__ import annotations

import importlib
import types
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from bondgraph.core.codegen import (
    ALL_FUNCTIONS,
    generate_source,
    load_module,
    module_from_source,
)
from bondgraph.core.equations import derive
from bondgraph.errors import ModelError
from bondgraph.numerics import derivation_cache


class Model:
    """Numerical model from a generated module.

    Parameters
    ----------
    module : module
        A module written by :mod:`bondgraph.core.codegen`.

    Attributes
    ----------
    name : str
    states, inputs, params, outputs : list of str
    f, h, dfdx, dfdtheta, dhdx, dhdtheta, f_dfdx : callables
        Batched functions of ``(x, u, theta)``; see :mod:`bondgraph.core.codegen`.
    theta0 : ndarray (n_theta,)
        Parameter defaults.
    lower, upper : ndarray (n_theta,)
        Parameter bounds.
    domain_notes : list of str
        The laws evaluated continued past their domain (``sqrt(q)`` taken as
        0 where q < 0; :mod:`bondgraph.core.domains`), one line each.
    """

    def __init__(self, module: types.ModuleType):
        self.module = module
        m = module
        self.name: str = m.NAME
        self.source: str = getattr(m, "SOURCE", "")
        self.description: str = getattr(m, "DESCRIPTION", "")
        self.states = list(m.STATES)
        self.state_units = list(m.STATE_UNITS)
        self.state_kinds = list(m.STATE_KINDS)
        self.inputs = list(m.INPUTS)
        self.input_units = list(m.INPUT_UNITS)
        self.params = list(m.PARAMS)
        self.param_units = list(m.PARAM_UNITS)
        self.param_descriptions = list(getattr(m, "PARAM_DESCRIPTIONS", [""] * len(self.params)))
        self.outputs = list(m.OUTPUTS)
        self.output_units = list(m.OUTPUT_UNITS)
        self.derivative_inputs = dict(getattr(m, "DERIVATIVE_INPUTS", {}))
        #: laws evaluated continued past their domain (bondgraph.core.domains), one line each
        self.domain_notes: list[str] = list(getattr(m, "DOMAIN_NOTES", ()))
        self.x0 = np.array(m.X0, dtype=float)
        self.u0 = np.array(m.INPUT_DEFAULTS, dtype=float)
        self.theta0 = np.array(m.PARAM_DEFAULTS, dtype=float)
        self.lower = np.array(m.PARAM_LOWER, dtype=float)
        self.upper = np.array(m.PARAM_UPPER, dtype=float)
        #: seconds of numpy UKF time spent on this model (bondgraph.numerics.compiled)
        for fn in ("f", "h", "dfdx", "dfdtheta", "dhdx", "dhdtheta", "dfdu", "dhdu", "f_dfdx", "energy",
                   "power_sources", "power_dissipated", "energy_rate", "meas_std", "proc_std",
                   "fx", "hx"):
            if hasattr(m, fn):
                setattr(self, fn, getattr(m, fn))

    # ----------------------------------------------------------- loading
    @classmethod
    def load(cls, name: str, directory: str | Path | None = None) -> "Model":
        """Load the generated code of a registered model (the registered
        ``generated`` package, :func:`bondgraph.numerics.registry.generated_dir`)
        or ``<directory>/<name>.py``.

        Raises
        ------
        ModelError
            If no such generated module exists; the message lists the
            registered models.
        """
        from bondgraph.numerics import registry

        if directory is not None:
            path = Path(directory) / f"{name}.py"
            if not path.exists():
                raise ModelError(f"no generated model '{name}' in {directory}")
            return cls(load_module(path))
        reg = registry.registered()
        path = registry.generated_dir() / f"{name}.py"
        if name not in reg or not path.exists():
            names = ", ".join(sorted(reg))
            hint = ("run `bondgraph generate`" if name in reg else
                    "give a registered name, module:function or path/to/file.py:function")
            raise ModelError(f"no generated model '{name}' (registered: {names}); {hint}")
        pkg = registry.generated_dir().name
        return cls(importlib.import_module(f"{pkg}.{name}"))

    @classmethod
    def from_spec(cls, spec: "str | Model", *, functions=None) -> "Model":
        """A model from a registered name (its generated code), or from a graph
        builder ``module:function`` / ``path/to/file.py:function`` (derived and
        generated in memory); a Model is returned as is.

        Raises
        ------
        ModelError
            Unknown name, builder not importable or not returning a BondGraph.
        """
        from bondgraph.numerics import registry

        if isinstance(spec, Model):
            return spec
        if spec in registry.registered():
            return cls.load(spec)
        return cls.from_graph(registry.graph_builder(spec)(), functions=functions)

    @classmethod
    def from_graph(cls, graph, *, functions=None, name: str | None = None,
                   lazy: Sequence[str] = ()) -> "Model":
        """Derive, generate and load a model in memory from a BondGraph.

        Parameters
        ----------
        graph : BondGraph
        functions : sequence of str, optional
            Generated functions (default all of them).
        name : str, optional
            Module name.
        lazy : sequence of str
            Those of ``functions`` generated only when first used (the
            Jacobians of a model that may never need them: their symbolic
            differentiation and code are most of the generation time).
        """
        lazy = tuple(fn for fn in lazy if fn in (functions or ALL_FUNCTIONS))
        eager = tuple(fn for fn in (functions or ALL_FUNCTIONS) if fn not in lazy)
        key = derivation_cache.graph_key(graph, ",".join(eager))
        cached = derivation_cache.load(key)
        if cached is None:
            ss = derive(graph)
            text = generate_source(ss, source=graph.source or f"<graph {graph.name}>",
                                   functions=eager)
            derivation_cache.store(key, (ss, text))
        else:
            ss, text = cached
            _restore_state_units(graph, ss)
        mod = module_from_source(text, name or f"_bondgraph_mem_{graph.name}")
        mod.__source_text__ = text
        mod.__state_space__ = ss       # for the numba kernels (bondgraph.numerics.compiled)
        mod.__lazy_functions__ = lazy
        mod.__derivation_key__ = key
        return cls(mod)

    def __getattr__(self, name: str):
        """A lazy function of a model built in memory (:meth:`from_graph`),
        generated and loaded on first use."""
        mod = self.__dict__.get("module")
        if name.startswith("__") or name not in getattr(mod, "__lazy_functions__", ()):
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        key = getattr(mod, "__derivation_key__", None)
        key = None if key is None else f"{key}-{name}"
        text = derivation_cache.load(key)
        if text is None:
            text = generate_source(mod.__state_space__, source=getattr(mod, "SOURCE", None),
                                   functions=(name,))
            derivation_cache.store(key, text)
        fn = getattr(module_from_source(text, f"{mod.__name__}__{name}"), name)
        setattr(self, name, fn)
        return fn

    # ------------------------------------------------------------- pickling
    def __reduce__(self):
        """Pickle by reference to the generated code (modules do not pickle):
        a module built in memory travels as its source text (and state
        space, for its numba kernels), a generated file as its import name
        and path. Used by the Dask executor to send criteria to workers."""
        m = self.module
        text = getattr(m, "__source_text__", None)
        if text is not None:
            return (_model_from_text, (text, m.__name__, getattr(m, "__state_space__", None),
                                       getattr(m, "__lazy_functions__", ())))
        return (_model_from_file, (m.__name__, getattr(m, "__file__", None)))

    # ------------------------------------------------------------- sizes
    @property
    def n_x(self) -> int:
        return len(self.states)

    @property
    def n_u(self) -> int:
        return len(self.inputs)

    @property
    def n_theta(self) -> int:
        return len(self.params)

    @property
    def n_y(self) -> int:
        return len(self.outputs)

    # ------------------------------------------------------------ lookup
    def _index(self, names: list[str], name: str, what: str) -> int:
        try:
            return names.index(name)
        except ValueError:
            close = [n for n in names if name.split(".")[-1] in n]
            hint = f" Did you mean {', '.join(close[:5])}?" if close else ""
            raise ModelError(f"model '{self.name}' has no {what} '{name}'.{hint} "
                             f"Known: {', '.join(names)}") from None

    def state_index(self, name: str) -> int:
        return self._index(self.states, name, "state")

    def input_index(self, name: str) -> int:
        return self._index(self.inputs, name, "input")

    def param_index(self, name: str) -> int:
        return self._index(self.params, name, "parameter")

    def output_index(self, name: str) -> int:
        return self._index(self.outputs, name, "output")

    def param_indices(self, names: Iterable[str]) -> np.ndarray:
        return np.array([self.param_index(n) for n in names], dtype=int)

    # ------------------------------------------------------------ vectors
    def theta(self, values: Mapping[str, float] | None = None, **kw: float) -> np.ndarray:
        """Full parameter vector: defaults with named overrides.

        >>> th = model.theta({"m": 2.0})  # doctest: +SKIP
        """
        th = self.theta0.copy()
        for k, v in {**(values or {}), **kw}.items():
            th[self.param_index(k)] = float(v)
        return th

    def state(self, values: Mapping[str, float] | None = None, **kw: float) -> np.ndarray:
        """State vector: X0 with named overrides."""
        x = self.x0.copy()
        for k, v in {**(values or {}), **kw}.items():
            x[self.state_index(k)] = float(v)
        return x

    def input(self, values: Mapping[str, float] | None = None, **kw: float) -> np.ndarray:
        """Input vector: defaults with named overrides."""
        u = self.u0.copy()
        for k, v in {**(values or {}), **kw}.items():
            u[self.input_index(k)] = float(v)
        return u

    def expand_theta(self, names: Sequence[str], values: np.ndarray,
                     base: np.ndarray | None = None) -> np.ndarray:
        """Full parameter arrays from values of a subset.

        Parameters
        ----------
        names : sequence of str
            Estimated parameters (length k).
        values : array (..., k)
        base : array (n_theta,), optional
            Values of the other parameters (default ``theta0``).

        Returns
        -------
        array (..., n_theta)
        """
        values = np.asarray(values, dtype=float)
        base = self.theta0 if base is None else np.asarray(base, dtype=float)
        idx = self.param_indices(names)
        if values.shape[-1] != len(idx):
            raise ModelError(f"expected {len(idx)} values for {list(names)}, got shape {values.shape}")
        out = np.broadcast_to(base, values.shape[:-1] + base.shape).copy()
        out[..., idx] = values
        return out

    def bounds(self, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        idx = self.param_indices(names)
        return self.lower[idx].copy(), self.upper[idx].copy()

    def param_table(self) -> str:
        """Markdown table of the parameters."""
        rows = ["| parameter | default | unit | bounds | description |", "|---|---|---|---|---|"]
        for i, n in enumerate(self.params):
            rows.append(f"| {n} | {self.theta0[i]:.6g} | {self.param_units[i]} | "
                        f"[{self.lower[i]:.4g}, {self.upper[i]:.4g}] | {self.param_descriptions[i]} |")
        return "\n".join(rows)

    def __repr__(self) -> str:
        return (f"<Model {self.name}: {self.n_x} states, {self.n_u} inputs, "
                f"{self.n_theta} parameters, {self.n_y} outputs>")


def load(name: str, directory: str | Path | None = None) -> Model:
    """Shortcut for :meth:`Model.load`."""
    return Model.load(name, directory)


def _restore_state_units(graph, ss) -> None:
    """What a derivation does to its graph, for one read from the cache: the
    storage states without a unit get the unit derived for them
    (:func:`bondgraph.core.equations.derive` gives them effort x s or
    flow x s)."""
    units = {s.name: s.unit for s in ss.states if getattr(s, "unit", "")}
    for el in graph.elements.values():
        st = getattr(el, "state", None)
        if st is not None and not getattr(st, "unit", "x") and st.name in units:
            st.unit = units[st.name]


def _model_from_text(text: str, name: str, ss=None, lazy=()) -> Model:
    """Unpickle a model built in memory (:meth:`Model.__reduce__`)."""
    mod = module_from_source(text, name)
    mod.__source_text__ = text
    mod.__state_space__ = ss
    mod.__lazy_functions__ = tuple(lazy) if ss is not None else ()
    return Model(mod)


def _model_from_file(name: str, file: str | None) -> Model:
    """Unpickle a model loaded from generated code (:meth:`Model.__reduce__`):
    by import name when it imports, else from its file."""
    try:
        return Model(importlib.import_module(name))
    except ImportError:
        if not file:
            raise ModelError(f"cannot rebuild model module '{name}' (no file)") from None
        return Model(load_module(file, name))
