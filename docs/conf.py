"""Sphinx configuration of the bondgraph documentation.

Build: ``sphinx-build -W --keep-going -b html docs docs/_build/html`` (the
test ``tests/test_docs.py`` runs exactly this in CI, and runs the tutorials'
code). Pages are MyST Markdown (the existing ``docs/*.md`` included) and
reST; the API, command, effect and benchmark references are generated at
every build (``_ext/bondgraph_docs.py``, sphinx-argparse, autosummary).

Intersphinx is off unless ``BONDGRAPH_DOCS_INTERSPHINX=1``: it downloads the
inventories of numpy, scipy, ... at every build, and a build without network
would then fail under ``-W`` (an unreachable inventory is a warning). The
links it adds are a convenience; the build that CI must pass is offline.
"""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path

DOCS = Path(__file__).resolve().parent
sys.path.insert(0, str(DOCS / "_ext"))

import bondgraph  # noqa: E402
import bondgraph_docs  # noqa: E402

bondgraph_docs.generate(DOCS)

project = "bondgraph"
author = "the bondgraph developers"
copyright = "the bondgraph developers, MIT licence"
release = bondgraph.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.intersphinx",
    "sphinx.ext.mathjax",
    "numpydoc",
    "myst_parser",
    "sphinxarg.ext",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "_ext", "**/.ipynb_checkpoints"]

# --- API pages from the docstrings
autosummary_generate = True
autosummary_imported_members = False
autodoc_default_options = {"members": True, "member-order": "bysource"}
autodoc_typehints = "none"           # numpydoc sections carry the types
numpydoc_show_class_members = False  # autodoc lists the members once
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

# numpydoc parses the docstrings of sympy's methods that our Symbol
# subclasses inherit; sections sympy names its own way are sympy's business
warnings.filterwarnings("ignore", message=r"Unknown section .* in .*site-packages",
                        category=UserWarning)

# --- Markdown
myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3

# --- links to the libraries' docs (network: opt in, see the module docstring)
if os.environ.get("BONDGRAPH_DOCS_INTERSPHINX") == "1":
    intersphinx_mapping = {
        "python": ("https://docs.python.org/3", None),
        "numpy": ("https://numpy.org/doc/stable", None),
        "scipy": ("https://docs.scipy.org/doc/scipy", None),
        "sympy": ("https://docs.sympy.org/latest", None),
        "filterpy": ("https://filterpy.readthedocs.io/en/latest", None),
        "dask": ("https://docs.dask.org/en/stable", None),
    }
else:
    intersphinx_mapping = {}

html_theme = "alabaster"
html_title = f"bondgraph {release}"
html_static_path: list[str] = []
templates_path = ["_templates"]
