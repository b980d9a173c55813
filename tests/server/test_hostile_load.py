"""Hostile load, second round (issue 31), at a scale a CI machine runs: a join flood from a
few loopback addresses against a cluster host, its Redis then stopped (SIGSTOP); keep-alive
clients that hold the slots; a burst of ``create_room``; one address recording long rounds
against a small retention budget; a large index over budget at start-up; ``--cluster``
pointed at nothing. Throughout, the bound the issue asks for: ``/healthz`` answers within
0.5 s (sampled every 50 ms from a thread of its own), the show room's frames advance,
a newcomer gets a slot, other players' replays stay."""

from __future__ import annotations

import asyncio
import contextlib
import http.server
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest
from clothball.game.net.client import NetClient, ServerError
from clothball.game.wire import protocol as P
from clothball.server import headroom
from clothball.server.app import GameServer, ServerConfig
from clothball.server.directory import OnDemand
from clothball.server.headroom import (
    OWN_LOAD_CORES,
    SUSTAINED,
    Headroom,
    room_cost,
    thread_cost,
)
from clothball.server.hostproc import free_port, http_base
from clothball.server.limits import Limits
from clothball.server.room import RoomSettings
from clothball.server.sim import Samples
from clothball.server.sim.pool import cpu_loops_default
from clothball.server.storage.index import PRUNE_BATCH, Retention, owner_key
from clothball.server.storage.sqlite import SqliteIndex
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from tests.server.conftest import TINY, http_json, run, until
from tests.server.test_cluster import REDIS, cluster_host, redis_server
from tests.server.test_idle_connections import close_of, lobby_client

HEALTHZ_BOUND_S = 0.5  # the acceptance criterion
HELLO = json.dumps({"type": "hello", "version": P.PROTOCOL_VERSION})


# The sampler runs in a process of its own: the test's clients (a flood of them) must not
# delay its requests, only the server may.
SAMPLER = """
import sys, time, urllib.request
url, out = sys.argv[1], []
try:
    while True:
        t0 = time.perf_counter()
        try:
            with urllib.request.urlopen(url, timeout=10) as r:
                ok = r.status == 200 and r.read() == b"ok\\n"
        except OSError as e:
            ok = False
        print(f"{time.perf_counter() - t0:.4f} {int(ok)}", flush=True)
        time.sleep(0.05)
except KeyboardInterrupt:
    pass
"""


class Healthz:
    """``GET /healthz`` every 50 ms from a process of its own; every answer's latency."""

    def __init__(self, base: str) -> None:
        self.url = base.rstrip("/") + "/healthz"
        self.latencies: list[float] = []
        self.failures = 0
        self._proc: subprocess.Popen[str] | None = None

    def __enter__(self) -> Healthz:
        self._proc = subprocess.Popen([sys.executable, "-c", SAMPLER, self.url],
                                      stdout=subprocess.PIPE, text=True)
        return self

    def __exit__(self, *exc: object) -> None:
        assert self._proc is not None
        self._proc.send_signal(signal.SIGINT)
        try:
            out, _ = self._proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:  # never left running, its pipe never left open
            self._proc.kill()
            self._proc.communicate()
            raise
        for line in out.split("\n"):
            if line.strip():
                latency, ok = line.split()
                self.latencies.append(float(latency))
                self.failures += ok != "1"

    def check(self, what: str) -> None:
        assert not self.failures, f"{what}: /healthz failed {self.failures} times"
        assert len(self.latencies) >= 10, f"{what}: too few /healthz samples"
        worst = max(self.latencies)
        assert worst < HEALTHZ_BOUND_S, (
            f"{what}: /healthz took {worst:.2f} s (bound {HEALTHZ_BOUND_S} s; "
            f"{len(self.latencies)} samples, {sum(x > 0.1 for x in self.latencies)} over 0.1 s)")


async def frames_advance(get_frames: Any, seconds: int, what: str) -> list[int]:
    """The show room's frame counter, once a second for ``seconds`` s: it must advance in
    every second (the flood did not stop it)."""
    seen = [await get_frames()]
    for _ in range(seconds):
        # (a fixed one-second window on purpose: the bound is that the room never stands
        # still for a second under the flood; any frame in it passes)
        await asyncio.sleep(1.0)
        seen.append(await get_frames())
        assert seen[-1] > seen[-2], f"{what}: the show room stood still: {seen}"
    return seen


