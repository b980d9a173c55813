"""The server suites against a host of two server processes (issue 17: ``--workers 2``
passes the server, reconnect, fault and hostile-input suites).

With ``CLOTHBALL_TEST_WORKERS=2`` the conftest's ``server()`` and ``live_server()`` run
their server as the first of two processes sharing one public port, as
``clothball host --workers 2`` runs them: the server under test stays in the test process
(so a test can still look at its rooms and counters), configured as a worker (the room
directory in the data directory, the shared port, a port of its own), and a second real
process (``tests/server/worker_proc.py``) is started with the same arguments. ``ws_url``
and ``http_url`` name the shared port, so the kernel spreads the tests' connections over
both processes: a client that lands on the process without its room is redirected and
follows, a new room may be placed on either, a reconnect token may arrive at either.

The second process must stop cleanly (exit 0) and log no error or traceback: its stderr is
checked when the server context ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import pickle
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

from clothball.game.cli.host import DIRECTORY_FILE
from clothball.server.directory import PUBLISH_S, SqliteDirectory
from clothball.server.hostproc import free_port

WORKERS = int(os.environ.get("CLOTHBALL_TEST_WORKERS", "1") or "1")
if WORKERS not in (1, 2):
    raise RuntimeError(f"CLOTHBALL_TEST_WORKERS must be 1 or 2, got {WORKERS}")

_now = [WORKERS]  # the processes of the servers started now (the conftest's fixture sets it)

# The suites of issue 17. Without CLOTHBALL_TEST_WORKERS, each of their tests that starts a
# server (calls server() or live_server()) runs twice, with one process and with two (the
# conftest's pytest_generate_tests): what CI runs.
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


WORKER_PROC = Path(__file__).with_name("worker_proc.py")
FIRST_ID, SECOND_ID = "test-worker-0", "test-worker-1"  # their host ids in the directory


class SecondWorker:
    """The other process of the pair: started with the test server's arguments, read, and
    stopped (SIGTERM) at the end."""

    def __init__(self, data: Path, kw: dict[str, Any], shared_port: int,
                 expected_errors: tuple[str, ...] = ()) -> None:
        self.shared_port = shared_port
        self.expected_errors = expected_errors  # regular expressions of errors it may log
        self.stderr: list[str] = []
        args = {**kw, "data_dir": str(data), "shared_port": shared_port,
                "host_id": SECOND_ID}
        fd, name = tempfile.mkstemp(suffix=".kwargs")
        with os.fdopen(fd, "wb") as f:
            pickle.dump(args, f)
        try:
            self.proc = subprocess.Popen([sys.executable, str(WORKER_PROC), name],
                                         stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                         text=True)
            assert self.proc.stdout is not None and self.proc.stderr is not None
            threading.Thread(target=self._read_stderr, daemon=True).start()
            first: list[str] = []
            reader = threading.Thread(target=lambda: first.append(self.proc.stdout.readline()),
                                      daemon=True)  # type: ignore[union-attr]
            reader.start()
            reader.join(60)
            try:
                self.port = int(json.loads(first[0])["port"])
            except (IndexError, ValueError, KeyError) as e:
                self.proc.kill()
                self.proc.wait(10)
                raise AssertionError("the second server process did not start:\n"
                                     + "".join(self.stderr)) from e
        finally:
            os.unlink(name)

    def _read_stderr(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.stderr.append(line)

    def stop(self) -> None:
        """SIGTERM, then check that it stopped cleanly and logged nothing wrong."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            rc = self.proc.wait(60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
            raise AssertionError("the second server process did not stop on SIGTERM:\n"
                                 + "".join(self.stderr)) from None
        for pipe in (self.proc.stdout, self.proc.stderr):
            if pipe is not None:
                with contextlib.suppress(ValueError):  # the reader thread's last line
                    pipe.close()
        text = "".join(self.stderr)
        assert rc == 0, f"the second server process exited {rc}:\n{text}"
        bad = [ln for ln in self.stderr if ln.startswith(("ERROR", "CRITICAL", "Traceback"))
               and not any(re.search(e, ln) for e in self.expected_errors)]
        assert not bad, f"the second server process logged errors:\n{text}"


