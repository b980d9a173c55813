"""A ``clothball host`` in a process of its own, for the benches that must not share an
interpreter with the server they measure (``--empty-rooms``, ``--soak``, ``--admit``)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import urllib.request
from pathlib import Path
from typing import Any


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


def http_base(ws_url: str) -> str:
    """ws://HOST:PORT/ws -> http://HOST:PORT"""
    return ws_url.replace("ws://", "http://", 1)[: -len("/ws")]


def get(url: str, timeout: float = 30.0) -> bytes:
    with urllib.request.urlopen(url, timeout=timeout) as r:
        return r.read()


def stats(ws_url: str) -> dict[str, Any]:
    """The server's ``/api/stats``."""
    return json.loads(get(f"{http_base(ws_url)}/api/stats", timeout=10.0))


def stop_host(proc: subprocess.Popen[str]) -> None:
    proc.terminate()
    proc.wait(timeout=60)
    if proc.stdout is not None:
        proc.stdout.close()
