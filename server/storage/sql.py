"""The replay index: the data directory's recorded rounds (files under ``replays/``, in
the format of ``game.wire.replay``) and their SQLite index ``index.sqlite``.

A file is indexed only once it is complete on disk (SQLite in WAL mode), so a crash loses at
most the round being written: never the index or an earlier round. At start-up, leftover
``.tmp`` files are deleted and any finished file the index lacks is indexed from its own
header.

The index has two connections: one that reads (listings, lookups) and one that writes, so a
listing never waits behind a write waiting for a lock. A write that finds the index locked
by another program (``clothball replays prune``, an ``sqlite3`` shell) waits: SQLite's
``busy_timeout`` (``BUSY_TIMEOUT_S``), then retries until ``lock_wait_s`` has passed; a
round whose index row could not be written keeps its file and is indexed at the next start.

Retention (``Retention``): the store keeps at most ``max_bytes`` of indexed rounds and none
older than ``max_age_s``; the oldest rounds go first, each one's index row and file together
(``_remove``: the files renamed aside, the rows' deletion committed, the files removed; a
crash in between is resolved at the next start), at most ``PRUNE_BATCH`` rounds a call: the
server prunes after each save and, in the background, until the backlog is gone (a store
opened over a large backlog serves at once). The newest round is never pruned for size, so
the last round played can always be watched. The rounds of one owner (the address whose
room played them, kept only as ``owner_key``, never listed) keep at most
``max_owner_bytes``: past that, that owner's oldest go, never another's.

A private room's rounds carry ``access`` (``access_key(room, code)``) in their header and
index row: they are listed and served only to a request that names the room's code.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import hashlib
import json
import logging
import os
import sqlite3
import threading
import time
import typing
import urllib.parse
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..game.wire.replay import ID_RE, ReplayError, read_replay_header, write_replay

log = logging.getLogger("clothball.server")

BUSY_TIMEOUT_S = 5.0  # SQLite's own wait for a lock (busy_timeout), per attempt
LOCK_WAIT_S = 60.0  # how long a write keeps retrying a locked index in all
PRUNE_BATCH = 200  # rounds removed by one prune call (one transaction)

SCHEMA = """
CREATE TABLE IF NOT EXISTS rounds (
    id TEXT PRIMARY KEY,
    room_id TEXT NOT NULL,
    room_name TEXT NOT NULL,
    scene TEXT NOT NULL,
    round INTEGER NOT NULL,
    players TEXT NOT NULL,
    conceded_edge INTEGER,
    conceded_by INTEGER,
    scores TEXT NOT NULL,
    started_at REAL NOT NULL,
    ended_at REAL NOT NULL,
    duration_s REAL NOT NULL,
    file TEXT NOT NULL,
    bytes INTEGER NOT NULL,
    access TEXT,
    owner TEXT
);
CREATE INDEX IF NOT EXISTS rounds_ended ON rounds (ended_at);
"""

# Every query the HTTP API makes walks one of these in its ORDER BY order and stops at
# LIMIT (see ``_QUERIES`` and tests/server/test_index_queries.py): no scan of the rounds.
# ``round_players`` holds each round's seat names (with the columns the filters need), so
# ``?player=`` is an index search, not a look into every round's JSON.
INDEXES = """
CREATE INDEX IF NOT EXISTS rounds_public ON rounds (access, ended_at DESC, id);
CREATE INDEX IF NOT EXISTS rounds_room ON rounds (room_id, access, ended_at DESC, id);
CREATE TABLE IF NOT EXISTS round_players (
    round_id TEXT NOT NULL,
    name TEXT NOT NULL,
    room_id TEXT NOT NULL,
    access TEXT,
    ended_at REAL NOT NULL,
    PRIMARY KEY (round_id, name)
) WITHOUT ROWID;
CREATE INDEX IF NOT EXISTS round_players_name
    ON round_players (name, access, ended_at DESC, round_id);
CREATE INDEX IF NOT EXISTS round_players_name_room
    ON round_players (name, room_id, access, ended_at DESC, round_id);
CREATE TRIGGER IF NOT EXISTS rounds_delete_players AFTER DELETE ON rounds BEGIN
    DELETE FROM round_players WHERE round_id = old.id;
