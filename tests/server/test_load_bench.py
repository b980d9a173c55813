"""``clothball bench --load`` runs end to end (a tiny, short configuration): it grows rooms,
measures each step from the server's own counters, /proc and its lean clients, and reports
them. Speed is not asserted here (docs/benchmarks/load.md has the figures).

The clients' native pump (native/bench/load_clients.hpp) is checked on socket pairs, the
test playing the server: its frames against websockets' own codec (an independent
implementation of RFC 6455) and the HIP codec, its latency samples against the send times it
wrote, its quantiles against NumPy's. No timing is asserted: the pump is given its clock."""

from __future__ import annotations

import inspect
import json
import math
import os
import shutil
import socket
import struct
import subprocess
import sys
import time
from collections import Counter

import numpy as np
import pytest
from clothball._native import LOAD_CLIENTS, LoadClients
from clothball.game import cli
from clothball.game.wire import protocol as P
from clothball.game.wire.wsframe import OP_BINARY, ZERO_KEY, frame_header
from clothball.server.bench import benchclients, loadbench
from clothball.server.room import Room
from websockets.frames import Frame, Opcode
from websockets.streams import StreamReader

MESH_HZ = inspect.signature(Room).parameters["mesh_hz"].default  # what the rooms send

BENCH = [sys.executable, "-m", "clothball.game.cli", "bench", "--load"]
# Tiny and short: two steps of a second, whatever they measure (--steps-past 1 measures the
# second step even when the first does not hold on a busy machine).
TINY = ["--load-seconds", "1", "--load-max-rooms", "2", "--server-n", "12",
        "--load-spectators", "1", "--steps-past", "1"]
STEP_KEYS = {
    "rooms", "clients", "rooms_per_host", "hosts", "lateness_p50_ms", "lateness_p99_ms",
    "skipped_frames", "messages_in_per_s", "messages_out_per_s", "hip_offered_per_s",
    "hip_sent_per_s", "load_average", "server_cpu_cores", "server_cpu_per_room",
    "server_cpu_per_added_room", "server_event_loop_cores", "server_busiest_thread_cores",
    "server_busiest_thread", "server_threads_cores", "clients_cpu_cores",
    "client_process_cores_max", "hip_to_corner_p50_ms", "hip_to_corner_p99_ms",
    "hip_to_corner_samples", "hip_echo_unknown", "hip_echo_mismatch", "corner_hz_asked",
    "corner_hz_received", "corner_hz_min",
    "corner_delivery", "mesh_hz_asked", "mesh_hz_received", "mesh_delivery", "frames_per_s",
    "frames_per_s_min", "client_errors", "client_last_error", "clients_lost",
    "clients_fell_behind", "held", "stopped_by", "why",
    "server_cores_by_kind", "server_cpu_us_per_message", "server_cpu_us_per_message_by_kind",
    "clients_cpu_per_room",
    "server_affinity", "client_affinity", "healthz_p50_ms", "healthz_p99_ms",
    "healthz_unanswered", "stats_p50_ms", "stats_p99_ms", "stats_unanswered",
}
REASONS = {"lateness", "delivery", "server_cpu", "clients_cpu"}


