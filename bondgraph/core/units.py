"""Units: parsing, dimension checks and conversion factors (via ``pint``).

Units are optional everywhere. Where they are given, the toolkit checks that
effort x flow is a power on every bond (or, on a pseudo bond graph of heat
transfer, temperature x heat flow), that both ends of a bond agree, and
data loaders convert columns to the units a model expects.

Radians are dimensionless (pint's convention), so ``N*m`` x ``rad/s`` is ``W``.
"""

from __future__ import annotations

import functools
import re

from bondgraph.errors import DataError, UnitMismatchError

#: largest |exponent| accepted in a unit string (``m**2``, ``s^-1``, ``m**(1/2)``);
#: pint evaluates exponents as Python numbers, so ``2**2**2**2**2**2**2`` would
#: not finish
MAX_EXPONENT = 12
#: longest unit string accepted (characters)
MAX_UNIT_LENGTH = 200

_POWER = re.compile(r"\*\*|\^")
_EXPONENT = re.compile(r"\s*(\()?\s*([-+]?\s*(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)"
                       r"(?:\s*/\s*(\d+\.?\d*|\.\d+))?\s*(\))?")

#: Effort and flow units of the usual energy domains (Karnopp, Margolis &
#: Rosenberg, *System Dynamics*, Table 1.1 / ch. 2); magnetic: magnetomotive
#: force and flux rate (a reluctance is a C on the flux, the coil a GY of its
#: turns); chemical: chemical potential and molar flow (Borutzky 2010,
#: *Bond Graph Methodology*, §2.6). Effort x flow is a power in each but
#: ``heat``: the pseudo bond graph of heat transfer (Karnopp, Margolis &
#: Rosenberg, ch. 12; 20-sim's thermal library), temperature and heat flow,
#: whose product is not a power; its C is a heat capacity [J/K], its R a
#: thermal resistance [K/W], and an R's e·f >= 0 still says that heat flows
#: from hot to cold. ``thermal`` is the true bond graph: temperature and
#: entropy flow.
DOMAINS: dict[str, tuple[str, str]] = {
    "translation": ("N", "m/s"),
    "rotation": ("N*m", "rad/s"),
    "electrical": ("V", "A"),
    "hydraulic": ("Pa", "m^3/s"),
    "thermal": ("K", "W/K"),
    "heat": ("K", "W"),
    "magnetic": ("A", "Wb/s"),
    "chemical": ("J/mol", "mol/s"),
}


@functools.lru_cache(maxsize=1)
def registry():
    """The shared pint ``UnitRegistry`` (created on first use), with pint's
    on-disk cache of its parsed definitions (``cache_folder=":auto:"``, the
    user's cache folder): a process then builds it in about 0.1 s instead of
    0.7 s (every command pays it once). Where the cache cannot be used
    (no writable folder, an entry another process is still writing) the
    registry is built from the definitions as without it."""
    return new_registry()


def new_registry():
    """A pint ``UnitRegistry`` as :func:`registry` builds it: from pint's
    disk cache, else (any error of the cache) from the definitions."""
    import pint

    try:
        return pint.UnitRegistry(cache_folder=":auto:")
    except Exception:  # the cache only saves time: without it, the same registry
        return pint.UnitRegistry()


@functools.lru_cache(maxsize=512)
def parse(unit: str):
    """Parse a unit string to a pint ``Quantity`` of magnitude 1 (or the
    unit's scale).

    Parameters
    ----------
    unit : str
        E.g. ``"N*m"``, ``"rad/s"``, ``"kg m^2"``; ``""`` or ``"1"`` is
        dimensionless.

    Raises
    ------
    UnitMismatchError
        If pint does not know the unit.
    """
    ureg = registry()
    text = (unit or "").strip()
    if text in ("", "1", "-"):
        return ureg.Quantity(1.0, "dimensionless")
    check_exponents(text)
    try:
        q = ureg.parse_expression(text)
    except Exception as exc:  # pint raises several types
        raise UnitMismatchError(f"unknown unit '{unit}': {exc}") from None
    if not hasattr(q, "dimensionality"):
        q = ureg.Quantity(float(q), "dimensionless")
    return q


