"""The SQL every replay index driver runs (``SqlIndex``): the tables, the queries of the
listings and lookups, indexing, saving and pruning. A driver (``storage.sqlite``,
``storage.postgres``) says how it connects and runs statements.

A file is indexed only once it is complete on disk, so a crash loses at most the round
being written: never the index or an earlier round. At start-up, leftover ``.tmp`` files
are deleted and any finished file the index lacks is indexed from its own header. Pruning
and private rounds: ``storage.index``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sqlite3
import threading
import time
import urllib.parse
from abc import ABC, abstractmethod
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ...game.wire.replay import ID_RE, ReplayError, read_replay_header, write_replay
from .index import PRUNE_BATCH, Retention, access_key, player_names

log = logging.getLogger("clothball.server")

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


def statements(script: str) -> list[str]:
    """``script`` split into whole statements (a trigger's body holds ``;`` too)."""
    out, cur = [], ""
    for line in script.splitlines(keepends=True):
        cur += line
        if sqlite3.complete_statement(cur):
            out.append(cur.strip())
            cur = ""
    return out



class SqlIndex(ABC):
    """A replay index (``storage.index.ReplayIndex``): the data directory's files under
    ``replays/`` and their rows, with every query. A driver implements how statements run
    (``_fetch``, ``_x``, ``_xmany``, ``_write``), which rows are its own (``_mine``), when
    counts may be remembered (``_count_stamp``) and what identifies its index (``_identity``).
    """

    columns: tuple[str, ...] = COLUMNS
    host: str | None = None  # whose files the rows name (a shared index: an HTTP address)
    index_error: str | None = None  # why the index cannot be written now (shared: its server)

    def __init__(self, data_dir: Path | str, lock_wait_s: float, retention: Retention | None,
                 read_only: bool) -> None:
        """What every driver starts with (before it connects)."""
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

    # --- the driver's part ---------------------------------------------------------------------
    @abstractmethod
    def _fetch(self, q: str, args: Any = ()) -> list[tuple[Any, ...]]:
        """The rows of a query."""

    @abstractmethod
    def _write(self, fn: Callable[[], Any]) -> Any:
        """``fn()`` in one write transaction."""

    @abstractmethod
    def _x(self, q: str, args: Any = ()) -> None:
        """One statement inside ``_write``."""

    @abstractmethod
    def _xmany(self, q: str, rows: list[tuple[Any, ...]]) -> None: ...

    @abstractmethod
    def _mine(self) -> tuple[str, list[Any]]:
        """The condition on the rows whose files are this index's."""

    @abstractmethod
    def _count_stamp(self) -> Any:
        """What changes whenever the index does (None: counts are not remembered)."""

    @abstractmethod
    def _identity(self) -> tuple[int, int] | None:
        """What identifies the index's file (None: no file here)."""

    @abstractmethod
    def _read_only_error(self) -> Exception:
        """What a write to an index opened read-only raises."""

    @abstractmethod
    def lock_is_free(self) -> bool: ...

    @abstractmethod
    def close(self) -> None: ...

    # --- shared ----------------------------------------------------------------------------
    def still_there(self) -> bool:
        """The index this store has open is still the data directory's."""
        return not self.read_only and self._identity() == self.identity and \
            self.replays.is_dir()

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


    @abstractmethod
    def retry_index(self) -> None:
        """Writes the index rows kept back while the index was unavailable."""

    def save(self, header: dict[str, Any], records: list[tuple[int, bytes]]) -> dict[str, Any]:
        """Write one round's file, then index it. Returns the index row."""
        rid = header["id"]
        if not ID_RE.match(rid):
            raise ValueError(f"replay id {rid!r} is not valid")
        if self.read_only:
            raise self._read_only_error()
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