END;
"""
INDEX_VERSION = 1  # PRAGMA user_version once ``round_players`` holds every round

COLUMNS = ("id", "room_id", "room_name", "scene", "round", "players", "conceded_edge",
           "conceded_by", "scores", "started_at", "ended_at", "duration_s", "file", "bytes",
           "access", "owner")
# Added to an index made before the column existed (SQLite, PostgreSQL). No index of its
# own: a quota check reads one owner's rows once per saved round, on the writer thread,
# and an index more would not fit a nearly full disk's first write (tests/server/
# test_faults.py).
OWNER_DDL = "ALTER TABLE rounds ADD COLUMN owner TEXT"


class IndexUnavailable(Exception):
    """The replay index's database cannot be reached or used now (a PostgreSQL index
    whose server is down): one line saying so. Rounds are kept as files meanwhile."""


def _statements(script: str) -> list[str]:
    """``script`` split into whole statements (a trigger's body holds ``;`` too)."""
    out, cur = [], ""
    for line in script.splitlines(keepends=True):
        cur += line
        if sqlite3.complete_statement(cur):
            out.append(cur.strip())
            cur = ""
    return out


@dataclass(frozen=True)
class Retention:
    """How much the store keeps: indexed rounds' bytes in all, and their age (by end)."""

    max_bytes: int = 2 << 30
    max_age_s: float = 30 * 86400.0
    max_owner_bytes: int | None = None  # one owner's rounds (None: only max_bytes)

    @classmethod
    def from_limits(cls, limits: Any) -> Retention:
        """From ``server.limits.Limits``' ``replays_max_mib``, ``replays_max_days`` and
        ``replays_address_share``."""
        total = int(limits.replays_max_mib * 2**20)
        return cls(total, limits.replays_max_days * 86400.0,
                   int(total * limits.replays_address_share))

    def describe(self) -> str:
        return f"at most {self.max_bytes / 2**20:g} MiB, {self.max_age_s / 86400:g} days"


def owner_key(address: str) -> str:
    """What a round's owner (the address that created its room) is kept as: a hash, so the
    index holds no address; it is never listed."""
    return hashlib.sha256(f"clothball-owner:{address}".encode()).hexdigest()[:32]


def access_key(room_id: str, code: str) -> str:
    """What a private room's rounds are locked with: a hash of its id and join code (the
    code itself is never stored)."""
    return hashlib.sha256(f"clothball-replay:{room_id}:{code}".encode()).hexdigest()


class ReplayStore:
    """The data directory's replays: files under ``replays/`` and the index ``index.sqlite``.

    Thread-safe: the server calls it from worker threads (``asyncio.to_thread``).

    This class is the embedded index (SQLite) and holds every query; the shared one
    (``PostgresReplayStore``) runs the same SQL on PostgreSQL and overrides how it connects
    and runs statements (``_fetch``, ``_x``, ``_xmany``, ``_write``), which rows are its
    own (``_mine``: its host's) and how a round is kept back while the database is away
    (``save``, ``retry_index``).
    """

    columns: tuple[str, ...] = COLUMNS
    host: str | None = None  # whose files the rows name (a shared index: an HTTP address)
    index_error: str | None = None  # why the index cannot be written now (shared: its server)

    def __init__(self, data_dir: Path | str, *, lock_wait_s: float = LOCK_WAIT_S,
                 retention: Retention | None = None, recover: bool = True,
                 read_only: bool = False, prune_at_open: bool = True) -> None:
        """``recover``: remove leftover ``.tmp`` files and index unindexed rounds (what the
        server does at start; a command run beside a live server must not: its ``.tmp``
        files are rounds being written). ``retention``: pruned after each save; None keeps
        everything. ``read_only``: list and serve what is there, write nothing (a read-only
        or full disk); the index must exist."""
        self._setup(data_dir, lock_wait_s, retention, read_only)
        if read_only:
            self._wdb: sqlite3.Connection | None = None
            self._db = self._connect_read_only()
            self.refresh_usage()
            return
        self.replays.mkdir(parents=True, exist_ok=True)
        self._wdb = self._connect()
        try:
            if self._wdb.execute("PRAGMA user_version").fetchone()[0] < INDEX_VERSION:
                self._write(self._migrate)
            if not self._has_owner():
                self._write(self._add_owner)
            self._db = self._connect()
            # 32 MiB of pages (default 2): a count over 100 000 rounds' index entries then
            # reads memory, not the OS's file cache (~6 ms instead of ~9).
            self._db.execute("PRAGMA cache_size=-32768")
        except BaseException:
            self._wdb.close()
            raise
        self.identity = self._identity()
        if recover:
            self._recover()
            if retention is not None and prune_at_open:
                self.prune_all(retention)
        self.refresh_usage()

    def _setup(self, data_dir: Path | str, lock_wait_s: float, retention: Retention | None,
               read_only: bool) -> None:
        """What every kind of index starts with (before it connects)."""
        self.dir = Path(data_dir)
        self.replays = self.dir / "replays"
        self.read_only = read_only
        self.lock_wait_s = lock_wait_s
        self.retention = retention
        self.rounds = 0  # indexed rounds and their bytes, as of the last write or refresh
        self.bytes = 0
        self.lock_waits = 0  # writes that found the index locked and waited
        self._lock = threading.Lock()  # the reading connection
        self._wlock = threading.Lock()  # the writing connection
        self._counts: dict[tuple[str, tuple[Any, ...]], int] = {}
        self._counts_stamp: Any = (-1, -1)
        self._counts_lock = threading.Lock()
        self.identity: tuple[int, int] | None = None

    def _identity(self) -> tuple[int, int] | None:
        """The index file's device and inode: another file (or none) there means the data
        directory was removed or replaced under the server."""
        try:
            st = (self.dir / "index.sqlite").stat()
        except OSError:
            return None
        return st.st_dev, st.st_ino

    def still_there(self) -> bool:
        """The index this store has open is still the data directory's."""
        return not self.read_only and self._identity() == self.identity and \
            self.replays.is_dir()

    def _connect_read_only(self) -> sqlite3.Connection:
        """The index for reading only: as it is (``mode=ro``), or, where SQLite cannot make
        its shared-memory file (a read-only filesystem), as a file nothing changes
        (``immutable=1``)."""
        path = self.dir / "index.sqlite"
        if not path.is_file():
            raise FileNotFoundError(2, "no replay index", str(path))
        last: sqlite3.Error | None = None
        for mode in ("mode=ro", "immutable=1"):
            db = sqlite3.connect(f"file:{urllib.parse.quote(str(path))}?{mode}", uri=True,
                                 check_same_thread=False, isolation_level=None,
                                 timeout=BUSY_TIMEOUT_S)
            try:
                version = db.execute("PRAGMA user_version").fetchone()[0]
                db.execute("SELECT COUNT(*) FROM rounds").fetchone()
            except sqlite3.Error as e:
                db.close()
                last = e
                continue
            if version < INDEX_VERSION:
                db.close()
                raise sqlite3.DatabaseError("the index is from an older version and cannot "
                                            "be brought up to date read-only")
            return db
        assert last is not None
        raise last

    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.dir / "index.sqlite", check_same_thread=False,
                             isolation_level=None, timeout=BUSY_TIMEOUT_S)
        try:
            db.execute(f"PRAGMA busy_timeout = {int(BUSY_TIMEOUT_S * 1000)}")
            self._retry(lambda: db.execute("PRAGMA journal_mode=WAL"))
            db.execute("PRAGMA synchronous=NORMAL")
        except BaseException:
            db.close()
            raise
        return db

    def _retry(self, fn: Callable[[], Any]) -> Any:
        """``fn()``, again while the index is locked by another connection, for at most
        ``lock_wait_s`` in all (each attempt already waits ``BUSY_TIMEOUT_S`` itself)."""
        deadline = time.monotonic() + self.lock_wait_s
        pause = 0.05
        while True:
            try:
                return fn()
            except sqlite3.OperationalError as e:
                if not _locked(e) or time.monotonic() + pause > deadline:
                    raise
                self.lock_waits += 1
                time.sleep(pause)
                pause = min(1.0, pause * 2)

    def _write(self, fn: Callable[[], Any]) -> Any:
        """``fn()`` in one write transaction, retried while the index is locked."""
        def once() -> Any:
            with self._transaction():
                return fn()

        return self._retry(once)

    def _migrate(self) -> None:
        """Creates the index, or brings an older one up to date: the query indexes, and
        ``round_players`` filled from the rounds it already holds; in one transaction (a new
        index's first write is then a few pages: it fits a nearly full disk). Called in a
        write transaction."""
        db = self._wdb
        if db.execute("PRAGMA user_version").fetchone()[0] >= INDEX_VERSION:
            return
        for stmt in _statements(SCHEMA):
            db.execute(stmt)
        have = {r[1] for r in db.execute("PRAGMA table_info(rounds)")}
        if "access" not in have:  # an index from before private rounds were locked
            db.execute("ALTER TABLE rounds ADD COLUMN access TEXT")
        if "owner" not in have:  # from before per-address quotas
            db.execute(OWNER_DDL)
        for stmt in _statements(INDEXES):
            db.execute(stmt)
        db.execute("DELETE FROM round_players")
        db.execute(
            "INSERT OR IGNORE INTO round_players (round_id, name, room_id, access, ended_at)"
            " SELECT rounds.id, json_extract(p.value, '$.name'), rounds.room_id,"
            " rounds.access, rounds.ended_at FROM rounds, json_each(rounds.players) AS p"
            " WHERE json_extract(p.value, '$.name') IS NOT NULL")
        db.execute(f"PRAGMA user_version = {INDEX_VERSION}")

    def _has_owner(self) -> bool:
        """The index has the ``owner`` column (an index of this version may not: it came
        later). Read, not written: a disk that refuses writes still opens the index."""
        assert self._wdb is not None
        return "owner" in {r[1] for r in self._wdb.execute("PRAGMA table_info(rounds)")}

    def _add_owner(self) -> None:
        assert self._wdb is not None
        if not self._has_owner():
            self._wdb.execute(OWNER_DDL)

    @contextlib.contextmanager
    def _transaction(self) -> Iterator[None]:
        """Holds the writing connection; commits what the block did, or none of it."""
        if self._wdb is None:
            raise sqlite3.OperationalError("the replay index is open read-only")
        with self._wlock:
            self._wdb.execute("BEGIN IMMEDIATE")
            try:
                yield
            except BaseException:
                self._wdb.execute("ROLLBACK")
                raise
            self._wdb.execute("COMMIT")

    def lock_is_free(self) -> bool:
        """Whether a write could take the index's lock now (tried, then let go)."""
        try:
            with self._transaction():
                pass
        except sqlite3.OperationalError as e:
            if _locked(e):
                return False
            raise
        return True

    def _recover(self) -> None:
        for tmp in self.replays.glob("*.cbr.tmp"):
            log.info("removing unfinished replay %s", tmp.name)
            tmp.unlink(missing_ok=True)
        known = self._known()
        for aside in self.replays.glob("*.cbr.del"):  # a prune cut short (see _remove)
            rid = aside.name[:-len(".cbr.del")]
            if rid in known:
                os.replace(aside, self.replays / f"{rid}.cbr")
            else:
                aside.unlink(missing_ok=True)
        self.reconcile()

    def _known(self) -> set[str]:
        """The ids of the indexed rounds whose files are this store's."""
        mine, args = self._mine()
        return {r[0] for r in self._fetch(f"SELECT id FROM rounds WHERE {mine}", args)}

    def reconcile(self) -> int:
        """Indexes the finished files the index lacks, from their own header. Returns how
        many."""
        indexed = 0
        known = self._known()
        for path in sorted(self.replays.glob("*.cbr")):
            rid = path.stem
            if rid in known:
                continue
            try:
                header = read_replay_header(path)
                self._index(header, path)
                indexed += 1
                log.info("indexed replay %s from its header", path.name)
            except (OSError, ReplayError, ValueError, KeyError, EOFError) as e:
                log.warning("ignoring damaged replay %s: %s", path.name, e)
        return indexed

    def _index(self, header: dict[str, Any], path: Path) -> None:
        self.index_many([(header, path.name, path.stat().st_size)])

    def index_many(self, rounds: list[tuple[dict[str, Any], str, int]]) -> None:
        """Index rounds (header, file name under ``replays/``, its size) in one transaction."""
        rows, players = [], []
        for header, name, size in rounds:
            row = self._tuple(header, name, size)
            rows.append(row)
            names = player_names(header["players"])
            players += [(row[0], n, row[1], row[14], row[10]) for n in sorted(names)]
        ids = [(r[0],) for r in rows]

        def write() -> None:
            self._xmany("DELETE FROM round_players WHERE round_id = ?", ids)
            self._xmany("DELETE FROM rounds WHERE id = ?", ids)
            self._xmany(f"INSERT INTO rounds ({', '.join(self.columns)}) "
                        f"VALUES ({', '.join('?' * len(self.columns))})", rows)
            self._xmany("INSERT INTO round_players (round_id, name, room_id, access, ended_at) "
                        "VALUES (?, ?, ?, ?, ?)", players)

        self._write(write)

    def _tuple(self, header: dict[str, Any], name: str, size: int) -> tuple[Any, ...]:
        """A round's index row, in ``columns`` order, from its header."""
        row = (
            header["id"], header["room_id"], header["room_name"], header["scene"],
            int(header["round"]), json.dumps(header["players"]),
            header.get("conceded_edge"), header.get("conceded_by"),
            json.dumps(header["scores"]), float(header["started_at"]),
            float(header["ended_at"]), float(header["duration_s"]), name, size,
            header.get("access"), header.get("owner"),
        )
        return row + ((self.host,) if "host" in self.columns else ())

    # --- how statements run: the SQLite connections (PostgresReplayStore overrides) -------
    def _fetch(self, q: str, args: Any = ()) -> list[tuple[Any, ...]]:
        """The rows of a query, on the reading connection."""
        with self._lock:
            return self._db.execute(q, args).fetchall()

    def _x(self, q: str, args: Any = ()) -> None:
        """One statement on the writing connection (inside ``_write``)."""
        assert self._wdb is not None
        self._wdb.execute(q, args)

    def _xmany(self, q: str, rows: list[tuple[Any, ...]]) -> None:
        assert self._wdb is not None
        self._wdb.executemany(q, rows)

    def _mine(self) -> tuple[str, list[Any]]:
        """The condition on the rows whose files are this store's (every row of an
        embedded index; of a shared one, this host's)."""
        return "1 = 1", []

    def _count_stamp(self) -> Any:
        """What changes whenever the index does (None: counts are not remembered)."""
        with self._lock:
            # data_version moves with other connections' commits, total_changes with ours
            return (self._db.execute("PRAGMA data_version").fetchone()[0],
                    self._db.total_changes)

    def retry_index(self) -> None:
        """Writes the index rows kept back while the index was unavailable (a shared
        index only; the embedded one indexes such rounds from their files, ``reconcile``)."""

    def save(self, header: dict[str, Any], records: list[tuple[int, bytes]]) -> dict[str, Any]:
        """Write one round's file, then index it. Returns the index row."""
        rid = header["id"]
        if not ID_RE.match(rid):
            raise ValueError(f"replay id {rid!r} is not valid")
        if self.read_only:
            raise sqlite3.OperationalError("the replay index is open read-only")
        path = self.replays / f"{rid}.cbr"
        # The owner goes into the index only: a replay file is anyone's to download.
        write_replay(path, {k: v for k, v in header.items() if k != "owner"}, records)
        self._index(header, path)
        row = self.get(rid)
        assert row is not None
        if self.retention is not None:
            self.prune_owner(self.retention, header.get("owner"))
            self.prune(self.retention)
        else:
            self.refresh_usage()
        return row

    def refresh_usage(self) -> None:
        """``rounds`` and ``bytes`` read again from the index (another program may prune)."""
        mine, args = self._mine()
        n, b = self._fetch("SELECT COUNT(*), COALESCE(SUM(bytes), 0) FROM rounds WHERE "
                           + mine, args)[0]
        self.rounds, self.bytes = int(n), int(b)

    def prune(self, retention: Retention, *, now: float | None = None,
              dry_run: bool = False, limit: int | None = PRUNE_BATCH) -> list[dict[str, Any]]:
        """Removes rounds ``retention`` does not keep, oldest first, at most ``limit`` (None:
        all): every round that ended more than ``max_age_s`` ago, then the oldest until the
        rest fit in ``max_bytes`` (never the newest). Each round's row and file go together
        (see the module's docstring). Returns the rounds removed (or, ``dry_run``, that
        would be); fewer than ``limit``: nothing more is due."""
        now = time.time() if now is None else now
        mine, margs = self._mine()
        n, total, oldest = self._fetch(
            "SELECT COUNT(*), COALESCE(SUM(bytes), 0), MIN(ended_at) FROM rounds WHERE "
            + mine, margs)[0]
        if total <= retention.max_bytes and (oldest is None or
                                             oldest >= now - retention.max_age_s):
            self.refresh_usage()
            return []  # the usual case after a save: nothing to read row by row
        # The oldest rows only, as many as may go: what is left must fit, newest kept.
        want = n if limit is None else min(n, limit)
        rows = self._fetch(f"SELECT id, ended_at, bytes FROM rounds WHERE {mine} "
                           "ORDER BY ended_at, id LIMIT ?", [*margs, want])
        excess, doomed = total - retention.max_bytes, []
        for i, (rid, ended_at, size) in enumerate(rows):
            too_old = ended_at < now - retention.max_age_s
            if not (too_old or (excess > 0 and i < n - 1)):
                break
            doomed.append(rid)
            excess -= size
        out = self._prune_rows(doomed, dry_run, retention.describe())
        self.refresh_usage()
        return out

    def prune_all(self, retention: Retention) -> list[dict[str, Any]]:
        """``prune`` until nothing more is due (``clothball replays prune``; a server
        prunes batch by batch in the background instead)."""
        out: list[dict[str, Any]] = []
        while True:
            batch = self.prune(retention)
            out += batch
            if len(batch) < PRUNE_BATCH:
                return out

    def prune_owner(self, retention: Retention, owner: str | None) -> list[dict[str, Any]]:
        """Removes ``owner``'s oldest rounds (never its newest) until its rounds fit in
        ``max_owner_bytes``: one owner's excess never costs another owner's rounds."""
        cap = retention.max_owner_bytes
        if owner is None or cap is None:
            return []
        rows = self._fetch("SELECT id, bytes FROM rounds WHERE owner = ? "
                           "ORDER BY ended_at DESC, id DESC", [owner])
        kept, doomed = 0, []
        for i, (rid, size) in enumerate(rows):
            if i > 0 and (doomed or kept + size > cap):
                doomed.append(rid)
            else:
                kept += size
        return self._prune_rows(doomed[::-1], False, f"at most {cap / 2**20:g} MiB of one "
                                "address's rooms")

    def _prune_rows(self, rids: list[str], dry_run: bool, why: str) -> list[dict[str, Any]]:
        out = [row for row in (self.get(rid) for rid in rids) if row is not None]
        if out and not dry_run:
            self._remove_many([r["id"] for r in out])
            log.info("pruned %d replays (%.1f MiB) to keep %s", len(out),
                     sum(r["bytes"] for r in out) / 2**20, why)
        return out

    def _remove(self, rid: str) -> None:
        self._remove_many([rid])

    def _remove_many(self, rids: list[str]) -> None:
        """Deletes the rounds' rows and their files, all or none: the files are renamed
        aside (``.cbr.del``), the rows' deletion committed, then the files removed. If the
        commit fails the files are put back; after a crash, the next start puts back a file
        whose row is still there and removes one whose row is gone (``_recover``)."""
        paths = [(self.replays / f"{rid}.cbr", self.replays / f"{rid}.cbr.del") for rid in rids]
        keys = [(rid,) for rid in rids]

        def remove() -> None:
            for path, aside in paths:
                with contextlib.suppress(FileNotFoundError):  # already gone: the row goes
                    os.replace(path, aside)
            self._xmany("DELETE FROM round_players WHERE round_id = ?", keys)
            self._xmany("DELETE FROM rounds WHERE id = ?", keys)

        try:
            self._write(remove)
        except BaseException:
            for path, aside in paths:
                if aside.exists() and not path.exists():
                    os.replace(aside, path)
            raise
        for _, aside in paths:
            self._discard(aside)

    @staticmethod
    def _discard(path: Path) -> None:
        path.unlink(missing_ok=True)

    def _queries(self, room_id: str | None, player: str | None, code: str | None,
                 limit: int = 100, offset: int = 0) -> dict[str, tuple[str, list[Any]]]:
        """The SQL (and its arguments) of ``list`` and ``count`` for these filters. The
        rounds a request may see: public ones, plus a private room's when the request names
        that room and its code. With ``player`` the filter reads ``round_players``."""
        table, rid = ("rounds", "id") if player is None else ("round_players", "round_id")
        base, args = "", []
        if player is not None:
            base, args = "name = ? AND ", [player]
        if room_id is not None:
            base, args = base + "room_id = ? AND ", [*args, room_id]
        # One arm per access value, each an index range already in page order: SQLite merges
        # them and stops at LIMIT (an OR would sort every row of the room first).
        arms = [(base + "access IS NULL", args)]
        if room_id is not None and code is not None:
            arms.append((base + "access = ?", [*args, access_key(room_id, code)]))
        # The page's ids from the index alone (a deep OFFSET steps over index entries, not
        # rows), then those rows by primary key.
        page = " UNION ALL ".join(f"SELECT {rid} AS id, ended_at FROM {table} WHERE {w}"
                                  for w, _ in arms)
        count = " + ".join(f"(SELECT COUNT(*) FROM {table} WHERE {w})" for w, _ in arms)
        every = [a for _, arm_args in arms for a in arm_args]
        return {
            "list": (f"SELECT {', '.join(self.columns)} FROM rounds WHERE id IN (SELECT id "
                     f"FROM ({page} ORDER BY ended_at DESC, id LIMIT ? OFFSET ?) AS page) "
                     "ORDER BY ended_at DESC, id", [*every, limit, offset]),
            "count": (f"SELECT {count}", every),
        }

    def list(self, limit: int = 100, offset: int = 0, room_id: str | None = None, *,
             player: str | None = None, code: str | None = None) -> list[dict[str, Any]]:
        """Newest first. ``player``: only rounds where a seat had that name; ``code``: a
        private room's code (with ``room_id``) to see its rounds too."""
        q, args = self._queries(room_id, player, code, limit, offset)["list"]
        rows = self._fetch(q, args)
        return [self._row(r) for r in rows]

    def count(self, room_id: str | None = None, *, player: str | None = None,
              code: str | None = None) -> int:
        """How many rounds ``list`` with the same filters would page through. Remembered
        until the index changes (counting 100 000 rows costs ~10 ms; a listing's pages all
        ask the same count)."""
        q, args = self._queries(room_id, player, code)["count"]
        key = (q, tuple(args))
        stamp = self._count_stamp()
        if stamp is None:
            return int(self._fetch(q, args)[0][0])
        with self._counts_lock:
            if stamp != self._counts_stamp:
                self._counts.clear()
                self._counts_stamp = stamp
            n = self._counts.get(key)
        if n is None:
            n = int(self._fetch(q, args)[0][0])  # as of ``stamp`` or newer
            with self._counts_lock:
                if stamp == self._counts_stamp:
                    if len(self._counts) >= 256:
                        self._counts.clear()
                    self._counts[key] = n
        return n

    def _all(self, what: str, room_id: str | None, player: str | None
             ) -> tuple[str, list[Any]]:
        where, args = [], []
        if room_id is not None:
            where, args = ["room_id = ?"], [room_id]
        if player is not None:
            where.append("id IN (SELECT round_id FROM round_players WHERE name = ?)")
            args.append(player)
        return (f"SELECT {what} FROM rounds" + (" WHERE " + " AND ".join(where)
                                                 if where else ""), args)

    def list_all(self, limit: int = 100, room_id: str | None = None,
                 player: str | None = None) -> list[dict[str, Any]]:
        """Newest first, private rooms' rounds too: the host's own view
        (``clothball replays list``), never the HTTP API's."""
        q, args = self._all(", ".join(self.columns), room_id, player)
        rows = self._fetch(q + " ORDER BY ended_at DESC, id LIMIT ?", [*args, limit])
        return [self._row(r) for r in rows]

    def count_all(self, room_id: str | None = None, player: str | None = None) -> int:
        q, args = self._all("COUNT(*)", room_id, player)
        return int(self._fetch(q, args)[0][0])

    def file_of(self, rid: str) -> Path | None:
        """The round's file whoever's it is (the host's view), if indexed and there."""
        if self._get(rid) is None:
            return None
        path = self.replays / f"{rid}.cbr"
        return path if path.is_file() else None

    def query_plans(self) -> dict[str, list[str]]:
        """SQLite's plan (``EXPLAIN QUERY PLAN``) of every query the HTTP API can make, by a
        name for it, as "PARENT:STEP" lines (parent 0: the outermost query): what tests
        check for scans and sorts of the rounds."""
        queries = {"get": (f"SELECT {', '.join(self.columns)} FROM rounds WHERE id = ?",
                           ["x"])}
        for room in (None, "r"):
            for player in (None, "p"):
                for code in (None, "c") if room else (None,):
                    for what, q in self._queries(room, player, code).items():
                        queries[f"{what} room={room} player={player} code={code}"] = q
        with self._lock:
            return {name: [f"{r[1]}:{r[3]}" for r in
                           self._db.execute("EXPLAIN QUERY PLAN " + q, args)]
                    for name, (q, args) in queries.items()}

    def _get(self, rid: str) -> dict[str, Any] | None:
        if not ID_RE.match(rid):
            return None
        rows = self._fetch(f"SELECT {', '.join(self.columns)} FROM rounds WHERE id = ?", [rid])
        return None if not rows else dict(zip(self.columns, rows[0], strict=True))

    def get(self, rid: str) -> dict[str, Any] | None:
        r = self._get(rid)
        return None if r is None else self._row(tuple(r.values()))

    def path_of(self, rid: str, code: str | None = None) -> Path | None:
        """The round's file, if it exists and the caller may have it (a private room's
        round only with that room's code)."""
        r = self._get(rid)
        if r is None:
            return None
        if r["access"] is not None and (
            code is None or access_key(r["room_id"], code) != r["access"]
        ):
            return None
        path = self.replays / f"{rid}.cbr"
        return path if path.is_file() else None

    def locate(self, rid: str, code: str | None = None) -> Path | str | None:
        """Where the round's file is, if the caller may have it: a path here, or (a shared
        index) the download URL on the host that holds it; None: no such round for them."""
        r = self._get(rid)
        if r is None or (r["access"] is not None and (
                code is None or access_key(r["room_id"], code) != r["access"])):
            return None
        path = self.replays / f"{rid}.cbr"
        if path.is_file():
            return path
        owner = r.get("host")
        if owner and owner != self.host:
            url = f"{owner.rstrip('/')}/api/replays/{rid}.cbr"
            return url + (f"?code={urllib.parse.quote(code)}" if code is not None else "")
        return None

    def _row(self, r: tuple[Any, ...]) -> dict[str, Any]:
        d = dict(zip(self.columns, r, strict=True))
        d["players"] = json.loads(d["players"])
        d["scores"] = json.loads(d["scores"])
        d["private"] = d.pop("access") is not None
        del d["file"], d["owner"]  # who played is listed; which address made the room, not
        return d

    def close(self) -> None:
        with self._lock, self._wlock:
            self._db.close()
            if self._wdb is not None:
                self._wdb.close()


