"""Frame assembly and interpolation: pure logic, no window, no network.

The server sends the full mesh at ~30 Hz (MESH) while the display runs at 60 Hz or more.
The client renders a moment in the past, ``delay`` behind the newest frame it has, and
interpolates linearly between the two received frames around that moment, so motion is
smooth at the display rate and a late packet does not make the cloth jump. The delay
adapts: about one and a half frame intervals plus the arrival jitter it has seen.

Server time is mapped to the local clock by ``ClockSync``: the offset ``local - server``
is the lower envelope of ``received_at - server_time`` over recent frames (the least
delayed packets), so network queueing shows up as jitter, not as a drift.

``assemble`` turns one sample plus the local hand and the room's seats into a
``RenderFrame``: everything the renderer draws, and nothing it has to compute itself
beyond uploading arrays.
"""

from __future__ import annotations

import bisect
import collections
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..sim.scene import ASSETS

PALETTE_PATH = ASSETS / "web" / "palette.json"  # the colours of both clients, one file


def _rgb(hex_colour: str) -> tuple[float, float, float]:
    v = int(hex_colour.lstrip("#"), 16)
    return ((v >> 16 & 255) / 255, (v >> 8 & 255) / 255, (v & 255) / 255)


PALETTE: dict[str, Any] = json.loads(PALETTE_PATH.read_text(encoding="utf-8"))
# Seat colours (RGB 0..1): corner handles, names and the edge each seat guards
# (0 north: red, 1 east: blue, 2 south: green, 3 west: yellow).
SEAT_COLOURS: tuple[tuple[float, float, float], ...] = tuple(
    _rgb(c) for c in PALETTE["seats"])
UNGUARDED = _rgb(PALETTE["unguarded"])
# The scene's colours (the window test recognises the cloth by its hue).
CLOTH_FRONT = _rgb(PALETTE["cloth_front"])  # canvas
CLOTH_BACK = _rgb(PALETTE["cloth_back"])
BALL_COLOUR = _rgb(PALETTE["ball"])
BACKGROUND = _rgb(PALETTE["background"])
WIRE_COLOUR = _rgb(PALETTE["wire"])
FLOOR_COLOUR = _rgb(PALETTE["floor"])
EDGE_NAMES = ("north", "east", "south", "west")


@dataclass(frozen=True)
class MeshFrame:
    """One received (or recorded) mesh frame."""

    server_time: float
    frame: int
    positions: np.ndarray  # (n, n, 3) float32
    ball_position: np.ndarray  # (3,)
    ball_radius: float
    hips: np.ndarray  # (4, 3)

    @classmethod
    def from_mesh(cls, mesh: Any) -> MeshFrame:
        """From a ``server.protocol.Mesh``."""
        return cls(
            server_time=float(mesh.server_time), frame=int(mesh.frame),
            positions=np.asarray(mesh.positions, dtype=np.float32),
            ball_position=np.asarray(mesh.ball_position, dtype=np.float64),
            ball_radius=float(mesh.ball_radius),
            hips=np.asarray(mesh.hips, dtype=np.float64).reshape(4, 3),
        )


@dataclass(frozen=True)
class Sample:
    """The scene at one (server) time, interpolated between two frames."""

    server_time: float
    frame: int
    positions: np.ndarray  # (n, n, 3) float32
    ball_position: np.ndarray
    ball_radius: float
    hips: np.ndarray
    alpha: float = 0.0  # 0: exactly frame a, 1: exactly frame b
    held: bool = False  # past the newest frame: the newest is held


def interpolate(a: MeshFrame, b: MeshFrame, t: float) -> Sample:
    """Linear interpolation between frames ``a`` and ``b`` at server time ``t`` (clamped
    to [a, b]). Frames of different sizes (a scene change) are not blended."""
    span = b.server_time - a.server_time
    if span <= 0.0 or a.positions.shape != b.positions.shape:
        alpha = 1.0 if t >= b.server_time else 0.0
    else:
        alpha = float(np.clip((t - a.server_time) / span, 0.0, 1.0))
    if alpha <= 0.0:
        return Sample(a.server_time, a.frame, a.positions, a.ball_position, a.ball_radius,
                      a.hips, 0.0)
    if alpha >= 1.0:
        return Sample(b.server_time, b.frame, b.positions, b.ball_position, b.ball_radius,
                      b.hips, 1.0)
    w = np.float32(alpha)
    pos = a.positions + (b.positions - a.positions) * w
    ball = a.ball_position + (b.ball_position - a.ball_position) * alpha
    hips = a.hips + (b.hips - a.hips) * alpha
    ts = a.server_time + span * alpha
    frame = int(round(a.frame + (b.frame - a.frame) * alpha))
    return Sample(ts, frame, pos, ball, b.ball_radius, hips, alpha)


