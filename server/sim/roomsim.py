"""One room's simulation (``RoomSim``): a slot of its scene's frame loop (``worker``).

The event loop talks to a room only through its ``RoomSim``: ``set_hip`` (the seat's hand
into the loop's block), ``set_awake``, ``command`` (the ball, arming the exit check, and the
recordings, which the worker's service thread keeps) and two callbacks: ``deliver`` (a
``FrameResult``: the newest frame's CORNER messages, an exit, a failure) and
``deliver_mesh`` (its newest MESH message). A room nobody is in sleeps
(``set_awake(False)``): its slot keeps its state and is not stepped.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import threading
from collections.abc import Callable
from typing import Any

from ...game.sim.scene import Scene
from ..storage.recorder import Recording
from .pool import SimPool
from .results import FrameResult
from .worker import FrameWorker, RoomStats

_OCCUPANTS = itertools.count(1)  # RoomSim.occupant's numbers

# (position, seq, client time) of a seat's newest HIP
Hand = tuple[Any, int, float]


class RoomSim:
    """One room's simulation (see the module doc).

    Made with a ``pool`` (the server's); without one it runs on a private pool of its own
    (a lone room, as in tests and tools), which ``stop`` closes.
    """

    def __init__(self, scene: Scene, backend: str = "auto", *,
                 deliver: Callable[[FrameResult], None] | None = None,
                 deliver_mesh: Callable[[bytes], None] | None = None,
                 loop: asyncio.AbstractEventLoop | None = None,
                 mesh_hz: float = 30.0, track_hz: float = 100.0,
                 pool: SimPool | None = None) -> None:
        self._own_pool = pool is None
        self.pool = SimPool(loop=loop) if pool is None else pool
        self.scene = scene
        self.frame_dt = float(scene["sim"]["frame_dt"])
        self.mesh_every = max(1, round(1.0 / (mesh_hz * self.frame_dt)))
        self.track_every = max(1, round(1.0 / (track_hz * self.frame_dt)))
        self._on_frame = deliver
        self._on_mesh = deliver_mesh
        self.wants_meshes = deliver_mesh is not None
        self._hands: list[Hand | None] = [None] * 4
        # Per seat, its occupant: a number new each time its hand is cleared (an occupant
        # left), unique in the process, so that a CORNER made from an earlier occupant's
        # HIP is not given to the next one (docs/protocol.md: `seq` is the last HIP the
        # server applied for this seat), and a HIP a gateway writes late for an occupant
        # that left, or for a room that left its slot, is ignored (native/loop/block.hpp).
        self.occupant = [next(_OCCUPANTS) for _ in range(4)]
        self.awake = True
        self._stopped = threading.Event()
        # s between this room's CORNER deliveries (0: every frame; inf: none wanted)
        self.corner_interval = 0.0
        self.delivered = -1  # the newest frame delivered
        self.slot: int | None = None
        self.error: str | None = None
        self.worker: FrameWorker = self.pool.worker_for(scene, backend, self.mesh_every,
                                                        self.track_every)
        self.arena = self.worker.arena  # anchors, floor, ball, coupling: the scene's
        self.backend = self.worker.batch.backend
        self.stats = RoomStats(self.worker, self)
        # The service thread's: the rounds being recorded (they may overlap: a round's tail
        # and the next round's start), each spooled to disk as it goes.
        self._recordings: dict[str, Recording] = {}

    # --- event-loop side ------------------------------------------------------------------
    def start(self) -> None:
        slot = self.worker.add(self, self.awake)
        for seat, hand in enumerate(self._hands):  # and each seat's occupant
            self._send_hand(slot, seat, hand)

    def stop(self) -> None:
        """Take the room off its worker (its recordings are discarded)."""
        if not self._stopped.is_set():
            self.stats.keep()
            self.worker.remove(self)
            self.worker.post(self, "drop", None)  # recordings, on the service thread
            self._stopped.set()
            self.worker.members -= 1
        if self._own_pool:
            self.pool.close()

    def set_awake(self, awake: bool) -> None:
        """Step the room (True) or let it sleep (False): no stepping, no CPU, until woken;
        it then starts afresh from the state it slept in, at once."""
        self.awake = bool(awake)
        if self.slot is not None:
            self.worker.set_awake(self.slot, self.awake)

    @property
    def asleep(self) -> bool:
        return not self.awake

    @property
    def alive(self) -> bool:
        """The room is on a running worker and has not failed."""
        return self.worker.running and self.error is None and not self._stopped.is_set()

    @property
    def substeps(self) -> int:
        return self.worker.substeps

    @property
    def frame(self) -> int:
        """Frames simulated since the room started."""
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
            self.occupant[seat] = next(_OCCUPANTS)
            self._hands[seat] = None
        else:
            self._hands[seat] = (position, seq, client_time)
        if self.slot is not None:
            self._send_hand(self.slot, seat, self._hands[seat])

    def _send_hand(self, slot: int, seat: int, hand: Hand | None) -> None:
        if hand is None:
            self.worker.clear_hip(slot, seat, self.occupant[seat])
        else:
            self.worker.set_hip(slot, seat, hand[0], hand[1], hand[2], self.occupant[seat])

    def lane_place(self, seat: int | None) -> dict[str, Any] | None:
        """Where a lane serves a client of this room (``server.lanes``): the block and slot,
        the seat's occupant (0 for none), the mesh board and its slot size, and whether a
        gateway can map both ("shared"); None while the room has no slot."""
        if self.slot is None:
            return None
        w = self.worker
        return {"block": w.block_id, "slot": self.slot,
                "occupant": 0 if seat is None else self.occupant[seat],
                "board": w.board_id, "board_slot": w.board_slot,
                "shared": w.block_share[1] >= 0 and w.board_share is not None}

    def hip_echo(self, seat: int) -> tuple[int, float]:
        """The (seq, client time) of the seat's HIP the newest frame applied (0, NaN: none
        since its occupant took it), as its CORNER echoes them."""
        if self.slot is None:
            return (0, math.nan)
        return self.worker.applied(self.slot, seat)

    def command(self, name: str, arg: Any = None) -> None:
        """``reset_ball`` ((pos, vel)), ``arm``, ``disarm`` (the exit check), and for the
        worker's service thread ``record_start`` ((id, cap in s)), ``record_event`` ((id,
        bytes): to that recording), ``record_stop`` ((id, callback): the callback gets that
        ``Recording``, or None, on the service thread). Recordings may overlap (a round's
        tail and the next round's start); each spools to disk as it goes."""
        if name == "reset_ball":
            if self.arena.has_ball and self.slot is not None:
                self.worker.set_ball(self.slot, arg[0], arg[1])
        elif name in ("arm", "disarm"):
            if self.slot is not None:
                self.worker.set_armed(self.slot, name == "arm")
        else:
            self.worker.post(self, name, arg)

    # --- the worker's service thread ------------------------------------------------------
    def apply(self, name: str, arg: Any) -> None:
        if name == "record_start":
            rid, cap_s = arg
            self._recordings[rid] = Recording(rid, self.pool.spool_dir, cap_s, self.frame_dt)
        elif name == "record_event":
            rid, data = arg
            if (rec := self._recordings.get(rid)) is not None:
                rec.append(0, data)
        elif name == "record_stop":
            rid, callback = arg
            callback(self._recordings.pop(rid, None))
        elif name == "drop":
            self.drop_recordings()

    def record(self, message: bytes) -> None:
        """A MESH or TRACK message into every recording in progress."""
        for rec in self._recordings.values():
            rec.append(1, message)

    def recording(self) -> bool:
        return bool(self._recordings)

    def drop_recordings(self) -> None:
        """The room is gone: recordings in progress are discarded."""
        for rec in self._recordings.values():
            rec.discard()
        self._recordings.clear()

    # --- the event loop's deliveries ------------------------------------------------------
    def deliver(self, result: FrameResult) -> None:
        if self._on_frame is not None and not self._stopped.is_set():
            for s, occupant in enumerate(result.occupants):
                if occupant != self.occupant[s]:  # made before the seat changed hands
                    result.corners[s] = None
            self._on_frame(result)

    def deliver_mesh(self, mesh: bytes) -> None:
        if self._on_mesh is not None and not self._stopped.is_set():
            self._on_mesh(mesh)