def _check_step(step: dict, i: int, rooms: int, spectators: int, hip_hz: float,
                corner_hz: float) -> None:
    assert set(step) == STEP_KEYS, set(step) ^ STEP_KEYS
    for k, v in step.items():
        if isinstance(v, float):
            assert math.isfinite(v), (i, k, v)
    assert step["rooms"] == rooms and sum(step["rooms_per_host"]) == rooms
    assert step["clients"] == rooms * (4 + spectators)
    assert step["hip_offered_per_s"] == 4 * hip_hz * rooms
    assert step["messages_in_per_s"] > 0 and step["messages_out_per_s"] > 0
    assert step["hip_sent_per_s"] > 0 and step["frames_per_s"] > 0
    assert step["lateness_p99_ms"] >= step["lateness_p50_ms"] >= 0
    assert step["hip_to_corner_samples"] > 0
    # every CORNER echoed a HIP this client sent, with the time it was sent with
    assert step["hip_echo_unknown"] == 0 and step["hip_echo_mismatch"] == 0
    assert step["hip_to_corner_p99_ms"] >= step["hip_to_corner_p50_ms"] > 0
    assert step["server_cpu_cores"] > 0 and step["clients_cpu_cores"] > 0
    assert step["server_cpu_per_room"] == pytest.approx(step["server_cpu_cores"] / rooms)
    assert step["server_busiest_thread_cores"] >= step["server_event_loop_cores"] > 0
    assert step["server_cpu_cores"] >= step["server_busiest_thread_cores"] - 0.05  # clock ticks
    assert step["server_busiest_thread"]
    # The per-thread split adds up to the processes' CPU (less threads gone by the end) and
    # names the engine's event loop; its busiest entry is at least the busiest thread.
    threads = step["server_threads_cores"]
    assert step["server_cpu_cores"] >= sum(threads.values()) - 0.05
    # (named, whatever it used: with the lanes in the gateway, the engine's event loop sees
    # control messages only, a few ticks or none in a short step)
    assert "engine event loop" in threads
    assert max(threads.values()) >= step["server_busiest_thread_cores"] - 1e-9
    assert step["clients_cpu_cores"] >= step["client_process_cores_max"] > 0
    assert step["clients_cpu_per_room"] == pytest.approx(step["clients_cpu_cores"] / rooms)
    # The same threads grouped by kind (frame loop, event loop, gateways, MESH encoders,
    # service threads, other): every kind named, together the per-thread split.
    kinds = step["server_cores_by_kind"]
    assert tuple(kinds) == loadbench.THREAD_KINDS and min(kinds.values()) >= 0
    assert sum(kinds.values()) == pytest.approx(sum(threads.values()), abs=1e-9)
    assert kinds["frame_loop"] > 0  # the native frame loop steps the rooms
    assert kinds["frame_loop"] == pytest.approx(sum(
        v for k, v in threads.items() if k.startswith("engine cb-frame-loop")), abs=1e-9)
    # µs of server CPU a message: its CPU over the messages in and out
    messages = step["messages_in_per_s"] + step["messages_out_per_s"]
    assert step["server_cpu_us_per_message"] == pytest.approx(
        step["server_cpu_cores"] * 1e6 / messages)
    assert step["server_cpu_us_per_message_by_kind"] == pytest.approx(
        {k: v * 1e6 / messages for k, v in kinds.items()})
    # the host's own pages, asked for by turns through the step: each answered, and the
    # quantiles in order
    assert step["healthz_unanswered"] == step["stats_unanswered"] == 0
    for page in ("healthz", "stats"):
        assert 0 < step[f"{page}_p50_ms"] <= step[f"{page}_p99_ms"]
    usable = sorted(os.sched_getaffinity(0))
    assert step["server_affinity"] and set(step["server_affinity"]) <= set(usable)
    assert step["client_affinity"] and set(step["client_affinity"]) <= set(usable)
    assert step["corner_hz_asked"] == corner_hz
    assert step["corner_delivery"] == pytest.approx(step["corner_hz_received"] / corner_hz)
    assert 0 < step["corner_hz_min"] <= step["corner_hz_received"] * (1 + 1e-12)  # the mean
    assert step["mesh_hz_asked"] == MESH_HZ
    assert step["mesh_delivery"] == pytest.approx(step["mesh_hz_received"]
                                                  / step["mesh_hz_asked"])
    assert step["client_errors"] == 0 and step["clients_lost"] == 0, step["client_last_error"]
    assert isinstance(step["held"], bool)
    assert set(step["stopped_by"]) <= REASONS
    assert step["held"] == (not step["stopped_by"])
    if not step["held"]:  # what stopped it is said
        assert step["why"]
    assert (step["lateness_p99_ms"] > 2.0) == ("lateness" in step["stopped_by"])


