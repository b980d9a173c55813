"""The pure game rules: edges, leaving the cloth, scoring, phases, illegal moves."""

from __future__ import annotations

import numpy as np
import pytest
from clothball.game.cloth import corners_of, rest_positions
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
from clothball.game.scene import Scene
from hypothesis import given
from hypothesis import strategies as st

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
