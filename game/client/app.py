"""The desktop window: lobby screens, the live game and replays (pyglet 2).

The window only renders state it is handed: the network thread (``netthread``) delivers
messages and frames, the ``ClientModel`` and the ``FrameBuffer`` turn them into what to
show, ``interp.assemble`` makes the ``RenderFrame`` and ``render.Renderer`` draws it.
Input goes the other way: the mouse moves the ``MouseDevice`` (the network thread sends
its hand position), clicks and keys become requests.

Keys: M wire mesh (Shift+M wire only), R ready, Esc leave / back, F5 refresh rooms,
N create a room, arrow keys or middle-drag orbit the camera, Ctrl+wheel zoom, C recentre
the hand, F12 screenshot. Replays: Space pause, Left/Right seek 2 s (Shift: 10 s),
Up/Down or +/- speed, Home restart, click the timeline to seek.
"""

from __future__ import annotations

import concurrent.futures
import logging
import queue
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyglet

from ..devices.mouse import MouseDevice
from .camera import OrbitCamera
from .interp import BACKGROUND, EDGE_NAMES, SEAT_COLOURS, FrameBuffer, RenderFrame, Sample, assemble
from .lobby_ui import Action, LobbyUI
from .model import ClientModel
from .netthread import NetThread
from .replay import ReplayPlayer

log = logging.getLogger("clothball.client")

FONT_SIZE = 12
# The lobby's title while not connected (the details go in the HUD's lines).
CONNECTION_TITLES = {
    "connecting": "clothball - connecting...",
    "reconnecting": "clothball - reconnecting...",
    "retrying": "clothball - cannot connect yet, retrying",
    "failed": "clothball - cannot connect",
    "closed": "clothball - disconnected",
}


def _rgb255(c: tuple[float, float, float], a: int = 255) -> tuple[int, int, int, int]:
    return (int(c[0] * 255), int(c[1] * 255), int(c[2] * 255), a)


def fit_label(label: pyglet.text.Label, width: float, smallest: int = 8) -> None:
    """Keep a button's text inside its button: a smaller font, then cut with an ellipsis."""
    while label.content_width > width and label.font_size > smallest:
        label.font_size -= 1
    text = label.text
    while label.content_width > width and len(text) > 1:
        text = text[:-1]
        label.text = text.rstrip() + "…"


def hand_help(device: Any) -> str:
    """How this seat's hand is moved, for the HUD (the device the player actually holds)."""
    if isinstance(device, MouseDevice):
        return "mouse moves, wheel / right-drag lifts, C recentres"
    name = getattr(device, "name", "")
    error = getattr(device, "error", None) if name.startswith("falcon") else None
    if error:
        return f"Falcon lost: {error}; replug it and join again"
    if name == "falcon":
        return "move the Falcon's grip; you feel the cloth pull back"
    if name == "falcon-emulator":
        return ("the emulated Falcon: no hand holds its grip, it goes where the cloth pulls "
                "it; a real one: --device falcon")
    if name == "bot":
        return "a bot plays this corner for you"
    return f"{name or 'your device'} moves it"


