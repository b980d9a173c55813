"""The pure game rules: edges, leaving the cloth, scoring, phases, illegal moves."""

from __future__ import annotations

import numpy as np
import pytest
from clothball import _native
from clothball.game.rules import (
    EDGE_NAMES,
    IllegalMove,
    Match,
    edge_corners,
    edge_distances,
    edge_of_seat,
    exit_edge,
    guard_of_edge,
)
from clothball.game.sim.cloth import corners_of, rest_positions
from clothball.game.sim.scene import Scene
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.conftest import examples

SCENE = Scene.load("classic").with_changes({"cloth": {"n": 8}})
CORNERS = corners_of(rest_positions(SCENE))  # (-,-z) (+,-z) (+,+z) (-,+z) at y = 1
FLOOR = -1.0


def test_corner_order_runs_clockwise_seen_from_above() -> None:
    # Seen from above, +x points right and +z down the screen (screen up is -z). In
    # screen axes a clockwise polygon has a negative shoelace area.
    x, zdown = CORNERS[:, 0], CORNERS[:, 2]
    screen_y = -zdown  # screen up is -z
    area = 0.5 * sum(
        x[i] * screen_y[(i + 1) % 4] - x[(i + 1) % 4] * screen_y[i] for i in range(4)
    )
    assert area < 0  # clockwise in ordinary screen-up axes


def test_each_seat_guards_the_edge_to_the_next_corner() -> None:
    assert [edge_of_seat(s) for s in range(4)] == [0, 1, 2, 3]
    assert [guard_of_edge(e) for e in range(4)] == [0, 1, 2, 3]
    assert [edge_corners(e) for e in range(4)] == [(0, 1), (1, 2), (2, 3), (3, 0)]
    assert EDGE_NAMES == ("north", "east", "south", "west")
    # north edge is z = -size/2: both its corners have z = -0.5
    assert CORNERS[0, 2] == CORNERS[1, 2] == -0.5


@pytest.mark.parametrize(
    ("ball", "edge"),
    [
        ((0.0, 0.5, -0.7), 0),  # beyond z = -0.5, below y = 1
        ((0.7, 0.5, 0.0), 1),
        ((0.0, 0.5, 0.7), 2),
        ((-0.7, 0.5, 0.0), 3),
    ],
)
def test_ball_beyond_an_edge_and_below_it_has_left_by_that_edge(ball, edge) -> None:
    assert exit_edge(np.array(ball), CORNERS, FLOOR) == edge


def test_ball_beyond_an_edge_but_above_it_is_still_in_play() -> None:
    assert exit_edge(np.array([0.0, 1.3, -0.7]), CORNERS, FLOOR) is None


def test_ball_inside_is_in_play_even_when_low() -> None:
    assert exit_edge(np.array([0.1, 0.2, 0.1]), CORNERS, FLOOR) is None


def test_ball_below_the_floor_counts_for_the_nearest_edge() -> None:
    assert exit_edge(np.array([0.45, -2.0, 0.0]), CORNERS, FLOOR) == 1
    assert exit_edge(np.array([0.0, -2.0, -0.45]), CORNERS, FLOOR) == 0


def test_edge_height_follows_the_corners() -> None:
    c = CORNERS.copy()
    c[0, 1] = c[1, 1] = 0.2  # north edge lowered to y = 0.2
    assert exit_edge(np.array([0.0, 0.5, -0.7]), c, FLOOR) is None  # above the lowered edge
    assert exit_edge(np.array([0.0, 0.1, -0.7]), c, FLOOR) == 0


@given(
    st.floats(-0.49, 0.49), st.floats(-0.49, 0.49), st.floats(-0.9, 3.0),
)
def test_any_point_inside_the_quad_is_in_play(x: float, z: float, y: float) -> None:
    assert exit_edge(np.array([x, y, z]), CORNERS, FLOOR) is None
    assert np.all(edge_distances(np.array([x, y, z]), CORNERS) < 0)


def test_winding_does_not_matter() -> None:
    mirrored = CORNERS[::-1].copy()
    d = edge_distances(np.array([0.0, 0.0, 0.0]), mirrored)
    assert np.all(d < 0)


def test_scoring_every_other_seated_player_scores() -> None:
    m = Match(first_to=3)
    m.start([0, 1, 2, 3])
    assert m.state == "countdown"
    assert m.begin_round() == 1
    r = m.concede(2, [0, 1, 2, 3])
    assert r.conceded_by == 2 and r.scorers == (0, 1, 3)
    assert r.scores == (1, 1, 0, 1) and not r.match_over
    assert m.state == "countdown"


def test_unguarded_edge_is_a_void_round() -> None:
    m = Match()
    m.start([0, 2])
    m.begin_round()
    r = m.concede(1, [0, 2])
    assert r.conceded_by is None and r.scorers == () and r.scores == (0, 0, 0, 0)


