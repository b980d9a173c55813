"""Stable substeps: the largest dt the integrator in use takes without blowing up.

The derivation is in ``docs/stability.md``. In short, linearise each node's equation of
motion to m x'' = -k_eff x - c x'. Semi-implicit Euler is then stable when
``omega^2 dt^2 + 2 gamma dt < 4`` with omega^2 = k_eff / m and gamma = c / m, i.e.
``dt < (sqrt(gamma^2 + 4 omega^2) - gamma) / omega^2``. Gershgorin's theorem bounds the
largest k_eff of the coupled system by each node's row sum: twice the stiffness of every
spring at the node (structural, shear, bending, ball contact; edge contact counts 8 k_b)
plus the plate bending term's row (64 D / L^2) plus the coupling spring to
the fixed hand. The ball is bounded the same way from the contacts it can have at once,
and must not move more than ``BALL_TRAVEL`` of its radius per substep (no tunnelling).

Per integrator (``sim.integrator``): velocity Verlet has the same bound with its damping
left out (the damping is implicit in its closing half kick, and the damped scheme is stable
for ``omega dt < 2`` whatever gamma; only the wind's explicit drag counts as damping);
implicit Euler is bounded by the tunnelling limit alone (one substep a frame without a ball).
"""

from __future__ import annotations

import math
import weakref
from typing import TYPE_CHECKING

import numpy as np

from .config import node_values

if TYPE_CHECKING:
    from .scene import Scene

SAFETY = 0.9  # stay this fraction inside the bound
BALL_TRAVEL = 0.2  # most of its radius the ball may move in one substep


def euler_dt_bound(omega2: float, gamma: float) -> float:
    """Largest stable semi-implicit Euler dt for m x'' = -k x - c x'.

    omega2 = k / m, gamma = c / m.
    """
    if omega2 <= 0.0:
        return 2.0 / gamma if gamma > 0.0 else math.inf
    return (math.sqrt(gamma * gamma + 4.0 * omega2) - gamma) / omega2


def node_stiffness(scene: Scene) -> float:
    """Gershgorin bound on the stiffness (N/m) acting on the stiffest node."""
    cloth, fx = scene["cloth"], scene.effects
    k = 0.0
    if "structural" in fx:
        k += 2 * 4 * cloth["k_structural"]
    if "shear" in fx:
        k += 2 * 4 * cloth["k_shear"]
    if "bend" in fx:
        k += 2 * 4 * cloth["k_bend"]
        # The plate term's row of k B^T B: |20| + 4 |-8| + 4 |2| + 4 |1| = 64 k in the interior
        # (less at the border).
        k += 64 * node_values(scene).plate_k
    if "ball" in fx:
        # Nodes: the contact's k_b on the diagonal and -k_b in the ball's column. Edges: each
        # of the 4 structural edges adds at most 2 k_b (docs/stability.md).
        k += (8 if scene["ball"]["contact"] == "edges" else 2) * node_values(scene).ball_k
    if "coupling" in fx:
        k += scene["coupling"]["stiffness"]
    return k


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
    m = scene.node_mass
    damped = "damping" in scene.effects and explicit_damping
    gamma = node_values(scene).damping / m if damped else 0.0
    if "wind" in scene.effects:
        # Drag is a damping force: d|F|/d|v| <= rho Cd A |u| on a node's share A = L^2 of
        # area, with |u| bounded by the wind's peak speed plus a generous node speed.
        w = scene["wind"]
        peak = math.hypot(*w["velocity"]) * (1.0 + w["gust_amplitude"]) + 10.0
        gamma += w["air_density"] * w["drag"] * scene.rest_length**2 * peak / m
    dt = euler_dt_bound(node_stiffness(scene) / m, gamma)
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
