"""Storage problems named and recovered from (issue 23): a data directory that is
read-only, full, missing or locked, at start and while the server runs. The server says
in one line what is wrong and what it does, keeps serving the stored rounds it can read,
tells the truth in ``/api/stats``, and resumes recording by itself once the problem is
gone.

Root ignores file permissions, so a read-only or full directory is made for real: a tmpfs
of the test's own, remounted read-only and back, or filled and emptied (root, where the
machine allows mounts). Without root, a directory without write permission stands in for
a read-only one; a full disk then is a free-space floor above what is free."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import shutil
import sqlite3
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from clothball.server.limits import Limits
from clothball.server.storage import sql as index_sql
from clothball.server.storage import sqlite as sqlite_index
from clothball.server.storage.datadir import StorageOff
from clothball.server.storage.sqlite import SqliteIndex

from tests.server.conftest import ErrorLog, http_get, http_json, run, server, until

FAST_CHECKS = Limits(storage_check_s=0.05, storage_min_free_mib=1.0)


def header(i: int) -> dict[str, Any]:
    return dict(id=f"disk{i:05d}-x", room_id="r", room_name="r", scene="tiny", round=i,
                players=[], scores=[0, 0, 0, 0], started_at=time.time() - 2,
                ended_at=time.time() - 1 + i * 1e-3, duration_s=1.0)


def _can_mount() -> bool:
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    probe = Path(f"/tmp/clothball-mount-probe-{os.getpid()}")
    probe.mkdir(exist_ok=True)
    try:
        ok = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(probe)],
                            capture_output=True).returncode == 0
        if ok:
            subprocess.run(["umount", str(probe)], check=True)
        return ok
    finally:
        probe.rmdir()


MOUNT = _can_mount()


class Disk:
    """A directory that can be made read-only and writable again, filled and emptied."""

    def __init__(self, root: Path, size_mib: int) -> None:
        self.root = root
        root.mkdir()
        if MOUNT:
            subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mib}m,mode=755",
                            "tmpfs", str(root)], check=True)

    def read_only(self, on: bool) -> None:
        if MOUNT:
            subprocess.run(["mount", "-o", f"remount,{'ro' if on else 'rw'}", str(self.root)],
                           check=True)
        elif os.geteuid() != 0:
            for p in (self.root, *self.root.rglob("*")):
                if p.is_dir():
                    p.chmod(0o555 if on else 0o755)
        else:
            pytest.skip("root without mount: no directory here can be made read-only")

    def close(self) -> None:
        if MOUNT:
            subprocess.run(["umount", "-l", str(self.root)], check=False)
        else:
            self.read_only(False)


@contextlib.contextmanager
def disk(tmp_path: Path, size_mib: int = 16) -> Iterator[Disk]:
    d = Disk(tmp_path / "disk", size_mib)
    try:
        yield d
    finally:
        d.close()


@contextlib.contextmanager
def server_log() -> Iterator[ErrorLog]:
    errors = ErrorLog(logging.WARNING)
    lg = logging.getLogger("clothball")
    lg.addHandler(errors)
    try:
        yield errors
    finally:
        lg.removeHandler(errors)


def stored(data: Path, n: int) -> dict[str, bytes]:
    """``n`` rounds saved by a store of its own (as an earlier server run left them)."""
    store = SqliteIndex(data)
    try:
        for i in range(n):
            store.save(header(i), [(1, os.urandom(2000))])
    finally:
        store.close()
    return {p.stem: p.read_bytes() for p in (data / "replays").glob("*.cbr")}


async def listed(srv: Any) -> list[str]:
    return [r["id"] for r in (await http_json(srv, "/api/replays"))["replays"]]


async def check_served(srv: Any, files: dict[str, bytes]) -> None:
    """Every stored round is listed and downloads whole."""
    assert sorted(await listed(srv)) == sorted(files)
    for rid, body in files.items():
        status, got, _ = await http_get(srv, f"/api/replays/{rid}")
        assert (status, got) == (200, body)


async def recording(srv: Any) -> str:
    return (await http_json(srv, "/api/stats"))["recording"]


def off_lines(log: ErrorLog) -> list[str]:
    return [r.getMessage() for r in log.records if "recording is off" in r.getMessage()]


def test_read_only_at_start_serves_the_stored_rounds_and_resumes_when_writable(
        tmp_path: Path) -> None:
    with disk(tmp_path) as d:
        data = d.root / "data"
        files = stored(data, 2)
        d.read_only(True)

        async def main() -> None:
            with server_log() as log:
                async with server(data, default_room=False, limits=FAST_CHECKS) as srv:
                    (line,) = off_lines(log)  # one line, at start
                    assert "read-only" in line and "stay listed and downloadable" in line
                    assert "resumes by itself once it can be written" in line
                    assert "\n" not in line
                    state = await recording(srv)
                    assert state.startswith("off: data directory") and "read-only" in state
                    await check_served(srv, files)
                    with pytest.raises(StorageOff, match="read-only"):
                        await srv.storage.save(header(5), [])
                    await asyncio.sleep(0.3)  # several checks: still one line
                    assert len(off_lines(log)) == 1

                    d.read_only(False)
                    await until(lambda: srv.recording_error is None, 20, "recording resumed")
                    assert await recording(srv) == "on"
                    assert any("recording resumed" in t for t in log.texts())
                    row = await srv.storage.save(header(6), [(1, b"x" * 100)])
                    files[row["id"]] = (data / "replays" / f"{row['id']}.cbr").read_bytes()
                    await check_served(srv, files)

        run(main())


@pytest.mark.skipif(not MOUNT, reason="a full disk needs a tmpfs of the test's own (root)")
def test_a_disk_that_fills_while_running_pauses_recording_until_space_is_freed(
        tmp_path: Path) -> None:
    with disk(tmp_path, size_mib=8) as d:
        data = d.root / "data"
        files = stored(data, 2)

        async def main() -> None:
            with server_log() as log:
                async with server(data, default_room=False, limits=FAST_CHECKS) as srv:
                    assert await recording(srv) == "on"
                    free = shutil.disk_usage(d.root).free
                    junk = d.root / "junk"
                    with open(junk, "wb") as f:  # leaves less than the 1 MiB floor
                        f.write(b"\0" * (free - 512 * 1024))
                    await until(lambda: srv.storage.kind == "full", 20, "full noticed")
                    (line,) = off_lines(log)
                    assert "is full" in line and "stay listed" in line and \
                        "once space is freed" in line
                    state = await recording(srv)
                    assert state.startswith("off:") and "full" in state
                    assert (await http_json(srv, "/api/stats"))["storage"]["state"] == "full"
                    await check_served(srv, files)
                    with pytest.raises(StorageOff, match="full"):
                        await srv.storage.save(header(7), [])

                    junk.unlink()
                    await until(lambda: srv.recording_error is None, 20, "recording resumed")
                    assert await recording(srv) == "on"
                    row = await srv.storage.save(header(8), [(1, b"y" * 100)])
                    assert row["id"] in await listed(srv)

        run(main())


def test_a_failed_write_names_a_full_disk_even_with_room_for_the_probe(
        tmp_path: Path, monkeypatch) -> None:
    """A round larger than the space left fails with ENOSPC while a small probe would fit:
    the write's own error names the problem, and the next look resumes recording."""
    async def main() -> None:
        with server_log():
            async with server(tmp_path, default_room=False,
                              limits=Limits(storage_check_s=3600)) as srv:
                real = index_sql.write_replay

                def no_space(*a: Any, **k: Any) -> int:
                    raise OSError(28, "No space left on device")

                monkeypatch.setattr(index_sql, "write_replay", no_space)
                with pytest.raises(StorageOff, match="could not write the replay: .*No "
                                                     "space left on device.*is full"):
                    await srv.storage.save(header(1), [])
                assert srv.storage.kind == "full"
                assert "full" in await recording(srv)
                monkeypatch.setattr(index_sql, "write_replay", real)
                await srv.storage.check()
                assert await recording(srv) == "on"
                await srv.storage.save(header(2), [])
                assert await listed(srv) == ["disk00002-x"]

    run(main())


