"""Falcon kinematics: closed-form inverse, Newton forward, Jacobian, torques, motor clamp."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from clothball._native import falcon as f

KIN = f.Kinematics()
# Geometry from FALCON.md (the model is documented in native/falcon/kinematics.hpp).
A, B, C, R, S, FF = 0.060, 0.1025, 0.01443, 0.0400, -0.02309, -0.025
PHI = np.radians([90 + 15, -30 + 15, -150 + 15])


def workspace(n: int = 7, margin: float = 0.0) -> list[np.ndarray]:
    xs = np.linspace(-0.03 - margin, 0.03 + margin, n)
    zs = np.linspace(0.095 - margin, 0.155 + margin, n)
    return [np.array(p) for p in itertools.product(xs, xs, zs)]


def test_encoder_angle_conversion() -> None:
    k = (math.pi * 0.01425 / (320 * 4)) / (math.pi * 0.110 / 360)
    assert f.DEG_PER_COUNT == pytest.approx(k, rel=1e-12)
    assert k == pytest.approx(0.03644, abs=1e-5)  # FALCON.md's rounded figure
    assert f.encoder_to_angle(0) == pytest.approx(math.radians(35.0))
    for n in (-2000, -1, 0, 1, 1234):
        assert f.encoder_to_angle(n) == pytest.approx(math.radians(n * k + 35))
        assert f.angle_to_encoder(f.encoder_to_angle(n)) == pytest.approx(n, abs=1e-9)


def test_inverse_satisfies_the_leg_constraints() -> None:
    """Each leg's knee sits a from the hip and b (the parallelogram) from the grip."""
    for p in workspace(5):
        theta = KIN.inverse(p.tolist())
        assert theta is not None, p
        for i, phi in enumerate(PHI):
            u = math.cos(phi) * p[0] + math.sin(phi) * p[1] + C - R
            v = -math.sin(phi) * p[0] + math.cos(phi) * p[1] - S
            w = p[2] + FF
            knee = np.array([A * math.cos(theta[i]), 0.0, A * math.sin(theta[i])])
            assert np.linalg.norm(np.array([u, v, w]) - knee) == pytest.approx(B, abs=1e-12)
            assert knee[0] > u  # knee-out branch: the knee is outside the grip's leg point


def test_whole_usable_cube_is_reachable_and_symmetric() -> None:
    t = KIN.inverse([0.0, 0.0, 0.125])
    assert t is not None
    assert t[0] == pytest.approx(t[1]) and t[1] == pytest.approx(t[2])  # centre: equal legs
    assert all(KIN.inverse(p.tolist()) is not None for p in workspace(9))


def test_round_trip_over_the_workspace_within_0_1_mm() -> None:
    """Every reachable point of a box 5 mm larger than the usable cube, cold-started."""
    worst, iters, n = 0.0, [], 0
    guess = [0.0, 0.0, 0.08]  # FALCON.md's cold-start guess
    for p in workspace(9) + workspace(9, margin=0.005):
        theta = KIN.inverse(p.tolist())
        if theta is None:  # only the margin box has unreachable corners
            continue
        n += 1
        res = KIN.forward(theta, guess)
        assert res is not None, p
        q, it = res
        iters.append(it)
        worst = max(worst, float(np.linalg.norm(np.array(q) - p)))
    assert n > 9**3  # the whole usable cube and part of the margin
    assert worst < 1e-4
    assert max(iters) <= 15


def test_round_trip_from_quantised_encoders_stays_within_one_count() -> None:
    """Counts are rounded, so the error is bounded by the Jacobian times half a count."""
    half_count = math.radians(f.DEG_PER_COUNT) / 2
    prev = [0.0, 0.0, 0.125]
    for p in workspace(5):
        enc = [round(f.angle_to_encoder(t)) for t in KIN.inverse(p.tolist())]
        q, _ = KIN.forward([f.encoder_to_angle(e) for e in enc], prev)  # warm start
        prev = q
        J = np.array(KIN.jacobian(p.tolist()))
        bound = np.linalg.norm(J, 2) * half_count * math.sqrt(3) * 1.05
        assert np.linalg.norm(np.array(q) - p) <= bound
        assert bound < 2e-4  # one count is a fraction of a millimetre anywhere in the cube


