"""The wire protocol: the one codec shared by the server and every client.

``docs/protocol.md`` documents every message. In short: JSON text frames carry control
messages (``{"type": ...}``), binary frames carry the hot streams, each with the same
16-byte little-endian header::

    offset 0  u8   type     HIP=1, CORNER=2, MESH=3, TRACK=4
    offset 1  u8   version  the message's format: 1, MESH 2 (MESH 1 still read)
    offset 2  u16  flags    MESH: bit 0 zlib payload, bit 1 row-delta payload
    offset 4  u32  seq      sender's sequence number (CORNER/MESH/TRACK: frame mod 2^32)
    offset 8  f64  time     sender's clock, seconds (server: since the server started)

Every decoder validates what it reads and raises ``ProtocolError`` (with a stable
``code`` and a human message) rather than return something half-formed.
"""

from __future__ import annotations

import json
import math
import struct
import unicodedata
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

PROTOCOL_VERSION = 1

HIP, CORNER, MESH, TRACK = 1, 2, 3, 4
BINARY_TYPES = {HIP: "HIP", CORNER: "CORNER", MESH: "MESH", TRACK: "TRACK"}

FLAG_ZLIB = 1
FLAG_DELTA = 2
# The header flags each type may set: MESH's payload coding; every other type sends 0.
KNOWN_FLAGS = {HIP: 0, CORNER: 0, MESH: FLAG_ZLIB | FLAG_DELTA, TRACK: 0}
# Each binary type's format version, in its header's version byte: a type's number changes
# when its layout does. MESH 2 lays its payload out in byte planes (docs/protocol.md,
# "MESH"); MESH 1 (interleaved uint16) is still read: old replays hold it.
# HIP, CORNER and TRACK are at PROTOCOL_VERSION (hello's); MESH at MESH_VERSION.
MESH_VERSION = 2
READ_VERSIONS = {HIP: (1,), CORNER: (1,), MESH: (1, 2), TRACK: (1,)}

HEADER = struct.Struct("<BBHId")
HIP_BODY = struct.Struct("<3f")
# frame, seat, pad, pos, vel, force, K, ball pos, ball vel, hip seq echo, hip time echo
CORNER_BODY = struct.Struct("<qB3x3f3f3ff3f3fId")
# frame, n, pad, bbox lo, bbox hi, ball pos, ball radius, hips (4x3)
MESH_BODY = struct.Struct("<qH2x3f3f3ff12f")
# frame, ball pos, ball vel, hips (4x3), corners (4x3)
TRACK_BODY = struct.Struct("<q3f3f12f12f")

HIP_SIZE = HEADER.size + HIP_BODY.size
CORNER_SIZE = HEADER.size + CORNER_BODY.size
TRACK_SIZE = HEADER.size + TRACK_BODY.size

MAX_JSON_BYTES = 4096  # largest control message a client may send
MAX_MESSAGE_BYTES = 65536  # anything larger closes the connection (websocket max_size)
MAX_MESH_N = 1024
QMAX = 65535

# Error codes sent in {"type": "error", "code": ...}.
ERROR_CODES = (
    "bad_json",  # not JSON, not an object, or not UTF-8
    "bad_message",  # a field missing, of the wrong type, non-finite or out of range
    "bad_binary",  # a binary frame of the wrong size, type or content
    "out_of_range",  # a HIP outside the seat's reach box
    "bad_version",  # protocol version not supported
    "unknown_type",  # no such message type
    "too_big",  # message larger than allowed
    "rate_limited",  # messages too frequent; the extra ones are dropped
    "not_allowed",  # this role or state cannot send that
    "unknown_room",
    "bad_seat",  # no such seat or not free
    "bad_code",  # private room join code wrong or missing
    "bad_token",  # reconnect token unknown or expired
    "room_full",
    "illegal_move",  # the game rules refuse it (e.g. start while playing)
    "cannot_start",  # start with empty seats in a room that allows neither bots nor unguarded
    "server_busy",  # too many rooms on the server
    "too_many_rooms",  # too many open rooms created from this address
    "room_stopped",  # the room's simulation failed; it is closed, the client is back in the lobby
)