def test_a_data_directory_removed_while_running_is_created_anew_and_told_truthfully(
        tmp_path: Path) -> None:
    data = tmp_path / "data"
    stored(data, 2)

    async def main() -> None:
        with server_log() as log:
            async with server(data, default_room=False, limits=FAST_CHECKS) as srv:
                assert len(await listed(srv)) == 2
                old = srv.store
                shutil.rmtree(data)
                await until(lambda: srv.store is not old, 20, "the new index")
                assert any("removed or replaced" in t for t in log.texts())
                # The rounds that went with the directory are not listed (no row that
                # answers 404); recording goes on in the new one.
                assert await listed(srv) == [] and await recording(srv) == "on"
                row = await srv.storage.save(header(3), [(1, b"z")])
                status, _, _ = await http_get(srv, f"/api/replays/{row['id']}")
                assert status == 200 and await listed(srv) == [row["id"]]

    run(main())


def test_a_missing_directory_that_cannot_be_created_is_named_and_recovered(
        tmp_path: Path) -> None:
    with disk(tmp_path) as d:
        data = d.root / "data"
        d.read_only(True)  # data does not exist and cannot be made

        async def main() -> None:
            with server_log() as log:
                async with server(data, default_room=False, limits=FAST_CHECKS) as srv:
                    (line,) = off_lines(log)
                    assert "is missing and cannot be created" in line
                    assert "no stored rounds can be served" in line
                    status, body, _ = await http_get(srv, "/api/replays")
                    assert status == 503 and b"missing" in body
                    assert "missing" in await recording(srv)
                    d.read_only(False)
                    await until(lambda: srv.recording_error is None, 20, "recording resumed")
                    assert await listed(srv) == [] and data.is_dir()
                    row = await srv.storage.save(header(9), [])
                    assert await listed(srv) == [row["id"]]

        run(main())


