"""Total mechanical energy of a cloth state: the yardstick of the stability tests and the
accuracy study. Gravity's potential is measured from y = 0."""

from __future__ import annotations

import numpy as np

from ..sim.oracle import (
    BEND_DIRS,
    STRUCTURAL_DIRS,
    edge_weights,
    grips,
    node_contact_stiffness,
    node_plate_stiffness,
    plate_energy,
)
from ..sim.scene import Scene, mass_weights


def _spring_energy(pos: np.ndarray, dirs, k: float, rest: float, two_sided: bool) -> float:
    n = pos.shape[0]
    total = 0.0
    for di, dj in dirs[1::2]:  # each spring once: the positive half of each direction pair
        rows = slice(0, n - di)
        cols = slice(0, n - dj)
        d = pos[di:, dj:][: n - di, : n - dj] - pos[rows, cols]
        ext = np.linalg.norm(d, axis=-1) - rest
        if not two_sided:
            ext = np.maximum(ext, 0.0)
        total += 0.5 * k * float(np.sum(edge_weights(n, di, dj)[..., 0] * ext * ext))
    return total


def _segment_distances(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Distance from c to each segment a-b (flattened)."""
    e = b - a
    e2 = np.einsum("...i,...i", e, e)
    t = np.einsum("...i,...i", c - a, e) / np.where(e2 > 1e-30, e2, 1.0)
    t = np.where(e2 > 1e-30, np.clip(t, 0.0, 1.0), 0.5)[..., None]
    return np.linalg.norm(a + t * e - c, axis=-1).ravel()


def total_energy(
    scene: Scene,
    pos: np.ndarray,
    vel: np.ndarray,
    ball_pos: np.ndarray | None = None,
    ball_vel: np.ndarray | None = None,
    hips: np.ndarray | None = None,
) -> float:
    """Kinetic + gravitational + spring + coupling + contact energy, J."""
    fx, cloth, m = scene.effects, scene["cloth"], scene.node_masses[..., 0]
    g = np.array(scene["sim"]["gravity"]) if "gravity" in fx else np.zeros(3)
    e = 0.5 * float(np.sum(m * np.sum(vel * vel, axis=-1))) - float(np.sum(m * (pos @ g)))
    L = scene.rest_length
    if "structural" in fx:
        e += _spring_energy(
            pos, STRUCTURAL_DIRS, cloth["k_structural"], L, cloth["structural_two_sided"]
        )
    if "shear" in fx:
        # Each diagonal once: (i, j)-(i+1, j+1) and (i, j+1)-(i+1, j).
        for a, b in ((pos[1:, 1:], pos[:-1, :-1]), (pos[1:, :-1], pos[:-1, 1:])):
            ext = np.linalg.norm(a - b, axis=-1) - L * np.sqrt(2.0)
            e += 0.5 * cloth["k_shear"] * float(np.sum(ext * ext))
    if "bend" in fx:
        e += _spring_energy(pos, BEND_DIRS, cloth["k_bend"], 2 * L, True)
        e += plate_energy(pos, node_plate_stiffness(scene))
    if "coupling" in fx and hips is not None:
        K = scene["coupling"]["stiffness"]
        for grip in grips(scene):
            d = hips[grip.corner] + grip.offset - pos[grip.i, grip.j]
            e += 0.5 * K * grip.share * float(d @ d)
    if "ball" in fx and ball_pos is not None and ball_vel is not None:
        ball = scene["ball"]
        e += 0.5 * ball["mass"] * float(ball_vel @ ball_vel) - ball["mass"] * float(ball_pos @ g)
        if ball["contact"] == "edges":
            # Edge contact is conservative too: 1/2 k_b (R - r)^2 per structural segment, r
            # its distance to the centre (the force is its gradient at the nearest point).
            r = np.concatenate([_segment_distances(a, b, ball_pos) for a, b in (
                (pos[:, :-1], pos[:, 1:]), (pos[:-1, :], pos[1:, :]))])
            n = pos.shape[0]
            w = np.concatenate([edge_weights(n, 0, 1).ravel(), edge_weights(n, 1, 0).ravel()])
        else:
            r = np.linalg.norm(pos - ball_pos, axis=-1).ravel()
            w = mass_weights(pos.shape[0]).ravel()
        pen = np.maximum(ball["radius"] - r, 0.0)
        e += 0.5 * node_contact_stiffness(scene) * float(np.sum(w * pen * pen))
    return e


def cloth_energy(cloth) -> float:
    """total_energy of a running Cloth (or ReferenceCloth-like object with the same API)."""
    bp, bv = cloth.ball()
    return total_energy(cloth.scene, cloth.positions(), cloth.velocities(), bp, bv, cloth.hips())
