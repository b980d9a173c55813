"""``TapConnection``: a websockets asyncio connection whose binary messages skip websockets'
parser, its message queue and the wake-up of the task reading it, and whose binary messages
out may be written at once, with websockets' public parts only.

The server takes 4 000 HIPs a second in its bench and a player 1 000 CORNERs: read through
websockets, each cost a parse, a queued message and a task's wake-up (about half a HIP's
cost in the server). Here every byte the socket gives passes a ``FrameTap``
(``game.wire.wsframe``) before websockets sees it, from the connection's first byte (the
HTTP head passes first), so the tap always knows where a frame starts; whole binary frames
go to ``on_binary`` while it is set and no message the tap passed on waits for the reader
(``message_read``: the reader counts what it takes, so the messages of a connection are
handled in the order they came). Text, control, fragmented and large frames, and all of
them while ``on_binary`` is unset, go to websockets, which checks and answers them.

What it relies on is public: ``serve``'s and ``connect``'s ``create_connection`` (a subclass
of the connection class), the connection's ``state``, and asyncio's protocol callbacks
(``connection_made``, ``data_received``) that websockets' connections are built on. A frame
written by ``send_now`` goes straight to the transport, which is safe because websockets
writes each frame it makes whole, in the call that makes it (a message it sends is one
frame: this project never sends fragmented ones), so between two of its writes the stream is
between two frames; ``send_now`` writes only while the socket holds nothing unsent."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from websockets.asyncio.server import ServerConnection
from websockets.protocol import State

from ..wire.wsframe import OP_BINARY, FrameTap, binary_frame_header, masked_frame

MAX_TAKE = 65535  # larger binary messages go through websockets (and its size limit)


class TapConnection:
    """Mix in before websockets' asyncio ``ServerConnection`` or ``ClientConnection``."""

    on_binary: Callable[[bytes], None] | None = None
    state: State
    _tap: FrameTap | None = None
    stream: Any = None  # the transport asyncio gave (connection_made)
    _read = 0  # messages the reader took from websockets

    def connection_made(self, transport: Any) -> None:
        super().connection_made(transport)  # type: ignore[misc]
        self.stream = transport
        # A server reads its client's masked frames, a client its server's unmasked ones.
        self._server = isinstance(self, ServerConnection)
        self._tap = FrameTap(self._take, masked=self._server, max_take=MAX_TAKE, head=True)

    def listen(self, on_binary: Callable[[bytes], None] | None,
               max_take: int = MAX_TAKE) -> None:
        """Hand binary messages of at most ``max_take`` bytes to ``on_binary`` as they come
        (None: no more; they are read the usual way)."""
        self.on_binary = on_binary
        if self._tap is not None:
            self._tap.max_take = min(max_take, MAX_TAKE)

    def message_read(self) -> None:
        """The reader took a message from websockets (``recv``, ``async for``)."""
        self._read += 1

    def data_received(self, data: bytes) -> None:
        tap = self._tap
        if tap is not None:
            data = tap.feed(data)
            if not data:
                return
        super().data_received(data)  # type: ignore[misc]

    def _take(self, payload: bytes) -> bool:
        hook = self.on_binary
        tap = self._tap
        if hook is None or tap is None or tap.messages != self._read \
                or self.state is not State.OPEN:
            return False
        hook(payload)
        return True

    def send_now(self, data: bytes) -> bool:
        """Write one binary message at once when the socket takes it without waiting (the
        connection open, nothing buffered): the frame ``await send(data)`` writes, without
        its context manager and without waking a task. False: nothing was written; send it
        the usual way."""
        t = self.stream
        if t is None or self.state is not State.OPEN or t.is_closing() \
                or t.get_write_buffer_size():
            return False
        if self._server:
            t.write(binary_frame_header(len(data)) + data)
        else:
            t.write(masked_frame(OP_BINARY, data))
        return True
