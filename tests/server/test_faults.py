"""Faults: clients that vanish or stop reading, the server killed with SIGKILL mid-round,
a data directory that is full, read-only or unusable, a simulation that turns non-finite.
The server keeps running and loses nothing it had stored."""

from __future__ import annotations

import base64
import contextlib
import json
import os
import random
import shutil
import signal
import socket
import sqlite3
import struct
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from clothball.game.net.client import NetClient
from clothball.game.wire.replay import read_replay
from clothball.server.app import GameServer, ServerConfig
from clothball.server.limits import Limits
from clothball.server.room import RoomSettings
from clothball.server.storage.sqlite import SqliteIndex

from tests.server import workers
from tests.server.conftest import (
    FAST,
    TINY,
    LiveServer,
    children,
    http_get,
    http_json,
    live_server,
    run,
    until,
)
from tests.server.unstable import unstable_scene

HERE = Path(__file__).parent


# --- a websocket client by hand: one that can stop reading or vanish ------------------------------


def raw_client(port: int, hello: dict[str, Any], rcvbuf: int | None = None) -> socket.socket:
    """A connection whose hello seats it, read until the hello's answer; a ``redirect`` (the
    room lives on the other process, with two) is followed to the port it names."""
    for _ in range(3):
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            answer = _seated(s, port, hello, rcvbuf)
        except BaseException:  # never left open when the hello fails
            s.close()
            raise
        if answer["type"] != "redirect":
            assert answer["type"] == "joined", answer
            return s
        s.close()
        port = int(urllib.parse.urlsplit(answer["url"]).port or 0)
    raise AssertionError("redirected too often")


def _seated(s: socket.socket, port: int, hello: dict[str, Any], rcvbuf: int | None
            ) -> dict[str, Any]:
    """``raw_client``'s connection and hello on ``s``: the hello's answer."""
    if rcvbuf:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    s.settimeout(10)
    s.connect(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16))
    s.sendall(b"GET /ws HTTP/1.1\r\nHost: localhost\r\nUpgrade: websocket\r\n"
              b"Connection: Upgrade\r\nSec-WebSocket-Key: " + key +
              b"\r\nSec-WebSocket-Version: 13\r\n\r\n")
    head = b""
    while b"\r\n\r\n" not in head:
        head += s.recv(1)
    assert b" 101 " in head.split(b"\r\n")[0], head
    payload = json.dumps(hello).encode()
    mask = os.urandom(4)
    n = len(payload)
    frame = bytes([0x81]) + (bytes([0x80 | n]) if n < 126 else bytes([0xFE]) +
                             struct.pack(">H", n))
    s.sendall(frame + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))
    while (answer := _next_text(s))["type"] not in ("joined", "redirect", "error"):
        pass
    return answer


def _exactly(s: socket.socket, n: int) -> bytes:
    out = b""
    while len(out) < n:
        got = s.recv(n - len(out))
        if not got:
            raise ConnectionError("closed by the server")
        out += got
    return out


def _next_text(s: socket.socket) -> dict[str, Any]:
    """The next text message the server sent (its frames are unmasked; others skipped)."""
    while True:
        b0, b1 = _exactly(s, 2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", _exactly(s, 2))[0]
        elif n == 127:
            n = struct.unpack(">Q", _exactly(s, 8))[0]
        data = _exactly(s, n)
        if b0 & 0x0F == 1:
            return dict(json.loads(data))


def conn_of(ls: LiveServer, seat: int) -> Any:
    room = ls.srv.main_room
    assert room is not None
    return ls.call(lambda: room.seats[seat].conn)


def wait(pred: Any, timeout: float, what: str) -> float:
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.02)
    return time.monotonic() - t0


