"""What a hand feels (``game/study/feel.py``): the step-response figures against signals whose
figures are known in closed form, and the default scene's feel measured to its end."""

from __future__ import annotations

import math

import numpy as np
import pytest
from clothball.game import Scene
from clothball.game.study.feel import BANDS, RUN_S, TAIL_S, feel, response

DT = 1e-3


def test_a_first_order_step_settles_at_tau_ln_of_the_band() -> None:
    """rest + step (1 - exp(-t / tau)) is within b of the step after tau ln(1 / b); its peak
    is its end."""
    tau, rest, step = 0.2, 4.0, 1.5
    t = np.arange(1, 4001) * DT
    f = rest + step * (1.0 - np.exp(-t / tau))
    r = response(f, 0, rest, DT)
    assert r.settled_n == pytest.approx(rest + step, abs=1e-6)
    for band, ms in zip(BANDS, r.settling_ms, strict=True):
        assert ms == pytest.approx(tau * math.log(1 / band) * 1e3, abs=1.0)
    assert r.peak_ms == pytest.approx(t[-1] * 1e3)


def test_an_underdamped_step_peaks_at_its_overshoot() -> None:
    """A second-order step response (damping ratio z, natural frequency w) peaks at
    pi / (w sqrt(1 - z^2)) with overshoot exp(-z pi / sqrt(1 - z^2)) of the step, from
    an event that starts ``start`` frames into the signal."""
    z, w, rest, step, start = 0.3, 2 * math.pi * 3.0, 5.0, 2.0, 250
    wd = w * math.sqrt(1 - z * z)
    t = np.arange(1, 4001) * DT
    x = 1 - np.exp(-z * w * t) * (np.cos(wd * t) + z / math.sqrt(1 - z * z) * np.sin(wd * t))
    f = np.concatenate([np.full(start, rest), rest + step * x])
    r = response(f, start, rest, DT)
    assert r.peak_n == pytest.approx(rest + step * (1 + math.exp(-z * math.pi / math.sqrt(
        1 - z * z))), rel=1e-4)
    assert r.peak_ms == pytest.approx(math.pi / wd * 1e3, abs=1.0)


def test_the_default_scene_settles_within_the_run() -> None:
    """At the game's n the hand's force after the lift and after the landing settles well
    before the run ends (else the settled value, the run's tail, would be no equilibrium),
    and the ball resting on the cloth adds to the force on a hand."""
    f = feel(Scene.load("default"))
    for r in (f.lift, f.landing):
        assert max(r.settling_ms) < (RUN_S - 2 * TAIL_S) * 1e3, r
        assert r.peak_n > r.settled_n > f.rest_n, (r, f.rest_n)
