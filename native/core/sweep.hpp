// Each spring's force once, for both of its nodes (issue 41): the sweep's layout and sums,
// plain C++ so that it is tested where there is no GPU; cuda/sweep.cuh runs it on warps
// (cuda/tiled.cu's tiled frame, cuda/batch.cu's fused frame).
//
// Node at a time, every spring is computed twice, once from each end. In the sweep a lane
// walks down one column of a region a row at a time, and each node computes only the
// springs it owns (OwnedSprings: those to the nodes after it); the others are its
// neighbours' own with the sign turned (spring_force(pj, pi) is -spring_force(pi, pj)
// exactly: only the difference's sign changes), taken from the lane beside it by a warp
// shuffle (its row's springs, the diagonals from the row above) or kept in a register from
// the lane's own previous rows (the springs down). A node's springs are then summed in
// node_force's order and the rest of its force is node_force's own (Springs = false), so
// the physics stays the one core shared with the CPU; the sum differs from a node's own
// only in rounding (the springs up come summed, and a product node_force adds as one fused
// multiply-add is rounded first).
//
// Lanes: consecutive lanes take consecutive columns of a band of rows; the bands' columns
// are laid one after another along a block's lanes, so a warp may end one band's row and
// begin the next one's. A warp's first `left` lanes and its last `right` repeat the
// neighbouring warp's columns, so that every lane that updates a node has its neighbours'
// springs in its own warp. Each band first walks `warm` rows above it, computing only the
// springs down from them.
#pragma once
#include <algorithm>

#include "forces.hpp"
#include "params.hpp"

