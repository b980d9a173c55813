"""The lanes as the engine's own port serves them: the native pump (native/net/pump.hpp)
reading a real frame loop's memory in place (``server.lanes.local.LocalLink``,
``Pump.set_local_maps``): a CORNER made from a former occupant's hand is never sent to the
seat's new occupant, whatever the timing."""

from __future__ import annotations

import json
import math
import socket
import time

from clothball import _native
from clothball.game.wire import protocol as P
from clothball.server.lanes.local import LocalLink

from tests.server.conftest import run, started_room, until
from tests.server.test_pump import HEAD, recv_exactly, text


def corners_in(data: bytes) -> tuple[list[P.Corner], bytes]:
    """The CORNER messages in ``data`` (a server's unmasked binary frames), and the rest."""
    out: list[P.Corner] = []
    while len(data) >= 2 and data[0] == 0x82 and data[1] < 126 and len(data) >= 2 + data[1]:
        out.append(P.decode_corner(data[2:2 + data[1]]))
        data = data[2 + data[1]:]
    return out, data


def test_a_corner_of_the_former_occupants_hand_is_not_sent_to_the_new_one() -> None:
    """Seat 2's hand is its occupant's (seq 41) in the newest frame; the seat changes hands
    while the frame loop is held between two passes, and the new occupant's lane opens then:
    the newest CORNER (the former occupant's HIP echoed) is not sent; once the loop steps
    on, the new occupant's CORNERs come, echoing no HIP."""
    async def main() -> None:
        with started_room() as sim:
            w = sim.worker
            pump = _native.Pump()
            link = LocalLink(sim.pool.local_shares, sim.pool.set_wake)
            link.attach(pump)
            link.start()
            link.want_block(w.block_id)  # (what the pump would ask for: its "block" event)
            client, c_pump = socket.socketpair()
            engine, e_pump = socket.socketpair()
            try:
                conn = pump.add(c_pump.detach(), e_pump.detach(), b"", False)
                joined = text(P.encode_json({"type": "joined", "room": "r"}).encode())
                engine.sendall(HEAD + joined)
                assert recv_exactly(client, len(HEAD + joined)) == HEAD + joined
                view = _native.BlockView(w.frame_loop.block())
                slot, seat = sim.slot, 2
                old = sim.occupant[seat]
                assert view.write_hip(slot, seat, old, *sim.arena.anchors[seat], 41, 3.5)
                await until(lambda: view.read_corner(slot, seat)[2] == old and
                            P.decode_corner(view.read_corner(slot, seat)[1]).hip_seq == 41,
                            10, "the former occupant's HIP echoed")
                w.frame_loop.lock()  # no pass until released
                try:
                    sim.set_hip(seat, None)  # the seat changes hands
                    new = sim.occupant[seat]
                    assert new != old
                    place = sim.lane_place(seat)
                    pump.open_lane(conn, json.dumps("r"), w.block_id, slot, seat, new,
                                   (-9.0,) * 3, (9.0,) * 3, 1 / 120, 1000.0, 1000.0, -1,
                                   place["board_slot"])
                    time.sleep(0.1)  # its timer looks several times meanwhile
                    client.setblocking(False)
                    try:
                        early = client.recv(1 << 16)
                    except BlockingIOError:
                        early = b""
                    assert early == b"", P.decode_corner(early[2:])
                finally:
                    w.frame_loop.unlock()
                got = b""
                client.settimeout(10)
                sent: list[P.Corner] = []
                end = time.monotonic() + 10
                while len(sent) < 3 and time.monotonic() < end:
                    got += client.recv(1 << 16)
                    more, got = corners_in(got)
                    sent += more
                assert len(sent) >= 3, "the new occupant's CORNERs"
                assert all(c.hip_seq == 0 and math.isnan(c.hip_time) for c in sent)
                assert pump.messages_out >= 3
            finally:
                pump.stop()
                await link.stop()
                client.close()
                engine.close()

    run(main())
