"""What a late room's replay holds (issue 40; docs/protocol.md, "Replay files"): a room
whose frames cost more than real time is stepped several frames a pass (at most
1 + max_catchup // 4), and a TRACK or MESH is recorded at the pass that reaches its mark,
so consecutive records are never closer than their spacing in frames (10 and 33 at 1 kHz)
and at most a pass's frames less one farther apart; the tail after the score is 1 s of the
room's frames, not of wall time. A real server, one room whose cloth
is too large for its thread to keep up (n = 192), four bots, a recorded round read back
with the protocol's own decoders."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest
from clothball.game.sim.scene import Scene
from clothball.game.wire import protocol as P
from clothball.game.wire.replay import read_replay
from clothball.server.app import GameServer, ServerConfig
from clothball.server.room import RECORD_TAIL, RoomSettings

from tests.server.conftest import BACKEND, FAST, http_get, http_json, no_admission, run

HEAVY = Scene.load("classic").with_changes({"cloth": {"n": 192}})
HEAVY.name = "heavy"


@pytest.mark.slow
def test_a_late_rooms_records_keep_their_spacing_in_frames(tmp_path) -> None:
    async def main() -> None:
        srv = GameServer(ServerConfig(tmp_path, scenes={"heavy": HEAVY}, backend=BACKEND,
                                      port=0, bots=4,
                                      room_settings=RoomSettings(autoplay=True, **FAST),
                                      limits=no_admission(None)))
        await srv.start()
        try:
            room = srv.main_room
            assert room is not None
            rows: list = []
            for _ in range(1200):
                rows[:] = (await http_json(srv, "/api/replays"))["replays"]
                if rows:
                    break
                await asyncio.sleep(0.1)
            assert rows, "no round saved"
            skipped = room.sim.stats.skipped_frames
            late = room.sim.stats.lateness.newest()
            status, body, _ = await http_get(srv, f"/api/replays/{rows[-1]['id']}")
            assert status == 200
            mesh_every, track_every = room.sim.mesh_every, room.sim.track_every
            max_pass = 1 + srv.sims.settings.max_catchup // 4
        finally:
            await srv.stop()
        header, records = read_replay(body)
        tracks, meshes, tail = [], [], []
        for kind, data in records:
            if kind == 1:
                m = P.decode_binary(data)
                (tracks if isinstance(m, P.Track) else meshes).append(m.frame)
                if tail and isinstance(m, P.Track):
                    tail.append(m.frame)
            elif json.loads(data).get("event") == "score":
                tail.append(tracks[-1])  # the TRACK before the score: the tail follows it
        assert header["track_hz"] * HEAVY["sim"]["frame_dt"] * track_every == 1.0
        for frames, every in ((tracks, track_every), (meshes, mesh_every)):
            gaps = np.diff(np.array(frames))
            assert gaps.size > 5, frames
            assert gaps.min() >= every, (every, gaps)
            assert gaps.max() <= every + max_pass - 1, (every, max_pass, gaps)
        # The tail is 1 s of the room's frames after the score, however late it ran (within
        # a TRACK's spacing and a pass either side of the exit frame).
        tail_frames = round(RECORD_TAIL / HEAVY["sim"]["frame_dt"])
        assert tail[-1] - tail[0] >= tail_frames - max_pass, (tail[0], tail[-1], tail_frames)
        # It was late: passes of several frames (else every gap is the spacing exactly).
        assert np.diff(np.array(tracks)).max() > track_every or skipped > 0 or \
            (late.size and float(np.max(late)) > 0.002), "the room kept real time here"

    run(main(), timeout=300)
