"""Which asyncio event loop a server process runs on: asyncio's own, or ``uvloop`` with
``CLOTHBALL_LOOP=uvloop`` (a one-line error naming what to install when it is missing).
asyncio's stays the default: measured with ``clothball bench --load``, uvloop took about a
fifth less of the server's CPU but held no more rooms, its frame lateness p99 no better
(``docs/benchmarks/load.md``)."""

from __future__ import annotations

import asyncio
import os
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

T = TypeVar("T")

CHOICES = ("asyncio", "uvloop")


class LoopError(ValueError):
    """The loop asked for cannot be had (one line, saying what to do)."""


def loop_factory(choice: str | None = None) -> tuple[str, Callable[[], asyncio.AbstractEventLoop]]:
    """The loop's name and a factory for it. ``choice``: one of ``CHOICES``; None reads
    ``CLOTHBALL_LOOP`` (default ``asyncio``)."""
    if choice is None:
        choice = os.environ.get("CLOTHBALL_LOOP", "").strip().lower() or "asyncio"
    if choice not in CHOICES:
        raise LoopError(f"CLOTHBALL_LOOP={choice!r} is not one of {', '.join(CHOICES)}")
    if choice == "uvloop":
        try:
            import uvloop
        except ImportError:
            raise LoopError("CLOTHBALL_LOOP=uvloop but uvloop is not installed: "
                            "pip install uvloop (Linux, macOS), or unset it") from None
        return "uvloop", uvloop.new_event_loop
    return "asyncio", asyncio.new_event_loop


def run(main: Coroutine[Any, Any, T], choice: str | None = None) -> T:
    """``asyncio.run(main)`` on the chosen loop (``loop_factory``)."""
    try:
        _, factory = loop_factory(choice)
    except LoopError:
        main.close()  # never started: no "never awaited" warning
        raise
    with asyncio.Runner(loop_factory=factory) as runner:
        return runner.run(main)


def running() -> str:
    """The running loop's kind: "uvloop" or "asyncio"."""
    mod = type(asyncio.get_running_loop()).__module__
    return "uvloop" if mod.split(".")[0] == "uvloop" else "asyncio"


__all__ = ["CHOICES", "LoopError", "loop_factory", "run", "running"]
