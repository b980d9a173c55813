"""The replay view in real headless Chromium with a round recorded by the ``--bots 4`` room:
the classic scene (60 x 60, meshes zlib'd, inflated by the page's DecompressionStream) and
four bots, as ``clothball host --bots 4`` hosts it. The page must keep answering while the
replay loads, plays, seeks, pauses and ends.

Every script call here runs under a short script timeout: a page that stops answering (its
main thread spinning) fails the call with a timeout instead of hanging the test.
"""

from __future__ import annotations

import base64
import contextlib
import json
import time
import urllib.request
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from clothball.game.sim.scene import Scene
from clothball.game.wire import protocol as P
from clothball.server.room import RoomSettings
from clothball.server.thread import ServerThread

from tests.web.conftest import console_errors, find_browser, wait_for, web_server

_, _, WHY = find_browser()
pytestmark = pytest.mark.skipif(bool(WHY), reason=WHY or "browser present")

# s a script call may take: a page that answers at all answers in milliseconds.
ANSWER_S = 5
# The host's room (classic scene, four bots), but a short countdown so that the first round
# comes soon.
SETTINGS = RoomSettings(autoplay=True, countdown=0.5)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[ServerThread, dict]]:
    """The server and the index row of the first round its bots' room recorded."""
    with web_server(tmp_path_factory.mktemp("replay"), scene=Scene.load("classic"),
                    settings=SETTINGS) as st:
        def rows() -> list[dict[str, Any]]:
            with urllib.request.urlopen(st.url + "api/replays", timeout=10) as r:
                return json.loads(r.read())["replays"]

        yield st, wait_for(rows, 120, "a round of the classic room recorded")[-1]


@pytest.fixture()
def page(driver: Any) -> Iterator[Any]:
    """The module's Chromium with a short script timeout, and a short wait for chromedriver
    itself (it waits on a frozen page however long its script timeout)."""
    config = driver.command_executor.client_config
    before = config.timeout
    config.timeout = ANSWER_S + 10
    try:
        driver.set_script_timeout(ANSWER_S)
        yield driver
    finally:
        with contextlib.suppress(Exception):  # frozen: quit_driver ends it
            driver.set_script_timeout(60)
        config.timeout = before


def answering(call: Any) -> Any:
    """``call()``, a frozen page turned into a test failure."""
    from selenium.common.exceptions import TimeoutException
    from urllib3.exceptions import TimeoutError as HttpTimeout

    try:
        return call()
    except (TimeoutException, HttpTimeout):
        raise AssertionError(f"the page did not answer within {ANSWER_S} s (its main thread "
                             "is busy: frozen)") from None


def answer(driver: Any) -> dict[str, Any]:
    """The page's replay state, from a script that resolves only after the page's event
    loop has turned (a timer and an animation frame ran): a frozen page times out."""
    return answering(lambda: driver.execute_async_script("""
        const done = arguments[arguments.length - 1];
        setTimeout(() => requestAnimationFrame(() => {
          const a = window.clothball, t = document.getElementById('transport');
          done({ state: t.dataset.state, time: Number(t.dataset.time || -1),
                 shown: a.shownMesh ? a.shownMesh.frame : null,
                 header: document.querySelector('#scoreboard .match')?.textContent || '' });
        }), 0);"""))


def wait_answering(driver: Any, pred: Any, timeout: float, what: str) -> dict[str, Any]:
    """Poll ``answer`` until ``pred`` holds; every poll must be answered (a frozen page
    fails the test at once, it is not polled again)."""
    end = time.monotonic() + timeout
    while True:
        seen = answer(driver)
        if pred(seen):
            return seen
        if time.monotonic() > end:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what} "
                                 f"(last: {seen})")
        time.sleep(0.2)


def js(driver: Any, script: str, *args: Any) -> Any:
    return answering(lambda: driver.execute_script(script, *args))


def click(driver: Any, element_id: str) -> None:
    answering(lambda: driver.find_element("id", element_id).click())


def open_url(driver: Any, url: str) -> None:
    answering(lambda: driver.get("about:blank"))
    console_errors(driver)  # drain
    answering(lambda: driver.get(url))


def seek(driver: Any, t: float) -> None:
    js(driver, """const s = document.getElementById('seek'); s.value = arguments[0];
        s.dispatchEvent(new Event('input', {bubbles: true}));""", t)


def mesh_frame_at(driver: Any, t: float) -> int:
    return js(driver, "const r = window.clothball.replay;"
                                 "return r.meshes[r.meshIndexAt(arguments[0])].frame", t)