def test_a_client_that_vanishes_without_a_close(tmp_path) -> None:
    limits = Limits(ping_interval=0.5, ping_timeout=0.5)
    with live_server(tmp_path, limits=limits) as ls:
        room = ls.srv.main_room
        assert room is not None
        hello = {"type": "hello", "version": 1, "role": "player", "room": room.id,
                 "corner_rate": 50, "mesh": False}
        # 1. the TCP connection is reset (a crashed client): noticed at once
        with contextlib.closing(raw_client(workers.public_port(ls.srv),
                                           {**hello, "seat": 2})) as s:
            wait(lambda: conn_of(ls, 2) is not None, 5, "seat 2 taken")
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            s.close()
        wait(lambda: conn_of(ls, 2) is None, 5, "the reset client's seat released")
        assert ls.call(lambda: room.seats[2].held_until) is not None  # held for its return
        # 2. the client goes silent (a pulled cable): the pings go unanswered
        with contextlib.closing(raw_client(workers.public_port(ls.srv),
                                           {**hello, "seat": 3})):
            wait(lambda: conn_of(ls, 3) is not None, 5, "seat 3 taken")
            took = wait(lambda: conn_of(ls, 3) is None, 10, "the silent client dropped")
            assert took < 5
        wait(lambda: ls.call(lambda: len(ls.srv.clients)) == 0, 5, "no clients left")
        assert room.sim.alive and ls.errors.texts() == []


class Reader:
    """Reads a connection on a thread of its own until it ends: the bytes, when the last
    came, and the close frame's code and reason (None: it ended without one)."""

    def __init__(self, s: socket.socket) -> None:
        self.s = s
        self.got = 0
        self.last = time.monotonic()
        self.close: tuple[int, str] | None = None
        self.ended = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        try:
            self.s.settimeout(30)
            while True:
                b0, b1 = _exactly(self.s, 2)
                n = b1 & 0x7F
                if n == 126:
                    n = struct.unpack(">H", _exactly(self.s, 2))[0]
                elif n == 127:
                    n = struct.unpack(">Q", _exactly(self.s, 8))[0]
                data = _exactly(self.s, n)
                self.got += 2 + n
                self.last = time.monotonic()
                if b0 & 0x0F == 8:
                    self.close = (struct.unpack(">H", data[:2])[0], data[2:].decode())
                    return
        except (OSError, ConnectionError):
            pass  # its end (or a reset)
        finally:
            self.ended.set()


DROP_MARGIN_S = 2.0  # a drop comes at most this long after slow_drop_s (a loaded machine's)


