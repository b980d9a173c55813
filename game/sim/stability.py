"""Stable substeps: the largest dt the integrator in use takes without blowing up.

The derivation is in ``docs/stability.md``. In short, linearise each node's equation of
motion to m x'' = -k_eff x - c x'. Semi-implicit Euler is then stable when
``omega^2 dt^2 + 2 gamma dt < 4`` with omega^2 = k_eff / m and gamma = c / m, i.e.
``dt < (sqrt(gamma^2 + 4 omega^2) - gamma) / omega^2``. Gershgorin's theorem bounds the
largest k_eff / m of the coupled system by each node's row sum over its mass: twice the
stiffness of every spring at the node (structural, shear, bending, ball contact; edge
contact counts 8 k_b) plus the plate bending term's row (64 D / L^2 inside) plus the
coupling spring to the fixed hand, over the node's mass by area (an interior node's m,
half on an edge, a quarter at a corner: fewer springs on less mass, so a border node
bounds it). The ball is bounded the same way from the contacts it can have at once,
and must not move more than ``BALL_TRAVEL`` of its radius per substep (no tunnelling).

Per integrator (``sim.integrator``): velocity Verlet has the same bound with its damping
left out (the damping is implicit in its closing half kick, and the damped scheme is stable
for ``omega dt < 2`` whatever gamma; only the wind's explicit drag counts as damping);
implicit Euler is bounded by the tunnelling limit alone (one substep a frame without a ball).
"""

from __future__ import annotations

import functools
import math
import weakref
from typing import TYPE_CHECKING

import numpy as np

from .config import node_values
from .grip import grips
from .scene import line_weights, mass_weights

if TYPE_CHECKING:
    from .scene import Scene

SAFETY = 0.9  # stay this fraction inside the bound
BALL_TRAVEL = 0.2  # most of its radius the ball may move in one substep
# Tension-only structural springs switch off as they cross their rest length, and across
# such a kink the explicit schemes keep no energy: a net shaken hard, nearly undamped
# (damping ratio 3.6e-5), resonated at 0.9 of the linear bound and not at 0.85, and with
# a ratio of 8.6e-5 not at 0.9 (docs/stability.md, "Tension-only springs"). Below
# SWITCH_ZETA the bound keeps SWITCH_MARGIN of itself instead of SAFETY.
SWITCH_ZETA = 2e-4
SWITCH_MARGIN = 0.85


def euler_dt_bound(omega2: float, gamma: float) -> float:
    """Largest stable semi-implicit Euler dt for m x'' = -k x - c x'.

    omega2 = k / m, gamma = c / m.
    """
    if omega2 <= 0.0:
        return 2.0 / gamma if gamma > 0.0 else math.inf
    return (math.sqrt(gamma * gamma + 4.0 * omega2) - gamma) / omega2


@functools.lru_cache(maxsize=64)
def _node_rows(n: int) -> tuple[np.ndarray, ...]:
    """Per node of an n x n grid, for Gershgorin's bound: its mass weight (1, 1/2, 1/4:
    masses by area), how many structural, shear and bending springs meet it (one along a
    free edge counts a half), and the absolute row sum of the plate term's B^T B (64
    inside, less near the border). A node's row depends only on
    its distance (up to 2) from each edge, so a grid of at most 9 x 9 has every kind."""
    m = min(n, 9)
    w, weight = line_weights(m), mass_weights(m)
    idx = np.arange(m)
    lo, hi = (idx > 0).astype(float), (idx < m - 1).astype(float)
    two = (idx >= 2).astype(float) + (idx <= m - 3)  # neighbours 2 away along an axis
    # Springs along a row count at the row's edge weight (1/2 on a border row: the core's
    # edge_spring_weight), springs along a column at the column's.
    struct = (lo + hi)[:, None] * w[None, :] + (lo + hi)[None, :] * w[:, None]
    shear = np.outer(lo, lo) + np.outer(lo, hi) + np.outer(hi, lo) + np.outer(hi, hi)
    bend = two[:, None] * w[None, :] + two[None, :] * w[:, None]
    # B: one row per second difference (rows, columns) and per cell's twist (weight 2 in E).
    rows = []
    for i in range(m):
        for j in range(m):
            for di, dj in ((0, 1), (1, 0)):
                if i + 2 * di < m and j + 2 * dj < m:
                    r = np.zeros((m, m))
                    r[i, j], r[i + di, j + dj], r[i + 2 * di, j + 2 * dj] = 1.0, -2.0, 1.0
                    rows.append(r.ravel())
            if i + 1 < m and j + 1 < m:
                r = np.zeros((m, m))
                r[i, j], r[i, j + 1], r[i + 1, j], r[i + 1, j + 1] = 1.0, -1.0, -1.0, 1.0
                rows.append(math.sqrt(2.0) * r.ravel())
    b = np.array(rows) if rows else np.zeros((0, m * m))
    plate = np.abs(b.T @ b).sum(axis=1).reshape(m, m)
    return weight, struct, shear, bend, plate


