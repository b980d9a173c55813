// The paper's physics, written once for both backends: per-node forces (eqs. 1, 2, 4, 7),
// the ball's motion (eqs. 5, 6) and semi-implicit Euler (eq. 3). Every force of a substep
// is computed from the state at the substep's start (the paper's double buffering).
#pragma once
#include "params.hpp"

namespace cb {

// Force on node i from a spring to node j. `compress` scales the force when the spring is
// shorter than its rest length: 0 gives the paper's tension-only spring (eq. 2), 1 a
// two-sided linear spring. Coincident nodes have no direction, so they exert no force
// instead of dividing by zero.
//
// On the GPU (CB_SPRING_RSQRT, on unless a lab build sets it 0) one reciprocal square root
// gives both the length (d2 r) and the division (k ext r): in float32 one special-function
// op where the square root and the division were two, in float64 one Newton sequence where
// there were two (issue 41). The CPU keeps the IEEE square root and division: its loops
// vectorise them at the same cost, and its results stay what they were.
#ifndef CB_SPRING_RSQRT
#define CB_SPRING_RSQRT 1
#endif
#if defined(__CUDA_ARCH__)
__device__ __forceinline__ float spring_rsqrt(float x) { return rsqrtf(x); }
__device__ __forceinline__ double spring_rsqrt(double x) { return ::rsqrt(x); }
#endif
template <class R>
CB_HD V3<R> spring_force(V3<R> pi, V3<R> pj, R k, R rest, R compress) {
  V3<R> d = pj - pi;
#if defined(__CUDA_ARCH__) && CB_SPRING_RSQRT
  const R d2 = dot(d, d);
  const bool has_dir = d2 > R(1e-24);  // |d| > 1e-12, as below
  const R r = spring_rsqrt(has_dir ? d2 : R(1));
  R ext = d2 * r - rest;
  ext *= ext > R(0) ? R(1) : compress;
  const R s = has_dir ? k * ext * r : R(0);
#else
  R len = length(d);
  R ext = len - rest;
  ext *= ext > R(0) ? R(1) : compress;
  // Selects, not branches, and a division that is always safe: the CPU loops vectorise.
  const bool has_dir = len > R(1e-12);
  R s = (has_dir ? k * ext : R(0)) / (has_dir ? len : R(1));
#endif
  return d * s;
}

// Contact force of eq. (4) on a node at distance vector d = p_i - p_b from the ball centre.
// A node exactly at the centre is pushed straight down (the ball then goes up).
// Written with selects rather than early returns so that CPU loops vectorise.
template <class R>
CB_HD V3<R> ball_contact(V3<R> d, R radius, R k) {
  R r = length(d);
  const bool inside = r < radius, centred = r <= R(1e-12);
  R s = ((inside & !centred) ? k * (radius - r) : R(0)) / (centred ? R(1) : r);
  V3<R> f = d * s;
  f.y -= (inside & centred) ? k * radius : R(0);
  return f;
}

// Edge contact: the structural segment from node x to its neighbour xn against the ball
// (centre c). Eq. (4) acts at the segment's point nearest the centre, q = x + t (xn - x)
// with t clamped to [0, 1], and this returns the node's share (1 - t) of it; the neighbour
// takes the rest, t, from its own side (where t' = 1 - t). A zero-length segment splits
// evenly. A ball can then not slip between nodes through a segment. Selects, not branches.
template <class R>
CB_HD V3<R> edge_contact_share(V3<R> x, V3<R> xn, V3<R> c, R radius, R k) {
  const V3<R> e = xn - x;
  const R e2 = dot(e, e);
  const bool has_len = e2 > R(1e-30);
  R t = dot(c - x, e) / (has_len ? e2 : R(1));
  t = t < R(0) ? R(0) : (t > R(1) ? R(1) : t);
  t = has_len ? t : R(0.5);
  return ball_contact(x + e * t - c, radius, k) * (R(1) - t);
}

// Aerodynamic force on one vertex of triangle (p0, p1, p2) with vertex velocities v0..v2:
// drag along the relative wind u and lift across it, both scaled by the area the wind
// sees (cos theta = u.n / |u|, with n turned to face the wind). kd, kl are 1/2 rho C / 3,
// the vertex's third share. Selects instead of branches, so CPU loops vectorise.
template <class R>
CB_HD V3<R> triangle_wind(V3<R> p0, V3<R> p1, V3<R> p2, V3<R> v0, V3<R> v1, V3<R> v2,
                          V3<R> wind, R kd, R kl) {
  V3<R> nrm = cross(p1 - p0, p2 - p0);
  R twice_area = length(nrm);
  V3<R> u = wind - (v0 + v1 + v2) * (R(1) / R(3));
  R u2 = dot(u, u);
  R ulen = sqrt(u2);
  const bool ok = (twice_area > R(1e-30)) & (ulen > R(1e-12));
  V3<R> nh = nrm * (R(1) / (ok ? twice_area : R(1)));
  R un = dot(u, nh);
  R flip = un < R(0) ? R(-1) : R(1);
  nh = nh * flip;
  un *= flip;
  R area = R(0.5) * twice_area;
  R inv_u = R(1) / (ok ? ulen : R(1));
  R c = un * inv_u;                                   // cos theta
  V3<R> drag = u * (kd * area * un);                  // 1/2 rho Cd A |u|^2 cos(th) u_hat
  V3<R> lift = (u * (c * inv_u) - nh) * (kl * area * u2 * c);  // .. cos(th) (cos u_hat - n)
  R on = ok ? R(1) : R(0);
  return (drag + lift) * on;
}

// The term `expr` for add_if, evaluated there.
#define CB_TERM(expr) [&]() CB_HD_LAMBDA { return expr; }

// acc += term() where `has` (the neighbour, or the hand's grip, exists): a branch, or with
// Select (the CPU's border loops, kSelectsAbsent) term() computed whatever `has` and added
// as +0 where it is false, which vectorises. Exact: these sums start at +0 and only add, so
// they are never -0, and x + 0 is x.
template <bool Select, class R, class T>
CB_HD void add_if(V3<R>& acc, bool has, T&& term) {
  if constexpr (Select) {
    const V3<R> t = term();
    acc += V3<R>{has ? t.x : R(0), has ? t.y : R(0), has ? t.z : R(0)};
  } else {
    if (has) acc += term();
  }
}

// Plate bending (cloth.bending_stiffness D; the `bend` effect's second term, beside its
// springs). The energy is D/2 times the integral of |grad grad x|^2 (every second
// derivative of the position, a plate of Poisson's ratio 0) over the sheet, discretised as
//   E = k/2 [sum over row and column triples |x_a - 2 x_b + x_c|^2
//            + 2 sum over cells |x_00 - x_01 - x_10 + x_11|^2],   k = D / L^2,
// every stencil inside the grid (a free edge's natural boundary). Why this one: it is the
// quadratic bending energy of Bergou et al. 2006 on a regular grid. Each stencil
// annihilates a plane, so the flat cloth at rest, and any rigid motion of it, feel nothing,
// and since it is a norm of linear combinations of positions it is invariant under
// rotations too; for a bend without stretching it is the bending energy D/2 (c1^2 + c2^2).
// It is quadratic: the force -k B^T B x is linear (f_i = -k sum_m c_m x_m, the 13-node
// biharmonic stencil 20, -8, 2, 1 in the interior, so force per area -D grad^4 x as L -> 0)
// and its Jacobian -k B^T B is exact, constant and negative semidefinite (what CG needs).
// Unlike the bend springs, whose resistance to bending is geometric (second order at rest)
// and fades as the grid refines, it resists a curvature alike at every n.
// plate_sum returns sum over m != i of c_m (at(m) - xi), the coefficients c_m = sum over
// the stencils holding i and m of their product (fewer stencils near the border); the
// force is -k times it. Differences against xi, not the positions, keep float32 accurate.
// Interior: every node within two exists (then 20, -8, 2, 1). `at(r)` is node r's vector
// (a position or a CG direction) at view index r; s is a row's step in the view.
template <class R, bool Interior, bool Select = false, class At>
CB_HD V3<R> plate_sum(int n, int i, int j, int q, int s, At&& at, V3<R> xi) {
  // Row triples that hold node j: centred at j - 1 (a), j (b), j + 1 (c); columns alike.
  const R a = (Interior || j >= 2) ? R(1) : R(0), c = (Interior || j <= n - 3) ? R(1) : R(0);
  const R b = (Interior || (j >= 1 && j <= n - 2)) ? R(1) : R(0);
  const R av = (Interior || i >= 2) ? R(1) : R(0), cv = (Interior || i <= n - 3) ? R(1) : R(0);
  const R bv = (Interior || (i >= 1 && i <= n - 2)) ? R(1) : R(0);
  // Cells that hold the node: rows of cells above and below it (u), columns aside (v).
  const R u = ((Interior || i >= 1) ? R(1) : R(0)) + ((Interior || i <= n - 2) ? R(1) : R(0));
  const R v = ((Interior || j >= 1) ? R(1) : R(0)) + ((Interior || j <= n - 2) ? R(1) : R(0));
  V3<R> t{R(0), R(0), R(0)};
  auto add = [&](bool has, auto term) CB_HD_LAMBDA { add_if<Select>(t, Interior || has, term); };
  add(j >= 1, CB_TERM((at(q - 1) - xi) * (R(-2) * (a + b + u))));
  add(j <= n - 2, CB_TERM((at(q + 1) - xi) * (R(-2) * (c + b + u))));
  add(i >= 1, CB_TERM((at(q - s) - xi) * (R(-2) * (av + bv + v))));
  add(i <= n - 2, CB_TERM((at(q + s) - xi) * (R(-2) * (cv + bv + v))));
  add(j >= 2, CB_TERM(at(q - 2) - xi));
  add(j <= n - 3, CB_TERM(at(q + 2) - xi));
  add(i >= 2, CB_TERM(at(q - 2 * s) - xi));
  add(i <= n - 3, CB_TERM(at(q + 2 * s) - xi));
  add(i >= 1 && j >= 1, CB_TERM((at(q - s - 1) - xi) * R(2)));
  add(i >= 1 && j <= n - 2, CB_TERM((at(q - s + 1) - xi) * R(2)));
  add(i <= n - 2 && j >= 1, CB_TERM((at(q + s - 1) - xi) * R(2)));
  add(i <= n - 2 && j <= n - 2, CB_TERM((at(q + s + 1) - xi) * R(2)));
  return t;
}

// The plate term's diagonal coefficient c_i (20 in the interior): the sum of the others'
// negatives, the stencils' coefficients summing to zero.
template <class R, bool Interior>
CB_HD R plate_diag(int n, int i, int j) {
  auto in = [](bool x) { return x ? R(1) : R(0); };
  const R rows = in(Interior || j >= 2) + R(4) * in(Interior || (j >= 1 && j <= n - 2)) +
                 in(Interior || j <= n - 3);
  const R cols = in(Interior || i >= 2) + R(4) * in(Interior || (i >= 1 && i <= n - 2)) +
                 in(Interior || i <= n - 3);
  const R u = in(Interior || i >= 1) + in(Interior || i <= n - 2);
  const R v = in(Interior || j >= 1) + in(Interior || j <= n - 2);
  return rows + cols + R(2) * u * v;
}

// Which coupled corner (0..3) node (i, j) is, or -1. Order: (0,0), (0,n-1), (n-1,n-1), (n-1,0).
CB_HD int corner_slot(int i, int j, int n) {
  int last = n - 1;
  if (i == 0) return j == 0 ? 0 : (j == last ? 1 : -1);
  if (i == last) return j == last ? 2 : (j == 0 ? 3 : -1);
  return -1;
}

// Node index of coupled corner c (0..3), in the order of corner_slot.
CB_HD int corner_node(int c, int n) {
  const int last = n - 1;
  return c == 0 ? 0 : c == 1 ? last : c == 2 ? n * n - 1 : last * n;
}

// What a hand's grip (params.hpp: grip_weight) does at node (i, j): the hand (corner slot,
// -1: none), the node's coupling stiffness, and its rest offset from the corner (the hand
// pulls it towards hip + offset). Only nodes of the cloth's edges are held.
template <class R>
struct GripNode {
  int corner;
  R k;
  V3<R> offset;
};

template <class R>
CB_HD GripNode<R> grip_node(const Params<R>& p, int i, int j) {
  const int n = p.n, last = n - 1, M = p.grip_nodes;
  // Inside the cloth no hand holds a node: one test for the (on the GPU, every) node there.
  if (i != 0 && i != last && j != 0 && j != last) return {-1, R(0), {R(0), R(0), R(0)}};
  GripNode<R> g{corner_slot(i, j, n), p.coupling_k, {R(0), R(0), R(0)}};
  if (M == 0) return g;  // the paper's: the corner node alone, with K
  if (g.corner >= 0) {
    g.k = p.grip_k_per_weight * grip_weight(0, p.grip_u);
    return g;
  }
  int ci = -1, cj = -1, m = 0;
  if (i == 0 || i == last) {  // along a row edge (x)
    ci = i;
    cj = j <= M ? 0 : (j >= last - M ? last : -1);
    m = cj == 0 ? j : last - j;
    g.offset.x = R(j - cj) * p.L;
  } else if (j == 0 || j == last) {  // along a column edge (z)
    cj = j;
    ci = i <= M ? 0 : (i >= last - M ? last : -1);
    m = ci == 0 ? i : last - i;
    g.offset.z = R(i - ci) * p.L;
  }
  if (ci < 0 || cj < 0) return {-1, R(0), {R(0), R(0), R(0)}};
  g.corner = corner_slot(ci, cj, n);
  g.k = p.grip_k_per_weight * grip_weight(m, p.grip_u);
  return g;
}

// Part of the point a hand holds: over the grip's nodes m = first, first + stride, ...
// (m = 0 the corner node, m >= 1 a node m along each of its two edges), each node's
// position less its rest offset and its velocity, weighted by its share of K, and the
// shares' total. The GPU splits a grip over lanes (finish_body); grip_point takes them all.
template <class R>
CB_HD void grip_point_part(const Params<R>& p, const Planes<R>& pos, const Planes<R>& vel, int c,
                           int first, int stride, V3<R>& x, V3<R>& v, R& total) {
  const int n = p.n, q = corner_node(c, n);
  x = {R(0), R(0), R(0)};
  v = {R(0), R(0), R(0)};
  total = R(0);
  if (p.grip_nodes == 0) {  // the corner node alone, its own state
    if (first == 0) {
      x = pos.get(q);
      v = vel.get(q);
      total = R(1);
    }
    return;
  }
  const int ci = q / n, cj = q - ci * n;
  const int di = ci == 0 ? 1 : -1, dj = cj == 0 ? 1 : -1;
  for (int m = first; m <= p.grip_nodes; m += stride) {
    const R w = grip_weight(m, p.grip_u);
    if (m == 0) {
      x += pos.get(q) * w;
      v += vel.get(q) * w;
      total += w;
      continue;
    }
    const R off = R(m) * p.L;
    const int a = ci * n + cj + dj * m, b = (ci + di * m) * n + cj;
    x += (pos.get(a) - V3<R>{R(dj) * off, R(0), R(0)}) * w;
    x += (pos.get(b) - V3<R>{R(0), R(0), R(di) * off}) * w;
    v += (vel.get(a) + vel.get(b)) * w;
    total += R(2) * w;
  }
}

// The point a hand holds (the corner at rest) and its velocity: the grip's nodes' positions
// less their rest offsets, and their velocities, weighted by their share of K. The force
// on the hand is then -K (hip - point), the sum of its nodes' couplings. With a single node
// it is the corner node's own state.
template <class R>
CB_HD void grip_point(const Params<R>& p, const Planes<R>& pos, const Planes<R>& vel, int c,
                      V3<R>& x, V3<R>& v) {
  R total;
  grip_point_part(p, pos, vel, c, 0, 1, x, v, total);
  x = x * (R(1) / total);
  v = v * (R(1) / total);
}

// Total force on node (i, j) from the state `pos`/`vel` at the substep's start (eq. 1).
// `contact` receives this node's ball contact force (eq. 4) for the ball's sum (eq. 5):
// at the node itself, or with p.ball_edges its shares of its (up to) 4 structural edges'.
// Interior = true promises that every neighbour up to two nodes away exists and that the
// node is no corner, so the bounds tests vanish (the CPU loop then vectorises).
// `pos` and `vel` are views of the grid (Planes, or a window of it: TilePlanes; vec.hpp).
template <class R, unsigned E, bool Interior = false, class G = Planes<R>>
CB_HD V3<R> node_force(const Params<R>& p, const G& pos, const G& vel, V3<R> pi, V3<R> vi,
                       int i, int j, const FrameInputs<R>& fin, V3<R> ball_p, V3<R>& contact) {
  const int n = p.n;
  const int q = node_at(pos, n, i, j), s = row_step(pos, n);
  V3<R> f{R(0), R(0), R(0)};
  // A term of an absent neighbour is skipped, or with a padded view selected out (add_if).
  constexpr bool Sel = !Interior && kSelectsAbsent<G>;
  auto add = [&](bool has, auto term) CB_HD_LAMBDA { add_if<Sel>(f, Interior || has, term); };
  if constexpr ((E & STRUCTURAL) != 0) {
    const R L = p.L, c = p.struct_compress;
    const R kr = p.k_struct * edge_spring_weight<R, Interior>(n, i);  // along the row
    const R kc = p.k_struct * edge_spring_weight<R, Interior>(n, j);  // along the column
    add(j > 0, CB_TERM(spring_force(pi, pos.get(q - 1), kr, L, c)));
    add(j < n - 1, CB_TERM(spring_force(pi, pos.get(q + 1), kr, L, c)));
    add(i > 0, CB_TERM(spring_force(pi, pos.get(q - s), kc, L, c)));
    add(i < n - 1, CB_TERM(spring_force(pi, pos.get(q + s), kc, L, c)));
  }
  if constexpr ((E & SHEAR) != 0) {
    const R k = p.k_shear, L = p.L_diag;
    add(i > 0 && j > 0, CB_TERM(spring_force(pi, pos.get(q - s - 1), k, L, R(1))));
    add(i > 0 && j < n - 1, CB_TERM(spring_force(pi, pos.get(q - s + 1), k, L, R(1))));
    add(i < n - 1 && j > 0, CB_TERM(spring_force(pi, pos.get(q + s - 1), k, L, R(1))));
    add(i < n - 1 && j < n - 1, CB_TERM(spring_force(pi, pos.get(q + s + 1), k, L, R(1))));
  }
  if constexpr ((E & BEND) != 0) {
    const R L = p.L_bend;
    const R kr = p.k_bend * edge_spring_weight<R, Interior>(n, i);
    const R kc = p.k_bend * edge_spring_weight<R, Interior>(n, j);
    add(j > 1, CB_TERM(spring_force(pi, pos.get(q - 2), kr, L, R(1))));
    add(j < n - 2, CB_TERM(spring_force(pi, pos.get(q + 2), kr, L, R(1))));
    add(i > 1, CB_TERM(spring_force(pi, pos.get(q - 2 * s), kc, L, R(1))));
    add(i < n - 2, CB_TERM(spring_force(pi, pos.get(q + 2 * s), kc, L, R(1))));
    // The plate term only where the scene has a bending stiffness: the test is the same
    // for every node of a call (hoisted by the compiler, uniform on the GPU), and a scene
    // without one (k_plate 0) pays nothing for it (summed always, it cost 16-30 % a
    // substep on the CPU) and steps bit for bit as before the term existed.
    if (p.k_plate != R(0)) {
      auto at = [&](int r) CB_HD_LAMBDA { return pos.get(r); };
      f += plate_sum<R, Interior, Sel>(n, i, j, q, s, at, pi) * (-p.k_plate);
    }
  }
  // Run-time effects (params.hpp): both terms are zero when the scene lacks them.
  // Both per unit of the node's mass (mass_weight: 1 inside, 1/2 on an edge, 1/4 at a corner).
  const R mw = mass_weight<R, Interior>(n, i, j);
  f += p.gravity_force * mw;
  f -= vi * (p.damping * mw);
  if constexpr ((E & BALL) != 0) {
    // Uniform over a sweep: a run-time mode (not an effect set), fixed at compile time
    // where E carries BALL_NODES or BALL_EDGES (the CPU sweep).
    constexpr bool fixed_mode = (E & (BALL_NODES | BALL_EDGES)) != 0;
    const bool edges = fixed_mode ? (E & BALL_EDGES) != 0 : p.ball_edges;
    if (edges) {
      // Per area, as the springs: an edge along the cloth's border stands for half a strip.
      const R rad = p.ball_radius;
      const R kr = p.ball_k * edge_spring_weight<R, Interior>(n, i);
      const R kc = p.ball_k * edge_spring_weight<R, Interior>(n, j);
      V3<R> c{R(0), R(0), R(0)};
      auto add_c = [&](bool has, auto term) CB_HD_LAMBDA { add_if<Sel>(c, Interior || has, term); };
      add_c(j > 0, CB_TERM(edge_contact_share(pi, pos.get(q - 1), ball_p, rad, kr)));
      add_c(j < n - 1, CB_TERM(edge_contact_share(pi, pos.get(q + 1), ball_p, rad, kr)));
      add_c(i > 0, CB_TERM(edge_contact_share(pi, pos.get(q - s), ball_p, rad, kc)));
      add_c(i < n - 1, CB_TERM(edge_contact_share(pi, pos.get(q + s), ball_p, rad, kc)));
      contact = c;
    } else {  // per area, as the mass: k_b of an inner node times the node's mass weight
      contact = ball_contact(pi - ball_p, p.ball_radius, p.ball_k * mw);
    }
    f += contact;
  }
  if constexpr (Sel) {  // the same from the view's table of grip_node (k 0: no hand)
    f += (pos.grip_hip.get(q) - (pi - pos.grip_offset.get(q))) * pos.grip_k[q];
  } else if constexpr (!Interior) {  // a run-time effect: the corners are never interior
    if ((p.effects & COUPLING) != 0) {
      const GripNode<R> g = grip_node(p, i, j);  // eq. (7), the node's side
      if (g.corner >= 0) f += (fin.hips[g.corner] - (pi - g.offset)) * g.k;
    }
  }
  if constexpr ((E & WIND) != 0) {
    // The (up to) six triangles around the node; quad (a, b, c, d) = ((i,j), (i,j+1),
    // (i+1,j+1), (i+1,j)) is split into (a, b, c) and (a, c, d).
    auto P = [&](int a, int b) CB_HD_LAMBDA { return pos.get(node_at(pos, n, a, b)); };
    auto V = [&](int a, int b) CB_HD_LAMBDA { return vel.get(node_at(vel, n, a, b)); };
    const V3<R> w = fin.wind;
    const R kd = p.wind_drag, kl = p.wind_lift;
    // The node is a of quad (i, j), b of quad (i, j-1), c of (i-1, j-1) and d of (i-1, j).
    const bool a = i < n - 1 && j < n - 1, b = i < n - 1 && j > 0;
    const bool c = i > 0 && j > 0, d = i > 0 && j < n - 1;
    add(a, CB_TERM(triangle_wind(pi, P(i, j + 1), P(i + 1, j + 1), vi, V(i, j + 1),
                                 V(i + 1, j + 1), w, kd, kl)));
    add(a, CB_TERM(triangle_wind(pi, P(i + 1, j + 1), P(i + 1, j), vi, V(i + 1, j + 1),
                                 V(i + 1, j), w, kd, kl)));
    add(b, CB_TERM(triangle_wind(P(i, j - 1), pi, P(i + 1, j), V(i, j - 1), vi, V(i + 1, j),
                                 w, kd, kl)));
    add(c, CB_TERM(triangle_wind(P(i - 1, j - 1), P(i - 1, j), pi, V(i - 1, j - 1),
                                 V(i - 1, j), vi, w, kd, kl)));
    add(c, CB_TERM(triangle_wind(P(i - 1, j - 1), pi, P(i, j - 1), V(i - 1, j - 1), vi,
                                 V(i, j - 1), w, kd, kl)));
    add(d, CB_TERM(triangle_wind(P(i - 1, j), P(i, j + 1), pi, V(i - 1, j), V(i, j + 1), vi,
                                 w, kd, kl)));
  }
  return f;
}

// Eq. (3): semi-implicit Euler, the velocity's kick and then the position's drift with the
// new velocity.
template <class R>
CB_HD void euler_kick(V3<R>& v, V3<R> f, R inv_mass, R dt) {
  v += f * (inv_mass * dt);
}

template <class R>
CB_HD void euler_drift(V3<R>& x, V3<R> v, R dt) {
  x += v * dt;
}

template <class R>
CB_HD void euler_update(V3<R>& x, V3<R>& v, V3<R> f, R inv_mass, R dt) {
  euler_kick(v, f, inv_mass, dt);
  euler_drift(x, v, dt);
}

// t - t accumulates 0 while every value is finite, NaN after.
template <class R>
CB_HD void check_finite(R& check, V3<R> x, V3<R> v) {
  R t = x.x + x.y + x.z + v.x + v.y + v.z;
  check += t - t;
}

// The first half of a node's semi-implicit Euler substep from the views (P, V) of the
// substep's start: its position there in x and its new velocity (the kick) in v. Returns
// the node's ball contact force, for the ball's sum.
template <class R, unsigned E, bool Interior = false, class G = Planes<R>>
CB_HD V3<R> se_node_kick(const Params<R>& p, const G& P, const G& V, const FrameInputs<R>& fin,
                         V3<R> ball_p, int i, int j, R dt, V3<R>& x, V3<R>& v) {
  const int q = node_at(P, p.n, i, j);
  x = P.get(q);
  v = V.get(q);
  V3<R> contact{R(0), R(0), R(0)};
  const V3<R> f = node_force<R, E, Interior>(p, P, V, x, v, i, j, fin, ball_p, contact);
  euler_kick(v, f, p.inv_mass * inv_mass_weight<R, Interior>(p.n, i, j), dt);
  return contact;
}

// One node's whole substep: the kick, then the drift; the new state in (x, v). `check`
// accumulates check_finite of it.
template <class R, unsigned E, bool Interior = false, class G = Planes<R>>
CB_HD V3<R> se_node_step(const Params<R>& p, const G& P, const G& V, const FrameInputs<R>& fin,
                         V3<R> ball_p, int i, int j, R dt, R& check, V3<R>& x, V3<R>& v) {
  const V3<R> contact = se_node_kick<R, E, Interior>(p, P, V, fin, ball_p, i, j, dt, x, v);
  euler_drift(x, v, dt);
  check_finite(check, x, v);
  return contact;
}

// se_node_step from buffer (P, V) into (P2, V2).
// G: the view of (P, V), Planes or the CPU's PaddedPlanes.
template <class R, unsigned E, bool Interior = false, class G = Planes<R>>
CB_HD V3<R> se_node_update(const Params<R>& p, const G& P, const G& V,
                           const Planes<R>& P2, const Planes<R>& V2, const FrameInputs<R>& fin,
                           V3<R> ball_p, int i, int j, R dt, R& check) {
  const int q = i * p.n + j;
  V3<R> x, v;
  const V3<R> contact = se_node_step<R, E, Interior>(p, P, V, fin, ball_p, i, j, dt, check, x, v);
  P2.set(q, x);
  V2.set(q, v);
  return contact;
}

// Provot's strain limiting along one line of structural springs: a row (first = i n,
// stride 1) or a column (first = j, stride n), as a Gauss-Seidel chain, follow-the-leader.
// Going along the line, each node whose spring to its just-limited predecessor is longer
// than max_len moves by the whole excess towards it, so after ONE pass every spring of
// the line holds the limit (a correction travels the whole line, not one node a sweep as
// in Jacobi). The line's first node is the leader and does not move; a backward pass
// after it would find nothing to do. The velocity takes the same correction over dt.
// In place: each line touches only its own nodes, so lines may run in parallel.
template <class R>
CB_HD void strain_limit_line(const Params<R>& p, const Planes<R>& P, const Planes<R>& V,
                             int first, int stride, R inv_dt) {
  V3<R> lead = P.get(first);
  for (int k = 1, q = first + stride; k < p.n; ++k, q += stride) {
    V3<R> x = P.get(q);
    const V3<R> d = lead - x;
    const R len = length(d);
    const R over = len - p.max_len;
    if (over > R(0)) {  // then len > max_len > 0
      const V3<R> corr = d * (over / len);
      x += corr;
      P.set(q, x);
      V.set(q, V.get(q) + corr * inv_dt);
    }
    lead = x;
  }
}

// Eqs. (5)-(6): the ball under gravity, minus the summed contact forces, minus damping.
template <class R>
CB_HD Ball<R> ball_update(const Params<R>& p, Ball<R> b, V3<R> contact_sum, R dt) {
  V3<R> f{R(0), R(0), R(0)};
  if ((p.effects & GRAVITY) != 0) f = p.gravity * p.ball_mass;
  f -= contact_sum;
  f -= b.v * p.ball_damping;
  euler_update(b.p, b.v, f, p.ball_inv_mass, dt);
  return b;
}

// Whether a node can touch the ball in the next substep; eq. (4) is zero unless one is
// inside it, and then the contact can be compiled out of that substep. `nearest2`: the
// smallest squared distance from a node's new position to the ball's centre before the
// ball's update; `moved`: the ball's displacement in that update. By the triangle
// inequality every node is then at least sqrt(nearest2) - |moved| from the new centre.
// Strain limiting moves nodes after the sweep, so with it contact stays on. NaN: on.
// Edge contact (p.ball_edges) stays on too: a segment can touch the ball while both its
// ends are farther than the radius, so the nearest node says nothing.
template <class R>
CB_HD bool contact_possible(const Params<R>& p, R nearest2, V3<R> moved, bool strain_limited) {
  return strain_limited || p.ball_edges || !(sqrt(nearest2) - length(moved) >= p.ball_radius);
}

// Unit normal at node (i, j) from the cross product of the grid tangents (central
// differences, one-sided at the border). Eq. (8) as printed is not a normal.
template <class R>
CB_HD V3<R> node_normal(const Planes<R>& pos, int n, int i, int j) {
  auto at = [&](int a, int b) { return pos.get(a * n + b); };
  int j0 = j > 0 ? j - 1 : j, j1 = j < n - 1 ? j + 1 : j;
  int i0 = i > 0 ? i - 1 : i, i1 = i < n - 1 ? i + 1 : i;
  V3<R> tu = at(i, j1) - at(i, j0);  // along +x at rest
  V3<R> tv = at(i1, j) - at(i0, j);  // along +z at rest
  V3<R> nrm = cross(tv, tu);         // +y for the flat cloth
  R len = length(nrm);
  if (len > R(0)) return nrm * (R(1) / len);
  return {R(0), R(1), R(0)};
}

}  // namespace cb
