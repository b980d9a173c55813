"""How far the grid study's ring estimate (game/study/grid.py: dominant_hz of the corner
force after the landing) moves as its window's ends move by a few frames: the lightly
damped default (tests/study/test_grid_convergence.py's "light") on the CPU, float64.
Run from the repository root: ``python tools/lab/ring_window.py 49``."""

from __future__ import annotations

import sys

from clothball.game.study import grid

sys.path.insert(0, "tests/study")
import test_grid_convergence as T  # noqa: E402


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 49
    seen = {}
    estimate = grid.dominant_hz

    def spy(signal, dt, min_hz=grid.MIN_HZ):  # the signal the study hands its estimate
        seen.setdefault("signal", (list(signal), dt, min_hz))
        return estimate(signal, dt, min_hz)

    grid.dominant_hz = spy
    run = grid.measure(grid.sized(T.scenario("light"), n), backend="cpu", precision="float64")
    signal, dt, min_hz = seen["signal"]
    starts = [estimate(signal[s:], dt, min_hz) for s in range(0, 40, 4)]
    ends = [estimate(signal[:len(signal) - s], dt, min_hz) for s in range(4, 120, 12)]
    every = starts + ends
    print(f"n = {n}: ring {run.quantities['ring_hz']:.4f} Hz over {len(signal)} frames")
    print("start 0-36 frames later:", " ".join(f"{v:.4f}" for v in starts))
    print("end 4-112 frames earlier:", " ".join(f"{v:.4f}" for v in ends))
    print(f"spread {max(every) - min(every):.4f} Hz")


if __name__ == "__main__":
    main()
