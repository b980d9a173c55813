"""The load generator of ``clothball bench --load``: many rooms' clients in one process,
costing a small fraction of the server they load.

Each client is a websocket of its own that behaves as the desktop client does on the wire:
a player joins with ``corner_rate`` and ``mesh: true``, says it is ready and sends HIP at
``--hip-rate``; a spectator joins and receives MESH. Python sets each client up (connect,
upgrade, hello, join, ready, redirects followed: control-rate work, on raw non-blocking
sockets) and then hands its socket, with the bytes already read past the setup, to the
native pump (``LoadClients``, ``native/bench/load_clients.hpp``), which drives every client
of the process on a thread of its own without the interpreter: nothing is done in Python
per message. The pump sends the HIPs, round robin with the players evenly staggered over the
HIP period, each masked with the zero key; reads CORNER for the HIP-to-CORNER latency (the
echoed seq and time against the time it sent that seq, once per HIP, into a fixed 10 µs-bin
histogram; an echo of another time, or of a seq not sent, counted); counts MESH from its
header and skips it; counts text messages (keeping the newest error); answers pings and
closes. What the real clients do with the data is left out.

Control, from the bench over stdin (one JSON object a line; each answered by one line on
stdout): ``{"op": "add", "ws": URL, "rooms": K}`` creates K rooms through URL (redirects
followed, as with ``clothball host --workers``) and connects their clients;
``{"op": "mark"}`` starts a measurement (clears the latency histogram); ``{"op": "snap"}``
answers the counters (cumulative) and the histogram since the mark. End of stdin closes
everything.

Run only through ``clothball bench --load`` (``server/bench/loadbench.py``)."""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import math
import os
import socket
import struct
import sys
import time
import urllib.parse
from collections.abc import Callable
from typing import Any, cast

from ..._native import LOAD_CLIENTS, LoadClients
from ...game.wire import protocol as P
from ...game.wire.wsframe import (
    OP_CLOSE,
    OP_PING,
    OP_PONG,
    OP_TEXT,
    ZERO_KEY,
    header_at,
    masked_frame,
)
from ..shared.listen import raise_open_files

HIST_BIN_S = float(LOAD_CLIENTS["hist_bin_s"])  # the latency histogram's bins (the pump's)
SETUP_TIMEOUT_S = 15.0
MAX_REDIRECTS = 3
HEAD_MAX = 1 << 16  # an upgrade answer longer than this is refused
READ = 1 << 16
# What the pump takes a text message for an error by: how the codec writes one's start.
ERROR_PREFIX = P.encode_json({"type": "error"})[:-1].encode()
_U16 = struct.Struct(">H")


class SetupError(Exception):
    """A client could not connect or join (one line, the server's reason)."""


def _frame(opcode: int, payload: bytes) -> bytes:
    """A masked client frame (zero key: the payload goes as it is)."""
    return masked_frame(opcode, payload, ZERO_KEY)


