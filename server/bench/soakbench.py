"""``clothball bench --soak``: the server under ordinary use carried far, sampled for growth.

A server in a process of its own (``clothball host --bots 4 --workers 1``: the show room's
four bots play match after match, every round recorded) with a small replay retention
(``--soak-retention-mib``, so pruning is reached within the first minutes), four spectators
of the show room and a downloader fetching the newest replay again and again. Every
``--soak-every`` seconds the bench samples the server process's resident memory and open
files (``/proc``), the bytes under its data directory and the rounds saved. At the end it
fits the memory and disk slopes over the second half of the run (after warm-up and once
retention is reached): flat is the target.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from ...game.net.client import NetClient
from ..hostproc import get, http_base, start_host, stats, stop_host


def configure_soak_flags(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("soak bench (--soak)")
    g.add_argument("--soak", action="store_true",
                   help="run a 4-bot match, spectators and a downloader for a fixed time, "
                        "sampling the server's memory, open files and disk")
    g.add_argument("--soak-seconds", type=float, default=600.0, metavar="S",
                   help="--soak: how long (default %(default)s)")
    g.add_argument("--soak-every", type=float, default=10.0, metavar="S",
                   help="--soak: seconds between samples (default %(default)s)")
    g.add_argument("--soak-rooms", type=int, default=3, choices=range(1, 9), metavar="K",
                   help="--soak: rooms of four bots playing, the show room included "
                        "(default %(default)s: K rooms for T seconds record what one room "
                        "records in K*T)")
    g.add_argument("--soak-retention-mib", type=float, default=16.0, metavar="MIB",
                   help="--soak: the server's replay retention (default %(default)s MiB)")


def _proc(pid: int) -> tuple[float, int]:
    """Resident memory (MiB) and open file descriptors of a process."""
    rss = 0.0
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) / 1024
    return rss, len(os.listdir(f"/proc/{pid}/fd"))


def _disk(path: Path) -> float:
    """MiB of files under ``path``."""
    total = 0
    for root, _dirs, files in os.walk(path):
        for name in files:
            try:
                total += os.stat(os.path.join(root, name)).st_size
            except OSError:
                pass
    return total / 2**20


async def _download_forever(http: str, stop: asyncio.Event, counts: dict[str, int]) -> None:
    while not stop.is_set():
        try:
            rows = json.loads(await asyncio.to_thread(get, f"{http}/api/replays?limit=1"))
            if rows.get("replays"):
                rid = rows["replays"][0]["id"]
                data = await asyncio.to_thread(get, f"{http}/api/replays/{rid}")
                counts["downloads"] += 1
                counts["bytes"] += len(data)
        except OSError:
            counts["failed"] += 1  # pruned between the listing and the download, say
        await asyncio.sleep(0.5)


async def _soak(url: str, proc: subprocess.Popen[str], data: Path,
                args: argparse.Namespace) -> dict[str, Any]:
    http = http_base(url)
    rooms = ["main"]
    owner = await NetClient.connect(url, name="owner")
    for k in range(args.soak_rooms - 1):
        made = await owner.request("create_room", name=f"soak{k}", autoplay=True)
        rooms.append(made["room"])
        await owner.join(made["room"], role="spectator")
        for seat in range(4):
            await owner.request("add_bot", seat=seat)
        await owner.request("leave")
    # Four spectators of the show room, one of each other room (a room nobody watches
    # sleeps, and records nothing).
    specs = [await NetClient.connect(url, name=f"s{k}", role="spectator", room="main",
                                     decode_mesh=False) for k in range(4)]
    specs += [await NetClient.connect(url, name=f"w{k}", role="spectator", room=r,
                                      decode_mesh=False) for k, r in enumerate(rooms[1:])]
    specs.append(owner)
    stop = asyncio.Event()
    counts = {"downloads": 0, "bytes": 0, "failed": 0}
    downloader = asyncio.create_task(_download_forever(http, stop, counts))
    samples = []
    t0 = time.monotonic()
    try:
        while (t := time.monotonic() - t0) < args.soak_seconds:
            rss, fds = _proc(proc.pid)
            now = await asyncio.to_thread(stats, url)
            s = {"t_s": round(t, 1), "rss_mib": round(rss, 2), "open_files": fds,
                 "disk_mib": round(_disk(data), 2), "rounds_saved": now["rounds_saved"]}
            samples.append(s)
            print(f"{s['t_s']:>8.0f} s  RSS {s['rss_mib']:>7.1f} MiB  files {fds:>4}  disk "
                  f"{s['disk_mib']:>7.1f} MiB  rounds {s['rounds_saved']:>5}  downloads "
                  f"{counts['downloads']:>5}", file=sys.stderr, flush=True)
            await asyncio.sleep(args.soak_every)
    finally:
        stop.set()
        await downloader
        for c in specs:
            await c.close()
    late = [s for s in samples if s["t_s"] >= args.soak_seconds / 2]

    def slope(key: str) -> float:  # per minute, over the second half
        if len(late) < 2:
            return float("nan")
        t = np.array([s["t_s"] for s in late]) / 60.0
        return float(np.polyfit(t, np.array([s[key] for s in late], dtype=float), 1)[0])

    return {"bench": "soak", "seconds": args.soak_seconds,
            "retention_mib": args.soak_retention_mib, "samples": samples,
            "rss_mib_per_min_second_half": slope("rss_mib"),
            "open_files_per_min_second_half": slope("open_files"),
            "disk_mib_per_min_second_half": slope("disk_mib"),
            "disk_mib_max": max(s["disk_mib"] for s in samples),
            "rss_mib_max": max(s["rss_mib"] for s in samples),
            "rounds_saved": samples[-1]["rounds_saved"], **counts}


def run_soak(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "data"
        proc, url = start_host(data, "--scene", "classic", "--bots", "4", "--limit",
                               f"replays_max_mib={args.soak_retention_mib}")
        if url is None:
            print(f"clothball bench: the server did not start (exit {proc.returncode})",
                  file=sys.stderr)
            return 1
        try:
            result = asyncio.run(_soak(url, proc, data, args))
        finally:
            stop_host(proc)
    print(f"soak {args.soak_seconds:g} s: RSS max {result['rss_mib_max']:.1f} MiB, slope "
          f"{result['rss_mib_per_min_second_half']:+.3f} MiB/min (second half); disk max "
          f"{result['disk_mib_max']:.1f} MiB (retention {args.soak_retention_mib:g} MiB), "
          f"slope {result['disk_mib_per_min_second_half']:+.3f} MiB/min; "
          f"{result['rounds_saved']} rounds saved, {result['downloads']} downloads",
          file=sys.stderr)
    print(json.dumps({k: v for k, v in result.items() if k != "samples"}))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0
