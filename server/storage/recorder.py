"""A round's recording, spooled to disk as it is made: memory stays bounded however long the
round lasts.

The simulation worker appends records (events, MESH and TRACK messages) to a ``Recording``.
They gather in a buffer of at most ``BUFFER_BYTES``; a full buffer is handed to one writer
thread that appends it to the recording's spool file (``<spool dir>/<id>.spool``, the
records in the replay file's record format, uncompressed). At most ``MAX_PENDING`` buffers
wait for the writer: a disk too slow for that, or a write that fails, ends the recording
there (``cut`` says why) rather than holding more in memory. A round longer than ``cap_s``
is recorded up to the cap and marked cut. ``records()`` reads the spool back in order
(the replay writer compresses it into the ``.cbr`` file); ``discard()`` removes the spool.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import shutil
import struct
import threading
from collections.abc import Iterator
from pathlib import Path

from ...game.wire import protocol as P
from ...game.wire.replay import RECORD
from ..shared.osthread import name_os_thread

log = logging.getLogger("clothball.server")

SPOOL_DIR = "spool"  # under the data directory; spools left by a crash are removed at start
BUFFER_BYTES = 256 * 1024  # records held in memory per recording before they go to disk
MAX_PENDING = 8  # full buffers waiting for the writer, per recording (then it is cut)
READ_CHUNK = 1 << 20


def spool_dir_for(data_dir: Path) -> Path:
    """This process's spool directory under ``data_dir``, after removing those of processes
    that no longer run (a crash's leftovers; processes of one host share the data dir)."""
    root = Path(data_dir) / SPOOL_DIR
    try:
        for d in root.iterdir():
            if d.name.isdigit() and int(d.name) != os.getpid() and not _running(int(d.name)):
                shutil.rmtree(d, ignore_errors=True)
    except OSError:
        pass  # no spool yet, or a data directory the storage check reports on
    return root / str(os.getpid())


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # exists, someone else's
    return True


class _Writer:
    """The one thread that appends spool buffers to their files, in order."""

    def __init__(self) -> None:
        self._q: queue.SimpleQueue[tuple[Recording, bytes] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="clothball-spool",
                                        daemon=True)
        self._thread.start()

    def put(self, rec: Recording, data: bytes) -> None:
        self._q.put((rec, data))

    def _run(self) -> None:
        name_os_thread()
        while True:
            item = self._q.get()
            if item is None:
                return
            rec, data = item
            rec._write(data)


_writer: _Writer | None = None
_writer_lock = threading.Lock()


def _spool_writer() -> _Writer:
    global _writer
    with _writer_lock:
        if _writer is None:
            _writer = _Writer()
        return _writer


class Recording:
    """One round's records, spooled to ``spool_dir`` (see the module doc)."""

    def __init__(self, rid: str, spool_dir: Path, cap_s: float, frame_dt: float) -> None:
        self.id = rid
        self.path = Path(spool_dir) / f"{rid}.spool"
        self.cap_frames = max(1, round(cap_s / frame_dt))
        self.frame_dt = frame_dt
        self.cut: str | None = None  # why the recording stopped early
        self.error: str | None = None  # why the spool could not be written (then not saved)
        self.first_frame: int | None = None
        self.last_frame: int | None = None
        self.bytes = 0  # record bytes taken (spooled or buffered)
        self.peak_buffer = 0  # most bytes held in memory at once (buffer + pending)
        self._buf: list[bytes] = []
        self._buf_bytes = 0
        self._pending = 0  # buffers handed to the writer, not yet written
        self._lock = threading.Lock()
        self._written = threading.Condition(self._lock)
        try:
            Path(spool_dir).mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "wb")  # noqa: SIM115 - closed by finish/discard
        except OSError as e:
            self._file = None
            self.error = self.cut = str(e.strerror or e)

    # --- the simulation's side ------------------------------------------------------------
    def append(self, kind: int, data: bytes) -> None:
        if self.cut is not None:
            return
        if kind == 1 and len(data) >= P.HEADER.size + 8 and data[0] in (P.MESH, P.TRACK):
            frame = struct.unpack_from("<q", data, P.HEADER.size)[0]
            # A MESH is encoded off the frame and may come after a newer TRACK: the span is
            # from the smallest frame to the largest (as replay.recorded_length takes it).
            if self.first_frame is None or frame < self.first_frame:
                self.first_frame = frame
            if frame - self.first_frame > self.cap_frames:
                self.cut = f"longer than the recording cap ({self.cap_frames * self.frame_dt:g} s)"
                self._flush()
                return
            if self.last_frame is None or frame > self.last_frame:
                self.last_frame = frame
        record = RECORD.pack(kind, len(data)) + data
        self._buf.append(record)
        self._buf_bytes += len(record)
        self.bytes += len(record)
        if self._buf_bytes >= BUFFER_BYTES:
            self._flush()

    def _flush(self) -> None:
        if not self._buf:
            return
        data = b"".join(self._buf)
        self._buf, self._buf_bytes = [], 0
        with self._lock:
            if self.error is not None:
                self.cut = self.cut or self.error
                return
            if self._pending >= MAX_PENDING:
                self.cut = self.cut or "the disk could not keep up with the recording"
                return
            self._pending += 1
            self.peak_buffer = max(self.peak_buffer, self._pending * len(data))
        _spool_writer().put(self, data)

    @property
    def duration_s(self) -> float:
        """First to last recorded MESH or TRACK frame (as ``replay.recorded_length``)."""
        if self.first_frame is None or self.last_frame is None:
            return 0.0
        return (self.last_frame - self.first_frame) * self.frame_dt

    # --- the writer thread ----------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        err = None
        try:
            if self._file is None:
                raise OSError("the spool file is closed")
            self._file.write(data)
        except OSError as e:
            err = str(e.strerror or e)
            log.warning("round %s: the recording could not be written: %s", self.id, err)
        with self._lock:
            self._pending -= 1
            if err is not None and self.error is None:
                self.error = err
            self._written.notify_all()

    # --- the saver's side -----------------------------------------------------------------
    def finish(self, timeout: float = 30.0) -> None:
        """Everything appended is on disk (blocks: call it off the event loop)."""
        self._flush()
        with self._lock:
            self._written.wait_for(lambda: self._pending == 0, timeout)
        if self._file is not None:
            try:
                self._file.close()
            except OSError as e:
                self.error = self.error or str(e.strerror or e)
            self._file = None

    def records(self) -> Iterator[tuple[int, bytes]]:
        """The spooled records in order, read in chunks (after ``finish``)."""
        with open(self.path, "rb") as f:
            tail = b""
            while True:
                chunk = f.read(READ_CHUNK)
                if not chunk:
                    break
                buf = tail + chunk
                off = 0
                while off + RECORD.size <= len(buf):
                    kind, length = RECORD.unpack_from(buf, off)
                    if off + RECORD.size + length > len(buf):
                        break
                    yield kind, buf[off + RECORD.size: off + RECORD.size + length]
                    off += RECORD.size + length
                tail = buf[off:]

    def __iter__(self) -> Iterator[tuple[int, bytes]]:
        return self.records()

    def discard(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
        with contextlib.suppress(OSError):  # gone with its directory, or never made
            self.path.unlink(missing_ok=True)
