"""The spectator page in real headless Chromium (Debian's chromium + chromedriver, driven by
Selenium; WebGL2 on SwiftShader) against a real game server on loopback with bots playing.

Skipped only when chromium or chromedriver is not installed (CI installs both).
"""

from __future__ import annotations

import io
import json
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from clothball.game.sim.scene import Scene
from clothball.server.room import RoomSettings
from clothball.server.thread import ServerThread

from tests.client.test_client_window import cloth_like
from tests.web.conftest import console_errors, find_browser, make_driver, wait_for, web_server
from tests.web.web_vectors import VECTORS

_, _, WHY = find_browser()
pytestmark = pytest.mark.skipif(bool(WHY), reason=WHY or "browser present")

# A small cloth keeps the room thread cheap on a 2-core machine; rounds come quickly (the
# ball starts with a sideways speed) and matches restart soon after they end.
SCENE = Scene.load("classic").with_changes({"cloth": {"n": 20}})
SCENE.name = "small"
SETTINGS = RoomSettings(autoplay=True, first_to=3, countdown=0.6, reset_speed=1.5,
                        restart_delay=1.0)

# The cloth's colours in the page are the desktop's (assets/web/palette.json, read by both
# clients), lit as base * (0.3 + 0.7 * diffuse) + a grey specular term: the hue ratio
# of the desktop's window test (unchanged by the light's scale and by added grey) tells
# cloth from the background, the floor grid and the ball.


def is_cloth(rgb: tuple[int, ...]) -> bool:
    return bool(cloth_like(np.array(rgb[:3], dtype=np.float64) / 255.0))


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerThread]:
    with web_server(tmp_path_factory.mktemp("web"), scene=SCENE, settings=SETTINGS) as st:
        yield st


def js(driver: Any, script: str, *args: Any) -> Any:
    return driver.execute_script(script, *args)


def open_page(driver: Any, url: str) -> None:
    driver.get("about:blank")
    console_errors(driver)  # drain
    driver.get(url)
    wait_for(lambda: js(driver, "return document.getElementById('conn').dataset.state") == "open",
             20, "the page to connect")


def main_room(live: ServerThread) -> str:
    return live.call(lambda s: s.main_room.id)


def test_page_loads_with_no_console_errors_and_lists_rooms(live: ServerThread, driver) -> None:
    open_page(driver, live.url)
    wait_for(lambda: "main" in driver.find_element("id", "rooms").text, 10, "the room list")
    rooms = driver.find_element("id", "rooms").text
    assert "small" in rooms and "bot-0" in rooms
    # everything came from the game server: no CDN, works offline
    origins = js(driver, """return performance.getEntriesByType('resource')
        .map(e => new URL(e.name).origin)""")
    assert origins and set(origins) == {live.url.rstrip("/")}
    assert js(driver, "return typeof window.clothball") == "object"
    assert console_errors(driver) == []


