"""Server threads named for the OS: Python (before 3.14) names its threads for itself only,
so /proc, ``top -H`` and the load bench's per-thread CPU saw every thread of a server as
``python3``. Each long-lived server thread calls ``name_os_thread`` as it starts (a
ThreadPoolExecutor's ``initializer``); the native frame loop names its own thread."""

from __future__ import annotations

import threading

from ... import _native


def name_os_thread() -> None:
    """Give the calling thread its Python name (cut to 15 bytes) in the OS."""
    _native.name_os_thread(threading.current_thread().name)
