"""Client logic without a window: interpolation between received frames, the clock
mapping, the live buffer at display rate, grid geometry and frame assembly."""

from __future__ import annotations

import numpy as np
import pytest
from clothball.game.client.interp import (
    SEAT_COLOURS,
    UNGUARDED,
    ClockSync,
    FrameBuffer,
    MeshFrame,
    Timeline,
    assemble,
    force_colour,
    grid_corners,
    grid_edge,
    grid_lines,
    grid_normals,
    grid_triangles,
    interpolate,
)
from clothball.game.rules import edge_corners
from clothball.game.sim.cloth import corners_of, rest_positions
from clothball.game.sim.scene import Scene
from clothball.game.wire import protocol as P
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.conftest import examples

N = 8


def rest_grid(n: int) -> np.ndarray:
    """The server's rest positions (n, n, 3) of the classic scene at size n."""
    return rest_positions(Scene.load("classic").with_changes({"cloth": {"n": n}}))


def grid(offset: float = 0.0, n: int = N) -> np.ndarray:
    """A flat n x n grid (rows along +z, columns along +x), lifted by ``offset``."""
    i, j = np.meshgrid(np.linspace(-0.5, 0.5, n), np.linspace(-0.5, 0.5, n), indexing="ij")
    return np.stack([j, np.full_like(i, 1.0 + offset), i], axis=-1).astype(np.float32)


def frame(t: float, offset: float = 0.0, f: int | None = None) -> MeshFrame:
    return MeshFrame(t, int(t * 1000) if f is None else f, grid(offset),
                     np.array([0.0, 1.2 + offset, 0.0]), 0.05, np.full((4, 3), offset))


def moving(t: float) -> MeshFrame:
    """The cloth rising at 0.3 m/s: linear motion, so interpolation is exact."""
    return frame(t, 0.3 * t)


def test_interpolate_is_exact_at_the_frames_and_linear_between() -> None:
    a, b = frame(1.0, 0.0), frame(1.1, 0.2)
    s = interpolate(a, b, 1.0)
    assert s.alpha == 0.0 and np.array_equal(s.positions, a.positions)
    s = interpolate(a, b, 1.1)
    assert s.alpha == 1.0 and np.array_equal(s.positions, b.positions)
    for w in (0.25, 0.5, 0.75):
        s = interpolate(a, b, 1.0 + 0.1 * w)
        assert s.alpha == pytest.approx(w)
        assert np.allclose(s.positions, a.positions * (1 - w) + b.positions * w, atol=1e-6)
        assert np.allclose(s.ball_position, [0.0, 1.2 + 0.2 * w, 0.0])
        assert np.allclose(s.hips, 0.2 * w)
        assert s.server_time == pytest.approx(1.0 + 0.1 * w)
    # outside [a, b]: clamped, never extrapolated
    assert np.array_equal(interpolate(a, b, 0.5).positions, a.positions)
    assert np.array_equal(interpolate(a, b, 9.0).positions, b.positions)


def test_frames_of_different_sizes_are_not_blended() -> None:
    a = frame(0.0)
    b = MeshFrame(0.1, 100, grid(0.0, n=5), np.zeros(3), 0.05, np.zeros((4, 3)))
    assert interpolate(a, b, 0.04).positions.shape == (N, N, 3)
    assert interpolate(a, b, 0.1).positions.shape == (5, 5, 3)


def test_timeline_orders_drops_stale_frames_and_holds_the_newest() -> None:
    tl = Timeline(capacity=4)
    assert tl.sample(0.0) is None
    for t in (0.0, 0.1, 0.2):
        assert tl.push(frame(t, t))
    assert not tl.push(frame(0.15, 9.0))  # older than the newest: dropped
    assert not tl.push(frame(0.2, 9.0))  # repeated
    s = tl.sample(0.15)
    assert s is not None and np.allclose(s.positions[..., 1], 1.15, atol=1e-6)
    s = tl.sample(5.0)
    assert s is not None and s.held and s.server_time == 0.2
    s = tl.sample(-1.0)
    assert s is not None and s.server_time == 0.0
    for t in (0.3, 0.4, 0.5):
        tl.push(frame(t))
    assert len(tl) == 4 and tl.start == pytest.approx(0.2)  # bounded


