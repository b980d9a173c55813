"""The spectator page across two servers of one service (two GameServers sharing a room
directory, as the hosts of ``--cluster`` do): a page from
one follows the redirect to the room's server (whose origin policy lets the other's page
in), and when that server goes away the page says which room's host went away and is back
in the lobby of the server it came from.

Skipped only when chromium or chromedriver is not installed (CI installs both).
"""

from __future__ import annotations

import pytest
from clothball.server.directory import SqliteDirectory

from tests.web.conftest import console_errors, find_browser, wait_for, web_server
from tests.web.test_web_browser import SCENE, SETTINGS, js, open_page

_, _, WHY = find_browser()
pytestmark = pytest.mark.skipif(bool(WHY), reason=WHY or "browser present")


def test_page_follows_a_room_to_another_host_and_hears_when_it_goes(tmp_path, driver) -> None:
    path = tmp_path / "rooms.sqlite"
    a = web_server(tmp_path / "a", scene=SCENE, settings=SETTINGS, bots=0,
                   directory=SqliteDirectory(path), host_id="host-a").start()
    b = web_server(tmp_path / "b", scene=SCENE, settings=SETTINGS, bots=0,
                   directory=SqliteDirectory(path), host_id="host-b").start()
    try:
        room_b = b.call(lambda s: s.main_room.id)
        assert room_b != a.call(lambda s: s.main_room.id)
        wait_for(lambda: room_b in [r["id"] for r in a.call(lambda s: s.lobby.listing())],
                 10, "a to list b's room")
        open_page(driver, f"{a.url}#/room/{room_b}")
        wait_for(lambda: js(driver, "return window.clothball.stats.meshFrames") > 0, 20,
                 "meshes from b's room")
        assert js(driver, "return window.clothball.room") == room_b
        assert js(driver, "return window.clothball.conn.url") == b.call(lambda s: s.own_url)
        b.stop()
        notice = driver.find_element("id", "lobby-notice")
        wait_for(notice.is_displayed, 15, "the page to say the host went away")
        assert f"The host of room {room_b}" in notice.text and "went away" in notice.text
        assert driver.find_element("id", "lobby").is_displayed()
        assert js(driver, "return location.hash") in ("#/", "")
        wait_for(lambda: js(driver, "return document.getElementById('conn').dataset.state")
                 == "open", 20, "the page back on a's lobby")
        assert js(driver, "return window.clothball.conn.url") == a.call(lambda s: s.ws_url)
        errs = [e for e in console_errors(driver) if "WebSocket" not in e["message"]]
        assert errs == []
    finally:
        b.stop()
        a.stop()
