"""A gateway's side of seated players' lanes (``server.shared.lanes``): it writes a seated
player's HIPs into the seat's hand in the engine's frame loop block and sends the player
its CORNER from the block at the client's ``corner_rate``, so that the engine's event loop
sees neither (the messages of a room: 4 players' HIPs at 120 Hz in, their CORNERs at 120 Hz
out, against 30 Hz MESH to each spectator and a few control messages).

* ``ClientFrames`` follows a client's websocket frames (masked, RFC 6455) and takes out the
  HIPs its lane takes; every other byte goes on to the engine unchanged.
* ``Lanes`` is the gateway's link to the engine's control socket: the blocks (memfds passed
  over it, mapped here) and the counts reported to the engine for the host's figures.
* ``Lane`` state of one client: its HIPs (the binary rate of ``server.limits``, the reach
  box, the occupant: anything the gateway does not take, it passes to the engine, which
  answers as documented) and its CORNER timer, or, above ``TIMER_MAX_HZ``, the frame
  wake-up that the engine's frame loops write after each pass (``server.shared.lanes``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ... import _native  # type: ignore[attr-defined]
from ...game.wire import protocol as P
from ...game.wire.wsframe import FIN, OP_BINARY, binary_frame_header, header_at
from ..shared import lanes
from ..shared.bucket import TokenBucket

log = logging.getLogger("clothball.gateway")

LANES_ENV = "CLOTHBALL_GATEWAY_LANES"  # "0": the gateway relays every message (A/B runs)
FRAME_S = 0.001  # the frame loop's frame: a lane's fastest CORNER interval
WRITE_SKIP = 1 << 16  # a client with this much unsent: its CORNER is skipped (a newer comes)
REPORT_S = 1.0  # counts reported to the engine this often
RETRY_S = 0.5  # between two requests for the blocks
RETRY_FRAME_S = 0.00025  # a CORNER due before its frame is looked for again this soon,
RETRIES = 4  # this many times (a frame's time)
MESH_LOOK_S = 0.004  # the watched rooms' boards are looked at this often (MESH: 30 Hz)
CORNER_HEAD = binary_frame_header(P.CORNER_SIZE)  # a server's frame of one CORNER


def lanes_wanted() -> bool:
    return os.environ.get(LANES_ENV, "1").strip() != "0"


class ClientFrames:
    """Follows one client-to-server stream from the first frame after the handshake:
    ``feed`` returns what goes on to the engine; a whole, unfragmented binary frame of a
    HIP's size is offered to ``take`` (its unmasked payload) first, and dropped if taken."""

    def __init__(self, take: Callable[[bytes], bool]) -> None:
        self.take = take
        self._partial = b""  # a frame header, or a HIP-sized frame, not yet whole
        self._skip = 0  # payload bytes of a passing frame still to come
        self._fragmented = False

    def feed(self, data: bytes) -> bytes:
        out = bytearray()
        buf, i = self._partial + data if self._partial else data, 0
        end = len(buf)
        while i < end:
            if self._skip:
                take = min(self._skip, end - i)
                out += buf[i:i + take]
                self._skip -= take
                i += take
                continue
            head = header_at(buf, i)
            if head is None:
                break
            b0, masked, n, hl = head
            op = b0 & 0x0F
            if b0 == FIN | OP_BINARY and masked and n == P.HIP_SIZE and not self._fragmented:
                if end - i < hl + n:
                    break  # held until whole
                mask = int.from_bytes(buf[i + hl - 4:i + hl] * 7, "little")
                payload = (int.from_bytes(buf[i + hl:i + hl + n], "little") ^ mask).to_bytes(
                    n, "little")
                if not self.take(payload):
                    out += buf[i:i + hl + n]
                i += hl + n
                continue
            if op < 0x8:  # a data frame: FIN ends its message
                self._fragmented = not b0 & 0x80
            out += buf[i:i + hl]
            i += hl
            self._skip = n
        self._partial = bytes(buf[i:])
        return bytes(out)


