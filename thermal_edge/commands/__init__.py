"""Sub-commands of ``thermal-edge``; each module has ``register(subparsers)``."""
from __future__ import annotations

from ..data import RunError
from ..lptn import ExprError, ModelError, NotPassive, UnstableDiscretisation
from ..sim.cycles import CycleError
from . import bench, calibrate, demo, discover, replay, simulate

COMMANDS = (simulate, replay, calibrate, discover, bench, demo)

#: errors caused by the user's input: reported in one line, exit status 2
USER_ERRORS = (ModelError, RunError, CycleError, ExprError, UnstableDiscretisation, NotPassive, KeyError, FileNotFoundError)
