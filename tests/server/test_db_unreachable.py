"""``clothball host --db`` at a PostgreSQL that does not answer (issue 40): the server runs,
its replay index's failure is said once and tried again with doubling waits (its state in
/api/stats), and the host token is kept in the data directory the lines printed name. No
PostgreSQL is needed: the URL names a loopback port nothing listens on."""

from __future__ import annotations

import asyncio
import logging
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from clothball.server.hostproc import free_port
from clothball.server.storage.datadir import RETRY_MAX_S

from tests.server.conftest import ErrorLog, http_json, run, server

pytest.importorskip("psycopg", reason="--db needs psycopg: pip install 'clothball[cluster]'")

CHECK_S = 0.05  # storage_check_s: the first retry's wait (a short one, to see it double)
WAIT_S = 60.0  # bound on waiting for five failures


def test_an_unreachable_index_is_said_once_and_retried_with_doubling_waits(
        tmp_path: Path) -> None:
    from clothball.server.limits import Limits

    url = f"postgresql://nobody@127.0.0.1:{free_port()}/clothball"
    said = ErrorLog(logging.WARNING)
    logger = logging.getLogger("clothball")
    logger.addHandler(said)

    async def main() -> None:
        limits = Limits().replace(storage_check_s=CHECK_S)
        data = tmp_path / "not-made-yet"
        async with server(data, db=url, limits=limits) as srv:
            state = None

            async def retried() -> bool:
                nonlocal state
                state = (await http_json(srv, "/api/stats"))["storage"]["index_retry"]
                return state["failures"] >= 5

            # Polled over HTTP (/api/stats is where it is shown); a bound on a loaded
            # machine, not a speed claim: five failures need 0.75 s of waits.
            end = asyncio.get_running_loop().time() + WAIT_S
            while not await retried() and asyncio.get_running_loop().time() < end:
                await asyncio.sleep(0.05)
            assert state is not None and state["failures"] >= 5, state
            assert "PostgreSQL" in state["error"] or "pruning" in state["error"], state
            # The wait doubles from storage_check_s at each failure (to RETRY_MAX_S).
            assert state["wait_s"] == pytest.approx(
                min(CHECK_S * 2 ** (state["failures"] - 1), RETRY_MAX_S)), state
            # The token is kept where the server says (the data directory made for it).
            assert srv.host_token_file == data / "host-token"
            assert (data / "host-token").read_text().strip() == srv.host_token

    try:
        run(main())
    finally:
        logger.removeHandler(said)
    # Said once (by the index, or by the pruning where it met the failure first), not at
    # every check.
    lines = [t for t in said.texts() if "cannot be used now" in t or "pruning the" in t]
    assert len(lines) == 1, said.texts()
    assert not [t for t in said.texts() if "host token could not be kept" in t], said.texts()


def _host_lines(tmp_path: Path, *args: str) -> str:
    """What ``clothball host ARGS`` prints up to its last status line; stopped after."""
    with open(tmp_path / "host.log", "w+") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "clothball.game.cli", "host", "--port", "0", "--backend",
             "cpu", "--scene", "classic", *args],
            stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "OMP_NUM_THREADS": "1"})
        try:
            for _ in range(1200):
                text = (tmp_path / "host.log").read_text()
                if "(only this machine can connect" in text or proc.poll() is not None:
                    break
                time.sleep(0.1)
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    return (tmp_path / "host.log").read_text()


def test_host_prints_the_token_file_it_made(tmp_path: Path) -> None:
    """The host's lines are true: a token line names a file that exists, and no "could not
    be kept" warning comes with it (with --db nothing else had made the data directory)."""
    url = f"postgresql://nobody@127.0.0.1:{free_port()}/clothball"
    data = tmp_path / "fresh"
    text = _host_lines(tmp_path, "--db", url, "--data", str(data))
    m = re.search(r"host token \(resets /api/stats\) in (\S+)", text)
    assert m is not None, text
    assert Path(m.group(1)) == (data / "host-token").resolve() and Path(m.group(1)).is_file()
    assert "could not be kept" not in text, text


def test_a_token_that_could_not_be_kept_is_not_said_to_be_in_a_file(tmp_path: Path) -> None:
    """A data directory that cannot be made (a file is in the way): the warning, and no
    line naming a token file that does not exist."""
    (tmp_path / "blocked").write_text("a file, not a directory\n")
    data = tmp_path / "blocked" / "data"
    text = _host_lines(tmp_path, "--data", str(data))
    assert "host token could not be kept" in text, text
    assert "NO host token file" in text, text
    assert "host token (resets /api/stats) in" not in text, text
    assert not (data / "host-token").exists()
