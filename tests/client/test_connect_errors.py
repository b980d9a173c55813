"""A connection that fails says what happened and what to do, in a line, with no traceback:
nothing listening (retried, then a Retry button), no answer, the wrong scheme or path, a
server that refuses, a protocol version mismatch. Against real sockets and real servers:
``explain_connect_error`` on what ``NetClient.connect`` raises, the terminal of
``clothball play`` and the window (pyglet under Xvfb, in a subprocess, as in
``test_client_window``)."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run as a script too

from clothball.game.net.client import NetClient, explain_connect_error  # noqa: E402
from clothball.server.limits import Limits  # noqa: E402
from clothball.server.thread import ServerThread  # noqa: E402

from tests.client.test_client_window import display  # noqa: E402,F401  (fixture)
from tests.server.conftest import TINY, local_server  # noqa: E402


def closed_port() -> int:
    """A loopback port nothing listens on (bound, then let go)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def server_on(data: Path, **kw: object) -> ServerThread:
    """A server (not started) with ``kw`` for ``GameServer``: a port, limits."""
    return ServerThread(data, scenes={TINY.name: TINY}, backend="cpu", **kw)


def failure(url: str, timeout: float = 5.0, **hello: object) -> tuple[str, bool]:
    async def go() -> BaseException:
        try:
            client = await NetClient.connect(url, timeout=timeout, **hello)
        except Exception as e:  # noqa: BLE001 - the failure is what the test looks at
            return e
        await client.close()
        raise AssertionError(f"{url} connected")

    return explain_connect_error(url, asyncio.run(go()))


def test_nothing_listening_says_how_to_start_a_server() -> None:
    port = closed_port()
    text, again = failure(f"ws://127.0.0.1:{port}/ws")
    assert f"nothing is listening at 127.0.0.1:{port}" in text
    assert "clothball host" in text and "--server" in text
    assert again  # a server that is not up yet may be soon


def test_a_silent_port_times_out_with_a_hint() -> None:
    with socket.socket() as s:  # accepts connections and never answers
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        text, again = failure(f"ws://127.0.0.1:{port}/ws", timeout=0.5)
    assert f"no answer from 127.0.0.1:{port}" in text and "firewall" in text
    assert again


def test_wrong_scheme_wrong_path_version_and_refusal(tmp_path) -> None:
    with local_server(tmp_path / "a") as st:
        host = f"127.0.0.1:{st.port}"
        text, again = failure(f"wss://{host}/ws")
        assert "does not speak TLS" in text and f"try ws://{host}/ws" in text and not again
        text, again = failure(f"ws://{host}/")  # the page, not the game's websocket
        assert f"no game at ws://{host}/" in text and f"ws://{host}/ws" in text
        assert not again
        # a client of another protocol version (what hello says is all the server sees)
        text, again = failure(f"ws://{host}/ws", version=2)
        assert "version mismatch" in text and "this server speaks 1" in text
        assert "clothball version" in text and not again
    with server_on(tmp_path / "b", limits=Limits(max_clients=0)) as st:
        text, again = failure(st.ws_url)
        assert text.startswith("the server refused: server full") and "HTTP 503" in text


def play(*args: str, screen: str, prelude: str = "") -> subprocess.CompletedProcess[str]:
    """``clothball play`` in a window on X display ``screen``; ``prelude``: Python run first."""
    code = (f"{prelude}\nimport sys\nfrom clothball.game.cli import main\n"
            f"sys.exit(main({['play', *args]!r}))")
    env = {**os.environ, "DISPLAY": screen}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env=env)


def assert_said(r: subprocess.CompletedProcess[str], *needles: str) -> None:
    assert "Traceback" not in r.stderr + r.stdout, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("clothball play:")]
    for needle in needles:
        assert any(needle in ln for ln in lines), r.stderr


def test_play_on_the_terminal(tmp_path, display) -> None:  # noqa: F811
    port = closed_port()
    r = play("--server", f"ws://127.0.0.1:{port}/ws", "--quit-after", "2", screen=display)
    assert_said(r, f"nothing is listening at 127.0.0.1:{port}", "retrying")
    with local_server(tmp_path) as st:
        r = play("--server", st.ws_url.replace("ws://", "wss://"), "--quit-after", "3",
                 screen=display)
        assert r.returncode == 1
        assert_said(r, "does not speak TLS", "press Enter (Retry)")
        # a newer client against this server
        r = play("--server", st.ws_url, "--quit-after", "3", screen=display,
                 prelude="import clothball.game.wire.protocol as P; P.PROTOCOL_VERSION = 2")
        assert r.returncode == 1
        assert_said(r, "version mismatch: this client speaks protocol 2", "speaks 1")


def test_window_shows_the_failure_and_retries(tmp_path, display) -> None:  # noqa: F811
    env = {**os.environ, "DISPLAY": display, "PYTHONUNBUFFERED": "1"}
    r = subprocess.run([sys.executable, __file__, "--driver", str(tmp_path)], env=env,
                       capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    port = out["port"]
    # while retrying, then after giving up: the reason in the window, a Retry button
    assert any(s == "retrying" for s, _ in out["states"]), out["states"]
    assert out["failed_title"] == "clothball - cannot connect"
    assert f"nothing is listening at 127.0.0.1:{port}" in out["failed_hud"]
    assert "Enter" in out["failed_hud"] and out["failed_buttons"] == ["Retry (Enter)"]
    # the terminal's lines (report) say the same, no more than a few
    assert out["said"][0].startswith(f"nothing is listening at 127.0.0.1:{port}")
    assert any(s.startswith("gave up after 2 tries") for s in out["said"]), out["said"]
    assert len(out["said"]) <= 4
    # Enter, once the server is up on that port: connected, its room listed
    assert out["after_retry"] == "connected" and out["rooms"] >= 1


def driver(data: Path) -> int:
    """The window against a port where nothing listens; once it has given up, a server
    starts there and Enter connects. Prints what the window showed, as JSON."""
    import time

    import pyglet
    from clothball.game.client.app import ClientWindow
    from clothball.game.client.netthread import NetThread

    port = closed_port()
    said: list[str] = []
    net = NetThread(f"ws://127.0.0.1:{port}/ws", reconnect_tries=1, report=said.append)
    net.start()
    w = ClientWindow(net=net, width=960, height=600, vsync=False)
    out: dict = {"port": port, "states": []}

    def tick_until(pred, what: str, timeout: float = 60) -> None:
        end = time.monotonic() + timeout
        while not pred():
            if time.monotonic() > end:
                raise SystemExit(f"driver: timed out waiting for {what}: {out}")
            w.update(0.05)
            w.switch_to()
            w.on_draw()
            w.dispatch_events()
            state = (w.model.connection, w.model.detail)
            if not out["states"] or out["states"][-1] != list(state):
                out["states"].append(list(state))
            time.sleep(0.02)

    tick_until(lambda: w.model.connection == "failed", "the failure")
    out["failed_title"] = w.title_label.text
    out["failed_hud"] = w.hud.text
    out["failed_buttons"] = [lb.text for lb in w._ui_labels]
    server = server_on(data, port=port).start()
    try:
        w.dispatch_event("on_key_press", pyglet.window.key.ENTER, 0)
        tick_until(lambda: w.model.connection == "connected" and w.model.rooms, "the retry")
        out["after_retry"] = w.model.connection
        out["rooms"] = len(w.model.rooms)
    finally:
        out["said"] = said
        w.close()
        net.stop()
        server.stop()
    print(json.dumps(out))
    return 0


if __name__ == "__main__" and "--driver" in sys.argv:
    sys.exit(driver(Path(sys.argv[-1])))
