"""``clothball host``: run a game server until Ctrl-C or SIGTERM.

With ``--workers N`` (default: one per core) it runs N server processes on one port: the
kernel spreads new connections over them (SO_REUSEPORT), each process steps its own rooms
and answers a request for a room another one hosts with a redirect to that process's own
port (docs/protocol.md, "Several processes"). They share the data directory, where a small
SQLite file is their room directory. This process supervises them: it restarts one that
dies and stops them all on Ctrl-C or SIGTERM."""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
from pathlib import Path
from typing import Any

from ...server import loops
from ...server.app import GameServer, default_data_dir
from ...server.directory import PUBLISH_S, Directory, RedisDirectory, SqliteDirectory
from ...server.headroom import usable_cores
from ...server.hostproc import free_port
from ...server.limits import Limits, parse_origins, parse_trusted_proxies
from ..sim.scene import Scene, SceneError
from .args import FIRST_TO, PORT, WORKERS, postgres_url, redis_url, ws_url

log = logging.getLogger("clothball.server")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on (0.0.0.0: every interface; default %(default)s)")
    parser.add_argument("--port", type=PORT, default=8765,
                        help="port (0: any free; default %(default)s)")
    parser.add_argument("--bots", type=int, default=0, choices=range(5), metavar="N",
                        help="fill N seats of the main room with bots (4: a self-playing demo)")
    parser.add_argument("--scene", action="append", default=None, metavar="S",
                        help="scene name or TOML path; repeat to offer several (default: "
                             "default, the game's; classic: the paper's set-up)")
    parser.add_argument("--backend", default="auto", choices=("auto", "cpu", "cuda"),
                        help="cloth backend (default: CUDA when a GPU is present, else CPU)")
    parser.add_argument("--data", type=Path, default=None,
                        help=f"data directory for recorded rounds (default: {default_data_dir()})")
    parser.add_argument("--first-to", type=FIRST_TO, default=5, metavar="N",
                        help="points to win a match in the main room (default %(default)s)")
    parser.add_argument("--limit", action="append", default=[], metavar="NAME=VALUE",
                        help="change a limit on clients, e.g. conns_per_address=8; repeatable "
                             "(the limits and defaults: docs/security.md)")
    parser.add_argument("--origin", action="append", default=None, metavar="URL",
                        help="also let browser pages from this origin connect (e.g. "
                             "https://example.org; * for any); repeatable; default: only "
                             "the server's own pages and non-browser clients")
    parser.add_argument("--trusted-proxy", action="append", default=None, metavar="ADDR",
                        help="a reverse proxy (address or network, e.g. 127.0.0.1) whose "
                             "X-Forwarded-For names the client: its clients then get the "
                             "per-address limits one by one; repeatable")
    parser.add_argument("--workers", type=WORKERS, default=None, metavar="N",
                        help="server processes sharing the port, each stepping its own rooms "
                             f"(default: one per core, here {os.cpu_count() or 1})")
    parser.add_argument("--cluster", type=redis_url, default=None, metavar="redis://HOST:PORT/DB",
                        help="join the hosts sharing this Redis as one service: one lobby, "
                             "rooms placed on the least-loaded host (docs/cluster.md); a "
                             "Redis that does not answer at start is an error")
    parser.add_argument("--cluster-optional", action="store_true",
                        help="with --cluster: when its Redis does not answer at start, run "
                             "standalone (saying so) instead of stopping")
    parser.add_argument("--advertise", type=ws_url, default=None, metavar="ws://HOST:PORT/ws",
                        help="the address other hosts give out for this host's rooms "
                             "(default: the listen address)")
    parser.add_argument("--db", type=postgres_url, default=None,
                        metavar="postgresql://USER@HOST:PORT/DB",
                        help="keep the replay index in this PostgreSQL database, shared by "
                             "the cluster's hosts: any host lists and serves every host's "
                             "rounds (default: SQLite in the data directory; docs/cluster.md)")
    # Set by the supervisor for each of its processes (not for users).
    parser.add_argument("--worker-index", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--shared-port", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--rooms-file", type=Path, default=None, help=argparse.SUPPRESS)


