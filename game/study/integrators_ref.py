"""Float64 NumPy reference integrators built on the oracle's forces (``ReferenceCloth``).

Three time integrators for the same equations (paper eqs. 1-7), each a subclass of
``ReferenceCloth`` so that it is driven the same way (``step(frames, substeps)``, ``pos``,
``vel``, ``ball_pos``, ``ball_vel``, ``hips``):

* ``semi_implicit_euler``: the paper's eq. (3), first order (the oracle's own ``substep``).
* ``velocity_verlet``: second order, explicit. The force splits into a position part
  ``F(x)`` (springs, gravity, ball contact, coupling) and linear damping ``-c v``:

      v½ = v + dt/2 (F(x)/m - γ v)            γ = c / m (nodes), β2 / M (ball)
      x' = x + dt v½
      v' = (v½ + dt/2 F(x')/m) / (1 + γ dt/2)

  i.e. an explicit half kick, a drift, and a half kick implicit in the (linear, diagonal)
  damping only. The two half steps are adjoint to each other (symplectic Euler and its
  adjoint), so the composition is symmetric and second order; undamped it is exactly the
  textbook velocity Verlet. One new force evaluation per substep: ``F(x')`` is kept and is
  the next substep's ``F(x)``; it is recomputed at ``(x, v)`` only when the state, the ball,
  the hands or the wind changed since (as the native engine does). The wind, the one other
  velocity-dependent force, is evaluated with the half-step velocity ``v½`` (explicit, so
  with wind on the drag is first order in dt); the engine does exactly the same.

* ``implicit_euler``: backward Euler linearised once per substep (one Newton step, as in
  Baraff & Witkin 1998):

      (M + dt C - dt² K) Δv = dt (F(x, v) + dt K v),   v' = v + Δv,   x' = x + dt v'

  with K = ∂F/∂x applied matrix-free (``force_jvp``) and the system solved by Jacobi-
  preconditioned conjugate gradients. The ball is one more unknown (3 rows) coupled to the
  nodes by the contact Jacobian. First order; unconditionally stable for the linear part.

The force Jacobian. Every interaction is a pair force: node i feels φ(d) with d = x_j - x_i
(its partner feels -φ). For a spring of stiffness k and rest length L, with l = |d|,
u = d / l, e = l - L and g(e) = e (stretched) or c·e (compressed; c = 0 is the paper's
tension-only spring, eq. 2), φ(d) = k g(e) u = s d with s = k g(e) / l, and

      Dφ · w = s (w - (u·w) u) + k g'(e) (u·w) u

a transverse stiffness s and an axial stiffness k g'(e). The ball contact of eq. (4) is the
same with partner b, d = b - x_i, rest length R and c = 1 (always compressed while the node
is inside the ball); the coupling of eq. (7) is a zero-length spring K to a fixed hand.
A compressed pair (a compressed two-sided spring, every contact) has s < 0: its Jacobian is
indefinite. CG needs a positive definite matrix, so the integrator (and the static Newton
solver) use the standard projection s -> max(s, 0) (Choi & Ko 2002); ``definite=False``
gives the exact Jacobian, which the tests check against finite differences. A linearly
implicit method stays first-order consistent with any Jacobian approximation; the
projection only costs some of the Newton step's accuracy in compressed contacts.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from ..sim.oracle import (
    BEND_DIRS,
    SHEAR_DIRS,
    STRUCTURAL_DIRS,
    ReferenceCloth,
    edge_weights,
    grips,
    node_contact_stiffness,
    node_plate_stiffness,
    plate_diagonal,
    plate_energy,
    plate_force,
)
from ..sim.scene import SCHEMA, Scene, mass_weights

INTEGRATORS = ("semi_implicit_euler", "velocity_verlet", "implicit_euler")
ORDERS = {"semi_implicit_euler": 1, "velocity_verlet": 2, "implicit_euler": 1}

Pair = tuple[np.ndarray, np.ndarray, np.ndarray]  # (s, axial, u), each (..., 1) or (..., 3)


def _slices(n: int, di: int, dj: int) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """Index of every node that has a neighbour at (di, dj), and of that neighbour."""
    rows = slice(max(0, -di), n - max(0, di))
    cols = slice(max(0, -dj), n - max(0, dj))
    nrows = slice(max(0, -di) + di, n - max(0, di) + di)
    ncols = slice(max(0, -dj) + dj, n - max(0, dj) + dj)
    return (rows, cols), (nrows, ncols)


def pair_terms(d: np.ndarray, k: float, rest: float, compress: float, definite: bool) -> Pair:
    """Transverse stiffness s, axial stiffness k g'(e) and direction u of φ(d) = s d."""
    length = np.linalg.norm(d, axis=-1, keepdims=True)
    ok = length > 1e-12
    safe = np.where(ok, length, 1.0)
    e = length - rest
    stretched = e > 0
    g = np.where(stretched, e, compress * e)
    gp = np.where(stretched, 1.0, compress)
    s = np.where(ok, k * g / safe, 0.0)
    if definite:
        s = np.maximum(s, 0.0)
    axial = np.where(ok, k * gp, 0.0)
    return s, axial, d / safe


