"""The mouse device: pointer, wheel and right-drag mapped onto the corner's reach box,
through the window's camera; the pull it shows."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from clothball.game.client.camera import OrbitCamera
from clothball.game.devices.base import CornerState, Device, Reach
from clothball.game.devices.mouse import MouseDevice
from hypothesis import given
from hypothesis import strategies as st

REACH = Reach(np.array([0.5, 1.0, -0.5]), np.array([0.3, 0.3, 0.3]))


def started() -> MouseDevice:
    m = MouseDevice(wheel_step=0.1, drag_gain=0.01)
    m.start(REACH)
    return m


def test_it_is_a_device_and_starts_at_the_anchor() -> None:
    m = MouseDevice()
    assert isinstance(m, Device) and m.name == "mouse"
    m.start(REACH)
    assert np.array_equal(m.hand_position(), REACH.centre)
    m.stop()
    m.stop()  # twice is fine
    m.set_unit(1.0, 1.0)  # ignored when stopped
    assert np.array_equal(m.hand_position(), REACH.centre)


def test_unit_coordinates_span_the_box_horizontally() -> None:
    m = started()
    m.set_unit(1.0, -1.0)
    assert np.allclose(m.hand_position(), [0.8, 1.0, -0.8])
    m.set_unit(-1.0, 1.0)
    assert np.allclose(m.hand_position(), [0.2, 1.0, -0.2])
    m.set_unit(5.0, 0.0)  # clamped
    assert np.allclose(m.hand_position(), [0.8, 1.0, -0.5])
    m.set_horizontal(-9.0, 9.0)
    assert np.allclose(m.hand_position(), [0.2, 1.0, -0.2])
    m.set_horizontal(float("nan"), 0.0)  # ignored
    assert np.allclose(m.hand_position(), [0.2, 1.0, -0.2])


def test_wheel_and_right_drag_move_the_height_within_the_box() -> None:
    m = started()
    m.scroll(1)
    assert m.hand_position()[1] == pytest.approx(1.0 + 0.1 * 0.3)
    m.scroll(-3)
    assert m.hand_position()[1] == pytest.approx(1.0 - 0.2 * 0.3)
    m.scroll(100)
    assert m.hand_position()[1] == pytest.approx(1.3)  # top of the box
    m.drag_height(-50)  # dragging down 50 px
    assert m.hand_position()[1] == pytest.approx(1.3 - 50 * 0.01 * 0.3)
    m.drag_height(-1e6)
    assert m.hand_position()[1] == pytest.approx(0.7)
    x, z = m.hand_position()[[0, 2]]
    assert (x, z) == (0.5, -0.5)  # the height never moves the hand sideways
    m.centre()
    assert np.array_equal(m.hand_position(), REACH.centre)


@given(u=st.floats(-1.0, 1.0), w=st.floats(-1.0, 1.0), yaw=st.floats(-3.1, 3.1),
       pitch=st.floats(0.3, 1.4))
def test_the_hand_goes_where_the_pointer_is_on_screen(u: float, w: float, yaw: float,
                                                       pitch: float) -> None:
    """A point of the box at the hand's height, projected to a pixel: pointing there
    puts the hand on it, whatever the camera's angle."""
    cam = OrbitCamera(target=np.array([0.0, 1.0, 0.0]), distance=2.5, yaw=yaw, pitch=pitch)
    m = started()
    target = REACH.from_unit(np.array([u, 0.0, w]))
    px, py, ok = cam.project(target, 1280, 800)
    assert ok
    origin, direction = cam.ray(px, py, 1280, 800)
    assert m.point_at_ray(origin, direction)
    assert np.allclose(m.hand_position(), target, atol=1e-6)


def test_rays_that_miss_the_plane_do_nothing() -> None:
    m = started()
    assert not m.point_at_ray(np.array([0.0, 2.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    assert not m.point_at_ray(np.array([0.0, 2.0, 0.0]), np.array([0.0, 1.0, 0.0]))  # behind
    assert np.array_equal(m.hand_position(), REACH.centre)
    # a point far outside the box is clamped to its edge
    assert m.point_at_ray(np.array([5.0, 2.0, -0.5]), np.array([0.0, -1.0, 0.0]))
    assert np.allclose(m.hand_position(), [0.8, 1.0, -0.5])


def test_the_pull_shown_is_the_coupling_force() -> None:
    m = started()
    assert m.pull() is None  # no corner state yet
    m.update_corner(CornerState(position=np.array([0.5, 0.9, -0.5]), stiffness=300.0))
    m.scroll(1)
    corner, hand, force = m.pull()
    assert np.allclose(corner, [0.5, 0.9, -0.5]) and np.allclose(hand, m.hand_position())
    assert force == pytest.approx(300.0 * (0.1 + 0.03))


def test_moves_from_one_thread_reads_from_another() -> None:
    m = started()
    stop = threading.Event()
    seen: list[np.ndarray] = []

    def reader() -> None:
        while not stop.is_set():
            seen.append(m.hand_position())

    t = threading.Thread(target=reader)
    t.start()
    for k in range(2000):
        m.set_unit(np.sin(k), np.cos(k))
        m.scroll(1 if k % 2 else -1)
    stop.set()
    t.join()
    lo, hi = REACH.centre - REACH.half_extent, REACH.centre + REACH.half_extent
    assert seen and all(np.all(h >= lo - 1e-12) and np.all(h <= hi + 1e-12) for h in seen)
    assert m.moves > 0
