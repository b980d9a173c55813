"""The game's rules, pure: no network, no clock, no simulation. Illegal moves raise.

Seats and edges
---------------
Seat ``s`` (0..3) holds corner ``s`` of the cloth, in the corner order of
``game.sim.cloth.corners_of``: (0,0), (0,n-1), (n-1,n-1), (n-1,0), which rest at
(-x,-z), (+x,-z), (+x,+z), (-x,+z) (y is up). Seen from above (looking down -y, +x to the
right, so +z points down the screen) that order runs **clockwise**, and seat ``s`` guards
the edge from its own corner to the next one clockwise, corner ``(s+1) % 4``:

======  ========  ===================  ==========
 seat    edge      from -> to corner    at rest
======  ========  ===================  ==========
 0       north     0 -> 1               z = -size/2
 1       east      1 -> 2               x = +size/2
 2       south     2 -> 3               z = +size/2
 3       west      3 -> 0               x = -size/2
======  ========  ===================  ==========

Leaving the cloth
-----------------
The ball has left by edge ``e`` when its centre is outside the corner quadrilateral across
``e`` (seen from above) *and* below the height of that edge at that point (the line between
the edge's two corners), or when it falls below the floor (then the edge it is furthest
outside of, or nearest to, counts). The guard of that edge concedes; every other seated
player scores one point. An edge nobody guards concedes nothing: the round is void.

A match is first to ``first_to`` points. Several players can reach it on the same
concession; they share the win.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

SEATS = 4
EDGE_NAMES = ("north", "east", "south", "west")
STATES = ("waiting", "countdown", "playing", "over")
MAX_FIRST_TO = 99


class IllegalMove(ValueError):
    """A move the rules do not allow in the current state (the message says why)."""


def edge_of_seat(seat: int) -> int:
    """The edge a seat guards: from its corner to the next one clockwise."""
    _check_seat(seat)
    return seat


def guard_of_edge(edge: int) -> int:
    """The seat that guards an edge."""
    _check_seat(edge, "edge")
    return edge


def edge_corners(edge: int) -> tuple[int, int]:
    """The two corners an edge runs between, clockwise seen from above."""
    _check_seat(edge, "edge")
    return edge, (edge + 1) % SEATS


def _check_seat(seat: object, what: str = "seat") -> None:
    if isinstance(seat, bool) or not isinstance(seat, int | np.integer) or not 0 <= seat < SEATS:
        raise IllegalMove(f"{what}: must be a whole number 0..{SEATS - 1}, got {seat!r}")


def edge_distances(ball: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Signed distance (m, seen from above) of the ball's centre outside each edge's line.

    Positive means outside the corner quadrilateral across that edge. Outward normals point
    away from the corners' centroid, so the result does not depend on the winding. Each
    dot product is written out (no BLAS call, which may fuse or reorder it), so that the
    answer is the same wherever it runs, and the frame loop's (native/loop/exit.hpp), which
    computes it step for step, can be tested against it bit for bit.
    """
    c = np.asarray(corners, dtype=np.float64)[:, (0, 2)]
    px, pz = (float(v) for v in np.asarray(ball, dtype=np.float64)[[0, 2]])
    mx = (((c[0, 0] + c[1, 0]) + c[2, 0]) + c[3, 0]) / 4.0
    mz = (((c[0, 1] + c[1, 1]) + c[2, 1]) + c[3, 1]) / 4.0
    out = np.empty(SEATS)
    for e in range(SEATS):
        ax, az = float(c[e, 0]), float(c[e, 1])
        dx, dz = float(c[(e + 1) % SEATS, 0]) - ax, float(c[(e + 1) % SEATS, 1]) - az
        # sqrt of the sum, not math.hypot: Python's hypot and the C library's differ by an
        # ulp in about 1 case of 160, which can flip the sign of a ball on an edge's line.
        length = math.sqrt(dx * dx + dz * dz)
        if length < 1e-12:
            nx, nz = ax - mx, az - mz
            nl = math.sqrt(nx * nx + nz * nz)
            nx, nz = (nx / nl, nz / nl) if nl > 1e-12 else (1.0, 0.0)
        else:
            nx, nz = dz / length, -dx / length
            if nx * (ax - mx) + nz * (az - mz) < 0.0:
                nx, nz = -nx, -nz
        out[e] = (px - ax) * nx + (pz - az) * nz
    return out


