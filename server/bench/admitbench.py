"""``clothball bench --admit``: how many rooms the server admits before its own measure says
it is at capacity (admission control, ``server/headroom.py``).

A server in a process of its own (``clothball host --workers 1``, default limits; its show
room runs too, with no bots); rooms of the scene are created one at a time, each watched by
one spectator (so it runs), ``--admit-settle`` seconds apart, until the server answers
``server_busy``. Printed: the rooms admitted, the refusal's reason, and the server's own
measure (frame lateness, skipped frames, CPU) at each step.

``--admit-burst K``: issue 40's burst instead: ``clothball host --bots 4`` (its default
scene), K ``create_room`` at once from 8 loopback addresses, each admitted room watched,
and the show room's pace (frames stepped over wall time) every 2 s.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

from websockets.asyncio.client import connect

from ...game.net.client import NetClient, ServerError
from ...game.wire.protocol import PROTOCOL_VERSION
from ..hostproc import bench_host, stats


def configure_admit_flags(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("admission bench (--admit)")
    g.add_argument("--admit", action="store_true",
                   help="rooms (each watched) the server admits before refusing server_busy")
    g.add_argument("--admit-settle", type=float, default=5.0, metavar="S",
                   help="--admit: seconds between rooms (default %(default)s)")
    g.add_argument("--admit-max", type=int, default=30, metavar="K",
                   help="--admit: stop at K rooms (default %(default)s)")
    g.add_argument("--admit-burst", type=int, default=0, metavar="K",
                   help="--admit: instead, K create_room at once from 8 loopback addresses "
                        "to a host with four bots in its show room (issue 40: 32); printed: "
                        "rooms admitted and refused, and the show room's pace (frames "
                        "stepped over real time) every 2 s for --admit-burst-s")
    g.add_argument("--admit-burst-s", type=float, default=20.0, metavar="S",
                   help="--admit-burst: seconds the show room is watched (default %(default)s)")


async def _admit(url: str, args: argparse.Namespace) -> dict[str, Any]:
    owner = await NetClient.connect(url, name="owner")
    clients = [owner]
    steps = []
    refused = None
    try:
        for k in range(args.admit_max):
            try:
                made = await owner.request("create_room", name=f"a{k}")
            except ServerError as e:
                refused = e.message
                break
            clients.append(await NetClient.connect(url, role="spectator", room=made["room"],
                                                   decode_mesh=False))
            await asyncio.sleep(args.admit_settle)
            h = (await asyncio.to_thread(stats, url))["headroom"]
            steps.append({"rooms": k + 1, **h})
            print(f"{k + 1:>3} rooms  lateness p99 {h['lateness_p99_ms']:6.2f} ms  skipped "
                  f"{h['skipped_frames']:>4}  CPU {h['cpu_cores']:.2f} cores  "
                  f"{'busy' if h['busy'] else 'room to spare'}", file=sys.stderr, flush=True)
    finally:
        for c in clients:
            await c.close()
    return {"bench": "admit", "admitted": len(steps), "refused": refused, "steps": steps}


BURST_ADDRESSES = 8
PACE_SAMPLE_S = 2.0


async def _burst(url: str, args: argparse.Namespace) -> dict[str, Any]:
    """``args.admit_burst`` create_room at once from 8 addresses; each admitted room watched;
    the show room's pace sampled."""
    # Raw connections: each from an address of its own (the per-address limits).
    makers = []
    for k in range(BURST_ADDRESSES):
        ws = await connect(url, local_addr=(f"127.0.0.{2 + k}", 0), compression=None)
        await ws.send(json.dumps({"type": "hello", "version": PROTOCOL_VERSION,
                                  "name": f"maker{k}", "id": 0}))
        makers.append(ws)
    clients: list[Any] = []
    try:
        for k in range(args.admit_burst):
            await makers[k % BURST_ADDRESSES].send(json.dumps(
                {"type": "create_room", "name": f"b{k}", "id": 1 + k}))
        replies = [await _reply(makers[k % BURST_ADDRESSES], 1 + k)
                   for k in range(args.admit_burst)]
        made = [r["room"] for r in replies if r["type"] == "room_created"]
        refused = [r for r in replies if r["type"] == "error"]
        codes = sorted({str(e.get("code")) for e in refused})
        for rid in made:
            clients.append(await NetClient.connect(url, role="spectator", room=rid,
                                                   decode_mesh=False))
        print(f"{len(made)} rooms admitted, {len(refused)} refused ({', '.join(codes)}); "
              f"{refused[0].get('message') if refused else ''}", file=sys.stderr, flush=True)
        paces = []
        loop = asyncio.get_running_loop()
        st = await asyncio.to_thread(stats, url)
        frames, t = st["rooms"]["main"]["frames"], loop.time()
        while len(paces) * PACE_SAMPLE_S < args.admit_burst_s:
            await asyncio.sleep(PACE_SAMPLE_S)
            st = await asyncio.to_thread(stats, url)
            f2, t2 = st["rooms"]["main"]["frames"], loop.time()
            pace = (f2 - frames) * FRAME_DT / (t2 - t)
            paces.append(pace)
            frames, t = f2, t2
            h = st["headroom"]
            print(f"show room {pace:5.2f}x real time  skipped {h['skipped_frames']:>5}  "
                  f"CPU {h['cpu_cores']:.2f} cores  {'busy' if h['busy'] else ''}",
                  file=sys.stderr, flush=True)
    finally:
        for c in clients:
            await c.close()
        for ws in makers:
            await ws.close()
    return {"bench": "admit-burst", "asked": args.admit_burst, "admitted": len(made),
            "refused": len(refused), "codes": codes, "paces": paces,
            "min_pace": min(paces) if paces else None,
            "room_cost": st["headroom"]["room_cost"]}


FRAME_DT = 0.001  # the shipped scenes' frame (1 ms)


async def _reply(ws: Any, rid: int) -> dict[str, Any]:
    """The reply to request ``rid`` (other messages skipped)."""
    while True:
        msg = json.loads(await asyncio.wait_for(ws.recv(), 30))
        if msg.get("re") == rid:
            return dict(msg)


def _on_a_host(bench: Callable[[str], Coroutine[Any, Any, dict[str, Any]]],
               *host_args: str) -> dict[str, Any] | None:
    """``bench(url)`` run against a ``clothball host`` of its own (``host_args``), stopped
    after; None (said) when the host did not start."""
    with bench_host(*host_args) as url:
        return None if url is None else asyncio.run(bench(url))


def run_admit(args: argparse.Namespace) -> int:
    if args.admit_burst:
        return _run_burst(args)
    scene = args.scene or "classic"
    result = _on_a_host(lambda url: _admit(url, args), "--scene", scene,
                        "--limit", f"rooms_per_address={args.admit_max + 1}",
                        "--limit", f"max_rooms={args.admit_max + 1}")
    if result is None:
        return 1
    result["scene"] = scene
    print(f"admitted {result['admitted']} rooms of {scene}; then: "
          f"{result['refused'] or 'never refused'}", file=sys.stderr)
    print(json.dumps({k: v for k, v in result.items() if k != "steps"}))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


def _run_burst(args: argparse.Namespace) -> int:
    scene = args.scene
    result = _on_a_host(lambda url: _burst(url, args), "--scene", scene, "--bots", "4")
    if result is None:
        return 1
    result["scene"] = scene
    print(f"{result['admitted']} of {result['asked']} rooms of {scene} admitted; the show "
          f"room's slowest 2 s: {result['min_pace']:.2f}x real time", file=sys.stderr)
    print(json.dumps(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0
