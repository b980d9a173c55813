"""Websocket frames (RFC 6455 5.2), the one place they are read and written by hand: their
headers and a masked payload's bytes, for the fast paths of a connection
(``game.net.fastpath``) and a gateway following and writing the streams it relays
(``server.gateway``)."""

from __future__ import annotations

import struct

OP_CONT, OP_TEXT, OP_BINARY, OP_CLOSE = 0x0, 0x1, 0x2, 0x8
FIN = 0x80

# A server's binary frame header (FIN, opcode 2, unmasked, the length in 7, 7 + 16 or
# 7 + 64 bits), as websockets' Frame.serialize writes it; the short ones made once.
SHORT_BINARY = [bytes((FIN | OP_BINARY, n)) for n in range(126)]
_MEDIUM = struct.Struct("!BBH")
_LONG = struct.Struct("!BBQ")


def frame_header(opcode: int, length: int) -> bytes:
    """The header of an unmasked, final frame of ``opcode`` and ``length`` payload bytes."""
    if length < 126:
        return bytes((FIN | opcode, length))
    if length < 65536:
        return _MEDIUM.pack(FIN | opcode, 126, length)
    return _LONG.pack(FIN | opcode, 127, length)


def binary_frame_header(length: int) -> bytes:
    """The header of an unmasked, final binary frame of ``length`` payload bytes."""
    return SHORT_BINARY[length] if length < 126 else frame_header(OP_BINARY, length)


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