class Timeline:
    """Frames ordered by server time; ``sample(t)`` interpolates. Replays hold a whole
    round in one; the live buffer keeps the newest few."""

    def __init__(self, frames: Sequence[MeshFrame] = (), capacity: int | None = None) -> None:
        self.capacity = capacity
        self.frames: collections.deque[MeshFrame] | list[MeshFrame]
        self.frames = collections.deque(maxlen=capacity) if capacity else []
        self._times: collections.deque[float] | list[float]
        self._times = collections.deque(maxlen=capacity) if capacity else []
        for f in sorted(frames, key=lambda f: f.server_time):
            self.push(f)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def start(self) -> float:
        return self.frames[0].server_time if self.frames else 0.0

    @property
    def end(self) -> float:
        return self.frames[-1].server_time if self.frames else 0.0

    def push(self, f: MeshFrame) -> bool:
        """Append a frame newer than the newest; older or repeated frames are dropped
        (False)."""
        if self.frames and f.server_time <= self.frames[-1].server_time:
            return False
        self.frames.append(f)
        self._times.append(f.server_time)
        return True

    def sample(self, t: float) -> Sample | None:
        if not self.frames:
            return None
        if t >= self._times[-1]:
            last = self.frames[-1]
            return Sample(last.server_time, last.frame, last.positions, last.ball_position,
                          last.ball_radius, last.hips, 1.0, held=t > last.server_time)
        i = bisect.bisect_right(self._times, t)  # frames[i-1].t <= t < frames[i].t
        if i == 0:
            return interpolate(self.frames[0], self.frames[0], t)
        return interpolate(self.frames[i - 1], self.frames[i], t)


class ClockSync:
    """Maps server time to local time: ``local = server + offset``.

    ``offset`` is the smallest ``received_at - server_time`` over the last ``window``
    samples (the packets that waited least). It follows a change of route within the
    window; it is None before the first sample.
    """

    def __init__(self, window: int = 90) -> None:
        self._samples: collections.deque[float] = collections.deque(maxlen=window)
        self.offset: float | None = None

    def add(self, server_time: float, local_time: float) -> None:
        self._samples.append(local_time - server_time)
        self.offset = min(self._samples)

    def jitter(self) -> float:
        """How much later than the least delayed packet a typical one arrives (s, p90)."""
        if len(self._samples) < 2 or self.offset is None:
            return 0.0
        return float(np.percentile(np.asarray(self._samples) - self.offset, 90))

    def to_server(self, local_time: float) -> float:
        return local_time - (self.offset or 0.0)