@pytest.mark.slow
def test_load_bench_runs_and_reports_every_step(tmp_path) -> None:
    dest = tmp_path / "load.json"
    out = subprocess.run([*BENCH, *TINY, "--json", str(dest)],
                         capture_output=True, text=True, timeout=180, check=True)
    r = json.loads(dest.read_text())
    assert r["n"] == 12 and r["scene"] == "classic" and r["spectators_per_room"] == 1
    assert r["hip_rate_hz"] == 120 and r["corner_rate_hz"] == 120  # the desktop client's
    assert r["cpus"] >= 1 and r["client_processes"] >= 1 and r["workers"] == 1
    assert r["server_cpus"] is None and r["client_cpus"] is None  # not pinned
    assert [s["rooms"] for s in r["steps"]] == [1, 2]
    for i, step in enumerate(r["steps"], start=1):
        _check_step(step, i, i, 1, 120.0, 120.0)
    assert r["idle_server_cpu_cores"] >= 0
    # The summary: the last step held before the stop, and the stop with its reasons.
    stop = r["stopped_at"]
    if stop is None:
        assert all(s["held"] for s in r["steps"]) and r["held"] == r["steps"][-1]
        assert "every step held" in out.stdout
    else:
        assert not stop["held"] and r["stopped_by"] == stop["stopped_by"]
        assert r["held"] is None or r["held"]["rooms"] < stop["rooms"]
        assert f"stopped: at {stop['rooms']} rooms by" in out.stdout
    assert "load average" in out.stderr and "held:" in out.stdout


@pytest.mark.slow
def test_load_bench_rates_and_rooms_step_are_the_flags(tmp_path) -> None:
    dest = tmp_path / "load.json"
    subprocess.run([*BENCH, "--load-seconds", "1", "--load-max-rooms", "3", "--rooms-step", "3",
                    "--server-n", "12", "--load-spectators", "0", "--steps-past", "1",
                    "--hip-rate", "50", "--corner-rate", "40", "--client-procs", "2",
                    "--json", str(dest)],
                   capture_output=True, text=True, timeout=180, check=True)
    r = json.loads(dest.read_text())
    assert r["client_processes"] == 2 and r["rooms_step"] == 3
    assert [s["rooms"] for s in r["steps"]] == [1, 3]
    for i, step in enumerate(r["steps"], start=1):
        _check_step(step, i, step["rooms"], 0, 50.0, 40.0)
    # No client asked for more than 40 CORNERs a second (the server's limit per connection).
    assert max(s["corner_hz_received"] for s in r["steps"]) <= 40 * 1.1


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("redis-server") is None,
                    reason="needs redis-server (apt: redis-server)")
def test_load_bench_over_a_cluster_places_rooms_on_every_host(tmp_path) -> None:
    dest = tmp_path / "cluster.json"
    out = subprocess.run(
        [*BENCH, "--cluster", "--cluster-hosts", "1,2", *TINY, "--json", str(dest)],
        capture_output=True, text=True, timeout=240, check=True,
    )
    r = json.loads(dest.read_text())
    assert set(r["hosts"]) == {"1", "2"} and "share" in r["note"]
    for n, series in r["hosts"].items():
        assert [s["rooms"] for s in series["steps"]] == [1, 2]
        for i, step in enumerate(series["steps"], start=1):
            assert step["hosts"] == int(n) and len(step["rooms_per_host"]) == int(n)
            _check_step(step, i, i, 1, 120.0, 120.0)
    # The first host, asked for every room, places each on the least-loaded host.
    assert sorted(r["hosts"]["2"]["steps"][1]["rooms_per_host"]) == [1, 1]
    assert "2 hosts: held" in out.stdout


