"""``clothball bench --empty-rooms N,N,...``: the show room's rate while N rooms with nobody
in them exist.

For each N: a server in a process of its own (``clothball host --bots 4 --workers 1``, the
show room played by four bots), N rooms created over the websocket by a client that then
leaves them; one spectator of the show room counts its MESH messages (30 Hz is the target)
and the server's own counters give its frame lateness and skipped frames. Nothing is
timed in-process with the server.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ...game.net.client import NetClient
from ..hostproc import start_host, stats, stop_host

MESH_TARGET_HZ = 30.0


def configure_empty_flags(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("empty-rooms bench (--empty-rooms)")
    g.add_argument("--empty-rooms", metavar="N,N,...", default=None,
                   help="the show room's mesh rate while N empty rooms exist (e.g. 0,10,30)")
    g.add_argument("--empty-seconds", type=float, default=10.0, metavar="S",
                   help="--empty-rooms: seconds measured per N (default %(default)s)")


def _start_host(data: Path, rooms: int) -> tuple[subprocess.Popen[str], str]:
    # Enough rooms for one address (the per-address limit is not what is measured), and
    # rooms that stay open while measured.
    proc, url = start_host(data, "--scene", "classic", "--bots", "4",
                           "--limit", f"max_rooms={rooms + 4}",
                           "--limit", f"rooms_per_address={rooms + 1}",
                           "--limit", "room_idle_close_s=3600")
    if url is None:
        raise RuntimeError(f"the server did not start (exit {proc.returncode})")
    return proc, url


async def _make_rooms(url: str, n: int) -> None:
    """N rooms made by one client, which then leaves: nobody is in them."""
    c = await NetClient.connect(url, name="maker")
    for k in range(n):
        await c.request("create_room", name=f"empty{k}")
    await c.close()


async def _measure(url: str, seconds: float) -> dict[str, float]:
    spec = await NetClient.connect(url, name="probe", role="spectator", room="main",
                                   decode_mesh=False)
    await asyncio.sleep(2.0)  # settle
    n0, t0 = spec.counts["mesh"], time.perf_counter()
    s0 = stats(url)
    await asyncio.sleep(seconds)
    n1, t1 = spec.counts["mesh"], time.perf_counter()
    s1 = stats(url)
    await spec.close()
    room, room0 = s1["rooms"]["main"], s0["rooms"]["main"]
    wall = t1 - t0
    return {"mesh_hz": (n1 - n0) / wall,
            "lateness_p99_ms": float(room["lateness_ms"].get("p99", float("nan"))),
            "skipped_frames": float(room["skipped_frames"] - room0["skipped_frames"]),
            "server_cores": (s1["cpu_s"] - s0["cpu_s"]) / wall}


def run_empty(args: argparse.Namespace) -> int:
    try:
        counts = [int(x) for x in str(args.empty_rooms).split(",") if x.strip()]
        if not counts or min(counts) < 0 or max(counts) > 500:
            raise ValueError
    except ValueError:
        print(f"clothball bench: --empty-rooms: a list of room counts in 0..500, got "
              f"{args.empty_rooms!r}", file=sys.stderr)
        return 2
    rows = []
    print(f"{'empty rooms':>11}  {'main mesh Hz':>12}  {'lateness p99 ms':>15}  "
          f"{'skipped':>7}  {'server cores':>12}", file=sys.stderr)
    for n in counts:
        with tempfile.TemporaryDirectory() as tmp:
            proc, url = _start_host(Path(tmp), n)
            try:
                asyncio.run(_make_rooms(url, n))
                got = asyncio.run(_measure(url, args.empty_seconds))
            finally:
                stop_host(proc)
        row = {"empty_rooms": n, **got, "held": got["mesh_hz"] >= MESH_TARGET_HZ - 1.0}
        rows.append(row)
        print(f"{n:>11}  {got['mesh_hz']:>12.1f}  {got['lateness_p99_ms']:>15.2f}  "
              f"{got['skipped_frames']:>7.0f}  {got['server_cores']:>12.2f}", file=sys.stderr)
    print(json.dumps({"bench": "empty-rooms", "seconds": args.empty_seconds, "rows": rows}))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0
