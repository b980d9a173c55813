// Scene parameters as the kernels see them, and the effect flags that specialise them.
#pragma once
#include <algorithm>
#include <cmath>

#include "vec.hpp"

namespace cb {

// Effects that change the per-node force. The costly ones (bits 0-4: springs, ball contact,
// wind; tens of flops a node) are compile-time choices: each of their 32 combinations is
// compiled as its own kernel, so an absent costly effect is compiled out rather than
// branched over. The cheap ones (bits 5-7) are parameters of those kernels: gravity adds a
// constant and damping -c v to each node (zeroed when absent: f + 0 and f - 0 v are exact,
// see Params::from), coupling acts on the hands' grips, nodes of the cloth's edges, which
// the bounds-tested border path reaches (a run-time test there; the CPU's semi-implicit
// Euler sweep reads a table of the grips instead, k 0 without coupling). Without them every
// effect set was a kernel of its own: 256 of them, and most of a 17-minute build (issue 19).
enum Effect : unsigned {
  STRUCTURAL = 1u << 0,
  SHEAR = 1u << 1,
  BEND = 1u << 2,
  BALL = 1u << 3,
  WIND = 1u << 4,
  GRAVITY = 1u << 5,
  DAMPING = 1u << 6,
  COUPLING = 1u << 7,
};
constexpr unsigned kNumForceEffects = 8;
constexpr unsigned kNumCompiledEffects = 5;  // bits 0-4
// Strain limiting is a pass after the substep, not a force: launched or not, per scene.
constexpr unsigned STRAIN_LIMIT = 1u << 8;
// The compiled effect sets: a backend's kernel tables have one entry per set, indexed by
// effects & (kNumEffectSets - 1).
constexpr unsigned kNumEffectSets = 1u << kNumCompiledEffects;
// The ball's contact mode as a compile-time choice, or-ed into E by the CPU sweep only: a
// run-time test inside its vectorised loop is not hoisted and made the sweep 4x slower.
// With neither bit node_force reads Params::ball_edges (the GPU: a uniform branch).
constexpr unsigned BALL_NODES = 1u << 9;
constexpr unsigned BALL_EDGES = 1u << 10;

// Time integrators (Config::integrator); the order of game/scene.py's INTEGRATORS.
enum Integrator : int { SEMI_IMPLICIT_EULER = 0, VELOCITY_VERLET = 1, IMPLICIT_EULER = 2 };

// Host-side configuration, always in double; converted to Params<R> by each backend.
struct Config {
  int n = 0;
  double rest_len = 0;      // L = size / (n - 1)
  double node_mass = 0;     // an interior node's: total mass / (n - 1)^2 (mass_weight)
  double k_struct = 0, k_shear = 0, k_bend = 0;
  double k_plate = 0;       // N/m: the plate bending term's k a stencil (BEND), D / L^2; 0: none
  double struct_compress = 0;  // 0: tension-only structural springs (eq. 2); 1: two-sided
  double gravity[3] = {0, -9.81, 0};
  double damping = 0;       // beta1, N s/m per node (eq. 1)
  double ball_radius = 0, ball_mass = 1, ball_k = 0, ball_damping = 0;
  bool ball_edges = false;  // ball contact on the structural edges, not only the nodes (eq. 4)
  // Material values, independent of n (docs/scenes.md); negative: not given, and the
  // per-node value above holds. per_node() below turns them into per-node values.
  double damping_rate = -1;  // 1/s: damping force per unit mass and unit velocity
  double ball_k_area = -1;   // N/m^3: contact force per unit penetration and contact area
  double bending_stiffness = -1;  // N m: the plate's D (Poisson's ratio 0), derives k_plate
  double coupling_k = 0;    // K of eq. (7): a hand's total
  double grip_radius = 0;   // m: a hand holds the border this near its corner; 0: the corner node
  double air_density = 1.2, drag = 1.0, lift = 0.3;  // wind on each triangle
  double max_strain = 0.1;  // strain limiting: longest spring is (1 + max_strain) L
  int strain_iterations = 10;  // strain limiting: passes (rows, then columns) a substep
  int threads = 0;          // CPU threads; 0: all
  int integrator = SEMI_IMPLICIT_EULER;
  int cg_max_iterations = 200;  // implicit Euler: CG iterations per substep, at most
  double cg_tolerance = 1e-5;   // implicit Euler: stop when |r| <= this |rhs|
  unsigned effects = 0;     // Effect bits, plus STRAIN_LIMIT
};

// The per-node values of a configuration whose scene gives material values (independent of
// n): the one place they are derived, at configuration time (make_cpu_backend,
// make_cuda_backend, Engine::configure), so the kernels see per-node values only.
// Idempotent: what it derived is no longer marked as material.
//  * damping: the rate gamma (1/s) per unit mass, so beta1 = gamma m_node, and a uniformly
//    moving cloth loses momentum at gamma whatever n (beta1 fixed made it grow as n^2).
//  * contact: a stiffness per contact area kappa (N/m^3), each node standing for its area
//    L^2 of the grid (or each structural edge for half of it: a node inside the ball gets
//    about one edge contact per direction, see edge_contact_share), so the ball's total
//    stiffness no longer grows with the nodes it covers.
//  * bending: a plate's bending stiffness D (N m), so k_plate = D / L^2: the plate term
//    (plate_sum in forces.hpp) sums second differences of the positions, each over L^2,
//    squared and weighted by the L^2 of sheet a stencil stands for: D / L^2 a stencil, and
//    the force per area tends to -D grad^4 x whatever n.
inline Config per_node(Config c) {
  if (c.damping_rate >= 0) c.damping = c.damping_rate * c.node_mass;
  if (c.ball_k_area >= 0)
    c.ball_k = c.ball_k_area * c.rest_len * c.rest_len * (c.ball_edges ? 0.5 : 1.0);
  if (c.bending_stiffness >= 0) c.k_plate = c.bending_stiffness / (c.rest_len * c.rest_len);
  c.damping_rate = -1;
  c.ball_k_area = -1;
  c.bending_stiffness = -1;
  return c;
}

// Strain-limiting passes a substep: the scene's iterations (at least 1); 0 without the
// effect. A pass limits every row, then every column (strain_limit_line in forces.hpp).
inline int strain_sweeps(const Config& c) {
  return (c.effects & STRAIN_LIMIT) ? std::max(1, c.strain_iterations) : 0;
}

// The effects a backend simulates for this configuration (force bits and STRAIN_LIMIT): its
// kernels' compiled set (bits 0-4) and the run-time ones.
inline unsigned compiled_effect_set(const Config& c) {
  return c.effects & (((1u << kNumForceEffects) - 1) | STRAIN_LIMIT);
}

// A hand's grip (eq. 7 over a patch; docs/scenes.md). With grip radius a > 0 a hand holds
// each of its corner's two edges with a stiffness density that falls smoothly from the
// corner to zero at a: rho(s) = (1 - (s / a)^2)^2 per unit length (the biweight kernel,
// even in s, so the corner is a smooth point of it, and flat where it ends). Node m (m
// spacings L from the corner along an edge) takes the density integrated against its hat
// function (1 - |s - m L| / L over two spacings), the share of the grip that linear
// elements give it; the corner node, on both edges, the half hat of each. The shares are
// normalised to K, so the total is K whatever n. Sampled at the nodes instead (the
// trapezoid rule, until 2026-11-29), the grip of a = 10 cm was about two spacings long at
// n = 25 and the sag and rebound did not converge monotonically from there
// (docs/accuracy.md, "The grip's shares"). A single node is a point support (its membrane
// displacement grows as log(1 / L) without bound); a = 0 is the paper's single corner node,
// and so is any a <= L. In units of L: u = a / L, and node m's weight is grip_weight(m, u).
template <class R>
CB_HD R grip_density(R x, R u) {  // rho at x spacings from the corner
  const R y = x / u, t = R(1) - y * y;
  return y < R(1) ? t * t : R(0);
}

// The integral over [t0, t1] (within [-1, 0] or [0, 1]) of node m's hat (1 - |t|) times
// rho(m + t): a polynomial of degree 5 there (t1 at most the density's end), so the
// 3-point Gauss-Legendre rule is exact.
template <class R>
CB_HD R grip_hat_piece(int m, R u, R t0, R t1) {
  if (!(t1 > t0)) return R(0);
  const R c = (t0 + t1) / 2, h = (t1 - t0) / 2, g = R(0.77459666924148337704);  // sqrt(3/5)
  R sum = R(0);
  for (int k = -1; k <= 1; ++k) {
    const R t = c + R(k) * g * h, hat = R(1) - (t < R(0) ? -t : t);
    sum += (k == 0 ? R(8) / R(9) : R(5) / R(9)) * hat * grip_density(R(m) + t, u);
  }
  return sum * h;
}

template <class R>
CB_HD R grip_weight(int m, R u) {
  const R end = u - R(m);  // where the density ends, in the hat's t
  const R left = end < R(0) ? end : R(0), right = end < R(1) ? end : R(1);
  if (m == 0) return R(2) * grip_hat_piece(0, u, R(0), right);  // a half hat on each edge
  return grip_hat_piece(m, u, R(-1), left) + grip_hat_piece(m, u, R(0), right);
}

// Nodes a grip holds along each edge beyond the corner: those whose hat meets the density
// (m - 1 < u), at most (n - 2) / 2 so that no node belongs to two corners (the weights are
// then normalised over the nodes held, and the total is still K).
inline int grip_node_count(double u, int n) {
  if (!(u > 1.0)) return 0;
  const double m = std::ceil(u);
  const int cap = std::max(0, (n - 2) / 2);
  return m < double(cap) ? int(m) : cap;
}

// Lumped masses by area: node (i, j) stands for its share of the sheet, L^2 inside, half of
// it on an edge, a quarter at a corner, so its mass is node_mass (an interior node's,
// total / (n - 1)^2) times this weight, 1/2 for each edge it lies on, and the weights sum
// to (n - 1)^2: the total is the cloth's mass. (Uniform masses total / n^2 gave the edges
// twice their share, an O(L) error in the sag: docs/accuracy.md.) From the indices alone,
// so no array; an interior node (Interior: no edge) is 1 at compile time. Gravity and
// damping (node_force) are per unit of it, so damping stays a rate, and every kick divides
// by node_mass times it; forces that are not per mass (springs, contact, grip, wind) are not.
template <class R, bool Interior = false>
CB_HD R mass_weight(int n, int i, int j) {
  if constexpr (Interior) return R(1);
  const R wi = (i == 0 || i == n - 1) ? R(0.5) : R(1);
  const R wj = (j == 0 || j == n - 1) ? R(0.5) : R(1);
  return wi * wj;
}

// 1 / mass_weight (1, 2 or 4), so a kick multiplies rather than divides: exact either way,
// the weights being powers of two.
template <class R, bool Interior = false>
CB_HD R inv_mass_weight(int n, int i, int j) {
  if constexpr (Interior) return R(1);
  const R wi = (i == 0 || i == n - 1) ? R(2) : R(1);
  const R wj = (j == 0 || j == n - 1) ? R(2) : R(1);
  return wi * wj;
}

// A spring along a free edge (a structural or bending spring between two nodes of the
// border row or column `line` lies on) stands for half the strip of sheet an inner one
// does, the other half lying outside the cloth, so it has half the stiffness: the springs'
// share of each cell, summed, as masses by area are the nodes' (with full-stiffness edge
// springs the free edges were a hem twice as stiff as the sheet, an O(L) error in the sag:
// docs/accuracy.md). `line` is the row index for a spring along a row (j to j +- d), the
// column index for one along a column; a diagonal spring is never along an edge.
template <class R, bool Interior = false>
CB_HD R edge_spring_weight(int n, int line) {
  if constexpr (Interior) return R(1);
  return (line == 0 || line == n - 1) ? R(0.5) : R(1);
}

template <class R>
struct Params {
  int n;
  R L, L_diag, L_bend;
  R inv_mass;           // an interior node's; node (i, j)'s is this times inv_mass_weight
  R k_struct, k_shear, k_bend, struct_compress;
  R k_plate;            // the plate bending term's k (BEND); 0: none, and the term adds 0
  unsigned effects;     // Config::effects: the run-time effects are tested here
  V3<R> gravity_force;  // m g of an interior node (times mass_weight); 0 without GRAVITY
  V3<R> gravity;
  R damping;            // an interior node's (times mass_weight); 0 without DAMPING
  R ball_radius, ball_inv_mass, ball_mass, ball_k, ball_damping;
  bool ball_edges;         // Config::ball_edges
  R coupling_k;
  int grip_nodes;          // per edge beyond the corner (grip_node_count); 0: the corner node only
  R grip_u;                // grip radius / L
  R grip_k_per_weight;     // coupling_k / (sum of the grip's weights): node m's k is this w_m
  R wind_drag, wind_lift;  // 1/2 rho C / 3: each vertex's share of a triangle's force
  R max_len;               // (1 + max_strain) L

