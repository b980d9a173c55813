"""The replay index in PostgreSQL (``PostgresIndex``, ``clothball host --db``), shared by the
hosts of a cluster: the SQL of ``storage.sql`` on PostgreSQL, with each host's rows naming
it."""

from __future__ import annotations

import contextlib
import logging
import urllib.parse
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .index import LOCK_WAIT_S, IndexUnavailable, Retention
from .sql import COLUMNS, INDEXES, OWNER_DDL, SCHEMA, SqlIndex, statements

log = logging.getLogger("clothball.server")


def postgres_ddl() -> list[str]:
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
    out = [s for s in statements(text) if not s.startswith("CREATE TRIGGER")]
    # A table from before per-owner quotas gets the column before any index names it.
    owner = OWNER_DDL.replace("ADD COLUMN", "ADD COLUMN IF NOT EXISTS")
    return [out[0], owner, *out[1:],
            "CREATE INDEX IF NOT EXISTS rounds_host ON rounds (host, ended_at)"]



class PostgresIndex(SqlIndex):
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
        super().__init__(data_dir, lock_wait_s, retention, read_only)
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
                for stmt in postgres_ddl():
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

    def _read_only_error(self) -> Exception:
        return IndexUnavailable("the replay index is open read-only")

    def lock_is_free(self) -> bool:
        return True  # PostgreSQL's locks are its own: a write waits for them

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