# --- 1 and 2: a join flood on a cluster host, then its Redis hung --------------------------


async def flooder(url: str, source: str, stop: asyncio.Event, sent: list[int]) -> None:
    """One client from ``source``: a join for an unknown room every 50 ms (the allowed 20
    control messages a second), replies read and dropped."""
    try:
        ws = await connect(url, local_addr=(source, 0), ping_interval=None, open_timeout=30)
    except (OSError, InvalidStatus):
        return
    await ws.send(HELLO)

    async def drain() -> None:
        with contextlib.suppress(ConnectionClosed):
            async for _ in ws:
                pass

    reader = asyncio.create_task(drain())
    try:
        while not stop.is_set():
            await ws.send(json.dumps({"type": "join", "room": secrets.token_urlsafe(6),
                                      "role": "spectator"}))
            sent[0] += 1
            await asyncio.sleep(0.05)
    except ConnectionClosed:
        pass
    finally:
        reader.cancel()
        await ws.close()


@pytest.mark.skipif(REDIS is None, reason="needs redis-server (apt: redis-server)")
def test_a_join_flood_and_a_hung_redis_never_stop_the_loop(tmp_path) -> None:
    with ExitStack() as stack:
        redis = stack.enter_context(redis_server(tmp_path))
        host = stack.enter_context(cluster_host(tmp_path, "a", redis))
        base = http_base(host.url)

        async def main() -> None:
            watcher = await NetClient.connect(host.url, role="spectator", room="main")

            def stats() -> Any:
                with urllib.request.urlopen(f"{base}/api/stats", timeout=10) as r:
                    return json.loads(r.read())

            async def frames() -> int:
                st = await asyncio.to_thread(stats)
                return int(st["rooms"]["main"]["frames"])

            stop = asyncio.Event()
            sent = [0]
            flood = [asyncio.create_task(flooder(host.url, f"127.0.0.{2 + k % 4}", stop, sent))
                     for k in range(32)]
            with Healthz(base) as hz:
                await asyncio.sleep(1.0)  # the flood under way (a fixed wait)
                await frames_advance(frames, 4, "join flood")
            hz.check("join flood")
            assert sent[0] > 32 * 20, sent  # the flood ran (about 640 joins a second)

            # Redis hangs (SIGSTOP): the flood goes on, and a join for an unknown room is
            # answered (once its wait for a read runs out), while frames and /healthz go on.
            assert redis.proc is not None
            redis.proc.send_signal(signal.SIGSTOP)
            try:
                with Healthz(base) as hz:
                    late = await NetClient.connect(host.url, name="late")
                    with pytest.raises(ServerError) as e:
                        await late.request("join", room="nowhere", role="spectator",
                                           timeout=15)
                    assert e.value.code == "unknown_room"
                    await frames_advance(frames, 4, "Redis stopped")
                hz.check("Redis stopped")
            finally:
                redis.proc.send_signal(signal.SIGCONT)
            stop.set()
            await asyncio.gather(*flood)
            # Redis answers again: the host is listed again, its rooms joinable.
            lobby = await NetClient.connect(host.url, name="after")
            await until_listed(lobby, "main")
            for c in (watcher, late, lobby):
                await c.close()

        run(main(), timeout=150)


async def until_listed(c: NetClient, rid: str, timeout: float = 15.0) -> None:
    end = time.monotonic() + timeout
    while True:
        reply = await c.request("list_rooms")
        if "directory_error" not in reply and rid in {r["id"] for r in reply["rooms"]}:
            return
        assert time.monotonic() < end, f"{rid} not listed again: {reply}"
        await asyncio.sleep(0.2)


