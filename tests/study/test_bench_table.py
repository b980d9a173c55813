"""``clothball bench`` (the Table 1 re-measurement): its JSON rows and the verdicts it
prints on issue 2's GPU targets."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from clothball.game.study.bench import gpu_target_verdicts


def _row(n: int, precision: str, us: float, backend: str = "cuda") -> dict:
    bytes_min = 12 * (4 if precision == "float32" else 8) * n * n
    return {"n": n, "backend": backend, "precision": precision, "substep_us": us,
            "effective_gbs": bytes_min / (us * 1e-6) / 1e9}


def test_verdicts_take_the_worst_row_of_each_target() -> None:
    copy = 3000.0
    # n = 2048 moves 201 MB a substep: at 84.0 us that is 2396.6 GB/s, 79.9 % of 3000.
    rows = [_row(25, "float32", 2.4), _row(250, "float32", 2.6), _row(512, "float32", 9.0),
            _row(2048, "float32", 84.0), _row(4096, "float32", 320.0),
            _row(2048, "float64", 84.0 * 2.2), _row(4096, "float64", 320.0 * 2.4),
            _row(100, "float32", 99.0, backend="cpu")]
    lines = gpu_target_verdicts(rows, copy)
    assert len(lines) == 3
    # The worst small-n row is n = 250 (n = 512 is beyond the target's range, and the CPU
    # row is not the GPU's).
    assert "worst 2.60 us (n = 250): MISSED" in lines[0]
    frac = 12 * 4 * 2048**2 / 84.0e-6 / 1e9 / copy
    assert frac < 0.80
    assert f"worst {frac:.1%} (n = 2048): MISSED" in lines[1]
    assert "worst 2.40x (n = 4096): met" in lines[2]


def test_verdicts_say_met_and_skip_targets_not_run() -> None:
    lines = gpu_target_verdicts([_row(50, "float32", 2.5)], 3000.0)
    assert lines == ["float32 <= 2.5 us per substep at n <= 256: worst 2.50 us (n = 50): met"]
    assert gpu_target_verdicts([_row(50, "float32", 2.0, backend="cpu")], None) == []


def test_bench_writes_the_rows_it_prints(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    proc = subprocess.run(
        [sys.executable, "-m", "clothball.game.cli", "bench", "--quick", "--backends", "cpu",
         "--sizes", "25", "--json", str(out)],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(out.read_text())["rows"]
    assert [(r["n"], r["backend"], r["precision"]) for r in rows] == [
        (25, "cpu", "float32"), (25, "cpu", "float64")]
    for r in rows:
        assert r["substep_us"] > 0
        want = r["min_bytes_per_substep"] / (r["substep_us"] * 1e-6) / 1e9
        assert r["effective_gbs"] == pytest.approx(want, rel=1e-9)
        assert f"{r['substep_us']:.2f}" in proc.stdout  # the table shows what the file holds
    assert "GPU targets" not in proc.stdout  # no CUDA rows, no GPU verdicts


@pytest.mark.slow
def test_effects_bench_runs_on_a_scene_that_sets_keys_of_its_own_effects(tmp_path: Path) -> None:
    """``bench --effects --scene default``: the default scene sets keys of shear, bend and
    coupling, which the subsets without those effects drop (before, the first such subset
    stopped the bench with a scene error). Every case gets a positive time."""
    dest = tmp_path / "effects.json"
    out = subprocess.run(
        [sys.executable, "-m", "clothball.game.cli", "bench", "--effects", "--scene", "default",
         "--sizes", "8", "--backends", "cpu", "--precisions", "float32", "--repeats", "1",
         "--json", str(dest)],
        capture_output=True, text=True, timeout=240, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = json.loads(dest.read_text())
    rows = rows["rows"] if isinstance(rows, dict) else rows
    labels = {r["label"] for r in rows}
    assert {"structural alone", "shear alone", "+ bend", "default as shipped",
            "default without ball"} <= labels
    assert all(r["substep_us"] > 0 and r["n"] == 8 for r in rows)
