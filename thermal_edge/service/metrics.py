"""Prometheus metrics of the service (prefix ``thermal_edge_``, base units).

Values that change every tick or every frame (node temperatures, limits, frame counters) are read
by a custom collector at scrape time from the engine's last tick and the CAN layer's counters, so
the hot paths do no metric work. Histograms (tick duration and lateness, adaptation duration) and
a few counters are updated as events happen.

Every labelled counter and flag an operator alerts on exists from the first scrape, 0 for each of
its known label values (frames, sensors and fault kinds, drop reasons; the derate reason and the
state say ``starting`` before the first tick), so that ``increase()`` and the alert rules see the
first event. Gauges of measured values (temperatures, errors) appear with their first value.

The endpoint is read only (``/metrics``); it binds 127.0.0.1:9108 unless configured otherwise.
"""
from __future__ import annotations

import logging
import math
import platform
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, Info
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, StateSetMetricFamily
from prometheus_client.registry import Collector

from .. import __version__
from ..bus.frames import TE_ESTIMATES, TE_FORECAST, TE_LIMITS, TE_STATUS, DerateReason, TeState
from ..bus.stats import DROP_REASONS
from .adaptation import ADAPT_STATUSES
from .flux_input import REFUSALS
from .inputs import FAULT_KINDS
from .metrics_server import MetricsServer

if TYPE_CHECKING:  # pragma: no cover
    from .derating import Limits
    from .engine import ThermalEngine, TickOutput

__all__ = ["ServiceMetrics"]

log = logging.getLogger(__name__)

P = "thermal_edge_"
#: label names of the labelled families built at scrape time, by name without the prefix (one
#: place for them: deploy/docs reads it for the families that have no sample yet)
LABELS: dict[str, tuple[str, ...]] = {
    "node_estimate_celsius": ("node",),
    "node_estimate_stddev_celsius": ("node",),
    "node_prediction_celsius": ("node",),
    "sensor_measurement_celsius": ("sensor", "node"),
    "prediction_error_celsius": ("sensor", "node"),
    "commissioned_gap_celsius": ("sensor",),
    "input_value": ("input",),
    "limited_node_celsius": ("limit", "node", "band"),
    "sensor_age_seconds": ("sensor",),
    "input_stale": ("frame",),
    "sensor_fault": ("sensor", "kind"),
    "parameter_value": ("parameter", "unit"),
    "parameter_band": ("parameter", "bound"),
    "parameter_identifiable": ("parameter",),
    "bad_readings": ("kind",),
    "frames_received": ("frame",),
    "frames_sent": ("frame",),
    "frames_dropped": ("reason",),
    "frames_dropped_by_frame": ("frame",),
    "frames_lost": ("frame",),
    "frame_clock_jumps": ("outcome",),
    "adaptation_last_refusal_timestamp_seconds": ("reason",),
    "flux_refused": ("reason",),
}

#: the frames the service sends (frames_sent has a series for each from the start)
SENT_FRAMES = (TE_LIMITS, TE_ESTIMATES, TE_FORECAST, TE_STATUS)


def _with_known(counts: dict[str, int], known: Iterable[str]) -> list[tuple[str, int]]:
    """Counts per label value, every known value present (0 if not counted yet), known ones first."""
    out = {k: 0 for k in known}
    out.update(counts)
    return list(out.items())


