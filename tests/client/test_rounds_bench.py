"""``clothball bench --rounds`` (``game.study.rounds``): a spectator times the rounds bots
play in a real room. The reference is the server's own record of each round: the replay
index's ``duration_s`` (the span of the round's recorded frames, from its start to the
ball's exit plus the recorded tail ``tail_s``). The summary is checked against NumPy's
percentiles of the same lengths. Nothing here is timed: the figure of record is the
benchmark's (docs/benchmarks/rounds.md)."""

from __future__ import annotations

import asyncio
import json
import time
import urllib.request

import numpy as np
from clothball.game.study import rounds

from tests.server.conftest import FAST, local_server

ROUNDS = 4


def test_watched_round_lengths_agree_with_the_servers_record(tmp_path) -> None:
    settings = {**FAST, "first_to": 99}  # one match: round numbers name rounds
    with local_server(tmp_path / "data", bots=4, **settings) as st:
        room = st.call(lambda srv: srv.main_room.id)
        played = asyncio.run(rounds.watch_rounds(st.ws_url, room, ROUNDS,
                                                 round_timeout=60))
        want = {r.round for r in played}
        end = time.monotonic() + 30
        while True:  # each round's file is saved after its tail
            with urllib.request.urlopen(f"{st.url.rstrip('/')}/api/replays?room={room}",
                                        timeout=10) as resp:
                saved = {x["round"]: x for x in json.loads(resp.read())["replays"]}
            if want <= set(saved) or time.monotonic() > end:
                break
            time.sleep(0.2)
        tail = st.call(lambda srv: __import__("clothball.server.room",
                                              fromlist=["RECORD_TAIL"]).RECORD_TAIL)
    assert len(played) == ROUNDS
    assert [r.round for r in played] == list(range(played[0].round,
                                                   played[0].round + ROUNDS))
    mesh_period = 1.0 / 30.0
    track_period = 1.0 / 100.0
    for r in played:
        rec = saved[r.round]
        assert rec["conceded_edge"] == r.edge
        # both ends read from the newest MESH a spectator had: good to a MESH period each
        assert abs(r.seconds - (rec["duration_s"] - tail)) <= 2 * mesh_period + track_period, (
            r, rec["duration_s"])
    s = rounds.summarise(played)
    lengths = np.array([r.seconds for r in played])
    assert s["rounds"] == ROUNDS and np.isclose(s["median_s"], np.median(lengths))
    assert np.isclose(s["q1_s"], np.percentile(lengths, 25))
    assert sum(b["count"] for b in s["histogram"]) == ROUNDS
    assert s["meets_target"] == (np.median(lengths) >= rounds.TARGET_MEDIAN_S)
