#!/usr/bin/env python3
"""Render the generated reference tables of README.md ("Deployment and operation").

Four tables, each between ``<!-- BEGIN GENERATED name -->`` and ``<!-- END GENERATED name -->``,
each rendered by its own module of ``deploy/docs`` (see there for the sources):
``can`` (the DBC), ``config`` (``config/edge.yaml`` and the defaults declared in
``thermal_edge.config``), ``metrics`` (the running service's ``/metrics``), ``alerts`` (the
Prometheus alert rules). ``--update`` also rewrites ``deploy/compose/edge-sim.yaml``.

Usage (from the repository root, with the package installed, e.g. ``.venv/bin/python``)::

    python deploy/gen_docs.py can|config|metrics|alerts   # print one table
    python deploy/gen_docs.py --update README.md       # rewrite all of them in place
    python deploy/gen_docs.py --check README.md        # exit 1 if any table is stale

``metrics`` starts ``thermal-edge demo`` (the service against the simulated machine) on a free
port and scrapes it; ``--metrics-from FILE`` renders a saved scrape instead.
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path
from typing import Callable


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
from thermal_edge_deploy_docs.config import render_config  # noqa: E402
from thermal_edge_deploy_docs.markdown import extract_block, replace_block  # noqa: E402
from thermal_edge_deploy_docs.metrics import render_metrics, scrape_demo  # noqa: E402
from thermal_edge_deploy_docs.paths import REPO, SIM_CONFIG  # noqa: E402
from thermal_edge_deploy_docs.sim_config import render_sim_config  # noqa: E402

__all__ = ["SIM_CONFIG", "extract_block", "render_alerts", "render_can", "render_config", "render_metrics",
           "render_sim_config"]

#: table name -> how it is rendered (the metrics table from a scrape)
TABLES: dict[str, Callable[[Callable[[], str]], str]] = {
    "can": lambda scrape: render_can(),
    "config": lambda scrape: render_config(),
    "metrics": lambda scrape: render_metrics(scrape()),
    "alerts": lambda scrape: render_alerts(),
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("table", nargs="?", choices=tuple(TABLES), help="print one table")
    p.add_argument("--update", metavar="README", help="rewrite the generated blocks of this file")
    p.add_argument("--check", metavar="README", help="exit 1 if a generated block differs")
    p.add_argument("--metrics-from", metavar="FILE", help="a saved /metrics scrape (default: run thermal-edge demo)")
    p.add_argument("--only", choices=tuple(TABLES), action="append", help="with --update/--check: only these tables")
    args = p.parse_args(argv)
    cache: dict[str, str] = {}

    def scrape() -> str:
        if "m" not in cache:
            cache["m"] = Path(args.metrics_from).read_text() if args.metrics_from else scrape_demo()
        return cache["m"]

    if args.table and not (args.update or args.check):
        print(TABLES[args.table](scrape))
        return 0
    target = args.update or args.check
    if not target:
        p.error("give a table to print, or --update/--check README.md")
    readme = Path(target).read_text(encoding="utf-8")
    names = args.only or ([args.table] if args.table else list(TABLES))
    stale = []
    new = readme
    for name in names:
        body = TABLES[name](scrape)
        if extract_block(readme, name) != body.strip("\n"):
            stale.append(name)
        new = replace_block(new, name, body)
    sim = render_sim_config() if not args.only or "config" in args.only else None
    sim_stale = sim is not None and (not SIM_CONFIG.exists() or SIM_CONFIG.read_text(encoding="utf-8") != sim)
    what = stale + ([str(SIM_CONFIG.relative_to(REPO))] if sim_stale else [])
    if args.update:
        if new != readme:
            Path(target).write_text(new, encoding="utf-8")
        if sim_stale:
            SIM_CONFIG.parent.mkdir(parents=True, exist_ok=True)
            SIM_CONFIG.write_text(sim, encoding="utf-8")  # type: ignore[arg-type]
        print(f"{target}: {'updated ' + ', '.join(what) if what else 'up to date'}")
        return 0
    if what:
        print(f"{target}: stale generated content: {', '.join(what)} (python deploy/gen_docs.py --update {target})")
        return 1
    print(f"{target}: generated tables up to date")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except Exception as exc:  # one line, not a traceback: e.g. config/edge.yaml does not load
        print(f"gen_docs: error: {type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc).strip() else ''}",
              file=sys.stderr)
        sys.exit(2)
