"""Scenes: what a cloth simulation is made of, loaded from TOML files or dicts.

A scene names only what it changes; every key but ``cloth.n`` has a default (see
``SCHEMA`` and ``docs/scenes.md``). Keys are SI units. Anything unknown, mistyped,
non-finite or out of range is refused with a ``SceneError`` naming the key.
"""

from __future__ import annotations

import copy
import importlib.resources
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# Package data of the wheel (clothball/assets: scenes and the web page), a directory on disk.
ASSETS = Path(str(importlib.resources.files("clothball") / "assets"))
SCENES_DIR = ASSETS / "scenes"

INTEGRATORS = ("semi_implicit_euler", "velocity_verlet", "implicit_euler")
PRECISIONS = ("float32", "float64")
CONTACTS = ("nodes", "edges")  # ball.contact: eq. (4) on nodes, or on structural edges
EFFECTS = (
    "structural",
    "shear",
    "bend",
    "gravity",
    "damping",
    "ball",
    "coupling",
    "wind",
    "strain_limit",
)
DEFAULT_EFFECTS = ("structural", "gravity", "damping", "ball", "coupling")


class SceneError(ValueError):
    """A scene file or dict is malformed; the message names the offending key."""


def line_weights(n: int) -> Any:
    """Each row's (or column's) share of an inner one's strip of sheet, an (n,) array: 1/2
    for the two on the border, 1 elsewhere (the engine's edge_spring_weight, params.hpp)."""
    import numpy as np

    w = np.ones(n)
    w[0] = w[-1] = 0.5
    return w


def mass_weights(n: int) -> Any:
    """Each node's share of an interior node's area (and mass), an (n, n) array: its row's
    and its column's ``line_weights`` multiplied, so 1 inside, 1/2 on an edge, 1/4 at a
    corner; the sum is (n - 1)^2."""
    import numpy as np

    w = line_weights(n)
    return np.outer(w, w)


@dataclass(frozen=True)
class Key:
    """One scene key: its default, its kind and its allowed range."""

    default: Any
    kind: str  # "int", "float", "bool", "str", "vec3", "effects"
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False  # lo itself is not allowed
    choices: tuple[str, ...] = ()
    effect: str | None = None  # setting this key means the scene must name this effect
    doc: str = ""


# Material keys (independent of n) and the per-node keys they replace: a scene gives one of
# each pair; the other reads None. The engine derives the per-node value (native per_node).
MATERIAL_KEYS = {
    ("cloth", "damping_rate"): "damping",
    ("ball", "stiffness_per_area"): "stiffness",
}
# Material keys with no per-node key to replace (the engine derives their per-node values
# the same way): the plate's bending stiffness, a term of its own beside the bend springs.
MATERIAL_ONLY_KEYS = (("cloth", "bending_stiffness"),)