def test_a_client_that_stops_reading_is_dropped_and_the_room_keeps_its_pace(tmp_path) -> None:
    """A seated player that stops reading is dropped by its gateway's pump (the engine's
    own port's, or a gateway process's) once its socket has been backed up for
    slow_drop_s: well before its pings (ping_interval, 20 s) could go unanswered. The
    engine sees it go; the client, reading again, gets a close frame 1008 ``too slow: ...``
    (or, where the pump could not write one, the connection's end). The room keeps its
    pace, and a player beside it that reads is served on."""
    limits = Limits(slow_drop_s=1.0, socket_send_buffer=16384)
    with live_server(tmp_path, limits=limits) as ls:
        room = ls.srv.main_room
        assert room is not None
        skipped0 = room.sim.stats.skipped_frames
        f0, t0 = room.sim.stats.frames, time.monotonic()
        hello = {"type": "hello", "version": 1, "role": "player", "room": room.id}
        port = workers.public_port(ls.srv)
        with contextlib.closing(raw_client(port, {**hello, "seat": 2})) as good, \
                contextlib.closing(raw_client(port, {**hello, "seat": 1}, rcvbuf=4096)) as slow:
            reading = Reader(good)
            wait(lambda: conn_of(ls, 1) is not None and conn_of(ls, 2) is not None, 5,
                 "both clients seated")
            seated = time.monotonic()
            conn, good_conn = conn_of(ls, 1), conn_of(ls, 2)
            peak_buffer, peak_queue = 0, 0
            while conn_of(ls, 1) is conn:  # never read: CORNER at 1 kHz and MESH pile up
                tr = conn.transport
                if tr is not None:
                    peak_buffer = max(peak_buffer, ls.call(tr.get_write_buffer_size))
                peak_queue = max(peak_queue, len(conn._control))
                assert time.monotonic() - seated < limits.slow_drop_s + DROP_MARGIN_S, \
                    "the slow client was not dropped within slow_drop_s"
                time.sleep(0.05)
            dropped_after = time.monotonic() - t0
            took = time.monotonic() - seated
            # the engine saw it go as any client's close: its seat held for its return
            assert ls.call(lambda: room.seats[1].held_until) is not None
            ended = Reader(slow)  # reading again: what the pump queued, then its close
            assert ended.ended.wait(10), "the slow client's connection did not end"
            assert ended.close is None or (ended.close[0] == 1008 and
                                           ended.close[1].startswith("too slow: ")), ended.close
            # the player beside it is served on: still seated, its messages still coming
            got = reading.got
            wait(lambda: reading.got > got + 1000, 5, "the reading client's messages")
            assert conn_of(ls, 2) is good_conn and not reading.ended.is_set()
        assert took < limits.slow_drop_s + DROP_MARGIN_S, took
        if workers.current() == 1:  # the engine's own port's pump dropped it
            assert ls.srv._own.pump.slow_drops == 1
        # the host's figures (/api/stats, /metrics) count it, whichever pump dropped it
        wait(lambda: ls.call(lambda: ls.srv.stats["slow_drops"]) == 1, 10,
             "the drop in the host's slow_drops")
        # the server held a bounded amount for it: one socket's worth, a short queue
        assert peak_buffer <= limits.max_write_buffer + 128 * 1024, peak_buffer
        assert peak_queue <= limits.max_control_queue
        # and the room kept its pace: every frame due while the client was there was
        # simulated, none skipped. The frame loop skips (and counts) the frames it is more
        # than its catch-up behind, so with none skipped the frames due by the drop are all
        # stepped: on a loaded machine the last of them a little later, so waited for, not
        # read at the drop (a 1 kHz count in a wall-clock window failed beside busy
        # processes while nothing was skipped).
        due = 0.9 * 1000 * (dropped_after - 0.2)
        wait(lambda: room.sim.stats.frames - f0 >= due, 30,
             f"the {due:.0f} frames due while the slow client was seated")
        assert room.sim.stats.skipped_frames == skipped0
        assert room.sim.alive and ls.errors.texts() == []


# --- SIGKILL mid-round --------------------------------------------------------------------------


@dataclass
class ServerProcs:
    """The server of the fault tests: one process, or (the test run with two processes,
    ``tests/server/workers.py``) an engine and a gateway on the public port; its room of
    four bots records into the data directory."""

    procs: list[subprocess.Popen[str]]
    port: int  # where clients connect: the gateway's with two
    ports: list[int]  # where each process's statistics are read (the public port)
    recording: str
    private: Path | None = None  # the engine socket's directory (two processes)


def start_server(data: Path, *args: str) -> ServerProcs:
    extra: list[str] = []
    server = ServerProcs([], 0, [], "")
    try:  # every process started so far killed if any step fails (stop, below)
        if workers.current() == 2:
            public = workers.free_port()
            server.private = Path(tempfile.mkdtemp(prefix="cb-engine-"))
            sock = server.private / "engine.sock"
            extra = ["--engine-socket", str(sock), "--public-port", str(public)]
            server.procs.append(subprocess.Popen(
                [sys.executable, "-m", "clothball.server.gateway", "--host", "127.0.0.1",
                 "--port", str(public), "--engine-socket", str(sock)],
                stdout=subprocess.PIPE, text=True))
        server.procs.insert(0, subprocess.Popen(
            [sys.executable, str(HERE / "server_proc.py"), str(data), *args, *extra],
            stdout=subprocess.PIPE, text=True))
        lines = [p.stdout.readline() for p in server.procs]  # type: ignore[union-attr]
        if not all(lines):
            raise AssertionError("the server process did not start")
        info = json.loads(lines[0])
    except BaseException:
        stop(server)
        raise
    # (its statistics from the public port too: an engine's own port is its bots' only)
    server.port = int(extra[-1]) if extra else info["port"]
    server.ports, server.recording = [server.port], info["recording"]
    return server


