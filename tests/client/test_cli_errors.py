"""A bad command line gets one or two lines saying what was wrong and what to do, never a
traceback: ports out of range, a match length out of range, an http:// server address, an
unknown replay id, no display."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests.conftest import needs_usb_transport
from tests.server.conftest import local_server


def clothball(*args: str, env: dict[str, str] | None = None,
              timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "clothball.game.cli", *args],
                          capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


def assert_short_error(r: subprocess.CompletedProcess[str], *needles: str) -> None:
    assert r.returncode != 0
    assert "Traceback" not in r.stderr and "Traceback" not in r.stdout, r.stderr
    for needle in needles:
        assert needle in r.stderr, r.stderr


@pytest.mark.parametrize("port", ["99999", "-1", "http"])
def test_host_refuses_a_port_out_of_range(port: str) -> None:
    r = clothball("host", "--port", port)
    assert_short_error(r, "--port", "0..65535")


@pytest.mark.parametrize("cmd", ["host", "play"])
@pytest.mark.parametrize("value", ["0", "100", "-3"])
def test_first_to_out_of_range_is_refused_not_clamped(cmd: str, value: str) -> None:
    r = clothball(cmd, "--first-to", value)
    assert_short_error(r, "--first-to", "1..99", value)


def test_play_says_the_server_address_is_a_websocket() -> None:
    r = clothball("play", "--server", "http://127.0.0.1:8765/")
    assert_short_error(r, "--server", "ws://127.0.0.1:8765/ws")


def test_play_without_a_display_says_what_to_do() -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    r = subprocess.run([sys.executable, "-m", "clothball.game.cli", "play", "--server",
                        "ws://127.0.0.1:9/ws"], capture_output=True, text=True, timeout=60,
                       env=env)
    assert_short_error(r, "no display", "xvfb-run", "browser")


def test_an_unknown_replay_id_says_how_to_list_them(tmp_path) -> None:
    with local_server(tmp_path) as st:
        r = clothball("replay", "nosuchround", "--server", st.ws_url)
    assert_short_error(r, "no replay 'nosuchround'", "clothball replay --server")


@needs_usb_transport
def test_falcon_check_without_a_device_points_to_the_emulator() -> None:
    r = clothball("falcon", "check")
    if "Falcon check: OK" in r.stdout:
        pytest.skip("a Falcon is plugged in here")
    assert_short_error(r, "no Novint Falcon found", "clothball falcon check --emulator")
