"""The documentation: the Sphinx site builds with warnings as errors, the
code blocks of its pages run, and the README stays short and says what CI runs.

Which blocks run (``code_blocks``): a fenced ``python`` block runs in Python,
a ``bash`` block in the shell (``bondgraph`` of this interpreter's
environment first on PATH); a ```` {code-block} python```` directive with a
``:caption: NAME.py`` is a file the page asks you to write, and is written
into the page's working directory; other blocks (``text``, captionless
``{code-block}``) are shown, not run. The blocks of the walk-through pages
(``RUN_UNDER``) run; each page runs in a fresh directory,
its blocks in page order; consecutive Python blocks run as one script.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
FENCE = re.compile(r"^```(?P<info>[^\n`]*)\n(?P<body>.*?)^```\s*$", re.S | re.M)


def code_blocks(page: Path) -> list[tuple[str, str]]:
    """``(kind, text)`` of a page's blocks that run: ``("python", code)``,
    ``("bash", script)``, ``("file:NAME", content)``."""
    out = []
    for m in FENCE.finditer(page.read_text()):
        info, body = m["info"].strip(), m["body"]
        if info in ("python", "bash"):
            out.append((info, body))
        elif info == "{code-block} python":
            cap = re.match(r"\s*:caption:\s*(\S+\.py)\s*\n", body)
            if cap:
                out.append((f"file:{cap[1]}", body[cap.end():].lstrip("\n")))
    return out


#: the pages whose blocks run: the walk-throughs (reference pages such as
#: data_format.md show fragments that name the reader's own files)
RUN_UNDER = ("getting_started.md", "tutorials/", "howto/")


def runnable_pages() -> list[Path]:
    return sorted(p for p in DOCS.rglob("*.md")
                  if p.relative_to(DOCS).as_posix().startswith(RUN_UNDER) and code_blocks(p))


#: a block that reads one of the real data sets (``../shared/data`` or
#: ``BONDGRAPH_DATA``) through one of these calls runs only where that data set
#: is present, as the data tests skip without it: call -> (data set, a file of it)
DATA_CALLS = {"camry_record(": ("camry", "61811011.csv")}


def _data_missing(text: str) -> bool:
    """Whether ``text`` reads a real data set (:data:`DATA_CALLS`) that is not here."""
    from bondgraph.data.datasets import find_local

    return any(call in text and find_local(ds, name) is None
               for call, (ds, name) in DATA_CALLS.items())


def _run(args, cwd, env, what):
    r = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True)
    assert r.returncode == 0, f"{what} failed ({r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"


def test_the_walkthrough_pages_are_run():
    """The tutorials the issue asks to run in CI have runnable blocks."""
    names = {p.relative_to(DOCS).as_posix() for p in runnable_pages()}
    assert {f"tutorials/{t}.md" for t in ("first_graph", "own_model", "estimation", "vehicle",
                                          "dask", "tracking", "discover")} <= names
    kinds = [k for k, _ in code_blocks(DOCS / "tutorials" / "own_model.md")]
    assert kinds[0] == "file:door.py" and "bash" in kinds
    assert kinds.index("file:my_effect.py") < len(kinds) - 1 and kinds[-1] == "python"


@pytest.mark.slow
@pytest.mark.parametrize("page", runnable_pages(), ids=lambda p: p.relative_to(DOCS).as_posix())
def test_page_code_runs(page, tmp_path):
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
               MPLBACKEND="Agg", PYTHONPATH=str(tmp_path))
    script: list[str] = []

    def flush():
        if script:
            (tmp_path / "_page.py").write_text("\n".join(script))
            _run([sys.executable, "_page.py"], tmp_path, env, f"{page.name}: python blocks")
            script.clear()

    for kind, text in code_blocks(page):
        if kind == "python":
            script.append(text)
            continue
        flush()
        if kind == "bash" and _data_missing(text):
            continue                    # the data set is absent: shown, not run here
        if kind == "bash":
            _run(["bash", "-euo", "pipefail", "-c", text], tmp_path, env, f"{page.name}: {text}")
        else:
            (tmp_path / kind.removeprefix("file:")).write_text(text)
    flush()


@pytest.mark.slow
def test_sphinx_build_without_warnings(tmp_path):
    """``sphinx-build -W``: a broken reference, a docstring numpydoc cannot
    parse, an option the command reference cannot render fail the test."""
    r = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html",
                        "-d", str(tmp_path / "doctrees"), str(DOCS), str(tmp_path / "html")],
                       cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-6000:]
    html = tmp_path / "html"
    effects = (html / "reference" / "generated" / "effects.html").read_text()
    assert "coulomb" in effects and "tanh" in effects         # equations derived at build time
    cli = (html / "reference" / "cli.html").read_text()
    assert "--max-steps" in cli and "example: bondgraph loop" in cli
    assert (html / "reference" / "generated" / "api" / "bondgraph.core.graph.BondGraph.html").exists()
    assert "effect_recovery.json" in (html / "background" / "generated" / "bench_tables.html").read_text()


def test_readme_is_short_and_says_what_ci_runs():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 150
    ci = (ROOT / ".ci" / "run").read_text()
    install = 'python3 -m venv .venv && . .venv/bin/activate && pip install -e ".[dev]"'
    assert install in ci and install in readme
    assert "pytest -q -n 2" in ci and re.search(r"^pytest -q -n 2\b", readme, re.M)
    assert re.search(r"^bondgraph loop\b", readme, re.M)
