// Compiled once per real type: CB_REAL is float or double (see native/CMakeLists.txt).
// The tiled frame (core/tiled_plan.hpp says what and when): a lone large cloth's whole
// frame in one cooperative launch, a tile a block, the tile's state on chip for the frame,
// a grid barrier between substeps. Each node's substep is se_node_tracked over the tile's
// shared-memory view (TilePlanes), the ball's sums are substep_ball_begin / _end: the same
// code as a launch a substep (cuda/substep.cuh), so the same arithmetic per node.
//
// Why a resident state and not temporal blocking (tiles advancing several substeps on a
// deeper halo between passes over device memory): the ball couples every substep. Its
// update at substep k + 1 needs the contact sum over the whole cloth at substep k, so no
// tile may run ahead of the others by a substep; the grid barrier is needed anyway, and
// with it the state never has to leave the chip (at n = 1024 in float32 it is 24 MB, and
// 132 multiprocessors hold 30 MB of shared memory). Only the tiles within twice the
// ball's radius of it add to its sums, but which those are is known only once every tile
// has finished the substep; a barrier among them alone would still order every tile after
// the ball's update, since every node reads the ball's position for its contact test.
//
// What a substep costs beside its nodes' updates: the grid barrier, the halo and the ball
// coming in from L2 after it (loaded together, one round trip), and the ball's sums (a
// block's warps meet in shared memory first, then one atomic a block and word).
#include <cooperative_groups.h>
#include <cuda_runtime.h>

#include <array>
#include <limits>

#include "core/backend.hpp"
#include "cuda/substep.cuh"

