"""A child process of ``clothball host`` (the engine, each gateway) ends when the host
does, however the host ends (SIGKILL included), so a supervisor that restarts the host
never finds an older generation still serving its port.

Two ties, the second a backup for the first: Linux's ``PR_SET_PDEATHSIG`` (the kernel
sends the child SIGTERM when its parent dies), and a pipe whose write end only the
parent holds: its read end, watched by the child's event loop, reads end-of-file once
the parent is gone (on any platform)."""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import ctypes.util
import os
import signal
import sys
from collections.abc import Callable

PR_SET_PDEATHSIG = 1  # from <sys/prctl.h>


def arm(parent_pid: int) -> None:
    """In the child, first thing: SIGTERM when the parent dies; exit now if it already
    has (it died before the tie was made: the child is the init process's by now)."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    if os.getppid() != parent_pid:
        os._exit(0)


def watch(fd: int, on_gone: Callable[[], None]) -> None:
    """Call ``on_gone`` (on the running event loop) when the pipe ``fd`` reads end of file
    or fails: the parent, the only writer, has exited."""
    loop = asyncio.get_running_loop()
    os.set_blocking(fd, False)

    def readable() -> None:
        try:
            data = os.read(fd, 64)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            loop.remove_reader(fd)
            on_gone()

    loop.add_reader(fd, readable)


def pipe() -> tuple[int, int]:
    """A lifeline for the parent to keep: (read end, for the children; write end, never
    written, inherited by no child)."""
    r, w = os.pipe()
    os.set_inheritable(r, True)
    os.set_inheritable(w, False)
    return r, w
