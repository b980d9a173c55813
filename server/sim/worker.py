"""The native frame loop's Python side: a sim worker whose 1 ms frames run in C++
(``native/loop``, docs/frameloop.md), with Python woken only at event and network rates.

A ``NativeWorker`` is a ``SimWorker`` (the same batch, pool, recordings and coalesced
hand-over) whose frames are stepped by ``_native.FrameLoop``: one C++ thread that paces the
frames, reads every room's newest hands from the memory block, steps every awake room in
one call and publishes corners, forces, ball, frame, exits, failures and lateness into the
block. Python learns of them through an eventfd the event loop waits on (``add_reader``):
each wake-up takes every room's events at once and, for a room whose CORNER is due
(``RoomSim.corner_interval`` after the last), reads its record and encodes its four CORNER
messages. Meshes (the due rooms' nodes copied by the loop in one transfer, encoded whole in
C++ and written into the mesh board), TRACK samples of rooms being recorded and the
recording commands are handled by the worker's service thread.
The block's layout is read from offsets the binding exports (one definition, in C++).
"""

from __future__ import annotations

import asyncio
import logging
import math
import mmap
import os
import queue
import secrets
import struct
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from .. import _native  # type: ignore[attr-defined]
from ..game.sim.cloth import _as_finite
from ..game.sim.stability import substep_speed_limits
from ..game.wire import protocol as P
from .frames import FrameResult, Samples
from .shared.lanes import board_slot_bytes
from .shared.osthread import name_os_thread

# server.sim makes the workers and imports this module: its types (SimPool, SimWorker,
# RoomSim) are named here only as strings, without an import (no cycle).
RoomSim = SimPool = SimWorker = Any

log = logging.getLogger("clothball.server")

