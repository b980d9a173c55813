"""Where every room of one service lives: the room directory the hosts of a cluster share.

Each host (its engine: ``docs/architecture.md``) publishes, every ``PUBLISH_S``, its own
address, its load (rooms, clients) and its rooms' public info, and reads back everyone's.
A host that stops publishing for ``ttl`` seconds (it died) drops out with its rooms.
Listing, joining and placing a room use the last snapshot read, so a websocket handler
never waits on the store, and the event loop never calls it: every call runs on the
server's directory threads with a timeout (``IO_TIMEOUT_S``). A join for a room the
snapshot lacks (made elsewhere since the last read) waits, that connection alone, for
the next read (``OnDemand``: one read for every join waiting, at most one every
``MIN_READ_GAP_S``), never a read of its own. A private room is listed for routing only
(its id and where it lives); its join code never leaves its process.

``RedisDirectory`` is the cluster's (``--cluster``). ``SqliteDirectory`` keeps it in one
SQLite file: servers of one machine share it with no server to run (the tests' clusters
of ``GameServer`` objects in one process).
"""

from __future__ import annotations

import asyncio
import json
import logging
import sqlite3
import threading
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

log = logging.getLogger("clothball.server")

PUBLISH_S = 0.5  # s between a process's publications (and reads of the others')
DEFAULT_TTL = 5.0  # s without a publication after which a process counts as gone
# s a directory call may take (Redis' socket timeout; a join's wait for a fresh read): a
# hung store costs a join at most this, and the rooms and /healthz nothing.
IO_TIMEOUT_S = 1.0
MIN_READ_GAP_S = 0.1  # s between reads made for joins (a flood of them shares each read)


class NotInView(Exception):
    """A room id the directory's last snapshot lacks, while another process may have made
    it since: the request is answered after the next read (``Lobby.get``)."""

    def __init__(self, room_id: str) -> None:
        super().__init__(f"room {room_id!r} not in the directory's last snapshot")
        self.room_id = room_id


class OnDemand:
    """Runs ``fn`` (a coroutine function) for whoever asks, coalesced: ``after_now`` returns
    once a run begun after the call has ended (or ``timeout`` has passed: False), however
    many ask meanwhile; runs are at least ``min_gap_s`` apart. Used for the directory reads
    that joins wait for and the publication a new room waits for, so that a flood of them
    costs the store a few calls a second, not one each."""

    def __init__(self, fn: Callable[[], Awaitable[None]], min_gap_s: float = 0.0) -> None:
        self.fn = fn
        self.min_gap_s = min_gap_s
        self.runs = 0
        self._next: asyncio.Future[None] | None = None  # the run not yet begun
        self._task: asyncio.Task[None] | None = None

    async def after_now(self, timeout: float) -> bool:
        if self._next is None:
            self._next = asyncio.get_running_loop().create_future()
        fut = self._next
        if self._task is None or self._task.done():
            self._task = asyncio.create_task(self._serve())
        try:
            async with asyncio.timeout(timeout):  # (wait_for may swallow a cancellation)
                await asyncio.shield(fut)
        except TimeoutError:
            return False
        return True

    async def _serve(self) -> None:
        loop = asyncio.get_running_loop()
        while self._next is not None:
            fut, self._next = self._next, None
            began = loop.time()
            try:
                await self.fn()
            except Exception as e:  # the store is away: the waiting requests go on
                log.debug("directory call failed: %s", e)
            finally:
                self.runs += 1
                if not fut.done():
                    fut.set_result(None)
            await asyncio.sleep(max(0.0, began + self.min_gap_s - loop.time()))

    def cancel(self) -> None:
        if self._task is not None:
            self._task.cancel()


class Moved(Exception):
    """A request for a room (or a new room) that another process or host serves: the
    client is answered ``redirect`` {``url``} and sends the request there."""

    def __init__(self, url: str, reason: str, with_fields: dict[str, Any] | None = None) -> None:
        super().__init__(reason)
        self.url = url
        self.reason = reason
        self.with_fields = with_fields or {}  # to add to the request when sent there


