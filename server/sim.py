"""A room's simulation thread: simulated time locked to wall time, in 1 ms frames.

The thread owns the ``Cloth`` (which is not thread-safe) and keeps its pace whatever the
event loop or the network does: it sleeps until the next frame is due, applies the latest
hand positions (latest wins), steps every frame that is due (catching up at most
``max_catchup`` frames after a hiccup; older time is dropped and counted), reads back the
four corners and the ball, checks whether the ball has left the cloth, and hands the result
to the event loop *coalesced*: at most one delivery is pending at a time and it carries the
newest frame, so a busy loop never builds a queue. Every ``1/mesh_hz`` s it quantises the
mesh into a MESH message (once for all spectators), and while a round is recorded it keeps
the MESH messages and a TRACK message every ``1/track_hz`` s.

The event loop talks to the thread only through ``set_hip`` (an atomic slot per seat) and
``command`` (a queue the thread drains between frames).
"""

from __future__ import annotations

import asyncio
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..game.rules import exit_edge_fast
from ..game.sim.cloth import Cloth, SimulationError, corners_of, rest_positions
from ..game.sim.scene import Scene
from ..game.wire import protocol as P

log = logging.getLogger("clothball.server")

# s: a sleep ends up to this late (Linux's default timer slack), so a frame may start this
# much before its time instead.
TIMER_SLACK = 50e-6


@dataclass
class FrameResult:
    """The state after the newest frame, as the event loop receives it."""

    frame: int
    server_time: float
    corners: list[bytes]  # one CORNER message per seat
    mesh: bytes | None = None  # newest MESH message, when one was made since the last delivery
    exit: tuple[int, int, list[float]] | None = None  # (edge, frame, ball position)
    sim_error: str | None = None


@dataclass
class SimStats:
    frames: int = 0
    steps: int = 0  # step calls (one frame each, more when catching up)
    skipped_frames: int = 0  # frames dropped because the loop fell further behind than allowed
    lateness: list[float] = field(default_factory=list)  # s, newest samples (bounded)
    meshes: int = 0


