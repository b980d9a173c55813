"""The local haptic law on a scripted clock: extrapolation, stale fade, passivity."""

from __future__ import annotations

import numpy as np
import pytest
from clothball._native import falcon as f

DT = 1e-3
C0 = [0.0, 0.0, 0.125]


def config(**kw: object) -> f.CouplingConfig:
    c = f.CouplingConfig()
    for k, v in kw.items():
        setattr(c, k, v)
    return c


def smoothstep(g: float) -> float:
    g = min(max(g, 0.0), 1.0)
    return g * g * (3 - 2 * g)


def test_no_corner_no_force() -> None:
    cp = f.Coupling()
    out = cp.compute(0.0, [0.01, 0, 0.12], [0.1, 0, 0], DT)
    assert out["force"] == [0.0, 0.0, 0.0] and out["age"] == -1.0


def test_spring_damper_with_extrapolated_corner() -> None:
    cfg = config(fade_in=1e-9, passivity=False)
    cp = f.Coupling(cfg)
    K, B = np.array([400.0, 500.0, 600.0]), np.array([2.0, 3.0, 4.0])
    c, cdot = np.array(C0), np.array([0.1, -0.05, 0.02])
    cp.set_corner(c.tolist(), cdot.tolist(), K.tolist(), B.tolist(), 1.0)
    h, hdot = np.array([0.004, 0.001, 0.126]), np.array([0.02, 0.0, -0.01])
    out = cp.compute(1.05, h.tolist(), hdot.tolist(), DT)  # 50 ms old sample
    c_ext = c + cdot * 0.05
    np.testing.assert_allclose(out["corner"], c_ext, atol=1e-15)
    np.testing.assert_allclose(out["force"], -K * (h - c_ext) - B * (hdot - cdot), rtol=1e-12)
    assert out["gain"] == 1.0 and out["age"] == pytest.approx(0.05)


def test_extrapolation_is_capped() -> None:
    cfg = config(fade_in=1e-9, passivity=False, max_extrapolation=0.02, stale_after=10.0)
    cp = f.Coupling(cfg)
    cp.set_corner(C0, [1.0, 0, 0], [100.0] * 3, [0.0] * 3, 0.0)
    out = cp.compute(0.5, C0, [0, 0, 0], DT)
    assert out["corner"][0] == pytest.approx(0.02)


def test_stiffness_damping_and_force_are_capped() -> None:
    cfg = config(fade_in=1e-9, passivity=False, max_stiffness=1000.0, max_force=5.0)
    cp = f.Coupling(cfg)
    cp.set_corner(C0, [0, 0, 0], [1e6] * 3, [0.0] * 3, 0.0)
    out = cp.compute(0.0, [0.001, 0, 0.125], [0, 0, 0], DT)
    assert out["force"][0] == pytest.approx(-1.0)  # K capped at 1000 N/m
    out = cp.compute(0.001, [0.03, 0.03, 0.125], [0, 0, 0], DT)
    assert np.linalg.norm(out["force"]) == pytest.approx(5.0) and out["clamped"]
    fx, fy, _ = out["force"]
    assert fx == pytest.approx(fy) and fx < 0  # direction kept


def run_schedule(cfg: f.CouplingConfig, updates: list[float], until: float) -> list[dict]:
    """Tick every ms; a fresh corner sample is received at each time in `updates`."""
    cp = f.Coupling(cfg)
    out, pending = [], sorted(updates)
    h = [0.01, 0.0, 0.125]
    for k in range(int(round(until / DT)) + 1):
        t = k * DT
        while pending and pending[0] <= t + 1e-12:
            cp.set_corner(C0, [0, 0, 0], [500.0] * 3, [0.0] * 3, pending.pop(0))
        out.append(dict(cp.compute(t, h, [0, 0, 0], DT), t=t))
    return out


def test_gain_fades_in_smoothly_at_the_configured_rate() -> None:
    cfg = config(passivity=False)  # fade_in 0.25 s
    ticks = run_schedule(cfg, [k * 0.01 for k in range(100)], 0.5)
    for o in ticks:
        # Every tick (the one at t = 0 included) advances the fade state by dt / fade_in.
        assert o["gain"] == pytest.approx(smoothstep((o["t"] + DT) / cfg.fade_in), abs=1e-9)
        assert o["force"][0] == pytest.approx(-o["gain"] * 500.0 * 0.01, abs=1e-12)
    assert ticks[0]["gain"] < 1e-4 and ticks[-1]["gain"] == 1.0


