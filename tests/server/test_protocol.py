"""The wire codec: round trips (property tests), quantisation error, and refusals."""

from __future__ import annotations

import json
import math
import struct
import zlib

import numpy as np
import pytest
from clothball.game.wire import protocol as P
from clothball.game.wire.replay import ReplayError, read_replay, write_replay
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from tests.conftest import examples

f32 = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False, width=32)
vec3 = st.tuples(f32, f32, f32)
u32 = st.integers(0, 2**32 - 1)
times = st.floats(0.0, 1e7, allow_nan=False)


@given(vec3, u32, times)
def test_hip_round_trip(pos, seq, t) -> None:
    data = P.encode_hip(pos, seq, t)
    assert len(data) == P.HIP_SIZE
    hip = P.decode_hip(data)
    assert hip.position == pos and hip.seq == seq and hip.time == t


@given(
    st.integers(0, 2**62), st.integers(0, 3), vec3, vec3, vec3, f32, vec3, vec3, u32,
    st.one_of(times, st.just(math.nan)), times,
)
def test_corner_round_trip(frame, seat, p, v, f, k, bp, bv, seq, ht, t) -> None:
    c = P.decode_corner(P.encode_corner(frame, seat, p, v, f, k, bp, bv, seq, ht, t))
    assert c.frame == frame and c.seat == seat and c.hip_seq == seq and c.server_time == t
    assert tuple(c.position) == p and tuple(c.velocity) == v and tuple(c.force) == f
    assert c.stiffness == k and tuple(c.ball_position) == bp and tuple(c.ball_velocity) == bv
    assert c.hip_time == ht or (math.isnan(ht) and math.isnan(c.hip_time))


@settings(max_examples=examples(60), deadline=None)
@given(
    st.integers(2, 24).flatmap(
        lambda n: hnp.arrays(np.float64, (n, n, 3), elements=st.floats(-50, 50, width=32))
    ),
    st.booleans(),
    st.integers(0, 2**40),
)
def test_mesh_round_trip_within_quantisation_error(pos, compress, frame) -> None:
    hips = np.arange(12.0).reshape(4, 3)
    data = P.encode_mesh(frame, 1.5, pos, (0.1, 0.2, 0.3), 0.08, hips, compress=compress)
    m = P.decode_mesh(data)
    assert m.frame == frame and m.server_time == 1.5 and m.ball_radius == pytest.approx(0.08)
    assert np.allclose(m.hips, hips)
    span = pos.reshape(-1, 3).max(0) - pos.reshape(-1, 3).min(0)
    # half a quantisation step, plus float32 rounding of the box corners
    tol = span / P.QMAX / 2 + 1e-5 * (1 + np.abs(pos).max())
    assert np.all(np.abs(m.positions - pos) <= tol + 1e-12)


def test_mesh_compresses_a_smooth_cloth_and_flags_it() -> None:
    n = 64
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    pos = np.stack([j / (n - 1) - 0.5, 1 - 0.1 * np.sin(i / 9) * np.cos(j / 7),
                    i / (n - 1) - 0.5], axis=-1)
    plain = P.encode_mesh(1, 0.0, pos, (0, 0, 0), 0.1, np.zeros((4, 3)), compress=False)
    packed = P.encode_mesh(1, 0.0, pos, (0, 0, 0), 0.1, np.zeros((4, 3)), compress=True)
    assert P.decode_header(plain).flags == 0
    assert P.decode_header(packed).flags == P.FLAG_ZLIB | P.FLAG_DELTA
    assert len(packed) < 0.9 * len(plain)
    assert np.allclose(P.decode_mesh(packed).positions, P.decode_mesh(plain).positions)


def test_mesh_of_a_flat_cloth_has_a_zero_span_axis() -> None:
    pos = np.zeros((4, 4, 3))
    pos[..., 0] = np.arange(4)[None, :]
    m = P.decode_mesh(P.encode_mesh(0, 0.0, pos, (0, 0, 0), 0.1, np.zeros((4, 3))))
    assert np.allclose(m.positions, pos)


