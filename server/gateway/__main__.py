"""``python -m clothball.server.gateway``: one gateway process, started by ``clothball
host`` (not for users). Prints one JSON line once it listens, relays until SIGTERM, or
until the host that started it is gone (``server.shared.lifeline``)."""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import signal
import sys
from pathlib import Path

from ..shared import lifeline
from ..shared.listen import raise_open_files
from .relay import Gateway


async def main(args: argparse.Namespace) -> int:
    try:
        gw = Gateway(args.host, args.port, args.engine_socket, slow_drop_s=args.slow_drop_s,
                     send_buffer=args.send_buffer)
        await gw.start()
    except (OSError, ValueError) as e:
        why = (e.strerror or str(e)) if isinstance(e, OSError) else str(e)
        print(json.dumps({"gateway": args.index, "error": why}), flush=True)
        return 1
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    if args.lifeline is not None:
        lifeline.watch(args.lifeline, stop.set)
    print(json.dumps({"gateway": args.index, "pid": os.getpid()}), flush=True)
    await stop.wait()
    await gw.stop()
    return 0


def limit_args(slow_drop_s: float, send_buffer: int) -> list[str]:
    """A gateway process's arguments for the host's ``Limits.slow_drop_s`` and
    ``socket_send_buffer`` (what ``clothball host`` gives each gateway)."""
    return ["--slow-drop-s", repr(slow_drop_s), "--send-buffer", str(send_buffer)]


def parse(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="clothball-gateway")
    p.add_argument("--host", required=True)
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--engine-socket", type=Path, required=True)
    p.add_argument("--index", type=int, default=0)
    p.add_argument("--parent", type=int, default=None)
    p.add_argument("--lifeline", type=int, default=None)
    # the host's Limits.slow_drop_s and socket_send_buffer (None: the defaults, the same)
    p.add_argument("--slow-drop-s", type=float, default=None)
    p.add_argument("--send-buffer", type=int, default=None)
    return p.parse_args(argv)


if __name__ == "__main__":
    a = parse(sys.argv[1:])
    if a.parent is not None:
        lifeline.arm(a.parent)
    raise_open_files()  # two sockets a client it relays
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")
    sys.exit(asyncio.run(main(a)))
