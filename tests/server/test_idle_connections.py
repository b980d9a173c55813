"""Connection slots (issue 23): idle lobby connections time out with a clear close reason
and a newcomer gets in; the server's own bots and the clients of a trusted proxy (by their
forwarded address) do not take an address's slots. Real server, real clients on loopback
from several addresses (127.0.0.2, 127.0.0.3, ...), scaled down."""

from __future__ import annotations

import asyncio
import ipaddress
import json
from typing import Any

import pytest
from clothball.game.wire import protocol as P
from clothball.server.conn import client_address
from clothball.server.limits import Limits, parse_trusted_proxies
from clothball.server.room import RoomSettings
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from tests.server.conftest import run, server, until

HELLO = json.dumps({"type": "hello", "version": P.PROTOCOL_VERSION})


async def lobby_client(srv: Any, source: str = "127.0.0.1",
                       forwarded: str | None = None) -> ClientConnection:
    """A client that says hello from ``source`` (through a proxy that forwards
    ``forwarded``), reads its welcome, and then sends nothing."""
    ws = await connect(srv.ws_url, local_addr=(source, 0), ping_interval=None,
                       additional_headers={"X-Forwarded-For": forwarded} if forwarded else None)
    await ws.send(HELLO)
    welcome = json.loads(await asyncio.wait_for(ws.recv(), 10))
    assert welcome["type"] == "welcome", welcome
    return ws


async def close_of(ws: ClientConnection, timeout: float = 60.0) -> tuple[int | None, str]:
    """Reads until the server closes; its close code and reason."""
    try:
        while True:
            await asyncio.wait_for(ws.recv(), timeout)
    except ConnectionClosed as e:
        return (e.rcvd.code, e.rcvd.reason) if e.rcvd else (None, "")


async def refused_or_closed(srv: Any, **kw: Any) -> tuple[int | None, str]:
    """A client the server does not keep: the HTTP status (503) or the close."""
    try:
        ws = await lobby_client(srv, **kw)
    except InvalidStatus as e:
        return e.response.status_code, e.response.body.decode() if e.response.body else ""
    except ConnectionClosed as e:
        return (e.rcvd.code, e.rcvd.reason) if e.rcvd else (None, "")
    return await close_of(ws, 10)


def test_idle_lobby_clients_time_out_and_a_newcomer_gets_in(tmp_path) -> None:
    async def main() -> None:
        lim = Limits(lobby_idle_s=1.0, max_clients=40, conns_per_address=8)
        async with server(tmp_path, limits=lim, settings=RoomSettings(autoplay=True)) as srv:
            # A spectator and an active lobby client, there before the idle ones: neither
            # is closed, however long they have been quiet or in the lobby.
            spectator = await connect(srv.ws_url, ping_interval=None)
            await spectator.send(json.dumps({"type": "hello", "version": 1,
                                             "role": "spectator", "room": "main"}))
            active = await lobby_client(srv)
            replies: list[Any] = []

            async def keep_talking() -> None:
                while True:
                    await active.send(json.dumps({"type": "list_rooms"}))
                    replies.append(await active.recv())
                    await asyncio.sleep(0.2)

            talker = asyncio.create_task(keep_talking())
            # One address each: the last slots are kept for addresses that hold none
            # (test_hostile_load.py fills them from a few addresses).
            idle = [await lobby_client(srv, f"127.0.0.{2 + i}") for i in range(38)]
            assert len(srv.clients) == lim.max_clients
            status, body = await refused_or_closed(srv)
            assert status == 503 and "server full" in body

            closes = await asyncio.gather(*(close_of(ws) for ws in idle))
            assert set(closes) == {(1008, "idle: no request but pings for 1 s in the lobby")}
            newcomer = None
            while newcomer is None:  # as soon as the slots come free, not one timeout later
                try:
                    newcomer = await lobby_client(srv, "127.0.0.99")
                except InvalidStatus:
                    await asyncio.sleep(0.05)
            # the active client is still answered (its count waited for: on a loaded
            # machine fewer of its 0.2 s rounds fit in the idle clients' timeout)
            await until(lambda: talker.done() or len(replies) > 5, 30, "six replies")
            assert not talker.done() and len(replies) > 5
            talker.cancel()
            watched = 0
            while watched < 3:  # the spectator still gets the room's frames
                msg = await asyncio.wait_for(spectator.recv(), 10)
                watched += isinstance(msg, bytes)
            for ws in (spectator, active, newcomer):
                await ws.close()

    run(main())