# The schema: section -> key -> Key. Defaults give the paper's set-up ("classic").
SCHEMA: dict[str, dict[str, Key]] = {
    "cloth": {
        "n": Key(None, "int", 2, 8192, doc="nodes per side (required)"),
        "size": Key(1.0, "float", 0.0, 100.0, lo_open=True, doc="side length, m"),
        "mass": Key(0.5, "float", 0.0, 1e4, lo_open=True, doc="total mass, kg"),
        "height": Key(1.0, "float", -100.0, 100.0, doc="rest height y of the cloth, m"),
        "k_structural": Key(2000.0, "float", 0.0, 1e9, doc="structural spring stiffness, N/m"),
        "structural_two_sided": Key(
            False, "bool", doc="structural springs also push when compressed (eq. 2: tension only)"
        ),
        "k_shear": Key(200.0, "float", 0.0, 1e9, effect="shear", doc="shear spring stiffness, N/m"),
        "k_bend": Key(50.0, "float", 0.0, 1e9, effect="bend", doc="bending spring stiffness, N/m"),
        "bending_stiffness": Key(
            0.0, "float", 0.0, 1e3, effect="bend",
            doc="plate bending stiffness D, N m (material: a linear bending force, the discrete "
            "D grad^4 x, k = D / L^2 a stencil, independent of n; beside or instead of the "
            "k_bend springs: set k_bend = 0 for none); 0: none",
        ),
        "damping": Key(
            0.002, "float", 0.0, 1e3, effect="damping",
            doc="velocity damping beta1 per node, N s/m (per node: its effect grows as n^2)",
        ),
        "damping_rate": Key(
            None, "float", 0.0, 1e6, effect="damping",
            doc="instead of damping: velocity damping per unit mass, 1/s (material: beta1 = "
            "this x node mass, independent of n)",
        ),
    },
    "ball": {
        "radius": Key(0.08, "float", 0.0, 100.0, lo_open=True, effect="ball", doc="m"),
        "mass": Key(0.2, "float", 0.0, 1e5, lo_open=True, effect="ball", doc="kg"),
        "stiffness": Key(
            5000.0, "float", 0.0, 1e9, effect="ball",
            doc="contact k_b per node (or per edge), N/m (per node: the ball's total contact "
            "stiffness grows with the nodes it covers, as n^2)",
        ),
        "stiffness_per_area": Key(
            None, "float", 0.0, 1e13, effect="ball",
            doc="instead of stiffness: contact stiffness per contact area, N/m^3 (material: "
            "k_b = this x L^2 on nodes, this x L^2 / 2 on edges, independent of n)",
        ),
        "damping": Key(0.01, "float", 0.0, 1e3, effect="ball", doc="beta2, N s/m"),
        "position": Key(
            None, "vec3", -1e3, 1e3, effect="ball", doc="start, m (default: 0.4 m above the centre)"
        ),
        "velocity": Key((0.0, 0.0, 0.0), "vec3", -1e3, 1e3, effect="ball", doc="start, m/s"),
        "contact": Key(
            "nodes", "str", choices=CONTACTS, effect="ball",
            doc="nodes: eq. (4) on each node inside the ball (the paper; a ball can slip "
            "between nodes through the springs); edges: eq. (4) at each structural spring's "
            "point nearest the centre, shared by its two nodes by distance (the ball cannot "
            "pass a spring; contact is never skipped; costs more; not with implicit_euler)",
        ),
    },
    "coupling": {
        "stiffness": Key(
            1000.0, "float", 0.0, 1e7, effect="coupling",
            doc="corner-to-HIP spring K (eq. 7), N/m: a hand's total, over its grip",
        ),
        "grip_radius": Key(
            0.0, "float", 0.0, 100.0, effect="coupling",
            doc="m: a hand holds each of its corner's two edges over this length, K spread "
            "along them with a smooth density falling to zero at this distance, (1 - (s / "
            "a)^2)^2 (integrated against each node's hat function, normalised to K; a fixed "
            "length in metres, so the sag converges as n grows); 0, or a length within one "
            "spacing: the corner node alone (the paper's point support, whose sag grows as "
            "log n)",
        ),
    },
    "wind": {
        "velocity": Key(
            (3.0, 0.0, 0.0), "vec3", -100.0, 100.0, effect="wind", doc="mean wind, m/s"
        ),
        "air_density": Key(1.2, "float", 0.0, 100.0, effect="wind", doc="rho, kg/m^3"),
        "drag": Key(1.0, "float", 0.0, 10.0, effect="wind", doc="drag coefficient C_d"),
        "lift": Key(0.3, "float", 0.0, 10.0, effect="wind", doc="lift coefficient C_l"),
        "gust_amplitude": Key(
            0.0, "float", 0.0, 10.0, effect="wind", doc="gusts: wind x (1 + a sin(2 pi t / T))"
        ),
        "gust_period": Key(2.0, "float", 0.0, 1e4, lo_open=True, effect="wind", doc="T, s"),
    },
    "strain_limit": {
        "max_strain": Key(
            0.1, "float", 0.0, 10.0, effect="strain_limit", doc="longest spring: (1 + this) L"
        ),
        "iterations": Key(
            10, "int", 1, 1000, effect="strain_limit", doc="passes (rows, then columns) per substep"
        ),
    },
    "sim": {
        "frame_dt": Key(0.001, "float", 0.0, 0.1, lo_open=True, doc="simulated time per frame, s"),
        "substeps": Key(None, "int", 1, 100000, doc="substeps per frame (default: automatic)"),
        "integrator": Key(
            "semi_implicit_euler", "str", choices=INTEGRATORS,
            doc="time integrator (docs/accuracy.md); strain_limit needs semi_implicit_euler",
        ),
        "cg_max_iterations": Key(
            200, "int", 1, 100000,
            doc="implicit_euler: conjugate-gradient iterations per substep, at most",
        ),
        "cg_tolerance": Key(
            1e-5, "float", 0.0, 1.0,
            doc="implicit_euler: CG stops at residual <= this x right-hand side (relative)",
        ),
        "precision": Key("float32", "str", choices=PRECISIONS),
        "gravity": Key((0.0, -9.81, 0.0), "vec3", -1e3, 1e3, effect="gravity", doc="m/s^2"),
        "effects": Key(DEFAULT_EFFECTS, "effects", doc="effects this scene simulates"),
        "allow_unstable": Key(
            False, "bool", doc="accept a fixed substep count beyond the stability bound (warns)"
        ),
    },
}


