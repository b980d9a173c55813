"""The websocket client on its own thread, handing frames to the render thread.

pyglet runs its own loop on the main thread; the network runs an asyncio loop on a
daemon thread (``NetThread``) with ``game.net.client.NetClient``. Neither waits for the
other:

* JSON messages go through a ``queue.SimpleQueue`` (never blocks); the window drains it
  each tick and applies them to its ``ClientModel``.
* MESH frames are decoded on the network thread into ``interp.MeshFrame`` and put in a
  short bounded ``FrameInbox`` (a lock held for an append or a swap; the oldest frames
  fall off if the window stalls), so the window's interpolation buffer sees every frame
  that arrived, not only the newest.
* CORNER state goes into a ``Latest`` slot (latest wins) and straight to the device
  (``update_corner``: the Falcon renders its force from it).
* The hand position is read from the device by the network thread at ``hip_rate`` and
  sent as HIP; the window only moves the mouse device.
* Requests from the window (join, ready, create a room...) are coroutines scheduled on
  the network loop; they return ``concurrent.futures.Future``s the window polls.

A dropped connection is retried with the seat's reconnect token (the server holds the
seat for a grace period); the state is reported as ``{"type": "_status"}`` messages.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Coroutine
from typing import Any, Generic, TypeVar

from ..devices.base import CornerState, Device
from ..net.client import NetClient, ServerError, explain_connect_error
from ..wire import protocol as P
from .interp import MeshFrame

log = logging.getLogger("clothball.client")

T = TypeVar("T")


class Latest(Generic[T]):
    """A one-value slot: ``put`` replaces, ``get`` reads the newest (never blocks long)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._value: T | None = None
        self._version = 0

    def put(self, value: T) -> None:
        with self._lock:
            self._value = value
            self._version += 1

    def get(self) -> tuple[T | None, int]:
        """The newest value and its version (bumped by every ``put``)."""
        with self._lock:
            return self._value, self._version


class FrameInbox:
    """Frames from the network thread, taken in order by the window (bounded)."""

    def __init__(self, maxlen: int = 16) -> None:
        self._lock = threading.Lock()
        self._items: collections.deque[tuple[MeshFrame, float]] = collections.deque(
            maxlen=maxlen)
        self.total = 0

    def put(self, frame: MeshFrame, received_at: float) -> None:
        with self._lock:
            self._items.append((frame, received_at))
            self.total += 1

    def take_all(self) -> list[tuple[MeshFrame, float]]:
        with self._lock:
            items, self._items = list(self._items), collections.deque(maxlen=self._items.maxlen)
        return items