@pytest.mark.slow
def test_load_bench_over_an_engine_and_a_gateway_on_one_port(tmp_path) -> None:
    dest = tmp_path / "workers.json"
    usable = sorted(os.sched_getaffinity(0))
    # The server on the first usable CPU, the clients on the others (issue 43), where there
    # are two.
    pinned = (["--server-cpus", str(usable[0]), "--client-cpus",
               ",".join(map(str, usable[1:]))] if len(usable) >= 2 else [])
    out = subprocess.run([*BENCH, "--workers", "2", *TINY, *pinned, "--json", str(dest)],
                         capture_output=True, text=True, timeout=240, check=True)
    r = json.loads(dest.read_text())
    assert r["workers"] == 2 and r["n"] == 12
    if pinned:
        assert r["server_cpus"] == usable[:1] and r["client_cpus"] == usable[1:]
        assert f"server on CPUs {usable[0]}, clients on" in out.stderr
        for step in r["steps"]:  # every thread of theirs, the ones started later included
            assert step["server_affinity"] == usable[:1]
            assert step["client_affinity"] == usable[1:]
            assert step["server_cores_by_kind"]["gateway_pumps"] > 0
    # The OS names the engine's native frame loop and the gateway's pump for the
    # per-thread split (server/shared/osthread.py, native/net/pump.cpp).
    for step in r["steps"]:
        assert step["server_threads_cores"]["engine cb-frame-loop"] > 0
        assert step["server_threads_cores"]["gateway cb-pump"] > 0
    assert [s["rooms"] for s in r["steps"]] == [1, 2]
    for i, step in enumerate(r["steps"], start=1):
        assert step["rooms_per_host"] == [i]  # every room in the one engine
        _check_step(step, i, i, 1, 120.0, 120.0)
    assert "an engine and 1 gateway on one port" in out.stderr


