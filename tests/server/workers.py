"""The server suites against a host of two processes, an engine and a gateway, as
``clothball host --workers 2`` runs them (issue 33; docs/architecture.md).

With ``CLOTHBALL_TEST_WORKERS=2`` the conftest's ``server()`` and ``live_server()`` run
their server as the host's engine: it stays in the test process (so a test can still look
at its rooms and counters), listening on the engine's Unix socket too, and a real gateway
process (``python -m clothball.server.gateway``) listens on the public port and carries
every connection there. ``ws_url`` and ``http_url`` name the public port, so every client
of the tests goes through the gateway, and none is ever redirected.

The gateway must stop cleanly (exit 0) and log no error or traceback: its stderr is
checked when the server context ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import types
import urllib.request
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from clothball.server.gateway.__main__ import limit_args
from clothball.server.hostproc import free_port

WORKERS = int(os.environ.get("CLOTHBALL_TEST_WORKERS", "1") or "1")
if WORKERS not in (1, 2):
    raise RuntimeError(f"CLOTHBALL_TEST_WORKERS must be 1 or 2, got {WORKERS}")

_now = [WORKERS]  # the processes of the servers started now (the conftest's fixture sets it)

# The suites of issue 17. Without CLOTHBALL_TEST_WORKERS, each of their tests that starts a
# server (calls server() or live_server()) runs twice, with one process and with an engine
# and a gateway (the conftest's pytest_generate_tests): what CI runs.
SUITES = ("test_server_bad_input", "test_server_fastpaths", "test_server_match",
          "test_server_play", "test_server_reconnect", "test_server_sim", "test_faults",
          "test_hostile_input")


def current() -> int:
    """How many processes a server started now has: 1 or 2."""
    return _now[0]


@contextlib.contextmanager
def using(n: int) -> Iterator[None]:
    old, _now[0] = _now[0], n
    try:
        yield
    finally:
        _now[0] = old


def starts_a_server(fn: Any) -> bool:
    """Whether a test function (or a function nested in it) calls ``server`` or
    ``live_server`` (or ``started`` here, or test_faults' ``start_server``, its server
    processes)."""
    def names(code: types.CodeType) -> Iterator[str]:
        yield from code.co_names
        for c in code.co_consts:
            if isinstance(c, types.CodeType):
                yield from names(c)

    code = getattr(fn, "__code__", None)
    return code is not None and bool({"server", "live_server", "started", "start_server"}
                                     & set(names(code)))


class Gateway:
    """The host's gateway process: started on the public port, in front of the engine's
    socket, read, and stopped (SIGTERM) at the end."""

    def __init__(self, shared_port: int, engine_socket: Path,
                 expected_errors: tuple[str, ...] = (), limits: Any = None) -> None:
        """``limits``: the engine's ``Limits``, of which the gateway is given what
        ``clothball host`` gives its gateways (None: none, the gateway's defaults)."""
        self.shared_port = self.port = shared_port
        self.expected_errors = expected_errors  # regular expressions of errors it may log
        self.stderr: list[str] = []
        extra = [] if limits is None else limit_args(limits.slow_drop_s,
                                                     limits.socket_send_buffer)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "clothball.server.gateway", "--host", "127.0.0.1",
             "--port", str(shared_port), "--engine-socket", str(engine_socket), *extra],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None and self.proc.stderr is not None
        threading.Thread(target=self._read_stderr, daemon=True).start()
        first: list[str] = []
        reader = threading.Thread(target=lambda: first.append(self.proc.stdout.readline()),
                                  daemon=True)  # type: ignore[union-attr]
        reader.start()
        reader.join(60)
        try:
            self.pid = int(json.loads(first[0])["pid"])
        except (IndexError, ValueError, KeyError) as e:
            self.proc.kill()
            self.proc.wait(10)
            for pipe in (self.proc.stdout, self.proc.stderr):  # none left open on failure
                with contextlib.suppress(ValueError):
                    pipe.close()
            raise AssertionError("the gateway process did not start:\n"
                                 + "".join(first + self.stderr)) from e

    def _read_stderr(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.stderr.append(line)

    def stop(self) -> None:
        """SIGTERM, then check that it stopped cleanly and logged nothing wrong."""
        try:
            if self.proc.poll() is None:
                self.proc.send_signal(signal.SIGTERM)
            try:
                rc = self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
                raise AssertionError("the gateway process did not stop on SIGTERM:\n"
                                     + "".join(self.stderr)) from None
        finally:  # its pipes closed however it stopped (killed included)
            for pipe in (self.proc.stdout, self.proc.stderr):
                if pipe is not None:
                    with contextlib.suppress(ValueError):  # the reader thread's last line
                        pipe.close()
        text = "".join(self.stderr)
        assert rc == 0, f"the gateway process exited {rc}:\n{text}"
        bad = [ln for ln in self.stderr if ln.startswith(("ERROR", "CRITICAL", "Traceback"))
               and not any(re.search(e, ln) for e in self.expected_errors)]
        assert not bad, f"the gateway process logged errors:\n{text}"


async def ready(engine: Any, gateway: Gateway, timeout: float = 20.0) -> None:
    """Wait until the public port answers for the engine (/healthz through the gateway).
    Runs on the loop of ``engine`` (the ``GameServer`` under test)."""
    url = f"http://127.0.0.1:{gateway.port}/healthz"

    def answers() -> bool:
        try:
            with urllib.request.urlopen(url, timeout=5) as r:
                return r.status == 200
        except OSError:
            return False

    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while not await asyncio.to_thread(answers):
        if loop.time() > end:
            raise AssertionError(f"the gateway did not answer for the engine within "
                                 f"{timeout:g} s")
        await asyncio.sleep(0.05)


@dataclass
class Process:
    """An HTTP address of the service, for ``conftest.http_get``/``http_json``."""

    http_url: str


def processes(srv: Any) -> list[Process]:
    """The addresses that answer for the whole host: the server's own with one process,
    the public port (any gateway) with an engine and gateways."""
    return [Process(f"http://127.0.0.1:{public_port(srv)}/")]


def public_port(srv: Any) -> int:
    """The port clients are given: the gateways' when there are gateways."""
    return int(srv.public_port if srv.public_port is not None else srv.port)


async def service_stats(srv: Any) -> dict[str, Any]:
    """``/api/stats`` of the whole service, from its public port (one process answers
    for the whole host)."""
    from tests.server.conftest import http_json

    return await http_json(processes(srv)[0], "/api/stats")


@contextlib.contextmanager
def pair(data: Path, kw: dict[str, Any], expected_errors: tuple[str, ...] = ()
         ) -> Iterator[tuple[Gateway, dict[str, Any]]]:
    """A gateway on a free port in front of an engine socket; yields it and the arguments
    that make the server under test that engine. Of ``kw`` (the test server's arguments)
    a gateway is given what the host gives its gateways, of its ``limits``."""
    port = free_port()
    # (the engine removes the directory when it stops)
    with tempfile.TemporaryDirectory(prefix="cb-engine-", ignore_cleanup_errors=True) as private:
        sock = Path(private) / "engine.sock"
        gateway = Gateway(port, sock, expected_errors, kw.get("limits"))
        try:
            yield gateway, {"public_port": port, "engine_socket": sock}
        finally:
            gateway.stop()


@contextlib.asynccontextmanager
async def started(data: Path, expected_errors: tuple[str, ...] = (),
                  **kw: Any) -> AsyncIterator[Any]:
    """``GameServer(ServerConfig(data, **kw))`` started (and stopped at the end), as the
    engine of an engine and a gateway when ``current()`` is 2, for a test that gives the
    server arguments the conftest's ``server()`` does not take. ``expected_errors``: regular
    expressions of the errors the gateway may log (a test that provokes them)."""
    from clothball.server.app import GameServer, ServerConfig

    if current() == 1:
        srv = GameServer(ServerConfig(data, **kw))
        await srv.start()
        try:
            yield srv
        finally:
            await srv.stop()
        return
    with pair(data, kw, expected_errors) as (gateway, extra):
        srv = GameServer(ServerConfig(data, **kw, **extra))
        await srv.start()
        try:
            await ready(srv, gateway)
            srv.second_worker = gateway
            yield srv
        finally:
            await srv.stop()
