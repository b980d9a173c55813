"""Server test helpers, also used by the client and Falcon tests: a real server on
loopback (port 0) and real clients; a server on a thread of its own for tests that drive it
from plain (blocking) code (hypothesis examples, raw sockets), with the errors it logs
collected, so a test can assert that no exception escaped a connection handler."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
import time
import urllib.error
import urllib.request
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import pytest
from clothball.game.sim.scene import Scene
from clothball.server.app import GameServer, ServerConfig
from clothball.server.limits import Limits
from clothball.server.room import RoomSettings
from clothball.server.sim import RoomSim, SimPool
from clothball.server.thread import ServerThread

T = TypeVar("T")

# A small cloth keeps the room threads cheap on a 2-core machine.
TINY = Scene.load("classic").with_changes({"cloth": {"n": 16}})
TINY.name = "tiny"

# Rounds that end fast: the ball is thrown sideways off the cloth at the start.
# The engine backend of the servers the suites start: "cpu" here and in CI; the GPU run sets
# CLOTHBALL_TEST_BACKEND=cuda to run the same suites on the CUDA engine (tools/gpu_server.sh).
BACKEND = os.environ.get("CLOTHBALL_TEST_BACKEND", "cpu")
FAST = dict(first_to=2, countdown=0.2, reset_speed=3.0, grace=1.0, restart_delay=30.0)


def run(coro: Awaitable[T], timeout: float = 90.0) -> T:
    async def wrapped() -> T:
        return await asyncio.wait_for(coro, timeout)

    return asyncio.run(wrapped())


@contextlib.asynccontextmanager
async def _one_process_server(data: Path, *, bots: int = 0,
                              settings: RoomSettings | None = None, **kw: Any
                              ) -> AsyncIterator[GameServer]:
    """A started server (scene TINY, CPU, port 0) in this process; ``server`` (below) is
    the tests' entry, with a second process when asked for."""
    kw["limits"] = no_admission(kw.get("limits"))
    srv = GameServer(ServerConfig(data, scenes={"tiny": TINY}, backend=BACKEND, host="127.0.0.1",
                                  port=0, bots=bots, room_settings=settings or RoomSettings(),
                                  **kw))
    await srv.start()
    try:
        yield srv
    finally:
        await srv.stop()


def http_get_url(url: str) -> tuple[int, bytes, dict[str, str]]:
    """GET ``url`` (blocking): status, body and headers, an error status included."""
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, r.read(), dict(r.headers)
    except urllib.error.HTTPError as e:
        with e:
            return e.code, e.read(), dict(e.headers)


async def http_get(srv: GameServer, path: str) -> tuple[int, bytes, dict[str, str]]:
    return await asyncio.to_thread(http_get_url, srv.http_url.rstrip("/") + path)


async def http_json(srv: GameServer, path: str) -> Any:
    status, body, _ = await http_get(srv, path)
    assert status == 200, body
    return json.loads(body)


async def until(pred: Callable[[], bool], timeout: float = 10.0, what: str = "") -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while not pred():
        if loop.time() > end:
            raise AssertionError(f"timed out waiting for {what or pred}")
        await asyncio.sleep(0.01)


@contextlib.contextmanager
def started_room(deliver: Callable[[Any], None] | None = None,
                 pool: SimPool | None = None,
                 deliver_mesh: Callable[[bytes], None] | None = None) -> Iterator[RoomSim]:
    """A started ``TINY`` room on the CPU engine in ``pool`` (else in a pool of its own,
    closed after), stopped after."""
    own = pool is None
    pool = SimPool() if pool is None else pool
    sim = RoomSim(TINY, "cpu", pool=pool, deliver=deliver, deliver_mesh=deliver_mesh)
    try:
        sim.start()
        yield sim
    finally:
        sim.stop()
        if own:
            pool.close()


def children() -> set[int] | None:
    """This process's child processes now, those exited and not yet reaped included (a
    test's teardown must wait for each one it started): Linux's
    /proc/self/task/*/children; None where that cannot be read."""
    found: set[int] = set()
    try:
        tasks = list(Path("/proc/self/task").iterdir())
    except OSError:
        return None
    for task in tasks:
        try:
            found.update(int(pid) for pid in (task / "children").read_text().split())
        except FileNotFoundError:
            if task.exists():  # (a thread that ended meanwhile has none)
                return None  # a kernel without CONFIG_PROC_CHILDREN
        except OSError:
            pass
    return found


def hand_of(room: Any, seat: int) -> tuple[int, Any]:
    """The hand a room's newest frame applied for a seat, (HIP seq, position), (0, None)
    for none, whoever wrote it (the player's lane, in the engine or its gateway:
    docs/architecture.md), read from the frame loop's block."""
    sim = room.sim
    if sim.slot is None:
        return 0, None
    r = sim.worker.rooms_view
    seq = int(r["applied_seq"][sim.slot, seat])
    return seq, (r["hips"][sim.slot, seat].copy() if seq else None)


def local_server(data: Path, *, bots: int = 0, **settings: Any) -> ServerThread:
    """A server with room ``main`` (scene TINY, CPU) on its own thread, not started: what
    ``clothball play --local`` runs. ``settings``: the main room's ``RoomSettings``."""
    settings.setdefault("autoplay", True)
    return ServerThread(data, scenes={TINY.name: TINY}, backend=BACKEND, bots=bots,
                        room_settings=RoomSettings(**settings), limits=no_admission(None))


