"""The hands' grips (eq. 7 over a patch, docs/scenes.md), node by node, from the scene
alone: what the oracle couples and the stability bound counts. The engine derives the same
shares in its own code (native/core/params.hpp: grip_weight), so the tests check it."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.polynomial import Polynomial

from .scene import Scene

# The hands' corners (i, j) in their slot order (native/core/forces.hpp corner_slot):
# (0, 0), (0, n - 1), (n - 1, n - 1), (n - 1, 0).
CORNER_INDEX = ((0, 0), (0, -1), (-1, -1), (-1, 0))


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


def hat_share(m: int, L: float, a: float) -> float:
    """The grip's density integrated against the hat function of the node m spacings from
    the corner (1 - |s - m L| / L), over the edge within a, in metres; the corner's (m = 0)
    over both edges. Exact: the density is a polynomial within a, integrated piece by
    piece (numpy's Polynomial), not the engine's Gauss rule."""
    rho = Polynomial([1.0, 0.0, -2.0 / a**2, 0.0, 1.0 / a**4])  # (1 - (s / a)^2)^2
    s_m = m * L
    pieces = [(s_m - L, s_m, Polynomial([1.0 - s_m / L, 1.0 / L])),  # rising side
              (s_m, s_m + L, Polynomial([1.0 + s_m / L, -1.0 / L]))]  # falling side
    total = 0.0
    for lo, hi, hat in pieces:
        lo, hi = max(lo, 0.0), min(hi, a)
        if hi > lo:
            f = (rho * hat).integ()
            total += f(hi) - f(lo)
    return 2.0 * total if m == 0 else total


def grips(scene: Scene) -> list[Grip]:
    """Every node the hands hold: a hand holds its corner node, and with
    ``coupling.grip_radius`` a > L (a spacing) the nodes of its corner's two edges whose hat
    function meets the density, (m - 1) L < a (none past the edge's middle, which would be
    another hand's), each with its ``hat_share``; the shares sum to 1 a hand."""
    n, L = scene.n, scene.rest_length
    a = scene["coupling"]["grip_radius"]
    spread = a > L  # else the corner node alone
    held = []  # (corner, i, j, weight, offset)
    for c, (ci, cj) in enumerate((i % n, j % n) for i, j in CORNER_INDEX):
        di, dj = (1 if ci == 0 else -1), (1 if cj == 0 else -1)
        held.append((c, ci, cj, hat_share(0, L, a) if spread else 1.0, np.zeros(3)))
        m = 1
        while spread and (m - 1) * L < a and 2 * m <= n - 2:
            w = hat_share(m, L, a)
            held.append((c, ci, cj + dj * m, w, np.array([dj * m * L, 0.0, 0.0])))
            held.append((c, ci + di * m, cj, w, np.array([0.0, 0.0, di * m * L])))
            m += 1
    total = [sum(h[3] for h in held if h[0] == c) for c in range(4)]
    return [Grip(c, i, j, w / total[c], off) for c, i, j, w, off in held]
