"""``/metrics`` (issue 33): a live server's Prometheus text, parsed with prometheus_client's
own parser, carries the figures ``/api/stats`` serves."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from clothball.game.net.client import NetClient
from clothball.server.metrics import exposition, registry_for
from clothball.server.room import RoomSettings
from prometheus_client.parser import text_string_to_metric_families

from tests.server.conftest import http_get, http_json, run, server, until

Samples = dict[tuple[str, tuple[tuple[str, str], ...]], float]


def parse(text: str) -> tuple[Samples, dict[str, str]]:
    """Every sample by (name, sorted labels), and every family's type."""
    samples: Samples = {}
    types: dict[str, str] = {}
    for fam in text_string_to_metric_families(text):
        types[fam.name] = fam.type
        for s in fam.samples:
            samples[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return samples, types


def expected(st: dict[str, Any]) -> Samples:
    """What /metrics must say for the /api/stats answer ``st``, written out by hand from
    the documented names (docs/cluster.md, "Metrics")."""
    def one(name: str, value: float, **labels: str) -> tuple[Any, float]:
        return (f"clothball_{name}", tuple(sorted(labels.items()))), float(value)

    storage, head = st["storage"], st["headroom"]
    rows = [
        one("uptime_seconds", st["uptime_s"]),
        one("clients", st["clients"]),
        one("rooms", len(st["rooms"])),
        one("cpu_seconds_total", st["cpu_s"]),
        one("recording", st["recording"] == "on"),
        one("replay_index_up", st["replay_index"] == "ok"),
        one("storage_rounds", storage["rounds"]),
        one("storage_bytes", storage["bytes"]),
        one("storage_max_bytes", storage["max_bytes"]),
        one("storage_free_bytes", storage["free_bytes"]),
        one("storage_max_age_seconds", storage["max_days"] * 86400),
        one("storage_state", 1, state=storage["state"]),
        one("busy", head["busy"] is not None),
        one("headroom_lateness_p99_seconds", head["lateness_p99_ms"] / 1000),
        one("headroom_skipped_frames", head["skipped_frames"]),
        one("headroom_cpu_cores", head["cpu_cores"]),
        one("headroom_carried_cores", head["carried_cores"]),
        one("headroom_steal_ratio", head["steal"]),
        one("headroom_cores", head["cores"]),
        one("headroom_load", head["load"]),
    ]
    rows += [one(f"{k}_total", st[k]) for k in (
        "messages_in", "messages_out", "lane_messages_in", "lane_messages_out",
        "bad_messages", "rounds_saved", "rounds_not_saved",
        "refused_connections", "rooms_stopped", "slow_drops")]
    rows += [one("room_cost_cores", c, scene=s) for s, c in head["room_cost"].items()]
    for rid, r in st["rooms"].items():
        rows += [one("room_frames_total", r["frames"], room=rid),
                 one("room_steps_total", r["steps"], room=rid),
                 one("room_skipped_frames_total", r["skipped_frames"], room=rid),
                 one("room_meshes_total", r["meshes"], room=rid),
                 one("room_substeps", r["substeps"], room=rid),
                 one("room_cloth_nodes", r["n"], room=rid),
                 one("room_backend", 1, room=rid, backend=r["backend"])]
        lat = r["lateness_ms"]
        rows.append(one("room_frame_lateness_frames", lat["count"], room=rid))
        if lat["count"]:
            rows += [one("room_frame_lateness_seconds", lat[k] / 1000, room=rid, quantile=q)
                     for k, q in (("p50", "0.5"), ("p99", "0.99"), ("p999", "0.999"),
                                  ("max", "1"))]
            rows.append(one("room_frame_lateness_mean_seconds", lat["mean"] / 1000, room=rid))
    return dict(rows)


def close(a: float, b: float) -> bool:
    return abs(a - b) <= 1e-9 * max(1.0, abs(a), abs(b))


def test_the_metrics_of_a_stats_answer_are_its_figures(tmp_path: Path) -> None:
    """Every figure of a live server's /api/stats answer, through the collector, the text
    format and prometheus_client's parser, comes back as the documented sample."""
    async def main() -> None:
        async with server(tmp_path, settings=RoomSettings(autoplay=True)) as srv:
            await http_json(srv, "/api/rooms")  # listed: the empty show room steps a while
            await until(lambda: srv.main_room is not None and
                        len(srv.main_room.sim.stats.lateness) > 20, 30, "frames timed")
            st = await http_json(srv, "/api/stats")
        assert st["rooms"]["main"]["lateness_ms"]["count"] > 0
        got, types = parse(exposition(registry_for(lambda: st)).decode())
        want = expected(st)
        assert set(got) == set(want)
        bad = {k: (got[k], v) for k, v in want.items() if not close(got[k], v)}
        assert not bad, bad
        assert types["clothball_messages_in"] == "counter"
        assert types["clothball_room_frame_lateness_seconds"] == "gauge"

    run(main())


def test_a_live_scrape_matches_api_stats(tmp_path: Path) -> None:
    """/metrics of a live server, scraped between two /api/stats answers: what cannot move
    while nothing happens is equal, counters lie between the two answers."""
    async def main() -> None:
        async with server(tmp_path, settings=RoomSettings(autoplay=True)) as srv:
            watcher = await NetClient.connect(srv.ws_url, name="w", role="spectator",
                                              room="main")
            try:
                await until(lambda: watcher.counts["mesh"] > 5, 30, "meshes")
                before = await http_json(srv, "/api/stats")
                status, body, headers = await http_get(srv, "/metrics")
                after = await http_json(srv, "/api/stats")
            finally:
                await watcher.close()
        assert status == 200 and headers["Content-Type"].startswith("text/plain")
        got, _ = parse(body.decode())
        want_a, want_b = expected(before), expected(after)
        for key in ("clients", "rooms", "recording", "replay_index_up", "storage_rounds",
                    "storage_bytes", "storage_max_bytes", "bad_messages_total",
                    "rooms_stopped_total"):
            k = (f"clothball_{key}", ())
            assert got[k] == want_a[k] == want_b[k], key
        assert got[("clothball_clients", ())] >= 1
        moving = ["uptime_seconds", "cpu_seconds_total", "messages_in_total",
                  "messages_out_total"]
        for key in moving:
            k = (f"clothball_{key}", ())
            assert want_a[k] <= got[k] <= want_b[k], (key, want_a[k], got[k], want_b[k])
        room = (("room", "main"),)
        k = ("clothball_room_frames_total", room)
        assert want_a[k] <= got[k] <= want_b[k]
        assert got[("clothball_room_frame_lateness_frames", room)] > 0
        assert ("clothball_room_frame_lateness_seconds",
                (("quantile", "0.99"), ("room", "main"))) in got
        # Private rooms are named by neither.
        assert json.dumps(sorted(before["rooms"])) == json.dumps(
            sorted({dict(k[1])["room"] for k in got if k[0] == "clothball_room_frames_total"}))

    run(main())
