"""The real window: pyglet under Xvfb (Mesa's software GL) connected to a live server.

The test starts Xvfb and a server on loopback, then runs the client in a subprocess (this
file with ``--driver``: pyglet's global state stays out of the test process). Synthetic
mouse events (``window.dispatch_event``) click through the lobby (room, corner) and move
the player's corner, then add a bot, say ready (countdown) and leave; a spectator connected
to the same server sees the hand arrive where the pointer is; the window's screenshot
shows the cloth (its shaded colour in the middle of the picture, not a blank window).
"""

from __future__ import annotations

import ctypes.util
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run as a script too

from clothball.game.client.interp import (  # noqa: E402
    BACKGROUND,
    BALL_COLOUR,
    CLOTH_BACK,
    CLOTH_FRONT,
    grid_corners,
)

SEAT = 2
SIZE = (960, 600)


def hue_ratio(c: np.ndarray) -> np.ndarray:
    """(G - B) / (R - B): unchanged by the shading's scale (diffuse) and by adding white
    (specular), so it names the material whatever the light."""
    c = np.asarray(c, dtype=np.float64)
    return (c[..., 1] - c[..., 2]) / np.maximum(c[..., 0] - c[..., 2], 1e-9)


def cloth_like(rgb: np.ndarray) -> np.ndarray:
    """Pixels whose hue is the cloth's (front or back side), not the background's or the
    ball's; the bounds are the cloth's two ratios, widened by a third of the gap to the
    nearest other colour in the scene."""
    front, back = hue_ratio(np.array(CLOTH_FRONT)), hue_ratio(np.array(CLOTH_BACK))
    ball = hue_ratio(np.array(BALL_COLOUR))
    lo, hi = min(front, back), max(front, back)
    lo -= (lo - ball) / 3
    hi += (1.0 - hi) / 3  # grey (R = G = B) and above is not cloth
    r = hue_ratio(rgb)
    warm = rgb[..., 0] - rgb[..., 2] > 0.05  # the background is cool (B > R)
    return warm & (r >= lo) & (r <= hi)