  static Params from(const Config& c) {
    Params p{};
    p.n = c.n;
    p.effects = c.effects;
    p.L = R(c.rest_len);
    p.L_diag = R(c.rest_len * 1.4142135623730951);
    p.L_bend = R(2.0 * c.rest_len);
    p.inv_mass = R(1.0 / c.node_mass);
    p.k_struct = R(c.k_struct);
    p.k_shear = R(c.k_shear);
    p.k_bend = R(c.k_bend);
    p.k_plate = R(c.k_plate);
    p.struct_compress = R(c.struct_compress);
    p.gravity = {R(c.gravity[0]), R(c.gravity[1]), R(c.gravity[2])};
    // Added to every node's force whether or not the scene has gravity or damping: zero
    // without them. node_force's sum starts at +0 and only adds, so it is never -0, and
    // f + 0 and f - (v * 0) are f exactly: the result is the one of a kernel compiled
    // without the term (for finite v; a non-finite v makes the node's own update
    // non-finite either way).
    const bool g = (c.effects & GRAVITY) != 0;
    p.gravity_force = {R(g ? c.gravity[0] * c.node_mass : 0.0),
                       R(g ? c.gravity[1] * c.node_mass : 0.0),
                       R(g ? c.gravity[2] * c.node_mass : 0.0)};
    p.damping = R((c.effects & DAMPING) ? c.damping : 0.0);
    p.ball_radius = R(c.ball_radius);
    p.ball_mass = R(c.ball_mass);
    p.ball_inv_mass = R(1.0 / c.ball_mass);
    p.ball_k = R(c.ball_k);
    p.ball_damping = R(c.ball_damping);
    p.ball_edges = c.ball_edges;
    p.coupling_k = R(c.coupling_k);
    const double u = c.grip_radius / c.rest_len;
    p.grip_nodes = grip_node_count(u, c.n);
    p.grip_u = R(u);
    double total = grip_weight(0, u);
    for (int m = 1; m <= p.grip_nodes; ++m) total += 2.0 * grip_weight(m, u);
    p.grip_k_per_weight = R(p.grip_nodes > 0 ? c.coupling_k / total : c.coupling_k);
    p.wind_drag = R(0.5 * c.air_density * c.drag / 3.0);
    p.wind_lift = R(0.5 * c.air_density * c.lift / 3.0);
    p.max_len = R((1.0 + c.max_strain) * c.rest_len);
    return p;
  }
};

// What the host may change every frame: the hands (eq. 7) and the wind (with its gusts).
template <class R>
struct FrameInputs {
  V3<R> hips[4];
  V3<R> wind;
};

// Ball state: position then velocity.
template <class R>
struct Ball {
  V3<R> p, v;
};

// The inverse mass of node q = i n + j of an n x n grid, from an interior node's.
template <class R>
CB_HD R node_inv_mass(R inv_mass, int n, int q) {
  return inv_mass * inv_mass_weight<R>(n, q / n, q % n);
}

}  // namespace cb
