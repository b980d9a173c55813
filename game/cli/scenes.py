"""``clothball scenes``: list the shipped scenes, their material values and what the engine
derives from them per node."""

from __future__ import annotations

import argparse

from ..sim.config import node_values
from ..sim.grip import grips
from ..sim.scene import MATERIAL_KEYS, Scene, available, schema_markdown

UNITS = {"damping": "N s/m per node", "stiffness": "N/m per node"}
MATERIAL_UNITS = {"damping_rate": "1/s", "stiffness_per_area": "N/m^3",
                  "bending_stiffness": "N m"}


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--markdown", action="store_true", help="print the scene key reference")


def describe(s: Scene) -> list[str]:
    """A scene's line and, for each per-node value it has, where it comes from."""
    lines = [f"{s.name:12} n={s.n:<5} effects: {', '.join(sorted(s.effects))}"]
    derived = node_values(s)
    values = {"damping": derived.damping, "stiffness": derived.ball_k}
    needs = {"damping": "damping", "stiffness": "ball"}
    for (section, material), per_node in MATERIAL_KEYS.items():
        if needs[per_node] not in s.effects:
            continue
        got = f"{section}.{per_node} {values[per_node]:.6g} {UNITS[per_node]}"
        given = s[section][material]
        if given is None:
            lines.append(f"{'':14}{got} (a per-node key: the material changes with n)")
        else:
            lines.append(f"{'':14}{section}.{material} = {given:.6g} "
                         f"{MATERIAL_UNITS[material]} -> {got} at n = {s.n}")
    if "bend" in s.effects and s["cloth"]["bending_stiffness"] > 0:
        lines.append(f"{'':14}cloth.bending_stiffness = {s['cloth']['bending_stiffness']:.6g} "
                     f"{MATERIAL_UNITS['bending_stiffness']} -> plate k {derived.plate_k:.6g} "
                     f"N/m a stencil (D / L^2) at n = {s.n}")
    if "coupling" in s.effects:
        k, a = s["coupling"]["stiffness"], s["coupling"]["grip_radius"]
        held = [g for g in grips(s) if g.corner == 0]
        if a > 0:
            lines.append(f"{'':14}coupling.grip_radius = {a:.6g} m -> K {k:.6g} N/m over "
                         f"{len(held)} nodes a hand (the corner node {k * held[0].share:.4g} N/m) "
                         f"at n = {s.n}")
        else:
            lines.append(f"{'':14}coupling: K {k:.6g} N/m on the corner node (a point support: "
                         f"the sag grows as log n)")
    return lines


def run(args: argparse.Namespace) -> int:
    if args.markdown:
        print(schema_markdown())
        return 0
    for name in available():
        print("\n".join(describe(Scene.load(name))))
    return 0
