"""A seated player's lane: what the engine and a gateway share so that the gateway serves
that player's HIPs and CORNERs itself, through the frame loop's block, and relays only the
rest (control messages, MESH, HTTP) between the client and the engine.

* The **lane message**: when a client that came through a gateway takes a seat in a room
  stepped by the native frame loop, the engine sends, in the client's own stream, a text
  message ``{"type": "_lane", ...}`` (``lane_message``); when the seat is left, one with
  ``"seat": null``. The gateway takes both out of the stream (the client never sees them).
  With a lane, the gateway writes the player's well-formed HIPs into the seat's hand in the
  block (under the seat's occupant: a late one for an occupant that has left is ignored by
  the loop) and sends the seat's CORNER from the block at the client's ``corner_rate``; the
  engine sends that client no CORNER. Anything else the client sends (a HIP that is not
  well formed or out of reach, past the binary rate, any control message) goes to the
  engine as before, which answers it as documented.
* The **control socket** beside the engine's (``ctl_path``): a gateway asks it for the
  blocks (``BLOCKS``: one JSON line naming each block's id and size, the memfds passed with
  it, SCM_RIGHTS) and reports its counts on it (one JSON line a second: messages in and out
  that the engine did not see), so that the host's figures stay whole.
"""

from __future__ import annotations

import json
import mmap
import os
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any

LANE_TYPE = "_lane"
LANE_PREFIX = b'{"type":"_lane"'  # how the engine's compact JSON of a lane message starts
BLOCKS = b"blocks\n"
MAX_BLOCKS = 64
LINE_MAX = 1 << 16


def ctl_path(engine_socket: Path) -> Path:
    """The engine's control socket, beside its socket for client connections."""
    return engine_socket.with_name(engine_socket.name + ".ctl")


@dataclass(frozen=True)
class Lane:
    """A seat served by the gateway: where its hand and CORNER are in which block, the
    seat's occupant, its reach box and the client's CORNER interval and binary rate."""

    room: str
    block: int
    slot: int
    seat: int
    occupant: int
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    corner_interval: float  # s (0: every frame)
    binary_rate: float  # messages a second (the engine's Limits.binary_rate)
    binary_burst: float


def lane_message(lane: Lane | None) -> dict[str, Any]:
    """The engine's message opening a lane (None: closing it)."""
    if lane is None:
        return {"type": LANE_TYPE, "seat": None}
    return {"type": LANE_TYPE, "seat": lane.seat, "room": lane.room, "block": lane.block,
            "slot": lane.slot, "occupant": lane.occupant, "lo": list(lane.lo),
            "hi": list(lane.hi), "corner_interval": lane.corner_interval,
            "binary_rate": lane.binary_rate, "binary_burst": lane.binary_burst}


def parse_lane(payload: bytes) -> Lane | None:
    """A lane message's payload as the gateway reads it (None: the lane is closed)."""
    m = json.loads(payload)
    if m.get("seat") is None:
        return None
    return Lane(str(m["room"]), int(m["block"]), int(m["slot"]), int(m["seat"]),
                int(m["occupant"]), tuple(map(float, m["lo"])), tuple(map(float, m["hi"])),
                float(m["corner_interval"]), float(m["binary_rate"]),
                float(m["binary_burst"]))


def send_blocks(sock: socket.socket, blocks: list[tuple[int, int, int]]) -> None:
    """The engine's answer to ``BLOCKS``: ``blocks`` as (id, memfd, bytes)."""
    line = json.dumps({"blocks": [{"id": i, "bytes": n} for i, _, n in blocks]}).encode()
    socket.send_fds(sock, [line + b"\n"], [fd for _, fd, _ in blocks])


def receive_blocks(sock: socket.socket) -> dict[int, mmap.mmap]:
    """The gateway's side of ``BLOCKS`` (a blocking socket): each block mapped read/write,
    by id."""
    sock.sendall(BLOCKS)
    data, fds, _, _ = socket.recv_fds(sock, LINE_MAX, MAX_BLOCKS)
    try:
        if not data.endswith(b"\n"):
            raise ConnectionError("the engine's answer to BLOCKS was cut short")
        named = json.loads(data)["blocks"]
        if len(named) != len(fds):
            raise ConnectionError(f"the engine named {len(named)} blocks and passed {len(fds)}")
        return {int(b["id"]): mmap.mmap(fd, int(b["bytes"])) for b, fd in zip(named, fds,
                                                                               strict=True)}
    finally:
        for fd in fds:
            os.close(fd)


def counts_line(counts: dict[str, int]) -> bytes:
    """A gateway's report: its totals since it connected (the engine adds the increase)."""
    return json.dumps({"counts": counts}, separators=(",", ":")).encode() + b"\n"
