"""Firmware handshake and upload against the emulator, and the errors a user sees."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from clothball._native import falcon as f
from clothball.game.devices import falcon as F

from tests.conftest import needs_usb_transport


def emulator(**kw: object) -> f.EmulatorTransport:
    o = f.EmulatorOptions()
    for k, v in kw.items():
        setattr(o, k, v)
    return f.EmulatorTransport(o)


def fast(**kw: int) -> f.FirmwareOptions:
    o = f.FirmwareOptions()
    o.reply_timeout_ms = 2
    o.echo_timeout_ms = 5
    for k, v in kw.items():
        setattr(o, k, v)
    return o


@pytest.fixture
def image() -> bytes:
    # Stand-in bytes: the emulator accepts any image. Not a multiple of the 62-byte chunk.
    return os.urandom(8500)


def test_fresh_device_has_no_firmware() -> None:
    assert not f.firmware_loaded(emulator())
    assert f.firmware_loaded(emulator(firmware_loaded=True))


def test_handshake_and_upload(image: bytes) -> None:
    emu = emulator()
    assert f.load_firmware(emu, image, fast()) == 1
    st = emu.state()
    assert st["firmware_loaded"] and st["handshakes"] == 1 and st["uploads"] == 1
    assert emu.uploaded() == image  # every chunk arrived, in order
    assert f.firmware_loaded(emu)  # and it answers packets in normal mode now


def test_handshake_retries_until_answered(image: bytes) -> None:
    emu = emulator(handshake_failures=7)
    assert f.load_firmware(emu, image, fast(handshake_tries=10)) == 1
    assert emu.state()["handshakes"] == 8


def test_no_handshake_answer_exhausts_retries(image: bytes) -> None:
    emu = emulator(handshake_failures=10_000)
    with pytest.raises(f.FirmwareLoadError) as e:
        f.load_firmware(emu, image, fast(handshake_tries=5, attempts=3))
    assert "after 3 attempts" in str(e.value) and "handshake" in str(e.value)
    assert emu.state()["handshakes"] == 15


def test_rejected_echo_is_retried_then_succeeds(image: bytes) -> None:
    emu = emulator(rejected_uploads=2)
    assert f.load_firmware(emu, image, fast(attempts=5)) == 3
    assert emu.state()["firmware_loaded"]


def test_rejected_echo_on_every_attempt(image: bytes) -> None:
    emu = emulator(rejected_uploads=-1)
    with pytest.raises(f.FirmwareLoadError) as e:
        f.load_firmware(emu, image, fast(attempts=4))
    msg = str(e.value)
    assert "after 4 attempts" in msg and "rejected the firmware" in msg and "hub" in msg
    assert emu.state()["uploads"] == 4 and not emu.state()["firmware_loaded"]


def test_firmware_load_error_is_a_falcon_error() -> None:
    assert issubclass(f.FirmwareLoadError, f.FalconError)
    assert issubclass(f.FalconError, RuntimeError)


def test_driver_loads_only_when_needed(image: bytes, tmp_path: Path) -> None:
    fw = tmp_path / "nvent.bin"
    fw.write_bytes(image)
    d = f.Driver(emulator(firmware_loaded=True))
    assert d.ensure_firmware("") == 0  # already running: no file needed
    emu = emulator()
    d = f.Driver(emu)
    assert d.ensure_firmware(str(fw), fast()) == 1
    assert emu.uploaded() == image


def test_missing_firmware_file(tmp_path: Path) -> None:
    d = f.Driver(emulator())
    with pytest.raises(f.FirmwareError, match="not found"):
        d.ensure_firmware(str(tmp_path / "nope.bin"))
    with pytest.raises(f.FirmwareError, match="--firmware"):
        d.ensure_firmware("")
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    with pytest.raises(f.FirmwareError, match="empty"):
        d.ensure_firmware(str(empty))


def test_open_falcon_errors_name_the_fix(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(F.FIRMWARE_ENV, raising=False)
    monkeypatch.setattr(F, "config_path", lambda: tmp_path / "none.toml")
    opts = f.EmulatorOptions()  # firmware not loaded
    with pytest.raises(F.FirmwareError, match="no firmware file was given"):
        F.open_falcon(emulator=True, emulator_options=opts)


def test_firmware_from_env_and_config(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                      image: bytes) -> None:
    fw = tmp_path / "fw.bin"
    fw.write_bytes(image)
    cfg = tmp_path / "config.toml"
    cfg.write_text(f'[falcon]\nfirmware = "{fw}"\n')
    monkeypatch.setattr(F, "config_path", lambda: cfg)
    monkeypatch.delenv(F.FIRMWARE_ENV, raising=False)
    assert F.configured_firmware() == str(fw)
    monkeypatch.setenv(F.FIRMWARE_ENV, "/elsewhere.bin")
    assert F.configured_firmware() == "/elsewhere.bin"
    monkeypatch.delenv(F.FIRMWARE_ENV)
    dev = F.open_falcon(emulator=True, emulator_options=f.EmulatorOptions(),
                        firmware_options=fast())
    try:
        assert dev.emulator.uploaded() == image
    finally:
        dev.stop()


@needs_usb_transport
def test_no_usb_device_error_is_actionable() -> None:
    if f.count_usb_devices() > 0:
        pytest.skip("a real Falcon is plugged in")
    with pytest.raises(f.NoDeviceError, match="0403:cb48"):
        f.open_usb_transport()


def test_udev_rule_grants_the_falcon() -> None:
    assert 'ATTRS{idVendor}=="0403"' in F.UDEV_RULE
    assert 'ATTRS{idProduct}=="cb48"' in F.UDEV_RULE
