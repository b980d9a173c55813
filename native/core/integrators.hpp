// Velocity Verlet and linearised implicit Euler, per node, written once for both backends.
// The equations are those of the NumPy reference (game/integrators_ref.py), term by term, so
// that in float64 the engine and the reference agree to rounding.
#pragma once
#include "forces.hpp"

namespace cb {

// --- the force Jacobian K = dF/dx, applied matrix-free ----------------------------------
// Compiled effects with a position Jacobian. Damping is a diagonal term (a runtime scalar of
// the CG operator), gravity and wind have none (wind is explicit in implicit Euler), and
// coupling's (the hands' grips, edge nodes) is a run-time test on the border path, as in node_force: the
// Jacobian-vector product needs 2^4 specialisations.
constexpr unsigned kStiffEffects = STRUCTURAL | SHEAR | BEND | BALL;
constexpr unsigned kNumStiffSets = 16;
static_assert(kStiffEffects == kNumStiffSets - 1, "the stiffness effects are bits 0-3");
// The idx-th subset of kStiffEffects, and a set's index: bits 0-3 are both.
constexpr unsigned stiff_set(unsigned idx) { return idx; }
constexpr unsigned stiff_index(unsigned e) { return e & kStiffEffects; }

// A pair force phi(d) = s d (d = partner - node, see spring_force) linearised: transverse
// stiffness s projected to s >= 0 (Choi & Ko: keeps -K positive semidefinite, so CG
// applies), axial stiffness k g'(e), direction u.
template <class R>
struct PairTerms {
  R s, axial;
  V3<R> u;
};

template <class R>
CB_HD PairTerms<R> pair_terms(V3<R> d, R k, R rest, R compress) {
  const R len = length(d);
  const bool ok = len > R(1e-12);
  const R safe = ok ? len : R(1);
  const R e = len - rest;
  const bool stretched = e > R(0);
  const R g = stretched ? e : compress * e;
  const R gp = stretched ? R(1) : compress;
  R s = ok ? k * g / safe : R(0);
  s = s > R(0) ? s : R(0);
  return {s, ok ? k * gp : R(0), {d.x / safe, d.y / safe, d.z / safe}};
}

// D phi . w = s w + (axial - s) (u . w) u
template <class R>
CB_HD V3<R> pair_jvp(const PairTerms<R>& t, V3<R> w) {
  return w * t.s + t.u * ((t.axial - t.s) * dot(t.u, w));
}

// The diagonal of D phi.
template <class R>
CB_HD V3<R> pair_diag(const PairTerms<R>& t) {
  const R a = t.axial - t.s;
  return {t.s + a * t.u.x * t.u.x, t.s + a * t.u.y * t.u.y, t.s + a * t.u.z * t.u.z};
}

// Calls fn(neighbour index, k, rest, compress) for every spring of node (i, j) the effect
// set S names, in node_force's order. Interior: every neighbour exists (no bounds tests).
template <class R, unsigned S, bool Interior, class Fn>
CB_HD void for_each_spring(const Params<R>& p, int i, int j, Fn&& fn) {
  const int n = p.n, q = i * n + j;
  if constexpr ((S & STRUCTURAL) != 0) {
    const R L = p.L, c = p.struct_compress;
    const R kr = p.k_struct * edge_spring_weight<R, Interior>(n, i);
    const R kc = p.k_struct * edge_spring_weight<R, Interior>(n, j);
    if (Interior || j > 0) fn(q - 1, kr, L, c);
    if (Interior || j < n - 1) fn(q + 1, kr, L, c);
    if (Interior || i > 0) fn(q - n, kc, L, c);
    if (Interior || i < n - 1) fn(q + n, kc, L, c);
  }
  if constexpr ((S & SHEAR) != 0) {
    const R k = p.k_shear, L = p.L_diag;
    if (Interior || (i > 0 && j > 0)) fn(q - n - 1, k, L, R(1));
    if (Interior || (i > 0 && j < n - 1)) fn(q - n + 1, k, L, R(1));
    if (Interior || (i < n - 1 && j > 0)) fn(q + n - 1, k, L, R(1));
    if (Interior || (i < n - 1 && j < n - 1)) fn(q + n + 1, k, L, R(1));
  }
  if constexpr ((S & BEND) != 0) {
    const R L = p.L_bend;
    const R kr = p.k_bend * edge_spring_weight<R, Interior>(n, i);
    const R kc = p.k_bend * edge_spring_weight<R, Interior>(n, j);
    if (Interior || j > 1) fn(q - 2, kr, L, R(1));
    if (Interior || j < n - 2) fn(q + 2, kr, L, R(1));
    if (Interior || i > 1) fn(q - 2 * n, kc, L, R(1));
    if (Interior || i < n - 2) fn(q + 2 * n, kc, L, R(1));
  }
}

// Ball contact of node x linearised (partner b, rest length R, always compressed while the
// node is inside; no term outside or at the very centre, as eq. 4's force); `weight` is the
// node's mass weight (contact per area, as node_force's).
template <class R>
CB_HD PairTerms<R> contact_terms(const Params<R>& p, V3<R> x, V3<R> ball_p, R weight) {
  const V3<R> d = ball_p - x;
  PairTerms<R> t = pair_terms(d, p.ball_k * weight, p.ball_radius, R(1));
  const bool inside = length(d) < p.ball_radius;
  t.s = inside ? t.s : R(0);
  t.axial = inside ? t.axial : R(0);
  return t;
}

// (K w) at node (i, j): w(r) gives the vector at node r, wi the node's own, wb the ball's.
// `cj` receives the contact part; the ball's row is minus the sum of those.
template <class R, unsigned S, bool Interior, class W>
CB_HD V3<R> node_jvp(const Params<R>& p, const Planes<R>& pos, const W& w, V3<R> xi, V3<R> wi,
                     int i, int j, V3<R> ball_p, V3<R> wb, V3<R>& cj) {
  V3<R> out{R(0), R(0), R(0)};
  for_each_spring<R, S, Interior>(p, i, j, [&](int r, R k, R rest, R c) {
    out += pair_jvp(pair_terms(pos.get(r) - xi, k, rest, c), w(r) - wi);
  });
  if constexpr ((S & BEND) != 0)  // the plate term is linear: K w = -k_plate B^T B w
    if (p.k_plate != R(0))
      out += plate_sum<R, Interior>(p.n, i, j, i * p.n + j, p.n, w, wi) * (-p.k_plate);
  if constexpr ((S & BALL) != 0) {
    cj = pair_jvp(contact_terms(p, xi, ball_p, mass_weight<R, Interior>(p.n, i, j)), wb - wi);
    out += cj;
  }
  if constexpr (!Interior) {
    if ((p.effects & COUPLING) != 0) {
      const GripNode<R> g = grip_node(p, i, j);
      if (g.corner >= 0) out -= wi * g.k;
    }
  }
  return out;
}

// The diagonal of -K at node (i, j); `cd` receives the contact part (the ball's diagonal is
// the sum of those).
template <class R, unsigned S, bool Interior>
CB_HD V3<R> node_neg_diag(const Params<R>& p, const Planes<R>& pos, V3<R> xi, int i, int j,
                          V3<R> ball_p, V3<R>& cd) {
  V3<R> out{R(0), R(0), R(0)};
  for_each_spring<R, S, Interior>(p, i, j, [&](int r, R k, R rest, R c) {
    out += pair_diag(pair_terms(pos.get(r) - xi, k, rest, c));
  });
  if constexpr ((S & BEND) != 0) {
    if (p.k_plate != R(0)) {
      const R d = p.k_plate * plate_diag<R, Interior>(p.n, i, j);
      out += V3<R>{d, d, d};
    }
  }
  if constexpr ((S & BALL) != 0) {
    cd = pair_diag(contact_terms(p, xi, ball_p, mass_weight<R, Interior>(p.n, i, j)));
    out += cd;
  }
  if constexpr (!Interior) {
    if ((p.effects & COUPLING) != 0) {
      const GripNode<R> g = grip_node(p, i, j);
      if (g.corner >= 0) out += V3<R>{g.k, g.k, g.k};
    }
  }
  return out;
}

// --- velocity Verlet ---------------------------------------------------------------------
// Kick-drift-kick. F is every force but damping, and is kept per node from one substep to
// the next (one force evaluation a substep). gamma = c / m; damping is implicit in the
// closing half kick, so the scheme stays symmetric (second order) with it:
//   v½ = v + dt/2 (F/m - gamma v),  x' = x + dt v½,  v' = (v½ + dt/2 F(x')/m) / (1 + gamma dt/2)
// The wind, the one other velocity-dependent force, sees the half-step velocity v½ (an
// explicit estimate: with wind on, its drag is first order in dt).
template <class R>
CB_HD void vv_drift(V3<R>& x, V3<R>& v, V3<R> f, R inv_mass, R gamma, R dt) {
  v = v + (f * inv_mass - v * gamma) * (R(0.5) * dt);
  x = x + v * dt;
}

template <class R>
CB_HD V3<R> vv_kick(V3<R> vh, V3<R> f, R inv_mass, R gamma, R dt) {
  const R h = R(0.5) * dt;
  return (vh + f * (inv_mass * h)) * (R(1) / (R(1) + h * gamma));
}

// Verlet's parameters: those of the scene with node_force's damping term zeroed, as F
// excludes damping (it is gamma, in the kicks).
template <class R>
CB_HD Params<R> vv_params(Params<R> p) {
  p.damping = R(0);
  return p;
}

// The force pass of one node: F at (x', v½) from buffer (P, V), closing kick into (P2, V2),
// F kept in Fb. With dt = 0 it only evaluates F (the priming pass). Returns the node's
// contact force, for the ball's sum. `p` comes from vv_params (F without damping).
template <class R, unsigned E, bool Interior = false>
CB_HD V3<R> vv_force_node(const Params<R>& p, const Planes<R>& P, const Planes<R>& V,
                          const Planes<R>& P2, const Planes<R>& V2, const Planes<R>& Fb,
                          const FrameInputs<R>& fin, V3<R> ball_p, int i, int j, R gamma, R dt,
                          R& check) {
  const int q = i * p.n + j;
  const V3<R> x = P.get(q), vh = V.get(q);
  V3<R> contact{R(0), R(0), R(0)};
  const V3<R> f = node_force<R, E, Interior>(p, P, V, x, vh, i, j, fin, ball_p, contact);
  const V3<R> v = vv_kick(vh, f, p.inv_mass * inv_mass_weight<R, Interior>(p.n, i, j), gamma, dt);
  Fb.set(q, f);
  P2.set(q, x);
  V2.set(q, v);
  check_finite(check, x, v);
  return contact;
}

// The ball's force in Verlet: weight minus the contacts (its damping is in the kicks).
template <class R>
CB_HD V3<R> vv_ball_force(const Params<R>& p, V3<R> contact_sum) {
  V3<R> f{R(0), R(0), R(0)};
  f -= contact_sum;
  if ((p.effects & GRAVITY) != 0) f += p.gravity * p.ball_mass;
  return f;
}

// --- linearised implicit Euler ----------------------------------------------------------
//   (M + dt C - dt^2 K) dv = dt (F(x, v) + dt K v),   v' = v + dv,   x' = x + dt v'
// solved by Jacobi-preconditioned CG from dv = 0. The unknowns are the n^2 nodes and the
// ball (index N = n^2 in every CG vector). `a` is m + dt c (nodes: an interior node's, times
// mass_weight at each node, as M and C are) or M_b + dt beta2 (ball).
template <class R>
struct CgVectors {
  Planes<R> x, r, z, d, p[2], ap;  // dv, residual, preconditioned residual, diagonal,
                                   // search direction (ping-pong), operator times it
};

// Stores residual r at CG entry q with its diagonal d and z = r / d; adds r . r and r . z.
template <class R>
CB_HD void cg_set_residual(const CgVectors<R>& cg, int q, V3<R> r, V3<R> d, R& rr, R& rz) {
  const V3<R> z{r.x / d.x, r.y / d.y, r.z / d.z};
  cg.r.set(q, r);
  cg.z.set(q, z);
  rr += dot(r, r);
  rz += dot(r, z);
}

// What one node adds to the sums of the right-hand side pass.
template <class R>
struct RhsSums {
  V3<R> contact, cj, cd;  // contact force, contact part of K v, contact diagonal
  R bb, rz;               // |rhs|^2, r . z
};

// Right-hand side, diagonal and CG start at node (i, j) from the state (P, V).
template <class R, unsigned E, bool Interior = false>
CB_HD void ie_rhs_node(const Params<R>& p, const Planes<R>& P, const Planes<R>& V,
                       const CgVectors<R>& cg, const FrameInputs<R>& fin, V3<R> ball_p,
                       V3<R> ball_v, int i, int j, R a_node, R dt, RhsSums<R>& sums) {
  constexpr unsigned S = E & kStiffEffects;
  const int q = i * p.n + j;
  const V3<R> x = P.get(q), v = V.get(q);
  V3<R> contact{R(0), R(0), R(0)}, cj{R(0), R(0), R(0)}, cd{R(0), R(0), R(0)};
  const V3<R> f = node_force<R, E, Interior>(p, P, V, x, v, i, j, fin, ball_p, contact);
  auto vel = [&](int r) { return V.get(r); };
  const V3<R> kv = node_jvp<R, S, Interior>(p, P, vel, x, v, i, j, ball_p, ball_v, cj);
  const V3<R> rhs = (f + kv * dt) * dt;
  const V3<R> nd = node_neg_diag<R, S, Interior>(p, P, x, i, j, ball_p, cd);
  const R dt2 = dt * dt, an = a_node * mass_weight<R, Interior>(p.n, i, j);
  const V3<R> dg{an + dt2 * nd.x, an + dt2 * nd.y, an + dt2 * nd.z};
  cg.x.set(q, {R(0), R(0), R(0)});
  cg.d.set(q, dg);
  cg_set_residual(cg, q, rhs, dg, sums.bb, sums.rz);
  sums.contact += contact;
  sums.cj += cj;
  sums.cd += cd;
}

// The ball's row of the right-hand side pass, from the summed node parts. Without a ball
// the row is all zeros with a unit diagonal (the reference's, too).
template <class R, unsigned E>
CB_HD void ie_rhs_ball(const Params<R>& p, const CgVectors<R>& cg, Ball<R> b,
                       const RhsSums<R>& s, R a_ball, R dt, int N, R& bb, R& rz) {
  V3<R> rhs{R(0), R(0), R(0)}, dg{R(1), R(1), R(1)};
  if constexpr ((E & BALL) != 0) {
    V3<R> fb = s.contact * R(-1) - b.v * p.ball_damping;
    if ((p.effects & GRAVITY) != 0) fb += p.gravity * p.ball_mass;
    const V3<R> kvb = s.cj * R(-1);
    rhs = (fb + kvb * dt) * dt;
    const R dt2 = dt * dt;
    dg = {a_ball + dt2 * s.cd.x, a_ball + dt2 * s.cd.y, a_ball + dt2 * s.cd.z};
  }
  cg.x.set(N, {R(0), R(0), R(0)});
  cg.d.set(N, dg);
  cg_set_residual(cg, N, rhs, dg, bb, rz);
}

// The search direction at entry r: p = z (first iteration) or z + beta p_old.
template <class R>
CB_HD V3<R> cg_direction(const CgVectors<R>& cg, int from, int r, bool first, R beta) {
  return first ? cg.z.get(r) : cg.z.get(r) + cg.p[from].get(r) * beta;
}

// CG operator at node (i, j): p_new (computed here for the node and its neighbours, so the
// direction update needs no pass of its own) into p[1 - from], A p_new into ap. Returns
// p . A p for the node; `cj` receives the contact part of K p.
template <class R, unsigned S, bool Interior = false>
CB_HD R ie_apply_node(const Params<R>& p, const Planes<R>& P, const CgVectors<R>& cg, int from,
                      bool first, R beta, V3<R> ball_p, V3<R> wb, int i, int j, R a_node, R dt,
                      V3<R>& cj) {
  const int q = i * p.n + j;
  auto w = [&](int r) { return cg_direction(cg, from, r, first, beta); };
  const V3<R> wi = w(q);
  const V3<R> kw = node_jvp<R, S, Interior>(p, P, w, P.get(q), wi, i, j, ball_p, wb, cj);
  const V3<R> ap = wi * (a_node * mass_weight<R, Interior>(p.n, i, j)) - kw * (dt * dt);
  cg.p[1 - from].set(q, wi);
  cg.ap.set(q, ap);
  return dot(wi, ap);
}

// The ball's row of the operator (index N), from the summed contact parts. Returns p . A p.
template <class R>
CB_HD R ie_apply_ball(const CgVectors<R>& cg, int from, bool first, R beta, V3<R> cj_sum,
                      R a_ball, R dt, int N) {
  const V3<R> wb = cg_direction(cg, from, N, first, beta);
  const V3<R> ap = wb * a_ball - (cj_sum * R(-1)) * (dt * dt);
  cg.p[1 - from].set(N, wb);
  cg.ap.set(N, ap);
  return dot(wb, ap);
}

// x += alpha p, r -= alpha A p, z = r / diag at entry q (a node or the ball). Adds r . r
// and r . z.
template <class R>
CB_HD void ie_update_entry(const CgVectors<R>& cg, int to, int q, R alpha, R& rr, R& rz) {
  cg.x.set(q, cg.x.get(q) + cg.p[to].get(q) * alpha);
  cg_set_residual(cg, q, cg.r.get(q) - cg.ap.get(q) * alpha, cg.d.get(q), rr, rz);
}

// v' = v + dv, x' = x + dt v' for node q from (P, V) into (P2, V2).
template <class R>
CB_HD void ie_finish_node(const CgVectors<R>& cg, const Planes<R>& P, const Planes<R>& V,
                          const Planes<R>& P2, const Planes<R>& V2, int q, R dt, R& check) {
  const V3<R> v = V.get(q) + cg.x.get(q);
  const V3<R> x = P.get(q) + v * dt;
  P2.set(q, x);
  V2.set(q, v);
  check_finite(check, x, v);
}

template <class R>
CB_HD Ball<R> ie_finish_ball(const CgVectors<R>& cg, Ball<R> b, int N, R dt) {
  b.v = b.v + cg.x.get(N);
  b.p = b.p + b.v * dt;
  return b;
}

// Whether CG has stopped before iteration k (k >= 1): the last p . A p was not positive
// (not definite along p), or |r| <= tol |rhs|. bb = |rhs|^2, rr = |r_k|^2.
template <class R>
CB_HD bool cg_stopped(int k, R bb, R pap_prev, R rr, R tol) {
  if (!(bb > R(0))) return true;
  if (k == 0) return false;
  return !(pap_prev > R(0)) || sqrt(rr) / sqrt(bb) <= tol;
}

}  // namespace cb