@dataclass
class HostEntry:
    """One server process as the directory knows it."""

    host_id: str
    address: str  # its own websocket URL (ws://host:port/ws)
    rooms: int = 0
    clients: int = 0
    busy: bool = False  # at capacity by its own measure (server.headroom): takes no rooms

    @property
    def load(self) -> tuple[bool, int, int]:
        return (self.busy, self.rooms, self.clients)


@dataclass
class Snapshot:
    hosts: dict[str, HostEntry] = field(default_factory=dict)
    # room id -> (host id, public, info); info is the room's lobby entry
    rooms: dict[str, tuple[str, bool, dict[str, Any]]] = field(default_factory=dict)

    def locate(self, room_id: str) -> HostEntry | None:
        entry = self.rooms.get(room_id)
        return None if entry is None else self.hosts.get(entry[0])

    def listing(self) -> list[dict[str, Any]]:
        """Every live process's public rooms, each marked with the address it lives at."""
        out = []
        for _rid, (host_id, public, info) in sorted(self.rooms.items()):
            host = self.hosts.get(host_id)
            if public and host is not None:
                out.append({**info, "host": host.address})
        return out


class Directory(Protocol):
    """What a server process needs from the shared room directory."""

    ttl: float

    def publish(self, host: HostEntry, rooms: list[tuple[str, bool, dict[str, Any]]]) -> None:
        """Replace this process's entry and rooms (room id, public, info)."""

    def read(self) -> Snapshot:
        """The live processes and their rooms."""

    def withdraw(self, host_id: str) -> None:
        """This process leaves (a clean stop)."""

    def claim(self, room_id: str, host_id: str) -> bool:
        """Takes ``room_id`` for ``host_id`` before its room exists (the show room), at once
        for all: True if it is now this host's, False if another live host holds it."""

    def close(self) -> None: ...


