"""``clothball bench --index``: the replay index's HTTP queries at scale (issue 22).

A data directory with ``--index-rounds`` indexed rounds (default 100 000: a busy public room
``main`` with bot seats, 200 other public rooms, 20 private ones, a few thousand player
names) is served by a game server in a process of its own. Measured from this process:

1. every kind of query ``/api/replays`` answers (first page, a deep page, a room, a
   private room with its code, a common and a rare player, player and room, a download),
   one at a time: answer time p50 / p99 / max, "warm" (asked again: the count of rows is
   remembered) and "cold" (another connection indexes a round before each, as the rooms
   do every few seconds: nothing remembered);
2. ``/healthz`` answer time while ``--index-clients`` clients (a process of their own) send
   player queries as fast as they are answered, once with the per-address rate limit lifted
   (the index's threads saturated) and once with the default limits.

Targets: every query's p99 <= 20 ms; ``/healthz`` p99 under load <= 50 ms.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..storage.index import access_key
from ..storage.sqlite import SqliteIndex

TARGET_QUERY_MS = 20.0
TARGET_HEALTHZ_MS = 50.0
PRIVATE_CODE = "bench-code"


def configure_index_flags(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("index bench (--index)")
    g.add_argument("--index-rounds", type=int, default=100_000,
                   help="rounds in the index (default %(default)s)")
    g.add_argument("--index-clients", type=int, default=60,
                   help="concurrent query clients for the /healthz test (default %(default)s)")
    g.add_argument("--index-seconds", type=float, default=10.0,
                   help="duration of each /healthz-under-load run (default %(default)s)")


def fill(data: Path, n: int, seed: int = 1) -> dict[str, str]:
    """An index of ``n`` rounds under ``data``; the ids and names the queries use."""
    from ...game.wire.replay import write_replay

    rng = random.Random(seed)
    store = SqliteIndex(data)
    names = [f"player{i}" for i in range(5000)]
    batch: list[tuple[dict[str, Any], str, int]] = []
    for i in range(n):
        kind = rng.random()
        if kind < 0.6:
            room, seats = "main", [f"bot-{s}" for s in range(4)]
        else:
            private = kind > 0.98
            room = f"{'p' if private else 'r'}{rng.randrange(20 if private else 200)}"
            seats = rng.sample(names, rng.randint(1, 4))
        header = _header(i, room, seats)
        batch.append((header, f"{header['id']}.cbr", 1000))
        if len(batch) == 5000:
            store.index_many(batch)
            batch = []
    store.index_many(batch)
    last = _header(n - 1, "main", [f"bot-{s}" for s in range(4)])
    write_replay(store.replays / f"{last['id']}.cbr", last, [])
    store.close()
    return {"download": last["id"], "rare": names[17]}


def _header(i: int, room: str, seats: list[str]) -> dict[str, Any]:
    """Round ``i``'s header (ended 30 s after round ``i - 1``)."""
    t = 1.7e9 + i * 30.0
    header = {
        "id": f"20260101-000000-{i:08d}", "room_id": room, "room_name": room,
        "scene": "classic", "round": i,
        "players": [{"seat": s, "kind": "human", "name": nm} for s, nm in enumerate(seats)],
        "scores": [0, 0, 0, 0], "started_at": t, "ended_at": t + 25.0, "duration_s": 25.0,
    }
    if room.startswith("p"):
        header["access"] = access_key(room, PRIVATE_CODE)
    return header


def serve(data: Path, limits: list[str]) -> None:
    """The server process: prints its port, serves until killed."""
    from ...game.sim.scene import Scene
    from ..app import GameServer, ServerConfig
    from ..limits import Limits

    lim = Limits(replays_max_days=1e6)  # the bench's rounds are dated 2023: keep them
    for text in limits:
        lim = lim.with_setting(text)

    async def main() -> None:
        srv = GameServer(ServerConfig(data, scenes={"classic": Scene.load("classic")}, port=0,
                                      default_room=False, limits=lim))
        await srv.start()
        print(srv.port, flush=True)
        await asyncio.Event().wait()

    asyncio.run(main())


async def _get(port: int, target: str) -> tuple[int, float]:
    """One GET on a fresh connection (the server closes each): status, seconds taken."""
    t = time.perf_counter()
    r, w = await asyncio.open_connection("127.0.0.1", port)
    w.write(f"GET {target} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
    data = await r.read()
    w.close()
    return int(data.split(b" ", 2)[1]), time.perf_counter() - t


def hammer(port: int, clients: int, seconds: float) -> None:
    """The load process: ``clients`` loops of player queries; prints the answers' count."""
    async def one(k: int, end: float, counts: dict[int, int]) -> None:
        while time.perf_counter() < end:
            status, _ = await _get(port, f"/api/replays?player=bot-{k % 4}&offset={k}")
            counts[status] = counts.get(status, 0) + 1

    async def main() -> None:
        counts: dict[int, int] = {}
        end = time.perf_counter() + seconds
        await asyncio.gather(*(one(k, end, counts) for k in range(clients)))
        print(json.dumps(counts), flush=True)

    asyncio.run(main())


def _ms(xs: list[float]) -> dict[str, float]:
    a = np.array(xs) * 1e3
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
            "max": float(a.max()), "n": len(xs)}