class _LiveCollector(Collector):
    """Reads the latest tick and the frame counters at scrape time."""

    def __init__(self, metrics: ServiceMetrics) -> None:
        self.m = metrics

    def collect(self) -> Iterable[Any]:
        m = self.m
        eng = m.engine
        out: TickOutput | None = eng.last if eng is not None else None
        model = eng.model if eng is not None else None
        # what TE_Limits carries now: the last tick's limits, or the policy's between ticks (a silent
        # bus, a stalled tick); None before the first tick
        sent = m.limits_now() if m.limits_now is not None else (out.limits if out is not None else None)
        if eng is not None and out is not None and model is not None:
            est = GaugeMetricFamily(P + "node_estimate_celsius", "Best estimate (observer) of each node's temperature",
                                    labels=LABELS["node_estimate_celsius"])
            sig = GaugeMetricFamily(P + "node_estimate_stddev_celsius", "Standard deviation of each node's estimate",
                                    labels=LABELS["node_estimate_stddev_celsius"])
            pre = GaugeMetricFamily(P + "node_prediction_celsius", "Open-loop model prediction of each node's temperature",
                                    labels=LABELS["node_prediction_celsius"])
            for i, node in enumerate(model.nodes):
                if math.isfinite(out.estimate[i]):
                    est.add_metric([node], float(out.estimate[i]))
                    sig.add_metric([node], float(out.sigma[i]))
                if math.isfinite(out.prediction[i]):
                    pre.add_metric([node], float(out.prediction[i]))
            yield est
            yield sig
            yield pre
            meas = GaugeMetricFamily(P + "sensor_measurement_celsius", "Latest usable reading of each sensor",
                                     labels=LABELS["sensor_measurement_celsius"])
            err = GaugeMetricFamily(P + "prediction_error_celsius",
                                    "Open-loop prediction minus reading, per sensor (last tick)",
                                    labels=LABELS["prediction_error_celsius"])
            for s, v in out.measured.items():
                node = model.sensors.get(s, "")
                if math.isfinite(v):
                    meas.add_metric([s, node], v)
                if s in out.pred_error:
                    err.add_metric([s, node], out.pred_error[s])
            yield meas
            yield err
            below = GaugeMetricFamily(P + "commissioned_gap_celsius", "How far the reading furthest below the "
                                      "commissioned model's open-loop prediction lies below it (negative: every reading "
                                      "above it); beyond derating.faults.commissioned_gap_k the readings are not believed",
                                      labels=LABELS["commissioned_gap_celsius"])
            gap = eng.commissioned.gap
            if gap is not None:
                below.add_metric([gap[0]], gap[1])
            yield below
            if math.isfinite(out.pred_err_rms):
                yield GaugeMetricFamily(P + "prediction_error_rms_celsius",
                                        "RMS open-loop prediction error over the last adaptation period",
                                        value=out.pred_err_rms)
            inp = GaugeMetricFamily(P + "input_value", "Model inputs of the last tick (units as the model names them)",
                                    labels=LABELS["input_value"])
            for k, v in out.inputs.items():
                if math.isfinite(v):
                    inp.add_metric([k], v)
            yield inp
            lim = GaugeMetricFamily(P + "limited_node_celsius", "Limited nodes: estimate, upper band derated on and sent "
                                    "(TE_Estimates), warn and max",
                                    labels=LABELS["limited_node_celsius"])
            for b, ln in zip(out.bands, eng.limited_nodes):
                node = model.nodes[ln.row]
                lim.add_metric([ln.name, node, "estimate"], b.estimate_c)
                lim.add_metric([ln.name, node, "upper"], b.upper_c)
                lim.add_metric([ln.name, node, "warn"], ln.warn_c)
                lim.add_metric([ln.name, node, "max"], ln.max_c)
            yield lim
            assert sent is not None
            yield GaugeMetricFamily(P + "current_limit_amperes", "Current limit sent in TE_Limits (A rms)",
                                    value=sent.current_a)
            yield GaugeMetricFamily(P + "torque_limit_newton_meters", "Torque limit sent in TE_Limits",
                                    value=sent.torque_nm)
            yield GaugeMetricFamily(P + "derate_active", "1 while the limits are reduced", value=float(sent.active))
            yield GaugeMetricFamily(P + "derate_reason_code", "TE_DerateReason sent in TE_Limits (enumeration value)",
                                    value=float(int(sent.reason)))
            if math.isfinite(out.lookahead_a):
                yield GaugeMetricFamily(P + "lookahead_current_amperes",
                                        "Largest RMS current that keeps every limit over the horizon",
                                        value=out.lookahead_a)
            yield GaugeMetricFamily(P + "time_to_limit_seconds",
                                    "Time to the first limit at the present load (+Inf: not within the horizon)",
                                    value=out.time_to_limit_s)
            yield GaugeMetricFamily(P + "lookahead_horizon_seconds", "Look-ahead horizon", value=out.horizon_s)
            yield GaugeMetricFamily(P + "state_code", "TE_State of the last tick (enumeration value)",
                                    value=float(int(out.state)))
            yield GaugeMetricFamily(P + "last_tick_timestamp_seconds", "Clock time of the last tick", value=out.t)
            age = GaugeMetricFamily(P + "sensor_age_seconds", "Seconds since each sensor's last valid reading",
                                    labels=LABELS["sensor_age_seconds"])
            for s in eng.config.sensors:
                # the tick's own ages: the accumulator's latest reading may have come after the tick
                a = out.ages.get(s, math.inf)
                if math.isfinite(a):
                    age.add_metric([s], a)
            yield age
        if eng is not None and model is not None:
            # what TE_Limits says now: before the first tick starting, nothing stale, no fault; on a
            # silent bus stale input, every frame missing
            reason = sent.reason if sent is not None else DerateReason.STARTING
            silent = m.silent_s() if m.silent_s is not None else None
            yield GaugeMetricFamily(P + "bus_silent_seconds", "Seconds since the last accepted frame once that exceeds "
                                    "transmit.bus_silence_s (TE_Limits then carries the safe limit); 0 otherwise",
                                    value=silent if silent is not None else 0.0)
            state = out.state if out is not None else TeState.STARTING
            yield StateSetMetricFamily(P + "derate_reason", "Why the limits are reduced",
                                       value={r.name.lower(): r == reason for r in DerateReason})
            yield StateSetMetricFamily(P + "state", "Service state", value={s.name.lower(): s == state for s in TeState})
            stale = GaugeMetricFamily(P + "input_stale", "1 for each frame missing longer than its timeout",
                                      labels=LABELS["input_stale"])
            for f in eng.config.timeouts:
                stale.add_metric([f], float(silent is not None or (out is not None and f in out.stale)))
            yield stale
            fault = GaugeMetricFamily(P + "sensor_fault", "1 for each required sensor/input reporting a fault",
                                      labels=LABELS["sensor_fault"])
            faults = out.faults if out is not None else {}
            for s in eng.accumulator.fault_sources:
                for kind in FAULT_KINDS:
                    fault.add_metric([s, kind], float(faults.get(s) == kind))
            yield fault
            val = GaugeMetricFamily(P + "parameter_value", "Adaptable parameter value (unit in the label)",
                                    labels=LABELS["parameter_value"])
            band = GaugeMetricFamily(P + "parameter_band",
                                     "95 % band of an adaptable parameter "
                                     "(Fisher information, the residuals' correlation in time counted)",
                                     labels=LABELS["parameter_band"])
            ident = GaugeMetricFamily(P + "parameter_identifiable",
                                      "1 if the sensors at hand pin the parameter down "
                                      "(relative sd as if the residuals were independent "
                                      "below adaptation.max_rel_std: the adapter's own gate)",
                                      labels=LABELS["parameter_identifiable"])
            units = {p.name: p.unit for p in model.parameters}
            param_bands, identifiable = eng.adaptation.parameter_bands()
            for name, v in eng.adaptation.values().items():
                val.add_metric([name, units.get(name, "")], v)
                if name in param_bands:
                    lo, hi = param_bands[name]
                    band.add_metric([name, "lower"], lo)
                    band.add_metric([name, "upper"], hi)
                if name in identifiable:
                    ident.add_metric([name], float(identifiable[name]))
            yield val
            yield band
            yield ident
            ad = eng.adaptation.counts
            yield GaugeMetricFamily(P + "parameter_version", "Accepted parameter sets so far", value=ad.version)
            status = eng.adaptation.status
            yield StateSetMetricFamily(P + "adaptation_status", "What the adaptation is doing after its last decision: "
                                       "fits (error below the threshold), waiting for data or for evidence on a challenger, "
                                       "learning (a challenger just promoted), refusing (the last challenger dropped)",
                                       value={st: st == status for st in ADAPT_STATUSES})
            refusal = eng.adaptation.last_refusal
            last = GaugeMetricFamily(P + "adaptation_last_refusal_timestamp_seconds", "Time of the last challenger "
                                     "dropped, labelled with why (not better, predicts SENSOR worse)",
                                     labels=LABELS["adaptation_last_refusal_timestamp_seconds"])
            if refusal is not None:
                last.add_metric([refusal[1]], refusal[0])
            yield last
            for name, value, doc in (
                ("adaptation_runs", ad.runs, "Adaptations run (prediction error above the threshold)"),
                ("adaptation_accepted", ad.accepted, "Adaptations accepted"),
                ("adaptation_rejected", ad.rejected, "Adaptations rolled back"),
                ("adaptation_failures", ad.failures, "Adaptations that failed with an error"),
                ("adaptation_skipped", ad.skipped, "Decisions above the threshold that could not optimise yet"),
                ("model_faults", eng.model_faults, "Times the model was found diverged (safe limit forced)"),
                ("readings_doubted", eng.commissioned.count, "Times the readings fell more than "
                 "derating.faults.commissioned_gap_k below the commissioned model's prediction (not believed, not "
                 "learnt from; safe limit until within half of it)"),
                ("ticks", eng.ticks, "Ticks run"),
                ("frame_gaps", eng.gaps, "Gaps in the frame clock bridged by cooling the state"),
            ):
                yield CounterMetricFamily(P + name, doc, value=value)
            fc = eng.frame_clock
            if fc is not None:  # timestamps out of order (only the frame clock reads them)
                yield CounterMetricFamily(P + "frame_clock_behind", "Frames stamped earlier than the frame clock (time "
                                          "going backwards; their data is used)", value=fc.behind)
                yield GaugeMetricFamily(P + "frame_clock_behind_max_seconds", "Largest step back of a frame's timestamp "
                                        "behind the frame clock", value=fc.behind_max_s)
                jumps = CounterMetricFamily(P + "frame_clock_jumps", "Timestamp jumps (a tick or more back, more than "
                                            "clock.max_catchup_s ahead), by what the frames after them said: joined (back, "
                                            "a new segment ticked on without a gap), ahead (a gap), ignored (a corrupt stamp)",
                                            labels=LABELS["frame_clock_jumps"])
                for outcome in ("joined", "ahead", "ignored"):
                    jumps.add_metric([outcome], getattr(fc, outcome))
                yield jumps
            fx = eng.flux
            if fx is not None:  # the optional voltage input (flux:), every refusal reason from the start
                refused = CounterMetricFamily(P + "flux_refused", "Flux-linkage estimates of the magnet refused, by reason: "
                                              "disagreement (beyond both 95 % bands), stale (no voltage frame), old (voltage "
                                              "frames far behind the frame clock), implausible (a voltage that implies a "
                                              "magnet outside the valid range)",
                                              labels=LABELS["flux_refused"])
                for r in REFUSALS:
                    refused.add_metric([r], fx.counts.get(r, 0))
                yield refused
                yield CounterMetricFamily(P + "flux_used", "Flux-linkage estimates of the magnet fused into the observer",
                                          value=fx.counts.get("used", 0))
                flux_last = fx.last_used
                if flux_last is not None and math.isfinite(flux_last.estimate_c):
                    yield GaugeMetricFamily(P + "flux_magnet_celsius", "Magnet temperature from the inverter's voltages "
                                            "(the last estimate fused into the observer)", value=flux_last.estimate_c)
                    if math.isfinite(flux_last.sigma_k):
                        yield GaugeMetricFamily(P + "flux_magnet_stddev_celsius", "Standard deviation of that estimate",
                                                value=flux_last.sigma_k)
                mg = out.magnet if out is not None else None
                if mg is not None and math.isfinite(mg.observer_upper_c - mg.estimate_c):
                    yield GaugeMetricFamily(P + "magnet_band_celsius", "Width of the observer's band of the magnet "
                                            "above its estimate (band_z sigma): what the voltages narrow; the upper "
                                            "band sent is limited_node_celsius band=upper, at least the recent "
                                            "readings of a sensor that bounds the magnet from below",
                                            value=mg.observer_upper_c - mg.estimate_c)
            acc = eng.accumulator
            bad = CounterMetricFamily(P + "bad_readings", "Sensor readings rejected, by kind", labels=LABELS["bad_readings"])
            for kind in FAULT_KINDS:
                bad.add_metric([kind], acc.bad_readings.get(kind, 0))
            yield bad
            yield CounterMetricFamily(P + "malformed_frames", "Accepted frames whose signals could not be used",
                                      value=acc.malformed)
        # frames (codec) and transport
        codec = m.codec
        if codec is not None:
            st = codec.stats
            received = eng.config.timeouts if eng is not None else ()  # the inverter's frames the service needs
            rx = CounterMetricFamily(P + "frames_received", "Frames accepted (counter and CRC good)",
                                     labels=LABELS["frames_received"])
            for k, v in _with_known(st.received, received):
                rx.add_metric([k], v)
            yield rx
            tx = CounterMetricFamily(P + "frames_sent", "Frames encoded for sending", labels=LABELS["frames_sent"])
            for k, v in _with_known(st.sent, SENT_FRAMES):
                tx.add_metric([k], v)
            yield tx
            dr = CounterMetricFamily(P + "frames_dropped", "Received frames dropped, by reason", labels=LABELS["frames_dropped"])
            for r in DROP_REASONS:
                dr.add_metric([r], getattr(st, r))
            yield dr
            # the same drops by the frame they were of (a known identifier's; e.g. a bad CRC on the voltage frame)
            flux_frame = (eng.config.flux.frame,) if eng is not None and eng.flux is not None else ()
            dbf = CounterMetricFamily(P + "frames_dropped_by_frame", "Received frames of a known identifier dropped "
                                      "(any reason), by frame", labels=LABELS["frames_dropped_by_frame"])
            for k, v in _with_known(st.dropped_by_frame, (*received, *flux_frame)):
                dbf.add_metric([k], v)
            yield dbf
            lost = CounterMetricFamily(P + "frames_lost", "Frames missing according to the alive counter",
                                       labels=LABELS["frames_lost"])
            for k, v in _with_known(st.lost_by_frame, received):
                lost.add_metric([k], v)
            yield lost
            yield CounterMetricFamily(P + "frames_lost_all", "Frames missing according to the alive counter (all frames)",
                                      value=st.lost)
            yield CounterMetricFamily(P + "frames_resynced", "Frames whose counter was not judged after a long gap",
                                      value=st.counter_resync)
            yield CounterMetricFamily(P + "frames_clamped", "Signal values saturated to the DBC range when sending",
                                      value=st.clamped)
        tr = m.transport_stats
        if tr is not None:
            for k, v in tr.as_dict().items():
                yield CounterMetricFamily(P + "transport_" + k, f"CAN transport: {k.replace('_', ' ')}", value=v)
        store = m.store
        if store is not None:
            yield CounterMetricFamily(P + "state_load_errors", "State files that could not be used at start",
                                      value=store.load_errors)
            yield CounterMetricFamily(P + "state_params_dropped", "Learned parameters dropped at start: the model has "
                                      "no parameter of that name, or its value there changed since they were learned",
                                      value=store.params_dropped)
            yield CounterMetricFamily(P + "state_save_errors", "State saves that failed", value=store.save_errors)
            yield CounterMetricFamily(P + "state_saves", "State saves", value=store.saves)
            yield CounterMetricFamily(P + "state_save_refused", "State saves refused because the file would not load "
                                      "back (the previous file kept; also counted in state_save_errors)",
                                      value=store.save_refused)
            yield CounterMetricFamily(P + "state_temp_files_removed", "Temporary files of interrupted saves removed at start",
                                      value=store.temp_removed)
            yield GaugeMetricFamily(P + "state_save_failing", "State saves failed in a row (0: the last save worked; 1 at "
                                    "start: the state directory is not writable)", value=store.failing)
        server = m._server
        if server is not None:
            yield CounterMetricFamily(P + "metrics_connections_rejected",
                                      "Connections to this endpoint closed without an answer: no complete request within "
                                      "the idle timeout, or the longest waiting dropped for a newer one",
                                      value=server.rejected)
        for name, fn, doc in m.extra:
            try:
                yield GaugeMetricFamily(P + name, doc, value=float(fn()))
            except Exception:  # a broken extra must not break the scrape
                log.debug("metric %s failed", name, exc_info=True)


