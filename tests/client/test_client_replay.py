"""Desktop replays without a window: parse a replay file, seek, pause, speed, scores at
the playhead; fetch by file, id and URL from a real server."""

from __future__ import annotations

import asyncio
import base64
import json
import time
from pathlib import Path

import numpy as np
import pytest
from clothball.game.client.replay import (
    SPEEDS,
    ReplayData,
    ReplayPlayer,
    fetch,
    http_base,
    list_remote,
)
from clothball.game.sim.cloth import rest_positions
from clothball.game.wire import protocol as P
from clothball.game.wire.replay import ReplayError, recorded_length, write_replay

from tests.server.conftest import TINY, run, server

T0 = 50.0  # server time the recording starts
MESH_HZ, TRACK_HZ, DURATION = 30.0, 100.0, 2.0


def lift(t: float) -> float:
    """The synthetic cloth rises linearly: 0.1 m/s."""
    return 0.1 * (t - T0)


def ball(t: float) -> np.ndarray:
    return np.array([0.2 * (t - T0), 1.0, 0.0])


def synthetic_records() -> list[tuple[int, bytes]]:
    rest = rest_positions(TINY)
    recs: list[tuple[int, bytes]] = []
    events = [
        (T0, {"type": "event", "event": "round_start", "round": 3, "time": T0,
              "frame": round(T0 * 1000)}),
        (T0 + 1.5, {"type": "event", "event": "score", "round": 3, "edge": 1,
                    "edge_name": "east", "conceded_by": 1, "scorers": [0, 2],
                    "scores": [3, 0, 3, 1], "time": T0 + 1.5,
                    "frame": round((T0 + 1.5) * 1000)}),
    ]
    for k in range(int(DURATION * TRACK_HZ) + 1):
        t = T0 + k / TRACK_HZ
        hips = np.tile(ball(t), (4, 1))
        recs.append((1, P.encode_track(int(t * 1000), t, ball(t), [0.2, 0, 0], hips, hips)))
    for k in range(int(DURATION * MESH_HZ) + 1):
        t = T0 + k / MESH_HZ
        pos = rest.copy()
        pos[..., 1] += lift(t)
        recs.append((1, P.encode_mesh(int(t * 1000), t, pos, ball(t) + 9.0, 0.05,
                                      np.zeros((4, 3)))))
    recs += [(0, P.encode_json(e).encode()) for _, e in events]
    return recs


STARTED = float(int(time.time()) - 60)
HEADER = {
    "format": "clothball-replay", "replay_version": 1, "id": "test-round-0001",
    "room_id": "r1", "room_name": "main", "scene": "tiny", "round": 3,
    "players": [{"seat": i, "kind": "bot", "name": f"bot-{i}"} for i in range(4)],
    "conceded_edge": 1, "conceded_by": 1, "scorers": [0, 2], "scores": [3, 0, 3, 1],
    # Recorded a minute ago: the server keeps rounds for 30 days (replays_max_days) and prunes
    # older ones when it starts.
    "started_at": STARTED, "ended_at": STARTED + 2, "duration_s": 2.0,
}


@pytest.fixture
def replay_file(tmp_path):
    path = tmp_path / "replays" / f"{HEADER['id']}.cbr"
    path.parent.mkdir(parents=True)
    write_replay(path, HEADER, synthetic_records())
    return path


def test_parse_and_play(replay_file) -> None:
    data = ReplayData.parse(replay_file.read_bytes())
    assert data.header["id"] == HEADER["id"]
    assert data.start == T0 and data.duration == pytest.approx(DURATION)
    assert len(data.timeline) == int(DURATION * MESH_HZ) + 1
    assert [e["event"] for _, e in data.events] == ["round_start", "score"]
    p = ReplayPlayer(data)
    assert p.position == 0.0 and p.scores() == [2, 0, 2, 1]  # before the point was scored
    # seek between mesh frames: the cloth is interpolated, the ball comes from the track
    p.seek(0.51)
    s = p.sample()
    assert s.server_time == pytest.approx(T0 + 0.51)
    mesh_err = 1e-4 + (TINY["cloth"]["size"] + 1.0) / 65535  # quantisation + float32
    assert np.allclose(s.positions[..., 1] - rest_positions(TINY)[..., 1], lift(T0 + 0.51),
                       atol=mesh_err)
    assert np.allclose(s.ball_position, ball(T0 + 0.51), atol=1e-6)
    assert np.allclose(s.hips, np.tile(ball(T0 + 0.51), (4, 1)), atol=1e-6)
    # playing: advance with the wall clock at the chosen speed
    p.advance(0.2)
    assert p.position == pytest.approx(0.71)
    p.faster()
    assert p.speed == 2.0
    p.advance(0.2)
    assert p.position == pytest.approx(1.11)
    p.toggle_pause()
    p.advance(5.0)
    assert p.position == pytest.approx(1.11) and p.paused
    p.toggle_pause()
    p.advance(0.25)
    assert p.position == pytest.approx(1.61)
    assert p.scores() == [3, 0, 3, 1]  # the score event at 1.5 s has passed
    assert [e["event"] for e in p.events_until()] == ["round_start", "score"]
    p.skip(-0.5)
    assert p.scores() == [2, 0, 2, 1]  # seeking back undoes it
    p.advance(100.0)
    assert p.position == pytest.approx(DURATION) and p.finished
    p.toggle_pause()
    p.toggle_pause()  # resuming at the end starts again
    assert p.position == 0.0
    p.seek(-5.0)
    assert p.position == 0.0
    p.seek_fraction(0.5)
    assert p.position == pytest.approx(DURATION / 2)