@settings(max_examples=examples(40), deadline=None)
@given(
    st.integers(2, 24).flatmap(
        lambda n: hnp.arrays(np.float64, (n, n, 3), elements=st.floats(-50, 50, width=32))
    ),
    st.booleans(),
)
def test_mesh_versions_1_and_2_carry_the_same_quantised_nodes(pos, compress) -> None:
    q, lo, hi = P.quantise(pos)
    for version in (1, 2):
        m = P.decode_mesh(P.encode_quantised_mesh(9, 0.5, q, lo, hi, (0, 0, 0), 0.1,
                                                  np.zeros((4, 3)), compress, version=version))
        assert m.version == version
        assert np.array_equal(m.positions, P.dequantise(q, lo, hi))


def _mesh_seeds() -> list[bytes]:
    """A smooth cloth's MESH in each version, compressed and not."""
    u = np.linspace(-0.5, 0.5, 12)
    x, z = np.meshgrid(u, u)
    pos = np.stack([x, 1.0 + 0.05 * np.sin(3 * x) * np.cos(2 * z), z], axis=-1)
    q, lo, hi = P.quantise(pos)
    return [P.encode_quantised_mesh(3, 0.1, q, lo, hi, (0, 1, 0), 0.1, np.zeros((4, 3)),
                                    compress, version=version)
            for version in (1, 2) for compress in (True, False)]


MESH_SEEDS = _mesh_seeds()


@settings(max_examples=examples(300), deadline=None)
@given(st.sampled_from(range(len(MESH_SEEDS))),
       st.lists(st.tuples(st.integers(0, 4000), st.integers(0, 255)), max_size=6),
       st.one_of(st.none(), st.integers(0, 4000)))
def test_damaged_meshes_decode_or_are_refused_with_a_code(k, flips, cut) -> None:
    """Any byte of either version's MESH changed (version and flags included), or the
    message cut short: it decodes to finite nodes or is refused with a documented code,
    never another exception."""
    data = bytearray(MESH_SEEDS[k])
    for at, value in flips:
        data[at % len(data)] = value
    if cut is not None:
        data = data[:cut]
    try:
        m = P.decode_mesh(bytes(data))
    except P.ProtocolError as e:
        assert e.code in P.ERROR_CODES and str(e)
    else:
        assert m.version in (1, 2) and m.positions.shape[2] == 3


def test_a_mesh_of_an_unknown_version_is_refused_naming_the_versions_read() -> None:
    for v in (0, 3, 255):
        bad = MESH_SEEDS[2][:1] + bytes([v]) + MESH_SEEDS[2][2:]
        with pytest.raises(P.ProtocolError,
                           match=f"MESH message version {v}; this side reads 1, 2"):
            P.decode_mesh(bad)
    hip = P.encode_hip([0, 0, 0], 1, 0.0)
    with pytest.raises(P.ProtocolError, match="HIP message version 2; this side reads 1"):
        P.decode_hip(hip[:1] + bytes([2]) + hip[2:])


@given(st.integers(0, 2**40), times, vec3, vec3)
def test_track_round_trip(frame, t, bp, bv) -> None:
    hips, corners = np.arange(12.0).reshape(4, 3), -np.arange(12.0).reshape(4, 3)
    tr = P.decode_track(P.encode_track(frame, t, bp, bv, hips, corners))
    assert tr.frame == frame and tr.server_time == t and tuple(tr.ball_position) == bp
    assert np.array_equal(tr.hips, hips) and np.array_equal(tr.corners, corners)


@given(st.binary(max_size=200))
def test_random_bytes_never_crash_the_decoders(data: bytes) -> None:
    for decode in (P.decode_hip, P.decode_corner, P.decode_mesh, P.decode_track,
                   P.decode_binary):
        try:
            decode(data)
        except P.ProtocolError as e:
            assert e.code in P.ERROR_CODES


@given(st.text(max_size=300))
def test_random_text_never_crashes_the_json_decoder(text: str) -> None:
    try:
        msg = P.decode_json(text)
    except P.ProtocolError as e:
        assert e.code in P.ERROR_CODES
    else:
        assert isinstance(msg, dict) and isinstance(msg["type"], str)