class RoomSim:
    """The simulation of one room, run on its own thread (see the module doc)."""

    LATENESS_SAMPLES = 200_000

    def __init__(self, scene: Scene, backend: str = "auto", *,
                 deliver: Callable[[FrameResult], None] | None = None,
                 loop: asyncio.AbstractEventLoop | None = None,
                 mesh_hz: float = 30.0, track_hz: float = 100.0, max_catchup: int = 50,
                 compress_mesh: bool = True, clock: Callable[[], float] = time.perf_counter,
                 epoch: float | None = None, cpu_threads: int | None = 1) -> None:
        self.scene = scene
        self.cpu_threads = cpu_threads
        # One CPU thread by default: on a small machine a second OpenMP thread competes with
        # the event loop for the cores, and its spinning barriers then cost whole slices.
        self.cloth = Cloth(scene, backend=backend, threads=cpu_threads)
        self.frame_dt = self.cloth.frame_dt
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
        self.max_catchup = max_catchup
        self.compress_mesh = compress_mesh
        self.clock = clock
        self.epoch = clock() if epoch is None else epoch  # server time zero
        self._deliver = deliver
        self._loop = loop
        self._hip_slots: list[tuple[Any, int, float] | None] = [None] * 4
        self._commands: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self._stop = threading.Event()
        # Cleared while nobody is there to see the room: the thread does not step (a room
        # with no one in it costs no CPU), and on waking the slept time is not caught up.
        self._awake = threading.Event()
        self._awake.set()
        self._thread: threading.Thread | None = None
        self._encoder: threading.Thread | None = None
        self._mesh_box: tuple[int, float, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._mesh_ready = threading.Event()
        self._pending_lock = threading.Lock()
        self._pending: FrameResult | None = None
        self._armed = False
        self._recordings: dict[str, list[tuple[int, bytes]]] = {}
        self.stats = SimStats()
        self._applied: list[tuple[int, float]] = [(0, math.nan)] * 4

    # --- event-loop side ------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="clothball-room-sim", daemon=True)
        self._thread.start()
        self._encoder = threading.Thread(target=self._encode_meshes, name="clothball-room-mesh",
                                         daemon=True)
        self._encoder.start()

    def stop(self) -> None:
        self._stop.set()
        self._mesh_ready.set()
        for t in (self._thread, self._encoder):
            if t is not None and t is not threading.current_thread():
                t.join(timeout=5.0)

    def set_awake(self, awake: bool) -> None:
        """Step the room (True) or let it sleep (False): no stepping, no CPU, until woken;
        it then starts afresh from the state it slept in, at once."""
        if awake:
            self._awake.set()
        else:
            self._awake.clear()

    @property
    def asleep(self) -> bool:
        return not self._awake.is_set()

    def now(self) -> float:
        """Server time: seconds since the server started."""
        return self.clock() - self.epoch

    def set_hip(self, seat: int, position: Any, seq: int = 0,
                client_time: float = math.nan) -> None:
        """The latest hand position for a seat, three floats (an array or a tuple; None:
        the corner rests at its anchor)."""
        self._hip_slots[seat] = None if position is None else (position, seq, client_time)

    def command(self, name: str, arg: Any = None) -> None:
        """Queue a command for the thread: ``reset_ball`` ((pos, vel)), ``arm``, ``disarm``,
        ``record_start`` (an id), ``record_event`` (bytes, to every recording in progress),
        ``record_stop`` ((id, callback): the callback gets that recording's records, on the
        thread). Recordings may overlap (a round's tail and the next round's start)."""
        self._commands.put((name, arg))

    # --- thread side ----------------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._loop_body()
        except Exception as e:  # pragma: no cover - a bug: the room stops, like a NaN
            log.exception("room simulation thread failed")
            self._publish(FrameResult(-1, self.now(), [], sim_error=f"internal error: {e}"))

    def _loop_body(self) -> None:
        cloth, dt = self.cloth, self.frame_dt
        t0 = self.clock()
        done = 0  # frames simulated since t0
        next_mesh = 0
        next_track = 0
        stats = self.stats
        while not self._stop.is_set():
            if not self._awake.is_set():
                self._drain_commands()  # a recording's end still answers while asleep
                if self._awake.wait(0.05):
                    # Woken: pace from now, a mesh at once; the slept time is not replayed.
                    t0, done, next_mesh, next_track = self.clock(), 0, 0, 0
                continue
            now = self.clock()
            behind = int((now - t0 + TIMER_SLACK) / dt) - done
            if behind <= 0:
                # Sleep the whole wait: spinning through the end of it would hold the GIL
                # while the event loop has HIPs to read and corners to send.
                time.sleep(t0 + (done + 1) * dt - TIMER_SLACK - now)
                continue
            if behind > self.max_catchup:
                skip = behind - self.max_catchup
                t0 += skip * dt
                stats.skipped_frames += skip
                behind = self.max_catchup
            # Behind, step a quarter of the frames due (at least one) per pass: each pass takes
            # the newest hand positions and publishes its corners, so a HIP waits for a part
            # of the backlog, not all of it, and a room far behind still catches up quickly.
            frames = min(behind, 1 + behind // 4)
            self._drain_commands()
            hips = self.anchors.copy()
            for s, slot in enumerate(self._hip_slots):
                if slot is not None:
                    hips[s] = slot[0]
                    self._applied[s] = (slot[1], slot[2])
            cloth.set_hips(hips)
            try:
                cloth.step(frames)
            except SimulationError as e:
                # The room stops (the server tells its clients and closes it); resetting
                # would hide a scene or engine fault behind a game that silently restarts.
                log.error("room simulation stopped: %s", e)
                self._stop.set()
                self._mesh_ready.set()
                self._publish(FrameResult(cloth.frame, self.now(), [], sim_error=str(e)))
                return
            done += frames
            frame = cloth.frame
            stats.frames += frames
            stats.steps += 1
            pos, vel = cloth.corners()
            force = cloth.corner_forces()
            if self.has_ball:
                bp, bv = cloth.ball()
            else:
                bp, bv = np.zeros(3), np.zeros(3)
            t_end = self.clock()
            server_time = t_end - self.epoch
            lat = stats.lateness
            lat.append(t_end - (t0 + done * dt))
            if len(lat) > self.LATENESS_SAMPLES:
                del lat[: len(lat) // 2]
            pl, bpl = pos.tolist(), bp.tolist()
            corners = P.encode_corners(frame, server_time, pl, vel.tolist(), force.tolist(),
                                       self.stiffness, bpl, bv.tolist(), self._applied)
            result = FrameResult(frame, server_time, corners)
            if self.has_ball:
                if self._armed:
                    # Plain floats and a cheap exact pre-test: the full test (NumPy, ~30 us)
                    # runs only when the ball is near an edge or the floor.
                    edge = exit_edge_fast(bpl, pl, self.floor_y)
                    if edge is not None:
                        self._armed = False
                        result.exit = (edge, frame, bpl)
                elif bp[1] < self.floor_y - 50.0 * self.size:
                    # Nobody is playing and the ball fell off: put it back, keep it bounded.
                    sp = self.scene["ball"]["position"]
                    cloth.set_ball(sp, (0.0, 0.0, 0.0))
            self._publish(result)
            # The mesh and the track after the per-frame work. Quantising and compressing
            # the mesh takes about a millisecond: the encoder thread does it, off the frame.
            if done >= next_mesh:
                next_mesh = done + self.mesh_every
                self._mesh_box = (frame, server_time, cloth.positions(), bp, hips.copy())
                self._mesh_ready.set()
            if self._recordings and done >= next_track:
                next_track = done + self.track_every
                track = P.encode_track(frame, server_time, bp, bv, hips, pos)
                for rec in self._recordings.values():
                    rec.append((1, track))

    def _encode_meshes(self) -> None:
        """The encoder thread: the newest mesh snapshot -> one MESH message."""
        while not self._stop.is_set():
            if not self._mesh_ready.wait(0.1):
                continue
            self._mesh_ready.clear()
            box, self._mesh_box = self._mesh_box, None
            if box is None:
                continue
            frame, server_time, positions, bp, hips = box
            mesh = P.encode_mesh(frame, server_time, positions, bp, self.ball_radius, hips,
                                 compress=self.compress_mesh)
            self.stats.meshes += 1
            self._commands.put(("record_mesh", mesh))
            self._publish_mesh(mesh)

    def _drain_commands(self) -> None:
        while True:
            try:
                name, arg = self._commands.get_nowait()
            except queue.Empty:
                return
            if name == "reset_ball" and self.has_ball:
                self.cloth.set_ball(arg[0], arg[1])
            elif name == "arm":
                self._armed = True
            elif name == "disarm":
                self._armed = False
            elif name == "record_start":
                self._recordings[arg] = []
            elif name == "record_mesh":
                for rec in self._recordings.values():
                    rec.append((1, arg))
            elif name == "record_event":
                for rec in self._recordings.values():
                    rec.append((0, arg))
            elif name == "record_stop":
                rid, callback = arg
                callback(self._recordings.pop(rid, []))

    def _publish(self, result: FrameResult) -> None:
        with self._pending_lock:
            prev = self._pending
            self._pending = result
            if prev is not None:
                # Coalesce: keep the newest frame, but never lose a mesh, an exit or an error.
                if result.mesh is None:
                    result.mesh = prev.mesh
                if result.exit is None:
                    result.exit = prev.exit
                if result.sim_error is None:
                    result.sim_error = prev.sim_error
                return
        self._schedule()

    def _publish_mesh(self, mesh: bytes) -> None:
        with self._pending_lock:
            if self._pending is not None:
                self._pending.mesh = mesh
                return
            self._pending = FrameResult(-1, 0.0, [], mesh=mesh)
        self._schedule()

    def _schedule(self) -> None:
        if self._loop is None or self._deliver is None:
            return
        try:
            self._loop.call_soon_threadsafe(self._hand_over)
        except RuntimeError:  # the loop is closed: the server is stopping
            self._stop.set()

    def _hand_over(self) -> None:
        with self._pending_lock:
            result, self._pending = self._pending, None
        if result is not None and self._deliver is not None:
            self._deliver(result)
