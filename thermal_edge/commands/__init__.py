"""Sub-commands of ``thermal-edge``; each module has ``register(subparsers)``."""
from __future__ import annotations

from ..data import RunError
from ..lptn import ExprError, ModelError, NotPassive, UnstableDiscretisation
from ..sim.cycles import CycleError
from . import bench, calibrate, demo, discover, replay, simulate
from . import run, serve_demo, simulate_candump  # the edge service, its demo, candump output of simulate

COMMANDS = (simulate, replay, calibrate, bench, demo, run, serve_demo, simulate_candump, discover)

#: errors caused by the user's input: reported in one line, exit status 2
USER_ERRORS = (ModelError, RunError, CycleError, ExprError, UnstableDiscretisation, NotPassive, KeyError, FileNotFoundError)
