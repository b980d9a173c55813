"""``clothball host``: run a game server until Ctrl-C or SIGTERM.

With ``--workers N`` (default: one per core; one process on 1-2 cores) of 2 or more it runs
one engine process, which
owns every room of the host, and N - 1 gateway processes that accept the clients on the
one public port (SO_REUSEPORT) and carry each connection to the engine over its Unix
socket (docs/architecture.md): a client reaches any room of the host through any gateway,
with no redirect. This process supervises them: it restarts one that dies, stops them all
on Ctrl-C or SIGTERM, and they end with it however it ends (``server.shared.lifeline``).
``--workers 1`` is one process that does it all."""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import resource
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
from pathlib import Path
from typing import Any

from ...server import loops
from ...server.app import GameServer, ServerConfig, default_data_dir
from ...server.directory import Directory, RedisDirectory
from ...server.gateway.__main__ import limit_args
from ...server.hostproc import free_port
from ...server.limits import Limits, parse_origins, parse_trusted_proxies
from ...server.shared import lifeline
from ...server.shared.listen import raise_open_files
from ...server.sim.pool import cpu_loops_default, loop_rooms_default
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
                        help="processes of this host: one engine (every room) and N - 1 "
                             "gateways sharing the port; 1: one process for everything "
                             f"(default: one per core, one process on 1-2 cores; here "
                             f"{default_workers()})")
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
    # Set by the supervisor for its engine process (not for users).
    parser.add_argument("--engine-socket", type=Path, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--public-port", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--parent", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--lifeline", type=int, default=None, help=argparse.SUPPRESS)


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
    engine = args.engine_socket is not None
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
    # The engine listens on a loopback port of its own (its bots connect there) and on
    # the gateways' socket; players are given the public port.
    config = ServerConfig(data, scenes=scenes, backend=args.backend,
                          host="127.0.0.1" if engine else args.host,
                          port=0 if engine else args.port, bots=args.bots,
                          room_settings=settings, limits=limits, origins=origins,
                          trusted_proxies=trusted, public_port=args.public_port,
                          engine_socket=args.engine_socket,
                          advertise=args.advertise or (_public_url(args) if engine else None),
                          host_id=f"{socket.gethostname()}-{os.getpid()}", db=args.db)
    server = GameServer(config, directory=directory)
    try:
        await server.start()
    except OSError as e:
        print(f"clothball host: cannot listen on {args.host}:{args.port}: {e.strerror}")
        return 1
    # Ctrl-C and SIGTERM stop it cleanly from before its first line: whoever reads the
    # lines (a supervisor, a test) may stop it at once.
    stop = _stop_on_signals(args.lifeline if engine else None)
    if engine:
        # One line for the supervisor, then this process runs quietly until stopped.
        print(json.dumps({"engine": os.getpid(), "url": server.own_url,
                          "backend": server.main_room.sim.backend if server.main_room
                          else args.backend,
                          "recording": server.recording_error,
                          "host_token_file": None if server.host_token_file is None
                          else str(server.host_token_file.resolve())}), flush=True)
        await stop.wait()
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
    _say_host_token(server.host_token_file)
    if args.host in ("127.0.0.1", "localhost", "::1"):
        print("(only this machine can connect; --host 0.0.0.0 to let others in)")
    if args.db:
        state = server.storage.index_error or "reachable"
        print(f"replay index in {_without_password(args.db)} ({state}), shared with the "
              f"other hosts; this host's files named as {server.advertised_http_url}")
    if clustered:
        print(f"in the cluster at {_without_password(args.cluster)} as "
              f"{server.advertised_url}")
    await stop.wait()
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


def _stop_on_signals(lifeline_fd: int | None = None) -> asyncio.Event:
    """An event set on SIGINT or SIGTERM, or (a child of the supervisor) once the
    supervisor is gone; the handlers are in place when it returns."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, stop.set)
        except (NotImplementedError, RuntimeError):  # pragma: no cover - not on this platform
            pass
    if lifeline_fd is not None:
        lifeline.watch(lifeline_fd, stop.set)
    return stop


RESTART_S = 1.0  # a process that died is started again after this long


# A frame loop's block and mesh board are memfds that gateway processes map; a file size
# limit below their size keeps them in the engine's memory alone (64 rooms' block and board
# are a few MiB at n = 48, 8 at n = 128).
SHARED_MEMORY_BYTES = 64 << 20


def _can_share_memory() -> bool:
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return soft == resource.RLIM_INFINITY or soft >= SHARED_MEMORY_BYTES


def default_workers(cpus: int | None = None) -> int:
    """This host's processes when ``--workers`` is not given: one per core, but one process
    on a machine of 1 or 2 cores. There the engine's frame loop and event loop need both
    cores, and a gateway beside them cost rooms: on a 2-core VM an engine and a gateway held
    4 and 2 rooms where one process held 6 and 4 (docs/benchmarks/host-2026-11-27-lanes/
    README.md). One process serves every room on the one port all the same."""
    cpus = cpus if cpus is not None else os.cpu_count() or 1
    return cpus if cpus >= 3 else 1


def run(args: argparse.Namespace) -> int:
    workers = args.workers or default_workers()
    try:  # CLOTHBALL_LOOP=uvloop chooses uvloop (server/loops.py)
        loops.loop_factory()
    except loops.LoopError as e:
        print(f"clothball host: {e}")
        return 2
    if args.parent is not None:
        lifeline.arm(args.parent)
    raise_open_files()  # every client is a socket or two in each process (issue 43)
    try:
        cpu_loops_default()
        loop_rooms_default()
    except ValueError as e:
        print(f"clothball host: {e}")
        return 2
    if workers > 1 and args.engine_socket is None and not _can_share_memory():
        print(f"clothball host: the file size limit (ulimit -f) is below "
              f"{SHARED_MEMORY_BYTES >> 20} MiB, so the rooms' memory cannot be shared with "
              "gateway processes: running one process (raise the limit for --workers)",
              flush=True)
        workers = 1
    if args.engine_socket is not None or workers == 1:
        return loops.run(serve(args))
    return supervise(args, workers)


class _Child:
    """One process of the supervisor (the engine or a gateway): started, its ready line
    read, its later output passed on."""

    def __init__(self, name: str, cmd: list[str], lifeline_fd: int) -> None:
        self.name = name
        self.cmd = cmd
        self.lifeline_fd = lifeline_fd
        self.proc: subprocess.Popen[str] | None = None
        self.ready: dict[str, object] | None = None

    def start(self, timeout: float = 120.0) -> None:
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.PIPE, text=True,
                                     pass_fds=(self.lifeline_fd,))
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
        if self.ready is not None and "error" in self.ready:
            print(f"clothball host: {self.name}: {self.ready['error']}")
            self.ready = None
        threading.Thread(target=self._pass_on, daemon=True).start()

    def _pass_on(self) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        for line in self.proc.stdout:
            print(line, end="", flush=True)


def supervise(args: argparse.Namespace, workers: int) -> int:
    """Run the engine and ``workers - 1`` gateways on one port until Ctrl-C or SIGTERM."""
    checked = _check(args)
    if checked is None:
        return 2
    limits = checked[1]
    try:
        port = args.port or free_port(args.host)
    except OSError as e:
        print(f"clothball host: cannot listen on {args.host}: {e.strerror}")
        return 1
    data = Path(args.data or default_data_dir())
    private = Path(tempfile.mkdtemp(prefix="clothball-host-"))  # 0700: the engine's socket
    sock = private / "engine.sock"
    life_r, life_w = lifeline.pipe()
    me = str(os.getpid())
    ties = ["--parent", me, "--lifeline", str(life_r)]
    engine = _Child("the engine", [
        sys.executable, "-m", "clothball.game.cli", *args.argv, "--data", str(data),
        "--port", "0", "--workers", "1", "--engine-socket", str(sock),
        "--public-port", str(port), *ties], life_r)
    gateways = [_Child(f"gateway {k}", [
        sys.executable, "-m", "clothball.server.gateway", "--host", args.host, "--port",
        str(port), "--engine-socket", str(sock), "--index", str(k),
        *limit_args(limits.slow_drop_s, limits.socket_send_buffer), *ties], life_r)
        for k in range(max(1, workers - 1))]
    procs = [engine, *gateways]
    stopping = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stopping.set())
    try:
        for w in procs:
            w.start()
            if w.ready is None:
                rc = w.proc.wait(timeout=30) if w.proc is not None else 1
                print(f"clothball host: {w.name} did not start (exit {rc})")
                return rc or 1
        first = engine.ready or {}
        url = f"ws://{_shown(args.host)}:{port}/ws"
        print(f"clothball server on {url}  (an engine and {len(gateways)} gateway"
              f"{'s' if len(gateways) > 1 else ''}; scene "
              f"{', '.join(args.scene or ['default'])}, backend {first.get('backend')})")
        print(f"spectate in a browser: http://{_shown(args.host)}:{port}/")
        if first.get("recording"):
            print(f"NOT recording rounds: {first['recording']}")
        else:
            print(f"recorded rounds in {data.resolve()}  (http://{_shown(args.host)}:{port}"
                  "/api/replays)")
        token_file = first.get("host_token_file")
        _say_host_token(Path(token_file) if isinstance(token_file, str) else None)
        if args.host in ("127.0.0.1", "localhost", "::1"):
            print("(only this machine can connect; --host 0.0.0.0 to let others in)")
        while not stopping.wait(0.2):
            for w in procs:
                if w.proc is not None and w.proc.poll() is not None and not stopping.is_set():
                    print(f"{w.name} exited ({w.proc.returncode}); starting it again",
                          flush=True)
                    time.sleep(RESTART_S)
                    w.start()
        print("stopping: finishing the writes in progress...")
    finally:
        # Gateways first (no new requests), then the engine (it finishes its writes).
        for group in (gateways, [engine]):
            for w in group:
                if w.proc is not None and w.proc.poll() is None:
                    w.proc.send_signal(signal.SIGTERM)
            for w in group:
                if w.proc is not None:
                    try:
                        w.proc.wait(timeout=30)
                    except subprocess.TimeoutExpired:
                        w.proc.kill()
        os.close(life_w)
        os.close(life_r)
        shutil.rmtree(private, ignore_errors=True)
    print("stopped")
    return 0


def _say_host_token(path: Path | None) -> None:
    """Where the host token is, only where it was kept (the server logged why not)."""
    if path is not None:
        print(f"host token (resets /api/stats) in {path.resolve()}")
    else:
        print("NO host token file (see the warning above): /api/stats?reset=1 is refused")


def _public_url(args: argparse.Namespace) -> str:
    """The engine's address for other hosts of a cluster: the gateways' public port."""
    return f"ws://{_shown(args.host)}:{args.public_port}/ws"


def _without_password(url: str) -> str:
    """``url`` with any password in it replaced by ``***`` (it is printed)."""
    parts = urllib.parse.urlsplit(url)
    if parts.password is None:
        return url
    netloc = parts.netloc.replace(f":{parts.password}@", ":***@", 1)
    return urllib.parse.urlunsplit(parts._replace(netloc=netloc))


def _shown(host: str) -> str:
    host = host if host not in ("0.0.0.0", "::", "") else "127.0.0.1"
    return f"[{host}]" if ":" in host else host