def no_admission(limits: Limits | None) -> Limits:
    """The limits with admission control off: a test of something else must not depend on
    how much spare capacity a loaded test machine has (tests/server/test_admission.py tests
    admission, with the default)."""
    return (limits or Limits()).replace(admit_lateness_ms=0.0, admit_load=0.0)


# --- a server on a thread, for blocking test code, with the errors it logs ---------------


class ErrorLog(logging.Handler):
    """Keeps every ERROR (or worse) record: handler crashes, failed saves, stopped rooms
    (or every record from ``level`` up)."""

    def __init__(self, level: int = logging.ERROR) -> None:
        super().__init__(level)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)

    def texts(self) -> list[str]:
        return [f"{r.name}: {r.getMessage()} {r.exc_text or ''}" for r in self.records]


class LiveServer:
    def __init__(self, st: ServerThread, errors: ErrorLog) -> None:
        assert st.server is not None and st.loop is not None
        self.st, self.srv, self.loop, self.errors = st, st.server, st.loop, errors

    def call(self, fn: Any, *args: Any) -> Any:
        """Run ``fn(*args)`` on the server's loop (its state is not thread-safe) and wait."""
        return self.st.call(lambda _srv: fn(*args))

    def http(self, raw: bytes, timeout: float = 5.0) -> bytes:
        """Send raw bytes to the HTTP port (the public one: a gateway's with two processes);
        the whole answer (until the server closes)."""
        port = self.srv.public_port if self.srv.public_port is not None else self.srv.port
        with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
            s.sendall(raw)
            return recv_all(s)


def recv_all(s: socket.socket, within_s: float | None = None) -> bytes:
    """What a socket receives until the other side closes it (or its timeout; or, given
    ``within_s``, that many seconds from now at most, in all)."""
    chunks = []
    end = None if within_s is None else time.monotonic() + within_s
    while True:
        if end is not None:
            if (left := end - time.monotonic()) <= 0:
                break
            s.settimeout(left)
        try:
            b = s.recv(65536)
        except (TimeoutError, ConnectionResetError):
            break
        if not b:
            break
        chunks.append(b)
    return b"".join(chunks)


@contextlib.contextmanager
def _one_process_live_server(data: Path, **kw: Any) -> Iterator[LiveServer]:
    """A server on a thread of its own, its errors collected; ``live_server`` (below) is
    the tests' entry, with a second process when asked for."""
    errors = ErrorLog()
    # The server's loggers only: a test's own clients log under websockets.client.
    loggers = [logging.getLogger("clothball"), logging.getLogger("websockets.server")]
    for lg in loggers:
        lg.addHandler(errors)
    kw.setdefault("room_settings", RoomSettings(bots_allowed=False, unguarded=True))
    kw["limits"] = no_admission(kw.get("limits"))
    st = ServerThread(data, scenes={"tiny": TINY}, backend=BACKEND, **kw)
    try:
        st.start(30)
        try:
            yield LiveServer(st, errors)
        finally:
            st.stop()
    finally:
        for lg in loggers:
            lg.removeHandler(errors)


# --- CLOTHBALL_TEST_WORKERS=2: the server as the first of two processes sharing one port ---
# (tests/server/workers.py says how): server() and live_server(), the tests' entries, over
# _one_process_server() and _one_process_live_server() above.


def _as_given(kw: dict[str, Any]) -> dict[str, Any]:
    """The GameServer arguments server() and live_server() give, for the second process."""
    return {"scenes": {"tiny": TINY}, "backend": BACKEND, "host": "127.0.0.1", **kw,
            "limits": no_admission(kw.get("limits"))}


@contextlib.asynccontextmanager
async def server(data: Path, *, bots: int = 0, settings: RoomSettings | None = None,
                 **kw: Any) -> AsyncIterator[GameServer]:
    from tests.server import workers

    if workers.current() == 1:
        async with _one_process_server(data, bots=bots, settings=settings, **kw) as srv:
            yield srv
        return
    given = _as_given({**kw, "bots": bots, "room_settings": settings or RoomSettings()})
    with workers.pair(data, given) as (second, extra):
        async with _one_process_server(data, bots=bots, settings=settings, **kw,
                                       **extra) as srv:
            await workers.ready(srv, second)
            srv.second_worker = second  # type: ignore[attr-defined]
            yield srv


@contextlib.contextmanager
def live_server(data: Path, **kw: Any) -> Iterator[LiveServer]:
    from tests.server import workers

    if workers.current() == 1:
        with _one_process_live_server(data, **kw) as ls:
            yield ls
        return
    with workers.pair(data, _as_given(kw)) as (second, extra):
        with _one_process_live_server(data, **kw, **extra) as ls:
            asyncio.run_coroutine_threadsafe(workers.ready(ls.srv, second), ls.loop).result(30)
            ls.srv.second_worker = second  # type: ignore[attr-defined]
            yield ls


@pytest.fixture(autouse=True)
def server_processes(request: pytest.FixtureRequest) -> Iterator[int]:
    """How many processes the test's servers have: CLOTHBALL_TEST_WORKERS (default 1), or
    this test's parameter (pytest_generate_tests)."""
    from tests.server import workers

    n = getattr(request, "param", workers.WORKERS)
    with workers.using(n):
        yield n


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    """In a plain run (CI), the issue 17 suites' tests that start a server run with one
    process and with two ("1proc", "2procs")."""
    from tests.server import workers

    module = metafunc.module.__name__.rpartition(".")[2]
    if workers.WORKERS == 1 and module in workers.SUITES and \
            workers.starts_a_server(metafunc.function):
        metafunc.parametrize("server_processes", [1, 2], ids=["1proc", "2procs"],
                             indirect=True)