def player_names(players: Any) -> set[str]:
    """The names a round is found by (``?player=``): each seat's, and everyone who held a
    seat during the round (``held_by``: a player who took it mid-round, or left it)."""
    names: set[str] = set()
    for p in players if isinstance(players, list) else ():
        if not isinstance(p, dict):
            continue
        held = p.get("held_by")
        for who in [p, *(held if isinstance(held, list) else ())]:
            if isinstance(who, dict) and isinstance(who.get("name"), str):
                names.add(who["name"])
    return names


def _postgres_ddl() -> list[str]:
    """The index's tables for PostgreSQL: the SQLite schema's, in PostgreSQL's words (8-byte
    floats and sizes, ids ordered by their bytes as SQLite orders them), with ``host``: the
    HTTP address of the host that holds each round's file. No trigger: a round's players
    are deleted with it by the statements that delete it (``_remove``, ``index_many``)."""
    swaps = [(" REAL ", " DOUBLE PRECISION "), ("bytes INTEGER", "bytes BIGINT"),
             ("id TEXT PRIMARY KEY", 'id TEXT COLLATE "C" PRIMARY KEY'),
             ("round_id TEXT NOT NULL", 'round_id TEXT COLLATE "C" NOT NULL'),
             ("    owner TEXT\n);", "    owner TEXT,\n    host TEXT\n);"),
             (") WITHOUT ROWID;", ");")]
    text = SCHEMA + INDEXES
    for old, new in swaps:
        assert old in text, old
        text = text.replace(old, new)
    out = [s for s in _statements(text) if not s.startswith("CREATE TRIGGER")]
    # A table from before per-owner quotas gets the column before any index names it.
    owner = OWNER_DDL.replace("ADD COLUMN", "ADD COLUMN IF NOT EXISTS")
    return [out[0], owner, *out[1:],
            "CREATE INDEX IF NOT EXISTS rounds_host ON rounds (host, ended_at)"]