def check_exponents(text: str) -> None:
    """Reject a unit string before pint evaluates it: longer than
    :data:`MAX_UNIT_LENGTH`, an exponent that is not a plain number or
    fraction (``m**x``), a power of a power (``2**2**2``), or an exponent
    beyond ±:data:`MAX_EXPONENT`.

    Raises
    ------
    UnitMismatchError
        Naming the unit string and the offending exponent.
    """
    if len(text) > MAX_UNIT_LENGTH:
        raise UnitMismatchError(f"unknown unit '{text[:40]}...': longer than "
                                f"{MAX_UNIT_LENGTH} characters")
    for op in _POWER.finditer(text):
        m = _EXPONENT.match(text, op.end())
        if m is None or bool(m.group(1)) != bool(m.group(4)):
            raise UnitMismatchError(f"unknown unit '{text}': the exponent after "
                                    f"'{op.group()}' at position {op.start() + 1} is not a "
                                    f"number or a fraction (n/m) in parentheses")
        value = float(m.group(2).replace(" ", ""))
        if m.group(3) is not None:
            den = float(m.group(3))
            value = value / den if den else float("inf")
        if not abs(value) <= MAX_EXPONENT:
            raise UnitMismatchError(f"unknown unit '{text}': exponent {m.group().strip()} is "
                                    f"beyond ±{MAX_EXPONENT}")
        if _POWER.match(text[m.end():].lstrip()):
            raise UnitMismatchError(f"unknown unit '{text}': a power of a power "
                                    f"('{text[op.start():].strip()[:30]}') is not a unit")


def dimensionality(unit: str):
    """Return pint's dimensionality of ``unit`` (hashable, comparable)."""
    return parse(unit).dimensionality


def same_dimension(a: str, b: str) -> bool:
    """True if the two unit strings have the same dimension."""
    return dimensionality(a) == dimensionality(b)


@functools.lru_cache(maxsize=4096)
def is_power(effort_unit: str, flow_unit: str) -> bool:
    """True if ``effort_unit * flow_unit`` has the dimension of watts."""
    q = parse(effort_unit) * parse(flow_unit)
    return q.dimensionality == parse("W").dimensionality


@functools.lru_cache(maxsize=4096)
def is_pseudo_power(effort_unit: str, flow_unit: str) -> bool:
    """True if ``effort_unit`` is a temperature and ``flow_unit`` a power: the
    bond of a pseudo bond graph of heat transfer (temperature and heat flow,
    domain ``heat``; Karnopp, Margolis & Rosenberg, *System Dynamics*, ch. 12)."""
    return (parse(effort_unit).dimensionality == parse("K").dimensionality
            and parse(flow_unit).dimensionality == parse("W").dimensionality)


def product(*units: str) -> str:
    """Unit string of a product, e.g. ``product("N*m", "s") == "N*m*s"``."""
    parts = [f"({u})" for u in units if u and u.strip() not in ("1", "")]
    return "*".join(parts) if parts else "1"


def quotient(num: str, den: str) -> str:
    """Unit string of a quotient."""
    n = num if num and num.strip() else "1"
    if not den or den.strip() in ("", "1"):
        return n
    return f"({n})/({den})"


def factor(from_unit: str, to_unit: str, *, what: str = "value") -> float:
    """Multiplicative factor converting ``from_unit`` to ``to_unit``.

    Raises
    ------
    DataError
        If the units are not convertible (different dimension) or are
        offset units (degC), which need more than a factor.
    """
    try:
        src, dst = parse(from_unit), parse(to_unit)
        q = src.to(dst.units)
        zero = registry().Quantity(0.0, src.units).to(dst.units).magnitude
    except UnitMismatchError:
        raise DataError(f"{what}: unknown unit '{from_unit}' (expected '{to_unit}')") from None
    except Exception:
        raise DataError(
            f"{what}: unit '{from_unit}' cannot be converted to '{to_unit}'") from None
    if zero != 0.0:
        raise DataError(f"{what}: '{from_unit}' -> '{to_unit}' is an offset conversion (e.g. "
                        f"degC), not a factor; convert the values first")
    return float(q.magnitude) / float(dst.magnitude)
