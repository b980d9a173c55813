"""The engine's control socket for its gateways (``server.shared.lanes``): a gateway asks it
for the frame loops' blocks (their memfds, passed over the socket) so that it can serve
seated players' lanes, and reports on it the messages it handled itself, which the
engine adds to the host's figures (``/api/stats``, ``/metrics``)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..shared import lanes

log = logging.getLogger("clothball.server")

COUNTED = ("messages_in", "messages_out")  # of what a gateway reports (lanes.REPORTED): lanes


def add_counts(stats: dict[str, int], seen: dict[str, int], counts: dict[str, int]) -> None:
    """A pump's running ``counts`` (a gateway's, or the engine's own port's), what grew
    since ``seen`` added to the host's totals ``stats`` and, for the lanes' messages, to
    their ``lane_`` figures."""
    for k in lanes.REPORTED:
        v = counts[k]
        if v > seen[k]:
            for key in (k, "lane_" + k) if k in COUNTED else (k,):
                stats[key] = stats.get(key, 0) + v - seen[k]
            seen[k] = v


class GatewayControl:
    """Serves ``path`` (in the engine socket's private directory): ``blocks()`` gives the
    blocks and mesh boards to pass, (id, memfd, bytes, kind) each; ``stats`` is the
    host's figures, to which each gateway's reported counts are added as they grow."""

    def __init__(self, path: Path, blocks: Callable[[], list[tuple[int, int, int, str]]],
                 stats: dict[str, int], set_wake: Callable[[int, bool], None]) -> None:
        self.path, self.blocks, self.stats = path, blocks, stats
        self.set_wake = set_wake  # an eventfd written by every frame loop a pass, or no more
        self._sock: socket.socket | None = None
        self._tasks: set[asyncio.Task[None]] = set()

    async def start(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.setblocking(False)
        sock.bind(str(self.path))
        os.chmod(self.path, 0o600)
        sock.listen(64)
        self._sock = sock
        self._spawn(self._accept(sock))

    async def stop(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        for t in list(self._tasks):
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        with contextlib.suppress(OSError):
            self.path.unlink()

    def _spawn(self, coro: Any) -> None:
        t = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(t)
        t.add_done_callback(self._tasks.discard)

    async def _accept(self, sock: socket.socket) -> None:
        loop = asyncio.get_running_loop()
        while True:
            try:
                conn, _ = await loop.sock_accept(sock)
            except OSError:
                return  # closed
            conn.setblocking(False)
            self._spawn(self._serve(conn))

    async def _serve(self, conn: socket.socket) -> None:
        """One gateway's connection: its requests and reports, a line each."""
        loop = asyncio.get_running_loop()
        seen = dict.fromkeys(lanes.REPORTED, 0)
        wake = [-1]  # this gateway's frame wake-up, once asked for
        buf = b""
        try:
            while True:
                data = await loop.sock_recv(conn, 4096)
                if not data:
                    return
                buf += data
                if len(buf) > lanes.LINE_MAX:
                    log.warning("a gateway's control line is too long: connection closed")
                    return
                while b"\n" in buf:
                    line, buf = buf.split(b"\n", 1)
                    self._line(conn, line, seen, wake)
        except OSError:
            return
        finally:
            if wake[0] >= 0:
                self.set_wake(wake[0], False)  # (no frame loop writes it from here on)
                os.close(wake[0])
            conn.close()

    def _line(self, conn: socket.socket, line: bytes, seen: dict[str, int],
              wake: list[int]) -> None:
        # A few dozen bytes and a few descriptors on a local socket: answers are sent at once.
        word = line + b"\n"
        if word == lanes.BLOCKS:
            lanes.send_blocks(conn, self.blocks())
            return
        if word == lanes.WAKE:
            if wake[0] < 0:
                wake[0] = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
            lanes.send_wake(conn, wake[0])
            return
        if word in (lanes.ARM, lanes.DISARM):
            if wake[0] >= 0:
                self.set_wake(wake[0], word == lanes.ARM)
            return
        try:
            counts = json.loads(line)["counts"]
            add_counts(self.stats, seen, {k: int(counts.get(k, 0)) for k in lanes.REPORTED})
        except (ValueError, KeyError, TypeError, AttributeError):
            log.warning("a gateway sent a control line that is not one: %.60r", line)