FRAME_LOOP_ENV = "CLOTHBALL_FRAME_LOOP"  # "native" (default) or "python" (sim.SimWorker)
MESH_THREADS = max(1, min(4, (os.cpu_count() or 1) // 4))  # a worker's MESH encoders
LAYOUT: dict[str, Any] = _native.frame_block_layout()
EVENT = LAYOUT["events"]


def _dtype(fields: list[tuple[str, int, str, tuple[int, ...]]], itemsize: int) -> np.dtype:
    """A NumPy structured type from the binding's field list (block.hpp's offsets)."""
    return np.dtype({"names": [f[0] for f in fields],
                     "formats": [(np.dtype(f[2]), f[3]) if f[3] else np.dtype(f[2])
                                 for f in fields],
                     "offsets": [f[1] for f in fields], "itemsize": itemsize})


ROOM_DTYPE = _dtype(LAYOUT["room"], LAYOUT["room_bytes"])
ENGINE_DTYPE = _dtype(LAYOUT["engine"], LAYOUT["engine_bytes"])
# What FrameLoop.read_room copies: the record up to its events.
# Where FrameLoop.read_room's copy (the record up to its events) holds what a wake-up reads.
_AT = {f[0]: f[1] for f in LAYOUT["room"]}
_FRAME, _TIME, _SUBSTEPS = struct.Struct("<q"), struct.Struct("<d"), struct.Struct("<I")
_OCCUPANTS = struct.Struct("<4Q")
assert _AT["events"] == LAYOUT["room_out_bytes"] and LAYOUT["corner_bytes"] == P.CORNER_SIZE


def frame_loop_wanted() -> bool:
    """Whether sim workers run the native frame loop (``CLOTHBALL_FRAME_LOOP``)."""
    v = os.environ.get(FRAME_LOOP_ENV, "native").strip().lower()
    if v not in ("native", "python"):
        raise ValueError(f"{FRAME_LOOP_ENV} must be 'native' or 'python', got {v!r}")
    return v == "native"


class RingSamples(Samples):
    """The engine's lateness ring in the block, read as ``Samples``: the newest samples
    since the start, or since ``clear()`` (which moves this view's start; each view, the
    worker's and each room's, has its own). The loop appends; this view only reads."""

    def __init__(self, engine: np.ndarray) -> None:
        self._total = engine["lateness_count"]  # views of the EngineRecord (one element)
        self._a = engine["lateness"][0]
        self._base = self._end()

    def _end(self) -> int:
        return int(self._total[0])

    @property
    def count(self) -> int:  # type: ignore[override]
        return self._end() - self._base

    def append(self, value: float) -> None:
        raise TypeError("the frame loop appends lateness samples; this view only reads")

    def clear(self) -> None:
        self._base = self._end()


class NativeStats:
    """A room's ``SimStats``, read from its record in the block."""

    def __init__(self, worker: NativeWorker, room: RoomSim) -> None:
        self._worker = worker
        self._room = room
        self.lateness = RingSamples(worker.engine_view)
        self.meshes = 0
        self._last = (0, 0, 0)  # frames, steps, skipped when the room left its slot

    def _get(self, field: str, k: int) -> int:
        slot = self._room.slot
        if slot is None:
            return self._last[k]
        return int(self._worker.rooms_view[field][slot])

    @property
    def frames(self) -> int:
        return self._get("frame", 0)

    @property
    def steps(self) -> int:
        return self._get("steps", 1)

    @property
    def skipped_frames(self) -> int:
        return self._get("skipped", 2)

    def keep(self) -> None:
        """The room leaves its slot: its counters stay as they were."""
        self._last = (self.frames, self.steps, self.skipped_frames)


def loop_config(worker: NativeWorker, sample: RoomSim) -> Any:
    """The frame loop's settings for a worker's scene (those of its rooms)."""
    scene = worker.scene
    c = _native.FrameLoopConfig()
    c.frame_dt = worker.frame_dt
    c.epoch = worker.pool.epoch
    c.max_catchup = worker.pool.max_catchup
    fixed = scene["sim"]["substeps"]
    c.fixed_substeps = int(fixed) if fixed is not None else 0
    if fixed is None:
        c.substep_speeds = substep_speed_limits(scene).tolist()
    c.has_ball = sample.has_ball
    c.floor_y = sample.floor_y
    c.lost_ball_y = sample.floor_y - 50.0 * sample.size
    if sample.has_ball:
        c.ball_start = np.asarray(scene["ball"]["position"], dtype=np.float64)
    c.stiffness = sample.stiffness
    c.anchors = np.asarray(sample.anchors, dtype=np.float64).reshape(12)
    c.mesh_every = sample.mesh_every
    c.track_every = sample.track_every
    return c


class NativeWorker:
    """Every room of one (scene, backend, precision) stepped by the native frame loop; the
    ``SimWorker`` API the pool and ``RoomSim`` use (see the module doc)."""

    native = True

    def __init__(self, pool: SimPool, base: SimWorker, sample: RoomSim) -> None:
        # `base`: a Python worker, never started, whose batch and coalesced hand-over to the
        # event loop this one uses.
        self._base = base
        scene = base.scene
        self.pool = pool
        self.scene = scene
        self.batch = self._base.batch
        self.frame_dt = self._base.frame_dt
        self.members = 0
        self.mesh_every, self.track_every = sample.mesh_every, sample.track_every
        self._ball_radius = sample.ball_radius  # the scene's: every room's here
        self._loop = _native.FrameLoop(self.batch.native_engine, loop_config(self, sample))
        block = np.frombuffer(self._loop.block(), dtype=np.uint8)
        # The block as a gateway maps it (server.shared.lanes: id, memfd, bytes).
        self.block_id = secrets.randbits(48)  # not reused by a restarted engine
        self.block_share = (self.block_id, self._loop.block_fd(), block.size)
        head = LAYOUT["header_bytes"]
        rooms = self.batch.capacity
        # Each slot's newest MESH message, for the gateways to send (native/loop/board.hpp;
        # a MESH is at most its header and the raw quantised nodes: P.encode_mesh).
        n = scene.n
        self.board_slot = board_slot_bytes(P.HEADER.size + P.MESH_BODY.size + 6 * n * n)
        self.board: mmap.mmap | None = None
        self.board_id: int | None = None
        self.board_share: tuple[int, int, int] | None = None
        self._board_fd = -1
        try:
            self._board_fd = os.memfd_create("clothball-meshes", os.MFD_CLOEXEC)
            os.ftruncate(self._board_fd, rooms * self.board_slot)
            self.board = mmap.mmap(self._board_fd, rooms * self.board_slot)
            self.board_id = secrets.randbits(48)
            self.board_share = (self.board_id, self._board_fd, rooms * self.board_slot)
        except OSError as e:  # e.g. a file size limit: the engine sends every MESH itself
            log.warning("no mesh board (%s): the gateways send no MESH", e)
            if self._board_fd >= 0:
                os.close(self._board_fd)
                self._board_fd = -1
        # MESH encoding on a few threads (C++ ones, else Python ones where the module was
        # built without zlib's headers): one thread encoding every room's MESH 30 times a
        # second was the limit of a 16-core host at ~64 rooms (H100 runs 4 and 16).
        self._encoders = MESH_THREADS
        self._encoder: ThreadPoolExecutor | None = None
        self.rooms_view = block[head:head + rooms * LAYOUT["room_bytes"]].view(ROOM_DTYPE)
        eng = head + rooms * LAYOUT["room_bytes"]
        self.engine_view = block[eng:eng + LAYOUT["engine_bytes"]].view(ENGINE_DTYPE)  # (1,)
        self.lateness = RingSamples(self.engine_view)
        self._by_slot: dict[int, RoomSim] = {}
        self._inbox: queue.SimpleQueue[tuple[RoomSim, str, Any]] = queue.SimpleQueue()
        self._tracks_seen: dict[int, int] = {}
        self._service: threading.Thread | None = None
        self._stop = threading.Event()
        self._reader_loop: asyncio.AbstractEventLoop | None = None

    # --- the SimWorker API ----------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._service is not None and not self._stop.is_set()

    @property
    def full(self) -> bool:
        return self.members >= self.batch.capacity

    @property
    def skipped_frames(self) -> int:
        return int(self.engine_view["skipped"][0])

    @property
    def passes(self) -> int:
        return int(self.engine_view["passes"][0])

    @property
    def substeps(self) -> int:
        r = self.rooms_view
        got = [int(r["substeps"][s]) for s in self._by_slot if r["awake"][s]]
        return max(got) if got and max(got) > 0 else self.batch.substeps

    def cpu_seconds(self) -> float:
        """CPU seconds the frame loop's thread has used (admission's calibration)."""
        return float(self._loop.cpu_seconds())

    def start(self) -> None:
        self._loop.start()
        self._service = threading.Thread(target=self._serve, name="clothball-mesh",
                                         daemon=True)
        self._service.start()
        self._watch()

    def _watch(self) -> None:
        """The event loop waits on the loop's eventfd (once it is known)."""
        loop = self.pool.loop
        if loop is not None and self._reader_loop is None:
            self._reader_loop = loop
            _on_loop(loop, loop.add_reader, self._loop.event_fd(), self._on_events)

    def stop(self) -> None:
        self._stop.set()
        loop = self._reader_loop
        if loop is not None and not loop.is_closed():
            _on_loop(loop, loop.remove_reader, self._loop.event_fd())
        self._loop.notify_service()
        if self._service is not None and self._service is not threading.current_thread():
            self._service.join(timeout=5.0)
        if self._service is None or not self._service.is_alive():
            # Recordings still open as the server stops (their rooms' removal, or the
            # round's end, not yet served): discarded, so that no spool file is left open
            # (a ResourceWarning when collected, in whatever test ran then: the CI dry run
            # at 344b387). Pending commands are not applied: their callbacks need the loop.
            rooms = list(self._by_slot.values())
            while True:
                try:
                    rooms.append(self._inbox.get_nowait()[0])
                except queue.Empty:
                    break
            for room in rooms:
                room.drop_recordings()
        self._loop.stop()
        if self._service is None or not self._service.is_alive():
            if self._encoder is not None:
                self._encoder.shutdown()
            if self.board is not None:
                self.board.close()  # (a gateway's mapping of it stays valid: a memfd)
                os.close(self._board_fd)

    def add_wake(self, fd: int) -> None:
        self._loop.add_wake(fd)

    def remove_wake(self, fd: int) -> None:
        self._loop.remove_wake(fd)

    def post(self, room: RoomSim, name: str, arg: Any) -> None:
        """A command for the service thread (recordings), in order."""
        self._inbox.put((room, name, arg))
        self._loop.notify_service()

    # --- rooms (event-loop side) ----------------------------------------------------------
    def add(self, room: RoomSim) -> None:
        self._watch()
        self._loop.lock()
        try:
            slot = self.batch.add()
            self.batch.set_active(slot, room._awake)
            self._loop.add_room(slot, room._awake)
        finally:
            self._loop.unlock()
        room.slot = slot
        self._by_slot[slot] = room
        room.stats = NativeStats(self, room)
        for seat, hip in enumerate(room._hip_slots):  # and each seat's occupant
            self.set_hip(room, seat, hip)

    def remove(self, room: RoomSim) -> None:
        slot = room.slot
        if slot is None:
            return
        if isinstance(room.stats, NativeStats):
            room.stats.keep()
        self._loop.lock()
        try:
            self._loop.remove_room(slot)
            self.batch.remove(slot)
        finally:
            self._loop.unlock()
        self._by_slot.pop(slot, None)
        self._tracks_seen.pop(slot, None)
        room.slot = None

    def set_hip(self, room: RoomSim, seat: int, hip: tuple[Any, int, float, int] | None) -> None:
        if room.slot is None:
            return
        if hip is None:
            self._loop.clear_hip(room.slot, seat, room._occupant[seat])
            return
        x, y, z = hip[0]
        self._loop.set_hip(room.slot, seat, float(x), float(y), float(z),
                           int(hip[1]) & 0xFFFFFFFFFFFFFFFF,
                           float(hip[2]), hip[3])

    def set_awake(self, room: RoomSim, awake: bool) -> None:
        if room.slot is not None:
            self._loop.set_awake(room.slot, awake)

    def set_armed(self, room: RoomSim, armed: bool) -> None:
        if room.slot is not None:
            self._loop.set_armed(room.slot, armed)

    def set_ball(self, room: RoomSim, pos: Any, vel: Any) -> None:
        if room.slot is None or not room.has_ball:
            return
        # The facade's check (ClothBatch.set_ball made it before this call replaced it).
        ball = np.concatenate([_as_finite("position", pos, (3,)),
                               _as_finite("velocity", vel, (3,))])
        # One native call (the loop's lock taken without the GIL): a Python critical section
        # under the loop's lock stalled every room of the loop while it waited for the GIL.
        self._loop.set_ball(room.slot, ball)

    def applied(self, room: RoomSim, seat: int) -> tuple[int, float]:
        if room.slot is None:
            return (0, math.nan)
        r = self.rooms_view
        return int(r["applied_seq"][room.slot, seat]), float(r["applied_time"][room.slot, seat])

    # --- the event loop's wake-up ---------------------------------------------------------
    def _on_events(self) -> None:
        slots, bits = self._loop.take_events()
        for slot, b in zip(slots.tolist(), bits.tolist(), strict=True):
            room = self._by_slot.get(slot)
            if room is not None:
                self._room_events(room, slot, b)

    def _room_events(self, room: RoomSim, slot: int, bits: int) -> None:
        raw = self._loop.read_room(slot)
        frame, server_time = _FRAME.unpack_from(raw, _AT["frame"])[0], \
            _TIME.unpack_from(raw, _AT["server_time"])[0]
        if frame <= room.delivered and not bits & (EVENT["exit"] | EVENT["failed"]):
            return  # this frame was delivered by an earlier wake-up
        # The four CORNER messages as the loop encoded them (native/loop/corner_msg.hpp).
        at = _AT["corner_msg"]
        corners = [raw[at + k * P.CORNER_SIZE:at + (k + 1) * P.CORNER_SIZE] for k in range(4)]
        result = FrameResult(frame, server_time, corners,
                             occupants=_OCCUPANTS.unpack_from(raw, _AT["applied_occupant"]))
        r = self.rooms_view
        if bits & EVENT["exit"]:
            result.exit = (int(r["exit_edge"][slot]), int(r["exit_frame"][slot]),
                           r["exit_ball"][slot].tolist())
        if bits & EVENT["failed"]:
            fail = int(r["fail_frame"][slot])
            room.error = (f"simulation state became non-finite by frame {fail} (backend "
                          f"{self.batch.backend}, {self.batch.precision}, "
                          f"{_SUBSTEPS.unpack_from(raw, _AT['substeps'])[0]} substeps)")
            log.error("room simulation stopped: %s", room.error)
            self.remove(room)
            result = FrameResult(fail, server_time, [], sim_error=room.error)
        if frame <= room.delivered:  # an exit or failure of a frame delivered already
            result.corners, result.occupants = [], ()
        room.delivered = max(room.delivered, frame)
        room.deliver(result)
        if room.slot is not None:
            # The next wake-up: when the room's players' next CORNER is due (their own
            # schedules, Conn.offer_corner), else one interval on (inf: none wanted).
            due = room.corner_due
            self._loop.set_corner_due(slot, due if due > server_time
                                      else server_time + room.corner_interval)

    # --- the service thread: recordings, tracks, meshes -----------------------------------
    def _serve(self) -> None:
        name_os_thread()
        try:
            while not self._stop.is_set():
                self._loop.wait_service(0.05)
                self._drain_tracks()
                self._drain_inbox()
                self._encode_meshes()
        except Exception:  # pragma: no cover - a bug: recordings and meshes stop
            log.exception("frame loop service thread failed")

    def _drain_inbox(self) -> None:
        while True:
            try:
                room, name, arg = self._inbox.get_nowait()
            except queue.Empty:
                return
            try:
                room.apply(name, arg)
            except OSError as e:  # e.g. a spool that cannot be removed: the others go on
                log.warning("room command %s failed: %s", name, e)
                continue
            if room.slot is not None and name in ("record_start", "record_stop", "remove"):
                self._loop.set_recording(room.slot, bool(room._recordings))
            if name == "record_start" and room.slot is not None:
                self._tracks_seen[room.slot] = int(self.rooms_view["track_count"][room.slot])

    def _drain_tracks(self) -> None:
        ring = LAYOUT["track_ring"]
        for slot, room in list(self._by_slot.items()):
            if not room._recordings:
                continue
            total = int(self.rooms_view["track_count"][slot])
            seen = self._tracks_seen.get(slot, total)
            lost = total - seen - ring
            if lost > 0:
                log.warning("room %s: %d TRACK samples overwritten before recorded",
                            slot, lost)
                seen = total - ring
            for c in range(seen, total):
                t = self.rooms_view["track"][slot, c % ring].copy()
                track = P.encode_track(int(t[0]), float(t[1]), t[2:5], t[5:8],
                                       t[8:20].reshape(4, 3), t[20:32].reshape(4, 3))
                for rec in room._recordings.values():
                    rec.append(1, track)
            self._tracks_seen[slot] = total

    def _encode_meshes(self) -> None:
        if hasattr(self._loop, "take_encoded"):
            # Encoded and written into the board in C++, without the GIL
            # (native/loop/mesh_msg.hpp): 4 threads encoding in Python contended for the
            # GIL with the event loop and one another (H100, 128 rooms: MESH at 17 of 30 Hz).
            # The due rooms are shared among MESH_THREADS threads: zlib takes ~0.5 ms a
            # mesh at n = 48, and one thread held 64 rooms' 30 Hz only at 0.95 core (H100).
            for slot, _, mesh in self._loop.take_encoded(
                    self.board, self.board_slot, self._ball_radius,
                    self.pool.compress_mesh, self._encoders):
                room = self._by_slot.get(slot)
                if room is not None:
                    self._delivered(room, mesh)
            return
        taken = self._loop.take_meshes()
        if not taken:
            return

        def encode(item: tuple[RoomSim, tuple[Any, ...]]) -> bytes:
            room, (_, frame, server_time, ball, hips, positions) = item
            # Quantised and delta-coded in C++, off the GIL (the same bits as
            # protocol.quantise and mesh_deltas; NumPy's took most of a mesh's encoding
            # time), then zlib'd (also off the GIL).
            q, deltas, lo, hi = _native.quantise_mesh(positions)
            return P.encode_quantised_mesh(frame, server_time, q, lo, hi, ball[:3],
                                           room.ball_radius, hips,
                                           compress=self.pool.compress_mesh, deltas=deltas)

        due = ((self._by_slot.get(m[0]), m) for m in taken)
        due = ((room, m) for room, m in due if room is not None)
        if len(taken) > 1 and self._encoders > 1:
            if self._encoder is None:
                self._encoder = ThreadPoolExecutor(self._encoders, "clothball-mesh-encode",
                                                   initializer=name_os_thread)
            items = list(due)
            done = zip(items, self._encoder.map(encode, items), strict=True)
        else:  # one at a time: a mesh's buffers are let go before the next one's
            done = ((item, encode(item)) for item in due)
        for (room, m), mesh in done:
            slot, frame = m[0], m[1]
            if self.board is not None:
                _native.board_write(self.board, slot * self.board_slot, frame, mesh)
            self._delivered(room, mesh)

    def _delivered(self, room: RoomSim, mesh: bytes) -> None:
        """A room's MESH, encoded (and on the board): counted, recorded, and handed to the
        event loop for the clients the engine sends it to."""
        room.stats.meshes += 1
        for rec in room._recordings.values():
            rec.append(1, mesh)
        self._base._publish(room, FrameResult(-1, 0.0, [], mesh=mesh), flush=True)



def _on_loop(loop: asyncio.AbstractEventLoop, fn: Any, *args: Any) -> None:
    """``fn(*args)`` on ``loop``'s thread: now when called there, else soon."""
    try:
        here = asyncio.get_running_loop() is loop
    except RuntimeError:
        here = False
    try:
        if here:
            fn(*args)
        else:
            loop.call_soon_threadsafe(fn, *args)
    except RuntimeError:  # the loop is closed: the server is stopping
        pass
