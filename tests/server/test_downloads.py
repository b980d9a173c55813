"""Replay downloads (issue 21): streamed from disk in chunks, one byte range with HTTP
``Range`` (206, ``Content-Range``; 416 for a range the file cannot satisfy), and twenty at
once cost the server bounded memory, measured as the server process's resident size and
as the bytes it holds for the downloads, never as a time."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from clothball.game.wire.replay import new_round_id
from clothball.server.app import GameServer, ServerConfig
from clothball.server.http import DOWNLOAD_CHUNK, RangeError, parse_range
from clothball.server.limits import Limits
from clothball.server.storage.sqlite import SqliteIndex

from tests.server.conftest import run, server, until


def save_round(data: Path, payload: bytes, records: int) -> tuple[str, bytes]:
    """One round of ``records`` incompressible records in ``data``; its id and file bytes."""
    store = SqliteIndex(data)
    try:
        rid = new_round_id()
        header = dict(id=rid, room_id="r", room_name="r", scene="tiny", round=1, players=[],
                      scores=[0, 0, 0, 0], started_at=time.time() - 1, ended_at=time.time(),
                      duration_s=1.0)  # now: retention keeps it
        store.save(header, [(1, payload[i::records]) for i in range(records)])
        return rid, (data / "replays" / f"{rid}.cbr").read_bytes()
    finally:
        store.close()


def request(port: int, rid: str, extra: str = "") -> socket.socket:
    s = socket.socket()
    try:
        # A small, fixed receive buffer (no autotuning to megabytes): a client that stops
        # reading backs the server up after a few chunks.
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 64 * 1024)
        s.settimeout(30)
        s.connect(("127.0.0.1", port))
        s.sendall(f"GET /api/replays/{rid} HTTP/1.1\r\nHost: x\r\n{extra}\r\n".encode())
    except BaseException:  # never left open when the request fails
        s.close()
        raise
    return s


def read_head(s: socket.socket) -> tuple[int, dict[str, str], bytes]:
    """The status, headers (lower-case names) and whatever body came with them."""
    buf = b""
    while b"\r\n\r\n" not in buf:
        b = s.recv(4096)
        assert b, f"closed before the head: {buf!r}"
        buf += b
    head, _, body = buf.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, _, v in (x.partition(":") for x in lines[1:])}
    return int(lines[0].split()[1]), headers, body


def read_all(s: socket.socket, body: bytes) -> bytes:
    chunks = [body]
    while b := s.recv(1 << 16):
        chunks.append(b)
    return b"".join(chunks)


def get(port: int, rid: str, range_: str | None = None) -> tuple[int, dict[str, str], bytes]:
    with request(port, rid, f"Range: {range_}\r\n" if range_ is not None else "") as s:
        status, headers, body = read_head(s)
        return status, headers, read_all(s, body)


# --- Range, against slices of the file itself --------------------------------------------------


@pytest.mark.parametrize(("header", "size", "want"), [
    (None, 10, None), ("bytes=0-0", 10, (0, 0)), ("bytes=2-5", 10, (2, 5)),
    ("bytes=2-", 10, (2, 9)), ("bytes=-3", 10, (7, 9)), ("bytes=-30", 10, (0, 9)),
    ("bytes=4-400", 10, (4, 9)), (" BYTES = 1-2 ", 10, (1, 2)), ("items=0-5", 10, None),
])
def test_parse_range_takes_the_forms_of_rfc_9110(header: str | None, size: int,
                                                  want: tuple[int, int] | None) -> None:
    assert parse_range(header, size) == want


@pytest.mark.parametrize(("header", "size", "words"), [
    ("bytes=10-", 10, "past the end"), ("bytes=10-20", 10, "past the end"),
    ("bytes=5-2", 10, "before the first"), ("bytes=-0", 10, "no byte"),
    ("bytes=0-1,4-5", 10, "one byte range"), ("bytes=x-1", 10, "is not"),
    ("bytes=-", 10, "is not"), ("bytes=0-", 0, "past the end"),
    ("bytes=" + "9" * 5000 + "-", 10, "is not"),  # int() would refuse 5000 digits
])
def test_parse_range_names_what_is_wrong(header: str, size: int, words: str) -> None:
    with pytest.raises(RangeError, match=words):
        parse_range(header, size)


def test_a_download_is_the_file_and_a_range_is_its_slice(tmp_path: Path) -> None:
    rid, whole = save_round(tmp_path, os.urandom(300_000), 7)
    size = len(whole)
    assert size > 3 * DOWNLOAD_CHUNK  # several chunks

    async def main() -> None:
        async with server(tmp_path, default_room=False) as srv:
            def check() -> None:
                status, h, body = get(srv.port, rid)
                assert (status, body, h["accept-ranges"]) == (200, whole, "bytes")
                assert int(h["content-length"]) == size and "content-range" not in h
                for rng, (a, b) in [("bytes=0-99", (0, 99)), ("bytes=1000-", (1000, size - 1)),
                                    ("bytes=-500", (size - 500, size - 1)),
                                    (f"bytes={size - 1}-{size + 50}", (size - 1, size - 1)),
                                    (f"bytes={DOWNLOAD_CHUNK - 3}-{2 * DOWNLOAD_CHUNK + 3}",
                                     (DOWNLOAD_CHUNK - 3, 2 * DOWNLOAD_CHUNK + 3))]:
                    status, h, body = get(srv.port, rid, rng)
                    assert status == 206, (rng, body[:200])
                    assert h["content-range"] == f"bytes {a}-{b}/{size}"
                    assert body == whole[a:b + 1] and int(h["content-length"]) == b - a + 1
                for rng in (f"bytes={size}-", "bytes=9-3", "bytes=0-1,3-4", "bytes=abc"):
                    status, h, body = get(srv.port, rid, rng)
                    assert status == 416, rng
                    assert h["content-range"] == f"bytes */{size}"
                    assert "error" in json.loads(body)
                status, _, _ = get(srv.port, "nosuchround1")
                assert status == 404

            await asyncio.to_thread(check)
            assert srv.http.downloads == 0

    run(main())


def test_a_pruned_file_is_still_sent_whole_to_a_download_under_way(tmp_path: Path) -> None:
    """The file is opened once: removing it mid-download cuts nothing short."""
    rid, whole = save_round(tmp_path, os.urandom(2_000_000), 16)

    async def main() -> None:
        async with server(tmp_path, default_room=False) as srv:
            s = await asyncio.to_thread(request, srv.port, rid)
            with s:
                status, _, body = await asyncio.to_thread(read_head, s)
                (tmp_path / "replays" / f"{rid}.cbr").unlink()
                assert status == 200
                assert await asyncio.to_thread(read_all, s, body) == whole

    run(main())


def test_twenty_stalled_downloads_hold_at_most_a_chunk_each(tmp_path: Path) -> None:
    """Clients that read the head and then stop: the server has read at most one chunk
    ahead for each (the bytes waiting for a socket), however large the file."""
    rid, whole = save_round(tmp_path, os.urandom(8_000_000), 32)

    async def main() -> None:
        async with server(tmp_path, default_room=False) as srv:
            socks = [await asyncio.to_thread(request, srv.port, rid) for _ in range(20)]
            try:
                heads = [await asyncio.to_thread(read_head, s) for s in socks]
                assert all(h[0] == 200 for h in heads)
                await until(lambda: srv.http.downloads == 20, 20, "20 downloads under way")
                assert srv.http.download_bytes_held_max <= 20 * DOWNLOAD_CHUNK
                for s, (_, _, body) in zip(socks, heads, strict=True):
                    assert await asyncio.to_thread(read_all, s, body) == whole
            finally:
                for s in socks:
                    s.close()
            await until(lambda: srv.http.downloads == 0, 20, "downloads finished")

    run(main())


def test_the_download_limit_answers_503(tmp_path: Path) -> None:
    rid, _ = save_round(tmp_path, os.urandom(4_000_000), 16)

    async def main() -> None:
        async with server(tmp_path, default_room=False, limits=Limits(max_downloads=2)) as srv:
            socks = [await asyncio.to_thread(request, srv.port, rid) for _ in range(2)]
            try:
                for s in socks:
                    await asyncio.to_thread(read_head, s)
                status, _, body = await asyncio.to_thread(get, srv.port, rid)
                assert status == 503 and "2 downloads" in json.loads(body)["error"]
            finally:
                for s in socks:
                    s.close()

    run(main())


def test_a_client_that_stops_reading_is_cut_after_the_stall_limit(tmp_path: Path) -> None:
    rid, _ = save_round(tmp_path, os.urandom(8_000_000), 32)

    async def main() -> None:
        async with server(tmp_path, default_room=False,
                          limits=Limits(download_stall_s=0.5)) as srv:
            s = await asyncio.to_thread(request, srv.port, rid)
            with s:
                await asyncio.to_thread(read_head, s)
                await until(lambda: srv.http.downloads == 0, 30, "the stalled download cut")

    run(main())


def test_stopping_the_server_cuts_a_stalled_download(tmp_path: Path) -> None:
    """A download whose client has stopped reading does not hold the server's stop up for
    its stall time (here ten minutes: the stop would time out)."""
    rid, whole = save_round(tmp_path, os.urandom(8_000_000), 32)

    async def main() -> None:
        srv = GameServer(ServerConfig(tmp_path, port=0, default_room=False,
                                      limits=Limits(download_stall_s=600)))
        await srv.start()
        s = await asyncio.to_thread(request, srv.port, rid)
        with s:
            _, _, body = await asyncio.to_thread(read_head, s)
            await until(lambda: srv.http.downloads == 1, 20, "the download under way")
            await srv.stop()
            assert srv.http.downloads == 0
            try:
                got = await asyncio.to_thread(read_all, s, body)
            except ConnectionResetError:
                got = b""
            assert len(got) < len(whole)  # cut, not finished

    run(main())


# --- the server process's memory ---------------------------------------------------------------

SERVER = """
import asyncio, json, sys
from clothball.server.app import GameServer, ServerConfig

