"""Recorded rounds for the desktop client: load one (file, id or URL) and play it back with
pause, seek and speed. Pure logic: the window draws ``ReplayPlayer.sample()``.

A replay (``game.wire.replay``) holds the MESH stream (~30 Hz), a TRACK stream (~100 Hz:
ball, hands and corners) and the round's events, each stamped with its simulation frame
(and the server's wall clock). Playback runs on the simulation's clock, frame x
``frame_dt``, from the first to the last recorded MESH or TRACK frame: the length the
index lists (``duration_s``) and the browser shows. (The wall clock runs slower than the
game where the server fell behind: 35 s of it for a round of 27 s.) The cloth is
interpolated between MESH frames, the ball and hands between TRACK samples (fresher), and
the events up to ``t`` give the scores and the log.
"""

from __future__ import annotations

import bisect
import json
import os
import urllib.parse
import urllib.request
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..wire import protocol as P
from ..wire.replay import ReplayError, read_replay
from .interp import MeshFrame, Sample, Timeline

SPEEDS = (0.125, 0.25, 0.5, 1.0, 2.0, 4.0)
DEFAULT_FRAME_DT = 0.001  # s: a header without geometry (the server's rooms step at 1 kHz)


def http_base(server: str) -> str:
    """``ws://host:port/ws`` (or ``http://host:port/...``) -> ``http://host:port``."""
    u = urllib.parse.urlsplit(server if "://" in server else f"ws://{server}")
    scheme = {"ws": "http", "wss": "https"}.get(u.scheme, u.scheme)
    return f"{scheme}://{u.netloc}"


def fetch(source: str, server: str = "ws://127.0.0.1:8765/ws", timeout: float = 20.0) -> bytes:
    """The bytes of a replay named by a file path, an http(s) URL or a replay id (fetched
    from ``server``'s ``/api/replays/<id>``)."""
    if os.path.isfile(source):
        return Path(source).read_bytes()
    if source.startswith(("http://", "https://")):
        url = source
    else:
        if "/" in source or not source:
            raise ReplayError(f"{source!r}: no such file, and not a replay id")
        url = f"{http_base(server)}/api/replays/{urllib.parse.quote(source)}"
    with urllib.request.urlopen(url, timeout=timeout) as r:  # noqa: S310 - the user's URL
        return bytes(r.read())


def list_remote(server: str, limit: int = 20, timeout: float = 10.0) -> list[dict[str, Any]]:
    """The server's recorded rounds, newest first."""
    with urllib.request.urlopen(f"{http_base(server)}/api/replays?limit={limit}",
                                timeout=timeout) as r:  # noqa: S310
        return list(json.loads(r.read())["replays"])


@dataclass(frozen=True)
class TrackPoint:
    time: float
    ball: np.ndarray
    hips: np.ndarray
    corners: np.ndarray


@dataclass
class ReplayData:
    """A parsed replay; every time in it is the simulation's (frame x ``frame_dt``), the
    ``server_time`` of its mesh frames included."""

    header: dict[str, Any]
    timeline: Timeline
    tracks: list[TrackPoint]
    events: list[tuple[float, dict[str, Any]]]  # (time, event message), by time
    start: float  # the first recorded MESH or TRACK frame's time
    end: float  # the last one's

    @classmethod
    def parse(cls, data: bytes) -> ReplayData:
        header, records = read_replay(data)
        geometry = header.get("geometry")
        dt = geometry.get("frame_dt") if isinstance(geometry, dict) else None
        dt = float(dt) if isinstance(dt, int | float) and dt > 0 else DEFAULT_FRAME_DT
        frames: list[MeshFrame] = []
        tracks: list[TrackPoint] = []
        raw: list[tuple[int | None, dict[str, Any]]] = []
        for kind, rec in records:
            if kind == 0:
                try:
                    msg = P.decode_json(rec, limit=len(rec) + 1)
                except P.ProtocolError:
                    continue
                f = msg.get("frame")
                raw.append((f if isinstance(f, int) and not isinstance(f, bool) else None, msg))
                continue
            try:
                m = P.decode_binary(rec)
            except P.ProtocolError as e:
                raise ReplayError(f"damaged record: {e}") from None
            if isinstance(m, P.Mesh):
                frames.append(replace(MeshFrame.from_mesh(m), server_time=m.frame * dt))
            elif isinstance(m, P.Track):
                tracks.append(TrackPoint(m.frame * dt, m.ball_position, m.hips, m.corners))
        if not frames:
            raise ReplayError("the replay holds no mesh frames")
        tracks.sort(key=lambda p: p.time)
        timeline = Timeline(frames)
        start = min([timeline.start, *(p.time for p in tracks[:1])])
        end = max([timeline.end, *(p.time for p in tracks[-1:])])
        # An event without a frame (none the server writes) is placed at the start.
        events = sorted(((start if f is None else f * dt, msg) for f, msg in raw),
                        key=lambda e: e[0])
        return cls(header, timeline, tracks, events, start, end)

    @property
    def duration(self) -> float:
        return self.end - self.start

    def seats(self) -> list[dict[str, Any]]:
        return list(self.header.get("players", []))