def stop(server: ServerProcs) -> None:
    """Every process killed and waited for, its pipe closed; the socket's directory gone
    (a killed engine leaves it)."""
    try:
        for proc in server.procs:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGKILL)
            proc.wait()
            if proc.stdout is not None:
                proc.stdout.close()
    finally:
        if server.private is not None:
            shutil.rmtree(server.private, ignore_errors=True)


def get(port: int, path: str) -> bytes:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=10) as r:
        return r.read()


def replays(port: int) -> dict[str, Any]:
    return json.loads(get(port, "/api/replays?limit=1000"))


def check_data_dir(data: Path) -> set[str]:
    """The index is a sound database and every finished file parses; the ids it holds."""
    db = sqlite3.connect(data / "index.sqlite")
    try:
        assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        ids = {r[0] for r in db.execute("SELECT id FROM rounds")}
    finally:
        db.close()
    for f in (data / "replays").glob("*.cbr"):
        header, records = read_replay(f.read_bytes())
        assert header["id"] == f.stem and records
    return ids


def test_a_server_that_does_not_start_leaves_no_process_behind(tmp_path, monkeypatch) -> None:
    """``start_server``'s own teardown: a server process that exits before its first line
    (an unknown option) fails the start, and every process it had started (the gateway too,
    with two) is killed and reaped, and the engine socket's directory removed."""
    before = children()
    if before is None:
        pytest.skip("needs Linux's /proc/self/task/*/children")
    made: list[str] = []
    mkdtemp = tempfile.mkdtemp
    monkeypatch.setattr(tempfile, "mkdtemp", lambda **kw: made.append(mkdtemp(**kw)) or made[-1])
    with pytest.raises(AssertionError, match="did not start"):
        start_server(tmp_path / "data", "--no-such-option")
    assert children() == before
    assert len(made) == (0 if workers.current() == 1 else 1)
    assert not any(Path(d).exists() for d in made)


@pytest.mark.slow
def test_sigkill_mid_round_and_restart_keep_the_index_and_every_earlier_round(tmp_path) -> None:
    data = tmp_path / "data"
    kept: dict[str, bytes] = {}
    rng = random.Random()
    for _ in range(3):
        procs = start_server(data)
        port = procs.port
        try:
            # every round recorded before any kill is listed and byte-for-byte the same
            listed = {r["id"] for r in replays(port)["replays"]}
            assert set(kept) <= listed
            for rid, body in kept.items():
                assert get(port, f"/api/replays/{rid}") == body
            assert not list((data / "replays").glob("*.tmp"))  # cleared at start-up
            target = len(listed) + 2
            wait(lambda p=port, n=target: replays(p)["total"] >= n, 60, "two more rounds")
            for r in replays(port)["replays"]:
                body = get(port, f"/api/replays/{r['id']}")
                assert read_replay(body)[0]["id"] == r["id"]
                kept[r["id"]] = body
            time.sleep(rng.uniform(0.0, 2.0))  # rounds last about a second: kill in one
        finally:
            stop(procs)
        assert set(kept) <= check_data_dir(data)
    assert len(kept) >= 6