def node_stiffness(scene: Scene) -> float:
    """Gershgorin bound on the stiffness (N/m) per interior node mass: the largest row sum
    of |K| over the node's mass weight (masses by area), so that omega_max^2 <= this / m
    with m an interior node's mass. A border node has fewer springs but half (a corner a
    quarter) of the mass, so it, not the interior, can be the stiffest per unit mass."""
    cloth, fx = scene["cloth"], scene.effects
    weight, struct, shear, bend, plate = _node_rows(scene.n)
    k = np.zeros_like(weight)
    if "structural" in fx:
        k += 2 * struct * cloth["k_structural"]
    if "shear" in fx:
        k += 2 * shear * cloth["k_shear"]
    if "bend" in fx:
        k += 2 * bend * cloth["k_bend"]
        # The plate term's row of k B^T B: |20| + 4 |-8| + 4 |2| + 4 |1| = 64 k in the interior
        # (less at the border).
        k += plate * node_values(scene).plate_k
    if "ball" in fx:
        # Nodes: the contact's k_b on the diagonal and -k_b in the ball's column. Edges: each
        # of the 4 structural edges adds at most 2 k_b (docs/stability.md). Per area, as the
        # masses: a border node's k_b (and its edges' along the border) are shares of it.
        k += (8 if scene["ball"]["contact"] == "edges" else 2) * node_values(scene).ball_k * weight
    bound = float(np.max(k / weight))
    if "coupling" in fx:
        # A held node's row gains its share of K (its grip's density: the corner's share is
        # the largest, on a quarter of the mass).
        K, n, m = scene["coupling"]["stiffness"], scene.n, weight.shape[0]

        def rep(i: int) -> int:  # the representative grid's row of the same kind
            return i if i < 3 else (m - n + i if n - 1 - i < 3 else m // 2)

        for g in grips(scene):
            a, b = rep(g.i), rep(g.j)
            bound = max(bound, (k[a, b] + K * g.share) / weight[a, b])
    return bound


def max_ball_contacts(scene: Scene) -> float:
    """Most contacts the ball can have at once. Nodes: the grid points of its cross-section.
    Edges: the structural edges whose midpoints lie within R + L/2 of its centre, a shifted
    grid per direction."""
    r = scene["ball"]["radius"] / scene.rest_length
    n = scene.n
    if scene["ball"]["contact"] == "edges":
        return min(2.0 * n * (n - 1), 2.0 * math.pi * (r + 1.5) ** 2)
    return min(float(n * n), math.pi * (r + 1.0) ** 2)


def stable_dt(scene: Scene, ball_speed: float = 0.0) -> float:
    """Largest substep dt, inside the stability bound of the scene's integrator with the
    SAFETY margin."""
    return float(stable_dts(scene, np.array([float(ball_speed)]))[0])


def stable_dts(scene: Scene, ball_speeds: np.ndarray) -> np.ndarray:
    """``stable_dt`` for many ball speeds at once (a batch's slots): element for element
    the same numbers."""
    integrator = scene["sim"]["integrator"]
    explicit_damping = integrator == "semi_implicit_euler"
    m = scene.node_mass  # an interior node's; node_stiffness is per unit of it
    damped = "damping" in scene.effects and explicit_damping
    gamma = node_values(scene).damping / m if damped else 0.0
    if "wind" in scene.effects:
        # Drag is a damping force: d|F|/d|v| <= rho Cd A |u| on a node's share A of area
        # (a third of each of its triangles': L^2 inside, where the node's mass is m), with
        # |u| bounded by the wind's peak speed plus a generous node speed. Per unit mass
        # (masses by area) a corner is the largest: two triangles, L^2 / 3, on m / 4.
        w = scene["wind"]
        peak = math.hypot(*w["velocity"]) * (1.0 + w["gust_amplitude"]) + 10.0
        area = scene.rest_length**2 * 4.0 / 3.0
        gamma += w["air_density"] * w["drag"] * area * peak / m
    omega2 = node_stiffness(scene) / m
    dt = euler_dt_bound(omega2, gamma)
    if switch_resonance(scene, omega2):
        dt *= SWITCH_MARGIN / SAFETY
    if integrator == "implicit_euler":
        dt = math.inf  # no stability limit on the step; tunnelling still bounds it below
    dts = np.full(len(ball_speeds), dt)
    if "ball" in scene.effects:
        ball = scene["ball"]
        if integrator != "implicit_euler":
            kb = 2.0 * max_ball_contacts(scene) * node_values(scene).ball_k
            gb = ball["damping"] / ball["mass"] if explicit_damping else 0.0
            dts = np.minimum(dts, euler_dt_bound(kb / ball["mass"], gb))
        frame = scene["sim"]["frame_dt"]
        g = math.hypot(*scene["sim"]["gravity"]) if "gravity" in scene.effects else 0.0
        speed = np.asarray(ball_speeds, dtype=np.float64) + g * frame
        with np.errstate(divide="ignore"):
            travel = BALL_TRAVEL * ball["radius"] / speed / SAFETY
        dts = np.where(speed > 0.0, np.minimum(dts, travel), dts)
    return SAFETY * dts


def switch_resonance(scene: Scene, omega2: float) -> bool:
    """Whether the scene's tension-only structural springs are so lightly damped that the
    bound needs SWITCH_MARGIN: the cloth's damping ratio at its fastest mode, rate / (2
    omega_max), below SWITCH_ZETA (whatever the integrator: the damping is the cloth's)."""
    fx = scene.effects
    if "structural" not in fx or scene["cloth"]["structural_two_sided"] or omega2 <= 0.0:
        return False
    rate = node_values(scene).damping / scene.node_mass if "damping" in fx else 0.0
    return rate / (2.0 * math.sqrt(omega2)) < SWITCH_ZETA


def auto_substeps(scene: Scene, ball_speed: float = 0.0) -> int:
    """Smallest substep count per frame whose dt lies within the stability bound."""
    return int(auto_substeps_all(scene, np.array([float(ball_speed)]))[0])


def auto_substeps_all(scene: Scene, ball_speeds: np.ndarray) -> np.ndarray:
    """``auto_substeps`` for many ball speeds at once."""
    frame = scene["sim"]["frame_dt"]
    return np.maximum(1, np.ceil(frame / stable_dts(scene, ball_speeds) - 1e-9)).astype(
        np.int64)


def substep_speed_limits(scene: Scene, most: int = 256) -> np.ndarray:
    """``auto_substeps`` as a table, for an engine that picks substeps without Python (the
    server's native frame loop): entry ``k - 1`` is the fastest ball speed (m/s) that ``k``
    substeps hold, ascending (-1: ``k`` never suffices), found by bisecting
    ``auto_substeps_all`` itself, so the rule has one home. Speeds past the last entry get
    ``most`` substeps."""
    k = np.arange(1, most + 1)
    lo = np.zeros(most)
    hi = np.full(most, 1e6)
    ok0 = auto_substeps_all(scene, lo) <= k
    for _ in range(80):  # to the nearest float64 of the boundary
        mid = 0.5 * (lo + hi)
        fits = auto_substeps_all(scene, mid) <= k
        lo = np.where(fits, mid, lo)
        hi = np.where(fits, hi, mid)
    return np.where(ok0, lo, -1.0)


# Each scene's speed table, built once and kept while the scene object lives.
_TABLES: weakref.WeakKeyDictionary[Scene, np.ndarray] = weakref.WeakKeyDictionary()


def substeps_for_speeds(scene: Scene, ball_speeds: np.ndarray) -> np.ndarray:
    """``auto_substeps_all``, element for element, by a lookup in the scene's
    ``substep_speed_limits`` table (the native frame loop's rule): what a cloth or a batch
    asks after every frame with a ball, ~12 µs where the formula took ~80 µs of NumPy (the
    larger part of a small cloth's frame). Speeds past the table's last entry take the
    formula."""
    limits = _TABLES.get(scene)
    if limits is None:
        limits = _TABLES[scene] = substep_speed_limits(scene)
    speeds = np.asarray(ball_speeds, dtype=np.float64)
    k = np.searchsorted(limits, speeds) + 1
    over = k > len(limits)
    if over.any():
        k[over] = auto_substeps_all(scene, speeds[over])
    return k.astype(np.int64)
