"""The replay index: the data directory's recorded rounds (files under ``replays/``, in
the format of ``game.wire.replay``) and their SQLite index ``index.sqlite``.

A file is indexed only once it is complete on disk (SQLite in WAL mode), so a crash loses at
most the round being written: never the index or an earlier round. At start-up, leftover
``.tmp`` files are deleted and any finished file the index lacks is indexed from its own
header.

A private room's rounds carry ``access`` (``access_key(room, code)``) in their header and
index row: they are listed and served only to a request that names the room's code.
"""

from __future__ import annotations

import hashlib
import json
import logging
import sqlite3
import threading
from pathlib import Path
from typing import Any

from ..game.wire.replay import ID_RE, ReplayError, read_replay_header, write_replay

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
    access TEXT
);
CREATE INDEX IF NOT EXISTS rounds_ended ON rounds (ended_at);
"""

COLUMNS = ("id", "room_id", "room_name", "scene", "round", "players", "conceded_edge",
           "conceded_by", "scores", "started_at", "ended_at", "duration_s", "file", "bytes",
           "access")


def access_key(room_id: str, code: str) -> str:
    """What a private room's rounds are locked with: a hash of its id and join code (the
    code itself is never stored)."""
    return hashlib.sha256(f"clothball-replay:{room_id}:{code}".encode()).hexdigest()


class ReplayStore:
    """The data directory's replays: files under ``replays/`` and the index ``index.sqlite``.

    Thread-safe: the server calls it from worker threads (``asyncio.to_thread``).
    """

    def __init__(self, data_dir: Path | str) -> None:
        self.dir = Path(data_dir)
        self.replays = self.dir / "replays"
        self.replays.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.dir / "index.sqlite", check_same_thread=False,
                                   isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.executescript(SCHEMA)
        have = {r[1] for r in self._db.execute("PRAGMA table_info(rounds)")}
        if "access" not in have:  # an index from before private rounds were locked
            self._db.execute("ALTER TABLE rounds ADD COLUMN access TEXT")
        self._recover()

    def _recover(self) -> None:
        for tmp in self.replays.glob("*.cbr.tmp"):
            log.info("removing unfinished replay %s", tmp.name)
            tmp.unlink(missing_ok=True)
        known = {r[0] for r in self._db.execute("SELECT id FROM rounds")}
        for path in sorted(self.replays.glob("*.cbr")):
            rid = path.stem
            if rid in known:
                continue
            try:
                header = read_replay_header(path)
                self._index(header, path)
                log.info("indexed replay %s from its header", path.name)
            except (OSError, ReplayError, ValueError, KeyError, EOFError) as e:
                log.warning("ignoring damaged replay %s: %s", path.name, e)

    def _index(self, header: dict[str, Any], path: Path) -> None:
        row = (
            header["id"], header["room_id"], header["room_name"], header["scene"],
            int(header["round"]), json.dumps(header["players"]), header.get("conceded_edge"),
            header.get("conceded_by"), json.dumps(header["scores"]), float(header["started_at"]),
            float(header["ended_at"]), float(header["duration_s"]), path.name,
            path.stat().st_size, header.get("access"),
        )
        with self._lock:
            self._db.execute(
                f"INSERT OR REPLACE INTO rounds ({', '.join(COLUMNS)}) "
                f"VALUES ({', '.join('?' * len(COLUMNS))})",
                row,
            )

    def save(self, header: dict[str, Any], records: list[tuple[int, bytes]]) -> dict[str, Any]:
        """Write one round's file, then index it. Returns the index row."""
        rid = header["id"]
        if not ID_RE.match(rid):
            raise ValueError(f"replay id {rid!r} is not valid")
        path = self.replays / f"{rid}.cbr"
        write_replay(path, header, records)
        self._index(header, path)
        row = self.get(rid)
        assert row is not None
        return row

    @staticmethod
    def _where(room_id: str | None, player: str | None, code: str | None
               ) -> tuple[str, list[Any]]:
        """The rounds a request may see: public ones, plus a private room's when the request
        names that room and its code."""
        if room_id is not None and code is not None:
            q, args = " WHERE room_id = ? AND (access IS NULL OR access = ?)", [
                room_id, access_key(room_id, code)]
        elif room_id is not None:
            q, args = " WHERE room_id = ? AND access IS NULL", [room_id]
        else:
            q, args = " WHERE access IS NULL", []
        if player is not None:
            q += (" AND EXISTS (SELECT 1 FROM json_each(rounds.players)"
                  " WHERE json_extract(value, '$.name') = ?)")
            args.append(player)
        return q, args

    def list(self, limit: int = 100, offset: int = 0, room_id: str | None = None, *,
             player: str | None = None, code: str | None = None) -> list[dict[str, Any]]:
        """Newest first. ``player``: only rounds where a seat had that name; ``code``: a
        private room's code (with ``room_id``) to see its rounds too."""
        where, args = self._where(room_id, player, code)
        q = f"SELECT {', '.join(COLUMNS)} FROM rounds{where}"
        q += " ORDER BY ended_at DESC, id LIMIT ? OFFSET ?"
        args += [limit, offset]
        with self._lock:
            rows = self._db.execute(q, args).fetchall()
        return [self._row(r) for r in rows]

    def count(self, room_id: str | None = None, *, player: str | None = None,
              code: str | None = None) -> int:
        """How many rounds ``list`` with the same filters would page through."""
        where, args = self._where(room_id, player, code)
        with self._lock:
            return int(self._db.execute(f"SELECT COUNT(*) FROM rounds{where}", args)
                       .fetchone()[0])

    def _get(self, rid: str) -> dict[str, Any] | None:
        if not ID_RE.match(rid):
            return None
        with self._lock:
            r = self._db.execute(
                f"SELECT {', '.join(COLUMNS)} FROM rounds WHERE id = ?", (rid,)
            ).fetchone()
        return None if r is None else dict(zip(COLUMNS, r, strict=True))

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

    @staticmethod
    def _row(r: tuple[Any, ...]) -> dict[str, Any]:
        d = dict(zip(COLUMNS, r, strict=True))
        d["players"] = json.loads(d["players"])
        d["scores"] = json.loads(d["scores"])
        d["private"] = d.pop("access") is not None
        del d["file"]
        return d

    def close(self) -> None:
        with self._lock:
            self._db.close()
