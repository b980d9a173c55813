"""``clothball bench --load`` runs end to end (a tiny, short configuration): it grows rooms,
measures each step from the server's own counters and reports them. Speed is not asserted
here (docs/benchmarks/load.md has the figures)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pytest


@pytest.mark.slow
def test_load_bench_runs_and_reports_every_step(tmp_path) -> None:
    dest = tmp_path / "load.json"
    out = subprocess.run(
        [sys.executable, "-m", "clothball.game.cli", "bench", "--load", "--load-seconds", "1",
         "--load-max-rooms", "2", "--server-n", "12", "--hip-rate", "50",
         "--load-spectators", "1", "--json", str(dest)],
        capture_output=True, text=True, timeout=180, check=True,
    )
    r = json.loads(dest.read_text())
    assert r["n"] == 12 and r["spectators_per_room"] == 1 and r["cpus"] >= 1
    assert 1 <= len(r["steps"]) <= 2
    for i, step in enumerate(r["steps"], start=1):
        assert step["rooms"] == i and step["clients"] == 5 * i
        assert step["hip_offered_per_s"] == 200 * i
        assert step["messages_in_per_s"] > 0 and step["messages_out_per_s"] > 0
        assert step["lateness_p99_ms"] >= step["lateness_p50_ms"] >= 0
        assert isinstance(step["met"], bool)
    held = r["held"]
    assert held is None or held["met"]
    assert "load average" in out.stderr and "held:" in out.stdout


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("redis-server") is None,
                    reason="needs redis-server (apt: redis-server)")
def test_load_bench_over_a_cluster_places_rooms_on_every_host(tmp_path) -> None:
    dest = tmp_path / "cluster.json"
    out = subprocess.run(
        [sys.executable, "-m", "clothball.game.cli", "bench", "--load", "--cluster",
         "--cluster-hosts", "1,2", "--load-seconds", "1", "--load-max-rooms", "2",
         "--server-n", "12", "--hip-rate", "50", "--load-spectators", "1", "--json", str(dest)],
        capture_output=True, text=True, timeout=240, check=True,
    )
    r = json.loads(dest.read_text())
    assert set(r["hosts"]) == {"1", "2"} and "share" in r["note"]
    for n, series in r["hosts"].items():
        for i, step in enumerate(series["steps"], start=1):
            assert step["hosts"] == int(n) and step["rooms"] == i
            assert len(step["rooms_per_host"]) == int(n) and sum(step["rooms_per_host"]) == i
            assert step["messages_in_per_s"] > 0
    # The first host, asked for every room, places each on the least-loaded host.
    two = r["hosts"]["2"]["steps"]
    if len(two) == 2:
        assert sorted(two[1]["rooms_per_host"]) == [1, 1]
    assert "2 hosts: held" in out.stdout


@pytest.mark.slow
def test_load_bench_over_two_processes_on_one_port_spreads_the_rooms(tmp_path) -> None:
    dest = tmp_path / "workers.json"
    out = subprocess.run(
        [sys.executable, "-m", "clothball.game.cli", "bench", "--load", "--workers", "2",
         "--load-seconds", "1", "--load-max-rooms", "2", "--server-n", "12", "--hip-rate", "50",
         "--load-spectators", "1", "--json", str(dest)],
        capture_output=True, text=True, timeout=240, check=True,
    )
    r = json.loads(dest.read_text())
    assert r["workers"] == 2 and r["n"] == 12
    for i, step in enumerate(r["steps"], start=1):
        assert step["rooms"] == i and step["clients"] == 5 * i
        assert len(step["rooms_per_host"]) == 2 and sum(step["rooms_per_host"]) == i
        assert step["messages_in_per_s"] > 0
    # Rooms asked through the shared port go to the least-loaded process.
    if len(r["steps"]) == 2:
        assert sorted(r["steps"][1]["rooms_per_host"]) == [1, 1]
    assert "2 server processes on one port" in out.stderr


def test_load_bench_refuses_fewer_than_one_worker() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "clothball.game.cli", "bench", "--load", "--workers", "0"],
        capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "--workers must be at least 1" in out.stderr
    assert "Traceback" not in out.stderr