async def main():
    srv = GameServer(ServerConfig(sys.argv[1], port=0, default_room=False))
    await srv.start()
    print(json.dumps({"port": srv.port}), flush=True)
    await asyncio.Event().wait()

asyncio.run(main())
"""


def rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS")


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux /proc")
def test_twenty_concurrent_downloads_of_a_large_replay_cost_less_than_one_file(
        tmp_path: Path) -> None:
    """Issue 21 measured 2.2 GB for 20 downloads of a 52 MB round (each read whole). Here 20
    clients download a 16 MB round and stop reading after the head: the server process
    grows by less than the file's size in all (it holds a chunk and a socket's buffer each)."""
    size = 16 << 20
    rid, whole = save_round(tmp_path, os.urandom(size), 64)
    proc = subprocess.Popen([sys.executable, "-c", SERVER, str(tmp_path)],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        port = json.loads(proc.stdout.readline())["port"]
        assert get(port, rid)[2] == whole  # warm: the pools' threads exist
        before = rss_bytes(proc.pid)
        socks: list[socket.socket] = []
        try:
            for _ in range(20):  # (each one made closed below, however far this got)
                socks.append(request(port, rid))
            heads: list[Any] = [read_head(s) for s in socks]
            assert all(h[0] == 200 for h in heads)
            grown = rss_bytes(proc.pid) - before
            print(f"server RSS grew {grown / 2**20:.1f} MiB for 20 downloads of "
                  f"{len(whole) / 2**20:.1f} MiB")
            assert grown < len(whole), f"the server grew {grown >> 20} MiB for 20 downloads"
            assert read_all(socks[0], heads[0][2]) == whole
        finally:
            for s in socks:
                s.close()
    finally:
        proc.kill()
        proc.communicate()