def pair_jvp(terms: Pair, w: np.ndarray) -> np.ndarray:
    """Dφ · w for the pairs described by ``terms``."""
    s, axial, u = terms
    uw = np.sum(u * w, axis=-1, keepdims=True)
    return s * w + (axial - s) * uw * u


def pair_diag(terms: Pair) -> np.ndarray:
    """The diagonal of Dφ (3 values per pair)."""
    s, axial, u = terms
    return s + (axial - s) * u * u


def spring_sets(scene: Scene) -> list[tuple[tuple[tuple[int, int], ...], float, float, float]]:
    """(directions, k, rest length, compress) of each spring family the scene simulates."""
    cloth, fx, L = scene["cloth"], scene.effects, scene.rest_length
    sets = []
    if "structural" in fx:
        c = 1.0 if cloth["structural_two_sided"] else 0.0
        sets.append((STRUCTURAL_DIRS, cloth["k_structural"], L, c))
    if "shear" in fx:
        sets.append((SHEAR_DIRS, cloth["k_shear"], L * np.sqrt(2.0), 1.0))
    if "bend" in fx:
        sets.append((BEND_DIRS, cloth["k_bend"], 2.0 * L, 1.0))
    return sets


def contact_mask(pos: np.ndarray, ball_pos: np.ndarray, radius: float) -> np.ndarray:
    """Nodes inside the ball whose contact force has a direction (not at the very centre)."""
    r = np.linalg.norm(pos - ball_pos, axis=-1)
    return (r < radius) & (r > 1e-12)


