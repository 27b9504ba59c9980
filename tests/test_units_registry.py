"""The shared pint registry (:func:`bondgraph.core.units.registry`): built
from pint's disk cache of its parsed definitions where it can be, from the
definitions where it cannot (a read-only or half-written cache); the same
conversions either way (values by hand)."""

from __future__ import annotations

import math

import pint
import pytest

from bondgraph.core import units

CASES = (("N*m/s", 1.0), ("km/h", 1 / 3.6), ("bar", 1e5), ("degree", math.pi / 180),
         ("kWh", 3.6e6), ("mV", 1e-3))


def _base(reg, text: str) -> float:
    return float(reg(text).to_base_units().magnitude)


def test_the_cached_and_the_plain_registry_convert_alike(monkeypatch):
    shared = units.registry()
    assert units.registry() is shared                      # one per process
    for text, si in CASES:
        assert _base(shared, text) == pytest.approx(si, rel=1e-14), text
    real = pint.UnitRegistry
    calls = []

    def no_cache(*args, **kw):
        calls.append(kw.get("cache_folder"))
        if "cache_folder" in kw:
            raise OSError("read-only file system: the cache cannot be written")
        return real(*args, **kw)

    monkeypatch.setattr(pint, "UnitRegistry", no_cache)
    plain = units.new_registry()
    assert calls == [":auto:", None]                       # tried with the cache, then without
    for text, si in CASES:
        assert _base(plain, text) == pytest.approx(si, rel=1e-14), text
