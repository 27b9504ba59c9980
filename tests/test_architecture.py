"""The architecture rules, checked: the import-linter contracts hold, each
layer of bondgraph/ imports alone without loading a higher layer, and no
function is longer than 80 lines (docstring included)."""

from __future__ import annotations

import ast
import json
import pkgutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import bondgraph

ROOT = Path(__file__).resolve().parent.parent

#: bondgraph's layers, lowest first (pyproject.toml, [tool.importlinter]);
#: the last entry holds two independent siblings
LAYERS = ["errors", "core", "numerics", "export", "data", "inference", "sensitivity", "diagnose",
          "report", "cli", "catalog"]
#: packages the library must never load
APPLICATION = ("vehicle_graphs", "generated")

MAX_LINES = 80
#: functions still over MAX_LINES, with the reason (none today). A
#: new long function fails test_no_function_over_80_lines; an entry whose
#: function got short fails test_length_allowlist_is_current.
LENGTH_ALLOWLIST: dict[str, str] = {
}


# ----------------------------------------------------------- import-linter
def test_import_contracts_are_kept():
    exe = Path(sys.executable).parent / "lint-imports"
    if not exe.exists():  # pragma: no cover - dev extra not installed
        pytest.skip("import-linter is not installed (pip install -e '.[dev]')")
    r = subprocess.run([str(exe), "--no-cache"], cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 broken" in r.stdout and " kept" in r.stdout, r.stdout
    # the three contracts of pyproject.toml are all there and kept
    for name in ("bondgraph layers follow the data flow",
                 "no import cycles inside bondgraph, at any depth",
                 "the library names no application package"):
        assert f"{name} KEPT" in r.stdout, r.stdout


# ----------------------------------------------------------- layer imports
def _layer_modules(layer: str) -> list[str]:
    """Every module of a layer (the package and its submodules, recursively)."""
    path = Path(bondgraph.__file__).parent / layer
    if not path.is_dir():
        return [f"bondgraph.{layer}"]
    return [f"bondgraph.{layer}"] + [
        m.name for m in pkgutil.walk_packages([str(path)], prefix=f"bondgraph.{layer}.")]


_CHILD = """
import importlib, json, sys
for name in {mods!r}:
    importlib.import_module(name)
print(json.dumps(sorted(sys.modules)))
"""


def _loaded_by(modules: list[str]) -> set[str]:
    r = subprocess.run([sys.executable, "-c", _CHILD.format(mods=modules)], cwd=ROOT,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, f"importing {modules} failed:\n{r.stderr}"
    return set(json.loads(r.stdout.strip().splitlines()[-1]))


@pytest.mark.parametrize("layer", LAYERS)
def test_each_layer_imports_alone(layer):
    """A fresh interpreter imports every module of the layer, and loads no
    module of a higher layer (nor of the independent sibling, nor the
    application packages)."""
    mods = _layer_modules(layer)
    assert len(mods) >= 1
    loaded = _loaded_by(mods)
    assert set(mods) <= loaded
    i = LAYERS.index(layer)
    higher = LAYERS[i + 1:]
    if layer == "catalog":
        higher = ["cli"]  # cli | catalog: independent siblings
    bad = sorted(m for m in loaded
                 if any(m == f"bondgraph.{h}" or m.startswith(f"bondgraph.{h}.") for h in higher)
                 or m.split(".")[0] in APPLICATION)
    assert not bad, f"importing the {layer} layer loads {bad}"


#: libraries a command needs only for some of its work, imported where they
#: are used (bondgraph.core.deferred): together about 2 of the 4.8 s that
#: ``import bondgraph.cli.loop`` took with them (2.7 s without, measured)
DEFERRED = ("matplotlib", "statsmodels", "pandas", "scipy.stats", "scipy.signal", "SALib",
            "pint", "sklearn", "pysindy")


def test_the_commands_start_without_the_deferred_libraries():
    """A fresh interpreter that imports every command's module (what
    ``bondgraph loop``, ``estimate``, ``sensitivity``, ``track`` ... load
    before their work starts) has imported none of :data:`DEFERRED`."""
    loaded = _loaded_by(_layer_modules("cli"))
    bad = sorted(m for m in loaded if m in DEFERRED or m.split(".")[0] in DEFERRED)
    assert not bad, f"the command line imports {bad[:8]} at its start"


def test_layer_list_matches_the_contract():
    """LAYERS above is the layers contract of pyproject.toml (so the import
    test checks the real rule)."""
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    contract = [c for c in cfg["tool"]["importlinter"]["contracts"] if c["type"] == "layers"][0]
    flat = []
    for entry in reversed(contract["layers"]):
        flat += sorted(p.strip() for p in entry.split("|"))
    assert flat == LAYERS[:-2] + sorted(LAYERS[-2:])
    on_disk = {p.stem if p.is_file() else p.name
               for p in Path(bondgraph.__file__).parent.iterdir()
               if (p.is_dir() and (p / "__init__.py").exists())
               or (p.suffix == ".py" and p.stem != "__init__")}
    assert on_disk == set(LAYERS), on_disk ^ set(LAYERS)


# ---------------------------------------------------------- function length
def long_functions(roots=("bondgraph", "vehicle_graphs"), limit: int = MAX_LINES,
                   base: Path = ROOT) -> dict[str, int]:
    """``"path:Qual.name" -> lines`` of every function (methods and nested
    functions too) longer than ``limit`` lines, counted from ``def`` to the
    last line of the body, docstring included; paths relative to ``base``."""
    out: dict[str, int] = {}

    def walk(node, path: str, prefix: str) -> None:
        for ch in ast.iter_child_nodes(node):
            if isinstance(ch, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = ch.end_lineno - ch.lineno + 1
                if n > limit:
                    out[f"{path}:{prefix}{ch.name}"] = n
                walk(ch, path, f"{prefix}{ch.name}.")
            elif isinstance(ch, ast.ClassDef):
                walk(ch, path, f"{prefix}{ch.name}.")

    for root in roots:
        for p in sorted((base / root).rglob("*.py")):
            rel = p.relative_to(base).as_posix()
            walk(ast.parse(p.read_text(encoding="utf-8"), filename=rel), rel, "")
    return out


def test_length_counter(tmp_path):
    """Lines from ``def`` to the last line, docstring and blank lines
    included, decorators not; methods and nested functions by qualified name."""
    stmts = [f"x{i} = {i}" for i in range(76)]
    lines = ["import functools", "",
             "def short():",                       # 1 + 2 + 76 = 79 lines
             "    '''doc", "    more'''"] + ["    " + s for s in stmts] + ["",
             "class A:",
             "    @functools.cache",
             "    def method(self):",              # 3 + 76 + 82 (inner) + 1 = 162 lines
             "        '''doc'''",
             ""] + ["        " + s for s in stmts] + [
             "        def inner():",               # 1 + 81 = 82 lines
             ] + ["            " + s for s in [f"y{i} = {i}" for i in range(81)]] + [
             "        return inner"]
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "m.py").write_text("\n".join(lines) + "\n")
    found = long_functions(("pkg",), base=tmp_path)
    assert found == {"pkg/m.py:A.method": 1 + 1 + 1 + 76 + 82 + 1,
                     "pkg/m.py:A.method.inner": 82}
    assert long_functions(("pkg",), limit=78, base=tmp_path)["pkg/m.py:short"] == 79
    assert "pkg/m.py:short" not in long_functions(("pkg",), limit=79, base=tmp_path)


def test_no_function_over_80_lines():
    new = {k: n for k, n in long_functions().items() if k not in LENGTH_ALLOWLIST}
    assert not new, ("functions over 80 lines (docstring included); split them along their "
                     f"steps: {new}")


def test_length_allowlist_is_current():
    long = long_functions()
    stale = sorted(k for k in LENGTH_ALLOWLIST if k not in long)
    assert not stale, f"no longer over 80 lines, remove from LENGTH_ALLOWLIST: {stale}"