class PostgresReplayStore(ReplayStore):
    """The replay index in PostgreSQL (``clothball host --db postgresql://...``), shared by
    the hosts of a cluster; each host keeps its rounds' files in its own data directory
    and its rows name it (``host``: its HTTP address), so any host lists every round and
    sends a download to the host that holds the file.

    PostgreSQL may be away (restarted, unreachable): a round is then still written as a
    file and its row kept back (at most ``max_pending``; past that the files themselves
    are the list) and written by ``retry_index`` once PostgreSQL answers again; meanwhile
    ``index_error`` says why. Connections are made when first needed and again after one
    breaks, so a store survives PostgreSQL restarting.
    """

    columns = (*COLUMNS, "host")
    _LOCK_ID = 0x636C6F74  # pg_advisory_xact_lock: one host creates the tables at a time

    def __init__(self, data_dir: Path | str, url: str, *, host: str,
                 retention: Retention | None = None, recover: bool = True,
                 read_only: bool = False, lock_wait_s: float = LOCK_WAIT_S,
                 max_pending: int = 1000, connect_timeout_s: float = 2.0,
                 prune_at_open: bool = True) -> None:
        import psycopg  # the shared index's driver: needed only with --db

        self._pg = psycopg
        self._setup(data_dir, lock_wait_s, retention, read_only)
        self.url, self.host = url, host
        self.max_pending = max_pending
        self.connect_timeout_s = connect_timeout_s
        self.pending: list[tuple[dict[str, Any], str, int]] = []  # rows to write
        self._rescan = False  # more were kept back than ``pending`` holds: read the files
        self._conns: dict[str, Any] = {}  # "r" (reads), "w" (writes)
        self._ready = False  # the tables exist
        self._wconn: Any = None
        if read_only:
            with contextlib.suppress(IndexUnavailable):
                self.refresh_usage()
            return
        self.replays.mkdir(parents=True, exist_ok=True)
        try:
            if recover:
                self._recover()
                if retention is not None and prune_at_open:
                    self.prune_all(retention)
            self.refresh_usage()
        except IndexUnavailable:
            self._rescan = recover  # the files the index may lack: indexed once it answers

    def _where(self) -> str:
        u = urllib.parse.urlsplit(self.url)
        return f"the replay index (PostgreSQL at {u.hostname or 'localhost'}:{u.port or 5432})"

    def _conn(self, which: str) -> Any:
        conn = self._conns.get(which)
        if conn is not None and not conn.closed and not conn.broken:
            return conn
        conn = self._pg.connect(self.url, autocommit=True,
                                connect_timeout=max(1, round(self.connect_timeout_s)))
        if not self._ready:
            with conn.transaction():
                conn.execute("SELECT pg_advisory_xact_lock(%s)", (self._LOCK_ID,))
                for stmt in _postgres_ddl():
                    conn.execute(stmt)
            self._ready = True
        self._conns[which] = conn
        return conn

    def _drop(self, which: str) -> None:
        conn = self._conns.pop(which, None)
        if conn is not None:
            with contextlib.suppress(Exception):
                conn.close()

    def _failed(self, which: str, e: Exception) -> IndexUnavailable:
        self._drop(which)
        why = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        line = f"{self._where()} cannot be used now ({why})"
        if self.index_error is None:
            log.warning("%s; rounds are kept as files and indexed once it is back", line)
        self.index_error = line
        return IndexUnavailable(line)

    @staticmethod
    def _sql(q: str) -> str:
        return q.replace("?", "%s")  # the shared SQL's placeholders in psycopg's style

    def _attempts(self, which: str, fn: Callable[[Any], Any]) -> Any:
        """``fn(connection)``; once more on a new connection when one kept from before
        turns out broken (PostgreSQL restarted since: its first use fails)."""
        for attempt in (0, 1):
            kept = which in self._conns
            try:
                return fn(self._conn(which))
            except self._pg.Error as e:
                if attempt or not kept or not isinstance(e, self._pg.OperationalError):
                    raise self._failed(which, e) from e
                self._drop(which)

    def _fetch(self, q: str, args: Any = ()) -> list[tuple[Any, ...]]:
        with self._lock:
            return self._attempts(
                "r", lambda c: list(c.execute(self._sql(q), list(args)).fetchall()))

    def _write(self, fn: Callable[[], Any]) -> Any:
        if self.read_only:
            raise IndexUnavailable("the replay index is open read-only")

        def once(conn: Any) -> Any:
            try:
                with conn.transaction():
                    self._wconn = conn
                    return fn()
            finally:
                self._wconn = None

        with self._wlock:
            return self._attempts("w", once)

    def _x(self, q: str, args: Any = ()) -> None:
        self._wconn.execute(self._sql(q), list(args))

    def _xmany(self, q: str, rows: list[tuple[Any, ...]]) -> None:
        if rows:
            with self._wconn.cursor() as cur:
                cur.executemany(self._sql(q), [list(r) for r in rows])

    def _mine(self) -> tuple[str, list[Any]]:
        return "host = ?", [self.host]

    def _count_stamp(self) -> Any:
        return None  # other hosts write too: counted afresh each time

    def _identity(self) -> tuple[int, int] | None:
        return None  # no index file here: the data directory is checked by its replays/

    def save(self, header: dict[str, Any], records: list[tuple[int, bytes]]) -> dict[str, Any]:
        """Write the round's file, then index it; with PostgreSQL away the row is kept back
        (``retry_index``) and the row it will have is returned."""
        try:
            return super().save(header, records)
        except IndexUnavailable:
            path = self.replays / f"{header['id']}.cbr"
            size = path.stat().st_size  # written: only the index failed
            if len(self.pending) < self.max_pending:
                self.pending.append((header, path.name, size))
            else:
                self._rescan = True
            self.rounds += 1
            self.bytes += size
            return self._row(self._tuple(header, path.name, size))

    def retry_index(self) -> None:
        if not (self.pending or self._rescan or self.index_error):
            return
        try:
            if self.pending:
                self.index_many(self.pending)
                log.info("%s is back: indexed the %d rounds kept back", self._where(),
                         len(self.pending))
                self.pending = []
            if self._rescan:
                self.reconcile()
                self._rescan = False
            if self.retention is not None:
                self.prune(self.retention)
            else:
                self.refresh_usage()
        except IndexUnavailable:
            return
        self.index_error = None

    def close(self) -> None:
        with self._lock, self._wlock:
            for conn in self._conns.values():
                with contextlib.suppress(Exception):
                    conn.close()
            self._conns.clear()


