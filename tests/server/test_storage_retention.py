"""Retention of recorded rounds (issue 21): a total size and an age, the oldest pruned first
with its file and index row together; the disk in use in ``/api/stats``; the
``clothball replays`` command."""

from __future__ import annotations

import contextlib
import json
import os
import random
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from clothball.game.cli import main as cli
from clothball.game.wire.replay import read_replay
from clothball.server.limits import Limits
from clothball.server.storage.index import Retention, access_key
from clothball.server.storage.sqlite import SqliteIndex

from tests.server.conftest import http_json, run, server, until

DAY = 86400.0


def header(i: int, ended_at: float, **kw: Any) -> dict[str, Any]:
    return dict(id=f"keep{i:05d}-x", room_id="r", room_name="r", scene="tiny", round=i,
                players=[{"seat": 0, "kind": "human", "name": f"p{i % 3}"}],
                scores=[0, 0, 0, 0], started_at=ended_at - 1, ended_at=ended_at,
                duration_s=1.0, **kw)


def fill(store: SqliteIndex, n: int, now: float, seed: int = 0) -> dict[str, tuple[float, int]]:
    """``n`` rounds of random sizes and ages; id -> (ended_at, file size)."""
    rng = random.Random(seed)
    out = {}
    for i in range(n):
        h = header(i, now - rng.uniform(0, 10 * DAY))
        row = store.save(h, [(1, os.urandom(rng.randint(100, 20_000)))])
        out[row["id"]] = (h["ended_at"], row["bytes"])
    return out


def on_disk(data: Path) -> set[str]:
    return {p.stem for p in (data / "replays").glob("*.cbr")}


def indexed(data: Path) -> set[str]:
    with sqlite3.connect(data / "index.sqlite") as db:
        return {r[0] for r in db.execute("SELECT id FROM rounds")}


def kept_reference(rounds: dict[str, tuple[float, int]], keep: Retention,
                   now: float) -> set[str]:
    """What retention keeps, by brute force: of the rounds young enough, the largest
    newest-first run that fits in the budget (at least the newest one)."""
    young = sorted((r for r in rounds.items() if r[1][0] >= now - keep.max_age_s),
                   key=lambda r: (r[1][0], r[0]), reverse=True)
    for k in range(len(young), 0, -1):
        if k == 1 or sum(size for _, (_, size) in young[:k]) <= keep.max_bytes:
            return {rid for rid, _ in young[:k]}
    return set()


@pytest.mark.parametrize(("max_bytes", "max_days"), [(60_000, 100), (10**9, 3.5),
                                                     (45_000, 6), (1, 100), (10**9, 1e-6)])
def test_prune_keeps_what_the_reference_keeps_files_and_rows_together(
        tmp_path: Path, max_bytes: int, max_days: float) -> None:
    now = 1.7e9
    store = SqliteIndex(tmp_path)
    rounds = fill(store, 40, now)
    keep = Retention(max_bytes, max_days * DAY)
    want = kept_reference(rounds, keep, now)
    would = store.prune(keep, now=now, dry_run=True)
    assert on_disk(tmp_path) == indexed(tmp_path) == set(rounds)  # a dry run removes nothing
    gone = store.prune(keep, now=now)
    assert {r["id"] for r in gone} == {r["id"] for r in would} == set(rounds) - want
    assert [r["ended_at"] for r in gone] == sorted(r["ended_at"] for r in gone)  # oldest first
    assert on_disk(tmp_path) == indexed(tmp_path) == want
    assert (store.rounds, store.bytes) == (len(want), sum(rounds[r][1] for r in want))
    assert store.count_all() == len(want)
    store.close()


def test_each_save_prunes_to_the_budget_and_the_newest_round_stays(tmp_path: Path) -> None:
    store = SqliteIndex(tmp_path, retention=Retention(50_000, 30 * DAY))
    now = time.time()  # saves prune by the clock
    rounds: dict[str, tuple[float, int]] = {}
    for i in range(12):
        h = header(i, now + i)
        row = store.save(h, [(1, os.urandom(15_000 if i != 7 else 80_000))])
        rounds[row["id"]] = (h["ended_at"], row["bytes"])
        want = kept_reference(rounds, store.retention, now + i)  # type: ignore[arg-type]
        assert on_disk(tmp_path) == indexed(tmp_path) == want
        assert row["id"] in want  # the round just saved, even the one over the budget
    store.close()


