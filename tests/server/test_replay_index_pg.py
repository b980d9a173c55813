"""The replay index in PostgreSQL (``PostgresIndex``, ``clothball host --db``) against
the SQLite one as the reference: the same rounds give the same listings, counts and rows
for every filter the HTTP API has; each host's retention and usage cover only its own
rounds; a download of another host's round is that host's URL (with the code of a private
one); with PostgreSQL away rounds are kept as files and their rows written once it is back,
past the kept-back bound too, and a store opened while it is away starts anyway."""

from __future__ import annotations

import itertools
import random
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from clothball.server.storage.index import IndexUnavailable, Retention, access_key
from clothball.server.storage.postgres import PostgresIndex
from clothball.server.storage.sqlite import SqliteIndex

from tests.server.postgres import MISSING, Postgres, postgres_server

pytestmark = pytest.mark.skipif(MISSING is not None, reason=str(MISSING))

CODE = "sesame-1234"
_dbs = itertools.count()


@pytest.fixture(scope="module")
def pg() -> Iterator[Postgres]:
    with postgres_server() as server:
        yield server


def db(pg: Postgres) -> str:
    return pg.database(f"t{next(_dbs)}")


def header(i: int, rng: random.Random, now: float) -> dict[str, Any]:
    room = rng.choice(["r0", "r1", "p0"])
    ended = now - rng.choice([0, 10, 20, 30]) * 60.0  # ties: ordered by id then
    names = rng.sample(["ann", "bob", "cy", "dee", "Émile"], 2)
    h = {"id": f"20260101-000000-{i:04d}", "room_id": room, "room_name": room.upper(),
         "scene": "tiny", "round": i,
         "players": [{"seat": s, "kind": "human", "name": n} for s, n in enumerate(names)],
         "conceded_edge": rng.randrange(4), "conceded_by": None,
         "scores": [rng.randrange(5) for _ in range(4)], "started_at": ended - 12.5,
         "ended_at": ended, "duration_s": 12.25}
    if room == "p0":
        h["access"] = access_key(room, CODE)
    return h


def without_host(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in r.items() if k != "host"} for r in rows]


def test_postgres_lists_and_counts_as_sqlite_does(pg: Postgres, tmp_path: Path) -> None:
    rng = random.Random(7)
    now = time.time()
    rounds = [(header(i, rng, now), f"{i}.cbr", 1000 + i) for i in range(80)]
    ref = SqliteIndex(tmp_path / "sqlite")
    url = db(pg)
    mine = PostgresIndex(tmp_path / "a", url, host="http://a.example:1")
    other = PostgresIndex(tmp_path / "b", url, host="http://b.example:2")
    try:
        ref.index_many(rounds)
        mine.index_many(rounds[:50])
        other.index_many(rounds[50:])  # the same rounds, held by two hosts
        for room in (None, "r0", "p0", "nowhere"):
            for player in (None, "ann", "Émile", "zed"):
                for code in (None, CODE, "wrong"):
                    for limit, offset in ((100, 0), (7, 0), (7, 21), (5, 78)):
                        want = ref.list(limit, offset, room, player=player, code=code)
                        got = mine.list(limit, offset, room, player=player, code=code)
                        assert without_host(got) == want, (room, player, code, limit, offset)
                    assert mine.count(room, player=player, code=code) == \
                        ref.count(room, player=player, code=code)
            assert without_host(mine.list_all(200, room)) == ref.list_all(200, room)
            assert mine.count_all(room) == ref.count_all(room)
        for h, _, _ in rounds:
            assert {**mine.get(h["id"]), "host": None} == {**ref.get(h["id"]), "host": None}
        held = {r["id"]: r["host"] for r in mine.list(1000, code=None)}
        assert set(held.values()) == {"http://a.example:1", "http://b.example:2"}
        assert all(held[h["id"]] == "http://a.example:1" for h, _, _ in rounds[:50]
                   if "access" not in h)
        # Usage is this host's own rounds.
        mine.refresh_usage()
        assert (mine.rounds, mine.bytes) == (50, sum(size for _, _, size in rounds[:50]))
    finally:
        for s in (ref, mine, other):
            s.close()