class Lanes:
    """The gateway's link to the engine's control socket at ``path``."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.blocks: dict[int, Any] = {}  # id -> _native.BlockView, or a mesh board's mmap
        self.counts = {"messages_in": 0, "messages_out": 0}
        # The rooms whose MESH this gateway sends, by (board, offset): their lanes, and the
        # frame of the newest sent; looked at every MESH_LOOK_S while there are any.
        self.watched: dict[tuple[int, int], tuple[set[Lane], list[int]]] = {}
        self._mesh_timer: asyncio.TimerHandle | None = None
        self._sock: socket.socket | None = None
        self._lock = asyncio.Lock()
        self._fetching: asyncio.Task[None] | None = None
        self._fetched_at = -math.inf
        self._reported: dict[str, int] = {}
        self._task: asyncio.Task[None] | None = None
        # The frame wake-up (an eventfd the engine's frame loops write after each pass,
        # while armed) and the lanes sending a CORNER on it: those above TIMER_MAX_HZ.
        self.framed: set[Lane] = set()
        self._wake = -1
        self._no_wake = False  # the engine gave none: those lanes use timers
        self._armed = False
        self._arming: asyncio.Task[None] | None = None

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._report_forever())

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        self._drop()

    def block(self, block_id: int) -> Any | None:
        """The block ``block_id``, else None, and it is asked for (not more than once per
        ``RETRY_S``): a later call has it. Block ids are random, so a restarted engine's
        blocks are never taken for its predecessor's."""
        view = self.blocks.get(block_id)
        loop = asyncio.get_running_loop()
        if view is None and (self._fetching is None or self._fetching.done()) \
                and loop.time() - self._fetched_at > RETRY_S:
            self._fetched_at = loop.time()
            self._fetching = loop.create_task(self._fetch())
        return view

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
        if on and self._no_wake:
            return False
        (self.framed.add if on else self.framed.discard)(lane)
        if bool(self.framed) != self._armed and self._wake >= 0 and \
                (self._arming is None or self._arming.done()):
            self._arming = asyncio.get_running_loop().create_task(self._arm())
        return True

    async def _arm(self) -> None:
        """The engine's frame loops write the wake-up while a lane here needs it."""
        async with self._lock:
            while self._wake >= 0 and bool(self.framed) != self._armed:
                want = bool(self.framed)
                line = lanes.ARM if want else lanes.DISARM
                try:
                    await asyncio.to_thread(lambda: self._connect().sendall(line))  # noqa: B023
                except OSError:
                    self._drop()
                    return
                self._armed = want

    def _frame(self) -> None:
        """A frame loop's pass has ended: the framed lanes' CORNERs that are due."""
        try:
            os.eventfd_read(self._wake)
        except OSError:  # (BlockingIOError: another reader's, or none yet)
            return
        now = asyncio.get_running_loop().time()
        for lane in list(self.framed):
            lane.on_frame(now)

    def _meshes(self) -> None:
        """Each watched room's newest MESH (from its board, written once by the engine)
        to its lanes' clients, when newer than the last sent."""
        self._mesh_timer = None
        if not self.watched:
            return
        for (board_id, offset), (watchers, sent) in list(self.watched.items()):
            board = self.block(board_id)
            if board is None:
                continue
            slot_bytes = next(iter(watchers)).lane.board_slot
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

    def _drop(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._wake >= 0:
            asyncio.get_running_loop().remove_reader(self._wake)
            os.close(self._wake)
            self._wake, self._armed = -1, False
        self.blocks = {}  # an engine's blocks die with it (its lanes' clients are closed)

    def _connect(self) -> socket.socket:
        if self._sock is None:
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.settimeout(5.0)
            try:
                s.connect(str(self.path))
            except OSError:
                s.close()
                raise
            self._sock = s
        return self._sock

    async def _fetch(self) -> None:
        async with self._lock:
            for attempt in range(2):  # a connection to an engine that has gone: a new one
                try:
                    maps = await asyncio.to_thread(
                        lambda: lanes.receive_blocks(self._connect()))
                    # a frame loop's block as a view of its records; a mesh board as bytes
                    self.blocks = {i: _native.BlockView(m) if kind == "block" else m
                                   for i, (kind, m) in maps.items()}
                    if self._wake < 0 and not self._no_wake:
                        await self._fetch_wake()
                    return
                except (OSError, ValueError) as e:
                    self._drop()
                    if attempt:
                        log.warning("the engine's blocks could not be had (%s): its "
                                    "players' messages go through the engine", e)

    async def _fetch_wake(self) -> None:
        try:
            self._wake = await asyncio.to_thread(lambda: lanes.receive_wake(self._connect()))
        except ConnectionError as e:  # an engine that has none: timers, a little late
            log.warning("%s: CORNERs above %g Hz are timed here", e, lanes.TIMER_MAX_HZ)
            self._no_wake = True
            for lane in list(self.framed):
                self.framed.discard(lane)
                lane.use_timer()
            return
        asyncio.get_running_loop().add_reader(self._wake, self._frame)
        if self.framed:
            self._arming = asyncio.get_running_loop().create_task(self._arm())

    async def _report_forever(self) -> None:
        while True:
            await asyncio.sleep(REPORT_S)
            if self.counts == self._reported:
                continue
            counts = dict(self.counts)
            async with self._lock:
                try:
                    line = lanes.counts_line(counts)
                    await asyncio.to_thread(lambda: self._connect().sendall(line))  # noqa: B023
                    self._reported = counts
                except OSError:
                    self._drop()  # the engine is away; a new one is asked when a lane opens
                    self._reported = {}


class Lane:
    """One client's open lane: ``write(kind, head, payload)`` sends a message ("corner" or
    "mesh", its frame header and payload) to the client at a message boundary of the engine's stream
    (``server.gateway.relay``), ``room`` says which room the engine last told the client it
    is in."""

    def __init__(self, lane: lanes.Lane, links: Lanes,
                 write: Callable[[str, bytes, bytes], None],
                 room: Callable[[], str | None]) -> None:
        self.lane, self.links = lane, links
        self.write, self.room = write, room
        self.view = links.block(lane.block)  # None until the block is had (then looked up)
        self.bucket = TokenBucket(lane.binary_rate, lane.binary_burst)
        self.fast = True  # HIPs taken here (off for good once the client passes its rate)
        self.sent_frame = -1
        self._retries = 0
        self._loop = asyncio.get_running_loop()
        self._due = self._loop.time()
        self._timer: asyncio.TimerHandle | None = None
        if lane.seat is not None:  # a seated player: its CORNERs are the gateway's to send
            framed = lane.corner_interval < 1.0 / lanes.TIMER_MAX_HZ - 1e-4 and \
                links.on_frames(self, True)
            if not framed:
                self._timer = self._loop.call_soon(self._corner)
        if lane.board is not None:
            links.watch(self)

    @property
    def mesh_key(self) -> tuple[int | None, int]:
        """Where its room's MESH is: the board, and the room's slot's offset in it."""
        return self.lane.board, self.lane.slot * self.lane.board_slot

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self in self.links.framed:
            self.links.on_frames(self, False)
        if self.lane.board is not None:
            self.links.unwatch(self)

    def send_mesh(self, head: bytes, data: bytes) -> None:
        if self.room() == self.lane.room:
            self.write("mesh", head, data)

    def _view(self) -> Any | None:
        if self.view is None:
            self.view = self.links.block(self.lane.block)
        return self.view

    def take(self, payload: bytes) -> bool:
        """A HIP from the client: written into the seat's hand, else False (the engine
        has it: a HIP that is not well formed, out of reach, past the rate, or of an
        occupant that has left the seat, or from a client that is not seated)."""
        ln = self.lane
        if ln.seat is None or not self.fast or self._view() is None:
            return False
        if not self.bucket.take():
            self.fast = False  # the engine's own limit and errors from here on
            return False
        try:
            hip = P.decode_hip(payload)
        except P.ProtocolError:
            return False
        x, y, z = hip.position
        lo, hi = ln.lo, ln.hi
        if not (lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and lo[2] <= z <= hi[2]):
            return False
        if not self.view.write_hip(ln.slot, ln.seat, ln.occupant, x, y, z,
                                   hip.seq & 0xFFFFFFFFFFFFFFFF, hip.time):
            return False
        self.links.counts["messages_in"] += 1
        return True

    def use_timer(self) -> None:
        """Its CORNERs on its own timer (taken off the frame wake-up: the gateway has none)."""
        self._timer = self._loop.call_soon(self._corner)

    def _send_newest(self) -> bool | None:
        """The seat's newest CORNER to the client if a newer frame than the last sent is
        there (True); False: none newer; None: the lane has ended (its slot holds another
        room now)."""
        ln = self.lane
        assert ln.seat is not None
        if self.room() != ln.room or self._view() is None:
            return False
        frame, msg = self.view.read_corner(ln.slot, ln.seat)
        if frame < self.sent_frame:
            return None
        if frame == self.sent_frame:
            return False
        self.sent_frame = frame
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
            due = self._due + max(self.lane.corner_interval, FRAME_S)
            self._due = due if due > now else now + FRAME_S / 2

    def _corner(self) -> None:
        """The seat's newest CORNER to the client, when a newer frame than the last sent
        is there; then the next one, an interval after this one was due (as the engine
        times its own: ``server.conn.Conn.offer_corner``)."""
        now = self._loop.time()
        sent = self._send_newest()
        if sent is None:
            self._timer = None
            return
        if sent:
            self._retries = 0
        elif self.room() == self.lane.room and self.view is not None:
            if self._retries < RETRIES:
                # Due just before the loop published the next frame (this timer and the
                # frames are not in step): look again a little later, not an interval later
                # (at corner_rate 1000 that lost one CORNER in eight).
                self._retries += 1
                self._timer = self._loop.call_at(now + RETRY_FRAME_S, self._corner)
                return
            self._retries = 0  # no new frame (the room sleeps): on at the rate
        interval = max(self.lane.corner_interval, FRAME_S)
        due = self._due + interval
        self._due = due if due > now else now + interval
        self._timer = self._loop.call_at(self._due, self._corner)