def test_joins_waiting_for_the_directory_share_its_reads() -> None:
    """200 joins asking at once cost the store one read; one asking while a read is under
    way waits for the next (it may lack a room made meanwhile); a read that hangs costs a
    waiting join its timeout, no more."""
    async def main() -> None:
        calls: list[float] = []
        hang = asyncio.Event()

        async def read() -> None:
            calls.append(asyncio.get_running_loop().time())
            if hang.is_set():
                await asyncio.sleep(3600)
            await asyncio.sleep(0.05)

        reads = OnDemand(read, min_gap_s=0.1)
        assert all(await asyncio.gather(*(reads.after_now(5.0) for _ in range(200))))
        assert len(calls) == 1
        first = asyncio.create_task(reads.after_now(5.0))
        await until(lambda: len(calls) == 2, 5, "a read under way")
        late = asyncio.create_task(reads.after_now(5.0))
        assert await first and await late and len(calls) == 3
        assert calls[2] - calls[1] >= 0.1  # reads made for joins are spaced
        hang.set()
        assert not await reads.after_now(0.3)  # timed out: answered from the view as it is
        reads.cancel()

    run(main())


# --- 3: keep-alive clients holding the slots ------------------------------------------------


def test_keep_alive_pings_do_not_hold_a_slot_and_a_newcomer_gets_in(tmp_path) -> None:
    async def main() -> None:
        lim = Limits(lobby_idle_s=1.5, max_clients=24, conns_per_address=16, reserved_slots=3)
        async with server_of(tmp_path, lim) as srv:
            # 21 clients from two addresses, each pinging every 0.2 s, fill all but the
            # reserved slots: a third connection from those addresses is refused...
            pingers = [await lobby_client(srv, f"127.0.0.{2 + k % 2}") for k in range(21)]

            async def ping(ws: Any) -> None:
                with contextlib.suppress(ConnectionClosed):
                    while True:
                        await ws.send(json.dumps({"type": "ping", "t": 1.0}))
                        await asyncio.sleep(0.2)

            keep = [asyncio.create_task(ping(ws)) for ws in pingers]
            with pytest.raises(InvalidStatus) as e:
                await lobby_client(srv, "127.0.0.2")
            assert e.value.response.status_code == 503
            assert b"kept for new addresses" in (e.value.response.body or b"")
            # ... while a newcomer's address gets one of the reserved slots at once.
            newcomer = await lobby_client(srv, "127.0.0.9")
            # However often they ping, the lobby clients that never join are closed.
            closes = await asyncio.gather(*(close_of(ws, 30) for ws in pingers))
            assert set(closes) == {(1008, "idle: no request but pings for 1.5 s in the lobby")}
            for t in keep:
                t.cancel()
            # The slots are free again for anyone.
            again = await lobby_client(srv, "127.0.0.2")
            for ws in (newcomer, again):
                await ws.close()

    run(main())


@contextlib.asynccontextmanager
async def server_of(data: Path, limits: Limits, **kw: Any) -> Any:
    """A one-process server of TINY with these limits as given (admission included)."""
    settings = kw.pop("room_settings", RoomSettings(autoplay=True))
    srv = GameServer(ServerConfig(data, scenes={"tiny": TINY}, backend="cpu", port=0,
                                  limits=limits, room_settings=settings, **kw))
    await srv.start()
    try:
        yield srv
    finally:
        await srv.stop()


# --- 4: a burst of create_room ----------------------------------------------------------------


def test_a_burst_of_rooms_is_refused_at_once_past_the_measured_capacity(tmp_path) -> None:
    cost = room_cost(TINY, "cpu")  # what the server measures at start (once a process)
    fixed = thread_cost(TINY, "cpu")  # a thread's own, once a thread
    load, fit = 0.75, 6  # the capacity given: six TINY rooms, the show room one of them
    threads = min(fit, cpu_loops_default())  # the loops six rooms are spread over
    cores = (threads * fixed + (fit + 0.5) * cost) / load

    async def main() -> None:
        lim = Limits(admit_load=load, admit_cores=cores, max_rooms=64)
        async with server_of(tmp_path, lim) as srv:
            assert srv.headroom.cost(TINY) == cost
            # 32 create_room at once from 8 addresses (4 each: the per-address limit).
            makers = [await lobby_client(srv, f"127.0.0.{2 + k}") for k in range(8)]
            for k in range(32):
                await makers[k % 8].send(json.dumps({"type": "create_room", "name": f"r{k}",
                                                     "bots_allowed": False, "id": k}))
            replies = [await reply_to(makers[k % 8], k) for k in range(32)]
            made = [r for r in replies if r["type"] == "room_created"]
            refused = [r for r in replies if r["type"] == "error"]
            assert len(made) + len(refused) == 32, replies
            assert len(made) == fit - 1, refused[0]  # the show room is one that fits
            assert {e["code"] for e in refused} == {"server_busy"}
            assert all("at capacity" in e["message"] and "cores" in e["message"]
                       for e in refused)
            # The admitted rooms run (watched), and so does the show room.
            watchers = [await NetClient.connect(srv.ws_url, role="spectator", room=r["room"])
                        for r in made]
            main_room = srv.main_room
            assert main_room is not None
            watchers.append(await NetClient.connect(srv.ws_url, role="spectator",
                                                    room="main"))

            async def frames() -> int:
                return main_room.sim.frame

            with Healthz(srv.http_url) as hz:
                await frames_advance(frames, 3, "after the burst")
            hz.check("after the burst")
            for c in watchers:
                await c.close()
            for ws in makers:
                await ws.close()

    run(main(), timeout=120)


