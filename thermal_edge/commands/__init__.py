"""Sub-commands of ``thermal-edge``; each module has ``register(subparsers)``."""
from __future__ import annotations

from ..bus import LogFormatError
from ..config import ConfigError
from ..data import RunError
from ..lptn import ExprError, ModelError, NotPassive, UnstableDiscretisation
from ..sim.cycles import CycleError
from . import bench, calibrate, demo, discover, monitor, replay, run, simulate
from . import fleet

COMMANDS = (run, demo, monitor, simulate, replay, calibrate, discover, bench)
COMMANDS += (fleet,)

#: errors caused by the user's input: reported in one line, exit status 2
USER_ERRORS = (ModelError, RunError, CycleError, ExprError, UnstableDiscretisation, NotPassive, ConfigError,
               LogFormatError, KeyError, FileNotFoundError)