def test_the_servers_own_bots_take_no_address_slot(tmp_path) -> None:
    """Every slot of 127.0.0.1 is held by idle clients: a bot added to a room (which the
    server runs as a client from 127.0.0.1) still connects."""
    async def main() -> None:
        lim = Limits(conns_per_address=2, lobby_idle_s=600)
        async with server(tmp_path, limits=lim, settings=RoomSettings()) as srv:
            holders = [await lobby_client(srv) for _ in range(2)]
            assert srv.per_address["127.0.0.1"] == 2
            code, reason = await refused_or_closed(srv)
            assert code == 1008 and "too many connections from 127.0.0.1" in reason
            room = srv.main_room
            assert room is not None
            room.add_bot(1, 0.5)
            await until(lambda: room.seats[1].kind == "bot" and room.seats[1].connected, 30,
                        "the bot connected")
            assert srv.per_address["127.0.0.1"] == 2  # the bot is not counted there
            for ws in holders:
                await ws.close()

    run(main())


def test_a_trusted_proxys_clients_are_limited_by_their_forwarded_address(tmp_path) -> None:
    async def main() -> None:
        lim = Limits(conns_per_address=2)
        trusted = parse_trusted_proxies(["127.0.0.1"])
        async with server(tmp_path, default_room=False, limits=lim,
                          trusted_proxies=trusted) as srv:
            a = [await lobby_client(srv, forwarded="203.0.113.5") for _ in range(2)]
            code, reason = await refused_or_closed(srv, forwarded="203.0.113.5")
            assert code == 1008 and "too many connections from 203.0.113.5 (limit 2)" in reason
            # others behind the same proxy have slots of their own; a client cannot pick
            # its address by writing one to the left of what the proxy appended
            b = [await lobby_client(srv, forwarded=f"203.0.113.{5 + i}, 198.51.100.7")
                 for i in range(2)]
            assert srv.per_address == {"203.0.113.5": 2, "198.51.100.7": 2}
            # a peer that is not a trusted proxy is its own address, whatever it forwards
            c = await lobby_client(srv, source="127.0.0.2", forwarded="203.0.113.77")
            assert srv.per_address["127.0.0.2"] == 1
            for ws in (*a, *b, c):
                await ws.close()

    run(main())


def test_without_a_trusted_proxy_forwarded_addresses_are_ignored(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path, default_room=False,
                          limits=Limits(conns_per_address=2)) as srv:
            a = [await lobby_client(srv, forwarded=f"203.0.113.{i}") for i in range(2)]
            code, reason = await refused_or_closed(srv, forwarded="203.0.113.99")
            assert code == 1008 and "too many connections from 127.0.0.1" in reason
            for ws in a:
                await ws.close()

    run(main())


NETS = parse_trusted_proxies(["10.0.0.0/8", "127.0.0.1", "::1"])


@pytest.mark.parametrize(("peer", "xff", "want"), [
    ("127.0.0.1", "203.0.113.5", "203.0.113.5"),
    ("127.0.0.1", None, "127.0.0.1"),
    ("198.51.100.1", "203.0.113.5", "198.51.100.1"),  # not a proxy of ours
    ("127.0.0.1", "1.2.3.4, 203.0.113.5", "203.0.113.5"),
    ("127.0.0.1", "203.0.113.5, 10.1.2.3", "203.0.113.5"),  # through two of our proxies
    ("127.0.0.1", "10.1.2.3, 10.4.5.6", "127.0.0.1"),  # only proxies: no client named
    ("127.0.0.1", "unknown", "127.0.0.1"),
    ("127.0.0.1", " 2001:db8::1 ", "2001:db8::1"),
    ("::1", "203.0.113.5", "203.0.113.5"),
])
def test_client_address_reads_the_proxys_own_entry(peer: str, xff: str | None,
                                                   want: str) -> None:
    assert client_address(peer, xff, NETS) == want


def test_trusted_proxy_values_are_checked() -> None:
    assert parse_trusted_proxies(["10.0.0.1", "192.168.0.0/16"]) == (
        ipaddress.ip_network("10.0.0.1"), ipaddress.ip_network("192.168.0.0/16"))
    with pytest.raises(ValueError, match="--trusted-proxy 'proxy.example': expected an IP"):
        parse_trusted_proxies(["proxy.example"])
