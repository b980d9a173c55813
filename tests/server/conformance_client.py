"""A websocket client written from ``docs/protocol.md`` alone (not from the codec), for the
conformance suite: every message it receives is kept in a shared ``Transcript``, so that
the suite can check each documented row against what a live server sent, and that the
server sent nothing the doc does not name."""

from __future__ import annotations

import asyncio
import base64
import itertools
import json
import os
import socket
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from tests.server.conftest import recv_all

HELLO: dict[str, Any] = {"type": "hello", "version": 1}


@dataclass
class Transcript:
    """Everything the suite's clients received: JSON messages (in order), binary messages
    by their header's type byte (the first few of each), and the close codes with their
    reasons."""

    json: list[dict[str, Any]] = field(default_factory=list)
    binary: dict[int, list[bytes]] = field(default_factory=dict)
    closes: list[tuple[int, str]] = field(default_factory=list)

    def of(self, type_: str) -> list[dict[str, Any]]:
        return [m for m in self.json if m.get("type") == type_]

    def events(self, event: str) -> list[dict[str, Any]]:
        return [m for m in self.of("event") if m.get("event") == event]

    def errors(self, code: str) -> list[dict[str, Any]]:
        return [m for m in self.of("error") if m.get("code") == code]


class Wire:
    """One connection: ``open`` says hello (following a redirect of a hello that joins),
    ``request`` sends a control message with an id and waits for its reply (following a
    redirect as the doc says: a new connection there, the same hello, the request again
    with the redirect's ``with`` fields)."""

    _ids = itertools.count(1)

    def __init__(self, t: Transcript, url: str) -> None:
        self.t, self.url = t, url
        self.ws: ClientConnection | None = None
        self.hello: dict[str, Any] = HELLO
        self.msgs: list[dict[str, Any]] = []
        self.binary: list[bytes] = []
        self.close_code: int | None = None
        self._reader: asyncio.Task[None] | None = None
        self._new = asyncio.Event()

    async def open(self, hello: dict[str, Any] | None = None, *, hops: int = 3
                   ) -> dict[str, Any]:
        """Connect and say hello; the ``welcome`` (or ``error``), then for a hello that
        joins its ``joined`` (or ``error``) is in ``self.joined``."""
        self.hello = {**HELLO, **(hello or {})}
        mark = len(self.msgs)  # this connection's messages (after a redirect: the new one's)
        await self._connect(self.url)
        await self.send(json.dumps(self.hello))
        first = await self.next(lambda m: m["type"] in ("welcome", "error"), since=mark)
        self.joined: dict[str, Any] | None = None
        joins = self.hello.get("role", "lobby") != "lobby" or "token" in self.hello
        if first["type"] == "welcome" and joins:
            reply = await self.next(lambda m: m["type"] in ("joined", "error", "redirect"),
                                    since=mark)
            if reply["type"] == "redirect" and hops > 0:
                await self.close()
                self.url = reply["url"]
                return await self.open(self.hello, hops=hops - 1)
            self.joined = reply
        return first

    async def _connect(self, url: str) -> None:
        self.ws = await connect(url, open_timeout=10, max_size=2**20)
        self.close_code = None
        self._reader = asyncio.create_task(self._read(self.ws))

    async def _read(self, ws: ClientConnection) -> None:
        try:
            async for m in ws:
                if isinstance(m, bytes):
                    self.binary.append(m)
                    if len(self.binary) > 400:
                        del self.binary[:200]
                    kept = self.t.binary.setdefault(m[0] if m else -1, [])
                    if len(kept) < 50:
                        kept.append(m)
                else:
                    msg = json.loads(m)
                    self.msgs.append(msg)
                    self.t.json.append(msg)
                self._new.set()
        except ConnectionClosed:
            pass
        finally:
            if ws is self.ws:
                self.close_code = ws.close_code
                if ws.close_code is not None:
                    self.t.closes.append((ws.close_code, ws.close_reason or ""))
                self._new.set()

    async def send(self, data: str | bytes) -> None:
        assert self.ws is not None
        await self.ws.send(data)

    async def next(self, pred: Callable[[dict[str, Any]], bool], timeout: float = 15.0,
                   since: int | None = None) -> dict[str, Any]:
        """The first message from index ``since`` (default: any so far) matching ``pred``."""
        start = 0 if since is None else since

        async def find() -> dict[str, Any]:
            while True:
                for m in self.msgs[start:]:
                    if pred(m):
                        return m
                if self.close_code is not None:
                    raise ConnectionError(f"closed {self.close_code} while waiting")
                self._new.clear()
                await self._new.wait()

        try:
            return await asyncio.wait_for(find(), timeout)
        except TimeoutError:
            raise AssertionError(f"{self.hello}: nothing awaited came in {timeout:g} s; the "
                                 f"last messages: {self.msgs[-4:]}") from None

    async def event(self, name: str, timeout: float = 30.0, since: int | None = None,
                    **match: Any) -> dict[str, Any]:
        return await self.next(lambda m: m["type"] == "event" and m["event"] == name and all(
            m.get(k) == v for k, v in match.items()), timeout, since)

    async def request(self, msg: dict[str, Any], hops: int = 3) -> dict[str, Any]:
        rid = next(self._ids)
        mark = len(self.msgs)
        await self.send(json.dumps({**msg, "id": rid}))
        reply = await self.next(lambda m: m.get("re") == rid, since=mark)
        if reply["type"] == "redirect" and hops > 0:
            await self.close()
            self.url = reply["url"]
            await self.open(self.hello)
            return await self.request({**msg, **reply.get("with", {})}, hops - 1)
        return reply

    async def closed(self, timeout: float = 15.0) -> int | None:
        """The close code the server closes this connection with."""
        async def wait() -> None:
            while self.close_code is None:
                self._new.clear()
                await self._new.wait()

        await asyncio.wait_for(wait(), timeout)
        return self.close_code

    async def close(self) -> None:
        if self.ws is not None:
            ws, self.ws = self.ws, None
            await ws.close()
            if self._reader is not None:
                await self._reader


