"""One client's lane (``Lane``), and where a process's lanes find the frame loops' blocks
and mesh boards (``Links``): the one code that serves every seated player's HIPs and
CORNERs and every client's MESH, in the engine (``server.lanes.local``) and in a gateway
(``server.gateway.lanes``) alike.

A ``Lane`` writes a seated player's well-formed HIPs (the binary rate of ``server.limits``,
the seat's reach box, the seat's occupant) into the seat's hand in the frame loop's block;
anything it does not take its process answers as before (the engine's own checks and
errors). It sends the seat's CORNER from the block at the client's ``corner_rate``, on its
own timer, or, above ``TIMER_MAX_HZ``, on the frame wake-up that the frame loops write after
each pass; and, when the client wants MESH, each newer MESH of its room from the mesh board
(``Links`` looks at every watched room's board on one timer).
"""

from __future__ import annotations

import asyncio
import math
import os
from collections.abc import Callable
from typing import Any

from ... import _native
from ...game.wire import protocol as P
from ...game.wire.wsframe import binary_frame_header
from ..shared import lanes
from ..shared.bucket import TokenBucket

FRAME_S = 0.001  # the frame loop's frame: a lane's fastest CORNER interval
RETRY_FRAME_S = 0.00025  # a CORNER due before its frame is looked for again this soon,
RETRIES = 4  # this many times (a frame's time)
CORNER_HEAD = binary_frame_header(P.CORNER_SIZE)  # a server's frame of one CORNER
MESH_LOOK_S = 0.004  # the watched rooms' boards are looked at this often (MESH: 30 Hz)


def on_grid(t: float) -> float:
    """``t`` rounded up to a whole frame of the event loop's clock. The lanes' CORNER timers
    fire on this grid, so those due within one frame go out in one wake-up of the event
    loop (and reach a client process together), not one wake-up each: 40 lanes at 120 Hz
    woke the engine's loop 4 800 times a second, beside the frame loop on two cores. The
    rate holds: the next is due an interval after this one was due, not after the grid."""
    return math.ceil(t / FRAME_S) * FRAME_S