def test_first_to_n_ends_the_match_and_ties_share_it() -> None:
    m = Match(first_to=2)
    m.start([0, 1, 2])
    for _ in range(2):
        m.begin_round()
        r = m.concede(0, [0, 1, 2])
    assert r.match_over and r.winners == (1, 2) and m.state == "over"
    with pytest.raises(IllegalMove):
        m.begin_round()
    m.start([0, 1])  # a new match after the end
    assert m.scores == [0, 0, 0, 0] and m.round == 0


def test_one_player_practice_match() -> None:
    m = Match(first_to=1)
    m.start([3])
    m.begin_round()
    r = m.concede(3, [3])
    assert r.conceded_by == 3 and r.scorers == () and not r.match_over


@pytest.mark.parametrize("bad", [0, 100, -1, 2.5, True, "5", None])
def test_first_to_must_be_sane(bad) -> None:
    with pytest.raises(IllegalMove, match="first_to"):
        Match(first_to=bad)


def test_illegal_moves_raise() -> None:
    m = Match()
    with pytest.raises(IllegalMove, match="nobody"):
        m.start([])
    with pytest.raises(IllegalMove, match="countdown"):
        m.begin_round()
    with pytest.raises(IllegalMove, match="no round"):
        m.concede(0, [0])
    m.start([0, 1])
    with pytest.raises(IllegalMove, match="already"):
        m.start([0, 1])
    m.begin_round()
    for bad in (4, -1, 1.0, True, "0"):
        with pytest.raises(IllegalMove):
            m.concede(bad, [0, 1])  # type: ignore[arg-type]
    with pytest.raises(IllegalMove, match="seat"):
        m.concede(0, [0, 7])
    with pytest.raises(IllegalMove):
        edge_of_seat(4)


def test_abort_returns_to_waiting_and_keeps_scores() -> None:
    m = Match()
    m.start([0, 1])
    m.begin_round()
    m.concede(0, [0, 1])
    m.abort()
    assert m.state == "waiting" and m.scores[1] == 1


# --- the frame loop's exit check (native/loop/exit.hpp) against exit_edge -------------------

_coord = st.floats(-2.0, 2.0, allow_nan=False, width=64)
_tiny = st.sampled_from([0.0, 1e-300, 1e-17, 1e-15, 1e-13, 1e-12, 1e-10, 1e-9, 1e-8, 1e-6,
                         1e-3]).flatmap(lambda v: st.sampled_from([v, -v]))


@st.composite
def _corners(draw: st.DrawFn) -> np.ndarray:
    kind = draw(st.sampled_from(["near_rest", "anywhere", "degenerate", "float32"]))
    if kind == "anywhere":
        c = np.array(draw(st.lists(st.tuples(_coord, _coord, _coord), min_size=4, max_size=4)))
    else:
        jitter = draw(st.floats(0.0, 0.4))
        d = np.array(draw(st.lists(st.tuples(_coord, _coord, _coord), min_size=4, max_size=4)))
        c = CORNERS + jitter * d
    if kind == "degenerate":  # corners on top of each other, or very nearly
        i, j = draw(st.sampled_from([(0, 1), (1, 2), (2, 3), (3, 0), (0, 2)]))
        c[j] = c[i] + draw(_tiny)
        if draw(st.booleans()):
            c[:] = c[0]
    if kind == "float32":  # what a float32 engine hands over
        c = c.astype(np.float32).astype(np.float64)
    return c


@st.composite
def _ball(draw: st.DrawFn, corners: np.ndarray) -> np.ndarray:
    kind = draw(st.sampled_from(["anywhere", "on_edge", "centroid", "corner"]))
    y = draw(st.one_of(_coord, st.just(FLOOR + draw(_tiny))))
    if kind == "anywhere":
        x, z = draw(_coord), draw(_coord)
    elif kind == "centroid":
        x, z = corners[:, 0].mean(), corners[:, 2].mean()
    elif kind == "corner":
        k = draw(st.integers(0, 3))
        x, z = corners[k, 0] + draw(_tiny), corners[k, 2] + draw(_tiny)
    else:  # on an edge's line, or a hair either side of it
        e = draw(st.integers(0, 3))
        a, b = corners[e], corners[(e + 1) % 4]
        t = draw(st.floats(-0.2, 1.2))
        d = (b - a)[[0, 2]]
        n = np.array([d[1], -d[0]])
        off = draw(_tiny)
        x, z = (a[[0, 2]] + t * d + off * n).tolist()
    return np.array([x, y, z], dtype=np.float64)


@st.composite
def _exit_case(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, float]:
    corners = draw(_corners())
    ball = draw(_ball(corners))
    floor = draw(st.one_of(st.just(FLOOR), _coord))
    return ball, corners, floor


@given(_exit_case())
@settings(max_examples=examples(3000), deadline=None)
def test_the_frame_loops_exit_check_agrees_with_exit_edge(case) -> None:
    """The one exit check the server runs (the native loop's) gives ``exit_edge``'s answer,
    also for degenerate quadrilaterals, balls a hair from an edge's line and float32
    corners."""
    ball, corners, floor = case
    want = exit_edge(ball, corners, floor)
    got = _native.exit_edge(ball, corners.reshape(12), floor)
    assert (None if got < 0 else got) == want