def test_js_decoder_agrees_with_python_vectors(live: ServerThread, driver) -> None:
    open_page(driver, live.url)
    vectors = json.loads(VECTORS.read_text())
    got = driver.execute_async_script("""
        const vectors = arguments[0], done = arguments[arguments.length - 1];
        (async () => {
          const P = await import('/static/protocol.js');
          const R = await import('/static/replay.js');
          const bytes = (s) => Uint8Array.from(atob(s), (c) => c.charCodeAt(0));
          const nan = (x) => (Number.isNaN(x) ? null : x);
          const norm = (m) => {
            switch (m.kind) {
              case 'HIP': return { kind: m.kind, position: m.position, seq: m.seq, time: m.time };
              case 'CORNER': return { kind: m.kind, frame: m.frame, seat: m.seat,
                position: m.position, velocity: m.velocity, force: m.force,
                stiffness: m.stiffness, ballPosition: m.ballPosition,
                ballVelocity: m.ballVelocity, hipSeq: m.hipSeq, hipTime: nan(m.hipTime),
                serverTime: m.serverTime };
              case 'MESH': return { kind: m.kind, frame: m.frame, serverTime: m.serverTime,
                n: m.n, flags: m.flags, version: m.version, lo: m.lo, hi: m.hi,
                ballPosition: m.ballPosition,
                ballRadius: m.ballRadius, hips: m.hips.flat(),
                positions: Array.from(P.meshPositions(m)) };
              case 'TRACK': return { kind: m.kind, frame: m.frame, serverTime: m.serverTime,
                ballPosition: m.ballPosition, ballVelocity: m.ballVelocity,
                hips: m.hips.flat(), corners: m.corners.flat() };
            }
            return { unknown: m.kind };
          };
          // MESH payloads are inflated by DecompressionStream: decoding is awaited.
          const decode = async (b) => {
            try { return norm(await P.decodeBinary(b)); }
            catch (e) { return { error: e.code || ('uncaught ' + e) }; }
          };
          const binary = [];
          for (const v of vectors.binary) binary.push(await decode(bytes(v.b64)));
          const replay = async (b64) => {
            const rep = await R.parseReplay(bytes(b64));
            const records = [];
            for (const r of rep.records) {
              records.push(r.kind === 0
                ? { record: 0, json: JSON.parse(new TextDecoder().decode(r.data)) }
                : { record: 1, ...(await decode(r.data)) });
            }
            return { header: rep.header, records };
          };
          // today's replay and an old one (version-1 MESH records)
          done({ binary, replay: await replay(vectors.replay.b64),
                 replay_v1: await replay(vectors.replay_v1.b64) });
        })().catch((e) => done({ fatal: String(e && e.stack || e) }));
    """, vectors)
    assert "fatal" not in got, got.get("fatal")
    assert len(got["binary"]) == len(vectors["binary"])
    for v, g in zip(vectors["binary"], got["binary"], strict=True):
        assert g == v["expect"], f"{v['name']}: JS decoded {str(g)[:200]}"
    assert got["replay"]["header"] == vectors["replay"]["header"]
    assert got["replay"]["records"] == vectors["replay"]["records"]
    assert got["replay_v1"] == {"header": vectors["replay_v1"]["header"],
                                "records": vectors["replay_v1"]["records"]}
    assert console_errors(driver) == []


def screenshot_rgb(driver: Any) -> Any:
    from PIL import Image

    return Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB")


