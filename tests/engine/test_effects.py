"""Effects: a scene simulates exactly what it names, each effect pushes the right way,
and an absent effect has no influence."""

from __future__ import annotations

import numpy as np
import pytest
from clothball import _native
from clothball.game import Cloth, Scene
from clothball.game.sim.cloth import rest_positions
from clothball.game.sim.config import native_config
from clothball.game.sim.scene import available


@pytest.mark.parametrize("name", available())
def test_compiled_effects_are_what_the_scene_names(name: str, backend: str) -> None:
    s = Scene.load(name)
    assert Cloth(s, backend=backend).compiled_effects == s.effects


def test_shipped_scenes_use_different_sets() -> None:
    sets = {name: Scene.load(name).effects for name in ("classic", "silk", "windy", "practice")}
    assert {"shear", "bend"} <= sets["silk"]
    assert "wind" in sets["windy"] and Scene.load("windy")["wind"]["gust_amplitude"] > 0
    assert "ball" not in sets["practice"]
    assert len(set(sets.values())) == 4


def test_wind_pushes_downwind(backend: str) -> None:
    wind = np.array([3.0, -2.0, 1.0])
    s = Scene.from_dict(
        {
            "cloth": {"n": 16},
            "wind": {"velocity": wind.tolist()},
            "sim": {"effects": ["structural", "wind"]},
        }
    )
    c = Cloth(s, backend=backend, precision="float64")
    c.step(200)
    shift = (c.positions() - rest_positions(s)).mean(axis=(0, 1))
    assert shift @ wind > 0.5 * np.linalg.norm(shift) * np.linalg.norm(wind)


def test_gusts_vary_the_wind() -> None:
    s = Scene.load("windy")
    c = Cloth(s, backend="cpu")
    period = s["wind"]["gust_period"]
    peak, trough = c.wind_at(period / 4), c.wind_at(3 * period / 4)
    mean = np.array(s["wind"]["velocity"])
    np.testing.assert_allclose(peak, mean * (1 + s["wind"]["gust_amplitude"]))
    np.testing.assert_allclose(trough, mean * (1 - s["wind"]["gust_amplitude"]))


def _folded(n: int) -> np.ndarray:
    """The cloth folded 90 degrees along its middle column, rest lengths kept."""
    s = Scene.from_dict({"cloth": {"n": n}})
    pos = rest_positions(s)
    mid = n // 2
    x_mid = pos[0, mid, 0]
    d = pos[:, mid:, 0] - x_mid
    pos[:, mid:, 0] = x_mid
    pos[:, mid:, 1] += d
    return pos


def _crease_angle(p: np.ndarray, mid: int) -> float:
    """Mean angle (degrees) at the fold line between the two halves: 180 when flat."""
    a = p[:, mid - 1] - p[:, mid]
    b = p[:, mid + 1] - p[:, mid]
    cos = np.sum(a * b, axis=-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))).mean())


