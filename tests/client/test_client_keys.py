"""Keys and buttons in the real window (pyglet under Xvfb, in a subprocess): N in the lobby
opens the room-name field without typing its own "n" into the name (pyglet sends on_text
after on_key_press for the same keystroke); the next keys type as usual. Every button's
text fits inside its button (the corner choices with a bot's name, the bot buttons)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run as a script too

from tests.client.test_client_window import display  # noqa: E402,F401  (fixture)


def driver() -> None:
    import pyglet
    from clothball.game.client.app import ClientWindow

    from tests.client.test_client_model import room, seats

    key = pyglet.window.key
    w = ClientWindow(width=640, height=400, visible=True, vsync=False)
    out = {}

    def send(*event: object) -> None:
        w.dispatch_event(*event)
        w.dispatch_events()  # outside the app loop pyglet queues window events
    # N then its own on_text, as pyglet sends them for one keystroke
    send("on_key_press", key.N, 0)
    send("on_text", "n")
    out["after_n"] = (w.lobby.screen, w.lobby.name_input)
    for sym, ch in ((key.N, "n"), (key.O, "o")):  # typed in the field: both count
        send("on_key_press", sym, 0)
        send("on_text", ch)
    out["typed"] = w.lobby.name_input

    def overflow() -> list[str]:
        w._ui_key = None
        w._update_ui()
        boxes = [(s.x, s.width) for s in w._ui_shapes]
        return [lb.text for lb, (x, bw) in zip(w._ui_labels, boxes, strict=True)
                if lb.x + lb.content_width > x + bw]

    # the corner choices of a room full of long-named bots
    full = room("r1", seats=[dict(s, name=f"bot-{i}-long-name") for i, s in
                             enumerate(seats("bot", "bot", "bot", "bot"))])
    w.model.apply({"type": "welcome", "rooms": [full]}, 0.0)
    w.lobby.act(("back",))
    w.lobby.act(("select_room", "r1"))
    out["seat_overflow"] = overflow()
    # the room bar of one's own room: ready, a bot button per empty corner, leave
    w.model.apply({"type": "joined", "room": "r1", "role": "player", "seat": 0, "edge": 0,
                   "edge_name": "north", "token": "t", "geometry": {},
                   "reach": {"centre": [0, 1, 0], "half_extent": [0.3] * 3},
                   "state": room("r1", seats=seats("human", "empty", "empty", "empty"))}, 1.0)
    out["bar_overflow"] = overflow()
    out["bar"] = [lb.text for lb in w._ui_labels]
    w.close()
    print(json.dumps(out))


def test_n_opens_the_name_field_without_typing_n(display) -> None:  # noqa: F811
    env = dict(os.environ, DISPLAY=display)
    r = subprocess.run([sys.executable, __file__, "--driver"], env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["after_n"] == ["create", ""]
    assert out["typed"] == "no"
    assert out["seat_overflow"] == [] and out["bar_overflow"] == []
    assert sum("Bot" in t for t in out["bar"]) == 3, out["bar"]


if __name__ == "__main__" and "--driver" in sys.argv:
    driver()