def test_live_room_shows_the_cloth(live: ServerThread, driver) -> None:
    rid = main_room(live)
    open_page(driver, f"{live.url}#/room/{rid}")
    wait_for(lambda: js(driver, "return window.clothball.stats.meshFrames") > 5, 20,
             "mesh frames")
    n = SCENE.n
    ij = [[i, j] for i in (n // 4, n // 2, 3 * n // 4) for j in (n // 4, n // 2, 3 * n // 4)]
    js(driver, "window.clothball.freeze(true)")  # the cloth holds still while we look
    # frames drawn after the latest upload: two animation frames of the page's own (its
    # renderer draws on each), waited for instead of a fixed 0.3 s
    driver.execute_async_script("""const done = arguments[arguments.length - 1];
                                   requestAnimationFrame(() => requestAnimationFrame(done));""")
    pts = js(driver, "return window.clothball.screenPoints(arguments[0])", ij)
    img = screenshot_rgb(driver)
    js(driver, "window.clothball.freeze(false)")
    assert pts and all(p is not None for p in pts)
    pixels = [img.getpixel((round(x), round(y))) for x, y in pts]
    hits = [is_cloth(p) for p in pixels]
    if sum(hits) < 6:
        img.save(Path(tempfile.gettempdir()) / "clothball-cloth-test.png")
    assert sum(hits) >= 6, (
        f"cloth colour at only {sum(hits)} of 9 interior nodes: {pixels} at {pts}; "
        f"screenshot in {tempfile.gettempdir()}/clothball-cloth-test.png"
    )
    # the classifier is not fooled by the background: the canvas's top-left corner
    rect = js(driver, "const r = document.getElementById('view').getBoundingClientRect();"
                      "return [r.left, r.top, r.width, r.height]")
    assert not is_cloth(img.getpixel((round(rect[0]) + 3, round(rect[1]) + 3)))
    # corner names and the scoreboard are shown (the labels once the room's state has come)
    wait_for(lambda: sum(e.text.startswith("bot-") for e in driver.find_elements(
        "css selector", "#labels .label")) >= 4, 20, "the corners' labels")
    labels = [e.text for e in driver.find_elements("css selector", "#labels .label")]
    assert len(labels) == 4 and all(lab.startswith("bot-") for lab in labels)
    assert len(driver.find_elements("css selector", "#scoreboard tr.seat")) == 4
    assert console_errors(driver) == []


def test_scoreboard_changes_after_a_bot_scored_round(live: ServerThread, driver) -> None:
    rid = main_room(live)
    open_page(driver, f"{live.url}#/room/{rid}")
    board = lambda: js(driver, "return document.getElementById('scoreboard').dataset.scores")  # noqa: E731
    first = wait_for(board, 10, "the scoreboard")
    wait_for(lambda: board() != first, 30, f"the scores to change from {first}")
    wait_for(lambda: "conceded" in driver.find_element("id", "events").text, 10,
             "a score event in the event list")
    # the shown scores are the server's
    shown = [int(x) for x in board().split(",")]
    assert len(shown) == 4 and all(s >= 0 for s in shown)
    assert console_errors(driver) == []


def test_orbit_camera_follows_drag_and_wheel(live: ServerThread, driver) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    rid = main_room(live)
    open_page(driver, f"{live.url}#/room/{rid}")
    wait_for(lambda: js(driver, "return window.clothball.camera !== null"), 10, "the camera")
    def cam() -> list[float]:
        return js(driver, "const c = window.clothball.camera; return [c.yaw, c.pitch, c.distance]")

    before = cam()
    canvas = driver.find_element("id", "view")
    ActionChains(driver).move_to_element(canvas).click_and_hold().move_by_offset(120, 40) \
        .release().perform()
    after = cam()
    assert after[0] != before[0] and after[1] != before[1] and after[2] == before[2]
    js(driver, """document.getElementById('view').dispatchEvent(new WheelEvent('wheel',
                  {deltaY: 300, bubbles: true, cancelable: true}))""")
    assert cam()[2] > after[2]


def latest_replay(live: ServerThread) -> dict[str, Any]:
    def get() -> list[dict[str, Any]]:
        with urllib.request.urlopen(live.url + "api/replays", timeout=10) as r:
            return json.loads(r.read())["replays"]

    return wait_for(get, 40, "a saved replay")[0]


def test_replay_plays_pauses_and_seeks(live: ServerThread, driver) -> None:
    row = latest_replay(live)
    open_page(driver, live.url)
    # the replay list shows it, filtered by player name and by room
    wait_for(lambda: row["id"] in js(driver, "return [...document.querySelectorAll('#replays li')]"
                                              ".map(li => li.dataset.id).join(' ')"), 10,
             "the replay in the list")
    box = driver.find_element("id", "replay-player")
    box.send_keys("no-such-player")
    wait_for(lambda: "No replay matches" in driver.find_element("id", "replays").text, 5)
    box.clear()
    box.send_keys("bot-2")
    wait_for(lambda: row["id"] in driver.find_element("id", "replays").get_attribute("innerHTML"),
             5)
    driver.find_element("css selector", f'#replays li[data-id="{row["id"]}"] a').click()
    state = lambda: js(driver, "const t = document.getElementById('transport');"  # noqa: E731
                               "return [t.dataset.state, Number(t.dataset.time || -1)]")
    wait_for(lambda: state()[0] == "playing", 20, "the replay to play")
    assert f"#/replay/{row['id']}" in driver.current_url
    t1 = state()[1]
    wait_for(lambda: state()[1] > t1, 10, "the replay's clock to advance")
    # pause: the clock stops
    driver.find_element("id", "play").click()
    wait_for(lambda: state()[0] == "paused", 5, "pause")
    paused_at = state()[1]
    time.sleep(0.4)  # (a fixed wait on purpose: the paused clock does not move in it)
    assert state() == ["paused", paused_at]
    # seek to the middle: the clock and the shown mesh follow
    duration = js(driver, "return window.clothball.replay.duration")
    mesh_before = js(driver, "return window.clothball.shownMesh.frame")
    target = 0.5 * duration if paused_at > 0.6 * duration or paused_at < 0.4 * duration \
        else 0.9 * duration
    js(driver, """const s = document.getElementById('seek'); s.value = arguments[0];
                  s.dispatchEvent(new Event('input', {bubbles: true}));""", target)
    assert abs(state()[1] - target) < 2e-3
    assert state()[0] == "paused"
    frame = js(driver, "return window.clothball.shownMesh.frame")
    assert frame != mesh_before
    t0_frame = js(driver, "return window.clothball.replay.frame0")
    dt = js(driver, "return window.clothball.replay.frameDt")
    assert (frame - t0_frame) * dt <= target + 1e-6
    # between two 30 Hz frames the cloth is drawn as a blend of the two around the time
    nxt = js(driver, """const r = window.clothball.replay;
        const k = r.meshes.findIndex(m => m.frame === arguments[0]);
        return r.meshes[Math.min(k + 1, r.meshes.length - 1)].frame""", frame)
    alpha = js(driver, "return window.clothball.renderer.alpha")
    now = js(driver, "return window.clothball.playback.time")
    want = 0.0 if nxt == frame else (now / dt + t0_frame - frame) / (nxt - frame)
    assert alpha == pytest.approx(want, abs=1e-6)
    # seek to the end: the score event is shown and the scoreboard has the final scores
    js(driver, """const s = document.getElementById('seek'); s.value = s.max;
                  s.dispatchEvent(new Event('input', {bubbles: true}));""")
    assert js(driver, "return document.getElementById('scoreboard').dataset.scores") == \
        ",".join(str(s) for s in row["scores"])
    assert "conceded" in driver.find_element("id", "events").text
    # a replay is one round: its header says "round over", "match over" only if it ended one
    header = driver.find_element("css selector", "#scoreboard .match").text
    ended = js(driver, "return window.clothball.replay.events"
                       ".some((e) => e.msg.event === 'match_end')")
    assert ("match over" in header) == ended and (ended or "round over" in header), header
    # the list's duration is the player's length
    assert row["duration_s"] == pytest.approx(duration, abs=1e-9)
    # speed: 4x plays four times as fast as 1x (loosely: rAF timing is coarse)
    js(driver, """const s = document.getElementById('seek'); s.value = 0;
                  s.dispatchEvent(new Event('input', {bubbles: true}));
                  const v = document.getElementById('speed'); v.value = '4';
                  v.dispatchEvent(new Event('change', {bubbles: true}));""")
    assert js(driver, "return window.clothball.playback.speed") == 4
    # the shareable link opens the same replay, paused at the given time
    share = driver.find_element("id", "share-url").get_attribute("value")
    assert share.endswith(f"#/replay/{row['id']}")
    open_page(driver, f"{share}?t={0.5 * duration:.3f}")
    wait_for(lambda: state()[0] == "paused", 20, "the shared replay to load")
    assert abs(state()[1] - 0.5 * duration) < 2e-3
    assert console_errors(driver) == []


def test_unknown_room_and_replay_get_a_clear_message(live: ServerThread, driver) -> None:
    open_page(driver, f"{live.url}#/room/no-such-room")
    wait_for(lambda: driver.find_element("id", "message").is_displayed(), 10, "the message")
    assert driver.find_element("id", "message-title").text == "No such room"
    text = driver.find_element("id", "message-text").text
    assert '"no-such-room" does not exist' in text
    # a way out: links to the rooms that are live
    rid = main_room(live)
    assert driver.find_element("css selector", f'#message-extra a[href="#/room/{rid}"]')
    open_page(driver, f"{live.url}#/replay/nope-nope-nope")
    wait_for(lambda: driver.find_element("id", "message").is_displayed(), 10, "the message")
    assert driver.find_element("id", "message-title").text == "No such replay"
    # the failed fetch (HTTP 404) is the only console error
    errs = console_errors(driver)
    assert all("404" in e["message"] for e in errs), errs


def test_phone_sized_layout(live: ServerThread) -> None:
    rid = main_room(live)
    d = make_driver(390, 780, mobile=True)
    try:
        open_page(d, f"{live.url}#/room/{rid}")
        wait_for(lambda: js(d, "return window.clothball.stats.meshFrames") > 2, 20, "meshes")
        width = js(d, "return window.innerWidth")
        assert js(d, "return document.documentElement.scrollWidth") <= width
        canvas = js(d, "const r = document.getElementById('view').getBoundingClientRect();"
                       "return [r.left, r.top, r.width, r.height]")
        board = js(d, "const r = document.getElementById('scoreboard').getBoundingClientRect();"
                      "return [r.left, r.top, r.width, r.height]")
        assert canvas[2] >= width - 1 and canvas[3] > 250  # the view spans the screen
        assert board[1] >= canvas[1] + canvas[3] - 1  # the scoreboard is below it
        assert board[2] <= width
        # touch: a one-finger drag orbits, a two-finger pinch zooms
        before = js(d, "const c = window.clothball.camera; return [c.yaw, c.distance]")
        js(d, """const v = document.getElementById('view');
          const ev = (type, id, x, y) => v.dispatchEvent(new PointerEvent(type, {pointerId: id,
            pointerType: 'touch', clientX: x, clientY: y, bubbles: true, cancelable: true}));
          ev('pointerdown', 1, 100, 200); ev('pointermove', 1, 160, 210);
          ev('pointerup', 1, 160, 210);
          ev('pointerdown', 2, 150, 200); ev('pointerdown', 3, 250, 200);
          ev('pointermove', 2, 120, 200); ev('pointermove', 3, 280, 200);
          ev('pointerup', 2, 120, 200); ev('pointerup', 3, 280, 200);""")
        after = js(d, "const c = window.clothball.camera; return [c.yaw, c.distance]")
        assert after[0] != before[0]
        assert after[1] < before[1]  # fingers apart: closer
        assert console_errors(d) == []
    finally:
        d.quit()


def test_reconnects_with_backoff_after_a_server_restart(tmp_path, driver) -> None:
    st = web_server(tmp_path, scene=SCENE, settings=SETTINGS, bots=0).start()
    port = st.port
    try:
        rid = st.call(lambda s: s.main_room.id)
        open_page(driver, f"{st.url}#/room/{rid}")
        wait_for(lambda: js(driver, "return window.clothball.stats.meshFrames") > 0, 20,
                 "meshes")
        st.stop()
        conn = lambda: js(driver, "return document.getElementById('conn').dataset.state")  # noqa: E731
        wait_for(lambda: conn() == "reconnecting", 10, "the page to notice")
        assert driver.find_element("id", "notice").is_displayed()
        wait_for(lambda: "retrying in" in driver.find_element("id", "conn-text").text, 10,
                 "the backoff countdown")
        st = web_server(tmp_path, scene=SCENE, settings=SETTINGS, bots=0, port=port).start()
        wait_for(lambda: conn() == "open", 30, "the page to reconnect")
        assert not driver.find_element("id", "notice").is_displayed()
        # the restarted server's permanent room has the same id: the page resumes it
        assert st.call(lambda s: s.main_room.id) == rid
        before = js(driver, "return window.clothball.stats.meshFrames")
        wait_for(lambda: js(driver, "return window.clothball.stats.meshFrames") > before, 20,
                 "meshes from the restarted room")
        assert js(driver, "return window.clothball.room") == rid
        assert not driver.find_element("id", "message").is_displayed()
        errs = [e for e in console_errors(driver) if "WebSocket" not in e["message"]]
        assert errs == []  # only the failed reconnect attempts are logged
    finally:
        st.stop()


def test_bench_module_measures_decode_and_upload(live: ServerThread, driver) -> None:
    """tests/web/web_bench.py's in-page part runs (what it measures is reported, not asserted)."""
    import base64

    from tests.web.web_vectors import messages

    frames = [base64.b64encode(d).decode() for name, d in messages()
              if name in ("mesh_n16_zlib", "mesh_n16_raw")]
    open_page(driver, live.url)
    r = driver.execute_async_script("""
        const [frames, done] = arguments;
        import('/static/bench.js').then((m) => m.benchDecodeUpload(frames,
          {batch: 2, repeats: 1})).then(done).catch((e) => done({error: String(e.stack || e)}));
    """, frames)
    assert "error" not in r, r.get("error")
    assert r["n"] == 16 and r["frames"] == 2
    for stage in ("decode", "upload", "decodeUpload", "decodeUploadFinish"):
        assert r[stage]["count"] == 2 and 0 <= r[stage]["median"] < 1000
    assert console_errors(driver) == []


def test_phone_banner_keeps_names_whole_under_the_corner_labels(live: ServerThread,
                                                                driver) -> None:
    """On a phone-sized page the match-over banner wraps between words, never inside a
    name such as "bot-2", and the corner labels stay above it (drawn over, not hidden)."""
    size = driver.get_window_size()
    driver.set_window_size(390, 844)
    try:
        rid = main_room(live)
        open_page(driver, f"{live.url}#/room/{rid}")
        wait_for(lambda: len(driver.find_elements("css selector", "#labels .label")) == 4, 20,
                 "corner labels")
        names = ["bot-0-with-a-long-name", "bot-2-with-a-long-name"]
        js(driver, "window.clothball.banner(arguments[0], 'end', 0)",
           f"match over: {names[0]} & {names[1]} won (5–3–1–0)")
        lines = js(driver, """
            const b = document.getElementById('banner'), t = b.firstChild, s = t.data;
            return arguments[0].map((n) => {
              const k = Math.max(s.indexOf(n), s.indexOf(n.replace(/-/g, '\\u2011')));
              if (k < 0) return -1;
              const r = document.createRange(); r.setStart(t, k); r.setEnd(t, k + n.length);
              return new Set([...r.getClientRects()].map((q) => Math.round(q.top))).size;
            });""", names)
        assert lines == [1, 1], f"a name split over lines: {lines}"
        z = js(driver, """const z = (id) =>
                            Number(getComputedStyle(document.getElementById(id)).zIndex);
                          return [z('labels'), z('banner')]""")
        assert z[0] > z[1]
    finally:
        driver.set_window_size(size["width"], size["height"])


def test_lobby_says_which_corner_a_human_can_take(live: ServerThread, driver) -> None:
    """Each live room says which corners a human may take (the server's ``open`` seats:
    empty ones and bots', bots being backfill) and the command that takes one."""
    open_page(driver, live.url)
    hint = wait_for(lambda: driver.find_element("css selector", "#rooms .seat-hint").text,
                    10, "the seat hint")
    info = live.call(lambda s: s.main_room.info())
    open_seats = [s for s in info["seats"] if s["open"]]
    assert open_seats, info["seats"]  # the bots' room: every corner is a bot's
    assert hint.startswith("To play, take a corner:")
    for s in open_seats:
        assert f"{s['edge']} ({s['name']}, a bot, makes way)" in hint, hint
    ws = live.url.replace("http://", "ws://").rstrip("/") + "/ws"
    assert (f"clothball play --server {ws} --room {info['id']} --seat "
            f"{open_seats[0]['seat']}") in hint, hint
    assert console_errors(driver) == []


def test_one_palette_for_both_clients(live: ServerThread, driver) -> None:
    """The page's seat colours (scoreboard swatches) and scene colours are the desktop
    window's: both read assets/web/palette.json."""
    from clothball.game.client.interp import BALL_COLOUR, CLOTH_BACK, CLOTH_FRONT, SEAT_COLOURS

    rid = main_room(live)
    open_page(driver, f"{live.url}#/room/{rid}")
    wait_for(lambda: len(driver.find_elements("css selector", "#scoreboard .swatch")) == 4, 10,
             "the scoreboard")
    swatches = js(driver, """return [...document.querySelectorAll('#scoreboard .swatch')]
        .map(e => getComputedStyle(e).backgroundColor)""")
    want = [f"rgb({', '.join(str(round(v * 255)) for v in c)})" for c in SEAT_COLOURS]
    assert swatches == want
    page = js(driver, """return import('/static/render.js').then(m => m.PALETTE)""")
    rgb = lambda hx: tuple(int(hx[k:k + 2], 16) / 255 for k in (1, 3, 5))  # noqa: E731
    assert np.allclose([rgb(page[k]) for k in ("cloth_front", "cloth_back", "ball")],
                       [CLOTH_FRONT, CLOTH_BACK, BALL_COLOUR])


def test_lobby_names_the_round_a_countdown_leads_to(tmp_path, driver) -> None:
    """Between rounds a room counts down to the next one: with round 1 over (and in the
    replay list), the lobby says "countdown · round 2", not round 1 again."""
    settings = RoomSettings(autoplay=True, first_to=3, countdown=8.0, reset_speed=1.5,
                            restart_delay=1.0)

    def api(st: ServerThread, path: str) -> Any:
        with urllib.request.urlopen(st.url + path, timeout=10) as r:
            return json.loads(r.read())

    with web_server(tmp_path, scene=SCENE, settings=settings) as st:
        def between() -> bool:
            room = api(st, "api/rooms")["rooms"][0]
            saved = [r["round"] for r in api(st, "api/replays")["replays"]]
            return room["state"] == "countdown" and room["round"] == 1 and saved == [1]

        wait_for(between, 60, "round 1 played and saved, the room counting down", poll=0.2)
        open_page(driver, st.url)
        line = wait_for(lambda: driver.find_element("css selector", "#rooms li.room").text,
                        5, "the room in the lobby")
        replays = wait_for(lambda: driver.find_element("id", "replays").text, 5, "the replays")
        assert "round 1" in replays
        assert "countdown · round 2" in line, line
        assert console_errors(driver) == []