class Links:
    """A process's side of its lanes (see the module doc). Subclasses say where blocks come
    from (``block``) and how the frame wake-up is armed (``_set_armed``)."""

    def __init__(self) -> None:
        # Messages the lanes handled: HIPs written into the block, CORNERs and MESHes sent.
        self.counts = {"messages_in": 0, "messages_out": 0}
        # The rooms whose MESH this process's lanes send, by (board, offset): their lanes,
        # and the frame of the newest sent; looked at every MESH_LOOK_S while there are any.
        self.watched: dict[tuple[int | None, int], tuple[set[Lane], list[int]]] = {}
        self._mesh_timer: asyncio.TimerHandle | None = None
        # The frame wake-up (an eventfd the frame loops write after each pass, while armed)
        # and the lanes sending a CORNER on it: those above TIMER_MAX_HZ.
        self.framed: set[Lane] = set()
        self.wake = -1
        self.no_wake = False  # there is none to have: those lanes use timers
        self._armed = False
        self._arming: asyncio.Task[None] | None = None

    def block(self, block_id: int) -> Any | None:
        """The block (a ``_native.BlockView``) or mesh board (a writable buffer) with this
        id, else None (a later call may have it)."""
        raise NotImplementedError

    async def _set_armed(self, on: bool) -> bool:
        """Have the frame loops write the wake-up after each pass (or no more); False: it
        could not be done (the wake-up is gone)."""
        raise NotImplementedError

    def watch(self, lane: Lane) -> None:
        self.watched.setdefault(lane.mesh_key, (set(), [-1]))[0].add(lane)
        if self._mesh_timer is None:
            self._mesh_timer = asyncio.get_running_loop().call_soon(self._meshes)

    def unwatch(self, lane: Lane) -> None:
        entry = self.watched.get(lane.mesh_key)
        if entry is not None:
            entry[0].discard(lane)
            if not entry[0]:
                del self.watched[lane.mesh_key]

    def on_frames(self, lane: Lane, on: bool) -> bool:
        """``lane`` sends its CORNERs on the frame wake-up from now on (or no more); False:
        there is none to have (it keeps its timer)."""
        if on and self.no_wake:
            return False
        (self.framed.add if on else self.framed.discard)(lane)
        self._rearm()
        return True

    def _rearm(self) -> None:
        if bool(self.framed) != self._armed and self.wake >= 0 and \
                (self._arming is None or self._arming.done()):
            self._arming = asyncio.get_running_loop().create_task(self._arm())

    async def _arm(self) -> None:
        while self.wake >= 0 and bool(self.framed) != self._armed:
            want = bool(self.framed)
            if not await self._set_armed(want):
                return
            self._armed = want

    def _listen_wake(self, fd: int) -> None:
        """``fd`` is the frame wake-up from now on (the event loop waits on it)."""
        self.wake = fd
        asyncio.get_running_loop().add_reader(fd, self._frame)
        self._rearm()

    def _forget_wake(self) -> None:
        if self.wake >= 0:
            asyncio.get_running_loop().remove_reader(self.wake)
            os.close(self.wake)
            self.wake, self._armed = -1, False

    def _frame(self) -> None:
        """A frame loop's pass has ended: the framed lanes' CORNERs that are due."""
        try:
            os.eventfd_read(self.wake)
        except OSError:  # (BlockingIOError: another reader's, or none yet)
            return
        now = asyncio.get_running_loop().time()
        for lane in list(self.framed):
            lane.on_frame(now)

    def _meshes(self) -> None:
        """Each watched room's newest MESH (from its board, written once by the engine's
        frame loop) to its lanes' clients, when newer than the last sent."""
        self._mesh_timer = None
        if not self.watched:
            return
        for (board_id, offset), (watchers, sent) in list(self.watched.items()):
            board = None if board_id is None else self.block(board_id)
            if board is None:
                continue
            slot_bytes = next(iter(watchers)).spec.board_slot
            frame, data = _native.board_read(board, offset, slot_bytes, sent[0])
            if frame < sent[0]:
                sent[0] = -1  # the slot was cleared for another room: from its first on
            if data is None:
                continue
            sent[0] = frame
            head = binary_frame_header(len(data))
            for lane in watchers:
                lane.send_mesh(head, data)
        self._mesh_timer = asyncio.get_running_loop().call_later(MESH_LOOK_S, self._meshes)


