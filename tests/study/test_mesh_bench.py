"""``clothball bench --mesh``: the MESH encoder's rows and the JSON it writes (what it
measures is reported, not asserted; the bytes of its fixed cloth states are facts)."""

from __future__ import annotations

import json

import pytest


def test_bench_mesh_writes_a_row_per_size_and_coding(tmp_path, clothball_cli) -> None:
    out = tmp_path / "mesh.json"
    r = clothball_cli("bench", "--mesh", "--backends", "cpu", "--sizes", "8,40",
                      "--mesh-rounds", "5", "--json", str(out), timeout=300)
    assert r.returncode == 0, r.stderr
    rows = json.loads(out.read_text())["rows"]
    assert [(row["n"], row["version"], row["deflater"]) for row in rows] == [
        (n, v, d) for n in (8, 40)
        for v, d in ((1, "zlib"), (2, "libdeflate"), (2, "literals"))]
    for row in rows:
        assert row["states"] == 30 and row["encodes"] == 5 * 30
        assert 0 < row["us_median"] <= row["us_p90"]
        assert row["bytes_min"] <= row["bytes_median"] <= row["bytes_max"] <= row["bytes_raw"]
    v1, *v2 = [row for row in rows if row["n"] == 40]
    assert all(row["bytes_median"] < 0.8 * v1["bytes_median"] for row in v2)  # the game's cloth
    assert "n = 40: v2 (literals) takes" in r.stdout


@pytest.mark.parametrize("args", [("--sizes", "1"), ("--sizes", "x"), ("--sizes", "8,2000"),
                                  ("--mesh-rounds", "0")])
def test_bench_mesh_refuses_bad_arguments(clothball_cli, args: tuple[str, str]) -> None:
    r = clothball_cli("bench", "--mesh", "--backends", "cpu", *args)
    assert r.returncode == 2 and args[0] in r.stderr and "Traceback" not in r.stderr