def test_bending_resists_folding(backend: str) -> None:
    n = 15
    angles = {}
    for fx in (["structural"], ["structural", "bend"]):
        s = Scene.from_dict({"cloth": {"n": n}, "sim": {"effects": fx}})
        c = Cloth(s, backend=backend, precision="float64")
        pos = _folded(n)
        c.set_state(pos, np.zeros_like(pos))
        c.step(20)
        angles[len(fx)] = _crease_angle(c.positions(), n // 2)
    folded = _crease_angle(_folded(n), n // 2)
    assert folded == pytest.approx(90.0)
    # Tension-only structural springs at rest length do nothing; bending springs open it.
    assert angles[1] == pytest.approx(folded, abs=1e-6)
    assert angles[2] > folded + 5.0, angles


def test_shear_resists_shearing(backend: str) -> None:
    n = 12
    res = {}
    for fx in (["structural"], ["structural", "shear"]):
        s = Scene.from_dict(
            {"cloth": {"n": n, "structural_two_sided": True}, "sim": {"effects": fx}}
        )
        c = Cloth(s, backend=backend, precision="float64")
        rest = rest_positions(s)
        pos = rest.copy()
        angle = 0.3  # rotate each row's nodes: a shear of the square into a rhombus
        pos[..., 0] = rest[..., 0] * np.cos(angle) + rest[..., 2] * np.sin(angle)
        pos[..., 2] = rest[..., 2] * np.cos(angle)
        pos[..., 2] += rest[..., 2] * 0  # rows keep their spacing along z
        c.set_state(pos, np.zeros_like(pos))
        c.step(60)
        p = c.positions()
        # The angle between the grid's two directions at the centre: 90 deg when unsheared.
        u = p[n // 2, n // 2 + 1] - p[n // 2, n // 2 - 1]
        v = p[n // 2 + 1, n // 2] - p[n // 2 - 1, n // 2]
        res[len(fx)] = abs(
            np.degrees(np.arccos(u @ v / np.linalg.norm(u) / np.linalg.norm(v))) - 90
        )
    assert res[2] < res[1] - 1.0, res


@pytest.mark.parametrize(
    "absent, field, values",
    [
        ("gravity", "gravity", ((0.0, 0.0, 0.0), (3.0, -50.0, 2.0))),
        ("shear", "k_shear", (0.0, 5e4)),
        ("bend", "k_bend", (0.0, 5e4)),
        ("damping", "damping", (0.0, 1.0)),
        ("ball", "ball_k", (0.0, 1e6)),
        ("coupling", "coupling_k", (0.0, 1e6)),
        ("wind", "drag", (0.0, 5.0)),
        ("strain_limit", "max_strain", (1e-6, 5.0)),
    ],
)
def test_absent_effect_has_no_influence(backend: str, absent: str, field: str, values) -> None:
    """With the effect absent, its parameters (even extreme ones) change nothing, bit for bit.
    Gravity, damping and coupling are run-time parameters of the kernels (the others are
    compiled out): their absence must zero them."""
    # Without gravity the hands (coupling) and damping move the cloth instead.
    fx = ["structural", "damping", "coupling"] if absent == "gravity" else ["structural", "gravity"]
    s = Scene.from_dict({"cloth": {"n": 12}, "sim": {"effects": fx}})
    results = []
    for v in values:
        cfg = native_config(s)
        setattr(cfg, field, v)
        e = _native.Engine(backend, True, cfg)
        rest = rest_positions(s)
        e.set_state(rest, np.zeros_like(rest))
        e.set_hips(rest[[0, 0, -1, -1], [0, -1, -1, 0]] + 0.3)
        e.set_ball(np.array([0.0, 1.0, 0.0, 0.0, 0.0, 0.0]))
        e.set_wind(np.array([5.0, -5.0, 0.0]))
        e.step(20, 4, 2.5e-4)
        results.append(e.positions())
    np.testing.assert_array_equal(results[0], results[1])


def _far_ball_pair(n: int) -> tuple[Scene, Scene]:
    """The same cloth with and without the ball effect; the ball starts far below."""
    cloth = {"n": n}
    sim = {"substeps": 8}
    fx = ["structural", "gravity", "damping", "coupling"]
    with_ball = Scene.from_dict(
        {
            "cloth": cloth,
            "ball": {"position": [0.0, -3.0, 0.0], "velocity": [0.0, 0.0, 0.0]},
            "sim": {**sim, "effects": [*fx, "ball"]},
        }
    )
    return with_ball, Scene.from_dict({"cloth": cloth, "sim": {**sim, "effects": fx}})


def test_ball_contact_skipped_while_off_the_cloth(backend: str) -> None:
    """With the ball far from every node the substeps run compiled without contact: the
    cloth moves bit for bit as in the scene without a ball, while the ball still falls."""
    with_ball, without = _far_ball_pair(20)
    a = Cloth(with_ball, backend=backend, precision="float64")
    b = Cloth(without, backend=backend, precision="float64")
    assert a.ball_contact_active  # until a substep shows otherwise
    hips = a.hips() + 0.05
    for c in (a, b):
        c.set_hips(hips)
        c.step(30)
    assert not a.ball_contact_active and not b.ball_contact_active
    np.testing.assert_array_equal(a.positions(), b.positions())
    np.testing.assert_array_equal(a.velocities(), b.velocities())
    assert a.ball()[0][1] < -3.0 - 0.5 * 9.81 * 0.03**2 * 0.9  # it fell
    # Press the ball into the cloth (1 cm deep, moving down): contact is back on at once,
    # and the cloth brakes the ball (gravity alone would speed it up).
    radius = with_ball["ball"]["radius"]
    a.set_ball(a.positions()[10, 10] + [0.0, radius - 0.01, 0.0], (0.0, -0.5, 0.0))
    assert a.ball_contact_active
    a.step(1)
    assert a.ball()[1][1] > -0.5
    b.step(1)
    assert not np.array_equal(a.positions(), b.positions())