@pytest.fixture
def display():
    if shutil.which("Xvfb") is None:
        pytest.skip("needs a virtual display: Xvfb is not installed (apt-get install xvfb "
                    "xauth libgl1-mesa-dri)")
    if ctypes.util.find_library("GL") is None:
        pytest.skip("needs OpenGL for the window: libGL is not installed (apt-get install "
                    "libgl1 libglx-mesa0 libgl1-mesa-dri libglu1-mesa)")
    r, w = os.pipe()
    proc = subprocess.Popen(
        ["Xvfb", "-displayfd", str(w), "-screen", "0", "1280x800x24", "-nolisten", "tcp"],
        pass_fds=(w,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(w)
    try:
        with os.fdopen(r) as f:
            number = f.readline().strip()
        assert number.isdigit(), "Xvfb did not report its display"
        yield f":{number}"
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_window_moves_a_corner_and_shows_the_cloth(tmp_path, display) -> None:
    from clothball.game.client.netthread import NetThread

    from tests.client.test_client_net import Pump
    from tests.server.conftest import local_server

    # no bots: nothing else shakes the cloth, so the picture's middle is cloth for sure
    srv = local_server(tmp_path / "data")
    url = srv.start().ws_url
    spectator = NetThread(url, name="spectator")
    out = tmp_path / "out"
    out.mkdir()
    seen: list[tuple[np.ndarray, np.ndarray]] = []  # (hand, cloth corner) of SEAT
    try:
        spectator.start()
        pump = Pump(spectator)
        pump.until(lambda: pump.model.connection == "connected", 10, "welcome")
        spectator.join(pump.model.rooms[0]["id"], "spectator").result(10)
        env = {**os.environ, "DISPLAY": display, "PYTHONUNBUFFERED": "1"}
        proc = subprocess.Popen([sys.executable, __file__, "--driver", url, str(out)], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        with proc:  # killed (if still running), reaped and its pipe closed, whatever happens
            try:
                end = time.monotonic() + 90
                while proc.poll() is None and time.monotonic() < end:
                    pump()
                    seen += [(f.hips[SEAT].copy(), grid_corners(f.positions)[SEAT])
                             for f in pump.frames]
                    pump.frames.clear()
                    time.sleep(0.02)
            finally:
                if proc.poll() is None:
                    proc.kill()
            log = proc.communicate()[0]
        assert proc.returncode == 0, log
    finally:
        spectator.stop()
        srv.stop()
    report = json.loads((out / "report.json").read_text())
    start, moved, target = (np.array(report[k]) for k in ("hand_start", "hand_end", "target"))
    # the pointer put the hand where it points (on the hand's plane, inside the box)
    assert report["seat"] == SEAT and report["moves"] > 0
    assert np.linalg.norm(moved - start) > 0.1, report
    assert np.allclose(moved[[0, 2]], target[[0, 2]], atol=1e-3), report
    assert moved[1] > start[1] + 0.01  # the wheel lifted it
    # the server saw the hand at rest, then where the mouse put it
    hips = [h for h, _ in seen]
    assert hips, "the spectator saw no frames"
    at_rest = [i for i, h in enumerate(hips) if np.allclose(h, start, atol=1e-5)]
    at_moved = [i for i, h in enumerate(hips) if np.allclose(h, moved, atol=1e-5)]
    assert at_rest, "the hand at rest was never seen"
    distinct = sorted({tuple(np.round(h, 3)) for h in hips})
    assert at_moved, (f"the moved hand was never seen ({len(hips)} frames, hands seen "
                      f"{distinct}), expected {moved}; spectator connection "
                      f"{pump.statuses}; client {report}")
    assert at_rest[0] < at_moved[0]
    # and the cloth's corner followed the hand there (the coupling spring pulls it)
    corner_then = seen[max(i for i in at_rest if i < at_moved[0])][1]
    corner_now = seen[at_moved[-1]][1]
    assert np.linalg.norm(corner_now - moved) < 0.5 * np.linalg.norm(corner_then - moved), (
        corner_then, corner_now, moved)
    # (after the client quits, the server lets go of the seat's hand: not checked here)
    # the screenshot shows the cloth in the middle of the window
    import matplotlib.image

    img = matplotlib.image.imread(out / "shot.png")[..., :3]
    assert img.shape[:2] == (SIZE[1], SIZE[0])
    h, w = img.shape[:2]
    middle = img[int(0.4 * h):int(0.6 * h), int(0.4 * w):int(0.6 * w)]
    frac = float(cloth_like(middle).mean())
    assert frac > 0.6, f"only {frac:.0%} of the middle looks like cloth ({out / 'shot.png'})"
    bg = np.abs(img - np.array(BACKGROUND)).max(axis=-1) < 0.02
    assert 0.1 < bg.mean() < 0.9  # a scene on a background, not a blank window
    assert report["frames_drawn"] > 10
    # then the room bar: a bot added by a click, R for ready starts the countdown (shown
    # big), Esc leaves back to the room list and lets go of the device
    assert report["countdown_shown"] in {"1", "2", "3"}
    assert report["left"] and report["device_stopped"]


# --- the client process --------------------------------------------------------------------


def driver(url: str, out: Path) -> int:
    """Open the client window on ``url``, click through the lobby to seat 2, move the hand
    with synthetic mouse events, write ``report.json`` and ``shot.png`` into ``out``."""
    import pyglet
    from clothball.game.client.app import ClientWindow, run_window
    from clothball.game.client.model import ClientModel
    from clothball.game.client.netthread import NetThread
    from clothball.game.devices.mouse import MouseDevice

    mouse = MouseDevice()
    net = NetThread(url, name="xvfb", device=mouse)
    net.start()
    window = ClientWindow(net=net, device=mouse, model=ClientModel(name="xvfb", server_url=url),
                          width=SIZE[0], height=SIZE[1], vsync=False)
    state: dict = {"phase": "lobby", "t": time.monotonic(), "deadline": time.monotonic() + 75}

    def click(action: tuple) -> bool:
        """Click the middle of the lobby button for ``action`` (False: not shown yet)."""
        for b in window.lobby.buttons(window.model, window.width, window.height):
            if b.action == action and b.enabled:
                x, y = round(b.x + b.w / 2), round(b.y + b.h / 2)
                window.dispatch_event("on_mouse_press", x, y, 1, 0)
                window.dispatch_event("on_mouse_release", x, y, 1, 0)
                return True
        return False

    def step(dt: float) -> None:
        now = time.monotonic()
        if now > state["deadline"]:
            print("driver: timed out in phase", state["phase"], window.model.connection_text())
            state["rc"] = 3
            window.close()
            return
        if state["phase"] == "lobby":  # through the lobby screens, as a user clicks
            rooms = window.model.rooms
            if window.model.connection == "connected" and rooms and window.lobby.screen == "rooms":
                click(("select_room", rooms[0]["id"]))
            elif window.lobby.screen == "seats" and click(("take_seat", SEAT)):
                state["phase"], state["t"] = "wait", now
        elif state["phase"] == "wait":
            if (window.model.seat == SEAT and window.frame is not None
                    and mouse.reach is not None and window.frames_drawn > 5
                    and now - state["t"] > 1.0):
                reach = mouse.reach
                state["start"] = mouse.hand_position()
                # a point of the box at the hand's height, then the pixel it is seen at
                target = reach.from_unit(np.array([0.8, 0.0, -0.7]))
                fw, fh = window.get_framebuffer_size()
                px, py, ok = window.camera.project(target, fw, fh)
                assert ok
                px, py = px * window.width / fw, py * window.height / fh
                x0, y0 = window.width / 2, window.height / 2
                for k in range(1, 11):  # a pointer path to the target, as a user's
                    x, y = x0 + (px - x0) * k / 10, y0 + (py - y0) * k / 10
                    window.dispatch_event("on_mouse_motion", round(x), round(y), 1, 1)
                reached = mouse.hand_position()
                # the pixel grid rounds the pointer: the hand is where the rounded
                # pixel's ray meets the plane
                origin, direction = window.camera.ray(round(px) * fw / window.width,
                                                      round(py) * fh / window.height, fw, fh)
                s = (reached[1] - origin[1]) / direction[1]
                state["target"] = origin + s * direction
                window.dispatch_event("on_mouse_scroll", round(px), round(py), 0, 3)
                state["phase"], state["t"] = "moved", now
        elif state["phase"] == "moved":
            # wait (however loaded the machine) until this window's own frames show the
            # server applied the hand and the corner followed it, then half a second more
            frames = window.buffer.timeline.frames
            hand = mouse.hand_position()
            if not frames or not np.allclose(frames[-1].hips[SEAT], hand, atol=1e-5):
                return
            corner = grid_corners(frames[-1].positions)[SEAT]
            if np.linalg.norm(corner - hand) > 0.5 * np.linalg.norm(state["start"] - hand):
                return
            state.setdefault("echoed", now)
            if now - state["echoed"] < 0.5:
                return
            report = {
                "seat": window.model.seat,
                "hand_start": state["start"].tolist(),
                "hand_end": mouse.hand_position().tolist(),
                "target": np.asarray(state["target"]).tolist(),
                "moves": mouse.moves,
                "frames_drawn": window.frames_drawn,
                "connection": window.model.connection_text(),
            }
            state["report"] = report
            window.screenshot(out / "shot.png")
            state["phase"] = "room"
        elif state["phase"] == "room":  # the room bar: a bot on corner 0, ready, countdown
            if click(("add_bot", 0)):
                state["phase"] = "ready"
        elif state["phase"] == "ready":
            if any(s.get("kind") == "bot" for s in window.model.seats):
                window.dispatch_event("on_key_press", pyglet.window.key.R, 0)
                state["phase"] = "countdown"
        elif state["phase"] == "countdown":
            if window.big.text.isdigit():  # the countdown, as last drawn
                state["report"]["countdown_shown"] = window.big.text
                window.dispatch_event("on_key_press", pyglet.window.key.ESCAPE, 0)
                state["phase"] = "leaving"
        elif state["phase"] == "leaving":
            if window.model.room is None and window.lobby.screen == "rooms":
                state["report"]["left"] = True
                state["report"]["device_stopped"] = mouse.reach is None
                (out / "report.json").write_text(json.dumps(state["report"]))
                state["rc"] = 0
                window.close()

    pyglet.clock.schedule_interval(step, 0.05)
    try:
        run_window(window, 30.0)
    finally:
        net.stop()
    return int(state.get("rc", 4))


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--driver":
        sys.exit(driver(sys.argv[2], Path(sys.argv[3])))
    sys.exit("usage: test_client_window.py --driver URL OUT_DIR")
