"""Every use of websockets' private internals, in one module: measured hot paths of the
server's and the clients' connections (a HIP stream at 1 kHz, 4 000 CORNERs a second).
``tests/server/test_fastpath.py`` fails loudly if a websockets release changes what they
rely on (``Connection.process_event``, ``recv_messages.frames``, ``protocol.send_binary``,
``send_data``, the parser waiting in ``StreamReader.at_eof`` between frames);
``websockets`` is pinned below its next major in ``pyproject.toml``.

``BinaryHook``: a connection that hands complete binary messages straight to a callback
from ``data_received``. Where the bytes read start with whole, final, binary frames
(masked as the side requires, within the size limit) while websockets' parser waits
between frames, those frames are parsed here and handed over, websockets' parser and
events skipped (its own per frame work was half a HIP's cost in the server); anything
else, and every byte after it, goes to websockets. ``try_send_binary``: a binary message
written at once; on a server's connection (frames unmasked, no extension) its frame is
written here (the header from ``game.wire.wsframe``), the bytes websockets'
``Frame.serialize`` makes, without its checks and objects.

The server takes 4 000 HIPs a second in its bench and a player 1 000 CORNERs: handed over
as they arrive, each costs no wake-up of the reader task. Only when no message is queued
ahead of it (so messages are handled in the order they came), and only while
``on_binary`` is set; text, control and fragmented frames, and everything while it is
unset, go the usual way."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from websockets.frames import Frame, Opcode
from websockets.protocol import OPEN, SERVER
from websockets.streams import StreamReader

from ..wire.wsframe import FIN, OP_BINARY, SHORT_BINARY, binary_frame_header, header_at, unmask

_AT_EOF = StreamReader.at_eof.__code__


class BinaryHook:
    """Mix in before a websockets asyncio ``Connection`` class."""

    on_binary: Callable[[bytes], None] | None = None
    recv_messages: Any  # the connection's message assembler
    protocol: Any

    def data_received(self, data: bytes) -> None:
        if self.on_binary is not None:
            data = _take_binary_frames(self, data)
            if not data:
                return
        super().data_received(data)  # type: ignore[misc]

    def process_event(self, event: Any) -> None:
        hook = self.on_binary
        if (hook is not None and type(event) is Frame and event.opcode is Opcode.BINARY
                and event.fin and not _queued(self.recv_messages)):
            data = event.data
            hook(data if type(data) is bytes else bytes(data))
            return
        super().process_event(event)  # type: ignore[misc]


def between_frames(protocol: Any) -> bool:
    """Whether websockets' parser holds no byte of a frame: its reader is empty and the
    parser waits at the top of its loop (in ``StreamReader.at_eof``), not inside a frame,
    and no fragmented message is under way. A version made otherwise reads False: the
    frames all go to websockets."""
    if protocol.reader.buffer or protocol.current_size is not None:
        return False
    gen, inner = protocol.parser, None
    for _ in range(4):  # a server's handshake parser delegates to Protocol.parse
        gen = getattr(gen, "gi_yieldfrom", None)
        if gen is None:
            break
        inner = gen
    return inner is not None and getattr(inner, "gi_code", None) is _AT_EOF


def _take_binary_frames(conn: Any, data: bytes) -> bytes:
    """Hand the whole, final, binary frames ``data`` starts with to ``conn.on_binary``, as
    websockets would (the same payloads, in order), while the connection is open, nothing
    is queued for its reader and websockets' parser is between frames. Returns the bytes
    left for websockets: from the first frame not taken (partial, another opcode, RSV bits,
    masked otherwise than the side requires, over the size limit), whole, so that its parser
    sees every frame it must check or answer."""
    protocol = conn.protocol
    if (protocol.state is not OPEN or protocol.extensions or protocol.reader.eof
            or _queued(conn.recv_messages) or not between_frames(protocol)):
        return data
    masked = protocol.side is SERVER  # a client masks every frame, a server none
    limit = protocol.max_message_size
    if protocol.max_fragment_size is not None:
        limit = protocol.max_fragment_size if limit is None else min(limit,
                                                                     protocol.max_fragment_size)
    at, end = 0, len(data)
    while True:
        head = header_at(data, at)
        if head is None:
            break
        b0, is_masked, n, hl = head
        # FIN, no RSV bit, opcode 2 (binary); the mask bit as the side requires; under
        # 64 KiB (larger ones: websockets' parser), within the size limit, whole
        if b0 != FIN | OP_BINARY or is_masked is not masked or n >= 65536:
            break
        if (limit is not None and n > limit) or end - at < hl + n:
            break
        body = data[at + hl:at + hl + n]
        payload = unmask(body, data[at + hl - 4:at + hl]) if masked else body
        at += hl + n
        conn.on_binary(payload)
        # The callback may have closed the connection, or unset itself: the rest goes to
        # websockets (as does everything while a message waits for the reader).
        if conn.on_binary is None or protocol.state is not OPEN:
            break
    return data[at:] if at else data


def _queued(assembler: Any) -> int:
    """Frames not read yet (websockets' Assembler keeps them in ``frames``; a version
    without it is taken as always busy: the fast path stays off)."""
    frames = getattr(assembler, "frames", None)
    return len(frames) if frames is not None else 1


def try_send_binary(ws: Any, data: bytes) -> bool:
    """Write one binary message on connection ``ws`` at once when the socket takes it
    without waiting (open, nothing buffered): the same frame that ``await ws.send(data)``
    writes, without its context manager and without waking a task. False: nothing was
    written; the caller sends it the usual way."""
    transport = ws.transport
    protocol = ws.protocol
    if (transport is None or transport.is_closing() or protocol.state is not OPEN
            or transport.get_write_buffer_size()):
        return False
    if (protocol.side is SERVER and not protocol.extensions and not protocol.writes
            and not protocol.expect_continuation_frame and not protocol.debug):
        # Nothing of the protocol's is waiting to be written (it is written as it is made),
        # so this frame goes in order.
        n = len(data)
        transport.write((SHORT_BINARY[n] if n < 126 else binary_frame_header(n)) + data)
        return True
    protocol.send_binary(data)
    ws.send_data()
    return True