def _check_value(where: str, key: Key, value: Any) -> Any:
    kind = key.kind
    if kind == "bool":
        if not isinstance(value, bool):
            raise SceneError(f"{where}: expected true or false, got {value!r}")
        return value
    if kind == "str":
        if not isinstance(value, str):
            raise SceneError(f"{where}: expected a string, got {value!r}")
        if key.choices and value not in key.choices:
            raise SceneError(f"{where}: {value!r} is not one of {', '.join(key.choices)}")
        return value
    if kind == "effects":
        if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
            raise SceneError(f"{where}: expected a list of effect names, got {value!r}")
        unknown = [v for v in value if v not in EFFECTS]
        if unknown:
            raise SceneError(
                f"{where}: unknown effect(s) {', '.join(unknown)}; known: {', '.join(EFFECTS)}"
            )
        if len(set(value)) != len(value):
            raise SceneError(f"{where}: an effect is named twice in {list(value)!r}")
        return tuple(value)
    if kind == "vec3":
        if not isinstance(value, list | tuple) or len(value) != 3:
            raise SceneError(f"{where}: expected 3 numbers, got {value!r}")
        return tuple(_check_number(f"{where}[{i}]", key, v, "float") for i, v in enumerate(value))
    return _check_number(where, key, value, kind)


def _check_number(where: str, key: Key, value: Any, kind: str) -> float | int:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise SceneError(f"{where}: expected a number, got {value!r}")
    if kind == "int":
        if isinstance(value, float):
            if not math.isfinite(value) or value != int(value):
                raise SceneError(f"{where}: expected a whole number, got {value!r}")
            value = int(value)
    else:
        value = float(value)
        if not math.isfinite(value):
            raise SceneError(f"{where}: must be finite, got {value!r}")
    if key.lo is not None and (value < key.lo or (key.lo_open and value == key.lo)):
        op = ">" if key.lo_open else ">="
        raise SceneError(f"{where}: must be {op} {key.lo}, got {value!r}")
    if key.hi is not None and value > key.hi:
        raise SceneError(f"{where}: must be <= {key.hi}, got {value!r}")
    return value


