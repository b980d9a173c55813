"""One client connection: its sender of control messages, rate limits and error replies.

Outgoing control messages (JSON: replies, room state, events) wait in a bounded FIFO; a
client that lets it fill up (``Limits.max_control_queue``) is too slow and is dropped.

Its binary messages never pass here: every client comes through a gateway (a gateway
process, or the engine's own port's, in this process), whose native pump serves its lane
(``server.shared.lanes``: the seat's hand in, its CORNER at ``corner_rate`` and its room's
MESH out, from the frame loop's memory), opened by a lane message in its stream
(``open_lane``).

A single sender task writes the control messages, waiting for the socket to drain. A
client whose socket stays backed up for ``Limits.slow_drop_s`` seconds is dropped. Every
number here is a ``server.limits.Limits`` field (``docs/security.md``).
"""

from __future__ import annotations

import asyncio
import collections
import ipaddress
import logging
import secrets
import time
from typing import TYPE_CHECKING, Any

from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed

from ..game.net.tap import TapConnection
from ..game.wire import protocol as P
from .limits import DEFAULT, Limits
from .shared.bucket import TokenBucket
from .shared.lanes import LaneSpec, lane_message

if TYPE_CHECKING:
    from .room import Room

log = logging.getLogger("clothball.server")

CLOSE_WAIT_S = 2.0  # a dropped client's closing handshake gets this long


def client_address(peer: str, forwarded_for: str | None,
                   trusted: tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...]) -> str:
    """The client's address: the socket's ``peer``, or, when the peer is a trusted proxy,
    the nearest address in its ``X-Forwarded-For`` that is not itself a trusted proxy
    (entries to the left of that one were written by the client and prove nothing)."""
    if not trusted or forwarded_for is None or not _within(peer, trusted):
        return peer
    for entry in reversed(forwarded_for.split(",")):
        entry = entry.strip()
        try:
            ip = ipaddress.ip_address(entry)
        except ValueError:
            return peer  # not an address: a proxy that does not say who its client is
        if not _within(str(ip), trusted):
            return str(ip)
    return peer


def _within(address: str, nets: tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...]
            ) -> bool:
    try:
        ip = ipaddress.ip_address(address)
    except ValueError:
        return False
    return any(ip in n for n in nets)