class Setup:
    """One client's websocket while it is set up: the upgrade and the JSON requests, on a
    raw non-blocking socket; ``buf`` holds what was read past the last reply taken."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.buf = b""

    async def _read(self) -> None:
        data = await asyncio.get_running_loop().sock_recv(self.sock, READ)
        if not data:
            raise ConnectionError("connection closed during the setup")
        self.buf += data

    async def _send(self, data: bytes) -> None:
        await asyncio.get_running_loop().sock_sendall(self.sock, data)

    async def upgrade(self, host: str, port: int, path: str) -> None:
        key = base64.b64encode(os.urandom(16)).decode()
        await self._send(
            f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
            "Sec-WebSocket-Version: 13\r\nUser-Agent: clothball-loadbench\r\n\r\n".encode())
        while (end := self.buf.find(b"\r\n\r\n")) < 0:
            if len(self.buf) > HEAD_MAX:
                raise ConnectionError("upgrade refused: an answer too long")
            await self._read()
        head, self.buf = self.buf[:end], self.buf[end + 4:]
        if not head.startswith(b"HTTP/1.1 101"):
            line = head.split(b"\r\n", 1)[0].decode("latin-1")
            raise ConnectionError(f"upgrade refused: {line}")

    async def request(self, msg: dict[str, Any], want: Callable[[dict[str, Any]], bool]
                      ) -> dict[str, Any]:
        """Send ``msg`` and wait for the first message ``want(reply)`` accepts; the frames
        before it (CORNER, MESH, events) are dropped: they come before the measurement."""
        await self._send(_frame(OP_TEXT, json.dumps(msg).encode()))
        while True:
            head = header_at(self.buf, 0)
            if head is None or len(self.buf) < head[3] + head[2]:
                await self._read()
                continue
            b0, _, n, hl = head
            body, self.buf = self.buf[hl:hl + n], self.buf[hl + n:]
            op = b0 & 0x0F
            if op == OP_PING:
                await self._send(_frame(OP_PONG, body))
            elif op == OP_CLOSE:
                raise ConnectionError("connection closed by the server during the setup")
            elif op == OP_TEXT:
                try:
                    reply = json.loads(body)
                except ValueError:
                    continue
                if isinstance(reply, dict) and want(reply):
                    return reply

    def close(self) -> None:
        try:
            self.sock.send(_frame(OP_CLOSE, _U16.pack(1000)))
        except OSError:
            pass
        self.sock.close()


async def _open(url: str, hello: dict[str, Any]) -> tuple[Setup, dict[str, Any]]:
    loop = asyncio.get_running_loop()
    for _ in range(MAX_REDIRECTS + 1):
        u = urllib.parse.urlsplit(url)
        host, port = u.hostname or "127.0.0.1", u.port or 80
        info = await loop.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        sock = socket.socket(info[0][0], socket.SOCK_STREAM)
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn = Setup(sock)
        try:
            await loop.sock_connect(sock, info[0][4])
            await conn.upgrade(host, port, u.path or "/")
            reply = await conn.request(
                hello, lambda m: m.get("re") == 0 and m.get("type") in ("joined", "error",
                                                                         "redirect"))
        except BaseException:
            conn.close()
            raise
        if reply["type"] == "redirect":
            conn.close()
            url = str(reply["url"])
            continue
        if reply["type"] == "error":
            conn.close()
            raise SetupError(f"{hello.get('role')} join refused: {reply.get('code')}: "
                             f"{reply.get('message')}")
        return conn, reply
    raise SetupError(f"too many redirects (last: {url})")


async def connect(url: str, hello: dict[str, Any]) -> tuple[Setup, dict[str, Any]]:
    """A client that said ``hello`` (a join: role and room) at ``url`` and was ``joined``,
    following redirects to the process that holds the room."""
    return await asyncio.wait_for(_open(url, hello), SETUP_TIMEOUT_S)


def _error_text(raw: bytes) -> str:
    """The newest error message the pump kept (its first bytes) as ``code: message``."""
    if not raw:
        return ""
    try:
        msg = json.loads(raw)
    except ValueError:  # cut at the bytes kept
        return raw.decode("utf-8", "replace")
    return f"{msg.get('code')}: {msg.get('message')}" if isinstance(msg, dict) else ""


class Load:
    """Every client of this process: set up here, then driven by the native pump."""

    def __init__(self, hip_rate: float, corner_rate: float, spectators: int) -> None:
        self.corner_rate, self.spectators = corner_rate, spectators
        self.pump = LoadClients(hip_rate, ERROR_PREFIX)
        self.pump.start()
        self.players: list[int] = []  # the pump's indices of the players
        self.watchers = 0  # spectators
        self.rooms: list[tuple[str, list[int]]] = []  # each room's players
        self.mesh_hz = math.nan

    async def add_room(self, ws: str) -> str:
        from ...game.net.client import NetClient  # room creation only: redirects handled there

        c = await NetClient.connect(ws, name="load")
        try:
            made = await c.request("create_room", name="load", bots_allowed=False,
                                   unguarded=True, first_to=99)
        finally:
            await c.close()
        room = str(made["room"])
        base = {"type": "hello", "version": P.PROTOCOL_VERSION, "id": 0, "room": room}
        joins = [connect(ws, {**base, "name": f"p{s}", "role": "player", "seat": s,
                              "corner_rate": self.corner_rate, "mesh": True})
                 for s in range(4)]
        joins += [connect(ws, {**base, "name": f"s{i}", "role": "spectator"})
                  for i in range(self.spectators)]
        done = await asyncio.gather(*joins, return_exceptions=True)
        conns = [r[0] for r in done if not isinstance(r, BaseException)]
        try:
            failed = [r for r in done if isinstance(r, BaseException)]
            if failed:
                raise failed[0]
            hands = []
            for s, (p, joined) in enumerate(cast(list[tuple[Setup, dict[str, Any]]], done[:4])):
                r = joined["reach"]
                self.mesh_hz = float(joined["geometry"]["mesh_hz"])
                hands.append((float(r["centre"][0]), float(r["centre"][1]),
                              float(r["centre"][2]), float(r["half_extent"][1]),
                              s * math.pi / 2))
                ok = await asyncio.wait_for(p.request(
                    {"type": "ready", "ready": True, "id": 1}, lambda m: m.get("re") == 1),
                    SETUP_TIMEOUT_S)
                if ok.get("type") == "error":
                    raise SetupError(f"ready refused: {ok.get('code')}: {ok.get('message')}")
        except BaseException:
            for c2 in conns:
                c2.close()
            raise
        # Handed over: the pump takes its own descriptor of each socket and the bytes read
        # past the setup; this process's socket is closed without a shutdown (the
        # connection stays, the pump's).
        players = [self.pump.add(p.sock.fileno(), p.buf, hand)
                   for p, hand in zip(conns[:4], hands, strict=True)]
        for w in conns[4:]:
            self.pump.add(w.sock.fileno(), w.buf, None)
        for c2 in conns:
            c2.sock.close()
        self.players += players
        self.watchers += len(conns) - 4
        self.rooms.append((room, players))
        return room

    def snap(self, mark: bool) -> dict[str, Any]:
        s = self.pump.snap(mark)
        players = self.players
        return {
            "cpu_s": time.process_time(),
            "wall_s": time.perf_counter(),
            "players": len(players),
            "spectators": self.watchers,
            "hips": sum(s["hips"]),
            "corners": [s["corners"][i] for i in players],
            "meshes": sum(s["meshes"]),
            "texts": sum(s["texts"]),
            "bytes_in": sum(s["bytes"]),
            "mesh_hz": self.mesh_hz,
            "frames": {room: max(s["frame"][i] for i in ps) for room, ps in self.rooms},
            "echo_unknown": s["echo_unknown"],
            "echo_mismatch": s["echo_mismatch"],
            "errors": sum(s["errors"]),
            "last_error": _error_text(s["last_error"]),
            "lost": sum(s["closed"]),
            "behind": s["behind"],
            "hist": {} if mark else s["hist"],
        }

    def close(self) -> None:
        self.pump.close()


async def _serve(args: argparse.Namespace) -> None:
    load = Load(args.hip_rate, args.corner_rate, args.spectators)
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader()
    await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
    try:
        while line := await reader.readline():
            cmd = json.loads(line)
            out: dict[str, Any]
            if cmd["op"] == "add":
                try:
                    rooms = [await load.add_room(cmd["ws"]) for _ in range(int(cmd["rooms"]))]
                    out = {"rooms": rooms}
                except SetupError as e:
                    out = {"error": str(e)}
                except Exception as e:  # noqa: BLE001 - any failure (a NetClient ServerError, a
                    # refused connection, a timeout) is said to the bench in one line
                    out = {"error": f"{type(e).__name__}: {e}"}
            else:
                out = load.snap(mark=cmd["op"] == "mark")
            sys.stdout.write(json.dumps(out) + "\n")
            sys.stdout.flush()
    finally:
        load.close()  # a close frame to every client


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m clothball.server.bench.benchclients")
    p.add_argument("--hip-rate", type=float, required=True)
    p.add_argument("--corner-rate", type=float, required=True)
    p.add_argument("--spectators", type=int, required=True)
    raise_open_files()
    asyncio.run(_serve(p.parse_args(argv)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
