"""The CAN edge service (``DESIGN.md`` §3): CAN frames in, 1 Hz LPTN tick with observer, online
adaptation and derating, limits out; metrics, persistence and systemd integration.

Modules, one job each:

- :mod:`.clock` -- wall clock (hardware) or frame-timestamp clock (replays, accelerated runs);
- :mod:`.inputs` -- per-tick input accumulation (mean i², mean speed, latest temperatures + age,
  stale and faulty inputs);
- :mod:`.lookahead` -- largest current that keeps every limit over a horizon, time to limit;
- :mod:`.derating` -- band derate, look-ahead, forced safe limit, slew (fall at once, rise slowly);
- :mod:`.adaptation` -- the online adapter in a worker, commands serialised;
- :mod:`.persistence` -- atomic state file, corrupt-file handling, cool-down over the downtime;
- :mod:`.engine` -- the tick pipeline without I/O (shared by the live service and replays);
- :mod:`.metrics` -- Prometheus metrics;
- :mod:`.systemd` -- ``sd_notify`` readiness, status and watchdog;
- :mod:`.service` -- the asyncio service;
- :mod:`.replay` -- a candump log through the pipeline.
"""
from .engine import ThermalEngine, TickOutput, load_service_model
from .replay import ReplayResult, replay_candump
from .service import EdgeService, status_line

__all__ = ["EdgeService", "ReplayResult", "ThermalEngine", "TickOutput", "load_service_model", "replay_candump",
           "status_line"]
