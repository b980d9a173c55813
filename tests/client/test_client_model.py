"""Client state without a window: the model built from server messages, the lobby
screens (layout, clicks, actions)."""

from __future__ import annotations

from typing import Any

import pytest
from clothball.game.client.lobby_ui import LobbyUI
from clothball.game.client.model import ClientModel


def seats(*kinds: str) -> list[dict[str, Any]]:
    return [{"seat": i, "edge": ("north", "east", "south", "west")[i], "kind": k,
             "name": "" if k == "empty" else f"{k}-{i}", "ready": k == "bot",
             "connected": k != "empty"} for i, k in enumerate(kinds)]


def room(rid: str = "r1", state: str = "waiting", **kw: Any) -> dict[str, Any]:
    info = {"id": rid, "name": f"room {rid}", "scene": "classic", "n": 16, "public": True,
            "state": state, "round": 0, "first_to": 5, "scores": [0, 0, 0, 0],
            "winners": [], "seats": seats("bot", "empty", "empty", "empty"),
            "spectators": 0, "bots_allowed": True, "frame": 0}
    info.update(kw)
    return info


def test_model_back_in_the_lobby_when_the_rooms_host_went_away() -> None:
    m = ClientModel(name="ann")
    m.apply({"type": "welcome", "rooms": [room("r1")]}, 0.0)
    m.apply({"type": "joined", "room": "r1", "role": "spectator", "geometry": {},
             "state": room("r1")}, 1.0)
    assert m.room is not None and m.role == "spectator"
    text = "the host of room r1 went away (ws://b:1/ws); back in the lobby at ws://a:1/ws"
    m.apply({"type": "host_gone", "room": "r1", "url": "ws://b:1/ws", "message": text}, 2.0)
    assert m.room is None and m.joined is None and m.role == "lobby"
    assert m.match_state == "lobby" and m.recent_events(2.0)[-1] == text


def test_model_follows_a_match() -> None:
    m = ClientModel(name="ann")
    m.apply({"type": "welcome", "rooms": [room("r1"), room("r2")]}, 0.0)
    assert m.connection == "connected" and [r["id"] for r in m.rooms] == ["r1", "r2"]
    assert m.seat is None and m.match_state == "lobby"
    m.apply({"type": "joined", "room": "r1", "role": "player", "seat": 2, "edge": 2,
             "edge_name": "south", "token": "t", "geometry": {"stiffness": 300.0},
             "reach": {"centre": [0, 1, 0], "half_extent": [0.3] * 3},
             "state": room("r1", seats=seats("bot", "empty", "human", "empty"))}, 1.0)
    assert m.seat == 2 and m.geometry["stiffness"] == 300.0 and m.match_state == "waiting"
    assert not m.ready()
    r = room("r1", seats=seats("bot", "empty", "human", "empty"))
    r["seats"][2]["ready"] = True
    m.apply({"type": "room", **r}, 1.5)
    assert m.ready()
    m.apply({"type": "room", **room("r2", state="playing")}, 1.6)  # another room's listing
    assert m.room is not None and m.room["id"] == "r1"
    assert next(x for x in m.rooms if x["id"] == "r2")["state"] == "playing"
    m.apply({"type": "event", "event": "match_start", "room": "r1", "first_to": 5}, 2.0)
    m.apply({"type": "event", "event": "countdown", "room": "r1", "seconds": 3}, 2.0)
    assert m.match_state == "countdown"
    assert m.countdown(2.1) == 3 and m.countdown(3.5) == 2 and m.countdown(4.9) == 1
    m.apply({"type": "event", "event": "round_start", "room": "r1", "round": 1}, 5.0)
    assert m.countdown(5.0) is None and m.match_state == "playing"
    m.apply({"type": "event", "event": "score", "room": "r1", "round": 1, "edge": 0,
             "edge_name": "north", "conceded_by": 0, "scorers": [2],
             "scores": [0, 0, 1, 0]}, 9.0)
    assert m.scores == [0, 0, 1, 0]
    assert m.recent_events(9.0)[-1] == "ball off the north edge: bot-0 concedes"
    m.apply({"type": "event", "event": "match_end", "room": "r1", "winners": [2],
             "scores": [0, 0, 5, 0]}, 30.0)
    assert m.recent_events(30.0)[-1] == "match over: human-2 wins"
    assert m.recent_events(30.0 + 100.0) == []  # old events fade out
    m.apply({"type": "event", "event": "replay_saved", "room": "r1", "id": "abc-123",
             "round": 1}, 31.0)
    assert m.replay_ids == ["abc-123"]
    m.apply({"type": "event", "event": "score", "room": "other", "scores": [9] * 4}, 32.0)
    assert m.scores == [0, 0, 1, 0]  # another room's events are not ours
    m.apply({"type": "left", "room": "r1"}, 40.0)
    assert m.room is None and m.seat is None


