"""Index writes wait for a lock another program holds (issue 21): SQLite's busy timeout,
then retries, instead of failing with "database is locked"; listings are answered while a
write waits."""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path
from typing import Any

import pytest
from clothball.server.storage import sqlite as sqlite_index
from clothball.server.storage.sqlite import SqliteIndex


def header(i: int) -> dict[str, Any]:
    return dict(id=f"lock{i:05d}-x", room_id="r", room_name="r", scene="tiny", round=i,
                players=[{"seat": 0, "kind": "human", "name": "ann"}], scores=[0, 0, 0, 0],
                started_at=0.0, ended_at=float(i), duration_s=1.0)


def hold_lock(data: Path) -> sqlite3.Connection:
    """Another connection, as another program would open it, holding the write lock."""
    db = sqlite3.connect(data / "index.sqlite", isolation_level=None, check_same_thread=False)
    db.execute("BEGIN IMMEDIATE")
    return db


def test_a_write_waits_for_a_lock_held_longer_than_the_busy_timeout(tmp_path: Path,
                                                                    monkeypatch) -> None:
    # SQLite's own wait made short, so that only the retries can carry the write through a
    # lock held many times longer (SQLite's default is 5 s: issue 21 saw it run out).
    monkeypatch.setattr(sqlite_index, "BUSY_TIMEOUT_S", 0.05)
    store = SqliteIndex(tmp_path)
    store.save(header(0), [])
    other = hold_lock(tmp_path)
    saved: list[Any] = []
    writer = threading.Thread(target=lambda: saved.append(store.save(header(1), [])))
    writer.start()
    try:
        # The write finds the lock taken and waits (several busy timeouts in all)...
        while store.lock_waits < 5:
            assert writer.is_alive() and not saved
            threading.Event().wait(0.01)
        # ... and meanwhile the listing, on its own connection, is answered.
        reader = threading.Thread(target=lambda: saved.append(store.list()))
        reader.start()
        reader.join(60)  # a hang guard, not a measurement
        assert not reader.is_alive()
        assert [r["id"] for r in saved.pop()] == ["lock00000-x"]
    finally:
        other.execute("COMMIT")
        other.close()
    writer.join(60)
    assert not writer.is_alive()
    assert saved[0]["id"] == "lock00001-x"
    assert [r["id"] for r in store.list()] == ["lock00001-x", "lock00000-x"]
    assert store.count(player="ann") == 2
    store.close()


def test_a_lock_held_past_the_wait_fails_the_write_and_the_file_is_indexed_next_start(
        tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(sqlite_index, "BUSY_TIMEOUT_S", 0.01)
    store = SqliteIndex(tmp_path, lock_wait_s=0.2)
    other = hold_lock(tmp_path)
    try:
        with pytest.raises(sqlite3.OperationalError, match="locked"):
            store.save(header(2), [])
    finally:
        other.execute("COMMIT")
        other.close()
    assert store.lock_waits > 0
    assert (tmp_path / "replays" / "lock00002-x.cbr").is_file()
    store.close()
    again = SqliteIndex(tmp_path)
    assert [r["id"] for r in again.list()] == ["lock00002-x"]
    again.close()
