"""Registered models: ``name -> "module:function"`` building a BondGraph.

``bondgraph generate`` writes ``generated/<name>.py`` for every registered
model; ``bondgraph generate --check`` fails, naming the stale model, when a
file differs from what its graph produces (a test runs it).

The toolkit's reference models live in :mod:`bondgraph.catalog.reference`; the vehicle's
graphs and filter models register themselves in ``vehicle_graphs.MODELS``.
"""

from __future__ import annotations

import difflib
import importlib
import time
from pathlib import Path

from bondgraph.errors import ModelError, StaleGeneratedCodeError

#: modules whose ``MODELS`` dict (name -> "module:function") is registered;
#: a module that is not installed is skipped
MODEL_MODULES: tuple[str, ...] = (
    "bondgraph.catalog.reference",            # reference models of the toolkit
    "bondgraph.catalog.benchmarks",  # graphs of the public real-data benchmarks
    "vehicle_graphs",              # the vehicle's graphs and filter models
)

COMMAND = "bondgraph generate"


def registered() -> dict[str, str]:
    """All registered models: the ``MODELS`` dicts of :data:`MODEL_MODULES`."""
    out: dict[str, str] = {}
    for modname in MODEL_MODULES:
        try:
            mod = importlib.import_module(modname)
        except ModuleNotFoundError as exc:
            if exc.name == modname:
                continue
            raise
        for k, v in getattr(mod, "MODELS", {}).items():
            if k in out and out[k] != v:
                raise ModelError(f"model '{k}' registered twice ({out[k]} and {v})")
            out[k] = v
    return out


def resolve(spec: str):
    """Import ``module:function``."""
    mod, _, fn = spec.partition(":")
    return getattr(importlib.import_module(mod), fn)


def build(name: str):
    """Build the BondGraph of a registered model (``graph.source`` is set)."""
    reg = registered()
    if name not in reg:
        raise ModelError(f"unknown model '{name}' (registered: {', '.join(sorted(reg))})")
    g = resolve(reg[name])()
    g.source = reg[name]
    if g.name != name:
        g.name = name
    return g


def generated_dir() -> Path:
    """The ``generated/`` package directory."""
    import generated

    return Path(generated.__file__).parent


def render(name: str) -> str:
    """Source text that ``bondgraph generate`` writes for model ``name``."""
    from bondgraph.core.codegen import generate_source

    g = build(name)
    ss = g.derive()
    return generate_source(ss, source=g.source, command=COMMAND)


def generate(names=None, *, check: bool = False, directory: Path | None = None,
             verbose: bool = True) -> list[str]:
    """(Re)generate registered models, or check them.

    Parameters
    ----------
    names : list of str, optional
        Models to process (default: all registered).
    check : bool
        Do not write; return the names whose file is missing or differs.
    directory : Path, optional
        Target directory (default :func:`generated_dir`).

    Returns
    -------
    list of str
        Stale models (check) or written models.
    """
    directory = Path(directory) if directory else generated_dir()
    names = sorted(registered()) if not names else list(names)
    out = []
    for n in names:
        t0 = time.perf_counter()
        text = render(n)
        path = directory / f"{n}.py"
        if check:
            old = path.read_text() if path.exists() else None
            if old != text:
                out.append(n)
                if verbose:
                    if old is None:
                        print(f"STALE {n}: {path} is missing")
                    else:
                        diff = list(difflib.unified_diff(old.splitlines(), text.splitlines(),
                                                         f"{path} (on disk)", f"{path} (from graph)",
                                                         lineterm="", n=1))
                        print(f"STALE {n}: {path} differs from its graph "
                              f"({sum(1 for d in diff if d[:1] in '+-')} changed lines):")
                        print("\n".join(diff[:20]))
            elif verbose:
                print(f"ok    {n}")
        else:
            if not path.exists() or path.read_text() != text:
                path.write_text(text)
                out.append(n)
                if verbose:
                    print(f"wrote {path} ({time.perf_counter() - t0:.2f} s)")
            elif verbose:
                print(f"same  {path}")
    return out


def check_or_raise(names=None) -> None:
    """Raise :class:`StaleGeneratedCodeError` naming stale models."""
    stale = generate(names, check=True, verbose=False)
    if stale:
        raise StaleGeneratedCodeError(f"generated code is stale for: {', '.join(stale)}; "
                                      f"run `{COMMAND}`")
