"""The second server process of a two-process host, for the suites run with
``CLOTHBALL_TEST_WORKERS=2`` (``tests/server/workers.py``):

    python tests/server/worker_proc.py KWARGS_FILE

KWARGS_FILE is a pickle of the ``GameServer`` arguments the test's own server was given
(data directory included). The server is made as ``clothball host --workers N`` makes each
of its processes (``game/cli/host.py``, ``serve``): the room directory in the data
directory, the shared public port plus a port of its own, no room of its own. Prints one
JSON line ({"port": ...}) once it listens, serves until SIGTERM, then stops cleanly.
Warnings and errors go to stderr, where the test process reads them.
"""

from __future__ import annotations

import asyncio
import json
import logging
import pickle
import signal
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from clothball.game.cli.host import DIRECTORY_FILE  # noqa: E402
from clothball.server import loops  # noqa: E402
from clothball.server.app import GameServer  # noqa: E402
from clothball.server.directory import SqliteDirectory  # noqa: E402


async def main(kwargs_file: str) -> None:
    sys.setswitchinterval(0.0005)  # as serve() does
    kw = pickle.loads(Path(kwargs_file).read_bytes())
    data = Path(kw.pop("data_dir"))
    directory = SqliteDirectory(data / DIRECTORY_FILE)
    srv = GameServer(data, directory=directory, **{**kw, "default_room": False, "port": 0})
    await srv.start()
    print(json.dumps({"port": srv.port}), flush=True)
    stop = asyncio.Event()
    asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, stop.set)
    await stop.wait()
    await srv.stop()
    directory.close()


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")
    loops.run(main(sys.argv[1]))  # on the loop serve() runs on (CLOTHBALL_LOOP)
