"""One room: four seats, spectators, a match, the simulation thread and the round recorder.

Everything here runs on the event loop, except ``RoomSim`` (its own thread). The room is a
thin layer between the connections and two pure parts: ``game.rules.Match`` (scores and
phases; raises on an illegal move) and the simulation.
"""

from __future__ import annotations

import asyncio
import logging
import math
import secrets
import time
from collections.abc import Awaitable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from ..game.rules import EDGE_NAMES, SEATS, IllegalMove, Match, edge_of_seat
from ..game.sim.scene import Scene
from ..game.wire import protocol as P
from ..game.wire.protocol import ProtocolError
from ..game.wire.replay import REPLAY_VERSION, new_round_id
from .limits import Limits
from .shared.lanes import LaneSpec, in_reach
from .sim import FrameResult, RoomSim, SimPool
from .storage.recorder import Recording

log = logging.getLogger("clothball.server")

REACH_FRACTION = 0.3  # a hand may move this fraction of the cloth's size from its anchor
RECORD_TAIL = 1.0  # s of the room's frames recorded after the ball left the cloth
RECORD_TAIL_LATE_S = 9.0  # a late room's tail waits at most this much longer (wall time)
# s the host's show room steps, with no one in it and no bots, after the rooms were listed
SHOWN_AWAKE_S = 30.0


class Peer(Protocol):
    """What a room needs from a connection (``server.conn.Conn`` is the one there is): who it
    is, where it sits, and how to send it something. The room never imports it."""

    id: str
    room: Room | None
    seat: int | None
    role: str  # "lobby", "player" or "spectator"

    def send_json(self, msg: dict[str, Any]) -> None: ...
    corner_interval: float  # s between its CORNER messages
    want_mesh: bool
    limits: Limits

    # Its lane (server.lanes: its HIPs in, its CORNERs and its room's MESH out), or none;
    # ``shared``: a gateway can map the room's block and board.
    def open_lane(self, spec: LaneSpec | None, shared: bool) -> None: ...
    def error(self, err: ProtocolError | str, message: str = "", re: object = None) -> None: ...
    def kicked(self, reason: str) -> None: ...


class RoomHost(Protocol):
    """What a room needs from its server."""

    def spawn_bot(self, room: Room, seat: int, token: str, difficulty: float) -> None: ...

    def save_round(self, header: dict[str, Any], records: Recording) -> None: ...

    def room_stopped(self, room: Room, reason: str) -> None: ...


@dataclass
class RoomSettings:
    """Per-room settings (``create_room`` fields of the same names)."""

    first_to: int = 5
    countdown: float = 3.0  # s before each round
    reset_offset: float = 0.05  # m: the ball restarts this far (at most) from the centre
    reset_speed: float = 0.0  # m/s: horizontal speed the ball restarts with (a harder game)
    bots_allowed: bool = True
    unguarded: bool = False  # a match may start with empty seats (their edges unguarded)
    bot_difficulty: float = 0.6
    grace: float = 15.0  # s a disconnected player's seat is held
    autoplay: bool = False  # start (and restart) matches when only bots are seated
    restart_delay: float = 5.0  # s after a match before an autoplay room starts the next
    # s of a round recorded at most: a longer round's replay stops there, marked "cut".
    record_cap_s: float = 600.0


@dataclass
class Seat:
    index: int
    kind: str = "empty"  # "empty", "human", "bot"
    name: str = ""
    token: str | None = None
    conn: Peer | None = None
    ready: bool = False
    held_until: float | None = None  # disconnected: seat held until this loop time
    grace_timer: asyncio.TimerHandle | None = None
    difficulty: float = 0.6

    @property
    def connected(self) -> bool:
        return self.conn is not None

    def info(self) -> dict[str, Any]:
        return {
            "seat": self.index,
            "edge": EDGE_NAMES[edge_of_seat(self.index)],
            "kind": self.kind,
            "name": self.name,
            "ready": self.ready or self.kind == "bot",
            "connected": self.connected,
            "open": self.kind != "human",  # a human who joins may take it (bots are backfill)
        }


