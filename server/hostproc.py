"""A ``clothball host`` in a process of its own, for the benches that must not share an
interpreter with the server they measure (``--empty-rooms``, ``--soak``, ``--admit``)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path


def start_host(data: Path, *extra: str) -> tuple[subprocess.Popen[str], str | None]:
    """``clothball host --workers 1 --port 0 --backend cpu --data DATA EXTRA...``; returns the
    process and its websocket URL (None, the process ended, when it did not start)."""
    cmd = [sys.executable, "-m", "clothball.game.cli", "host", "--workers", "1", "--port", "0",
           "--data", str(data), "--backend", "cpu", *extra]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert proc.stdout is not None
    for line in proc.stdout:
        m = re.match(r"clothball server on (ws://\S+)", line)
        if m:
            return proc, m.group(1)
    proc.wait()
    return proc, None


def stop_host(proc: subprocess.Popen[str]) -> None:
    proc.terminate()
    proc.wait(timeout=60)
    if proc.stdout is not None:
        proc.stdout.close()
