"""MESH messages made in C++ by the native frame loop's service thread
(native/loop/mesh_msg.hpp, ``FrameLoop.take_encoded``: encoded without the GIL and written
into the mesh board) against the Python encoder (``protocol.encode_quantised_mesh``,
docs/protocol.md), in version 2 (its planes deflated as literals, a Huffman code a plane,
native/loop/huffman_deflate.hpp, or by libdeflate) and 1 (zlib's): the same header, body
and nodes; the compressed payload inflates (Python's zlib) to the Python encoder's payload
(deflaters' bytes differ, what they inflate to may not), and decodes to the quantised nodes
exactly, for random cloths, flat ones, stepped ones and large frame numbers; version-1
messages and a replay made before version 2 still decode; a live loop's meshes are the ones
on its board."""

from __future__ import annotations

import base64
import contextlib
import json
import zlib
from pathlib import Path

import numpy as np
import pytest
from clothball import _native
from clothball.game.sim.cloth import Cloth
from clothball.game.sim.scene import Scene
from clothball.game.wire import protocol as P
from clothball.game.wire.replay import read_replay
from clothball.server.sim import SimPool
from clothball.server.sim import worker as sim_worker
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.conftest import examples
from tests.server.conftest import run, started_room, until

HEAD = P.HEADER.size + P.MESH_BODY.size
MESH_V1 = Path(__file__).parent.parent / "data" / "mesh_v1.json"


def _python(positions, frame, server_time, ball, radius, hips, compress, version) -> bytes:
    q, lo, hi = P.quantise(positions)
    return P.encode_quantised_mesh(frame, server_time, q, lo, hi, ball, radius, hips,
                                   compress=compress, version=version)


def _same(ours: bytes, ref: bytes) -> bool:
    """Whether both chose the same coding (compressed or not); the nodes the same always."""
    flags, ref_flags = P.HEADER.unpack_from(ours)[2], P.HEADER.unpack_from(ref)[2]
    assert ours[:2] == ref[:2] and ours[4:HEAD] == ref[4:HEAD]  # all but the flags
    if flags == ref_flags:
        if flags & P.FLAG_ZLIB:
            assert zlib.decompress(ours[HEAD:]) == zlib.decompress(ref[HEAD:])
        else:
            assert ours[HEAD:] == ref[HEAD:]
    a, b = P.decode_mesh(ours), P.decode_mesh(ref)
    assert np.array_equal(a.positions, b.positions) and a.frame == b.frame
    return flags == ref_flags


@pytest.mark.parametrize(("version", "deflater"),
                         [(1, "auto"), (2, "auto"), (2, "literals"), (2, "libdeflate")])
@pytest.mark.parametrize("compress", [True, False])
def test_the_loops_mesh_is_the_python_encoders_for_random_cloths(compress: bool, version: int,
                                                                   deflater: str) -> None:
    rng = np.random.default_rng(33)
    same = 0
    for k in range(200):
        n = int(rng.choice([2, 3, 16, 48, 61]))
        scale = 10.0 ** rng.uniform(-4, 2)
        grid = np.stack(np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n)), -1)
        positions = np.concatenate([grid, np.zeros((n, n, 1))], -1) * scale
        positions += rng.normal(0.0, scale * 10.0 ** rng.uniform(-6, 0), (n, n, 3))
        if k % 9 == 0:
            positions[..., 1] = 0.75  # flat: a span of zero on y
        if k % 13 == 0:  # white noise: compression gains too little, the nodes go raw
            positions = rng.normal(0.0, 1.0, (n, n, 3))
        frame = int(rng.integers(0, 2**40)) if k % 2 else int(rng.integers(0, 2**20))
        ball = rng.normal(0.0, 1.0, 3)
        hips = rng.normal(0.0, 1.0, (4, 3))
        args = (positions, frame, float(rng.uniform(0, 1e6)), ball, float(rng.uniform(0, 1)),
                hips, compress, version)
        ours = _native.encode_mesh_msg(positions, frame, args[2], ball, args[4],
                                       hips.reshape(12), compress, version, deflater)
        assert ours[1] == version
        same += _same(ours, _python(*args))
    # Deflaters' sizes differ, so near the 90 % mark one may send the nodes raw where the
    # other compresses (tiny meshes, where a Huffman block's header weighs; noisy ones, where
    # a code a plane beats zlib's): the nodes are the same either way, checked above.
    assert same >= 150


