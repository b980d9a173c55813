"""The replay index in SQLite: the data directory's ``index.sqlite`` (``SqliteIndex``),
in WAL mode.

The index has two connections: one that reads (listings, lookups) and one that writes, so a
listing never waits behind a write waiting for a lock. A write that finds the index locked
by another program (``clothball replays prune``, an ``sqlite3`` shell) waits: SQLite's
``busy_timeout`` (``BUSY_TIMEOUT_S``), then retries until ``lock_wait_s`` has passed; a
round whose index row could not be written keeps its file and is indexed at the next start.
"""

from __future__ import annotations

import contextlib
import sqlite3
import time
import urllib.parse
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from .index import LOCK_WAIT_S, Retention
from .sql import INDEX_VERSION, INDEXES, OWNER_DDL, SCHEMA, SqlIndex, statements

BUSY_TIMEOUT_S = 5.0  # SQLite's own wait for a lock (busy_timeout), per attempt


class SqliteIndex(SqlIndex):
    """The data directory's replays: files under ``replays/`` and the index
    ``index.sqlite``."""

    def __init__(self, data_dir: Path | str, *, lock_wait_s: float = LOCK_WAIT_S,
                 retention: Retention | None = None, recover: bool = True,
                 read_only: bool = False, prune_at_open: bool = True) -> None:
        """``recover``: remove leftover ``.tmp`` files and index unindexed rounds (what the
        server does at start; a command run beside a live server must not: its ``.tmp``
        files are rounds being written). ``retention``: pruned after each save; None keeps
        everything. ``read_only``: list and serve what is there, write nothing (a read-only
        or full disk); the index must exist."""
        super().__init__(data_dir, lock_wait_s, retention, read_only)
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

    def _identity(self) -> tuple[int, int] | None:
        """The index file's device and inode: another file (or none) there means the data
        directory was removed or replaced under the server."""
        try:
            st = (self.dir / "index.sqlite").stat()
        except OSError:
            return None
        return st.st_dev, st.st_ino

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
                if not locked(e) or time.monotonic() + pause > deadline:
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
        for stmt in statements(SCHEMA):
            db.execute(stmt)
        have = {r[1] for r in db.execute("PRAGMA table_info(rounds)")}
        if "access" not in have:  # an index from before private rounds were locked
            db.execute("ALTER TABLE rounds ADD COLUMN access TEXT")
        if "owner" not in have:  # from before per-address quotas
            db.execute(OWNER_DDL)
        for stmt in statements(INDEXES):
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
            if locked(e):
                return False
            raise
        return True

    # --- how statements run: the two connections ---------------------------------------
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
        """Nothing is kept back: rounds whose row could not be written are indexed from
        their files (``reconcile``)."""

    def _read_only_error(self) -> Exception:
        return sqlite3.OperationalError("the replay index is open read-only")

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

    def close(self) -> None:
        with self._lock, self._wlock:
            self._db.close()
            if self._wdb is not None:
                self._wdb.close()


def locked(e: sqlite3.OperationalError) -> bool:
    """An error that waiting may cure: another connection holds the lock."""
    code = getattr(e, "sqlite_errorcode", None)
    if code is not None:
        return code & 0xFF in (sqlite3.SQLITE_BUSY, sqlite3.SQLITE_LOCKED)
    return "locked" in str(e) or "busy" in str(e)