async def reply_to(ws: Any, rid: int) -> dict[str, Any]:
    """The reply to request ``rid`` (other messages skipped)."""
    while True:
        msg = json.loads(await asyncio.wait_for(ws.recv(), 30))
        if msg.get("re") == rid:
            return msg


class _Worker:
    def __init__(self) -> None:
        self.lateness = Samples(1000)
        self.skipped_frames = 0


class _Pool:
    def __init__(self) -> None:
        self.workers = [_Worker()]


class _Clock:
    """The process's CPU and wall clocks as the test sets them."""

    def __init__(self) -> None:
        self.cpu = self.wall = 0.0

    def process_time(self) -> float:
        return self.cpu

    def perf_counter(self) -> float:
        return self.wall


def test_late_frames_refuse_rooms_whatever_cpu_the_server_used(monkeypatch) -> None:
    """Frames 50 ms late while the process uses a tenth of a core (CPU taken from outside:
    steal, neighbours): its own rooms are late, so busy all the same (issue 40: at load ~9
    a ramp took 16 rooms while its skipped frames rose to 11 702/s), the refusal naming the
    outside cause; the same lateness while the process itself uses a core: busy, without
    it."""
    clock = _Clock()
    monkeypatch.setattr(headroom, "time", clock)
    pool = _Pool()
    hr = Headroom(pool, 5.0, load=0)  # type: ignore[arg-type]

    def window(spin: bool) -> None:
        for _ in range(50):
            pool.workers[0].lateness.append(0.05)
        clock.wall += 1.0
        clock.cpu += 1.0 if spin else 0.1
        hr.sample()

    for _ in range(SUSTAINED - 1):
        window(spin=False)
    assert hr.busy is None  # not yet sustained
    window(spin=False)
    assert hr.last.lateness_p99_ms == pytest.approx(50.0)
    assert hr.last.cpu_cores < OWN_LOAD_CORES
    assert hr.outside is not None and "CPU taken from outside" in hr.outside
    assert hr.busy is not None and "at capacity" in hr.busy and hr.outside in hr.busy
    assert hr.refusal(TINY, []) == hr.busy
    for _ in range(SUSTAINED):
        window(spin=True)
    assert hr.last.cpu_cores >= OWN_LOAD_CORES
    assert hr.outside is None
    assert hr.busy is not None and "at capacity" in hr.busy
    assert "outside" not in hr.busy
    assert hr.refusal(TINY, []) == hr.busy


def test_an_empty_server_admits_its_first_room_whatever_the_model_says(tmp_path) -> None:
    async def main() -> None:
        # Capacity for less than one room: an empty server still admits one.
        lim = Limits(admit_cores=room_cost(TINY, "cpu") / 10)
        async with server_of(tmp_path, lim, default_room=False) as srv:
            c = await NetClient.connect(srv.ws_url)
            made = await c.request("create_room", name="first")
            assert made["room"] in srv.lobby.rooms
            with pytest.raises(ServerError) as e:
                await c.request("create_room", name="second")
            assert e.value.code == "server_busy" and "at capacity" in e.value.message
            await c.close()

    run(main())


# --- 5: one address recording long rounds ---------------------------------------------------


