"""``clothball bench --admit``: how many rooms the server admits before its own measure says
it is at capacity (admission control, ``server/headroom.py``).

A server in a process of its own (``clothball host --workers 1``, default limits; its show
room runs too, with no bots); rooms of the scene are created one at a time, each watched by
one spectator (so it runs), ``--admit-settle`` seconds apart, until the server answers
``server_busy``. Printed: the rooms admitted, the refusal's reason, and the server's own
measure (frame lateness, skipped frames, CPU) at each step.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

from ...game.net.client import NetClient, ServerError
from ..hostproc import start_host, stats, stop_host


def configure_admit_flags(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("admission bench (--admit)")
    g.add_argument("--admit", action="store_true",
                   help="rooms (each watched) the server admits before refusing server_busy")
    g.add_argument("--admit-settle", type=float, default=5.0, metavar="S",
                   help="--admit: seconds between rooms (default %(default)s)")
    g.add_argument("--admit-max", type=int, default=30, metavar="K",
                   help="--admit: stop at K rooms (default %(default)s)")


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


def run_admit(args: argparse.Namespace) -> int:
    scene = args.scene or "classic"
    with tempfile.TemporaryDirectory() as tmp:
        proc, url = start_host(Path(tmp) / "data", "--scene", scene,
                               "--limit", f"rooms_per_address={args.admit_max + 1}",
                               "--limit", f"max_rooms={args.admit_max + 1}")
        if url is None:
            print(f"clothball bench: the server did not start (exit {proc.returncode})",
                  file=sys.stderr)
            return 1
        try:
            result = asyncio.run(_admit(url, args))
        finally:
            stop_host(proc)
    result["scene"] = scene
    print(f"admitted {result['admitted']} rooms of {scene}; then: "
          f"{result['refused'] or 'never refused'}", file=sys.stderr)
    print(json.dumps({k: v for k, v in result.items() if k != "steps"}))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0