namespace cb {
namespace {

namespace cg = cooperative_groups;

constexpr int kThreads = tiled_threads(sizeof(CB_REAL));

// One frame: load the tile and its halo from buffer b0, `substeps` substeps in shared
// memory, store the tile to the buffer the frame ends in (the one a launch a substep
// would have written last). Between substeps a tile's border positions go to the other
// global buffer (L2) and, past the grid barrier, its halo's come back from there: the two
// buffers alternate, so a border written at substep k + 1 never lands where a halo of
// substep k is still being read.
template <class R, unsigned E>
__global__ void __launch_bounds__(kThreads, 1) tiled_frame(TiledArgs<R> a) {
  extern __shared__ __align__(16) unsigned char shared_bytes[];
  R* sh = reinterpret_cast<R*>(shared_bytes);
  const Params<R>& p = a.p;
  const int n = p.n, N = n * n, s = a.reach;
  const int t = int(threadIdx.x), T = int(blockDim.x);
  const int ty = int(blockIdx.x) / a.tiles_x, tx = int(blockIdx.x) - ty * a.tiles_x;
  const int ib = ty * a.th, jb = tx * a.tw;                       // the tile's first node
  const int th = min(a.th, n - ib), tw = min(a.tw, n - jb);       // and its size
  const int W = a.tw + 2 * s;                                     // a row with its halo
  const size_t cells = size_t(a.th + 2 * s) * size_t(W);
  const TilePlanes<R> P{{sh, sh + cells, sh + 2 * cells}, W, ib - s, jb - s};
  const TilePlanes<R> V{{sh + 3 * cells, sh + 4 * cells, sh + 5 * cells}, W, ib - s, jb - s};
  const int hw = tw + 2 * s, hh = th + 2 * s;

  {  // the tile and its halo, from the buffer the frame starts in
    const DevBuf<R> g = dev_buf(a.state + size_t(a.b0) * 6 * size_t(N), N);
    for (int c = t; c < hh * hw; c += T) {
      const int r = c / hw, i = ib - s + r, j = jb - s + (c - r * hw);
      if (i < 0 || i >= n || j < 0 || j >= n) continue;
      const int q = i * n + j, l = node_at(P, n, i, j);
      P.set(l, g.pos.get(q));
      V.set(l, g.vel.get(q));
    }
  }
  __syncthreads();

  // This thread's nodes: the tile's t, t + T, ... in row-major order. The update is in
  // place in two passes: the kick of every node (each writes only its own velocity, which
  // only it reads: no wind), a block barrier, then the drift of every node (a position is
  // overwritten only when every node of the tile has read the old one).
  const int r0 = t / tw, c0 = t - r0 * tw, dr = T / tw, dc = T - dr * tw;
  auto next = [&](int& r, int& c) {
    r += dr;
    c += dc;
    if (c >= tw) {
      c -= tw;
      ++r;
    }
  };
  const int ring = 2 * s * hw + 2 * s * th;  // halo cells
  const bool leader = blockIdx.x == 0 && t == 0;
  R* const scratch = sh + 6 * cells;  // the ball's sums, a warp's (substep_ball_end_block)
  // Every thread runs the same number of rounds over the tile's nodes (the last one with
  // some lanes idle), so that a whole warp can agree on its nodes' code: warps whose nodes
  // all lie `s` or more from the cloth's border (all but a tile-border sliver) take the
  // interior code, with no bounds tests and no corner coupling (node_force's Interior).
  // Not in float64 with bending springs: there the interior code's twelve neighbours
  // spill at the 128 registers a thread has.
  constexpr bool kInterior = !(sizeof(R) == 8 && (E & BEND) != 0);
  const int rounds = (th * tw + T - 1) / T;
  const unsigned all = 0xffffffffu;
  cg::grid_group grid = cg::this_grid();
  int b = a.b0;
  // Substep k's ball buffers, made where used from the arguments (constant memory) rather
  // than kept in registers across the substep.
  auto ball_at = [&](int k) { return substep_ball_at(a.ball + b, a.ball + (1 - b), a.ring, a.ctl, k); };
  BallNow<R> now = substep_ball_begin<R, E>(p, ball_at(0), a.dt, leader);
  for (int k = 0; k < a.substeps; ++k) {
    V3<R> contact{R(0), R(0), R(0)};
#pragma unroll 1
    for (int u = 0, r = r0, c = c0; u < rounds; ++u, next(r, c)) {
      const int i = ib + r, j = jb + c;
      const bool mine = r < th;
      const bool inner = i >= s && i < n - s && j >= s && j < n - s;
      V3<R> x, v;
      if (kInterior && __all_sync(all, inner || !mine)) {
        if (mine) {
          contact += se_kick_touch<R, E, true>(p, P, V, *a.fin, now, i, j, a.dt, x, v);
          V.set(node_at(V, n, i, j), v);
        }
      } else if (mine) {
        contact += se_kick_touch<R, E>(p, P, V, *a.fin, now, i, j, a.dt, x, v);
        V.set(node_at(V, n, i, j), v);
      }
    }
    __syncthreads();  // every old position of the tile is read
    const DevBuf<R> g = dev_buf(a.state + size_t(1 - b) * 6 * size_t(N), N);
    R check = 0;
    R near2 = std::numeric_limits<R>::infinity();
#pragma unroll 1
    for (int r = r0, c = c0; r < th; next(r, c)) {
      const int i = ib + r, j = jb + c, l = node_at(P, n, i, j);
      V3<R> x = P.get(l);
      se_drift_tracked<R, E>(now, x, V.get(l), a.dt, check, near2);
      P.set(l, x);
      if (r < s || th - 1 - r < s || c < s || tw - 1 - c < s) {  // in a neighbour's halo
        const int q = i * n + j;
        __stcg(g.pos.x + q, x.x);
        __stcg(g.pos.y + q, x.y);
        __stcg(g.pos.z + q, x.z);
      }
    }
    if (check != R(0)) *a.nonfinite = 1;  // sticky until the host resets the state
    substep_ball_end_block<R, E>(p, ball_at(k), contact, near2, leader, scratch);
    grid.sync();  // every border, and the substep's ball sums, are written
    if (k + 1 == a.substeps) break;  // after the last substep: no halo, the frame's end has the ball
    b = 1 - b;
    const SubstepBall<R> sb = ball_at(k + 1);
    // The next substep's ball from this one's sums (ball_now): its inputs are loaded here,
    // before the halo, so that both come in from L2 together, and used after it.
    Ball<R> b0{};
    BallAcc<R> acc{};
    bool strain = false;
    if constexpr ((E & BALL) != 0) {
      b0 = *sb.prev;
      acc = *sb.acc_prev;
      strain = sb.ctl->strain_limited != 0;
    }
    for (int h = t; h < ring; h += T) {  // the halo: s rows above and below, s columns aside
      int hr, hc;
      if (h < 2 * s * hw) {
        const int rr = h / hw;
        hc = h - rr * hw;
        hr = rr < s ? rr : th + rr;
      } else {
        const int k2 = h - 2 * s * hw, rr = k2 / (2 * s), cc = k2 - rr * 2 * s;
        hr = s + rr;
        hc = cc < s ? cc : tw + cc;
      }
      const int i = ib - s + hr, j = jb - s + hc;
      if (i < 0 || i >= n || j < 0 || j >= n) continue;
      const int q = i * n + j;
      P.set(node_at(P, n, i, j), {__ldcg(g.pos.x + q), __ldcg(g.pos.y + q), __ldcg(g.pos.z + q)});
    }
    if constexpr ((E & BALL) != 0) {
      now = ball_after<R>(p, b0, acc, strain, a.dt);
      substep_ball_store<R, E>(p, sb, now, leader);
    }
    __syncthreads();
  }
  if (a.substeps > 0) b = 1 - b;

  // The tile to the buffer the frame ends in (b); the frame's end (finish_frame) follows.
  const DevBuf<R> g = dev_buf(a.state + size_t(b) * 6 * size_t(N), N);
  for (int l = t; l < th * tw; l += T) {
    const int r = l / tw, i = ib + r, j = jb + (l - r * tw);
    const int q = i * n + j, x = node_at(P, n, i, j);
    g.pos.set(q, P.get(x));
    g.vel.set(q, V.get(x));
  }
}

template <class R, unsigned E>
constexpr TiledFrameFn<R> tiled_fn() {
  if constexpr ((E & WIND) != 0)
    return nullptr;  // wind reads the neighbours' velocities (tiled_capable)
  else
    return &tiled_frame<R, E>;
}

template <class R>
struct TiledEntry {
  template <unsigned E>
  struct At {
    static constexpr TiledFrameFn<R> fn = tiled_fn<R, E>();
  };
};

}  // namespace

template <>
const std::array<TiledFrameFn<CB_REAL>, kNumEffectSets>& tiled_kernel_table<CB_REAL>() {
#ifdef CB_LAB_EFFECT_SET
  static std::array<TiledFrameFn<CB_REAL>, kNumEffectSets> t{};
  constexpr unsigned kLab = (CB_LAB_EFFECT_SET) & (kNumEffectSets - 1);
  t[kLab] = TiledEntry<CB_REAL>::template At<kLab>::fn;
  return t;
#else
  return dispatch_table<TiledFrameFn<CB_REAL>, TiledEntry<CB_REAL>::template At>();
#endif
}

}  // namespace cb