def test_record_cap_s_is_bounded_by_the_host(tmp_path) -> None:
    async def main() -> None:
        async with server_of(tmp_path, Limits(record_cap_max_s=120), default_room=False) as srv:
            c = await NetClient.connect(srv.ws_url)
            with pytest.raises(ServerError) as e:
                await c.request("create_room", name="long", record_cap_s=3600)
            assert e.value.code == "bad_message"
            assert "record_cap_s 3600 is over this server's limit of 120 s" in e.value.message
            made = await c.request("create_room", name="ok", record_cap_s=120)
            assert srv.lobby.rooms[made["room"]].settings.record_cap_s == 120
            dflt = await c.request("create_room", name="default")  # 600 s asked by nobody
            assert srv.lobby.rooms[dflt["room"]].settings.record_cap_s == 120
            await c.close()

    run(main())


def header(k: int, ended: float, room: str, owner: str | None) -> dict[str, Any]:
    h = {"id": f"r{k:05d}-{room}", "room_id": room, "room_name": room, "scene": "tiny",
         "round": k, "players": [{"seat": 0, "name": f"p{k}"}], "scores": [0, 0, 0, 0],
         "started_at": ended - 1, "ended_at": ended, "duration_s": 1.0}
    if owner is not None:
        h["owner"] = owner
    return h


