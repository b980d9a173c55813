"""``clothball bench --server``: the game server under load, on loopback.

Three processes so that each side's CPU is its own: the server (one room, CPU or CUDA
backend, n = 64 by default), the players (4 clients sending HIP at 1 kHz and timing how
long until a CORNER message echoes each HIP they sent), and the spectators (50 clients
counting MESH messages). Reported: frame lateness p50/p99 (how long after its wall-clock
deadline each frame's state was ready, from the server's own counters), HIP-to-corner
latency p50/p99 (client clock, send -> receipt of the CORNER that applied it), messages per
second in and out of the server, spectator mesh rates, and CPU use of each process.

``clothball bench --load``: how many rooms the server holds. Rooms of 4 players (as the
desktop client: HIP at ``--hip-rate``, 120 Hz, ``corner_rate`` ``--corner-rate``, 120, MESH
on) and ``--load-spectators`` spectators each are added a step at a time (1 room, then
``--rooms-step`` K more each step) and measured for ``--load-seconds``. The clients are
``server/bench/benchclients.py``'s, many rooms to a process (``--client-procs``), set up in
Python and then driven by a native pump (``native/bench/load_clients.hpp``: no Python per
message), so that they cost a small part of what they measure; their CPU is reported beside
the server's.
A step holds while every room's frame lateness p99 is within ``--lateness-target`` (2 ms)
and the players receive at least 90 % of the CORNER rate they asked; the first step that
does not hold ends the run, saying what stopped it (lateness, delivery, server CPU
saturated, clients' CPU saturated). Reported per step (``--json``: one row each): rooms,
frame lateness p50/p99 (the server's counters, the worst room), HIP-to-CORNER latency
p50/p99 (client clock), server CPU (/proc, every thread of every server process; per room;
per added room; by thread kind, ``server_cores_by_kind``; µs of it a message in or out),
messages in and out a second, the clients' CPU (and a room's share), CORNER and MESH rates
received against those asked, frames advanced a second. ``--server-cpus`` and
``--client-cpus`` (CPU lists) pin the server's processes and the clients (and the bench
itself) to CPUs of their own (``os.sched_setaffinity``), read back in each row.

``clothball bench --load --workers N``: the same with an engine and N - 1 gateways on one
port, as ``clothball host --workers N`` runs them (docs/architecture.md): every client
connects to the public port; the server CPU counts the gateways too.
``clothball bench --load --cluster``: with 1, 2 and 3 server processes joined as the hosts
of a cluster through a Redis the bench starts (``redis-server`` on the PATH, a free port of
loopback): rooms are created through the first host, which places each on the least-loaded
one, and their clients connect through it too (redirected to the room's host). Every step
measures all the hosts; on one machine they share its cores with each other and with the
clients, which the figures say.

Run ``python -m clothball.server.bench.loadbench --role server|spectators ...`` only through the
bench; ``run(args)`` and ``run_load(args)`` start the others themselves.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import itertools
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from .. import loops
from ..hostproc import free_port, get, get_json, start_redis
from ..shared.listen import raise_open_files
from .benchclients import HIST_BIN_S

TARGET_LATENCY_P99_MS = 5.0
TARGET_LATENESS_P99_MS = 5.0
TARGET_MESH_HZ = 30.0
LOAD_HIP_HZ = 120.0  # what the desktop client sends (game/client/netthread.py) ...
LOAD_CORNER_HZ = 120.0  # ... and the corner_rate it asks
SERVER_HIP_HZ = 1000.0  # --server: players at the most a seat may send
DELIVERY_MIN = 0.9  # of the CORNER rate asked, for a step to hold
SATURATED = 0.9  # of a core: a server's event-loop thread, or a client process, this busy
SETTLE_S = 1.0  # after rooms are added, before a step is measured


def configure_server_flags(parser: argparse.ArgumentParser) -> None:
    """Flags of ``clothball bench --server`` and ``--load`` (``--json`` and ``--scene`` are the
    bench's own)."""
    g = parser.add_argument_group("server benches (--server, --load)")
    g.add_argument("--seconds", type=float, default=30.0,
                   help="measured duration of the server bench (default %(default)s)")
    g.add_argument("--spectators", type=int, default=50,
                   help="spectator clients (default %(default)s)")
    g.add_argument("--players", type=int, default=4, choices=range(1, 5),
                   help="player clients (default %(default)s)")
    g.add_argument("--hip-rate", type=float, default=None,
                   help=f"HIP messages a second per player (default {SERVER_HIP_HZ:g} with "
                        f"--server, {LOAD_HIP_HZ:g} with --load: the desktop client's rate)")
    g.add_argument("--corner-rate", type=float, default=None,
                   help=f"the corner_rate each player asks, CORNER messages a second (default "
                        f"the server's, 1000, with --server; {LOAD_CORNER_HZ:g} with --load: "
                        "what the desktop client asks)")
    g.add_argument("--server-n", type=int, default=None,
                   help="cloth nodes per side in the bench rooms (default 64 on the classic "
                        "scene the bench uses; with --scene, that scene's own)")
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
    g.add_argument("--rooms-step", type=int, default=1, metavar="K",
                   help="--load: rooms added a step (1 room first, then K, 2K, ...; default "
                        "%(default)s)")
    g.add_argument("--lateness-target", type=float, default=2.0, metavar="MS",
                   help="--load: a step holds while every room's frame lateness p99 is within "
                        "MS and the players receive 90 %% of the CORNER rate asked (default "
                        "%(default)s)")
    g.add_argument("--steps-past", type=int, default=0, metavar="N",
                   help="--load: steps still measured after the first that did not hold (the "
                        "curve past it; default %(default)s)")
    g.add_argument("--client-procs", type=int, default=None, metavar="P",
                   help="--load: processes of lean clients, rooms given to them in turn "
                        "(default: a quarter of the CPUs, 1 to 4)")
    g.add_argument("--workers", type=int, default=1, metavar="N",
                   help="--load: an engine and N - 1 gateways on one port, as `clothball host "
                        "--workers N` runs them; default %(default)s")
    g.add_argument("--cluster", action="store_true",
                   help="--load: rooms held by 1, 2 and 3 hosts of a cluster on this machine, "
                        "joined through a Redis the bench starts (needs redis-server)")
    g.add_argument("--cluster-hosts", default="1,2,3", metavar="N,N,...",
                   help="--load --cluster: the numbers of hosts measured (default %(default)s)")
    g.add_argument("--server-cpus", default=None, metavar="LIST",
                   help="--load: the CPUs the server's processes run on (os.sched_setaffinity), "
                        "a list like 0-7 or 0,2,4-6 (default: any)")
    g.add_argument("--client-cpus", default=None, metavar="LIST",
                   help="--load: the CPUs the bench's clients (and the bench itself) run on, "
                        "none of --server-cpus (default: any)")


def configure(parser: argparse.ArgumentParser) -> None:
    """Stand-alone use (``python -m clothball.server.bench.loadbench``)."""
    configure_server_flags(parser)
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--scene", default=None, help="scene name or path (default classic)")
    parser.add_argument("--load", action="store_true", help="how many rooms the server holds")
    parser.add_argument("--role", choices=("bench", "server", "spectators"),
                        default="bench", help=argparse.SUPPRESS)
    parser.add_argument("--url", default="", help=argparse.SUPPRESS)
    parser.add_argument("--no-room", action="store_true", help=argparse.SUPPRESS)
    # A host's room directory: redis://... (--load --cluster).
    parser.add_argument("--directory", default=None, help=argparse.SUPPRESS)
    # The engine of an engine and gateways (--workers): its socket and the public port.
    parser.add_argument("--engine-socket", type=Path, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--public-port", type=int, default=None, help=argparse.SUPPRESS)


# --- the server process ------------------------------------------------------------------------


def bench_scene(args: argparse.Namespace) -> Any:
    """The bench rooms' scene: ``--scene`` (default classic) with ``--server-n`` nodes a side
    (default: 64 on classic, else the scene's own). ``SceneError`` when there is none such."""
    from ...game.sim.scene import Scene

    scene = Scene.load(getattr(args, "scene", None) or "classic")
    n = args.server_n if args.server_n is not None else (
        None if getattr(args, "scene", None) else 64)
    return scene if n is None else scene.with_changes({"cloth": {"n": n}})


async def _serve(args: argparse.Namespace) -> None:
    from ..app import GameServer, ServerConfig
    from ..limits import Limits
    from ..room import RoomSettings

    sys.setswitchinterval(0.0005)
    scene = bench_scene(args)
    scene_name, scene.name = scene.name, "bench"
    cluster: dict[str, Any] = {}
    directory = None
    if getattr(args, "directory", None):  # a host of --load --cluster
        from ..directory import RedisDirectory

        directory = RedisDirectory(args.directory)
        cluster = {"host_id": f"bench-{os.getpid()}"}
    if getattr(args, "engine_socket", None) is not None:  # the engine of --workers
        cluster.update(engine_socket=args.engine_socket, public_port=args.public_port)
    with tempfile.TemporaryDirectory() as data:
        # Every client comes from 127.0.0.1: the per-address limits would stop the bench.
        # Nor may admission control refuse rooms: the bench finds where the server stops.
        limits = Limits(conns_per_address=100_000, rooms_per_address=100_000, max_rooms=100_000,
                        max_clients=1_000_000, spectators_per_room=100_000, admit_lateness_ms=0,
                        admit_load=0)
        srv = GameServer(ServerConfig(data, scenes={"bench": scene}, backend=args.server_backend,
                                      host="127.0.0.1", port=0, default_room=not args.no_room,
                                      room_settings=RoomSettings(first_to=99, bots_allowed=False,
                                                    unguarded=True), limits=limits, **cluster),
                         directory=directory)
        await srv.start()
        room = srv.main_room
        probe = room.sim if room is not None else None
        if probe is None:  # no room yet: a throw-away cloth says what a room will run
            from ...game.sim.cloth import Cloth

            probe = Cloth(scene, backend=args.server_backend, threads=1)
        print(json.dumps({"port": srv.port, "room": room.id if room is not None else None,
                          "backend": probe.backend, "substeps": probe.substeps,
                          "scene": scene_name, "n": scene.n,
                          "token": srv.host_token, "loop": loops.running()}), flush=True)
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        loop.add_signal_handler(signal.SIGTERM, stop.set)
        loop.add_signal_handler(signal.SIGINT, stop.set)
        await stop.wait()
        await srv.stop()


# --- spectators --------------------------------------------------------------------------------


async def _spectate(args: argparse.Namespace) -> None:
    from ...game.net.client import NetClient

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


async def _play(ws_url: str, room: str, n_players: int, rate: float,
                corner_rate: float | None, seconds: float, reset_stats: Any) -> dict[str, Any]:
    from ...game.net.client import NetClient

    players = [await NetClient.connect(ws_url, name=f"p{i}", role="player", room=room, seat=i,
                                       record_latency=True, mesh=False, corner_rate=corner_rate)
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
        raise_open_files()  # hundreds of rooms' clients
        loops.run(_serve(args), args.server_loop)
        return 0
    if role == "spectators":
        asyncio.run(_spectate(args))
        return 0
    if getattr(args, "load", False):
        return run_load(args)
    if args.hip_rate is None:
        args.hip_rate = SERVER_HIP_HZ
    err = load_arg_error(args)
    if err is not None:
        print(f"clothball bench: {err}", file=sys.stderr)
        return 2
    seconds = float(args.seconds)
    base = [sys.executable, "-m", "clothball.server.bench.loadbench", *_scene_flags(args),
            "--server-backend", args.server_backend, "--seconds", str(seconds),
            "--spectators", str(args.spectators)]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    server = subprocess.Popen([*base, "--role", "server", *_loop_flag(args)],
                              stdout=subprocess.PIPE, text=True, env=_server_env(args))
    spect: subprocess.Popen[str] | None = None
    try:
        info, http, ws = _server_info(server)
        print(f"server bench: {args.players} players x {args.hip_rate:g} Hz HIP, "
              f"{args.spectators} spectators, {seconds:g} s, scene {info['scene']} "
              f"n={info['n']}, backend {info['backend']} ({info['substeps']} substeps/frame), "
              f"event loop {info['loop']}, {os.cpu_count()} CPUs", file=sys.stderr)
        if args.spectators > 0:
            spect = subprocess.Popen(
                [*base, "--role", "spectators", "--url",
                 json.dumps({"ws": ws, "room": info["room"]})],
                stdout=subprocess.PIPE, text=True, env=env)
            assert spect.stdout is not None
            json.loads(spect.stdout.readline())  # connected
        players = asyncio.run(_play(ws, info["room"], args.players, args.hip_rate,
                                    args.corner_rate, seconds,
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
        "scene": info["scene"],
        "n": info["n"],
        "corner_rate_asked_hz": args.corner_rate,
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
    there, the summary still printed); ``python -m clothball.server.bench.loadbench --json`` gives
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
    parser = argparse.ArgumentParser(prog="python -m clothball.server.bench.loadbench")
    configure(parser)
    return run(parser.parse_args(argv))



# --- clothball bench --load ---------------------------------------------------------------------

def load_arg_error(args: argparse.Namespace) -> str | None:
    """What is wrong with the ``--load`` (or ``--server``) flags, in one line; None: fine."""
    def bad(v: float, lo: float, hi: float, lo_open: bool = False) -> bool:
        return not math.isfinite(v) or v < lo or (lo_open and v == lo) or v > hi

    if args.hip_rate is not None and bad(args.hip_rate, 0.0, 1000.0, lo_open=True):
        return (f"--hip-rate must be more than 0 and at most 1000 (HIP messages a second "
                f"per player), got {args.hip_rate:g}")
    if args.corner_rate is not None and bad(args.corner_rate, 1.0, 1000.0):
        return (f"--corner-rate must be 1 to 1000 (CORNER messages a second a player asks, "
                f"as join's corner_rate), got {args.corner_rate:g}")
    from ...game.sim.scene import SceneError

    try:
        bench_scene(args)
    except SceneError as e:
        return f"--scene, --server-n: {e}"
    cpus = cpu_lists(args)
    if isinstance(cpus, str):
        return cpus
    if not getattr(args, "load", False):
        if cpus != (None, None):
            return "--server-cpus and --client-cpus go with --load"
        return None
    if args.workers < 1:
        return f"--workers must be at least 1, got {args.workers}"
    if bad(args.load_seconds, 0.0, math.inf, lo_open=True):
        return f"--load-seconds must be a number of seconds above 0, got {args.load_seconds:g}"
    if args.rooms_step < 1:
        return f"--rooms-step must be at least 1 (rooms added a step), got {args.rooms_step}"
    if args.load_max_rooms < 1:
        return f"--load-max-rooms must be at least 1, got {args.load_max_rooms}"
    if args.load_spectators < 0:
        return f"--load-spectators must be 0 or more, got {args.load_spectators}"
    if bad(args.lateness_target, 0.0, math.inf, lo_open=True):
        return (f"--lateness-target must be a number of milliseconds above 0, got "
                f"{args.lateness_target:g}")
    if args.steps_past < 0:
        return f"--steps-past must be 0 or more, got {args.steps_past}"
    if args.client_procs is not None and args.client_procs < 1:
        return f"--client-procs must be at least 1, got {args.client_procs}"
    return None


def parse_cpu_list(text: str, flag: str) -> frozenset[int]:
    """``0-3,8,10-11`` (as ``taskset -c`` and /sys's lists write them) as a set of CPUs;
    ``ValueError`` with one line naming ``flag`` when it is not one, is empty, or names a
    CPU this process may not run on."""
    usable = os.sched_getaffinity(0)
    out: set[int] = set()
    for part in str(text).split(","):
        part = part.strip()
        lo, dash, hi = part.partition("-")
        try:
            a = int(lo)
            b = int(hi) if dash else a
        except ValueError:
            a = b = -1
        if not part or a < 0 or b < a or (dash and not hi.strip()):
            raise ValueError(f"{flag} must be a list of CPUs like 0-3 or 0,2,4-6, got {text!r}")
        out.update(range(a, b + 1))
    missing = sorted(out - usable)
    if missing:
        raise ValueError(f"{flag} names CPU{'s' * (len(missing) > 1)} "
                         f"{_cpus_text(missing)} that this machine does not let the bench use "
                         f"(usable: {_cpus_text(sorted(usable))})")
    return frozenset(out)


def _cpus_text(cpus: list[int] | frozenset[int]) -> str:
    """CPUs as a list of ranges: 0-3,8."""
    runs: list[list[int]] = []
    for c in sorted(cpus):
        if runs and c == runs[-1][1] + 1:
            runs[-1][1] = c
        else:
            runs.append([c, c])
    return ",".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs)


def cpu_lists(args: argparse.Namespace
              ) -> tuple[frozenset[int] | None, frozenset[int] | None] | str:
    """``--server-cpus`` and ``--client-cpus`` as sets (None: not given), or what is wrong
    with them in one line."""
    got: list[frozenset[int] | None] = []
    for flag in ("--server-cpus", "--client-cpus"):
        text = getattr(args, flag[2:].replace("-", "_"), None)
        try:
            got.append(None if text is None else parse_cpu_list(text, flag))
        except ValueError as e:
            return str(e)
    server, client = got
    if server is not None and client is not None and server & client:
        return (f"--server-cpus and --client-cpus share CPU"
                f"{'s' * (len(server & client) > 1)} {_cpus_text(server & client)}: the "
                "server and its clients run on separate cores")
    return server, client


def pin(procs: list[subprocess.Popen[Any]], cpus: frozenset[int] | None) -> None:
    """Every thread of these processes (just started: their first) onto ``cpus``; the
    threads they start later inherit it."""
    if cpus is None:
        return
    for p in procs:
        try:
            tids = [int(t) for t in os.listdir(f"/proc/{p.pid}/task")]
        except OSError:
            tids = [p.pid]
        for tid in tids:
            with contextlib.suppress(ProcessLookupError):
                os.sched_setaffinity(tid, cpus)


def room_counts(step: int, most: int) -> list[int]:
    """The rooms of each step: 1, then every multiple of ``step`` up to ``most`` (and
    ``most`` itself): one room first, for what a room alone costs."""
    counts = [1, *range(step, most + 1, step)] if step > 1 else list(range(1, most + 1))
    if counts[-1] != most:
        counts.append(most)
    return sorted(set(counts))


def _server_env(args: argparse.Namespace) -> dict[str, str]:
    """The server processes' environment: this one's, unbuffered."""
    return {**os.environ, "PYTHONUNBUFFERED": "1"}


class _Clients:
    """The client processes (``server/bench/benchclients.py``): rooms are given to them in
    turn; each answers one JSON line per command."""

    def __init__(self, args: argparse.Namespace, n: int,
                 cpus: frozenset[int] | None = None) -> None:
        cmd = [sys.executable, "-m", "clothball.server.bench.benchclients",
               "--hip-rate", repr(args.hip_rate), "--corner-rate", repr(args.corner_rate),
               "--spectators", str(args.load_spectators)]
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.procs = [subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                       text=True, env=env) for _ in range(n)]
        pin(self.procs, cpus)
        self._turn = 0

    def _ask(self, cmds: list[tuple[subprocess.Popen[str], dict[str, Any]]]
             ) -> list[dict[str, Any]]:
        for proc, cmd in cmds:  # every process at once, then every answer
            assert proc.stdin is not None
            proc.stdin.write(json.dumps(cmd) + "\n")
            proc.stdin.flush()
        out = []
        for proc, _ in cmds:
            assert proc.stdout is not None
            line = proc.stdout.readline()
            if not line:
                raise RuntimeError(f"a client process ended (exit status {proc.wait()})")
            out.append(json.loads(line))
        return out

    def add(self, ws: str, rooms: int) -> None:
        share = [0] * len(self.procs)
        for _ in range(rooms):
            share[self._turn] += 1
            self._turn = (self._turn + 1) % len(self.procs)
        for r in self._ask([(p, {"op": "add", "ws": ws, "rooms": k})
                            for p, k in zip(self.procs, share, strict=True) if k]):
            if "error" in r:
                raise RuntimeError(f"the clients could not join a room: {r['error']}")

    def snap(self, mark: bool) -> list[dict[str, Any]]:
        return self._ask([(p, {"op": "mark" if mark else "snap"}) for p in self.procs])

    def cpu_seconds(self) -> list[float]:
        return [_cpu_seconds([p]) for p in self.procs]

    def stop(self) -> None:
        for proc in self.procs:
            if proc.stdin is not None:
                proc.stdin.close()  # their signal to close every client
        for proc in self.procs:
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def run_load(args: argparse.Namespace) -> int:
    """Add rooms step by step until a step does not hold; print (or --json) every step."""
    _load_defaults(args)
    err = load_arg_error(args)
    if err is not None:
        print(f"clothball bench: {err}", file=sys.stderr)
        return 2
    _, client_cpus = _cpus(args)
    if client_cpus is not None:  # the bench's own measuring stays off the server's cores
        os.sched_setaffinity(0, client_cpus)
    try:
        return run_load_cluster(args) if getattr(args, "cluster", False) else _run_load(args)
    except (OSError, RuntimeError, ValueError) as e:  # a server or client process gone
        print(f"clothball bench --load: stopped: {e}", file=sys.stderr)
        return 1


def _run_load(args: argparse.Namespace) -> int:
    load_before = os.getloadavg()
    if args.workers > 1:
        series = _load_series(args, 1, None, free_port())
    else:
        series = _load_series(args, 1, None)
    result = {**_load_meta(args, series.pop("info"), load_before), "workers": args.workers,
              **series}
    if _write_json(result, getattr(args, "json", None)):
        print(json.dumps(result, indent=2))
    elif args.workers > 1:
        print(_held_line(f"{args.workers} processes", result["held"]))
    else:
        h = result["held"]
        print("held: " + (f"{h['rooms']} rooms, {h['clients']} clients, "
                          f"{h['messages_in_per_s']:.0f} msgs/s in, "
                          f"{h['messages_out_per_s']:.0f} out, lateness p99 "
                          f"{h['lateness_p99_ms']:.2f} ms, server CPU "
                          f"{h['server_cpu_cores']:.2f} cores" if h else "not even one room"))
    if getattr(args, "json", None) is not True:
        print(_stopped_line(result))
    return 0


def _load_defaults(args: argparse.Namespace) -> None:
    """The real clients' rates where no flag says otherwise."""
    if args.hip_rate is None:
        args.hip_rate = LOAD_HIP_HZ
    if args.corner_rate is None:
        args.corner_rate = LOAD_CORNER_HZ
    if getattr(args, "client_procs", None) is None:
        args.client_procs = min(4, max(1, (os.cpu_count() or 1) // 4))


def _cpus(args: argparse.Namespace) -> tuple[frozenset[int] | None, frozenset[int] | None]:
    """``--server-cpus``, ``--client-cpus`` (checked already by ``load_arg_error``), parsed
    once: the bench then runs on the clients' CPUs, and would no longer see the server's as
    its own."""
    got = getattr(args, "_cpus", None)
    if got is None:
        got = cpu_lists(args)
        assert not isinstance(got, str), got
        args._cpus = got
    return got


def _load_meta(args: argparse.Namespace, info: dict[str, Any], load_before: tuple[float, ...]
               ) -> dict[str, Any]:
    server_cpus, client_cpus = _cpus(args)
    return {
        "server_cpus": None if server_cpus is None else sorted(server_cpus),
        "client_cpus": None if client_cpus is None else sorted(client_cpus),
        "scene": info.get("scene"), "n": info.get("n"), "backend": info.get("backend"),
        "substeps": info.get("substeps"), "server_loop": info.get("loop"),
        "cpus": os.cpu_count(),
        "hip_rate_hz": args.hip_rate, "corner_rate_hz": args.corner_rate,
        "spectators_per_room": args.load_spectators, "seconds_per_step": args.load_seconds,
        "rooms_step": args.rooms_step, "lateness_target_ms": args.lateness_target,
        "client_processes": args.client_procs, "load_average_before": list(load_before),
    }


def _stopped_line(result: dict[str, Any]) -> str:
    """What ended each series: the first step that did not hold, and why."""
    series = ({f"{n} host{'s' if n != '1' else ''} ": r for n, r in result["hosts"].items()}
              if "hosts" in result else {"": result})
    lines = []
    for what, s in series.items():
        at = s["stopped_at"]
        lines.append(what + "stopped: " + (f"at {at['rooms']} rooms by " + "; ".join(at["why"])
                                           if at is not None else
                                           "every step held, up to --load-max-rooms"))
    return "\n".join(lines)


def _load_series(args: argparse.Namespace, n_hosts: int, directory: str | None,
                 shared_port: int | None = None) -> dict[str, Any]:
    """Rooms added ``--rooms-step`` at a time to ``n_hosts`` server processes until a step
    does not hold. ``directory``: the room directory they share (None: one process alone);
    with ``shared_port`` the one server is the engine of ``--workers`` - 1 gateways on
    that port, and every client connects there, else rooms are asked of the first host."""
    seconds = float(args.load_seconds)
    base = [sys.executable, "-m", "clothball.server.bench.loadbench", *_scene_flags(args),
            "--server-backend", args.server_backend, "--role", "server", "--no-room",
            *_loop_flag(args)]
    if directory is not None:
        base += ["--directory", directory]
    private = tempfile.mkdtemp(prefix="clothball-bench-")
    gateways: list[subprocess.Popen[str]] = []
    if shared_port is not None:
        sock = str(Path(private) / "engine.sock")
        base += ["--engine-socket", sock, "--public-port", str(shared_port)]
        gateways = [subprocess.Popen(
            [sys.executable, "-m", "clothball.server.gateway", "--host", "127.0.0.1",
             "--port", str(shared_port), "--engine-socket", sock, "--index", str(k)],
            stdout=subprocess.DEVNULL) for k in range(max(1, args.workers - 1))]
    servers = [subprocess.Popen(base, stdout=subprocess.PIPE, text=True,
                                env=_server_env(args)) for _ in range(n_hosts)]
    server_cpus, client_cpus = _cpus(args)
    clients: _Clients | None = None
    steps: list[dict[str, Any]] = []
    stopped: dict[str, Any] | None = None
    past = 0  # steps measured after the stop (--steps-past)
    try:
        pin(servers + gateways, server_cpus)
        infos = [_server_info(s) for s in servers]
        if shared_port is not None:  # an engine's own port is its bots' only
            infos = [(i, f"http://127.0.0.1:{shared_port}", f"ws://127.0.0.1:{shared_port}/ws")
                     for i, _, _ in infos]
        entry = infos[0][2] if shared_port is None else f"ws://127.0.0.1:{shared_port}/ws"
        if directory is not None:
            time.sleep(1.5)  # every host has read the others from the directory
        clients = _Clients(args, args.client_procs, client_cpus)
        info = infos[0][0]
        what = (f"an engine and {len(gateways)} gateway{'s' * (len(gateways) > 1)} on one "
                "port" if gateways else
                "one server process" if directory is None else
                f"{n_hosts} host{'s' if n_hosts > 1 else ''} in a cluster")
        counts = room_counts(args.rooms_step, args.load_max_rooms)
        print(f"load bench, {what}: rooms of 4 players (HIP {args.hip_rate:g} Hz, corner_rate "
              f"{args.corner_rate:g} Hz, MESH) + {args.load_spectators} spectators, "
              f"{seconds:g} s a step, rooms {_counts_text(counts)}, scene {info['scene']} "
              f"n={info['n']}, backend {info['backend']} ({info['substeps']} substeps/frame), "
              f"event loop {info['loop']}, "
              f"{args.client_procs} client process{'es' if args.client_procs > 1 else ''}, "
              f"{_cpus_line(server_cpus, client_cpus)}, load average "
              f"{os.getloadavg()[0]:.2f}", file=sys.stderr, flush=True)
        procs = servers + gateways  # every process of the server side, for its CPU
        cpu0, w0 = _cpu_seconds(procs), time.perf_counter()
        time.sleep(SETTLE_S)
        idle = (_cpu_seconds(procs) - cpu0) / (time.perf_counter() - w0)
        prev = (0, idle)
        tag = f"{args.workers}p " if gateways else "" if directory is None else f"{n_hosts}h "
        for rooms in counts:
            try:
                clients.add(entry, rooms - prev[0])
            except RuntimeError as e:  # a room refused or a client process gone: said, kept
                if stopped is None:
                    stopped = {"rooms": rooms, "stopped_by": ["join"], "why": [str(e)]}
                print(f"{tag}{rooms:3d} rooms  STOP: {e}", file=sys.stderr, flush=True)
                break
            time.sleep(SETTLE_S)
            step = _measure(args, procs, infos, clients, rooms, seconds, prev)
            step["hosts"] = n_hosts
            steps.append(step)
            print(tag + _load_line(step), file=sys.stderr, flush=True)
            if stopped is None and not step["held"]:
                stopped, past = step, 0
            elif stopped is not None:
                past += 1
            if stopped is not None and past >= args.steps_past:
                break
            prev = (rooms, step["server_cpu_cores"])
    finally:
        if clients is not None:
            clients.stop()
        for s in gateways + servers:
            _stop_server(s)
        shutil.rmtree(private, ignore_errors=True)
    # The last step that held before the stop (steps past it may hold again: noise).
    held = [s for s in steps if s["held"] and (stopped is None or s["rooms"] < stopped["rooms"])]
    return {"info": info, "idle_server_cpu_cores": idle, "held": held[-1] if held else None,
            "stopped_at": stopped, "stopped_by": stopped["stopped_by"] if stopped else [],
            "steps": steps}


def _cpus_line(server: frozenset[int] | None, client: frozenset[int] | None) -> str:
    if server is None and client is None:
        return f"{os.cpu_count()} CPUs shared by servers and clients"
    return (f"server on CPUs {_cpus_text(server) if server is not None else 'any'}, clients on "
            f"{_cpus_text(client) if client is not None else 'any'} (of {os.cpu_count()})")


def _counts_text(counts: list[int]) -> str:
    return ", ".join(map(str, counts)) if len(counts) <= 6 else \
        f"{', '.join(map(str, counts[:3]))}, ... {counts[-1]}"


def _scene_flags(args: argparse.Namespace) -> list[str]:
    out = ["--scene", args.scene] if getattr(args, "scene", None) else []
    return out + (["--server-n", str(args.server_n)] if args.server_n is not None else [])


def _measure(args: argparse.Namespace, servers: list[subprocess.Popen[str]],
             infos: list[tuple[dict[str, Any], str, str]], clients: _Clients, rooms: int,
             seconds: float, prev: tuple[int, float]) -> dict[str, Any]:
    """One step: ``seconds`` of the servers' counters, their CPU from /proc and what the
    clients received."""
    c0 = clients.snap(mark=True)
    s0 = [get_json(f"{http}/api/stats?reset=1", i["token"]) for i, http, _ in infos]
    srv0, thr0 = _cpu_seconds(servers), _threads_cpu_seconds(servers)
    cl0, w0 = clients.cpu_seconds(), time.perf_counter()
    pages = _probe_pages(infos[0][1], seconds)
    s1 = [get_json(f"{http}/api/stats") for _, http, _ in infos]
    srv1, thr1 = _cpu_seconds(servers), _threads_cpu_seconds(servers)
    cl1, dt = clients.cpu_seconds(), time.perf_counter() - w0
    c1 = clients.snap(mark=False)
    step = _server_step(rooms, _merged(s0), _merged(s1), args)
    step.update(pages)
    step["rooms_per_host"] = [len(s["rooms"]) for s in s1]
    step["server_cpu_cores"] = (srv1 - srv0) / dt
    step["server_cpu_per_room"] = step["server_cpu_cores"] / rooms
    step["server_cpu_per_added_room"] = ((step["server_cpu_cores"] - prev[1])
                                         / (rooms - prev[0]))
    # Each thread's share: the event loop (a process's main thread: its network work) and
    # the busiest of any (a frame loop, a sim worker, or that event loop).
    threads = {k: (name, (t - thr0[k][1]) / dt) for k, (name, t) in thr1.items() if k in thr0}
    step["server_event_loop_cores"] = max(
        (c for (pid, tid), (_, c) in threads.items() if pid == tid), default=0.0)
    (pid, tid), (name, cores) = max(threads.items(), key=lambda kv: kv[1][1])
    step["server_busiest_thread_cores"] = cores
    step["server_busiest_thread"] = f"{name} (event loop)" if pid == tid else name
    # Where the server's CPU goes: cores by process kind and thread name, summed over the
    # processes (the engine's frame loops, its service threads, the gateways' event loops).
    kinds = {p.pid: _process_kind(p) for p in servers}
    spent: dict[str, float] = {}
    for (pid, tid), (name, c) in threads.items():
        label = f"{kinds[pid]} {'event loop' if pid == tid else name}"
        spent[label] = spent.get(label, 0.0) + c
    step["server_threads_cores"] = dict(sorted(spent.items(), key=lambda kv: -kv[1]))
    by_kind = dict.fromkeys(THREAD_KINDS, 0.0)
    for (pid, tid), (name, c) in threads.items():
        by_kind[thread_kind(kinds[pid], name, pid == tid)] += c
    step["server_cores_by_kind"] = by_kind
    messages = step["messages_in_per_s"] + step["messages_out_per_s"]
    step["server_cpu_us_per_message"] = (step["server_cpu_cores"] * 1e6 / messages
                                         if messages > 0 else None)
    # ... and by thread kind: what each kind spends a message of the server's (issue 43's
    # per-message path: the gateways' pumps' figure is the HIP, CORNER and MESH path's).
    step["server_cpu_us_per_message_by_kind"] = {
        k: (v * 1e6 / messages if messages > 0 else None) for k, v in by_kind.items()}
    # Where their threads may run, read back (--server-cpus, --client-cpus: every thread,
    # the frame loops and encoders started after the pinning included).
    step["server_affinity"] = _affinity(servers)
    step["client_affinity"] = _affinity(clients.procs)
    per_client = [(b - a) / dt for a, b in zip(cl0, cl1, strict=True)]
    step["clients_cpu_cores"] = sum(per_client)
    step["clients_cpu_per_room"] = step["clients_cpu_cores"] / rooms
    step["client_process_cores_max"] = max(per_client)
    step.update(_client_step(c0, c1, args))
    _judge(step, args)
    return step


PAGE_EVERY_S = 0.1  # the host's own pages asked for this often while a step is measured
PAGE_TIMEOUT_S = 2.0  # an answer later than this counts as this late (and as unanswered)
PAGES = {"healthz": "/healthz", "stats": "/api/stats"}  # (the step's keys: their names)


def _probe_pages(http: str, seconds: float) -> dict[str, Any]:
    """For ``seconds``, ``/healthz`` and ``/api/stats`` by turns every ``PAGE_EVERY_S``, as
    an operator's monitoring would (issue 43: they must answer under full load): each one's
    p50 and p99 answer time in ms and how many went unanswered."""
    times: dict[str, list[float]] = {page: [] for page in PAGES}
    failed = dict.fromkeys(PAGES, 0)
    end = time.perf_counter() + seconds
    turns = itertools.cycle(PAGES.items())
    while time.perf_counter() < end:
        page, path = next(turns)
        t0 = time.perf_counter()
        try:
            get(f"{http}{path}", timeout=PAGE_TIMEOUT_S)
            times[page].append(time.perf_counter() - t0)
        except OSError:
            failed[page] += 1
            times[page].append(PAGE_TIMEOUT_S)
        time.sleep(max(0.0, min(end, t0 + PAGE_EVERY_S) - time.perf_counter()))
    out: dict[str, Any] = {}
    for page, ts in times.items():
        v = np.array(ts) * 1e3 if ts else None
        out[f"{page}_p50_ms"] = None if v is None else float(np.percentile(v, 50))
        out[f"{page}_p99_ms"] = None if v is None else float(np.percentile(v, 99))
        out[f"{page}_unanswered"] = failed[page]
    return out


def _server_step(rooms: int, s0: dict[str, Any], s1: dict[str, Any], args: argparse.Namespace
                 ) -> dict[str, Any]:
    dt = s1["uptime_s"] - s0["uptime_s"]
    per_room = s1["rooms"].values()
    p99 = max((r["lateness_ms"].get("p99", math.inf) for r in per_room), default=math.inf)
    p50 = max((r["lateness_ms"].get("p50", math.inf) for r in per_room), default=math.inf)
    skipped = sum(r["skipped_frames"] - s0["rooms"].get(k, {}).get("skipped_frames", 0)
                  for k, r in s1["rooms"].items())
    return {
        "rooms": rooms,
        "clients": rooms * (4 + args.load_spectators),
        "lateness_p50_ms": p50,
        "lateness_p99_ms": p99,
        "skipped_frames": skipped,
        "messages_in_per_s": (s1["messages_in"] - s0["messages_in"]) / dt,
        "messages_out_per_s": (s1["messages_out"] - s0["messages_out"]) / dt,
        "hip_offered_per_s": 4 * args.hip_rate * rooms,
        "load_average": os.getloadavg()[0],
    }


def _client_step(c0: list[dict[str, Any]], c1: list[dict[str, Any]], args: argparse.Namespace
                 ) -> dict[str, Any]:
    """What the clients sent and received between two snapshots of every client process."""
    corner, frames, hist = [], [], Counter()
    hips = meshes = mesh_clients = errors = lost = behind = unknown = mismatch = 0.0
    last_error, mesh_hz = "", math.nan
    for a, b in zip(c0, c1, strict=True):
        dt = b["wall_s"] - a["wall_s"]
        corner += [(y - x) / dt for x, y in zip(a["corners"], b["corners"], strict=True)]
        frames += [(f - a["frames"][r]) / dt for r, f in b["frames"].items()
                   if a["frames"].get(r, -1) >= 0]
        hips += (b["hips"] - a["hips"]) / dt
        meshes += (b["meshes"] - a["meshes"]) / dt
        mesh_clients += b["players"] + b["spectators"]
        errors += b["errors"] - a["errors"]
        lost += b["lost"]
        behind += b["behind"] - a["behind"]
        unknown += b["echo_unknown"] - a["echo_unknown"]
        mismatch += b["echo_mismatch"] - a["echo_mismatch"]
        hist.update({int(k): v for k, v in b["hist"].items()})
        last_error = last_error or b["last_error"]
        mesh_hz = b["mesh_hz"] if math.isfinite(b["mesh_hz"]) else mesh_hz
    lat50, lat99 = (_hist_ms(hist, q) for q in (0.5, 0.99))
    corner_mean = sum(corner) / len(corner) if corner else 0.0
    mesh_mean = meshes / mesh_clients if mesh_clients else 0.0
    return {
        "hip_to_corner_p50_ms": lat50,
        "hip_to_corner_p99_ms": lat99,
        "hip_to_corner_samples": sum(hist.values()),
        "hip_echo_unknown": int(unknown),
        "hip_echo_mismatch": int(mismatch),
        "hip_sent_per_s": hips,
        "corner_hz_asked": args.corner_rate,
        "corner_hz_received": corner_mean,
        "corner_hz_min": min(corner, default=0.0),
        "corner_delivery": corner_mean / args.corner_rate,
        "mesh_hz_asked": mesh_hz,
        "mesh_hz_received": mesh_mean,
        "mesh_delivery": mesh_mean / mesh_hz if mesh_hz > 0 else 0.0,
        "frames_per_s": sum(frames) / len(frames) if frames else 0.0,
        "frames_per_s_min": min(frames, default=0.0),
        "client_errors": int(errors),
        "client_last_error": last_error,
        "clients_lost": int(lost),
        "clients_fell_behind": int(behind),
    }


def _hist_ms(hist: Counter[int], q: float) -> float | None:
    """The ``q`` quantile (ms) of a latency histogram of ``benchclients.HIST_BIN_S`` bins
    (the middle of its bin); None without samples."""
    total = sum(hist.values())
    if total == 0:
        return None
    seen = 0
    for i in sorted(hist):
        seen += hist[i]
        if seen >= q * total:
            return (i + 0.5) * HIST_BIN_S * 1e3
    return None


def _judge(step: dict[str, Any], args: argparse.Namespace) -> None:
    """Held: frame lateness p99 within the target and CORNER delivered at 90 % of the rate
    asked. Whatever else is saturated is said too (a step the clients could not drive
    measures them, not the server)."""
    why: list[tuple[str, str]] = []
    if not step["lateness_p99_ms"] <= args.lateness_target:
        why.append(("lateness", f"frame lateness p99 {step['lateness_p99_ms']:.2f} ms > "
                                f"{args.lateness_target:g} ms"))
    if not step["corner_delivery"] >= DELIVERY_MIN:
        why.append(("delivery", f"CORNER {step['corner_hz_received']:.0f} Hz of "
                                f"{args.corner_rate:g} asked ({step['corner_delivery']:.0%}, "
                                f"under {DELIVERY_MIN:.0%})"))
    held = not why
    cpus = os.cpu_count() or 1
    if step["server_busiest_thread_cores"] >= SATURATED:
        why.append(("server_cpu", f"server CPU saturated: thread "
                                  f"{step['server_busiest_thread']} at "
                                  f"{step['server_busiest_thread_cores']:.2f} core"))
    elif step["server_cpu_cores"] + step["clients_cpu_cores"] >= SATURATED * cpus:
        why.append(("server_cpu", f"server CPU saturated: servers and clients use "
                                  f"{step['server_cpu_cores'] + step['clients_cpu_cores']:.1f}"
                                  f" of {cpus} cores"))
    if step["client_process_cores_max"] >= SATURATED:
        why.append(("clients_cpu", f"clients' CPU saturated: a client process at "
                                   f"{step['client_process_cores_max']:.2f} core"))
    elif step["hip_sent_per_s"] < DELIVERY_MIN * step["hip_offered_per_s"]:
        why.append(("clients_cpu", f"the clients sent {step['hip_sent_per_s']:.0f} HIP/s of "
                                   f"{step['hip_offered_per_s']:.0f}"))
    step["held"] = held
    step["stopped_by"] = [] if held else [k for k, _ in why]
    step["why"] = [text for _, text in why]


def _cpu_seconds(procs: list[subprocess.Popen[str]]) -> float:
    """User + system CPU seconds of these processes so far, every thread (Linux /proc;
    else NaN)."""
    return sum(_stat_cpu_seconds(f"/proc/{p.pid}/stat") for p in procs)


def _process_kind(p: subprocess.Popen[str]) -> str:
    """A server process as the per-thread figures name it: a gateway or the engine (the one
    process of ``--workers 1`` included)."""
    return "gateway" if "clothball.server.gateway" in p.args else "engine"


# The server's threads by what they do (``server_cores_by_kind``): the native frame loops,
# the engine's event loop (its network and control messages; a process's main thread), the
# gateway processes' Python (accepting, lane messages, control) and their native pumps
# (relaying and their clients' lanes: native/net/pump.hpp), the native MESH encoders, the
# engine's service threads (each frame loop's Python service thread, the recorder, the
# replay index's and the directory's pools), and any other (unnamed) thread.
THREAD_KINDS = ("frame_loop", "event_loop", "gateways", "gateway_pumps", "mesh_encoders",
                "service_threads", "other")
SERVICE_THREADS = ("clothball-", "replay-", "directory")


def thread_kind(process: str, name: str, main: bool) -> str:
    """The kind (``THREAD_KINDS``) of a server thread: of a ``process`` ("engine" or
    "gateway"), named ``name`` by the OS, the process's main thread or not."""
    if process == "gateway":  # its pump (the lanes, the relay), else its Python
        return "gateway_pumps" if name.startswith("cb-pump") else "gateways"
    if main:
        return "event_loop"
    if name.startswith("cb-frame-loop"):
        return "frame_loop"
    if name.startswith("cb-mesh-encode"):
        return "mesh_encoders"
    if name.startswith(SERVICE_THREADS):
        return "service_threads"
    return "other"


def _affinity(procs: list[subprocess.Popen[str]]) -> list[int]:
    """The CPUs any thread of these processes may run on (their union)."""
    cpus: set[int] = set()
    for p in procs:
        try:
            tids = [int(t) for t in os.listdir(f"/proc/{p.pid}/task")]
        except OSError:
            continue
        for tid in tids:
            with contextlib.suppress(OSError):
                cpus |= os.sched_getaffinity(tid)
    return sorted(cpus)


def _threads_cpu_seconds(procs: list[subprocess.Popen[str]]
                         ) -> dict[tuple[int, int], tuple[str, float]]:
    """Every thread of these processes: (pid, tid) -> (its name, CPU seconds so far)."""
    out = {}
    for p in procs:
        try:
            tids = os.listdir(f"/proc/{p.pid}/task")
        except OSError:
            continue
        for tid in tids:
            path = f"/proc/{p.pid}/task/{tid}/stat"
            try:
                text = Path(path).read_text()
            except OSError:  # the thread ended
                continue
            out[(p.pid, int(tid))] = (text[text.index("(") + 1:text.rindex(")")],
                                      _stat_cpu_seconds(path, text))
    return out


def _stat_cpu_seconds(path: str, text: str | None = None) -> float:
    """User + system CPU seconds in a /proc stat file (``text``: already read)."""
    try:
        fields = (text or Path(path).read_text()).rsplit(")", 1)[1].split()
    except OSError:
        return math.nan
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _load_line(s: dict[str, Any]) -> str:
    def ms(v: float | None) -> str:
        return "-" if v is None else f"{v:.2f}"

    verdict = "held" if s["held"] else "STOP"
    if s["why"]:
        verdict += ": " + "; ".join(s["why"])
    return (f"{s['rooms']:3d} rooms {s['clients']:4d} clients  in {s['messages_in_per_s']:6.0f}/s"
            f" out {s['messages_out_per_s']:6.0f}/s  lateness p50 {ms(s['lateness_p50_ms'])} "
            f"p99 {ms(s['lateness_p99_ms'])} ms  HIP->CORNER p50 "
            f"{ms(s['hip_to_corner_p50_ms'])} p99 {ms(s['hip_to_corner_p99_ms'])} ms  CORNER "
            f"{s['corner_hz_received']:.0f}/{s['corner_hz_asked']:g} MESH "
            f"{s['mesh_hz_received']:.1f}/{s['mesh_hz_asked']:g} Hz  frames "
            f"{s['frames_per_s']:.0f}/s  CPU server {s['server_cpu_cores']:.2f} "
            f"({s['server_cpu_per_room']:.3f}/room) clients {s['clients_cpu_cores']:.2f} cores"
            f"  load {s['load_average']:.1f}  {verdict}"
            f"\n      pages: /healthz p50 {ms(s.get('healthz_p50_ms'))} p99 "
            f"{ms(s.get('healthz_p99_ms'))} ms, /api/stats p50 {ms(s.get('stats_p50_ms'))} "
            f"p99 {ms(s.get('stats_p99_ms'))} ms"
            + (f" ({s['healthz_unanswered'] + s['stats_unanswered']} unanswered within "
               f"{PAGE_TIMEOUT_S:g} s)" if s.get("healthz_unanswered", 0)
               + s.get("stats_unanswered", 0) else "")
            + "\n      server cores by kind: " + ", ".join(
                f"{k.replace('_', ' ')} {v:.2f}" for k, v in s["server_cores_by_kind"].items())
            + f"; {_us(s['server_cpu_us_per_message'])} µs of server CPU a message ("
            + ", ".join(f"{k.replace('_', ' ')} {_us(v)}" for k, v in
                        s.get("server_cpu_us_per_message_by_kind", {}).items() if v)
            + "); clients "
            f"{s['clients_cpu_per_room']:.3f} core a room"
            "\n      busiest threads (cores): " + ", ".join(
                f"{k} {v:.2f}" for k, v in list(s.get("server_threads_cores", {}).items())[:5]))


def _us(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"


# --- clothball bench --load --cluster -----------------------------------------------------------


def run_load_cluster(args: argparse.Namespace) -> int:
    """The load series over 1, 2 and 3 hosts (``--cluster-hosts``) joined through a Redis
    of the bench's own; print (or --json) every step of each."""
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
        pin([redis], _cpus(args)[0])  # the cluster's store is the server side's
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
    info = next(iter(series.values()))["info"]
    for s in series.values():
        s.pop("info")
    result = {
        **_load_meta(args, info, load_before),
        "note": f"every host, Redis and the clients run on this one machine and share its "
                f"{os.cpu_count()} cores",
        "hosts": series,
    }
    if _write_json(result, getattr(args, "json", None)):
        print(json.dumps(result, indent=2))
    else:
        for n, r in series.items():
            print(_held_line(f"{n} host{'s' if n != '1' else ''}", r["held"]))
        print(_stopped_line(result))
    return 0


def _held_line(what: str, h: dict[str, Any] | None) -> str:
    """The summary of a series of steps over several hosts or processes."""
    if h is None:
        return f"{what}: held not even one room"
    return (f"{what}: held {h['rooms']} rooms ({'+'.join(map(str, h['rooms_per_host']))}), "
            f"{h['clients']} clients, lateness p99 {h['lateness_p99_ms']:.2f} ms, "
            f"server CPU {h['server_cpu_cores']:.2f} cores")


def _redis_flush(url: str) -> None:
    import redis

    r = redis.Redis.from_url(url)
    try:
        r.flushdb()
    finally:
        r.close()


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
