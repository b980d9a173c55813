"""The lobby: the server's rooms and the scenes a room can be created with."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
from collections.abc import Awaitable, Callable, Iterator
from typing import Any, Protocol

from ..game.sim.scene import Scene
from ..game.wire import protocol as P
from ..game.wire.protocol import ProtocolError
from .directory import HostEntry, Moved, NotInView, Snapshot
from .room import Room, RoomHost, RoomSettings
from .sim import SimPool

log = logging.getLogger("clothball.server")

MAX_ROOMS = 32  # the default of Limits.max_rooms


class LobbyHooks(Protocol):
    """What a lobby asks of its server (``server.app.GameServer``'s), besides a room's
    ``RoomHost`` calls."""

    def busy(self) -> str | None:
        """Why no room more fits on this server now (``server.headroom``); None: room to
        spare."""
        ...

    def admit(self, scene: Scene) -> str | None:
        """Why a new room of ``scene`` would not fit beside the open ones (and what it
        would cost); None: it fits."""
        ...

    def fresh_view(self) -> Awaitable[bool]:
        """A read of the shared directory begun after now, shared by every join waiting for
        one (a room made elsewhere since the last read): True once read, False timed
        out."""
        ...

    def publish_now(self) -> Awaitable[bool] | None:
        """This process's rooms published soon; a new room's reply waits for it, so the room
        is in the directory before anyone is told its id. None: nothing to wait for."""
        ...

    def index_error(self) -> str | None:
        """Why the shared replay index cannot be written now (rounds wait as files)."""
        ...


class AlwaysRoom:
    """``LobbyHooks`` of a lobby that is the whole service and never full."""

    def busy(self) -> str | None:
        return None

    def admit(self, scene: Scene) -> str | None:
        return None

    async def fresh_view(self) -> bool:
        return True

    def publish_now(self) -> Awaitable[bool] | None:
        return None

    def index_error(self) -> str | None:
        return None


class Lobby:
    def __init__(self, scenes: dict[str, Scene], host: RoomHost, backend: str = "auto",
                 max_rooms: int = MAX_ROOMS, room_factory: Callable[..., Room] = Room,
                 sims: SimPool | None = None, hooks: LobbyHooks | None = None) -> None:
        if not scenes:
            raise ValueError("scenes: at least one scene is needed")
        self.scenes = scenes
        self.default_scene = next(iter(scenes))
        self.host = host
        self.backend = backend
        self.max_rooms = max_rooms
        self.rooms: dict[str, Room] = {}
        self.addresses: dict[str, str] = {}  # room id -> the address that created it
        self._room_factory = room_factory
        self.sims = sims  # the simulation workers every room of this lobby runs on
        # With a shared directory (several processes or hosts): this process's entry and
        # the last snapshot of everyone's rooms (None: this lobby is the whole service).
        self.me: HostEntry | None = None
        self.peers: Snapshot | None = None
        self.directory_error: str | None = None  # why the others' rooms are not listed
        self.hooks: LobbyHooks = hooks or AlwaysRoom()
        self._fresh = False  # lookups now are answered from a view read after they came

    def create(self, name: str, scene: str | None = None, *, public: bool = True,
               settings: RoomSettings | None = None, owner: str | None = None,
               permanent: bool = False, room_id: str | None = None,
               address: str | None = None) -> Room:
        """Create and start a room. ``room_id`` fixes its id (the host's permanent room is
        "main", so a spectator's link survives a server restart); else a random one."""
        scene_name = self.scene_name(scene)
        if len(self.rooms) >= self.max_rooms:
            raise ProtocolError("server_busy", f"this server already runs {self.max_rooms} rooms")
        why = None if permanent else self.hooks.admit(self.scenes[scene_name])
        if why is not None:
            raise ProtocolError("server_busy", why)
        if room_id is None:
            room_id = secrets.token_urlsafe(6)
        elif room_id in self.rooms:
            raise ValueError(f"room id {room_id!r} is taken")
        room = self._room_factory(room_id, name, self.scenes[scene_name], self.host,
                                  backend=self.backend, public=public, settings=settings,
                                  owner=owner, sims=self.sims)
        self.rooms[room_id] = room
        if address is not None:
            self.addresses[room_id] = address
        room.permanent = permanent
        if self.me is not None:
            self.me.rooms = len(self.rooms)  # placement sees this room before it is published
        room.start()
        room.published = self.hooks.publish_now()
        log.info("room %s (%s) created: scene %s, %s", room_id, name, scene_name,
                 "public" if public else "private")
        return room

    def scene_name(self, scene: str | None) -> str:
        """The scene a new room would run (None: the default); ``ProtocolError`` naming the
        scenes there are when it is unknown."""
        scene_name = scene or self.default_scene
        if scene_name not in self.scenes:
            raise ProtocolError(
                "bad_message", f"scene {scene_name!r} unknown; this server has "
                f"{', '.join(sorted(self.scenes))}"
            )
        return scene_name

    def get(self, room_id: object) -> Room:
        """A room of this process; ``Moved`` when another process or host has it."""
        if isinstance(room_id, str) and room_id in self.rooms:
            return self.rooms[room_id]
        if isinstance(room_id, str) and self.peers is not None and self.me is not None:
            there = self.peers.locate(room_id)
            if there is None and not self._fresh:
                raise NotInView(room_id)  # perhaps made elsewhere since the last read
            if there is not None and there.host_id != self.me.host_id:
                raise Moved(there.address, f"room {room_id} lives at {there.address}")
        raise ProtocolError("unknown_room", f"no room {room_id!r}")

    @contextlib.contextmanager
    def viewed_fresh(self) -> Iterator[None]:
        """Lookups within are answered from the view as it is (a read made after the
        request came, or none in time): ``get`` raises no ``NotInView``."""
        self._fresh = True
        try:
            yield
        finally:
            self._fresh = False

    def place(self, clients: int) -> None:
        """Where a new room goes: here, or ``Moved`` to the least-loaded process or host
        (rooms, then clients; this one's ``clients`` as of now) when that is not this
        one."""
        if self.peers is None or self.me is None:
            return
        self.me.rooms, self.me.clients = len(self.rooms), clients
        self.me.busy = self.hooks.admit(self.scenes[self.default_scene]) is not None
        hosts = dict(self.peers.hosts)
        hosts[self.me.host_id] = self.me  # this process's own load as of now
        best = min(hosts.values(), key=lambda h: (h.load, h.host_id != self.me.host_id))
        if best.host_id != self.me.host_id and best.load < self.me.load and not best.busy:
            # `placed`: the host it is sent to takes it, whatever its own (perhaps older)
            # view of the loads says; else two views could send it to and fro.
            raise Moved(best.address, f"new rooms go to {best.address} (least loaded)",
                        {"placed": True})

    def rooms_of(self, address: str) -> int:
        """How many open rooms were created from ``address``."""
        return sum(1 for a in self.addresses.values() if a == address)

    async def remove(self, room_id: str) -> None:
        """Take a room out of the lobby and close it."""
        room = self.rooms.pop(room_id, None)
        self.addresses.pop(room_id, None)
        if room is not None:
            await room.close()

    def listing(self) -> list[dict[str, Any]]:
        """The public rooms (private ones are joined by id and code): this process's as
        they are now and, with a directory, every other process's as last published, each
        marked with the address it lives at (``host``)."""
        if self.me is None:
            return [r.info() for r in self.rooms.values() if r.public]
        mine = [{**r.info(), "host": self.me.address} for r in self.rooms.values() if r.public]
        others = [] if self.peers is None else [
            r for r in self.peers.listing()
            if r["id"] not in self.rooms and r["host"] != self.me.address]
        return sorted(mine + others, key=lambda r: r["id"])

    def rooms_message(self) -> dict[str, Any]:
        """The ``rooms`` reply: the listing and, while the shared directory cannot be
        reached, ``directory_error`` saying so (only this process's rooms are listed); while
        the shared replay index cannot be written, ``replay_index_error``."""
        msg: dict[str, Any] = {"type": "rooms", "rooms": self.listing()}
        if self.directory_error is not None:
            msg["directory_error"] = self.directory_error
        index_error = self.hooks.index_error()
        if index_error is not None:
            msg["replay_index_error"] = index_error
        return msg

    def published(self) -> list[tuple[str, bool, dict[str, Any]]]:
        """This process's rooms for the directory: (id, public, info); a private room's
        info is only its id (its code never leaves this process)."""
        return [(rid, r.public, r.info() if r.public else {"id": rid})
                for rid, r in self.rooms.items()]

    def shown(self) -> None:
        """Someone listed the rooms (a lobby client, ``/api/rooms``): the host's show room
        wakes for a while, so its listing is live (``Room.shown``)."""
        for room in self.rooms.values():
            room.shown()

    async def close_idle(self, now: float, after: float) -> None:
        """Close the rooms nobody has been in for ``after`` s (not the host's own, which
        sleeps again once no one has listed the rooms for a while)."""
        for rid, room in list(self.rooms.items()):
            if room.permanent:
                room.update_awake()
                continue
            if room.is_empty() and now - room.last_active > after:
                if any(s.kind == "bot" for s in room.seats) and room.spectators:
                    continue
                log.info("closing idle room %s", rid)
                await self.remove(rid)

    async def close(self) -> None:
        rooms, self.rooms = list(self.rooms.values()), {}
        self.addresses.clear()
        await asyncio.gather(*(r.close() for r in rooms))


def parse_settings(msg: dict[str, Any]) -> RoomSettings:
    """Room settings from a ``create_room`` message (every field optional, range-checked)."""
    d = RoomSettings()
    return RoomSettings(
        first_to=P.field_int(msg, "first_to", d.first_to, 1, 99),  # type: ignore[arg-type]
        countdown=P.field_float(msg, "countdown", d.countdown, 0.0, 10.0),  # type: ignore[arg-type]
        reset_offset=P.field_float(msg, "reset_offset", d.reset_offset, 0.0, 0.2),  # type: ignore[arg-type]
        reset_speed=P.field_float(msg, "reset_speed", d.reset_speed, 0.0, 5.0),  # type: ignore[arg-type]
        bots_allowed=P.field_bool(msg, "bots_allowed", d.bots_allowed),
        unguarded=P.field_bool(msg, "unguarded", d.unguarded),
        bot_difficulty=P.field_float(msg, "bot_difficulty", d.bot_difficulty, 0.0, 1.0),  # type: ignore[arg-type]
        grace=P.field_float(msg, "grace", d.grace, 0.5, 60.0),  # type: ignore[arg-type]
        autoplay=P.field_bool(msg, "autoplay", d.autoplay),
        restart_delay=P.field_float(msg, "restart_delay", d.restart_delay, 0.0, 60.0),  # type: ignore[arg-type]
        record_cap_s=P.field_float(msg, "record_cap_s", d.record_cap_s, 1.0, 3600.0),  # type: ignore[arg-type]
    )
