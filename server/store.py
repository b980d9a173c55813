"""Recorded rounds: one compressed file per round plus an SQLite index.

Replay file (``<id>.cbr``, a gzip stream; format version ``REPLAY_VERSION``)::

    16 bytes  magic b"CLOTHBALL-REPLAY"
    u32       format version
    u32       header length H
    H bytes   header, UTF-8 JSON: id, room, players, scene, conceded edge, scores, rates...
    then records until the end, each:
    u8        kind: 0 = event (UTF-8 JSON text), 1 = binary protocol message (MESH or TRACK,
              exactly as ``server.protocol`` encodes them)
    u32       length L
    L bytes   the record

All integers little-endian. A file is written to ``<id>.cbr.tmp``, flushed to disk, then
renamed, and only then indexed (SQLite in WAL mode), so a crash loses at most the round
being written: never the index or an earlier round. At start-up, leftover ``.tmp`` files
are deleted and any finished file the index lacks is indexed from its own header.

A private room's rounds carry ``access`` (``access_key(room, code)``) in their header and
index row: they are listed and served only to a request that names the room's code.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import logging
import os
import re
import sqlite3
import struct
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

log = logging.getLogger("clothball.server")

MAGIC = b"CLOTHBALL-REPLAY"
REPLAY_VERSION = 1
RECORD = struct.Struct("<BI")
ID_RE = re.compile(r"^[A-Za-z0-9_-]{8,64}$")

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


class ReplayError(ValueError):
    """A replay file that is not one, or is damaged."""


def write_replay(path: Path, header: dict[str, Any], records: Iterable[tuple[int, bytes]]) -> int:
    """Write a replay file crash-safely (temp file, fsync, rename). Returns its size."""
    tmp = path.with_name(path.name + ".tmp")
    head = json.dumps(header, separators=(",", ":"), allow_nan=False).encode()
    try:
        with open(tmp, "wb") as raw:
            with gzip.GzipFile(fileobj=raw, mode="wb", compresslevel=6, mtime=0) as gz:
                gz.write(MAGIC + struct.pack("<II", REPLAY_VERSION, len(head)) + head)
                for kind, data in records:
                    gz.write(RECORD.pack(kind, len(data)))
                    gz.write(data)
            raw.flush()
            os.fsync(raw.fileno())
    except BaseException:
        tmp.unlink(missing_ok=True)  # a full disk keeps no half-written file
        raise
    os.replace(tmp, path)
    _fsync_dir(path.parent)
    return path.stat().st_size


def _fsync_dir(d: Path) -> None:
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:  # pragma: no cover - not every platform opens directories
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def read_replay(data: bytes) -> tuple[dict[str, Any], list[tuple[int, bytes]]]:
    """Parse a whole replay file (its bytes as stored/downloaded): header and records."""
    try:
        body = gzip.decompress(data)
    except (OSError, EOFError) as e:
        raise ReplayError(f"not a gzip stream: {e}") from None
    return _parse(body)


def read_replay_header(path: Path) -> dict[str, Any]:
    with gzip.open(path, "rb") as f:
        start = f.read(len(MAGIC) + 8)
        if len(start) < len(MAGIC) + 8 or not start.startswith(MAGIC):
            raise ReplayError(f"{path.name}: not a clothball replay")
        version, hlen = struct.unpack_from("<II", start, len(MAGIC))
        if version != REPLAY_VERSION:
            raise ReplayError(f"{path.name}: replay format {version}, expected {REPLAY_VERSION}")
        return json.loads(f.read(hlen))


def _parse(body: bytes) -> tuple[dict[str, Any], list[tuple[int, bytes]]]:
    if not body.startswith(MAGIC) or len(body) < len(MAGIC) + 8:
        raise ReplayError("not a clothball replay (bad magic)")
    version, hlen = struct.unpack_from("<II", body, len(MAGIC))
    if version != REPLAY_VERSION:
        raise ReplayError(f"replay format {version}, this reader knows {REPLAY_VERSION}")
    off = len(MAGIC) + 8
    try:
        header = json.loads(body[off:off + hlen])
    except ValueError as e:
        raise ReplayError(f"replay header is not JSON: {e}") from None
    off += hlen
    records: list[tuple[int, bytes]] = []
    while off < len(body):
        if off + RECORD.size > len(body):
            raise ReplayError("replay truncated in a record header")
        kind, length = RECORD.unpack_from(body, off)
        off += RECORD.size
        if kind not in (0, 1) or off + length > len(body):
            raise ReplayError("replay record damaged or truncated")
        records.append((kind, body[off:off + length]))
        off += length
    return header, records


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


def new_round_id() -> str:
    import secrets

    return time.strftime("%Y%m%d-%H%M%S-", time.gmtime()) + secrets.token_urlsafe(6)
