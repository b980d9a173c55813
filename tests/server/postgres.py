"""A PostgreSQL server of a test's own: Debian's binaries (``/usr/lib/postgresql/*/bin``,
apt: postgresql), a cluster made by ``initdb`` in a temporary directory and run on a free
port of loopback, never a system service. PostgreSQL refuses to run as root: as root (CI)
the directory is given to the ``postgres`` system user and the commands run as it
(``runuser``)."""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from clothball.server.hostproc import free_port


def _bin_dir() -> Path | None:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"),
                   key=lambda p: int(Path(p).parent.parent.name)
                   if Path(p).parent.parent.name.isdigit() else 0)
    if found:
        return Path(found[-1]).parent
    initdb = shutil.which("initdb")
    return Path(initdb).parent if initdb else None


BIN = _bin_dir()
AS_ROOT = os.geteuid() == 0
MISSING = None
if BIN is None:
    MISSING = "needs PostgreSQL's initdb and pg_ctl (apt: postgresql)"
elif AS_ROOT and shutil.which("runuser") is None:
    MISSING = "running as root needs runuser (util-linux) to start PostgreSQL as postgres"


class Postgres:
    """``start()``, ``stop()`` (fast shutdown: what it stored stays), ``start()`` again."""

    def __init__(self) -> None:
        assert BIN is not None, MISSING
        self.port = free_port()
        # Not under pytest's tmp_path: as root that is a 0700 directory postgres cannot enter.
        self.dir = Path(tempfile.mkdtemp(prefix="clothball-pg-"))
        self.data = self.dir / "data"
        try:
            if AS_ROOT:
                shutil.chown(self.dir, "postgres", "postgres")
            self._run("initdb", "-D", str(self.data), "-U", "clothball", "--auth=trust",
                      "-E", "UTF8", "--no-sync")
        except BaseException:  # the directory not left behind when initdb fails
            shutil.rmtree(self.dir, ignore_errors=True)
            raise

    @property
    def url(self) -> str:
        return f"postgresql://clothball@127.0.0.1:{self.port}/postgres"

    def database(self, name: str) -> str:
        """A new empty database on this server; its URL."""
        import psycopg

        with psycopg.connect(self.url, autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return f"postgresql://clothball@127.0.0.1:{self.port}/{name}"

    def _run(self, tool: str, *args: str) -> None:
        assert BIN is not None
        cmd = [str(BIN / tool), *args]
        if AS_ROOT:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                       timeout=120)

    def start(self) -> None:
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.dir / "log"), "-w",
                  "-t", "60", "-o",
                  f"-p {self.port} -k {self.dir} -c listen_addresses=127.0.0.1 -c fsync=off",
                  "start")

    def stop(self) -> None:
        self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "-t", "60", "stop")

    def running(self) -> bool:
        return (self.data / "postmaster.pid").exists()

    def remove(self) -> None:
        try:
            if self.running():
                try:
                    self.stop()
                except (subprocess.SubprocessError, OSError):
                    # a fast shutdown that failed: an immediate one, never left running
                    self._run("pg_ctl", "-D", str(self.data), "-m", "immediate", "-w",
                              "-t", "60", "stop")
                    raise
        finally:  # the directory removed however the server stopped
            shutil.rmtree(self.dir, ignore_errors=True)


@contextmanager
def postgres_server() -> Iterator[Postgres]:
    pg = Postgres()
    try:
        pg.start()
        yield pg
    finally:
        pg.remove()