class Conn:
    """A websocket client of the server (lobby, player or spectator)."""

    def __init__(self, ws: ServerConnection, limits: Limits = DEFAULT, *,
                 address: str | None = None, house: bool = False,
                 own_gateway: bool = False) -> None:
        """``address``: the client's, where a trusted proxy forwarded it (else the
        socket's peer); ``house``: one of the server's own bots (no per-address slot);
        ``own_gateway``: it came through the engine's own port's gateway (in this
        process: its lanes read the frame loops' memory whether or not it is shared)."""
        self.id = secrets.token_urlsafe(6)
        self.ws = ws
        # Its transport, for the backlog checks and a cut.
        self.transport: Any = ws.stream if isinstance(ws, TapConnection) else None
        self.limits = limits
        addr = ws.remote_address
        self.address: str = address or (str(addr[0]) if addr else "?")
        self.house = house
        self.last_in = time.monotonic()  # its last control message other than a ping
        self.role = "lobby"  # "lobby", "player", "spectator"
        self.room: Room | None = None
        self.seat: int | None = None
        self.name = "guest"
        self.want_mesh = True
        self.corner_interval = 0.0  # s between CORNER messages (client's corner_rate)
        # Its gateway serves lanes (server.shared.lanes), in memory it can map.
        self.gateway_lanes = bool(getattr(ws, "lanes", False))
        self.own_gateway = own_gateway
        self.relayed_lane = False  # its gateway serves its lane
        self.hello_done = False
        self.closed = False
        self._control: collections.deque[str] = collections.deque()
        self._wake = asyncio.Event()
        self.control_bucket = TokenBucket(limits.control_rate, limits.control_burst)
        self.binary_bucket = TokenBucket(limits.binary_rate, limits.binary_burst)
        self.error_bucket = TokenBucket(limits.error_rate, limits.error_burst)
        self.errors_suppressed = 0
        self.rate_drops: collections.deque[float] = collections.deque()
        self.sent = 0
        self.received = 0
        self._backed_up_since: float | None = None
        self._sending_since: float | None = None
        self._closing: asyncio.Future[None] | None = None
        self._sender = asyncio.create_task(self._send_loop())

    # --- offering data --------------------------------------------------------------------
    def send_json(self, msg: dict[str, Any]) -> None:
        if self.closed:
            return
        if len(self._control) >= self.limits.max_control_queue:
            self.drop("too slow: control messages are not being read")
            return
        self._control.append(P.encode_json(msg))
        self._wake.set()

    def stuck(self) -> bool:
        """A message has waited on its socket past ``slow_drop_s``: dropped (True)."""
        since = self._sending_since
        if since is not None and time.monotonic() - since > self.limits.slow_drop_s:
            self.drop("too slow: one message has waited for the socket too long")
            return True
        return False

    def open_lane(self, spec: LaneSpec | None, shared: bool) -> None:
        """Its lane from now on (None: none), served by its gateway's pump: a lane message
        in its stream. A gateway process maps the room's memory only where it is
        ``shared`` (a memfd); the engine's own gateway reads it in place. Where neither
        can, it has no lane: its HIPs reach the room (``Room.on_hip``), and it gets no
        CORNER or MESH (a host whose file size limit keeps the memory from being shared
        runs one process: ``clothball host``)."""
        if spec is not None and self.gateway_lanes and (shared or self.own_gateway):
            self.relayed_lane = True
            self.send_json(lane_message(spec))
            return
        if self.relayed_lane:
            self.relayed_lane = False
            self.send_json(lane_message(None))

    def error(self, err: P.ProtocolError | str, message: str = "", re: object = None) -> None:
        """Send an error reply, unless this client has had too many lately."""
        if isinstance(err, P.ProtocolError):
            code, message = err.code, err.message
        else:
            code = err
        if not self.error_bucket.take():
            self.errors_suppressed += 1
            return
        msg = P.error_message(code, message, re)
        if self.errors_suppressed:
            msg["suppressed"] = self.errors_suppressed
            self.errors_suppressed = 0
        self.send_json(msg)

    def rate_dropped(self) -> bool:
        """Count a message dropped for rate; True when the client should be disconnected."""
        now = time.monotonic()
        self.rate_drops.append(now)
        while self.rate_drops and self.rate_drops[0] < now - self.limits.abuse_window:
            self.rate_drops.popleft()
        return len(self.rate_drops) > self.limits.abuse_drops

    # --- sending --------------------------------------------------------------------------
    async def _send_loop(self) -> None:
        ws = self.ws
        try:
            while True:
                await self._wake.wait()
                self._wake.clear()
                while self._control:
                    msg = self._control.popleft()
                    self._sending_since = time.monotonic()
                    await ws.send(msg)
                    self._sending_since = None
                    self.sent += 1
                    self._check_backlog()
        except ConnectionClosed:
            pass
        except asyncio.CancelledError:
            raise
        except Exception:  # pragma: no cover - a sender bug must not kill the server
            log.exception("sender for client %s failed", self.id)
        self.closed = True

    def _check_backlog(self) -> None:
        transport = self.transport
        if transport is None:
            return
        if transport.get_write_buffer_size() > self.limits.max_write_buffer:
            now = time.monotonic()
            if self._backed_up_since is None:
                self._backed_up_since = now
            elif now - self._backed_up_since > self.limits.slow_drop_s:
                self.drop("too slow: the connection has been backed up too long")
        else:
            self._backed_up_since = None

    def drop(self, reason: str) -> None:
        """Close the connection (policy violation), without waiting."""
        if self.closed:
            return
        self.closed = True
        log.info("dropping client %s: %s", self.id, reason)
        self._closing = asyncio.ensure_future(self._close(1008, reason[:120]))

    def fail(self, reason: str) -> None:
        """Close the connection as a failing handler would (1011), without waiting."""
        if self.closed:
            return
        self.closed = True
        self._closing = asyncio.ensure_future(self._close(1011, reason[:120]))

    def kicked(self, reason: str) -> None:
        if self.closed:
            return
        self.closed = True
        self._closing = asyncio.ensure_future(self._close(4000, reason[:120]))

    async def _close(self, code: int, reason: str) -> None:
        # A client that stopped reading blocks the sender inside ws.send, which holds the
        # connection's send lock that a clean close needs: bound the wait, then cut it.
        try:
            await asyncio.wait_for(self.ws.close(code, reason), CLOSE_WAIT_S)
        except Exception:
            pass
        finally:
            if self.transport is not None and not self.transport.is_closing():
                self.transport.abort()

    async def finish(self) -> None:
        self.open_lane(None, False)
        if self._closing is not None:
            # The close code and reason go out before the handler returns (which would
            # close the connection as a normal 1000).
            await asyncio.gather(self._closing, return_exceptions=True)
        self.closed = True
        self._sender.cancel()
        try:
            await self._sender
        except (asyncio.CancelledError, Exception):
            pass
