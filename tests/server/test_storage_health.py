"""Health checks never wait behind index queries or replay writes (issue 23): with the
replay writer stuck on a locked index, a storage check queued behind it and every index
query thread busy, ``/healthz``, ``/api/stats``, ``/api/rooms`` and the page still answer,
while all of that is still stuck."""

from __future__ import annotations

import asyncio
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any

from clothball.server.http import INDEX_THREADS
from clothball.server.storage import sqlite as sqlite_index

from tests.server.conftest import http_get, http_json, run, server, until


def test_health_answers_while_writes_and_index_queries_are_stuck(tmp_path: Path,
                                                                 monkeypatch) -> None:
    monkeypatch.setattr(sqlite_index, "BUSY_TIMEOUT_S", 0.02)  # waits show as retries at once

    async def main() -> None:
        async with server(tmp_path, default_room=False) as srv:
            store = srv.store
            assert store is not None
            store.lock_wait_s = 120.0
            other = sqlite3.connect(tmp_path / "index.sqlite", isolation_level=None,
                                    check_same_thread=False)
            other.execute("BEGIN IMMEDIATE")  # the writer's lock, held by another program
            release = threading.Event()
            real_count = store.count

            def stuck_count(*a: Any, **k: Any) -> int:
                release.wait(120)
                return real_count(*a, **k)

            store.count = stuck_count  # type: ignore[method-assign]
            try:
                h = dict(id="health-0001", room_id="r", room_name="r", scene="tiny", round=1,
                         players=[], scores=[0, 0, 0, 0], started_at=time.time() - 1,
                         ended_at=time.time(), duration_s=1.0)
                save = asyncio.create_task(srv.storage.save(h, []))
                check = asyncio.create_task(srv.storage.check())  # queued behind the save
                queries = [asyncio.create_task(http_get(srv, "/api/replays"))
                           for _ in range(INDEX_THREADS + 2)]
                await until(lambda: store.lock_waits > 0, 30, "the save waiting for the lock")
                await until(lambda: srv.http._waiting == len(queries), 30, "queries waiting")

                status, body, _ = await http_get(srv, "/healthz")
                assert (status, body) == (200, b"ok\n")
                stats = await http_json(srv, "/api/stats")
                assert stats["recording"] == "on" and "storage" in stats
                assert (await http_json(srv, "/api/rooms"))["rooms"] == []
                status, _, _ = await http_get(srv, "/")
                assert status == 200
                # ... and all of it was answered while the rest was still stuck.
                assert srv.storage.saving == 1 and not save.done() and not check.done()
                assert srv.http._waiting == len(queries)
                assert not any(q.done() for q in queries)
            finally:
                release.set()
                other.execute("COMMIT")
                other.close()
            row = await save
            await check
            for q in queries:
                status, _, _ = await q
                assert status == 200
            assert (await http_json(srv, "/api/replays"))["replays"][0]["id"] == row["id"]

    run(main())
