"""A real server on loopback: bots play a match to the end; rounds are recorded, listed,
downloaded intact and kept across a restart."""

from __future__ import annotations

import numpy as np
from clothball.game.net.client import NetClient
from clothball.game.wire import protocol as P
from clothball.game.wire.replay import read_replay, write_replay
from clothball.server.room import RoomSettings
from clothball.server.storage.sqlite import SqliteIndex

from tests.server.conftest import FAST, http_get, http_json, run, server, until


def test_bots_play_a_match_to_the_end_and_rounds_are_recorded(tmp_path) -> None:
    settings = RoomSettings(autoplay=True, **FAST)

    async def main() -> None:
        async with server(tmp_path, bots=4, settings=settings) as srv:
            room = srv.main_room
            assert room is not None
            spec = await NetClient.connect(srv.ws_url, role="spectator", room=room.id)
            end = await spec.wait_event("match_end", timeout=60)
            assert max(end["scores"]) >= 2 and end["winners"]
            assert all(end["scores"][w] >= 2 for w in end["winners"])
            scores = [m for m in spec.messages if m.get("event") == "score"]
            assert scores, "no round was scored"
            for s in scores:
                assert s["conceded_by"] == s["edge"]  # every seat is held by a bot
                assert sorted(s["scorers"]) == [x for x in range(4) if x != s["edge"]]
            # every scored round is saved and listed
            await until(lambda: srv.stats["rounds_saved"] >= len(scores), 20, "rounds saved")
            listing = await http_json(srv, "/api/replays")
            assert listing["total"] >= len(scores)
            row = listing["replays"][0]
            assert row["room_id"] == room.id and row["scene"] == "tiny"
            assert [p["kind"] for p in row["players"]] == ["bot"] * 4
            assert row["conceded_edge"] in range(4) and row["duration_s"] > 0
            status, body, headers = await http_get(srv, f"/api/replays/{row['id']}")
            assert status == 200 and int(headers["Content-Length"]) == row["bytes"]
            header, records = read_replay(body)
            assert header["id"] == row["id"] and header["replay_version"] == 1
            assert header["conceded_edge"] == row["conceded_edge"]
            kinds = {P.decode_header(d).type for k, d in records if k == 1}
            assert kinds == {P.MESH, P.TRACK}
            meshes = [P.decode_mesh(d) for k, d in records if k == 1 and d[0] == P.MESH]
            assert meshes and all(m.positions.shape == (16, 16, 3) for m in meshes)
            frames = [m.frame for m in meshes]
            assert frames == sorted(frames)
            events = [P.decode_json(d)["event"] for k, d in records if k == 0]
            assert "round_start" in events and "score" in events
            tracks = [P.decode_track(d) for k, d in records if k == 1 and d[0] == P.TRACK]
            assert np.all(np.isfinite([t.ball_position for t in tracks]))
            # unknown ids and junk
            for bad in ("nope", "../index.sqlite", "%2e%2e%2findex.sqlite", "x" * 300):
                status, body, _ = await http_get(srv, f"/api/replays/{bad}")
                assert status == 404
            await spec.close()

    run(main())
    # kept across a restart; a half-written file is removed; a finished file the index
    # lacks is indexed from its own header
    store = SqliteIndex(tmp_path)
    before = store.list()
    assert before
    (tmp_path / "replays" / "junk.cbr.tmp").write_bytes(b"partial")
    header = dict(read_replay((tmp_path / "replays" / f"{before[0]['id']}.cbr").read_bytes())[0])
    header["id"] = "orphan-round-1"
    write_replay(tmp_path / "replays" / "orphan-round-1.cbr", header, [])
    store.close()

    async def again() -> None:
        async with server(tmp_path, settings=RoomSettings()) as srv:
            listing = await http_json(srv, "/api/replays?limit=1000")
            ids = {r["id"] for r in listing["replays"]}
            assert {r["id"] for r in before} <= ids and "orphan-round-1" in ids
            assert not (tmp_path / "replays" / "junk.cbr.tmp").exists()

    run(again())


def test_a_player_who_took_a_seat_mid_round_is_in_its_replay_and_found_by_name(tmp_path
                                                                              ) -> None:
    # Rounds of about a second (a slower throw than FAST's), so that a join lands in one.
    settings = RoomSettings(autoplay=True, **{**FAST, "reset_speed": 1.0})

    async def main() -> None:
        async with server(tmp_path, bots=4, settings=settings) as srv:
            room = srv.main_room
            assert room is not None
            spec = await NetClient.connect(srv.ws_url, role="spectator", room=room.id,
                                           mesh=False)
            late = None
            for _ in range(10):  # a join that lands between two rounds is tried again
                start = await spec.wait_event("round_start", timeout=30)
                late = await NetClient.connect(srv.ws_url, name="latecomer", role="player",
                                               room=room.id, mesh=False, corner_rate=5)
                assert late.joined is not None
                state = late.joined["state"]
                if state["state"] == "playing" and state["round"] == start["round"]:
                    break
                await late.close()
                late = None
            assert late is not None, "no join landed in a round"
            seat, rnd = late.seat, start["round"]
            saved = await spec.wait_event("replay_saved", timeout=30, round=rnd)
            # the round was found by the name of the player who joined it mid-round
            listing = await http_json(srv, "/api/replays?player=latecomer")
            assert saved["id"] in {r["id"] for r in listing["replays"]}, listing
            row = next(r for r in listing["replays"] if r["id"] == saved["id"])
            assert row["round"] == rnd
            # its seat lists the bot it replaced, then the player, in order
            held = row["players"][seat]["held_by"]
            assert held == [{"kind": "bot", "name": f"bot-{seat}"},
                            {"kind": "human", "name": "latecomer"}], held
            assert row["players"][seat]["name"] == "latecomer"
            status, body, _ = await http_get(srv, f"/api/replays/{saved['id']}")
            assert status == 200 and read_replay(body)[0]["players"] == row["players"]
            await late.close()
            await spec.close()

    run(main())