class StorageOff(Exception):
    """A round was not recorded: why, in one line (the data directory's problem)."""


# What each problem needs before recording can resume (the end of its one line).
_RESUMES = {
    "full": "once space is freed",
    "read-only": "once it can be written",
    "missing": "once it can be created",
    "locked": "once the other program lets go of index.sqlite",
    "unusable": "once it is fixed",
}


class Storage:
    """The data directory as the server uses it: a ``ReplayStore`` that records when the
    directory can be written, that only lists and serves when it cannot (full, read-only,
    locked), or none (missing, unusable); ``problem`` says in one line what is wrong and
    what the server does, and is logged whenever it changes.

    ``check`` looks again (the server calls it every ``Limits.storage_check_s``, and after a
    failed save): recording resumes by itself once the problem is gone, and rounds written
    meanwhile as files are indexed. A directory removed while the server runs is created
    anew (as at a first start) with an empty index. Every disk access runs on the one
    ``replay-writer`` thread, never on the event loop or the index's query threads.
    """

    def __init__(self, data_dir: Path | str, *, retention: Retention | None = None,
                 min_free_bytes: int = 64 << 20, lock_wait_s: float = LOCK_WAIT_S,
                 db: str | None = None, host_url: str | None = None) -> None:
        """``db``: a PostgreSQL URL for an index shared by several hosts
        (``PostgresReplayStore``; ``host_url``, this host's HTTP address, must be set
        before the first ``check_now``), else the data directory's own SQLite index."""
        self.dir = Path(data_dir)
        self.db = db
        self.host_url = host_url
        self.retention = retention
        self.min_free_bytes = min_free_bytes
        self.lock_wait_s = lock_wait_s
        self.store: ReplayStore | None = None
        self.kind: str | None = None  # full, read-only, missing, locked, unusable
        self.problem: str | None = None  # the one line; None while recording
        self.free_bytes: int | None = None
        self.saving = 0  # saves under way (on the writer thread or waiting for it)
        self._lock_trouble = False
        self._logged_without_store = False
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="replay-writer")

    def _open_store(self, **kw: Any) -> ReplayStore:
        if self.db is None:
            return ReplayStore(self.dir, **kw)
        assert self.host_url is not None, "Storage.host_url is needed with a shared index"
        return PostgresReplayStore(self.dir, self.db, host=self.host_url, **kw)

    @property
    def index_error(self) -> str | None:
        """Why the shared replay index cannot be written now (rounds wait as files)."""
        store = self.store
        if store is None or store.index_error is None:
            return None
        waiting = len(getattr(store, "pending", ()))
        return store.index_error + (f"; {waiting} rounds wait to be indexed" if waiting
                                    else "")

    # --- on the event loop -------------------------------------------------------------------
    async def _run(self, fn: Callable[..., Any], *args: Any) -> Any:
        return await asyncio.get_running_loop().run_in_executor(self._pool, fn, *args)

    async def check(self) -> None:
        await self._run(self.check_now)

    async def prune_some(self) -> int:
        """One batch of the rounds retention does not keep removed (on the writer thread,
        so saves go on between batches); how many (``PRUNE_BATCH``: more may be due)."""
        return await self._run(self._prune_now)

    def _prune_now(self) -> int:
        store = self.store
        if store is None or store.read_only or self.retention is None:
            return 0
        try:
            return len(store.prune(self.retention))
        except (OSError, sqlite3.Error, IndexUnavailable) as e:
            log.warning("pruning the replays failed: %s", e)
            return 0

    async def save(self, header: dict[str, Any], records: list[tuple[int, bytes]]
                   ) -> dict[str, Any]:
        """Records one round (on the writer thread); ``StorageOff`` naming why not."""
        self.saving += 1
        try:
            return await self._run(self.save_now, header, records)
        finally:
            self.saving -= 1

    # --- on the writer thread (or before the server starts) ---------------------------------
    def save_now(self, header: dict[str, Any], records: list[tuple[int, bytes]]
                 ) -> dict[str, Any]:
        store = self.store
        if store is None or store.read_only:
            raise StorageOff(f"recording is off: {self.problem}")
        try:
            return store.save(header, records)
        except sqlite3.OperationalError as e:
            if not _locked(e):
                self._failed(e)
            self._lock_trouble = True
            self.check_now()
            raise StorageOff(f"the replay index {self.dir / 'index.sqlite'} stayed locked "
                             f"for {self.lock_wait_s:g} s; the round's file is kept and "
                             "indexed once the lock is free") from e
        except (OSError, sqlite3.Error) as e:
            self._failed(e)

    def _failed(self, e: BaseException) -> typing.NoReturn:
        err = getattr(e, "errno", None)
        self.check_now(hint=_ERRNO_KINDS.get(err) if err is not None else None,
                       reason=str(e))
        raise StorageOff(f"could not write the replay: {e}" + (
            f"; recording is off: {self.problem}" if self.problem else "")) from e

    def check_now(self, hint: str | None = None, reason: str = "") -> None:
        """Looks at the directory again and acts on what it finds (see the class)."""
        found = self._diagnose()
        if found is None and hint is not None:
            # A write just failed for a reason the directory does not show now (a full
            # disk with room for a small probe): believe the write until the next check.
            found = hint, f"{_KIND_WORDS[hint]} (a write failed: {reason})"
        if found is None:
            found = self._open_for_recording()
        if found is None:
            self._set(None, None)
            assert self.store is not None
            self.store.retry_index()
            return
        kind, what = found
        if self.store is not None and not self.store.read_only and kind != "locked":
            self.store.close()
            self.store = None
        if self.store is None and kind not in ("missing", "unusable"):
            try:
                self.store = self._open_store(read_only=True)
            except (OSError, sqlite3.Error):
                self.store = None
        self._set(kind, what)

    def _open_for_recording(self) -> tuple[str, str] | None:
        store = self.store
        if store is not None and not store.read_only and store.still_there():
            if self._lock_trouble:
                try:
                    if not store.lock_is_free():
                        return "locked", "(index.sqlite) is locked by another program"
                    store.reconcile()  # the rounds written while it was locked
                except (OSError, sqlite3.Error) as e:
                    return "unusable", f"cannot be used ({e})"
                self._lock_trouble = False
            return None
        first = store is None and self.kind is None
        if store is not None and not store.read_only:
            log.warning("the data directory %s was removed or replaced while the server "
                        "ran: recording goes on in a new index there (the rounds listed "
                        "before are gone)", self.dir)
        try:
            # A backlog over retention is pruned in the background (``prune_some``).
            new = self._open_store(retention=self.retention, lock_wait_s=self.lock_wait_s,
                                   prune_at_open=False,
                                   recover=first)
            if not first:
                # Not .tmp files: the rounds being written now are someone's.
                new.reconcile()
        except sqlite3.OperationalError as e:
            if _locked(e):
                self._lock_trouble = True
                return "locked", "(index.sqlite) is locked by another program"
            return "unusable", f"cannot be used ({e})"
        except (OSError, sqlite3.Error) as e:
            err = getattr(e, "errno", None)
            return _ERRNO_KINDS.get(err, "unusable") if err else "unusable", \
                f"cannot be used ({e})"
        if store is not None:
            store.close()
        self.store = new
        return None

    def _diagnose(self) -> tuple[str, str] | None:
        """(kind, what is wrong) that keeps the directory from recording, or None."""
        d = self.dir
        if not d.exists():
            try:
                (d / "replays").mkdir(parents=True, exist_ok=True)
            except OSError as e:
                return "missing", f"is missing and cannot be created ({e.strerror or e})"
            if self.kind is not None or self.store is not None:
                log.warning("the data directory %s was missing: created it anew", d)
        if not d.is_dir():
            return "unusable", "is not a directory"
        try:
            st = os.statvfs(d)
        except OSError as e:
            return "unusable", f"cannot be read ({e.strerror or e})"
        if st.f_flag & os.ST_RDONLY:
            return "read-only", "is on a read-only filesystem"
        self.free_bytes = st.f_bavail * st.f_frsize
        if self.free_bytes < self.min_free_bytes:
            return "full", (f"is full ({self.free_bytes / 2**20:.1f} MiB free; recording "
                            f"needs {self.min_free_bytes / 2**20:g} MiB)")
        # Write and remove a small file: permissions, quotas and read-only mounts the
        # numbers above do not show.
        where = d / "replays" if (d / "replays").is_dir() else d
        probe = where / f".probe-{os.getpid()}"
        try:
            fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            try:
                os.write(fd, b"\0" * 4096)
                os.fsync(fd)
            finally:
                os.close(fd)
                probe.unlink(missing_ok=True)
        except OSError as e:
            kind = _ERRNO_KINDS.get(e.errno or 0, "unusable")
            return kind, f"{_KIND_WORDS[kind]} (a write failed: {e.strerror or e})"
        return None

    def _set(self, kind: str | None, what: str | None) -> None:
        if kind is None:
            if self.kind is not None:
                log.warning("recording resumed: the data directory %s can be written again",
                            self.dir)
            self.kind = self.problem = None
            return
        if self.store is not None:
            serves = "stored rounds stay listed and downloadable (read-only)"
        else:
            serves = "no stored rounds can be served"
        if kind == "locked":
            serves = "rounds are kept as files, to be indexed"
        problem = (f"data directory {str(self.dir)!r} {what}; {serves}; recording resumes "
                   f"by itself {_RESUMES[kind]}")
        if (kind, self.store is None) != (self.kind, self._logged_without_store):
            log.error("recording is off: %s", problem)  # once per change, not every check
        self._logged_without_store = self.store is None
        self.kind, self.problem = kind, problem

    def close(self) -> None:
        self._pool.shutdown(wait=True)
        if self.store is not None:
            self.store.close()
            self.store = None


_KIND_WORDS = {"full": "is full", "read-only": "is read-only", "missing": "is missing",
               "locked": "is locked", "unusable": "cannot be used"}
_ERRNO_KINDS = {
    errno.ENOSPC: "full", errno.EDQUOT: "full", errno.EFBIG: "full",
    errno.EROFS: "read-only", errno.EACCES: "read-only", errno.EPERM: "read-only",
    errno.ENOENT: "missing",
}


def _locked(e: sqlite3.OperationalError) -> bool:
    """An error that waiting may cure: another connection holds the lock."""
    code = getattr(e, "sqlite_errorcode", None)
    if code is not None:
        return code & 0xFF in (sqlite3.SQLITE_BUSY, sqlite3.SQLITE_LOCKED)
    return "locked" in str(e) or "busy" in str(e)
