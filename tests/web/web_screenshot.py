"""Take docs/spectator.png: the spectator page watching a live bot match in headless
Chromium (the classic scene, four bots, the server's default room settings).

    python -m tests.web.web_screenshot [--out docs/spectator.png] [--width 1280 --height 760]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from clothball.game.sim.scene import Scene  # noqa: E402
from clothball.server.room import RoomSettings  # noqa: E402

from tests.web.conftest import make_driver, wait_for, web_server  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "spectator.png")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=760)
    ap.add_argument("--scene", default="classic")
    ap.add_argument("--after", type=float, default=0.4,
                    help="seconds after a round starts to take the picture")
    args = ap.parse_args(argv)
    scene = Scene.load(args.scene)
    with tempfile.TemporaryDirectory() as d, web_server(
        Path(d), scene=scene, bots=4, settings=RoomSettings(autoplay=True)
    ) as st:
        rid = st.call(lambda s: s.main_room.id)
        driver = make_driver(args.width, args.height)
        try:
            driver.get(f"{st.url}#/room/{rid}")
            # a round in play, and the scoreboard showing at least one scored round
            wait_for(lambda: driver.execute_script(
                "return (document.getElementById('scoreboard').dataset.scores || '')"
                ".split(',').some(x => Number(x) > 0)"), 120, "a scored round", poll=0.5)
            wait_for(lambda: "ball in play" in driver.find_element("id", "events").text
                     .split("\n")[0], 60, "the next round to start", poll=0.05)
            time.sleep(args.after)
            # the ball on the cloth: inside the corners seen from above, not below them
            wait_for(lambda: driver.execute_script("""
                const r = window.clothball.renderer, b = r.ball && r.ball.position;
                if (!b || !r.corners) return false;
                const xs = r.corners.map(c => c[0]), zs = r.corners.map(c => c[2]);
                const ys = r.corners.map(c => c[1]);
                return b[0] > Math.min(...xs) + 0.1 && b[0] < Math.max(...xs) - 0.1
                  && b[2] > Math.min(...zs) + 0.1 && b[2] < Math.max(...zs) - 0.1
                  && b[1] > Math.min(...ys) - 0.5;"""), 60, "the ball on the cloth",
                     poll=0.02)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            driver.save_screenshot(str(args.out))
        finally:
            driver.quit()
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