@pytest.mark.slow
def test_sigkill_while_writing_replays_leaves_them_complete_or_absent(tmp_path) -> None:
    """Kill a process that does nothing but save large rounds, at random moments: what it
    reported saved is there and intact; the round being written is complete or absent."""
    writer = (
        "import sys, os\n"
        "from clothball.server.storage.sqlite import SqliteIndex\n"
        "from clothball.game.wire.replay import new_round_id\n"
        "store = SqliteIndex(sys.argv[1])\n"
        "while True:\n"
        "    rid = new_round_id()\n"
        "    header = dict(id=rid, room_id='r', room_name='r', scene='tiny', round=1,\n"
        "                  players=[], scores=[0, 0, 0, 0], started_at=0.0, ended_at=1.0,\n"
        "                  duration_s=1.0)\n"
        "    store.save(header, [(1, os.urandom(4096)) for _ in range(200)])\n"
        "    print(rid, flush=True)\n"
    )
    data = tmp_path / "data"
    saved: list[str] = []
    for _ in range(4):
        proc = subprocess.Popen([sys.executable, "-c", writer, str(data)],
                                stdout=subprocess.PIPE, text=True)
        try:
            assert proc.stdout is not None
            saved.append(proc.stdout.readline().strip())  # at least one round per life
            # (a random moment to kill it at, not a wait for anything to happen)
            time.sleep(random.uniform(0.05, 0.5))
        finally:  # killed and reaped, its pipe read to the end, whatever happened above
            proc.send_signal(signal.SIGKILL)
            out, _ = proc.communicate()
        saved += out.split()
        store = SqliteIndex(data)  # start-up: recovery
        try:
            assert not list((data / "replays").glob("*.tmp"))
            for rid in saved:
                p = store.path_of(rid)
                assert p is not None, rid
                assert len(read_replay(p.read_bytes())[1]) == 200
            assert store.count() == len(list((data / "replays").glob("*.cbr")))
        finally:
            store.close()
        check_data_dir(data)


# --- the data directory full, read-only or unusable -----------------------------------------------


@pytest.mark.slow
def test_a_full_disk_loses_the_round_not_the_match(tmp_path) -> None:
    data = tmp_path / "data"
    procs = start_server(data, "--fsize", "40000")
    port = procs.port
    try:
        assert procs.recording == "on"

        async def main() -> str:
            spec = await NetClient.connect(f"ws://127.0.0.1:{port}/ws", role="spectator",
                                           room="main")
            failed = await spec.wait_event("replay_failed", timeout=60)
            assert "could not write the replay" in failed["reason"]
            assert "File too large" in failed["reason"] or "No space" in failed["reason"]
            await spec.wait_event("score", timeout=30, since=spec.received_total)
            await spec.close()
            return str(failed["id"])

        lost = run(main())
        each = [json.loads(get(p, "/api/stats")) for p in procs.ports]  # per process
        assert sum(st["rounds_not_saved"] for st in each) >= 1
        assert each[0]["rooms"]["main"]["frames"] > 0
        # the index (the processes share it) still answers
        assert replays(port)["total"] == sum(st["rounds_saved"] for st in each)
        # no half-written file kept, nothing indexed for it
        assert not (data / "replays" / f"{lost}.cbr.tmp").exists()
        assert not (data / "replays" / f"{lost}.cbr").exists()
        assert lost not in [r["id"] for r in replays(port)["replays"]]
    finally:
        stop(procs)


@pytest.mark.parametrize("kind", ["not-a-directory", "read-only"])
def test_an_unusable_data_directory_turns_recording_off_and_play_goes_on(tmp_path, kind) -> None:
    if kind == "not-a-directory":
        (tmp_path / "a-file").write_text("not a directory")
        data = tmp_path / "a-file" / "data"
    else:
        if os.geteuid() != 0:
            data = tmp_path / "ro"
            data.mkdir()
            data.chmod(0o500)
        elif any(m.split()[1] == "/sys" and m.split()[3].split(",")[0] == "ro"
                 for m in Path("/proc/mounts").read_text().splitlines()):
            data = Path("/sys/clothball-data")  # a read-only filesystem, even for root
        else:
            pytest.skip("root on a writable /sys: no read-only directory to be had here")

    async def main() -> None:
        settings = RoomSettings(**{**FAST, "first_to": 99}, autoplay=True)
        srv = GameServer(ServerConfig(data, scenes={"tiny": TINY}, backend="cpu", port=0, bots=4,
                                      room_settings=settings))
        await srv.start()
        try:
            assert srv.store is None and srv.recording_error
            stats = await http_json(srv, "/api/stats")
            assert stats["recording"].startswith("off: data directory")
            status, body, _ = await http_get(srv, "/api/replays")
            assert status == 503 and b"recording is off" in body
            spec = await NetClient.connect(srv.ws_url, role="spectator", room="main")
            failed = await spec.wait_event("replay_failed", timeout=40)
            assert failed["reason"].startswith("recording is off")
            await spec.wait_event("score", timeout=30, since=spec.received_total)
            await spec.close()
        finally:
            await srv.stop()

    run(main())


