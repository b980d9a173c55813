"""A client's lane: what the engine and a gateway share so that the gateway serves a seated
player's HIPs and CORNERs, and any client's MESH, itself, from the engine's shared memory
(the frame loop's block, its mesh board), and relays only the rest (control messages,
HTTP) between the client and the engine.

* The **lane message**: when a client that came through a gateway takes a seat in a room
  stepped by the native frame loop, or watches one, the engine sends, in the client's own
  stream, a text message ``{"type": "_lane", ...}`` (``lane_message``); when it leaves the
  seat or the room, one with no room. The gateway takes both out of the stream (the client
  never sees them). With a seated lane, the gateway writes the player's well-formed HIPs
  into the seat's hand in the block (under the seat's occupant: a late one for an
  occupant that has left is ignored by the loop) and sends the seat's CORNER from the
  block at the client's ``corner_rate``; with a mesh board, it sends the room's MESH from
  the board (the engine writes each room's newest there once); the engine sends that
  client neither. Anything else the client sends (a HIP that is not well formed or out of
  reach, past the binary rate, any control message) goes to the engine as before, which
  answers it as documented.
* The **control socket** beside the engine's (``ctl_path``): a gateway asks it for the
  blocks and mesh boards (``BLOCKS``: one JSON line naming each one's id, size and kind,
  the memfds passed with it, SCM_RIGHTS) and reports its counts on it (one JSON line a
  second: messages in and out that the engine did not see), so that the host's figures
  stay whole. ``WAKE`` asks for the gateway's **frame wake-up**, an eventfd (passed the same
  way, once per connection) that every frame loop of the engine writes after each pass
  while the gateway has it armed (``ARM``, ``DISARM``: unanswered lines): the gateway
  sends CORNERs faster than its timers can (``corner_rate`` above ``TIMER_MAX_HZ``) as
  each frame is published.
"""

from __future__ import annotations

import json
import os
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any

LANE_TYPE = "_lane"
LANE_PREFIX = b'{"type":"_lane"'  # how the engine's compact JSON of a lane message starts
BLOCKS = b"blocks\n"
WAKE, ARM, DISARM = b"wake\n", b"arm\n", b"disarm\n"
# Up to this corner_rate a gateway times a lane's CORNERs with its own timers; above it,
# on the frame wake-up (asyncio's timers on epoll wait whole milliseconds: at 1 kHz they
# fired late or on no new frame).
TIMER_MAX_HZ = 500.0
MAX_BLOCKS = 64
LINE_MAX = 1 << 16


BOARD_HEAD = 64  # a mesh board slot's header (native/loop/board.hpp): lock, length, frame


