"""The engine's links for the lanes it serves itself (``LocalLinks``): the clients connected
to the engine (one process, or where its gateway cannot serve a lane), served by the same
lane code as a gateway's, from the same block and board, mapped in this process."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from typing import Any

from ... import _native
from .lane import Links

# (id, buffer, kind): a frame loop's block ("block") or its mesh board ("board"), in memory
# that lives while the frame loop's worker does (the owner, kept here with it)
Share = tuple[int, Any, str, object]


class LocalLinks(Links):
    """``shares()``: every frame loop's block and board now; ``set_wake(fd, on)``: every
    frame loop writes the eventfd after each pass (or no more)."""

    def __init__(self, shares: Callable[[], Iterable[Share]],
                 set_wake: Callable[[int, bool], None]) -> None:
        super().__init__()
        self._shares = shares
        self._set_wake = set_wake
        self._blocks: dict[int, tuple[Any, object]] = {}  # id -> (view or board, owner)

    def start(self) -> None:
        """The frame wake-up, an eventfd of this process's (armed while a lane needs it)."""
        if self.wake < 0:
            self._listen_wake(os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC))

    def stop(self) -> None:
        if self.wake >= 0 and self._armed:
            self._set_wake(self.wake, False)
        self._forget_wake()
        self._blocks.clear()

    def block(self, block_id: int) -> Any | None:
        got = self._blocks.get(block_id)
        if got is None:  # a frame loop made since: look again
            self._blocks = {i: (_native.BlockView(buf) if kind == "block" else buf, owner)
                            for i, buf, kind, owner in self._shares()}
            got = self._blocks.get(block_id)
        return None if got is None else got[0]

    async def _set_armed(self, on: bool) -> bool:
        if self.wake < 0:
            return False
        self._set_wake(self.wake, on)  # (a gateway's arming is a socket round trip; this none)
        return True
