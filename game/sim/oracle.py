"""A NumPy float64 implementation of the same equations: the test oracle.

Readable rather than fast, and independent of the native core (it shares no code with
it, only the scene). Every force of a substep comes from the state at the substep's start.
"""

from __future__ import annotations

import numpy as np

from ... import _native
from .cloth import corners_of, rest_positions
from .grip import grips
from .scene import Scene, line_weights, mass_weights

STRUCTURAL_DIRS = ((0, -1), (0, 1), (-1, 0), (1, 0))
SHEAR_DIRS = ((-1, -1), (-1, 1), (1, -1), (1, 1))
BEND_DIRS = ((0, -2), (0, 2), (-2, 0), (2, 0))


def spring(pi: np.ndarray, pj: np.ndarray, k: float, rest: float, compress: float) -> np.ndarray:
    """Force on i from a spring to j (eq. 2); compress=0 makes it tension-only."""
    d = pj - pi
    length = np.linalg.norm(d, axis=-1, keepdims=True)
    ext = length - rest
    ext = np.where(ext > 0, ext, ext * compress)
    scale = np.where(length > 1e-12, k * ext / np.where(length > 1e-12, length, 1.0), 0.0)
    return d * scale


def edge_weights(n: int, di: int, dj: int) -> np.ndarray:
    """The stiffness factor of each node's spring to its neighbour at (di, dj), over the
    nodes that have one ((rows, cols, 1)): 1/2 for a spring along a free edge (both ends on
    the border row or column), which stands for half the strip of sheet an inner one does;
    1 elsewhere."""
    w = np.ones((n - abs(di), n - abs(dj), 1))
    if di == 0:  # along a row: the row's weight
        w = w * line_weights(n)[:, None, None]
    if dj == 0:  # along a column: the column's
        w = w * line_weights(n)[None, :, None]
    return w


def add_springs(f: np.ndarray, pos: np.ndarray, dirs, k: float, rest: float, compress: float):
    """Add to f the force on each node from its neighbour at offset (di, dj), where it
    exists (a spring along a free edge at half k: ``edge_weights``)."""
    n = pos.shape[0]
    for di, dj in dirs:
        rows = slice(max(0, -di), n - max(0, di))
        cols = slice(max(0, -dj), n - max(0, dj))
        nrows = slice(max(0, -di) + di, n - max(0, di) + di)
        ncols = slice(max(0, -dj) + dj, n - max(0, dj) + dj)
        kw = k * edge_weights(n, di, dj)
        f[rows, cols] += spring(pos[rows, cols], pos[nrows, ncols], kw, rest, compress)


def plate_force(pos: np.ndarray, k: float) -> np.ndarray:
    """The plate bending force (cloth.bending_stiffness) on every node: minus the gradient
    of E = k/2 (sum of |x_a - 2 x_b + x_c|^2 over the row and column triples + 2 sum of
    |x_00 - x_01 - x_10 + x_11|^2 over the cells), k = D / L^2, each second difference
    scattered back to its nodes (B^T B x; the engine sums a 13-node stencil instead). Linear
    in the positions; zero on any plane."""
    f = np.zeros_like(pos)
    rows = pos[:, :-2] - 2.0 * pos[:, 1:-1] + pos[:, 2:]
    f[:, :-2] -= k * rows
    f[:, 1:-1] += 2.0 * k * rows
    f[:, 2:] -= k * rows
    cols = pos[:-2] - 2.0 * pos[1:-1] + pos[2:]
    f[:-2] -= k * cols
    f[1:-1] += 2.0 * k * cols
    f[2:] -= k * cols
    cells = pos[:-1, :-1] - pos[:-1, 1:] - pos[1:, :-1] + pos[1:, 1:]
    f[:-1, :-1] -= 2.0 * k * cells
    f[:-1, 1:] += 2.0 * k * cells
    f[1:, :-1] += 2.0 * k * cells
    f[1:, 1:] -= 2.0 * k * cells
    return f


def plate_energy(pos: np.ndarray, k: float) -> float:
    """The plate bending energy whose negative gradient is ``plate_force``, J."""
    rows = pos[:, :-2] - 2.0 * pos[:, 1:-1] + pos[:, 2:]
    cols = pos[:-2] - 2.0 * pos[1:-1] + pos[2:]
    cells = pos[:-1, :-1] - pos[:-1, 1:] - pos[1:, :-1] + pos[1:, 1:]
    return 0.5 * k * float(np.sum(rows * rows) + np.sum(cols * cols) + 2.0 * np.sum(cells * cells))


