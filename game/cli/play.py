"""``clothball play``: the desktop client (pyglet window), live against a server.

    clothball play                          # lobby of ws://127.0.0.1:8765/ws, mouse
    clothball play --server ws://host:8765/ws --room ROOM --seat 2 --name ann
    clothball play --local                  # in-process server with 3 bots: a solo game
    clothball play --device falcon --firmware novint.bin
"""

from __future__ import annotations

import argparse
import getpass
import logging
import sys
from pathlib import Path
from typing import Any

import numpy as np

from .args import FIRST_TO, ws_url
from .display import window_error

log = logging.getLogger("clothball.client")

DEVICES = ("mouse", "falcon", "falcon-emulator", "bot")
DEFAULT_SERVER = "ws://127.0.0.1:8765/ws"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--server", type=ws_url, default=DEFAULT_SERVER, metavar="URL",
                        help="server websocket URL (default %(default)s)")
    parser.add_argument("--room", default=None, metavar="R",
                        help="join this room at once (default: choose in the lobby)")
    parser.add_argument("--seat", type=int, default=None, choices=range(4), metavar="S",
                        help="corner 0..3 to take (default: the first free one)")
    parser.add_argument("--code", default=None, help="join code of a private room")
    parser.add_argument("--spectate", action="store_true", help="watch instead of playing")
    parser.add_argument("--name", default=None, metavar="N",
                        help="your name (default: your login name)")
    parser.add_argument("--device", default="mouse", choices=DEVICES,
                        help="input device (default %(default)s)")
    parser.add_argument("--firmware", default=None, metavar="FILE",
                        help="Falcon firmware file (only needed when the device has none)")
    parser.add_argument("--difficulty", type=float, default=0.6,
                        help="--device bot: skill 0..1 (default %(default)s)")
    parser.add_argument("--ready", action="store_true", help="say ready as soon as seated")
    parser.add_argument("--local", action="store_true",
                        help="start an in-process server with bots and join it")
    parser.add_argument("--bots", type=int, default=3, choices=range(4), metavar="N",
                        help="--local: bots in the room (default %(default)s)")
    parser.add_argument("--scene", default="default",
                        help="--local: scene (default: default, the game's; classic: the "
                             "paper's set-up)")
    parser.add_argument("--backend", default="auto", choices=("auto", "cpu", "cuda"),
                        help="--local: cloth backend")
    parser.add_argument("--first-to", type=FIRST_TO, default=5, metavar="N",
                        help="--local: points to win (default %(default)s)")
    parser.add_argument("--data", type=Path, default=None,
                        help="--local: data directory for the recorded rounds")
    parser.add_argument("--size", default="1280x800", metavar="WxH", help="window size")
    parser.add_argument("--fps", type=float, default=60.0, help="display rate (default 60)")
    parser.add_argument("--screenshot", type=Path, default=None, metavar="PNG",
                        help="save a screenshot after --quit-after seconds, then quit")
    parser.add_argument("--quit-after", type=float, default=None, metavar="S",
                        help="close the window after S seconds")


class SeatBot:
    """``game.bots.BotDevice`` for a seat known only once joined (``bind``)."""

    name = "bot"

    def __init__(self, difficulty: float) -> None:
        self.difficulty = difficulty
        self.bot: Any = None

    def bind(self, joined: dict[str, Any]) -> None:
        from ..bots import BotDevice

        self.bot = BotDevice(int(joined["seat"]), np.array(joined["geometry"]["anchors"]),
                             self.difficulty)

    def start(self, reach: Any) -> None:
        self.bot.start(reach)

    def stop(self) -> None:
        if self.bot is not None:
            self.bot.stop()

    def hand_position(self) -> np.ndarray:
        return self.bot.hand_position()

    def update_corner(self, state: Any) -> None:
        self.bot.update_corner(state)

    def update_ball(self, position: Any, velocity: Any, t: float) -> None:
        self.bot.update_ball(position, velocity, t)


def make_device(args: argparse.Namespace) -> Any:
    if args.device == "mouse":
        from ..devices.mouse import MouseDevice

        return MouseDevice()
    if args.device == "bot":
        return SeatBot(args.difficulty)
    from ..devices.falcon import open_falcon

    return open_falcon(args.firmware, emulator=args.device == "falcon-emulator",
                       status=lambda msg: print(msg, flush=True))


def run(args: argparse.Namespace) -> int:
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        print(f"clothball play: --size must be WIDTHxHEIGHT, got {args.size!r}", file=sys.stderr)
        return 2
    name = args.name or _login_name()
    try:
        device = make_device(args)
    except Exception as e:  # noqa: BLE001 - NoDeviceError, AccessDeniedError, FirmwareError...
        print(f"clothball play: cannot open the {args.device}: {e}", file=sys.stderr)
        return 2
    local = None
    url = args.server
    if args.local:
        from ...server.app import default_data_dir
        from ...server.room import RoomSettings
        from ...server.thread import ServerThread
        from ..sim.scene import Scene, SceneError

        data = args.data if args.data is not None else default_data_dir() / "local"
        try:
            scene = Scene.load(args.scene)
        except SceneError as e:
            print(f"clothball play: {e}", file=sys.stderr)
            device.stop()
            return 2
        # The room thread needs the GIL briefly every frame (see cli.host).
        sys.setswitchinterval(0.0005)
        local = ServerThread(data, scenes={scene.name: scene}, backend=args.backend,
                             bots=args.bots,
                             room_settings=RoomSettings(first_to=args.first_to, autoplay=True))
        print("starting a local server...", flush=True)
        url = local.start().ws_url
        print(f"local server on {url}  (recorded rounds in {data})", flush=True)
    from ..client.netthread import NetThread

    fast = args.device.startswith("falcon")
    net = NetThread(url, name=name, device=device if not args.spectate else None,
                    corner_rate=1000.0 if fast else 120.0, hip_rate=1000.0 if fast else 120.0,
                    report=_say)
    auto_join = None
    if args.room is not None or args.local:
        auto_join = {"room": args.room, "seat": args.seat, "code": args.code,
                     "role": "spectator" if args.spectate else "player",
                     "ready": args.ready}
    try:
        import pyglet  # noqa: F401 - a clear message when there is no display

        from ..client.app import ClientWindow, fps_summary, run_window
        from ..client.model import ClientModel
    except Exception as e:  # noqa: BLE001 - NoSuchDisplayException and friends
        print(f"clothball play: {window_error(e)}", file=sys.stderr)
        if local is not None:
            local.stop()
        device.stop()
        return 1
    net.start()
    model = ClientModel(name=name, server_url=url)
    window = ClientWindow(net=net, device=device, model=model, auto_join=auto_join,
                          width=w, height=h, title=f"clothball - {name}")
    if args.quit_after is not None:
        import pyglet

        def finish(dt: float) -> None:
            if args.screenshot is not None:
                window.screenshot(args.screenshot)
                print(f"screenshot saved: {args.screenshot}", flush=True)
            window.close()

        pyglet.clock.schedule_once(finish, args.quit_after)
    try:
        run_window(window, args.fps)
    finally:
        log.info("%s", fps_summary(window))
        net.stop()
        if local is not None:
            local.stop()
    return 1 if model.connection == "failed" else 0


def _say(line: str) -> None:
    """A connection problem on the terminal too (the window shows it as well)."""
    print(f"clothball play: {line}", file=sys.stderr, flush=True)


def _login_name() -> str:
    try:
        return getpass.getuser()[:32] or "player"
    except Exception:  # noqa: BLE001 - no login name in some containers
        return "player"
