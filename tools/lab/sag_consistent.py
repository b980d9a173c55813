"""Lab (issue 42): the static sag (no ball) of a scene with each boundary term of a
cell-assembled discretisation switched on alone or together, by Newton's method on an
energy of its own (sparse Jacobian; needs SciPy). Flags, one letter each:

    M  masses by area (interior L^2, edges half, corners a quarter of the sheet's density)
    E  springs along a free edge (structural, bending) at half k: each stands for half a strip
    P  the plate's row and column stencils along a free edge at half weight
    B  each line's end segments given the stretch of the bend spring they lack (+2 k_bend)
    G  the grip's shares its density integrated against each node's hat function
    x  none: uniform masses and springs (the engine before issue 42's border: ME ships now)

    python tools/lab/sag_consistent.py default 13,25,49 x,M,E,ME     # seconds each
    python tools/lab/sag_consistent.py default 97 ME                 # n = 97: minutes
"""

from __future__ import annotations

import sys
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from clothball.game import Scene
from clothball.game.sim.cloth import corners_of, rest_positions
from clothball.game.sim.oracle import grips
from clothball.game.study.grid import sized


def springs(scene: Scene, flags: str) -> np.ndarray:
    """Rows (i, j, k, rest, compress), each spring once."""
    n, L, c, fx = scene.n, scene.rest_length, scene["cloth"], scene.effects
    idx = np.arange(n * n).reshape(n, n)
    out = []

    def family(di: int, dj: int, k: float, rest: float, compress: float) -> None:
        for a in range(n - di):
            for b in range(max(0, -dj), n - max(0, dj)):
                along_edge = (di == 0 and a in (0, n - 1)) or (dj == 0 and b in (0, n - 1))
                w = 0.5 if "E" in flags and along_edge else 1.0
                out.append((idx[a, b], idx[a + di, b + dj], k * w, rest, compress))

    two_sided = 1.0 if c["structural_two_sided"] else 0.0
    if "structural" in fx:
        family(0, 1, c["k_structural"], L, two_sided)
        family(1, 0, c["k_structural"], L, two_sided)
    if "shear" in fx:
        family(1, 1, c["k_shear"], L * 2**0.5, 1.0)
        family(1, -1, c["k_shear"], L * 2**0.5, 1.0)
    if "bend" in fx:
        family(0, 2, c["k_bend"], 2 * L, 1.0)
        family(2, 0, c["k_bend"], 2 * L, 1.0)
        if "B" in flags:
            for a in range(n):
                w = 0.5 if "E" in flags and a in (0, n - 1) else 1.0
                for b1, b2 in ((0, 1), (n - 2, n - 1)):
                    kb = 2 * c["k_bend"] * w
                    out.append((idx[a, b1], idx[a, b2], kb, L, two_sided))
                    out.append((idx[b1, a], idx[b2, a], kb, L, two_sided))
    return np.array(out, dtype=np.float64)


def plate(scene: Scene, flags: str) -> sp.csr_matrix:
    """k B^T B of the plate term (k = D / L^2), its edge stencils halved with P."""
    n, L = scene.n, scene.rest_length
    N = n * n
    if "bend" not in scene.effects:
        return sp.csr_matrix((N, N))
    idx = np.arange(N).reshape(n, n)
    rows, cols, vals = [], [], []

    def stencil(nodes: list[int], coefs: list[float], w: float) -> None:
        r = len(rows) and rows[-1] + 1
        for q, cf in zip(nodes, coefs, strict=True):
            rows.append(r)
            cols.append(q)
            vals.append(cf * w**0.5)

    half = 0.5 if "P" in flags else 1.0
    for a in range(n):
        for b in range(n - 2):
            w = half if a in (0, n - 1) else 1.0
            stencil([idx[a, b], idx[a, b + 1], idx[a, b + 2]], [1, -2, 1], w)
            w = half if a in (0, n - 1) else 1.0  # the column triple along column a
            stencil([idx[b, a], idx[b + 1, a], idx[b + 2, a]], [1, -2, 1], w)
    for a in range(n - 1):
        for b in range(n - 1):
            stencil([idx[a, b], idx[a, b + 1], idx[a + 1, b], idx[a + 1, b + 1]],
                    [1, -1, -1, 1], 2.0)
    B = sp.csr_matrix((vals, (rows, cols)), shape=(rows[-1] + 1, N))
    return (scene["cloth"]["bending_stiffness"] / L**2 * (B.T @ B)).tocsr()