def test_warm_start_converges_in_few_iterations() -> None:
    p = np.array([0.01, -0.02, 0.13])
    theta = KIN.inverse(p.tolist())
    q, it = KIN.forward(theta, (p + 0.0005).tolist())
    assert np.linalg.norm(np.array(q) - p) < 1e-9
    assert it <= 4


def test_out_of_reach() -> None:
    assert KIN.inverse([0.0, 0.0, 0.5]) is None
    assert KIN.jacobian([0.0, 0.0, 0.5]) is None


@pytest.mark.parametrize("p", [[0, 0, 0.125], [0.02, -0.01, 0.1], [-0.025, 0.028, 0.15]])
def test_jacobian_matches_finite_differences(p: list[float]) -> None:
    h = 1e-7
    Jinv = np.array(KIN.jacobian_inverse(p))  # d theta / d p
    fd = np.zeros((3, 3))
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = h
        tp = np.array(KIN.inverse((np.array(p) + dp).tolist()))
        tm = np.array(KIN.inverse((np.array(p) - dp).tolist()))
        fd[:, k] = (tp - tm) / (2 * h)
    np.testing.assert_allclose(Jinv, fd, rtol=1e-5, atol=1e-6)
    # d p / d theta by differencing the forward kinematics.
    J = np.array(KIN.jacobian(p))
    theta = np.array(KIN.inverse(p))
    fdf = np.zeros((3, 3))
    for k in range(3):
        dt = np.zeros(3)
        dt[k] = 1e-6
        qp = np.array(KIN.forward((theta + dt).tolist(), p)[0])
        qm = np.array(KIN.forward((theta - dt).tolist(), p)[0])
        fdf[:, k] = (qp - qm) / 2e-6
    np.testing.assert_allclose(J, fdf, rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(J @ Jinv, np.eye(3), atol=1e-9)


def test_torques_do_the_same_virtual_work_as_the_force() -> None:
    p = np.array([0.01, 0.015, 0.12])
    F = np.array([1.5, -2.0, 3.0])
    tau = np.array(KIN.torques(p.tolist(), F.tolist()))
    np.testing.assert_allclose(tau, np.array(KIN.jacobian(p.tolist())).T @ F, rtol=1e-12)
    np.testing.assert_allclose(KIN.force_from_torques(p.tolist(), tau.tolist()), F, rtol=1e-9)
    dp = np.array([2e-7, -1e-7, 3e-7])
    dtheta = np.array(KIN.inverse((p + dp).tolist())) - np.array(KIN.inverse(p.tolist()))
    assert float(tau @ dtheta) == pytest.approx(float(F @ dp), rel=1e-4)


def test_motor_commands_are_minus_torque_times_10000() -> None:
    tau = [0.01, -0.02, 0.003]
    assert list(f.torques_to_motors(tau)) == [round(-t * 10000) for t in tau]
    back = f.motors_to_torques(f.torques_to_motors(tau))
    np.testing.assert_allclose(back, tau, atol=0.5 / 10000)


def test_motor_clamp_keeps_direction_and_cap() -> None:
    tau = np.array([0.9, -0.3, 0.45])  # -tau * 10000 exceeds 4096 on motor 0
    m = np.array(f.torques_to_motors(tau.tolist()))
    assert np.abs(m).max() == f.MOTOR_LIMIT == 4096
    expect = -tau * 10000 * (4096 / 9000)
    np.testing.assert_allclose(m, expect, atol=0.5)
    # Above the torque cap (30 N m) all three scale together first: same direction.
    big = np.array([100.0, -50.0, 25.0])
    mb = np.array(f.torques_to_motors(big.tolist()))
    np.testing.assert_allclose(mb, -big / 100 * 4096, atol=0.5)
    assert np.abs(np.array(f.torques_to_motors([1e9, -1e9, 1e9]))).max() == 4096
    assert list(f.torques_to_motors([math.nan, 0.0, 0.0])) == [0, 0, 0]
    assert np.abs(np.array(f.torques_to_motors(tau.tolist(), 1000))).max() == 1000


def test_largest_force_fits_the_motor_range_near_the_centre() -> None:
    """8 N (the Falcon's continuous maximum) needs roughly the documented motor range."""
    tau = np.array(KIN.torques([0, 0, 0.125], [0.0, 0.0, 8.0]))
    peak = np.abs(tau).max() * f.MOTOR_PER_TORQUE
    assert 1000 < peak < 2 * f.MOTOR_LIMIT
