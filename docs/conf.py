"""Sphinx configuration of the thermal_edge manual (``make docs``).

The reference pages of configuration, metrics, CAN frames, alerts and the command line are
generated at build time from their one home (``deploy/gen_docs.py``: the shipped ``edge.yaml`` and
the configuration's declarations, a scrape of the running service's ``/metrics``, the DBC, the
Prometheus rules, the command-line parser) into ``docs/_generated/``, which the pages include.
"""
from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
REPO = DOCS.parent


def _generate() -> None:
    spec = importlib.util.spec_from_file_location("thermal_edge_gen_docs", REPO / "deploy" / "gen_docs.py")
    assert spec is not None and spec.loader is not None
    gen_docs = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = gen_docs
    spec.loader.exec_module(gen_docs)
    # THERMAL_EDGE_DOCS_METRICS_FROM: a saved /metrics scrape instead of running the demo
    gen_docs.write_tables(DOCS / "_generated", metrics_from=os.environ.get("THERMAL_EDGE_DOCS_METRICS_FROM"))


_generate()

project = "thermal_edge"
author = "the thermal_edge authors"
copyright = "the thermal_edge authors, Apache-2.0"
try:
    from thermal_edge import __version__ as release
except ImportError:  # the package is not installed: the manual builds without its version
    release = ""
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "numpydoc",
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_generated", "_build", "discovery-example/ambiguous/report.md"]

myst_enable_extensions = ["colon_fence", "dollarmath"]
myst_heading_anchors = 4

# numpydoc: the docstrings are numpy style; no autosummary tables of every member
numpydoc_show_class_members = False
numpydoc_xref_param_type = False
autodoc_typehints = "none"
autodoc_member_order = "bysource"

# -n: every reference must resolve, except to the standard library and third-party classes (no
# intersphinx: the build needs no network beyond the package index)
nitpicky = True
nitpick_ignore_regex = [
    (r"py:.*", r"(numpy|np|scipy|pathlib|collections|typing|datetime|enum|argparse|can|cantools|yaml)(\..*)?"),
    (r"py:.*", r"(.*\.)?_[a-z]\w*"),  # a docstring may name a private helper; it has no page
]

html_theme = "furo"
html_title = f"thermal_edge {release}".strip()
html_static_path: list[str] = []
