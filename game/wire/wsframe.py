"""Websocket frames (RFC 6455 5.2), the one place they are read and written by hand: their
headers, a masked payload's bytes, and ``FrameTap``, which takes whole binary messages out
of a stream as it passes. Used by every connection of the game's (``game.net.tap``: the
engine's clients and the game's own clients) and by a gateway following and writing the
streams it relays (``server.gateway``); websockets does everything else."""

from __future__ import annotations

import os
import struct
from collections.abc import Callable

OP_CONT, OP_TEXT, OP_BINARY, OP_CLOSE, OP_PING, OP_PONG = 0x0, 0x1, 0x2, 0x8, 0x9, 0xA
FIN = 0x80

# A server's binary frame header (FIN, opcode 2, unmasked, the length in 7, 7 + 16 or
# 7 + 64 bits), as websockets' Frame.serialize writes it; the short ones made once.
SHORT_BINARY = [bytes((FIN | OP_BINARY, n)) for n in range(126)]
_MEDIUM = struct.Struct("!BBH")
_LONG = struct.Struct("!BBQ")


def frame_header(opcode: int, length: int, masked: bool = False) -> bytes:
    """The header of a final frame of ``opcode`` and ``length`` payload bytes (``masked``:
    the mask bit set; the key follows the header)."""
    m = 0x80 if masked else 0
    if length < 126:
        return bytes((FIN | opcode, m | length))
    if length < 65536:
        return _MEDIUM.pack(FIN | opcode, m | 126, length)
    return _LONG.pack(FIN | opcode, m | 127, length)


def binary_frame_header(length: int) -> bytes:
    """The header of an unmasked, final binary frame of ``length`` payload bytes."""
    return SHORT_BINARY[length] if length < 126 else frame_header(OP_BINARY, length)


ZERO_KEY = bytes(4)


def masked_frame(opcode: int, payload: bytes, key: bytes | None = None) -> bytes:
    """A client's final frame of ``payload`` (RFC 6455 5.3: a client masks every frame),
    masked with ``key``: a fresh random one unless given (the load bench's clients give
    ``ZERO_KEY``, which leaves the payload as it is and costs nothing)."""
    key = os.urandom(4) if key is None else key
    body = payload if key == ZERO_KEY else unmask(payload, key)
    return frame_header(opcode, len(payload), masked=True) + key + body


def header_at(buf: bytes | bytearray, i: int) -> tuple[int, bool, int, int] | None:
    """The frame header at ``buf[i:]``: its first byte, whether it is masked, the payload's
    length and the header's (the mask's four bytes included); None while it is not all
    there."""
    if len(buf) - i < 2:
        return None
    b0, b1 = buf[i], buf[i + 1]
    n, hl = b1 & 0x7F, 2
    hl += 2 if n == 126 else 8 if n == 127 else 0
    masked = bool(b1 & 0x80)
    hl += 4 if masked else 0
    if len(buf) - i < hl:
        return None
    if n >= 126:
        n = int.from_bytes(buf[i + 2:i + (4 if n == 126 else 10)], "big")
    return b0, masked, n, hl


def unmask(payload: bytes | bytearray | memoryview, key: bytes | bytearray | memoryview
           ) -> bytes:
    """A masked frame's payload with its 4-byte masking ``key`` applied (RFC 6455 5.3)."""
    n = len(payload)
    if n == 0:
        return b""
    reps = -(-n // 4)
    mask = int.from_bytes((bytes(key) * reps)[:n], "little")
    return (int.from_bytes(payload, "little") ^ mask).to_bytes(n, "little")


HEAD_END = b"\r\n\r\n"
HEAD_MAX = 1 << 16  # an HTTP head longer than this is not followed: the tap gives up


class FrameTap:
    """Follows one direction of a websocket stream and takes whole binary messages out of
    it as they pass, for a reader that wants them without a websocket implementation's
    parsing and task wake-ups (a HIP, a CORNER, a MESH).

    ``feed(data)`` returns the bytes that go on: all of them, in order, but the frames
    taken. A final, unfragmented binary frame (no RSV bit, masked as ``masked`` says, a
    payload of at most ``max_take`` bytes) is held until whole and offered to ``take`` (its
    payload, unmasked): taken, it leaves the stream; refused, it passes as it came. Every
    other frame (text, control, fragmented, larger, malformed) passes byte for byte as it
    arrives, for the implementation behind the tap to read, check and answer.

    ``head``: the stream opens with an HTTP head (the upgrade request, or its answer),
    which passes first; frames follow it, unless it is an answer other than 101 (then
    nothing is taken). ``messages`` counts the data messages passed on (at their final
    frame's header), so that a reader may keep the taken and the passed in order."""

    def __init__(self, take: Callable[[bytes], bool], *, masked: bool, max_take: int,
                 head: bool = False) -> None:
        self.take = take
        self.masked = masked
        self.max_take = max_take
        self.messages = 0
        self.given_up = False  # not a websocket stream: everything passes
        self._head: bytearray | None = bytearray() if head else None
        self._partial = b""  # a frame header, or a frame to offer, not yet whole
        self._skip = 0  # payload bytes of a passing frame still to come
        self._fragmented = False

    def feed(self, data: bytes) -> bytes:
        if self.given_up:
            return data
        if self._head is not None:
            return self._feed_head(data)
        return self._frames(data)

    def _feed_head(self, data: bytes) -> bytes:
        head = self._head
        assert head is not None
        start = max(0, len(head) - 3)
        head += data
        end = head.find(HEAD_END, start)
        if end < 0:
            if len(head) > HEAD_MAX:
                self.given_up, self._head = True, None
            return data
        end += len(HEAD_END)
        if head.startswith(b"HTTP/") and head[9:13] != b"101 ":
            self.given_up = True  # an answer that is not an upgrade: no frames follow
        self._head = None
        rest = len(head) - end  # of ``data``, the bytes after the head
        passed = data[:len(data) - rest]
        return passed + (self.feed(data[len(data) - rest:]) if rest else b"")

    def _frames(self, data: bytes) -> bytes:
        out = bytearray()
        buf, i = self._partial + data if self._partial else data, 0
        end = len(buf)
        while i < end:
            if self._skip:
                n = min(self._skip, end - i)
                out += buf[i:i + n]
                self._skip -= n
                i += n
                continue
            head = header_at(buf, i)
            if head is None:
                break
            b0, masked, n, hl = head
            if (b0 == FIN | OP_BINARY and masked is self.masked and n <= self.max_take
                    and not self._fragmented):
                if end - i < hl + n:
                    break  # held until whole
                body = buf[i + hl:i + hl + n]
                payload = unmask(body, buf[i + hl - 4:i + hl]) if masked else bytes(body)
                if not self.take(payload):
                    out += buf[i:i + hl + n]
                    self.messages += 1
                i += hl + n
                continue
            if b0 & 0x0F < 0x8:  # a data frame: FIN ends its message
                self._fragmented = not b0 & FIN
                self.messages += 0 if self._fragmented else 1
            out += buf[i:i + hl]
            i += hl
            self._skip = n
        self._partial = bytes(buf[i:])
        return bytes(out)
