"""The HUD says how the seated player's hand moves with the device they hold: the mouse's
keys for the mouse, the grip for a Falcon, what the emulated Falcon does, a bot; never the
mouse's help for another device. The real window (pyglet under Xvfb, in a subprocess) with
the real devices: the mouse, the emulated Falcon (``open_falcon(emulator=True)``, the
device ``clothball play --device falcon-emulator`` seats), the bot of ``--device bot``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run as a script too

from tests.client.test_client_window import display  # noqa: E402,F401  (fixture)

MOUSE_HELP = "mouse moves"


def driver() -> None:
    from clothball.game.cli.play import SeatBot
    from clothball.game.client.app import ClientWindow
    from clothball.game.devices.falcon import open_falcon
    from clothball.game.devices.mouse import MouseDevice

    from tests.client.test_client_model import room, seats

    out = {}
    for label, make in (("mouse", MouseDevice), ("emulator", lambda: open_falcon(emulator=True)),
                        ("bot", lambda: SeatBot(0.6))):
        device = make()
        w = ClientWindow(device=device, width=640, height=400, visible=True, vsync=False)
        w.model.apply({"type": "joined", "room": "r1", "role": "player", "seat": 1, "edge": 1,
                       "edge_name": "east", "token": "t", "geometry": {},
                       "reach": {"centre": [0, 1, 0], "half_extent": [0.3] * 3},
                       "state": room("r1", seats=seats("bot", "human", "bot", "bot"))}, 0.0)
        w._update_labels()
        out[label] = w.hud.text
        w.close()
        device.stop()
    print(json.dumps(out))


def test_hud_help_matches_the_device(display) -> None:  # noqa: F811
    env = dict(os.environ, DISPLAY=display)
    r = subprocess.run([sys.executable, __file__, "--driver"], env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert "corner 1, guarding the east edge" in out["mouse"]
    assert MOUSE_HELP in out["mouse"] and "C recentres" in out["mouse"]
    assert MOUSE_HELP not in out["emulator"] and "emulated Falcon" in out["emulator"]
    assert "--device falcon" in out["emulator"]
    assert MOUSE_HELP not in out["bot"] and "a bot plays this corner" in out["bot"]


if __name__ == "__main__" and "--driver" in sys.argv:
    driver()