def test_one_address_cannot_flush_anothers_replays(tmp_path) -> None:
    """Retention 1 MiB, a quarter per address; each round ~100 KiB. Others' rounds (and
    the host's own) first, then one address records far past its share: its own oldest go,
    never another's, and what it keeps stays within its share."""
    budget = 1 << 20
    ret = Retention(budget, 1e9, budget // 4)
    store = SqliteIndex(tmp_path, retention=ret)
    blob = [(0, os.urandom(100_000))]
    t = 1.7e9
    others = [store.save(header(k, t + k, "calm", owner_key("198.51.100.7")), blob)["id"]
              for k in range(3, 5)]
    mine = [store.save(header(k, t + k, "show", None), blob)["id"] for k in range(3)]
    hog = owner_key("203.0.113.66")
    for k in range(5, 40):
        store.save(header(k, t + k, "hog", hog), blob)
    kept = {r["id"] for r in store.list(1000)}
    assert set(others) | set(mine) <= kept  # nobody else's round went
    hogs = [r for r in store.list(1000) if r["room_id"] == "hog"]
    assert hogs and sum(r["bytes"] for r in hogs) <= budget // 4
    assert hogs[0]["id"] == "r00039-hog"  # its newest kept
    assert store.bytes <= budget
    assert all("owner" not in r for r in store.list(1000))  # never listed
    assert "owner" not in (tmp_path / "replays" / "r00039-hog.cbr").read_bytes()[:4096] \
        .decode("latin-1")
    store.close()


# --- 6: a large index over budget at start-up -----------------------------------------------


def test_a_large_backlog_is_pruned_in_the_background_while_the_host_serves(tmp_path) -> None:
    n = 6000
    store = SqliteIndex(tmp_path)
    t = time.time() - n - 3600  # within replays_max_days: pruned for size only
    (tmp_path / "replays").mkdir(exist_ok=True)
    rounds = []
    for k in range(n):
        h = header(k, t + k, "old", None)
        (tmp_path / "replays" / f"{h['id']}.cbr").write_bytes(b"x" * 100)
        rounds.append((h, f"{h['id']}.cbr", 100))
    store.index_many(rounds)
    store.close()

    async def main() -> None:
        # Every round but the newest 50 (of 100 bytes each) is over the budget.
        lim = Limits(replays_max_mib=5000 / 2**20)
        async with server_of(tmp_path, lim) as srv:
            # Serving before the backlog is gone (it takes 30 batches, PRUNE_PAUSE_S apart).
            assert srv.store is not None and srv.store.rounds > 50
            with Healthz(srv.http_url) as hz:
                await until(lambda: srv.store.rounds == 50, 120, "the backlog pruned")
            hz.check("pruning a backlog")
            listed = await http_json(srv, "/api/replays?limit=100")
            assert [r["id"] for r in listed["replays"]] == \
                [f"r{k:05d}-old" for k in range(n - 1, n - 51, -1)]
        assert len(list((tmp_path / "replays").glob("*.cbr"))) == 50

    assert n // PRUNE_BATCH >= 20  # many batches, not one
    run(main(), timeout=150)


# --- 8: --cluster pointed at nothing --------------------------------------------------------


@contextlib.contextmanager
def http_port() -> Iterator[int]:
    """Something that is not Redis: an HTTP server on a free port."""
    srv = http.server.HTTPServer(("127.0.0.1", 0), http.server.BaseHTTPRequestHandler)
    th = threading.Thread(target=srv.serve_forever, daemon=True)
    th.start()
    try:
        yield srv.server_address[1]
    finally:
        srv.shutdown()
        srv.server_close()


def host_cmd(tmp: Path, url: str, *extra: str) -> list[str]:
    return [sys.executable, "-m", "clothball.game.cli", "host", "--workers", "1", "--port",
            "0", "--cluster", url, "--scene", "classic", "--backend", "cpu", "--data",
            str(tmp / "data"), *extra]


def test_a_cluster_that_cannot_be_reached_is_an_error_unless_optional(tmp_path) -> None:
    nothing = f"redis://127.0.0.1:{free_port()}/0"
    with http_port() as port:
        for url in (nothing, f"redis://127.0.0.1:{port}/0"):
            proc = subprocess.run(host_cmd(tmp_path, url), capture_output=True, text=True,
                                  timeout=60)
            out = proc.stdout + proc.stderr
            assert proc.returncode == 1, out
            lines = out.strip().splitlines()
            assert len(lines) == 1 and "Traceback" not in out, out
            assert lines[0].startswith(f"clothball host: the cluster's Redis at {url} does "
                                       "not answer (") and "--cluster-optional" in lines[0]
    text = started_and_stopped(host_cmd(tmp_path, nothing, "--cluster-optional"))
    assert f"NOT in a cluster: the Redis at {nothing} does not answer" in text
    assert "in the cluster at" not in text


def started_and_stopped(cmd: list[str]) -> str:
    """Runs a host until its status lines are out, stops it (SIGTERM); all it printed. It
    must stop cleanly."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None
    out = []
    try:
        for line in proc.stdout:
            out.append(line)
            if line.startswith("(only this machine can connect"):  # the last status line
                break
        proc.send_signal(signal.SIGTERM)  # (its stop handler is set before its first line)
        with proc.stdout:
            rest = proc.stdout.read()  # (not communicate: lines read ahead are in this buffer)
        proc.wait(60)
    finally:  # never left running, its pipe never left open, whatever happened above
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
    text = "".join(out) + rest
    assert proc.returncode == 0 and "Traceback" not in text, text
    return text


def test_the_status_line_names_the_cluster_it_is_in(tmp_path) -> None:
    if shutil.which("redis-server") is None:
        pytest.skip("needs redis-server")
    with redis_server(tmp_path) as redis:
        text = started_and_stopped(host_cmd(tmp_path, redis.url))
        assert f"in the cluster at {redis.url} as ws://" in text, text


def test_a_frame_loops_rooms_share_their_lateness_figures() -> None:
    """``/api/stats`` makes a frame loop's lateness figures once for the rooms whose views
    of its ring hold the same samples (``Samples.key``), and each room's are still its own
    where they differ: views made over one ring at different starts."""
    import numpy as np
    from clothball.server.sim.worker import RingSamples

    engine = np.zeros(1, dtype=[("lateness_count", "<u8"), ("lateness", "<f8", (64,))])
    a, b = RingSamples(engine), RingSamples(engine)
    engine["lateness"][0][:10] = np.arange(10)
    engine["lateness_count"][0] = 10
    assert a.key() == b.key() and np.array_equal(a.newest(), b.newest())
    b.clear()
    engine["lateness"][0][10:12] = [7.0, 8.0]
    engine["lateness_count"][0] = 12
    assert a.key() != b.key()
    assert list(b.newest()) == [7.0, 8.0] and len(a.newest()) == 12
    # a full ring: the loop's next sample, between two rooms' reads, keeps their key (one
    # computation for both, not one a room)
    engine["lateness_count"][0] = 200
    key = a.key()
    assert key == b.key()
    engine["lateness_count"][0] = 201
    assert a.key() == b.key() == key
