"""Distributions of :mod:`scipy.stats` imported at their first use.

``scipy.stats`` costs about 0.6 s of every command's start (it pulls in
scipy's sparse, spatial, interpolate and ndimage packages), and most
commands meet a χ² quantile only after seconds of filtering. The modules that
test with it import :data:`chi2`, :data:`norm` or :data:`stats` from here;
the first attribute read (``chi2.sf(x, k)``) imports scipy.stats and every
later one goes straight to scipy's object.
"""

from __future__ import annotations

import importlib
from typing import Any


class Deferred:
    """``module.name`` (or the module itself, ``name=None``) imported at the
    first attribute read; every attribute is the imported object's."""

    __slots__ = ("_module", "_name", "_target")

    def __init__(self, module: str, name: str | None = None) -> None:
        self._module = module
        self._name = name
        self._target = None

    def _load(self) -> Any:
        if self._target is None:
            obj = importlib.import_module(self._module)   # thread-safe: the import lock
            self._target = obj if self._name is None else getattr(obj, self._name)
        return self._target

    def __getattr__(self, attr: str) -> Any:
        return getattr(self._load(), attr)

    def __repr__(self) -> str:
        what = self._module if self._name is None else f"{self._module}.{self._name}"
        return f"<deferred {what}>"


#: :data:`scipy.stats.chi2`
chi2 = Deferred("scipy.stats", "chi2")
#: :data:`scipy.stats.norm`
norm = Deferred("scipy.stats", "norm")
#: :mod:`scipy.stats`
stats = Deferred("scipy.stats")
