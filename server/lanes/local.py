"""The engine's own gateway's link (``LocalLink``): the engine serves its own port (the
public port of one process, its bots' loopback port beside gateways) with the same
``server.gateway.relay.Gateway`` and native pump as a gateway process, relaying to its own
Unix socket. The pump's lanes read this process's frame loop memory as it is (no memfd
needed, so a file size limit that keeps it from being shared does not matter here), and the
frame wake-up is this process's eventfd, armed directly: what a gateway's ``EngineLink``
asks its engine for over the control socket is a call here."""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Callable, Iterable
from typing import Any

from ..shared.lanes import REPORTED
from .control import add_counts

REPORT_S = 1.0  # its pump's counts added to the host's figures this often (as a gateway's)

# (id, buffer, kind, owner): a frame loop's block ("block") or its mesh board ("board"),
# in memory that lives while its owner (the frame loop's worker) does
Share = tuple[int, Any, str, object]


class LocalLink:
    """``shares()``: every frame loop's block and board now; ``set_wake(fd, on)``: every
    frame loop writes the eventfd after each pass (or no more); ``stats``: the host's
    figures, to which the pump's counts are added (``messages_in``, ``messages_out`` and
    their ``lane_`` parts, as ``server.lanes.control`` adds a gateway's). The frame loops'
    workers live until the server's pool closes, after its gateway's pump has stopped."""

    def __init__(self, shares: Callable[[], Iterable[Share]],
                 set_wake: Callable[[int, bool], None],
                 stats: dict[str, int] | None = None) -> None:
        self._shares = shares
        self._set_wake = set_wake
        self.stats = stats if stats is not None else {}
        self.pump: Any = None
        self.have: set[int] = set()
        self._wake = -1
        self._armed = False
        self._seen = dict.fromkeys(REPORTED, 0)
        self._task: asyncio.Task[None] | None = None

    def attach(self, pump: Any) -> None:
        self.pump = pump

    def start(self) -> None:
        """The frame wake-up: an eventfd of this process's, a duplicate the pump's."""
        self._wake = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        self.pump.set_wake(os.dup(self._wake))
        self._task = asyncio.get_running_loop().create_task(self._report_forever())

    async def _report_forever(self) -> None:
        while True:
            await asyncio.sleep(REPORT_S)
            self.report()

    def report(self) -> None:
        """The pump's counts since the last report, added to the host's figures."""
        add_counts(self.stats, self._seen, {k: int(getattr(self.pump, k)) for k in REPORTED})

    async def stop(self) -> None:
        """After the pump has stopped: its last counts; the loops write the wake-up no
        more."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
            self.report()
        if self._wake >= 0:
            if self._armed:
                self._set_wake(self._wake, False)
                self._armed = False
            os.close(self._wake)
            self._wake = -1

    def want_block(self, block_id: int) -> None:
        """The pump needs block ``block_id``: every frame loop's memory, as it is now."""
        if block_id in self.have:
            return
        shares = list(self._shares())
        self.pump.set_local_maps([(i, kind == "board", buf) for i, buf, kind, _ in shares])
        self.have = {i for i, *_ in shares}

    def want_armed(self, on: bool) -> None:
        if on != self._armed and self._wake >= 0:
            self._set_wake(self._wake, on)
            self._armed = on


__all__ = ["LocalLink"]
