"""A gateway's side of its clients' lanes (``server.lanes``): the lanes themselves are the
one lane code the engine runs too; here are what only a gateway needs.

* ``client_frames`` follows a client's websocket frames (masked, RFC 6455) and takes out the
  HIPs its lane takes (``game.wire.wsframe.FrameTap``); every other byte goes on to the
  engine unchanged.
* ``SocketLinks`` is the gateway's link to the engine's control socket: the blocks and mesh
  boards (memfds passed over it, mapped here), the frame wake-up (an eventfd passed the
  same way) and the counts reported to the engine for the host's figures.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ... import _native
from ...game.wire import protocol as P
from ...game.wire.wsframe import FrameTap
from ..lanes.lane import Links
from ..shared import lanes

log = logging.getLogger("clothball.gateway")

LANES_ENV = "CLOTHBALL_GATEWAY_LANES"  # "0": the gateway relays every message (A/B runs)
WRITE_SKIP = 1 << 16  # a client with this much unsent: its CORNER is skipped (a newer comes)
REPORT_S = 1.0  # counts reported to the engine this often
RETRY_S = 0.5  # between two requests for the blocks


def lanes_wanted() -> bool:
    return os.environ.get(LANES_ENV, "1").strip() != "0"


def client_frames(take: Callable[[bytes], bool]) -> FrameTap:
    """A client's stream from the first frame after the handshake: each whole HIP-sized
    binary frame is offered to ``take`` (unmasked), and dropped if taken."""
    return FrameTap(take, masked=True, max_take=P.HIP_SIZE)


class SocketLinks(Links):
    """The gateway's link to the engine's control socket at ``path``."""

    def __init__(self, path: Path) -> None:
        super().__init__()
        self.path = path
        self.blocks: dict[int, Any] = {}  # id -> _native.BlockView, or a mesh board's mmap
        self._sock: socket.socket | None = None
        self._lock = asyncio.Lock()
        self._fetching: asyncio.Task[None] | None = None
        self._fetched_at = -math.inf
        self._reported: dict[str, int] = {}
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._report_forever())

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        self._drop()

    def block(self, block_id: int) -> Any | None:
        """The block ``block_id``, else None, and it is asked for (not more than once per
        ``RETRY_S``): a later call has it. Block ids are random, so a restarted engine's
        blocks are never taken for its predecessor's."""
        view = self.blocks.get(block_id)
        loop = asyncio.get_running_loop()
        if view is None and (self._fetching is None or self._fetching.done()) \
                and loop.time() - self._fetched_at > RETRY_S:
            self._fetched_at = loop.time()
            self._fetching = loop.create_task(self._fetch())
        return view

    async def _set_armed(self, on: bool) -> bool:
        async with self._lock:
            line = lanes.ARM if on else lanes.DISARM
            try:
                await asyncio.to_thread(lambda: self._connect().sendall(line))
            except OSError:
                self._drop()
                return False
            return True

    def _drop(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        self._forget_wake()
        self.blocks = {}  # an engine's blocks die with it (its lanes' clients are closed)

    def _connect(self) -> socket.socket:
        if self._sock is None:
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.settimeout(5.0)
            try:
                s.connect(str(self.path))
            except OSError:
                s.close()
                raise
            self._sock = s
        return self._sock

    async def _fetch(self) -> None:
        async with self._lock:
            for attempt in range(2):  # a connection to an engine that has gone: a new one
                try:
                    maps = await asyncio.to_thread(
                        lambda: lanes.receive_blocks(self._connect()))
                    # a frame loop's block as a view of its records; a mesh board as bytes
                    self.blocks = {i: _native.BlockView(m) if kind == "block" else m
                                   for i, (kind, m) in maps.items()}
                    if self.wake < 0 and not self.no_wake:
                        await self._fetch_wake()
                    return
                except (OSError, ValueError) as e:
                    self._drop()
                    if attempt:
                        log.warning("the engine's blocks could not be had (%s): its "
                                    "players' messages go through the engine", e)

    async def _fetch_wake(self) -> None:
        try:
            fd = await asyncio.to_thread(lambda: lanes.receive_wake(self._connect()))
        except ConnectionError as e:  # an engine that has none: timers, a little late
            log.warning("%s: CORNERs above %g Hz are timed here", e, lanes.TIMER_MAX_HZ)
            self.no_wake = True
            for lane in list(self.framed):
                self.framed.discard(lane)
                lane.use_timer()
            return
        self._listen_wake(fd)

    async def _report_forever(self) -> None:
        while True:
            await asyncio.sleep(REPORT_S)
            if self.counts == self._reported:
                continue
            counts = dict(self.counts)
            async with self._lock:
                try:
                    line = lanes.counts_line(counts)
                    await asyncio.to_thread(lambda: self._connect().sendall(line))  # noqa: B023
                    self._reported = counts
                except OSError:
                    self._drop()  # the engine is away; a new one is asked when a lane opens
                    self._reported = {}
