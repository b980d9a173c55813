"""A round's recording spools to disk as it is made: memory holds at most a bounded buffer
however long the round, a round longer than the cap is recorded up to it and marked cut,
and the replay read back is exactly what was recorded."""

from __future__ import annotations

import asyncio
import os
import threading

import numpy as np
import pytest
from clothball.game.wire import protocol as P
from clothball.game.wire.replay import read_replay, recorded_length, write_replay
from clothball.server.room import RoomSettings
from clothball.server.storage import recorder
from clothball.server.storage.recorder import BUFFER_BYTES, MAX_PENDING, Recording

from tests.server.conftest import FAST, http_get, http_json, run, server

DT = 1e-3


def track(frame: int) -> bytes:
    z = np.zeros(3)
    return P.encode_track(frame, frame * DT, z, z, np.zeros((4, 3)), np.zeros((4, 3)))


def test_records_spool_to_disk_with_a_bounded_buffer_and_read_back_exactly(tmp_path) -> None:
    rec = Recording("r1", tmp_path, cap_s=3600.0, frame_dt=DT)
    sent = []
    for f in range(60_000):  # a minute of 1 kHz TRACKs, ~8 MB of records
        data = track(f)
        rec.append(1, data)
        sent.append((1, data))
        if f % 1000 == 0:
            ev = P.encode_json({"type": "event", "n": f}).encode()
            rec.append(0, ev)
            sent.append((0, ev))
        assert rec._buf_bytes < BUFFER_BYTES  # never more than one buffer gathering
    rec.finish()
    assert rec.cut is None and rec.error is None
    assert 0 < rec.peak_buffer <= MAX_PENDING * (BUFFER_BYTES + 4096)
    assert rec.bytes > 20 * BUFFER_BYTES  # most of it went to disk, not memory
    got = list(rec.records())
    assert got == sent
    assert rec.duration_s == pytest.approx(recorded_length(DT, sent))
    # The replay writer takes the recording as its records.
    write_replay(tmp_path / "r1.cbr", {"id": "r1"}, rec)
    header, records = read_replay((tmp_path / "r1.cbr").read_bytes())
    assert header == {"id": "r1"} and records == sent
    rec.discard()
    assert not rec.path.exists()


def test_a_recording_past_its_cap_stops_there_and_says_so(tmp_path) -> None:
    rec = Recording("r2", tmp_path, cap_s=2.0, frame_dt=DT)
    for f in range(5000):
        rec.append(1, track(f))
    rec.finish()
    assert rec.cut is not None and "cap" in rec.cut and rec.error is None
    assert rec.duration_s == pytest.approx(2.0)
    frames = [P.decode_binary(d).frame for _, d in rec.records()]
    assert frames == list(range(2001))
    rec.discard()


def test_a_slow_disk_cuts_the_recording_instead_of_holding_it_in_memory(tmp_path,
                                                                        monkeypatch) -> None:
    stuck = threading.Event()  # the writer hangs on its first write until set
    real_write = Recording._write

    def slow_write(self: Recording, data: bytes) -> None:
        stuck.wait(10)
        real_write(self, data)

    monkeypatch.setattr(Recording, "_write", slow_write)
    rec = Recording("r3", tmp_path, cap_s=3600.0, frame_dt=DT)
    f = 0
    while rec.cut is None:
        rec.append(1, track(f))
        f += 1
        assert f < 1_000_000
    assert "disk could not keep up" in rec.cut
    held = rec._buf_bytes + rec._pending * BUFFER_BYTES
    assert held <= (MAX_PENDING + 1) * (BUFFER_BYTES + 4096)
    stuck.set()
    rec.finish()
    rec.discard()


def test_a_write_error_is_the_recordings_error(tmp_path) -> None:
    rec = Recording("r4", tmp_path, cap_s=3600.0, frame_dt=DT)
    os.close(rec._file.fileno())  # the disk goes away under the spool
    for f in range(10_000):
        rec.append(1, track(f))
    rec.finish()
    assert rec.error is not None
    rec.discard()