@pytest.mark.parametrize("n", [16, 48, 61])
def test_a_stepped_cloths_mesh_decodes_to_its_quantised_nodes(n: int) -> None:
    """The game's cloth from its start (what the server sends): the C++ version-2 message
    decodes in Python to exactly the nodes ``protocol.quantise`` makes, compressed, and no
    larger than version 1's."""
    cloth = Cloth(Scene.load("default").with_changes({"cloth": {"n": n}}), "cpu", threads=1)
    hips = cloth.hips()
    for k in range(3):
        cloth.set_hips(hips + [0.02 * k, 0.03 * k, 0.0])
        cloth.step(150)
        p = np.asarray(cloth.positions(), dtype=np.float64)
        q, lo, hi = P.quantise(p)
        msgs = {(v, d): _native.encode_mesh_msg(p, k, 0.5, [0, 1, 0], 0.1, hips.reshape(12),
                                                True, v, d)
                for v, d in ((1, "auto"), (2, "literals"), (2, "libdeflate"))}
        for (v, _), msg in msgs.items():
            m = P.decode_mesh(msg)
            assert m.version == v and m.flags == P.FLAG_ZLIB | P.FLAG_DELTA
            assert np.array_equal(m.positions, P.dequantise(q, lo, hi))
            assert len(msg) <= len(msgs[(1, "auto")])


def test_version_1_meshes_and_an_old_replay_still_decode() -> None:
    """Golden bytes made by the encoder before version 2 (tests/data/mesh_v1.json): each
    decodes to the quantised nodes stored beside it, and the old replay's records too."""
    fixture = json.loads(MESH_V1.read_text())
    by_bytes = {}
    for v in fixture["messages"]:
        data = base64.b64decode(v["b64"])
        m = P.decode_mesh(data)
        assert m.version == 1 and m.flags == v["flags"]
        q = np.array(v["q"], dtype=np.uint16).reshape(m.positions.shape)
        assert np.array_equal(m.positions, P.dequantise(q, np.array(v["lo"]), np.array(v["hi"])))
        by_bytes[data] = m
    header, records = read_replay(base64.b64decode(fixture["replay_b64"]))
    assert header["protocol_version"] == 1
    meshes = [P.decode_binary(r) for _, r in records if r[0] == P.MESH]
    assert len(meshes) == 3 and all(isinstance(m, P.Mesh) and m.version == 1 for m in meshes)
    for (_, r), m in zip([x for x in records if x[1][0] == P.MESH], meshes, strict=True):
        assert np.array_equal(m.positions, by_bytes[r].positions)


def test_the_encoder_refuses_an_unknown_version() -> None:
    with pytest.raises(ValueError, match="version"):
        _native.encode_mesh_msg(np.zeros((4, 4, 3)), 0, 0.0, [0, 0, 0], 0.1, np.zeros(12),
                                True, 3)
    with pytest.raises(ValueError, match="version"):
        _native.time_mesh_encoder(np.zeros((1, 4, 4, 3)), 0)
    with pytest.raises(ValueError, match="deflater"):
        _native.encode_mesh_msg(np.zeros((4, 4, 3)), 0, 0.0, [0, 0, 0], 0.1, np.zeros(12),
                                True, 2, "zopfli")


def test_a_live_loops_meshes_are_on_its_board() -> None:
    """A running room's MESH from the service thread (``take_encoded``): what the room
    delivers is what the board's slot holds (when of the same frame), an n x n cloth with
    the scene's ball."""

    async def main() -> None:
        got: list[bytes] = []
        with started_room(deliver_mesh=got.append) as sim:
            w = sim.worker
            await until(lambda: len(got) >= 3, 10, "meshes")
            mesh = got[-1]
            assert w.board is not None
            frame, raw = _native.board_read(w.board, sim.slot * w.board_slot, w.board_slot, -1)
            m = P.decode_mesh(mesh)
            assert frame >= m.frame
            if frame == m.frame:
                assert raw == mesh
            assert m.positions.shape == (16, 16, 3)
            assert np.isfinite(m.positions).all()
            assert m.ball_radius == pytest.approx(sim.arena.ball_radius, rel=1e-6)

    run(main())


