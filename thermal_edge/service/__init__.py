"""The CAN edge service: CAN frames in, 1 Hz LPTN tick with observer, online
adaptation and derating, limits out; metrics, persistence and systemd integration.

Modules, one job each:

- :mod:`.clock` -- wall clock (hardware) or frame-timestamp clock (replays, accelerated runs);
- :mod:`.inputs` -- per-tick input accumulation (mean i², mean speed, latest temperatures + age,
  stale and faulty inputs);
- :mod:`.lookahead` -- largest current that keeps every limit over a horizon, time to limit;
- :mod:`.derating` -- every derating rule: reaction-time current, approach, forced safe limit at the
  measured temperatures, slew, and the limit between ticks (bus silence, stalled ticks);
- :mod:`.adaptation` -- the online adapter in a worker, commands serialised; the parameters in use
  and when decisions are requested and applied;
- :mod:`.persistence` -- atomic state file, corrupt-file handling, cool-down over the downtime;
- :mod:`.estimate` -- the observer's estimate and the open-loop prediction (start, restore, restart);
- :mod:`.health` -- the reasons that force the safe limit (stale or faulty inputs, model faults);
- :mod:`.outputs` -- what a tick produced and the contents of the frames sent from it;
- :mod:`.events` -- safety events in the log, once each, with their journald priority;
- :mod:`.engine` -- the tick pipeline without I/O, wiring the parts above (shared by the live
  service and replays);
- :mod:`.metrics` -- Prometheus metrics;
- :mod:`.systemd` -- ``sd_notify`` readiness, status and watchdog;
- :mod:`.service` -- the asyncio service;
- :mod:`.replay` -- a candump log through the pipeline;
- :mod:`.logruns` -- a CAN log as runs: the inputs and readings per tick, as the service saw them.
"""
from .engine import ThermalEngine, load_service_model
from .outputs import TickOutput
from .replay import ReplayResult, replay_candump
from .service import EdgeService, adapt_phrase, status_line

__all__ = ["EdgeService", "ReplayResult", "ThermalEngine", "TickOutput", "load_service_model", "replay_candump",
           "adapt_phrase", "status_line"]
