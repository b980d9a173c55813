"""Where a server's byte stream to a client stands, read as it passes through a gateway:
still in the HTTP answer, or in websocket frames (between two, or inside one), and
whether the server has sent its close frame, and the room the client is in. A gateway
whose engine vanished uses it to tell each client in a room that its room stopped, then to
end the stream with a close frame of its own, which it may only write between two frames
of a complete message (RFC 6455: server frames are unmasked, their lengths in the header).

The room is read from the start of the engine's text messages (compact JSON, keys in the
order the engine writes them, ``game.wire.protocol.encode_json``): a ``joined`` puts the
client in its ``room``, a ``left`` or an ``error`` ``room_stopped`` takes it out. The
room's frame and server time come from the header of its binary messages (CORNER, MESH:
``seq`` is the frame mod 2^32, then the time) and from its events. Only a message's first
bytes are looked at, never parsed whole.

The engine's lane messages (``server.shared.lanes``: small text messages that open and
close a seated player's lane in this gateway) are taken out of the stream: a small text
frame is held until it is whole, then passed on, or handed to ``on_lane`` and dropped."""

from __future__ import annotations

import json
import re
import struct
from collections.abc import Callable

from ...game.wire.wsframe import OP_BINARY, OP_CLOSE, OP_TEXT, frame_header, header_at
from ..shared.lanes import LANE_PREFIX

HEAD_MAX = 1 << 16  # an HTTP answer's head longer than this is not followed further
PEEK = 256  # bytes of a text message's start kept: the fields read are among the first
HOLD = 2048  # a whole text frame up to this long is held until complete (a lane message?)
BINARY_HEAD = struct.Struct("<BBHId")  # docs/protocol.md's 16-byte header: type .. time
_JOINED = re.compile(rb'\{"type":"joined","room":("(?:[^"\\]|\\.)*")')
_EVENT = re.compile(rb'\{"type":"event","event":"[a-z_]+","room":"(?:[^"\\]|\\.)*",'
                    rb'"frame":(\d+),"time":([0-9.eE+-]+)')
_OUT = (b'{"type":"left"', b'{"type":"error","code":"room_stopped"')


class ServerFrames:
    """Follows one server-to-client stream, fed each chunk as it goes out."""

    def __init__(self, on_lane: Callable[[bytes], None] | None = None) -> None:
        self.on_lane = on_lane  # given each lane message's payload (else they pass on)
        self._head = bytearray()
        self.websocket = False  # the server answered 101: frames follow
        self.given_up = False  # not a websocket stream (an HTTP answer): not followed
        self.closed = False  # the server's close frame went out
        self._fragmented = False  # inside a message sent in several frames
        self._skip = 0  # payload bytes of the current frame still to come
        self._partial = b""  # the start of a frame header
        self._peek: bytearray | None = None  # the start of the text message coming in
        self._peek_left = 0  # of its payload still to come into ``_peek``
        self._peek_binary = False  # ``_peek`` is a binary message's header
        self.room: str | None = None  # the room the client is in, as the engine said
        # The room's frame and server time, as last seen (-1: none seen yet in this room).
        self.frame, self.time = -1, 0.0

    def feed(self, data: bytes) -> bytes:
        """Follow ``data``; what of it goes on to the client (all of it but lane messages,
        and the start of a small text frame not yet whole, which a later call gives)."""
        if self.given_up or self.closed:
            return data
        if not self.websocket:
            self._head += data
            end = self._head.find(b"\r\n\r\n")
            if end < 0:
                self.given_up = len(self._head) > HEAD_MAX
                return data
            self.websocket = self._head.startswith((b"HTTP/1.1 101", b"HTTP/1.0 101"))
            self.given_up = not self.websocket
            rest, self._head = bytes(self._head[end + 4:]), bytearray()
            head = data[:len(data) - len(rest)]
            return head + self._frames(rest) if self.websocket else data
        return self._frames(data)

    def _frames(self, data: bytes) -> bytes:
        out = bytearray()
        buf, i = self._partial + data, 0
        while True:
            if self._skip:
                take = min(self._skip, len(buf) - i)
                if self._peek is not None:
                    self._peek += buf[i:i + min(take, self._peek_left)]
                    self._peek_left -= min(take, self._peek_left)
                out += buf[i:i + take]
                self._skip -= take
                i += take
                if self._peek is not None and (not self._peek_left or not self._skip):
                    self._seen(bytes(self._peek), self._peek_binary)
                    self._peek = None
                if self._skip:
                    break
            head = header_at(buf, i)
            if head is None:
                break
            b0, _, n, hl = head
            op = b0 & 0x0F
            if op == OP_TEXT and b0 & 0x80 and not self._fragmented and 0 < n <= HOLD:
                if len(buf) - i < hl + n:
                    break  # held (in _partial) until whole
                payload = bytes(buf[i + hl:i + hl + n])
                if self.on_lane is not None and payload.startswith(LANE_PREFIX):
                    self.on_lane(payload)
                else:
                    self._seen(payload[:PEEK], binary=False)
                    out += buf[i:i + hl + n]
                i += hl + n
                continue
            if op == OP_CLOSE:
                self.closed = True
            elif op < 0x8:  # a data frame (continuation, text, binary): FIN ends a message
                self._fragmented = not b0 & 0x80
            out += buf[i:i + hl]
            i += hl
            self._skip = n
            if (op == OP_TEXT and n) or (op == OP_BINARY and n >= BINARY_HEAD.size):
                self._peek_binary = op == OP_BINARY
                self._peek = bytearray()
                self._peek_left = BINARY_HEAD.size if self._peek_binary else min(n, PEEK)
        self._partial = bytes(buf[i:])
        return bytes(out)

    def _seen(self, start: bytes, binary: bool) -> None:
        """A message's first bytes: where the client is."""
        if binary:
            _, _, _, seq, time = BINARY_HEAD.unpack(start)
            ahead = (seq - self.frame) % (1 << 32)  # seq is the frame mod 2^32
            if self.frame < 0 or ahead < 1 << 31:  # (not an older frame's message)
                self.frame = seq if self.frame < 0 else self.frame + ahead
                self.time = time
        elif m := _JOINED.match(start):
            self.room = json.loads(m.group(1))
            self.frame = -1  # another room's frames: from its first message on
        elif start.startswith(_OUT):
            self.room = None
        elif m := _EVENT.match(start):
            self.frame, self.time = int(m.group(1)), float(m.group(2))

    def sent_binary(self, payload: bytes) -> None:
        """A binary message the gateway itself wrote to the client (a lane's CORNER or
        MESH): its room's frame and time, as from the engine's."""
        if len(payload) >= BINARY_HEAD.size:
            self._seen(payload[:BINARY_HEAD.size], binary=True)

    def between_messages(self) -> bool:
        """A close frame may be written now: a websocket stream, open, between messages."""
        return (self.websocket and not self.closed and not self._skip
                and not self._partial and not self._fragmented)


def text_frame(msg: dict[str, object]) -> bytes:
    """A server's (unmasked) text frame holding ``msg`` as compact JSON, as the engine
    writes it."""
    payload = json.dumps(msg, separators=(",", ":"), allow_nan=False).encode()
    return frame_header(OP_TEXT, len(payload)) + payload


def close_frame(code: int, reason: str) -> bytes:
    """A server's (unmasked) close frame."""
    payload = code.to_bytes(2, "big") + reason.encode()[:123]
    return frame_header(OP_CLOSE, len(payload)) + payload
