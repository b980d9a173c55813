"""The replay file format: one gzip stream per recorded round.

Replay file (``<id>.cbr``; format version ``REPLAY_VERSION``)::

    16 bytes  magic b"CLOTHBALL-REPLAY"
    u32       format version
    u32       header length H
    H bytes   header, UTF-8 JSON: id, room, players, scene, conceded edge, scores, rates...
    then records until the end, each:
    u8        kind: 0 = event (UTF-8 JSON text), 1 = binary protocol message (MESH or TRACK,
              exactly as ``game.wire.protocol`` encodes them)
    u32       length L
    L bytes   the record

All integers little-endian. A file is written to ``<id>.cbr.tmp``, flushed to disk, then
renamed, so a crash never leaves a half-written ``.cbr``. The server's index of these files
is ``server.storage``; every client reads them with ``read_replay``.
"""

from __future__ import annotations

import gzip
import json
import os
import re
import secrets
import struct
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from . import protocol as P

MAGIC = b"CLOTHBALL-REPLAY"
REPLAY_VERSION = 1
RECORD = struct.Struct("<BI")
ID_RE = re.compile(r"^[A-Za-z0-9_-]{8,64}$")

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


def recorded_length(frame_dt: float, records: Iterable[tuple[int, bytes]]) -> float:
    """Seconds from the first to the last recorded MESH or TRACK frame: the length a
    replay player shows (assets/web/replay.js), so the index lists the same figure."""
    frames = [struct.unpack_from("<q", data, P.HEADER.size)[0] for kind, data in records
              if kind == 1 and len(data) >= P.HEADER.size + 8 and data[0] in (P.MESH, P.TRACK)]
    return (max(frames) - min(frames)) * frame_dt if frames else 0.0


def new_round_id() -> str:
    return time.strftime("%Y%m%d-%H%M%S-", time.gmtime()) + secrets.token_urlsafe(6)
