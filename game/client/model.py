"""What the client knows about the server, the room and the match: pure state, updated
from the server's JSON messages (``apply``) and read by the window to draw the HUD.

No network and no window here: the network thread hands messages over, the window thread
applies them (one thread owns the model), and the tests feed it messages by hand.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field
from typing import Any

from .interp import EDGE_NAMES

EVENT_LINES = 6
EVENT_SECONDS = 8.0


@dataclass
class EventLine:
    text: str
    at: float  # local time it arrived
    kind: str = "event"


@dataclass
class ClientModel:
    """Connection, lobby and match state as the server last described it."""

    name: str = "player"
    connection: str = "connecting"  # connecting, connected, reconnecting, closed, failed
    detail: str = ""  # why the connection state is what it is
    server_url: str = ""
    welcome: dict[str, Any] = field(default_factory=dict)
    rooms: list[dict[str, Any]] = field(default_factory=list)
    room: dict[str, Any] | None = None  # the joined room's info()
    joined: dict[str, Any] | None = None
    role: str = "lobby"  # lobby, player, spectator
    countdown_to: float | None = None  # local time the countdown reaches zero
    events: collections.deque[EventLine] = field(
        default_factory=lambda: collections.deque(maxlen=50))
    rtt: float | None = None  # s, control round trip (ping)
    hip_latency: float | None = None  # s, HIP sent -> the CORNER that applied it
    last_error: str | None = None
    replay_ids: list[str] = field(default_factory=list)

    # --- reading --------------------------------------------------------------------------
    @property
    def seat(self) -> int | None:
        if self.joined is None or self.role != "player":
            return None
        s = self.joined.get("seat")
        return int(s) if s is not None else None

    @property
    def seats(self) -> list[dict[str, Any]]:
        return list(self.room.get("seats", [])) if self.room else []

    @property
    def scores(self) -> list[int]:
        return list(self.room.get("scores", [0, 0, 0, 0])) if self.room else [0, 0, 0, 0]

    @property
    def match_state(self) -> str:
        return str(self.room.get("state", "waiting")) if self.room else "lobby"

    @property
    def geometry(self) -> dict[str, Any]:
        return dict(self.joined.get("geometry", {})) if self.joined else {}

    def countdown(self, now: float) -> int | None:
        """Whole seconds left in the countdown, or None when none is running."""
        if self.countdown_to is None or self.match_state != "countdown":
            return None
        left = self.countdown_to - now
        return max(1, math.ceil(left - 1e-9)) if left > -0.5 else None

    def recent_events(self, now: float, lines: int = EVENT_LINES) -> list[str]:
        fresh = [e.text for e in self.events if now - e.at < EVENT_SECONDS]
        return fresh[-lines:]

    def seat_name(self, seat: int | None) -> str:
        if seat is None:
            return "nobody"
        for s in self.seats:
            if s.get("seat") == seat:
                return str(s.get("name") or f"seat {seat}")
        return f"seat {seat}"

    def ready(self) -> bool:
        s = self.seat
        if s is None:
            return False
        return any(x.get("seat") == s and x.get("ready") for x in self.seats)

    def connection_text(self) -> str:
        parts = [self.connection]
        if self.rtt is not None:
            parts.append(f"rtt {self.rtt * 1e3:.0f} ms")
        if self.hip_latency is not None:
            parts.append(f"hand->corner {self.hip_latency * 1e3:.0f} ms")
        if self.detail:
            parts.append(self.detail)
        return " | ".join(parts)

    # --- writing --------------------------------------------------------------------------
    def log(self, text: str, now: float, kind: str = "event") -> None:
        self.events.append(EventLine(text, now, kind))

    def set_connection(self, state: str, detail: str = "") -> None:
        self.connection, self.detail = state, detail

    def apply(self, msg: dict[str, Any], now: float) -> None:
        """Take in one JSON message from the server."""
        t = msg.get("type")
        if t == "welcome":
            self.welcome = msg
            self.rooms = list(msg.get("rooms", []))
            self.connection = "connected"
        elif t == "rooms":
            self.rooms = list(msg.get("rooms", []))
        elif t == "room_created":
            state = msg.get("state")
            if isinstance(state, dict):
                self._upsert_room(state)
        elif t == "joined":
            self.joined = msg
            self.role = str(msg.get("role", "player"))
            if isinstance(msg.get("state"), dict):
                self.room = msg["state"]
                self._upsert_room(msg["state"])
            where = f" seat {msg['seat']} ({msg.get('edge_name')})" if "seat" in msg else ""
            self.log(f"joined room {msg.get('room')} as {self.role}{where}", now, "info")
        elif t == "left":
            self.joined, self.room, self.role = None, None, "lobby"
            self.countdown_to = None
        elif t == "room":
            info = {k: v for k, v in msg.items() if k != "type"}
            if self.room is None or info.get("id") == self.room.get("id"):
                self.room = info
            self._upsert_room(info)
            if info.get("state") != "countdown":
                self.countdown_to = None
        elif t == "event":
            self._event(msg, now)
        elif t == "pong":
            sent = msg.get("t")
            if isinstance(sent, int | float):
                rtt = now - float(sent)
                if 0 <= rtt < 60:
                    self.rtt = rtt if self.rtt is None else 0.7 * self.rtt + 0.3 * rtt
        elif t == "error":
            self.last_error = f"{msg.get('code')}: {msg.get('message')}"
            self.log(f"server: {msg.get('message')}", now, "error")
        elif t == "host_gone":  # NetClient's own: the room's host went away, back in a lobby
            self.joined, self.room, self.role = None, None, "lobby"
            self.countdown_to = None
            self.log(str(msg.get("message") or "the room's host went away"), now, "error")
        elif t == "kicked" or t == "bye":
            self.log(f"server: {msg.get('reason') or msg.get('message') or t}", now, "error")

    def _upsert_room(self, info: dict[str, Any]) -> None:
        rid = info.get("id")
        if rid is None or not info.get("public", True):
            return
        for i, r in enumerate(self.rooms):
            if r.get("id") == rid:
                self.rooms[i] = info
                return
        self.rooms.append(info)

    def _event(self, msg: dict[str, Any], now: float) -> None:
        ev = msg.get("event")
        if self.room is not None and msg.get("room") not in (None, self.room.get("id")):
            return
        text: str | None = None
        if ev == "countdown":
            secs = float(msg.get("seconds", 0))
            self.countdown_to = now + secs
            if self.room is not None:
                self.room["state"] = "countdown"
        elif ev == "match_start":
            text = f"match starts: first to {msg.get('first_to')}"
        elif ev == "round_start":
            self.countdown_to = None
            if self.room is not None:
                self.room["state"] = "playing"
                self.room["round"] = msg.get("round")
            text = f"round {msg.get('round')}: go!"
        elif ev == "score":
            edge = msg.get("edge")
            who = self.seat_name(msg.get("conceded_by"))
            edge_name = msg.get("edge_name") or (
                EDGE_NAMES[edge] if isinstance(edge, int) and 0 <= edge < 4 else "?")
            if self.room is not None and isinstance(msg.get("scores"), list):
                self.room["scores"] = msg["scores"]
            if msg.get("conceded_by") is None:
                text = f"ball off the {edge_name} edge: nobody guards it, round void"
            else:
                text = f"ball off the {edge_name} edge: {who} concedes"
        elif ev == "match_end":
            winners = msg.get("winners") or []
            names = ", ".join(self.seat_name(w) for w in winners) or "nobody"
            text = f"match over: {names} win{'s' if len(winners) == 1 else ''}"
        elif ev == "match_abort":
            text = f"match aborted: {msg.get('reason')}"
        elif ev == "seat":
            seat, kind = msg.get("seat"), msg.get("kind")
            corner = EDGE_NAMES[seat] if isinstance(seat, int) and 0 <= seat < 4 else "?"
            if kind == "empty":
                text = f"{corner} corner is free ({msg.get('reason', 'left')})"
            elif msg.get("held_for"):
                text = f"{msg.get('name')} dropped; seat held {msg['held_for']:.0f} s"
            elif msg.get("resumed"):
                text = f"{msg.get('name')} is back"
            else:
                why = {"replaced_bot": " (the bot makes way)",
                       "backfill": " (an empty seat filled)"}.get(str(msg.get("reason")), "")
                text = f"{msg.get('name')} takes the {corner} corner{why}"
        elif ev == "replay_saved":
            rid = msg.get("id")
            if isinstance(rid, str):
                self.replay_ids.append(rid)
            text = f"round {msg.get('round')} saved: clothball replay {rid}"
        elif ev == "room_stopped":
            text = f"room stopped: {msg.get('reason')}"
        elif ev == "cannot_start":
            text = f"cannot start: {msg.get('reason')}"
        elif ev == "replay_failed":
            text = f"round {msg.get('round')} not recorded: {msg.get('reason')}"
        else:
            text = str(ev)
        if text:
            self.log(text, now)