def test_each_host_prunes_its_own_and_sends_downloads_to_the_holder(pg: Postgres,
                                                                     tmp_path: Path) -> None:
    url = db(pg)
    a = PostgresIndex(tmp_path / "a", url, host="http://a.example:1")
    b = PostgresIndex(tmp_path / "b", url, host="http://b.example:2")
    try:
        rng = random.Random(3)
        now = time.time()
        old = {**header(1, rng, now), "room_id": "r0", "ended_at": now - 40 * 86400.0}
        old.pop("access", None)
        b.save(old, [(0, b"{}")])
        private = {**header(2, rng, now), "room_id": "p0", "access": access_key("p0", CODE)}
        a.save(private, [(0, b"{}")])
        # a's retention (30 days) must not prune b's old round: a cannot delete b's file.
        assert a.prune(Retention(max_age_s=30 * 86400.0)) == []
        assert b.get(old["id"]) is not None
        assert b.locate(old["id"]) == tmp_path / "b" / "replays" / f"{old['id']}.cbr"
        assert a.locate(old["id"]) == f"http://b.example:2/api/replays/{old['id']}.cbr"
        assert b.locate(private["id"]) is None  # a private round without its code
        assert b.locate(private["id"], "wrong") is None
        assert b.locate(private["id"], CODE) == \
            f"http://a.example:1/api/replays/{private['id']}.cbr?code={CODE}"
        assert [r["id"] for r in b.prune(Retention(max_age_s=30 * 86400.0))] == [old["id"]]
        assert a.get(old["id"]) is None
        assert not (tmp_path / "b" / "replays" / f"{old['id']}.cbr").exists()
    finally:
        a.close()
        b.close()


def test_rounds_written_while_postgres_is_away_are_indexed_when_it_is_back(
        tmp_path: Path) -> None:
    with postgres_server() as pg:
        store = PostgresIndex(tmp_path / "a", pg.url, host="http://a.example:1",
                                    max_pending=1)
        rng = random.Random(5)
        now = time.time()
        before = store.save(header(0, rng, now), [(0, b"{}")])
        pg.stop()
        kept = [store.save(header(i, rng, now), [(0, b"{}")]) for i in (1, 2, 3)]
        assert store.index_error is not None and "PostgreSQL" in store.index_error
        assert len(store.pending) == 1  # the bound; the rest are read from their files
        for row in kept:
            assert (tmp_path / "a" / "replays" / f"{row['id']}.cbr").is_file()
        with pytest.raises(IndexUnavailable):
            store.list()
        # A host started while PostgreSQL is away starts, and indexes its files later.
        late_dir = tmp_path / "late"
        (late_dir / "replays").mkdir(parents=True)
        offline = SqliteIndex(tmp_path / "scratch")  # writes the file the late host finds
        late_row = offline.save(header(9, rng, now), [(0, b"{}")])
        offline.close()
        (tmp_path / "scratch" / "replays" / f"{late_row['id']}.cbr").rename(
            late_dir / "replays" / f"{late_row['id']}.cbr")
        late = PostgresIndex(late_dir, pg.url, host="http://late.example:3")
        assert late.index_error is not None
        store.retry_index()  # still away: nothing changes, nothing raised
        assert store.index_error is not None
        pg.start()
        store.retry_index()
        late.retry_index()
        assert store.index_error is None and store.pending == [] and late.index_error is None
        listed = {r["id"]: r for r in store.list_all(100)}
        assert {before["id"], *(r["id"] for r in kept), late_row["id"]} == set(listed)
        for row in [before, *kept]:
            assert listed[row["id"]] == row
        assert listed[late_row["id"]]["host"] == "http://late.example:3"
        store.close()
        late.close()
