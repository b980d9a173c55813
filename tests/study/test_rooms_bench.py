"""``clothball bench --rooms``: the search over room counts and the JSON it writes (what it
measures is reported, not asserted)."""

from __future__ import annotations

import json
import subprocess
import sys

from clothball.game.study.rooms import counts, held_counts


def test_counts_double_then_bisect_to_the_largest_held() -> None:
    for limit in (1, 5, 37, 100, 1000):
        tried = list(counts(4096, lambda k, limit=limit: k <= limit))
        doubling = [1 << i for i in range(limit.bit_length() + 1)]
        assert tried[: len(doubling)] == doubling  # 1, 2, 4, ... past the limit
        best = max(k for k in tried if k <= limit)
        assert limit - best <= max(1, best // 16)  # within the resolution
        assert len(tried) == len(set(tried))  # no count tried twice
    assert list(counts(8, lambda k: True)) == [1, 2, 4, 8]  # stops at the cap
    assert list(counts(8, lambda k: False)) == [1]


def test_held_counts_take_the_largest_held_row() -> None:
    rows = [{"backend": "cpu", "precision": "float32", "n": 16, "rooms": r, "held": h}
            for r, h in ((1, True), (2, True), (4, False), (3, True))]
    assert held_counts(rows) == {("cpu", "float32", 16): 3}


def test_bench_rooms_writes_its_rows(tmp_path) -> None:
    out = tmp_path / "rooms.json"
    r = subprocess.run(
        [sys.executable, "-m", "clothball.game.cli", "bench", "--rooms", "--backends", "cpu",
         "--sizes", "8", "--rooms-frames", "20", "--max-rooms", "4", "--json", str(out)],
        capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    rows = json.loads(out.read_text())["rows"]
    assert [row["rooms"] for row in rows][:1] == [1]
    for row in rows:
        assert {"backend", "precision", "n", "rooms", "frame_us_p50", "frame_us_p99",
                "mesh_us_per_room", "held"} <= set(row)
        assert row["backend"] == "cpu" and row["n"] == 8 and row["precision"] == "float32"
        assert 0 < row["frame_us_p50"] <= row["frame_us_p99"]
        assert row["mesh_us_per_room"] > 0
    assert "rooms held at 1 kHz" in r.stdout


def test_bench_rooms_refuses_bad_sizes(clothball_cli) -> None:
    r = clothball_cli("bench", "--rooms", "--backends", "cpu", "--sizes", "1000")
    assert r.returncode == 2 and "--sizes" in r.stderr and "Traceback" not in r.stderr