def first_worker_kw(data: Path, shared_port: int) -> dict[str, Any]:
    """What the process under test is given on top of the test's arguments to be the first
    of the pair (``serve`` in ``game/cli/host.py`` gives each process the same)."""
    data.mkdir(parents=True, exist_ok=True)
    return {"directory": SqliteDirectory(data / DIRECTORY_FILE), "shared_port": shared_port,
            "host_id": FIRST_ID}


async def ready(first: Any, second: SecondWorker, timeout: float = 20.0) -> None:
    """Wait until each process has read the other from the directory (as the supervisor
    waits before giving out the address): the first lists the second among its peers, the
    second lists the first's public rooms. Runs on the loop of ``first`` (the
    ``GameServer`` under test)."""
    want = {r.id for r in first.lobby.rooms.values() if r.public}
    url = f"http://127.0.0.1:{second.port}/api/rooms"

    def listed() -> set[str]:
        with urllib.request.urlopen(url, timeout=5) as r:
            return {room["id"] for room in json.loads(r.read())["rooms"]}

    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while True:
        peers = first.lobby.peers
        if peers is not None and SECOND_ID in peers.hosts and \
                want <= await asyncio.to_thread(listed):
            return
        if loop.time() > end:
            raise AssertionError("the two server processes did not see each other within "
                                 f"{timeout:g} s")
        await asyncio.sleep(PUBLISH_S / 5)


@dataclass
class Process:
    """One process of the service, for ``conftest.http_get``/``http_json``: its own HTTP
    address (not the shared port, where the kernel picks the process)."""

    http_url: str


def processes(srv: Any) -> list[Process]:
    """Every process of the service, the server under test first: one without
    ``CLOTHBALL_TEST_WORKERS=2``, two with it (``srv.second_worker``, set by the
    conftest)."""
    ports = [srv.port]
    if getattr(srv, "second_worker", None) is not None:
        ports.append(srv.second_worker.port)
    return [Process(f"http://127.0.0.1:{p}/") for p in ports]


def public_port(srv: Any) -> int:
    """The port clients are given: the shared one when there are two processes."""
    return int(srv.shared_port if srv.shared_port is not None else srv.port)


async def service_stats(srv: Any) -> dict[str, Any]:
    """``/api/stats`` of the whole service: with two processes, each one's (statistics
    are per process, docs/protocol.md "Several processes") summed: the counters added, the
    rooms of both (each room lives on one)."""
    from tests.server.conftest import http_json

    each = [await http_json(p, "/api/stats") for p in processes(srv)]
    total = dict(each[0])
    for other in each[1:]:
        for k in COUNTERS:
            total[k] += other[k]
        total["rooms"] = {**total["rooms"], **other["rooms"]}
    return total


COUNTERS = ("messages_in", "messages_out", "bad_messages", "rounds_saved", "rounds_not_saved",
            "refused_connections", "rooms_stopped", "clients", "cpu_s")


@contextlib.contextmanager
def pair(data: Path, kw: dict[str, Any], expected_errors: tuple[str, ...] = ()
         ) -> Iterator[tuple[SecondWorker, dict[str, Any]]]:
    """The second process started with ``kw`` (the test server's arguments); yields it and
    the arguments to give the server under test."""
    port = free_port()
    extra = first_worker_kw(data, port)
    second = SecondWorker(data, kw, port, expected_errors)
    try:
        yield second, extra
    finally:
        try:
            second.stop()
        finally:
            extra["directory"].close()


@contextlib.asynccontextmanager
async def started(data: Path, expected_errors: tuple[str, ...] = (),
                  **kw: Any) -> AsyncIterator[Any]:
    """``GameServer(data, **kw)`` started (and stopped at the end), as the first of two
    processes when ``current()`` is 2, for a test that gives the server arguments the
    conftest's ``server()`` does not take. ``expected_errors``: regular expressions of the
    errors the second process may log (a test that provokes them)."""
    from clothball.server.app import GameServer

    if current() == 1:
        srv = GameServer(data, **kw)
        await srv.start()
        try:
            yield srv
        finally:
            await srv.stop()
        return
    with pair(data, kw, expected_errors) as (second, extra):
        srv = GameServer(data, **kw, **extra)
        await srv.start()
        try:
            await ready(srv, second)
            srv.second_worker = second
            yield srv
        finally:
            await srv.stop()