class NetThread:
    """A connection to a clothball server, run on its own thread."""

    def __init__(self, url: str, name: str = "player", device: Device | None = None, *,
                 corner_rate: float = 120.0, hip_rate: float = 120.0,
                 ping_interval: float = 1.0, reconnect_tries: int = 5,
                 clock: Callable[[], float] = time.perf_counter,
                 report: Callable[[str], None] | None = None) -> None:
        self.url = url
        self.name = name
        self.device = device
        self.corner_rate = corner_rate
        self.hip_rate = hip_rate
        self.ping_interval = ping_interval
        self.reconnect_tries = reconnect_tries
        self.clock = clock
        self.report = report  # called (on the network thread) with connection problems
        self._retry: asyncio.Event | None = None  # set while a failure waits for retry()
        self.messages: queue.SimpleQueue[tuple[float, dict[str, Any]]] = queue.SimpleQueue()
        self.frames = FrameInbox()
        self.corner: Latest[tuple[CornerState, P.Corner]] = Latest()
        self.hips_sent = 0
        self.last_hand: Latest[Any] = Latest()  # the hand position last sent (any device)
        self.hip_latency: float | None = None
        self.client: NetClient | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._stopping = False
        self._device_started = False
        self._join_args: dict[str, Any] | None = None
        self._hip_task: asyncio.Task[None] | None = None
        self._main: asyncio.Task[None] | None = None
        self._last_echo = 0

    # --- life (window thread) -------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="clothball-net", daemon=True)
        self._thread.start()
        self._ready.wait(10.0)

    def stop(self, timeout: float = 5.0) -> None:
        self._stopping = True
        loop = self.loop
        if loop is not None and self._main is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._main.cancel)
            except RuntimeError:
                pass
        if self._thread is not None:
            self._thread.join(timeout)
        if self.device is not None and self._device_started:
            self.device.stop()
            self._device_started = False

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def submit(self, coro: Coroutine[Any, Any, T]) -> concurrent.futures.Future[T]:
        """Run a coroutine on the network loop (from any thread)."""
        if self.loop is None:
            coro.close()
            fut: concurrent.futures.Future[T] = concurrent.futures.Future()
            fut.set_exception(ConnectionError("not connected"))
            return fut
        return asyncio.run_coroutine_threadsafe(coro, self.loop)

    # --- requests (window thread; each returns a Future of the reply) ----------------------
    def request(self, type_: str, **fields: Any) -> concurrent.futures.Future[dict[str, Any]]:
        return self.submit(self._request(type_, **fields))

    def list_rooms(self) -> concurrent.futures.Future[dict[str, Any]]:
        return self.request("list_rooms")

    def create_room(self, name: str, **settings: Any) -> concurrent.futures.Future[dict[str, Any]]:
        return self.request("create_room", name=name, **settings)

    def join(self, room: str, role: str = "player", seat: int | None = None,
             code: str | None = None) -> concurrent.futures.Future[dict[str, Any]]:
        return self.submit(self._join(room, role, seat, code))

    def leave(self) -> concurrent.futures.Future[dict[str, Any]]:
        return self.submit(self._leave())

    def ready(self, ready: bool = True) -> concurrent.futures.Future[dict[str, Any]]:
        return self.request("ready", ready=ready)

    def add_bot(self, seat: int | None = None) -> concurrent.futures.Future[dict[str, Any]]:
        fields = {} if seat is None else {"seat": seat}
        return self.request("add_bot", **fields)

    # --- the network thread ---------------------------------------------------------------
    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self.loop = loop
        asyncio.set_event_loop(loop)
        try:
            self._main = loop.create_task(self._session())
            self._ready.set()
            loop.run_until_complete(self._main)
        except asyncio.CancelledError:
            pass
        except Exception as e:  # noqa: BLE001 - told in a line, the window decides
            log.debug("network thread failed", exc_info=True)
            text = f"the connection failed: {type(e).__name__}: {e}"
            self._status("failed", text)
            self._say(text)
        finally:
            try:
                loop.run_until_complete(self._shutdown())
            finally:
                loop.close()
                self._ready.set()

    async def _shutdown(self) -> None:
        if self._hip_task is not None:
            self._hip_task.cancel()
            await asyncio.gather(self._hip_task, return_exceptions=True)
        if self.client is not None:
            try:
                await asyncio.wait_for(self.client.close(), 3.0)
            except (TimeoutError, OSError, asyncio.CancelledError):
                pass
        if self._stopping:  # otherwise the last status says why the session ended
            self._status("closed", "")

    def retry(self) -> None:
        """Connect again now (after a failure the thread waits for this)."""
        loop, event = self.loop, self._retry
        if loop is not None and event is not None and not loop.is_closed():
            loop.call_soon_threadsafe(event.set)

    async def _retry_wanted(self) -> None:
        self._retry = asyncio.Event()
        try:
            await self._retry.wait()
        finally:
            self._retry = None

    def _say(self, line: str) -> None:
        """A connection problem for the terminal (``report``), as the window shows it."""
        if self.report is not None:
            self.report(line)

    def _status(self, state: str, detail: str = "") -> None:
        self.messages.put((self.clock(), {"type": "_status", "state": state, "detail": detail}))

    async def _session(self) -> None:
        tries = 0
        while not self._stopping:
            token = self.client.token if self.client is not None else None
            try:
                self._status("connecting" if token is None else "reconnecting", self.url)
                if token is not None and self._join_args is not None:
                    client = await NetClient.connect(
                        self.url, name=self.name, role="player", token=token,
                        room=self._join_args.get("room"), corner_rate=self.corner_rate,
                        mesh=True, decode_mesh=False)
                else:
                    client = await NetClient.connect(self.url, name=self.name, role="lobby",
                                                     decode_mesh=False)
            except asyncio.CancelledError:
                raise
            except Exception as e:  # noqa: BLE001 - every failure is explained to the user
                if isinstance(e, ServerError) and e.code == "bad_token":
                    self.client, self._join_args = None, None  # the seat is gone
                    self._status("reconnecting", "the seat was given up: back to the lobby")
                    continue
                text, transient = explain_connect_error(self.url, e)
                tries += 1
                if transient and tries <= self.reconnect_tries:
                    delay = min(2.0, 0.25 * 2 ** tries)
                    self._status("retrying", f"{text} (try {tries} of "
                                             f"{self.reconnect_tries + 1}, again in {delay:g} s)")
                    if tries == 1:
                        self._say(f"{text}; retrying...")
                    await asyncio.sleep(delay)
                    continue
                self._status("failed", text)
                self._say(text if tries == 1 else f"gave up after {tries} tries: {text}")
                self._say("press Enter (Retry) in the window to try again, Esc to quit")
                await self._retry_wanted()
                tries = 0
                continue
            tries = 0
            self._attach(client)
            self._status("connected", "")
            if client.joined is not None and client.reach is not None:
                await self._on_joined(client)
            elif (client.joined is None and self._join_args is not None
                  and self._join_args.get("role") == "spectator"):
                try:  # a spectator has no seat to resume: it simply watches again
                    await client.join(self._join_args["room"], "spectator", mesh=True)
                except (ServerError, ConnectionError, TimeoutError) as e:
                    self._join_args = None
                    self._status("connected", f"could not watch again: {e}")
            pinger = asyncio.create_task(self._pinger(client))
            try:
                await client.wait_closed(timeout=1e9)
            except TimeoutError:
                pass
            finally:
                pinger.cancel()
            if self._stopping:
                return
            why = f"closed ({client.close_code} {client.close_reason})".strip()
            log.info("connection %s", why)
            if client.close_code == 4000 or client.token is None:
                # kicked, or never seated: no seat to resume
                self._status("closed", why)
                if client.close_code == 4000:
                    self._say(f"the server removed this client: {client.close_reason}")
                    return
            self._status("reconnecting", why)
            await asyncio.sleep(0.3)

    def _attach(self, client: NetClient) -> None:
        """Take over a fresh connection: its history first, then the live callbacks (no
        await in between, so no message falls in the gap)."""
        self.client = client
        now = self.clock()
        for m in list(client.messages):
            self.messages.put((now, m))
        client.on_message = lambda m: self.messages.put((self.clock(), m))
        client.on_mesh = self._on_mesh
        client.on_corner = self._on_corner

    def _on_mesh(self, data: bytes) -> None:
        now = self.clock()
        try:
            self.frames.put(MeshFrame.from_mesh(P.decode_mesh(data)), now)
        except P.ProtocolError as e:
            log.debug("bad MESH: %s", e)

    def _on_corner(self, c: P.Corner) -> None:
        client = self.client
        if client is None:
            return
        state = client.corner_state()
        if state is None:
            return
        if c.hip_seq != self._last_echo and math.isfinite(c.hip_time):
            self._last_echo = c.hip_seq
            lat = self.clock() - c.hip_time
            if 0 <= lat < 10:
                self.hip_latency = lat if self.hip_latency is None else (
                    0.9 * self.hip_latency + 0.1 * lat)
        self.corner.put((state, c))
        dev = self.device
        if dev is not None and self._device_started:
            dev.update_corner(state)
            update_ball = getattr(dev, "update_ball", None)
            if update_ball is not None:
                update_ball(c.ball_position, c.ball_velocity, c.server_time)

    async def _pinger(self, client: NetClient) -> None:
        while True:
            try:
                await client.request("ping", timeout=5.0, t=self.clock())
            except (ServerError, ConnectionError, OSError, TimeoutError):
                pass
            except Exception as e:  # websockets' ConnectionClosed
                if "ConnectionClosed" not in type(e).__name__:
                    raise
                return
            await asyncio.sleep(self.ping_interval)

    async def _request(self, type_: str, **fields: Any) -> dict[str, Any]:
        if self.client is None:
            raise ConnectionError("not connected")
        return await self.client.request(type_, **fields)

    async def _join(self, room: str, role: str, seat: int | None, code: str | None
                    ) -> dict[str, Any]:
        if self.client is None:
            raise ConnectionError("not connected")
        fields: dict[str, Any] = {"corner_rate": self.corner_rate, "mesh": True}
        if seat is not None:
            fields["seat"] = seat
        if code:
            fields["code"] = code
        reply = await self.client.join(room, role, **fields)
        self._join_args = {"room": room, "role": role}
        if role == "player":
            await self._on_joined(self.client)
        return reply

    async def _on_joined(self, client: NetClient) -> None:
        """A seat is ours: start the device in its reach box and stream the hand."""
        reach = client.reach
        dev = self.device
        if dev is not None and reach is not None and not self._device_started:
            bind = getattr(dev, "bind", None)  # devices that need the seat (bots)
            if bind is not None and client.joined is not None:
                bind(client.joined)
            await asyncio.to_thread(dev.start, reach)  # a Falcon homes here (blocking)
            self._device_started = True
        if self._hip_task is not None:
            self._hip_task.cancel()
        self._hip_task = asyncio.create_task(self._send_hips(client))

    async def _leave(self) -> dict[str, Any]:
        if self.client is None:
            raise ConnectionError("not connected")
        if self._hip_task is not None:
            self._hip_task.cancel()
            self._hip_task = None
        reply = await self.client.request("leave")
        self.client.joined = None
        self._join_args = None
        if self.device is not None and self._device_started:
            await asyncio.to_thread(self.device.stop)
            self._device_started = False
        return reply

    async def _send_hips(self, client: NetClient) -> None:
        dev = self.device
        if dev is None:
            return
        period = 1.0 / self.hip_rate
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        try:
            while client.joined is not None and client.seat is not None:
                h = dev.hand_position()
                await client.send_hip(h)
                self.last_hand.put(h)
                self.hips_sent += 1
                next_t += period
                delay = next_t - loop.time()
                if delay < -0.25:
                    next_t = loop.time()
                await asyncio.sleep(max(0.0, delay))
        except Exception as e:  # websockets' ConnectionClosed: the session loop reconnects
            if "ConnectionClosed" not in type(e).__name__ and not isinstance(e, OSError):
                raise