def test_a_locked_index_keeps_the_round_as_a_file_and_indexes_it_when_free(
        tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(sqlite_index, "BUSY_TIMEOUT_S", 0.02)

    async def main() -> None:
        with server_log() as log:
            async with server(tmp_path, default_room=False, limits=FAST_CHECKS) as srv:
                assert srv.store is not None
                srv.store.lock_wait_s = 0.2
                other = sqlite3.connect(tmp_path / "index.sqlite", isolation_level=None,
                                        check_same_thread=False)
                other.execute("BEGIN IMMEDIATE")
                try:
                    with pytest.raises(StorageOff, match="stayed locked"):
                        await srv.storage.save(header(4), [(1, b"w")])
                    assert (tmp_path / "replays" / "disk00004-x.cbr").is_file()
                    assert srv.storage.kind == "locked"
                    state = await recording(srv)
                    assert "locked" in state and "kept as files" in state
                    assert len(off_lines(log)) == 1
                finally:
                    other.execute("COMMIT")
                    other.close()
                await until(lambda: srv.recording_error is None, 20, "recording resumed")
                assert await listed(srv) == ["disk00004-x"]

    run(main())


def test_a_query_on_an_index_closed_under_it_gets_a_503_not_a_500(tmp_path: Path) -> None:
    """The moment the server swaps the index (a problem found, or gone), a query that had
    taken the old one is told to try again."""
    stored(tmp_path, 1)

    async def main() -> None:
        async with server(tmp_path, default_room=False) as srv:
            assert srv.store is not None
            srv.store.close()  # as Storage does when it switches to read-only
            status, body, _ = await http_get(srv, "/api/replays")
            assert status == 503 and b"try again" in body
            srv.storage.store = None
            await srv.storage.check()  # reopened, as the next look would
            assert len(await listed(srv)) == 1

    run(main())
