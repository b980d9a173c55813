"""A bad command line gets one or two lines saying what was wrong and what to do, never a
traceback: ports out of range, a match length out of range, an http:// server address, an
unknown replay id, no display."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from clothball.game import cuda_unavailable_reason
from clothball.game.sim.scene import available
from clothball.server.hostproc import free_port

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


@pytest.mark.parametrize("source", [None, "20250101-120000-abcd"])
def test_replay_with_no_server_says_so_as_play_does(source: str | None) -> None:
    """Nothing listening at --server: the address and what to do, in play's words, not
    urllib's ``urlopen error``."""
    server = f"ws://127.0.0.1:{free_port()}/ws"
    r = clothball("replay", *([source] if source else []), "--server", server)
    where = server[len("ws://"):-len("/ws")]
    assert_short_error(r, f"nothing is listening at {where}", "clothball host", "--server")
    assert "urlopen" not in r.stderr, r.stderr


@needs_usb_transport
def test_falcon_check_without_a_device_points_to_the_emulator() -> None:
    r = clothball("falcon", "check")
    if "Falcon check: OK" in r.stdout:
        pytest.skip("a Falcon is plugged in here")
    assert_short_error(r, "no Novint Falcon found", "clothball falcon check --emulator")
    assert r.returncode == 2  # a FalconError's status (docs/falcon.md)


def test_a_command_whose_module_fails_to_import_says_what_to_install() -> None:
    """A dependency missing (here websockets, blocked before the CLI imports it) makes the
    command unavailable, saying which import failed and what to install, whatever options
    follow: they are not refused as unrecognised first."""
    code = ("import sys; sys.modules['websockets'] = None\n"
            "from clothball.game.cli import main\n"
            "sys.exit(main(['bench', '--load', '--server-backend', 'cuda']))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2
    assert_short_error(r, "clothball bench: not available", "'websockets",
                       "pip install websockets")
    assert "unrecognized arguments" not in r.stderr, r.stderr
    # a command that imports still refuses an option it does not have
    r = clothball("scenes", "--no-such-option")
    assert_short_error(r, "unrecognized arguments: --no-such-option")


needs_no_cuda = pytest.mark.skipif(not cuda_unavailable_reason(),
                                   reason="the CUDA backend is available here")


@needs_no_cuda
def test_bench_load_on_cuda_without_cuda_is_one_clear_line() -> None:
    r = clothball("bench", "--load", "--server-backend", "cuda")
    assert_short_error(r, "--server-backend cuda", "no CUDA backend")
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr


@needs_no_cuda
def test_bench_on_cuda_without_cuda_says_why_truly() -> None:
    """The reason is the build's own, and true of this machine: a build that skipped CUDA
    for want of nvcc or of a GPU says which (checked against this machine, where the
    module was built), never "on a machine with nvcc" where nvcc is."""
    r = clothball("bench", "--backends", "cuda", "--quick")
    why = cuda_unavailable_reason()
    assert_short_error(r, "--backends", why)
    nvcc_here = shutil.which("nvcc") is not None or Path("/usr/local/cuda/bin/nvcc").exists()
    if nvcc_here:
        assert "machine with nvcc" not in why, why
    if "no CUDA compiler (nvcc) was found" in why:
        assert not nvcc_here, why
    if "saw no GPU" in why:
        gpu = shutil.which("nvidia-smi") is not None and subprocess.run(
            ["nvidia-smi", "-L"], capture_output=True, timeout=60).returncode == 0
        assert not gpu, why
    assert any(s in why for s in ("CLOTHBALL_CUDA=OFF", "no CUDA compiler (nvcc) was found",
                                  "saw no GPU")), why


def test_host_with_an_unknown_scene_lists_the_scenes_once() -> None:
    r = clothball("host", "--scene", "nope", "--port", "0")
    out = r.stdout + r.stderr
    assert r.returncode != 0 and "Traceback" not in out, out
    assert "scene 'nope': no such scene" in out, out
    for name in available():
        assert out.count(name) == 1, out
