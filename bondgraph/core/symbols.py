"""Symbols of a bond graph: parameters, inputs, states and port variables.

All are ``sympy.Symbol`` subclasses (real), so users write constitutive laws
with ordinary sympy arithmetic, e.g. ``Fc * sympy.tanh(v / eps)``. Each
carries its metadata (default value, unit, bounds, description).

Symbols are created uncached, so two graphs may declare a parameter ``m``
with different defaults; inside one graph names are unique.
"""

from __future__ import annotations

import math
from typing import Any

import sympy as sp

from bondgraph.errors import GraphError, ParameterError


class _MetaSymbol(sp.Symbol):
    """Uncached real symbol carrying metadata in ``__dict__``."""

    _meta_fields: tuple[str, ...] = ()

    def __new__(cls, name: str, *args: Any, **kwargs: Any):
        # sympy's cache would return one shared object per name; metadata
        # must not leak between graphs, so bypass it.
        obj = sp.Symbol.__xnew__(cls, name, real=True)
        return obj

    def __getnewargs_ex__(self):  # pickling / deepcopy
        return ((self.name,), {})

    def __reduce_ex__(self, protocol):
        state = {k: getattr(self, k, None) for k in self._meta_fields}
        return (_rebuild_symbol, (type(self), self.name, state))

    def meta(self) -> dict[str, Any]:
        """Metadata as a plain dict (for generated code and reports)."""
        return {"name": self.name, **{k: getattr(self, k, None) for k in self._meta_fields}}