@given(st.dictionaries(st.text(max_size=8), st.one_of(st.integers(), st.text(max_size=8),
                                                      st.booleans(), st.none()), max_size=5))
def test_json_round_trip(fields) -> None:
    msg = {**fields, "type": "x"}
    assert P.decode_json(P.encode_json(msg)) == msg


@pytest.mark.parametrize(
    ("data", "code", "text"),
    [
        (b"", "bad_binary", "HIP message must be 28 bytes"),
        (P.encode_hip((0, 0, 0), 1, 0.0)[:-1], "bad_binary", "28 bytes"),
        (P.encode_hip((0, 0, 0), 1, 0.0) + b"x", "bad_binary", "28 bytes"),
        (P.encode_hip((math.nan, 0, 0), 1, 0.0), "bad_binary", "finite"),
        (P.encode_hip((0, math.inf, 0), 1, 0.0), "bad_binary", "finite"),
        (P.encode_hip((0, 0, 0), 1, math.nan), "bad_binary", "time must be finite"),
        (b"\x09" + P.encode_hip((0, 0, 0), 1, 0.0)[1:], "bad_binary", "unknown binary"),
        (b"\x01\x07" + P.encode_hip((0, 0, 0), 1, 0.0)[2:], "bad_version", "version 7"),
        (b"\x02" + P.encode_hip((0, 0, 0), 1, 0.0)[1:], "bad_binary", "expected a HIP"),
    ],
)
def test_bad_hip_is_refused_with_a_clear_error(data, code, text) -> None:
    with pytest.raises(P.ProtocolError, match=text) as e:
        P.decode_hip(data)
    assert e.value.code == code


def test_bad_mesh_is_refused() -> None:
    good = P.encode_mesh(3, 0.0, np.zeros((4, 4, 3)), (0, 0, 0), 0.1, np.zeros((4, 3)),
                         compress=False)
    with pytest.raises(P.ProtocolError, match="payload"):
        P.decode_mesh(good[:-2])
    bad_n = bytearray(good)
    struct.pack_into("<H", bad_n, P.HEADER.size + 8, 5000)
    with pytest.raises(P.ProtocolError, match="n must be"):
        P.decode_mesh(bytes(bad_n))
    zipped = bytearray(good)
    struct.pack_into("<H", zipped, 2, P.FLAG_ZLIB)
    with pytest.raises(P.ProtocolError, match="zlib"):
        P.decode_mesh(bytes(zipped))
    # a zlib bomb is cut off at the expected size
    bomb = bytes(good[: P.HEADER.size + P.MESH_BODY.size]) + zlib.compress(b"\0" * 10**6)
    bomb = bytearray(bomb)
    struct.pack_into("<H", bomb, 2, P.FLAG_ZLIB)
    with pytest.raises(P.ProtocolError, match="payload"):
        P.decode_mesh(bytes(bomb))


@pytest.mark.parametrize(
    ("text", "code"),
    [
        ("{", "bad_json"),
        ("[1, 2]", "bad_json"),
        ('"hello"', "bad_json"),
        ('{"type": 5}', "bad_message"),
        ('{"no_type": 1}', "bad_message"),
        ('{"type": "x", "v": NaN}', "bad_json"),
        ('{"type": "x", "v": Infinity}', "bad_json"),
        ("[" * 100000 + "]" * 100000, "too_big"),
        ('{"type": "' + "x" * 5000 + '"}', "too_big"),
        (b"\xff\xfe{}", "bad_json"),
    ],
)
def test_bad_json_is_refused(text, code) -> None:
    with pytest.raises(P.ProtocolError) as e:
        P.decode_json(text)
    assert e.value.code == code


def test_deeply_nested_json_within_the_size_limit_is_refused_cleanly() -> None:
    with pytest.raises(P.ProtocolError) as e:
        P.decode_json('{"type": "x", "a": ' + "[" * 2000 + "]" * 2000 + "}", limit=10**6)
    assert e.value.code == "bad_json"
    # the bound, whatever the Python's parser allows: 32 levels pass, 33 do not
    ok = '{"type": "x", "a": ' + "[" * 31 + "]" * 31 + "}"
    assert P.decode_json(ok)["type"] == "x"
    with pytest.raises(P.ProtocolError, match="nested deeper than 32"):
        P.decode_json('{"type": "x", "a": ' + "[" * 32 + "]" * 32 + "}")


