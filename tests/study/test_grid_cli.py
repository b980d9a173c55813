"""``clothball accuracy --grid``: bad flags get a short error naming the flag; a tiny run
goes through end to end."""

from __future__ import annotations

import json

import pytest
from clothball.game.cli import main


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