def test_the_length_is_the_simulations_as_the_index_lists_it(tmp_path) -> None:
    """A server that fell behind stamps its wall clock 1.3x slower than the game (a round of
    27.3 s of play over 35.5 s); the TRACK stream goes on 40 ms after the last MESH. The
    desktop's length is the game's, first to last MESH or TRACK frame x frame_dt: the
    header's duration_s (the index's) and the browser's; events sit at their frames."""
    dt, f0, lag = 0.001, 123_000, 1.3
    rest = rest_positions(TINY)
    wall = lambda f: 1000.0 + lag * (f - f0) * dt  # noqa: E731
    mesh_frames = list(range(f0, f0 + 2000, 33))
    track_frames = list(range(f0 + 5, mesh_frames[-1] + 41, 10))
    recs = [(1, P.encode_mesh(f, wall(f), rest, [0, 1, 0], 0.05, np.zeros((4, 3))))
            for f in mesh_frames]
    recs += [(1, P.encode_track(f, wall(f), [0, 1, 0], [0, 0, 0], np.zeros((4, 3)),
                                np.zeros((4, 3)))) for f in track_frames]
    score_frame = mesh_frames[-1] - 500
    recs.append((0, P.encode_json({"type": "event", "event": "score", "frame": score_frame,
                                   "time": wall(score_frame), "scores": [1, 0, 0, 0]}).encode()))
    length = (track_frames[-1] - mesh_frames[0]) * dt
    header = {**HEADER, "geometry": {"frame_dt": dt}, "duration_s": length}
    write_replay(tmp_path / "r.cbr", header, recs)
    data = ReplayData.parse((tmp_path / "r.cbr").read_bytes())
    assert data.duration == pytest.approx(length, abs=1e-9)
    assert data.duration == pytest.approx(recorded_length(dt, recs), abs=1e-9)
    p = ReplayPlayer(data)
    p.seek((score_frame - f0) * dt - 0.002)
    assert p.events_until() == []
    p.seek((score_frame - f0) * dt)
    assert [e["event"] for e in p.events_until()] == ["score"]
    p.advance(100.0)
    assert p.position == pytest.approx(length, abs=1e-9) and p.finished


def test_an_old_replay_of_version_1_meshes_plays() -> None:
    """A replay recorded before MESH version 2 (tests/data/mesh_v1.json, the encoder of its
    day): the desktop player reads its three meshes, each the nodes stored beside it."""
    fixture = json.loads((Path(__file__).parent.parent / "data" / "mesh_v1.json").read_text())
    data = ReplayData.parse(base64.b64decode(fixture["replay_b64"]))
    stored = [m for m in fixture["messages"] if m["flags"]]  # the replay's: compressed ones
    frames = list(data.timeline.frames)
    assert len(frames) == len(stored) == 3
    for f, m in zip(frames, stored, strict=True):
        q = np.array(m["q"], dtype=np.uint16).reshape(16, 16, 3)
        want = P.dequantise(q, np.array(m["lo"]), np.array(m["hi"])).astype(np.float32)
        assert np.array_equal(f.positions, want)
    p = ReplayPlayer(data)
    p.seek_fraction(0.5)
    assert p.sample().positions.shape == (16, 16, 3)


def test_speed_steps_and_loop(replay_file) -> None:
    p = ReplayPlayer(ReplayData.parse(replay_file.read_bytes()), loop=True)
    for _ in range(10):
        p.slower()
    assert p.speed == SPEEDS[0]
    for _ in range(10):
        p.faster()
    assert p.speed == SPEEDS[-1]
    p.speed = 1.0
    p.seek(1.9)
    p.advance(0.3)
    assert p.position == pytest.approx(0.2) and not p.finished


def test_damaged_replays_are_refused(tmp_path, replay_file) -> None:
    with pytest.raises(ReplayError):
        ReplayData.parse(b"not a replay")
    empty = tmp_path / "empty.cbr"
    write_replay(empty, HEADER, [])
    with pytest.raises(ReplayError, match="no mesh frames"):
        ReplayData.parse(empty.read_bytes())
    with pytest.raises(ReplayError):
        fetch("no/such/file.cbr")


def test_fetch_by_file_id_and_url(tmp_path, replay_file) -> None:
    assert fetch(str(replay_file)) == replay_file.read_bytes()
    assert http_base("ws://127.0.0.1:8765/ws") == "http://127.0.0.1:8765"
    assert http_base("wss://example.org/ws") == "https://example.org"

    async def main() -> None:
        # the server indexes the finished file it finds in its data directory
        async with server(tmp_path) as srv:
            rows = await asyncio.to_thread(list_remote, srv.ws_url)
            assert [r["id"] for r in rows] == [HEADER["id"]]
            by_id = await asyncio.to_thread(fetch, HEADER["id"], srv.ws_url)
            by_url = await asyncio.to_thread(
                fetch, f"{srv.http_url}api/replays/{HEADER['id']}")
            assert by_id == by_url == replay_file.read_bytes()

    run(main())