namespace cb {

template <class R>
struct OwnedSprings {
  V3<R> r, d;    // structural: to (i, j + 1), (i + 1, j)
  V3<R> dr, dl;  // shear: to (i + 1, j + 1), (i + 1, j - 1)
  V3<R> r2, d2;  // bend: to (i, j + 2), (i + 2, j)
};

template <unsigned E>
struct SweepLanes {
  static constexpr bool springs = (E & (STRUCTURAL | SHEAR | BEND)) != 0;
  static constexpr int left = (E & BEND) != 0 ? 2 : 1;    // the bend spring from j - 2
  static constexpr int right = (E & SHEAR) != 0 ? 1 : 0;  // the diagonal from (i - 1, j + 1)
  static constexpr int fresh = 32 - left - right;         // new columns a warp takes
  static constexpr int warm = (E & BEND) != 0 ? 2 : 1;    // rows above a band it reads
};

// A block's region: it updates the nodes [i0, i1) x [j0, j1) and can read the columns
// [c0, c1) (clipped to the cloth) of the rows from i0 - warm to i1 + warm - 1 (a tile's
// halo, or the whole cloth).
struct SweepRegion {
  int i0, i1, j0, j1, c0, c1;
};

// How a block's warps cover its region: `bands` bands of `rows` rows (the last may have
// fewer), each band's columns [v0, v0 + vw). bands 0: the region is too wide for the
// block's lanes (then the node-at-a-time code runs).
struct SweepPlan {
  int v0, vw, bands, rows;
};

template <unsigned E>
CB_HD SweepPlan sweep_plan(const SweepRegion& g, int warps) {
  using L = SweepLanes<E>;
  const int v0 = std::max(g.j0 - L::left, g.c0), v1 = std::min(g.j1 + L::right, g.c1);
  const int vw = v1 - v0, h = g.i1 - g.i0;
  // Lane `left` of warp 0 takes slot 0, and the last warp's last updating lane slot
  // warps * fresh - 1: that many slots, a band's vw each.
  int bands = std::min(warps * L::fresh / vw, h);
  if (bands <= 0) return {v0, vw, 0, 0};
  const int rows = (h + bands - 1) / bands;
  bands = (h + rows - 1) / rows;
  return {v0, vw, bands, rows};
}

// The springs node (i, j) owns, each where its far end is in the cloth and in the
// region's columns; zero else. A row above a band needs only its springs down: `across`
// false leaves the row's own out, `down1` false the ones a row down.
template <class R, unsigned E, class G>
CB_HD OwnedSprings<R> owned_springs(const Params<R>& p, const G& P, int i,
                                                         int j, int c0, int c1, bool across,
                                                         bool down1) {
  const int n = p.n;
  const V3<R> z{R(0), R(0), R(0)};
  OwnedSprings<R> o{z, z, z, z, z, z};
  const V3<R> pi = P.get(node_at(P, n, i, j));
  auto at = [&](int a, int b) { return P.get(node_at(P, n, a, b)); };
  if constexpr ((E & STRUCTURAL) != 0) {
    const R k = p.k_struct, L = p.L, c = p.struct_compress;
    if (across && j + 1 < c1) o.r = spring_force(pi, at(i, j + 1), k, L, c);
    if (down1 && i + 1 < n) o.d = spring_force(pi, at(i + 1, j), k, L, c);
  }
  if constexpr ((E & SHEAR) != 0) {
    const R k = p.k_shear, L = p.L_diag;
    if (down1 && i + 1 < n && j + 1 < c1) o.dr = spring_force(pi, at(i + 1, j + 1), k, L, R(1));
    if (down1 && i + 1 < n && j - 1 >= c0) o.dl = spring_force(pi, at(i + 1, j - 1), k, L, R(1));
  }
  if constexpr ((E & BEND) != 0) {
    const R k = p.k_bend, L = p.L_bend;
    if (across && j + 2 < c1) o.r2 = spring_force(pi, at(i, j + 2), k, L, R(1));
    if (i + 2 < n) o.d2 = spring_force(pi, at(i + 2, j), k, L, R(1));
  }
  return o;
}

// The sweep over a region by this block's thread t: node(i, j, springs) is called once for
// every node of the region, with the sum of its springs (node_force's terms, summed in
// another order: up, left, its own). Every lane of a warp must arrive: X::up(v, d) and
// X::down(v, d) give lane l the value v of lane l - d and l + d (on the GPU a warp
// shuffle, cuda/sweep.cuh).
template <class R, unsigned E, class X, class G, class Node>
CB_HD void sweep_region(const Params<R>& p, const G& P, const SweepRegion& g,
                        const SweepPlan& plan, int t, Node&& node) {
  using L = SweepLanes<E>;
  const int lane = t & 31, warp = t >> 5;
  const int slot = warp * L::fresh + lane - L::left, slots = plan.bands * plan.vw;
  if (warp * L::fresh - L::left >= slots) return;  // the whole warp is past the region
  const bool live = slot >= 0 && slot < slots;
  const int band = live ? slot / plan.vw : 0;
  const int j = plan.v0 + (live ? slot - band * plan.vw : 0);
  const bool updates = live && lane >= L::left && lane < 32 - L::right && j >= g.j0 && j < g.j1;
  const int ia = g.i0 + band * plan.rows, ib = std::min(ia + plan.rows, g.i1);
  const V3<R> z{R(0), R(0), R(0)};
  // What the rows above give the next row's node, carried in registers: the sum of its
  // springs up (structural, both diagonals, and the bend spring from two rows up), and
  // the bend spring down from this row, for the row after it.
  V3<R> above = z, d2_above = z;
#pragma unroll 1
  for (int step = 0; step < plan.rows + L::warm; ++step) {
    const int i = ia - L::warm + step;
    OwnedSprings<R> o{z, z, z, z, z, z};
    if (live && i >= 0 && i < ib)
      o = owned_springs<R, E>(p, P, i, j, g.c0, g.c1, i >= ia, i >= ia - 1);
    V3<R> f = above;  // the springs' sum: those up, then left and its own
    V3<R> left_r = z, left_r2 = z;
    if constexpr ((E & STRUCTURAL) != 0) left_r = X::up(o.r, 1);
    if constexpr ((E & BEND) != 0) left_r2 = X::up(o.r2, 2);
    // The next row's springs up: this row's down ones, the diagonals from the lanes aside.
    V3<R> next = z;
    if constexpr ((E & STRUCTURAL) != 0) next -= o.d;
    if constexpr ((E & SHEAR) != 0) {
      const V3<R> from_left = X::up(o.dr, 1), from_right = X::down(o.dl, 1);
      if (j >= 1) next -= from_left;
      if (j + 1 < p.n) next -= from_right;
    }
    if constexpr ((E & BEND) != 0) {
      next -= d2_above;
      d2_above = o.d2;
    }
    if (updates && i >= ia && i < ib) {
      if constexpr ((E & STRUCTURAL) != 0) {
        if (j >= 1) f -= left_r;
        f += o.r;
        f += o.d;
      }
      if constexpr ((E & SHEAR) != 0) {
        f += o.dl;
        f += o.dr;
      }
      if constexpr ((E & BEND) != 0) {
        if (j >= 2) f -= left_r2;
        f += o.r2;
        f += o.d2;
      }
      node(i, j, f);
    }
    above = next;
  }
}

}  // namespace cb