class FrameBuffer:
    """The live mesh stream: push frames as they arrive, sample at the display's time.

    ``sample(now)`` returns the scene at about server time ``now - offset - delay``: the
    delay is ``delay_frames`` frame intervals plus the jitter seen (bounded by
    ``max_delay``), so at display rate the cloth moves between two real frames, never past
    the newest; the shown time is slewed towards that target (``render_time``), so it never
    steps back. Call ``sample`` once per displayed frame, with increasing times.
    """

    def __init__(self, capacity: int = 16, delay_frames: float = 1.5,
                 min_delay: float = 0.01, max_delay: float = 0.25, slew: float = 0.1,
                 snap: float = 0.25) -> None:
        self.timeline = Timeline(capacity=capacity)
        self.clock = ClockSync()
        self.delay_frames = delay_frames
        self.min_delay = min_delay
        self.max_delay = max_delay
        self.slew = slew  # the shown clock may run this much fast or slow to catch up
        self.snap = snap  # ...or jump ahead when it is this far behind (s)
        self.received = 0
        self.dropped = 0
        self._last: tuple[float, float] | None = None  # (local time, shown server time)

    def push(self, f: MeshFrame, received_at: float) -> None:
        # A server restart (time going backwards by a lot) starts a fresh stream.
        if self.timeline.frames and f.server_time < self.timeline.end - 5.0:
            self.reset()
        if self.timeline.push(f):
            self.received += 1
            self.clock.add(f.server_time, received_at)
        else:
            self.dropped += 1

    def reset(self) -> None:
        self.timeline = Timeline(capacity=self.timeline.capacity)
        self.clock = ClockSync()
        self._last = None

    def interval(self) -> float:
        """Median spacing of the buffered frames (s); 1/30 until there are two."""
        ts = [f.server_time for f in self.timeline.frames]
        if len(ts) < 2:
            return 1.0 / 30.0
        return float(np.median(np.diff(ts)))

    @property
    def delay(self) -> float:
        d = self.delay_frames * self.interval() + self.clock.jitter()
        return float(np.clip(d, self.min_delay, self.max_delay))

    def target_time(self, local_now: float) -> float:
        """The server time ideally shown at ``local_now``: ``delay`` behind the stream."""
        return self.clock.to_server(local_now) - self.delay

    def render_time(self, local_now: float) -> float:
        """The server time to show at local time ``local_now``.

        The target moves in small steps whenever the clock offset or the delay is
        re-estimated; the shown time follows it without jumps: it advances with the local
        clock, at most ``slew`` faster or slower, never backwards, and jumps forward only
        when it has fallen ``snap`` behind (after a stall)."""
        target = self.target_time(local_now)
        if self._last is None or local_now <= self._last[0]:
            shown = target if self._last is None else self._last[1]
        else:
            last_local, last_shown = self._last
            dt = local_now - last_local
            predicted = last_shown + dt
            err = target - predicted
            if err > self.snap:
                shown = target
            else:
                shown = predicted + float(np.clip(err, -self.slew * dt, self.slew * dt))
            shown = max(shown, last_shown)
        self._last = (local_now, shown)
        return shown

    def sample(self, local_now: float) -> Sample | None:
        return self.timeline.sample(self.render_time(local_now))


# --- geometry the renderer uploads -----------------------------------------------------------


def grid_normals(positions: np.ndarray) -> np.ndarray:
    """Unit vertex normals (n, n, 3) float32 of a grid mesh, from central differences
    (one-sided at the border). At rest (row index along +z, column along +x) they point
    up (+y). Degenerate spots get (0, 1, 0)."""
    p = np.asarray(positions, dtype=np.float32)
    du = np.empty_like(p)
    dv = np.empty_like(p)
    du[1:-1] = p[2:] - p[:-2]
    du[0] = p[1] - p[0]
    du[-1] = p[-1] - p[-2]
    dv[:, 1:-1] = p[:, 2:] - p[:, :-2]
    dv[:, 0] = p[:, 1] - p[:, 0]
    dv[:, -1] = p[:, -1] - p[:, -2]
    nrm = np.cross(du, dv)
    length = np.linalg.norm(nrm, axis=-1, keepdims=True)
    ok = length > 1e-12
    out = np.where(ok, nrm / np.where(ok, length, 1.0), np.array([0.0, 1.0, 0.0], np.float32))
    return out.astype(np.float32)


def grid_triangles(n: int) -> np.ndarray:
    """Triangle indices (uint32, flat) of an n x n grid, two per cell."""
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    b, c, d = a + 1, a + n, a + n + 1
    return np.stack([a, c, b, b, c, d], axis=1).ravel().astype(np.uint32)


def grid_lines(n: int) -> np.ndarray:
    """Line indices (uint32, flat) of an n x n grid's springs along rows and columns."""
    idx = np.arange(n * n).reshape(n, n)
    rows = np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], axis=1)
    cols = np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], axis=1)
    return np.concatenate([rows, cols]).ravel().astype(np.uint32)


def grid_corners(positions: np.ndarray) -> np.ndarray:
    """The four corner nodes (4, 3) in seat order: (0,0), (0,n-1), (n-1,n-1), (n-1,0)."""
    p = np.asarray(positions)
    return np.stack([p[0, 0], p[0, -1], p[-1, -1], p[-1, 0]]).astype(np.float64)


