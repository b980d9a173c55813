"""End to end: an emulated Falcon player joins a live local server, moves its corner, and
the cloth's pull comes back as motor commands of the right sign and size."""

from __future__ import annotations

import asyncio
import collections
import time

import numpy as np
from clothball._native import falcon as f
from clothball.game.devices import falcon as F
from clothball.game.net.client import NetClient
from clothball.server.room import RoomSettings

from tests.server.conftest import run, server, until

KIN = f.Kinematics()


def test_emulated_falcon_player_feels_the_cloth(tmp_path) -> None:
    async def main() -> None:
        async with server(tmp_path, settings=RoomSettings()) as srv:
            room = srv.main_room
            assert room is not None
            p = await NetClient.connect(srv.ws_url, name="falcon", role="player", room=room.id,
                                        seat=2)
            p.clock = time.monotonic  # the clock FalconDevice measures sample ages with
            reach = p.reach
            assert reach is not None
            anchors = np.array(p.geometry["anchors"], dtype=np.float64)
            anchor, centre = anchors[2], anchors.mean(axis=0)
            opts = f.EmulatorOptions()
            opts.firmware_loaded = True
            opts.home_after_packets = 20
            settings = F.FalconSettings()
            dev = F.open_falcon(emulator=True, emulator_options=opts, settings=settings)
            await asyncio.to_thread(dev.start, reach)
            stop = asyncio.Event()
            sent: collections.deque = collections.deque(maxlen=50)  # handed to the device

            async def pump() -> None:  # what the desktop client's loop does
                while not stop.is_set():
                    await p.send_hip(dev.hand_position())
                    cs = p.corner_state()
                    if cs is not None:
                        dev.update_corner(cs)
                        sent.append(cs)
                    await asyncio.sleep(0.002)

            task = asyncio.create_task(pump())
            try:
                # 1. The player pulls the grip outwards, away from the cloth's centre: the
                #    corner follows the Falcon.
                out = anchor - centre
                out[1] = 0.0
                out /= np.linalg.norm(out)
                target = reach.clamp(anchor + out * 0.6 * reach.half_extent)
                dev.hold(target, stiffness=300.0, damping=5.0)
                await until(lambda: p.corner is not None and
                            float((p.corner.position - anchor) @ out) > 0.2 * reach.half_extent[0],
                            10, "the corner follows the Falcon outwards")
                # settle (a fixed wait: the samples below skip stale ones and compare
                # means, so a slow settle only costs samples, within their deadline)
                await asyncio.sleep(1.0)
                # Sample the loop and the server's corner state while corner updates are
                # fresh (on a busy machine the room can stall; the loop then fades the
                # spring out, which is tested elsewhere). The corner node jitters (HIPs
                # arrive at irregular times), so compare means: the spring term is linear,
                # the damping terms average out at rest.
                m = dev.mapping
                assert m is not None
                hs, cs_dev, forces, corners, expects = [], [], [], [], []
                deadline = time.monotonic() + 20.0
                skipped = collections.Counter()
                while len(hs) < 40 and time.monotonic() < deadline:
                    await asyncio.sleep(0.01)
                    snap = dev.snapshot()
                    assert snap["error"] is None and sent
                    if snap["gain"] < 1.0 or not 0 <= snap["age"] < settings.stale_after:
                        skipped["stale"] += 1
                        continue
                    # Which corner state did this tick use? (The loop takes the newest one
                    # handed over; find it among the recent ones by its extrapolated corner.)
                    for cs in reversed(sent):
                        c_dot = m.velocity_to_device(cs.velocity)
                        c_ext = m.to_device(cs.position) + c_dot * snap["age"]
                        if np.allclose(snap["corner"], c_ext, rtol=0, atol=1e-9):
                            break
                    else:
                        skipped["older sample"] += 1
                        continue
                    # What the law F = -k (h - c_ext) - B (h_dot - c_dot) - alpha h_dot gives
                    # for that server corner state, mapped into the device frame by the
                    # test: k = K * scale (capped), c_ext = c + c_dot * age, |F| <= max_force
                    # (alpha: the passivity controller's damping that tick).
                    k_dev = np.minimum(settings.force_scale * cs.stiffness * m.scale,
                                       settings.max_stiffness)
                    e = (-k_dev * (np.array(snap["position"]) - c_ext)
                         - settings.damping * (np.array(snap["velocity"]) - c_dot)
                         - snap["alpha"] * np.array(snap["velocity"]))
                    e *= min(1.0, settings.max_force / np.linalg.norm(e))
                    expects.append(e)
                    hs.append(snap["position"])
                    cs_dev.append(m.to_device(cs.position))
                    forces.append(snap["force"])
                    corners.append(cs)
                assert len(hs) == 40, (
                    f"too few fresh corner states: {dict(skipped)}; corners received "
                    f"{p.counts['corner']}, last {time.monotonic() - p.corner_received_at:.2f} s "
                    f"ago, connection close code {p.close_code}")
                h_dev, c_dev = np.mean(hs, axis=0), np.mean(cs_dev, axis=0)
                force, expect = np.mean(forces, axis=0), np.mean(expects, axis=0)
                # 2. The stretched cloth holds the corner back, inwards of the hand...
                pull_world = m.to_world(c_dev) - m.to_world(h_dev)
                assert float(pull_world @ -out) > 0.0
                # ...and the Falcon renders that pull with the right size.
                assert np.linalg.norm(expect) > 0.2  # a pull worth feeling, in newtons
                np.testing.assert_allclose(force, expect, rtol=1e-6, atol=1e-6)
                # Right sign: inwards in the world, along the server's own coupling force.
                f_world = m.force_to_world(force, settings.force_scale)
                assert float(f_world @ -out) > 0.0
                # and on the same side as the server's own coupling force on the device.
                server_force = np.mean([c.force for c in corners], axis=0)
                assert float(f_world @ server_force) > 0.0
                # The motors carry it: Jacobian-transpose torques of the tick's force, and
                # the emulated motors push on the grip with that force.
                dev.driver.stop()  # step the loop by hand to compare single ticks
                t = dev.driver.now()
                snap = dev.driver.step(t)
                dev.driver.step(t + 1e-3)  # sends the motor commands computed by `snap`
                tick_force = np.array(snap["force"])
                assert snap["motor"] == list(f.torques_to_motors(
                    KIN.torques(snap["position"], tick_force.tolist())))
                assert max(abs(x) for x in snap["motor"]) > 50
                np.testing.assert_allclose(dev.emulator.state()["motor_force"], tick_force,
                                           atol=0.02 * np.linalg.norm(tick_force) + 0.02)
            finally:
                stop.set()
                await task
                dev.stop()
                await p.close()

    run(main())