def test_a_file_that_cannot_be_removed_keeps_its_row(tmp_path: Path, monkeypatch) -> None:
    store = SqliteIndex(tmp_path)
    rounds = fill(store, 5, 1.7e9)

    def refuse(src: Any, dst: Any) -> None:
        raise PermissionError(13, "Permission denied", str(src))

    monkeypatch.setattr(os, "replace", refuse)
    with pytest.raises(PermissionError):
        store.prune(Retention(1, 1e9), now=1.7e9)
    monkeypatch.undo()
    assert on_disk(tmp_path) == indexed(tmp_path) == set(rounds)  # neither went
    store.close()


def test_a_failed_commit_puts_the_file_back(tmp_path: Path, monkeypatch) -> None:
    store = SqliteIndex(tmp_path)
    rounds = fill(store, 3, 1.7e9)
    real = store._transaction

    @contextlib.contextmanager
    def failing() -> Iterator[None]:
        with real():
            yield
            raise sqlite3.OperationalError("disk I/O error")  # rolled back

    monkeypatch.setattr(store, "_transaction", failing)
    with pytest.raises(sqlite3.OperationalError):
        store.prune(Retention(1, 1e9), now=1.7e9)
    monkeypatch.undo()
    assert on_disk(tmp_path) == indexed(tmp_path) == set(rounds)
    assert not list((tmp_path / "replays").glob("*.del"))
    store.close()


# A process that prunes one round and is killed (os._exit: nothing more runs) at one point.
CRASH = """
import os, sys
from clothball.server.storage.index import Retention
from clothball.server.storage.sqlite import SqliteIndex
store = SqliteIndex(sys.argv[1])
if sys.argv[2] == "before-commit":
    real = os.replace
    def replace(a, b):
        real(a, b)
        os._exit(9)  # the file is aside, the row's deletion not committed
    os.replace = replace
else:
    SqliteIndex._discard = staticmethod(lambda p: os._exit(9))  # committed, file aside
store.prune(Retention(1, 1e12), now=1.7e9)
"""


@pytest.mark.parametrize("when", ["before-commit", "after-commit"])
def test_a_prune_killed_midway_leaves_both_or_neither_after_the_next_start(
        tmp_path: Path, when: str) -> None:
    store = SqliteIndex(tmp_path)
    rounds = fill(store, 3, 1.7e9)
    store.close()
    oldest = min(rounds, key=lambda r: rounds[r][0])
    proc = subprocess.run([sys.executable, "-c", CRASH, str(tmp_path), when])
    assert proc.returncode == 9
    assert (tmp_path / "replays" / f"{oldest}.cbr.del").exists()
    again = SqliteIndex(tmp_path)  # the next start
    # One transaction removes the batch (every round but the newest here): all or none.
    newest = max(rounds, key=lambda r: rounds[r][0])
    want = set(rounds) if when == "before-commit" else {newest}
    assert on_disk(tmp_path) == indexed(tmp_path) == want
    assert not list((tmp_path / "replays").glob("*.del"))
    again.close()


def test_stats_show_the_disk_in_use_and_the_limits(tmp_path: Path) -> None:
    store = SqliteIndex(tmp_path)
    rounds = fill(store, 6, time.time() + 11 * DAY)  # ended 1 to 11 days from now: none too old
    store.close()
    sizes = sum(p.stat().st_size for p in (tmp_path / "replays").glob("*.cbr"))

    async def main() -> None:
        limits = Limits(replays_max_mib=512, replays_max_days=7)
        async with server(tmp_path, default_room=False, limits=limits) as srv:
            st = (await http_json(srv, "/api/stats"))["storage"]
            assert st["rounds"] == len(rounds) and st["bytes"] == sizes
            assert st["max_bytes"] == 512 * 2**20 and st["max_days"] == 7

    run(main())


