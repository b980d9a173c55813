"""The load generator of ``clothball bench --load``: many rooms' clients in one asyncio
process, costing a small fraction of the server they load.

Each client is a websocket of its own (a raw ``asyncio.Protocol``, no websockets library on
the hot path) that behaves as the desktop client does on the wire: a player joins with
``corner_rate`` and ``mesh: true``, says it is ready and sends HIP at ``--hip-rate``; a
spectator joins and receives MESH. What the real clients do with the data is left out:

* MESH is counted from its frame header and first payload byte, never copied or decoded
  (its bytes are skipped as they arrive);
* CORNER is read only as far as its frame number and the echo of the newest HIP the server
  applied (seq, client time): the HIP-to-CORNER latency is the receipt time less the time
  that seq was sent (kept by the client, on this process's clock), once per HIP (the first
  CORNER that echoes it), into a fixed histogram (10 µs bins), so the memory does not grow
  with the run; an echoed time other than the one sent, or a seq never sent, is counted;
* HIPs of every player of the process are sent by one pacing task, round robin with the
  players evenly staggered over the HIP period (real clients are not in step), each a
  34-byte frame masked with the zero key (a server unmasks whatever key it is given; a zero
  key makes masking free).

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
import struct
import sys
import time
import urllib.parse
from typing import Any, cast

from ...game.wire import protocol as P
from ...game.wire.wsframe import (
    OP_BINARY,
    OP_CLOSE,
    OP_PING,
    OP_PONG,
    OP_TEXT,
    ZERO_KEY,
    frame_header,
    header_at,
    masked_frame,
)
from ..shared.listen import raise_open_files

HIST_BIN_S = 1e-5  # latency histogram: 10 µs bins ...
HIST_BINS = 100_000  # ... to 1 s; the last bin holds everything later (a quantile there: ≥ 1 s)
SENT_RING = 256  # HIP send times kept a player (2 s at 120 Hz), to match the echoes to
SETUP_TIMEOUT_S = 15.0
MAX_REDIRECTS = 3
FAR_BEHIND_S = 0.05  # the pacer this late: it starts again from now rather than burst

# A client's HIP, websocket frame included (the header and zero key, then the message),
# packed in one call.
_HIP_HEAD = frame_header(OP_BINARY, P.HIP_SIZE, masked=True) + ZERO_KEY
_HIP_FRAME = struct.Struct(f"<{len(_HIP_HEAD)}s" + P.HIP_MSG.format[1:])
# What a CORNER is read for: its frame, and the seq and client time of the HIP it echoes.
_CORNER_ECHO = struct.Struct(f"<{P.HEADER.size}xq{P.CORNER_SIZE - 12 - P.HEADER.size - 8}xId")
_U16 = struct.Struct(">H")
_MESH, _CORNER = P.MESH, P.CORNER


class SetupError(Exception):
    """A client could not connect or join (one line, the server's reason)."""


def _frame(opcode: int, payload: bytes) -> bytes:
    """A masked client frame (zero key: the payload goes as it is)."""
    return masked_frame(opcode, payload, ZERO_KEY)


class Conn(asyncio.Protocol):
    """One client's websocket: the handshake, then frames parsed in place."""

    def __init__(self, hist: list[int]) -> None:
        self.transport: asyncio.Transport | None = None
        self.hist = hist
        self._head = b""  # the HTTP answer, until the upgrade is done
        self._upgraded: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._buf = b""  # a frame cut by the end of a read, until the rest comes
        self._skip = 0  # bytes of a MESH still to come, to be skipped
        self._waiter: tuple[Any, asyncio.Future[dict[str, Any]]] | None = None
        self.corners = 0
        self.meshes = 0
        self.texts = 0
        self.errors = 0
        self.last_error = ""
        self.frame = -1  # the newest CORNER's frame
        self.echo_seq = 0  # the newest HIP seq a CORNER echoed
        self.echo_unknown = 0  # echoes of a seq not among the last SENT_RING sent
        self.echo_mismatch = 0  # echoes whose time is not the one that HIP was sent with
        self.lost = False
        # players
        self.seq = 0
        self.hips = 0
        self.sent = [0.0] * SENT_RING  # send times by seq (mod SENT_RING)
        self.hand: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    # --- asyncio.Protocol --------------------------------------------------------------
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # a stream transport (uvloop's is not an asyncio.Transport subclass, hence the cast)
        self.transport = cast(asyncio.Transport, transport)

    def connection_lost(self, exc: Exception | None) -> None:
        self.lost = True
        if not self._upgraded.done():
            self._upgraded.set_exception(ConnectionError("connection closed during the upgrade"))
        if self._waiter is not None and not self._waiter[1].done():
            self._waiter[1].set_exception(ConnectionError("connection closed"))

    def data_received(self, data: bytes) -> None:
        if not self._upgraded.done():
            self._head += data
            end = self._head.find(b"\r\n\r\n")
            if end < 0:
                return
            head, data = self._head[:end], self._head[end + 4:]
            self._head = b""
            if not head.startswith(b"HTTP/1.1 101"):
                line = head.split(b"\r\n", 1)[0].decode("latin-1")
                self._upgraded.set_exception(ConnectionError(f"upgrade refused: {line}"))
                return
            self._upgraded.set_result(None)
            if not data:
                return
        self._frames(data)

    def _frames(self, data: bytes) -> None:
        skip = self._skip
        if skip:
            if len(data) <= skip:
                self._skip = skip - len(data)
                return
            data = data[skip:]
            self._skip = 0
        if self._buf:
            data = self._buf + data
            self._buf = b""
        pos, end = 0, len(data)
        while True:
            head = header_at(data, pos)
            if head is None:
                break
            b0, _, ln, hl = head
            op, start = b0 & 0x0F, pos + hl
            stop = start + ln
            if op == OP_BINARY and start < end and data[start] == _MESH:
                self.meshes += 1  # counted, never decoded: its bytes are skipped
                if stop > end:
                    self._skip = stop - end
                    return
                pos = stop
                continue
            if stop > end:
                break
            if op == OP_BINARY:
                if data[start] == _CORNER and ln == P.CORNER_SIZE:
                    self._corner(data, start)
            elif op == OP_TEXT:
                self._text(data[start:stop])
            elif op == OP_PING:
                self._write(_frame(OP_PONG, data[start:stop]))
            elif op == OP_CLOSE:
                self.lost = True
                if self.transport is not None:
                    self.transport.close()
                return
            pos = stop
        if pos < end:
            self._buf = data[pos:]

    def _corner(self, data: bytes, start: int) -> None:
        frame, seq, echoed = _CORNER_ECHO.unpack_from(data, start)
        self.corners += 1
        self.frame = frame
        if seq == self.echo_seq or not seq:  # not the first CORNER that echoes a HIP
            return
        self.echo_seq = seq
        if (self.seq - seq) & 0xFFFFFFFF >= SENT_RING:
            self.echo_unknown += 1  # a seq this client never sent (or long ago)
            return
        sent = self.sent[seq & (SENT_RING - 1)]
        if echoed != sent:  # the server echoed another time than this HIP's
            self.echo_mismatch += 1
        i = int((time.perf_counter() - sent) / HIST_BIN_S)
        self.hist[i if 0 <= i < HIST_BINS else (0 if i < 0 else HIST_BINS)] += 1

    def _text(self, raw: bytes) -> None:
        self.texts += 1
        try:
            msg = json.loads(raw)
        except ValueError:
            return
        if not isinstance(msg, dict):
            return
        if msg.get("type") == "error":
            self.errors += 1
            self.last_error = f"{msg.get('code')}: {msg.get('message')}"
        w = self._waiter
        if w is not None and not w[1].done() and w[0](msg):
            w[1].set_result(msg)

    def _write(self, data: bytes) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.write(data)

    # --- setup (not on the hot path) --------------------------------------------------
    async def upgrade(self, host: str, port: int, path: str) -> None:
        key = base64.b64encode(os.urandom(16)).decode()
        assert self.transport is not None
        self.transport.write(
            f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
            "Sec-WebSocket-Version: 13\r\nUser-Agent: clothball-loadbench\r\n\r\n".encode())
        await asyncio.wait_for(self._upgraded, SETUP_TIMEOUT_S)

    async def request(self, msg: dict[str, Any], want: Any) -> dict[str, Any]:
        """Send ``msg`` and wait for the first message ``want(reply)`` accepts."""
        fut: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._waiter = (want, fut)
        try:
            self._write(_frame(OP_TEXT, json.dumps(msg).encode()))
            return await asyncio.wait_for(fut, SETUP_TIMEOUT_S)
        finally:
            self._waiter = None

    def close(self) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.write(_frame(OP_CLOSE, _U16.pack(1000)))
            self.transport.close()

    # --- players ----------------------------------------------------------------------
    def send_hip(self, now: float) -> None:
        """The next HIP: a slow sine up and down the seat's reach, stamped ``now``."""
        cx, cy, cz, hy, phase = self.hand
        seq = self.seq = (self.seq + 1) & 0xFFFFFFFF
        self.sent[seq & (SENT_RING - 1)] = now
        y = cy + 0.3 * math.sin(math.pi * now + phase) * hy
        self._write(_HIP_FRAME.pack(_HIP_HEAD, P.HIP, P.PROTOCOL_VERSION, 0,
                                    seq, now, cx, y, cz))
        self.hips += 1


async def connect(url: str, hello: dict[str, Any], hist: list[int]) -> tuple[Conn, dict[str, Any]]:
    """A client that said ``hello`` (a join: role and room) at ``url`` and was ``joined``,
    following redirects to the process that holds the room."""
    loop = asyncio.get_running_loop()
    for _ in range(MAX_REDIRECTS + 1):
        u = urllib.parse.urlsplit(url)
        host, port = u.hostname or "127.0.0.1", u.port or 80
        _, conn = await loop.create_connection(lambda: Conn(hist), host, port)
        try:
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


class Load:
    """Every client of this process, their pacing and counters."""

    def __init__(self, hip_rate: float, corner_rate: float, spectators: int) -> None:
        self.hip_rate, self.corner_rate, self.spectators = hip_rate, corner_rate, spectators
        self.hist = [0] * (HIST_BINS + 1)
        self.players: list[Conn] = []
        self.watchers: list[Conn] = []  # spectators
        self.rooms: list[tuple[str, list[Conn]]] = []  # each room's players
        self.mesh_hz = math.nan
        self.behind = 0  # times the pacer fell FAR_BEHIND_S behind
        self._wake = asyncio.Event()

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
                              "corner_rate": self.corner_rate, "mesh": True}, self.hist)
                 for s in range(4)]
        joins += [connect(ws, {**base, "name": f"s{i}", "role": "spectator"}, self.hist)
                  for i in range(self.spectators)]
        done = await asyncio.gather(*joins, return_exceptions=True)
        failed = [r for r in done if isinstance(r, BaseException)]
        conns = [r[0] for r in done if not isinstance(r, BaseException)]
        if failed:
            for c2 in conns:
                c2.close()
            raise failed[0]
        players = conns[:4]
        for s, (p, (_, joined)) in enumerate(zip(players, done[:4], strict=True)):
            r = joined["reach"]
            self.mesh_hz = float(joined["geometry"]["mesh_hz"])
            p.hand = (float(r["centre"][0]), float(r["centre"][1]), float(r["centre"][2]),
                      float(r["half_extent"][1]), s * math.pi / 2)
            ok = await p.request({"type": "ready", "ready": True, "id": 1},
                                 lambda m: m.get("re") == 1)
            if ok.get("type") == "error":
                raise SetupError(f"ready refused: {ok.get('code')}: {ok.get('message')}")
        self.players += players
        self.watchers += conns[4:]
        self.rooms.append((room, players))
        self._wake.set()
        return room

    async def pace(self) -> None:
        """Every player's HIPs at ``hip_rate``, staggered evenly over the period."""
        loop = asyncio.get_running_loop()
        period = 1.0 / self.hip_rate
        clock = time.perf_counter
        k, t = 0, loop.time()
        while True:
            players = self.players
            if not players:
                self._wake.clear()
                await self._wake.wait()
                t = loop.time()
                continue
            n = len(players)
            gap = period / n
            now = loop.time()
            if now - t > FAR_BEHIND_S:
                self.behind += 1
                t = now
            while t <= now:
                p = players[k % n]
                k += 1
                if not p.lost:
                    p.send_hip(clock())
                t += gap
            await asyncio.sleep(t - loop.time())

    def snap(self, mark: bool) -> dict[str, Any]:
        hist = {i: c for i, c in enumerate(self.hist) if c}
        if mark:
            self.hist[:] = [0] * len(self.hist)
        everyone = [*self.players, *self.watchers]
        return {
            "cpu_s": time.process_time(),
            "wall_s": time.perf_counter(),
            "players": len(self.players),
            "spectators": len(self.watchers),
            "hips": sum(p.hips for p in self.players),
            "corners": [p.corners for p in self.players],
            "meshes": sum(c.meshes for c in everyone),
            "mesh_hz": self.mesh_hz,
            "frames": {room: max(p.frame for p in ps) for room, ps in self.rooms},
            "echo_unknown": sum(p.echo_unknown for p in self.players),
            "echo_mismatch": sum(p.echo_mismatch for p in self.players),
            "errors": sum(c.errors for c in everyone),
            "last_error": next((c.last_error for c in everyone if c.last_error), ""),
            "lost": sum(c.lost for c in everyone),
            "behind": self.behind,
            "hist": {} if mark else hist,
        }

    def close(self) -> None:
        for c in [*self.players, *self.watchers]:
            c.close()


async def _serve(args: argparse.Namespace) -> None:
    load = Load(args.hip_rate, args.corner_rate, args.spectators)
    pacer = asyncio.create_task(load.pace())
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
        pacer.cancel()
        load.close()
        await asyncio.sleep(0.1)  # the close frames go out


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