def grid_edge(positions: np.ndarray, edge: int) -> np.ndarray:
    """The nodes (n, 3) along edge ``edge``, from its corner to the next one clockwise
    (north: row 0, east: column n-1, south: row n-1 reversed, west: column 0 reversed)."""
    p = np.asarray(positions)
    if edge == 0:
        return p[0, :]
    if edge == 1:
        return p[:, -1]
    if edge == 2:
        return p[-1, ::-1]
    if edge == 3:
        return p[::-1, 0]
    raise ValueError(f"edge must be 0..3, got {edge}")


# --- frame assembly --------------------------------------------------------------------------


@dataclass(frozen=True)
class Handle:
    """One corner as drawn: where it is, who holds it, their hand."""

    seat: int
    position: np.ndarray  # (3,) the cloth corner
    hip: np.ndarray | None  # (3,) the hand (None: nobody's hand is on it)
    name: str
    kind: str  # "empty", "human", "bot"
    colour: tuple[float, float, float]
    own: bool = False


@dataclass(frozen=True)
class Pull:
    """The player's own pull: the line from the corner to the hand, coloured by force."""

    corner: np.ndarray
    hand: np.ndarray
    force: float  # N, |F| = K |h - c|
    colour: tuple[float, float, float]


@dataclass(frozen=True)
class RenderFrame:
    """Everything the window draws for one displayed frame."""

    positions: np.ndarray  # (n, n, 3) float32
    normals: np.ndarray  # (n, n, 3) float32
    ball_position: np.ndarray
    ball_radius: float
    handles: tuple[Handle, ...]
    edge_colours: tuple[tuple[float, float, float], ...]  # per edge 0..3
    pull: Pull | None = None
    server_time: float = 0.0
    frame: int = 0
    extras: dict[str, Any] = field(default_factory=dict)


def force_colour(force: float, full: float) -> tuple[float, float, float]:
    """Green (no pull) through yellow to red (``full`` newtons or more)."""
    x = float(np.clip(force / full, 0.0, 1.0)) if full > 0 else 0.0
    if x < 0.5:
        return (2.0 * x, 0.85, 0.2)
    return (1.0, 0.85 * (2.0 - 2.0 * x), 0.2)


def assemble(sample: Sample, seats: Sequence[dict[str, Any]] = (), *,
             own_seat: int | None = None, own_hand: np.ndarray | None = None,
             stiffness: float = 0.0, full_force: float = 20.0,
             with_normals: bool = True) -> RenderFrame:
    """One ``RenderFrame`` from an interpolated sample, the room's seats (``info()``'s
    ``seats``) and, for a player, the local hand (fresher than the echoed one)."""
    pos = sample.positions
    corners = grid_corners(pos)
    by_seat = {int(s.get("seat", i)): s for i, s in enumerate(seats)}
    handles = []
    edge_colours = []
    for s in range(4):
        info = by_seat.get(s, {})
        kind = str(info.get("kind", "empty"))
        colour = SEAT_COLOURS[s]
        hip: np.ndarray | None = np.asarray(sample.hips[s], dtype=np.float64)
        if own_seat == s and own_hand is not None:
            hip = np.asarray(own_hand, dtype=np.float64)
        if kind == "empty" and own_seat != s:
            hip = None
        name = str(info.get("name") or ("you" if own_seat == s else ""))
        handles.append(Handle(s, corners[s], hip, name, kind, colour, own=own_seat == s))
        edge_colours.append(colour if kind != "empty" or own_seat == s else UNGUARDED)
    pull = None
    if own_seat is not None and own_hand is not None:
        h = np.asarray(own_hand, dtype=np.float64)
        c = corners[own_seat]
        f = stiffness * float(np.linalg.norm(h - c))
        pull = Pull(c, h, f, force_colour(f, full_force))
    normals = grid_normals(pos) if with_normals else np.zeros_like(pos)
    return RenderFrame(pos, normals, np.asarray(sample.ball_position, dtype=np.float64),
                       sample.ball_radius, tuple(handles), tuple(edge_colours), pull,
                       sample.server_time, sample.frame)