def plate_diagonal(n: int, k: float) -> np.ndarray:
    """The diagonal of k B^T B (n, n): each node's squared coefficients over the stencils
    that hold it (1 or 4 a triple, 2 a cell)."""
    d = np.zeros((n, n))
    for sl in (np.s_[:, :-2], np.s_[:, 2:], np.s_[:-2], np.s_[2:]):
        d[sl] += 1.0
    for sl in (np.s_[:, 1:-1], np.s_[1:-1]):
        d[sl] += 4.0
    for sl in (np.s_[:-1, :-1], np.s_[:-1, 1:], np.s_[1:, :-1], np.s_[1:, 1:]):
        d[sl] += 2.0
    return k * d


def ball_contact(pos: np.ndarray, centre: np.ndarray, radius: float,
                 k: float | np.ndarray) -> np.ndarray:
    """Eq. (4) on every node inside the ball (k: one for all, or each node's, (..., 1)); a
    node at the very centre is pushed down."""
    d = pos - centre
    r = np.linalg.norm(d, axis=-1, keepdims=True)
    inside = r < radius
    safe_r = np.where(r > 1e-12, r, 1.0)
    f = np.where(inside & (r > 1e-12), d * (k * (radius - r) / safe_r), 0.0)
    at_centre = (inside & (r <= 1e-12))[..., 0]
    f[at_centre] = 0.0
    f[at_centre, 1] = -np.broadcast_to(k, r.shape)[at_centre, 0] * radius
    return f


def edge_contact(
    pos: np.ndarray, centre: np.ndarray, radius: float, k: float
) -> tuple[np.ndarray, np.ndarray]:
    """Edge contact: eq. (4) at each structural segment's point nearest the ball's centre,
    q = a + t (b - a) with t clamped to [0, 1] (t = 1/2 for a zero-length segment); node a
    takes (1 - t) of it, node b takes t. Returns the force on every node and the summed
    contact force (the ball takes minus it). Per area, as the springs: a segment along the
    cloth's border takes half of k (``edge_weights``)."""
    n = pos.shape[0]
    f = np.zeros_like(pos)
    total = np.zeros(3)
    for a_sl, b_sl, (di, dj) in (
        ((slice(None), slice(0, n - 1)), (slice(None), slice(1, n)), (0, 1)),  # along j
        ((slice(0, n - 1), slice(None)), (slice(1, n), slice(None)), (1, 0)),  # along i
    ):
        a, b = pos[a_sl], pos[b_sl]
        e = b - a
        e2 = np.einsum("...i,...i", e, e)
        has_len = e2 > 1e-30
        t = np.einsum("...i,...i", centre - a, e) / np.where(has_len, e2, 1.0)
        t = np.where(has_len, np.clip(t, 0.0, 1.0), 0.5)[..., None]
        fe = ball_contact(a + t * e, centre, radius, k * edge_weights(n, di, dj))
        f[a_sl] += (1.0 - t) * fe
        f[b_sl] += t * fe
        total += fe.sum(axis=(0, 1))
    return f, total


def triangles(n: int) -> np.ndarray:
    """Vertex indices (T, 3) of the grid's triangles: quad (a, b, c, d) = ((i,j), (i,j+1),
    (i+1,j+1), (i+1,j)) split into (a, b, c) and (a, c, d)."""
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a, b = i * n + j, i * n + j + 1
    c, d = (i + 1) * n + j + 1, (i + 1) * n + j
    t1 = np.stack([a, b, c], axis=-1).reshape(-1, 3)
    t2 = np.stack([a, c, d], axis=-1).reshape(-1, 3)
    return np.concatenate([t1, t2])


def wind_forces(
    pos: np.ndarray, vel: np.ndarray, wind: np.ndarray, rho: float, cd: float, cl: float
) -> np.ndarray:
    """Drag and lift on every triangle from the relative wind, a third to each vertex.

    Per triangle with unit normal n turned to face the relative wind u = wind - mean vertex
    velocity, area A and cos(theta) = u.n / |u|: drag 1/2 rho Cd A |u|^2 cos(theta) u/|u|,
    lift 1/2 rho Cl A |u|^2 cos(theta) (cos(theta) u/|u| - n).
    """
    n = pos.shape[0]
    P, V = pos.reshape(-1, 3), vel.reshape(-1, 3)
    tri = triangles(n)
    p0, p1, p2 = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
    u = wind - (V[tri[:, 0]] + V[tri[:, 1]] + V[tri[:, 2]]) / 3.0
    nrm = np.cross(p1 - p0, p2 - p0)
    twice_area = np.linalg.norm(nrm, axis=1)
    ulen = np.linalg.norm(u, axis=1)
    ok = (twice_area > 1e-30) & (ulen > 1e-12)
    nh = nrm / np.where(ok, twice_area, 1.0)[:, None]
    un = np.einsum("ij,ij->i", u, nh)
    nh = np.where((un < 0)[:, None], -nh, nh)
    un = np.abs(un)
    area = 0.5 * twice_area
    cos = un / np.where(ok, ulen, 1.0)
    u_hat = u / np.where(ok, ulen, 1.0)[:, None]
    drag = 0.5 * rho * cd * (area * ulen**2 * cos)[:, None] * u_hat
    lift = 0.5 * rho * cl * (area * ulen**2 * cos)[:, None] * (cos[:, None] * u_hat - nh)
    f_tri = np.where(ok[:, None], drag + lift, 0.0)
    out = np.zeros_like(P)
    for k in range(3):
        np.add.at(out, tri[:, k], f_tri / 3.0)
    return out.reshape(pos.shape)


