"""The fleet: calibrate, evaluate and screen many machines' recorded runs on Dask.

One machine's runs are one Dask task (:mod:`.calibrate`, :mod:`.evaluate`) on an embedded
``LocalCluster`` or a running scheduler (:mod:`.cluster`); the machines are found from paths and
globs (:mod:`.runs`); the fleet's parameter distribution and its outliers come from
:mod:`.screen`; the results are one Parquet table (:mod:`.results`) and a Markdown report with
plots (:mod:`.report`). Dask and pyarrow are the optional extra ``thermal-edge[fleet]``: this
package imports them only where it uses them, so that the edge service never needs them.
"""
from __future__ import annotations

from ..errors import ThermalEdgeError

#: what to tell the user when the extra is missing
INSTALL_HINT = "pip install thermal-edge[fleet]"


class MissingExtra(ThermalEdgeError, RuntimeError):
    """Dask or pyarrow is not installed; the message says how to install the extra."""


def require_fleet_extra() -> None:
    """Raise :class:`MissingExtra` unless ``distributed`` and ``pyarrow`` can be imported (tqdm is a core dependency)."""
    missing = []
    for mod in ("distributed", "pyarrow"):
        try:
            __import__(mod)
        except ImportError:
            missing.append(mod)
    if missing:
        raise MissingExtra(f"{' and '.join(missing)} not installed: {INSTALL_HINT}")