class Scene:
    """A validated scene. Read values as ``scene["cloth"]["k_structural"]`` or the
    properties below; ``scene.explicit`` holds what the source actually set."""

    def __init__(self, data: Mapping[str, Any], name: str = "custom") -> None:
        if not isinstance(data, Mapping):
            raise SceneError(f"scene: expected a table of sections, got {type(data).__name__}")
        self.name = name
        explicit: dict[str, dict[str, Any]] = {}
        for section, table in data.items():
            if section not in SCHEMA:
                raise SceneError(
                    f"unknown section [{section}]; known: {', '.join(f'[{s}]' for s in SCHEMA)}"
                )
            if not isinstance(table, Mapping):
                raise SceneError(f"[{section}]: expected a table, got {table!r}")
            for key, value in table.items():
                if key not in SCHEMA[section]:
                    known = ", ".join(SCHEMA[section])
                    raise SceneError(f"{section}.{key}: unknown key; [{section}] knows {known}")
                checked = _check_value(f"{section}.{key}", SCHEMA[section][key], value)
                explicit.setdefault(section, {})[key] = checked
        if "n" not in explicit.get("cloth", {}):
            raise SceneError("cloth.n: required (nodes per side), e.g. n = 60")
        self.explicit = explicit
        values = {s: {k: key.default for k, key in keys.items()} for s, keys in SCHEMA.items()}
        for section, table in explicit.items():
            values[section].update(table)
        for (section, material), per_node in MATERIAL_KEYS.items():
            given = explicit.get(section, {})
            if material in given and per_node in given:
                raise SceneError(
                    f"{section}.{material}: set together with {section}.{per_node}; give one "
                    f"(the material value, independent of n, or the per-node value)"
                )
            if material in given:
                values[section][per_node] = None
        if values["ball"]["position"] is None:
            values["ball"]["position"] = (0.0, values["cloth"]["height"] + 0.4, 0.0)
        self._values = values
        effects = set(values["sim"]["effects"])
        for section, table in explicit.items():
            for key in table:
                needs = SCHEMA[section][key].effect
                if needs is not None and needs not in effects:
                    raise SceneError(
                        f"{section}.{key}: set, but the scene does not name the '{needs}' effect "
                        f"in sim.effects (add it, or remove the key)"
                    )
        integrator = values["sim"]["integrator"]
        if "strain_limit" in effects and integrator != "semi_implicit_euler":
            # Velocity Verlet keeps F(x) between substeps and the projection would move x under
            # it; implicit Euler needs no limiter to stay stable.
            raise SceneError(
                f"sim.integrator: {integrator!r} does not support the 'strain_limit' effect "
                f"(use semi_implicit_euler, or remove strain_limit from sim.effects)"
            )
        if values["ball"]["contact"] == "edges" and integrator == "implicit_euler":
            # Implicit Euler's Jacobian linearises node contact only (integrators.hpp).
            raise SceneError(
                "ball.contact: 'edges' is not supported by the implicit_euler integrator "
                "(its Jacobian linearises node contact); use nodes or an explicit integrator"
            )

    # --- constructors ---------------------------------------------------------------------
    @classmethod
    def load(cls, name_or_path: str | Path) -> Scene:
        """Load a scene by name (a file in ``assets/scenes``) or by path to a TOML file."""
        path = Path(name_or_path)
        if not path.suffix and not path.exists():
            path = SCENES_DIR / f"{name_or_path}.toml"
            if not path.exists():
                raise SceneError(
                    f"scene '{name_or_path}': no such scene; available: {', '.join(available())}"
                )
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as e:
            raise SceneError(f"scene '{name_or_path}': cannot read {path}: {e.strerror}") from e
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise SceneError(f"scene '{path}': not valid TOML: {e}") from e
        try:
            return cls(data, name=path.stem)
        except SceneError as e:
            raise SceneError(f"scene '{path}': {e}") from e

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], name: str = "custom") -> Scene:
        """Build a scene from a dict with the TOML file's structure."""
        return cls(copy.deepcopy(dict(d)), name=name)

    def with_changes(self, changes: Mapping[str, Mapping[str, Any]]) -> Scene:
        """A copy of this scene with some keys changed (same structure as the TOML)."""
        data = copy.deepcopy(self.explicit)
        for section, table in changes.items():
            data.setdefault(section, {}).update(table)
        return Scene(data, name=self.name)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """The explicit keys: loading this dict gives the same scene."""
        return copy.deepcopy(self.explicit)

    # --- values ---------------------------------------------------------------------------
    def __getitem__(self, section: str) -> dict[str, Any]:
        return dict(self._values[section])

    @property
    def n(self) -> int:
        return int(self._values["cloth"]["n"])

    @property
    def rest_length(self) -> float:
        return self._values["cloth"]["size"] / (self.n - 1)

    @property
    def node_mass(self) -> float:
        """An interior node's mass, kg: total / (n - 1)^2, as it stands for L^2 of the sheet;
        node (i, j) has this times ``mass_weights`` (1/2 on an edge, 1/4 at a corner)."""
        return self._values["cloth"]["mass"] / ((self.n - 1) * (self.n - 1))

    @property
    def node_masses(self) -> Any:
        """Every node's mass, kg, an (n, n, 1) array (broadcasts against (n, n, 3)): lumped
        by area, summing to the cloth's mass (the engine's mass_weight, params.hpp)."""
        return (self.node_mass * mass_weights(self.n))[..., None]

    @property
    def material_keys(self) -> list[str]:
        """The material keys (independent of n) this scene gives, as "section.key"."""
        keys = [*MATERIAL_KEYS, *MATERIAL_ONLY_KEYS]
        return [f"{s}.{k}" for (s, k) in keys if k in self.explicit.get(s, {})]

    @property
    def effects(self) -> frozenset[str]:
        return frozenset(self._values["sim"]["effects"])

    def __repr__(self) -> str:
        return f"Scene({self.name!r}, n={self.n}, effects={sorted(self.effects)})"