class ClientWindow(pyglet.window.Window):
    """The clothball window. Give it a ``NetThread`` (live) or a ``ReplayPlayer``."""

    def __init__(self, *, net: NetThread | None = None, replay: ReplayPlayer | None = None,
                 device: Any = None, model: ClientModel | None = None,
                 auto_join: dict[str, Any] | None = None, width: int = 1280,
                 height: int = 800, title: str = "clothball", visible: bool = True,
                 clock: Callable[[], float] = time.perf_counter, vsync: bool = True) -> None:
        config = pyglet.gl.Config(double_buffer=True, depth_size=24, major_version=3,
                                  minor_version=3, forward_compatible=True)
        try:
            super().__init__(width, height, title, resizable=True, visible=visible,
                             config=config, vsync=vsync)
        except pyglet.window.NoSuchConfigException:
            super().__init__(width, height, title, resizable=True, visible=visible,
                             vsync=vsync)
        from .render import Renderer

        self.renderer = Renderer()
        self.background = BACKGROUND
        self.net = net
        self.replay = replay
        self.device = device
        self.model = model or ClientModel()
        self.clock = clock
        self.buffer = FrameBuffer()
        self.camera = OrbitCamera()
        self.lobby = LobbyUI()
        self.auto_join = auto_join
        self._auto_join_sent = False
        # The key that opened the name field: pyglet sends its on_text after on_key_press.
        self._swallow_text = ""
        self._pending: list[tuple[str, concurrent.futures.Future[Any]]] = []
        self._camera_set_for: tuple[Any, ...] | None = None
        self.frame: RenderFrame | None = None
        self.frames_drawn = 0
        self.draw_times: list[float] = []
        self._last_corner_version = 0
        self.batch = pyglet.graphics.Batch()
        self.hud = pyglet.text.Label("", x=12, y=height - 12, anchor_y="top", multiline=True,
                                     width=900, font_size=FONT_SIZE, batch=self.batch,
                                     color=(235, 235, 235, 255))
        self.status = pyglet.text.Label("", x=12, y=10, font_size=FONT_SIZE - 2,
                                        batch=self.batch, color=(170, 190, 210, 255))
        self.events_label = pyglet.text.Label("", x=12, y=34, anchor_y="bottom",
                                              multiline=True, width=700,
                                              font_size=FONT_SIZE - 1, batch=self.batch,
                                              color=(250, 230, 160, 255))
        self.big = pyglet.text.Label("", x=width // 2, y=height // 2, anchor_x="center",
                                     anchor_y="center", font_size=64, batch=self.batch,
                                     color=(255, 255, 255, 230))
        self.title_label = pyglet.text.Label("", x=width // 2, y=height - 40,
                                             anchor_x="center", font_size=20,
                                             batch=self.batch, color=(235, 235, 235, 255))
        self.name_labels = [pyglet.text.Label("", font_size=FONT_SIZE, anchor_x="center",
                                              batch=self.batch, color=_rgb255(SEAT_COLOURS[i]))
                            for i in range(4)]
        self._ui_shapes: list[Any] = []
        self._ui_labels: list[Any] = []
        self._ui_key: tuple[Any, ...] | None = None
        self.ui_batch = pyglet.graphics.Batch()
        pyglet.clock.schedule(self.update)

    # --- the tick ---------------------------------------------------------------------------
    def update(self, dt: float) -> None:
        now = self.clock()
        if self.net is not None:
            self._drain(now)
        if self.replay is not None:
            self.replay.advance(dt)
        self._poll_pending(now)
        self.frame = self._make_frame(now)

    def _drain(self, now: float) -> None:
        assert self.net is not None
        while True:
            try:
                at, msg = self.net.messages.get_nowait()
            except queue.Empty:
                break
            if msg.get("type") == "_status":
                self.model.set_connection(msg["state"], msg.get("detail", ""))
                if msg["state"] == "connecting":
                    self.buffer.reset()
                continue
            self.model.apply(msg, at)
        for f, at in self.net.frames.take_all():
            self.buffer.push(f, at)
        self.model.hip_latency = self.net.hip_latency
        if (self.auto_join and not self._auto_join_sent
                and self.model.connection == "connected"):
            self._auto_join_sent = True
            a = self.auto_join
            room = a.get("room")
            if room is None and self.model.rooms:
                room = self.model.rooms[0].get("id")
            if room is not None:
                self._track("join", self.net.join(room, a.get("role", "player"),
                                                  a.get("seat"), a.get("code")))
                if a.get("ready"):
                    self._ready_after_join = True

    _ready_after_join = False

    def _track(self, what: str, fut: concurrent.futures.Future[Any]) -> None:
        self._pending.append((what, fut))

    def _poll_pending(self, now: float) -> None:
        still = []
        for what, fut in self._pending:
            if not fut.done():
                still.append((what, fut))
                continue
            try:
                reply = fut.result()
            except Exception as e:  # noqa: BLE001 - shown to the user
                self.model.log(f"{what} failed: {e}", now, "error")
                self.lobby.message = f"{what} failed: {e}"
                continue
            if what == "create_room" and isinstance(reply, dict):
                self.model.apply(reply, now)
                self.lobby.selected, self.lobby.screen = reply.get("room"), "seats"
            elif what == "join" and self._ready_after_join and self.net is not None:
                self._ready_after_join = False
                self._track("ready", self.net.ready(True))
            elif what == "refresh" and isinstance(reply, dict):
                self.model.apply(reply, now)
            elif what == "leave" and isinstance(reply, dict):
                self.model.apply(reply, now)
                self.buffer.reset()
                self._camera_set_for = None
                self.lobby.screen = "rooms"
                if self.net is not None:
                    self._track("refresh", self.net.list_rooms())
        self._pending = still

    def _make_frame(self, now: float) -> RenderFrame | None:
        seats: list[dict[str, Any]]
        if self.replay is not None:
            sample: Sample | None = self.replay.sample()
            seats = self.replay.data.seats()
            own_seat, own_hand, k = None, None, 0.0
        else:
            sample = self.buffer.sample(now) if self.model.room is not None else None
            seats = self.model.seats
            own_seat = self.model.seat
            own_hand = None
            k = float(self.model.geometry.get("stiffness", 0.0))
            if own_seat is not None:
                if isinstance(self.device, MouseDevice):
                    own_hand = self.device.hand_position()  # fresher than the one sent
                elif self.net is not None:
                    own_hand = self.net.last_hand.get()[0]  # Falcon, bot: as sent
        if sample is None:
            return None
        self._aim_camera(sample, own_seat)
        full = 0.15 * k * float(self.model.geometry.get("size", 1.0)) if k else 20.0
        return assemble(sample, seats, own_seat=own_seat, own_hand=own_hand, stiffness=k,
                        full_force=max(full, 1e-6))

    def _aim_camera(self, sample: Sample, own_seat: int | None) -> None:
        key = (own_seat, sample.positions.shape[0])
        if self._camera_set_for == key:
            return
        self._camera_set_for = key
        p = sample.positions.reshape(-1, 3)
        size = float(max(np.ptp(p[:, 0]), np.ptp(p[:, 2]), 0.2))
        self.camera.target = p.mean(axis=0)
        self.camera.distance = 2.6 * size  # room for the hands' reach around the cloth
        self.camera.pitch = 0.85
        if own_seat is not None:
            corners = [sample.positions[0, 0], sample.positions[0, -1],
                       sample.positions[-1, -1], sample.positions[-1, 0]]
            self.camera.face(corners[own_seat])
        else:
            self.camera.yaw = 0.0

    # --- drawing ----------------------------------------------------------------------------
    def on_draw(self) -> None:
        t0 = time.perf_counter()
        pyglet.gl.glClearColor(*self.background, 1.0)
        self.clear()
        w, h = self.get_framebuffer_size()
        if self.frame is not None:
            self.renderer.draw(self.frame, self.camera, w, h)
        self._update_labels()
        self._update_ui()
        self.ui_batch.draw()
        self.batch.draw()
        self.frames_drawn += 1
        self.draw_times.append(time.perf_counter() - t0)
        if len(self.draw_times) > 600:
            del self.draw_times[:300]

    def _update_labels(self) -> None:
        now = self.clock()
        m = self.model
        w, h = self.width, self.height
        fw, fh = self.get_framebuffer_size()
        sx, sy = w / max(1, fw), h / max(1, fh)
        lines: list[str] = []
        if self.replay is not None:
            rp = self.replay
            hd = rp.data.header
            scores = rp.scores()
            lines.append(f"replay {hd.get('id')}  room {hd.get('room_name')}  "
                         f"round {hd.get('round')}  scene {hd.get('scene')}")
            lines.append(self._score_line(scores, rp.data.seats()))
            lines.append(f"{rp.position:6.2f} / {rp.data.duration:.2f} s   speed "
                         f"{rp.speed:g}x{'   PAUSED' if rp.paused else ''}")
            events = [self._replay_event_text(e) for e in rp.events_until()][-5:]
            self._set(self.events_label, "\n".join(t for t in events if t))
            self._set(self.status, "Space pause  Left/Right seek  Up/Down speed  "
                                   "Home restart  M wire mesh  (click the bar to seek)")
            self.events_label.y = 48
        else:
            if m.room is not None:
                lines.append(f"room {m.room.get('name')} ({m.room.get('id')})  "
                             f"{m.match_state}  round {m.room.get('round')}  "
                             f"first to {m.room.get('first_to')}")
                lines.append(self._score_line(m.scores, m.seats))
                if m.seat is not None:
                    lines.append(f"you: corner {m.seat}, guarding the {EDGE_NAMES[m.seat]} "
                                 f"edge  ({hand_help(self.device)})")
                    pull = self.frame.pull if self.frame is not None else None
                    if pull is not None:
                        lines.append(f"pull {pull.force:5.1f} N")
                    if m.match_state in ("waiting", "over"):
                        lines.append("press R (or the Ready button) when you are ready"
                                     if not m.ready() else "ready: waiting for the others")
                else:
                    lines.append("watching")
            elif m.connection != "connected" and m.detail:
                lines.append(m.detail)  # what happened and what to do (net.client)
                if m.connection == "failed":
                    lines.append("Enter (or the Retry button): try again    Esc: quit")
            self._set(self.events_label, "\n".join(m.recent_events(now)))
            self.events_label.y = 34 if m.room is not None else 96  # above the lobby buttons
            self._set(self.status, f"{m.server_url}  {m.connection_text()}  "
                                   f"[M wire mesh  Esc leave]")
        self._set(self.hud, "\n".join(lines))
        # in the lobby the lines (a connection problem) go below its centred title
        self.hud.y = h - 12 if self.replay is not None or m.room is not None else h - 70
        cd = m.countdown(now) if self.replay is None else None
        self._set(self.big, str(cd) if cd is not None else "")
        self.big.x, self.big.y = w // 2, h // 2
        # names at the corners, pushed outwards on screen (off the cloth and its bands)
        centre_px = None
        if self.frame is not None:
            cx, cy, ok = self.camera.project(self.frame.positions.reshape(-1, 3).mean(axis=0),
                                             fw, fh)
            centre_px = np.array([cx, cy]) if ok else None
        for i, lab in enumerate(self.name_labels):
            text, pos = "", None
            if self.frame is not None:
                hnd = self.frame.handles[i]
                if hnd.kind != "empty" or hnd.own:
                    text = ("you" if hnd.own else hnd.name) or f"seat {i}"
                    pos = hnd.position
            if pos is not None:
                px, py, ok = self.camera.project(pos, fw, fh)
                if ok:
                    out = np.array([0.0, 1.0])
                    if centre_px is not None:
                        d = np.array([px, py]) - centre_px
                        out = d / max(float(np.linalg.norm(d)), 1e-9)
                    lab.x = int(px * sx + 34 * out[0])
                    lab.y = int(py * sy + 30 * out[1] - 6)
                else:
                    text = ""
            self._set(lab, text)

    @staticmethod
    def _set(label: Any, text: str) -> None:
        if label.text != text:
            label.text = text

    @staticmethod
    def _score_line(scores: list[int], seats: list[dict[str, Any]]) -> str:
        names = {int(s.get("seat", i)): s for i, s in enumerate(seats)}
        parts = []
        for i in range(4):
            s = names.get(i, {})
            if s.get("kind", "empty") == "empty":
                continue
            parts.append(f"{s.get('name') or i} [{EDGE_NAMES[i]}] "
                         f"{scores[i] if i < len(scores) else 0}")
        return "scores: " + ("   ".join(parts) if parts else "-")

    @staticmethod
    def _replay_event_text(ev: dict[str, Any]) -> str:
        kind = ev.get("event")
        if kind == "score":
            return f"ball off the {ev.get('edge_name')} edge (seat {ev.get('conceded_by')})"
        if kind == "round_start":
            return f"round {ev.get('round')} starts"
        return ""

    def _update_ui(self) -> None:
        """The lobby buttons (or the room bar) as shapes and labels, rebuilt on change."""
        w, h = self.width, self.height
        if self.replay is not None:
            key: tuple[Any, ...] = ("replay", w, h, round(self.replay.position, 2))
            if key == self._ui_key:
                return
            self._ui_key = key
            self._clear_ui()
            bar_w = w - 80
            frac = self.replay.position / max(self.replay.data.duration, 1e-9)
            self._ui_shapes.append(pyglet.shapes.Rectangle(
                40, 30, bar_w, 8, color=(80, 90, 110), batch=self.ui_batch))
            self._ui_shapes.append(pyglet.shapes.Rectangle(
                40, 30, bar_w * frac, 8, color=(240, 160, 60), batch=self.ui_batch))
            return
        buttons = self.lobby.buttons(self.model, w, h)
        in_lobby = self.model.room is None
        title = ""
        if in_lobby:
            title = {"rooms": f"clothball - rooms on {self.model.server_url}",
                     "create": f"new room name: {self.lobby.name_input}_",
                     "seats": "choose a corner"}.get(self.lobby.screen, "")
            if self.model.connection != "connected":
                title = CONNECTION_TITLES.get(self.model.connection, self.model.connection)
        self._set(self.title_label, title)
        self.title_label.x, self.title_label.y = w // 2, h - 40
        key = (w, h, tuple((b.action, b.label, b.enabled) for b in buttons))
        if key == self._ui_key:
            return
        self._ui_key = key
        self._clear_ui()
        for b in buttons:
            alpha = 230 if b.enabled else 120
            self._ui_shapes.append(pyglet.shapes.Rectangle(
                b.x, b.y, b.w, b.h, color=_rgb255(b.colour, alpha), batch=self.ui_batch))
            label = pyglet.text.Label(
                b.label, x=int(b.x + 10), y=int(b.y + b.h / 2), anchor_y="center",
                font_size=FONT_SIZE, batch=self.ui_batch, color=(255, 255, 255, 255))
            fit_label(label, b.w - 20)
            self._ui_labels.append(label)

    def _clear_ui(self) -> None:
        for s in self._ui_shapes + self._ui_labels:
            s.delete()
        self._ui_shapes, self._ui_labels = [], []

    # --- input ------------------------------------------------------------------------------
    def _playing(self) -> bool:
        return (self.replay is None and self.model.seat is not None
                and isinstance(self.device, MouseDevice))

    def _point(self, x: float, y: float) -> None:
        if not self._playing():
            return
        fw, fh = self.get_framebuffer_size()
        sx, sy = fw / max(1, self.width), fh / max(1, self.height)
        origin, direction = self.camera.ray(x * sx, y * sy, fw, fh)
        self.device.point_at_ray(origin, direction)

    def on_mouse_motion(self, x: int, y: int, dx: int, dy: int) -> None:
        self._point(x, y)

    def on_mouse_drag(self, x: int, y: int, dx: int, dy: int, buttons: int,
                      modifiers: int) -> None:
        mouse = pyglet.window.mouse
        shift = modifiers & pyglet.window.key.MOD_SHIFT
        if buttons & mouse.MIDDLE or (buttons & mouse.LEFT and shift):
            self.camera.orbit(-dx * 0.01, -dy * 0.01)
        elif buttons & mouse.RIGHT:
            if self._playing():
                self.device.drag_height(dy)
        elif buttons & mouse.LEFT:
            if self.replay is not None and 22 <= y <= 46:
                self._seek_bar(x)
            else:
                self._point(x, y)

    def on_mouse_scroll(self, x: int, y: int, scroll_x: float, scroll_y: float) -> None:
        if self._playing() and not (self._modifiers & pyglet.window.key.MOD_CTRL):
            self.device.scroll(scroll_y)
        else:
            self.camera.zoom(0.9 ** scroll_y)

    _modifiers = 0

    def on_key_release(self, symbol: int, modifiers: int) -> None:
        self._modifiers = modifiers

    def _seek_bar(self, x: float) -> None:
        if self.replay is not None:
            self.replay.seek_fraction((x - 40) / max(1, self.width - 80))

    def on_mouse_press(self, x: int, y: int, button: int, modifiers: int) -> None:
        if self.replay is not None:
            if 22 <= y <= 46:
                self._seek_bar(x)
            return
        action = self.lobby.hit(self.model, self.width, self.height, x, y)
        if action is not None:
            self.perform(action)

    def perform(self, action: Action) -> None:
        """Carry out a lobby action (from a click or a key)."""
        net = self.net
        if net is None:
            return
        kind = action[0]
        if kind == "refresh":
            self._track("refresh", net.list_rooms())
        elif kind == "retry":
            self.model.set_connection("connecting", net.url)
            net.retry()
        elif kind == "create_room":
            self._track("create_room", net.create_room(action[1]))
        elif kind == "join":
            _, room, role, seat = action
            self._camera_set_for = None
            self.buffer.reset()
            self._track("join", net.join(room, role, seat))
        elif kind == "ready":
            self._track("ready", net.ready(bool(action[1])))
        elif kind == "add_bot":
            self._track("add bot", net.add_bot(action[1]))
        elif kind == "leave":
            self._track("leave", net.leave())

    def on_text(self, text: str) -> None:
        swallow, self._swallow_text = self._swallow_text, ""
        if swallow and text.lower() == swallow:
            return  # the N that opened the name field is not part of the name
        if self.model.room is None and self.lobby.screen == "create":
            self.lobby.type_text(text)

    def on_key_press(self, symbol: int, modifiers: int) -> None:
        key = pyglet.window.key
        self._modifiers = modifiers
        self._swallow_text = ""  # a keystroke's on_text comes before the next key's press
        typing = self.model.room is None and self.lobby.screen == "create"
        if symbol == key.ESCAPE:
            if self.replay is not None:
                self.close()
            elif self.model.room is not None:
                self.perform(("leave",))
            elif self.lobby.screen != "rooms":
                self.lobby.act(("back",))
            else:
                self.close()
            return
        if symbol == key.F12:
            path = Path(f"clothball-{time.strftime('%Y%m%d-%H%M%S')}.png")
            self.screenshot(path)
            self.model.log(f"screenshot saved: {path}", self.clock(), "info")
            return
        if typing:
            if symbol == key.BACKSPACE:
                self.lobby.backspace()
            elif symbol in (key.ENTER, key.RETURN):
                action = self.lobby.act(("submit_create",))
                if action is not None:
                    self.perform(action)
            return
        if symbol == key.M:
            if modifiers & key.MOD_SHIFT:
                self.renderer.wire_only = not self.renderer.wire_only
            else:
                self.renderer.wire = not self.renderer.wire
                self.renderer.wire_only = False
        elif symbol in (key.LEFT, key.RIGHT, key.UP, key.DOWN) and self.replay is None:
            d = {key.LEFT: (0.08, 0), key.RIGHT: (-0.08, 0), key.UP: (0, 0.06),
                 key.DOWN: (0, -0.06)}[symbol]
            self.camera.orbit(*d)
        elif self.replay is not None:
            self._replay_key(symbol, modifiers)
        elif symbol == key.R and self.model.seat is not None:
            self.perform(("ready", not self.model.ready()))
        elif symbol == key.C and isinstance(self.device, MouseDevice):
            self.device.centre()
        elif self.model.room is None:
            if symbol in (key.ENTER, key.RETURN) and self.model.connection == "failed":
                self.perform(("retry",))
            elif symbol == key.F5:
                self.perform(("refresh",))
            elif symbol == key.N:
                self.lobby.act(("create",))
                self._swallow_text = "n"
            elif symbol == key.W and self.lobby.screen == "seats":
                action = self.lobby.act(("spectate",))
                if action is not None:
                    self.perform(action)

    def _replay_key(self, symbol: int, modifiers: int) -> None:
        key = pyglet.window.key
        rp = self.replay
        assert rp is not None
        step = 10.0 if modifiers & key.MOD_SHIFT else 2.0
        if symbol == key.SPACE:
            rp.toggle_pause()
        elif symbol == key.LEFT:
            rp.skip(-step)
        elif symbol == key.RIGHT:
            rp.skip(step)
        elif symbol in (key.UP, key.PLUS, key.EQUAL, key.NUM_ADD):
            rp.faster()
        elif symbol in (key.DOWN, key.MINUS, key.NUM_SUBTRACT):
            rp.slower()
        elif symbol == key.HOME:
            rp.seek(0.0)
        elif symbol == key.END:
            rp.seek(rp.data.duration)

    # --- misc -------------------------------------------------------------------------------
    def screenshot(self, path: Path | str) -> None:
        """Save the last drawn frame (the back buffer after a draw) as a PNG."""
        self.switch_to()
        self.on_draw()  # directly: outside the loop pyglet would only queue the event
        pyglet.image.get_buffer_manager().get_color_buffer().save(str(path))

    def on_close(self) -> None:
        pyglet.clock.unschedule(self.update)
        super().on_close()


def run_window(window: ClientWindow, fps: float = 60.0) -> None:
    """pyglet's loop until the window closes."""
    pyglet.app.run(1.0 / fps)


def fps_summary(window: ClientWindow) -> str:
    times = window.draw_times[-300:]
    if not times:
        return "no frames drawn"
    return (f"{window.frames_drawn} frames drawn, draw time p50 "
            f"{np.median(times) * 1e3:.1f} ms, max {max(times) * 1e3:.1f} ms")


__all__ = ["ClientWindow", "fps_summary", "hand_help", "run_window"]
