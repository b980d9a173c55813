"""``clothball accuracy --grid``: bad flags get a short error naming the flag; a tiny run
goes through end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest
from clothball.game.cli import main
from clothball.game.study.gamestart import events


@pytest.mark.parametrize("argv, flag", [
    (["--reference-sizes", "9"], "--reference-sizes"),
    (["--reference-sizes", "2,9"], "--reference-sizes"),
    (["--grid-sizes", "x"], "--grid-sizes"),
    (["--steps", "0"], "--steps"),
    (["--scene", "no-such-scene"], "no such scene"),
    (["--duration", "0"], "--duration"),
])
def test_bad_grid_flags(argv: list[str], flag: str, capsys) -> None:
    assert main(["accuracy", "--grid", *argv]) == 2
    err = capsys.readouterr().err
    assert flag in err and "Traceback" not in err


def test_a_tiny_grid_study(tmp_path, capsys) -> None:
    out = tmp_path / "grid.json"
    assert main(["accuracy", "--grid", "--grid-sizes", "9", "--reference-sizes", "5,9,17",
                 "--steps", "1,2", "--duration", "0.2", "--threads", "1",
                 "--json", str(out)]) == 0
    study = json.loads(out.read_text())["studies"][0]
    assert [r["n"] for r in study["runs"]] == [5, 9, 17, 9, 9]
    assert {row["substeps"] for row in study["rows"]} == {study["rows"][0]["substeps"] * f
                                                          for f in (1, 2)}
    assert "reference: Richardson limit from n = 5, 9, 17" in capsys.readouterr().out


def test_a_tiny_game_start_study(tmp_path, capsys) -> None:
    """``--grid --game-start``: each grid's trajectory and the distances between grids
    whose spacing halves, written as JSON."""
    out = tmp_path / "start.json"
    assert main(["accuracy", "--grid", "--game-start", "--scene", "default",
                 "--grid-sizes", "5,9,17", "--json", str(out)]) == 0
    table = json.loads(out.read_text())[0]
    assert table["ns"] == [5, 9, 17] and set(table["distances"]) == {"5,9", "9,17"}
    assert all(0.0 < d < 1.0 for d in table["distances"].values())
    assert "trajectory d (mm)" in capsys.readouterr().out


def test_game_start_events_of_a_known_motion() -> None:
    """A ball at 1 + 0.1 cos(4 pi t), sampled after each 1 ms frame: lowest at 0.25 s,
    0.9 m, and it rises 0.2 m to its next top."""
    dt = 1e-3
    t = dt * np.arange(1, 1001)
    q = events(1.0 + 0.1 * np.cos(4 * np.pi * t), dt)
    assert q["lowest_s"] == pytest.approx(0.25, abs=1e-6)
    assert q["lowest_y_m"] == pytest.approx(0.9, abs=1e-8)
    assert q["rebound_m"] == pytest.approx(0.2, abs=1e-8)
