"""A gateway's link to its engine's control socket (``server.shared.lanes``), for the lanes
its pump serves (``_native.Pump``, native/net/pump.hpp): the blocks and mesh boards (memfds
passed over the socket, handed to the pump, which maps them), the frame wake-up (an eventfd
passed the same way, the pump's from then on), arming it, and the counts reported to the
engine for the host's figures (messages the pump handled that the engine did not see).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import socket
from pathlib import Path
from typing import Any

from ..shared import lanes

log = logging.getLogger("clothball.gateway")

REPORT_S = 1.0  # counts reported to the engine this often
RETRY_S = 0.5  # between two requests for the blocks


COALESCE_ENV = "CLOTHBALL_PUMP_COALESCE_US"  # the pump's wake-ups under load (A/B runs)


def pump_coalesce_s() -> float | None:
    """The pump's coalescing time from ``COALESCE_ENV`` (µs, 0-10 000), None: its default.
    Raises ``ValueError`` saying what is wrong."""
    text = os.environ.get(COALESCE_ENV, "").strip()
    if not text:
        return None
    try:
        us = float(text)
    except ValueError:
        us = math.nan
    if not (0 <= us <= 10_000):
        raise ValueError(f"{COALESCE_ENV}={text!r}: give microseconds from 0 to 10000")
    return us * 1e-6


class EngineLink:
    """The gateway's link to the engine's control socket at ``path``, feeding ``pump``."""

    def __init__(self, path: Path, pump: Any) -> None:
        self.path, self.pump = path, pump
        self.have: set[int] = set()  # the ids of the blocks the pump has
        self.no_wake = False  # the engine has no wake-up: the pump times every CORNER
        self._wake = False  # the pump has the wake-up
        self._armed = False
        self._want_armed = False
        self._sock: socket.socket | None = None
        self._lock = asyncio.Lock()
        self._fetching: asyncio.Task[None] | None = None
        self._arming: asyncio.Task[None] | None = None
        self._fetched_at = -math.inf
        self._reported: tuple[int, ...] = ()
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._report_forever())

    async def stop(self) -> None:
        for task in (self._task, self._fetching, self._arming):
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        self._drop()

    def want_block(self, block_id: int) -> None:
        """The pump needs block ``block_id``: the blocks are asked for (not more than once
        per ``RETRY_S``). Block ids are random, so a restarted engine's blocks are never
        taken for its predecessor's."""
        loop = asyncio.get_running_loop()
        if block_id not in self.have and (self._fetching is None or self._fetching.done()) \
                and loop.time() - self._fetched_at > RETRY_S:
            self._fetched_at = loop.time()
            self._fetching = loop.create_task(self._fetch())

    def want_armed(self, on: bool) -> None:
        """The pump has lanes on the frame wake-up (or none now): the engine's loops write
        it after each pass (or no more)."""
        self._want_armed = on
        if self._arming is None or self._arming.done():
            self._arming = asyncio.get_running_loop().create_task(self._arm())

    async def _arm(self) -> None:
        while self._wake and self._want_armed != self._armed:
            want = self._want_armed
            async with self._lock:
                try:
                    line = lanes.ARM if want else lanes.DISARM
                    await asyncio.to_thread(lambda: self._connect().sendall(line))  # noqa: B023
                except OSError:
                    self._drop()
                    return
            self._armed = want

    def _drop(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        # An engine's blocks and wake-up die with it (its lanes' clients are closed).
        self.pump.drop_maps()
        self.have = set()
        self._wake = self._armed = False

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
                    shares = await asyncio.to_thread(
                        lambda: lanes.receive_block_fds(self._connect()))
                    try:
                        self.pump.set_maps([(i, kind == "board", fd, n)
                                            for i, (kind, fd, n) in shares.items()])
                    finally:
                        for _, fd, _ in shares.values():
                            os.close(fd)
                    self.have = set(shares)
                    break
                except (OSError, ValueError) as e:
                    self._drop()
                    if attempt:
                        log.warning("the engine's blocks could not be had (%s): its "
                                    "players' messages go through the engine", e)
                        return
            if not self._wake and not self.no_wake:
                await self._fetch_wake()
        if self._want_armed:
            self.want_armed(True)

    async def _fetch_wake(self) -> None:
        try:
            fd = await asyncio.to_thread(lambda: lanes.receive_wake(self._connect()))
        except ConnectionError as e:  # an engine that has none: timers, a little late
            log.warning("%s: CORNERs above %g Hz are timed here", e, lanes.TIMER_MAX_HZ)
            self.no_wake = True
            self.pump.no_wake()
            return
        except OSError:
            self._drop()
            return
        self.pump.set_wake(fd)
        self._wake = True

    async def _report_forever(self) -> None:
        while True:
            await asyncio.sleep(REPORT_S)
            counts = tuple(int(getattr(self.pump, k)) for k in lanes.REPORTED)
            if counts == self._reported:
                continue
            async with self._lock:
                try:
                    line = lanes.counts_line(dict(zip(lanes.REPORTED, counts, strict=True)))
                    await asyncio.to_thread(lambda: self._connect().sendall(line))  # noqa: B023
                    self._reported = counts
                except OSError:
                    self._drop()  # the engine is away; a new one is asked when a lane opens
                    self._reported = ()
