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
// 132 multiprocessors hold 30 MB of shared memory).
//
// What bounds it (H100, µs a substep, ball off / on the cloth): the nodes' own updates, not
// memory or the barrier. Classic float32 9.1 / 10.3 at n = 768 (4 480 nodes a tile),
// 14.5 / 15.9 at 1024 (8 037): 1.5 ns a node a multiprocessor (3 cycles; the four springs'
// square roots and divisions, each spring computed from both its ends) on ~2.3 µs a
// substep of barrier, halo and ball. Float64: 3.5 ns a node on ~4 µs; the default scene
// (12 springs a node): ~2.9 ns. Tried against this code in one A/B run there and left
// out, since no combination of them was faster (all three: 14.6 / 15.9 at 1024, 10.0 /
// 10.8 at 768): the ball's sums met a block at a time before the atomics (+0.4 µs with
// the ball on the cloth: the extra block barrier cost more than the atomics it saved),
// the interior nodes' code without bounds tests chosen a warp at a time (-0.3 to -0.7 µs
// within that build, but the loop it needs, every thread the same rounds, lost as much),
// the next substep's ball loaded with the halo, one L2 round trip instead of two.
// H200 (issue 41, Nsight Compute; docs/benchmarks/gpu-h200-2026-11-28-roofline): instruction
// issue bounds it, 70 % of the issue slots busy, 342 instructions a node's substep (classic)
// for 132 flops, and the barrier, halo and ball cost 3.44 us a substep.
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
  cg::grid_group grid = cg::this_grid();
  int b = a.b0;
  for (int k = 0; k < a.substeps; ++k) {
    const SubstepBall<R> sb = substep_ball_at(a.ball + b, a.ball + (1 - b), a.ring, a.ctl, k);
    const BallNow<R> now = substep_ball_begin<R, E>(p, sb, a.dt, leader);
    V3<R> contact{R(0), R(0), R(0)};
#pragma unroll 1
    for (int r = r0, c = c0; r < th; next(r, c)) {
      const int i = ib + r, j = jb + c;
      V3<R> x, v;
      contact += se_kick_touch<R, E>(p, P, V, *a.fin, now, i, j, a.dt, x, v);
      V.set(node_at(V, n, i, j), v);
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
    substep_ball_end<R, E>(p, sb, contact, near2, leader);
    grid.sync();  // every border, and the substep's ball sums, are written
    const int halo = k + 1 < a.substeps ? ring : 0;  // after the last substep: none needed
    for (int h = t; h < halo; h += T) {  // the halo: s rows above and below, s columns aside
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
    __syncthreads();
    b = 1 - b;
  }

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
