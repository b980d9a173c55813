"""``/metrics``: the server's figures in the Prometheus text format, for an operator's usual
dashboards. The same figures ``/api/stats`` serves, read from ``stats_snapshot()`` at each
scrape by a custom collector: nothing is counted twice, and no metric call runs on the
message or frame paths.

Frame lateness is a gauge per room and quantile (``quantile="0.5"``, ``"0.99"``,
``"0.999"``, ``"1"`` for the maximum), not a Prometheus summary or histogram: the engine
keeps the newest frames' lateness in a window (the frame loop's ring,
native/loop/block.hpp), not the cumulative count and sum those types promise, so the
quantiles are the window's, as in
``/api/stats``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

CONTENT_TYPE = CONTENT_TYPE_LATEST
PREFIX = "clothball_"

# /api/stats counter -> (metric name without _total, help)
COUNTERS = {
    "messages_in": ("messages_in", "websocket messages received"),
    "messages_out": ("messages_out", "websocket messages sent"),
    "lane_messages_in": ("lane_messages_in",
                         "of messages_in, the HIPs the gateways wrote into the block"),
    "lane_messages_out": ("lane_messages_out",
                          "of messages_out, the CORNERs the gateways sent from the block"),
    "bad_messages": ("bad_messages", "websocket messages refused as malformed"),
    "rounds_saved": ("rounds_saved", "rounds recorded and indexed"),
    "rounds_not_saved": ("rounds_not_saved", "rounds that could not be recorded"),
    "refused_connections": ("refused_connections",
                            "connections refused (origin policy, connection limits)"),
    "rooms_stopped": ("rooms_stopped", "rooms stopped by a failed simulation"),
    "slow_drops": ("slow_drops", "clients dropped for staying behind past slow_drop_s"),
    "cpu_s": ("cpu_seconds", "CPU time the server process has used"),
}
# room figure in /api/stats -> (metric name, counter?, help)
ROOM_FIGURES = {
    "frames": ("room_frames", True, "frames the room has run"),
    "steps": ("room_steps", True, "simulation steps the room has run"),
    "skipped_frames": ("room_skipped_frames", True, "frames skipped to catch up"),
    "meshes": ("room_meshes", True, "MESH messages the room has made"),
    "substeps": ("room_substeps", False, "simulation substeps per frame"),
    "n": ("room_cloth_nodes", False, "cloth nodes per side"),
}
LATENESS_QUANTILES = {"p50": "0.5", "p99": "0.99", "p999": "0.999", "max": "1"}
# headroom figure -> (metric name, scale to base units, help)
HEADROOM = {
    "lateness_p99_ms": ("headroom_lateness_p99_seconds", 1e-3,
                        "frame lateness p99 of the last admission window, all rooms"),
    "skipped_frames": ("headroom_skipped_frames", 1.0,
                       "frames skipped in the last admission window"),
    "cpu_cores": ("headroom_cpu_cores", 1.0, "the process's CPU use over the last window"),
    "carried_cores": ("headroom_carried_cores", 1.0, "what the awake rooms cost by the model"),
    "steal": ("headroom_steal_ratio", 1.0, "share of the machine's CPU time stolen"),
    "cores": ("headroom_cores", 1.0, "cores the admission gives rooms"),
    "load": ("headroom_load", 1.0, "share of those cores the rooms may take"),
}
STORAGE = {
    "rounds": ("storage_rounds", "rounds in the replay index"),
    "bytes": ("storage_bytes", "bytes of the replay files"),
    "max_bytes": ("storage_max_bytes", "the replays' size budget (retention)"),
    "free_bytes": ("storage_free_bytes", "bytes free on the data directory's filesystem"),
}


class SnapshotCollector(Collector):
    """Turns one ``stats_snapshot()`` into metric families at each scrape."""

    def __init__(self, snapshot: Callable[[], dict[str, Any]]) -> None:
        self.snapshot = snapshot

    def collect(self) -> Iterator[Metric]:
        return iter(families(self.snapshot()))


def families(st: dict[str, Any]) -> list[Metric]:
    """The metric families of one ``/api/stats`` snapshot ``st``."""
    out: list[Metric] = []

    def gauge(name: str, doc: str, value: float, **labels: str) -> None:
        g = GaugeMetricFamily(PREFIX + name, doc, labels=list(labels))
        g.add_metric(list(labels.values()), float(value))
        out.append(g)

    gauge("uptime_seconds", "seconds since the server started", st["uptime_s"])
    gauge("clients", "websocket connections open", st["clients"])
    gauge("rooms", "public rooms open (the rooms /api/stats lists)", len(st["rooms"]))
    for key, (name, doc) in COUNTERS.items():
        out.append(CounterMetricFamily(PREFIX + name, doc, value=float(st[key])))
    gauge("recording", "1 while rounds are recorded, 0 while recording is off",
          st["recording"] == "on")
    gauge("replay_index_up", "1 while the replay index can be written",
          st["replay_index"] == "ok")
    storage = st["storage"]
    for key, (name, doc) in STORAGE.items():
        if storage.get(key) is not None:
            gauge(name, doc, storage[key])
    gauge("storage_max_age_seconds", "the replays' age budget (retention)",
          storage["max_days"] * 86400)
    gauge("storage_state", "the data directory's state (label state; 1)", 1,
          state=str(storage["state"]))
    head = st["headroom"]
    for key, (name, scale, doc) in HEADROOM.items():
        gauge(name, doc, head[key] * scale)
    gauge("busy", "1 while admission refuses new rooms by the measured signal",
          head["busy"] is not None)
    room_cost = GaugeMetricFamily(PREFIX + "room_cost_cores", "a room's cost in cores, "
                                  "by scene", labels=["scene"])
    for scene, cost in sorted(head["room_cost"].items()):
        room_cost.add_metric([scene], cost)
    out.append(room_cost)

    rooms = sorted(st["rooms"].items())
    for key, (name, counter, doc) in ROOM_FIGURES.items():
        fam: Metric = (CounterMetricFamily if counter else GaugeMetricFamily)(
            PREFIX + name, doc, labels=["room"])
        for rid, r in rooms:
            fam.add_metric([rid], float(r[key]))  # type: ignore[attr-defined]
        out.append(fam)
    backend = GaugeMetricFamily(PREFIX + "room_backend", "the room's engine backend "
                                "(label backend; 1)", labels=["room", "backend"])
    late = GaugeMetricFamily(PREFIX + "room_frame_lateness_seconds",
                             "frame lateness over the newest frames (quantile 1: the most)",
                             labels=["room", "quantile"])
    late_mean = GaugeMetricFamily(PREFIX + "room_frame_lateness_mean_seconds",
                                  "mean frame lateness over the newest frames", labels=["room"])
    late_n = GaugeMetricFamily(PREFIX + "room_frame_lateness_frames",
                               "frames the lateness figures are over", labels=["room"])
    for rid, r in rooms:
        backend.add_metric([rid, str(r["backend"])], 1)
        lat = r["lateness_ms"]
        late_n.add_metric([rid], lat["count"])
        if lat["count"]:
            for key, q in LATENESS_QUANTILES.items():
                late.add_metric([rid, q], lat[key] * 1e-3)
            late_mean.add_metric([rid], lat["mean"] * 1e-3)
    out += [backend, late, late_mean, late_n]
    return out


def registry_for(snapshot: Callable[[], dict[str, Any]]) -> CollectorRegistry:
    """A registry of one server's own (not the process-wide default: several servers may
    run in one process, as in the tests)."""
    reg = CollectorRegistry(auto_describe=False)
    reg.register(SnapshotCollector(snapshot))
    return reg


def exposition(registry: CollectorRegistry) -> bytes:
    """The text a scrape gets."""
    return generate_latest(registry)


__all__ = ["CONTENT_TYPE", "SnapshotCollector", "exposition", "families", "registry_for"]