def test_clock_sync_takes_the_least_delayed_packet() -> None:
    c = ClockSync(window=10)
    assert c.offset is None
    delays = [0.030, 0.012, 0.050, 0.013, 0.020]
    for k, d in enumerate(delays):
        c.add(server_time=k * 0.1, local_time=100.0 + k * 0.1 + d)
    assert c.offset == pytest.approx(100.012)
    assert c.to_server(100.512) == pytest.approx(0.5)
    assert 0.0 < c.jitter() <= max(delays) - min(delays) + 1e-12


@settings(max_examples=examples(25), deadline=None)
@given(seed=st.integers(0, 2**31 - 1), display_hz=st.sampled_from([60.0, 75.0, 144.0]))
def test_live_buffer_is_smooth_at_display_rate(seed: int, display_hz: float) -> None:
    """Frames at 30 Hz with random network delay (5..40 ms); the display samples at its
    own rate. Shown server time never goes backwards, never passes the newest frame, and
    the cloth shown is the true (linear) motion at the shown time."""
    rng = np.random.default_rng(seed)
    buf = FrameBuffer()
    arrivals = sorted((k / 30.0 + 10.0 + rng.uniform(0.005, 0.040), k / 30.0)
                      for k in range(90))
    shown: list[float] = []
    ai = 0
    t = arrivals[0][0]
    while t < arrivals[-1][0]:
        while ai < len(arrivals) and arrivals[ai][0] <= t:
            buf.push(moving(arrivals[ai][1]), arrivals[ai][0])
            ai += 1
        s = buf.sample(t)
        assert s is not None
        newest = buf.timeline.end
        assert s.server_time <= newest + 1e-12
        # exact linear motion at the shown time (float32 storage)
        assert np.allclose(s.positions[..., 1], 1.0 + 0.3 * s.server_time, atol=2e-6)
        if t > arrivals[0][0] + 0.5:  # after the first frames: interpolating, not holding
            shown.append(s.server_time)
        t += 1.0 / display_hz
    steps = np.diff(shown)
    assert np.all(steps >= -1e-9), "shown time went backwards"
    # it advances at the display's pace: no frame-long stalls once the buffer is primed
    assert np.median(steps) == pytest.approx(1.0 / display_hz, rel=0.05)
    assert 1.0 / 30.0 <= buf.delay <= buf.max_delay


def test_buffer_restarts_when_the_server_clock_restarts() -> None:
    buf = FrameBuffer()
    for k in range(10):
        buf.push(frame(100.0 + k / 30), 5.0 + k / 30)
    buf.push(frame(0.5), 6.0)
    assert len(buf.timeline) == 1 and buf.timeline.end == 0.5


