"""The lobby screens as pure state: layout, hit tests and the action each click means.

Screens: **rooms** (the server's public rooms; refresh, create, select one; when the
connection failed, a Retry button instead), **create**
(type a name, Enter), **seats** (the chosen room's four corners: take a free one, or
watch), and in a room the **room bar** (ready, add a bot to a free corner, start, leave).
``buttons()`` lays the current screen out for a window size; ``hit()`` says which
button is under a point; the window turns the action into a request on the network
thread and draws the buttons. Keeping this free of pyglet lets the tests click through
the lobby without a window.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from .interp import EDGE_NAMES, SEAT_COLOURS
from .model import ClientModel

Action = tuple[Any, ...]


@dataclass(frozen=True)
class Button:
    action: Action
    label: str
    x: float
    y: float  # bottom-left, pyglet's window coordinates
    w: float
    h: float
    enabled: bool = True
    colour: tuple[float, float, float] = (0.25, 0.32, 0.42)

    def contains(self, px: float, py: float) -> bool:
        return self.x <= px <= self.x + self.w and self.y <= py <= self.y + self.h


def seat_open(seat: dict[str, Any]) -> bool:
    """Whether a human may take this seat: empty, or held by a bot (bots are backfill)."""
    return bool(seat.get("open", seat.get("kind") == "empty"))


@dataclass
class LobbyUI:
    screen: str = "rooms"  # rooms, create, seats
    selected: str | None = None  # room id on the seats screen
    name_input: str = ""
    message: str = ""
    max_rooms_shown: int = 8
    pending: dict[str, Any] = field(default_factory=dict)

    # --- layout ---------------------------------------------------------------------------
    def buttons(self, model: ClientModel, width: int, height: int) -> list[Button]:
        if model.room is not None and model.joined is not None:
            return self.room_bar(model, width, height)
        if self.screen == "create":
            return self._create(width, height)
        if self.screen == "seats":
            room = self.room(model)
            if room is not None:
                return self._seats(room, width, height)
            self.screen = "rooms"
        return self._rooms(model, width, height)

    def room(self, model: ClientModel) -> dict[str, Any] | None:
        for r in model.rooms:
            if r.get("id") == self.selected:
                return r
        return None

    def _rooms(self, model: ClientModel, width: int, height: int) -> list[Button]:
        bw, bh = min(640.0, width - 80.0), 40.0
        x = (width - bw) / 2
        top = height - 140.0
        out = []
        for i, r in enumerate(model.rooms[: self.max_rooms_shown]):
            seats = r.get("seats", [])
            free = sum(1 for s in seats if seat_open(s))
            scores = "-".join(str(s) for s in r.get("scores", []))
            label = (f"{r.get('name')}   [{r.get('scene')}, {r.get('state')}]   "
                     f"{free} corner{'s' if free != 1 else ''} to take   {scores}")
            out.append(Button(("select_room", r.get("id")), label, x, top - i * (bh + 8), bw, bh))
        y = 40.0
        if model.connection == "failed":  # the network thread waits for the user's word
            out.append(Button(("retry",), "Retry (Enter)", x, y, 180, bh,
                              colour=(0.2, 0.5, 0.3)))
            return out
        out.append(Button(("refresh",), "Refresh (F5)", x, y, 180, bh))
        out.append(Button(("create",), "Create room (N)", x + 200, y, 200, bh))
        return out

    def _create(self, width: int, height: int) -> list[Button]:
        x = width / 2 - 200
        return [
            Button(("submit_create",), f"Create '{self.name_input or 'room'}' (Enter)",
                   x, height / 2 - 60, 400, 40, colour=(0.2, 0.5, 0.3)),
            Button(("back",), "Back (Esc)", x, height / 2 - 110, 400, 40),
        ]

    def _seats(self, room: dict[str, Any], width: int, height: int) -> list[Button]:
        bw, bh = 300.0, 56.0
        cx, cy = width / 2, height / 2 + 20
        out = []
        # corners placed as seen from above: north-west (0) top-left, clockwise
        spots = [(-1, 1), (1, 1), (1, -1), (-1, -1)]
        for s in room.get("seats", []):
            i = int(s.get("seat", 0))
            free = seat_open(s)
            kind = s.get("kind")
            who = ("free" if kind == "empty" else f"{s.get('name')} (bot): take it" if free
                   else f"{s.get('name')} ({kind})")
            label = f"corner {i}: guards {EDGE_NAMES[i]} - {who}"
            dx, dy = spots[i]
            out.append(Button(("take_seat", i), label, cx + dx * (bw / 2 + 20) - bw / 2,
                              cy + dy * (bh / 2 + 20) - bh / 2, bw, bh, enabled=free,
                              colour=SEAT_COLOURS[i] if free else (0.3, 0.3, 0.3)))
        out.append(Button(("spectate",), "Watch (W)", cx - 210, 40, 200, 40))
        out.append(Button(("back",), "Back (Esc)", cx + 10, 40, 200, 40))
        return out

    def room_bar(self, model: ClientModel, width: int, height: int) -> list[Button]:
        """The buttons shown while in a room (top-right)."""
        out = []
        x, y, w, h = width - 200.0, height - 50.0, 180.0, 34.0
        state = model.match_state
        if model.role == "player" and state in ("waiting", "over"):
            ready = model.ready()
            out.append(Button(("ready", not ready), "Not ready (R)" if ready else "Ready (R)",
                              x, y, w, h, colour=(0.2, 0.55, 0.3) if not ready else
                              (0.5, 0.4, 0.2)))
            y -= h + 6
            for s in model.seats:
                if s.get("kind") == "empty" and (model.room or {}).get("bots_allowed", True):
                    i = int(s.get("seat", 0))
                    out.append(Button(("add_bot", i), f"Bot on corner {i} ({EDGE_NAMES[i]})",
                                      x, y, w, h, colour=SEAT_COLOURS[i]))
                    y -= h + 6
        out.append(Button(("leave",), "Leave (Esc)", x, y, w, h))
        return out

    def hit(self, model: ClientModel, width: int, height: int, x: float, y: float
            ) -> Action | None:
        for b in self.buttons(model, width, height):
            if b.enabled and b.contains(x, y):
                return self.act(b.action)
        return None

    # --- actions --------------------------------------------------------------------------
    def act(self, action: Action) -> Action | None:
        """Apply what is local to the screens; return what needs the server (or None)."""
        kind = action[0]
        if kind == "select_room":
            self.selected, self.screen = action[1], "seats"
            return None
        if kind == "create":
            self.screen, self.name_input = "create", ""
            return None
        if kind == "back":
            self.screen = "rooms"
            return None
        if kind == "submit_create":
            self.screen = "rooms"
            return ("create_room", self.name_input.strip() or "room")
        if kind in ("take_seat", "spectate"):
            if self.selected is None:
                return None
            return ("join", self.selected, "player" if kind == "take_seat" else "spectator",
                    action[1] if kind == "take_seat" else None)
        return action  # refresh, retry, ready, add_bot, leave

    def type_text(self, text: str) -> None:
        if self.screen == "create":
            self.name_input = (self.name_input + "".join(
                ch for ch in text if ch.isprintable()))[:48]

    def backspace(self) -> None:
        if self.screen == "create":
            self.name_input = self.name_input[:-1]
