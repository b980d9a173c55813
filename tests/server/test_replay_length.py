"""The replay list's duration is the player's length: the index's ``duration_s`` for a
saved round equals the span of its recorded MESH and TRACK frames (what the web player's
``Replay.duration`` computes), decoded here with the protocol's own decoders."""

from __future__ import annotations

import asyncio

import pytest
from clothball.game.wire import protocol as P
from clothball.game.wire.replay import read_replay
from clothball.server.room import RoomSettings

from tests.server.conftest import http_get, http_json, run, server


def test_listed_duration_is_the_recorded_length(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path, bots=4,
                          settings=RoomSettings(autoplay=True, countdown=0.2)) as srv:
            rows: list = []

            async def listed() -> bool:
                rows[:] = (await http_json(srv, "/api/replays"))["replays"]
                return bool(rows)

            for _ in range(600):
                if await listed():
                    break
                await asyncio.sleep(0.1)
            assert rows, "no round saved"
            row = rows[0]
            status, body, _ = await http_get(srv, f"/api/replays/{row['id']}")
            assert status == 200
            header, records = read_replay(body)
            frames = []
            for kind, data in records:
                if kind != 1:
                    continue
                m = P.decode_binary(data)
                if isinstance(m, (P.Mesh, P.Track)):
                    frames.append(m.frame)
            want = (max(frames) - min(frames)) * header["geometry"]["frame_dt"]
            assert row["duration_s"] == pytest.approx(want, rel=1e-12, abs=1e-12)
            assert header["duration_s"] == row["duration_s"]

    run(main())
