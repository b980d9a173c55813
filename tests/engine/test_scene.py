"""Scene files: defaults, shipped scenes, and clear errors naming the key."""

from __future__ import annotations

import math

import pytest
from clothball.game import Scene, SceneError
from clothball.game.sim.scene import MATERIAL_KEYS, SCHEMA, available


def test_shipped_scenes_load() -> None:
    names = available()
    assert {"classic", "silk"} <= set(names)
    for name in names:
        scene = Scene.load(name)
        assert scene.n >= 2


def test_classic_is_the_paper_setup() -> None:
    s = Scene.load("classic")
    assert s.effects == {"structural", "gravity", "damping", "ball", "coupling"}
    assert s["cloth"]["structural_two_sided"] is False  # eq. (2): tension only
    assert s["sim"]["frame_dt"] == 0.001


def test_silk_has_shear_and_bending() -> None:
    assert {"shear", "bend"} <= Scene.load("silk").effects


def test_every_key_but_n_has_a_default() -> None:
    s = Scene.from_dict({"cloth": {"n": 5}})
    for section, keys in SCHEMA.items():
        for key, spec in keys.items():
            if (section, key) in (("cloth", "n"), ("sim", "substeps"), ("ball", "position")):
                continue
            if (section, key) in MATERIAL_KEYS:  # given instead of a per-node key, or None
                assert spec.default is None and s[section][key] is None
                continue
            assert spec.default is not None, f"{section}.{key} has no default"
            assert s[section][key] is not None


def test_a_material_key_replaces_its_per_node_key() -> None:
    """Given, a material key leaves the per-node key it replaces None (so no code reads a
    stale per-node default); not given, it reads None and the per-node key holds."""
    s = Scene.from_dict({"cloth": {"n": 9, "damping_rate": 4.0},
                         "ball": {"stiffness_per_area": 2e6}})
    assert s["cloth"]["damping"] is None and s["cloth"]["damping_rate"] == 4.0
    assert s["ball"]["stiffness"] is None and s["ball"]["stiffness_per_area"] == 2e6
    assert s.material_keys == ["cloth.damping_rate", "ball.stiffness_per_area"]
    plain = Scene.from_dict({"cloth": {"n": 9}})
    assert plain["cloth"]["damping"] == 0.002 and plain["cloth"]["damping_rate"] is None
    assert plain.material_keys == []


def test_load_by_path(tmp_path) -> None:
    p = tmp_path / "mine.toml"
    p.write_text("[cloth]\nn = 9\nsize = 2.0\n")
    s = Scene.load(p)
    assert s.n == 9 and s.rest_length == pytest.approx(0.25) and s.name == "mine"


@pytest.mark.parametrize(
    "data, key",
    [
        ({"cloth": {}}, "cloth.n"),
        ({"cloth": {"n": 5, "colour": 3}}, "cloth.colour"),
        ({"cloth": {"n": 5}, "sky": {}}, "[sky]"),
        ({"cloth": {"n": "5"}}, "cloth.n"),
        ({"cloth": {"n": 5.5}}, "cloth.n"),
        ({"cloth": {"n": 1}}, "cloth.n"),
        ({"cloth": {"n": 5, "size": math.nan}}, "cloth.size"),
        ({"cloth": {"n": 5, "mass": math.inf}}, "cloth.mass"),
        ({"cloth": {"n": 5, "mass": 0.0}}, "cloth.mass"),
        ({"cloth": {"n": 5, "k_structural": -1.0}}, "cloth.k_structural"),
        ({"cloth": {"n": 5, "structural_two_sided": 1}}, "cloth.structural_two_sided"),
        ({"cloth": {"n": 5}, "sim": {"precision": "half"}}, "sim.precision"),
        ({"cloth": {"n": 5}, "sim": {"effects": ["structural", "magic"]}}, "sim.effects"),
        ({"cloth": {"n": 5}, "sim": {"gravity": [0, -9.81]}}, "sim.gravity"),
        ({"cloth": {"n": 5}, "ball": {"position": [0, math.nan, 0]}}, "ball.position[1]"),
        ({"cloth": {"n": 5}, "sim": {"frame_dt": 0}}, "sim.frame_dt"),
        ({"cloth": {"n": 5}, "sim": {"substeps": 0}}, "sim.substeps"),
        ({"cloth": {"n": 5, "k_shear": 10.0}}, "cloth.k_shear"),  # shear not named
        (
            {"cloth": {"n": 5}, "ball": {"radius": 0.1}, "sim": {"effects": ["structural"]}},
            "ball.radius",
        ),
        # A material key and the per-node key it replaces: one of the two.
        ({"cloth": {"n": 5, "damping": 0.01, "damping_rate": 3.0}}, "cloth.damping_rate"),
        ({"cloth": {"n": 5}, "ball": {"stiffness": 1e3, "stiffness_per_area": 1e6}},
         "ball.stiffness_per_area"),
        ({"cloth": {"n": 5, "damping_rate": -1.0}}, "cloth.damping_rate"),
        ({"cloth": {"n": 5}, "ball": {"stiffness_per_area": math.inf}}, "ball.stiffness_per_area"),
        ({"cloth": {"n": 5, "damping_rate": 1.0}, "sim": {"effects": ["structural"]}},
         "cloth.damping_rate"),
    ],
)
def test_bad_scenes_name_the_key(data: dict, key: str) -> None:
    with pytest.raises(SceneError) as e:
        Scene.from_dict(data)
    assert key in str(e.value)


def test_bad_files(tmp_path) -> None:
    with pytest.raises(SceneError, match="no such scene"):
        Scene.load("does-not-exist")
    p = tmp_path / "broken.toml"
    p.write_text("[cloth\nn = 3")
    with pytest.raises(SceneError, match="not valid TOML"):
        Scene.load(p)
    p.write_text("[cloth]\nn = 3\nsize = nan\n")
    with pytest.raises(SceneError, match="cloth.size"):
        Scene.load(p)


def test_scene_reference_is_current() -> None:
    """docs/scenes.md is generated from the schema; regenerate it when the schema changes."""
    from pathlib import Path

    from clothball.game.sim.scene import schema_markdown

    doc = Path(__file__).resolve().parents[2] / "docs" / "scenes.md"
    assert doc.read_text().strip() == schema_markdown().strip()