class SqliteDirectory:
    """The directory in one SQLite file shared by the processes of one machine."""

    def __init__(self, path: Path, ttl: float = DEFAULT_TTL) -> None:
        self.path = Path(path)
        self.ttl = ttl
        self._lock = threading.Lock()  # one connection, used from worker threads in turn
        self._db = sqlite3.connect(self.path, timeout=5.0, isolation_level=None,
                                   check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA busy_timeout=5000")
        self._db.executescript("""
            CREATE TABLE IF NOT EXISTS hosts2 (host_id TEXT PRIMARY KEY, address TEXT NOT NULL,
                rooms INTEGER NOT NULL, clients INTEGER NOT NULL, busy INTEGER NOT NULL,
                seen REAL NOT NULL);
            CREATE TABLE IF NOT EXISTS rooms (room_id TEXT PRIMARY KEY, host_id TEXT NOT NULL,
                public INTEGER NOT NULL, info TEXT NOT NULL);
            CREATE INDEX IF NOT EXISTS rooms_host ON rooms (host_id);
        """)

    def publish(self, host: HostEntry, rooms: list[tuple[str, bool, dict[str, Any]]]) -> None:
        now = time.time()
        with self._lock:
            db = self._db
            db.execute("BEGIN IMMEDIATE")
            try:
                db.execute("INSERT OR REPLACE INTO hosts2 VALUES (?, ?, ?, ?, ?, ?)",
                           (host.host_id, host.address, host.rooms, host.clients,
                            int(host.busy), now))
                db.execute("DELETE FROM rooms WHERE host_id = ?", (host.host_id,))
                # Processes gone (silent for the TTL): their rooms died with them.
                gone = now - self.ttl
                db.execute("DELETE FROM rooms WHERE host_id IN "
                           "(SELECT host_id FROM hosts2 WHERE seen < ?)", (gone,))
                db.execute("DELETE FROM hosts2 WHERE seen < ?", (gone,))
                # A room id another live process holds stays its own (never taken over).
                db.executemany(
                    "INSERT OR IGNORE INTO rooms VALUES (?, ?, ?, ?)",
                    [(rid, host.host_id, int(public), json.dumps(info))
                     for rid, public, info in rooms])
                db.execute("COMMIT")
            except BaseException:
                db.execute("ROLLBACK")
                raise

    def read(self) -> Snapshot:
        live_after = time.time() - self.ttl
        with self._lock:
            hosts = self._db.execute(
                "SELECT host_id, address, rooms, clients, busy FROM hosts2 WHERE seen >= ?",
                (live_after,)).fetchall()
            rows = self._db.execute("SELECT room_id, host_id, public, info FROM rooms").fetchall()
        snap = Snapshot({h[0]: HostEntry(h[0], h[1], h[2], h[3], bool(h[4])) for h in hosts})
        for rid, host_id, public, info in rows:
            if host_id in snap.hosts:
                snap.rooms[rid] = (host_id, bool(public), json.loads(info))
        return snap

    def claim(self, room_id: str, host_id: str) -> bool:
        live_after = time.time() - self.ttl
        with self._lock:
            db = self._db
            db.execute("BEGIN IMMEDIATE")
            try:
                row = db.execute(
                    "SELECT r.host_id FROM rooms r JOIN hosts2 h ON h.host_id = r.host_id "
                    "WHERE r.room_id = ? AND h.seen >= ?", (room_id, live_after)).fetchone()
                if row is None:  # free, or held by a process gone: this one's now
                    # Private until the room itself is published (nothing to list yet).
                    db.execute("INSERT OR REPLACE INTO rooms VALUES (?, ?, 0, '{}')",
                               (room_id, host_id))
                db.execute("COMMIT")
            except BaseException:
                db.execute("ROLLBACK")
                raise
        return row is None or row[0] == host_id

    def withdraw(self, host_id: str) -> None:
        with self._lock:
            self._db.execute("DELETE FROM rooms WHERE host_id = ?", (host_id,))
            self._db.execute("DELETE FROM hosts2 WHERE host_id = ?", (host_id,))

    def close(self) -> None:
        with self._lock:
            self._db.close()


class RedisDirectory:
    """The directory of a cluster of hosts in Redis (``clothball host --cluster
    redis://HOST:PORT/DB``). Keys, all under ``prefix``:

    - ``host:<id>``: the host's address and load (JSON), expiring after the TTL: a host
      that dies leaves the directory by itself;
    - ``rooms:<id>``: its rooms (a hash: room id -> JSON {public, info}), same expiry;
    - ``room:<room id>``: which host holds that id, claimed with SET NX (a host never takes
      an id another live host holds), same expiry;
    - channel ``lobby``: a message whenever a host's rooms change, so the others re-read at
      once instead of at their next publication.
    """

    def __init__(self, url: str, ttl: float = DEFAULT_TTL, prefix: str = "clothball:") -> None:
        import redis  # the cluster's store: needed only with --cluster

        self.url = url
        self.ttl = ttl
        self.prefix = prefix
        self._redis = redis.Redis.from_url(url, socket_timeout=IO_TIMEOUT_S,
                                           socket_connect_timeout=IO_TIMEOUT_S)
        self._last_rooms: dict[str, str] = {}
        self.conflicts: list[str] = []  # room ids this host found held by another

    def _ms(self) -> int:
        return max(1, int(self.ttl * 1000))

    def publish(self, host: HostEntry, rooms: list[tuple[str, bool, dict[str, Any]]]) -> None:
        p = self.prefix
        r = self._redis
        ttl = self._ms()
        # Claim (or keep) every room id; one that another host holds is not listed here.
        pipe = r.pipeline(transaction=False)
        for rid, _public, _info in rooms:
            pipe.set(f"{p}room:{rid}", host.host_id, nx=True, px=ttl)
            pipe.get(f"{p}room:{rid}")
        claimed = pipe.execute()
        mine: dict[str, str] = {}
        for k, (rid, public, info) in enumerate(rooms):
            owner = claimed[2 * k + 1]
            if owner is not None and owner.decode() != host.host_id:
                if rid not in self.conflicts:
                    self.conflicts.append(rid)
                    log.error("room id %s is held by host %s: not listed from this host", rid,
                              owner.decode())
                continue
            mine[rid] = json.dumps({"public": public, "info": info})
        pipe = r.pipeline(transaction=True)
        pipe.set(f"{p}host:{host.host_id}", json.dumps(
            {"address": host.address, "rooms": host.rooms, "clients": host.clients,
             "busy": host.busy}), px=ttl)
        pipe.delete(f"{p}rooms:{host.host_id}")
        if mine:
            pipe.hset(f"{p}rooms:{host.host_id}", mapping=mine)
            pipe.pexpire(f"{p}rooms:{host.host_id}", ttl)
            for rid in mine:
                pipe.pexpire(f"{p}room:{rid}", ttl)
        for rid in set(self._last_rooms) - set(mine):
            pipe.delete(f"{p}room:{rid}")  # closed here: the id is free again
        pipe.execute()
        if mine != self._last_rooms:
            r.publish(f"{p}lobby", host.host_id)
        self._last_rooms = mine

    def read(self) -> Snapshot:
        p = self.prefix
        r = self._redis
        keys = sorted(r.scan_iter(match=f"{p}host:*", count=500))
        snap = Snapshot()
        if not keys:
            return snap
        values = r.mget(keys)
        pipe = r.pipeline(transaction=False)
        ids = []
        for key, raw in zip(keys, values, strict=True):
            if raw is None:
                continue  # expired between the scan and the read
            host_id = key.decode()[len(f"{p}host:"):]
            d = json.loads(raw)
            snap.hosts[host_id] = HostEntry(host_id, d["address"], int(d["rooms"]),
                                            int(d["clients"]), bool(d.get("busy")))
            ids.append(host_id)
            pipe.hgetall(f"{p}rooms:{host_id}")
        for host_id, rooms in zip(ids, pipe.execute(), strict=True):
            for rid, raw in rooms.items():
                d = json.loads(raw)
                snap.rooms[rid.decode()] = (host_id, bool(d["public"]), d["info"])
        return snap

    def claim(self, room_id: str, host_id: str) -> bool:
        key = f"{self.prefix}room:{room_id}"
        if self._redis.set(key, host_id, nx=True, px=self._ms()):
            return True  # the publications that follow keep it
        owner = self._redis.get(key)
        return owner is not None and owner.decode() == host_id

    def withdraw(self, host_id: str) -> None:
        p = self.prefix
        pipe = self._redis.pipeline(transaction=True)
        for rid in self._last_rooms:
            pipe.delete(f"{p}room:{rid}")
        pipe.delete(f"{p}host:{host_id}", f"{p}rooms:{host_id}")
        pipe.publish(f"{p}lobby", host_id)
        pipe.execute()
        self._last_rooms = {}

    def check(self) -> None:
        """Raises ``ValueError`` (one line: what went wrong) unless a Redis answers PING at
        ``url`` now: nothing listening, another service there, a password wanted."""
        try:
            ok = self._redis.ping()
        except Exception as e:
            first = (str(e).splitlines() or [""])[0][:160]
            raise ValueError(f"{type(e).__name__}: {first}" if first else type(e).__name__
                             ) from None
        if ok is not True:
            raise ValueError(f"PING answered {ok!r}, not as a Redis does")

    def changes(self) -> Any:
        """A pub/sub subscription to lobby changes (``get_message`` polls it)."""
        sub = self._redis.pubsub(ignore_subscribe_messages=True)
        sub.subscribe(f"{self.prefix}lobby")
        return sub

    def close(self) -> None:
        self._redis.close()
