"""The hands' grips (eq. 7 over a patch, docs/scenes.md), node by node, from the scene
alone: what the oracle couples and the stability bound counts. The engine derives the same
shares in its own code (native/core/params.hpp: grip_weight), so the tests check it."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .scene import Scene


class Grip(NamedTuple):
    """One node a hand holds: its hand (corner slot), the node, its share of the hand's
    stiffness K and its rest offset from the corner (m; the hand pulls it to hip + offset)."""

    corner: int
    i: int
    j: int
    share: float
    offset: np.ndarray


def grip_density(s: float, a: float) -> float:
    """The grip's stiffness density along an edge at s from the corner, relative to the
    corner's: (1 - (s / a)^2)^2 within a (smooth at the corner, where it is even, and flat
    where it ends), 0 beyond."""
    x = s / a
    return (1.0 - x * x) ** 2 if x < 1.0 else 0.0


def grips(scene: Scene) -> list[Grip]:
    """Every node the hands hold: a hand holds its corner node, and with
    ``coupling.grip_radius`` a > 0 the nodes of its corner's two edges closer than a to the
    corner (none past the edge's middle, which would be another hand's), each with the
    density at its point times the spacing (the trapezoid rule; the corner's on both edges:
    its density once), shares summing to 1 a hand."""
    n, L = scene.n, scene.rest_length
    a = scene["coupling"]["grip_radius"]
    held = []  # (corner, i, j, weight, offset)
    for c, (ci, cj) in enumerate(((0, 0), (0, n - 1), (n - 1, n - 1), (n - 1, 0))):
        di, dj = (1 if ci == 0 else -1), (1 if cj == 0 else -1)
        held.append((c, ci, cj, 1.0, np.zeros(3)))
        m = 1
        while a > 0 and m * L < a and 2 * m <= n - 2:
            w = grip_density(m * L, a)
            held.append((c, ci, cj + dj * m, w, np.array([dj * m * L, 0.0, 0.0])))
            held.append((c, ci + di * m, cj, w, np.array([0.0, 0.0, di * m * L])))
            m += 1
    total = [sum(h[3] for h in held if h[0] == c) for c in range(4)]
    return [Grip(c, i, j, w / total[c], off) for c, i, j, w, off in held]
