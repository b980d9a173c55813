"""CORNER messages made by the native frame loop (native/loop/corner_msg.hpp, written into
the block as it publishes a frame; the server only sends them) against the Python encoder
(``protocol.encode_corners``, docs/protocol.md): byte for byte, for random states and for a
live loop's own records."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from clothball import _native
from clothball.game.wire import protocol as P
from clothball.server.sim import RoomSim, SimPool
from clothball.server.sim import worker as sim_worker

from tests.server.conftest import TINY


def _python(frame, server_time, pos, vel, force, k, ball, seq, time):
    return P.encode_corners(frame, server_time, pos.tolist(), vel.tolist(), force.tolist(), k,
                            ball[:3].tolist(), ball[3:].tolist(),
                            [(int(q), float(t)) for q, t in zip(seq, time, strict=True)])


def _native_msgs(frame, server_time, pos, vel, force, k, ball, seq, time):
    return _native.encode_corners(frame, server_time, pos, vel, force, k, ball,
                                  [int(q) for q in seq], [float(t) for t in time])


def test_the_loops_corner_bytes_are_the_python_encoders_for_random_states() -> None:
    rng = np.random.default_rng(32)
    for k in range(3000):
        scale = 10.0 ** rng.uniform(-6, 6)
        pos, vel, force = (rng.normal(0.0, scale, (4, 3)) for _ in range(3))
        ball = rng.normal(0.0, scale, 6)
        frame = int(rng.integers(0, 2**40)) if k % 3 else int(rng.integers(0, 2**33))
        seq = rng.integers(0, 2**63, 4, dtype=np.uint64) if k % 2 else \
            rng.integers(0, 2**32, 4, dtype=np.uint64)
        time = rng.normal(0.0, 1e3, 4)
        if k % 7 == 0:
            time[k % 4] = math.nan  # a seat with no HIP applied
        if k % 11 == 0:  # non-finite floats pack as they are (float32 inf/nan)
            vel[k % 4, k % 3] = math.inf
            ball[k % 6] = -math.inf
        stiffness = float(rng.uniform(0.0, 5e4))
        server_time = float(rng.uniform(0.0, 1e6))
        args = (frame, server_time, pos, vel, force, stiffness, ball, seq, time)
        ours, ref = _native_msgs(*args), _python(*args)
        # NaN payloads may differ between encoders only in bits nobody reads: compare the
        # messages with NaN as NaN.
        for a, b in zip(ours, ref, strict=True):
            assert len(a) == P.CORNER_SIZE
            if a != b:
                fa = struct.unpack(P.CORNER_MSG.format, a)
                fb = struct.unpack(P.CORNER_MSG.format, b)
                same = [x == y or (x != x and y != y) for x, y in zip(fa, fb, strict=True)]
                assert all(same), (k, fa, fb)
            assert P.decode_corner(a).frame == frame


def test_a_live_loops_corner_bytes_encode_its_own_record() -> None:
    """The block's corner_msg of a running room is what the Python encoder makes of the
    same record's fields (read in one consistent copy)."""
    pool = SimPool()
    try:
        sim = RoomSim(TINY, "cpu", pool=pool)
        sim.start()
        sim.set_hip(1, (float(sim.arena.anchors[1][0]), float(sim.arena.anchors[1][1]) + 0.01,
                        float(sim.arena.anchors[1][2])), 77, 1.5)
        worker = sim.worker
        dtype = sim_worker._dtype([f for f in sim_worker.LAYOUT["room"]
                                   if f[1] < sim_worker.LAYOUT["room_out_bytes"]],
                                  sim_worker.LAYOUT["room_out_bytes"])
        seen = 0
        while seen < 20:
            rec = np.frombuffer(worker.frame_loop.read_room(sim.slot), dtype=dtype)[0]
            if rec["frame"] == 0:
                continue
            seen += 1
            applied = list(zip(rec["applied_seq"].tolist(), rec["applied_time"].tolist(),
                               strict=True))
            ref = P.encode_corners(int(rec["frame"]), float(rec["server_time"]),
                                   rec["corner_pos"].tolist(), rec["corner_vel"].tolist(),
                                   rec["force"].tolist(), sim.arena.stiffness,
                                   rec["ball"][:3].tolist(), rec["ball"][3:].tolist(), applied)
            got = [bytes(rec["corner_msg"][s]) for s in range(4)]
            assert got == ref
        assert P.decode_corner(got[1]).hip_seq == 77
        sim.stop()
    finally:
        pool.close()


@pytest.mark.parametrize("n", [3, 13])
def test_wrong_sizes_are_refused(n: int) -> None:
    with pytest.raises(ValueError, match="positions"):
        _native.encode_corners(1, 0.0, np.zeros(n), np.zeros(12), np.zeros(12), 1.0,
                               np.zeros(6), [0] * 4, [0.0] * 4)


def test_a_corners_position_is_its_hands_grip_point_which_the_same_frames_mesh_gives() -> None:
    """docs/protocol.md, CORNER: the position is the point the seat's hand holds, its grip's
    nodes less their rest offsets weighted by their shares (``oracle.grip_points``), not the
    corner node (the default scene's hands hold a 1 cm grip): from the engine's own nodes of
    the same frame to float32 rounding, and from the same frame's MESH nodes to within the
    MESH's quantisation (its box / 65535 an axis) and float32 rounding."""
    import time

    from clothball import _native
    from clothball.game.sim.oracle import grip_points
    from clothball.game.sim.scene import Scene

    scene = Scene.load("default").with_changes({"cloth": {"n": 16}})
    assert scene["coupling"]["grip_radius"] > 0
    pool = SimPool()
    sim = RoomSim(scene, "cpu", pool=pool)
    try:
        sim.start()
        w = sim.worker
        sim.set_hip(2, sim.arena.anchors[2] + [0.0, 0.06, 0.02], 5, 1.0)  # a hand that pulls
        matched = 0
        end = time.monotonic() + 60
        while matched < 3 and time.monotonic() < end:
            w.frame_loop.lock()  # between two passes: the record and the nodes of one frame
            try:
                frame = int(w.rooms_view["frame"][sim.slot])
                nodes = w.batch.positions(sim.slot)
                msgs = [bytes(w.rooms_view["corner_msg"][sim.slot][s]) for s in range(4)]
                mesh_frame, raw = _native.board_read(w.board, sim.slot * w.board_slot,
                                                     w.board_slot, -1)
            finally:
                w.frame_loop.unlock()
            if frame < 200:
                time.sleep(0.01)
                continue
            held = grip_points(scene, nodes)
            got = np.array([P.decode_corner(m).position for m in msgs])
            scale = np.abs(held).max()
            assert np.abs(got - held).max() <= 4 * np.finfo(np.float32).eps * scale
            # the corner node itself is another point (the grip's deformation)
            ends = nodes[[0, 0, -1, -1], [0, -1, -1, 0]]
            assert np.abs(ends - held).max() > 1e-5
            if raw is not None and mesh_frame == frame:
                m = P.decode_mesh(raw)
                step = (m.hi - m.lo) / 65535.0
                bound = step + 4 * np.finfo(np.float32).eps * scale
                assert np.all(np.abs(grip_points(scene, m.positions) - got) <= bound)
                matched += 1
            time.sleep(0.001)
        assert matched == 3, "no MESH of the frame the record held"
    finally:
        sim.stop()
        pool.close()