class Lane:
    """One client's open lane (see the module doc): ``write(kind, head, payload)`` sends a
    message ("corner" or "mesh", its websocket frame header and payload) to the client at a
    message boundary of its connection; ``room`` says which room the client is in now
    (its lane serves it only while that is the lane's room)."""

    def __init__(self, spec: lanes.LaneSpec, links: Links,
                 write: Callable[[str, bytes, bytes], None],
                 room: Callable[[], str | None]) -> None:
        self.spec, self.links = spec, links
        self.write, self.room = write, room
        self.view = links.block(spec.block)  # None until the block is had (then looked up)
        self.bucket = TokenBucket(spec.binary_rate, spec.binary_burst)
        self.fast = True  # HIPs taken here (off for good once the client passes its rate)
        self.sent_frame = -1
        self._retries = 0
        self._loop = asyncio.get_running_loop()
        self._due = self._loop.time()
        self._timer: asyncio.TimerHandle | None = None
        if spec.seat is not None:  # a seated player: its CORNERs are the lane's to send
            framed = spec.corner_interval < 1.0 / lanes.TIMER_MAX_HZ - 1e-4 and \
                links.on_frames(self, True)
            if not framed:
                self._timer = self._loop.call_soon(self._corner)
        if spec.board is not None:
            links.watch(self)

    @property
    def mesh_key(self) -> tuple[int | None, int]:
        """Where its room's MESH is: the board, and the room's slot's offset in it."""
        return self.spec.board, self.spec.slot * self.spec.board_slot

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self in self.links.framed:
            self.links.on_frames(self, False)
        if self.spec.board is not None:
            self.links.unwatch(self)

    def send_mesh(self, head: bytes, data: bytes) -> None:
        if self.room() == self.spec.room:
            self.write("mesh", head, data)

    def _view(self) -> Any | None:
        if self.view is None:
            self.view = self.links.block(self.spec.block)
        return self.view

    def take(self, payload: bytes) -> bool:
        """A HIP from the client: written into the seat's hand, else False (its process
        answers it: a HIP that is not well formed, out of reach, past the rate, or of an
        occupant that has left the seat, or from a client that is not seated)."""
        sp = self.spec
        if sp.seat is None or not self.fast or self._view() is None:
            return False
        if not self.bucket.take():
            self.fast = False  # the process's own limit and errors from here on
            return False
        try:
            hip = P.decode_hip(payload)
        except P.ProtocolError:
            return False
        if not lanes.in_reach(sp.lo, sp.hi, hip.position):
            return False
        x, y, z = hip.position
        if not self.view.write_hip(sp.slot, sp.seat, sp.occupant, x, y, z,
                                   hip.seq & 0xFFFFFFFFFFFFFFFF, hip.time):
            return False
        self.links.counts["messages_in"] += 1
        return True

    def use_timer(self) -> None:
        """Its CORNERs on its own timer (taken off the frame wake-up: there is none)."""
        self._timer = self._loop.call_soon(self._corner)

    def _send_newest(self) -> bool | None:
        """The seat's newest CORNER to the client if a newer frame than the last sent is
        there (True); False: none newer; None: the lane has ended (its slot holds another
        room now)."""
        sp = self.spec
        assert sp.seat is not None
        if self.room() != sp.room or self._view() is None:
            return False
        frame, msg, occupant = self.view.read_corner(sp.slot, sp.seat)
        if frame < self.sent_frame:
            return None
        if frame == self.sent_frame:
            return False
        self.sent_frame = frame
        if occupant != sp.occupant:  # made from a former occupant's hand: it echoes its HIP
            return False
        self.write("corner", CORNER_HEAD, msg)
        return True

    def on_frame(self, now: float) -> None:
        """A pass has ended (the frame wake-up): its CORNER, when due (within half a
        frame: passes come a frame apart, give or take)."""
        if now < self._due - FRAME_S / 2:
            return
        sent = self._send_newest()
        if sent is None:  # as its timer would stop
            self.links.on_frames(self, False)
        elif sent:
            due = self._due + max(self.spec.corner_interval, FRAME_S)
            self._due = due if due > now else now + FRAME_S / 2

    def _corner(self) -> None:
        """The seat's newest CORNER to the client, when a newer frame than the last sent
        is there; then the next one, an interval after this one was due (not after it was
        sent: timed from each send, a rate that is no whole number of 1 ms frames lost up
        to a frame a message, corner_rate 120 gave 111 a second)."""
        now = self._loop.time()
        sent = self._send_newest()
        if sent is None:
            self._timer = None
            return
        if sent:
            self._retries = 0
        elif self.room() == self.spec.room and self.view is not None:
            if self._retries < RETRIES:
                # Due just before the loop published the next frame (this timer and the
                # frames are not in step): look again a little later, not an interval later
                # (at corner_rate 1000 that lost one CORNER in eight).
                self._retries += 1
                self._timer = self._loop.call_at(now + RETRY_FRAME_S, self._corner)
                return
            self._retries = 0  # no new frame (the room sleeps): on at the rate
        interval = max(self.spec.corner_interval, FRAME_S)
        due = self._due + interval
        self._due = due if due > now else now + interval
        self._timer = self._loop.call_at(on_grid(self._due), self._corner)