def test_grid_geometry() -> None:
    n = 5
    tris = grid_triangles(n)
    assert tris.dtype == np.uint32 and len(tris) == 2 * (n - 1) ** 2 * 3
    assert tris.min() == 0 and tris.max() == n * n - 1
    lines = grid_lines(n)
    assert len(lines) == 2 * 2 * n * (n - 1)  # 2n(n-1) springs, 2 indices each
    # every line joins grid neighbours (one step along a row or a column)
    a, b = lines[0::2].astype(np.int64), lines[1::2].astype(np.int64)
    steps = np.abs(np.stack([a // n - b // n, a % n - b % n], axis=1)).sum(axis=1)
    assert np.all(steps == 1) and len({(x, y) for x, y in zip(a, b, strict=True)}) == len(a)
    # corners in the server's (and the rules') seat order
    rest = rest_grid(n)
    assert np.array_equal(grid_corners(rest), corners_of(rest))
    for e in range(4):
        start, end = edge_corners(e)
        edge = grid_edge(rest, e)
        assert np.array_equal(edge[0], corners_of(rest)[start])
        assert np.array_equal(edge[-1], corners_of(rest)[end])


def test_normals_point_up_at_rest_and_follow_a_tilt() -> None:
    rest = rest_grid(6)
    assert np.allclose(grid_normals(rest), [0.0, 1.0, 0.0], atol=1e-6)
    tilted = rest.copy()
    tilted[..., 1] += 0.5 * tilted[..., 0]  # y = 0.5 x: normal (-0.5, 1, 0)/|.|
    expect = np.array([-0.5, 1.0, 0.0]) / np.linalg.norm([-0.5, 1.0, 0.0])
    assert np.allclose(grid_normals(tilted), expect, atol=1e-5)
    bumpy = rest + np.random.default_rng(1).normal(0.0, 0.02, rest.shape)
    nrm = grid_normals(bumpy)
    assert np.allclose(np.linalg.norm(nrm, axis=-1), 1.0, atol=1e-5)
    collapsed = np.zeros((4, 4, 3), np.float32)  # all nodes coincident: no NaN
    assert np.allclose(grid_normals(collapsed), [0.0, 1.0, 0.0])


def test_mesh_frame_from_the_wire() -> None:
    pos = rest_grid(N)
    hips = np.arange(12, dtype=float).reshape(4, 3) / 10
    data = P.encode_mesh(1234, 1.5, pos, [0.1, 1.2, 0.3], 0.05, hips)
    f = MeshFrame.from_mesh(P.decode_mesh(data))
    assert f.frame == 1234 and f.server_time == 1.5 and f.positions.dtype == np.float32
    assert np.allclose(f.positions, pos, atol=1e-4) and np.allclose(f.hips, hips, atol=1e-6)


def test_assemble_a_render_frame() -> None:
    s = interpolate(frame(0.0), frame(0.1), 0.05)
    seats = [
        {"seat": 0, "kind": "bot", "name": "bot-0"},
        {"seat": 1, "kind": "empty", "name": ""},
        {"seat": 2, "kind": "human", "name": "ann"},
        {"seat": 3, "kind": "human", "name": "bob"},
    ]
    hand = grid_corners(s.positions)[2] + np.array([0.0, 0.1, 0.0])
    rf = assemble(s, seats, own_seat=2, own_hand=hand, stiffness=200.0, full_force=40.0)
    assert rf.positions.shape == rf.normals.shape == (N, N, 3)
    assert [h.name for h in rf.handles] == ["bot-0", "", "ann", "bob"]
    assert rf.handles[1].hip is None  # nobody's hand on an empty corner
    assert np.array_equal(rf.handles[2].hip, hand) and rf.handles[2].own  # local hand wins
    assert np.allclose(rf.handles[3].hip, s.hips[3])
    assert rf.edge_colours == (SEAT_COLOURS[0], UNGUARDED, SEAT_COLOURS[2], SEAT_COLOURS[3])
    assert rf.pull is not None and rf.pull.force == pytest.approx(200.0 * 0.1)
    assert rf.pull.colour == pytest.approx(force_colour(20.0, 40.0))
    spectator = assemble(s, seats)
    assert spectator.pull is None and not any(h.own for h in spectator.handles)


def test_force_colour_runs_green_to_red() -> None:
    assert force_colour(0.0, 10.0) == (0.0, 0.85, 0.2)
    assert force_colour(10.0, 10.0) == (1.0, 0.0, 0.2)
    assert force_colour(99.0, 10.0) == force_colour(10.0, 10.0)
    reds = [force_colour(f, 10.0)[0] for f in np.linspace(0, 10, 11)]
    greens = [force_colour(f, 10.0)[1] for f in np.linspace(0, 10, 11)]
    assert reds == sorted(reds) and greens == sorted(greens, reverse=True)
