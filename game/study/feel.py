"""What a hand feels: the force on hand 0 (the corner a Falcon player holds, -K (h - c),
what the server sends back) at rest, after a standard hand move, and after the ball lands.

``feel`` measures one scene at its own n (the game's cloth), CPU float64, each run from the
hanging cloth's equilibrium (``grid.rest_state``), the other hands held at their anchors:

* **rest**: |F| with the cloth at rest, no ball;
* **lift**: hand 0 raised by ``LIFT_M`` in ``LIFT_S`` (a brisk tug, 0.5 m/s) and held, the
  ball out of play: the peak |F| and when, the |F| it settles to and the settling time;
* **landing**: the scene's ball let go at its start onto the cloth at rest: the peak |F|
  after the landing and when, the |F| with the ball come to rest, the settling time.

The settled value is the mean over the last ``TAIL_S`` of a ``RUN_S`` run; a settling time
is the last moment |F| is farther from it than a fraction (``BANDS``) of the step (settled
minus rest), from the move's start or the landing: the classic 5 % settling time of a step
response, and the 10 % one beside it, because a slow hump of |F| near the 5 % edge (the
landing's, a few hundredths of a newton) moves the 5 % time by hundreds of ms.

    python -m clothball.game.study.feel default other.toml   # docs/scenes.md: the feel
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

import numpy as np

from ..sim.cloth import Cloth, corners_of, rest_positions
from ..sim.scene import Scene
from .grid import rest_state

LIFT_M = 0.05  # m, straight up
LIFT_S = 0.1  # s to get there
RUN_S = 3.0  # s after the move's start or the ball's release
TAIL_S = 0.1  # s: the settled value's average
BANDS = (0.05, 0.10)  # of the step: settled when |F| stays this close to its settled value


@dataclass
class Response:
    """|F| on hand 0 after an event (N, ms from the event)."""

    peak_n: float
    peak_ms: float
    settled_n: float
    settling_ms: tuple[float, ...]  # one per band of ``BANDS``


@dataclass
class Feel:
    scene: str
    n: int
    rest_n: float
    lift: Response
    landing: Response


def response(force: np.ndarray, start: int, rest_n: float, frame_dt: float,
             tail_s: float = TAIL_S, bands: tuple[float, ...] = BANDS) -> Response:
    """The peak, settled value and settling times of |F| (one a frame) from frame ``start``."""
    f = np.asarray(force, dtype=np.float64)[start:]
    settled = float(f[-max(1, round(tail_s / frame_dt)):].mean())
    times = []
    for band in bands:
        off = np.flatnonzero(np.abs(f - settled) > band * abs(settled - rest_n))
        times.append((int(off[-1]) + 1 if len(off) else 0) * frame_dt * 1e3)
    peak = int(np.argmax(f))
    return Response(float(f[peak]), (peak + 1) * frame_dt * 1e3, settled, tuple(times))


def feel(scene: Scene, threads: int | None = 1) -> Feel:
    """``scene``'s feel at its n (module doc)."""
    x, _, rest_n = rest_state(scene, "cpu", threads)
    dt = float(scene["sim"]["frame_dt"])
    frames = round(RUN_S / dt)
    anchors = corners_of(rest_positions(scene))

    def cloth() -> Cloth:
        c = Cloth(scene, backend="cpu", precision="float64", threads=threads)
        c.set_state(x, np.zeros_like(x))
        c.set_hips(anchors)
        return c

    c, hips, lift = cloth(), anchors.copy(), []
    c.set_ball((0.0, -1e3, 0.0))  # out of play
    ramp = round(LIFT_S / dt)
    for f in range(frames):
        hips[0] = anchors[0] + min(1.0, (f + 1) / ramp) * np.array([0.0, LIFT_M, 0.0])
        c.set_hips(hips)
        c.step(1)
        lift.append(float(np.linalg.norm(c.corner_forces()[0])))

    ball, radius = scene["ball"], float(scene["ball"]["radius"])
    c, land, landed = cloth(), [], -1
    c.set_ball(np.array(ball["position"], dtype=np.float64),
               np.array(ball["velocity"], dtype=np.float64))
    for f in range(frames):
        c.step(1)
        land.append(float(np.linalg.norm(c.corner_forces()[0])))
        if landed < 0 and np.min(np.linalg.norm(x - c.ball()[0], axis=-1)) < radius:
            landed = f  # the first frame that ends with the ball in the cloth at rest
    if landed < 0:
        raise RuntimeError(f"{scene.name}: the ball did not land in {RUN_S} s")
    return Feel(scene.name, scene.n, rest_n, response(np.array(lift), 0, rest_n, dt),
                response(np.array(land), landed, rest_n, dt))


def table(feels: list[Feel]) -> str:
    """One row per scene and event: |F| on hand 0 in N, times in ms from the event."""
    bands = " ".join(f"{f'{b:.0%} ms':>7}" for b in BANDS)
    rows = [f"hand 0, |F| in N; lift: {LIFT_M * 100:g} cm up in {LIFT_S * 1e3:g} ms, held",
            f"{'scene':24} {'n':>3} {'rest':>6} {'event':>7} {'peak':>6} {'at ms':>6} "
            f"{'settled':>7} {bands}"]
    for f in feels:
        for event, r in (("lift", f.lift), ("landing", f.landing)):
            rows.append(f"{f.scene[:24]:24} {f.n:>3} {f.rest_n:>6.3f} {event:>7} {r.peak_n:>6.3f} "
                        f"{r.peak_ms:>6.0f} {r.settled_n:>7.3f} "
                        + " ".join(f"{t:>7.0f}" for t in r.settling_ms))
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m clothball.game.study.feel",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("scenes", nargs="+", help="scene names or TOML paths")
    p.add_argument("--n", type=int, default=0, help="grid (default: each scene's own n)")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    feels = []
    for name in a.scenes:
        s = Scene.load(name)
        feels.append(feel(s.with_changes({"cloth": {"n": a.n}}) if a.n else s, a.threads))
    print(table(feels))
    return 0


if __name__ == "__main__":
    sys.exit(main())
