"""The server process's event loop (server/loops.py): asyncio's own by default, uvloop when
asked for, a one-line error for a choice that cannot be had."""

from __future__ import annotations

import sys

import pytest
from clothball.server import loops


async def kind() -> str:
    return loops.running()


def test_asyncio_by_default_and_uvloop_on_request(monkeypatch) -> None:
    pytest.importorskip("uvloop")
    monkeypatch.delenv("CLOTHBALL_LOOP", raising=False)
    assert loops.run(kind()) == "asyncio"
    assert loops.run(kind(), "uvloop") == "uvloop"
    monkeypatch.setenv("CLOTHBALL_LOOP", "uvloop")
    assert loops.run(kind()) == "uvloop"
    assert loops.run(kind(), "asyncio") == "asyncio"  # the argument over the environment


def test_without_uvloop_asking_for_it_says_what_to_install(monkeypatch) -> None:
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