def test_a_spool_that_could_not_be_made_is_discarded_without_an_error(tmp_path) -> None:
    # A data directory that is a file's child (unusable): no spool, the error says why,
    # and discarding it (as the server does after every round) raises nothing.
    (tmp_path / "a-file").write_text("not a directory")
    rec = Recording("r1", tmp_path / "a-file" / "spool", cap_s=10.0, frame_dt=0.001)
    assert rec.error is not None and rec.cut is not None
    rec.append(1, P.encode_track(1, 0.0, [0, 0, 0], [0, 0, 0], np.zeros((4, 3)),
                                 np.zeros((4, 3))))
    rec.finish()
    rec.discard()


def test_a_served_round_longer_than_the_cap_is_cut_and_marked(tmp_path) -> None:
    async def main() -> None:
        settings = RoomSettings(**{**FAST, "first_to": 99}, autoplay=True, record_cap_s=0.3)
        async with server(tmp_path, bots=4, settings=settings) as srv:
            rows: list = []
            for _ in range(600):
                rows[:] = (await http_json(srv, "/api/replays"))["replays"]
                if rows:
                    break
                await asyncio.sleep(0.1)
            assert rows, "no round saved"
            status, body, _ = await http_get(srv, f"/api/replays/{rows[0]['id']}")
            assert status == 200
            header, records = read_replay(body)
            # The round lasts longer (its tail alone is 1 s): recorded up to the cap.
            assert "cap" in header["cut"]
            assert header["duration_s"] <= 0.3 + 1e-9
            frames = [P.decode_binary(d).frame for k, d in records if k == 1]
            assert (max(frames) - min(frames)) * DT <= 0.3 + 1e-9
        # Nothing is left in the spool once the round is saved.
        spool = tmp_path / recorder.SPOOL_DIR
        assert not any(p.is_file() for p in spool.rglob("*.spool"))

    run(main())


def test_the_span_is_smallest_to_largest_frame_whatever_their_order(tmp_path) -> None:
    # A MESH encoded off the frame can be recorded after a newer TRACK.
    rec = Recording("r5", tmp_path, cap_s=3600.0, frame_dt=DT)
    order = [40, 33, 34, 35, 10, 36, 70, 66]
    for f in order:
        rec.append(1, track(f))
    rec.finish()
    sent = [(1, track(f)) for f in order]
    assert rec.duration_s == pytest.approx(recorded_length(DT, sent)) == pytest.approx(0.060)
    rec.discard()


def test_a_rounds_tail_keeps_none_of_the_next_rounds_events(tmp_path) -> None:
    """The countdown (0.2 s) is shorter than the recording's tail (1 s): the next round's
    countdown and start happen while the last round still records its tail, and belong to
    the next round's replay only."""
    async def main() -> None:
        settings = RoomSettings(**{**FAST, "first_to": 99}, autoplay=True)
        async with server(tmp_path, bots=4, settings=settings) as srv:
            rows: list = []
            for _ in range(900):
                rows[:] = (await http_json(srv, "/api/replays"))["replays"]
                if len(rows) >= 2:
                    break
                await asyncio.sleep(0.1)
            assert len(rows) >= 2, "fewer than two rounds saved"
            for row in rows:
                status, body, _ = await http_get(srv, f"/api/replays/{row['id']}")
                assert status == 200
                header, records = read_replay(body)
                events = [P.decode_json(d) for k, d in records if k == 0]
                kinds = [e["event"] for e in events]
                assert "score" in kinds, kinds
                rounds = {e["round"] for e in events if "round" in e}
                assert rounds == {header["round"]}, (header["round"], events)
                # Nothing of the next round after the score that ended this one.
                assert "countdown" not in kinds[kinds.index("score"):], kinds

    run(main(), timeout=150.0)
