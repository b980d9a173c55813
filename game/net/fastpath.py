"""Every use of websockets' private internals, in one module: measured hot paths of the
server's and the clients' connections (a HIP stream at 1 kHz, 4 000 CORNERs a second).
``tests/server/test_fastpath.py`` fails loudly if a websockets release changes what they
rely on (``Connection.process_event``, ``recv_messages.frames``, ``protocol.send_binary``,
``send_data``); ``websockets`` is pinned below its next major in ``pyproject.toml``.

``BinaryHook``: a connection that hands complete binary messages straight to a callback
from ``data_received``.

The server takes 4 000 HIPs a second in its bench and a player 1 000 CORNERs: handed over
as they arrive, each costs no wake-up of the reader task. Only when no message is queued
ahead of it (so messages are handled in the order they came), and only while
``on_binary`` is set; text, control and fragmented frames, and everything while it is
unset, go the usual way."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from websockets.frames import Frame, Opcode
from websockets.protocol import OPEN


class BinaryHook:
    """Mix in before a websockets asyncio ``Connection`` class."""

    on_binary: Callable[[bytes], None] | None = None
    recv_messages: Any  # the connection's message assembler

    def process_event(self, event: Any) -> None:
        hook = self.on_binary
        if (hook is not None and type(event) is Frame and event.opcode is Opcode.BINARY
                and event.fin and not _queued(self.recv_messages)):
            data = event.data
            hook(data if type(data) is bytes else bytes(data))
            return
        super().process_event(event)  # type: ignore[misc]


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
    if (transport is None or transport.is_closing() or ws.protocol.state is not OPEN
            or transport.get_write_buffer_size()):
        return False
    ws.protocol.send_binary(data)
    ws.send_data()
    return True