class ReplayPlayer:
    """A playhead over a replay: ``advance(dt)`` with the wall clock, ``seek``, ``speed``,
    ``paused``; ``sample()`` is the scene at the playhead."""

    def __init__(self, data: ReplayData, speed: float = 1.0, loop: bool = False) -> None:
        self.data = data
        self.t = data.start
        self.speed = float(speed)
        self.paused = False
        self.loop = loop
        self._track_times = [p.time for p in data.tracks]
        self._event_times = [e[0] for e in data.events]

    @property
    def position(self) -> float:
        """Seconds since the start of the recording."""
        return self.t - self.data.start

    @property
    def finished(self) -> bool:
        return self.t >= self.data.end and not self.loop

    def advance(self, dt: float) -> None:
        if self.paused or dt <= 0:
            return
        t = self.t + dt * self.speed
        if t > self.data.end and self.loop and self.data.duration > 0:
            t = self.data.start + (t - self.data.start) % self.data.duration
        self.t = min(t, self.data.end)

    def seek(self, seconds: float) -> None:
        """Jump to ``seconds`` after the start (clamped to the recording)."""
        self.t = float(np.clip(self.data.start + seconds, self.data.start, self.data.end))

    def seek_fraction(self, x: float) -> None:
        self.seek(float(np.clip(x, 0.0, 1.0)) * self.data.duration)

    def skip(self, seconds: float) -> None:
        self.seek(self.position + seconds)

    def toggle_pause(self) -> None:
        self.paused = not self.paused
        if not self.paused and self.finished:
            self.seek(0.0)

    def faster(self) -> None:
        i = bisect.bisect_right(SPEEDS, self.speed + 1e-9)
        self.speed = SPEEDS[min(i, len(SPEEDS) - 1)]

    def slower(self) -> None:
        i = bisect.bisect_left(SPEEDS, self.speed - 1e-9)
        self.speed = SPEEDS[max(i - 1, 0)]

    def _track_at(self, t: float) -> tuple[np.ndarray, np.ndarray] | None:
        tr = self.data.tracks
        if not tr:
            return None
        i = bisect.bisect_right(self._track_times, t)
        if i == 0:
            return tr[0].ball, tr[0].hips
        if i >= len(tr):
            return tr[-1].ball, tr[-1].hips
        a, b = tr[i - 1], tr[i]
        span = b.time - a.time
        w = 0.0 if span <= 0 else (t - a.time) / span
        return a.ball + (b.ball - a.ball) * w, a.hips + (b.hips - a.hips) * w

    def sample(self) -> Sample:
        s = self.data.timeline.sample(self.t)
        assert s is not None  # parse() refuses a replay without frames
        tr = self._track_at(self.t)
        if tr is not None:
            s = replace(s, ball_position=tr[0], hips=tr[1])
        return s

    def events_until(self) -> list[dict[str, Any]]:
        """The events at or before the playhead, in order."""
        i = bisect.bisect_right(self._event_times, self.t)
        return [e[1] for e in self.data.events[:i]]

    def scores(self) -> list[int]:
        """Scores at the playhead: the last score event's, or the round's start."""
        for ev in reversed(self.events_until()):
            if ev.get("event") == "score" and isinstance(ev.get("scores"), list):
                return list(ev["scores"])
        final = list(self.data.header.get("scores", [0, 0, 0, 0]))
        scorers = self.data.header.get("scorers", [])
        return [s - (1 if i in scorers else 0) for i, s in enumerate(final)]