@pytest.mark.parametrize(("flags", "says"), [
    (["--workers", "0"], "--workers must be at least 1"),
    (["--hip-rate", "0"], "--hip-rate must be more than 0 and at most 1000"),
    (["--hip-rate", "nan"], "--hip-rate must be more than 0 and at most 1000"),
    (["--hip-rate", "1001"], "--hip-rate must be more than 0 and at most 1000"),
    (["--corner-rate", "0.5"], "--corner-rate must be 1 to 1000"),
    (["--corner-rate", "inf"], "--corner-rate must be 1 to 1000"),
    (["--rooms-step", "0"], "--rooms-step must be at least 1"),
    (["--load-max-rooms", "0"], "--load-max-rooms must be at least 1"),
    (["--load-seconds", "0"], "--load-seconds must be a number of seconds above 0"),
    (["--load-spectators", "-1"], "--load-spectators must be 0 or more"),
    (["--lateness-target", "-2"], "--lateness-target must be a number of milliseconds"),
    (["--steps-past", "-1"], "--steps-past must be 0 or more"),
    (["--client-procs", "0"], "--client-procs must be at least 1"),
    (["--scene", "nosuch"], "--scene, --server-n: scene 'nosuch': no such scene"),
    (["--server-n", "1"], "--scene, --server-n: cloth.n: must be >= 2"),
    (["--server-cpus", "x"], "--server-cpus must be a list of CPUs like 0-3 or 0,2,4-6, got 'x'"),
    (["--server-cpus", "3-1"], "--server-cpus must be a list of CPUs like 0-3 or 0,2,4-6"),
    (["--server-cpus", "0-"], "--server-cpus must be a list of CPUs like 0-3 or 0,2,4-6"),
    (["--client-cpus", ""], "--client-cpus must be a list of CPUs like 0-3 or 0,2,4-6"),
    (["--client-cpus", "0,,1"], "--client-cpus must be a list of CPUs like 0-3 or 0,2,4-6"),
    (["--client-cpus", "-1"], "--client-cpus must be a list of CPUs like 0-3 or 0,2,4-6"),
    (["--server-cpus", "100000"], "--server-cpus names CPU 100000 that this machine does not "
                                  "let the bench use (usable: "),
    (["--server-cpus", "0", "--client-cpus", "0"],
     "--server-cpus and --client-cpus share CPU 0: the server and its clients run on "
     "separate cores"),
])
def test_load_bench_refuses_bad_flags_in_one_line(flags: list[str], says: str, capsys) -> None:
    # The command itself, in this process (it refuses before starting anything).
    assert cli.main(["bench", "--load", *flags]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("clothball bench: ") and says in lines[0]


def test_cpu_lists_go_with_load_only(capsys) -> None:
    assert cli.main(["bench", "--server", "--server-cpus", "0"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "clothball bench: --server-cpus and --client-cpus go with --load"]


def test_cpu_lists_parse_as_taskset_writes_them() -> None:
    usable = os.sched_getaffinity(0)
    c = min(usable)
    assert loadbench.parse_cpu_list(f"{c}", "--server-cpus") == {c}
    assert loadbench.parse_cpu_list(f" {c}-{c} ", "--server-cpus") == {c}
    every = ",".join(map(str, sorted(usable)))
    assert loadbench.parse_cpu_list(every, "--client-cpus") == usable
    assert loadbench._cpus_text([0, 1, 2, 5, 7, 8]) == "0-2,5,7-8"
    assert loadbench.thread_kind("gateway", "python3", True) == "gateways"
    assert loadbench.thread_kind("gateway", "cb-pump", False) == "gateway_pumps"
    assert loadbench.thread_kind("engine", "python3", True) == "event_loop"
    assert loadbench.thread_kind("engine", "cb-frame-loop", False) == "frame_loop"
    assert loadbench.thread_kind("engine", "cb-mesh-encode", False) == "mesh_encoders"
    assert loadbench.thread_kind("engine", "clothball-mesh", False) == "service_threads"
    assert loadbench.thread_kind("engine", "replay-index_0", False) == "service_threads"
    assert loadbench.thread_kind("engine", "python3", False) == "other"


def test_load_bench_refuses_a_bad_flag_from_the_command_line() -> None:
    out = subprocess.run([*BENCH, "--hip-rate", "-5"], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.strip().splitlines() == [
        "clothball bench: --hip-rate must be more than 0 and at most 1000 (HIP messages a "
        "second per player), got -5"]


def test_room_counts_start_with_one_room_then_add_k_a_step() -> None:
    assert loadbench.room_counts(1, 3) == [1, 2, 3]
    assert loadbench.room_counts(8, 20) == [1, 8, 16, 20]
    assert loadbench.room_counts(4, 4) == [1, 4]
    assert loadbench.room_counts(5, 1) == [1]


def test_latency_quantiles_match_numpy_within_a_bin() -> None:
    rng = np.random.default_rng(7)
    x = rng.lognormal(np.log(4e-3), 0.6, 20_000)  # seconds, a few ms like HIP -> CORNER
    hist: dict[int, int] = {}
    for v in x:  # binned as the pump bins them
        i = min(int(v / benchclients.HIST_BIN_S), int(LOAD_CLIENTS["hist_bins"]))
        hist[i] = hist.get(i, 0) + 1
    for q in (0.5, 0.99):
        want = float(np.percentile(x, q * 100, method="inverted_cdf")) * 1e3
        got = loadbench._hist_ms(Counter(hist), q)
        assert got is not None and abs(got - want) <= benchclients.HIST_BIN_S * 1e3 / 2 + 1e-12
    assert loadbench._hist_ms(Counter(), 0.5) is None


def _corner(frame: int, seq: int, sent: float) -> bytes:
    return P.CORNER_MSG.pack(P.CORNER, P.PROTOCOL_VERSION, 0, frame & 0xFFFFFFFF, 1.0, frame, 0,
                             *([0.0] * 9), 100.0, *([0.0] * 6), seq, sent)


def _server_frame(opcode: Opcode, data: bytes) -> bytes:
    """A frame as a server sends it (unmasked), by websockets' own codec."""
    return Frame(opcode, data).serialize(mask=False)


def _client_frames(data: bytes) -> list[Frame]:
    """The frames a client wrote, read back by websockets as a server reads them."""
    reader = StreamReader()
    reader.feed_data(data)
    reader.feed_eof()
    frames = []
    while reader.buffer:  # (at_eof is a generator in websockets)
        gen = Frame.parse(reader.read_exact, mask=True)
        try:
            next(gen)
        except StopIteration as e:
            frames.append(e.value)
        else:
            raise AssertionError("a frame cut short")
    return frames


K = LOAD_CLIENTS  # the pump's wire constants and histogram bins
MESH_SMALL = bytes([P.MESH]) + bytes(100)  # length < 126
MESH_MID = bytes([P.MESH]) + bytes(5000)  # 16-bit length
MESH_BIG = bytes([P.MESH]) + bytes(70_000)  # 64-bit length


def test_the_pump_speaks_the_codec_s_wire() -> None:
    assert (K["hip_type"], K["corner_type"], K["mesh_type"]) == (P.HIP, P.CORNER, P.MESH)
    assert (K["hip_bytes"], K["corner_bytes"]) == (P.HIP_SIZE, P.CORNER_SIZE)
    assert K["protocol_version"] == P.PROTOCOL_VERSION
    assert benchclients.HIST_BIN_S == K["hist_bin_s"] == 1e-5
    assert benchclients.ERROR_PREFIX == P.encode_json(P.error_message("x", "m")).encode()[:15]


@pytest.mark.parametrize(("args", "says"), [((0.0, b""), "hip_rate must be"),
                                            ((math.nan, b""), "hip_rate must be"),
                                            ((1001.0, b""), "hip_rate must be")])
def test_the_pump_refuses_a_bad_rate_in_one_line(args: tuple, says: str) -> None:
    with pytest.raises(ValueError, match=says):
        LoadClients(*args)


def test_the_pump_refuses_a_closed_descriptor_and_calls_out_of_turn() -> None:
    pump = LoadClients(10.0, b"")
    with pytest.raises(ValueError, match="fd"):
        pump.add(-1, b"", None)
    pump.start()
    with pytest.raises(RuntimeError, match="runs on its thread"):
        pump.poll(1.0, 0)
    with pytest.raises(RuntimeError, match="started already"):
        pump.start()
    pump.close()
    pump.close()  # once is enough; twice says nothing
    a, b = socket.socketpair()
    with pytest.raises(RuntimeError, match="closed"):
        pump.add(a.fileno(), b"", None)
    a.close()
    b.close()


def _drain(sock: socket.socket) -> bytes:
    """What the pump wrote so far (it writes within its turn: nothing is on the way)."""
    sock.setblocking(False)
    out = b""
    while True:
        try:
            got = sock.recv(1 << 20)
        except BlockingIOError:
            return out
        if not got:
            return out
        out += got


def _pump_until(pump: LoadClients, now: float, done) -> dict:
    """Turns of the pump at ``now`` until ``done(snap)`` (bytes still in the socket)."""
    for _ in range(1000):
        s = pump.snap(False)
        if done(s):
            return s
        pump.poll(now, 100)
    raise AssertionError(f"the pump did not get there: {s}")


def test_pump_sends_each_player_s_hips_staggered_as_masked_frames() -> None:
    """Two players at 100 Hz: the pacer sends them in turn, 5 ms apart, each player's HIPs
    stamped with the pump's clock at the turn; the bytes are a masked client frame (zero key)
    around the codec's HIP, which websockets reads back as a server does."""
    hands = [(0.1, 0.5, -0.2, 0.3, 0.0), (-0.1, 0.6, 0.2, 0.25, math.pi / 2)]
    pairs = [socket.socketpair() for _ in hands]
    pump = LoadClients(100.0, benchclients.ERROR_PREFIX)
    for (mine, _), hand in zip(pairs, hands, strict=True):
        pump.add(mine.fileno(), b"", hand)
        mine.close()  # the pump holds its own descriptor
    t0 = 1000.0
    turns = [t0, t0 + 0.006, t0 + 0.0101, t0 + 0.0302]  # the last late: three HIPs due
    for now in turns:
        pump.poll(now, 0)
    s = pump.snap(False)
    # t0: player 0; +5 ms: player 1; +10: 0; +15, +20, +25, +30: 1, 0, 1, 0
    assert s["hips"] == [4, 3] and s["behind"] == 0
    stamps = [[t0, t0 + 0.0101, t0 + 0.0302, t0 + 0.0302], [t0 + 0.006, t0 + 0.0302, t0 + 0.0302]]
    for (_, peer), hand, want in zip(pairs, hands, stamps, strict=True):
        data = _drain(peer)
        head = frame_header(OP_BINARY, P.HIP_SIZE, masked=True) + ZERO_KEY
        cx, cy, cz, hy, phase = hand
        expect = b"".join(
            head + P.encode_hip((cx, cy + 0.3 * math.sin(math.pi * t + phase) * hy, cz), seq, t)
            for seq, t in enumerate(want, start=1))
        assert data == expect  # the bytes benchclients' Python wrote, bit for bit
        frames = _client_frames(data)
        assert all(f.opcode is Opcode.BINARY and f.fin for f in frames)
        hips = [P.decode_hip(bytes(f.data)) for f in frames]
        assert [h.seq for h in hips] == [1, 2, 3, 4][:len(want)]
        assert [h.time for h in hips] == want
        peer.close()
    pump.close()


@pytest.mark.parametrize("chunk", [1, 3, 7, 64, 1000, 1 << 20])
def test_pump_reads_a_server_stream_cut_anywhere(chunk: int) -> None:
    """CORNERs, MESHes of every websocket length form (counted, not read), text (an error,
    a fragmented message, a long one), a ping and a close, written by a peer playing the
    server in chunks of every size: every message counted once; a latency sample once per
    HIP echoed, in the bin of the pump's clock less the time it sent that seq; an echo of
    another time, or of a seq never sent, counted; the ping answered with a pong and the
    close with a close, which websockets reads back; the client then counted closed."""
    mine, peer = socket.socketpair()
    pump = LoadClients(1000.0, benchclients.ERROR_PREFIX)
    pump.add(mine.fileno(), b"", (0.0, 0.5, 0.0, 0.3, 0.0))
    mine.close()
    t0 = 5000.0
    pump.poll(t0, 0)  # HIP 1, sent at t0
    pump.poll(t0 + 0.0015, 0)  # HIP 2, at t0 + 1.5 ms; the next is due at t0 + 2 ms
    hips = _client_frames(_drain(peer))
    s1, s2 = (P.decode_hip(bytes(f.data)).time for f in hips)
    assert (s1, s2) == (t0, t0 + 0.0015)
    now = t0 + 0.00185  # every read below: no HIP is due yet
    error = P.encode_json(P.error_message("x", "m")).encode()
    stream = b"".join([
        _server_frame(Opcode.BINARY, _corner(10, 0, math.nan)),  # no HIP applied yet
        _server_frame(Opcode.BINARY, MESH_MID),
        _server_frame(Opcode.BINARY, _corner(11, 1, s1)),
        _server_frame(Opcode.TEXT, error),
        _server_frame(Opcode.BINARY, _corner(12, 1, s1)),  # the same HIP: no new sample
        _server_frame(Opcode.BINARY, MESH_BIG),
        _server_frame(Opcode.PING, b"hi"),
        Frame(Opcode.TEXT, b'{"type":"ev', fin=False).serialize(mask=False),
        Frame(Opcode.CONT, b'ent"}', fin=True).serialize(mask=False),
        _server_frame(Opcode.BINARY, MESH_SMALL),
        _server_frame(Opcode.TEXT, json.dumps({"type": "scores", "x": "y" * 9000}).encode()),
        _server_frame(Opcode.BINARY, _corner(13, 2, s2 + 7.0)),  # not the time sent
        _server_frame(Opcode.BINARY, _corner(14, 77, 0.0)),  # never sent
    ])
    for i in range(0, len(stream), chunk):
        peer.sendall(stream[i:i + chunk])
        pump.poll(now, 100)
    s = _pump_until(pump, now, lambda s: s["bytes"] == [len(stream)])
    assert s["corners"] == [5] and s["meshes"] == [3] and s["frame"] == [14]
    assert s["texts"] == [3] and s["errors"] == [1] and s["closed"] == [False]
    assert benchclients._error_text(s["last_error"]) == "x: m"
    assert s["echo_mismatch"] == 1 and s["echo_unknown"] == 1
    # HIPs 1 and 2, once each, from their send times, binned as benchclients binned them
    assert s["hist"] == Counter(int((now - t) / benchclients.HIST_BIN_S) for t in (s1, s2))
    assert s["hips"] == [2]
    (pong,) = _client_frames(_drain(peer))
    assert pong.opcode is Opcode.PONG and pong.data == b"hi"
    # A mark clears the histogram, not the counters.
    assert pump.snap(True)["hist"] and pump.snap(False)["hist"] == {}
    peer.sendall(_server_frame(Opcode.CLOSE, struct.pack(">H", 1001)))
    s = _pump_until(pump, now, lambda s: s["closed"] == [True])
    (close,) = _client_frames(_drain(peer))
    assert close.opcode is Opcode.CLOSE and close.data == struct.pack(">H", 1001)
    assert peer.recv(1) == b""  # and it hung up
    peer.close()
    pump.close()


def test_pump_reads_the_bytes_setup_read_past_its_last_reply() -> None:
    """What Python read past the setup's last reply (here a whole CORNER and half of the
    next) is the pump's first bytes: counted as if read from the socket."""
    mine, peer = socket.socketpair()
    pump = LoadClients(10.0, b"")
    stream = _server_frame(Opcode.BINARY, _corner(3, 0, math.nan)) * 2
    cut = len(stream) - 50
    pump.add(mine.fileno(), stream[:cut], None)
    mine.close()
    peer.sendall(stream[cut:])
    s = _pump_until(pump, 1.0, lambda s: s["bytes"] == [len(stream)])
    assert s["corners"] == [2] and s["frame"] == [3] and s["hips"] == [0]
    peer.close()
    s = _pump_until(pump, 1.0, lambda s: s["closed"] == [True])  # a hang-up: closed
    pump.close()


def test_pump_refuses_a_masked_server_frame_and_says_so() -> None:
    mine, peer = socket.socketpair()
    pump = LoadClients(10.0, b"")
    pump.add(mine.fileno(), b"", None)
    mine.close()
    peer.sendall(Frame(Opcode.BINARY, b"\x03abc").serialize(mask=True))
    s = _pump_until(pump, 1.0, lambda s: s["closed"] == [True])
    assert s["errors"] == [1] and s["last_error"] == b"protocol: a masked frame from the server"
    assert benchclients._error_text(s["last_error"]).startswith("protocol: a masked frame")
    peer.close()
    pump.close()


def _wait(pump: LoadClients, done) -> dict:
    """Snapshots of a started pump until ``done(snap)`` (a deadline, not a timing claim)."""
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        s = pump.snap(False)
        if done(s):
            return s
        time.sleep(0.01)
    raise AssertionError(f"the pump did not get there: {s}")


def test_started_pump_echoes_over_tcp_land_in_the_histogram_once() -> None:
    """On its thread, over loopback TCP (the kernel's receipt times): the test, playing the
    server, echoes each HIP it reads in a CORNER; every echo is one sample, none unknown or
    mismatched, each at least 0 and under a second; the close at the end is sent."""
    with socket.create_server(("127.0.0.1", 0)) as lsn:
        mine = socket.create_connection(lsn.getsockname())
        peer, _ = lsn.accept()
    pump = LoadClients(50.0, benchclients.ERROR_PREFIX)
    pump.add(mine.fileno(), b"", (0.0, 0.5, 0.0, 0.3, 0.0))
    mine.close()
    pump.start()
    got = b""
    while len(got) < 3 * (6 + P.HIP_SIZE):
        got += peer.recv(4096)
    hips = [P.decode_hip(bytes(f.data)) for f in _client_frames(got[:3 * (6 + P.HIP_SIZE)])]
    assert [h.seq for h in hips] == [1, 2, 3]
    for frame, h in enumerate(hips):
        peer.sendall(_server_frame(Opcode.BINARY, _corner(frame, h.seq, h.time)))
    s = _wait(pump, lambda s: s["corners"] == [3])
    assert sum(s["hist"].values()) == 3 and max(s["hist"]) < K["hist_bins"]
    assert s["echo_unknown"] == 0 and s["echo_mismatch"] == 0 and s["closed"] == [False]
    pump.close()
    rest = b""
    while chunk := peer.recv(4096):
        rest += chunk
    assert _client_frames(got[3 * (6 + P.HIP_SIZE):] + rest)[-1].opcode is Opcode.CLOSE
    peer.close()