def strain_limit_lines(pos: np.ndarray, vel: np.ndarray, max_len: float, inv_dt: float) -> None:
    """Provot's strain limiting along the lines pos[l, :] (all lines at once), in place:
    follow-the-leader, going along j, node j moves by the whole excess of its spring to the
    just-limited node j - 1 (node 0 leads and stays); the velocity takes the correction
    times inv_dt. One pass leaves every spring of every line within max_len."""
    n = pos.shape[1]
    lead = pos[:, 0].copy()
    for j in range(1, n):
        x = pos[:, j]
        d = lead - x
        length = np.sqrt(np.sum(d * d, axis=-1, keepdims=True))
        over = length - max_len
        on = over > 0
        corr = np.where(on, d * (over / np.where(on, length, 1.0)), 0.0)
        pos[:, j] = np.where(on, x + corr, x)
        vel[:, j] = np.where(on, vel[:, j] + corr * inv_dt, vel[:, j])
        lead = pos[:, j].copy()


def grid_normals(pos: np.ndarray) -> np.ndarray:
    """Unit normals from the cross product of the grid tangents (central differences)."""
    tv = np.gradient(pos, axis=0)  # along i (+z at rest)
    tu = np.gradient(pos, axis=1)  # along j (+x at rest)
    nrm = np.cross(tv, tu)
    length = np.linalg.norm(nrm, axis=-1, keepdims=True)
    up = np.broadcast_to(np.array([0.0, 1.0, 0.0]), nrm.shape)
    return np.where(length > 0, nrm / np.where(length > 0, length, 1.0), up)


def node_damping(scene: Scene) -> float:
    """beta1 of an interior node, N s/m (node (i, j)'s is this times its mass weight, as
    its mass is): the scene's, or from its material rate gamma (1/s) per unit mass: gamma
    times the interior node's mass (total mass / (n - 1)^2)."""
    cloth = scene["cloth"]
    if cloth["damping_rate"] is None:
        return float(cloth["damping"])
    return float(cloth["damping_rate"]) * float(cloth["mass"]) / float(scene.n - 1) ** 2


def node_contact_stiffness(scene: Scene) -> float:
    """k_b per node (per structural edge with edge contact), N/m: the scene's, or from its
    stiffness per contact area kappa (N/m^3): kappa times the area a node stands for,
    (size / (n - 1))^2, half of it for an edge (a node in the ball meets about one edge
    contact per grid direction)."""
    ball = scene["ball"]
    if ball["stiffness_per_area"] is None:
        return float(ball["stiffness"])
    spacing = float(scene["cloth"]["size"]) / (scene.n - 1)
    share = 0.5 if ball["contact"] == "edges" else 1.0
    return float(ball["stiffness_per_area"]) * spacing * spacing * share


def node_plate_stiffness(scene: Scene) -> float:
    """k = D / L^2 (N/m) of the plate bending term from the scene's bending stiffness D
    (N m): each of its stencils stands for L^2 of sheet and divides by L^2 twice."""
    if "bend" not in scene.effects:
        return 0.0
    spacing = float(scene["cloth"]["size"]) / (scene.n - 1)
    return float(scene["cloth"]["bending_stiffness"]) / (spacing * spacing)


def grip_points(scene: Scene, pos: np.ndarray, vel: np.ndarray | None = None) -> np.ndarray:
    """The point each hand holds (4, 3): its nodes' positions less their rest offsets,
    weighted by their shares (the corner nodes when a hand holds one node); with ``vel``
    the velocities alike instead."""
    out = np.zeros((4, 3))
    for g in grips(scene):
        x = pos[g.i, g.j] - g.offset if vel is None else vel[g.i, g.j]
        out[g.corner] += g.share * x
    return out