async def serve(args: argparse.Namespace) -> int:
    from ...server.room import RoomSettings

    # The room threads need the GIL for a moment every frame: do not let the event loop
    # hold it for the default 5 ms.
    sys.setswitchinterval(0.0005)
    if not args.verbose:
        logging.getLogger("websockets").setLevel(logging.WARNING)

    checked = _check(args)
    if checked is None:
        return 2
    scenes, limits, origins, trusted = checked
    data = args.data or default_data_dir()
    settings = RoomSettings(first_to=args.first_to, autoplay=True)
    worker = args.worker_index
    directory: Directory | None = None
    clustered = False
    if args.cluster:
        redis_dir = RedisDirectory(args.cluster)
        try:
            await asyncio.to_thread(redis_dir.check)
            directory, clustered = redis_dir, True
        except ValueError as e:
            redis_dir.close()
            where = _without_password(args.cluster)
            if not args.cluster_optional:
                print(f"clothball host: the cluster's Redis at {where} does not answer ({e}); "
                      "start it, fix --cluster, or add --cluster-optional to run standalone",
                      flush=True)
                return 1
            print(f"NOT in a cluster: the Redis at {where} does not answer ({e}); running "
                  "standalone (--cluster-optional)", flush=True)
    if directory is None and worker is not None:
        directory = SqliteDirectory(args.rooms_file or Path(data) / DIRECTORY_FILE)
    server = GameServer(data, scenes=scenes, backend=args.backend, host=args.host,
                        port=0 if worker is not None else args.port,
                        bots=args.bots, room_settings=settings, limits=limits,
                        origins=origins, trusted_proxies=trusted,
                        default_room=not worker, directory=directory,
                        shared_port=args.shared_port, advertise=args.advertise,
                        host_id=f"{socket.gethostname()}-{os.getpid()}", db=args.db)
    try:
        await server.start()
    except OSError as e:
        print(f"clothball host: cannot listen on {args.host}:{args.port}: {e.strerror}")
        return 1
    if worker is not None:
        # One line for the supervisor, then this process runs quietly until stopped.
        print(json.dumps({"worker": worker, "url": server.own_url,
                          "backend": server.main_room.sim.backend if server.main_room
                          else args.backend,
                          "recording": server.recording_error}), flush=True)
        await _until_stopped()
        await server.stop()
        if directory is not None:
            directory.close()
        return 0
    room = server.main_room
    backend = room.sim.backend if room is not None else args.backend
    print(f"clothball server on {server.ws_url}  (scene {', '.join(scenes)}, backend {backend})")
    print(f"spectate in a browser: {server.http_url}")
    if server.recording_error is not None:
        print(f"NOT recording rounds: {server.recording_error}")
    else:
        print(f"recorded rounds in {Path(data).resolve()}  ({server.http_url}api/replays)")
        print(f"host token (resets /api/stats) in {Path(data).resolve() / 'host-token'}")
    if args.host in ("127.0.0.1", "localhost", "::1"):
        print("(only this machine can connect; --host 0.0.0.0 to let others in)")
    if args.db:
        state = server.storage.index_error or "reachable"
        print(f"replay index in {_without_password(args.db)} ({state}), shared with the "
              f"other hosts; this host's files named as {server.advertised_http_url}")
    if clustered:
        print(f"in the cluster at {_without_password(args.cluster)} as "
              f"{server.advertised_url}")
    await _until_stopped()
    print("stopping: finishing the writes in progress...")
    await server.stop()
    if directory is not None:
        directory.close()
    print("stopped")
    return 0


def _check(args: argparse.Namespace) -> tuple[dict[str, Scene], Limits, Any, Any] | None:
    """The scenes, limits, origins and trusted proxies asked for; None (said why) when one
    is wrong. The supervisor checks them too, before starting any process."""
    scenes: dict[str, Scene] = {}
    for s in args.scene or ["default"]:
        try:
            scene = Scene.load(s)
        except SceneError as e:
            print(f"clothball host: {e}")  # an unknown name's error lists the scenes
            return None
        scenes[scene.name] = scene
    if args.db is not None:
        try:
            import psycopg  # noqa: F401  (the shared replay index's driver)
        except ImportError:
            print("clothball host: --db needs psycopg: pip install 'clothball[cluster]'")
            return None
    try:
        limits = Limits()
        for text in args.limit:
            limits = limits.with_setting(text)
        return scenes, limits, parse_origins(args.origin), \
            parse_trusted_proxies(args.trusted_proxy)
    except ValueError as e:
        print(f"clothball host: {e}")
        return None


async def _until_stopped() -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, stop.set)
        except (NotImplementedError, RuntimeError):  # pragma: no cover - not on this platform
            pass
    await stop.wait()


DIRECTORY_FILE = "rooms.sqlite"  # the processes' room directory, in the data directory
RESTART_S = 1.0  # a process that died is started again after this long


def run(args: argparse.Namespace) -> int:
    workers = args.workers or os.cpu_count() or 1
    try:  # CLOTHBALL_LOOP=uvloop chooses uvloop (server/loops.py)
        loops.loop_factory()
    except loops.LoopError as e:
        print(f"clothball host: {e}")
        return 2
    if args.worker_index is not None or workers == 1:
        return loops.run(serve(args))
    return supervise(args, workers)