def raw_ws_close_code(host: str, port: int, hello: bytes, wait_s: float) -> int | None:
    """A websocket client that says hello and then never answers a keep-alive ping (it only
    reads): the close code the server's close frame names, read until the server closes
    the connection, waiting at most ``wait_s`` (None if no close came by then). Blocking:
    run it in a thread."""
    key = base64.b64encode(os.urandom(16)).decode()
    with socket.create_connection((host, port), timeout=wait_s) as s:
        s.sendall((f"GET /ws HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
                   f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                   "Sec-WebSocket-Version: 13\r\n\r\n").encode())
        buf = b""
        while b"\r\n\r\n" not in buf:
            buf += s.recv(4096)
        buf = buf.split(b"\r\n\r\n", 1)[1]
        mask = os.urandom(4)
        body = bytes(b ^ mask[i % 4] for i, b in enumerate(hello))
        assert len(hello) < 126
        s.sendall(bytes([0x81, 0x80 | len(hello)]) + mask + body)
        # (until the server closes, not a fixed time: a loaded machine only takes longer)
        buf += recv_all(s, wait_s)
    # the server's frames, unmasked: find the close frame (opcode 8)
    off = 0
    while off + 2 <= len(buf):
        op, ln = buf[off] & 0x0F, buf[off + 1] & 0x7F
        off += 2
        if ln == 126:
            ln = struct.unpack_from(">H", buf, off)[0]
            off += 2
        elif ln == 127:
            ln = struct.unpack_from(">Q", buf, off)[0]
            off += 8
        if op == 8 and ln >= 2:
            return int(struct.unpack_from(">H", buf, off)[0])
        off += ln
    return None
