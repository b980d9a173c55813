"""Falcon packet codec: golden vectors, round trips, the re-synchronising reader."""

from __future__ import annotations

import pytest
from clothball._native import falcon as f
from hypothesis import given
from hypothesis import strategies as st

int16 = st.integers(-32768, 32767)


def dec_cmd(pkt: bytes) -> tuple[tuple[int, ...], int] | None:
    d = f.decode_command(pkt)
    return None if d is None else (tuple(d[0]), d[1])


def dec_rep(pkt: bytes) -> tuple[tuple[int, ...], int, int] | None:
    d = f.decode_report(pkt)
    return None if d is None else (tuple(d[0]), d[1], d[2])


def nibbles_low_first(v: int) -> list[int]:
    u = v & 0xFFFF
    return [(u >> (4 * i)) & 0xF for i in range(4)]


def test_golden_vector_motor_4095_in_field_0() -> None:
    pkt = f.encode_command((4095, 0, 0), 0)
    # FALCON.md: host packet bytes 3c 50 50 50 41 ... carry 4095 in the first field.
    assert pkt[:5] == bytes([0x3C, 0x50, 0x50, 0x50, 0x41])
    assert pkt[5:15] == bytes([0x41] * 10)
    assert pkt[15] == 0x3E
    assert dec_cmd(pkt) == ((4095, 0, 0), 0)


def test_command_layout_matches_the_spec() -> None:
    motors, flags = (-1, 1234, -4096), f.FLAG_HOMING | f.FLAG_RED
    pkt = f.encode_command(motors, flags)
    want = [0x3C]
    for m in motors:
        want += [0x41 + n for n in nibbles_low_first(m)]
    want += [0x41 + flags, 0x41, 0x3E]
    assert list(pkt) == want
    assert list(pkt[1:5]) == [0x50, 0x50, 0x50, 0x50]  # -1 = 0xFFFF


def test_report_layout_buttons_and_homed_bits() -> None:
    enc, buttons, homed = (100, -200, 32767), f.BUTTON_CENTRE | f.BUTTON_MINUS, 0b101
    pkt = f.encode_report(enc, buttons, homed)
    assert pkt[13] - 0x41 == buttons | (homed << 4)
    assert dec_rep(pkt) == (enc, buttons, homed)


@given(st.tuples(int16, int16, int16), st.integers(0, 15))
def test_command_round_trip(motors: tuple[int, int, int], flags: int) -> None:
    pkt = f.encode_command(motors, flags)
    assert len(pkt) == 16 and pkt[0] == 0x3C and pkt[15] == 0x3E
    assert all(0x41 <= b <= 0x50 for b in pkt[1:15])
    assert dec_cmd(pkt) == (motors, flags)


@given(st.tuples(int16, int16, int16), st.integers(0, 15), st.integers(0, 7))
def test_report_round_trip(enc: tuple[int, int, int], buttons: int, homed: int) -> None:
    assert dec_rep(f.encode_report(enc, buttons, homed)) == (enc, buttons, homed)


def test_decode_rejects_bad_bytes() -> None:
    good = bytearray(f.encode_report((1, 2, 3)))
    bad = bytearray(good)
    bad[3] = 0x30  # below the nibble base
    assert f.decode_report(bytes(bad)) is None
    bad = bytearray(good)
    bad[15] = 0x00
    assert f.decode_report(bytes(bad)) is None
    with pytest.raises(ValueError):
        f.decode_report(b"<>")


def _drain(reader: f.PacketReader) -> list[bytes]:
    out = []
    while (p := reader.next()) is not None:
        out.append(p)
    return out


def test_reader_keeps_a_partial_tail_between_reads() -> None:
    a, b = f.encode_report((1, 2, 3)), f.encode_report((4, 5, 6), 1, 7)
    stream = a + b
    r = f.PacketReader()
    got: list[bytes] = []
    pieces = [stream[:5], stream[5:11], stream[11:20], stream[20:]]
    for piece in pieces:
        r.feed(piece)
        got += _drain(r)
        assert r.pending < 16
    assert got == [a, b]
    assert r.dropped_bytes == 0


def test_reader_resyncs_on_delimiters() -> None:
    a, b, c = (f.encode_report((i, -i, 2 * i)) for i in (7, 8, 9))
    noise1 = bytes([0x00, 0x13, 0x3E])  # junk with a stray '>'
    cut = a[:9]  # a packet cut off by a new '<'
    noise2 = bytes([0x3E, 0x3E])
    stream = noise1 + a + cut + b + noise2 + c[:4]
    r = f.PacketReader()
    got: list[bytes] = []
    for i in range(0, len(stream), 3):  # feed in 3-byte pieces
        r.feed(stream[i : i + 3])
        got += _drain(r)
    assert got == [a, b]
    assert r.pending == 4  # the start of c waits for the rest
    r.feed(c[4:])
    assert _drain(r) == [c]
    assert r.dropped_bytes == len(noise1) + len(cut) + len(noise2)


def test_reader_drops_an_overlong_frame() -> None:
    r = f.PacketReader()
    junk = b"<" + bytes([0x41] * 20)  # no delimiter for too long
    good = f.encode_report((3, 2, 1))
    r.feed(junk + good)
    assert _drain(r) == [good]


def test_strip_ftdi_status_every_64_bytes() -> None:
    payload = bytes(range(200))
    raw = b""
    rest = payload
    while rest:
        raw += b"\x31\x60" + rest[:62]
        rest = rest[62:]
    assert f.strip_ftdi_status(raw, 64) == payload
    assert f.strip_ftdi_status(b"\x31\x60", 64) == b""
