"""A game server in a process of its own, for the fault tests (SIGKILL, a full disk):

    python tests/server/server_proc.py DATA_DIR [--fsize BYTES]
        [--engine-socket PATH --public-port PORT]

The main room has four bots playing fast rounds, recorded under DATA_DIR. Prints one JSON
line ({"port": ..., "recording": ...}) once it listens, then runs until killed.
``--fsize`` caps the size of any file the process writes (RLIMIT_FSIZE): a write past it
fails with EFBIG, as a write to a full disk fails with ENOSPC. ``--engine-socket``: the
engine of a host whose gateways listen on ``--public-port``, as ``clothball host
--workers`` runs it.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import resource
import signal
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from clothball.server.app import GameServer, ServerConfig  # noqa: E402
from clothball.server.room import RoomSettings  # noqa: E402

from tests.server.conftest import BACKEND, FAST, TINY  # noqa: E402


async def main(data: str, engine_socket: Path | None, public_port: int | None) -> None:
    sys.setswitchinterval(0.0005)
    settings = RoomSettings(**{**FAST, "first_to": 99}, autoplay=True)
    together = {} if engine_socket is None else {"engine_socket": engine_socket,
                                                 "public_port": public_port}
    srv = GameServer(ServerConfig(data, scenes={"tiny": TINY}, backend=BACKEND, port=0, bots=4,
                                  room_settings=settings, **together))
    await srv.start()
    print(json.dumps({"port": srv.port, "recording": srv.recording_error or "on"}), flush=True)
    await asyncio.Event().wait()


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("--fsize", type=int, default=0)
    ap.add_argument("--engine-socket", type=Path, default=None)
    ap.add_argument("--public-port", type=int, default=None)
    a = ap.parse_args()
    if a.fsize:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of being killed
        resource.setrlimit(resource.RLIMIT_FSIZE, (a.fsize, a.fsize))
    asyncio.run(main(a.data, a.engine_socket, a.public_port))
