"""A new player in the bots' room (what ``clothball host --bots 4`` serves): the real
window (pyglet under Xvfb, in a subprocess) lists the room, offers the bots' corners, takes
one with a click (the bot makes way), says ready if no match is on, moves its hand with the
mouse and plays a round to its end. The server's own record of that round (its replay in
the index: players and score) is the reference, not the window's word."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run as a script too

from tests.client.test_client_window import display  # noqa: E402,F401  (fixture)
from tests.server.conftest import FAST, local_server  # noqa: E402

SEAT = 1
NAME = "newcomer"


def test_a_new_player_takes_a_bots_corner_and_plays_a_round(tmp_path, display) -> None:  # noqa: F811
    # one long match: the player joins it under way and plays its next round (a ready
    # pressed while an autoplay room waits to restart is lost: a server issue of its own)
    settings = {**FAST, "first_to": 99}
    with local_server(tmp_path / "data", bots=4, **settings) as st:
        env = {**os.environ, "DISPLAY": display, "PYTHONUNBUFFERED": "1"}
        r = subprocess.run([sys.executable, __file__, "--driver", st.ws_url], env=env,
                           capture_output=True, text=True, timeout=240)
        assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
        out = json.loads(r.stdout.strip().splitlines()[-1])
        # the server's record of the rounds this player played (its replay index)
        end = time.monotonic() + 30
        while True:
            with urllib.request.urlopen(f"{st.url.rstrip('/')}/api/replays?player={NAME}",
                                        timeout=10) as resp:
                rounds = json.loads(resp.read())["replays"]
            if any(x["id"] == out["replay"] for x in rounds) or time.monotonic() > end:
                break
            time.sleep(0.2)
    # the lobby offered every corner (all bots), and the click took the bot's corner
    assert out["offered"] == [0, 1, 2, 3]
    assert out["seat_event"] == {"seat": SEAT, "kind": "human", "name": NAME,
                                 "reason": "replaced_bot"}
    assert out["seats_after_join"][SEAT] == ["human", NAME]
    assert sum(k == "bot" for k, _ in out["seats_after_join"]) == 3
    assert out["hand_moves"] > 0
    # a round that started with the player seated ended with a score
    start, score = out["round_start"], out["score"]
    assert score["round"] == start["round"] and sum(score["scores"]) >= 1
    assert out["hud_score_line"].count(NAME) == 1
    # ... and the server recorded it: this player at that corner, the edge that conceded
    (rec,) = [x for x in rounds if x["id"] == out["replay"]]
    assert rec["round"] == start["round"] and rec["conceded_edge"] == score["edge"]
    players = {p["seat"]: p for p in rec["players"]}
    assert players[SEAT]["kind"] == "human" and players[SEAT]["name"] == NAME


def driver(url: str) -> int:
    """Click through the lobby to corner ``SEAT`` of the first room, play, report as JSON."""
    import numpy as np
    import pyglet
    from clothball.game.client.app import ClientWindow, run_window
    from clothball.game.client.model import ClientModel
    from clothball.game.client.netthread import NetThread
    from clothball.game.devices.mouse import MouseDevice

    mouse = MouseDevice()
    net = NetThread(url, name=NAME, device=mouse)
    net.start()
    window = ClientWindow(net=net, device=mouse, model=ClientModel(name=NAME, server_url=url),
                          width=960, height=600, vsync=False)
    seen: list[dict] = []
    apply = window.model.apply

    def spy(msg: dict, at: float) -> None:  # every message the window takes in, in order
        seen.append(msg)
        apply(msg, at)

    window.model.apply = spy  # type: ignore[method-assign]
    out: dict = {}
    state = {"phase": "lobby", "deadline": time.monotonic() + 200, "rc": 4, "t": 0.0}

    def buttons() -> list:
        return window.lobby.buttons(window.model, window.width, window.height)

    def click(action: tuple) -> bool:
        for b in buttons():
            if b.action == action and b.enabled:
                x, y = round(b.x + b.w / 2), round(b.y + b.h / 2)
                window.dispatch_event("on_mouse_press", x, y, 1, 0)
                window.dispatch_event("on_mouse_release", x, y, 1, 0)
                return True
        return False

    def events(kind: str, since: int = 0) -> list[dict]:
        return [m for m in seen[since:] if m.get("type") == "event" and m.get("event") == kind]

    def step(dt: float) -> None:
        now = time.monotonic()
        m = window.model
        if now > state["deadline"]:
            print("driver: timed out in phase", state["phase"], m.match_state, out)
            window.close()
            return
        phase = state["phase"]
        if phase == "lobby":
            if m.connection == "connected" and m.rooms and window.lobby.screen == "rooms":
                click(("select_room", m.rooms[0]["id"]))
            elif window.lobby.screen == "seats":
                out["offered"] = [b.action[1] for b in buttons()
                                  if b.action[0] == "take_seat" and b.enabled]
                if click(("take_seat", SEAT)):
                    state["phase"] = "joining"
        elif phase == "joining" and m.seat == SEAT and mouse.reach is not None:
            ev = [e for e in events("seat") if e.get("seat") == SEAT and e.get("kind") == "human"]
            if not ev:
                return
            out["seat_event"] = {k: ev[-1].get(k) for k in ("seat", "kind", "name", "reason")}
            out["seats_after_join"] = [[s["kind"], s["name"]] for s in m.seats]
            state["joined_at"] = len(seen)
            state["phase"] = "ready"
        elif phase == "ready":
            if m.match_state in ("waiting", "over"):
                if not m.ready():
                    window.dispatch_event("on_key_press", pyglet.window.key.R, 0)
            state["phase"] = "round"
        elif phase == "round":
            # a round that starts after the join, played to its score
            if m.match_state in ("waiting", "over") and not m.ready() and now > state["t"]:
                window.dispatch_event("on_key_press", pyglet.window.key.R, 0)
                state["t"] = now + 1.0
            starts = events("round_start", state["joined_at"])
            if starts:
                a = 2 * np.pi * (now % 2.0) / 2.0  # the pointer circles round the window
                window.dispatch_event("on_mouse_motion", round(480 + 120 * np.cos(a)),
                                      round(300 + 80 * np.sin(a)), 1, 1)
                i = seen.index(starts[0])
                scores = [e for e in events("score", i) if e.get("round") == starts[0]["round"]]
                saved = [e for e in events("replay_saved", i)
                         if e.get("round") == starts[0]["round"]]
                if scores and saved:
                    out["round_start"] = {"round": starts[0]["round"]}
                    out["score"] = {k: scores[0].get(k) for k in ("round", "edge", "scores",
                                                                  "conceded_by")}
                    out["replay"] = saved[0]["id"]
                    out["hand_moves"] = mouse.moves
                    window._update_labels()
                    out["hud_score_line"] = window.hud.text.splitlines()[1]
                    state["rc"] = 0
                    window.close()

    pyglet.clock.schedule_interval(step, 0.05)
    try:
        run_window(window, 30.0)
    finally:
        net.stop()
    print(json.dumps(out))
    return int(state["rc"])


if __name__ == "__main__" and "--driver" in sys.argv:
    sys.exit(driver(sys.argv[-1]))
