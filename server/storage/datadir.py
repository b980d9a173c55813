"""The data directory as the server uses it (``Storage``): its replay index opened to record
while the directory can be written, to list and serve only while it cannot, and a one-line
``problem`` naming what is wrong and what the server does."""

from __future__ import annotations

import asyncio
import errno
import logging
import os
import sqlite3
import time
import typing
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from ..shared.osthread import name_os_thread
from .index import LOCK_WAIT_S, IndexUnavailable, ReplayIndex, Retention
from .postgres import PostgresIndex
from .sqlite import SqliteIndex, locked

log = logging.getLogger("clothball.server")

# The replay index away (a shared PostgreSQL that does not answer): a failed pruning is
# said once, and the index is tried again (pruning, indexing what waits) after
# ``Storage.retry_s`` (the server's storage_check_s), the wait doubling at each failure up
# to RETRY_MAX_S: an index away for hours costs two log lines and a few connection
# attempts, not a line and a connection timeout every check.
RETRY_MAX_S = 300.0


class Backoff:
    """Failures in a row of one thing, and when it is tried next (doubling waits). Its
    state is one tuple, replaced whole: the event loop reads it while the writer thread
    changes it."""

    def __init__(self, first_s: float, max_s: float = RETRY_MAX_S) -> None:
        self.first_s, self.max_s = first_s, max_s
        # (last failure's reason or None, failures in a row, wait after it, retry_at)
        self._st: tuple[str | None, int, float, float] = (None, 0, 0.0, 0.0)

    @property
    def error(self) -> str | None:
        return self._st[0]

    @property
    def wait_s(self) -> float:
        return self._st[2]

    def due(self) -> bool:
        return time.monotonic() >= self._st[3]

    def failed(self, why: str) -> bool:
        """One more failure; True for the first of a run (the one to say)."""
        error, failures, _, _ = self._st
        wait = min(self.first_s * 2 ** failures, self.max_s)
        self._st = (why, failures + 1, wait, time.monotonic() + wait)
        return error is None

    def worked(self) -> bool:
        """It worked; True where it had been failing (the recovery to say)."""
        was = self._st[0] is not None
        self._st = (None, 0, 0.0, 0.0)
        return was

    def state(self) -> dict[str, Any]:
        error, failures, wait, retry_at = self._st
        return {"error": error, "failures": failures, "wait_s": wait,
                "retry_in_s": max(0.0, retry_at - time.monotonic())}


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
    """The data directory as the server uses it: a replay index that records when the
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
                 db: str | None = None, host_url: str | None = None,
                 retry_s: float = 5.0) -> None:
        """``db``: a PostgreSQL URL for an index shared by several hosts
        (``PostgresIndex``; ``host_url``, this host's HTTP address, must be set
        before the first ``check_now``), else the data directory's own SQLite index."""
        self.dir = Path(data_dir)
        self.db = db
        self.host_url = host_url
        self.retention = retention
        self.min_free_bytes = min_free_bytes
        self.lock_wait_s = lock_wait_s
        self.store: ReplayIndex | None = None
        self.kind: str | None = None  # full, read-only, missing, locked, unusable
        self.problem: str | None = None  # the one line; None while recording
        self.free_bytes: int | None = None
        self.saving = 0  # saves under way (on the writer thread or waiting for it)
        self.retry = Backoff(retry_s)  # the replay index away: when it is tried again
        self._lock_trouble = False
        self._logged_without_store = False
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="replay-writer",
                                        initializer=name_os_thread)

    def _open_store(self, **kw: Any) -> ReplayIndex:
        if self.db is None:
            return SqliteIndex(self.dir, **kw)
        assert self.host_url is not None, "Storage.host_url is needed with a shared index"
        return PostgresIndex(self.dir, self.db, host=self.host_url, **kw)

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
        if not self.retry.due():
            return 0
        try:
            pruned = len(store.prune(self.retention))
        except (OSError, sqlite3.Error, IndexUnavailable) as e:
            if self.retry.failed(f"pruning the replays failed: {e}"):
                log.warning("pruning the replays failed: %s; tried again in %g s, then less "
                            "often (up to every %g s) until it works", e, self.retry.wait_s,
                            self.retry.max_s)
            return 0
        if self.retry.worked():
            log.warning("the replay index answers again: pruning resumed")
        return pruned

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
            if not locked(e):
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
            store = self.store
            assert store is not None
            if store.index_error is not None and not self.retry.due():
                return  # away: tried again when its back-off says (``Backoff``)
            store.retry_index()
            if store.index_error is not None:
                self.retry.failed(store.index_error)  # the index said it once itself
            elif self.retry.worked():
                log.warning("the replay index answers again")
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
            if locked(e):
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
