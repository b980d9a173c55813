"""The client's network thread against a real server on loopback (no window): joins,
streams the mouse's hand (the server applies it), hands frames over, reconnects with its
seat token; a recorded round from a real match plays back."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from clothball.game.client.interp import MeshFrame
from clothball.game.client.model import ClientModel
from clothball.game.client.netthread import FrameInbox, Latest, NetThread
from clothball.game.client.replay import ReplayData, ReplayPlayer, fetch
from clothball.game.devices.mouse import MouseDevice

from tests.server.conftest import FAST, TINY, local_server


def wait(pred: Callable[[], bool], timeout: float = 10.0, what: str = "") -> None:
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


class Pump:
    """What the window does each tick, without a window: drain messages and frames."""

    def __init__(self, net: NetThread) -> None:
        self.net = net
        self.model = ClientModel()
        self.frames: list[MeshFrame] = []
        self.statuses: list[str] = []

    def __call__(self) -> None:
        while not self.net.messages.empty():
            at, msg = self.net.messages.get_nowait()
            if msg["type"] == "_status":
                self.statuses.append(msg["state"])
                self.model.set_connection(msg["state"], msg.get("detail", ""))
            else:
                self.model.apply(msg, at)
        self.frames += [f for f, _ in self.net.frames.take_all()]

    def until(self, pred: Callable[[], bool], timeout: float = 10.0, what: str = "") -> None:
        def step() -> bool:
            self()
            return pred()

        wait(step, timeout, what)


@pytest.fixture
def local(tmp_path):
    srv = local_server(tmp_path)
    srv.start()
    yield srv
    srv.stop()


def test_latest_and_inbox_never_block_and_keep_order() -> None:
    slot: Latest[int] = Latest()
    assert slot.get() == (None, 0)
    inbox = FrameInbox(maxlen=4)
    f = [MeshFrame(float(k), k, np.zeros((2, 2, 3), np.float32), np.zeros(3), 0.1,
                   np.zeros((4, 3))) for k in range(10)]

    def producer() -> None:
        for k in range(10):
            slot.put(k)
            inbox.put(f[k], float(k))

    t = threading.Thread(target=producer)
    t.start()
    t.join()
    assert slot.get() == (9, 10)
    got = inbox.take_all()
    assert [x.frame for x, _ in got] == [6, 7, 8, 9] and inbox.total == 10  # newest kept
    assert inbox.take_all() == []


def test_mouse_hand_reaches_the_server(local) -> None:
    mouse = MouseDevice()
    net = NetThread(local.ws_url, name="ann", device=mouse, corner_rate=120, hip_rate=120)
    net.start()
    pump = Pump(net)
    try:
        pump.until(lambda: pump.model.connection == "connected", 10, "welcome")
        main = pump.model.rooms[0]["id"]
        reply = net.join(main, "player", seat=1).result(10)
        assert reply["seat"] == 1 and mouse.reach is not None
        reach = mouse.reach
        assert np.allclose(reach.centre, reply["reach"]["centre"])
        pump.until(lambda: len(pump.frames) > 3, 10, "mesh frames")
        first = pump.frames[-1]
        assert np.allclose(first.hips[1], reach.centre, atol=1e-5)  # the hand at rest
        # the mouse moves: the server applies the new hand (the MESH echoes the HIPs)
        mouse.set_unit(1.0, -1.0)
        mouse.scroll(5)
        target = mouse.hand_position()
        assert np.linalg.norm(target - reach.centre) > 0.1
        pump.until(lambda: np.allclose(pump.frames[-1].hips[1], target, atol=1e-5), 10,
                   "the server to apply the moved hand")
        # and the corner follows the hand (the CORNER stream, handed over latest-wins)
        wait(lambda: np.linalg.norm(net.corner.get()[0][0].position - target)
             < 0.5 * np.linalg.norm(reach.centre - target), 10, "the corner to follow")
        state, corner = net.corner.get()[0]
        assert corner.seat == 1 and state.stiffness > 0
        pull = mouse.pull()  # the device got the corner state for its pull display
        assert pull is not None and pull[2] > 0
        assert net.hips_sent > 10 and net.hip_latency is not None
        pump.until(lambda: pump.model.rtt is not None, 5, "a ping reply")
        # frames keep arriving in order
        times = [f.server_time for f in pump.frames]
        assert times == sorted(times)
        # a dropped connection comes back on the same seat with its token
        net.submit(net.client.ws.close()).result(5)
        pump.until(lambda: pump.statuses[-1:] == ["connected"] and "reconnecting"
                   in pump.statuses, 10, "the reconnect")
        n0 = len(pump.frames)
        pump.until(lambda: len(pump.frames) > n0 + 3, 10, "frames after the reconnect")
        assert net.client is not None and net.client.seat == 1
        mouse.set_unit(-1.0, 1.0)
        target = mouse.hand_position()
        pump.until(lambda: np.allclose(pump.frames[-1].hips[1], target, atol=1e-5), 10,
                   "the hand after the reconnect")
        # leaving frees the seat and stops the device
        net.leave().result(5)
        assert mouse.reach is None
    finally:
        net.stop()
    assert not net.alive


def test_a_recorded_round_plays_back(tmp_path) -> None:
    srv = local_server(tmp_path, bots=4, **FAST)
    url = srv.start().ws_url
    net = NetThread(url, name="watcher")
    net.start()
    pump = Pump(net)
    try:
        pump.until(lambda: pump.model.connection == "connected", 10, "welcome")
        net.join(pump.model.rooms[0]["id"], "spectator").result(10)
        pump.until(lambda: bool(pump.model.replay_ids), 60, "a saved round")
        rid = pump.model.replay_ids[0]
    finally:
        net.stop()
        srv.stop()
    data = ReplayData.parse(fetch(str(tmp_path / "replays" / f"{rid}.cbr")))
    assert data.header["id"] == rid and data.duration > 0.1
    kinds = [e["event"] for _, e in data.events]
    assert "round_start" in kinds and "score" in kinds
    # events, mesh frames and track samples share the server's clock
    for t, _ in data.events:
        assert data.start - 1.0 <= t <= data.end + 1e-6
    assert data.tracks[0].time <= data.start + 0.1 and data.tracks[-1].time >= data.end - 0.1
    p = ReplayPlayer(data)
    score_t = next(t for t, e in data.events if e["event"] == "score")
    p.seek(score_t - data.start + 0.01)
    final: Any = data.header["scores"]
    assert p.scores() == final
    s = p.sample()
    assert s.positions.shape == (TINY.n, TINY.n, 3) and np.all(np.isfinite(s.positions))
