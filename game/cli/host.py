"""``clothball host``: run a game server until Ctrl-C or SIGTERM."""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys
from pathlib import Path

from ...server.app import GameServer, default_data_dir
from ...server.limits import Limits, parse_origins, parse_trusted_proxies
from ..sim.scene import Scene, SceneError, available
from .args import FIRST_TO, PORT

log = logging.getLogger("clothball.server")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on (0.0.0.0: every interface; default %(default)s)")
    parser.add_argument("--port", type=PORT, default=8765,
                        help="port (0: any free; default %(default)s)")
    parser.add_argument("--bots", type=int, default=0, choices=range(5), metavar="N",
                        help="fill N seats of the main room with bots (4: a self-playing demo)")
    parser.add_argument("--scene", action="append", default=None, metavar="S",
                        help="scene name or TOML path; repeat to offer several (default: classic)")
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


async def serve(args: argparse.Namespace) -> int:
    from ...server.room import RoomSettings

    # The room threads need the GIL for a moment every frame: do not let the event loop
    # hold it for the default 5 ms.
    sys.setswitchinterval(0.0005)
    if not args.verbose:
        logging.getLogger("websockets").setLevel(logging.WARNING)

    scenes: dict[str, Scene] = {}
    for s in args.scene or ["classic"]:
        try:
            scene = Scene.load(s)
        except SceneError as e:
            print(f"clothball host: {e}; shipped scenes: {', '.join(available())}")
            return 2
        scenes[scene.name] = scene
    data = args.data or default_data_dir()
    settings = RoomSettings(first_to=args.first_to, autoplay=True)
    try:
        limits = Limits()
        for text in args.limit:
            limits = limits.with_setting(text)
        origins = parse_origins(args.origin)
        trusted = parse_trusted_proxies(args.trusted_proxy)
    except ValueError as e:
        print(f"clothball host: {e}")
        return 2
    server = GameServer(data, scenes=scenes, backend=args.backend, host=args.host,
                        port=args.port, bots=args.bots, room_settings=settings, limits=limits,
                        origins=origins, trusted_proxies=trusted)
    try:
        await server.start()
    except OSError as e:
        print(f"clothball host: cannot listen on {args.host}:{args.port}: {e.strerror}")
        return 1
    room = server.main_room
    backend = room.sim.cloth.backend if room is not None else args.backend
    print(f"clothball server on {server.ws_url}  (scene {', '.join(scenes)}, backend {backend})")
    print(f"spectate in a browser: {server.http_url}")
    if server.recording_error is not None:
        print(f"NOT recording rounds: {server.recording_error}")
    else:
        print(f"recorded rounds in {Path(data).resolve()}  ({server.http_url}api/replays)")
        print(f"host token (resets /api/stats) in {Path(data).resolve() / 'host-token'}")
    if args.host in ("127.0.0.1", "localhost", "::1"):
        print("(only this machine can connect; --host 0.0.0.0 to let others in)")
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, stop.set)
        except (NotImplementedError, RuntimeError):  # pragma: no cover - not on this platform
            pass
    await stop.wait()
    print("stopping: finishing the writes in progress...")
    await server.stop()
    print("stopped")
    return 0


def run(args: argparse.Namespace) -> int:
    return asyncio.run(serve(args))