def test_the_server_prunes_at_start_by_its_limits(tmp_path: Path) -> None:
    store = SqliteIndex(tmp_path)
    now = time.time()
    old = store.save(header(1, now - 9 * DAY), [])["id"]
    new = store.save(header(2, now - 1 * DAY), [])["id"]
    store.close()

    async def main() -> None:
        async with server(tmp_path, default_room=False,
                          limits=Limits(replays_max_days=5)) as srv:
            # In the background, at once (test_hostile_load: a large backlog).
            await until(lambda: srv.store is not None and srv.store.rounds == 1, 10,
                        "the start-up prune")
            assert [r["id"] for r in (await http_json(srv, "/api/replays"))["replays"]] == [new]
            assert srv.store is not None and srv.store.rounds == 1

    run(main())
    assert on_disk(tmp_path) == {new} and old not in indexed(tmp_path)


# --- clothball replays --------------------------------------------------------------------------


def test_cli_lists_prunes_and_exports(tmp_path: Path, capsys) -> None:
    data = tmp_path / "data"
    store = SqliteIndex(data)
    rounds = fill(store, 8, 1.7e9)
    secret = header(99, 1.8e9, access=access_key("r", "pw"))
    store.save(secret, [(0, b'{"type":"x"}')])
    store.close()
    assert cli(["replays", "--data", str(data), "list", "--json", "--limit", "100"]) == 0
    listed = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["id"] for r in listed][0] == secret["id"]  # the host sees private rounds
    assert {r["id"] for r in listed} == set(rounds) | {secret["id"]}
    assert cli(["replays", "list", "--player", "p1", "--data", str(data)]) == 0  # either place
    out = capsys.readouterr().out
    assert f"of {sum(1 for r in rounds if int(r[4:9]) % 3 == 1)} rounds shown" in out

    out_dir = tmp_path / "out"
    out_dir.mkdir()
    assert cli(["replays", "--data", str(data), "export", secret["id"], "--to",
                str(out_dir)]) == 0
    exported = read_replay((out_dir / f"{secret['id']}.cbr").read_bytes())
    assert exported[0]["id"] == secret["id"]
    capsys.readouterr()

    everything = {**rounds, secret["id"]: (1.8e9, (data / "replays" /
                                                   f"{secret['id']}.cbr").stat().st_size)}
    want = kept_reference(everything, Retention(int(0.03 * 2**20), 1e9 * DAY), 1.9e9)
    assert 1 < len(want) < len(everything)
    assert cli(["replays", "--data", str(data), "prune", "--max-mib", "0.03",
                "--max-days", "1e9", "--dry-run"]) == 0
    assert on_disk(data) == set(everything)
    assert cli(["replays", "--data", str(data), "prune", "--max-mib", "0.03",
                "--max-days", "1e9"]) == 0
    assert f"removed {len(everything) - len(want)} rounds" in capsys.readouterr().out
    assert on_disk(data) == indexed(data) == want


@pytest.mark.parametrize(("argv", "words"), [
    (["list"], "no replay index in"),
    (["export", "nosuchround", "--to", "."], "no round 'nosuchround'"),
    (["export", "a1234567", "b1234567", "--to", "missing-dir"], "must be an existing directory"),
])
def test_cli_errors_name_the_problem(tmp_path: Path, capsys, argv: list[str],
                                     words: str) -> None:
    data = tmp_path / "data"
    if argv[0] != "list":
        SqliteIndex(data).close()
    else:
        data = tmp_path / "nothing-here"
    assert cli(["replays", "--data", str(data), *argv]) == 1
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err and err.count("\n") == 1


def test_cli_export_refuses_to_overwrite(tmp_path: Path, capsys) -> None:
    store = SqliteIndex(tmp_path / "data")
    (rid,) = fill(store, 1, 1.7e9)
    store.close()
    target = tmp_path / "x.cbr"
    target.write_bytes(b"mine")
    assert cli(["replays", "--data", str(tmp_path / "data"), "export", rid, "--to",
                str(target)]) == 1
    assert "exists" in capsys.readouterr().err and target.read_bytes() == b"mine"
    with pytest.raises(SystemExit):
        cli(["replays", "--data", str(tmp_path / "data"), "prune", "--max-mib", "-1"])