class _Worker:
    """One server process of the supervisor: started, its ready line read, its later output
    passed on."""

    def __init__(self, index: int, cmd: list[str]) -> None:
        self.index = index
        self.cmd = cmd
        self.proc: subprocess.Popen[str] | None = None
        self.ready: dict[str, object] | None = None

    def start(self, timeout: float = 120.0) -> None:
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.append(self.proc.stdout.readline()),
                                  daemon=True)  # type: ignore[union-attr]
        reader.start()
        reader.join(timeout)
        first = lines[0] if lines else ""
        try:
            self.ready = json.loads(first)
        except json.JSONDecodeError:
            self.ready = None
            print(first, end="")
        threading.Thread(target=self._pass_on, daemon=True).start()

    def _pass_on(self) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        for line in self.proc.stdout:
            print(line, end="", flush=True)


def supervise(args: argparse.Namespace, workers: int) -> int:
    """Run ``workers`` server processes on one port until Ctrl-C or SIGTERM."""
    if _check(args) is None:
        return 2
    try:
        port = args.port or free_port(args.host)
    except OSError as e:
        print(f"clothball host: cannot listen on {args.host}: {e.strerror}")
        return 1
    data = Path(args.data or default_data_dir())
    rooms_file, spare = _rooms_file(data)
    base = [sys.executable, "-m", "clothball.game.cli", *args.argv]
    if not any(s.replace("-", "_").startswith("admit_cores=") for s in args.limit):
        # Admission: each process's rooms may use its share of the machine's cores.
        base += ["--limit", f"admit_cores={usable_cores() / workers:.3g}"]
    procs = [_Worker(k, [*base, "--data", str(data), "--port", str(port), "--workers", "1",
                         "--worker-index", str(k), "--shared-port", str(port),
                         "--rooms-file", str(rooms_file)])
             for k in range(workers)]
    stopping = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stopping.set())
    try:
        for w in procs:
            w.start()
            if w.ready is None:
                rc = w.proc.wait(timeout=30) if w.proc is not None else 1
                print(f"clothball host: server process {w.index} did not start (exit {rc})")
                return rc or 1
        # Every process reads the directory every PUBLISH_S: by now each knows the others.
        time.sleep(2 * PUBLISH_S)
        first = procs[0].ready or {}
        url = f"ws://{_shown(args.host)}:{port}/ws"
        print(f"clothball server on {url}  ({workers} processes; scene "
              f"{', '.join(args.scene or ['default'])}, backend {first.get('backend')})")
        print(f"spectate in a browser: http://{_shown(args.host)}:{port}/")
        if first.get("recording"):
            print(f"NOT recording rounds: {first['recording']}")
        else:
            print(f"recorded rounds in {data.resolve()}  (http://{_shown(args.host)}:{port}"
                  "/api/replays)")
            print(f"host token (resets /api/stats) in {data.resolve() / 'host-token'}")
        if args.host in ("127.0.0.1", "localhost", "::1"):
            print("(only this machine can connect; --host 0.0.0.0 to let others in)")
        while not stopping.wait(0.5):
            for w in procs:
                if w.proc is not None and w.proc.poll() is not None:
                    print(f"server process {w.index} exited ({w.proc.returncode}); "
                          "starting it again")
                    time.sleep(RESTART_S)
                    w.start()
        print("stopping: finishing the writes in progress...")
    finally:
        for w in procs:
            if w.proc is not None and w.proc.poll() is None:
                w.proc.send_signal(signal.SIGTERM)
        for w in procs:
            if w.proc is not None:
                try:
                    w.proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    w.proc.kill()
        if spare is not None:
            shutil.rmtree(spare, ignore_errors=True)
    print("stopped")
    return 0


def _without_password(url: str) -> str:
    """``url`` with any password in it replaced by ``***`` (it is printed)."""
    parts = urllib.parse.urlsplit(url)
    if parts.password is None:
        return url
    netloc = parts.netloc.replace(f":{parts.password}@", ":***@", 1)
    return urllib.parse.urlunsplit(parts._replace(netloc=netloc))


def _rooms_file(data: Path) -> tuple[Path, Path | None]:
    """Where the processes keep their room directory: in the data directory, or, when that
    cannot be written (the processes then play without recording, as one process does), in
    a directory of its own made for this run (returned second, to be removed at the end)."""
    try:
        data.mkdir(parents=True, exist_ok=True)
        SqliteDirectory(data / DIRECTORY_FILE).close()
        return data / DIRECTORY_FILE, None
    except (OSError, sqlite3.Error) as e:
        spare = Path(tempfile.mkdtemp(prefix="clothball-rooms-"))
        print(f"the data directory {data} cannot be used ({getattr(e, 'strerror', None) or e}):"
              f" the processes' room directory is in {spare}")
        return spare / DIRECTORY_FILE, spare


def _shown(host: str) -> str:
    host = host if host not in ("0.0.0.0", "::", "") else "127.0.0.1"
    return f"[{host}]" if ":" in host else host