def test_latency_and_errors() -> None:
    m = ClientModel()
    m.apply({"type": "pong", "t": 10.0, "server_time": 1.0}, 10.020)
    assert m.rtt == pytest.approx(0.020)
    m.apply({"type": "pong", "t": 11.0}, 11.040)
    assert 0.020 < m.rtt < 0.040
    m.hip_latency = 0.012
    assert "rtt" in m.connection_text() and "12 ms" in m.connection_text()
    m.apply({"type": "error", "code": "bad_seat", "message": "seat 1 is taken"}, 12.0)
    assert m.last_error == "bad_seat: seat 1 is taken"
    assert "seat 1 is taken" in m.recent_events(12.0)[-1]


def test_lobby_click_through() -> None:
    m = ClientModel()
    m.apply({"type": "welcome", "rooms": [room("r1"), room("r2")]}, 0.0)
    ui = LobbyUI()
    w, h = 1280, 800
    buttons = ui.buttons(m, w, h)
    rooms = [b for b in buttons if b.action[0] == "select_room"]
    assert [b.action[1] for b in rooms] == ["r1", "r2"]
    b = rooms[1]
    assert ui.hit(m, w, h, b.x + b.w / 2, b.y + b.h / 2) is None  # local: opens the seats
    assert ui.screen == "seats" and ui.selected == "r2"
    seat_buttons = {b.action: b for b in ui.buttons(m, w, h)}
    taken = seat_buttons[("take_seat", 0)]
    assert not taken.enabled  # a bot sits there
    assert ui.hit(m, w, h, taken.x + 1, taken.y + 1) is None
    free = seat_buttons[("take_seat", 3)]
    assert ui.hit(m, w, h, free.x + 1, free.y + 1) == ("join", "r2", "player", 3)
    watch = seat_buttons[("spectate",)]
    assert ui.hit(m, w, h, watch.x + 1, watch.y + 1) == ("join", "r2", "spectator", None)
    back = seat_buttons[("back",)]
    ui.hit(m, w, h, back.x + 1, back.y + 1)
    assert ui.screen == "rooms"
    # nothing overlaps: every button's centre hits only that button
    for screen in ("rooms", "seats", "create"):
        ui.screen = screen
        bs = ui.buttons(m, w, h)
        for b in bs:
            assert sum(o.contains(b.x + b.w / 2, b.y + b.h / 2) for o in bs) == 1


def test_lobby_create_and_room_bar() -> None:
    m = ClientModel()
    m.apply({"type": "welcome", "rooms": []}, 0.0)
    ui = LobbyUI()
    assert ui.act(("create",)) is None and ui.screen == "create"
    ui.type_text("fri\x07day")
    ui.type_text(" game")
    ui.backspace()
    assert ui.name_input == "friday gam"
    assert ui.act(("submit_create",)) == ("create_room", "friday gam")
    m.apply({"type": "room_created", "room": "r9", "code": None, "state": room("r9")}, 1.0)
    assert [r["id"] for r in m.rooms] == ["r9"]
    m.apply({"type": "joined", "room": "r9", "role": "player", "seat": 1,
             "state": room("r9", seats=seats("bot", "human", "empty", "empty"))}, 2.0)
    bar = {b.action: b for b in ui.buttons(m, 1280, 800)}
    assert ("ready", True) in bar and ("leave",) in bar
    assert ("add_bot", 2) in bar and ("add_bot", 3) in bar and ("add_bot", 0) not in bar
    b = bar[("add_bot", 3)]
    assert ui.hit(m, 1280, 800, b.x + 1, b.y + 1) == ("add_bot", 3)
    m.apply({"type": "room", **room("r9", state="playing",
                                    seats=seats("bot", "human", "empty", "empty"))}, 3.0)
    assert [b.action for b in ui.buttons(m, 1280, 800)] == [("leave",)]


def test_seat_events_say_why_a_player_took_a_corner() -> None:
    """A human who takes a bot's corner: the event says the bot made way; a bot put on an
    empty corner when a match starts says it filled it; a plain join says neither."""
    m = ClientModel()
    m.apply({"type": "event", "event": "seat", "seat": 1, "kind": "human", "name": "ann",
             "reason": "replaced_bot"}, 0.0)
    m.apply({"type": "event", "event": "seat", "seat": 3, "kind": "bot", "name": "bot-3",
             "reason": "backfill"}, 0.0)
    m.apply({"type": "event", "event": "seat", "seat": 2, "kind": "human", "name": "bo"}, 0.0)
    assert m.recent_events(0.0) == ["ann takes the east corner (the bot makes way)",
                                    "bot-3 takes the west corner (an empty seat filled)",
                                    "bo takes the south corner"]