def test_stale_updates_fade_out_then_restore_smoothly() -> None:
    cfg = config(passivity=False)
    # Updates every 10 ms until 0.5 s, a 300 ms gap, then updates again.
    updates = [k * 0.01 for k in range(51)] + [0.8 + k * 0.01 for k in range(60)]
    ticks = run_schedule(cfg, updates, 1.4)
    g = np.array([o["gain"] for o in ticks])
    t = np.array([o["t"] for o in ticks])
    age = np.array([o["age"] for o in ticks])
    # Full strength while fresh, before the gap.
    assert np.all(g[(t >= cfg.fade_in) & (t <= 0.5 + cfg.stale_after)] == 1.0)
    # Stale once the last sample (0.5 s) is older than stale_after; out within fade_out.
    stale_at = 0.5 + cfg.stale_after
    assert np.all(age[(t > stale_at + DT) & (t < 0.8)] > cfg.stale_after)
    assert np.all(g[(t >= stale_at + cfg.fade_out + 2 * DT) & (t < 0.8)] == 0.0)
    fading = (t > stale_at) & (t < stale_at + cfg.fade_out)
    assert np.all(np.diff(g[fading]) <= 0)
    # The raw fade state moves at most dt / fade_out per tick: smoothstep's slope <= 1.5.
    assert np.max(np.abs(np.diff(g))) <= 1.5 * DT / min(cfg.fade_out, cfg.fade_in) + 1e-12
    # Restored after the gap over fade_in, monotonically.
    back = (t >= 0.8) & (t <= 0.8 + cfg.fade_in)
    assert np.all(np.diff(g[back]) >= 0)
    assert g[np.searchsorted(t, 0.8 + cfg.fade_in + 2 * DT)] == 1.0
    # The force follows the gain: zero while faded out.
    fx = np.array([o["force"][0] for o in ticks])
    np.testing.assert_allclose(fx, -g * 500.0 * 0.01, atol=1e-12)


def delayed_loop(passivity: bool, rtt: float = 0.08, K: float = 500.0, seconds: float = 4.0
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A hand (0.1 kg, lightly damped) coupled to a corner that follows the hand, seen
    `rtt` late (the server's stiff corner node tracks the HIP; its state comes back over
    the network). Returns the hand's energy (kinetic + spring) and alpha per tick."""
    cp = f.Coupling(config(passivity=passivity, fade_in=1e-9))
    mh, bh, B = 0.1, 0.5, 3.0
    h, hv = np.array([0.005, 0.0, 0.125]), np.zeros(3)
    lag = int(round(rtt / DT))
    history = [(np.array(C0), np.zeros(3))] * (lag + 1)
    energy, alpha = [], []
    for k in range(int(seconds / DT)):
        t = k * DT
        c, cv = history[-(lag + 1)]
        cp.set_corner(c.tolist(), cv.tolist(), [K] * 3, [B] * 3, t)  # just received
        out = cp.compute(t, h.tolist(), hv.tolist(), DT)
        hv = hv + (np.array(out["force"]) - bh * hv) / mh * DT
        h = h + hv * DT
        history = history[-(lag + 1):] + [(h.copy(), hv.copy())]
        energy.append(0.5 * mh * hv @ hv + 0.5 * K * np.sum((h - c) ** 2))
        alpha.append(out["alpha"])
    return np.array(energy), np.array(alpha)


@pytest.mark.parametrize("rtt", [0.06, 0.08, 0.12])
def test_passivity_controller_stabilises_a_delayed_coupling(rtt: float) -> None:
    e_free, a_free = delayed_loop(False, rtt)
    e_pc, a_pc = delayed_loop(True, rtt)
    e0 = e_free[0]
    assert e_pc[0] == e0
    # Without the controller the delay pumps energy in: the hand ends far livelier.
    assert e_free[-500:].max() > 10 * e0
    assert np.all(a_free == 0)
    # With it, the observer sees the generated energy, damps, and the motion dies out.
    assert a_pc.max() > 0
    assert a_pc.max() <= f.CouplingConfig().max_passivity_damping
    assert e_pc.max() <= 2 * e0
    assert e_pc[-500:].max() < 0.01 * e0


def test_passivity_controller_leaves_a_passive_spring_alone() -> None:
    """A hand on a spring to a still corner: no delay, nothing to correct."""
    cp = f.Coupling(config(passivity=True, fade_in=1e-9))
    cp.set_corner(C0, [0, 0, 0], [500.0] * 3, [0.0] * 3, 0.0)
    mh = 0.1
    h, hv = np.array([0.005, 0.0, 0.125]), np.zeros(3)
    e0 = 0.5 * 500.0 * 0.005**2
    for k in range(2000):
        out = cp.compute(k * DT, h.tolist(), hv.tolist(), DT)
        # Energy-conserving (symplectic) update: velocity at the half step.
        hv = hv + np.array(out["force"]) / mh * DT
        h = h + hv * DT
    assert cp.total_dissipated < 0.05 * e0
