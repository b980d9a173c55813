"""The server process's event loop (server/loops.py): uvloop where installed, asyncio's own
without it or when asked for, a one-line error for a choice that cannot be had."""

from __future__ import annotations

import sys

import pytest
from clothball.server import loops


async def kind() -> str:
    return loops.running()


def test_auto_is_uvloop_where_installed_and_asyncio_on_request(monkeypatch) -> None:
    pytest.importorskip("uvloop")
    monkeypatch.delenv("CLOTHBALL_LOOP", raising=False)
    assert loops.run(kind()) == "uvloop"
    assert loops.run(kind(), "asyncio") == "asyncio"
    monkeypatch.setenv("CLOTHBALL_LOOP", "asyncio")
    assert loops.run(kind()) == "asyncio"
    assert loops.run(kind(), "uvloop") == "uvloop"  # the argument over the environment


def test_without_uvloop_auto_falls_back_and_uvloop_says_what_to_install(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "uvloop", None)  # import uvloop raises ImportError
    monkeypatch.delenv("CLOTHBALL_LOOP", raising=False)
    assert loops.run(kind()) == "asyncio"
    with pytest.raises(loops.LoopError, match="pip install uvloop"):
        loops.run(kind(), "uvloop")


def test_a_bad_choice_is_named(monkeypatch) -> None:
    monkeypatch.setenv("CLOTHBALL_LOOP", "trio")
    with pytest.raises(loops.LoopError, match="CLOTHBALL_LOOP='trio' is not one of"):
        loops.loop_factory()
    coro = kind()
    with pytest.raises(loops.LoopError):
        loops.run(coro)
    assert coro.cr_frame is None  # closed, never started: no "never awaited" warning
