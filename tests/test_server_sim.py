"""The room's simulation thread: catching up one frame at a time, and the catch-up bound."""

from __future__ import annotations

import time

from clothball.server.sim import RoomSim
from server_helpers import TINY


class ManualClock:
    """A clock that moves only when the test moves it (the thread still sleeps for real)."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def wait_for(cond, what: str, timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.005)


def test_frames_behind_are_caught_up_one_frame_per_step_and_the_excess_skipped() -> None:
    clock = ManualClock()
    sim = RoomSim(TINY, "cpu", clock=clock, epoch=0.0, max_catchup=50)
    sim.start()
    try:
        st = sim.stats
        clock.t = 10.5 * sim.frame_dt  # ten frames due at once
        wait_for(lambda: st.frames >= 10, "ten frames")
        # No batch: each due frame is its own step (newest HIPs, its own corner state).
        assert (st.frames, st.steps, st.skipped_frames) == (10, 10, 0)
        assert len(st.lateness) == 10
        clock.t = 210.5 * sim.frame_dt  # 200 more due: 50 are simulated, 150 skipped
        wait_for(lambda: st.frames >= 60, "the catch-up")
        time.sleep(0.05)  # nothing more is due: the thread sleeps
        assert (st.frames, st.steps, st.skipped_frames) == (60, 60, 150)
        assert sim.cloth.frame == 60
    finally:
        sim.stop()