class ProtocolError(ValueError):
    """A message that breaks the protocol. ``code`` is one of ``ERROR_CODES``."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message

    def to_message(self, re: object = None) -> dict[str, Any]:
        return error_message(self.code, self.message, re)


def error_message(code: str, message: str, re: object = None) -> dict[str, Any]:
    msg: dict[str, Any] = {"type": "error", "code": code, "message": message}
    if re is not None:
        msg["re"] = re
    return msg


# --- JSON control messages -------------------------------------------------------------------


def encode_json(msg: dict[str, Any]) -> str:
    """A control message as compact JSON text (NaN/Inf refused)."""
    return json.dumps(msg, separators=(",", ":"), allow_nan=False)


def _reject_constant(name: str) -> float:
    raise ProtocolError("bad_json", f"{name} is not allowed in JSON")


# Control messages are a few levels deep. Deeper ones are refused whatever the Python: 3.11's
# parser raised RecursionError near 1 000 levels, 3.12's parses 2 000 and more.
MAX_JSON_DEPTH = 32


def _depth_over(msg: Any, most: int) -> bool:
    """Whether ``msg``'s containers nest deeper than ``most`` (without recursion)."""
    todo = [(msg, 1)]
    while todo:
        value, depth = todo.pop()
        if depth > most:
            return True
        items = value.values() if isinstance(value, dict) else value
        todo.extend((v, depth + 1) for v in items if isinstance(v, (dict, list)))
    return False


def decode_json(text: str | bytes, limit: int = MAX_JSON_BYTES) -> dict[str, Any]:
    """Parse a control message: a JSON object with a string ``type``."""
    if len(text) > limit:
        raise ProtocolError("too_big", f"control message of {len(text)} bytes; limit {limit}")
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError as e:
            raise ProtocolError("bad_json", f"not UTF-8: {e}") from None
    try:
        msg = json.loads(text, parse_constant=_reject_constant)
    except ProtocolError:
        raise
    except (ValueError, RecursionError) as e:
        raise ProtocolError("bad_json", f"not valid JSON: {e}") from None
    if not isinstance(msg, dict):
        raise ProtocolError("bad_json", f"expected a JSON object, got {type(msg).__name__}")
    if _depth_over(msg, MAX_JSON_DEPTH):
        raise ProtocolError("bad_json", f"nested deeper than {MAX_JSON_DEPTH} levels")
    t = msg.get("type")
    if not isinstance(t, str) or not t:
        raise ProtocolError("bad_message", "missing field 'type' (a string)")
    check_text("type", t, 32)  # named back in errors: no surrogates or control characters
    return msg


# Bidi embeddings, overrides and isolates: unlike the marks (U+200E/F, U+061C) they change
# the direction of whatever follows them, so a name could reorder a listing around it.
_BIDI_CONTROLS = frozenset("\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")


def check_text(key: str, v: str, max_len: int = 64) -> str:
    """A client's string made safe to store, log, index and send anywhere: Unicode scalar
    values only (no lone surrogate, which UTF-8 cannot encode), NFC-normalised, at most
    ``max_len`` code points, no control characters (C0, DEL, C1) and no bidi embedding,
    override or isolate. The normalised text, or ``ProtocolError("bad_message")`` naming
    ``key`` and what is wrong."""
    if len(v) > 4 * max_len:  # NFC never shrinks text by more than this: no need to look
        raise ProtocolError("bad_message", f"'{key}': at most {max_len} characters, got {len(v)}")
    try:
        v.encode("utf-8")
    except UnicodeEncodeError as e:
        raise ProtocolError(
            "bad_message", f"'{key}': not valid Unicode text (lone surrogate "
            f"U+{ord(v[e.start]):04X} at {e.start}); send UTF-8 text") from None
    v = unicodedata.normalize("NFC", v)
    if len(v) > max_len:
        raise ProtocolError("bad_message", f"'{key}': at most {max_len} characters, got {len(v)}")
    for i, ch in enumerate(v):
        if ch in _BIDI_CONTROLS or unicodedata.category(ch) == "Cc":
            raise ProtocolError("bad_message", f"'{key}': control character U+{ord(ch):04X} at "
                                f"{i} is not allowed")
    return v