@dataclass
class RoundRecord:
    id: str
    round: int
    started_at: float
    # Per seat, everyone who held it during the round, in order ({kind, name}): a player who
    # takes a seat mid-round played the round too, and its replay must say so.
    held: list[list[dict[str, str]]] = field(default_factory=list)

    def note(self, seat: Seat) -> None:
        """``seat``'s occupant now (a new one is appended; empty seats hold no one)."""
        who = {"kind": seat.kind, "name": seat.name}
        if seat.kind != "empty" and (not self.held[seat.index]
                                     or self.held[seat.index][-1] != who):
            self.held[seat.index].append(who)


class Room:
    def __init__(self, room_id: str, name: str, scene: Scene, host: RoomHost, *,
                 backend: str = "auto", public: bool = True,
                 settings: RoomSettings | None = None, owner: str | None = None,
                 mesh_hz: float = 30.0, track_hz: float = 100.0,
                 rng: np.random.Generator | None = None, sims: SimPool | None = None) -> None:
        self.id = room_id
        self.name = name
        self.scene = scene
        self.public = public
        self.code = None if public else secrets.token_urlsafe(8)
        self.settings = settings or RoomSettings()
        self.owner = owner  # client id allowed to start and add bots (None: any seated player)
        self.host = host
        self.match = Match(first_to=self.settings.first_to)
        self.seats = [Seat(i, difficulty=self.settings.bot_difficulty) for i in range(SEATS)]
        self.spectators: set[Peer] = set()
        self.mesh_hz = mesh_hz
        self.track_hz = track_hz
        self.rng = rng or np.random.default_rng()
        self.loop = asyncio.get_running_loop()
        # `sims`: the server's pool (this room becomes a slot of its scene's worker).
        self.sim = RoomSim(scene, backend, deliver=self._on_frame, loop=self.loop,
                           mesh_hz=mesh_hz, track_hz=track_hz, pool=sims)
        self.sim.corner_interval = math.inf  # its frames are wanted for exits and failures
        self.anchors = self.sim.arena.anchors
        self.size = self.sim.arena.size
        self.half_extent = np.full(3, REACH_FRACTION * self.size)
        self._reach_lo = [tuple((a - self.half_extent - 1e-6).tolist()) for a in self.anchors]
        self._reach_hi = [tuple((a + self.half_extent + 1e-6).tolist()) for a in self.anchors]
        self.created = time.time()
        self.last_active = self.loop.time()
        # The host's own room (the --bots demo): never closed for idleness; with no one in
        # it, it steps while its bots play or for SHOWN_AWAKE_S after the rooms were listed
        # (its frame counter moves for whoever looks), else it sleeps like any room.
        self.permanent = False
        self._shown_at: float | None = None
        # Its publication to a shared directory (``Lobby.create``): its id is given out
        # once that is done. None: nothing to wait for.
        self.published: Awaitable[bool] | None = None
        self._task: asyncio.Task[None] | None = None  # the countdown / restart in progress
        self._finishing: set[asyncio.Task[None]] = set()  # rounds' recordings being ended
        self._recording: RoundRecord | None = None
        self._closed = False
        self.last_exit: tuple[int, int, list[float]] | None = None

    # --- life -----------------------------------------------------------------------------
    def start(self) -> None:
        self.update_awake()
        self.sim.start()

    def update_awake(self) -> None:
        """A room steps while a human holds a seat or someone watches it; else it sleeps
        (no CPU), except the host's own room (``permanent``) while bots play in it or for a
        while after the rooms were listed (``shown``)."""
        awake = not self.is_empty()
        if self.permanent and not awake:
            shown = self._shown_at is not None and \
                self.loop.time() - self._shown_at < SHOWN_AWAKE_S
            awake = shown or any(s.kind == "bot" for s in self.seats)
        if awake == self.sim.asleep:
            self.sim.set_awake(awake)

    def shown(self) -> None:
        """Someone listed the rooms: the host's show room steps for ``SHOWN_AWAKE_S``."""
        if self.permanent:
            self._shown_at = self.loop.time()
            self.update_awake()

    async def close(self) -> None:
        self._closed = True
        if self._task is not None:
            self._task.cancel()
        if self._finishing:
            # A round that just ended is still recording its tail: let it be saved (the
            # simulation answers until it stops below), then nothing is left pending.
            _, late = await asyncio.wait(set(self._finishing),
                                         timeout=RECORD_TAIL + RECORD_TAIL_LATE_S + 6.0)
            for t in late:
                t.cancel()
        for s in self.seats:
            if s.grace_timer is not None:
                s.grace_timer.cancel()
        await asyncio.to_thread(self.sim.stop)

    # --- views ----------------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "name": self.name,
            "scene": self.scene.name,
            "n": self.scene.n,
            "public": self.public,
            "state": self.match.state,
            "round": self.match.round,
            "first_to": self.match.first_to,
            "scores": list(self.match.scores),
            "winners": list(self.match.winners),
            "seats": [s.info() for s in self.seats],
            "spectators": len(self.spectators),
            "bots_allowed": self.settings.bots_allowed,
            "unguarded": self.settings.unguarded,
            "frame": self.sim.frame,
        }

    def geometry(self) -> dict[str, Any]:
        """What a client needs to draw the cloth and map a device onto a corner."""
        sc = self.scene
        return {
            "scene": sc.name,
            "n": sc.n,
            "size": self.size,
            "height": float(sc["cloth"]["height"]),
            "ball_radius": self.sim.arena.ball_radius,
            "stiffness": self.sim.arena.stiffness,
            "frame_dt": self.sim.frame_dt,
            "mesh_hz": self.mesh_hz,
            "anchors": self.anchors.tolist(),
            "reach_half_extent": self.half_extent.tolist(),
            "edges": list(EDGE_NAMES),
        }

    def conns(self) -> list[Peer]:
        out = [s.conn for s in self.seats if s.conn is not None]
        return out + list(self.spectators)

    def humans(self) -> list[Seat]:
        return [s for s in self.seats if s.kind == "human"]

    def seated(self) -> list[int]:
        return [s.index for s in self.seats if s.kind != "empty"]

    def is_empty(self) -> bool:
        return not self.spectators and all(s.kind != "human" for s in self.seats)

    # --- messages out ---------------------------------------------------------------------
    def broadcast(self, msg: dict[str, Any]) -> None:
        for c in self.conns():
            c.send_json(msg)

    def broadcast_state(self) -> None:
        # Every change of who is in the room comes through here.
        self.update_awake()
        self.broadcast({"type": "room", **self.info()})

    def event(self, kind: str, /, **fields: Any) -> None:
        msg = {"type": "event", "event": kind, "room": self.id, "frame": self.sim.frame,
               "time": self.sim.now(), **fields}
        self.broadcast(msg)
        if self._recording is not None:
            # The round in progress only: an ended round's tail (RECORD_TAIL) can overlap
            # the next round's countdown and start, which are not its events.
            self.sim.command("record_event", (self._recording.id, P.encode_json(msg).encode()))

    # --- seats ----------------------------------------------------------------------------
    def check_code(self, code: str | None) -> None:
        if self.code is not None and not (code and secrets.compare_digest(code, self.code)):
            raise ProtocolError("bad_code", f"room {self.id} is private: a valid 'code' is needed")

    def join_player(self, conn: Peer, seat: int | None, name: str, code: str | None
                    ) -> dict[str, Any]:
        """Seat a human: an empty seat, or else one a bot holds (bots are backfill: the bot
        leaves at once and the event says so). ``seat`` asks for one seat in particular."""
        self.check_code(code)
        if seat is None:
            open_seats = ([s for s in self.seats if s.kind == "empty"]
                          or [s for s in self.seats if s.kind == "bot"])
            if not open_seats:
                raise ProtocolError("room_full", f"room {self.id} has no free seat (every "
                                    "corner is held by a player)")
            target = open_seats[0]
        else:
            target = self._seat(seat)
            if target.kind == "human":
                raise ProtocolError("bad_seat", f"seat {seat} is taken by a player")
        replaced = target.kind == "bot"
        if replaced:
            bot = target.conn
            self._detach(target)
            if bot is not None:
                bot.kicked("a player took this seat")
        target.kind, target.name, target.ready = "human", name, False
        target.token = self._new_token()
        self._attach(target, conn)
        if self._recording is not None:
            self._recording.note(target)
        if replaced:
            self.event("seat", seat=target.index, kind="human", name=name,
                       reason="replaced_bot")
        else:
            self.event("seat", seat=target.index, kind="human", name=name)
        self.broadcast_state()
        return self._joined(target)

    def _seat(self, index: int) -> Seat:
        """Seat ``index``, or ``bad_seat`` for a number that names none."""
        if not 0 <= index < SEATS:
            raise ProtocolError("bad_seat", f"seat must be 0..{SEATS - 1}, got {index}")
        return self.seats[index]

    def _new_token(self) -> str:
        """A seat's reconnect key: this room's id, a dot, a secret. The id lets any process
        of a service send a reconnect to the room's own (``token_room``)."""
        return f"{self.id}.{secrets.token_urlsafe(24)}"

    def resume(self, conn: Peer, token: str) -> dict[str, Any]:
        """Take a held seat back (a reconnect, or a bot claiming the seat it was given)."""
        for s in self.seats:
            if s.token is not None and secrets.compare_digest(s.token, token):
                if s.conn is not None and s.conn is not conn:
                    old = s.conn
                    self._detach(s)
                    old.kicked("your seat was resumed by another connection")
                if s.grace_timer is not None:
                    s.grace_timer.cancel()
                    s.grace_timer = None
                s.held_until = None
                self._attach(s, conn)
                self.event("seat", seat=s.index, kind=s.kind, name=s.name, resumed=True)
                self.broadcast_state()
                return self._joined(s)
        raise ProtocolError("bad_token", "reconnect token unknown or expired")

    def _attach(self, seat: Seat, conn: Peer) -> None:
        seat.conn = conn
        conn.room, conn.seat, conn.role = self, seat.index, "player"
        self.last_active = self.loop.time()
        self._open_lane(conn, seat.index)

    def _open_lane(self, conn: Peer, seat: int | None) -> None:
        """The client's lane (server.lanes): a seated player's HIPs and CORNERs, and the
        MESH it wants, from the room's frame loop memory, by its gateway or the engine."""
        place = self.sim.lane_place(seat)
        mesh = place is not None and conn.want_mesh
        if place is None or (seat is None and not mesh):
            conn.open_lane(None, False)
            return
        # A seated player's CORNERs, at any corner_rate: above what timers keep, on the
        # frame loops' wake-up (server.shared.lanes).
        i = 0 if seat is None else seat
        conn.open_lane(LaneSpec(
            self.id, place["block"], place["slot"], seat, place["occupant"],
            self._reach_lo[i], self._reach_hi[i], conn.corner_interval,
            conn.limits.binary_rate, conn.limits.binary_burst,
            place["board"] if mesh else None, place["board_slot"]), place["shared"])

    @staticmethod
    def _close_lane(conn: Peer) -> None:
        conn.open_lane(None, False)

    def _detach(self, seat: Seat) -> None:
        conn = seat.conn
        if conn is not None:
            conn.room, conn.seat, conn.role = None, None, "lobby"
            self._close_lane(conn)
        seat.conn = None
        self.sim.set_hip(seat.index, None)

    def _joined(self, seat: Seat) -> dict[str, Any]:
        return {
            "type": "joined",
            "room": self.id,
            "role": "player",
            "seat": seat.index,
            "edge": edge_of_seat(seat.index),
            "edge_name": EDGE_NAMES[edge_of_seat(seat.index)],
            "token": seat.token,
            "kind": seat.kind,
            "reach": {
                "centre": self.anchors[seat.index].tolist(),
                "half_extent": self.half_extent.tolist(),
            },
            "geometry": self.geometry(),
            "state": self.info(),
            "code": self.code,
        }

    def join_spectator(self, conn: Peer, code: str | None) -> dict[str, Any]:
        self.check_code(code)
        self.spectators.add(conn)
        conn.room, conn.seat, conn.role = self, None, "spectator"
        self.last_active = self.loop.time()
        self._open_lane(conn, None)
        self.broadcast_state()
        return {"type": "joined", "room": self.id, "role": "spectator",
                "geometry": self.geometry(), "state": self.info()}

    def leave(self, conn: Peer) -> None:
        """The connection leaves on purpose: its seat is freed at once."""
        if conn in self.spectators:
            self.spectators.discard(conn)
            conn.room, conn.role = None, "lobby"
            self._close_lane(conn)
            self.broadcast_state()
            return
        if conn.seat is not None and self.seats[conn.seat].conn is conn:
            seat = self.seats[conn.seat]
            self._detach(seat)
            self._free(seat, "left")

    def disconnected(self, conn: Peer) -> None:
        """The connection dropped: a player's seat is held for the grace period."""
        if conn in self.spectators:
            self.spectators.discard(conn)
            self._close_lane(conn)
            self.broadcast_state()
            return
        if conn.seat is None or self.seats[conn.seat].conn is not conn:
            return
        seat = self.seats[conn.seat]
        self._detach(seat)
        grace = self.settings.grace
        seat.held_until = self.loop.time() + grace
        seat.grace_timer = self.loop.call_later(grace, self._grace_over, seat.index)
        self.event("seat", seat=seat.index, kind=seat.kind, name=seat.name, held_for=grace)
        self.broadcast_state()

    def _grace_over(self, index: int) -> None:
        seat = self.seats[index]
        seat.grace_timer = None
        seat.held_until = None
        if seat.conn is not None or self._closed:
            return
        if seat.kind == "human" and self.settings.bots_allowed:
            self.add_bot(index, self.settings.bot_difficulty, reason="grace_over")
        else:
            self._free(seat, "grace_over")

    def _free(self, seat: Seat, reason: str) -> None:
        seat.kind, seat.name, seat.token, seat.ready = "empty", "", None, False
        self.sim.set_hip(seat.index, None)
        self.event("seat", seat=seat.index, kind="empty", reason=reason)
        self.broadcast_state()
        if not self.humans() and not self._bot_seats() and self.match.state in (
            "countdown", "playing"
        ):
            self._abort("everyone left")
        self._maybe_start()

    def _bot_seats(self) -> list[Seat]:
        return [s for s in self.seats if s.kind == "bot"]

    def add_bot(self, index: int | None, difficulty: float, reason: str = "added") -> int:
        index = self._place_bot(index, difficulty, reason)
        self._maybe_start()
        return index

    def _place_bot(self, index: int | None, difficulty: float, reason: str) -> int:
        if not self.settings.bots_allowed:
            raise ProtocolError("not_allowed", f"room {self.id} does not allow bots")
        if index is None:
            free = [s.index for s in self.seats if s.kind == "empty"]
            if not free:
                raise ProtocolError("room_full", f"room {self.id} has no free seat")
            index = free[0]
        seat = self._seat(index)
        if seat.kind != "empty" and not (reason == "grace_over" and seat.conn is None):
            raise ProtocolError("bad_seat", f"seat {index} is taken ({seat.kind})")
        seat.kind, seat.name, seat.ready = "bot", f"bot-{index}", True
        seat.difficulty = difficulty
        seat.token = self._new_token()
        if self._recording is not None:
            self._recording.note(seat)
        self.event("seat", seat=index, kind="bot", name=seat.name, reason=reason)
        self.broadcast_state()
        self.host.spawn_bot(self, index, seat.token, difficulty)
        return index

    def remove_bot(self, index: int) -> None:
        seat = self._seat(index)
        if seat.kind != "bot":
            raise ProtocolError("bad_seat", f"seat {index} holds no bot")
        conn = seat.conn
        self._detach(seat)
        self._free(seat, "bot_removed")
        if conn is not None:
            conn.kicked("bot removed")

    # --- control --------------------------------------------------------------------------
    def may_control(self, conn: Peer) -> bool:
        if self.owner is not None:
            return conn.id == self.owner
        return conn.seat is not None

    def set_ready(self, conn: Peer, ready: bool) -> None:
        if conn.seat is None:
            raise ProtocolError("not_allowed", "only a seated player can be ready")
        self.seats[conn.seat].ready = ready
        self.broadcast_state()
        self._maybe_start()

    def request_start(self, conn: Peer) -> None:
        if not self.may_control(conn):
            raise ProtocolError("not_allowed", "only the room's host can start the match")
        why = self._guard_edges()
        if why:
            raise ProtocolError("cannot_start", why)
        self._start_match()

    def _guard_edges(self) -> str:
        """Before a match: bots take the empty seats (a match of unguarded edges is rounds
        void), unless the room asks for empty seats. Returns why it cannot start, or ""."""
        empty = [s.index for s in self.seats if s.kind == "empty"]
        if not empty or self.settings.unguarded:
            return ""
        if not self.settings.bots_allowed:
            corners = ", ".join(str(i) for i in empty)
            return (f"corner(s) {corners} empty and this room allows no bots: "
                    "wait for players to take them")
        for i in empty:
            self._place_bot(i, self.settings.bot_difficulty, "backfill")
        return ""

    def _maybe_start(self) -> None:
        if self._closed or self.match.state not in ("waiting", "over"):
            return
        if self._task is not None and not self._task.done():
            return
        humans = self.humans()
        if humans:
            if all(s.ready for s in humans) and all(s.conn is not None for s in humans):
                why = self._guard_edges()
                if why:
                    self.event("cannot_start", reason=why)
                    return
                self._start_match()
        elif self._bot_seats() and self.settings.autoplay:
            delay = self.settings.restart_delay if self.match.state == "over" else 0.0
            self._task = asyncio.create_task(self._delayed_start(delay))

    async def _delayed_start(self, delay: float) -> None:
        await asyncio.sleep(delay)
        self._task = None
        if self.humans():
            # A human took a seat meanwhile: their readiness decides (a ready pressed
            # during the wait found this task pending and must not be lost).
            self._maybe_start()
        elif self._bot_seats() and self.match.state in ("waiting", "over"):
            self._start_match()

    def _start_match(self) -> None:
        try:
            self.match.start(self.seated())
        except IllegalMove as e:
            raise ProtocolError("illegal_move", str(e)) from None
        for s in self.seats:
            if s.kind == "human":
                s.ready = False
        self.event("match_start", first_to=self.match.first_to, seats=self.seated())
        self.broadcast_state()
        self._run(self._countdown())

    def _run(self, coro: Any) -> None:
        if self._task is not None and not self._task.done():
            self._task.cancel()
        self._task = asyncio.create_task(coro)

    async def _countdown(self) -> None:
        remaining = self.settings.countdown
        while remaining > 0:
            self.event("countdown", seconds=math.ceil(remaining - 1e-9))
            step = min(1.0, remaining)
            await asyncio.sleep(step)
            remaining -= step
        if self.match.state != "countdown":
            return
        pos, vel = self._reset_ball()
        rnd = self.match.begin_round()
        self.sim.command("reset_ball", (pos, vel))
        self._recording = RoundRecord(id=new_round_id(), round=rnd, started_at=time.time(),
                                      held=[[] for _ in self.seats])
        for s in self.seats:
            self._recording.note(s)
        self.sim.command("record_start", (self._recording.id, self.settings.record_cap_s))
        self.event("round_start", round=rnd, ball=pos.tolist(), ball_velocity=vel.tolist())
        self.sim.command("arm")
        self.broadcast_state()

    def _reset_ball(self) -> tuple[np.ndarray, np.ndarray]:
        """The scene's start position with a small random horizontal offset."""
        start = np.array(self.scene["ball"]["position"], dtype=np.float64)
        v0 = np.array(self.scene["ball"]["velocity"], dtype=np.float64)
        angle = self.rng.uniform(0.0, 2.0 * math.pi)
        r = self.settings.reset_offset * math.sqrt(self.rng.uniform(0.0, 1.0))
        pos = start + np.array([r * math.cos(angle), 0.0, r * math.sin(angle)])
        angle = self.rng.uniform(0.0, 2.0 * math.pi)
        s = self.settings.reset_speed
        vel = v0 + np.array([s * math.cos(angle), 0.0, s * math.sin(angle)])
        return pos, vel

    def _abort(self, why: str) -> None:
        self.match.abort()
        self.sim.command("disarm")
        if self._task is not None:
            self._task.cancel()
            self._task = None
        if self._recording is not None:
            self.sim.command("record_stop", (self._recording.id, _discard))
            self._recording = None
        self.event("match_abort", reason=why)
        self.broadcast_state()

    # --- frames from the simulation -------------------------------------------------------
    def _on_frame(self, result: FrameResult) -> None:
        """An exit or a failure of the room's frame loop (its CORNERs and MESH go out by
        the lanes, server.lanes, without the room)."""
        if self._closed:
            return
        if result.sim_error is not None:
            self._stop_on_error(result.sim_error)
            return
        if result.exit is not None:
            self._on_exit(*result.exit)

    def _stop_on_error(self, reason: str) -> None:
        """The simulation failed (non-finite state): this room stops, says why, and sends
        its clients back to the lobby; the server's other rooms run on."""
        if self._closed:
            return
        if self.match.state in ("countdown", "playing"):
            self._abort("the simulation stopped")
        self.event("room_stopped", reason=reason)
        for c in self.conns():
            c.error("room_stopped", f"room {self.id} stopped: {reason}")
        for s in self.seats:
            if s.conn is not None:
                s.conn.room, s.conn.seat, s.conn.role = None, None, "lobby"
                self._close_lane(s.conn)
                if s.kind == "bot":
                    s.conn.kicked("room stopped")
                s.conn = None
        for c in self.spectators:
            c.room, c.role = None, "lobby"
            self._close_lane(c)
        self.spectators.clear()
        self._closed = True
        self.host.room_stopped(self, reason)

    def on_hip(self, conn: Peer, hip: P.Hip) -> None:
        seat = conn.seat
        if seat is None or self.seats[seat].conn is not conn:
            raise ProtocolError("not_allowed", "HIP messages are for seated players only")
        if not in_reach(self._reach_lo[seat], self._reach_hi[seat], hip.position):
            raise ProtocolError(
                "out_of_range",
                f"HIP {[round(v, 4) for v in hip.position]} is outside seat {seat}'s reach box "
                f"{self.anchors[seat].round(4).tolist()} +/- {self.half_extent[0]:.3g} m",
            )
        self.sim.set_hip(seat, hip.position, hip.seq, hip.time)

    def _on_exit(self, edge: int, frame: int, ball: list[float]) -> None:
        if self.match.state != "playing":
            return
        self.last_exit = (edge, frame, ball)
        result = self.match.concede(edge, self.seated())
        self.event(
            "score", round=result.round, edge=edge, edge_name=EDGE_NAMES[edge],
            conceded_by=result.conceded_by, scorers=list(result.scorers),
            scores=list(result.scores), ball=ball,
        )
        if result.match_over:
            self.event("match_end", winners=list(result.winners), scores=list(result.scores))
        rec = self._recording
        self._recording = None
        if rec is not None:
            header = self._round_header(rec, edge, result.conceded_by, list(result.scores),
                                        list(result.scorers))
            t = asyncio.create_task(self._finish_recording(header, frame))
            self._finishing.add(t)
            t.add_done_callback(self._finishing.discard)
        self.broadcast_state()
        if result.match_over:
            self._task = None
            self._maybe_start()
        else:
            self._run(self._countdown())

    def _round_header(self, rec: RoundRecord, edge: int, conceded_by: int | None,
                      scores: list[int], scorers: list[int]) -> dict[str, Any]:
        ended = time.time()
        return {
            "format": "clothball-replay",
            "replay_version": REPLAY_VERSION,
            "protocol_version": P.PROTOCOL_VERSION,
            "id": rec.id,
            "room_id": self.id,
            "room_name": self.name,
            "scene": self.scene.name,
            "scene_data": self.scene.to_dict(),
            "geometry": self.geometry(),
            "round": rec.round,
            # The seats when the round was decided, each with everyone who held it in the
            # round (``conceded_by`` names a seat of this list).
            "players": [{**s.info(), "held_by": held} for s, held in zip(self.seats, rec.held,
                                                                           strict=True)],
            "conceded_edge": edge,
            "conceded_by": conceded_by,
            "scorers": scorers,
            "scores": scores,
            "first_to": self.match.first_to,
            "started_at": rec.started_at,
            "ended_at": ended,
            "duration_s": ended - rec.started_at,
            "track_hz": self.track_hz,
            "tail_s": RECORD_TAIL,
        }

    async def _tail(self, exit_frame: int) -> None:
        """Until RECORD_TAIL of the room's own frames have followed the score: a room that
        runs late takes longer in wall time (at most RECORD_TAIL_LATE_S more), one that stops
        stepping (asleep, stopped) no longer."""
        want = exit_frame + round(RECORD_TAIL / self.sim.frame_dt)
        await asyncio.sleep(RECORD_TAIL)
        end = self.loop.time() + RECORD_TAIL_LATE_S
        while self.sim.frame < want and self.sim.alive and self.sim.awake \
                and self.loop.time() < end:
            await asyncio.sleep(0.02)

    async def _finish_recording(self, header: dict[str, Any], exit_frame: int) -> None:
        await self._tail(exit_frame)
        fut: asyncio.Future[Recording | None] = self.loop.create_future()

        def got(rec: Recording | None) -> None:
            def settle() -> None:
                if not fut.done():
                    fut.set_result(rec)
                elif rec is not None:
                    rec.discard()

            try:
                self.loop.call_soon_threadsafe(settle)
            except RuntimeError:  # loop closed
                _discard(rec)

        self.sim.command("record_stop", (header["id"], got))
        try:
            rec = await asyncio.wait_for(fut, timeout=5.0)
        except TimeoutError:
            log.warning("room %s: round %s not saved (simulation stopped)", self.id, header["id"])
            return
        if rec is None:
            return
        await asyncio.to_thread(rec.finish)  # every record on disk
        # The round's length as a player shows it: its recorded frames, the tail included.
        header["duration_s"] = rec.duration_s
        if rec.cut is not None:
            header["cut"] = rec.cut  # recorded up to where it stopped, and says why
        self.host.save_round(header, rec)


def _discard(rec: Recording | None) -> None:
    """A recording nobody will save (an aborted match): its spool goes."""
    if rec is not None:
        rec.discard()
