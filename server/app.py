"""The game server: one port serving the websocket endpoint ``/ws`` (``server.ws``) and a
small HTTP surface (``server.http``). ``GameServer`` wires them to the lobby, the rooms, the
bots and the replay index, and is the rooms' ``RoomHost``.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import functools
import json
import logging
import math
import os
import secrets
import tempfile
import time
import urllib.parse
from collections.abc import Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from websockets.asyncio.server import Server, serve

from ..game.sim.scene import ASSETS, Scene
from .conn import Conn
from .directory import IO_TIMEOUT_S, MIN_READ_GAP_S, PUBLISH_S, Directory, HostEntry, OnDemand
from .gateway.relay import Gateway
from .headroom import WINDOW_S, Headroom
from .http import HttpSurface
from .lanes.control import GatewayControl
from .lanes.local import LocalLink
from .limits import DEFAULT, Limits
from .lobby import Lobby
from .room import Room, RoomSettings
from .shared import lanes
from .shared.listen import ACCEPT_BACKLOG
from .shared.osthread import name_os_thread
from .sim import SimPool
from .storage.datadir import Storage, StorageOff
from .storage.index import PRUNE_BATCH, ReplayIndex, Retention, access_key, owner_key
from .storage.recorder import Recording, spool_dir_for
from .ws import Connection, WsEndpoint

log = logging.getLogger("clothball.server")

WEB_DIR = ASSETS / "web"
LOBBY_PUSH_S = 0.5  # how often lobby clients' room list is checked for changes
PRUNE_PAUSE_S = 0.05  # s between batches of a pruning backlog (saves and checks go between)
SHOW_ROOM_TRIES = 8  # ids the show room's claim tries (main, main-<host>, then random ones)

@dataclass(frozen=True)
class ServerConfig:
    """What a ``GameServer`` is made with: ``clothball host``'s options, and what the tests
    and benches set."""

    data_dir: Path | str
    scenes: dict[str, Scene] | None = None  # None: the classic scene alone
    backend: str = "auto"
    host: str = "127.0.0.1"
    port: int = 8765
    bots: int = 0  # in the host's own room (0..4)
    room_settings: RoomSettings | None = None  # of the host's own room
    default_room: bool = True  # the host's own room, "main"
    web_dir: Path | None = None
    hello_timeout: float | None = None  # overrides limits.hello_timeout
    limits: Limits | None = None
    origins: tuple[str, ...] | None = None  # websocket Origin allow-list (None: any)
    host_token: str | None = None  # the host's credential (None: a new one, kept on disk)
    trusted_proxies: tuple[Any, ...] = ()  # peers whose X-Forwarded-For names the client
    # The engine of a host of several processes (`clothball host --workers`,
    # docs/architecture.md): its gateways listen on the public port (the port players are
    # given) and bring every connection here through the Unix socket ``engine_socket``.
    public_port: int | None = None
    engine_socket: Path | None = None
    # One of several hosts of a cluster: the address this host is reached at, its id, and
    # the replay index in PostgreSQL (its rows name this host by its HTTP address).
    advertise: str | None = None
    host_id: str | None = None
    db: str | None = None


class GameServer:
    """The clothball server. ``await start()``, then ``await stop()`` (or ``run_forever``).
    ``directory``: the rooms' directory it shares with other processes or hosts;
    ``bot_factory``: how its bots are made (tests)."""

    def __init__(self, config: ServerConfig, *, directory: Directory | None = None,
                 bot_factory: Callable[..., Any] | None = None) -> None:
        c = config
        self.config = c
        scenes = c.scenes if c.scenes is not None else {"classic": Scene.load("classic")}
        backend = c.backend
        self.scenes = scenes
        self.backend = backend
        self.host = c.host
        self.port = c.port
        self.bots = max(0, min(4, c.bots))
        self.room_settings = c.room_settings
        self.default_room = c.default_room
        self.web_dir = c.web_dir or WEB_DIR
        self.data_dir = Path(c.data_dir)
        self.epoch = time.perf_counter()
        self.directory = directory
        self.public_port = c.public_port
        self.engine_socket = c.engine_socket
        self.advertise = c.advertise
        self.host_id = c.host_id or secrets.token_hex(6)
        self._own: Gateway | None = None  # its own port's gateway, in this process
        self._control: GatewayControl | None = None  # the gateways' control socket
        self.limits = c.limits or DEFAULT
        if c.hello_timeout is not None:
            self.limits = self.limits.replace(hello_timeout=c.hello_timeout)
        self.origins = c.origins
        # The host's own credential (/api/stats?reset=1), kept in DATA/host-token, which
        # only the host's account can read (see _share_host_token).
        self.host_token = c.host_token or secrets.token_urlsafe(24)
        self._token_given = c.host_token is not None
        # Peers whose X-Forwarded-For names the client (limits.parse_trusted_proxies), and
        # the key in the URL of the server's own bots (their connections take no slot).
        self.trusted_proxies = c.trusted_proxies
        self.house_key = secrets.token_urlsafe(16)
        # A data directory that cannot be written does not stop the game: matches go on
        # without recording, stored rounds are served if they can be read, every place
        # that would show replays says why, and recording resumes once it can.
        lim = self.limits
        # ``db``: the replay index in PostgreSQL, shared by a cluster's hosts; its rows name
        # this host by its HTTP address, known once it listens (``start``).
        self.storage = Storage(self.data_dir, retention=Retention.from_limits(lim),
                               min_free_bytes=int(lim.storage_min_free_mib * 2**20), db=c.db,
                               retry_s=lim.storage_check_s)
        if c.db is None:
            self.storage.check_now()
        # Every room of a scene is a slot of that scene's worker: one call steps them all.
        self.sims = SimPool(epoch=self.epoch, spool_dir=spool_dir_for(self.data_dir))
        # The Unix socket every connection comes in by: the host's (engine_socket, shared
        # with its gateway processes), else one of its own in a private directory.
        self.socket_path = c.engine_socket
        self._share_host_token()
        self.lobby = Lobby(scenes, self, backend=backend, max_rooms=self.limits.max_rooms,
                           sims=self.sims, hooks=_LobbyHooks(self))
        # Admission control: the server's own measure of what more it can run.
        self.headroom = Headroom(self.sims, lim.admit_lateness_ms, load=lim.admit_load,
                                 cores=lim.admit_cores, backend=backend)
        # Every directory call runs on these threads, bounded by IO_TIMEOUT_S: a hung store
        # never holds the event loop (joins wait for a read made for all of them at once).
        self._dir_pool = ThreadPoolExecutor(3, thread_name_prefix="directory",
                                            initializer=name_os_thread)
        self._reads = OnDemand(self._read_directory, MIN_READ_GAP_S)
        self._publications = OnDemand(self._publish_rooms)
        self.clients: set[Conn] = set()
        self.per_address: collections.Counter[str] = collections.Counter()
        self._server: Server | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._saves: set[asyncio.Task[Any]] = set()
        self._bot_factory = bot_factory
        self.main_room: Room | None = None
        # /healthz answers 200 only while this is set: from the end of ``start`` (every
        # room the host starts with open and joinable) to the start of ``stop``. It listens
        # earlier (its bots need the port), so a probe must not take listening for ready.
        self.ready = False
        self.stats = {"messages_in": 0, "messages_out": 0, "lane_messages_in": 0,
                      "lane_messages_out": 0, "bad_messages": 0, "rounds_saved": 0,
                      "rounds_not_saved": 0, "refused_connections": 0, "rooms_stopped": 0,
                      "slow_drops": 0}
        # Its own port (the public port of one process; its bots' beside gateways) is
        # served by a gateway in this process, relaying to its Unix socket like any other
        # gateway: one data plane, the native pump's lanes, for every client
        # (docs/architecture.md). Its lanes read the frame loops' memory in place.
        self.lane_link = LocalLink(self.sims.local_shares, self.sims.set_wake, self.stats)
        self._cpu0 = time.process_time()
        self._wall0 = time.perf_counter()
        self.http = HttpSurface(self)
        self.ws = WsEndpoint(self)

    # --- life -----------------------------------------------------------------------------
    async def start(self) -> tuple[str, int]:
        """Listen and open the main room. A failure to listen (``OSError``: port taken,
        address not here) closes the replay index it opened, so nothing is left open."""
        try:
            if self.socket_path is None:
                self.socket_path = Path(tempfile.mkdtemp(prefix="clothball-engine-")) \
                    / "engine.sock"
            self._server = await self._listen_gateways(self.socket_path)
            if self.engine_socket is not None:
                self._control = GatewayControl(lanes.ctl_path(self.engine_socket),
                                               self.sims.shares, self.stats,
                                               self.sims.set_wake)
                await self._control.start()
            self._own = Gateway(self.host, self.port, self.socket_path, link=self.lane_link,
                                reuse_port=False, slow_drop_s=self.limits.slow_drop_s,
                                send_buffer=self.limits.socket_send_buffer)
            await self._own.start()
        except BaseException:
            await self._close_listeners()
            self.storage.close()
            raise
        assert self._own.server is not None
        sock = next(iter(self._own.server.sockets))
        self.port = sock.getsockname()[1]
        # What a room of each scene costs here, for admission (a fraction of a second).
        await asyncio.to_thread(self.headroom.measure, self.scenes.values())
        if self.storage.db is not None:
            self.storage.host_url = self.advertised_http_url
            await self.storage.check()
        main_id = "main"
        if self.directory is not None:
            self.lobby.me = HostEntry(self.host_id, self.advertised_url)
            await self._publish()
            if self.default_room:
                main_id = await self._claim_show_room()
        if self.default_room:
            settings = self.room_settings or RoomSettings(autoplay=True)
            self.main_room = self.lobby.create("main", public=True, settings=settings,
                                               permanent=True, room_id=main_id)
            for _ in range(self.bots):
                self.main_room.add_bot(None, settings.bot_difficulty)
        if self.directory is not None:
            await self._publish()  # the others know this process before anyone is sent here
            self._spawn(self._publish_forever())
        self._spawn(self._housekeeping())
        self._spawn(self._push_room_lists())
        self._spawn(self._watch_storage())
        self._spawn(self._watch_headroom())
        self._spawn(self.ws.sweep_idle())
        self.ready = True
        return self.host, self.port

    async def _claim_show_room(self) -> str:
        """The show room's id, claimed in the directory before the room exists: ``main``,
        else (another host's show room is ``main``) ``main-<suffix>``; a claim lost to a
        host started at the same moment picks another id and tries again. The store away:
        ``main`` unclaimed (its publication claims it, or logs the conflict)."""
        directory = self.directory
        assert directory is not None
        for k in range(SHOW_ROOM_TRIES):
            rid = "main" if k == 0 else f"main-{self.host_id[-4:]}" if k == 1 else \
                f"main-{secrets.token_hex(3)}"
            try:
                if await self._dir(directory.claim, rid, self.host_id):
                    return rid
            except Exception as e:
                log.warning("the show room's id could not be claimed (%s): it is main",
                            type(e).__name__)
                return "main"
        raise RuntimeError(f"no free id for the show room after {SHOW_ROOM_TRIES} claims")

    async def _listen_gateways(self, path: Path) -> Server:
        """The Unix socket the host's gateways connect to (one connection per client),
        in a directory only this account can enter; a socket left by an engine that died
        is replaced."""
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        srv = await self._listen(path=str(path), unix=True)
        os.chmod(path, 0o600)
        return srv

    async def _close_listeners(self) -> None:
        """Its own gateway (every connection through it cut), the control socket, the
        Unix socket's listener (its connections closed) and its directory."""
        own, self._own = self._own, None
        if own is not None:
            await own.stop()
        control, self._control = self._control, None
        if control is not None:
            await control.stop()
        if self._server is not None:
            self._server.close(close_connections=True)
            await self._server.wait_closed()
        if self.socket_path is not None:
            # Its directory too (made for this run), so that a host killed with SIGKILL,
            # whose engine stops on the kernel's SIGTERM, leaves nothing behind.
            with contextlib.suppress(OSError):
                self.socket_path.unlink()
                self.socket_path.parent.rmdir()

    async def _listen(self, **extra: Any) -> Server:
        return await serve(
            self.ws.handler, process_request=self.http.process_request,
            max_size=self.limits.max_message_bytes, max_queue=64, compression=None,
            create_connection=Connection,
            ping_interval=self.limits.ping_interval, ping_timeout=self.limits.ping_timeout,
            close_timeout=2,
            open_timeout=None,  # Connection bounds its own handshake (server.ws)
            backlog=ACCEPT_BACKLOG,  # a burst of connections waits to be accepted (issue 43)
            **extra,
        )

    async def _dir(self, fn: Callable[..., Any], *args: Any, timeout: float = 3 * IO_TIMEOUT_S
                   ) -> Any:
        """``fn(*args)`` on a directory thread; ``TimeoutError`` after ``timeout`` s (the
        store's own socket timeout ends the call itself soon after)."""
        fut = asyncio.get_running_loop().run_in_executor(self._dir_pool, fn, *args)
        # Not wait_for: on 3.11 it swallows a cancellation that meets a finished call, and
        # the server's stop would wait for the publishing task for ever.
        async with asyncio.timeout(timeout):
            return await fut

    async def _publish(self) -> None:
        """This process's rooms and load to the directory; everyone's back."""
        assert self.directory is not None and self.lobby.me is not None
        me = self.lobby.me
        me.rooms, me.clients = len(self.lobby.rooms), len(self.clients)
        try:
            await self._dir(self.directory.publish, me, self.lobby.published())
            self.lobby.peers = await self._dir(self.directory.read)
        except Exception as e:  # the store is away: keep the rooms running, say so
            if self.lobby.directory_error is None:
                log.warning("room directory unavailable (%s); listing this process's rooms "
                            "only until it is back", type(e).__name__ if
                            isinstance(e, TimeoutError) else e)
            self.lobby.peers = None
            self.lobby.directory_error = (f"the cluster's room directory is unavailable "
                                          f"({type(e).__name__}); only this host's rooms "
                                          "are listed")
            return
        if self.lobby.directory_error is not None:
            log.info("room directory back: registered again")
            self.lobby.directory_error = None

    async def _publish_rooms(self) -> None:
        me = self.lobby.me
        if self.directory is None or me is None or self.lobby.directory_error is not None:
            return
        me.rooms, me.clients = len(self.lobby.rooms), len(self.clients)
        await self._dir(self.directory.publish, me, self.lobby.published())

    def _publish_now(self) -> Awaitable[bool] | None:
        """This process's rooms to the directory soon (a new room is there before its id is
        given out: the reply waits for this, the event loop does not); None while the
        directory is away (the periodic publication reports it and retries)."""
        if self.directory is None or self.lobby.me is None or \
                self.lobby.directory_error is not None:
            return None
        return asyncio.ensure_future(self._publications.after_now(3 * IO_TIMEOUT_S))

    async def _read_directory(self) -> None:
        """A fresh view of the directory, for the joins that wait for one."""
        if self.directory is None or self.lobby.directory_error is not None:
            return  # away: the periodic publication finds it again
        self.lobby.peers = await self._dir(self.directory.read)

    async def _publish_forever(self) -> None:
        changes = None
        next_at = asyncio.get_running_loop().time()
        while True:
            if changes is None and hasattr(self.directory, "changes"):
                try:  # another host's rooms changed: read at once, not at the next tick
                    changes = await self._dir(self.directory.changes)
                except Exception:
                    changes = None
            next_at += PUBLISH_S
            wait = next_at - asyncio.get_running_loop().time()
            if changes is not None and wait > 0:
                try:
                    msg = await self._dir(functools.partial(changes.get_message, timeout=wait),
                                          timeout=wait + IO_TIMEOUT_S)
                except Exception:
                    changes, msg = None, None
                if msg is not None and self.lobby.peers is not None:
                    with contextlib.suppress(Exception):
                        self.lobby.peers = await self._dir(self.directory.read)
                    continue
            elif wait > 0:
                await asyncio.sleep(wait)
            if asyncio.get_running_loop().time() - next_at > PUBLISH_S:
                next_at = asyncio.get_running_loop().time()  # fell behind: no burst
            await self._publish()

    def _url(self, port: int) -> str:
        host = self.host if self.host not in ("0.0.0.0", "::", "") else "127.0.0.1"
        if ":" in host:
            host = f"[{host}]"
        return f"ws://{host}:{port}/ws"

    @property
    def ws_url(self) -> str:
        """The address players are given: the gateways' public port when there is one."""
        return self._url(self.public_port if self.public_port is not None else self.port)

    @property
    def advertised_url(self) -> str:
        """The address other hosts of a cluster give out for this host's rooms:
        ``advertise``, else the address players are given here."""
        return self.advertise or self.ws_url

    @property
    def own_url(self) -> str:
        """This process's own listening address (its bots connect there; with gateways,
        no client is ever given it)."""
        return self._url(self.port)

    @property
    def advertised_http_url(self) -> str:
        """The HTTP address of ``advertised_url`` (where other hosts send this host's
        replay downloads)."""
        parts = urllib.parse.urlsplit(self.advertised_url)
        scheme = "https" if parts.scheme == "wss" else "http"
        return urllib.parse.urlunsplit((scheme, parts.netloc, "", "", ""))

    @property
    def http_url(self) -> str:
        return self.ws_url.replace("ws://", "http://", 1)[: -len("/ws")] + "/"

    async def stop(self) -> None:
        """Stop accepting, close every connection and room, finish the writes under way."""
        self.ready = False
        self.http.abort_downloads()
        own, self._own = self._own, None
        if own is not None:
            await own.stop()  # (its pump: every client's connection through it cut at once)
        if self._server is not None:
            self._server.close(close_connections=True)
        for t in list(self._tasks):
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self._close_listeners()
        if self.directory is not None:
            self._reads.cancel()
            self._publications.cancel()
            try:
                await self._dir(self.directory.withdraw, self.host_id)
            except Exception as e:
                log.warning("could not leave the room directory: %s", e)
        self._dir_pool.shutdown(wait=False)
        await self.lobby.close()
        await self.lane_link.stop()  # (after the pump: the frame loops outlive it)
        await asyncio.to_thread(self.sims.close)
        if self._saves:
            await asyncio.gather(*self._saves, return_exceptions=True)
        self.http.close()
        self.storage.close()

    def _share_host_token(self) -> None:
        """DATA/host-token holds the token: made by the first server of the data directory
        and read by the others (the processes of ``--workers``, later restarts), so one
        token works whichever process answers; a token given to this server replaces it.
        Delete the file for a new token at the next start."""
        path = self.data_dir / "host-token"
        self.host_token_file: Path | None = None  # where the token is kept, once it is
        if not self._token_given:
            with contextlib.suppress(OSError, UnicodeError):
                found = path.read_text().strip()
                if len(found) >= 32:
                    self.host_token, self.host_token_file = found, path
                    return
        tmp = path.with_name(f".host-token-{os.getpid()}")
        try:
            # With --db nothing else has made the data directory yet (SQLite's check does).
            self.data_dir.mkdir(parents=True, exist_ok=True)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as f:
                os.fchmod(f.fileno(), 0o600)
                f.write(self.host_token + "\n")
            if self._token_given:
                os.replace(tmp, path)
            else:
                try:
                    os.link(tmp, path)  # only if no other process made it meanwhile
                except FileExistsError:
                    found = path.read_text().strip()
                    if len(found) >= 32:
                        self.host_token = found
                    else:  # damaged: ours replaces it
                        os.replace(tmp, path)
            self.host_token_file = path
        except (OSError, UnicodeError) as e:
            log.warning("the host token could not be kept in %s (%s): statistics can be "
                        "reset only by a GameServer given host_token", path,
                        getattr(e, "strerror", None) or e)
        finally:
            with contextlib.suppress(OSError):  # never made, on a directory that is not
                tmp.unlink(missing_ok=True)

    def _spawn(self, coro: Any) -> asyncio.Task[Any]:
        t = asyncio.create_task(coro)
        self._tasks.add(t)
        t.add_done_callback(self._tasks.discard)
        return t

    async def _housekeeping(self) -> None:
        while True:
            await asyncio.sleep(1.0)
            await self.lobby.close_idle(asyncio.get_running_loop().time(),
                                        self.limits.room_idle_close_s)

    @property
    def store(self) -> ReplayIndex | None:
        """The replay index, when stored rounds can be read (see ``recording_error``)."""
        return self.storage.store

    @property
    def recording_error(self) -> str | None:
        """Why rounds are not being recorded now (one line), or None."""
        return self.storage.problem

    async def _watch_headroom(self) -> None:
        while True:
            await asyncio.sleep(WINDOW_S)
            self.headroom.sample(r.scene for r in self.lobby.rooms.values() if not r.sim.asleep)
            if self.lobby.me is not None:
                # Busy for the others' placement: no room of its default scene fits here.
                scene = self.scenes[self.lobby.default_scene]
                self.lobby.me.busy = self.lobby.hooks.admit(scene) is not None

    async def _watch_storage(self) -> None:
        """The data directory looked at again and again: problems named as they come,
        recording resumed as they go (``server.storage.datadir.Storage``); the rounds retention
        does not keep pruned in batches, so a large backlog never holds up a request."""
        while True:
            while await self.storage.prune_some() >= PRUNE_BATCH:
                await asyncio.sleep(PRUNE_PAUSE_S)
            await asyncio.sleep(self.limits.storage_check_s)
            await self.storage.check()

    async def _push_room_lists(self) -> None:
        """Lobby clients get the public room list again whenever it changes (rooms opened or
        closed, seats, phases, scores); the frame counter alone is not a change."""
        def key(rooms: list[dict[str, Any]]) -> str:
            return json.dumps([{**r, "frame": 0} for r in rooms], sort_keys=True)

        last = key(self.lobby.rooms_message()["rooms"])
        while True:
            await asyncio.sleep(LOBBY_PUSH_S)
            msg = self.lobby.rooms_message()
            now = key(msg["rooms"]) + str(msg.get("directory_error")) + \
                str(msg.get("replay_index_error"))
            if now == last:
                continue
            last = now
            for c in self.clients:
                if c.role == "lobby" and c.hello_done:
                    c.send_json(msg)

    # --- RoomHost -------------------------------------------------------------------------
    def spawn_bot(self, room: Room, seat: int, token: str, difficulty: float) -> None:
        factory = self._bot_factory
        if factory is None:
            from ..game.bots import run_bot

            factory = run_bot
        self._spawn(factory(f"{self.own_url}?house={self.house_key}", room.id, token, difficulty))

    def room_stopped(self, room: Room, reason: str) -> None:
        """A room's simulation failed: it leaves the lobby; the other rooms run on."""
        self.stats["rooms_stopped"] += 1
        log.error("room %s stopped: %s", room.id, reason)
        if self.lobby.rooms.get(room.id) is room:
            self._spawn(self.lobby.remove(room.id))

    def save_round(self, header: dict[str, Any], records: Recording) -> None:
        room = self.lobby.rooms.get(header["room_id"])
        if room is not None and room.code is not None:
            # A private room's rounds are listed and served only to holders of its code.
            header = {**header, "access": access_key(room.id, room.code)}
        address = self.lobby.addresses.get(header["room_id"])
        if address is not None:  # its creator's rounds share one quota (Retention)
            header = {**header, "owner": owner_key(address)}

        def failed(reason: str) -> None:
            self.stats["rounds_not_saved"] += 1
            r = self.lobby.rooms.get(header["room_id"])
            if r is not None:
                r.event("replay_failed", id=header.get("id"), round=header.get("round"),
                        reason=reason)

        async def save() -> None:
            try:
                row = await self.storage.save(header, records)  # type: ignore[arg-type]
            except StorageOff as e:
                # Disk full, read-only, gone, locked: this round is lost (or, locked, kept
                # as a file to be indexed), the match goes on.
                log.warning("round %s not recorded: %s", header.get("id"), e)
                failed(str(e))
                return
            except Exception as e:  # pragma: no cover - a bug must not stop the match
                log.exception("could not save round %s", header.get("id"))
                failed(f"could not write the replay: {e}")
                return
            self.stats["rounds_saved"] += 1
            r = self.lobby.rooms.get(header["room_id"])
            if r is not None:
                r.event("replay_saved", id=row["id"], round=row["round"], bytes=row["bytes"])

        async def save_and_clean() -> None:
            try:
                if records.error is not None and self.recording_error is None:
                    # The disk refused the round as it was made (else storage says why).
                    log.warning("round %s not recorded: %s", header.get("id"), records.error)
                    failed(f"could not write the replay: {records.error}")
                    return
                await save()
            finally:
                records.discard()  # the spool, saved into the replay file or not

        t = asyncio.create_task(save_and_clean())
        self._saves.add(t)
        t.add_done_callback(self._saves.discard)

    def stats_snapshot(self) -> dict[str, Any]:
        rooms = {}
        made: dict[tuple[int, int], dict[str, float]] = {}  # (Samples.key)
        for rid, room in self.lobby.rooms.items():
            if not room.public:  # public endpoint: private rooms are nobody else's business
                continue
            st = room.sim.stats
            key = st.lateness.key()
            if key not in made:
                made[key] = _percentiles(st.lateness.newest() * 1e3)
            rooms[rid] = {
                "frames": st.frames, "steps": st.steps, "skipped_frames": st.skipped_frames,
                "meshes": st.meshes, "substeps": room.sim.substeps,
                "backend": room.sim.backend, "n": room.scene.n,
                "lateness_ms": made[key],
            }
        return {
            "uptime_s": time.perf_counter() - self._wall0,
            "recording": "on" if self.recording_error is None else
                         f"off: {self.recording_error}",
            "replay_index": "ok" if self.storage.index_error is None else
                            f"unavailable: {self.storage.index_error}",
            "storage": self.storage_snapshot(),
            "cpu_s": time.process_time() - self._cpu0,
            "clients": len(self.clients),
            "headroom": {**vars(self.headroom.last), "busy": self.headroom.busy,
                         "outside": self.headroom.outside, "cores": self.headroom.cores,
                         "load": self.headroom.load,
                         "room_cost": {n: self.headroom.cost(s) for n, s in self.scenes.items()},
                         "thread_cost": {n: self.headroom.thread_cost(s)
                                         for n, s in self.scenes.items()}},
            **self.stats,
            "messages_out": self.stats["messages_out"] + sum(c.sent for c in self.clients),
            "rooms": rooms,
        }


    def storage_snapshot(self) -> dict[str, Any]:
        """The replay store's use of the disk against its retention (no I/O: the counts as
        of its last write)."""
        r = Retention.from_limits(self.limits)
        out: dict[str, Any] = {"max_bytes": r.max_bytes, "max_days": r.max_age_s / 86400,
                               "state": self.storage.kind or "ok",
                               "free_bytes": self.storage.free_bytes,
                               "index_retry": self.storage.retry.state()}
        if self.store is not None:
            out.update(rounds=self.store.rounds, bytes=self.store.bytes)
        return out


def _percentiles(values: np.ndarray) -> dict[str, float]:
    if values.size == 0:
        return {"count": 0}
    p50, p99, p999 = np.percentile(values, [50, 99, 99.9])
    return {"count": int(values.size), "p50": float(p50), "p99": float(p99),
            "p999": float(p999), "max": float(values.max()),
            "mean": float(values.mean()) if math.isfinite(values.mean()) else 0.0}


def default_data_dir() -> Path:
    import platformdirs

    return Path(os.environ.get("CLOTHBALL_DATA") or platformdirs.user_data_dir("clothball"))


__all__ = ["GameServer", "default_data_dir"]


class _LobbyHooks:
    """The server's answers to its lobby (``server.lobby.LobbyHooks``)."""

    def __init__(self, srv: GameServer) -> None:
        self._srv = srv

    def busy(self) -> str | None:
        return self._srv.headroom.busy

    def admit(self, scene: Scene) -> str | None:
        return self._srv.headroom.refusal(scene,
                                          [r.scene for r in self._srv.lobby.rooms.values()])

    def fresh_view(self) -> Awaitable[bool]:
        return self._srv._reads.after_now(IO_TIMEOUT_S)

    def publish_now(self) -> Awaitable[bool] | None:
        return self._srv._publish_now()

    def index_error(self) -> str | None:
        return self._srv.storage.index_error