def test_events_after_the_last_frame_are_shown_at_the_end(recorded, page) -> None:
    """Events the recorder stamped after its last MESH/TRACK frame (the room's frame when
    they happened, a few frames after the last track) are on the timeline's end."""
    st, _ = recorded
    open_url(page, st.url)
    frame_dt = 0.001
    zeros = np.zeros((4, 3))
    tracks = [P.encode_track(f, f * frame_dt, np.zeros(3), np.zeros(3), zeros, zeros)
              for f in (1000, 1010, 1020)]
    events = [{"type": "event", "event": e, "frame": f}
              for e, f in (("round_start", 1000), ("score", 1020), ("match_end", 1023))]
    got = page.execute_async_script("""
        const [tracks, events, dt, done] = arguments;
        import('/static/replay.js').then((R) => {
          const bytes = (s) => Uint8Array.from(atob(s), (c) => c.charCodeAt(0));
          const records = [...events.map((e) => ({ kind: 0, data: new TextEncoder().encode(
            JSON.stringify(e)) })), ...tracks.map((t) => ({ kind: 1, data: bytes(t) }))];
          const r = new R.Replay({ header: { geometry: { frame_dt: dt } }, records });
          done({ duration: r.duration,
                 end: r.eventsUntil(r.duration).map((e) => e.msg.event),
                 before: r.eventsUntil(r.duration - 0.002).map((e) => e.msg.event) });
        }).catch((e) => done({ error: String(e.stack || e) }));
    """, [base64.b64encode(t).decode() for t in tracks], events, frame_dt)
    assert "error" not in got, got.get("error")
    assert got["duration"] == pytest.approx(0.020)
    assert got["end"] == ["round_start", "score", "match_end"]
    assert got["before"] == ["round_start"]


def test_replay_of_the_bots_room_stays_responsive(recorded, page) -> None:
    st, row = recorded
    open_url(page, f"{st.url}#/replay/{row['id']}")
    # loads and plays; the page answers all along
    first = wait_answering(page, lambda s: s["state"] == "playing" and s["time"] > 0, 30,
                           "the replay to play")
    wait_answering(page, lambda s: s["time"] > first["time"] and s["shown"] is not None, 10,
                   "the clock to advance with a cloth shown")
    duration = js(page, "return window.clothball.replay.duration")
    assert duration == pytest.approx(row["duration_s"], abs=1e-9)
    # seeks in a burst (each one asks for meshes not yet inflated): the newest one wins,
    # its mesh is shown once inflated
    click(page, "play")
    wait_answering(page, lambda s: s["state"] == "paused", 5, "pause")
    targets = [duration * k for k in (0.9, 0.2, 0.7, 0.4, 0.55)]
    js(page, """const s = document.getElementById('seek');
        for (const t of arguments[0]) {
          s.value = t; s.dispatchEvent(new Event('input', {bubbles: true}));
        }""", targets)
    # The slider rounds to its step (1 ms) and the page seeks to the rounded value, so the
    # mesh due is the one at that value: where a mesh starts between the target and its
    # rounding, the target's is the mesh before (seen once in ~20 runs: 3565 asked, 3598
    # shown). The page shows its clock to 0.1 ms.
    sought = js(page, "return Number(document.getElementById('seek').value)")
    assert sought == pytest.approx(targets[-1], abs=1e-3)
    want = mesh_frame_at(page, sought)
    got = wait_answering(page, lambda s: s["shown"] == want, 10,
                         f"the mesh at {sought:.3f} s (frame {want}) shown")
    assert got["state"] == "paused" and got["time"] == pytest.approx(sought, abs=1e-4)
    # paused: the clock holds
    assert answer(page)["time"] == got["time"]
    # seek to the end: the last mesh, and every event of the replay is listed
    seek(page, duration)
    last = js(page, "const m = window.clothball.replay.meshes;"
                               "return m[m.length - 1].frame")
    end = wait_answering(page, lambda s: s["shown"] == last, 10, "the last mesh shown")
    ended = js(page, "return window.clothball.replay.events"
                                ".some((e) => e.msg.event === 'match_end')")
    assert ("match over" in end["header"]) == ended, end["header"]
    assert ended or "round over" in end["header"], end["header"]
    # play from near the end: it runs out, stops at the end and still answers
    seek(page, max(0.0, duration - 0.5))
    click(page, "play")
    done = wait_answering(page, lambda s: s["state"] == "paused" and s["time"] >= duration - 1e-3,
                          15, "the replay to play to its end")
    # The clock may reach the end while the last mesh is still being inflated (one at a
    # time, the newest decoded shown meanwhile: replay.js): it is shown once ready, the
    # clock still held at the end (the CI dry run at 5132588 asserted a frame too early).
    done = wait_answering(page, lambda s: s["shown"] == last, 10, "the last mesh shown")
    assert done["state"] == "paused" and done["time"] >= duration - 1e-3, done
    # play again from the end: starts over
    click(page, "play")
    again = wait_answering(page, lambda s: s["state"] == "playing", 5, "a replay from the start")
    assert again["time"] < duration - 0.4
    assert console_errors(page) == []
