"""The CG cost measurement's plumbing on the CPU (its timings are the GPU run's to read):
every case is measured, forced cases report their cap, and the iterations CG needs grow as
the tolerance tightens."""

from __future__ import annotations

import json

from clothball.game.study.cg_cost import FORCED, TOLERANCES, main


def test_cg_cost_rows(tmp_path, capsys) -> None:
    out = tmp_path / "cg.json"
    assert main(["--backend", "cpu", "--sizes", "12", "--precisions", "float64",
                 "--frames", "2", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())
    assert len(rows) == len(FORCED) + len(TOLERANCES)
    forced = [r for r in rows if r["cg_tolerance"] == 0]
    assert [r["iterations"] for r in forced] == [float(k) for k in FORCED]
    needed = [r["iterations"] for r in rows if r["cg_tolerance"] > 0]
    assert needed == sorted(needed) and 0 < needed[0] < needed[-1] <= 200
    assert all(r["us_per_substep"] > 0 for r in rows)
    assert "us/substep" in capsys.readouterr().out


def test_cg_cost_bad_sizes(capsys) -> None:
    assert main(["--backend", "cpu", "--sizes", "x"]) == 2
    assert "--sizes" in capsys.readouterr().err


def test_cg_cost_unroll_rows_and_bad_unroll(tmp_path, capsys) -> None:
    out = tmp_path / "cg.json"
    assert main(["--backend", "cpu", "--sizes", "8", "--precisions", "float64", "--frames",
                 "1", "--unroll", "1,4", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())
    assert [r["unroll"] for r in rows] == [1] * (len(rows) // 2) + [4] * (len(rows) // 2)
    assert "unroll 4" in capsys.readouterr().out
    for bad in ("0", "x", "4,33"):
        assert main(["--backend", "cpu", "--sizes", "8", "--unroll", bad]) == 2
        assert "--unroll" in capsys.readouterr().err
