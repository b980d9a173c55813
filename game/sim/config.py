"""The native engine's view of a scene: its configuration, effect bits and per-node values.

A scene may give material values (independent of n, ``scene.MATERIAL_KEYS``) instead of
per-node ones; the native core derives the per-node values from them (``per_node`` in
``native/core/params.hpp``), once for both backends. ``node_values`` asks it, for the
Python code that must agree with the engine (the stability bound).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

from ... import _native
from .scene import EFFECTS, Scene


def native_config(scene: Scene, threads: int = 0) -> _native.Config:
    """The native engine's view of a scene (material values as given: the engine derives)."""
    c = _native.Config()
    cloth, ball = scene["cloth"], scene["ball"]
    c.n = scene.n
    c.rest_len = scene.rest_length
    c.node_mass = scene.node_mass
    c.k_struct = cloth["k_structural"]
    c.k_shear = cloth["k_shear"]
    c.k_bend = cloth["k_bend"]
    c.bending_stiffness = cloth["bending_stiffness"]  # D, N m: the engine derives its k
    c.struct_compress = 1.0 if cloth["structural_two_sided"] else 0.0
    c.gravity = list(scene["sim"]["gravity"])
    # A material key leaves its per-node key None; the engine derives that value (-1: not
    # given, the per-node value holds).
    c.damping = cloth["damping"] if cloth["damping_rate"] is None else 0.0
    c.damping_rate = -1.0 if cloth["damping_rate"] is None else cloth["damping_rate"]
    c.ball_radius = ball["radius"]
    c.ball_mass = ball["mass"]
    c.ball_k = ball["stiffness"] if ball["stiffness_per_area"] is None else 0.0
    c.ball_k_area = -1.0 if ball["stiffness_per_area"] is None else ball["stiffness_per_area"]
    c.ball_damping = ball["damping"]
    c.ball_edges = ball["contact"] == "edges"
    c.coupling_k = scene["coupling"]["stiffness"]
    c.grip_radius = scene["coupling"]["grip_radius"]
    wind = scene["wind"]
    c.air_density = wind["air_density"]
    c.drag = wind["drag"]
    c.lift = wind["lift"]
    c.max_strain = scene["strain_limit"]["max_strain"]
    c.strain_iterations = scene["strain_limit"]["iterations"]
    c.threads = threads
    c.integrator = _native.INTEGRATOR_IDS[scene["sim"]["integrator"]]
    c.cg_max_iterations = scene["sim"]["cg_max_iterations"]
    c.cg_tolerance = scene["sim"]["cg_tolerance"]
    c.effects = effect_bits(scene.effects)
    return c


@dataclass(frozen=True)
class NodeValues:
    """The per-node values the engine runs a scene with."""

    damping: float  # beta1, N s/m per node
    ball_k: float  # k_b, N/m per node (per structural edge with edge contact)
    plate_k: float  # D / L^2, N/m: the plate bending term's stiffness a stencil


@lru_cache(maxsize=256)  # a scene is immutable; the stability bound asks every few frames
def node_values(scene: Scene) -> NodeValues:
    """What the engine derives from the scene's material values and n (or the scene's own
    per-node values where it gives those)."""
    c = _native.per_node(native_config(scene))
    return NodeValues(damping=float(c.damping), ball_k=float(c.ball_k),
                      plate_k=float(c.k_plate))


def effect_bits(effects: frozenset[str] | Sequence[str]) -> int:
    """The native bit mask of an effect set."""
    bits = 0
    for e in effects:
        bits |= _native.EFFECT_BITS[e]
    return bits


def effect_names(bits: int) -> frozenset[str]:
    """The effect names of a native bit mask."""
    return frozenset(e for e in EFFECTS if bits & _native.EFFECT_BITS[e])