class ServiceMetrics:
    """The service's metrics in their own registry, optionally served over HTTP.

    Parameters
    ----------
    registry : CollectorRegistry, optional
        Default: a new registry (several services in one process do not collide).
    """

    def __init__(self, registry: CollectorRegistry | None = None) -> None:
        self.registry = registry if registry is not None else CollectorRegistry()
        self.engine: ThermalEngine | None = None
        self.codec: Any = None
        self.transport_stats: Any = None
        self.store: Any = None
        self.extra: list[tuple[str, Callable[[], float], str]] = []
        #: the limits TE_Limits carries now (between ticks too: a silent bus, a stalled tick); without
        #: it, the last tick's
        self.limits_now: Callable[[], Limits] | None = None
        #: seconds the bus has been silent beyond ``transmit.bus_silence_s`` (None: it is not)
        self.silent_s: Callable[[], float | None] | None = None
        r = self.registry
        buckets = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 1.0)
        self.tick_duration = Histogram(P + "tick_duration_seconds", "Compute (CPU) time of one tick", registry=r,
                                       buckets=buckets)
        self.tick_wall = Histogram(P + "tick_wall_seconds", "Wall time of one tick (CPU time plus waits for the "
                                   "processor and the interpreter)", registry=r, buckets=buckets)
        self.tick_lateness = Histogram(P + "tick_lateness_seconds", "Start of a tick after its scheduled time (wall clock)",
                                       registry=r, buckets=(0.001, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0))
        # absolute buckets: what matters is the inverter's timeout (300 ms in the CAN matrix), not the period
        self.limits_interval = Histogram(P + "limits_send_interval_seconds", "Interval between two TE_Limits frames "
                                         "handed to the bus (the inverter falls back to its own protection after "
                                         "300 ms without one)", registry=r,
                                         buckets=(0.05, 0.09, 0.11, 0.15, 0.2, 0.3, 0.5, 1.0, 2.5))
        self.adapt_duration = Histogram(P + "adaptation_duration_seconds", "Wall time of one adaptation decision",
                                        registry=r, buckets=(0.01, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60))
        self.watchdog_pings = Counter(P + "watchdog_pings", "systemd watchdog notifications sent", registry=r)
        self.info = Info(P + "build", "Build information", registry=r)
        self.up = Gauge(P + "up", "1 while the service runs", registry=r)
        r.register(_LiveCollector(self))
        self._server: MetricsServer | None = None

    def attach(self, engine: ThermalEngine, codec: Any = None, transport_stats: Any = None, store: Any = None) -> None:
        self.engine, self.codec, self.transport_stats, self.store = engine, codec, transport_stats, store
        self.info.info({
            "version": __version__,
            "model": engine.model.name,
            "python": platform.python_version(),
            "clock": engine.config.clock.mode,
        })

    def observe_tick(self, out: TickOutput, lateness_s: float | None = None) -> None:
        self.tick_duration.observe(out.compute_s)
        self.tick_wall.observe(out.wall_s)
        if lateness_s is not None:
            self.tick_lateness.observe(lateness_s)
        for res in out.new_results:
            self.adapt_duration.observe(res.wall_s)

    def serve(self, address: str, port: int) -> tuple[str, int]:
        """Start the HTTP endpoint (bounded threads, idle timeout) in a daemon thread; returns the bound (address, port)."""
        self._server = MetricsServer(self.registry, address, port)
        host, bound = self._server.address
        log.info("metrics on http://%s:%d/metrics", host if ":" not in host else f"[{host}]", bound)
        return host, bound

    @property
    def port(self) -> int | None:
        return self._server.address[1] if self._server is not None else None

    def text(self) -> str:
        from prometheus_client import generate_latest

        return generate_latest(self.registry).decode()

    def close(self) -> None:
        if self._server is not None:
            try:
                self._server.close()
            except Exception:
                pass
            self._server = None