def _number(value: Any, what: str, error=GraphError) -> float:
    """``float(value)`` for a declaration, finite.

    Raises
    ------
    GraphError (or ``error``)
        Naming ``what`` and the value.
    """
    try:
        v = float(value)
    except (TypeError, ValueError, OverflowError):
        raise error(f"{what} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise error(f"{what} must be finite, got {value!r}")
    return v


def _rebuild_symbol(cls, name, state):
    obj = sp.Symbol.__xnew__(cls, name, real=True)
    for k, v in state.items():
        setattr(obj, k, v)
    return obj


class Parameter(_MetaSymbol):
    """A model parameter θ_i.

    Parameters
    ----------
    name : str
        Name, unique in the graph (namespaced by fragments, e.g. ``engine.J``).
    default : float
        Nominal value, in ``unit``.
    unit : str, optional
        Unit string understood by pint (``"kg*m^2"``).
    bounds : (float, float), optional
        Box for estimation; defaults to (default/10, default*10) for positive
        defaults, (default-1, default+1) otherwise.
    description : str, optional
        Meaning, shown in parameter tables.
    source : str, optional
        Where the value comes from (measurement, literature, guess).

    Attributes
    ----------
    box_declared : bool
        Whether ``bounds`` was given. A parameter declared without a box is
        read as a known value: ``bondgraph loop`` without ``--params``
        holds it at its declared value when the record does not identify
        it apart from others, or when the declared fit moves it onto a bound
        of that default box (LoopSettings.hold_unidentified).
    """

    _meta_fields = ("default", "unit", "bounds", "description", "source", "box_declared")

    def __new__(cls, name: str, default: float = 1.0, unit: str | None = None,
                bounds: tuple[float, float] | None = None, description: str = "",
                source: str = ""):
        obj = super().__new__(cls, name)
        d = _number(default, f"parameter '{name}': the default", ParameterError)
        obj.default = d
        obj.unit = unit or ""
        obj.bounds = _bounds(name, d, bounds)
        obj.description = description
        obj.source = source
        obj.box_declared = bounds is not None
        return obj

    def with_name(self, name: str) -> "Parameter":
        """Copy with another name (used when fragments are namespaced)."""
        p = Parameter(name, self.default, self.unit, self.bounds, self.description, self.source)
        p.box_declared = getattr(self, "box_declared", True)
        return p


def _bounds(name: str, default: float, bounds) -> tuple[float, float]:
    """The estimation box of a parameter: ``bounds`` checked, or the default
    box (default/10, default*10) for positive defaults, (default*10,
    default/10) for negative ones, (-1, 1) for zero.

    Raises
    ------
    ParameterError
        Bounds that are not a pair of finite numbers, reversed bounds, or a
        default outside them (the parameter, bounds and default named).
    """
    if bounds is None:
        if default > 0:
            return default / 10.0, default * 10.0
        if default < 0:
            return default * 10.0, default / 10.0
        return -1.0, 1.0
    try:
        lo_, hi_ = bounds
    except (TypeError, ValueError):
        raise ParameterError(f"parameter '{name}': bounds must be a pair (lower, upper), got "
                             f"{bounds!r}") from None
    lo = _number(lo_, f"parameter '{name}': the lower bound", ParameterError)
    hi = _number(hi_, f"parameter '{name}': the upper bound", ParameterError)
    if lo > hi:
        raise ParameterError(f"parameter '{name}': bounds ({lo:g}, {hi:g}) are reversed "
                             f"(lower > upper)", hint=f"write bounds=({hi:g}, {lo:g})")
    if not lo <= default <= hi:
        raise ParameterError(f"parameter '{name}': default {default:g} lies outside its "
                             f"bounds ({lo:g}, {hi:g})")
    return lo, hi


class Input(_MetaSymbol):
    """An input signal u_j (throttle, voltage, road grade, ...).

    Parameters
    ----------
    name : str
        Name, unique in the graph.
    unit : str, optional
        Unit string.
    default : float, optional
        Value used when an experiment does not give the input.
    description : str, optional
    derivative_of : Input, optional
        Set on the automatically created ``der(u)`` inputs that derivative
        causality through a time-varying modulus needs.
    """

    _meta_fields = ("unit", "default", "description", "derivative_of")

    def __new__(cls, name: str, unit: str | None = None, default: float = 0.0,
                description: str = "", derivative_of: "Input | None" = None):
        obj = super().__new__(cls, name)
        obj.unit = unit or ""
        obj.default = _number(default, f"input '{name}': the default")
        obj.description = description
        obj.derivative_of = derivative_of
        return obj

    def with_name(self, name: str) -> "Input":
        return Input(name, self.unit, self.default, self.description, self.derivative_of)


class StateVar(_MetaSymbol):
    """A state x_i: momentum of an I, displacement of a C, or a signal state.

    ``state_kind`` is ``"momentum"``, ``"displacement"``, ``"signal"`` or
    ``"integral"`` (integrator added for a displacement or momentum sensor).
    """

    _meta_fields = ("state_kind", "element", "unit", "initial", "description")

    def __new__(cls, name: str, kind: str = "signal", element: str | None = None,
                unit: str | None = None, initial: float = 0.0, description: str = ""):
        obj = super().__new__(cls, name)
        obj.state_kind = kind
        obj.element = element
        obj.unit = unit or ""
        obj.initial = _number(initial, f"state '{name}': the initial value")
        obj.description = description
        return obj

    def with_name(self, name: str, element: str | None = None) -> "StateVar":
        return StateVar(name, self.state_kind, element if element is not None else self.element,
                        self.unit, self.initial, self.description)


class Var(_MetaSymbol):
    """A port or junction variable (effort or flow) usable in laws and sensors.

    ``var_kind`` is ``"effort"`` or ``"flow"``; ``owner`` names the element or
    junction. These symbols are replaced by their solved expressions during
    equation derivation.
    """

    _meta_fields = ("var_kind", "owner")

    def __new__(cls, name: str, kind: str = "effort", owner: str | None = None):
        obj = super().__new__(cls, name)
        obj.var_kind = kind
        obj.owner = owner
        return obj

    def with_name(self, name: str, owner: str | None = None) -> "Var":
        return Var(name, self.var_kind, owner if owner is not None else self.owner)


def rename(sym: sp.Symbol, name: str, owner: str | None = None) -> sp.Symbol:
    """Copy a toolkit symbol under a new name (fragments' namespacing)."""
    if isinstance(sym, (StateVar, Var)):
        return sym.with_name(name, owner)
    if isinstance(sym, (Parameter, Input)):
        return sym.with_name(name)
    return sp.Symbol(name, real=True)


def identifier(name: str) -> str:
    """A Python identifier for a (possibly dotted) toolkit name.

    ``engine.J_e`` -> ``engine__J_e``; other characters become ``_``.
    """
    out = []
    for ch in name:
        if ch.isalnum() or ch == "_":
            out.append(ch)
        elif ch == ".":
            out.append("__")
        else:
            out.append("_")
    text = "".join(out)
    if not text or text[0].isdigit():
        text = "_" + text
    import keyword

    if keyword.iskeyword(text):
        text += "_"
    return text
