"""The recorded-trace device: a trace written from the emulated Falcon plays back."""

from __future__ import annotations

import numpy as np
import pytest
from clothball._native import falcon as f
from clothball.game.devices import Device, Reach
from clothball.game.devices import falcon as F
from clothball.game.devices.falcon_trace import TraceDevice, TraceError, record_trace


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_trace_replays_with_interpolation(tmp_path) -> None:
    path = tmp_path / "trace.csv"
    path.write_text("t,x,y,z,buttons\n0,0,0,0.125,0\n1,0.03,0,0.125,4\n2,0.03,0.03,0.155,0\n")
    clock = Clock()
    dev = TraceDevice(path, clock=clock, loop=False)
    assert isinstance(dev, Device)
    reach = Reach(np.array([0.0, 1.0, 0.0]), np.array([0.3, 0.3, 0.3]))
    dev.start(reach)
    np.testing.assert_allclose(dev.hand_position(), reach.centre)
    clock.t += 0.5
    np.testing.assert_allclose(dev.hand_position(), reach.centre + [0.15, 0.0, 0.0])
    assert dev.buttons() == 0
    clock.t += 0.5
    assert dev.buttons() == 4
    clock.t += 5.0  # past the end without looping: holds the last sample
    np.testing.assert_allclose(dev.hand_position(), reach.centre + reach.half_extent * [1, 1, 1])


def test_bad_traces_are_refused(tmp_path) -> None:
    with pytest.raises(TraceError, match="cannot read"):
        TraceDevice(tmp_path / "none.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text("time,x\n")
    with pytest.raises(TraceError, match="first line"):
        TraceDevice(bad)
    bad.write_text("t,x,y,z,buttons\n1,0,0,0.1,0\n0,0,0,0.1,0\n")
    with pytest.raises(TraceError, match="non-decreasing"):
        TraceDevice(bad)


def test_record_from_the_emulator_and_play_back(tmp_path) -> None:
    opts = f.EmulatorOptions()
    opts.firmware_loaded, opts.home_after_packets = True, 20
    live = F.open_falcon(emulator=True, emulator_options=opts)
    reach = Reach(np.array([0.0, 1.0, 0.0]), np.array([0.3, 0.3, 0.3]))
    live.start(reach)
    try:
        live.emulator.set_position([0.02, -0.01, 0.14])
        path = tmp_path / "rec.csv"
        n = record_trace(live, path, seconds=0.2, rate=200.0)
    finally:
        live.stop()
    clock = Clock()
    replay = TraceDevice(path, clock=clock, loop=False)
    assert len(replay.times) == n > 10
    replay.start(reach)
    clock.t += float(replay.times[-1])
    np.testing.assert_allclose(replay.device_position(), [0.02, -0.01, 0.14], atol=3e-4)