def test_two_processes_on_an_unusable_data_directory_play_without_recording(tmp_path) -> None:
    """``clothball host --workers 2`` whose data directory cannot be made: as one process
    does, the host (engine and gateway) plays without recording."""
    from tests.server.test_workers import host

    (tmp_path / "a-file").write_text("not a directory")
    unusable = tmp_path / "a-file" / "data"

    async def main(url: str) -> None:
        spec = await NetClient.connect(url, role="spectator", room="main")
        await until(lambda: spec.mesh is not None, 10, "a mesh")
        at = workers.Process(url.replace("ws://", "http://")[:-len("ws")])
        status, body, _ = await http_get(at, "/api/replays")
        assert status == 503 and b"recording is off" in body
        await spec.close()

    with host(tmp_path, 2, "--data", str(unusable), "--bots", "4") as h:
        run(main(h.url))


# --- a simulation that turns non-finite --------------------------------------------------------


@pytest.mark.filterwarnings("ignore::clothball.game.sim.cloth.UnstableSceneWarning")
def test_a_non_finite_room_stops_with_a_clear_error_and_the_others_run_on(tmp_path) -> None:
    unstable = unstable_scene()

    async def main() -> None:
        async with workers.started(
                tmp_path, expected_errors=(r"room \S+ stopped: .*non-finite",),
                scenes={"tiny": TINY, "unstable": unstable}, backend="cpu", port=0,
                room_settings=RoomSettings(bots_allowed=False, unguarded=True)) as srv:
            main_room = srv.main_room
            assert main_room is not None
            watcher = await NetClient.connect(srv.ws_url, role="spectator", room="main")
            owner = await NetClient.connect(srv.ws_url)
            made = await owner.request("create_room", scene="unstable")
            rid = made["room"]
            player = await NetClient.connect(srv.ws_url, role="player", room=rid)
            spec = await NetClient.connect(srv.ws_url, role="spectator", room=rid)
            for c in (player, spec):
                ev = await c.wait_event("room_stopped", timeout=30, since=0)
                assert "non-finite" in ev["reason"]
                err = await c.wait_for(lambda m: m["type"] == "error", since=0)
                assert err["code"] == "room_stopped" and rid in err["message"]
            # gone from this process and (two processes) from the directory it read
            await until(lambda: rid not in srv.lobby.rooms and (
                srv.lobby.peers is None or rid not in srv.lobby.peers.rooms), 5,
                "the room closed")
            assert (await workers.service_stats(srv))["rooms_stopped"] == 1
            # the clients are back in the lobby, connected, and can go elsewhere
            assert rid not in [r["id"] for r in (await player.request("list_rooms"))["rooms"]]
            again = await player.join("main", role="spectator")
            assert again["room"] == "main"
            # the other room never noticed
            f0 = main_room.sim.stats.frames
            await until(lambda: main_room.sim.stats.frames > f0 + 200, 30,
                        "the main room's frames going on")
            assert main_room.sim.alive
            assert watcher._reader is not None and not watcher._reader.done()
            stats = await workers.service_stats(srv)
            assert rid not in stats["rooms"] and "main" in stats["rooms"]
            for c in (watcher, owner, player, spec):
                await c.close()

    run(main())
