#!/usr/bin/env python3
"""Render the manual's generated reference pages from their one home each.

Five tables, each rendered by its own module of ``deploy/docs`` (see there for the sources):
``can`` (the DBC), ``config`` (``config/edge.yaml`` and the defaults declared in
``thermal_edge.config``), ``metrics`` (the running service's ``/metrics``), ``alerts`` (the
Prometheus alert rules), ``cli`` (the command-line parser). The Sphinx build (``make docs``,
``docs/conf.py``) calls :func:`write_tables`; the pages under ``docs/reference/`` include them.

Usage (from the repository root, with the package installed, e.g. ``.venv/bin/python``)::

    python deploy/gen_docs.py can|config|metrics|alerts|cli   # print one table
    python deploy/gen_docs.py --out docs/_generated           # write all of them (as the docs build does)
    python deploy/gen_docs.py --compose                       # rewrite deploy/compose/edge-sim.yaml
    python deploy/gen_docs.py --check-compose                 # exit 1 if it is stale

``metrics`` starts ``thermal-edge demo`` (the service against the simulated machine) on a free
port and scrapes it; ``--metrics-from FILE`` renders a saved scrape instead.
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
from collections.abc import Callable
from pathlib import Path


def _docs_package() -> object:
    """``deploy/docs`` as a package of its own name (this script runs as a file, not a module)."""
    name = "thermal_edge_deploy_docs"
    if name not in sys.modules:
        here = Path(__file__).resolve().parent / "docs"
        spec = importlib.util.spec_from_file_location(name, here / "__init__.py", submodule_search_locations=[str(here)])
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


_docs_package()
from thermal_edge_deploy_docs.alerts import render_alerts  # noqa: E402
from thermal_edge_deploy_docs.can import render_can  # noqa: E402
from thermal_edge_deploy_docs.cli import render_cli  # noqa: E402
from thermal_edge_deploy_docs.config import render_config  # noqa: E402
from thermal_edge_deploy_docs.metrics import render_metrics, scrape_demo  # noqa: E402
from thermal_edge_deploy_docs.paths import REPO, SIM_CONFIG  # noqa: E402
from thermal_edge_deploy_docs.sim_config import render_sim_config  # noqa: E402

__all__ = ["SIM_CONFIG", "TABLES", "render_alerts", "render_can", "render_cli", "render_config", "render_metrics",
           "render_sim_config", "write_tables"]

#: table name -> how it is rendered (the metrics table from a scrape)
TABLES: dict[str, Callable[[Callable[[], str]], str]] = {
    "can": lambda scrape: render_can(),
    "config": lambda scrape: render_config(),
    "metrics": lambda scrape: render_metrics(scrape()),
    "alerts": lambda scrape: render_alerts(),
    "cli": lambda scrape: render_cli(),
}


def write_tables(out: Path, metrics_from: str | None = None) -> list[Path]:
    """Write every table to ``out/<name>.md`` (a file whose text is unchanged is not touched, so
    Sphinx rebuilds only what changed); the files written."""
    out.mkdir(parents=True, exist_ok=True)
    cache: dict[str, str] = {}

    def scrape() -> str:
        if "m" not in cache:
            cache["m"] = Path(metrics_from).read_text(encoding="utf-8") if metrics_from else scrape_demo()
        return cache["m"]

    paths = []
    for name, render in TABLES.items():
        path = out / f"{name}.md"
        text = render(scrape).strip("\n") + "\n"
        if not path.exists() or path.read_text(encoding="utf-8") != text:
            path.write_text(text, encoding="utf-8")
        paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("table", nargs="?", choices=tuple(TABLES), help="print one table")
    p.add_argument("--out", metavar="DIR", help="write every table to DIR/<table>.md")
    p.add_argument("--compose", action="store_true", help="rewrite deploy/compose/edge-sim.yaml")
    p.add_argument("--check-compose", action="store_true", help="exit 1 if deploy/compose/edge-sim.yaml is stale")
    p.add_argument("--metrics-from", metavar="FILE", help="a saved /metrics scrape (default: run thermal-edge demo)")
    args = p.parse_args(argv)
    if args.table:
        scrape = (lambda: Path(args.metrics_from).read_text(encoding="utf-8")) if args.metrics_from else scrape_demo
        print(TABLES[args.table](scrape))
        return 0
    if args.out:
        for path in write_tables(Path(args.out), args.metrics_from):
            print(path)
        return 0
    if args.compose or args.check_compose:
        sim = render_sim_config()
        stale = not SIM_CONFIG.exists() or SIM_CONFIG.read_text(encoding="utf-8") != sim
        shown = SIM_CONFIG.relative_to(REPO)
        if args.check_compose:
            print(f"{shown}: {'stale (python deploy/gen_docs.py --compose)' if stale else 'up to date'}")
            return 1 if stale else 0
        if stale:
            SIM_CONFIG.parent.mkdir(parents=True, exist_ok=True)
            SIM_CONFIG.write_text(sim, encoding="utf-8")
        print(f"{shown}: {'updated' if stale else 'up to date'}")
        return 0
    p.error("give a table to print, --out DIR, --compose or --check-compose")
    return 2


if __name__ == "__main__":
    try:
        sys.exit(main())
    except Exception as exc:  # one line, not a traceback: e.g. config/edge.yaml does not load
        print(f"gen_docs: error: {type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc).strip() else ''}",
              file=sys.stderr)
        sys.exit(2)