def energy(x, S, P, load, hips, held, hessian):
    """Energy, gradient and (with hessian) the projected Hessian at positions x (N, 3)."""
    i, j = S[:, 0].astype(int), S[:, 1].astype(int)
    k, rest, comp = S[:, 2], S[:, 3], S[:, 4]
    d = x[j] - x[i]
    length = np.linalg.norm(d, axis=1)
    ext = length - rest
    kk = np.where(ext > 0, k, k * comp)
    px = P @ x
    e = 0.5 * np.sum(kk * ext * ext) + 0.5 * float(np.sum(x * px)) - float(np.sum(load * x))
    g = px - load
    f = (kk * ext / length)[:, None] * d
    np.add.at(g, i, -f)
    np.add.at(g, j, f)
    for corner, node, kg, off in held:
        dh = x[node] - hips[corner] - off  # the grip's spring to its hand
        e += 0.5 * kg * dh @ dh
        g[node] += kg * dh
    if not hessian:
        return e, g, None
    u = d / length[:, None]
    s = np.maximum(0.0, 1.0 - rest / length) * kk
    blocks = s[:, None, None] * np.eye(3) + (kk - s)[:, None, None] * u[:, :, None] * u[:, None, :]
    r, c, v = [], [], []
    for p, q, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
        for a in range(3):
            for b in range(3):
                r.append(3 * p + a)
                c.append(3 * q + b)
                v.append(sign * blocks[:, a, b])
    N = x.shape[0]
    H = sp.csr_matrix((np.concatenate(v), (np.concatenate(r), np.concatenate(c))),
                      shape=(3 * N, 3 * N)) + sp.kron(P, sp.identity(3))
    diag = np.zeros(3 * N)
    for _, node, kg, _ in held:
        diag[3 * node:3 * node + 3] += kg
    return e, g, (H + sp.diags(diag)).tocsc()


def hat_grips(scene: Scene) -> list:
    """G: each held node's share the grip's density integrated against the node's hat
    function along each edge (the trapezoid rule on a fine grid), not sampled at the node:
    the node past the grip's end takes a share too. What the engine does since 2026-11-29
    (game/sim/grip.py hat_share, exactly), so G now repeats the shipped grip."""
    from clothball.game.sim.grip import Grip, grip_density
    n, L, a = scene.n, scene.rest_length, scene["coupling"]["grip_radius"]
    s = np.linspace(0.0, a, 4001)
    rho = np.array([grip_density(v, a) for v in s])

    def w(m: int) -> float:  # one edge's integral of rho times node m's hat
        hat = np.clip(1.0 - np.abs(s - m * L) / L, 0.0, None)
        return float(np.trapezoid(rho * hat, s))

    held = []
    for c, (ci, cj) in enumerate(((0, 0), (0, n - 1), (n - 1, n - 1), (n - 1, 0))):
        di, dj = (1 if ci == 0 else -1), (1 if cj == 0 else -1)
        held.append((c, ci, cj, 2.0 * w(0), np.zeros(3)))
        m = 1
        while m * L < a + L and 2 * m <= n - 2:
            wm = w(m)
            if wm > 0.0:
                held.append((c, ci, cj + dj * m, wm, np.array([dj * m * L, 0.0, 0.0])))
                held.append((c, ci + di * m, cj, wm, np.array([0.0, 0.0, di * m * L])))
            m += 1
    total = [sum(h[3] for h in held if h[0] == c) for c in range(4)]
    return [Grip(c, i, j, wt / total[c], off) for c, i, j, wt, off in held]


def sag(scene: Scene, flags: str) -> tuple[float, int]:
    """The centre's sag at rest (m) and the Newton iterations it took."""
    n = scene.n
    S, P = springs(scene, flags), plate(scene, flags)
    w = np.ones((n, n))
    if "M" in flags:
        for edge in (np.s_[0, :], np.s_[-1, :], np.s_[:, 0], np.s_[:, -1]):
            w[edge] *= 0.5
    load = (scene["cloth"]["mass"] * w / w.sum()).reshape(-1, 1) * np.array(
        scene["sim"]["gravity"])
    x = rest_positions(scene).reshape(-1, 3).copy()
    hips = corners_of(rest_positions(scene))
    K = scene["coupling"]["stiffness"]
    held = [(g.corner, g.i * n + g.j, K * g.share, g.offset) for g in
            (hat_grips(scene) if "G" in flags else grips(scene))]
    tol = 1e-7 * float(np.abs(load).max())
    mu = 1e-2 * scene["cloth"]["k_structural"]
    e, g, H = energy(x, S, P, load, hips, held, True)
    it = 0
    for it in range(1, 401):  # noqa: B007 - reported
        if np.abs(g).max() < tol:
            break
        step = spla.spsolve(H + mu * sp.identity(H.shape[0], format="csc"), -g.ravel())
        for alpha in (1.0, 0.5, 0.25, 0.125):
            xt = x + alpha * step.reshape(x.shape)
            et, gt, _ = energy(xt, S, P, load, hips, held, False)
            if et < e or (et <= e + 1e-13 * abs(e) and np.abs(gt).max() < np.abs(g).max()):
                x, mu = xt, max(mu / 10, 1e-12)
                e, g, H = energy(x, S, P, load, hips, held, True)
                break
        else:
            mu *= 10
    centre = x.reshape(n, n, 3)[(n - 1) // 2:n // 2 + 1, (n - 1) // 2:n // 2 + 1, 1]
    return float(scene["cloth"]["height"] - centre.mean()), it


if __name__ == "__main__":
    name, sizes, flag_sets = sys.argv[1], sys.argv[2], sys.argv[3]
    for flags in flag_sets.split(","):
        out = []
        for n in (int(v) for v in sizes.split(",")):
            t = time.time()
            value, it = sag(sized(Scene.load(name), n), flags)
            out.append(value * 1e3)
            print(f"{name} {flags} n={n}: sag {value * 1e3:.4f} mm ({it} iterations, "
                  f"{time.time() - t:.0f} s)", flush=True)
        d = np.diff(out)
        orders = [float(np.log2(abs(d[q] / d[q + 1]))) for q in range(len(d) - 1)]
        print(f"{name} {flags}: differences {np.round(d, 3)}, orders {np.round(orders, 2)}")
