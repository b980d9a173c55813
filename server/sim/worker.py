"""A sim worker: every room of one (scene, backend, precision), up to its batch's capacity,
stepped by one native frame loop (``native/loop``, docs/frameloop.md), with Python woken
only at event and network rates.

``_native.FrameLoop`` is one C++ thread that paces the 1 ms frames (simulated time locked
to the monotonic clock, or to a test's clock set with ``SimPool.set_clock``), reads every
room's newest hands from the memory block, sets each room's wind gusts, steps every awake
room in one call and publishes corners, forces, ball, frame, exits, failures and lateness
into the block, without the interpreter lock. Python learns of them through an eventfd the
event loop waits on (``add_reader``): each wake-up takes every room's events at once and,
for a room whose CORNER is due (``corner_interval`` after the last), reads its record with
its four CORNER messages as the loop encoded them. Meshes (the due rooms' nodes copied by
the loop in one transfer, encoded whole in C++ on ``MESH_THREADS`` threads and written
into the mesh board), TRACK samples of rooms being recorded and the recording commands are
handled by the worker's service thread; a room's MESH reaches the event loop coalesced (the
newest one per room, one hand-over for all rooms pending).
The block's layout is read from offsets the binding exports (one definition, in C++).
"""

from __future__ import annotations

import asyncio
import logging
import mmap
import os
import queue
import secrets
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from ... import _native
from ...game.sim.batch import ClothBatch
from ...game.sim.cloth import _as_finite, corners_of, rest_positions
from ...game.sim.scene import Scene
from ...game.sim.stability import substep_speed_limits
from ...game.wire import protocol as P
from ..shared.lanes import board_slot_bytes
from ..shared.osthread import name_os_thread
from .results import FrameResult, Samples

log = logging.getLogger("clothball.server")

