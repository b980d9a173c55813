"""The accuracy study's facts and plumbing: float64 beats float32 at small steps on the
native engine, the fitted orders and the Pareto front, and a tiny end-to-end study that
writes its table, JSON and both plots."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from clothball.game import Scene
from clothball.game.accuracy import (
    Plan,
    fig4_start,
    fitted_order,
    make_sim,
    pareto_front,
    plot_error_vs_cost,
    plot_fig4,
    run_study,
    run_trajectory,
    table,
    trajectory_errors,
)
from clothball.game.cli import main


def small_drop() -> Scene:
    """The Fig. 4 set-up on a small, fine cloth, the ball let go just above it."""
    return Scene.from_dict({
        "cloth": {"n": 12, "size": 0.5},
        "ball": {"position": [0.0, 0.93, 0.0], "radius": 0.06},
    })


def test_float64_error_at_most_float32_at_small_dt(backend: str) -> None:
    """A gentle oscillation (1 mm bump on the hanging cloth): at 128 substeps a frame the
    step's own error is small enough that float32 rounding dominates float32's error."""
    scene = Scene.from_dict({"cloth": {"n": 10, "size": 0.5},
                             "sim": {"effects": ["structural", "gravity", "damping",
                                                 "coupling"]}})
    start = fig4_start(scene)
    n = scene.n
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    start.pos[..., 1] += 0.001 * np.sin(np.pi * i / (n - 1)) * np.sin(np.pi * j / (n - 1))
    s = 128
    ref_sim, _ = make_sim(scene, "semi_implicit_euler", "float64", 16 * s, backend)
    ref = run_trajectory(ref_sim, scene, start, 0.02, 5)
    errs = {}
    for prec in ("float32", "float64"):
        sim, engine = make_sim(scene, "semi_implicit_euler", prec, s, backend)
        assert engine == f"native-{backend}"
        errs[prec] = trajectory_errors(run_trajectory(sim, scene, start, 0.02, 5), ref)[0]
    assert 0 < errs["float64"] <= errs["float32"]


def test_fitted_order_and_pareto() -> None:
    dts = [1.0, 0.5, 0.25, 0.125]
    assert fitted_order(dts, [3 * d**2 for d in dts]) == pytest.approx(2.0)
    pts = [(1.0, 1.0), (2.0, 0.5), (3.0, 0.7), (4.0, 0.1), (0.5, 5.0), (5.0, math.inf)]
    assert pareto_front(pts) == [4, 0, 1, 3]


def test_tiny_study_end_to_end(tmp_path) -> None:
    scene = Scene.from_dict({"cloth": {"n": 6, "size": 0.5},
                             "ball": {"position": [0.0, 0.95, 0.0], "radius": 0.1}})
    plan = Plan(scene=scene, sizes=[6], integrators=["semi_implicit_euler"],
                precisions=["float32", "float64"], levels=2, duration_s=0.02, sample_ms=5,
                sag_sizes=[5], hold_s=0.02)
    labels: list[str] = []
    study = run_study(plan, labels.append)
    assert len(labels) == plan.cases() + 1
    assert len(study.rows) == 4
    for r in study.rows:
        assert math.isfinite(r.error_rms_m) and r.error_rms_m >= 0
        assert math.isfinite(r.us_per_sim_ms) and r.us_per_sim_ms > 0
        assert r.reference_substeps == 16 * 2 * study.rows[0].substeps
    assert study.rows[1].substeps == 2 * study.rows[0].substeps
    assert [c["n"] for c in study.sag_convergence] == [5, 6]
    text = table(study)
    assert "semi_implicit_euler" in text and "fitted order" in text
    data = study.to_json()
    json.dumps(data)  # serialisable (no NaN objects that break strict readers)
    for key in ("integrator", "precision", "n", "substeps", "error_rms_m", "ball_error_m",
                "us_per_sim_ms"):
        assert key in data["rows"][0]
    plot_error_vs_cost(study, str(tmp_path / "cost.png"))
    plot_fig4(study, str(tmp_path / "fig4.png"))
    for name in ("cost.png", "fig4.png"):
        assert (tmp_path / name).read_bytes()[:4] == b"\x89PNG"


def test_cli_refuses_bad_arguments(capsys) -> None:
    assert main(["accuracy", "--sizes", "2"]) == 2
    assert "--sizes" in capsys.readouterr().err
    assert main(["accuracy", "--integrators", "rk4"]) == 2
    assert "rk4" in capsys.readouterr().err


def test_ball_is_recorded_every_frame() -> None:
    scene = small_drop()
    start = fig4_start(scene)
    sim, _ = make_sim(scene, "semi_implicit_euler", "float64", 8, "cpu")
    run = run_trajectory(sim, scene, start, 0.01, 5)
    assert len(run.ball) == 11 and len(run.pos) == 3
    assert np.allclose(run.times_s[-1], 0.01)
