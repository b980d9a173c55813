"""The driver loop against the emulator: homing, force rendering, stale fade, unplugging,
the 1 kHz thread (behaviour, not speed), FalconDevice and the CLI."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
from clothball._native import falcon as f
from clothball.game.cli import falcon as falcon_cmd
from clothball.game.devices import Device, Reach
from clothball.game.devices import falcon as F
from clothball.game.devices.base import CornerState

KIN = f.Kinematics()
DT = 1e-3
CENTRE = [0.0, 0.0, 0.125]


def options(**kw: object) -> f.EmulatorOptions:
    o = f.EmulatorOptions()
    o.firmware_loaded = True
    o.home_after_packets = 20
    for k, v in kw.items():
        setattr(o, k, v)
    return o


def emulator(**kw: object) -> f.EmulatorTransport:
    return f.EmulatorTransport(options(**kw))


def stepped(emu: f.EmulatorTransport, ticks: int, t0: float = 0.0,
            driver: f.Driver | None = None) -> tuple[f.Driver, dict, float]:
    d = driver or f.Driver(emu)
    snap: dict = {}
    t = t0
    for _ in range(ticks):
        snap = d.step(t)
        t += DT
    return d, snap, t


def test_homing_then_green_and_tracking() -> None:
    emu = emulator()
    d, snap, _ = stepped(emu, 10)
    assert snap["homed"] != 7 and emu.state()["flags"] & f.FLAG_HOMING
    assert snap["motor"] == [0, 0, 0]  # no forces before homing
    emu.set_position([0.012, -0.02, 0.14])
    d, snap, _ = stepped(emu, 40, driver=d)
    assert snap["homed"] == 7 and emu.state()["flags"] == f.FLAG_GREEN
    # Forward kinematics of the quantised encoders: within a count's worth of the truth.
    np.testing.assert_allclose(snap["position"], emu.state()["position"], atol=2e-4)


def test_renders_the_coupling_force_with_the_right_sign_and_size() -> None:
    emu = emulator()
    d, _, t = stepped(emu, 30)
    K, user_k = 400.0, 200.0
    corner, target = np.array(CENTRE), np.array([0.015, -0.01, 0.135])
    emu.set_user(target.tolist(), user_k, 5.0)
    for _ in range(3000):
        d.set_corner_at(corner.tolist(), [0, 0, 0], [K] * 3, [2.0] * 3, t)
        snap = d.step(t)
        t += DT
    # At rest the user's spring balances the coupling: h = (k_u target + K c) / (k_u + K).
    h_eq = (user_k * target + K * corner) / (user_k + K)
    h = np.array(snap["position"])
    np.testing.assert_allclose(h, h_eq, atol=3e-4)
    force = np.array(snap["force"])
    np.testing.assert_allclose(force, -K * (h - corner), atol=0.02)
    assert np.all(np.sign(force) == -np.sign(h_eq - corner))  # pulled back to the corner
    # The motor commands are the Jacobian-transpose torques of that force.
    tau = KIN.torques(snap["position"], snap["force"])
    assert snap["motor"] == list(f.torques_to_motors(tau))
    # And the emulated motors push on the grip with that force.
    np.testing.assert_allclose(emu.state()["motor_force"], force, atol=0.02)


def test_stale_corner_fades_the_motors_out_and_back() -> None:
    emu = emulator()
    d, _, t = stepped(emu, 30)
    emu.set_user([0.02, 0.0, 0.125], 300.0, 5.0)
    corner = CENTRE
    history = []
    # Fresh updates for 0.5 s, then none for 0.4 s, then fresh again for 0.5 s.
    for k in range(1400):
        if k < 500 or k >= 900:
            d.set_corner_at(corner, [0, 0, 0], [500.0] * 3, [0.0] * 3, t)
        snap = d.step(t)
        history.append((k, snap["gain"], np.abs(snap["motor"]).max(), snap["age"]))
        t += DT
    by_k = {k: (g, m, a) for k, g, m, a in history}
    cfg = f.CouplingConfig()
    assert by_k[499][0] == 1.0 and by_k[499][1] > 100
    stale_until = 500 + int((cfg.stale_after + cfg.fade_out) / DT) + 3
    for k in range(stale_until, 900):
        assert by_k[k][0] == 0.0 and by_k[k][1] == 0  # faded out: motors idle
    assert by_k[1399][0] == 1.0 and by_k[1399][1] > 100  # restored
    gains = [by_k[k][0] for k in range(900, 1400)]
    assert all(b >= a for a, b in zip(gains, gains[1:], strict=False))  # smoothly back up


def test_homing_timeout_says_what_to_do() -> None:
    d = f.Driver(emulator(home_after_packets=-1))
    with pytest.raises(f.HomingTimeoutError, match="pull the Falcon's grip all the way out"):
        d.home(0.1)


def test_thread_loop_runs_and_pulls_the_hand_to_the_corner() -> None:
    emu = emulator()
    d = f.Driver(emu)
    d.home(2.0)
    emu.set_position([0.02, 0.01, 0.14])
    corner = [0.0, 0.0, 0.12]
    d.set_corner(corner, [0, 0, 0], [300.0] * 3, [3.0] * 3, 0.0)
    d.start()
    try:
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            time.sleep(0.05)
            d.set_corner(corner, [0, 0, 0], [300.0] * 3, [3.0] * 3, 0.0)
            if np.linalg.norm(np.array(emu.state()["position"]) - corner) < 1e-3:
                break
        snap, stats = d.snapshot(), d.stats()
    finally:
        d.stop()
    assert snap["running"] and snap["error"] is None
    assert np.linalg.norm(np.array(emu.state()["position"]) - corner) < 1e-3
    assert stats["ticks"] > 100 and stats["missed_replies"] == 0
    assert emu.state()["packets"] >= stats["ticks"]
    assert stats["period_p50"] > 0 and stats["rate"] > 0  # measured (not asserted as timing)
    assert not d.running and emu.state()["motor"] == [0, 0, 0]  # motors off after stop


def test_noisy_fragmented_line_is_resynchronised() -> None:
    emu = emulator(fragment=True, seed=7)
    d, snap, t = stepped(emu, 300)
    assert snap["homed"] == 7 and snap["ticks"] == 300
    assert d.stats()["dropped_bytes"] > 0  # the line noise was seen and thrown away
    emu.set_position([0.01, 0.01, 0.11])
    d, snap, _ = stepped(emu, 5, t0=t, driver=d)
    np.testing.assert_allclose(snap["position"], [0.01, 0.01, 0.11], atol=2e-4)


def test_unplugged_mid_game_the_corner_rests(caplog: pytest.LogCaptureFixture) -> None:
    dev = F.open_falcon(emulator=True, emulator_options=options())
    reach = Reach(np.array([0.5, 0.3, -0.5]), np.array([0.15, 0.15, 0.15]))
    dev.start(reach)
    try:
        dev.emulator.set_user(dev.mapping.to_device(reach.centre + [0.1, 0.0, 0.0]).tolist(),
                              300.0, 5.0)
        time.sleep(0.3)  # (a fixed wait: the hand settles; its move is waited for below)
        deadline = time.monotonic() + 10.0  # the hand moved: waited for, however slowly
        while (before := dev.hand_position())[0] <= reach.centre[0] + 0.05 \
                and time.monotonic() < deadline:
            time.sleep(0.01)
        assert before[0] > reach.centre[0] + 0.05
        dev.emulator.unplug()
        deadline = time.monotonic() + 2.0
        while dev.error is None and time.monotonic() < deadline:
            time.sleep(0.01)
        with caplog.at_level(logging.WARNING):
            rest = dev.hand_position()
        assert dev.error is not None and "unplugged" in dev.error
        assert np.linalg.norm(rest - before) < 0.01  # rests where it was
        np.testing.assert_array_equal(dev.hand_position(), rest)
        dev.update_corner(CornerState(position=reach.centre, stiffness=1000.0,
                                      received_at=time.monotonic()))  # ignored, no raise
    finally:
        dev.stop()
        dev.stop()  # safe twice


def test_falcon_device_mapping_and_stiffness_scaling() -> None:
    reach = Reach(np.array([1.0, 0.4, -1.0]), np.array([0.3, 0.15, 0.3]))
    m = F.FalconMapping(reach)
    np.testing.assert_allclose(m.to_world(F.CUBE_CENTRE), reach.centre)
    np.testing.assert_allclose(m.to_world(F.CUBE_HI), reach.centre + reach.half_extent)
    np.testing.assert_allclose(m.to_world(F.CUBE_LO), reach.centre - reach.half_extent)
    p = np.array([0.01, -0.02, 0.1])
    np.testing.assert_allclose(m.to_device(m.to_world(p)), p, atol=1e-15)
    np.testing.assert_allclose(m.scale, reach.half_extent / F.CUBE_HALF)
    flipped = F.FalconMapping(reach, (1.0, 1.0, -1.0))
    assert flipped.to_world(F.CUBE_HI)[2] == pytest.approx(reach.centre[2] - 0.3)

    # Through the device: a world K over a world offset -> the device force.
    settings = F.FalconSettings(max_stiffness=3000.0, damping=0.0, max_force=8.0, fade_in=1e-6)
    dev = F.open_falcon(emulator=True, emulator_options=options(), settings=settings)
    assert isinstance(dev, Device) and dev.name == "falcon-emulator"
    try:
        dev.start(reach)
        dev.driver.stop()  # drive it by hand from here
        h_dev = np.array(dev.snapshot()["position"])
        offset_world = np.array([0.01, -0.005, 0.002])
        corner_world = m.to_world(h_dev) + offset_world
        K = 80.0
        t = dev.driver.now()
        for _ in range(3):
            dev.update_corner(CornerState(position=corner_world, stiffness=K,
                                          received_at=time.monotonic()))
            snap = dev.driver.step(t)
            t += DT
        k_dev = settings.force_scale * K * m.scale
        expect = -k_dev * (np.array(snap["position"]) - m.to_device(corner_world))
        np.testing.assert_allclose(snap["force"], expect, rtol=1e-6, atol=1e-9)
        assert np.all(np.sign(snap["force"]) == np.sign(offset_world))  # pulled to the corner
        hp = dev.hand_position()
        assert np.all(np.abs(hp - reach.centre) <= reach.half_extent + 1e-12)
    finally:
        dev.stop()


def test_cli_check_bench_and_udev(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    assert falcon_cmd.main(["check", "--emulator", "--seconds", "0.3"]) == 0
    assert "Falcon check: OK" in capsys.readouterr().out
    out_json = tmp_path / "bench.json"
    assert falcon_cmd.main(["bench", "--seconds", "0.5", "--json", str(out_json)]) == 0
    out = capsys.readouterr().out
    assert "Hz" in out and "p99" in out
    import json

    figures = json.loads(out_json.read_text())
    assert figures["ticks"] > 0 and figures["rate_hz"] > 0
    assert falcon_cmd.main(["udev"]) == 0
    assert "cb48" in capsys.readouterr().out
    code = falcon_cmd.main(["check", "--emulator", "--firmware", str(tmp_path / "missing.bin")])
    assert code == 2
    assert "not found" in capsys.readouterr().err


def test_cli_check_without_a_falcon_exits_2_and_counts_only_what_it_can(
        capsys: pytest.CaptureFixture[str]) -> None:
    """No Falcon (or no USB transport in this build): a FalconError like the others, so the
    status docs/falcon.md gives (2); the bus count printed only by a build that can read it."""
    usb = f.usb_transport_available()
    if usb and f.count_usb_devices() > 0:
        pytest.skip("a Falcon is plugged in: this checks the machine without one")
    assert falcon_cmd.main(["check", "--homing-timeout", "1"]) == 2
    captured = capsys.readouterr()
    if usb:
        assert "Falcons on the USB bus: 0" in captured.out
    else:
        assert "Falcons on the USB bus: 0" not in captured.out
        assert "no USB transport" in captured.out
    assert "--emulator" in captured.err