MESH_THREADS = max(1, min(4, (os.cpu_count() or 1) // 4))  # a worker's MESH encoders
# The service thread's passes are at least this far apart. A room's MESH is due every 33
# frames and rooms are out of phase, so some room's is due nearly every 1 ms frame: a pass
# each frame woke each worker's Python thread 1 000 times a second, each time taking the
# interpreter lock from the event loop. A MESH waits at most this much more (a spectator's
# 30 Hz is 33 ms); a TRACK ring holds 0.64 s.
SERVICE_PERIOD_S = 0.005
# The recording rooms' TRACK samples are drained this often (and before any recording
# command, which may end a recording): a room gains one every 10 ms, and drained each pass,
# each of 256 rooms' single sample cost a NumPy encode and an append of its own (the
# service threads took ~1 core there, H200). The ring holds 0.64 s.
TRACK_PERIOD_S = 0.05
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
# Where FrameLoop.read_room's copy (the record up to its events) holds what a wake-up reads.
_AT = {f[0]: f[1] for f in LAYOUT["room"]}
_FRAME, _TIME, _SUBSTEPS = struct.Struct("<q"), struct.Struct("<d"), struct.Struct("<I")
_OCCUPANTS = struct.Struct("<4Q")
assert _AT["events"] == LAYOUT["room_out_bytes"] and LAYOUT["corner_bytes"] == P.CORNER_SIZE


class Stepped(Protocol):
    """What a worker knows of a room it steps (``RoomSim``): its slot, and where its frames,
    meshes and recording commands go."""

    slot: int | None
    delivered: int  # the newest frame delivered
    corner_interval: float  # s between its CORNER deliveries (0: every frame; inf: none)
    error: str | None
    stats: RoomStats
    wants_meshes: bool  # its MESH messages are handed to the event loop (deliver_mesh)

    def deliver(self, result: FrameResult) -> None: ...  # on the event loop
    def deliver_mesh(self, mesh: bytes) -> None: ...  # on the event loop
    def apply(self, name: str, arg: Any) -> None: ...  # a recording command, service thread
    def record(self, message: bytes) -> None: ...  # a MESH or TRACK, service thread
    def recording(self) -> bool: ...
    def drop_recordings(self) -> None: ...


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


class RoomStats:
    """A room's counters, read from its record in the block (kept as they were once the
    room leaves its slot), its frames' lateness (its worker's passes) and its meshes."""

    def __init__(self, worker: FrameWorker, room: Stepped) -> None:
        self._worker = worker
        self._room = room
        self.lateness = RingSamples(worker.engine_view)
        self.meshes = 0  # MESH messages encoded (the service thread counts them)
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


@dataclass(frozen=True)
class Arena:
    """What every room of a scene shares that the loop and the room both use: the hands'
    anchors, the floor, the ball and the coupling, from the scene's keys."""

    anchors: np.ndarray  # (4, 3): each seat's corner at rest (its hand without a HIP)
    size: float
    floor_y: float  # below it, the ball is out (docs/protocol.md)
    has_ball: bool
    ball_radius: float
    ball_start: tuple[float, float, float]
    stiffness: float  # the coupling's K (0 without it)

    @classmethod
    def of(cls, scene: Scene) -> Arena:
        size = float(scene["cloth"]["size"])
        has_ball = "ball" in scene.effects
        coupled = "coupling" in scene.effects
        return cls(anchors=corners_of(rest_positions(scene)), size=size,
                   floor_y=float(scene["cloth"]["height"]) - 1.5 * size, has_ball=has_ball,
                   ball_radius=float(scene["ball"]["radius"]) if has_ball else 0.0,
                   ball_start=tuple(scene["ball"]["position"]) if has_ball else (0, 0, 0),
                   stiffness=float(scene["coupling"]["stiffness"]) if coupled else 0.0)


@dataclass(frozen=True)
class LoopSettings:
    """How a pool's frame loops keep time and encode meshes (``SimPool``'s)."""

    epoch: float  # monotonic seconds of server time 0 (0 with a manual clock)
    max_catchup: int = 50  # frames a loop steps to catch up; older time is dropped
    cpu_threads: int | None = 1  # the CPU engine's threads a loop (None: one per core)
    compress_mesh: bool = True
    manual_clock: bool = False  # time moves only by SimPool.set_clock (a test's clock)


def loop_config(scene: Scene, arena: Arena, settings: LoopSettings, frame_dt: float,
                mesh_every: int, track_every: int) -> _native.FrameLoopConfig:
    """The frame loop's settings for a worker's scene (those of its rooms)."""
    c = _native.FrameLoopConfig()
    c.frame_dt = frame_dt
    c.epoch = settings.epoch
    c.max_catchup = settings.max_catchup
    c.manual_clock = settings.manual_clock
    fixed = scene["sim"]["substeps"]
    c.fixed_substeps = int(fixed) if fixed is not None else 0
    if fixed is None:
        c.substep_speeds = substep_speed_limits(scene).tolist()
    c.has_ball = arena.has_ball
    c.floor_y = arena.floor_y
    c.lost_ball_y = arena.floor_y - 50.0 * arena.size
    c.ball_start = np.asarray(arena.ball_start, dtype=np.float64)
    c.stiffness = arena.stiffness
    c.anchors = np.asarray(arena.anchors, dtype=np.float64).reshape(12)
    c.mesh_every = mesh_every
    c.track_every = track_every
    if "wind" in scene.effects and scene["wind"]["gust_amplitude"] > 0.0:
        # The loop sets each room's wind every frame (game.sim.cloth.wind_at's formula).
        c.wind = np.asarray(scene["wind"]["velocity"], dtype=np.float64)
        c.gust_amplitude = float(scene["wind"]["gust_amplitude"])
        c.gust_period = float(scene["wind"]["gust_period"])
    return c


class FrameWorker:
    """Every room of one (scene, backend, precision), up to ``capacity``, stepped by one
    native frame loop (see the module doc). Rooms are ``Stepped`` (``RoomSim``)."""

    def __init__(self, scene: Scene, backend: str, capacity: int, settings: LoopSettings,
                 mesh_every: int, track_every: int) -> None:
        self.scene = scene
        self.settings = settings
        self.arena = Arena.of(scene)
        self.batch = ClothBatch(scene, capacity, backend, on_failure="remove",
                                threads=settings.cpu_threads)
        self.frame_dt = self.batch.frame_dt
        self.members = 0  # rooms assigned here and not yet removed (event-loop side)
        self.mesh_every, self.track_every = mesh_every, track_every
        self.frame_loop = _native.FrameLoop(
            self.batch.native_engine,
            loop_config(scene, self.arena, settings, self.frame_dt, mesh_every, track_every))
        block = np.frombuffer(self.frame_loop.block(), dtype=np.uint8)
        # The block as a gateway maps it (server.shared.lanes: id, memfd, bytes).
        self.block_id = secrets.randbits(48)  # not reused by a restarted engine
        self.block_share = (self.block_id, self.frame_loop.block_fd(), block.size)
        head = LAYOUT["header_bytes"]
        rooms = self.batch.capacity
        # Each slot's newest MESH message, for the gateways to send (native/loop/board.hpp;
        # a MESH is at most its header and the raw quantised nodes: P.encode_mesh).
        n = scene.n
        self.board_slot = board_slot_bytes(P.HEADER.size + P.MESH_BODY.size + 6 * n * n)
        # A memfd, so that the gateways map it too; where the process may not make one (a
        # file size limit), anonymous memory: the engine's own port's pump reads it in
        # place, no gateway process.
        size = rooms * self.board_slot
        self.board_id = secrets.randbits(48)
        self.board_share: tuple[int, int, int] | None = None
        self._board_fd = -1
        try:
            self._board_fd = os.memfd_create("clothball-meshes", os.MFD_CLOEXEC)
            os.ftruncate(self._board_fd, size)
            self.board = mmap.mmap(self._board_fd, size)
            self.board_share = (self.board_id, self._board_fd, size)
        except OSError as e:
            log.warning("mesh board not shared (%s): the engine sends its rooms' MESH", e)
            if self._board_fd >= 0:
                os.close(self._board_fd)
                self._board_fd = -1
            self.board = mmap.mmap(-1, size)
        # MESH encoding on a few C++ threads: one thread encoding every room's MESH 30 times
        # a second was the limit of a 16-core host at ~64 rooms (H100 runs 4 and 16).
        self.encoders = MESH_THREADS
        self.rooms_view = block[head:head + rooms * LAYOUT["room_bytes"]].view(ROOM_DTYPE)
        eng = head + rooms * LAYOUT["room_bytes"]
        self.engine_view = block[eng:eng + LAYOUT["engine_bytes"]].view(ENGINE_DTYPE)  # (1,)
        self.lateness = RingSamples(self.engine_view)
        self._by_slot: dict[int, Stepped] = {}
        self._inbox: queue.SimpleQueue[tuple[Stepped, str, Any]] = queue.SimpleQueue()
        self._tracks_seen: dict[int, int] = {}
        self._service: threading.Thread | None = None
        self._stop = threading.Event()
        self._event_loop: asyncio.AbstractEventLoop | None = None
        # The service thread's meshes for the event loop: the newest per room, one
        # hand-over scheduled at a time.
        self._meshes_lock = threading.Lock()
        self._meshes: dict[Stepped, bytes] = {}
        self._scheduled = False

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
        return float(self.frame_loop.cpu_seconds())

    @property
    def service_thread_id(self) -> int | None:
        """The OS thread id of the service thread (None before start)."""
        return None if self._service is None else self._service.native_id

    def start(self) -> None:
        self.frame_loop.start()
        self._service = threading.Thread(target=self._serve, name="clothball-mesh",
                                         daemon=True)
        self._service.start()

    def watch(self, loop: asyncio.AbstractEventLoop) -> None:
        """Deliver to ``loop``: it waits on the frame loop's eventfd (from its own thread)."""
        if self._event_loop is None:
            self._event_loop = loop
            _on_loop(loop, loop.add_reader, self.frame_loop.event_fd(), self._on_events)

    def stop(self) -> None:
        self._stop.set()
        loop = self._event_loop
        if loop is not None and not loop.is_closed():
            _on_loop(loop, loop.remove_reader, self.frame_loop.event_fd())
        self.frame_loop.notify_service()
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
        self.frame_loop.stop()
        if self._board_fd >= 0:
            os.close(self._board_fd)  # (a mapping of it, a gateway's, stays valid)
            self._board_fd = -1

    def add_wake(self, fd: int) -> None:
        self.frame_loop.add_wake(fd)

    def remove_wake(self, fd: int) -> None:
        self.frame_loop.remove_wake(fd)

    def local_shares(self) -> list[tuple[int, Any, str, object]]:
        """Its block and board as this process's lanes read them (``server.lanes.local``),
        with itself as their owner (the memory lives while it does)."""
        return [(self.block_id, self.frame_loop.block(), "block", self),
                (self.board_id, self.board, "board", self)]

    def set_clock(self, t: float) -> None:
        """The loop's time, with a manual clock (``LoopSettings.manual_clock``)."""
        self.frame_loop.set_clock(t)

    def post(self, room: Stepped, name: str, arg: Any) -> None:
        """A recording command for the service thread, in order."""
        self._inbox.put((room, name, arg))
        self.frame_loop.notify_service()

    # --- rooms (event-loop side) ----------------------------------------------------------
    def add(self, room: Stepped, awake: bool) -> int:
        """A slot for ``room``, stepped from the next pass (its hands at their anchors)."""
        self.frame_loop.lock()
        try:
            slot = self.batch.add()
            self.batch.set_active(slot, awake)
            self.frame_loop.add_room(slot, awake)
        finally:
            self.frame_loop.unlock()
        room.slot = slot
        self._by_slot[slot] = room
        return slot

    def remove(self, room: Stepped) -> None:
        slot = room.slot
        if slot is None:
            return
        self.frame_loop.lock()
        try:
            self.frame_loop.remove_room(slot)
            self.batch.remove(slot)
        finally:
            self.frame_loop.unlock()
        self._by_slot.pop(slot, None)
        self._tracks_seen.pop(slot, None)
        with self._meshes_lock:
            self._meshes.pop(room, None)
        room.slot = None

    def set_hip(self, slot: int, seat: int, position: Any, seq: int, client_time: float,
                occupant: int) -> None:
        x, y, z = position
        self.frame_loop.set_hip(slot, seat, float(x), float(y), float(z),
                                int(seq) & 0xFFFFFFFFFFFFFFFF, float(client_time), occupant)

    def clear_hip(self, slot: int, seat: int, occupant: int) -> None:
        self.frame_loop.clear_hip(slot, seat, occupant)

    def set_awake(self, slot: int, awake: bool) -> None:
        self.frame_loop.set_awake(slot, awake)

    def set_armed(self, slot: int, armed: bool) -> None:
        self.frame_loop.set_armed(slot, armed)

    def set_ball(self, slot: int, pos: Any, vel: Any) -> None:
        # The facade's check (ClothBatch.set_ball made it before this call replaced it).
        ball = np.concatenate([_as_finite("position", pos, (3,)),
                               _as_finite("velocity", vel, (3,))])
        # One native call (the loop's lock taken without the GIL): a Python critical section
        # under the loop's lock stalled every room of the loop while it waited for the GIL.
        self.frame_loop.set_ball(slot, ball)

    def applied(self, slot: int, seat: int) -> tuple[int, float]:
        r = self.rooms_view
        return int(r["applied_seq"][slot, seat]), float(r["applied_time"][slot, seat])

    # --- the event loop's wake-up ---------------------------------------------------------
    def _on_events(self) -> None:
        slots, bits = self.frame_loop.take_events()
        for slot, b in zip(slots.tolist(), bits.tolist(), strict=True):
            room = self._by_slot.get(slot)
            if room is not None:
                self._room_events(room, slot, b)

    def _room_events(self, room: Stepped, slot: int, bits: int) -> None:
        raw = self.frame_loop.read_room(slot)
        frame, server_time = _FRAME.unpack_from(raw, _AT["frame"])[0], \
            _TIME.unpack_from(raw, _AT["server_time"])[0]
        if frame <= room.delivered and not bits & (EVENT["exit"] | EVENT["failed"]):
            return  # this frame was delivered by an earlier wake-up
        # The four CORNER messages as the loop encoded them (native/loop/corner_msg.hpp).
        at = _AT["corner_msg"]
        corners: list[bytes | None] = [raw[at + k * P.CORNER_SIZE:at + (k + 1) * P.CORNER_SIZE]
                                       for k in range(4)]
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
            # The next wake-up for a frame: one interval on (inf: none wanted, only exits
            # and failures wake it).
            self.frame_loop.set_corner_due(slot, server_time + room.corner_interval)

    # --- the service thread: recordings, tracks, meshes -----------------------------------
    def _serve(self) -> None:
        name_os_thread()
        tracks_due = 0.0
        try:
            while not self._stop.is_set():
                self.frame_loop.wait_service(0.05)
                began = time.monotonic()
                if began >= tracks_due or not self._inbox.empty():
                    self._drain_tracks()
                    tracks_due = began + TRACK_PERIOD_S
                self._drain_inbox()
                self._encode_meshes()
                self._stop.wait(SERVICE_PERIOD_S - (time.monotonic() - began))
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
            if room.slot is not None and name in ("record_start", "record_stop"):
                self.frame_loop.set_recording(room.slot, room.recording())
            if name == "record_start" and room.slot is not None:
                self._tracks_seen[room.slot] = int(self.rooms_view["track_count"][room.slot])
            elif name == "record_stop" and room.slot is not None and not room.recording():
                self._tracks_seen.pop(room.slot, None)  # (its samples are looked at no more)

    def _drain_tracks(self) -> None:
        """Each recording room's TRACK samples written since the last look, into its
        recordings (every ``TRACK_PERIOD_S``): the recording rooms' counts are compared in
        one array operation and only the rooms with new samples looked at."""
        recording = list(self._tracks_seen.items())  # (slot, seen); changed by other threads
        if not recording:
            return
        slots, seen = np.array(recording, dtype=np.int64).T
        totals = self.rooms_view["track_count"][slots].astype(np.int64)
        ring = LAYOUT["track_ring"]
        for k in np.nonzero(totals != seen)[0]:
            slot, total, first = int(slots[k]), int(totals[k]), int(seen[k])
            room = self._by_slot.get(slot)
            if room is None or not room.recording():
                continue
            lost = total - first - ring
            if lost > 0:
                log.warning("room %s: %d TRACK samples overwritten before recorded",
                            slot, lost)
                first = total - ring
            msgs = P.encode_tracks(self.rooms_view["track"][slot, np.arange(first, total) % ring])
            for i in range(0, len(msgs), P.TRACK_SIZE):
                room.record(msgs[i:i + P.TRACK_SIZE])
            self._tracks_seen[slot] = total

    def _encode_meshes(self) -> None:
        # Encoded and written into the board in C++, without the GIL
        # (native/loop/mesh_msg.hpp): 4 threads encoding in Python contended for the GIL
        # with the event loop and one another (H100, 128 rooms: MESH at 17 of 30 Hz). The
        # due rooms are shared among the encoder threads: zlib took ~0.5 ms a mesh at
        # n = 48 (one thread held 64 rooms' 30 Hz only at 0.95 core, H100); MESH version
        # 2 takes ~0.2x that (`clothball bench --mesh`).
        taken = self.frame_loop.take_encoded(self.board, self.board_slot,
                                             self.arena.ball_radius,
                                             self.settings.compress_mesh, self.encoders)
        fresh: dict[Stepped, bytes] = {}
        for slot, _, mesh in taken:
            room = self._by_slot.get(slot)
            if room is not None:
                room.stats.meshes += 1
                room.record(mesh)
                if room.wants_meshes:
                    fresh[room] = mesh
        if fresh:
            self._hand_over(fresh)

    def _hand_over(self, fresh: dict[Stepped, bytes]) -> None:
        """Rooms' newest MESH to the event loop: one scheduled call delivers every room's
        pending one, however many the service thread made meanwhile."""
        loop = self._event_loop
        if loop is None:
            return
        with self._meshes_lock:
            self._meshes.update(fresh)
            if self._scheduled:
                return
            self._scheduled = True
        try:
            loop.call_soon_threadsafe(self._deliver_meshes)
        except RuntimeError:  # the loop is closed: the server is stopping
            self._stop.set()

    def _deliver_meshes(self) -> None:
        with self._meshes_lock:
            meshes, self._meshes = self._meshes, {}
            self._scheduled = False
        for room, mesh in meshes.items():
            room.deliver_mesh(mesh)


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