def test_field_checks() -> None:
    msg = {"type": "t", "s": "ok", "i": 3, "f": 0.5, "b": True, "nan": math.nan, "big": 10**9,
           "ctl": "a\nb", "long": "x" * 100, "bool_as_int": True}
    assert P.field_str(msg, "s") == "ok"
    assert P.field_int(msg, "i", None, 0, 5) == 3
    assert P.field_float(msg, "f", None, 0, 1) == 0.5
    assert P.field_bool(msg, "b", False) is True
    assert P.field_int(msg, "missing", 7, 0, 9) == 7
    for call in (
        lambda: P.field_float(msg, "nan", None, -1, 1),
        lambda: P.field_int(msg, "big", None, 0, 5),
        lambda: P.field_int(msg, "bool_as_int", None, 0, 5),
        lambda: P.field_str(msg, "ctl"),
        lambda: P.field_str(msg, "long"),
        lambda: P.field_str(msg, "i"),
        lambda: P.field_bool(msg, "i", False),
        lambda: P.field_int(msg, "missing", None, 0, 1, required=True),
    ):
        with pytest.raises(P.ProtocolError) as e:
            call()
        assert e.value.code == "bad_message"


def test_error_message_shape() -> None:
    e = P.ProtocolError("bad_seat", "seat 9 is not a seat")
    assert e.to_message(re=4) == {"type": "error", "code": "bad_seat",
                                  "message": "seat 9 is not a seat", "re": 4}
    assert json.loads(P.encode_json(e.to_message()))["code"] == "bad_seat"
    with pytest.raises(ValueError):
        P.encode_json({"type": "x", "v": math.nan})


def test_replay_file_round_trip(tmp_path) -> None:
    mesh = P.encode_mesh(5, 0.1, np.zeros((3, 3, 3)), (0, 0, 0), 0.1, np.zeros((4, 3)))
    event = P.encode_json({"type": "event", "event": "score"}).encode()
    header = {"id": "abcdefgh12", "round": 1}
    path = tmp_path / "r.cbr"
    write_replay(path, header, [(1, mesh), (0, event)])
    assert not (tmp_path / "r.cbr.tmp").exists()
    h, records = read_replay(path.read_bytes())
    assert h == header and records == [(1, mesh), (0, event)]
    with pytest.raises(ReplayError):
        read_replay(b"not gzip")
    import gzip

    with pytest.raises(ReplayError, match="magic"):
        read_replay(gzip.compress(b"something else entirely"))
    whole = gzip.decompress(path.read_bytes())
    with pytest.raises(ReplayError, match="truncated"):
        read_replay(gzip.compress(whole[:-3]))


def test_tracks_are_the_documented_bytes_one_by_one_or_in_a_batch() -> None:
    """``encode_tracks`` against the doc's layout packed field by field with ``struct``
    (the header <BBHId, the body <q3f3f12f12f), for a batch and each row alone."""
    import struct
    rng = np.random.default_rng(7)
    rows = rng.normal(size=(9, 32))
    rows[:, 0] = rng.integers(0, 2**40, size=9)  # frames past 2^32: seq wraps
    rows[:, 1] = np.abs(rows[:, 1]) * 100
    want = b"".join(
        struct.pack("<BBHId", P.TRACK, P.PROTOCOL_VERSION, 0, int(r[0]) & 0xFFFFFFFF, r[1])
        + struct.pack("<q3f3f12f12f", int(r[0]), *r[2:32]) for r in rows)
    assert P.encode_tracks(rows) == want
    assert b"".join(P.encode_track(int(r[0]), r[1], r[2:5], r[5:8], r[8:20].reshape(4, 3),
                                   r[20:32].reshape(4, 3)) for r in rows) == want
    assert P.TRACK_RECORD.itemsize == P.TRACK_SIZE
