"""The replay index is one interface (``storage.index.ReplayIndex``) with two drivers
(issue 33, item 6): each implements all of it and starts through the shared constructor.
What the drivers do is tested against each other and a reference in
test_replay_index_pg.py and the storage tests."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
from clothball.server.hostproc import free_port
from clothball.server.storage.index import ReplayIndex
from clothball.server.storage.postgres import PostgresIndex
from clothball.server.storage.sql import SqlIndex
from clothball.server.storage.sqlite import SqliteIndex


def interface() -> set[str]:
    names = {n for n, v in vars(ReplayIndex).items()
             if not n.startswith("_") and inspect.isfunction(v)}
    return names | set(ReplayIndex.__annotations__)


def test_both_drivers_implement_the_whole_interface() -> None:
    assert {"save", "list", "count", "locate", "prune", "close", "rounds"} <= interface()
    for driver in (SqliteIndex, PostgresIndex):
        assert issubclass(driver, SqlIndex)
        assert not inspect.isabstract(driver), driver.__abstractmethods__
        methods = {n for n in interface() if n in vars(ReplayIndex)}
        assert all(callable(getattr(driver, n, None)) for n in methods), driver


def test_each_driver_has_every_attribute_the_interface_names(tmp_path: Path) -> None:
    """Set up by the shared constructor: the PostgreSQL one too, with its server away (a
    port nothing listens on: it starts all the same, saying the index is unavailable)."""
    pytest.importorskip("psycopg", reason="the PostgreSQL driver needs psycopg")
    away = f"postgresql://nobody@127.0.0.1:{free_port()}/none"
    for index in (SqliteIndex(tmp_path / "a"),
                  PostgresIndex(tmp_path / "b", away, host="http://b.example:1",
                                connect_timeout_s=1)):
        try:
            missing = [n for n in interface() if not hasattr(index, n)]
            assert not missing, (type(index).__name__, missing)
        finally:
            index.close()
    assert index.index_error is not None and "cannot be used now" in index.index_error
