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
from collections.abc import Iterable, Sequence
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
    away from the corners' centroid, so the result does not depend on the winding.
    """
    c = np.asarray(corners, dtype=np.float64)[:, (0, 2)]
    p = np.asarray(ball, dtype=np.float64)[[0, 2]]
    centroid = c.mean(axis=0)
    out = np.empty(SEATS)
    for e in range(SEATS):
        a, b = c[e], c[(e + 1) % SEATS]
        d = b - a
        length = float(np.hypot(*d))
        if length < 1e-12:
            normal = a - centroid
            nl = float(np.hypot(*normal))
            normal = normal / nl if nl > 1e-12 else np.array([1.0, 0.0])
        else:
            normal = np.array([d[1], -d[0]]) / length
            if float(np.dot(normal, a - centroid)) < 0.0:
                normal = -normal
        out[e] = float(np.dot(p - a, normal))
    return out


def edge_height(ball: np.ndarray, corners: np.ndarray, edge: int) -> float:
    """Height of an edge's corner-to-corner line where the ball's centre projects onto it."""
    i, j = edge_corners(edge)
    c = np.asarray(corners, dtype=np.float64)
    a, b = c[i], c[j]
    d = (b - a)[[0, 2]]
    dd = float(np.dot(d, d))
    t = 0.0 if dd < 1e-24 else float(np.dot(np.asarray(ball)[[0, 2]] - a[[0, 2]], d)) / dd
    t = min(1.0, max(0.0, t))
    return float(a[1] + t * (b[1] - a[1]))


def exit_edge(ball: np.ndarray, corners: np.ndarray, floor_y: float) -> int | None:
    """The edge the ball has left the cloth by, or None while it is still in play."""
    ball = np.asarray(ball, dtype=np.float64)
    dist = edge_distances(ball, corners)
    crossed = [e for e in range(SEATS) if dist[e] > 0.0 and ball[1] < edge_height(ball, corners, e)]
    if crossed:
        return max(crossed, key=lambda e: dist[e])
    if ball[1] < floor_y:
        return int(np.argmax(dist))
    return None


# Margins of the pre-test below, relative to the size of the coordinates involved. The two
# computations of one signed distance differ by a few ulps of that size (about 1e-15 of
# it); these margins are six orders of magnitude wider.
_INSIDE_MARGIN = 1e-9
_SHORT_EDGE = 1e-4


def ball_clearly_in_play(ball: Sequence[float], corners: Sequence[Sequence[float]],
                         floor_y: float) -> bool:
    """A cheap, conservative pre-test of ``exit_edge``: True only when ``exit_edge`` would
    return None, because the ball is not below the floor and its centre is inside every
    edge's line by a clear margin (seen from above). False means "not sure": ask
    ``exit_edge``. Plain floats, no NumPy: a few microseconds instead of tens.

    Exact where it answers: ``exit_edge`` can only return an edge whose signed distance
    (``edge_distances``) is positive, or when the ball is below the floor. This recomputes
    each distance with the same formula (the same outward normal, away from the corners'
    centroid) and answers True only when every one is negative by ``_INSIDE_MARGIN`` times
    the coordinates' size, far beyond the rounding by which the two computations can differ;
    an edge shorter than ``_SHORT_EDGE`` times that size (its normal ill-conditioned), a
    centroid nearly on an edge's line, or a NaN/Inf gives False. The floor test is the same
    comparison of the same floats. ``tests/test_rules.py`` checks the equivalence with
    hypothesis.
    """
    px, py, pz = float(ball[0]), float(ball[1]), float(ball[2])
    if not py >= floor_y:  # exit_edge tests ball[1] < floor_y (NaN: not sure)
        return False
    xs = [float(c[0]) for c in corners]
    zs = [float(c[2]) for c in corners]
    scale = 1.0 + max(abs(px), abs(pz), *map(abs, xs), *map(abs, zs))
    tol = _INSIDE_MARGIN * scale
    short = _SHORT_EDGE * scale
    cx = (xs[0] + xs[1] + xs[2] + xs[3]) * 0.25
    cz = (zs[0] + zs[1] + zs[2] + zs[3]) * 0.25
    for e in range(SEATS):
        ax, az = xs[e], zs[e]
        dx, dz = xs[(e + 1) % SEATS] - ax, zs[(e + 1) % SEATS] - az
        length = math.hypot(dx, dz)
        if not length >= short:
            return False
        # Unit normal (dz, -dx) / length; s: its side of the centroid, q: the ball's.
        s = (dz * (ax - cx) - dx * (az - cz)) / length
        q = (dz * (px - ax) - dx * (pz - az)) / length
        if s > tol:  # the normal points outward: distance q
            if not q < -tol:
                return False
        elif s < -tol:  # exit_edge flips the normal: distance -q
            if not q > tol:
                return False
        else:
            return False
    return True


def exit_edge_fast(ball: Sequence[float], corners: Sequence[Sequence[float]],
                   floor_y: float) -> int | None:
    """``exit_edge`` with the pre-test first: the same answer, cheaply while the ball is
    clearly on the cloth (the room thread asks every frame)."""
    if ball_clearly_in_play(ball, corners, floor_y):
        return None
    return exit_edge(np.asarray(ball, dtype=np.float64), np.asarray(corners, dtype=np.float64),
                     floor_y)


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
