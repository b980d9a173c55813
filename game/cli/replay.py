"""``clothball replay``: play a recorded round in a desktop window (pause, seek, speed).

    clothball replay                        # list the server's recorded rounds
    clothball replay 20250101-120000-abcd   # by id, from --server
    clothball replay round.cbr              # a downloaded file
    clothball replay http://host:8765/api/replays/<id>
"""

from __future__ import annotations

import argparse
import sys
import time
import urllib.error
import urllib.parse
from pathlib import Path

from .display import window_error

DEFAULT_SERVER = "ws://127.0.0.1:8765/ws"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", nargs="?", default=None, metavar="ID|FILE|URL",
                        help="the round: a replay id (from --server), a .cbr file or a URL; "
                             "leave out to list the server's rounds")
    parser.add_argument("--server", default=DEFAULT_SERVER, metavar="URL",
                        help="server to fetch ids from (default %(default)s)")
    parser.add_argument("--speed", type=float, default=1.0, help="playback speed (default 1)")
    parser.add_argument("--start", type=float, default=0.0, metavar="S",
                        help="start S seconds into the round")
    parser.add_argument("--loop", action="store_true", help="play again from the start")
    parser.add_argument("--paused", action="store_true", help="open paused")
    parser.add_argument("--wire", action="store_true", help="start with the wire mesh shown")
    parser.add_argument("--size", default="1280x800", metavar="WxH", help="window size")
    parser.add_argument("--screenshot", type=Path, default=None, metavar="PNG",
                        help="save a screenshot after --quit-after seconds, then quit")
    parser.add_argument("--quit-after", type=float, default=None, metavar="S",
                        help="close the window after S seconds")


def _unreachable(url: str, e: BaseException) -> str:
    """Why the server at ``url`` could not be asked, in the words ``clothball play`` uses
    (the address, what to start or check), not urllib's wrapper."""
    from ..net.client import explain_connect_error

    if isinstance(e, urllib.error.URLError) and not isinstance(e, urllib.error.HTTPError):
        reason = e.reason
    elif isinstance(e, TimeoutError):  # an answer that stopped half-way
        reason = e
    else:  # a file that cannot be read, a bad URL, a damaged replay: its own words
        return str(e)
    if not isinstance(reason, OSError):
        return str(reason)
    parts = urllib.parse.urlsplit(url)
    return explain_connect_error(f"ws://{parts.netloc}/ws", reason)[0]


def run(args: argparse.Namespace) -> int:
    from ..client.replay import ReplayData, ReplayError, ReplayPlayer, fetch, list_remote

    if args.source is None:
        try:
            rows = list_remote(args.server)
        except (OSError, urllib.error.URLError, ValueError) as e:
            print(f"clothball replay: cannot list the rounds on {args.server}: "
                  f"{_unreachable(args.server, e)}", file=sys.stderr)
            return 1
        if not rows:
            print("no recorded rounds yet")
        for r in rows:
            when = time.strftime("%Y-%m-%d %H:%M", time.localtime(r["ended_at"]))
            names = ", ".join(p.get("name") or "-" for p in r["players"])
            print(f"{r['id']}  {when}  room {r['room_name']}  round {r['round']}  "
                  f"{r['duration_s']:.1f} s  conceded edge {r['conceded_edge']}  [{names}]")
        return 0
    try:
        data = ReplayData.parse(fetch(args.source, args.server))
    except urllib.error.HTTPError as e:
        if e.code != 404:
            print(f"clothball replay: cannot load {args.source}: {e}", file=sys.stderr)
            return 1
        print(f"clothball replay: no replay {args.source!r} on {args.server}; list the "
              f"recorded rounds with `clothball replay --server {args.server}` (no id)",
              file=sys.stderr)
        return 1
    except (OSError, urllib.error.URLError, ReplayError) as e:
        where = args.source if args.source.startswith(("http://", "https://")) else args.server
        print(f"clothball replay: cannot load {args.source}: {_unreachable(where, e)}",
              file=sys.stderr)
        return 1
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        print(f"clothball replay: --size must be WIDTHxHEIGHT, got {args.size!r}",
              file=sys.stderr)
        return 2
    player = ReplayPlayer(data, speed=args.speed, loop=args.loop)
    player.seek(args.start)
    player.paused = args.paused
    print(f"replay {data.header.get('id')}: {data.duration:.1f} s, "
          f"{len(data.timeline)} mesh frames, {len(data.tracks)} track samples")
    try:
        import pyglet

        from ..client.app import ClientWindow, run_window
    except Exception as e:  # noqa: BLE001 - no display
        print(f"clothball replay: {window_error(e)}", file=sys.stderr)
        return 1
    window = ClientWindow(replay=player, width=w, height=h,
                          title=f"clothball replay {data.header.get('id')}")
    window.renderer.wire = args.wire
    if args.quit_after is not None:
        def finish(dt: float) -> None:
            if args.screenshot is not None:
                window.screenshot(args.screenshot)
            window.close()

        pyglet.clock.schedule_once(finish, args.quit_after)
    run_window(window)
    return 0