def available() -> list[str]:
    """Names of the scenes shipped in ``assets/scenes``."""
    return sorted(p.stem for p in SCENES_DIR.glob("*.toml"))


# docs/scenes.md's section on units and the grid (schema_markdown).
GRID_MARKDOWN = (
    "## Units, and what depends on the grid",
    "",
    "A cloth of n x n nodes stands for one sheet: refining n should change the accuracy, not",
    "the material. Most keys are already values of the sheet; two of the paper's are per",
    "node, and their effect grows as n^2. Each of those has a material key to give instead",
    "(one of the pair, never both); the engine derives the per-node value from it and n in",
    "one place, `per_node` in `native/core/params.hpp`, when it is configured (both",
    "backends; the kernels see per-node values only). `clothball scenes` shows each scene's",
    "derived values. L = size / (n - 1) is the spacing; a node stands for L^2 of sheet.",
    "",
    "| key | unit | as a sheet (independent of n?) | per node or spring |",
    "| --- | --- | --- | --- |",
    "| `cloth.mass` | kg | total mass: yes | node mass by area: m = mass / (n - 1)^2 inside, "
    "half on an edge, a quarter at a corner |",
    "| `cloth.size`, `cloth.height` | m | yes | L = size / (n - 1) |",
    "| `cloth.k_structural` | N/m per spring | stretch modulus (force per width per strain) "
    "k_structural: yes (a spring pulls k e L, one per L of width) | as given |",
    "| `cloth.k_shear` | N/m per spring | adds k_shear to the stretch modulus: yes | as given |",
    "| `cloth.k_bend` | N/m per spring | adds 4 k_bend to the stretch and compression modulus "
    "(two cross each cut a row): yes. Its resistance to bending proper is geometric (a bend "
    "of curvature c shortens a spring by c^2 L^3 / 3, a quartic energy) and shrinks as the "
    "grid refines; one k a spring cannot make both n-independent: a bending stiffness is "
    "`bending_stiffness`'s term | as given |",
    "| `cloth.bending_stiffness` | N m | yes: a plate's bending stiffness D (Poisson's ratio "
    "0), energy D/2 \\|grad grad x\\|^2 per area, so a bend of curvature c holds D c^2 / 2 "
    "per area and the force per area tends to -D grad^4 x. Part of the `bend` effect, beside "
    "its springs (`k_bend = 0` for none); 0 (the default): no such term | k = D / L^2 a "
    "stencil: the second differences of the positions along each row and column triple and "
    "the mixed one on each cell, squared (the 13-node biharmonic stencil, "
    "native/core/forces.hpp: plate_sum); zero on any plane, so the flat cloth and its rigid "
    "motions feel nothing |",
    "| `cloth.damping` | N s/m per node | no: total damping (n - 1)^2 damping (masses by "
    "area), rate (n - 1)^2 damping / mass | beta1 as given |",
    "| `cloth.damping_rate` | 1/s | yes: every node loses velocity at this rate per unit "
    "mass | beta1 = damping_rate x m |",
    "| `ball.stiffness` | N/m per node (per edge) | no: the ball's total contact stiffness "
    "grows with the nodes it covers, as n^2 | k_b as given |",
    "| `ball.stiffness_per_area` | N/m^3 (pressure per metre of penetration) | yes: a ball "
    "of radius R whose centre is h above a flat sheet feels pi kappa h (R - h)^2 | k_b = "
    "kappa L^2 (nodes), kappa L^2 / 2 (edges: a node inside the ball meets about one edge "
    "contact per grid direction; each row and column adds one more at its segment nearest "
    "the centre, so the edges' total exceeds the sheet's by O(L / R), halving as L does: "
    "+9 % at R = 13 L, pressed in 3/8 R) |",
    "| `ball.radius`, `mass`, `damping`, `position`, `velocity` | m, kg, N s/m, m, m/s | "
    "the ball's own: yes | - |",
    "| `coupling.stiffness` | N/m | a hand's total: yes | the corner node's K (grip radius "
    "0), or split over the grip's nodes |",
    "| `coupling.grip_radius` | m | yes: a hand holds each of its corner's two edges over "
    "this length, with a stiffness density (1 - (s / a)^2)^2 at s from the corner, smooth "
    "at the corner and flat where it ends. A single node is a point support, under which a "
    "membrane's displacement grows as log(1 / L): the sag grows by ~3 mm each time the "
    "spacing halves and never converges (a segment of fixed length holds a finite "
    "displacement) | node m (m L from the corner along an edge, (m - 1) L < a) takes K w_m "
    "/ sum w, w_m the density integrated against the node's hat function (1 - |s - m L| / "
    "L: the share linear elements give it; the corner its half hat on each edge), so the "
    "total is K at every n (the hats sum to one); sampled at the nodes instead, a 10 cm grip "
    "two spacings long at n = 25 kept the sag and rebound from converging monotonically "
    "(docs/accuracy.md); a <= L: the corner node alone. The hand's point (what `corners()` "
    "reads and the Falcon is pulled to) is the grip's nodes less their rest offsets, "
    "weighted alike: the corner at rest, and the force on the hand is -K (hip - point) |",
    "| `[wind]` | m/s, kg/m^3, 1 | on each triangle's area: yes | - |",
    "| `strain_limit.max_strain` | 1 | a strain: yes | (1 + max_strain) L |",
    "| `sim.*` | s, m/s^2 | - | - |",
    "",
    "The paper's per-node keys stay (a scene may give them), but every shipped scene gives",
    "material values. `classic` (the paper's set-up) gives those that derive the paper's",
    "per-node values at the paper's resolution, n = 60 (damping 0.002 N s/m, contact 5000",
    "N/m), and at any other n the same material's; `windy` and `practice` alike, `silk` at",
    "its n = 64. `default` (the game's) gives `damping_rate` and `stiffness_per_area` chosen",
    "so that at its n = 48 they derive the per-node values it had before (0.02 N s/m, 5000",
    "N/m), and a `bending_stiffness` of 0.002 N m beside its bending springs, with which the",
    "ball's rebound and the game's start converge as n grows (with the springs alone the",
    "rebound turned at n = 97; with 0.0005 N m the start did at n = 193; `silk` has 0.0005",
    "N m beside its own, weaker springs, for the same reason). Every",
    "shipped scene's hands hold a 10 cm `grip_radius` (the paper held each corner by its",
    "node, a point support whose sag has no limit in n: the one departure of `classic` from",
    "the paper's set-up). docs/accuracy.md: what converges, at what order, per scene.",
)