def test_a_board_too_small_for_the_meshes_is_refused() -> None:
    with started_room() as sim, pytest.raises(ValueError, match="board"):
        sim.worker.frame_loop.take_encoded(bytearray(64 * 4), 64, 0.1, True)


def test_meshes_encoded_on_several_threads_land_in_their_own_rooms_slots(monkeypatch) -> None:
    """MESH_THREADS threads share out the due rooms' meshes (native/loop/work_pool.hpp):
    each room's delivered MESH is the one in its own slot of the board (when of the same
    frame), for every room of one loop."""
    monkeypatch.setattr(sim_worker, "MESH_THREADS", 3)
    rooms = 6

    async def main() -> None:
        pool = SimPool(cpu_loops=1)  # (every room on one loop)
        got: list[list] = [[] for _ in range(rooms)]
        try:
            with contextlib.ExitStack() as stack:
                sims = [stack.enter_context(started_room(deliver_mesh=got[k].append, pool=pool))
                        for k in range(rooms)]
                w = sims[0].worker
                assert all(s.worker is w for s in sims) and w.encoders == 3
                await until(lambda: all(len(g) >= 3 for g in got), 20, "every room's meshes")
                # No pass while the board is read, and the meshes already taken delivered
                # by then: each room's newest delivered MESH is its slot's.
                w.frame_loop.lock()
                try:
                    # (the meshes taken before the lock are handed over by the service
                    # thread: waited for, however long a loaded machine takes)
                    def newest_delivered() -> bool:
                        return all(g and _native.board_read(
                            w.board, sim.slot * w.board_slot, w.board_slot, -1)[1] == g[-1]
                            for sim, g in zip(sims, got, strict=True))

                    await until(newest_delivered, 20, "each room's newest MESH delivered")
                    slots = set()
                    for sim, g in zip(sims, got, strict=True):
                        mesh = g[-1]
                        frame, raw = _native.board_read(w.board, sim.slot * w.board_slot,
                                                        w.board_slot, -1)
                        assert raw == mesh and P.decode_mesh(raw).frame == frame
                        assert P.decode_mesh(raw).positions.shape == (16, 16, 3)
                        slots.add(sim.slot)
                    assert len(slots) == rooms
                finally:
                    w.frame_loop.unlock()
        finally:
            pool.close()

    run(main())


def test_mesh_encoder_threads_out_of_range_are_refused() -> None:
    with started_room() as sim, pytest.raises(ValueError, match="threads"):
        sim.worker.frame_loop.take_encoded(None, 0, 0.1, True, 0)


def _fibonacci_bytes(symbols: int) -> bytes:
    """Byte i counted F(i) times: a Huffman code over them is `symbols` deep, past deflate's
    15 bits from 16 symbols on (the rebalanced lengths of huffman_deflate.hpp)."""
    a, b, out = 1, 1, bytearray()
    for s in range(symbols):
        out += bytes([s]) * a
        a, b = b, a + b
    return bytes(np.random.default_rng(symbols).permutation(np.frombuffer(out, np.uint8)))


@pytest.mark.parametrize("data", [b"", b"\0", b"\7" * 5000, bytes(range(256)) * 3,
                                  _fibonacci_bytes(12), _fibonacci_bytes(22)],
                         ids=["empty", "one", "one_value", "flat", "fib12", "fib22"])
@pytest.mark.parametrize("segments", [1, 6])
def test_the_literal_deflater_is_inflated_by_zlib(data: bytes, segments: int) -> None:
    """MESH version 2's deflater (native/loop/huffman_deflate.hpp) against zlib's inflater:
    empty and one-value blocks, every byte value, codes deeper than 15 bits."""
    z = _native.deflate_literals(data, segments, 2 * len(data) + 1024)
    assert z is not None and zlib.decompress(z) == data
    assert _native.deflate_literals(data, segments, 16) is None or len(data) < 4


@settings(max_examples=examples(200), deadline=None)
@given(st.binary(max_size=5000), st.integers(1, 8), st.integers(0, 255))
def test_the_literal_deflater_on_any_bytes(data: bytes, segments: int, skew: int) -> None:
    data = bytes(b if b > skew else 0 for b in data)  # from noise to mostly zeros
    z = _native.deflate_literals(data, segments, 2 * len(data) + 1024)
    assert z is not None and zlib.decompress(z) == data
    cap = len(z) - 1  # a room one byte short: refused, never overrun
    assert _native.deflate_literals(data, segments, cap) is None