def board_slot_bytes(mesh_bytes: int) -> int:
    """A mesh board's slot for MESH messages of at most ``mesh_bytes`` (64-byte aligned)."""
    return BOARD_HEAD + -(-mesh_bytes // 64) * 64


def ctl_path(engine_socket: Path) -> Path:
    """The engine's control socket, beside its socket for client connections."""
    return engine_socket.with_name(engine_socket.name + ".ctl")


@dataclass(frozen=True)
class LaneSpec:
    """A client served by the gateway from the engine's shared memory: a seated player's
    hand and CORNER (``seat``: where they are in which block, the seat's occupant, its
    reach box, the client's CORNER interval and binary rate), and any client's MESH
    (``board``: the mesh board and the room's slot in it; None: the engine sends them)."""

    room: str
    block: int
    slot: int
    seat: int | None  # None: not seated (a spectator): MESH only; else its CORNERs too
    occupant: int
    lo: tuple[float, ...]
    hi: tuple[float, ...]
    corner_interval: float  # s (0: every frame)
    binary_rate: float  # messages a second (the engine's Limits.binary_rate)
    binary_burst: float
    board: int | None  # the mesh board's id (None: no MESH from the gateway)
    board_slot: int  # bytes of a board slot; the room's is at slot * board_slot


def in_reach(lo: tuple[float, ...], hi: tuple[float, ...], position: tuple[float, ...]) -> bool:
    """A hand ``position`` is inside a seat's reach box [lo, hi] (the one check, for a
    lane's HIPs and for the engine's answer to one a lane refused)."""
    x, y, z = position
    return lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and lo[2] <= z <= hi[2]


def lane_message(lane: LaneSpec | None) -> dict[str, Any]:
    """The engine's message opening a lane (None: closing it)."""
    if lane is None:
        return {"type": LANE_TYPE}
    return {"type": LANE_TYPE, "room": lane.room, "block": lane.block, "slot": lane.slot,
            "seat": lane.seat,
            "occupant": lane.occupant, "lo": list(lane.lo),
            "hi": list(lane.hi), "corner_interval": lane.corner_interval,
            "binary_rate": lane.binary_rate, "binary_burst": lane.binary_burst,
            "board": lane.board, "board_slot": lane.board_slot}


def parse_lane(payload: bytes) -> LaneSpec | None:
    """A lane message's payload as the gateway reads it (None: the lane is closed)."""
    m = json.loads(payload)
    if "room" not in m:
        return None
    seat, board = m["seat"], m["board"]
    return LaneSpec(str(m["room"]), int(m["block"]), int(m["slot"]),
                None if seat is None else int(seat), int(m["occupant"]),
                tuple(map(float, m["lo"])), tuple(map(float, m["hi"])),
                float(m["corner_interval"]), float(m["binary_rate"]),
                float(m["binary_burst"]), None if board is None else int(board),
                int(m["board_slot"]))


def send_blocks(sock: socket.socket, shares: list[tuple[int, int, int, str]]) -> None:
    """The engine's answer to ``BLOCKS``: ``shares`` as (id, memfd, bytes, kind), kind
    ``block`` (a frame loop's) or ``board`` (its mesh board)."""
    line = json.dumps({"blocks": [{"id": i, "bytes": n, "kind": k}
                                  for i, _, n, k in shares]}).encode()
    socket.send_fds(sock, [line + b"\n"], [fd for _, fd, _, _ in shares])


def receive_block_fds(sock: socket.socket) -> dict[int, tuple[str, int, int]]:
    """The gateway's side of ``BLOCKS`` (a blocking socket): each share as (kind, memfd,
    bytes), by id; the descriptors are the caller's to close."""
    sock.sendall(BLOCKS)
    data, fds, _, _ = socket.recv_fds(sock, LINE_MAX, MAX_BLOCKS)
    try:
        if not data.endswith(b"\n"):
            raise ConnectionError("the engine's answer to BLOCKS was cut short")
        named = json.loads(data)["blocks"]
        if len(named) != len(fds):
            raise ConnectionError(f"the engine named {len(named)} blocks and passed {len(fds)}")
        return {int(b["id"]): (str(b["kind"]), fd, int(b["bytes"]))
                for b, fd in zip(named, fds, strict=True)}
    except BaseException:
        for fd in fds:
            os.close(fd)
        raise


def send_wake(sock: socket.socket, fd: int) -> None:
    """The engine's answer to ``WAKE``: the eventfd, with one line."""
    socket.send_fds(sock, [b'{"wake":true}\n'], [fd])


def receive_wake(sock: socket.socket) -> int:
    """The gateway's side of ``WAKE`` (a blocking socket): the eventfd (its own to close)."""
    sock.sendall(WAKE)
    data, fds, _, _ = socket.recv_fds(sock, LINE_MAX, 1)
    if data != b'{"wake":true}\n' or len(fds) != 1:
        for fd in fds:
            os.close(fd)
        raise ConnectionError(f"the engine's answer to WAKE was not one: {data[:60]!r}")
    return fds[0]


# What a gateway reports, its pump's running counts: the messages its lanes handled, and
# the clients it dropped for staying behind past slow_drop_s.
REPORTED = ("messages_in", "messages_out", "slow_drops")


def counts_line(counts: dict[str, int]) -> bytes:
    """A gateway's report: its totals since it connected (the engine adds the increase)."""
    return json.dumps({"counts": counts}, separators=(",", ":")).encode() + b"\n"