def schema_markdown() -> str:
    """docs/scenes.md, generated from SCHEMA so that the documentation stays true."""
    lines = [
        "# Scene files",
        "",
        "A scene is a TOML file in `assets/scenes/` (load it by name) or anywhere (by path).",
        "Every key but `cloth.n` has a default, so a scene names only what it changes. Units are",
        "SI. Unknown sections or keys, wrong types, NaN/Inf and out-of-range values are refused",
        "with an error naming the key. A key that belongs to an effect the scene does not name in",
        "`sim.effects` is refused too (it is almost always a mistake).",
        "",
        "Effects: " + ", ".join(f"`{e}`" for e in EFFECTS) + ".",
        "",
        "Regenerate this file with `clothball scenes --markdown > docs/scenes.md`.",
        "",
        *GRID_MARKDOWN,
        "",
    ]
    for section, keys in SCHEMA.items():
        lines += [
            f"## [{section}]",
            "",
            "| key | default | range / choices | effect | meaning |",
            "| --- | --- | --- | --- | --- |",
        ]
        for name, key in keys.items():
            if key.choices:
                rng = ", ".join(key.choices)
            elif key.lo is not None:
                rng = f"{'(' if key.lo_open else '['}{key.lo:g}, {key.hi:g}]"
            else:
                rng = ""
            d = list(key.default) if isinstance(key.default, tuple) else key.default
            lines.append(f"| `{name}` | `{d}` | {rng} | {key.effect or ''} | {key.doc} |")
        lines.append("")
    return "\n".join(lines)