def field_str(msg: dict[str, Any], key: str, default: str | None = None, *, max_len: int = 64,
              required: bool = False) -> str | None:
    """A string field checked and normalised by ``check_text`` (every client string goes
    through here), or ``default`` when absent."""
    if key not in msg or msg[key] is None:
        if required:
            raise ProtocolError("bad_message", f"missing field '{key}' (a string)")
        return default
    v = msg[key]
    if not isinstance(v, str):
        raise ProtocolError("bad_message", f"'{key}': expected a string, got {type(v).__name__}")
    return check_text(key, v, max_len)


def field_int(msg: dict[str, Any], key: str, default: int | None, lo: int, hi: int, *,
              required: bool = False) -> int | None:
    """A whole-number field in ``lo..hi``, or ``default`` when absent."""
    if key not in msg or msg[key] is None:
        if required:
            raise ProtocolError("bad_message", f"missing field '{key}' (a whole number)")
        return default
    v = msg[key]
    if isinstance(v, bool) or not isinstance(v, int):
        raise ProtocolError("bad_message", f"'{key}': expected a whole number, got {v!r}")
    if not lo <= v <= hi:
        raise ProtocolError("bad_message", f"'{key}': must be in {lo}..{hi}, got {v}")
    return v


def field_float(msg: dict[str, Any], key: str, default: float | None, lo: float, hi: float, *,
                required: bool = False) -> float | None:
    """A finite number field in ``[lo, hi]``, or ``default`` when absent."""
    if key not in msg or msg[key] is None:
        if required:
            raise ProtocolError("bad_message", f"missing field '{key}' (a number)")
        return default
    v = msg[key]
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ProtocolError("bad_message", f"'{key}': expected a number, got {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise ProtocolError("bad_message", f"'{key}': must be finite, got {v!r}")
    if not lo <= v <= hi:
        raise ProtocolError("bad_message", f"'{key}': must be in [{lo}, {hi}], got {v}")
    return v


def field_bool(msg: dict[str, Any], key: str, default: bool) -> bool:
    if key not in msg or msg[key] is None:
        return default
    v = msg[key]
    if not isinstance(v, bool):
        raise ProtocolError("bad_message", f"'{key}': expected true or false, got {v!r}")
    return v


MAX_REQUEST_ID = 2**53  # integer ids beyond this lose precision in a browser's JSON


def request_id(msg: dict[str, Any]) -> str | int | None:
    """The optional ``id`` a client puts on a request; replies echo it as ``re``, exactly
    as sent. None when absent; ``ProtocolError("bad_message")`` for one that is not a
    string of at most 64 characters (checked as every client string is) or an integer of
    magnitude at most 2**53 (``null``, a fraction, a list: the request is refused, and the
    error carries no ``re``, having no id to echo)."""
    if "id" not in msg:
        return None
    v = msg["id"]
    if isinstance(v, str):
        check_text("id", v, 64)
        return v
    if isinstance(v, int) and not isinstance(v, bool) and -MAX_REQUEST_ID <= v <= MAX_REQUEST_ID:
        return v
    shown = json.dumps(v)
    shown = shown if len(shown) <= 40 else shown[:37] + "..."
    raise ProtocolError("bad_message", "'id': expected a string of at most 64 characters or "
                        f"a whole number within +/-2**53, got {shown}")


# --- binary header ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Header:
    type: int
    version: int
    flags: int
    seq: int
    time: float


def decode_header(data: bytes, expect: int | None = None) -> Header:
    if len(data) < HEADER.size:
        raise ProtocolError("bad_binary", f"binary message of {len(data)} bytes; header is 16")
    t, v, flags, seq, time = HEADER.unpack_from(data)
    if t not in BINARY_TYPES:
        raise ProtocolError("bad_binary", f"unknown binary message type {t}")
    if v not in READ_VERSIONS[t]:
        known = ", ".join(map(str, READ_VERSIONS[t]))
        raise ProtocolError("bad_version",
                            f"{BINARY_TYPES[t]} message version {v}; this side reads {known}")
    if expect is not None and t != expect:
        raise ProtocolError(
            "bad_binary", f"expected a {BINARY_TYPES[expect]} message, got {BINARY_TYPES[t]}"
        )
    if flags & ~KNOWN_FLAGS[t]:  # a flag this version does not define: refused, not ignored
        raise ProtocolError("bad_binary", f"{BINARY_TYPES[t]} unknown flags {flags:#x} "
                            f"(defined: {KNOWN_FLAGS[t]:#x})")
    if not math.isfinite(time):
        raise ProtocolError("bad_binary", "header time must be finite")
    return Header(t, v, flags, seq, time)


# --- HIP: client -> server --------------------------------------------------------------------


@dataclass(frozen=True)
class Hip:
    """A hand position (world metres) with the client's sequence number and clock."""

    position: tuple[float, float, float]
    seq: int
    time: float


def encode_hip(position: Any, seq: int, time: float) -> bytes:
    x, y, z = (float(v) for v in position)
    return HEADER.pack(HIP, PROTOCOL_VERSION, 0, seq & 0xFFFFFFFF, time) + HIP_BODY.pack(x, y, z)


# A whole HIP message in one struct (the server reads 4 000 a second in the bench).
HIP_MSG = struct.Struct(HEADER.format + HIP_BODY.format[1:])
_isfinite = math.isfinite


def decode_hip(data: bytes) -> Hip:
    """A HIP frame; raises ``ProtocolError`` on a wrong size, type, version or a NaN/Inf."""
    if len(data) == HIP_SIZE:  # a well-formed HIP in one unpack; anything else: checked below
        t, v, _flags, seq, time, x, y, z = HIP_MSG.unpack(data)
        if (t == HIP and v == PROTOCOL_VERSION and not _flags and _isfinite(time)
                and _isfinite(x) and _isfinite(y) and _isfinite(z)):
            return Hip((x, y, z), seq, time)
    return _decode_hip_checked(data)


def _decode_hip_checked(data: bytes) -> Hip:
    if len(data) != HIP_SIZE:
        raise ProtocolError("bad_binary", f"HIP message must be {HIP_SIZE} bytes, got {len(data)}")
    h = decode_header(data, HIP)
    x, y, z = HIP_BODY.unpack_from(data, HEADER.size)
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise ProtocolError("bad_binary", "HIP position must be finite (got NaN or Inf)")
    return Hip((x, y, z), h.seq, h.time)


# --- CORNER: server -> player, every frame ----------------------------------------------------


@dataclass(frozen=True)
class Corner:
    """One corner's state after a frame (see ``game.devices.base.CornerState``)."""

    frame: int
    seat: int
    position: np.ndarray  # (3,) m
    velocity: np.ndarray  # (3,) m/s
    force: np.ndarray  # (3,) N, on the device: -K (h - c)
    stiffness: float  # coupling K, N/m
    ball_position: np.ndarray  # (3,) m
    ball_velocity: np.ndarray  # (3,) m/s
    hip_seq: int  # seq of the last HIP the server applied (0: none yet)
    hip_time: float  # that HIP's client time (NaN: none yet)
    server_time: float  # s, server clock at the end of the frame


def encode_corner(frame: int, seat: int, position: Any, velocity: Any, force: Any,
                  stiffness: float, ball_position: Any, ball_velocity: Any, hip_seq: int,
                  hip_time: float, server_time: float) -> bytes:
    return HEADER.pack(
        CORNER, PROTOCOL_VERSION, 0, frame & 0xFFFFFFFF, server_time
    ) + CORNER_BODY.pack(
        frame, seat, *position, *velocity, *force, stiffness, *ball_position, *ball_velocity,
        hip_seq & 0xFFFFFFFF, hip_time,
    )


# A whole CORNER message (header and body) in one struct: the same bytes as HEADER + CORNER_BODY.
CORNER_MSG = struct.Struct(HEADER.format + CORNER_BODY.format[1:])


def encode_corners(frame: int, server_time: float, positions: Any, velocities: Any,
                   forces: Any, stiffness: float, ball_position: Any, ball_velocity: Any,
                   applied: Any) -> list[bytes]:
    """The CORNER messages of one frame for every seat (row ``s`` of ``positions``,
    ``velocities``, ``forces``; ``applied[s]``: that seat's (hip seq, hip time) echo), byte
    for byte what ``encode_corner`` makes seat by seat, with one ``pack`` call each: the
    room thread makes four of these every millisecond."""
    pack = CORNER_MSG.pack
    seq = frame & 0xFFFFFFFF
    ball = (stiffness, *ball_position, *ball_velocity)
    return [
        pack(CORNER, PROTOCOL_VERSION, 0, seq, server_time, frame, s, *positions[s],
             *velocities[s], *forces[s], *ball, applied[s][0] & 0xFFFFFFFF, applied[s][1])
        for s in range(len(applied))
    ]


def decode_corner(data: bytes) -> Corner:
    if len(data) != CORNER_SIZE:
        raise ProtocolError(
            "bad_binary", f"CORNER message must be {CORNER_SIZE} bytes, got {len(data)}"
        )
    h = decode_header(data, CORNER)
    v = CORNER_BODY.unpack_from(data, HEADER.size)
    f = np.array(v[2:18], dtype=np.float64)
    return Corner(
        frame=v[0], seat=v[1], position=f[0:3], velocity=f[3:6], force=f[6:9],
        stiffness=float(f[9]), ball_position=f[10:13], ball_velocity=f[13:16],
        hip_seq=v[18], hip_time=v[19], server_time=h.time,
    )


# --- MESH: server -> spectators, ~30 Hz -------------------------------------------------------


@dataclass(frozen=True)
class Mesh:
    frame: int
    server_time: float
    positions: np.ndarray  # (n, n, 3) float64, dequantised
    lo: np.ndarray  # (3,) bounding box the positions were quantised in
    hi: np.ndarray
    ball_position: np.ndarray  # (3,)
    ball_radius: float
    hips: np.ndarray  # (4, 3)
    flags: int
    version: int = MESH_VERSION  # the payload's layout (1: interleaved, 2: byte planes)


def quantise(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions (n, n, 3) -> uint16 per axis relative to their bounding box (lo, hi)."""
    p = np.asarray(positions, dtype=np.float64)
    flat = p.reshape(-1, 3)
    lo = flat.min(axis=0).astype(np.float32).astype(np.float64)
    hi = flat.max(axis=0).astype(np.float32).astype(np.float64)
    hi = np.maximum(hi, lo)  # float32 rounding must not flip the box
    span = hi - lo
    scale = np.where(span > 0.0, QMAX / np.where(span > 0.0, span, 1.0), 0.0)
    x = (p - lo) * scale
    x += 0.5  # round half up: x >= 0 up to float32 rounding of lo, clipped below
    np.clip(x, 0.0, QMAX, out=x)
    return x.astype("<u2"), lo, hi


def dequantise(q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return lo + q.astype(np.float64) * ((hi - lo) / QMAX)


def encode_mesh(frame: int, server_time: float, positions: np.ndarray, ball_position: Any,
                ball_radius: float, hips: Any, compress: bool = True) -> bytes:
    """A MESH frame. Positions are quantised to uint16 in their bounding box (error at most
    extent/131070 per axis); with ``compress`` the rows are delta-coded and zlib'd when that
    is at least 10% smaller."""
    p = np.asarray(positions)
    if p.ndim != 3 or p.shape[0] != p.shape[1] or p.shape[2] != 3:
        raise ValueError(f"positions: expected (n, n, 3), got {p.shape}")
    q, lo, hi = quantise(p)
    return encode_quantised_mesh(frame, server_time, q, lo, hi, ball_position, ball_radius,
                                 hips, compress)


def mesh_deltas(q: np.ndarray) -> np.ndarray:
    """Quantised nodes (n, n, 3) with each row delta-coded along it: its first node as it
    is, each next one minus the one before (uint16 wraps: decoded by a cumulative sum)."""
    d = q.copy()
    d[:, 1:, :] = q[:, 1:, :] - q[:, :-1, :]
    return d


def mesh_residuals(deltas: np.ndarray) -> np.ndarray:
    """MESH version 2's prediction: row deltas (``mesh_deltas``) less the row above's (each
    node less its left, upper and upper-left neighbours' plane), zigzag mapped (0, -1, 1, -2
    ... to 0, 1, 2, 3 ...) so that small residuals of either sign have a zero high byte."""
    r = deltas.copy()
    r[1:] = deltas[1:] - deltas[:-1]  # uint16: wraps, as the decoder's sums do
    s = r.view(np.int16)
    return ((r << 1) ^ (s >> 15).view(np.uint16)).astype(np.uint16)


def mesh_unresiduals(z: np.ndarray) -> np.ndarray:
    """``mesh_residuals`` and ``mesh_deltas`` undone: the quantised nodes (n, n, 3)."""
    r = (z >> 1) ^ (np.uint16(0) - (z & 1))
    return np.cumsum(np.cumsum(r, axis=0, dtype=np.uint16), axis=1, dtype=np.uint16)


def to_planes(v: np.ndarray) -> bytes:
    """MESH version 2's payload order of n*n*3 uint16 (x y z a node): for each axis, the low
    bytes of all its values (nodes row-major), then their high bytes."""
    axes = np.ascontiguousarray(np.asarray(v, dtype="<u2").reshape(-1, 3).T)  # (3, nodes)
    return np.ascontiguousarray(axes.view(np.uint8).reshape(3, -1, 2).transpose(0, 2, 1)).tobytes()


def from_planes(payload: bytes, n: int) -> np.ndarray:
    """``to_planes`` undone: (n, n, 3) uint16."""
    b = np.frombuffer(payload, dtype=np.uint8).reshape(3, 2, n * n)
    v = b[:, 0, :].astype(np.uint16) | (b[:, 1, :].astype(np.uint16) << 8)
    return np.ascontiguousarray(v.T).reshape(n, n, 3)


def encode_quantised_mesh(frame: int, server_time: float, q: np.ndarray, lo: Any, hi: Any,
                          ball_position: Any, ball_radius: float, hips: Any,
                          compress: bool = True, deltas: np.ndarray | None = None,
                          version: int = MESH_VERSION) -> bytes:
    """``encode_mesh`` from nodes already quantised (``quantise``'s q, lo, hi; ``deltas``:
    ``mesh_deltas(q)`` where already made, e.g. by the server's native quantiser).
    ``version`` 1 makes the old layout (interleaved), for tests of old replays' bytes."""
    if version not in READ_VERSIONS[MESH]:
        raise ValueError(f"version: expected one of {READ_VERSIONS[MESH]}, got {version}")
    n = q.shape[0]
    payload = to_planes(q) if version == 2 else q.tobytes()
    flags = 0
    if compress:
        d = mesh_deltas(q) if deltas is None else deltas
        z = zlib.compress(to_planes(mesh_residuals(d)) if version == 2 else d.tobytes(), 1)
        if len(z) <= 0.9 * len(payload):
            payload, flags = z, FLAG_ZLIB | FLAG_DELTA
    body = MESH_BODY.pack(frame, n, *lo, *hi, *ball_position, ball_radius,
                          *np.asarray(hips, dtype=np.float64).reshape(12))
    head = HEADER.pack(MESH, version, flags, frame & 0xFFFFFFFF, server_time)
    return head + body + payload


def decode_mesh(data: bytes) -> Mesh:
    h = decode_header(data, MESH)
    if len(data) < HEADER.size + MESH_BODY.size:
        raise ProtocolError("bad_binary", "MESH message too short")
    v = MESH_BODY.unpack_from(data, HEADER.size)
    frame, n = v[0], v[1]
    if not 2 <= n <= MAX_MESH_N:
        raise ProtocolError("bad_binary", f"MESH n must be 2..{MAX_MESH_N}, got {n}")
    f = np.array(v[2:], dtype=np.float64)
    payload = data[HEADER.size + MESH_BODY.size:]
    expected = n * n * 3 * 2
    if h.flags & FLAG_ZLIB:
        try:
            d = zlib.decompressobj()
            payload = d.decompress(payload, expected + 1)
        except zlib.error as e:
            raise ProtocolError("bad_binary", f"MESH payload not valid zlib: {e}") from None
    if len(payload) != expected:
        raise ProtocolError("bad_binary", f"MESH payload of {len(payload)} bytes, need {expected}")
    if h.version == 2:
        q = from_planes(payload, n)
        if h.flags & FLAG_DELTA:
            q = mesh_unresiduals(q)
    else:
        q = np.frombuffer(payload, dtype="<u2").reshape(n, n, 3)
        if h.flags & FLAG_DELTA:
            q = np.cumsum(q, axis=1, dtype=np.uint16)
    lo, hi = f[0:3], f[3:6]
    return Mesh(
        frame=frame, server_time=h.time, positions=dequantise(q, lo, hi), lo=lo, hi=hi,
        ball_position=f[6:9], ball_radius=float(f[9]), hips=f[10:22].reshape(4, 3),
        flags=h.flags, version=h.version,
    )


# --- TRACK: replay files, ~100 Hz -------------------------------------------------------------


@dataclass(frozen=True)
class Track:
    frame: int
    server_time: float
    ball_position: np.ndarray
    ball_velocity: np.ndarray
    hips: np.ndarray  # (4, 3)
    corners: np.ndarray  # (4, 3)


# A TRACK message as a NumPy record (docs/protocol.md: the header, then the body), so that
# a batch of samples is encoded in one pass (the engine records 100 a second a room).
TRACK_RECORD = np.dtype([("type", "u1"), ("version", "u1"), ("flags", "<u2"), ("seq", "<u4"),
                         ("time", "<f8"), ("frame", "<i8"), ("ball", "<f4", (6,)),
                         ("hips", "<f4", (12,)), ("corners", "<f4", (12,))])


def encode_tracks(samples: np.ndarray) -> bytes:
    """TRACK messages, one per row of ``samples`` (k x 32: frame, server time, ball position
    and velocity, hips 4 x 3, corners 4 x 3, as the frame loop's track ring holds them),
    concatenated (``TRACK_SIZE`` bytes each)."""
    rows = np.asarray(samples, dtype=np.float64).reshape(-1, 32)
    out = np.zeros(len(rows), TRACK_RECORD)
    frames = rows[:, 0].astype(np.int64)
    out["type"], out["version"] = TRACK, PROTOCOL_VERSION
    out["seq"] = frames & 0xFFFFFFFF
    out["time"] = rows[:, 1]
    out["frame"] = frames
    out["ball"] = rows[:, 2:8]
    out["hips"] = rows[:, 8:20]
    out["corners"] = rows[:, 20:32]
    return out.tobytes()


def encode_track(frame: int, server_time: float, ball_position: Any, ball_velocity: Any,
                 hips: Any, corners: Any) -> bytes:
    return encode_tracks(np.concatenate((
        [frame, server_time], np.asarray(ball_position, dtype=np.float64).reshape(3),
        np.asarray(ball_velocity, dtype=np.float64).reshape(3),
        np.asarray(hips, dtype=np.float64).reshape(12),
        np.asarray(corners, dtype=np.float64).reshape(12))))


def decode_track(data: bytes) -> Track:
    if len(data) != TRACK_SIZE:
        raise ProtocolError("bad_binary", f"TRACK message must be {TRACK_SIZE} bytes")
    h = decode_header(data, TRACK)
    v = TRACK_BODY.unpack_from(data, HEADER.size)
    f = np.array(v[1:], dtype=np.float64)
    return Track(v[0], h.time, f[0:3], f[3:6], f[6:18].reshape(4, 3), f[18:30].reshape(4, 3))


def decode_binary(data: bytes) -> Hip | Corner | Mesh | Track:
    """Any binary message, by its header type."""
    h = decode_header(data)
    return {HIP: decode_hip, CORNER: decode_corner, MESH: decode_mesh, TRACK: decode_track}[h.type](
        data
    )
