"""Processes around a server: a ``clothball host`` of its own, for the benches that must
not share an interpreter with the server they measure (``--empty-rooms``, ``--soak``,
``--admit``); a free port and a Redis of its own on one (``bench --load --cluster`` and the
cluster tests); reading a server's HTTP API."""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


def start_host(data: Path, *extra: str, port: int = 0, workers: int = 1
               ) -> tuple[subprocess.Popen[str], str | None]:
    """``clothball host --workers 1 --port 0 --backend cpu --data DATA EXTRA...`` (``port``
    and ``workers`` as given); returns the process and its websocket URL (None, the process
    ended, when it did not start)."""
    cmd = [sys.executable, "-m", "clothball.game.cli", "host", "--workers", str(workers),
           "--port", str(port), "--data", str(data), "--backend", "cpu", *extra]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert proc.stdout is not None
    for line in proc.stdout:
        m = re.match(r"clothball server on (ws://\S+)", line)
        if m:
            return proc, m.group(1)
    proc.wait()
    proc.stdout.close()  # ended: nothing more to read, and nothing left open
    return proc, None


@contextmanager
def bench_host(*extra: str, workers: int = 1) -> Iterator[str | None]:
    """A ``clothball host`` of a bench's own (``start_host``'s ``extra`` and ``workers``, its
    data in a temporary directory): its websocket URL while the block runs, stopped after;
    None (said on stderr) when it did not start."""
    with tempfile.TemporaryDirectory() as tmp:
        proc, url = start_host(Path(tmp) / "data", *extra, workers=workers)
        if url is None:
            print(f"clothball bench: the host did not start (exit {proc.returncode})",
                  file=sys.stderr)
            yield None
            return
        try:
            yield url
        finally:
            stop_host(proc)


def http_base(ws_url: str) -> str:
    """ws://HOST:PORT/ws -> http://HOST:PORT"""
    return ws_url.replace("ws://", "http://", 1)[: -len("/ws")]


def get(url: str, timeout: float = 30.0, token: str | None = None) -> bytes:
    """GET ``url``; ``token``: the host's (``/api/stats?reset=1`` needs it)."""
    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"} if token
                                 else {})
    with urllib.request.urlopen(req, timeout=timeout) as r:
        return r.read()


def get_json(url: str, token: str | None = None) -> Any:
    return json.loads(get(url, timeout=10.0, token=token))


def stats(ws_url: str) -> dict[str, Any]:
    """The server's ``/api/stats``."""
    return get_json(f"{http_base(ws_url)}/api/stats")


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` now (IPv4 or IPv6)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def wait_port(port: int, what: str, timeout: float = 20.0) -> None:
    """Until something listens on ``port`` of 127.0.0.1; ``RuntimeError`` naming ``what``
    after ``timeout`` s."""
    end = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return
        except OSError:
            if time.monotonic() > end:
                raise RuntimeError(f"{what} did not start on port {port}") from None
            time.sleep(0.05)


def start_redis(redis_server: str, port: int, workdir: Path | str) -> subprocess.Popen[bytes]:
    """``redis-server`` on 127.0.0.1:``port``, nothing persisted (its files in ``workdir``),
    started and answering."""
    proc = subprocess.Popen(
        [redis_server, "--port", str(port), "--bind", "127.0.0.1", "--save", "",
         "--appendonly", "no", "--dir", str(workdir)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_port(port, "redis-server")
    except RuntimeError:
        proc.kill()
        proc.wait()
        raise
    return proc


def stop_host(proc: subprocess.Popen[str]) -> None:
    """SIGTERM, then SIGKILL if it has not ended within a minute; its pipe closed."""
    try:
        proc.terminate()
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    finally:
        if proc.stdout is not None:
            proc.stdout.close()