class ReferenceCloth:
    """The oracle: same scene, same equations, float64 NumPy, one step at a time."""

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self.fx = scene.effects
        self.pos = rest_positions(scene)
        self.vel = np.zeros_like(self.pos)
        self.hips = corners_of(self.pos)
        ball = scene["ball"]
        self.ball_pos = np.array(ball["position"], dtype=np.float64)
        self.ball_vel = np.array(ball["velocity"], dtype=np.float64)
        self.wind = np.array(scene["wind"]["velocity"], dtype=np.float64)
        # Per-node values derived here, in float64, from the scene's material values: not
        # the engine's derivation (native per_node), so the tests check that too.
        self.damping = node_damping(scene)
        self.ball_k = node_contact_stiffness(scene)
        self.plate_k = node_plate_stiffness(scene)
        self.grips = grips(scene)

    def forces(self, pos: np.ndarray, vel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Force on every node (eq. 1) and the summed contact force on the ball."""
        s, fx = self.scene, self.fx
        cloth, L = s["cloth"], s.rest_length
        f = np.zeros_like(pos)
        if "structural" in fx:
            compress = 1.0 if cloth["structural_two_sided"] else 0.0
            add_springs(f, pos, STRUCTURAL_DIRS, cloth["k_structural"], L, compress)
        if "shear" in fx:
            add_springs(f, pos, SHEAR_DIRS, cloth["k_shear"], L * np.sqrt(2.0), 1.0)
        if "bend" in fx:
            add_springs(f, pos, BEND_DIRS, cloth["k_bend"], 2.0 * L, 1.0)
            if self.plate_k:
                f += plate_force(pos, self.plate_k)
        if "gravity" in fx:
            f += s.node_masses * np.array(s["sim"]["gravity"])
        if "damping" in fx:  # per unit mass: the mass weights (1, 1/2, 1/4), as the masses
            f -= self.damping * mass_weights(s.n)[..., None] * vel
        contact_sum = np.zeros(3)
        if "ball" in fx:
            ball = s["ball"]
            if ball["contact"] == "edges":
                contact, contact_sum = edge_contact(pos, self.ball_pos, ball["radius"], self.ball_k)
            else:
                # Per area, as the mass: an inner node's k_b times each node's mass weight.
                kw = self.ball_k * mass_weights(s.n)[..., None]
                contact = ball_contact(pos, self.ball_pos, ball["radius"], kw)
                contact_sum = contact.sum(axis=(0, 1))
            f += contact
        if "coupling" in fx:
            K = s["coupling"]["stiffness"]
            for g in self.grips:
                f[g.i, g.j] += K * g.share * (self.hips[g.corner] + g.offset - pos[g.i, g.j])
        if "wind" in fx:
            w = s["wind"]
            f += wind_forces(pos, vel, self.wind, w["air_density"], w["drag"], w["lift"])
        return f, contact_sum

    def substep(self, dt: float) -> None:
        """Semi-implicit Euler (eq. 3) for nodes and ball (eqs. 5, 6)."""
        f, contact_sum = self.forces(self.pos, self.vel)
        if "ball" in self.fx:
            ball = self.scene["ball"]
            fb = -contact_sum - ball["damping"] * self.ball_vel
            if "gravity" in self.fx:
                fb = fb + ball["mass"] * np.array(self.scene["sim"]["gravity"])
            self.ball_vel = self.ball_vel + fb / ball["mass"] * dt
            self.ball_pos = self.ball_pos + self.ball_vel * dt
        self.vel = self.vel + f / self.scene.node_masses * dt
        self.pos = self.pos + self.vel * dt
        if "strain_limit" in self.fx:
            limit = self.scene["strain_limit"]
            max_len = (1.0 + limit["max_strain"]) * self.scene.rest_length
            passes = _native.strain_sweeps(limit["iterations"])  # the engine's count
            inv_dt = 1.0 / dt
            for _ in range(passes):  # rows (along j), then columns (along i)
                strain_limit_lines(self.pos, self.vel, max_len, inv_dt)
                cols_p, cols_v = self.pos.swapaxes(0, 1), self.vel.swapaxes(0, 1)
                strain_limit_lines(cols_p, cols_v, max_len, inv_dt)

    def step(self, frames: int, substeps: int) -> None:
        dt = self.scene["sim"]["frame_dt"] / substeps
        for _ in range(frames * substeps):
            self.substep(dt)

    def normals(self) -> np.ndarray:
        return grid_normals(self.pos)

    def corner_forces(self) -> np.ndarray:
        if "coupling" not in self.fx:
            return np.zeros((4, 3))
        held = grip_points(self.scene, self.pos)
        return -self.scene["coupling"]["stiffness"] * (self.hips - held)
