"""What to tell a user whose window cannot open."""

from __future__ import annotations

import os


def window_error(e: BaseException) -> str:
    """One line: why no window, and what to do instead."""
    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        return ("cannot open a window: no display (DISPLAY is not set). Run it in a desktop "
                "session or under xvfb-run; to watch without a window, open the server's "
                "page (http://HOST:PORT/) in a browser")
    return f"cannot open a window on display {os.environ.get('DISPLAY', '?')}: {e}"
