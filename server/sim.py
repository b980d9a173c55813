"""The rooms' simulation: simulated time locked to wall time, in 1 ms frames, every room of
one scene stepped by one call.

A ``SimPool`` holds the server's sim workers, one per (scene, backend, precision). A worker
owns a ``ClothBatch`` (each room is one slot). By default its frames run in the native
frame loop (``server.frameloop``, docs/frameloop.md): one C++ thread per worker that paces
the frames, reads every room's hands from a shared memory block, steps, publishes and checks
exits without the interpreter lock, and wakes the event loop through an eventfd at event
and network rates. ``CLOTHBALL_FRAME_LOOP=python`` (and a pool with a test's clock, or a
scene with wind gusts) selects the Python loop below, ``SimWorker``: one thread that keeps
the pace whatever the event loop or the network does: it sleeps until the next frame is
due, applies every room's latest hand positions (latest wins) in one call, steps every frame
that is due for all its rooms in one call (catching up at most ``max_catchup`` frames after
a hiccup; older time is dropped and counted), reads back all corners and balls in one call,
checks each room's ball against its edges, and hands the results to the event loop
*coalesced*: at most one delivery per room is pending at a time and it carries the newest
frame, so a busy loop never builds a queue, and one loop wake-up carries every room's
result. Both loops make a room's mesh every ``1/mesh_hz`` s (quantised into a MESH message
once for all its spectators, on the worker's encoder thread), and while a round is recorded
the room keeps the MESH messages and a TRACK message every ``1/track_hz`` s.

The event loop talks to a room only through its ``RoomSim``: ``set_hip`` (an atomic slot
per seat) and ``command`` (a queue the worker drains between frames). A room nobody is in
sleeps (``set_awake(False)``): its slot keeps its state and is not stepped.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import math
import queue
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..game.rules import exit_edge_fast
from ..game.sim.batch import ClothBatch
from ..game.sim.cloth import corners_of, resolve_backend, rest_positions
from ..game.sim.scene import Scene
from ..game.wire import protocol as P
from .frameloop import NativeWorker, frame_loop_wanted
from .frames import FrameResult, Samples
from .shared.osthread import name_os_thread
from .storage.recorder import Recording

_OCCUPANTS = itertools.count(1)  # RoomSim._occupant's numbers

log = logging.getLogger("clothball.server")

# s: a sleep ends up to this late (Linux's default timer slack), so a frame may start this
# much before its time instead.
TIMER_SLACK = 50e-6
# Rooms one worker's batch holds; a pool opens another worker of the same scene beyond it.
WORKER_CAPACITY = 64


LATENESS_SAMPLES = 100_000  # per room and per worker: 0.8 MB each, taken once


@dataclass
class SimStats:
    frames: int = 0
    steps: int = 0  # step calls (one frame each, more when catching up)
    skipped_frames: int = 0  # frames dropped because the loop fell further behind than allowed
    lateness: Samples = field(default_factory=lambda: Samples(LATENESS_SAMPLES))  # s
    meshes: int = 0


class RoomSim:
    """One room's simulation: a slot of its scene's worker (see the module doc).

    Made with a ``pool`` (the server's); without one it runs on a private pool of its own
    (a lone room, as in tests and tools), which ``stop`` closes.
    """

    def __init__(self, scene: Scene, backend: str = "auto", *,
                 deliver: Callable[[FrameResult], None] | None = None,
                 loop: asyncio.AbstractEventLoop | None = None,
                 mesh_hz: float = 30.0, track_hz: float = 100.0, max_catchup: int = 50,
                 compress_mesh: bool = True, clock: Callable[[], float] = time.perf_counter,
                 epoch: float | None = None, cpu_threads: int | None = 1,
                 pool: SimPool | None = None) -> None:
        self._own_pool = pool is None
        if pool is None:
            pool = SimPool(loop=loop, clock=clock, epoch=epoch, max_catchup=max_catchup,
                           cpu_threads=cpu_threads, compress_mesh=compress_mesh)
        self.pool = pool
        self.scene = scene
        self.frame_dt = float(scene["sim"]["frame_dt"])
        rest = rest_positions(scene)
        self.anchors = corners_of(rest)
        self.size = float(scene["cloth"]["size"])
        self.floor_y = float(scene["cloth"]["height"]) - 1.5 * self.size
        self.has_ball = "ball" in scene.effects
        self.ball_radius = float(scene["ball"]["radius"]) if self.has_ball else 0.0
        coupled = "coupling" in scene.effects
        self.stiffness = float(scene["coupling"]["stiffness"]) if coupled else 0.0
        self.mesh_every = max(1, round(1.0 / (mesh_hz * self.frame_dt)))
        self.track_every = max(1, round(1.0 / (track_hz * self.frame_dt)))
        self._deliver = deliver
        self._hip_slots: list[tuple[Any, int, float, int] | None] = [None] * 4
        self._applied: list[tuple[int, float]] = [(0, math.nan)] * 4
        # Per seat, its occupant: a number new each time its hand is cleared (an occupant
        # left), unique in the process, so that a CORNER made from an earlier occupant's
        # HIP is not given to the next one (docs/protocol.md: `seq` is the last HIP the
        # server applied for this seat), and a HIP a gateway writes late for an occupant
        # that left, or for a room that left its slot, is ignored (native/loop/block.hpp).
        self._occupant = [next(_OCCUPANTS) for _ in range(4)]
        self._applied_occupant = list(self._occupant)
        self._awake = True
        self._stopped = threading.Event()
        self.stats: Any = SimStats()  # a NativeStats on the native loop (same fields)
        # s between this room's CORNER deliveries on the native loop (0: every frame; inf:
        # none wanted); the Python loop delivers every pass.
        self.corner_interval = 0.0
        # server time the room's first player's next CORNER is due (its Room sets it as it
        # offers them; -inf: not known, the native loop then waits corner_interval)
        self.corner_due = -math.inf
        self.delivered = -1  # the newest frame the native loop delivered
        self.worker: Any = pool.worker_for(scene, backend, room=self)
        self._native = getattr(self.worker, "native", False)
        self.backend = self.worker.batch.backend
        # Worker-thread state.
        self.slot: int | None = None
        self._armed = False
        self._recordings: dict[str, Recording] = {}
        self._done = 0  # frames stepped since the room last woke
        self._next_mesh = 0
        self._next_track = 0
        self.error: str | None = None

    # --- event-loop side ------------------------------------------------------------------
    def start(self) -> None:
        if self._native:
            self.worker.add(self)
        else:
            self.worker.post(self, "add", None)

    def stop(self) -> None:
        """Take the room off its worker (waits for the worker to let go of it)."""
        if not self._stopped.is_set():
            if self._native:
                self.worker.remove(self)
                self.worker.post(self, "drop", None)  # recordings, on the service thread
                self._stopped.set()
            else:
                self.worker.post(self, "remove", None)
                if not (self.worker.running and self._stopped.wait(timeout=5.0)):
                    self._stopped.set()
            self.worker.members -= 1
        if self._own_pool:
            self.pool.close()

    def set_awake(self, awake: bool) -> None:
        """Step the room (True) or let it sleep (False): no stepping, no CPU, until woken;
        it then starts afresh from the state it slept in, at once."""
        self._awake = bool(awake)
        if self._native:
            self.worker.set_awake(self, self._awake)
        else:
            self.worker.post(self, "awake", self._awake)

    @property
    def asleep(self) -> bool:
        return not self._awake

    @property
    def alive(self) -> bool:
        """The room is on a running worker and has not failed."""
        return self.worker.running and self.error is None and not self._stopped.is_set()

    @property
    def substeps(self) -> int:
        return self.worker.substeps if self._native else self.worker.batch.substeps

    @property
    def frame(self) -> int:
        """Frames simulated since the room started (or last failed and reset)."""
        return self.stats.frames

    def now(self) -> float:
        """Server time: seconds since the server started."""
        return self.pool.now()

    def set_hip(self, seat: int, position: Any, seq: int = 0,
                client_time: float = math.nan) -> None:
        """The latest hand position for a seat, three floats (an array or a tuple; None:
        the corner rests at its anchor, and the seat's occupant changed: its HIP echo
        starts again from seq 0)."""
        if position is None:
            self._occupant[seat] = next(_OCCUPANTS)
            self._hip_slots[seat] = None
        else:
            self._hip_slots[seat] = (position, seq, client_time, self._occupant[seat])
        if self._native:
            self.worker.set_hip(self, seat, self._hip_slots[seat])

    def lane_place(self, seat: int | None) -> dict[str, Any] | None:
        """Where a gateway serves a client of this room (``server.shared.lanes``): the
        block and slot, the seat's occupant (0 for none), the mesh board and its slot
        size; None where the room is not in a native frame loop's block."""
        if not self._native or self.slot is None:
            return None
        w = self.worker
        return {"block": w.block_id, "slot": self.slot,
                "occupant": 0 if seat is None else self._occupant[seat],
                "board": w.board_id, "board_slot": w.board_slot}  # board None: no MESH

    def hip_echo(self, seat: int) -> tuple[int, float]:
        """The (seq, client time) of the seat's HIP the newest frame applied (0, NaN: none
        since its occupant took it), as its CORNER echoes them."""
        return self.worker.applied(self, seat) if self._native else self._applied[seat]

    def command(self, name: str, arg: Any = None) -> None:
        """Queue a command for the worker: ``reset_ball`` ((pos, vel)), ``arm``, ``disarm``,
        ``record_start`` ((id, cap in s)), ``record_event`` ((id, bytes): to that
        recording), ``record_stop`` ((id, callback): the callback gets that ``Recording``,
        or None, on the worker's thread). Recordings may overlap (a round's tail and the
        next round's start). A recording spools to disk as it goes (``server.recorder``)."""
        if self._native and name == "reset_ball":
            self.worker.set_ball(self, arg[0], arg[1])
        elif self._native and name in ("arm", "disarm"):
            self.worker.set_armed(self, name == "arm")
        else:
            self.worker.post(self, name, arg)

    # --- worker side (called on the worker's thread only) ------------------------------------
    def apply(self, name: str, arg: Any) -> None:
        w = self.worker
        if name == "reset_ball":
            if self.has_ball and self.slot is not None:
                w.batch.set_ball(self.slot, arg[0], arg[1])
        elif name == "arm":
            self._armed = True
        elif name == "disarm":
            self._armed = False
        elif name == "record_start":
            rid, cap_s = arg
            self._recordings[rid] = Recording(rid, self.pool.spool_dir, cap_s, self.frame_dt)
        elif name == "record_mesh":
            for rec in self._recordings.values():
                rec.append(1, arg)
        elif name == "record_event":
            rid, data = arg
            if (rec := self._recordings.get(rid)) is not None:
                rec.append(0, data)
        elif name == "record_stop":
            rid, callback = arg
            callback(self._recordings.pop(rid, None))
        elif name == "drop":
            self.drop_recordings()

    def drop_recordings(self) -> None:
        """The room is gone: recordings in progress are discarded."""
        for rec in self._recordings.values():
            rec.discard()
        self._recordings.clear()

    def fill_hips(self, out: np.ndarray) -> None:
        """This frame's hands into ``out`` (4, 3): the newest HIP per seat, else the anchor."""
        out[:] = self.anchors
        for s in range(4):
            occupant = self._occupant[s]  # read before the slot: see set_hip
            slot = self._hip_slots[s]
            if slot is None:
                self._applied[s] = (0, math.nan)
                self._applied_occupant[s] = occupant
            else:
                out[s] = slot[0]
                self._applied[s] = (slot[1], slot[2])
                self._applied_occupant[s] = slot[3]

    def woke(self) -> None:
        """Pace from now, a mesh at once; the slept time is not replayed."""
        self._done = self._next_mesh = self._next_track = 0

    def after_step(self, frames: int, pos: np.ndarray, vel: np.ndarray, ball: np.ndarray,
                   hips: np.ndarray, server_time: float, late: float) -> FrameResult:
        stats = self.stats
        self._done += frames
        stats.frames += frames
        stats.steps += 1
        frame = stats.frames
        stats.lateness.append(late)
        force = -self.stiffness * (hips - pos)
        bp, bv = ball[:3], ball[3:]
        pl, bpl = pos.tolist(), bp.tolist()
        corners = P.encode_corners(frame, server_time, pl, vel.tolist(), force.tolist(),
                                   self.stiffness, bpl, bv.tolist(), self._applied)
        result = FrameResult(frame, server_time, corners,
                             occupants=tuple(self._applied_occupant))
        if self.has_ball:
            if self._armed:
                # Plain floats and a cheap exact pre-test: the full test (NumPy, ~30 us)
                # runs only when the ball is near an edge or the floor.
                edge = exit_edge_fast(bpl, pl, self.floor_y)
                if edge is not None:
                    self._armed = False
                    result.exit = (edge, frame, bpl)
            elif bp[1] < self.floor_y - 50.0 * self.size and self.slot is not None:
                # Nobody is playing and the ball fell off: put it back, keep it bounded.
                self.worker.batch.set_ball(self.slot, self.scene["ball"]["position"],
                                           (0.0, 0.0, 0.0))
        if self._done >= self._next_mesh:
            self._next_mesh = self._done + self.mesh_every
            self.worker.want_mesh(self, (frame, server_time, bp.copy(), hips.copy()))
        if self._recordings and self._done >= self._next_track:
            self._next_track = self._done + self.track_every
            track = P.encode_track(frame, server_time, bp, bv, hips, pos)
            for rec in self._recordings.values():
                rec.append(1, track)
        return result

    def deliver(self, result: FrameResult) -> None:
        if self._deliver is not None and not self._stopped.is_set():
            for s, occupant in enumerate(result.occupants):
                if occupant != self._occupant[s]:  # made before the seat changed hands
                    result.corners[s] = None
            self._deliver(result)


class SimWorker:
    """Every room of one (scene, backend, precision), up to its batch's capacity, stepped
    by one thread (see the module doc)."""

    def __init__(self, pool: SimPool, scene: Scene, backend: str, capacity: int) -> None:
        self.pool = pool
        self.scene = scene
        self.batch = ClothBatch(scene, capacity, backend, on_failure="remove",
                                threads=pool.cpu_threads)
        self.frame_dt = self.batch.frame_dt
        self._hips = np.zeros((capacity, 4, 3))
        self._hips[:] = corners_of(rest_positions(scene))
        self.rooms: list[RoomSim] = []  # on the batch (worker thread's list)
        self.members = 0  # rooms assigned here and not yet removed (event-loop side)
        # (room, command, argument, clock when posted)
        self._inbox: queue.SimpleQueue[tuple[RoomSim, str, Any, float]] = queue.SimpleQueue()
        self._resume_at: float | None = None  # when the first room of an idle spell woke
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._encoder: threading.Thread | None = None
        self._mesh_lock = threading.Lock()
        self._mesh_wanted: dict[RoomSim, tuple[Any, ...]] = {}
        self._mesh_ready = threading.Event()
        self._pending_lock = threading.Lock()
        self._pending: dict[RoomSim, FrameResult] = {}
        self._scheduled = False  # a hand-over is queued on the event loop
        self.passes = 0  # step calls, all rooms at once
        self.skipped_frames = 0  # frames dropped for being too far behind (all rooms)
        self.lateness = Samples(LATENESS_SAMPLES)  # s, per pass

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def full(self) -> bool:
        return self.members >= self.batch.capacity

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="clothball-sim", daemon=True)
        self._thread.start()
        self._encoder = threading.Thread(target=self._encode_meshes, name="clothball-mesh",
                                         daemon=True)
        self._encoder.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        self._mesh_ready.set()
        for t in (self._thread, self._encoder):
            if t is not None and t is not threading.current_thread():
                t.join(timeout=5.0)

    def post(self, room: RoomSim, name: str, arg: Any) -> None:
        self._inbox.put((room, name, arg, self.pool.clock()))
        self._wake.set()

    # --- the worker's thread --------------------------------------------------------------
    def _run(self) -> None:
        name_os_thread()
        try:
            self._loop_body()
        except Exception as e:  # pragma: no cover - a bug: every room of the worker stops
            log.exception("simulation worker failed")
            for room in list(self.rooms):
                room.error = f"internal error: {e}"
                self._publish(room, FrameResult(-1, self.pool.now(), [], sim_error=room.error))

    def _drain(self) -> None:
        while True:
            try:
                room, name, arg, posted = self._inbox.get_nowait()
            except queue.Empty:
                return
            if name == "add" or (name == "awake" and arg):
                # An idle worker paces from the moment a room arrived or woke.
                if self._resume_at is None:
                    self._resume_at = posted
            if name == "add":
                if room.slot is None and not room._stopped.is_set():
                    room.slot = self.batch.add()
                    self.rooms.append(room)
                    self.batch.set_active(room.slot, room._awake)
            elif name == "remove":
                self._drop(room)
                room.drop_recordings()
                room._stopped.set()
            elif name == "awake":
                if room.slot is not None and arg != self.batch.active(room.slot):
                    self.batch.set_active(room.slot, arg)
                    if arg:
                        room.woke()
            else:
                room.apply(name, arg)

    def _drop(self, room: RoomSim) -> None:
        if room in self.rooms:
            self.rooms.remove(room)
        if room.slot is not None:
            self.batch.remove(room.slot)
            room.slot = None
        with self._mesh_lock:
            self._mesh_wanted.pop(room, None)

    def _loop_body(self) -> None:
        batch, dt, clock = self.batch, self.frame_dt, self.pool.clock
        max_catchup = self.pool.max_catchup
        t0 = clock()
        done = 0  # frames simulated since t0
        was_idle = True
        while not self._stop.is_set():
            self._drain()
            live = [r for r in self.rooms if r.slot is not None and batch.active(r.slot)]
            if not live:
                # Nothing to step: wait for a room, a wake-up or a command, using no CPU.
                was_idle = True
                self._resume_at = None
                self._wake.wait(0.05)
                self._wake.clear()
                continue
            if was_idle:
                # Pace afresh: the idle time is not replayed.
                t0 = clock() if self._resume_at is None else self._resume_at
                was_idle, done, self._resume_at = False, 0, None
            now = clock()
            behind = int((now - t0 + TIMER_SLACK) / dt) - done
            if behind <= 0:
                # Sleep the whole wait: spinning through the end of it would hold the GIL
                # while the event loop has HIPs to read and corners to send.
                time.sleep(t0 + (done + 1) * dt - TIMER_SLACK - now)
                continue
            if behind > max_catchup:
                skip = behind - max_catchup
                t0 += skip * dt
                self.skipped_frames += skip
                for r in live:
                    r.stats.skipped_frames += skip
                behind = max_catchup
            # Behind, step a quarter of the frames due (at least one) per pass: each pass takes
            # the newest hand positions and publishes its corners, so a HIP waits for a part
            # of the backlog, not all of it, and a room far behind still catches up quickly.
            frames = min(behind, 1 + behind // 4)
            hips = self._hips
            for r in live:
                r.fill_hips(hips[r.slot])
            batch.set_hips_all(hips)
            failed = batch.step(frames)
            done += frames
            self.passes += 1
            pos, vel, balls = batch.corners_all()
            t_end = clock()
            server_time = t_end - self.pool.epoch
            late = t_end - (t0 + done * dt)
            self.lateness.append(late)
            for r in live:
                if r.slot in failed:
                    self._fail(r, frames)
                    continue
                s = r.slot
                self._publish(r, r.after_step(frames, pos[s], vel[s], balls[s], hips[s],
                                              server_time, late))
            self._flush()

    def _fail(self, room: RoomSim, frames: int) -> None:
        # The batch freed the slot (on_failure="remove"): this room stops (the server tells
        # its clients and closes it); resetting would hide a scene or engine fault behind a
        # game that silently restarts. The worker's other rooms step on.
        frame = room.stats.frames + frames
        room.error = (f"simulation state became non-finite by frame {frame} (backend "
                      f"{self.batch.backend}, {self.batch.precision}, "
                      f"{self.batch.substeps} substeps)")
        log.error("room simulation stopped: %s", room.error)
        room.slot = None
        if room in self.rooms:
            self.rooms.remove(room)
        self._publish(room, FrameResult(frame, self.pool.now(), [], sim_error=room.error))

    def want_mesh(self, room: RoomSim, box: tuple[Any, ...]) -> None:
        """A mesh of this room is due: read its nodes now (one copy) and let the encoder
        thread quantise and compress it (about a millisecond), off the frame."""
        assert room.slot is not None
        with self._mesh_lock:
            self._mesh_wanted[room] = (*box, self.batch.positions(room.slot))
        self._mesh_ready.set()

    def _encode_meshes(self) -> None:
        """The encoder thread: each room's newest mesh snapshot -> one MESH message."""
        name_os_thread()
        while not self._stop.is_set():
            if not self._mesh_ready.wait(0.1):
                continue
            self._mesh_ready.clear()
            with self._mesh_lock:
                boxes, self._mesh_wanted = self._mesh_wanted, {}
            for room, (frame, server_time, bp, hips, positions) in boxes.items():
                mesh = P.encode_mesh(frame, server_time, positions, bp, room.ball_radius, hips,
                                     compress=self.pool.compress_mesh)
                room.stats.meshes += 1
                self.post(room, "record_mesh", mesh)
                self._publish(room, FrameResult(-1, 0.0, [], mesh=mesh), flush=True)

    # --- hand-over to the event loop ------------------------------------------------------
    def _publish(self, room: RoomSim, result: FrameResult, flush: bool = False) -> None:
        with self._pending_lock:
            prev = self._pending.get(room)
            if prev is not None:
                if result.frame < 0:  # a mesh alone rides on the pending frame
                    prev.mesh = result.mesh
                    return
                result.merge_older(prev)
            self._pending[room] = result
        if flush:
            self._flush()

    def _flush(self) -> None:
        loop = self.pool.loop
        if loop is None:
            with self._pending_lock:
                self._pending.clear()
            return
        with self._pending_lock:
            if not self._pending or self._scheduled:
                return
            self._scheduled = True
        try:
            loop.call_soon_threadsafe(self._hand_over)
        except RuntimeError:  # the loop is closed: the server is stopping
            self._stop.set()

    def _hand_over(self) -> None:
        with self._pending_lock:
            results, self._pending = self._pending, {}
            self._scheduled = False
        for room, result in results.items():
            room.deliver(result)


class SimPool:
    """The server's sim workers: one per (scene, backend, precision), each stepping up to
    ``capacity`` rooms in one call per frame (another opens when one is full)."""

    def __init__(self, *, loop: asyncio.AbstractEventLoop | None = None,
                 clock: Callable[[], float] = time.perf_counter, epoch: float | None = None,
                 max_catchup: int = 50, cpu_threads: int | None = 1,
                 compress_mesh: bool = True, capacity: int = WORKER_CAPACITY,
                 spool_dir: Path | None = None) -> None:
        self.loop = loop
        self.clock = clock
        self.epoch = clock() if epoch is None else epoch  # server time zero
        self.max_catchup = max_catchup
        # One CPU thread per worker by default: on a small machine a second OpenMP thread
        # competes with the event loop for the cores, and its spinning barriers then cost
        # whole slices (`clothball host --workers` spreads rooms over processes instead).
        self.cpu_threads = cpu_threads
        self.compress_mesh = compress_mesh
        self.capacity = capacity
        # Where recordings spool while a round lasts (the data directory's, for a server).
        self.spool_dir = spool_dir or Path(tempfile.gettempdir()) / "clothball-spool"
        self._workers: dict[tuple[str, str, str], list[SimWorker]] = {}
        self._lock = threading.Lock()
        self._wakes: set[int] = set()  # eventfds every native frame loop writes each pass

    def now(self) -> float:
        return self.clock() - self.epoch

    def worker_for(self, scene: Scene, backend: str, room: RoomSim | None = None) -> Any:
        """A worker with room for one more room of ``scene`` (started if new): a native
        frame loop's (``server.frameloop``) unless ``CLOTHBALL_FRAME_LOOP=python``, the
        pool's clock is not the monotonic clock the loop keeps (a test's), or the scene's
        wind gusts (set per frame by Python); else a ``SimWorker``."""
        if self.loop is None:
            try:  # results are handed to the loop the rooms are made on
                self.loop = asyncio.get_running_loop()
            except RuntimeError:
                pass
        resolved, precision, _ = resolve_backend(scene, backend, None)
        native = room is not None and self.native_for(scene)
        key = (json.dumps(scene.to_dict(), sort_keys=True), resolved, precision,
               (room.mesh_every, room.track_every) if native and room is not None else None)
        with self._lock:
            workers = self._workers.setdefault(key, [])
            for w in workers:
                if not w.full:
                    break
            else:
                w = SimWorker(self, scene, resolved, self.capacity)
                if native:
                    w = NativeWorker(self, w, room)
                    for fd in self._wakes:
                        w.add_wake(fd)
                workers.append(w)
                w.start()
            w.members += 1
            return w

    def native_for(self, scene: Scene) -> bool:
        gusts = "wind" in scene.effects and scene["wind"]["gust_amplitude"] > 0.0
        return frame_loop_wanted() and self.clock is time.perf_counter and not gusts

    def set_wake(self, fd: int, on: bool) -> None:
        """An eventfd written by every native frame loop, now and to come, once a pass
        (``on``), or no more (a gateway's: ``server.shared.lanes``)."""
        with self._lock:
            (self._wakes.add if on else self._wakes.discard)(fd)
            for w in (w for ws in self._workers.values() for w in ws):
                if getattr(w, "native", False):
                    (w.add_wake if on else w.remove_wake)(fd)

    @property
    def workers(self) -> list[Any]:
        with self._lock:
            return [w for ws in self._workers.values() for w in ws]

    def close(self) -> None:
        for w in self.workers:
            w.stop()
        with self._lock:
            self._workers.clear()
