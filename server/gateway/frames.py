"""Where a server's byte stream to a client stands, read as it passes through a gateway:
still in the HTTP answer, or in websocket frames (between two, or inside one), and
whether the server has sent its close frame. A gateway whose engine vanished uses it to
end each websocket client's stream with a close frame of its own, which it may only
write between two frames of a complete message (RFC 6455: server frames are unmasked,
their lengths in the header)."""

from __future__ import annotations

HEAD_MAX = 1 << 16  # an HTTP answer's head longer than this is not followed further
OP_CLOSE = 0x8


class ServerFrames:
    """Follows one server-to-client stream, fed each chunk as it goes out."""

    def __init__(self) -> None:
        self._head = bytearray()
        self.websocket = False  # the server answered 101: frames follow
        self.given_up = False  # not a websocket stream (an HTTP answer): not followed
        self.closed = False  # the server's close frame went out
        self._fragmented = False  # inside a message sent in several frames
        self._skip = 0  # payload bytes of the current frame still to come
        self._partial = b""  # the start of a frame header

    def feed(self, data: bytes) -> None:
        if self.given_up or self.closed:
            return
        if not self.websocket:
            self._head += data
            end = self._head.find(b"\r\n\r\n")
            if end < 0:
                self.given_up = len(self._head) > HEAD_MAX
                return
            self.websocket = self._head.startswith((b"HTTP/1.1 101", b"HTTP/1.0 101"))
            self.given_up = not self.websocket
            data, self._head = bytes(self._head[end + 4:]), bytearray()
        buf, i = self._partial + data, 0
        while True:
            if self._skip:
                take = min(self._skip, len(buf) - i)
                self._skip -= take
                i += take
                if self._skip:
                    break
            if len(buf) - i < 2:
                break
            b0, b1 = buf[i], buf[i + 1]
            n, hl = b1 & 0x7F, 2
            hl += 2 if n == 126 else 8 if n == 127 else 0
            hl += 4 if b1 & 0x80 else 0
            if len(buf) - i < hl:
                break
            if n >= 126:
                n = int.from_bytes(buf[i + 2:i + (4 if n == 126 else 10)], "big")
            op = b0 & 0x0F
            if op == OP_CLOSE:
                self.closed = True
            elif op < 0x8:  # a data frame (continuation, text, binary): FIN ends a message
                self._fragmented = not b0 & 0x80
            i += hl
            self._skip = n
        self._partial = bytes(buf[i:])

    def between_messages(self) -> bool:
        """A close frame may be written now: a websocket stream, open, between messages."""
        return (self.websocket and not self.closed and not self._skip
                and not self._partial and not self._fragmented)


def close_frame(code: int, reason: str) -> bytes:
    """A server's (unmasked) close frame."""
    payload = code.to_bytes(2, "big") + reason.encode()[:123]
    return bytes([0x80 | OP_CLOSE, len(payload)]) + payload
