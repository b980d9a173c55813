"""``clothball bench --server``: the game server under load, on loopback.

Three processes so that each side's CPU is its own: the server (one room, CPU or CUDA
backend, n = 64 by default), the players (4 clients sending HIP at 1 kHz and timing how
long until a CORNER message echoes each HIP they sent), and the spectators (50 clients
counting MESH messages). Reported: frame lateness p50/p99 (how long after its wall-clock
deadline each frame's state was ready, from the server's own counters), HIP-to-corner
latency p50/p99 (client clock, send -> receipt of the CORNER that applied it), messages per
second in and out of the server, spectator mesh rates, and CPU use of each process.

``clothball bench --load``: how many rooms the server holds. Rooms of 4 player clients
(HIP at 1 kHz, playing a match) plus ``--load-spectators`` spectators each are added one at
a time (each room's clients in a process of their own) and measured for ``--load-seconds``,
until a target is missed: frame lateness p99 <= 5 ms in every room, no frame skipped, and
the server taking in at least 90 % of the HIPs offered. Reported per step: rooms, clients,
messages a second in and out, lateness, CPU, the load average.

``clothball bench --load --cluster``: the same with 1, 2 and 3 server processes joined as
the hosts of a cluster through a Redis the bench starts (``redis-server`` on the PATH, a
free port of loopback): rooms are created through the first host, which places each on the
least-loaded one, and their clients connect through it too (redirected to the room's
host). Every step measures all the hosts; on one machine they share its cores with each
other and with the clients, which the figures say.

Run ``python -m clothball.server.loadbench --role server|spectators|room-clients ...`` only
through the bench; ``run(args)`` and ``run_load(args)`` start the others themselves.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from . import loops
from .hostproc import free_port, get_json, start_redis

TARGET_LATENCY_P99_MS = 5.0
TARGET_LATENESS_P99_MS = 5.0
TARGET_MESH_HZ = 30.0


def configure_server_flags(parser: argparse.ArgumentParser) -> None:
    """Flags of ``clothball bench --server`` (``--json`` is the bench's own)."""
    g = parser.add_argument_group("server bench (--server)")
    g.add_argument("--seconds", type=float, default=30.0,
                   help="measured duration of the server bench (default %(default)s)")
    g.add_argument("--spectators", type=int, default=50,
                   help="spectator clients (default %(default)s)")
    g.add_argument("--players", type=int, default=4, choices=range(1, 5),
                   help="player clients (default %(default)s)")
    g.add_argument("--hip-rate", type=float, default=1000.0,
                   help="HIP messages a second per player (default %(default)s)")
    g.add_argument("--server-n", type=int, default=64,
                   help="cloth nodes per side in the bench room (default %(default)s)")
    g.add_argument("--server-backend", default="cpu", choices=("auto", "cpu", "cuda"),
                   help="cloth backend of the bench room (default %(default)s)")
    g.add_argument("--server-loop", default=None, choices=loops.CHOICES,
                   help="the server process's event loop (default: $CLOTHBALL_LOOP, else "
                        "asyncio)")
    g.add_argument("--load-seconds", type=float, default=10.0,
                   help="--load: measured seconds per number of rooms (default %(default)s)")
    g.add_argument("--load-spectators", type=int, default=4,
                   help="--load: spectators per room (default %(default)s)")
    g.add_argument("--load-max-rooms", type=int, default=32,
                   help="--load: stop growing at this many rooms (default %(default)s)")
    g.add_argument("--workers", type=int, default=1, metavar="N",
                   help="--load: N server processes on one port, as `clothball host --workers "
                        "N` runs them (rooms placed on the least-loaded); default %(default)s")
    g.add_argument("--cluster", action="store_true",
                   help="--load: rooms held by 1, 2 and 3 hosts of a cluster on this machine, "
                        "joined through a Redis the bench starts (needs redis-server)")
    g.add_argument("--cluster-hosts", default="1,2,3", metavar="N,N,...",
                   help="--load --cluster: the numbers of hosts measured (default %(default)s)")


def configure(parser: argparse.ArgumentParser) -> None:
    """Stand-alone use (``python -m clothball.server.loadbench``)."""
    configure_server_flags(parser)
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--load", action="store_true", help="how many rooms the server holds")
    parser.add_argument("--role", choices=("bench", "server", "spectators", "room-clients"),
                        default="bench", help=argparse.SUPPRESS)
    parser.add_argument("--url", default="", help=argparse.SUPPRESS)
    parser.add_argument("--no-room", action="store_true", help=argparse.SUPPRESS)
    # A host's room directory: redis://... (--load --cluster) or a SQLite file (--workers).
    parser.add_argument("--directory", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--shared-port", type=int, default=None, help=argparse.SUPPRESS)


# --- the server process ------------------------------------------------------------------------


async def _serve(args: argparse.Namespace) -> None:
    from ..game.sim.scene import Scene
    from .app import GameServer
    from .limits import Limits
    from .room import RoomSettings

    sys.setswitchinterval(0.0005)
    scene = Scene.load("classic").with_changes({"cloth": {"n": args.server_n}})
    scene.name = "bench"
    cluster: dict[str, Any] = {}
    if getattr(args, "directory", None):  # a host of --load --cluster, or a --workers process
        from .directory import RedisDirectory, SqliteDirectory

        kind = RedisDirectory if args.directory.startswith("redis://") else SqliteDirectory
        cluster = {"directory": kind(args.directory), "host_id": f"bench-{os.getpid()}",
                   "shared_port": getattr(args, "shared_port", None)}
    with tempfile.TemporaryDirectory() as data:
        # Every client comes from 127.0.0.1: the per-address limits would stop the bench.
        limits = Limits(conns_per_address=100_000, rooms_per_address=100_000, max_rooms=1000,
                        max_clients=100_000, spectators_per_room=100_000)
        srv = GameServer(data, scenes={"bench": scene}, backend=args.server_backend,
                         host="127.0.0.1", port=0, default_room=not args.no_room,
                         room_settings=RoomSettings(first_to=99, bots_allowed=False,
                                                    unguarded=True),
                         limits=limits, **cluster)
        await srv.start()
        room = srv.main_room
        probe = room.sim if room is not None else None
        if probe is None:  # no room yet: a throw-away cloth says what a room will run
            from ..game.sim.cloth import Cloth

            probe = Cloth(scene, backend=args.server_backend, threads=1)
        print(json.dumps({"port": srv.port, "room": room.id if room is not None else None,
                          "backend": probe.backend, "substeps": probe.substeps,
                          "token": srv.host_token, "loop": loops.running()}), flush=True)
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        loop.add_signal_handler(signal.SIGTERM, stop.set)
        loop.add_signal_handler(signal.SIGINT, stop.set)
        await stop.wait()
        await srv.stop()


# --- spectators --------------------------------------------------------------------------------


async def _spectate(args: argparse.Namespace) -> None:
    from ..game.net.client import NetClient

    room = json.loads(args.url)["room"]
    url = json.loads(args.url)["ws"]
    clients = []
    for _ in range(args.spectators):
        clients.append(await NetClient.connect(url, role="spectator", room=room,
                                               decode_mesh=False))
    print(json.dumps({"ready": True}), flush=True)
    await asyncio.sleep(1.0)  # settle
    c0 = [c.counts["mesh"] for c in clients]
    cpu0, t0 = time.process_time(), time.perf_counter()
    await asyncio.sleep(args.seconds)
    dt = time.perf_counter() - t0
    rates = [(c.counts["mesh"] - n) / dt for c, n in zip(clients, c0, strict=True)]
    cpu = (time.process_time() - cpu0) / dt
    for c in clients:
        await c.close()
    print(json.dumps({"rates": rates, "cpu": cpu}), flush=True)


# --- players (this process) --------------------------------------------------------------------


async def _drive(i: int, p: Any, rate: float, stop_at: list[float], sent: list[int]) -> None:
    """Player ``i`` sends HIPs at ``rate`` Hz (a slow sine up and down its reach) until the
    loop time passes ``stop_at[0]``, counting them in ``sent[i]``."""
    reach = p.reach
    assert reach is not None
    loop = asyncio.get_running_loop()
    period = 1.0 / rate
    nxt = loop.time()
    phase = i * math.pi / 2
    # reach.from_unit((0, u, 0)) in plain floats (the same numbers: u is within [-1, 1]), so
    # that the players' process spends less of the machine the server is measured on.
    (cx, cy, cz), hy = reach.centre.tolist(), float(reach.half_extent[1])
    while loop.time() < stop_at[0]:
        t = loop.time()
        h = (cx, cy + 0.3 * math.sin(2 * math.pi * 0.5 * t + phase) * hy, cz)
        await p.send_hip(h)
        sent[i] += 1
        nxt += period
        delay = nxt - loop.time()
        if delay < -0.05:  # far behind: do not burst to catch up
            nxt = loop.time()
        await asyncio.sleep(max(0.0, delay))


async def _play(ws_url: str, room: str, n_players: int, rate: float, seconds: float,
                reset_stats: Any) -> dict[str, Any]:
    from ..game.net.client import NetClient

    players = [await NetClient.connect(ws_url, name=f"p{i}", role="player", room=room, seat=i,
                                       record_latency=True, mesh=False)
               for i in range(n_players)]
    for p in players:
        await p.request("ready", ready=True)
    sent = [0] * n_players
    loop = asyncio.get_running_loop()
    stop_at = [loop.time() + 1.0 + seconds]
    tasks = [asyncio.create_task(_drive(i, p, rate, stop_at, sent))
             for i, p in enumerate(players)]
    await asyncio.sleep(1.0)  # settle, then measure
    for p in players:
        p.latencies.clear()
    stats0 = await asyncio.to_thread(reset_stats)
    s0, c0 = list(sent), [p.counts["corner"] for p in players]
    cpu0, t0 = time.process_time(), time.perf_counter()
    await asyncio.gather(*tasks)
    dt = time.perf_counter() - t0
    cpu = (time.process_time() - cpu0) / dt
    lat = np.concatenate([np.array(p.latencies) for p in players]) * 1e3
    out = {
        "hip_rate_hz": [(s - s_) / dt for s, s_ in zip(sent, s0, strict=True)],
        "corner_rate_hz": [(p.counts["corner"] - c) / dt for p, c in zip(players, c0,
                                                                         strict=True)],
        "latency_ms": _pct(lat),
        "cpu": cpu,
        "stats0": stats0,
        "t0": t0,
    }
    for p in players:
        await p.close()
    return out


def _loop_flag(args: argparse.Namespace) -> list[str]:
    choice = getattr(args, "server_loop", None)
    return ["--server-loop", choice] if choice else []


def _pct(v: np.ndarray) -> dict[str, float]:
    if v.size == 0:
        return {"count": 0}
    p50, p99, p999 = np.percentile(v, [50, 99, 99.9])
    return {"count": int(v.size), "min": float(v.min()), "p50": float(p50), "p99": float(p99),
            "p999": float(p999), "max": float(v.max())}


def _server_info(server: subprocess.Popen[str]) -> tuple[dict[str, Any], str, str]:
    """What the bench's server process printed when it started; its HTTP and ws URLs."""
    assert server.stdout is not None
    info = json.loads(server.stdout.readline())
    return info, f"http://127.0.0.1:{info['port']}", f"ws://127.0.0.1:{info['port']}/ws"


def _stop_server(server: subprocess.Popen[str]) -> None:
    server.send_signal(signal.SIGTERM)
    try:
        server.wait(timeout=20)
    except subprocess.TimeoutExpired:
        server.kill()


def run(args: argparse.Namespace) -> int:
    """Run the whole bench (server, spectators and players) and print the figures."""
    role = getattr(args, "role", "bench")
    if role == "server":
        loops.run(_serve(args), args.server_loop)
        return 0
    if role == "spectators":
        asyncio.run(_spectate(args))
        return 0
    if role == "room-clients":
        asyncio.run(_room_clients(args))
        return 0
    if getattr(args, "load", False):
        return run_load(args)
    seconds = float(args.seconds)
    base = [sys.executable, "-m", "clothball.server.loadbench", "--server-n", str(args.server_n),
            "--server-backend", args.server_backend, "--seconds", str(seconds),
            "--spectators", str(args.spectators)]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    server = subprocess.Popen([*base, "--role", "server", *_loop_flag(args)],
                              stdout=subprocess.PIPE, text=True,
                              env=env)
    spect: subprocess.Popen[str] | None = None
    try:
        info, http, ws = _server_info(server)
        print(f"server bench: {args.players} players x {args.hip_rate:g} Hz HIP, "
              f"{args.spectators} spectators, {seconds:g} s, n={args.server_n}, "
              f"backend {info['backend']} ({info['substeps']} substeps/frame), "
              f"event loop {info['loop']}, "
              f"{os.cpu_count()} CPUs", file=sys.stderr)
        if args.spectators > 0:
            spect = subprocess.Popen(
                [*base, "--role", "spectators", "--url",
                 json.dumps({"ws": ws, "room": info["room"]})],
                stdout=subprocess.PIPE, text=True, env=env)
            assert spect.stdout is not None
            json.loads(spect.stdout.readline())  # connected
        players = asyncio.run(_play(ws, info["room"], args.players, args.hip_rate, seconds,
                                    lambda: get_json(f"{http}/api/stats?reset=1", info["token"])))
        stats0, t0 = players.pop("stats0"), players.pop("t0")
        stats1 = get_json(f"{http}/api/stats")
        dt = time.perf_counter() - t0
        spec_out = {"rates": [], "cpu": 0.0}
        if spect is not None:
            assert spect.stdout is not None
            spec_out = json.loads(spect.stdout.readline())
            spect.wait(timeout=30)
    finally:
        _stop_server(server)
        if spect is not None and spect.poll() is None:
            spect.kill()
    room = next(iter(stats1["rooms"].values()))
    room0 = next(iter(stats0["rooms"].values()))
    rates = np.array(spec_out["rates"]) if spec_out["rates"] else np.zeros(0)
    result = {
        "seconds": seconds,
        "players": args.players,
        "spectators": args.spectators,
        "hip_rate_target_hz": args.hip_rate,
        "n": args.server_n,
        "backend": info["backend"],
        "substeps": info["substeps"],
        "cpus": os.cpu_count(),
        "frame_lateness_ms": room["lateness_ms"],
        "skipped_frames": room["skipped_frames"] - room0["skipped_frames"],
        "frames": room["frames"] - room0["frames"],
        "hip_to_corner_ms": players["latency_ms"],
        "hip_rate_hz": players["hip_rate_hz"],
        "corner_rate_hz": players["corner_rate_hz"],
        "server_messages_in_per_s": (stats1["messages_in"] - stats0["messages_in"]) / dt,
        "server_messages_out_per_s": (stats1["messages_out"] - stats0["messages_out"]) / dt,
        "spectator_mesh_hz": _pct(rates) if rates.size else {"count": 0},
        "cpu_server_cores": (stats1["cpu_s"] - stats0["cpu_s"]) / dt,
        "cpu_players_cores": players["cpu"],
        "cpu_spectators_cores": spec_out["cpu"],
    }
    lat, late = result["hip_to_corner_ms"], result["frame_lateness_ms"]
    result["targets"] = {
        "hip_to_corner_p99_le_5ms": bool(lat.get("p99", math.inf) <= TARGET_LATENCY_P99_MS),
        "frame_lateness_p99_le_5ms": bool(late.get("p99", math.inf) <= TARGET_LATENESS_P99_MS),
        "all_spectators_30hz": bool(rates.size == 0 or rates.min() >= 0.95 * TARGET_MESH_HZ),
    }
    if _write_json(result, getattr(args, "json", None)):
        print(json.dumps(result, indent=2))
    else:
        _print(result)
    return 0


def _write_json(result: dict[str, Any], dest: object) -> bool:
    """``--json``: ``clothball bench --json FILE`` gives a path (the figures are written
    there, the summary still printed); ``python -m clothball.server.loadbench --json`` gives
    True (the figures are printed instead of the summary). True when they are to be
    printed."""
    if isinstance(dest, str | os.PathLike):
        Path(dest).write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {dest}")
        return False
    return dest is True


def _print(r: dict[str, Any]) -> None:
    def p(d: dict[str, float]) -> str:
        if not d.get("count"):
            return "no samples"
        return f"p50 {d['p50']:.2f}  p99 {d['p99']:.2f}  p99.9 {d['p999']:.2f}  max {d['max']:.2f}"

    mesh = r["spectator_mesh_hz"]
    ok = {True: "meets target", False: "MISSES target"}
    t = r["targets"]
    print(f"frame lateness (ms)       {p(r['frame_lateness_ms'])}   "
          f"[{ok[t['frame_lateness_p99_le_5ms']]}: p99 <= 5]")
    print(f"HIP -> corner state (ms)  {p(r['hip_to_corner_ms'])}   "
          f"[{ok[t['hip_to_corner_p99_le_5ms']]}: p99 <= 5]")
    print(f"frames                    {r['frames']} simulated, {r['skipped_frames']} skipped "
          "(fell further behind than the catch-up bound)")
    print("HIP sent (Hz/player)      " + ", ".join(f"{x:.0f}" for x in r["hip_rate_hz"]))
    print("CORNER recv (Hz/player)   " + ", ".join(f"{x:.0f}" for x in r["corner_rate_hz"]))
    rates = (f"min {mesh['min']:.1f}  p50 {mesh['p50']:.1f}  max {mesh['max']:.1f}"
             if mesh.get("count") else "none")
    print(f"spectator MESH (Hz)       {rates}   "
          f"[{ok[t['all_spectators_30hz']]}: every spectator >= 28.5 Hz]")
    print(f"server messages/s         in {r['server_messages_in_per_s']:.0f}  "
          f"out {r['server_messages_out_per_s']:.0f}")
    print(f"CPU (cores)               server {r['cpu_server_cores']:.2f}  "
          f"players {r['cpu_players_cores']:.2f}  spectators {r['cpu_spectators_cores']:.2f}"
          f"  (of {r['cpus']})")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m clothball.server.loadbench")
    configure(parser)
    return run(parser.parse_args(argv))



# --- clothball bench --load ---------------------------------------------------------------------


async def _room_clients(args: argparse.Namespace) -> None:
    """One room's clients: 4 players (ready, HIP at --hip-rate) and --load-spectators
    spectators, until stdin closes."""
    from ..game.net.client import NetClient

    where = json.loads(args.url)
    ws, room = where["ws"], where["room"]
    players = [await NetClient.connect(ws, name=f"p{i}", role="player", room=room, seat=i,
                                       mesh=False) for i in range(4)]
    spectators = [await NetClient.connect(ws, role="spectator", room=room, decode_mesh=False)
                  for _ in range(args.load_spectators)]
    for p in players:
        await p.request("ready", ready=True)
    sent = [0] * 4
    stop_at = [math.inf]
    tasks = [asyncio.create_task(_drive(i, p, args.hip_rate, stop_at, sent))
             for i, p in enumerate(players)]
    print(json.dumps({"ready": True}), flush=True)
    await asyncio.to_thread(sys.stdin.read)
    stop_at[0] = -math.inf
    await asyncio.gather(*tasks)
    for c in [*players, *spectators]:
        await c.close()


async def _create_room(ws: str) -> str:
    from ..game.net.client import NetClient

    c = await NetClient.connect(ws, name="load")
    try:
        made = await c.request("create_room", name="load", bots_allowed=False,
                               unguarded=True, first_to=99)
    finally:
        await c.close()
    return str(made["room"])


def _start_room(base: list[str], ws: str, env: dict[str, str]) -> subprocess.Popen[str]:
    """Creates a room through ``ws`` and starts its players and spectators in a process of
    their own; returns once they are connected and the room has settled."""
    room = asyncio.run(_create_room(ws))
    proc = subprocess.Popen([*base, "--role", "room-clients", "--url",
                             json.dumps({"ws": ws, "room": room})],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    assert proc.stdout is not None
    if not proc.stdout.readline():
        proc.kill()
        raise RuntimeError("a room's clients did not connect")
    time.sleep(1.0)  # settle
    return proc


def _stop_clients(clients: list[subprocess.Popen[str]]) -> None:
    """Ends the rooms' client processes (their stdin closing is their signal)."""
    for proc in clients:
        if proc.stdin is not None:
            proc.stdin.close()
    for proc in clients:
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()


def run_load(args: argparse.Namespace) -> int:
    """Add rooms one at a time until a target is missed; print (or --json) every step."""
    if getattr(args, "cluster", False):
        return run_load_cluster(args)
    if getattr(args, "workers", 1) < 1:
        print(f"clothball bench: --workers must be at least 1, got {args.workers}",
              file=sys.stderr)
        return 2
    if getattr(args, "workers", 1) > 1:
        return run_load_workers(args)
    seconds = float(args.load_seconds)
    base = [sys.executable, "-m", "clothball.server.loadbench", "--server-n", str(args.server_n),
            "--server-backend", args.server_backend, "--hip-rate", str(args.hip_rate),
            "--load-spectators", str(args.load_spectators)]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    load_before = os.getloadavg()
    server = subprocess.Popen([*base, "--role", "server", "--no-room", *_loop_flag(args)],
                              stdout=subprocess.PIPE,
                              text=True, env=env)
    clients: list[subprocess.Popen[str]] = []
    steps: list[dict[str, Any]] = []
    try:
        info, http, ws = _server_info(server)
        print(f"load bench: rooms of 4 players x {args.hip_rate:g} Hz HIP + "
              f"{args.load_spectators} spectators, {seconds:g} s a step, n={args.server_n}, "
              f"backend {info['backend']} ({info['substeps']} substeps/frame), "
              f"event loop {info['loop']}, "
              f"{os.cpu_count()} CPUs, load average {load_before[0]:.2f}", file=sys.stderr)
        for rooms in range(1, args.load_max_rooms + 1):
            clients.append(_start_room(base, ws, env))
            s0 = get_json(f"{http}/api/stats?reset=1", info["token"])
            c0, w0 = _cpu_seconds(clients), time.perf_counter()
            time.sleep(seconds)
            s1 = get_json(f"{http}/api/stats")
            step = _load_step(rooms, s0, s1, args)
            # The clients share the machine with the server: what they cost is reported.
            step["clients_cpu_cores"] = (_cpu_seconds(clients) - c0) / (time.perf_counter() - w0)
            steps.append(step)
            print(_load_line(step), file=sys.stderr, flush=True)
            if not step["met"]:
                break
    finally:
        _stop_clients(clients)
        _stop_server(server)
    held = [s for s in steps if s["met"]]
    result = {
        "n": args.server_n, "backend": info["backend"], "substeps": info["substeps"],
        "server_loop": info["loop"],
        "cpus": os.cpu_count(), "hip_rate_hz": args.hip_rate,
        "spectators_per_room": args.load_spectators, "seconds_per_step": seconds,
        "load_average_before": list(load_before),
        "held": held[-1] if held else None,
        "first_missed": next((s for s in steps if not s["met"]), None),
        "steps": steps,
    }
    if _write_json(result, getattr(args, "json", None)):
        print(json.dumps(result, indent=2))
    else:
        h = result["held"]
        print("held: " + (f"{h['rooms']} rooms, {h['clients']} clients, "
                          f"{h['messages_in_per_s']:.0f} msgs/s in, "
                          f"{h['messages_out_per_s']:.0f} out, lateness p99 "
                          f"{h['lateness_p99_ms']:.2f} ms" if h else "not even one room"))
    return 0


def _load_step(rooms: int, s0: dict[str, Any], s1: dict[str, Any], args: argparse.Namespace
               ) -> dict[str, Any]:
    dt = s1["uptime_s"] - s0["uptime_s"]
    per_room = s1["rooms"].values()
    p99 = max((r["lateness_ms"].get("p99", math.inf) for r in per_room), default=math.inf)
    p50 = max((r["lateness_ms"].get("p50", math.inf) for r in per_room), default=math.inf)
    skipped = sum(r["skipped_frames"] - s0["rooms"].get(k, {}).get("skipped_frames", 0)
                  for k, r in s1["rooms"].items())
    msgs_in = (s1["messages_in"] - s0["messages_in"]) / dt
    offered = 4 * args.hip_rate * rooms
    step = {
        "rooms": rooms,
        "clients": rooms * (4 + args.load_spectators),
        "messages_in_per_s": msgs_in,
        "messages_out_per_s": (s1["messages_out"] - s0["messages_out"]) / dt,
        "hip_offered_per_s": offered,
        "lateness_p50_ms": p50,
        "lateness_p99_ms": p99,
        "skipped_frames": skipped,
        "server_cpu_cores": (s1["cpu_s"] - s0["cpu_s"]) / dt,
        "load_average": os.getloadavg()[0],
    }
    step["met"] = bool(p99 <= TARGET_LATENESS_P99_MS and skipped == 0
                       and msgs_in >= 0.9 * offered)
    return step


def _cpu_seconds(procs: list[subprocess.Popen[str]]) -> float:
    """User + system CPU seconds of these processes so far (Linux /proc; else NaN)."""
    total = 0.0
    for p in procs:
        try:
            fields = Path(f"/proc/{p.pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return math.nan
        total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def _load_line(s: dict[str, Any]) -> str:
    return (f"{s['rooms']:3d} rooms {s['clients']:4d} clients  in {s['messages_in_per_s']:7.0f}/s"
            f" (of {s['hip_offered_per_s']:.0f})  out {s['messages_out_per_s']:7.0f}/s  lateness "
            f"p50 {s['lateness_p50_ms']:.2f} p99 {s['lateness_p99_ms']:.2f} ms  skipped "
            f"{s['skipped_frames']}  CPU server {s['server_cpu_cores']:.2f} clients "
            f"{s['clients_cpu_cores']:.2f} cores  load "
            f"{s['load_average']:.1f}  {'ok' if s['met'] else 'MISSED'}")


# --- clothball bench --load --cluster -----------------------------------------------------------


def run_load_cluster(args: argparse.Namespace) -> int:
    """``run_load`` over 1, 2 and 3 hosts (``--cluster-hosts``) joined through a Redis of
    the bench's own; print (or --json) every step of each."""
    import shutil

    redis_bin = shutil.which("redis-server")
    if redis_bin is None:
        print("clothball bench --load --cluster: needs redis-server on the PATH "
              "(apt: redis-server)", file=sys.stderr)
        return 2
    try:
        counts = [int(x) for x in str(args.cluster_hosts).split(",") if x.strip()]
        if not counts or min(counts) < 1:
            raise ValueError
    except ValueError:
        print(f"clothball bench: --cluster-hosts must be numbers of hosts like 1,2,3, got "
              f"{args.cluster_hosts!r}", file=sys.stderr)
        return 2
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="clothball-bench-redis-") as rdir:
        redis = start_redis(redis_bin, port, rdir)
        try:
            url = f"redis://127.0.0.1:{port}/0"
            load_before = os.getloadavg()
            series = {}
            for n in counts:
                _redis_flush(url)
                series[str(n)] = _load_series(args, n, url)
        finally:
            redis.terminate()
            redis.wait(timeout=20)
    result = {
        "n": args.server_n, "backend": args.server_backend, "cpus": os.cpu_count(),
        "hip_rate_hz": args.hip_rate, "spectators_per_room": args.load_spectators,
        "seconds_per_step": float(args.load_seconds),
        "load_average_before": list(load_before),
        "note": f"every host, Redis and the clients run on this one machine and share its "
                f"{os.cpu_count()} cores",
        "hosts": series,
    }
    if _write_json(result, getattr(args, "json", None)):
        print(json.dumps(result, indent=2))
    else:
        for n, r in series.items():
            print(_held_line(f"{n} host{'s' if n != '1' else ''}", r["held"]))
    return 0


def _held_line(what: str, h: dict[str, Any] | None) -> str:
    """The summary of a series of steps over several hosts or processes."""
    if h is None:
        return f"{what}: held not even one room"
    return (f"{what}: held {h['rooms']} rooms ({'+'.join(map(str, h['rooms_per_host']))}), "
            f"{h['clients']} clients, lateness p99 {h['lateness_p99_ms']:.2f} ms, "
            f"server CPU {h['server_cpu_cores']:.2f} cores")


def run_load_workers(args: argparse.Namespace) -> int:
    """``run_load`` over ``--workers`` server processes sharing one port and a SQLite room
    directory, as ``clothball host --workers N`` runs them."""
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="clothball-bench-workers-") as d:
        series = _load_series(args, args.workers, str(Path(d) / "rooms.sqlite"), free_port())
    result = {
        "n": args.server_n, "backend": args.server_backend, "cpus": os.cpu_count(),
        "workers": args.workers, "hip_rate_hz": args.hip_rate,
        "spectators_per_room": args.load_spectators, "seconds_per_step": float(args.load_seconds),
        "load_average_before": list(load_before), **series,
    }
    if _write_json(result, getattr(args, "json", None)):
        print(json.dumps(result, indent=2))
    else:
        print(_held_line(f"{args.workers} processes", series["held"]))
    return 0


def _redis_flush(url: str) -> None:
    import redis

    r = redis.Redis.from_url(url)
    try:
        r.flushdb()
    finally:
        r.close()


def _load_series(args: argparse.Namespace, n_hosts: int, directory: str,
                 shared_port: int | None = None) -> dict[str, Any]:
    """Rooms added one at a time to ``n_hosts`` hosts sharing the room ``directory`` until a
    target is missed; with ``shared_port`` they are one host's processes on that port and
    rooms are asked of it (as clients of `clothball host --workers` reach them)."""
    seconds = float(args.load_seconds)
    base = [sys.executable, "-m", "clothball.server.loadbench", "--server-n", str(args.server_n),
            "--server-backend", args.server_backend, "--hip-rate", str(args.hip_rate),
            "--load-spectators", str(args.load_spectators)]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    shared = ["--shared-port", str(shared_port)] if shared_port is not None else []
    servers = [subprocess.Popen([*base, "--role", "server", "--no-room", "--directory",
                                 directory, *shared, *_loop_flag(args)],
                                stdout=subprocess.PIPE, text=True, env=env)
               for _ in range(n_hosts)]
    clients: list[subprocess.Popen[str]] = []
    steps: list[dict[str, Any]] = []
    try:
        infos = [_server_info(s) for s in servers]
        # Rooms are asked of the first host (or the shared port), which places them.
        entry = infos[0][2] if shared_port is None else f"ws://127.0.0.1:{shared_port}/ws"
        time.sleep(1.5)  # every host has read the others from the directory
        what = (f"{n_hosts} server processes on one port" if shared_port is not None
                else f"{n_hosts} host{'s' if n_hosts > 1 else ''} in a cluster")
        print(f"load bench, {what}: rooms "
              f"of 4 players x {args.hip_rate:g} Hz HIP + {args.load_spectators} spectators, "
              f"{seconds:g} s a step, n={args.server_n}, backend {infos[0][0]['backend']}, "
              f"event loop {infos[0][0].get('loop')}, {os.cpu_count()} CPUs shared by hosts "
              "and clients", file=sys.stderr)
        for rooms in range(1, args.load_max_rooms + 1):
            clients.append(_start_room(base, entry, env))
            s0 = [get_json(f"{http}/api/stats?reset=1", info["token"]) for info, http, _ in infos]
            c0, w0 = _cpu_seconds(clients), time.perf_counter()
            time.sleep(seconds)
            s1 = [get_json(f"{http}/api/stats") for _, http, _ in infos]
            step = _load_step(rooms, _merged(s0), _merged(s1), args)
            step["hosts"] = n_hosts
            step["rooms_per_host"] = [len(s["rooms"]) for s in s1]
            step["clients_cpu_cores"] = (_cpu_seconds(clients) - c0) / (time.perf_counter() - w0)
            steps.append(step)
            tag = "p" if shared_port is not None else "h"  # processes of one host, or hosts
            print(f"{n_hosts}{tag} " + _load_line(step), file=sys.stderr, flush=True)
            if not step["met"]:
                break
    finally:
        _stop_clients(clients)
        for s in servers:
            _stop_server(s)
    held = [s for s in steps if s["met"]]
    return {"server_loop": infos[0][0].get("loop"), "held": held[-1] if held else None,
            "first_missed": next((s for s in steps if not s["met"]), None), "steps": steps}


def _merged(stats: list[dict[str, Any]]) -> dict[str, Any]:
    """Several hosts' ``/api/stats`` as one server's (counters summed, rooms together; the
    clock is the first host's, read within milliseconds of the others')."""
    out: dict[str, Any] = {"uptime_s": stats[0]["uptime_s"], "rooms": {}}
    for key in ("messages_in", "messages_out", "cpu_s"):
        out[key] = sum(s[key] for s in stats)
    for s in stats:
        out["rooms"].update(s["rooms"])
    return out


if __name__ == "__main__":
    sys.exit(main())