def _start_server(data: Path, limits: list[str]) -> tuple[subprocess.Popen[str], int]:
    cmd = [sys.executable, "-m", "clothball.server.bench.indexbench", "--role", "server",
           "--data", str(data), *[a for lim in limits for a in ("--limit", lim)]]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env=os.environ.copy())
    assert proc.stdout is not None
    return proc, int(proc.stdout.readline())


def _healthz_under_load(port: int, clients: int, seconds: float) -> dict[str, Any]:
    load = subprocess.Popen(
        [sys.executable, "-m", "clothball.server.bench.indexbench", "--role", "hammer", "--port",
         str(port), "--clients", str(clients), "--seconds", str(seconds)],
        stdout=subprocess.PIPE, text=True)

    async def probe() -> list[float]:
        await asyncio.sleep(0.5)  # the clients are under way
        out, end = [], time.perf_counter() + seconds - 1.0
        while time.perf_counter() < end:
            status, dt = await _get(port, "/healthz")
            assert status == 200
            out.append(dt)
            await asyncio.sleep(0.02)
        return out

    times = asyncio.run(probe())
    answers, _ = load.communicate(timeout=seconds + 60)
    return {"healthz_ms": _ms(times), "query_answers": json.loads(answers)}


def run(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory(prefix="clothball-indexbench-") as tmp:
        data = Path(tmp)
        t = time.perf_counter()
        ids = fill(data, args.index_rounds)
        print(f"indexed {args.index_rounds} rounds in {time.perf_counter() - t:.1f} s")
        n = args.index_rounds
        queries = {
            "first page": "/api/replays",
            "deep page": f"/api/replays?offset={max(0, n // 2 - 100)}&limit=100",
            "public room (main)": "/api/replays?room=main",
            "small room": "/api/replays?room=r17",
            "private room + code": f"/api/replays?room=p3&code={PRIVATE_CODE}",
            "common player": "/api/replays?player=bot-0",
            "rare player": f"/api/replays?player={ids['rare']}",
            "player + room": "/api/replays?player=bot-1&room=main",
            "download": f"/api/replays/{ids['download']}",
        }
        results: dict[str, Any] = {"rounds": n, "queries": {}}
        proc, port = _start_server(data, ["index_rate=1000000", "index_burst=1000000"])
        writer = SqliteIndex(data)  # another connection, as a second server process would be
        extra = n
        try:
            for name, target in queries.items():
                for cold in (False, True):
                    times = []
                    for _ in range(30):
                        if cold:  # a round indexed first: nothing remembered helps
                            writer.index_many([(_header(extra, "r0", ["extra"]), "x.cbr", 1)])
                            extra += 1
                        status, dt = asyncio.run(_get(port, target))
                        assert status == 200, (name, status)
                        times.append(dt)
                    results["queries"][f"{name} ({'cold' if cold else 'warm'})"] = _ms(times)
            results["load_unlimited"] = _healthz_under_load(port, args.index_clients,
                                                            args.index_seconds)
        finally:
            writer.close()
            proc.kill()
            proc.wait()
        proc, port = _start_server(data, [])
        try:
            results["load_default_limits"] = _healthz_under_load(port, args.index_clients,
                                                                 args.index_seconds)
        finally:
            proc.kill()
            proc.wait()
    print(f"\n{'query':<29} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8}")
    for name, r in results["queries"].items():
        print(f"{name:<29} {r['p50']:8.2f} {r['p99']:8.2f} {r['max']:8.2f}")
    for key in ("load_unlimited", "load_default_limits"):
        h = results[key]["healthz_ms"]
        print(f"/healthz, {args.index_clients} query clients ({key[5:]}): p50 {h['p50']:.2f} "
              f"p99 {h['p99']:.2f} max {h['max']:.2f} ms; query answers by status "
              f"{results[key]['query_answers']}")
    worst = max(r["p99"] for r in results["queries"].values())
    hz = max(results[k]["healthz_ms"]["p99"] for k in ("load_unlimited", "load_default_limits"))
    print(f"\ntargets: every query p99 <= {TARGET_QUERY_MS:g} ms: "
          f"{'met' if worst <= TARGET_QUERY_MS else 'MISSED'} (worst {worst:.2f}); /healthz "
          f"p99 under load <= {TARGET_HEALTHZ_MS:g} ms: "
          f"{'met' if hz <= TARGET_HEALTHZ_MS else 'MISSED'} (worst {hz:.2f})")
    if args.json:
        Path(args.json).write_text(json.dumps({**results, "argv": sys.argv[1:]}, indent=2))
        print(f"wrote {args.json}")
    return 0


def main() -> None:
    p = argparse.ArgumentParser(description="the index bench's helper processes")
    p.add_argument("--role", choices=("server", "hammer"), required=True)
    p.add_argument("--data", type=Path)
    p.add_argument("--limit", action="append", default=[])
    p.add_argument("--port", type=int)
    p.add_argument("--clients", type=int, default=60)
    p.add_argument("--seconds", type=float, default=10.0)
    a = p.parse_args()
    if a.role == "server":
        serve(a.data, a.limit)
    else:
        hammer(a.port, a.clients, a.seconds)


if __name__ == "__main__":
    main()