class Linearization:
    """K = ∂F/∂x at one state, ready to apply many times (the pair terms are computed once).

    Applies to the node forces (eqs. 1, 2, 4, 7) and the ball force (eq. 5) as functions of
    the node positions and the ball position.
    """

    def __init__(self, scene: Scene, pos: np.ndarray, ball_pos: np.ndarray,
                 definite: bool = False) -> None:
        n = pos.shape[0]
        self.shape = pos.shape
        self.springs: list[tuple[tuple, tuple, Pair]] = []
        for dirs, k, rest, compress in spring_sets(scene):
            for di, dj in dirs:
                here, there = _slices(n, di, dj)
                kw = k * edge_weights(n, di, dj)
                terms = pair_terms(pos[there] - pos[here], kw, rest, compress, definite)
                self.springs.append((here, there, terms))
        self.inside: np.ndarray | None = None
        if "ball" in scene.effects:
            ball = scene["ball"]
            inside = contact_mask(pos, ball_pos, ball["radius"])
            if inside.any():
                self.inside = inside
                kw = node_contact_stiffness(scene) * mass_weights(n)[inside][:, None]
                self.contact = pair_terms(ball_pos - pos[inside], kw,
                                          ball["radius"], 1.0, definite)
        K = scene["coupling"]["stiffness"] if "coupling" in scene.effects else 0.0
        self.coupling = [(g.i, g.j, K * g.share) for g in grips(scene)] if K else []
        # The plate bending force is linear in the positions: its Jacobian is itself,
        # constant and negative semidefinite (-k B^T B).
        self.plate_k = node_plate_stiffness(scene)

    def jvp(self, w: np.ndarray, wb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """K·(w, wb): the change of every node force and of the ball force for a change w
        of the node positions and wb of the ball position."""
        out = np.zeros(self.shape)
        for here, there, terms in self.springs:
            out[here] += pair_jvp(terms, w[there] - w[here])
        out_b = np.zeros(3)
        if self.inside is not None:
            df = pair_jvp(self.contact, wb - w[self.inside])
            out[self.inside] += df
            out_b -= df.sum(axis=0)
        for i, j, k in self.coupling:
            out[i, j] -= k * w[i, j]
        if self.plate_k:
            out += plate_force(w, self.plate_k)
        return out, out_b

    def neg_diag(self) -> tuple[np.ndarray, np.ndarray]:
        """The diagonal of -K (nodes, ball): the Jacobi preconditioner's stiffness part."""
        out = np.zeros(self.shape)
        for here, _, terms in self.springs:
            out[here] += pair_diag(terms)
        out_b = np.zeros(3)
        if self.inside is not None:
            dg = pair_diag(self.contact)
            out[self.inside] += dg
            out_b += dg.sum(axis=0)
        for i, j, k in self.coupling:
            out[i, j] += k
        if self.plate_k:
            out += plate_diagonal(self.shape[0], self.plate_k)[..., None]
        return out, out_b


def force_jvp(
    scene: Scene,
    pos: np.ndarray,
    ball_pos: np.ndarray,
    w: np.ndarray,
    wb: np.ndarray,
    definite: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """K·(w, wb) at the state (pos, ball_pos); see ``Linearization``."""
    return Linearization(scene, pos, ball_pos, definite).jvp(w, wb)


def stiffness_diag(
    scene: Scene, pos: np.ndarray, ball_pos: np.ndarray, definite: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """The diagonal of -K (nodes, ball)."""
    return Linearization(scene, pos, ball_pos, definite).neg_diag()


def potential_energy(scene: Scene, pos: np.ndarray, ball_pos: np.ndarray,
                     hips: np.ndarray) -> float:
    """Potential energy whose negative gradient is the position part of the forces."""
    n, fx = pos.shape[0], scene.effects
    energy = 0.0
    for dirs, k, rest, compress in spring_sets(scene):
        for di, dj in dirs:
            here, there = _slices(n, di, dj)
            e = np.linalg.norm(pos[there] - pos[here], axis=-1) - rest
            kw = k * edge_weights(n, di, dj)[..., 0]
            # Each spring is seen from both ends: half its energy each time.
            energy += 0.5 * 0.5 * float(np.sum(kw * np.where(e > 0, e * e, compress * e * e)))
    energy += plate_energy(pos, node_plate_stiffness(scene))
    g = np.array(scene["sim"]["gravity"]) if "gravity" in fx else np.zeros(3)
    energy -= float(np.sum(scene.node_masses[..., 0] * (pos @ g)))
    if "ball" in fx:
        ball = scene["ball"]
        r = np.linalg.norm(pos - ball_pos, axis=-1)
        pen = np.maximum(ball["radius"] - r, 0.0)
        kw = node_contact_stiffness(scene) * mass_weights(n)
        energy += 0.5 * float(np.sum(kw * pen * pen))
        energy -= ball["mass"] * float(ball_pos @ g)
    if "coupling" in fx:
        K = scene["coupling"]["stiffness"]
        for grip in grips(scene):
            dh = hips[grip.corner] + grip.offset - pos[grip.i, grip.j]
            energy += 0.5 * K * grip.share * float(dh @ dh)
    return energy


def kinetic_energy(scene: Scene, vel: np.ndarray, ball_vel: np.ndarray) -> float:
    energy = 0.5 * float(np.sum(scene.node_masses * vel * vel))
    if "ball" in scene.effects:
        energy += 0.5 * scene["ball"]["mass"] * float(ball_vel @ ball_vel)
    return energy


def pcg(
    apply: Callable[[np.ndarray], np.ndarray],
    rhs: np.ndarray,
    diag: np.ndarray,
    tol: float,
    max_iter: int,
) -> tuple[np.ndarray, int, float]:
    """Jacobi-preconditioned conjugate gradients from x = 0 on a flat vector.

    Stops when |r| <= tol |rhs|. Returns the solution, the iterations and |r| / |rhs|.
    """
    x = np.zeros_like(rhs)
    r = rhs.copy()
    bnorm = float(np.linalg.norm(rhs))
    if bnorm == 0.0:
        return x, 0, 0.0
    z = r / diag
    p = z.copy()
    rz = float(r @ z)
    it = 0
    rel = 1.0
    while it < max_iter:
        ap = apply(p)
        pap = float(p @ ap)
        if pap <= 0.0:  # not positive definite along p: stop with what we have
            break
        alpha = rz / pap
        x += alpha * p
        r -= alpha * ap
        it += 1
        rel = float(np.linalg.norm(r)) / bnorm
        if rel <= tol:
            break
        z = r / diag
        rz_new = float(r @ z)
        p = z + (rz_new / rz) * p
        rz = rz_new
    return x, it, rel


class IntegratingCloth(ReferenceCloth):
    """The oracle stepped by one of ``INTEGRATORS`` (float64 NumPy)."""

    def __init__(self, scene: Scene, integrator: str = "semi_implicit_euler",
                 cg_tol: float = 1e-10, cg_max_iter: int = 2000) -> None:
        if integrator not in INTEGRATORS:
            raise ValueError(f"integrator: must be one of {', '.join(INTEGRATORS)}, "
                             f"got {integrator!r}")
        if "strain_limit" in scene.effects and integrator != "semi_implicit_euler":
            raise ValueError(f"integrator: {integrator} does not support the 'strain_limit' "
                             f"effect (semi_implicit_euler does)")
        super().__init__(scene)
        self.integrator = integrator
        self._kept: tuple[tuple[np.ndarray, ...], np.ndarray, np.ndarray] | None = None
        self.cg_tol = cg_tol
        self.cg_max_iter = cg_max_iter
        self.cg_iterations = 0  # summed over all implicit substeps
        self.cg_worst_residual = 0.0

    # --- forces -----------------------------------------------------------------------
    def _gamma(self) -> tuple[float, float]:
        """Damping rates c / m of the nodes and of the ball."""
        s = self.scene
        g = self.damping / s.node_mass if "damping" in self.fx else 0.0
        gb = s["ball"]["damping"] / s["ball"]["mass"] if "ball" in self.fx else 0.0
        return g, gb

    def all_forces(self, pos: np.ndarray, vel: np.ndarray, ball_pos: np.ndarray,
                   ball_vel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Force on every node and on the ball at the given state."""
        saved = self.ball_pos
        self.ball_pos = ball_pos
        try:
            f, contact_sum = self.forces(pos, vel)
        finally:
            self.ball_pos = saved
        fb = np.zeros(3)
        if "ball" in self.fx:
            ball = self.scene["ball"]
            fb = -contact_sum - ball["damping"] * ball_vel
            if "gravity" in self.fx:
                fb = fb + ball["mass"] * np.array(self.scene["sim"]["gravity"])
        return f, fb

    def energy(self) -> float:
        """Total mechanical energy of the current state (kinetic + potential)."""
        return kinetic_energy(self.scene, self.vel, self.ball_vel) + potential_energy(
            self.scene, self.pos, self.ball_pos, self.hips)

    # --- integrators ------------------------------------------------------------------
    def substep(self, dt: float) -> None:
        if self.integrator == "semi_implicit_euler":
            super().substep(dt)
        elif self.integrator == "velocity_verlet":
            self._verlet(dt)
        else:
            self._implicit(dt)

    def verlet_forces(self, pos: np.ndarray, vel: np.ndarray,
                      ball_pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Velocity Verlet's F: every force but the damping (nodes and ball); ``vel`` is
        what the wind sees."""
        fx = self.fx
        self.fx = fx - {"damping"}
        try:
            return self.all_forces(pos, vel, ball_pos, np.zeros(3))
        finally:
            self.fx = fx

    def _inputs(self) -> tuple[np.ndarray, ...]:
        return tuple(np.array(a, dtype=np.float64) for a in (
            self.pos, self.vel, self.ball_pos, self.ball_vel, self.hips, self.wind))

    def _verlet(self, dt: float) -> None:
        m = self.scene.node_masses
        mb = self.scene["ball"]["mass"]
        gamma, gamma_b = self._gamma()
        has_ball = "ball" in self.fx
        kept = self._kept
        if kept is not None and all(np.array_equal(a, b) for a, b in zip(
                kept[0], self._inputs(), strict=True)):
            f, fb = kept[1], kept[2]
        else:
            f, fb = self.verlet_forces(self.pos, self.vel, self.ball_pos)
        v_half = self.vel + 0.5 * dt * (f / m - gamma * self.vel)
        self.pos = self.pos + dt * v_half
        if has_ball:
            u_half = self.ball_vel + 0.5 * dt * (fb / mb - gamma_b * self.ball_vel)
            self.ball_pos = self.ball_pos + dt * u_half
        f, fb = self.verlet_forces(self.pos, v_half, self.ball_pos)
        self.vel = (v_half + 0.5 * dt * f / m) / (1.0 + 0.5 * dt * gamma)
        if has_ball:
            self.ball_vel = (u_half + 0.5 * dt * fb / mb) / (1.0 + 0.5 * dt * gamma_b)
        self._kept = (self._inputs(), f, fb)

    def _implicit(self, dt: float) -> None:
        s = self.scene
        m = s.node_masses  # (n, n, 1): M and C are diagonal, by area (c per unit mass)
        has_ball = "ball" in self.fx
        mb = s["ball"]["mass"] if has_ball else 1.0
        c = self.damping / s.node_mass if "damping" in self.fx else 0.0
        c = c * m
        cb = s["ball"]["damping"] if has_ball else 0.0
        pos, bpos = self.pos, self.ball_pos
        f, fb = self.all_forces(pos, self.vel, bpos, self.ball_vel)
        lin = Linearization(s, pos, bpos, definite=True)
        kv, kvb = lin.jvp(self.vel, self.ball_vel if has_ball else np.zeros(3))
        N = pos.size
        rhs = np.concatenate([(dt * (f + dt * kv)).ravel(), dt * (fb + dt * kvb)])
        a_node, a_ball = m + dt * c, mb + dt * cb

        def apply(w: np.ndarray) -> np.ndarray:
            wn = w[:N].reshape(pos.shape)
            wb = w[N:] if has_ball else np.zeros(3)
            jn, jb = lin.jvp(wn, wb)
            nodes = (a_node * wn - dt * dt * jn).ravel()  # a_node (n, n, 1)
            return np.concatenate([nodes, a_ball * wb - dt * dt * jb])

        dn, db = lin.neg_diag()
        diag = np.concatenate([(a_node + dt * dt * dn).ravel(), a_ball + dt * dt * db])
        dv, iters, rel = pcg(apply, rhs, diag, self.cg_tol, self.cg_max_iter)
        self.cg_iterations += iters
        self.cg_worst_residual = max(self.cg_worst_residual, rel)
        self.vel = self.vel + dv[:N].reshape(pos.shape)
        self.pos = self.pos + dt * self.vel
        if has_ball:
            self.ball_vel = self.ball_vel + dv[N:]
            self.ball_pos = self.ball_pos + dt * self.ball_vel


def with_effects(scene: Scene, drop: Iterable[str]) -> Scene:
    """The scene without the effects in ``drop`` (and without the keys that belong to them)."""
    gone = set(drop)
    data = scene.to_dict()
    for section, table in data.items():
        for key in list(table):
            if SCHEMA[section][key].effect in gone:
                del table[key]
    data.setdefault("sim", {})["effects"] = sorted(scene.effects - gone)
    return Scene(data, name=scene.name)


def static_equilibrium(
    scene: Scene,
    hips: np.ndarray | None = None,
    x0: np.ndarray | None = None,
    tol: float = 1e-7,
    max_iter: int = 400,
) -> tuple[np.ndarray, dict[str, float]]:
    """Newton's method for F(x) = 0: the hanging cloth at rest, hands fixed at ``hips``
    (default: the rest corners), no ball.

    The energy's Hessian is -K (projected definite, see the module doc), damped by a
    Levenberg-Marquardt term μ k I that vanishes as it converges (the flat start has slack
    springs, so the plain Hessian is singular there), with a backtracking line search on
    the potential energy. Converged when every node's residual force is below ``tol``
    times its weight. Returns the positions and a summary (iterations, residual).
    """
    s = with_effects(scene, ["ball", "damping"])
    fx = s.effects
    ref = ReferenceCloth(s)
    if hips is not None:
        ref.hips = np.array(hips, dtype=np.float64)
    x = ref.pos.copy() if x0 is None else np.array(x0, dtype=np.float64)
    g = np.linalg.norm(s["sim"]["gravity"]) if "gravity" in fx else 1.0
    weight = s.node_mass * g / 4.0  # the lightest node's (a corner's)
    kscale = max(s["cloth"]["k_structural"], 1e-9)
    zero_b = np.zeros(3)

    def residual(p: np.ndarray) -> np.ndarray:
        return ref.forces(p, np.zeros_like(p))[0]

    def energy(p: np.ndarray) -> float:
        return potential_energy(s, p, zero_b, ref.hips)

    x, f, it = damped_newton(s, x, residual, energy, weight * tol, kscale, max_iter)
    info = {"iterations": float(it), "max_residual_over_weight": float(np.abs(f).max() / weight)}
    return x, info


def neg_jacobian_sparse(lin: Linearization):  # noqa: ANN201 - scipy is optional
    """-K of the nodes (no ball) as a scipy sparse matrix, assembled from 75 matrix-free
    products: nodes coloured (i mod 5, j mod 5) never share a 5 x 5 stencil window, so one
    product per colour and component recovers every column of that colour."""
    import scipy.sparse as sp  # noqa: PLC0415

    n = lin.shape[0]
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    rows, cols, vals = [], [], []
    zero_b = np.zeros(3)
    for a in range(5):
        for b in range(5):
            qi = i + (a - i + 2) % 5 - 2  # the node of colour (a, b) in (i, j)'s window
            qj = j + (b - j + 2) % 5 - 2
            ok = (qi >= 0) & (qi < n) & (qj >= 0) & (qj < n)
            sel = (i % 5 == a) & (j % 5 == b)
            for c in range(3):
                w = np.zeros(lin.shape)
                w[sel, c] = 1.0
                out = -lin.jvp(w, zero_b)[0]
                p = (i * n + j)[ok]
                q = (qi * n + qj)[ok]
                for comp in range(3):
                    rows.append(3 * p + comp)
                    cols.append(3 * q + c)
                    vals.append(out[ok][:, comp])
    r, cidx, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    keep = v != 0.0
    size = 3 * n * n
    return sp.csc_matrix((v[keep], (r[keep], cidx[keep])), shape=(size, size))


def damped_newton(s: Scene, x: np.ndarray, residual: Callable[[np.ndarray], np.ndarray],
                  energy: Callable[[np.ndarray], float], f_tol: float, kscale: float,
                  max_iter: int) -> tuple[np.ndarray, np.ndarray, int]:
    """``static_equilibrium``'s iteration, for any residual force and energy on scene
    ``s``'s springs: damped Newton steps on the projected Hessian with a backtracking line
    search, until every residual is within ``f_tol``. Returns the positions, their residual
    and the iterations taken."""
    zero_b = np.zeros(3)
    mu = 1e-2
    f = residual(x)
    e = energy(x)
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - reported below
        if np.abs(f).max() <= f_tol:
            break
        lin = Linearization(s, x, zero_b, definite=True)
        step = _newton_step(lin, f, mu * kscale, mu).reshape(x.shape)
        accepted = False
        fmax = np.abs(f).max()
        for alpha in (1.0, 0.5, 0.25):
            xt = x + alpha * step
            et, ft = energy(xt), residual(xt)
            # Near the solution the energy changes below its rounding: then the residual
            # decides.
            if et < e or (et <= e + 1e-13 * abs(e) and np.abs(ft).max() < fmax):
                x, e, f, accepted = xt, et, ft, True
                break
        mu = max(mu / 10.0, 1e-14) if accepted else mu * 10.0
    return x, f, it


def _newton_step(lin: Linearization, f: np.ndarray, reg: float, mu: float) -> np.ndarray:
    """Solve (-K + reg I) d = f: sparse direct where SciPy is present, else CG."""
    try:
        import scipy.sparse as sp  # noqa: PLC0415
        import scipy.sparse.linalg as spla  # noqa: PLC0415
    except ImportError:
        sp = None
    if sp is not None:
        h = neg_jacobian_sparse(lin) + reg * sp.identity(f.size, format="csc")
        return spla.spsolve(h, f.ravel())
    dn, _ = lin.neg_diag()
    zero_b = np.zeros(3)

    def apply(w: np.ndarray) -> np.ndarray:
        wn = w.reshape(lin.shape)
        return (reg * wn - lin.jvp(wn, zero_b)[0]).ravel()

    return pcg(apply, f.ravel(), (dn + reg).ravel(), 1e-3 * min(1.0, mu) + 1e-10,
               4 * f.size)[0]


def centre_sag(scene: Scene, pos: np.ndarray) -> float:
    """How far the cloth's centre hangs below its rest height, m (mean of the central
    node or the four central nodes)."""
    n = pos.shape[0]
    lo, hi = (n - 1) // 2, n // 2
    return float(scene["cloth"]["height"] - pos[lo:hi + 1, lo:hi + 1, 1].mean())