def edge_height(ball: np.ndarray, corners: np.ndarray, edge: int) -> float:
    """Height of an edge's corner-to-corner line where the ball's centre projects onto it."""
    i, j = edge_corners(edge)
    c = np.asarray(corners, dtype=np.float64)
    ax, ay, az = (float(v) for v in c[i])
    bx, by, bz = (float(v) for v in c[j])
    px, pz = float(ball[0]), float(ball[2])
    dx, dz = bx - ax, bz - az
    dd = dx * dx + dz * dz
    t = 0.0 if dd < 1e-24 else ((px - ax) * dx + (pz - az) * dz) / dd
    t = min(1.0, max(0.0, t))
    return ay + t * (by - ay)


def exit_edge(ball: np.ndarray, corners: np.ndarray, floor_y: float) -> int | None:
    """The edge the ball has left the cloth by, or None while it is still in play.

    The server runs one exit check, the frame loop's (native/loop/exit.hpp, every frame);
    this is the reference it is tested against (tests/server/test_rules.py) and the rule
    as the docs state it."""
    ball = np.asarray(ball, dtype=np.float64)
    dist = edge_distances(ball, corners)
    crossed = [e for e in range(SEATS) if dist[e] > 0.0 and ball[1] < edge_height(ball, corners, e)]
    if crossed:
        return max(crossed, key=lambda e: dist[e])
    if ball[1] < floor_y:
        return int(np.argmax(dist))
    return None


@dataclass(frozen=True)
class RoundResult:
    """What one concession did to the match."""

    round: int
    edge: int
    conceded_by: int | None  # None: nobody guards that edge, the round is void
    scorers: tuple[int, ...]
    scores: tuple[int, ...]
    match_over: bool
    winners: tuple[int, ...]


@dataclass
class Match:
    """The state of one match: scores, round number and phase. Pure; raises on illegal moves.

    Phases: ``waiting`` (no match yet) -> ``countdown`` -> ``playing`` -> (concession)
    ``countdown`` -> ``playing`` ... -> ``over`` once someone reaches ``first_to``.
    """

    first_to: int = 5
    scores: list[int] = field(default_factory=lambda: [0] * SEATS)
    state: str = "waiting"
    round: int = 0
    winners: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        ft = self.first_to
        if isinstance(ft, bool) or not isinstance(ft, int) or not 1 <= ft <= MAX_FIRST_TO:
            raise IllegalMove(f"first_to: must be a whole number 1..{MAX_FIRST_TO}, got {ft!r}")

    def start(self, seated: Iterable[int]) -> None:
        """Begin a new match (scores to zero) with a countdown to its first round."""
        seats = _seat_set(seated)
        if self.state in ("countdown", "playing"):
            raise IllegalMove(f"start: a match is already running ({self.state})")
        if not seats:
            raise IllegalMove("start: nobody is seated")
        self.scores = [0] * SEATS
        self.round = 0
        self.winners = ()
        self.state = "countdown"

    def begin_round(self) -> int:
        """The countdown is over: the ball is in play. Returns the round number (1-based)."""
        if self.state != "countdown":
            raise IllegalMove(f"begin_round: only after a countdown, not while {self.state}")
        self.round += 1
        self.state = "playing"
        return self.round

    def concede(self, edge: int, seated: Iterable[int]) -> RoundResult:
        """The ball left by ``edge``: its guard concedes, every other seated player scores."""
        _check_seat(edge, "edge")
        seats = _seat_set(seated)
        if self.state != "playing":
            raise IllegalMove(f"concede: no round is being played ({self.state})")
        guard = guard_of_edge(edge)
        conceded_by = guard if guard in seats else None
        scorers: tuple[int, ...] = ()
        if conceded_by is not None:
            scorers = tuple(sorted(s for s in seats if s != conceded_by))
            for s in scorers:
                self.scores[s] += 1
        self.winners = tuple(s for s in range(SEATS) if self.scores[s] >= self.first_to)
        self.state = "over" if self.winners else "countdown"
        return RoundResult(
            round=self.round,
            edge=edge,
            conceded_by=conceded_by,
            scorers=scorers,
            scores=tuple(self.scores),
            match_over=bool(self.winners),
            winners=self.winners,
        )

    def abort(self) -> None:
        """Stop the match where it stands (everyone left); scores are kept for display."""
        if self.state in ("countdown", "playing"):
            self.state = "waiting"


def _seat_set(seated: Iterable[int]) -> frozenset[int]:
    seats = frozenset(seated)
    for s in seats:
        _check_seat(s)
    return seats
